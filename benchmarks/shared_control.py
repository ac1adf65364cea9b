"""Speed of the shared-control layer: the collision check and the whole decision.

Prints:
* the collision probability of B predicted paths (k = 10) running up to a wall, against a
  1081-beam scan of the simulated room, for B = 1, 64, 256, 1024 (p50 / p99 of the CPU
  time, ms, one core): the raster and the exact method (the rectangle against every
  obstacle point in reach) side by side with position covariances, with the raster's
  tolerance and how far its per-step probabilities lie above the exact ones; then the
  default method with position covariances and with pose covariances (the heading sampled
  too);
* the distance field of one scan (:meth:`collision.DistanceField.from_scan`, built for
  every decision), p50 / p99 of the CPU time, with OpenCV's exact Euclidean transform (the
  one used) and, side by side, with ``scipy.ndimage.distance_transform_edt``;
* the layer's decision on a simulated drive of an inattentive user
  (:mod:`asgp_ros.sim.shared_drive`): p50 / p99 ms per decision and the share of one core
  it takes at 5 Hz, beside the same drive without the layer (the simulator's own cost).

Usage: benchmarks/shared_control.py [MODEL] [--minutes M] [--no-heading] [--no-exact]
                                   [--hull-reference SECONDS]
(without MODEL a tile model is trained on 10 simulated minutes first, about a minute).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from asgp_ros.core import collision
from asgp_ros.core.modelfile import load_model
from asgp_ros.core.shared_control import SharedControlConfig
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


def _paths(rng: np.random.Generator, B: int) -> tuple[np.ndarray, np.ndarray]:
    """B paths of 10 steps straight ahead at speeds up to 1 m/s (the first at 1 m/s, into
    the wall), headings drifting apart; position sd 2 to 10 cm, heading sd 0.6 to 6
    degrees, correlated with y (a turn)."""
    pose = np.zeros((B, 10, 3))
    speed = rng.uniform(0.0, 1.0, B)
    speed[0] = 1.0
    pose[..., 0] = speed[:, None] * np.linspace(0.2, 2.0, 10)[None]
    pose[..., 2] = rng.normal(0.0, 0.3, B)[:, None] * np.linspace(0.1, 1.0, 10)[None]
    sd = np.linspace(0.02, 0.1, 10)
    sd_th = np.linspace(0.01, 0.1, 10)
    cov = np.zeros((B, 10, 3, 3))
    cov[..., 0, 0] = cov[..., 1, 1] = sd**2
    cov[..., 2, 2] = sd_th**2
    cov[..., 1, 2] = cov[..., 2, 1] = 0.5 * sd * sd_th
    return pose, cov


def _time(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    """p50 and p99 of the CPU time of ``fn`` (ms): on a machine shared with other jobs
    the wall time also counts the waits for a core."""
    times = []
    for _ in range(repeats):
        t = time.process_time()
        fn()
        times.append(time.process_time() - t)
    ms = 1e3 * np.array(times)
    return float(np.percentile(ms, 50)), float(np.percentile(ms, 99))


def collision_speed(repeats: int = 30, exact: bool = True) -> None:
    room = Room()
    lidar = Lidar(room, seed=0)
    x_hi = room.free_box[1]
    s = lidar.scan(x_hi - 1.5, 0.0, 0.0)
    scan = collision.Scan(s.ranges, s.angle_min, s.angle_increment, s.range_min, s.range_max)
    fld = collision.DistanceField.from_scan(scan)
    to_scan = collision.inverse_pose(lidar.config.mount)  # base frame -> scan frame
    rng = np.random.default_rng(0)

    def probability(pose: np.ndarray, cov: np.ndarray, method: str = "auto"
                    ) -> collision.Contact:
        return collision.contact_probability(fld, pose, cov, transform=to_scan,
                                             method=method)

    probability(*_paths(np.random.default_rng(1), 1))  # the draws are made on the first call
    batches = [(B, *_paths(rng, B)) for B in (1, 64, 256, 1024)]
    print("collision probability, k = 10 steps, 1081-beam scan, wall 1.5 m ahead, CPU time "
          "on one core")
    print("the two methods, position covariances (ms; tol: a sample counted as touching "
          "touches the footprint grown by tol)")
    print(f"{'B':>6} | {'raster p50 / p99':>17} {'tol':>6} | {'exact p50 / p99':>17} | "
          "raster - exact per step: mean, largest, smallest")
    for B, pose, cov in batches:
        pos = np.ascontiguousarray(cov[..., :2, :2])
        fast = probability(pose, pos, "raster")
        r50, r99 = _time(lambda: probability(pose, pos, "raster"), repeats)  # noqa: B023
        line = f"{B:6d} | {r50:7.2f} / {r99:7.2f} {100 * fast.tolerance:4.1f}cm |"
        if exact:
            ref = probability(pose, pos, "exact")
            e50, e99 = _time(lambda: probability(pose, pos, "exact"),  # noqa: B023
                             max(3, repeats // (1 + B // 64)))
            gap = fast.per_step - ref.per_step
            line += (f" {e50:7.1f} / {e99:7.1f} | {gap.mean():.4f}, {gap.max():.3f}, "
                     f"{gap.min():.3f}")
        print(line, flush=True)
    print("the default (method auto: exact for a path or two, else the raster), position "
          "covariances and pose covariances (heading sd 0.6 to 6 degrees)")
    print(f"{'B':>6} | {'position p50 / p99':>19} {'tol':>6} | {'pose p50 / p99':>17} {'tol':>6}")
    for B, pose, cov in batches:
        pos = np.ascontiguousarray(cov[..., :2, :2])
        a, b = probability(pose, pos), probability(pose, cov)
        p50, p99 = _time(lambda: probability(pose, pos), repeats)  # noqa: B023
        h50, h99 = _time(lambda: probability(pose, cov), repeats)  # noqa: B023
        print(f"{B:6d} | {p50:8.2f} / {p99:8.2f} {100 * a.tolerance:4.1f}cm | {h50:7.2f} / "
              f"{h99:7.2f} {100 * b.tolerance:4.1f}cm", flush=True)


def field_speed(repeats: int = 200) -> None:
    """The distance field of a 1081-beam scan of the simulated room (8 m range, 5 cm cells),
    OpenCV's transform and scipy's, alternately, three times."""
    import scipy.ndimage

    room = Room()
    s = Lidar(room, seed=0).scan(2.0, 0.3, 0.2)
    scan = collision.Scan(s.ranges, s.angle_min, s.angle_increment, s.range_min, s.range_max)
    used = collision._distances

    def scipy_distances(mask: np.ndarray, res: float) -> np.ndarray:
        if not mask.any():
            return np.full(mask.shape, np.inf)
        edt = scipy.ndimage.distance_transform_edt(~mask)
        return np.maximum(np.asarray(edt, dtype=np.float64) * res - 0.5 * res, 0.0)

    print("the distance field of one scan (1081 beams, 8 m, 5 cm cells), CPU time on one core:")
    fields = {}
    for _ in range(3):
        line = []
        for name, fn in (("OpenCV", used), ("scipy", scipy_distances)):
            collision._distances = fn
            try:
                fields[name] = collision.DistanceField.from_scan(scan)
                p50, p99 = _time(lambda: collision.DistanceField.from_scan(scan), repeats)
            finally:
                collision._distances = used
            line.append(f"{name} p50 / p99 {p50:.2f} / {p99:.2f} ms")
        print("  " + ";  ".join(line))
    gap = fields["scipy"].dist - fields["OpenCV"].dist
    print(f"  clearances: OpenCV's at most scipy's ({bool(np.all(gap >= 0.0))}), by at most "
          f"{1e6 * gap.max():.3f} um")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model", nargs="?")
    ap.add_argument("--minutes", type=float, default=5.0)
    ap.add_argument("--no-heading", action="store_true",
                    help="the layer checks with the position covariance and mean heading")
    ap.add_argument("--no-exact", action="store_true", help="skip the exact method")
    ap.add_argument("--hull-reference", type=float, default=0.0, metavar="SECONDS",
                    help="also time a hybrid drive of SECONDS with the raster's windows from "
                    "the hull and from every point, side by side")
    args = ap.parse_args(argv)
    config = SharedControlConfig(heading_uncertainty=not args.no_heading)
    with threadpool_limits(limits=1):
        collision_speed(exact=not args.no_exact)
        field_speed()
        model = _model(args.model)
        t = time.process_time()
        base = drive(model, 60 * args.minutes, 1, layer=False)
        cpu_sim = time.process_time() - t
        t = time.process_time()
        run = drive(model, 60 * args.minutes, 1, layer=True, config=config)
        cpu_layer = time.process_time() - t - cpu_sim
    ms = np.asarray(run.solve_ms)
    decisions = len(ms)
    print(f"decisions on a {args.minutes:g}-minute inattentive drive (heading "
          f"{'not ' if args.no_heading else ''}sampled): {decisions}")
    print(f"  per decision: p50 {np.percentile(ms, 50):.2f} ms, p99 {np.percentile(ms, 99):.2f} "
          f"ms, mean {ms.mean():.2f} ms")
    rate = decisions / (60 * args.minutes)
    print(f"  the layer's CPU (drive with it less the drive without, which took "
          f"{cpu_sim:.1f} s): {cpu_layer:.1f} s = {100 * cpu_layer / (60 * args.minutes):.1f} % "
          f"of one core at {rate:.1f} decisions/s")
    print(f"  contacts without / with the layer: {base.contacts} / {run.contacts}")
    if args.hull_reference:
        hull_side_by_side(model, args.hull_reference)
    return 0


def hull_side_by_side(model, seconds: float) -> None:
    """The raster's windows cut by the obstacle points' convex hull (now) or by every
    point's box (``collision._support_points`` the identity, as before), on a hybrid drive
    of ``seconds`` with the velocity source 'auto' (the obstacle memory carried by scan
    matching, many points in reach), alternately, twice each: CPU time of the whole drive,
    and whether the two drives are the same."""
    hull = collision._support_points
    print(f"the raster's windows from the hull vs from every point, a {seconds:g}-s hybrid "
          "drive (velocity source auto), CPU s of the whole drive:")
    summaries = []
    for _ in range(2):
        for name, support in (("hull", hull), ("every point", lambda p: p)):
            collision._support_points = support
            try:
                t = time.process_time()
                r = drive(model, seconds, 3, layer=True, inattention=0.5, surface="hybrid",
                          velocity_source="auto")
                print(f"  {name:11s} {time.process_time() - t:6.2f} s")
            finally:
                collision._support_points = hull
            summaries.append(r.summary() | {"solve_p50_ms": 0, "solve_p99_ms": 0})
    print(f"  the same drive every time: {all(x == summaries[0] for x in summaries)}")


if __name__ == "__main__":
    sys.exit(main())
