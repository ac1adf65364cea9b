"""serial_bridge_node in-process against the simulated board on a pty: joy in order and
calibrated, overrides while fresh (and no longer when stale), unplug/replug seen in
diagnostics within 1 s, a board restart, a device that is not the board, parameter
validation."""

from __future__ import annotations

import dataclasses
import itertools
import math
import os
import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import QoSProfile, qos_profile_sensor_data  # noqa: E402
from sensor_msgs.msg import Joy  # noqa: E402
from test_serial_sequence import echoing_pty  # noqa: E402

from asgp_ros.nodes import conversions as conv  # noqa: E402
from asgp_ros.nodes.serial_bridge_node import SerialBridgeNode  # noqa: E402
from asgp_ros.serial import safety as fw  # noqa: E402
from asgp_ros.serial.calibration import AxisCalibration  # noqa: E402
from asgp_ros.serial.link import (  # noqa: E402
    HANDSHAKE_ERROR_AFTER,
    SEQ_RESTART_AFTER,
    LinkState,
)
from asgp_ros.serial.protocol import Mode, Status  # noqa: E402
from asgp_ros.sim.board import SimulatedBoard  # noqa: E402

pytestmark = pytest.mark.ros


class Harness:
    def __init__(self, context, board: SimulatedBoard, **params) -> None:
        overrides = [Parameter("port", value=board.port)] + [
            Parameter(k, value=v) for k, v in params.items()]
        self.board = board
        self.node = SerialBridgeNode(context=context, parameter_overrides=overrides)
        self.probe = rclpy.create_node("probe", context=context)
        self.joy: list[tuple[float, Joy]] = []
        self.diag: list[DiagnosticArray] = []
        # the bridge's sensor-data QoS, with a queue deep enough that a loaded machine's
        # slow spinning of this probe drops nothing (depth 5 did, under a loaded CI: the
        # test then measured the probe's queue, not the bridge)
        self.probe.create_subscription(
            Joy, "joy", lambda m: self.joy.append((time.monotonic(), m)),
            QoSProfile(depth=1000, reliability=qos_profile_sensor_data.reliability,
                       durability=qos_profile_sensor_data.durability))
        self.applied: list[Joy] = []
        self.probe.create_subscription(
            Joy, "joy_applied", self.applied.append,
            QoSProfile(depth=1000, reliability=qos_profile_sensor_data.reliability,
                       durability=qos_profile_sensor_data.durability))
        self.probe.create_subscription(DiagnosticArray, "diagnostics", self.diag.append, 10)
        self.override_pub = self.probe.create_publisher(Joy, "joy_override", 10)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self.executor.add_node(self.probe)

    def spin_until(self, pred, timeout: float, each=None) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if each is not None:
                each()
            self.executor.spin_once(timeout_sec=0.01)
            if pred():
                return True
        return bool(pred())

    def spin_for(self, duration: float, each=None) -> None:
        deadline = time.monotonic() + duration
        while time.monotonic() < deadline:
            if each is not None:
                each()
            self.executor.spin_once(timeout_sec=0.01)

    def link_status(self) -> DiagnosticStatus | None:
        for arr in reversed(self.diag):
            for st in arr.status:
                if st.name == "serial_bridge: link":
                    return st
        return None

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.probe.destroy_node()


@pytest.fixture
def harness(rclpy_context, tmp_path):
    made: list[Harness] = []

    def make(joystick, **params) -> Harness:
        board = SimulatedBoard(joystick, link_path=tmp_path / "asgp_joystick",
                               record=True).start()
        h = Harness(rclpy_context, board, **params)
        made.append(h)
        return h

    yield make
    for h in made:
        h.close()
        h.board.stop()
        assert h.board.error is None, h.board.error


