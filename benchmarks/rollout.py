"""Rollout speed: k-step prediction with uncertainty (paper Algorithm 1, batched).

Trains the two channels (SparseGP, M = 40, s = 4, D = 9) on a simulated first-order-lag
chair (N ~ 2,000 rows, enough for timing), then times ``rollout`` for one sequence and for
batches of candidate joystick sequences, with linearised uncertainty ("linear"), without
("none") and with Monte Carlo ("mc"). Targets (issue 2): k = 10 with variance under
0.5 ms for one sequence and under 10 ms for a batch of 1,024.

Side by side with a reference (``--reference REV``, default the commit before the FITC
posterior and the kernel became shared modules): ``asgp_ros/core/rollout.py`` and
``asgp_ros/core/sparse_gp.py`` of that revision are extracted with ``git show`` into a
temporary directory and imported under other names. Both rollouts then run on the same
fitted channels and inputs (the reference rollout reads them through
``SparseGP.get_state``, as it always did), timed in alternating order within every run
so that a change in the machine's load hits both alike; the outputs are compared too.

    python benchmarks/rollout.py [--k 10] [--batch 1024] [--repeat 7] [--blas-threads 1]
                                 [--reference REV | --reference none]

Prints figures only (no assertions): the best and the median of ``--repeat`` timing runs,
and the load average, since a shared machine inflates the figures.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from asgp_ros.core.features import FeatureConfig, design_matrix
from asgp_ros.core.models import MotionModel
from asgp_ros.core.resample import ResampleConfig, Resampled
from asgp_ros.core.rollout import rollout
from asgp_ros.core.sparse_gp import SparseGP

REPO = Path(__file__).resolve().parents[1]
#: The last commit with the FITC posterior and the kernel coded separately in sparse_gp.py
#: and rollout.py (the rollout's own ``_FusedSparseGP``).
REFERENCE = "3d263b47098add450075c58f4663fdbe41769378"


def load_reference(rev: str, names: tuple[str, ...] = ("sparse_gp", "rollout")
                   ) -> dict[str, ModuleType]:
    """Modules ``asgp_ros/core/<name>.py`` of revision ``rev``, imported as ``_ref_<name>``.

    The files are extracted with ``git show`` into a temporary directory. Their own
    imports of ``asgp_ros`` resolve to the working tree (features, unicycle, models and,
    inside the reference rollout, the current ``SparseGP``, whose ``get_state`` it reads).

    Raises:
        RuntimeError: git is missing or does not know ``rev``.
    """
    modules: dict[str, ModuleType] = {}
    with tempfile.TemporaryDirectory(prefix="asgp_reference_") as tmp:
        for name in names:
            try:
                source = subprocess.run(
                    ["git", "-C", str(REPO), "show", f"{rev}:asgp_ros/core/{name}.py"],
                    check=True, capture_output=True, text=True).stdout
            except (OSError, subprocess.CalledProcessError) as err:
                detail = getattr(err, "stderr", "") or err
                raise RuntimeError(f"cannot read {name}.py of {rev}: {detail}") from err
            path = Path(tmp) / f"_ref_{name}.py"
            path.write_text(source)
            spec = importlib.util.spec_from_file_location(f"_ref_{name}", path)
            assert spec is not None and spec.loader is not None
            module = importlib.util.module_from_spec(spec)
            sys.modules[spec.name] = module  # dataclasses look their module up by name
            spec.loader.exec_module(module)
            modules[name] = module
    return modules


def simulated(T: int, seed: int = 0) -> Resampled:
    """A 5 Hz recording of a saturating first-order-lag chair with random driving."""
    rng = np.random.default_rng(seed)
    joy = np.clip(np.cumsum(rng.normal(0, 0.12, (T, 2)), axis=0) * 0.3, -1, 1)
    vel = np.zeros((T, 2))
    for t in range(1, T):
        vel[t, 0] = 0.7 * vel[t - 1, 0] + 0.45 * np.tanh(2 * joy[t, 0]) + rng.normal(0, 0.02)
        vel[t, 1] = (0.6 * vel[t - 1, 1] + 0.48 * joy[t, 1] * (1 - 0.3 * abs(vel[t - 1, 0]))
                     + rng.normal(0, 0.02))
    ok = np.ones(T, dtype=bool)
    no = np.zeros(T, dtype=bool)
    return Resampled(t=np.arange(T) / 5.0, k=np.arange(T, dtype=np.int64), joy=joy, vel=vel,
                     valid=ok, stale=no, tracking_lost=no, gap=no,
                     segment=np.zeros(T, dtype=np.int64), truth=np.full((T, 5), np.nan),
                     truth_valid=no, rate_hz=5.0)


def timeit(fn: Callable[[], object], repeat: int,
           min_time: float = 0.2) -> tuple[float, float, float]:
    """(best, median, best CPU) seconds per call over ``repeat`` runs of >= ``min_time``.

    The CPU time of this process is less inflated than wall time when other processes
    compete for the cores.
    """
    fn()
    t0 = time.perf_counter()
    fn()
    once = max(time.perf_counter() - t0, 1e-7)
    number = max(1, int(min_time / once))
    runs, cpu = [], []
    for _ in range(repeat):
        t0 = time.perf_counter()
        c0 = time.process_time()
        for _ in range(number):
            fn()
        cpu.append((time.process_time() - c0) / number)
        runs.append((time.perf_counter() - t0) / number)
    return min(runs), statistics.median(runs), min(cpu)


def timeit_pair(fns: tuple[Callable[[], object], Callable[[], object]], repeat: int,
                min_time: float = 0.2) -> list[tuple[float, float, float]]:
    """:func:`timeit` for two functions, interleaved run by run (order alternating)."""
    number = []
    for fn in fns:
        fn()
        t0 = time.perf_counter()
        fn()
        number.append(max(1, int(min_time / max(time.perf_counter() - t0, 1e-7))))
    n = min(number)
    runs: list[list[float]] = [[], []]
    cpu: list[list[float]] = [[], []]
    for r in range(repeat):
        for i in ((0, 1) if r % 2 == 0 else (1, 0)):
            t0 = time.perf_counter()
            c0 = time.process_time()
            for _ in range(n):
                fns[i]()
            cpu[i].append((time.process_time() - c0) / n)
            runs[i].append((time.perf_counter() - t0) / n)
    return [(min(runs[i]), statistics.median(runs[i]), min(cpu[i])) for i in range(2)]


def max_difference(a: object, b: object) -> tuple[float, float]:
    """Largest absolute difference of the rollouts' arrays, and the largest relative to the
    magnitude of each array (max |a - b| / max |b|)."""
    worst_abs = worst_rel = 0.0
    for name in ("vel", "vel_cov", "pose", "pose_cov"):
        x, y = getattr(a, name), getattr(b, name)
        diff = float(np.max(np.abs(x - y)))
        worst_abs = max(worst_abs, diff)
        worst_rel = max(worst_rel, diff / max(float(np.max(np.abs(y))), 1e-300))
    return worst_abs, worst_rel


def compare_with_reference(model: MotionModel, joy_past: np.ndarray, vel_past: np.ndarray,
                           futures: dict[int, np.ndarray], rev: str, repeat: int) -> None:
    """The current rollout next to revision ``rev``'s, B = 1 and B = 1024, in one run."""
    try:
        reference = load_reference(rev)["rollout"].rollout
    except RuntimeError as err:
        print(f"reference {rev}: not available ({err})")
        return
    print(f"side by side with the reference {rev[:12]} (interleaved runs; best / median ms,"
          " ratio = current / reference; max |diff| over vel, pose and their covariances,"
          " relative to each array's largest value):")
    for batch, fut in futures.items():
        for unc in ("linear", "none"):
            new, old = timeit_pair(
                (lambda f=fut, u=unc: rollout(model, joy_past, vel_past, f, u),
                 lambda f=fut, u=unc: reference(model, joy_past, vel_past, f, u)), repeat)
            diff_abs, diff_rel = max_difference(rollout(model, joy_past, vel_past, fut, unc),
                                                reference(model, joy_past, vel_past, fut, unc))
            print(f"  batch {batch:5d} {unc:6s}  current {new[0] * 1e3:8.3f} / "
                  f"{new[1] * 1e3:8.3f}   reference {old[0] * 1e3:8.3f} / {old[1] * 1e3:8.3f}"
                  f"   ratio {new[0] / old[0]:5.3f} / {new[1] / old[1]:5.3f}"
                  f" (best cpu {new[2] / old[2]:5.3f})"
                  f"   max |diff| {diff_abs:.1e} (relative {diff_rel:.1e})")


