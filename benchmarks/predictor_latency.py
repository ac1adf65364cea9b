"""Latency and CPU of the predictor node, measured across processes.

    .venv/bin/python benchmarks/predictor_latency.py [--steps 1000] [--cpu-seconds 20]

Set-up: a model is trained with `asgp train` on a simulated bag (ASGP, s = 4, M = 20/40,
the paper's configuration) unless ``--model`` is given; the predictor node runs as its own
process with ``use_sim_time``; this script publishes /clock, joystick (30 Hz; ``--joy-hz``)
and VO (5 Hz) and subscribes to ``predicted_path``. ``--applied`` also publishes each
joystick sample on ``joy_applied``, as ``serial_bridge_node`` does (the board's output); the
bridge publishes both at the board's 100 Hz, so ``--joy-hz 100 --applied`` gives the node the
messages it gets on the chair.

1. Latency: for each of ``--steps`` grid steps, the joystick samples of the step are sent
   first, then the VO message that completes the step (the next step's VO message when
   the model reads the VO at the middle of its interval); the latency is the wall time from
   publishing that VO message to receiving the step's path here (so it includes DDS
   delivery both ways and the node's executor, not only the prediction). The next step
   starts when the path has arrived. The node's own figure (VO callback entry to path
   publication) is read from its diagnostics.
2. CPU: the same inputs at their real rates (5 Hz steps) for ``--cpu-seconds``; the node
   process's user + system time from /proc/<pid>/stat divided by the wall time. The
   latency of these steps is printed too: in 1. a step follows the previous path at once,
   so whatever the node does after publishing can delay it (adaptation's learning waits
   20 ms after a path, or until the next step's data if they come first); at the real rate
   that work ends before the next step (the joystick samples are sent at their own times,
   30 Hz, and the VO message just after the step's end). The node's own p99 over its last
   1,000 paths, two of its parts (the prediction; the path's message made
   and published) and the ellipses' message that follows the path (made only while
   something subscribes to it; this script does not), are read from its diagnostics
   after these steps: with a small ``--steps`` they are mostly real-rate paths.

``--adapt both`` runs the node twice, without and with online adaptation (adapt.enabled),
side by side on the same model.

``--reference echo`` (the default) runs, after the node, ``benchmarks/echo_node.py`` the same
way: an rclpy node that answers each VO message with a path of the same length at once and
does nothing else. Its latency is the floor on this machine (rclpy's executor and DDS
delivery both ways); the ratio node / echo of each figure is printed last. ``none`` skips it.

``--clock system`` runs the node as on the chair: without ``use_sim_time``, so no /clock
messages (with ``sim``, as when a bag is replayed, this script publishes /clock with every
joystick sample, and each one wakes the node too); the inputs are stamped with the wall
clock and sent at their own times, so only the real-rate part (2.) is measured.

``--joy-late 0.03`` sends each step's joystick samples 30 ms after its VO message at the
real rate (a joystick slower than the VO), so that the joystick completes each step; the
latency is counted from them (a model reading the VO at its frames' stamps is needed).

``--joy-poll 0,0.25`` runs the node with each ``joy_poll_period_s`` in turn (0: rclpy's
callback for each joystick message, as before the polling; 0.25: the default, the
joystick read in batches every 250 ms, before each VO message and, while a step waits for
the joystick only, every 10 ms).

Each run has a ROS domain of its own (``--domain-id``, default 60 + pid % 80) on localhost:
two runs at once used to share the default domain, and each node got both drivers' inputs.

Targets: p99 latency under 5 ms (with adaptation too); CPU under 5% of one core.
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DT = 0.2


def _cli(*args: str) -> None:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    subprocess.run([sys.executable, "-m", "asgp_ros.cli", *args], cwd=REPO, env=env,
                   check=True, capture_output=True, text=True)


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of process ``pid`` (s), from /proc."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    utime, stime = int(fields[11]), int(fields[12])  # fields 14 and 15 of proc(5)
    return (utime + stime) / os.sysconf("SC_CLK_TCK")


def spin_until(executor, cond, timeout: float) -> bool:
    """Spin ``executor`` until ``cond()`` holds (True) or ``timeout`` seconds pass (False)."""
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            return False
        executor.spin_once(timeout_sec=0.001)
    return True


def stop_node(node: subprocess.Popen) -> None:
    """SIGINT to a node's process and wait for it; killed after 10 s."""
    node.send_signal(signal.SIGINT)
    try:
        node.wait(timeout=10)
    except subprocess.TimeoutExpired:
        print("the node did not stop within 10 s of SIGINT: killed", file=sys.stderr)
        node.kill()
        node.wait()


