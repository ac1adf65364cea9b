"""How far the obstacle memory's odometry drifts: the error of a remembered point.

The shared-control layer carries the scans' obstacle points along with the chair
(:class:`asgp_ros.core.obstacle_memory.ScanMemory`), by dead reckoning of the VO's twists
(:class:`~asgp_ros.core.obstacle_memory.Odometer`) or by matching the scans
(:class:`asgp_ros.core.scan_match.ScanOdometer`). A point seen ``age`` seconds ago, 1 m
from the chair, is misplaced by the error of the chair's relative pose over that time:
the translation error plus the heading error times 1 m. This drives the simulated chair
with the simulated user, feeds the odometer what the offline shared-control drive feeds
it (a frame-to-frame VO at 5 Hz, with noise; :mod:`asgp_ros.sim.shared_drive`) and prints
the error's median, p95 and maximum for ages of 2, 5 and 10 s, at the simulated VO's noise
and at multiples of it, and of scan matching on the simulated scanner's scans of the same
drive. With ``--bag``, the same from a recording's ``vo/twist`` against its
``ground_truth/odom`` (``asgp demo`` records both in ``run_bag``: the rendered camera's VO;
on a real chair, any ground truth published as nav_msgs/Odometry on that topic), and scan
matching on scans cast from that ground truth. For a bag of the simulated room (``asgp
demo``, ``--surface`` its floor) it also replays the memory itself: scans cast from the
true poses at 10 Hz, the memory (10 s) carried by the bag's twists, by the true ones and by
scan matching, and prints the share of remembered points that sit more than 5 cm inside
the free floor (ghost obstacles).

Usage: benchmarks/odometer_drift.py [--minutes 10] [--seed 1] [--noise 1,2,4]
[--bag BAG [--surface tile]]
"""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np

from asgp_ros.common import topics
from asgp_ros.core import collision
from asgp_ros.core.obstacle_memory import Odometer, ScanMemory, compose
from asgp_ros.core.quaternion import quaternion_to_yaw
from asgp_ros.core.scan_match import ScanOdometer
from asgp_ros.sim.chair import Chair
from asgp_ros.sim.driver import Driver
from asgp_ros.sim.lidar import Lidar
from asgp_ros.sim.shared_drive import STEP_S, VO_EVERY, VO_NOISE, frame_twist
from asgp_ros.sim.world import room_for_surface

AGES_S = (2.0, 5.0, 10.0)


def relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pose b in the frame of pose a."""
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy, math.remainder(b[2] - a[2], 2 * math.pi)])


def point_errors(stamps: np.ndarray, truth: np.ndarray, est: np.ndarray, epochs: np.ndarray
                 ) -> dict[float, np.ndarray]:
    """Error (m) of a point 1 m from the chair remembered for each of ``AGES_S``: truth and
    est [n, 3] poses at ``stamps`` [n]; pairs across an epoch break are skipped."""
    out = {}
    for age in AGES_S:
        later = np.searchsorted(stamps, stamps + age)
        errs = []
        for i, j in enumerate(later):
            if j >= len(stamps) or epochs[j] != epochs[i]:
                continue
            rt, re = relative(truth[i], truth[j]), relative(est[i], est[j])
            errs.append(math.hypot(rt[0] - re[0], rt[1] - re[1])
                        + abs(math.remainder(rt[2] - re[2], 2 * math.pi)) * 1.0)
        out[age] = np.array(errs)
    return out


def read_bag(bag: str) -> tuple[np.ndarray, np.ndarray]:
    """A recording's twists [n, 3] (t, v, omega) and ground truth [m, 4] (t, x, y, yaw)."""
    from pathlib import Path

    from rosbags.highlevel import AnyReader  # only for --bag

    twists, truth = [], []
    with AnyReader([Path(bag)]) as reader:
        wanted = {topics.in_bag(topics.VO_TWIST), topics.BAG_GROUND_TRUTH}
        conns = [c for c in reader.connections if c.topic in wanted]
        if {c.topic for c in conns} != wanted:
            raise SystemExit(f"{bag} needs {sorted(wanted)}")
        for conn, _, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            t = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
            if conn.topic == topics.BAG_GROUND_TRUTH:
                q = msg.pose.pose.orientation
                truth.append((t, msg.pose.pose.position.x, msg.pose.pose.position.y,
                              float(quaternion_to_yaw(q.x, q.y, q.z, q.w))))
            else:
                twists.append((t, msg.twist.linear.x, msg.twist.angular.z))
    return np.array(sorted(twists)), np.array(sorted(truth))


