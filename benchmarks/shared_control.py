"""Speed of the shared-control layer: the collision check and the whole decision.

Prints:
* the collision probability of B predicted paths (k = 10) against a 1081-beam scan of the
  simulated room, for B = 1, 64, 256, 1024 (p50 / p99 ms), on one core;
* the layer's decision on a simulated drive of an inattentive user
  (:mod:`asgp_ros.sim.shared_drive`): p50 / p99 ms per decision and the share of one core
  it takes at 5 Hz, beside the same drive without the layer (the simulator's own cost).

Usage: benchmarks/shared_control.py [MODEL] [--minutes M]
(without MODEL a tile model is trained on 10 simulated minutes first, about a minute).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from asgp_ros.core import collision
from asgp_ros.core.modelfile import load_model
from asgp_ros.sim.lidar import Lidar
from asgp_ros.sim.shared_drive import drive
from asgp_ros.sim.world import Room


def _model(path: str | None):
    if path:
        return load_model(path)
    from asgp_ros.learning.training import AutoOptions, read_series, train_auto
    from asgp_ros.sim.simulate import simulate, write_recording

    with tempfile.TemporaryDirectory() as tmp:
        bag = Path(tmp) / "tile"
        write_recording(bag, simulate("tile", 10.0, 11))
        return train_auto(read_series([str(bag)]), AutoOptions(budget_s=30.0))


def collision_speed(repeats: int = 30) -> None:
    room = Room()
    lidar = Lidar(room, seed=0)
    x_hi = room.free_box[1]
    s = lidar.scan(x_hi - 1.5, 0.0, 0.0)
    scan = collision.Scan(s.ranges, s.angle_min, s.angle_increment, s.range_min, s.range_max)
    check = collision.scan_check(scan, mount=lidar.config.mount)
    rng = np.random.default_rng(0)
    print("collision probability, k = 10 steps, 1081-beam scan, wall 1.5 m ahead")
    for B in (1, 64, 256, 1024):
        pose = np.zeros((B, 10, 3))
        speed = rng.uniform(0.0, 1.0, B)
        pose[..., 0] = speed[:, None] * np.linspace(0.2, 2.0, 10)[None]
        pose[..., 2] = rng.normal(0.0, 0.3, B)[:, None] * np.linspace(0.1, 1.0, 10)[None]
        cov = np.tile(np.eye(2), (B, 10, 1, 1)) * (np.linspace(0.02, 0.1, 10) ** 2)[
            None, :, None, None]
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            check(pose, cov)
            times.append(time.perf_counter() - t)
        ms = 1e3 * np.array(times)
        print(f"  B = {B:5d}: p50 {np.percentile(ms, 50):7.2f} ms  p99 "
              f"{np.percentile(ms, 99):7.2f} ms")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model", nargs="?")
    ap.add_argument("--minutes", type=float, default=5.0)
    args = ap.parse_args(argv)
    with threadpool_limits(limits=1):
        collision_speed()
        model = _model(args.model)
        t = time.process_time()
        base = drive(model, 60 * args.minutes, 1, layer=False)
        cpu_sim = time.process_time() - t
        t = time.process_time()
        run = drive(model, 60 * args.minutes, 1, layer=True)
        cpu_layer = time.process_time() - t - cpu_sim
    ms = np.asarray(run.solve_ms)
    decisions = len(ms)
    print(f"decisions on a {args.minutes:g}-minute inattentive drive: {decisions}")
    print(f"  per decision: p50 {np.percentile(ms, 50):.2f} ms, p99 {np.percentile(ms, 99):.2f} "
          f"ms, mean {ms.mean():.2f} ms")
    rate = decisions / (60 * args.minutes)
    print(f"  the layer's CPU (drive with it less the drive without, which took "
          f"{cpu_sim:.1f} s): {cpu_layer:.1f} s = {100 * cpu_layer / (60 * args.minutes):.1f} % "
          f"of one core at {rate:.1f} decisions/s")
    print(f"  contacts without / with the layer: {base.contacts} / {run.contacts}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
