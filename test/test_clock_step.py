"""The nodes keep working when the system clock is set back (NTP stepping a laptop whose
clock ran ahead, a user setting the time).

Each node runs as its own process under libfaketime (the Debian package; LD_PRELOAD),
which moves the process's system clock, and only that (``FAKETIME_DONT_FAKE_MONOTONIC``),
by the offset written in a file, read at every call. The test sets it back an hour in the
middle of the run. A timer on the ROS clock (system time) stopped at such a step until the
clock had caught up: an hour of no overrides from the bridge, no shared control, no
watchdog and no diagnostics (``runtime.pacing_clock``).
"""

from __future__ import annotations

import glob
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

rclpy = pytest.importorskip("rclpy")

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from sensor_msgs.msg import Joy  # noqa: E402

from asgp_ros.nodes import conversions as conv  # noqa: E402
from asgp_ros.sim.board import SimulatedBoard  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]

LIBS = sorted(glob.glob("/usr/lib/*/faketime/libfaketimeMT.so.1"))
STEP_S = 3600.0
HANG_S = 30.0  # deadlines tell a stop from a slow machine; nothing here is a timing target

needs_faketime = pytest.mark.skipif(
    not LIBS, reason="libfaketime not installed (scripts/install-system-deps.sh installs it)")


class Clock:
    """The faked process's clock offset, in the file libfaketime reads."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.set(0.0)

    def set(self, offset_s: float) -> None:
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(f"{offset_s:+.0f}\n")
        os.replace(tmp, self.path)  # never a half-written offset

    def env(self) -> dict[str, str]:
        # FAKETIME_FORCE_MONOTONIC_FIX=0: libfaketime's fix for waits on a condition variable
        # of the monotonic clock (on by default for this glibc) made each of them return at
        # once, so two Python threads contending for the GIL spun: on a busy core the node
        # crawled (diagnostics seconds apart, overrides not sent). The monotonic clock is
        # not faked here, so those waits need no fix.
        return {"LD_PRELOAD": LIBS[0], "FAKETIME_TIMESTAMP_FILE": str(self.path),
                "FAKETIME_NO_CACHE": "1", "FAKETIME_DONT_FAKE_MONOTONIC": "1",
                "FAKETIME_FORCE_MONOTONIC_FIX": "0"}


class Probe:
    """Diagnostics received in this process (its clock is not faked), and a publisher."""

    def __init__(self, prefix: str) -> None:
        self.prefix = prefix
        self.context = rclpy.context.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("clock_step_probe", context=self.context)
        self.stamps: list[float] = []  # the header stamps of the node's diagnostics
        self.sent: list[tuple[float, int]] = []  # the bridge's (stamp, overrides_sent)
        self.node.create_subscription(DiagnosticArray, "diagnostics", self._on_diag, 100)
        self.override_pub = self.node.create_publisher(Joy, "joy_override", 10)
        self.executor = rclpy.executors.SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def _on_diag(self, msg: DiagnosticArray) -> None:
        if any(st.name.startswith(self.prefix) for st in msg.status):
            self.stamps.append(conv.stamp_to_seconds(msg.header.stamp))
        for st in msg.status:
            if st.name == "serial_bridge: override":
                self.sent.append((conv.stamp_to_seconds(msg.header.stamp),
                                  int(conv.diagnostic_values(st)["overrides_sent"])))

    def spin_until(self, cond, timeout: float, proc: subprocess.Popen, each=None) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            assert proc.poll() is None, "the node exited"
            if each is not None:
                each()
            if cond():
                return True
            self.executor.spin_once(timeout_sec=0.05)
        return cond()

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def _start(repo_root: Path, tmp_path: Path, clock: Clock, module: str,
           params: dict[str, str]) -> tuple[subprocess.Popen, Path]:
    log_path = tmp_path / "node.log"
    args = [a for k, v in params.items() for a in ("-p", f"{k}:={v}")]
    with open(log_path, "w") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", f"asgp_ros.nodes.{module}", "--ros-args", *args],
            cwd=repo_root, stdout=log, stderr=subprocess.STDOUT,
            env=dict(os.environ, PYTHONPATH=str(repo_root), **clock.env()))
    return proc, log_path


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=HANG_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _diagnostics_survive_the_step(probe: Probe, proc: subprocess.Popen, clock: Clock,
                                  log_path: Path, each=None) -> None:
    assert probe.spin_until(lambda: len(probe.stamps) >= 3, HANG_S, proc, each), \
        log_path.read_text()
    before = probe.stamps[-1]
    assert abs(before - time.time()) < 60.0  # the fake clock starts at the real one
    clock.set(-STEP_S)
    stepped = len(probe.stamps)

    def after_the_step() -> list[float]:
        return [t for t in probe.stamps[stepped:] if t < before - STEP_S / 2]

    # the node's diagnostics go on, stamped an hour back (so the step did happen)
    assert probe.spin_until(lambda: len(after_the_step()) >= 5, HANG_S, proc, each), (
        f"{len(probe.stamps) - stepped} diagnostics after the step, none set back\n"
        + log_path.read_text())
    assert abs(after_the_step()[-1] - (time.time() - STEP_S)) < 60.0


MODEL = "docs/reproduction/models/tile_asgp.npz"

NODES = {
    "predictor_node": ("predictor_node:", {"model_path": MODEL,
                                           "diagnostics_period_s": "0.2"}),
    "shared_control_node": ("shared_control_node:", {"model_path": MODEL,
                                                     "diagnostics_period_s": "0.2"}),
    "vo_node": ("vo_node:", {"diagnostics_period_s": "0.2"}),
}


@needs_faketime
@pytest.mark.parametrize("module", list(NODES))
def test_diagnostics_go_on_after_the_clock_is_set_back(repo_root, tmp_path, module):
    prefix, params = NODES[module]
    clock = Clock(tmp_path / "faketime")
    probe = Probe(prefix)
    proc, log_path = _start(repo_root, tmp_path, clock, module, params)
    try:
        _diagnostics_survive_the_step(probe, proc, clock, log_path)
    finally:
        _stop(proc)
        probe.close()


@needs_faketime
def test_bridge_overrides_go_on_after_the_clock_is_set_back(repo_root, tmp_path):
    """The bridge keeps writing a fresh override to the board after the step (by its own
    count, and the board is overriding a second and more after it: its 200 ms watchdog
    hands the chair back to the user as soon as the overrides stop)."""
    clock = Clock(tmp_path / "faketime")
    probe = Probe("serial_bridge:")
    # the user holds the stick (the firmware overrides only a held stick: NEUTRAL_STOP)
    with SimulatedBoard(lambda t: (0.3, 0.0), link_path=tmp_path / "joy") as board:
        proc, log_path = _start(repo_root, tmp_path, clock, "serial_bridge_node",
                                {"port": board.port, "diagnostics_period": "0.2"})
        # unstamped overrides: this process's clock is an hour off the node's
        drive = lambda: probe.override_pub.publish(Joy(axes=[0.3, 0.0]))  # noqa: E731
        try:
            assert probe.spin_until(lambda: board.output.override_active, HANG_S, proc,
                                    drive), log_path.read_text()
            _diagnostics_survive_the_step(probe, proc, clock, log_path, drive)
            # (the step is over a second old: a stopped bridge would have lost the board)
            split = probe.stamps[-1] + STEP_S / 2  # diagnostics stamped before the step lie above
            sent_at_step = max(n for t, n in probe.sent if t > split)

            def sent_since() -> int:
                return max((n for t, n in probe.sent if t < split), default=0) - sent_at_step

            assert probe.spin_until(lambda: sent_since() >= 20, HANG_S, proc, drive), (
                f"{sent_since()} overrides sent after the step\n" + log_path.read_text())
            assert probe.spin_until(lambda: board.output.override_active, HANG_S, proc,
                                    drive), log_path.read_text()
        finally:
            _stop(proc)
            probe.close()


@needs_faketime
def test_paths_come_again_after_the_clock_is_set_back(repo_root, tmp_path):
    """Inputs stamped with the node's clock, which steps back an hour: the predictor
    restarts its buffers at the jump and publishes paths again, stamped on the new clock."""
    from geometry_msgs.msg import TwistStamped
    from nav_msgs.msg import Path as PathMsg
    from rclpy.qos import QoSProfile, qos_profile_sensor_data

    clock = Clock(tmp_path / "faketime")
    probe = Probe("predictor_node:")
    t0s: list[float] = []
    probe.node.create_subscription(PathMsg, "predicted_path",
                                   lambda m: t0s.append(conv.stamp_to_seconds(m.header.stamp)),
                                   QoSProfile(depth=100))
    joy_pub = probe.node.create_publisher(Joy, "joy", qos_profile_sensor_data)
    vo_pub = probe.node.create_publisher(TwistStamped, "vo/twist", qos_profile_sensor_data)
    offset = [0.0]  # the node's clock minus this process's
    due = {"joy": 0.0, "vo": 0.0}

    def drive() -> None:  # joystick at 20 Hz, VO at 5 Hz, stamped with the node's clock
        mono, t = time.monotonic(), time.time() + offset[0]
        if mono >= due["joy"]:
            due["joy"] = mono + 0.05
            joy_pub.publish(conv.joy_from_sample(t, 0.5 + 0.3 * math.sin(t), 0.2))
        if mono >= due["vo"]:
            due["vo"] = mono + 0.2
            vo_pub.publish(conv.twist_stamped_from_sample(t, 0.45 + 0.2 * math.sin(t), 0.1))

    proc, log_path = _start(repo_root, tmp_path, clock, "predictor_node",
                            {"model_path": MODEL, "diagnostics_period_s": "0.2"})
    try:
        assert probe.spin_until(lambda: len(t0s) >= 5, HANG_S, proc, drive), \
            log_path.read_text()
        before = t0s[-1]
        clock.set(-STEP_S)
        offset[0] = -STEP_S

        def after() -> list[float]:
            return [t for t in t0s if t < before - STEP_S / 2]

        assert probe.spin_until(lambda: len(after()) >= 5, HANG_S, proc, drive), (
            f"{len(after())} paths after the step\n" + log_path.read_text())
        assert abs(after()[-1] - (time.time() - STEP_S)) < 60.0
    finally:
        _stop(proc)
        probe.close()


def _build(module: str, context, tmp_path: Path, sim_time: bool, namespace: str = ""):
    from rclpy.parameter import Parameter

    from asgp_ros.nodes import predictor_node, serial_bridge_node, shared_control_node, vo_node
    base = [Parameter("use_sim_time", value=sim_time)]
    if module == "serial_bridge_node":  # a port that never opens: the node still runs
        return serial_bridge_node.SerialBridgeNode(
            context=context, namespace=namespace, parameter_overrides=[
                *base, Parameter("port", value=str(tmp_path / "no_such_port"))])
    if module == "vo_node":
        return vo_node.VONode(context=context, namespace=namespace, parameter_overrides=base)
    cls = (predictor_node.PredictorNode if module == "predictor_node"
           else shared_control_node.SharedControlNode)
    return cls(context=context, namespace=namespace, parameter_overrides=[
        *base, Parameter("model_path", value=str(Path(__file__).parents[1] / MODEL))])


@pytest.mark.parametrize("module", [*NODES, "serial_bridge_node"])
def test_a_namespaced_node_is_told_apart_on_the_one_diagnostics_topic(rclpy_context,
                                                                     tmp_path, module):
    """Two chairs' stacks in /chair1 and /chair2: each node published on its namespace's
    diagnostics (nothing reached /diagnostics, where an aggregator listens) under a name
    without the namespace (the two chairs' predictors were one entry: one chair's ERROR
    overwritten by the other's OK). Now /diagnostics, each name after the namespace."""
    from diagnostic_msgs.msg import DiagnosticArray

    node = _build(module, rclpy_context, tmp_path, False, namespace="chair1")
    probe = rclpy.create_node("diagnostics_probe", context=rclpy_context)
    executor = rclpy.executors.SingleThreadedExecutor(context=rclpy_context)
    executor.add_node(node)
    executor.add_node(probe)
    heard: list[DiagnosticArray] = []
    probe.create_subscription(DiagnosticArray, "/diagnostics", heard.append, 10)
    try:
        deadline = time.monotonic() + HANG_S
        while not heard and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        assert heard, "nothing on /diagnostics"
        label = "serial_bridge" if module == "serial_bridge_node" else module
        names = [st.name for st in heard[0].status]
        assert names and all(n.startswith(f"chair1/{label}: ") for n in names), names
    finally:
        executor.shutdown()
        probe.destroy_node()
        node.destroy_node()


@pytest.mark.parametrize("sim_time", [False, True], ids=["system_time", "sim_time"])
@pytest.mark.parametrize("module", [*NODES, "serial_bridge_node"])
def test_every_timer_runs_on_the_pacing_clock(rclpy_context, tmp_path, module, sim_time):
    """Each timer of each node: the steady clock, or the ROS clock with use_sim_time (so a
    replayed bag paces it). The process test above steps the clock for one timer of each
    node; this one covers them all (the shared-control layer's overrides and watchdog)."""
    from rclpy.clock import ClockType

    if module == "serial_bridge_node" and sim_time:
        pytest.skip("the bridge refuses use_sim_time (test_serial_bridge_node)")

    node = _build(module, rclpy_context, tmp_path, sim_time)
    try:
        timers = _paced_timers(node)
        assert len(timers) >= 1
        want = ClockType.ROS_TIME if sim_time else ClockType.STEADY_TIME
        assert [t.clock.clock_type for t in timers] == [want] * len(timers)
    finally:
        node.destroy_node()


def _paced_timers(node) -> list:
    """The node's timers but those that read its polled joystick topics (the drain, and the
    predictor's quick reads while a step waits for the joystick), which run on the steady
    clock whatever use_sim_time says (the messages arrive on the wall clock, and a paused
    /clock must not leave them waiting)."""
    from rclpy.clock import ClockType

    polled = getattr(node, "polled", None)
    if polled is None:
        return list(node.timers)
    readers = [polled.timer]
    if getattr(node, "_joy_wait_timer", None) is not None:
        readers.append(node._joy_wait_timer)
    for timer in readers:
        assert timer is not None and timer in list(node.timers)
        assert timer.clock.clock_type == ClockType.STEADY_TIME
    return [t for t in node.timers if all(t is not r for r in readers)]


@pytest.mark.parametrize("sim_time", [False, True], ids=["system_time", "sim_time"])
@pytest.mark.parametrize("module", list(NODES))
def test_the_clock_is_not_switched_while_a_node_runs(rclpy_context, tmp_path, module,
                                                     sim_time):
    """use_sim_time switched at runtime left the timers on the clock chosen at start-up:
    refused with the reason, and the clock stays as it was; setting the value it has is
    fine. The layer and the VO refuse their start-up parameters too (the layer accepted
    them without a word and went on with the old values)."""
    from rclpy.clock import ClockType
    from rclpy.parameter import Parameter

    from asgp_ros.nodes.parameters import SIM_TIME_AT_START

    node = _build(module, rclpy_context, tmp_path, sim_time)
    try:
        result = node.set_parameters([Parameter("use_sim_time", value=not sim_time)])[0]
        assert not result.successful and result.reason == SIM_TIME_AT_START
        assert node.get_parameter("use_sim_time").value is sim_time
        want = ClockType.ROS_TIME if sim_time else ClockType.STEADY_TIME
        timers = _paced_timers(node)
        assert [t.clock.clock_type for t in timers] == [want] * len(timers)
        assert node.get_clock().ros_time_is_active is sim_time
        assert node.set_parameters([Parameter("use_sim_time", value=sim_time)])[0].successful
        if module != "predictor_node":  # its runtime parameters: test_predictor_node
            name = "threshold" if module == "shared_control_node" else "sync_tolerance_s"
            result = node.set_parameters([Parameter(name, value=0.07)])[0]
            assert not result.successful and "read at start-up" in result.reason
            assert node.get_parameter(name).value != 0.07
    finally:
        node.destroy_node()


@pytest.mark.parametrize("module", list(NODES))
def test_a_negative_clock_is_refused_by_every_node(rclpy_context, tmp_path, module):
    """With use_sim_time, a /clock of -5 s (a bag with bogus stamps played) raised inside
    rclpy's own clock subscription and stopped the node: each node refuses it, and its
    clock stays where it was."""
    from builtin_interfaces.msg import Time as TimeMsg
    from rosgraph_msgs.msg import Clock as ClockMsg

    node = _build(module, rclpy_context, tmp_path, True)
    probe = rclpy.create_node("clock_probe", context=rclpy_context)
    executor = rclpy.executors.SingleThreadedExecutor(context=rclpy_context)
    executor.add_node(node)
    executor.add_node(probe)
    pub = probe.create_publisher(ClockMsg, "/clock", 10)
    try:
        def at(sec: int) -> bool:
            pub.publish(ClockMsg(clock=TimeMsg(sec=sec, nanosec=0)))
            deadline = time.monotonic() + HANG_S
            while time.monotonic() < deadline:
                executor.spin_once(timeout_sec=0.01)  # (raised ValueError here)
                if node.get_clock().now().nanoseconds == sec * 10**9:
                    return True
            return False

        assert at(100)
        pub.publish(ClockMsg(clock=TimeMsg(sec=-5, nanosec=0)))
        for _ in range(30):
            executor.spin_once(timeout_sec=0.01)
        assert node.get_clock().now().nanoseconds == 100 * 10**9
        assert at(101)
    finally:
        executor.shutdown()
        probe.destroy_node()
        node.destroy_node()
