"""CPU of the shared-control layer's node, fed at the chair's rates, across processes.

    .venv/bin/python benchmarks/shared_control_cpu.py [--seconds 30] [--poll 0,0.25]
        [--runs 2] [--model M.npz]

Set-up: ``shared_control_node`` runs as its own process on the system clock (as on the
chair: no ``use_sim_time``), with its defaults (config/shared_control.yaml: obstacles from
the laser, its memory carried by scan matching, the velocity from the scans while they
match, adapting) on ``--model`` (default: the committed tile model of the reproduction).
This script is the rest of the chair, paced by the wall clock and stamping with it:

* ``joy`` and ``joy_applied`` at 100 Hz, one stamp per sample, ``joy`` first, as the serial
  bridge publishes them;
* ``vo/twist`` at 15 Hz, the demo camera's rate (a twist per frame, as ``vo_node``);
* ``scan`` at 10 Hz, 1,081 beams over 270 degrees, from the simulated scanner
  (:mod:`asgp_ros.sim.lidar`) in the simulator's room (:class:`asgp_ros.sim.world.Room`);

on a scripted drive: back and forth along the room, 0.7 m/s at the most, the heading
swinging by 0.25 rad, the far wall close enough at the end of each run forward for the
layer to judge it (and at times to intervene).

For each value of ``--poll`` in turn (the node's ``joy_poll_period_s``: 0 is rclpy's
callback for each joystick message; 0.25 the default, read in batches), repeated
``--runs`` times and alternated: 5 s of warm-up, then the node process's user + system time
(/proc/PID/stat) over ``--seconds`` divided by the wall time. Printed per run: that CPU
share, the decisions taken and interventions begun (the node's diagnostics, over the
measured time), its solve time p50 / p99 and the joystick messages it read in batches;
then per setting the range over the runs and the median ratio against the first setting.

Each run has a ROS domain of its own (``--domain-id``, default 60 + pid % 80) on localhost.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from predictor_latency import cpu_seconds, spin_until, stop_node

REPO = Path(__file__).resolve().parents[1]
DEFAULT_MODEL = REPO / "docs" / "reproduction" / "models" / "tile_asgp.npz"
JOY_HZ, VO_HZ, SCAN_HZ = 100.0, 15.0, 10.0
PERIOD_S = 16.0  # of the drive back and forth
V_MAX, SWING = 0.7, 0.25


class Drive:
    """The scripted drive: velocity (v, omega) at time t, and the pose integrated from the
    middle of the room's free area."""

    def __init__(self, x0: float) -> None:
        self.x, self.y, self.theta = x0, 0.0, 0.0
        self.t = 0.0

    @staticmethod
    def velocity(t: float) -> tuple[float, float]:
        v = V_MAX * math.sin(2.0 * math.pi * t / PERIOD_S)
        w = SWING * (2.0 * math.pi / 11.0) * math.cos(2.0 * math.pi * t / 11.0)
        return v, w

    def advance(self, t: float) -> None:
        while self.t < t:
            dt = min(0.005, t - self.t)
            v, w = self.velocity(self.t + 0.5 * dt)
            self.x += v * math.cos(self.theta) * dt
            self.y += v * math.sin(self.theta) * dt
            self.theta += w * dt
            self.t += dt


