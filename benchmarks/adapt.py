"""Online posterior updates (asgp_ros.core.adapt): the cost per absorbed row.

Usage::

    python benchmarks/adapt.py                  # M = 80, D = 18, 3,000 rows
    python benchmarks/adapt.py --rows 5000 --m 40 --d 9

A channel trained (``SparseGP.from_params``, fixed hyperparameters) on ``--train`` rows of
a smooth function absorbs ``--rows`` further rows one at a time
(:meth:`OnlinePosterior.absorb`, half-life 60 s at 5 Hz, each row's update publishing a
new posterior); each call is timed by the wall clock and by the thread's CPU time (which
leaves out the time the thread waits for a core on a loaded machine).  Then the same rows
in blocks of 10 (:meth:`OnlinePosterior.absorb_rows`, one posterior per block).  Side by
side, as the named reference: the batch refit of the posterior at the same
hyperparameters (``SparseGP.from_params``) on the trained rows plus the new rows, which
is what an update would cost without the online statistics.  BLAS runs on one thread
(threadpoolctl; the updates limit themselves to one thread anyway).  Target from
issue 12: under 0.3 ms per row at M = 80, D = 18.

Then the online predictor (``Predictor``, what the node runs) with and without adaptation,
side by side: an ASGP of M = ``--m`` pseudo-inputs on coupled s = 4 inputs (D = 18) is
conditioned at fixed hyperparameters on a simulated tile drive, and a simulated carpet
drive (``--drive-min`` minutes) is replayed into both predictors sample by sample; at each
completed grid step the time of ``predict`` (what lies between a VO message and the
published path: the node calls ``learn`` after publishing) and of ``learn`` (absorbing the
settled steps, checking the predictions whose outcomes arrived) are measured.  The node's
own latency across processes: ``benchmarks/predictor_latency.py --adapt both``.

Prints figures only (no assertions).  Timings depend on the machine's load.
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np
from threadpoolctl import threadpool_limits

from asgp_ros.core.adapt import AdaptConfig, OnlinePosterior
from asgp_ros.core.sparse_gp import SparseGP

DT = 0.2  # s, the 5 Hz grid


def make_data(n: int, D: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Inputs like standardised autoregressive windows and a smooth nonlinear target."""
    X = rng.standard_normal((n, D))
    w = rng.standard_normal(D) / np.sqrt(D)
    y = np.tanh(X @ w) + 0.2 * np.sin(X[:, 0]) + 0.01 * rng.standard_normal(n)
    return X, y


def percentiles(times: np.ndarray) -> str:
    ms = 1e3 * times
    return (f"median {np.median(ms):.3f} ms, p99 {np.percentile(ms, 99):.3f} ms, "
            f"max {ms.max():.3f} ms")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--m", type=int, default=80, help="pseudo-inputs M")
    parser.add_argument("--d", type=int, default=18, help="input dimension D")
    parser.add_argument("--train", type=int, default=20000, help="trained rows N_T")
    parser.add_argument("--rows", type=int, default=3000, help="rows absorbed")
    parser.add_argument("--refits", type=int, default=5, help="batch refits timed")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--drive-min", type=float, default=5.0,
                        help="minutes of the replayed drive (predictor side by side)")
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    M, D = args.m, args.d
    X_train, y_train = make_data(args.train, D, rng)
    X_new, y_new = make_data(args.rows, D, rng)
    Z = X_train[rng.choice(args.train, M, replace=False)]
    ls, sf2, sn2 = np.full(D, np.sqrt(D)), 0.5, 1e-4
    print(f"M = {M}, D = {D}, N_T = {args.train}, rows absorbed = {args.rows}; "
          f"{platform.processor() or platform.machine()}, numpy {np.__version__}, "
          "BLAS threads = 1")
    with threadpool_limits(limits=1, user_api="blas"):
        gp = SparseGP.from_params(X_train, y_train, Z, ls, sf2, sn2)
        online = OnlinePosterior.from_sparse_gp(gp, AdaptConfig(half_life_s=60.0))
        for i in range(50):  # warm-up, then back to the trained posterior
            online.absorb(X_new[i], float(y_new[i]), DT * i)
        online.reset()
        times = np.empty(args.rows)
        cpu = np.empty(args.rows)
        for i in range(args.rows):
            start, start_cpu = time.perf_counter(), time.thread_time()
            online.absorb(X_new[i], float(y_new[i]), DT * i)
            cpu[i] = time.thread_time() - start_cpu
            times[i] = time.perf_counter() - start
        s = online.stats
        print(f"absorb one row, wall clock:  {percentiles(times)}")
        print(f"absorb one row, CPU time:    {percentiles(cpu)}")
        print(f"  absorbed {s.rows_absorbed}, rejected {dict(s.rejected)}, effective size "
              f"{s.effective_size:.0f} (data {s.data_weight:.0f}, trained weight "
              f"{s.trained_weight:.3f})")
        block = 10
        online.reset()
        btimes = []
        for i in range(0, args.rows - block + 1, block):
            start = time.perf_counter()
            online.absorb_rows(X_new[i:i + block], y_new[i:i + block],
                               DT * np.arange(i, i + block))
            btimes.append((time.perf_counter() - start) / block)
        print(f"absorb_rows, blocks of {block}:   {percentiles(np.asarray(btimes))} per row")

        X_all = np.vstack([X_train, X_new])
        y_all = np.concatenate([y_train, y_new])
        rtimes = []
        for _ in range(args.refits):
            start = time.perf_counter()
            SparseGP.from_params(X_all, y_all, Z, ls, sf2, sn2)
            rtimes.append(time.perf_counter() - start)
        print(f"reference: batch refit (from_params, N = {X_all.shape[0]}): "
              f"{percentiles(np.asarray(rtimes))} per refit")

    predictor_side_by_side(M, args.drive_min, args.seed)


