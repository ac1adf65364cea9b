"""How soon the serial link and the board react: the timings the tests leave to benchmarks.

    .venv/bin/python benchmarks/link_timing.py [--runs 10] [--load 0] [--domain-id N]

Everything runs on this machine for real: the simulated board on a pty (in this process),
the link manager, and ``serial_bridge_node`` as its own process on a ROS domain of its
own (localhost, UDPv4). Printed, p50 / p99 / max over ``--runs`` runs, each beside its
target:

* **reconnect**: the board's port replugged -> the link CONNECTED again (target 1 s: the
  open retries are at most ``reconnect_max`` = 0.25 s apart);
* **stale**: the board falls silent -> the link STALE (heartbeat timeout 0.4 s here; up
  to one 0.2 s heartbeat period earlier or later, target 0.15-1.0 s);
* **host lost**: the host falls silent in override mode -> the board back in passthrough,
  on the board's clock from the host's last byte (never before 1 s, target 1.0-1.1 s);
* **hand-back, publisher stops**: the last ``joy_override`` published -> the board
  following the user's stick again (the bridge's ``override_timeout`` 0.15 s, plus the
  board's 200 ms watchdog, plus a 25 Hz send period and a 100 Hz tick: target 0.4 s),
  and the same on the board's clock from the last override frame (never before 200 ms);
* **hand-back, publisher killed**: the same after SIGKILL of the process that publishes
  ``joy_override`` at 20 Hz (the shared-control layer dying), timed from the kill.

``--load N`` keeps N busy loops beside it (timings under load are what a laptop on a chair
sees while the VO and the predictor run).
"""

from __future__ import annotations

import argparse
import logging
import math
import multiprocessing
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

PUBLISHER_SCRIPT = """
import time, rclpy
from rclpy.qos import QoSProfile
from sensor_msgs.msg import Joy
rclpy.init()
node = rclpy.create_node("link_timing_layer")
pub = node.create_publisher(Joy, "joy_override", QoSProfile(depth=10))
while True:
    pub.publish(Joy(axes=[0.2, 0.0]))
    rclpy.spin_once(node, timeout_sec=0.05)
"""


def _busy() -> None:
    while True:
        pass


def wait_until(pred: Callable[[], bool], timeout: float, each: Callable[[], None] | None = None,
               period: float = 0.002) -> float:
    """Seconds until ``pred`` held (``nan`` if it never did within ``timeout``)."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if pred():
            return time.monotonic() - t0
        if each is not None:
            each()
        time.sleep(period)
    return math.nan


def summary(name: str, values: list[float], target: str, unit: float = 1e3) -> None:
    v = np.asarray(values, dtype=float)
    missed = int(np.sum(~np.isfinite(v)))
    v = v[np.isfinite(v)]
    if v.size == 0:
        print(f"{name:<38} no run completed ({missed} timed out)   target {target}")
        return
    print(f"{name:<38} {np.percentile(v, 50) * unit:7.0f} {np.percentile(v, 99) * unit:7.0f} "
          f"{v.max() * unit:7.0f} ms   target {target}"
          + (f"   ({missed} timed out)" if missed else ""))


def link_timings(runs: int, tmp: Path) -> dict[str, list[float]]:
    """Reconnect after replug, STALE after silence, host lost on the board's clock."""
    import serial

    from asgp_ros.serial import protocol as proto
    from asgp_ros.serial import safety as fw
    from asgp_ros.serial.link import LinkConfig, LinkManager, LinkState
    from asgp_ros.sim.board import SimulatedBoard

    out: dict[str, list[float]] = {"reconnect": [], "stale": [], "host lost": []}
    board = SimulatedBoard(lambda t: (0.4, 0.0), link_path=tmp / "joystick").start()
    try:
        cfg = LinkConfig(board.port, heartbeat_timeout=0.4, silence_reopen=5.0)
        with LinkManager(cfg) as link:
            if not link.wait_for_state(LinkState.CONNECTED, 10.0):
                raise RuntimeError("the link never connected")
            for _ in range(runs):
                board.unplug()
                link.wait_for_state(LinkState.CONNECTING, 5.0)
                time.sleep(0.3)
                board.replug()
                out["reconnect"].append(
                    wait_until(lambda: link.state == LinkState.CONNECTED, 5.0))
            for _ in range(runs):
                board.set_silent(True)
                out["stale"].append(wait_until(lambda: link.state == LinkState.STALE, 5.0))
                board.set_silent(False)
                link.wait_for_state(LinkState.CONNECTED, 5.0)
    finally:
        board.stop()
    board = SimulatedBoard(lambda t: (0.4, 0.0), link_path=tmp / "joystick2").start()
    try:
        for i in range(runs):
            with serial.Serial(board.port, 115200, timeout=0.1) as raw:
                raw.write(proto.encode(proto.Hello(), 3 * i) + proto.encode(proto.SetMode(1),
                                                                             3 * i + 1))
                raw.flush()
                wait_until(lambda: board.mode == proto.Mode.OVERRIDE, 5.0)
                n = len(board.host_lost_events)
                wait_until(lambda n=n: len(board.host_lost_events) > n, 5.0)
            if len(board.host_lost_events) > n:
                reset_ms, host_ms = board.host_lost_events[-1]
                out["host lost"].append((reset_ms - host_ms) / 1e3)
            else:
                out["host lost"].append(math.nan)
        assert all(not v < fw.HOST_TIMEOUT_MS / 1e3 for v in out["host lost"])
    finally:
        board.stop()
    return out