class Feeder:
    """Publishes the chair's inputs at their rates; reads the node's diagnostics."""

    def __init__(self) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import TwistStamped
        from rclpy.qos import QoSProfile, qos_profile_sensor_data
        from sensor_msgs.msg import Joy, LaserScan

        from asgp_ros.nodes import conversions as conv
        from asgp_ros.sim.lidar import Lidar
        from asgp_ros.sim.world import Room

        self.conv = conv
        self.node = rclpy.create_node("shared_control_cpu_bench")
        self.executor = rclpy.executors.SingleThreadedExecutor()
        self.executor.add_node(self.node)
        sensor = qos_profile_sensor_data
        self.joy_pub = self.node.create_publisher(Joy, "joy", sensor)
        self.applied_pub = self.node.create_publisher(Joy, "joy_applied", sensor)
        self.vo_pub = self.node.create_publisher(TwistStamped, "vo/twist", sensor)
        self.scan_pub = self.node.create_publisher(LaserScan, "scan", sensor)
        self.diag: dict[str, str] = {}
        self.node.create_subscription(DiagnosticArray, "diagnostics", self._on_diag,
                                      QoSProfile(depth=10))
        room = Room()
        self.lidar = Lidar(room, seed=0)
        x_lo, x_hi = room.free_box[0], room.free_box[1]
        # the runs forward end 1.2 m short of the free area's edge (the wall's band)
        self.drive = Drive(x_hi - 1.2 - V_MAX * PERIOD_S / math.pi)
        assert self.drive.x > x_lo
        self.rng = np.random.default_rng(0)

    def _on_diag(self, msg) -> None:
        for status in msg.status:
            if "shared control" in status.name:
                self.diag = {kv.key: kv.value for kv in status.values}

    def spin_until(self, cond, timeout: float) -> bool:
        return spin_until(self.executor, cond, timeout)

    def feed(self, seconds: float) -> None:
        """The inputs for ``seconds`` of wall time, each at its own time."""
        start = time.monotonic()
        wall0 = time.time() - start
        due = {"joy": start, "vo": start, "scan": start}
        periods = {"joy": 1.0 / JOY_HZ, "vo": 1.0 / VO_HZ, "scan": 1.0 / SCAN_HZ}
        end = start + seconds
        while True:
            kind = min(due, key=due.__getitem__)
            t_mono = due[kind]
            if t_mono >= end:
                return
            while (wait := t_mono - time.monotonic()) > 0.0:
                self.executor.spin_once(timeout_sec=min(wait, 0.005))
            t = wall0 + t_mono  # the stamp, on the wall clock
            self.drive.advance(t_mono - self._origin)
            self._publish(kind, t)
            due[kind] += periods[kind]

    def start(self) -> None:
        """The drive begins now."""
        self._origin = time.monotonic()

    def _publish(self, kind: str, t: float) -> None:
        conv = self.conv
        v, w = Drive.velocity(self.drive.t)
        if kind == "joy":
            msg = conv.joy_from_sample(t, float(np.clip(v / 0.9, -1.0, 1.0)),
                                       float(np.clip(w / 0.8, -1.0, 1.0)))
            self.joy_pub.publish(msg)
            self.applied_pub.publish(msg)
        elif kind == "vo":
            self.vo_pub.publish(conv.twist_stamped_from_sample(
                t, v + self.rng.normal(0.0, 0.003), w + self.rng.normal(0.0, 0.003)))
        else:
            d = self.drive
            s = self.lidar.scan(d.x, d.y, d.theta)
            self.scan_pub.publish(conv.scan_to_msg(
                s.ranges, s.angle_min, s.angle_increment, s.range_min, s.range_max, t,
                "laser", 1.0 / SCAN_HZ))