def bag_drift(tw: np.ndarray, gt: np.ndarray) -> tuple[dict[float, np.ndarray], int]:
    """:func:`point_errors` of a recording's twists against its ground truth."""
    odo = Odometer(0.5)
    stamps, est, epochs = [], [], []
    for t, v, w in tw:
        if odo.feed(t, v, w):
            pose = odo.pose_at(t)
            assert pose is not None
            stamps.append(t)
            est.append(pose)
            epochs.append(odo.epoch)
    st = np.array(stamps)
    idx = np.clip(np.searchsorted(gt[:, 0], st), 0, len(gt) - 1)  # the truth at each twist
    return point_errors(st, gt[idx, 1:], np.array(est), np.array(epochs)), odo.breaks


def ghost_share(tw: np.ndarray | None, gt: np.ndarray, surface: str) -> float:
    """Share of remembered points more than 5 cm inside the simulated room's free floor,
    the memory carried by the twists ``tw`` [n, 3] (None: by matching the scans) and scans
    cast from the truth ``gt``."""
    room = room_for_surface(surface)
    lidar = Lidar(room, seed=1)
    mount = lidar.config.mount
    odo, memory = Odometer(0.5), ScanMemory(mount)
    matcher = ScanOdometer(mount)
    x_lo, x_hi, y_lo, y_hi = room.free_box
    k, inside, total = 0, 0, 0
    for t in np.arange(gt[0, 0] + 1.0, gt[-1, 0], 1.0 / lidar.config.rate_hz):
        while tw is not None and k < len(tw) and tw[k, 0] <= t:
            odo.feed(*tw[k])
            k += 1
        i = min(int(np.searchsorted(gt[:, 0], t)), len(gt) - 1)
        x, y, th = gt[i, 1:]
        r = lidar.scan(x, y, th)
        scan = collision.Scan(r.ranges, r.angle_min, r.angle_increment, r.range_min,
                              r.range_max, float(t))
        if tw is None:
            extra = memory.add(scan, matcher.add(scan), matcher.epoch)
        else:
            extra = memory.add(scan, odo.pose_at(float(t)), odo.epoch)
        if not extra.size:
            continue
        sx, sy, sth = compose((x, y, th), mount)  # the scanner's true pose
        c, s = math.cos(sth), math.sin(sth)
        wx = sx + c * extra[:, 0] - s * extra[:, 1]
        wy = sy + s * extra[:, 0] + c * extra[:, 1]
        depth = np.minimum.reduce([wx - x_lo, x_hi - wx, wy - y_lo, y_hi - wy])
        inside += int((depth > 0.05).sum())
        total += extra.shape[0]
    return inside / max(total, 1)


def drift(minutes: float, seed: int, noise_scale: float) -> dict[float, np.ndarray]:
    room = room_for_surface("tile")
    chair = Chair.for_room(room, seed=seed, blocked=room.overlap)
    state = chair.reset((0.0, 0.0, 0.0))
    driver = Driver(seed + 1, room)
    rng = np.random.default_rng(seed + 2)
    odo = Odometer(0.5)
    truth, est = [], []
    prev = None
    stick = np.zeros(2)
    for n in range(round(60.0 * minutes / STEP_S)):
        t = n * STEP_S
        if n % 2 == 0:
            stick = driver.command(t, state)
        state = chair.step(stick, STEP_S)
        if n % VO_EVERY != 3:
            continue
        if prev is not None:  # the offline drive's VO
            v, w = frame_twist(prev, state, t, rng,
                               (noise_scale * VO_NOISE[0], noise_scale * VO_NOISE[1]))
            odo.feed(t, v, w)
            pose = odo.pose_at(t)
            assert pose is not None
            truth.append((state.x, state.y, state.theta))
            est.append(pose)
        prev = (state.x, state.y, state.theta, t)
    tr, es = np.array(truth), np.array(est)
    stamps = VO_EVERY * STEP_S * np.arange(len(tr))
    return point_errors(stamps, tr, es, np.zeros(len(tr), dtype=int))