def floored_model_line(model: MotionModel, joy_past: np.ndarray, vel_past: np.ndarray,
                       futures: np.ndarray, repeat: int) -> None:
    """An adapted model's rollout (``MotionModel.variance_floor`` of OutsideFloor channels,
    as ``asgp_ros.core.adaptive`` publishes it): the floor reusing the step's kernel rows,
    side by side with the floor computing them again (interleaved runs)."""
    from dataclasses import replace

    from asgp_ros.core import posterior

    floors = tuple(posterior.OutsideFloor(ch.posterior) for ch in model.channels)
    floored = replace(model, variance_floor=replace(model, channels=floors))
    shared = posterior.same_kernel_rows

    def again() -> object:
        posterior.same_kernel_rows = lambda a, b: False  # type: ignore[assignment]
        try:
            return rollout(floored, joy_past, vel_past, futures)
        finally:
            posterior.same_kernel_rows = shared

    (a, b) = timeit_pair((lambda: rollout(floored, joy_past, vel_past, futures), again),
                         repeat)
    plain = timeit(lambda: rollout(model, joy_past, vel_past, futures), repeat)
    print(f"  batch     1  with an adapted model's floor: {a[0] * 1e3:.3f} / {a[1] * 1e3:.3f} "
          f"ms, the floor computing its own kernel rows {b[0] * 1e3:.3f} / {b[1] * 1e3:.3f} "
          f"ms, no floor {plain[0] * 1e3:.3f} / {plain[1] * 1e3:.3f} ms")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--k", type=int, default=10, help="horizon in steps (10 = 2 s at 5 Hz)")
    ap.add_argument("--batch", type=int, default=1024)
    ap.add_argument("--rows", type=int, default=2000, help="training rows per channel")
    ap.add_argument("--inducing", type=int, default=40)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--mc-samples", type=int, default=500)
    ap.add_argument("--reference", default=REFERENCE,
                    help="git revision to time side by side ('none' to skip); default the "
                    "commit before the shared FITC posterior and kernel modules")
    ap.add_argument("--blas-threads", type=int, default=1,
                    help="BLAS threads (threadpoolctl; 0 = the library default). The "
                    "matrices are small, so extra threads only add synchronisation, "
                    "which costs a lot on a loaded machine")
    args = ap.parse_args()
    if args.blas_threads > 0:
        from threadpoolctl import threadpool_limits

        threadpool_limits(args.blas_threads)

    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.2f}, BLAS threads "
          f"{args.blas_threads if args.blas_threads > 0 else 'default'}")
    res = simulated(args.rows + 4)
    fc = FeatureConfig(lags=4)
    gps = []
    t0 = time.perf_counter()
    for c in range(2):
        X, y, _ = design_matrix(res, c, fc)
        gps.append(SparseGP(num_inducing=args.inducing, seed=0).fit(X, y, max_iter=100))
    print(f"trained 2 x SparseGP (N={X.shape[0]}, D={X.shape[1]}, M={args.inducing}) in "
          f"{time.perf_counter() - t0:.2f} s")
    model = MotionModel("asgp", fc, ResampleConfig(), (gps[0], gps[1]))

    rng = np.random.default_rng(1)
    t = 500
    joy_past, vel_past = res.joy[t - 4:t], res.vel[t - 4:t]
    k = args.k
    print(f"rollout k={k}, wall time best / median of {args.repeat} runs, and best CPU time:")
    for batch in (1, 64, args.batch):
        futures = np.clip(res.joy[t:t + k][None] + rng.normal(0, 0.3, (batch, k, 2)), -1, 1)
        for unc in ("linear", "none"):
            best, med, cpu = timeit(
                lambda f=futures, u=unc: rollout(model, joy_past, vel_past, f, u), args.repeat
            )
            label = "with variance (linear)" if unc == "linear" else "mean only (none)"
            print(f"  batch {batch:5d}  {label:24s} {best * 1e3:8.3f} / {med * 1e3:8.3f} ms"
                  f"   cpu {cpu * 1e3:8.3f} ms")
    futures = res.joy[t:t + k][None]
    n = args.mc_samples
    best, med, cpu = timeit(
        lambda: rollout(model, joy_past, vel_past, futures, "mc", n_samples=n),
        max(3, args.repeat // 2))
    print(f"  batch     1  Monte Carlo, {n} samples  {best * 1e3:8.3f} / {med * 1e3:8.3f} ms"
          f"   cpu {cpu * 1e3:8.3f} ms")
    print("targets: batch 1 with variance < 0.5 ms; batch 1024 with variance < 10 ms")
    floored_model_line(model, joy_past, vel_past, res.joy[t:t + k][None], args.repeat)
    if args.reference.lower() != "none":
        futures_by_batch = {
            batch: np.clip(res.joy[t:t + k][None] + rng.normal(0, 0.3, (batch, k, 2)), -1, 1)
            for batch in (1, args.batch)
        }
        compare_with_reference(model, joy_past, vel_past, futures_by_batch, args.reference,
                               args.repeat)


if __name__ == "__main__":
    main()