def measure(args: argparse.Namespace, model: str, poll: float) -> dict[str, float] | None:
    """One run of the node with ``joy_poll_period_s`` = ``poll``: its figures, or None
    when it did not come up."""
    import rclpy

    env = dict(os.environ, PYTHONPATH=str(REPO))
    node = subprocess.Popen(
        [sys.executable, "-m", "asgp_ros.nodes.shared_control_node", "--ros-args",
         "--params-file", str(REPO / "config" / "shared_control.yaml"),
         "-p", f"model_path:={model}", "-p", f"joy_poll_period_s:={poll!r}",
         "--log-level", "warn"],
        cwd=REPO, env=env)
    rclpy.init()
    feeder = Feeder()
    try:
        if not feeder.spin_until(lambda: feeder.node.count_subscribers("scan") > 0
                                 and feeder.node.count_publishers("diagnostics") > 0, 30.0):
            print("the shared-control node did not come up", file=sys.stderr)
            return None
        feeder.start()
        feeder.feed(5.0)  # warm-up
        before = dict(feeder.diag)
        cpu0, wall0 = cpu_seconds(node.pid), time.monotonic()
        feeder.feed(args.seconds)
        cpu = (cpu_seconds(node.pid) - cpu0) / (time.monotonic() - wall0)
        feeder.feed(1.2)  # one more diagnostics message
        after = feeder.diag
    finally:
        feeder.executor.shutdown()
        feeder.node.destroy_node()
        rclpy.try_shutdown()
        stop_node(node)

    def count(key: str) -> float:
        try:
            return float(after.get(key, "nan")) - float(before.get(key, "nan"))
        except ValueError:
            return math.nan

    return {"cpu": cpu, "decisions": count("decisions"),
            "interventions": count("interventions"), "polled": count("polled_messages"),
            "solve_p50": float(after.get("solve_p50_ms", "nan")),
            "solve_p99": float(after.get("solve_p99_ms", "nan"))}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=30.0,
                        help="measured time of each run (30 s, after 5 s of warm-up)")
    parser.add_argument("--poll", default="0,0.25", metavar="S[,S...]",
                        help="the node's joy_poll_period_s values, in turn (0,0.25)")
    parser.add_argument("--runs", type=int, default=2, help="runs of each value (2)")
    parser.add_argument("--model", default=str(DEFAULT_MODEL),
                        help="model file (default: the committed tile ASGP)")
    parser.add_argument("--domain-id", type=int,
                        help="ROS_DOMAIN_ID (default 60 + pid %% 80)")
    args = parser.parse_args(argv)
    if not (math.isfinite(args.seconds) and 5.0 <= args.seconds <= 3600.0):
        parser.error("--seconds must be in [5, 3600]")
    if not 1 <= args.runs <= 100:
        parser.error("--runs must be in [1, 100]")
    try:
        polls = [float(x) for x in args.poll.split(",")]
    except ValueError:
        parser.error(f"--poll: not a list of seconds: {args.poll!r}")
    if not Path(args.model).is_file():
        parser.error(f"--model: no such file: {args.model}")
    os.environ["ROS_DOMAIN_ID"] = str(args.domain_id if args.domain_id is not None
                                      else 60 + os.getpid() % 80)
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    print(f"shared_control_node on {args.model}; joy and joy_applied {JOY_HZ:g} Hz, VO "
          f"{VO_HZ:g} Hz, scans {SCAN_HZ:g} Hz; {args.seconds:g} s measured per run; "
          f"ROS_DOMAIN_ID {os.environ['ROS_DOMAIN_ID']}", flush=True)
    results: dict[float, list[dict[str, float]]] = {p: [] for p in polls}
    for run in range(args.runs):
        for poll in polls:
            r = measure(args, str(Path(args.model).resolve()), poll)
            if r is None:
                return 1
            results[poll].append(r)
            print(f"run {run + 1}, joy_poll_period_s {poll:g}: CPU {100 * r['cpu']:.1f}% "
                  f"of one core; {r['decisions']:.0f} decisions, {r['interventions']:.0f} "
                  f"interventions begun; solve p50 / p99 {r['solve_p50']:.2f} / "
                  f"{r['solve_p99']:.2f} ms; joystick messages read in batches "
                  f"{r['polled']:.0f}", flush=True)
    first = np.median([r["cpu"] for r in results[polls[0]]])
    for poll in polls:
        cpus = 100 * np.array([r["cpu"] for r in results[poll]])
        print(f"joy_poll_period_s {poll:g}: CPU {cpus.min():.1f}-{cpus.max():.1f}% "
              f"(median {np.median(cpus):.1f}%), ratio to {polls[0]:g}: "
              f"{np.median(cpus) / (100 * first):.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