def hand_back_timings(runs: int, tmp: Path, env: dict[str, str]) -> dict[str, list[float]]:
    """The bridge as its own process: the override's publisher stops, or is killed."""
    import rclpy
    from rclpy.qos import QoSProfile
    from sensor_msgs.msg import Joy

    from asgp_ros.sim.board import SimulatedBoard

    out: dict[str, list[float]] = {"stops": [], "stops, board clock": [], "killed": [],
                                   "killed, board clock": []}
    board = SimulatedBoard(lambda t: (0.6, 0.0), link_path=tmp / "joystick3").start()
    bridge = subprocess.Popen(
        [sys.executable, "-m", "asgp_ros.nodes.serial_bridge_node", "--ros-args",
         "--log-level", "warn", "-p", f"port:={board.port}"], env=env,
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    rclpy.init()
    node = rclpy.create_node("link_timing")
    pub = node.create_publisher(Joy, "joy_override", QoSProfile(depth=10))
    try:
        if math.isnan(wait_until(lambda: node.count_subscribers("joy_override") > 0, 30.0,
                                 each=lambda: rclpy.spin_once(node, timeout_sec=0.01))):
            raise RuntimeError("the bridge never subscribed to joy_override")

        def engage(publish: Callable[[], None] | None) -> bool:
            last = [0.0]

            def each() -> None:
                if publish is not None and time.monotonic() - last[0] >= 0.05:
                    last[0] = time.monotonic()
                    publish()
            dt = wait_until(lambda: board.output.override_active, 10.0, each=each)
            return not math.isnan(dt)

        for _ in range(runs):
            if not engage(lambda: pub.publish(Joy(axes=[0.2, 0.0]))):
                raise RuntimeError("the board never took the override")
            for _ in range(5):  # hold it a quarter of a second
                pub.publish(Joy(axes=[0.2, 0.0]))
                time.sleep(0.05)
            n = len(board.revert_events)
            pub.publish(Joy(axes=[0.2, 0.0]))
            out["stops"].append(wait_until(lambda n=n: len(board.revert_events) > n, 5.0))
            revert_ms, override_ms = board.revert_events[-1]
            out["stops, board clock"].append((revert_ms - override_ms) / 1e3)
            time.sleep(0.3)
        for _ in range(runs):
            layer = subprocess.Popen([sys.executable, "-c", PUBLISHER_SCRIPT], env=env,
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            try:
                if not engage(None):
                    raise RuntimeError("the board never took the killed-layer override")
                time.sleep(0.25)
                n = len(board.revert_events)
                layer.kill()
                out["killed"].append(wait_until(lambda n=n: len(board.revert_events) > n, 5.0))
                revert_ms, override_ms = board.revert_events[-1]
                out["killed, board clock"].append((revert_ms - override_ms) / 1e3)
            finally:
                layer.kill()
                layer.wait()
            time.sleep(0.3)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        bridge.terminate()
        try:
            bridge.wait(timeout=10)
        except subprocess.TimeoutExpired:
            bridge.kill()
        board.stop()
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=10, help="runs of each (10)")
    ap.add_argument("--load", type=int, default=0, help="busy loops beside the runs (0)")
    ap.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID (default 100 + pid %% 100)")
    args = ap.parse_args(argv)
    domain = args.domain_id if args.domain_id is not None else 100 + os.getpid() % 100
    os.environ.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                      FASTDDS_BUILTIN_TRANSPORTS="UDPv4")
    os.environ.setdefault("AMENT_PREFIX_PATH", sys.prefix)
    env = dict(os.environ, PYTHONPATH=str(REPO))
    logging.basicConfig(level=logging.ERROR)  # the unplugs are meant: no warning per run
    hogs = [multiprocessing.Process(target=_busy, daemon=True) for _ in range(args.load)]
    for h in hogs:
        h.start()
    try:
        with tempfile.TemporaryDirectory() as tmp:
            link = link_timings(args.runs, Path(tmp))
            hand = hand_back_timings(args.runs, Path(tmp), env)
    finally:
        for h in hogs:
            h.terminate()
    print(f"{args.runs} runs, {args.load} busy loops beside, ROS_DOMAIN_ID {domain}")
    print(f"{'':<38} {'p50':>7} {'p99':>7} {'max':>7}")
    summary("reconnect after replug", link["reconnect"], "< 1000 ms")
    summary("STALE after the board falls silent", link["stale"], "150-1000 ms")
    summary("host lost (board clock)", link["host lost"], "1000-1100 ms, never < 1000")
    summary("hand-back, publisher stops", hand["stops"], "< 400 ms")
    summary("  board clock, from the last override", hand["stops, board clock"],
            "200-210 ms, never < 200")
    summary("hand-back, publisher killed", hand["killed"], "< 400 ms")
    summary("  board clock, from the last override", hand["killed, board clock"],
            "200-210 ms, never < 200")
    return 0


if __name__ == "__main__":
    sys.exit(main())