def test_joy_in_order_calibrated_and_stamped(harness):
    h = harness(lambda t: (((2.5 * t) % 2.0) - 1.0, 0.7 * math.sin(6.0 * t)),
                **{"calibration.turn.invert": True, "calibration.forward.dead_zone": 0.03})
    assert h.spin_until(lambda: len(h.joy) >= 80, 10.0)
    msgs = [m for _, m in h.joy]
    fwd = AxisCalibration(dead_zone=0.03)
    turn = AxisCalibration(invert=True)
    expected = [(fwd.deflection(s.raw_forward), turn.deflection(s.raw_turn))
                for s in h.board.sent]
    got = [(m.axes[0], m.axes[1]) for m in msgs]
    # the Joy stream is a contiguous run of the board's samples, in order (the joystick
    # repeats itself, so look for the run among all alignments)
    g, e = np.array(got), np.array(expected)
    runs = [i for i in range(len(e) - len(g) + 1)
            if np.allclose(e[i:i + len(g)], g, atol=1e-6)]
    assert runs, "the Joy stream is not the board's samples in order"
    assert not np.all(g == 0.0)
    stamps = [conv.stamp_to_seconds(m.header.stamp) for m in msgs]
    assert all(b >= a for a, b in itertools.pairwise(stamps))
    # stamped at reception: close to now, and spaced at the board's 100 Hz
    now = h.node.get_clock().now().nanoseconds * 1e-9
    assert now - 1.0 < stamps[-1] <= now
    rate = (len(stamps) - 1) / (stamps[-1] - stamps[0])
    assert 60.0 < rate < 140.0
    assert min(a[0] for a in got) < -0.3 and max(a[0] for a in got) > 0.3


def test_override_sent_while_fresh_then_board_falls_back(harness):
    h = harness(lambda t: (0.5, 0.0))
    assert h.spin_until(lambda: len(h.joy) > 5, 10.0)

    def publish():
        h.override_pub.publish(Joy(axes=[-0.25, 0.6]))

    # (a deadline, not a fixed time: a loaded machine's stalled spinning can let the board's
    # watchdog revert once before the override holds)
    assert h.spin_until(lambda: h.board.output.override_active, 5.0, each=publish)
    h.spin_for(0.2, each=publish)
    out = h.board.output
    assert out.override_active
    # (what the stick the host reads as (-0.25, 0.6) makes the board write: the host's
    # dead zone and the board's differ by a fraction of a count)
    assert (out.forward, out.turn) == pytest.approx((-0.25, 0.6), abs=0.005)
    # joy_applied: the board's output while the override drives, the stick (joy) before;
    # each with its joy message's stamp
    assert h.spin_until(lambda: len(h.applied) > 20 and h.applied[-1].axes[0] < 0.0, 5.0)
    applied = [(conv.stamp_to_seconds(m.header.stamp), m.axes[0], m.axes[1])
               for m in h.applied]
    joy = {conv.stamp_to_seconds(m.header.stamp): tuple(m.axes) for _, m in h.joy}
    assert {t for t, _, _ in applied} <= set(joy)
    user = tuple(h.joy[0][1].axes)  # the stick as calibrated on the host
    assert user[0] > 0.4 and applied[0][1:] == user
    assert applied[-1][1:] == pytest.approx((-0.25, 0.6), abs=2.0 / fw.DAC_SPAN)
    assert joy[applied[-1][0]] == user  # joy: the user's stick all along
    sent = h.node.link.stats().overrides_sent
    assert sent >= 5
    # stop publishing: the node stops sending once stale, the board reverts by itself (by
    # its watchdog, never early; how soon: benchmarks/link_timing.py)
    n_reverts = len(h.board.revert_events)
    assert h.spin_until(lambda: not h.board.output.override_active, 10.0)
    assert len(h.board.revert_events) == n_reverts + 1
    revert_ms, last_override_ms = h.board.revert_events[-1]
    assert revert_ms - last_override_ms >= fw.WATCHDOG_MS
    sent_after = h.node.link.stats().overrides_sent
    h.spin_for(0.3)
    assert h.node.link.stats().overrides_sent == sent_after  # nothing sent while stale
    assert sent_after - sent <= 5  # at most override_timeout's worth after the last msg
    assert h.board.output.forward == pytest.approx(h.board.output.user_forward, abs=2e-3)
    n = len(h.applied)
    assert h.spin_until(lambda: len(h.applied) > n + 5, 5.0)
    assert tuple(h.applied[-1].axes) == user  # the user's again
    # and the node releases override mode after mode_release_after
    assert h.spin_until(lambda: h.board.mode == 0, 2.0)


