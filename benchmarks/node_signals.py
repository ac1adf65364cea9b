"""How the nodes end on SIGINT in the middle of heavy traffic, many times.

    .venv/bin/python benchmarks/node_signals.py [--runs 100]
        [--node predictor|vo|shared_control|bridge|both|all] [--load 0] [--timeout 10]
        [--model M.npz]

Each run starts the node as its own process on a ROS domain of its own (localhost, UDPv4),
waits for discovery, floods it (predictor: joystick at 300 Hz and VO twists at 60 Hz, a
prediction at every model step; VO: 320x240 rendered RGB-D frames at 30 Hz;
shared_control: the same joystick and VO plus 1081-beam scans of a wall 1.2 m ahead at
60 Hz, so that it decides and overrides; bridge: ``joy_override`` at 300 Hz, with a
simulated board on a pty in this process streaming its samples at 100 Hz), sends SIGINT
after a random 0.3-1.5 s of it, keeps the traffic going, and waits up to ``--timeout`` s
for the exit.
``--load N`` keeps N busy loops beside it (signal races show under load).

Printed: exit time p50 / p99 / max, and the runs that hung (killed at the timeout), exited
non-zero, or printed a traceback or "Exception ignored" on stderr (the first of each is
shown). Target: every run exits 0 within 2 s with a clean stderr.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import multiprocessing
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

EXIT_TARGET_S = 2.0
BAD_OUTPUT = ("Traceback", "Exception ignored", "Segmentation fault", "Fatal Python error")


def _busy() -> None:
    while True:
        pass


class Traffic:
    """Publishes the node's inputs from this process."""

    def __init__(self, node_kind: str) -> None:
        import rclpy
        from geometry_msgs.msg import TwistStamped
        from rclpy.qos import qos_profile_sensor_data
        from sensor_msgs.msg import CameraInfo, Image, Joy

        from asgp_ros.nodes import conversions as conv

        self.kind = node_kind
        self.conv = conv
        self.node = rclpy.create_node("node_signals_bench")
        qos = qos_profile_sensor_data
        if node_kind in ("predictor", "shared_control"):
            self.joy = self.node.create_publisher(Joy, "joy", qos)
            self.vo = self.node.create_publisher(TwistStamped, "vo/twist", qos)
            self.inputs = "vo/twist"
            if node_kind == "shared_control":
                from sensor_msgs.msg import LaserScan
                self.scan = self.node.create_publisher(LaserScan, "scan", qos)
                self.inputs = "scan"
        elif node_kind == "bridge":
            from asgp_ros.sim.board import SimulatedBoard
            self.override = self.node.create_publisher(Joy, "joy_override", 10)
            self.board = SimulatedBoard(lambda t: (0.6, 0.1)).start()
            self.inputs = "joy_override"
        else:
            from asgp_ros.demo import camera as demo_camera

            self.color = self.node.create_publisher(Image, "camera/color/image_raw", qos)
            self.depth = self.node.create_publisher(Image, "camera/depth/image_raw", qos)
            self.info = self.node.create_publisher(CameraInfo, "camera/color/camera_info", qos)
            self.camera = demo_camera
            self.frames = self._frames()
            self.inputs = "camera/color/image_raw"
        self.i = 0

    @staticmethod
    def _frames() -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
        """K and a short rendered drive (rendered once, sent round and round)."""
        from asgp_ros.sim.render import RGBDRenderer
        from asgp_ros.sim.scene import build_scene, segment_drive

        r = RGBDRenderer(build_scene(preset="rich", seed=0), width=320, height=240, seed=7)
        drive = segment_drive((0.0, 0.5, 0.3), [(0.4, 0.25, 2.0)], 3.0)
        frames = []
        for x, y, th in zip(drive.x, drive.y, drive.theta, strict=True):
            color, depth = r.render_chair(x, y, th)
            frames.append((color, np.rint(depth * 1000).astype(np.uint16)))
        return r.K, frames

    def _wall_scan(self, t: float, beams: int = 1081, distance: float = 1.2):
        """A 270-degree scan of a wall ``distance`` ahead (inf beyond 8 m)."""
        a0, inc = -0.75 * math.pi, 1.5 * math.pi / (beams - 1)
        ang = a0 + inc * np.arange(beams)
        with np.errstate(divide="ignore"):
            r = np.where(np.cos(ang) > 1e-9, distance / np.cos(ang), np.inf)
        return self.conv.scan_to_msg(np.where(r > 8.0, np.inf, r), a0, inc, 0.05, 8.0, t,
                                     "laser")

    def close(self) -> None:
        if self.kind == "bridge":
            self.board.stop()
        self.node.destroy_node()

    def ready(self) -> bool:
        return self.node.count_subscribers(self.inputs) > 0

    def send(self) -> None:
        """One burst's worth: 5 joystick messages and one VO twist, or one camera frame."""
        t = time.time()
        if self.kind in ("predictor", "shared_control"):
            for j in range(5):
                tj = t - 0.015 + 0.003 * j
                self.joy.publish(self.conv.joy_from_sample(
                    tj, 0.5 + 0.4 * math.sin(0.3 * tj), 0.3 * math.cos(0.2 * tj)))
            self.vo.publish(self.conv.twist_stamped_from_sample(
                t, 0.45 + 0.35 * math.sin(0.3 * t), 0.25 * math.cos(0.2 * t)))
            if self.kind == "shared_control":
                self.scan.publish(self._wall_scan(t))
        elif self.kind == "bridge":
            for _ in range(5):
                self.override.publish(self.conv.joy_from_sample(t, 0.3, -0.2))
        else:
            K, frames = self.frames
            color, depth = frames[self.i % len(frames)]
            h, w = color.shape[:2]
            cam = self.camera
            self.info.publish(cam.camera_info_from_matrix(t, K, w, h, "camera"))
            self.color.publish(cam.image_from_array(t, color, "camera"))
            self.depth.publish(cam.image_from_array(t, depth, "camera"))
        self.i += 1


