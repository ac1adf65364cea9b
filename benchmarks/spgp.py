"""SPGP/FITC training and prediction speed: asgp_ros SparseGP against GPy's FITC.

Usage::

    python benchmarks/spgp.py            # the paper's scale: N = 36,000, D = 9, M = 40
    python benchmarks/spgp.py --quick    # small smoke run (N = 3,000, 30 iterations)
    python benchmarks/spgp.py --reference none   # no side-by-side prediction timing

Both models start from the same pseudo-inputs and hyperparameters (SparseGP's k-means
initialisation, converted to original units) and get the same L-BFGS-B budget
(``--iters`` iterations and as many function evaluations, GPy's convention).  The log
marginal likelihoods are the same quantity: GPy is given y minus its mean, which is the
prior mean SparseGP uses.  The data look like the paper's autoregressive wheelchair
features for the v channel: X_t = [j_{t-4..t-1}, v_{t-4..t-1}, j_t], y = v_t from a
nonlinear first-order-lag chair driven by a smooth, held joystick signal, with VO noise.

Prediction is also timed side by side with ``SparseGP`` of a reference revision
(``--reference REV``, default the commit before the FITC posterior and the kernel became
shared modules; see ``benchmarks/rollout.py``), restored from the same state, in
alternating runs.

Prints figures only (no assertions).  Timings depend on the machine's load.
"""

from __future__ import annotations

import argparse
import importlib.util
import platform
import time
from types import ModuleType

import numpy as np
from threadpoolctl import threadpool_limits

from asgp_ros.core.sparse_gp import SparseGP

LAGS = 4
DT = 0.2  # s, the paper's 5 Hz grid