class Driver:
    """Publishes the clock and the inputs; receives the paths."""

    def __init__(self, sim_clock: bool = True, joy_per_step: int = 6,
                 applied: bool = False) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import TwistStamped
        from nav_msgs.msg import Path as PathMsg
        from rclpy.qos import QoSProfile, qos_profile_sensor_data
        from rosgraph_msgs.msg import Clock
        from sensor_msgs.msg import Joy

        from asgp_ros.nodes import conversions as conv

        self.conv = conv
        self.Clock = Clock
        self.sim_clock = sim_clock
        # stamps are n * DT seconds; on the system clock they are wall times, and a step's
        # inputs are sent when the wall clock reads their stamps
        self.wall_offset = time.time() - time.monotonic()
        self.node = rclpy.create_node("predictor_latency_bench")
        self.executor = rclpy.executors.SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.clock_pub = self.node.create_publisher(Clock, "/clock", QoSProfile(depth=10))
        self.joy_pub = self.node.create_publisher(Joy, "joy", qos_profile_sensor_data)
        self.applied_pub = (self.node.create_publisher(Joy, "joy_applied",
                                                       qos_profile_sensor_data)
                            if applied else None)
        self.joy_per_step = joy_per_step
        self.vo_pub = self.node.create_publisher(TwistStamped, "vo/twist",
                                                 qos_profile_sensor_data)
        self.received: dict[int, float] = {}
        self.diag: dict[str, str] = {}
        self.node.create_subscription(PathMsg, "predicted_path", self._on_path,
                                      QoSProfile(depth=10))
        self.node.create_subscription(DiagnosticArray, "diagnostics", self._on_diag,
                                      QoSProfile(depth=10))

    def _on_path(self, msg) -> None:
        t0 = self.conv.stamp_to_seconds(msg.header.stamp)
        self.received[round(t0 / DT)] = time.perf_counter()

    def _on_diag(self, msg) -> None:
        for status in msg.status:
            self.diag = {kv.key: kv.value for kv in status.values}

    def spin_until(self, cond, timeout: float) -> bool:
        return spin_until(self.executor, cond, timeout)

    def send_step_inputs(self, n: int, paced_from: float | None = None,
                         hold: list[Any] | None = None) -> None:
        """/clock and the joystick samples of grid step n (the last one after t_n).

        ``paced_from``: the wall time (time.monotonic) the step's interval starts; each
        sample is then sent at its own time within the interval (30 Hz by default), spinning
        between them, instead of all at once. ``hold``: the samples are appended to it
        instead of sent (:meth:`send_joy` sends them later)."""
        t_prev = n * DT - DT
        if not self.sim_clock:
            paced_from = t_prev - self.wall_offset
        m = self.joy_per_step
        for j in range(m):
            offset = 0.04 + j * (5 * DT / 6) / (m - 1)  # 0.04 .. 0.207 s into the step
            t = t_prev + offset
            if paced_from is not None:
                due = paced_from + offset
                self.spin_until(lambda due=due: time.monotonic() >= due, DT)
            if self.sim_clock:
                self.clock_pub.publish(self.Clock(clock=self.conv.seconds_to_stamp(t)))
            msg = self.conv.joy_from_sample(
                t, 0.5 + 0.4 * math.sin(0.3 * t), 0.3 * math.cos(0.2 * t))
            if hold is not None:
                hold.append(msg)
            else:
                self.send_joy([msg])
        if paced_from is not None:
            due = paced_from + DT + 0.01
            self.spin_until(lambda: time.monotonic() >= due, DT)
        if self.sim_clock:
            self.clock_pub.publish(self.Clock(clock=self.conv.seconds_to_stamp(n * DT + 0.03)))

    def send_joy(self, msgs: list[Any]) -> float:
        """Publish joystick messages (on joy_applied too with ``applied``); the
        ``perf_counter`` time after the last."""
        for msg in msgs:
            self.joy_pub.publish(msg)
            if self.applied_pub is not None:
                self.applied_pub.publish(msg)
        return time.perf_counter()

    def send_vo(self, n: int) -> float:
        t = n * DT + 0.01
        msg = self.conv.twist_stamped_from_sample(
            t, 0.45 + 0.35 * math.sin(0.3 * t - 0.1), 0.25 * math.cos(0.2 * t - 0.1))
        sent = time.perf_counter()
        self.vo_pub.publish(msg)
        return sent


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=1000, help="latency samples (1000)")
    parser.add_argument("--cpu-seconds", type=float, default=20.0,
                        help="duration of the real-rate CPU measurement (20)")
    parser.add_argument("--horizon", type=int, default=10, help="k steps (10 = 2.0 s)")
    parser.add_argument("--model", help="model file (default: train one on a simulated bag)")
    parser.add_argument("--clock", choices=("sim", "system"), default="sim",
                        help="sim: use_sim_time and /clock from this script (bag replay); "
                             "system: the wall clock, no /clock (on the chair)")
    parser.add_argument("--joy-hz", type=float, default=30.0,
                        help="joystick messages per second (30; the bridge publishes 100)")
    parser.add_argument("--applied", action="store_true",
                        help="also publish each joystick sample on joy_applied, as the "
                             "bridge does")
    parser.add_argument("--adapt", choices=("off", "on", "both"), default="on",
                        help="online adaptation (adapt.enabled) of the node: off, on (the "
                             "node's default), or both "
                             "one after the other (side by side)")
    parser.add_argument("--joy-poll", default="0.25", metavar="S[,S...]",
                        help="the node's joy_poll_period_s (0.25, its default; 0 = a "
                             "callback per joystick message); several, comma-separated, "
                             "run side by side")
    parser.add_argument("--joy-late", type=float, default=0.0, metavar="S",
                        help="at the real rate, send each step's joystick samples S seconds "
                             "after its VO message (a joystick slower than the VO: the "
                             "joystick completes the step); the latency is then counted "
                             "from them. Needs a model reading the VO at its frames' stamps "
                             "(the one trained without --model is, with this option)")
    parser.add_argument("--reference", choices=("echo", "none"), default="echo",
                        help="echo: also measure benchmarks/echo_node.py, a node answering "
                             "each VO message with a path at once (the floor); none: skip")
    parser.add_argument("--domain-id", type=int,
                        help="ROS_DOMAIN_ID of the run (default 60 + pid %% 80: two runs at "
                             "once must not hear each other's inputs)")
    args = parser.parse_args(argv)
    # a domain of its own on localhost, for this script and the node it starts
    os.environ["ROS_DOMAIN_ID"] = str(args.domain_id if args.domain_id is not None
                                      else 60 + os.getpid() % 80)
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    if not 10.0 <= args.joy_hz <= 1000.0:
        parser.error("--joy-hz must be in [10, 1000]")
    if not 0.0 <= args.joy_late <= 0.15:
        parser.error("--joy-late must be in [0, 0.15] s (the joystick times out at 0.5 s)")
    try:
        polls = [float(x) for x in args.joy_poll.split(",")]
    except ValueError:
        parser.error(f"--joy-poll: not a list of seconds: {args.joy_poll!r}")

    with tempfile.TemporaryDirectory() as tmp:
        model = args.model
        if model is None:
            bag = Path(tmp) / "train_bag"
            model = str(Path(tmp) / "chair.npz")
            print("training an ASGP model on a 3-minute simulated bag ...", flush=True)
            _cli("simulate", "--minutes", "3", "--seed", "5", "--out", str(bag), "--no-truth")
            _cli("train", "--out", model, str(bag),
                 *(["--vo-stamp", "frame"] if args.joy_late > 0 else []))
        modes = {"off": [False], "on": [True], "both": [False, True]}[args.adapt]
        runs: list[tuple[str, dict[str, float]]] = []
        for adapt in modes:
            for poll in polls:
                figures = measure(args, model, adapt, poll)
                if figures is None:
                    return 1
                runs.append((f"adaptation {'on' if adapt else 'off'}, joy_poll_period_s "
                             f"{poll:g}", figures))
        if args.reference == "echo":
            echo = measure(args, model, False, 0.0, echo=True)
            if echo is None:
                return 1
            print("ratio predictor node / echo node (p50 / p99 back to back | p50 / p99 at the "
                  "real rate | CPU):")
            for label, figures in runs:
                print(f"  {label}: " + "  ".join(
                    f"{figures[key] / echo[key]:.2f}" if echo.get(key) and key in figures
                    else "-" for key in FIGURES))
    return 0