def scan_drift(stamps: np.ndarray, gt: np.ndarray, surface: str
               ) -> tuple[dict[float, np.ndarray], int]:
    """:func:`point_errors` of the scan matcher (:mod:`asgp_ros.core.scan_match`) on scans
    cast from the poses ``gt`` [n, 3] at ``stamps`` [n] in the simulated room."""
    room = room_for_surface(surface)
    lidar = Lidar(room, seed=2)
    odo = ScanOdometer(lidar.config.mount)
    est, epochs = [], []
    for t, (x, y, th) in zip(stamps, gt, strict=True):
        r = lidar.scan(x, y, th)
        est.append(odo.add(collision.Scan(r.ranges, r.angle_min, r.angle_increment,
                                          r.range_min, r.range_max, float(t))))
        epochs.append(odo.epoch)
    return point_errors(stamps, gt, np.array(est), np.array(epochs)), odo.breaks


def truth_at_scans(minutes: float, seed: int, rate_hz: float = 10.0
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The simulated user's drive of :func:`drift` (same seed): stamps and true poses at the
    scanner's rate."""
    room = room_for_surface("tile")
    chair = Chair.for_room(room, seed=seed, blocked=room.overlap)
    state = chair.reset((0.0, 0.0, 0.0))
    driver = Driver(seed + 1, room)
    every = round(1.0 / (rate_hz * STEP_S))
    stamps, poses = [], []
    stick = np.zeros(2)
    for n in range(round(60.0 * minutes / STEP_S)):
        t = n * STEP_S
        if n % 2 == 0:
            stick = driver.command(t, state)
        state = chair.step(stick, STEP_S)
        if n % every == 0:
            stamps.append(t)
            poses.append((state.x, state.y, state.theta))
    return np.array(stamps), np.array(poses)


def print_errors(label: str, errors: dict[float, np.ndarray]) -> None:
    for age, errs in errors.items():
        print(f"{label} | {age:4g} s | {100 * np.median(errs):5.1f} cm | "
              f"{100 * np.percentile(errs, 95):5.1f} cm | {100 * errs.max():5.1f} cm")


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--noise", default="1,2,4",
                    help="multiples of the simulated VO's noise (1 cm/s, 0.01 rad/s)")
    ap.add_argument("--bag", help="a recording with vo/twist and ground_truth/odom instead")
    ap.add_argument("--surface", default="tile", help="the simulated room of --bag")
    args = ap.parse_args(argv)
    if args.bag:
        tw, gt = read_bag(args.bag)
        errors, breaks = bag_drift(tw, gt)
        print(f"error of a point 1 m from the chair, remembered for AGE ({args.bag}: "
              f"vo/twist against ground_truth/odom; {breaks} breaks in the twists)")
        print("age  | median  | p95     | max")
        for age, errs in errors.items():
            print(f"{age:4g} s | {100 * np.median(errs):5.1f} cm | "
                  f"{100 * np.percentile(errs, 95):5.1f} cm | {100 * errs.max():5.1f} cm")
        # the truth's twists: the differences of its poses over their intervals
        rel = [relative(gt[j - 1, 1:], gt[j, 1:]) for j in range(1, len(gt))]
        dt = np.diff(gt[:, 0])
        truth_twists = np.column_stack([gt[1:, 0], [r[0] for r in rel] / dt,
                                        [r[2] for r in rel] / dt])
        print(f"remembered points > 5 cm inside the free floor ({args.surface} room, memory "
              f"10 s): {100 * ghost_share(tw, gt, args.surface):.2f} % carried by the bag's "
              f"twists, {100 * ghost_share(truth_twists, gt, args.surface):.2f} % by the "
              f"truth's, {100 * ghost_share(None, gt, args.surface):.2f} % by scan matching")
        at = np.arange(gt[0, 0] + 1.0, gt[-1, 0], 0.1)  # the truth at 10 Hz
        idx = np.clip(np.searchsorted(gt[:, 0], at), 0, len(gt) - 1)
        errors, breaks = scan_drift(at, gt[idx, 1:], args.surface)
        print(f"scan matching on scans cast from the truth ({breaks} breaks):")
        print_errors("scan matching", errors)
        return 0
    print(f"error of a point 1 m from the chair, remembered for AGE ({args.minutes:g} "
          f"simulated minutes, seed {args.seed})")
    print("VO noise      | age  | median  | p95     | max")
    for scale in (float(x) for x in args.noise.split(",")):
        print_errors(f"{scale:4g} x sim    ", drift(args.minutes, args.seed, scale))
    stamps, poses = truth_at_scans(args.minutes, args.seed)
    errors, breaks = scan_drift(stamps, poses, "tile")
    print_errors("scan matching", errors)
    print(f"(scan matching, 10 Hz scans of the simulated room: {breaks} breaks)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