def test_an_override_drives_the_chair_as_the_stick_at_that_reading(harness):
    """A joystick wired the other way round on the turn axis, and one that does not reach
    the board's full scale forward (the host calibration says both): an override of what
    joy reads makes the board write what the stick itself writes there (it was mirrored on
    the turn axis, and forward the stick at 0.40 of the board's scale read 0.615 on the
    host, which the override wrote as 0.615: half again as fast), and joy_applied reads it
    back."""
    stick = [(0.4, 0.5)]
    h = harness(lambda t: stick[0], **{"calibration.turn.invert": True,
                                       "calibration.forward.maximum": 650.0})
    assert h.spin_until(lambda: len(h.joy) > 10, 10.0)
    user = tuple(h.joy[-1][1].axes)
    passthrough = (h.board.output.code_forward, h.board.output.code_turn)
    assert user[0] > 0.55 and user[1] < -0.4  # the inverted turn: + on the board is right
    stick[0] = (0.2, -0.3)  # the user moves; the override asks for the old reading

    def publish():
        h.override_pub.publish(Joy(axes=[float(a) for a in user]))

    assert h.spin_until(lambda: h.board.output.override_active, 5.0, each=publish)
    h.spin_for(0.2, each=publish)
    out = h.board.output
    assert out.override_active
    assert abs(out.code_forward - passthrough[0]) <= 5
    assert abs(out.code_turn - passthrough[1]) <= 5
    assert h.spin_until(lambda: h.applied and tuple(h.applied[-1].axes) != tuple(
        h.joy[-1][1].axes), 5.0)
    assert tuple(h.applied[-1].axes) == pytest.approx(user, abs=0.01)


def test_invalid_overrides_are_refused(harness):
    h = harness(lambda t: (0.5, 0.0))
    assert h.spin_until(lambda: len(h.joy) > 5, 10.0)
    h.spin_for(0.3, each=lambda: h.override_pub.publish(Joy(axes=[1.5, 0.0])))
    h.spin_for(0.2, each=lambda: h.override_pub.publish(Joy(axes=[math.nan, 0.0])))
    h.spin_for(0.2, each=lambda: h.override_pub.publish(Joy(axes=[0.2])))
    assert h.node.link.stats().overrides_sent == 0
    assert not h.board.output.override_active


def _override_status(h: Harness) -> DiagnosticStatus | None:
    for arr in reversed(h.diag):
        for st in arr.status:
            if st.name == "serial_bridge: override":
                return st
    return None


def test_a_stamped_override_delivered_late_never_drives_the_chair(harness):
    """A joy_override stamped more than override_timeout before the node's clock (held back
    by a transport, or a publisher's clock behind) is refused and counted, and the
    diagnostics say why; one stamped now drives the chair."""
    h = harness(lambda t: (0.5, 0.0), diagnostics_period=0.2)
    assert h.spin_until(lambda: len(h.joy) > 5, 10.0)

    def stamped(age_s: float) -> Joy:
        now = h.node.get_clock().now().nanoseconds * 1e-9
        return conv.joy_from_sample(now - age_s, -0.25, 0.6)

    h.spin_for(0.5, each=lambda: h.override_pub.publish(stamped(1.0)))
    assert h.node.link.stats().overrides_sent == 0
    assert not h.board.output.override_active
    assert h.spin_until(lambda: (st := _override_status(h)) is not None
                        and st.level == DiagnosticStatus.WARN, 10.0)
    st = _override_status(h)
    assert "refused" in st.message and "stamped 1.0" in st.message
    assert int(conv.diagnostic_values(st)["overrides_stale"]) >= 5
    # a fresh stamp: sent, and the board follows it
    assert h.spin_until(lambda: h.board.output.override_active, 5.0,
                        each=lambda: h.override_pub.publish(stamped(0.0)))
    h.spin_for(0.3, each=lambda: h.override_pub.publish(stamped(0.0)))
    assert h.node.link.stats().overrides_sent >= 5
    assert h.board.output.override_active
    assert (h.board.output.forward, h.board.output.turn) == pytest.approx(
        (-0.25, 0.6), abs=1.0 / fw.DAC_SPAN)
    assert _override_status(h).level == DiagnosticStatus.OK


