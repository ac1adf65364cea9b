"""Speed of the inverse model and of the batched rollout it rests on.

Prints, on one core (BLAS limited to one thread):
* one solve over k = 10 steps, for each method (p50 / p99 ms over ``--targets`` varied
  reachable targets, after one solve not timed);
* the batched rollout of 1,024 candidate joystick sequences over k = 10 ("none" and
  "linear" uncertainty), in candidate-steps per second, beside the machine's
  matrix-multiply rate measured in the same run (GFLOP/s of a 1024 x M x M product, M the
  model's pseudo-inputs), and the rollout's arithmetic in the same unit, so the distance
  to the hardware's limit is visible.

Usage: benchmarks/inverse.py [MODEL] [--targets N]   (default: a tile model trained on 10 simulated
minutes, about a minute)
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from asgp_ros.core.inverse import METHODS, solve
from asgp_ros.core.modelfile import load_model
from asgp_ros.core.rollout import rollout


def _model(path: str | None):
    if path:
        return load_model(path)
    from asgp_ros.learning.training import AutoOptions, read_series, train_auto
    from asgp_ros.sim.simulate import simulate, write_recording

    with tempfile.TemporaryDirectory() as tmp:
        bag = Path(tmp) / "tile"
        write_recording(bag, simulate("tile", 10.0, 11))
        return train_auto(read_series([str(bag)]), AutoOptions(budget_s=30.0))


def _pct(ms: list[float]) -> str:
    a = np.asarray(ms)
    return f"p50 {np.percentile(a, 50):7.2f} ms  p99 {np.percentile(a, 99):7.2f} ms"


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model", nargs="?", default=None,
                    help="model file (default: train a tile model on 10 simulated minutes)")
    ap.add_argument("--targets", type=int, default=200,
                    help="reachable targets the solves are timed on (200)")
    args = ap.parse_args(argv)
    model = _model(args.model)
    s, k = model.feature_config.lags, 10
    rng = np.random.default_rng(0)
    M = max(int(getattr(ch, "inducing_inputs", np.zeros((40, 1))).shape[0])
            for ch in model.channels)
    with threadpool_limits(limits=1):
        print(f"model: s = {s}, M = {M}, coupled = {model.feature_config.coupled}")
        cases = []
        for _ in range(max(1, args.targets)):
            jp = np.tile(rng.uniform([0.0, -0.5], [0.8, 0.5]), (s, 1))
            vp = np.tile([0.9 * jp[0, 0], 0.6 * jp[0, 1]], (s, 1)) + rng.normal(0, 0.01, (s, 2))
            U = np.clip(jp[-1] + np.cumsum(rng.normal(0, 0.1, (k, 2)), axis=0), -1, 1)
            target = rollout(model, jp, vp, U[None], uncertainty="none").pose[0, :, :2]
            cases.append((jp, vp, target))
        for method in METHODS:
            times, errors = [], []
            solve(model, *cases[0], method=method)  # warm-up: a node pays it once, at start
            for jp, vp, target in cases:
                t = time.perf_counter()
                res = solve(model, jp, vp, target, method=method)
                times.append(1e3 * (time.perf_counter() - t))
                errors.append(float(res.tracking_error[-1]))
            print(f"solve, k = {k}, {method:12s}: {_pct(times)}; reachable targets: median "
                  f"error at the horizon {1e3 * np.median(errors):.1f} mm")

        B = 1024
        jp, vp, _ = cases[0]
        U = rng.uniform(-1, 1, (B, k, 2))
        for mode in ("none", "linear"):
            rollout(model, jp, vp, U, uncertainty=mode)  # warm-up
            t = time.perf_counter()
            reps = 5
            for _ in range(reps):
                rollout(model, jp, vp, U, uncertainty=mode)
            dt = (time.perf_counter() - t) / reps
            print(f"rollout of {B} candidates x {k} steps ({mode}): {dt * 1e3:.1f} ms = "
                  f"{B * k / dt / 1e6:.2f} M candidate-steps/s")
        A = rng.standard_normal((B, M))
        W = rng.standard_normal((M, M))
        A @ W
        t = time.perf_counter()
        reps = 50
        for _ in range(reps):
            A @ W
        gflops = 2 * B * M * M * reps / (time.perf_counter() - t) / 1e9
        print(f"matrix multiply {B} x {M} x {M}: {gflops:.1f} GFLOP/s on this core")
        D = model.feature_config.input_dim
        mean_flops = 2 * 2 * B * k * M * (D + 1)  # kernel row and mean, both channels
        print(f"  the rollout's mean needs about {mean_flops / 1e9:.3f} GFLOP per {B}-batch: "
              f"{mean_flops / 1e9 / gflops * 1e3:.1f} ms at that rate")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