def one_run(traffic: Traffic, model: str, timeout: float, rng: random.Random,
            env: dict[str, str]) -> tuple[str, float, int | None, str]:
    """Start, flood, SIGINT, wait: (outcome, exit time, return code, stderr)."""
    import rclpy

    kind = traffic.kind
    module = {"predictor": "asgp_ros.nodes.predictor_node", "vo": "asgp_ros.nodes.vo_node",
              "shared_control": "asgp_ros.nodes.shared_control_node",
              "bridge": "asgp_ros.nodes.serial_bridge_node"}
    args = [sys.executable, "-m", module[kind], "--ros-args", "--log-level", "warn"]
    if kind in ("predictor", "shared_control"):
        args[-2:-2] = ["-p", f"model_path:={model}"]
    elif kind == "bridge":
        args[-2:-2] = ["-p", f"port:={traffic.board.port}"]
    proc = subprocess.Popen(args, cwd=REPO, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    period = 1 / 30 if kind == "vo" else 1 / 60
    try:
        deadline = time.monotonic() + 30.0
        while not traffic.ready():
            if time.monotonic() > deadline or proc.poll() is not None:
                proc.kill()
                return "no_start", math.nan, proc.wait(), proc.stderr.read() if proc.stderr \
                    else ""
            rclpy.spin_once(traffic.node, timeout_sec=0.02)
        flood_until = time.monotonic() + rng.uniform(0.3, 1.5)
        while time.monotonic() < flood_until:
            traffic.send()
            time.sleep(period)
        proc.send_signal(signal.SIGINT)
        sent = time.monotonic()
        while proc.poll() is None and time.monotonic() - sent < timeout:
            traffic.send()
            time.sleep(period)
        elapsed = time.monotonic() - sent
        if proc.poll() is None:
            proc.kill()
            proc.wait()
            return "hang", elapsed, None, proc.stderr.read() if proc.stderr else ""
        err = proc.stderr.read() if proc.stderr else ""
        if proc.returncode != 0:
            return "exit_code", elapsed, proc.returncode, err
        if any(s in err for s in BAD_OUTPUT):
            return "output", elapsed, 0, err
        return "ok", elapsed, 0, err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=100, help="runs per node (100)")
    ap.add_argument("--node", choices=("predictor", "vo", "shared_control", "bridge", "both",
                                       "all"), default="both",
                    help="both: predictor and vo; all: the four")
    ap.add_argument("--load", type=int, default=0, help="busy loops beside the runs (0)")
    ap.add_argument("--timeout", type=float, default=10.0, help="a hang after this (10 s)")
    ap.add_argument("--model", help="predictor model (default: the reproduction's tile model)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID (default 100 + pid %% 100)")
    args = ap.parse_args(argv)

    model = args.model or str(REPO / "docs/reproduction/models/tile_asgp.npz")
    domain = args.domain_id if args.domain_id is not None else 100 + os.getpid() % 100
    os.environ.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                      FASTDDS_BUILTIN_TRANSPORTS="UDPv4")
    # a native crash prints the Python stack of every thread (faulthandler)
    env = dict(os.environ, PYTHONPATH=str(REPO), PYTHONFAULTHANDLER="1")
    kinds = {"both": ["predictor", "vo"],
             "all": ["predictor", "vo", "shared_control", "bridge"]}.get(args.node, [args.node])
    loads = [multiprocessing.Process(target=_busy, daemon=True) for _ in range(args.load)]
    for p in loads:
        p.start()

    import rclpy

    rclpy.init()
    rng = random.Random(args.seed)
    failed = 0
    try:
        for kind in kinds:
            traffic = Traffic(kind)
            times: list[float] = []
            bad: dict[str, list[tuple[int, int | None, str]]] = {}
            for run in range(args.runs):
                outcome, elapsed, code, err = one_run(traffic, model, args.timeout, rng, env)
                if math.isfinite(elapsed):
                    times.append(elapsed)
                if outcome != "ok":
                    bad.setdefault(outcome, []).append((run, code, err))
                    print(f"{kind} run {run}: {outcome} (exit {code}, {elapsed:.2f} s)",
                          flush=True)
            t = np.array(times) if times else np.array([math.nan])
            slow = int(np.sum(t > EXIT_TARGET_S))
            label = "serial_bridge" if kind == "bridge" else kind
            print(f"{label}_node, {args.runs} SIGINTs in heavy traffic (load {args.load}): "
                  f"exit p50 {np.percentile(t, 50):.2f} s, p99 {np.percentile(t, 99):.2f} s, "
                  f"max {np.max(t):.2f} s; over {EXIT_TARGET_S:.0f} s: {slow}; "
                  + ", ".join(f"{k}: {len(v)}" for k, v in sorted(bad.items()))
                  + ("" if bad else "no hang, no failed exit, clean stderr"), flush=True)
            for outcome, runs in sorted(bad.items()):
                run, code, err = runs[0]
                print(f"--- first '{outcome}' (run {run}, exit {code}) stderr:\n"
                      f"{err.strip()[-3000:]}\n---")
            failed += sum(len(v) for v in bad.values()) + slow
            traffic.close()
    finally:
        rclpy.try_shutdown()
        for p in loads:
            with contextlib.suppress(Exception):
                p.kill()
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