def test_unplug_replug_reconnects_and_diagnostics_say_so(harness):
    h = harness(lambda t: (0.3, 0.0), diagnostics_period=0.2)
    assert h.spin_until(lambda: (st := h.link_status()) is not None
                        and st.level == DiagnosticStatus.OK, 10.0)
    h.board.unplug()
    assert h.spin_until(lambda: h.link_status().level == DiagnosticStatus.ERROR, 2.0)
    assert "disconnected" in h.link_status().message
    h.spin_for(0.3)
    n_joy = len(h.joy)
    h.board.replug()
    assert h.spin_until(lambda: h.link_status().level == DiagnosticStatus.OK
                        and "reconnected 1" in h.link_status().message, 10.0)
    values = conv.diagnostic_values(h.link_status())
    assert values["reconnects"] == "1" and values["state"] == "connected"
    assert h.spin_until(lambda: len(h.joy) > n_joy + 10, 2.0)  # joy flows again


def test_the_override_status_is_not_ok_while_nothing_reaches_the_board(harness):
    """A planner keeps sending fresh overrides; the board is unplugged, then silent (hung,
    its port open). The override status said OK "sending (board mode override)" and OK
    "active: the chair follows joy_override", from the board's last sample, while nothing
    reached it; it now says WARN, not reaching the board, the user drives."""
    h = harness(lambda t: (0.5, 0.0), diagnostics_period=0.2)
    assert h.spin_until(lambda: (st := h.link_status()) is not None
                        and st.level == DiagnosticStatus.OK, 10.0)

    def send() -> None:
        now = h.node.get_clock().now().nanoseconds * 1e-9
        h.override_pub.publish(conv.joy_from_sample(now, 0.2, 0.0))

    def override_says(level: int, text: str) -> bool:
        h.spin_for(0.05, each=send)
        st = _override_status(h)
        return st is not None and st.level == level and text in st.message

    assert h.spin_until(lambda: override_says(DiagnosticStatus.OK, "active"), 10.0)
    h.board.unplug()
    assert h.spin_until(lambda: override_says(DiagnosticStatus.WARN, "not reaching the "
                                                                     "board: the link is "
                                                                     "connecting"), 5.0)
    assert "the user drives" in _override_status(h).message
    h.board.replug()
    assert h.spin_until(lambda: override_says(DiagnosticStatus.OK, "active"), 10.0)
    h.board.set_silent(True)
    assert h.spin_until(lambda: override_says(DiagnosticStatus.WARN, "not reaching the "
                                                                     "board: the link is "
                                                                     "stale"), 5.0)
    h.board.set_silent(False)


def test_an_old_or_previous_connections_sample_decides_no_override_verdict(harness):
    """Reconnected after the bridge was suspended, the override status said OK "active:
    the chair follows joy_override (board mode passthrough)" from the previous
    connection's last sample, 10 s old, next to "no joystick sample for 10.00 s". A sample
    older than sample_timeout, or from before the link's last handshake, decides nothing:
    the status says what the bridge does (idle, or sending)."""
    h = harness(lambda t: (0.5, 0.0), diagnostics_period=0.2)
    assert h.spin_until(lambda: (st := h.link_status()) is not None
                        and st.level == DiagnosticStatus.OK, 10.0)

    def send() -> None:
        now = h.node.get_clock().now().nanoseconds * 1e-9
        h.override_pub.publish(conv.joy_from_sample(now, 0.2, 0.0))

    def active() -> bool:
        h.spin_for(0.05, each=send)
        st = _override_status(h)
        return st is not None and "active" in st.message

    assert h.spin_until(active, 10.0)
    node = h.node
    live = node.link.stats()
    assert live.state is LinkState.CONNECTED and node._last_sample is not None
    assert Status.OVERRIDE_ACTIVE in node._last_sample.status
    # the diagnostics timer after a suspension: connected, the last sample 10 s old
    old = dataclasses.replace(live, last_sample_age=10.0, board_mode=Mode.PASSTHROUGH)
    st = node._override_status(old)
    assert st.message.startswith(("sending", "idle")), st.message
    assert conv.diagnostic_values(st)["status"] == ""
    # the link reconnects (a handshake in between): the previous connection's sample,
    # however recent, decides nothing once connected again
    h.board.unplug()
    assert h.spin_until(lambda: node.link.stats().state is not LinkState.CONNECTED, 5.0)
    again = dataclasses.replace(live, last_sample_age=0.05, board_mode=Mode.PASSTHROUGH,
                                reconnects=live.reconnects + 1)
    st = node._override_status(again)
    assert st.message.startswith(("sending", "idle")), st.message
    h.board.replug()
    assert h.spin_until(active, 10.0)  # the new connection's samples decide again