#: The figures :func:`measure` returns, in the order the ratios are printed.
FIGURES = ("p50", "p99", "paced_p50", "paced_p99", "cpu")


def warm_up_and_measure_back_to_back(drv: Driver, args: argparse.Namespace, lag: int
                                     ) -> tuple[int, np.ndarray, int, str] | None:
    """Warm-up, then part 1 (sim clock): the next step number, the latencies (ms), the
    steps without a path and the node's own p99 (from its diagnostics); None when no path
    came during the warm-up."""
    # discovery of every endpoint, then warm-up steps (buffers, first allocations)
    n = 1000
    while not drv.received:
        drv.send_step_inputs(n)
        drv.send_vo(n)
        drv.spin_until(lambda n=n: n - lag in drv.received, 0.5)
        n += 1
        if n > 1100:
            print("no path from the node", file=sys.stderr)
            return None
    for _ in range(20):
        drv.send_step_inputs(n)
        drv.send_vo(n)
        drv.spin_until(lambda n=n: n - lag in drv.received, 1.0)
        n += 1

    # ---- 1. latency ---------------------------------------------------------------------
    latencies, missed = [], 0
    for _ in range(args.steps):
        drv.send_step_inputs(n)
        drv.spin_until(lambda: False, 0.002)  # let the joystick samples land first
        sent = drv.send_vo(n)
        if drv.spin_until(lambda n=n: n - lag in drv.received, 1.0):
            latencies.append(drv.received[n - lag] - sent)
        else:
            missed += 1
        n += 1
    lat_ms = 1e3 * np.asarray(latencies)
    drv.spin_until(lambda: False, 0.6)  # one more diagnostics message
    node_p99 = drv.diag.get("latency_p99_ms", "nan")

    return n, lat_ms, missed, node_p99