def predictor_side_by_side(M: int, minutes: float, seed: int) -> None:
    """predict() and learn() of the online predictor, adapting and not (see the docstring)."""
    from asgp_ros.core.adaptive import AdaptSettings
    from asgp_ros.core.features import FeatureConfig, design_matrix
    from asgp_ros.core.models import MotionModel
    from asgp_ros.core.online import Predictor
    from asgp_ros.core.resample import ResampleConfig, resample
    from asgp_ros.core.streams import RawStreams
    from asgp_ros.sim.simulate import simulate

    def streams(surface: str, s: int) -> RawStreams:
        rec = simulate(surface, minutes, s)
        return RawStreams(joy_t=rec.joy_t, joy=rec.joy, vel_t=rec.vo_t, vel=rec.vo,
                          vel_ok=~rec.vo_stale)

    rc, fc = ResampleConfig(), FeatureConfig(lags=4, coupled=True)
    res = resample(streams("tile", seed + 1), rc)
    rng = np.random.default_rng(seed)
    channels = []
    for c in (0, 1):
        X, y, _ = design_matrix(res, c, fc)
        Z = X[rng.choice(X.shape[0], M, replace=False)]
        channels.append(SparseGP.from_params(X, y, Z, 3.0 * X.std(axis=0) + 1e-3,
                                             float(np.var(y)), 1e-4))
    model = MotionModel(kind="asgp", feature_config=fc, resample_config=rc,
                        channels=(channels[0], channels[1]))
    drive = streams("carpet", seed + 2)
    events = sorted([(t, 0, j) for j, t in enumerate(drive.joy_t)]
                    + [(t, 1, j) for j, t in enumerate(drive.vel_t)])
    print(f"\nonline predictor, M = {M}, D = {fc.input_dim}, k = 10, a {minutes:g}-minute "
          "carpet drive replayed (model conditioned on tile):")
    with threadpool_limits(limits=1, user_api="blas"):
        for adapt in (None, AdaptSettings()):
            pred = Predictor(model, adapt=adapt)
            t_pred, t_learn, last = [], [], None
            for t, kind, j in events:
                if kind == 0:
                    pred.feed_joy(t, drive.joy[j])
                else:
                    pred.feed_vo(t, drive.vel[j], bool(drive.vel_ok[j]))
                step = pred.ready_step()
                if step is None or step == last:
                    continue
                last = step
                start = time.perf_counter()
                result = pred.predict(t, learn=False)
                mid = time.perf_counter()
                pred.learn()
                end = time.perf_counter()
                if result.ok:
                    t_pred.append(mid - start)
                    t_learn.append(end - mid)
            label = "adapting    " if adapt is not None else "not adapting"
            print(f"  {label}: predict {percentiles(np.asarray(t_pred))}; learn "
                  f"{percentiles(np.asarray(t_learn))} ({len(t_pred)} steps)")
            stats = pred.adaptation
            if stats is not None:
                print(f"    {stats.rows_absorbed} steps absorbed, {stats.checked} predictions "
                      f"checked, published {stats.published}, scales "
                      + "/".join(f"{x:.2f}" for x in stats.scales))


if __name__ == "__main__":
    main()