def test_parameters_are_validated_at_runtime(harness):
    h = harness(lambda t: (0.5, 0.0))
    node = h.node
    r = node.set_parameters([Parameter("port", value="/dev/other")])
    assert not r[0].successful
    r = node.set_parameters([Parameter("calibration.forward.minimum", value=900.0)])
    assert not r[0].successful and "calibration.forward" in r[0].reason
    r = node.set_parameters([Parameter("override_rate", value=2.0)])
    assert not r[0].successful
    # in range, but its timer is made at start-up: it was accepted and changed nothing
    r = node.set_parameters([Parameter("override_rate", value=200.0)])
    assert not r[0].successful and "start-up" in r[0].reason
    # shorter than two of the override timer's periods (25 Hz): an override could go stale
    # between two ticks and never be written
    r = node.set_parameters([Parameter("override_timeout", value=0.05)])
    assert not r[0].successful and "two periods" in r[0].reason, r[0].reason
    assert node.params.override_timeout == 0.15
    r = node.set_parameters([Parameter("calibration.forward.invert", value=True)])
    assert r[0].successful
    n = len(h.joy)
    assert h.spin_until(lambda: len(h.joy) > n + 5, 5.0)
    assert h.joy[-1][1].axes[0] < -0.3  # the new calibration is applied to live samples


def test_bad_startup_parameters_raise(rclpy_context):
    with pytest.raises(ValueError, match="reconnect_max"):
        SerialBridgeNode(context=rclpy_context, parameter_overrides=[
            Parameter("port", value="/nonexistent"), Parameter("reconnect_min", value=1.0),
            Parameter("reconnect_max", value=0.5)])


def test_the_bridge_refuses_a_replayed_clock(rclpy_context, harness):
    """use_sim_time would let a replayed /clock make replayed overrides fresh: refused at
    start-up and at runtime."""
    with pytest.raises(ValueError, match="use_sim_time must be false"):
        SerialBridgeNode(context=rclpy_context, parameter_overrides=[
            Parameter("port", value="/nonexistent"), Parameter("use_sim_time", value=True)])
    node = harness(lambda t: (0.5, 0.0)).node
    result = node.set_parameters([Parameter("use_sim_time", value=True)])[0]
    assert not result.successful and "use_sim_time must be false" in result.reason
    assert node.get_parameter("use_sim_time").value is False
    assert node.set_parameters([Parameter("use_sim_time", value=False)])[0].successful


def test_params_file_loads_into_the_node(repo_root, tmp_path):
    """config/bridge.yaml as a --params-file: every value has the declared type."""
    board = SimulatedBoard(lambda t: (0.2, 0.0), link_path=tmp_path / "joy").start()
    context = rclpy.context.Context()
    rclpy.init(context=context, args=[
        "--ros-args", "--params-file", str(repo_root / "config/bridge.yaml"),
        "-p", f"port:={board.port}", "-p", "calibration.turn.dead_zone:=0.02"])
    try:
        node = SerialBridgeNode(context=context)
        try:
            assert node.params.port == board.port
            assert node.params.calibration.turn.dead_zone == 0.02
            assert node.params.calibration.forward.maximum == 717.0
            assert node.link.wait_for_state(node.link.state.CONNECTED, 3.0)
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
        board.stop()


