"""Serial bridge benchmark: the simulated board at 100 Hz on a pty -> serial_bridge_node ->
a Joy subscriber in the same process.

Prints frames lost (target 0) and the latency from the moment the frame's last byte was
written to the pty to (a) the link's reception timestamp and (b) the Joy message arriving
at a subscriber over DDS (target p99 < 2 ms).

    python benchmarks/serial_bridge.py [--seconds 10] [--rate 100]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


BOARD_SCRIPT = """
import json, math, sys, time
from asgp_ros.sim.board import SimulatedBoard
rate, seconds, link, out = float(sys.argv[1]), float(sys.argv[2]), sys.argv[3], sys.argv[4]
def joystick(t):
    return ((1.3 * t) % 2.0) - 1.0, 0.8 * math.sin(2.0 * t)
board = SimulatedBoard(joystick, rate_hz=rate, link_path=link, record=True).start()
print(board.port, flush=True)
sys.stdin.readline()  # the host says when to stop
board.stop()
json.dump([[s.seq, s.t_written, s.raw_forward, s.raw_turn] for s in board.sent], open(out, "w"))
"""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--rate", type=float, default=100.0)
    args = ap.parse_args()

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import Joy

    from asgp_ros.nodes.serial_bridge_node import SerialBridgeNode
    from asgp_ros.serial.calibration import AxisCalibration

    rclpy.init()
    with tempfile.TemporaryDirectory() as tmp:
        # the board runs in its own process, as real hardware would (no shared GIL)
        sent_file = Path(tmp) / "sent.json"
        board = subprocess.Popen(
            [sys.executable, "-c", BOARD_SCRIPT, str(args.rate), str(args.seconds),
             str(Path(tmp) / "joy"), str(sent_file)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
            env=dict(os.environ, PYTHONPATH=str(REPO)))
        port = board.stdout.readline().strip()
        node = SerialBridgeNode(parameter_overrides=[Parameter("port", value=port)])
        probe = rclpy.create_node("bench_probe")
        received: list[tuple[float, float, float]] = []
        link_rx: list[tuple[int, float]] = []
        forward_sample = node._on_sample

        def on_sample(s):  # also keep the link's reception stamps
            link_rx.append((s.seq, s.t_rx))
            forward_sample(s)

        node.link._on_sample = on_sample
        published: list[float] = []
        publish = node._joy_pub.publish

        def timed_publish(msg):
            publish(msg)
            published.append(time.monotonic())

        node._joy_pub.publish = timed_publish
        probe.create_subscription(
            Joy, "joy", lambda m: received.append((time.monotonic(), m.axes[0], m.axes[1])),
            qos_profile_sensor_data)
        ex = SingleThreadedExecutor()
        ex.add_node(node)
        ex.add_node(probe)
        t_end = time.monotonic() + 5.0
        while len(received) < 10 and time.monotonic() < t_end:  # link up, discovery done
            ex.spin_once(timeout_sec=0.01)
        received.clear()
        link_rx.clear()
        published.clear()
        t_end = time.monotonic() + args.seconds
        while time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.01)
        board.stdin.write("stop\n")
        board.stdin.flush()
        board.wait(10)
        t_drain = time.monotonic() + 0.3
        while time.monotonic() < t_drain:
            ex.spin_once(timeout_sec=0.01)
        stats = node.link.stats()
        ex.shutdown()
        node.destroy_node()
        probe.destroy_node()
        sent = json.loads(sent_file.read_text())  # [seq, t_written, raw_forward, raw_turn]
    rclpy.try_shutdown()

    cal = AxisCalibration()
    exp = np.array([(cal.deflection(f), cal.deflection(t)) for _, _, f, t in sent])
    got = np.array([(a, b) for _, a, b in received])
    # the Joy stream is a contiguous run of the board's samples, in order
    start = next(i for i in range(len(sent) - 3)
                 if np.allclose(exp[i:i + 3], got[:3], atol=1e-6))
    n = len(got)
    in_order = n <= len(sent) - start and np.allclose(exp[start:start + n], got, atol=1e-6)
    t_first, t_last = received[0][0], received[-1][0]
    window = [k for k, s in enumerate(sent) if k >= start and s[1] <= t_last]
    lost = len(window) - n  # samples written before the last Joy arrived, not received
    joy_lat = np.array([t - sent[start + k][1] for k, (t, _, _) in enumerate(received)])
    by_seq: dict[int, list[float]] = {}
    for s in sent[start:]:
        by_seq.setdefault(s[0], []).append(s[1])
    link_lat = np.array([t_rx - tw for seq, t_rx in link_rx for tw in by_seq.get(seq, [])
                         if 0.0 <= t_rx - tw < 0.5])
    load = os.getloadavg()[0]
    print(f"serial bridge at {args.rate:g} Hz for {t_last - t_first:.1f} s over a pty "
          f"(board in its own process; load average {load:.1f} on {os.cpu_count()} CPUs)")
    print(f"  samples sent           {len(window)}")
    print(f"  Joy received           {n}  (the board's samples, in order: {in_order})")
    print(f"  frames lost            {lost}  (link sequence gaps {stats.frames_lost}, "
          f"CRC errors {stats.crc_errors})")
    k0 = len(published) - len(received)
    pub_lat = np.array([published[k0 + k] - sent[start + k][1] for k in range(n)
                        if 0 <= k0 + k < len(published)])
    for name, lat in (("frame -> link t_rx", link_lat), ("frame -> Joy published", pub_lat),
                      ("frame -> Joy received", joy_lat)):
        ms = lat * 1e3
        print(f"  latency {name:22s} p50 {np.percentile(ms, 50):.3f} ms  "
              f"p99 {np.percentile(ms, 99):.3f} ms  max {ms.max():.3f} ms  (n={len(ms)})")
    ok = lost == 0 and in_order and np.percentile(joy_lat, 99) < 2e-3
    print(f"  targets (0 lost, p99 < 2 ms): {'met' if ok else 'NOT met'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