def measure(args: argparse.Namespace, model: str, adapt: bool, poll: float,
            echo: bool = False) -> dict[str, float] | None:
    """Start the node on ``model`` (adapting or not; the joystick read every ``poll`` s),
    or with ``echo`` benchmarks/echo_node.py, measure, print, stop it; its figures (ms and
    the CPU share, see FIGURES), None when it failed."""
    import rclpy

    from asgp_ros.core.modelfile import load_model

    # The VO message sent for step n is stamped just after t_n. Read at its own stamp
    # ("frame") it completes step n; read at the middle of its interval ("midpoint", a
    # frame-to-frame VO's mean velocity) it completes step n - 1 (README, "VO stamps").
    lag = 1 if load_model(model).resample_config.vel_stamp == "midpoint" else 0
    if args.joy_late > 0 and lag:
        print("--joy-late needs a model that reads the VO at its frames' stamps: with "
              "midpoint stamps the VO message completes the step before, whose joystick "
              "samples are already in", file=sys.stderr)
        return None

    sim = args.clock == "sim"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    if echo:
        command = [sys.executable, str(REPO / "benchmarks" / "echo_node.py"), "--horizon",
                   str(args.horizon), "--lag", str(lag), *(["--sim"] if sim else [])]
    else:
        command = [
            sys.executable, "-m", "asgp_ros.nodes.predictor_node", "--ros-args",
            "-p", f"model_path:={model}", "-p", f"use_sim_time:={str(sim).lower()}",
            "-p", f"horizon_steps:={args.horizon}", "-p", "diagnostics_period_s:=0.5",
            "-p", f"adapt.enabled:={'true' if adapt else 'false'}",
            "-p", f"joy_poll_period_s:={poll!r}",
            "--log-level", "warn"]
    node = subprocess.Popen(command, cwd=REPO, env=env)
    rclpy.init()
    drv = Driver(sim_clock=sim, joy_per_step=max(2, round(args.joy_hz * DT)),
                 applied=args.applied)
    lat_ms, missed, node_p99 = np.zeros(0), 0, "nan"
    paced_node: dict[str, str] = {}
    try:
        if not drv.spin_until(lambda: drv.node.count_subscribers("vo/twist") > 0
                              and drv.node.count_publishers("predicted_path") > 0, 30.0):
            print("the predictor node did not come up", file=sys.stderr)
            return None
        if sim:
            measured = warm_up_and_measure_back_to_back(drv, args, lag)
            if measured is None:
                return None
            n, lat_ms, missed, node_p99 = measured
        else:  # inputs at their wall-clock times from the start: 5 s of warm-up
            n = math.ceil(time.time() / DT) + 2
            for _ in range(25):
                drv.send_step_inputs(n)
                drv.send_vo(n)
                n += 1
            if not drv.received:
                print("no path from the node", file=sys.stderr)
                return None

        # ---- 2. CPU at the real rate ------------------------------------------------
        cpu0, wall0 = cpu_seconds(node.pid), time.monotonic()
        steps_cpu = round(args.cpu_seconds / DT)
        start = time.monotonic()
        sent_at: dict[int, float] = {}
        for i in range(steps_cpu):
            held: list[Any] | None = [] if args.joy_late > 0 else None
            drv.send_step_inputs(n, paced_from=start + i * DT if sim else None, hold=held)
            sent_at[n - lag] = drv.send_vo(n)
            if held is not None:  # the joystick completes the step
                due = time.monotonic() + args.joy_late
                drv.spin_until(lambda due=due: time.monotonic() >= due, 1.0)
                sent_at[n - lag] = drv.send_joy(held)
            n += 1
        cpu = (cpu_seconds(node.pid) - cpu0) / (time.monotonic() - wall0)
        drv.spin_until(lambda: False, 0.6)  # one more diagnostics message
        paced_node = {k: drv.diag.get(k, "nan") for k in (
            "latency_p99_ms", "predict_p99_ms", "path_p99_ms", "ellipses_p99_ms",
            "joy_waits")}
        paced_ms = 1e3 * np.asarray([drv.received[k] - t for k, t in sent_at.items()
                                     if k in drv.received])
    finally:
        drv.executor.shutdown()
        drv.node.destroy_node()
        rclpy.try_shutdown()
        stop_node(node)

    what = ("echo node (the reference)" if echo else
            f"predictor node, adaptation {'on' if adapt else 'off'}, joy_poll_period_s {poll:g}")
    print(f"{what}, horizon {args.horizon} steps, clock {args.clock}, {len(lat_ms)} steps back "
          f"to back ({missed} without a path)")
    figures = {"cpu": cpu}
    if len(lat_ms):
        figures.update(p50=float(np.percentile(lat_ms, 50)),
                       p99=float(np.percentile(lat_ms, 99)))
    if len(paced_ms):
        figures.update(paced_p50=float(np.percentile(paced_ms, 50)),
                       paced_p99=float(np.percentile(paced_ms, 99)))
    if echo:
        if len(lat_ms):
            print(f"  VO publish -> path received: p50 {figures['p50']:.2f} ms, p99 "
                  f"{figures['p99']:.2f} ms, max {lat_ms.max():.2f} ms")
        if len(paced_ms):
            print(f"  at the real rate: p50 {figures['paced_p50']:.2f} ms, p99 "
                  f"{figures['paced_p99']:.2f} ms")
        print(f"  CPU at 5 Hz: {100 * cpu:.1f}% of one core")
        return figures
    if adapt:
        print(f"  adaptation: {drv.diag.get('adapt_rows_absorbed', '?')} steps absorbed, "
              f"last update {drv.diag.get('adapt_last_update_ms', '?')} ms, last check "
              f"{drv.diag.get('adapt_last_check_ms', '?')} ms")
    if len(lat_ms):
        print(f"  VO publish -> path received (across processes): p50 "
              f"{np.percentile(lat_ms, 50):.2f} ms, p99 {np.percentile(lat_ms, 99):.2f} ms, "
              f"max {lat_ms.max():.2f} ms   (target p99 < 5 ms)")
        print(f"  inside the node (VO callback -> path published): p99 {node_p99} ms")
    if len(paced_ms):
        late = (f", each step's joystick sent {1e3 * args.joy_late:.0f} ms after its VO "
                "message and the latency counted from it" if args.joy_late > 0 else "")
        print(f"  at the real rate (a step every {1e3 * DT:.0f} ms, {len(paced_ms)} steps"
              f"{late}): "
              f"p50 {np.percentile(paced_ms, 50):.2f} ms, p99 "
              f"{np.percentile(paced_ms, 99):.2f} ms")
        ellipses = paced_node.get("ellipses_p99_ms", "nan")
        ellipses = ("none made (this script does not subscribe to them, as nothing on the "
                    "chair does)" if ellipses == "nan" else f"p99 {ellipses} ms")
        print("  inside the node, over its last 1,000 paths (mostly at the real rate with a "
              f"small --steps): p99 {paced_node.get('latency_p99_ms', 'nan')} ms; its parts: "
              f"prediction p99 {paced_node.get('predict_p99_ms', 'nan')} ms, the path's "
              f"message p99 {paced_node.get('path_p99_ms', 'nan')} ms; then the ellipses': "
              f"{ellipses}")
    joy_hz = drv.joy_per_step / DT
    clock = f"/clock {joy_hz + 1 / DT:g} Hz, " if sim else ""
    joy = f"joystick {joy_hz:g} Hz" + (" on joy and joy_applied" if args.applied else "")
    print(f"  CPU at 5 Hz ({joy}, {clock}VO 5 Hz): {100 * cpu:.1f}% of one core "
          f"(target < 5%); steps that waited for the joystick "
          f"{paced_node.get('joy_waits', 'nan')}")
    return figures


if __name__ == "__main__":
    sys.exit(main())