@pytest.mark.slow
def test_node_process_runs_and_stops_cleanly(repo_root, tmp_path):
    import os
    import signal
    import subprocess
    import sys

    board = SimulatedBoard(lambda t: (0.2, 0.0), link_path=tmp_path / "joy").start()
    proc = subprocess.Popen(
        [sys.executable, "-m", "asgp_ros.nodes.serial_bridge_node", "--ros-args",
         "--params-file", str(repo_root / "config/bridge.yaml"), "-p", f"port:={board.port}"],
        cwd=repo_root, env=dict(os.environ, PYTHONPATH=str(repo_root)),
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 20.0
        while time.monotonic() < deadline and board.mode == 0 and board._logic.rx_frames < 5:
            time.sleep(0.05)
        assert board._logic.rx_frames >= 5  # handshake and heartbeats from the node
    finally:
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=15)
        board.stop()
    assert proc.returncode == 0, out
    assert "Traceback" not in out, out


def test_no_event_handler_per_endpoint_and_an_unmatched_subscriber_is_named(harness):
    """As the other nodes' (asgp_ros.nodes.qos_watch): rclpy's per-endpoint QoS event
    handlers are off on the bridge's endpoints, and a subscriber of the best-effort joy
    that asks for reliable delivery (it gets nothing) is named in the link's diagnostics,
    found by the bridge's own check at its diagnostics period, until it goes."""
    from rclpy.qos import ReliabilityPolicy

    h = harness(lambda t: (0.3, 0.0), diagnostics_period=0.2)
    node = h.node
    mine = [e for e in [*node.subscriptions, *node.publishers]
            if e.topic_name not in ("/parameter_events", "/rosout")]
    assert len(mine) == 4 and all(not e.event_handlers for e in mine), [
        e.topic_name for e in mine if e.event_handlers]

    def mismatch() -> str:
        st = h.link_status()
        return conv.diagnostic_values(st).get("qos_mismatch", "") if st is not None else ""

    assert h.spin_until(lambda: mismatch() == "none", 10.0)
    wrong = h.probe.create_subscription(
        Joy, "joy", lambda _: None,
        QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
    assert h.spin_until(lambda: mismatch().startswith("/joy: subscription of /probe:"), 10.0)
    assert "best effort publisher and reliable subscription" in mismatch().lower()
    # the link itself is up, but a subscriber gets nothing: the status says so
    st = h.link_status()
    assert st.level == DiagnosticStatus.WARN and st.message.startswith("connected")
    assert "cannot be matched: /joy: subscription of /probe:" in st.message
    h.probe.destroy_subscription(wrong)
    assert h.spin_until(lambda: mismatch() == "none", 10.0)
    assert h.spin_until(lambda: h.link_status().level == DiagnosticStatus.OK, 10.0)


def test_board_restart_is_followed_and_said(harness):
    """The board resets (its watchdog, a brown-out) while the host overrides: its count and
    uptime start over in passthrough. joy goes on without a reading twice or out of order,
    the restart is counted, and the override is applied again (MODE first)."""
    h = harness(lambda t: (((2.5 * t) % 2.0) - 1.0 if t % 2.0 < 1.0 else 0.6, 0.0),
                diagnostics_period=0.2)
    assert h.spin_until(lambda: (st := h.link_status()) is not None
                        and st.level == DiagnosticStatus.OK and len(h.joy) > 20, 10.0)
    push = lambda: h.override_pub.publish(Joy(axes=[0.2, 0.0]))  # noqa: E731
    # a deadline, not a fixed 0.3 s: on a loaded machine the spinning can stall past the
    # board's 200 ms watchdog once before the override holds (CI: MODE_OVERRIDE|WATCHDOG)
    assert h.spin_until(lambda: h.board.output.override_active, 5.0, each=push)
    h.board.restart()
    ok = False
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline and not ok:
        h.spin_for(0.05, each=push)
        st = h.link_status()
        ok = (conv.diagnostic_values(st)["board_restarts"] == "1"
              and st.level == DiagnosticStatus.OK and h.board.output.override_active)
    assert ok, conv.diagnostic_values(h.link_status())
    stamps = [conv.stamp_to_seconds(m.header.stamp) for _, m in h.joy]
    assert all(b >= a for a, b in itertools.pairwise(stamps))
    st = h.node.link.stats()
    assert st.frames_repeated == 0 and st.frames_late == 0
    assert st.frames_lost <= SEQ_RESTART_AFTER - 1 + 2  # the restart's first frames
    assert h.node._published <= len(h.board.sent)


def test_a_device_that_never_answers_the_handshake_is_an_error_with_a_reason(harness,
                                                                           tmp_path):
    """Another device behind the joystick's path (here one that echoes everything back)
    answers but never with a VERSION: after HANDSHAKE_ERROR_AFTER the link is an ERROR that
    says what was heard."""
    h = harness(lambda t: (0.3, 0.0), diagnostics_period=0.2)
    assert h.spin_until(lambda: (st := h.link_status()) is not None
                        and st.level == DiagnosticStatus.OK, 10.0)
    h.board.unplug()
    link = tmp_path / "asgp_joystick"
    with echoing_pty() as path:
        os.symlink(path, link)
        try:
            assert h.spin_until(lambda: h.link_status().level == DiagnosticStatus.ERROR
                                and "handshake" in h.link_status().message,
                                HANDSHAKE_ERROR_AFTER + 5.0)
            msg = h.link_status().message
            assert "HELLO" in msg and "echo" in msg and "baud" in msg, msg
        finally:
            os.unlink(link)


def test_overrides_are_refused_while_a_second_chair_shares_the_graph(harness):
    """Two chairs started without a namespace on one ROS domain: each bridge took the one
    layer's overrides and drove its own chair with them, every status OK. While another
    node of the bridge's full name, or another publisher of its joy, is on the graph, every
    override is refused, the board goes back to the user, and the override status is an
    ERROR that says why; once it has gone, overrides drive again."""
    from rclpy import create_node

    h = harness(lambda t: (0.5, 0.0), diagnostics_period=0.2)
    assert h.spin_until(lambda: len(h.joy) > 5, 10.0)
    push = lambda: h.override_pub.publish(Joy(axes=[-0.25, 0.6]))  # noqa: E731
    assert h.spin_until(lambda: h.board.output.override_active, 5.0, each=push)
    said = {"serial_bridge_node": "other node(s) named /serial_bridge_node",
            "other_chair": "other publisher(s) of /joy",
            # a second chair's bridge in /chair2, its override topic remapped onto ours
            "chair2_bridge": "another bridge reads /joy_override (/chair2/chair2_bridge"}
    for name in said:
        other = create_node(name, context=h.node.context,
                            namespace="chair2" if name == "chair2_bridge" else "")
        if name == "other_chair":
            other.create_publisher(Joy, "joy", qos_profile_sensor_data)
        if name == "chair2_bridge":
            other.create_publisher(Joy, "joy", qos_profile_sensor_data)  # (/chair2/joy)
            other.create_subscription(Joy, "/joy_override", lambda _: None,
                                      qos_profile_sensor_data)
        h.executor.add_node(other)
        assert h.spin_until(lambda: not h.board.output.override_active, 5.0, each=push)
        assert h.spin_until(lambda: (st := _override_status(h)) is not None
                            and st.level == DiagnosticStatus.ERROR, 5.0, each=push)
        message = _override_status(h).message
        assert said[name] in message, message
        sent = h.node.link.stats().overrides_sent
        h.spin_for(0.5, each=push)
        assert h.node.link.stats().overrides_sent == sent  # nothing written to the board
        assert not h.board.output.override_active
        assert int(conv.diagnostic_values(_override_status(h))["overrides_refused_crowd"]) > 0
        h.executor.remove_node(other)
        other.destroy_node()
        assert h.spin_until(lambda: h.board.output.override_active, 10.0, each=push)
        assert h.spin_until(lambda: _override_status(h).level == DiagnosticStatus.OK, 5.0,
                            each=push)