def wheelchair_series(T: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Joystick forward deflection j [T] and measured forward speed v [T] at 5 Hz."""
    rng = np.random.default_rng(seed)
    # Joystick: targets held for exponential durations (mean 3 s), 30 % of them "stop",
    # smoothed by the hand (first-order, 0.3 s), a little tremor, clipped to [-1, 1].
    targets = np.empty(T)
    t = 0
    while t < T:
        hold = max(1, int(rng.exponential(3.0) / DT))
        target = 0.0 if rng.random() < 0.3 else rng.uniform(-0.6, 1.0)
        targets[t : t + hold] = target
        t += hold
    j = np.empty(T)
    j[0] = 0.0
    a_hand = DT / 0.3
    for k in range(1, T):
        j[k] = j[k - 1] + min(a_hand, 1.0) * (targets[k] - j[k - 1])
    j = np.clip(j + 0.02 * rng.standard_normal(T), -1.0, 1.0)
    # Chair: dead zone, saturating speed command, faster braking than acceleration.
    v = np.empty(T)
    v[0] = 0.0
    for k in range(1, T):
        jj = j[k - 1]
        cmd = 0.0 if abs(jj) < 0.08 else 1.2 * np.tanh(1.8 * (jj - 0.08 * np.sign(jj)))
        tau = 0.6 if abs(cmd) > abs(v[k - 1]) else 0.35
        v[k] = v[k - 1] + DT / (tau + DT) * (cmd - v[k - 1]) + 0.01 * rng.standard_normal()
    v_meas = v + 0.02 * rng.standard_normal(T)  # VO noise
    return j, v_meas


def ar_features(j: np.ndarray, v: np.ndarray, s: int = LAGS) -> tuple[np.ndarray, np.ndarray]:
    """Paper eq. 3: X_t = [j_{t-s..t-1}, v_{t-s..t-1}, j_t] [N, 2s+1], y_t = v_t [N]."""
    T = j.shape[0]
    idx = np.arange(s, T)
    past = idx[:, None] + np.arange(-s, 0)[None, :]
    X = np.hstack([j[past], v[past], j[idx][:, None]])
    return X, v[idx]


def make_data(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    j, v = wheelchair_series(n + LAGS, seed)
    return ar_features(j, v)


def time_sparse_gp(
    X: np.ndarray, y: np.ndarray, M: int, iters: int, threads: int
) -> tuple[SparseGP, float, list[tuple[float, float]]]:
    """Fit; returns the model, the training time and (elapsed s, log likelihood) per iteration."""
    trace: list[tuple[float, float]] = []
    t0 = time.perf_counter()
    gp = SparseGP(num_inducing=M, seed=0, threads=threads).fit(
        X, y, max_iter=iters, max_fun=iters,
        callback=lambda _it, lml: trace.append((time.perf_counter() - t0, lml)),
    )
    return gp, time.perf_counter() - t0, trace


def time_gpy(
    X: np.ndarray, y: np.ndarray, start: dict[str, np.ndarray], iters: int
) -> tuple[float, float, int] | None:
    if importlib.util.find_spec("GPy") is None:
        return None
    import GPy

    D = X.shape[1]
    kern = GPy.kern.RBF(
        D,
        variance=float(start["signal_variance"]),
        lengthscale=np.array(start["lengthscales"]),
        ARD=True,
    )
    lik = GPy.likelihoods.Gaussian(variance=float(start["noise_variance"]))
    t0 = time.perf_counter()
    model = GPy.core.SparseGP(
        X,
        (y - y.mean())[:, None],
        np.array(start["inducing_inputs"]),
        kern,
        lik,
        inference_method=GPy.inference.latent_function_inference.FITC(),
    )
    # GPy gets the same single-threaded BLAS as SparseGP's fit (its faster setting here too).
    with threadpool_limits(limits=1, user_api="blas"):
        opt = model.optimize("lbfgsb", max_iters=iters, messages=False)
    elapsed = time.perf_counter() - t0
    return elapsed, float(model.log_likelihood()), int(getattr(opt, "funct_eval", -1))


def rollout_benchmark() -> ModuleType:
    """benchmarks/rollout.py, for its reference-revision loader and paired timer."""
    from pathlib import Path

    spec = importlib.util.spec_from_file_location(
        "_bench_rollout", Path(__file__).resolve().parent / "rollout.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def time_predict_against(gp: SparseGP, X: np.ndarray, rev: str) -> None:
    """predict / predict_with_grad of ``gp`` next to revision ``rev``'s, same state."""
    bench = rollout_benchmark()
    try:
        ref = bench.load_reference(rev, ("sparse_gp",))["sparse_gp"]
    except RuntimeError as err:
        print(f"  reference {rev}: not available ({err})")
        return
    old = ref.SparseGP.from_state(gp.get_state())
    print(f"  side by side with the reference {rev[:12]} (interleaved, best of 7; "
          "ratio = current / reference):")
    for batch in (1, 1024, 36_000):
        Xb = np.resize(X, (batch, X.shape[1]))
        for name in ("predict", "predict_with_grad"):
            f_new, f_old = getattr(gp, name), getattr(old, name)
            new_t, old_t = bench.timeit_pair(
                (lambda f=f_new, a=Xb: f(a), lambda f=f_old, a=Xb: f(a)), 7)
            diff = max(float(np.max(np.abs(a - b)) / max(float(np.max(np.abs(b))), 1e-300))
                       for a, b in zip(f_new(Xb), f_old(Xb), strict=True))
            print(f"    batch {batch:6d} {name:18s} current {new_t[0] * 1e3:8.3f} ms  "
                  f"reference {old_t[0] * 1e3:8.3f} ms  ratio {new_t[0] / old_t[0]:5.3f}  "
                  f"(cpu {new_t[2] / old_t[2]:5.3f})  max |diff| / max |ref| {diff:.1e}")


def time_predict(gp: SparseGP, X: np.ndarray) -> None:
    for batch in (1, 1024, 36_000):
        Xb = np.resize(X, (batch, X.shape[1]))
        gp.predict(Xb)
        reps = max(3, min(2000, 200_000 // batch))
        t0 = time.perf_counter()
        for _ in range(reps):
            gp.predict(Xb)
        dt = (time.perf_counter() - t0) / reps
        t0 = time.perf_counter()
        for _ in range(reps):
            gp.predict_with_grad(Xb)
        dtg = (time.perf_counter() - t0) / reps
        print(
            f"  predict batch {batch:6d}: {dt * 1e3:8.3f} ms  "
            f"({dt / batch * 1e6:7.3f} us/point); with input gradient {dtg * 1e3:8.3f} ms"
        )


def time_rollout(gp_v: SparseGP, gp_w: SparseGP, k: int = 10) -> None:
    """k-step rollout with variance for 1 sequence and a batch of 1,024 (paper Algorithm 1).

    Uses asgp_ros.core.rollout / models when they are available (see core_api contract);
    prints a note otherwise.
    """
    try:
        from asgp_ros.core.features import FeatureConfig
        from asgp_ros.core.models import MotionModel
        from asgp_ros.core.resample import ResampleConfig
        from asgp_ros.core.rollout import rollout
    except ImportError as err:
        print(f"  rollout timing skipped: {err}")
        return
    try:
        model = MotionModel(
            kind="asgp",
            feature_config=FeatureConfig(lags=LAGS),
            resample_config=ResampleConfig(),
            channels=(gp_v, gp_w),
            meta={},
        )
    except TypeError as err:
        print(f"  rollout timing skipped (MotionModel signature: {err})")
        return
    rng = np.random.default_rng(0)
    joy_past = rng.uniform(-0.5, 0.5, (LAGS, 2))
    vel_past = rng.uniform(-0.3, 0.3, (LAGS, 2))
    for batch in (1, 1024):
        joy_future = rng.uniform(-1, 1, (batch, k, 2))
        rollout(model, joy_past, vel_past, joy_future)
        reps = 200 if batch == 1 else 20
        t0 = time.perf_counter()
        for _ in range(reps):
            rollout(model, joy_past, vel_past, joy_future)
        dt = (time.perf_counter() - t0) / reps
        print(f"  rollout k={k} with variance, batch {batch:5d}: {dt * 1e3:8.3f} ms")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small smoke run")
    parser.add_argument("--n", type=int, default=None, help="training samples (36000)")
    parser.add_argument("--m", type=int, default=40, help="pseudo-inputs (40)")
    parser.add_argument("--iters", type=int, default=None, help="L-BFGS-B budget (200)")
    parser.add_argument("--no-gpy", action="store_true", help="skip the GPy reference")
    parser.add_argument("--reference", default=None,
                        help="git revision whose SparseGP.predict is timed side by side "
                        "('none' to skip; default that of benchmarks/rollout.py)")
    args = parser.parse_args()
    n = args.n or (3000 if args.quick else 36_000)
    iters = args.iters or (30 if args.quick else 200)

    X, y = make_data(n, seed=0)
    print(f"SPGP/FITC benchmark: N={X.shape[0]}, D={X.shape[1]}, M={args.m}, "
          f"budget {iters} L-BFGS-B iterations / function evaluations")
    print(f"  machine: {platform.machine()}, python {platform.python_version()}, "
          f"numpy {np.__version__}")

    start = SparseGP(num_inducing=args.m, seed=0).initial_params(X, y)
    results = {}
    for threads in (2, 1):
        gp_t, t_fit, trace = time_sparse_gp(X, y, args.m, iters, threads)
        res = gp_t.optimiser_result
        nfev = int(res.nfev) if res is not None else -1
        results[threads] = (gp_t, t_fit, trace)
        print(f"  asgp_ros SparseGP (threads={threads}): train {t_fit:8.2f} s, log marginal "
              f"likelihood {gp_t.log_marginal_likelihood():14.4f}, {nfev} evaluations "
              f"({t_fit / max(nfev, 1) * 1e3:.1f} ms each)")
    gp, t_ours, trace2 = results[2]
    lml_ours = gp.log_marginal_likelihood()
    gpy = None if args.no_gpy else time_gpy(X, y, start, iters)
    if gpy is None:
        print("  GPy FITC: skipped")
    else:
        t_gpy, lml_gpy, nfev_gpy = gpy
        print(f"  GPy FITC (BLAS 1 thread):       train {t_gpy:8.2f} s, log marginal "
              f"likelihood {lml_gpy:14.4f}, {nfev_gpy} evaluations "
              f"({t_gpy / max(nfev_gpy, 1) * 1e3:.1f} ms each)")
        print(f"  speed-up over GPy: {t_gpy / t_ours:.1f}x (threads=2), "
              f"{t_gpy / results[1][1]:.1f}x (threads=1); log likelihood difference "
              f"(ours - GPy) {lml_ours - lml_gpy:+.4f}")
        reached = [t for t, lml in trace2 if lml >= lml_gpy]
        if reached:
            print(f"  SparseGP (threads=2) reached GPy's final log likelihood after "
                  f"{reached[0]:.2f} s: {t_gpy / reached[0]:.1f}x faster to equal likelihood")

    print("prediction (cached posterior):")
    time_predict(gp, X)
    reference = args.reference or rollout_benchmark().REFERENCE
    if reference.lower() != "none":
        time_predict_against(gp, X, reference)

    print("rollout:")
    gp_w = SparseGP(num_inducing=args.m, seed=1).fit(X, y, max_iter=1)  # stand-in channel
    time_rollout(gp, gp_w)


if __name__ == "__main__":
    main()
