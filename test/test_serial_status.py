"""What the host does with every SAMPLE status bit (docs/serial_protocol.md, "What the host
does with each status bit"), on the simulated board over a real pty: an ADC fault is never
published as a deflection and is an ERROR on diagnostics from the very sample that carries
it; the other bits leave ``joy`` the user's joystick and are reported on diagnostics; both
recover when good samples return. A stray VERSION frame does not stop ``joy``."""

from __future__ import annotations

import time

import pytest

from asgp_ros.serial import protocol as proto
from asgp_ros.serial import safety as fw
from asgp_ros.serial import status as status_mod
from asgp_ros.serial.calibration import AxisCalibration
from asgp_ros.serial.link import LinkConfig, LinkManager, LinkState
from asgp_ros.sim.board import SimulatedBoard

FAULT_RAW = (1023, 512)  # forward wire shorted to 5 V: reads as the forward end stop


def wait_until(pred, timeout: float, period: float = 0.005) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(period)
    return bool(pred())


def test_link_never_calibrates_a_faulty_reading(tmp_path):
    board = SimulatedBoard(lambda t: (0.5, 0.0), link_path=tmp_path / "joy").start()
    samples: list = []
    try:
        with LinkManager(LinkConfig(board.port), on_sample=samples.append) as link:
            assert link.wait_for_state(LinkState.CONNECTED, 3.0)
            assert wait_until(lambda: len(samples) > 5, 2.0)
            board.set_raw_override(FAULT_RAW)
            assert wait_until(lambda: sum(proto.Status.ADC_FAULT in s.status
                                          for s in samples) > 5, 2.0)
            board.set_raw_override(None)
            n = len(samples)
            assert wait_until(lambda: len(samples) > n + 5, 2.0)
            assert samples[-1].status == proto.Status.NONE
    finally:
        board.stop()
    faulty = [s for s in samples if proto.Status.ADC_FAULT in s.status]
    assert all((s.raw_forward, s.raw_turn) == FAULT_RAW for s in faulty)
    assert all(s.forward is None and s.turn is None and not s.valid for s in faulty)
    assert all(s.valid and s.forward == pytest.approx(0.479, abs=0.01)
               for s in samples if s not in faulty)


@pytest.mark.parametrize("status, sending, level, text", [
    (proto.Status.CLAMPED | proto.Status.OVERRIDE_ACTIVE, None, "WARN", "override was limited"),
    (proto.Status.CLAMPED, None, "OK", "output is limited"),
    (proto.Status.ADC_FAULT, True, "WARN", "not applied: ADC_FAULT"),
    (proto.Status.NONE, True, "OK", "sending"),
])
def test_verdicts_of_status_combinations(status, sending, level, text):
    if sending is None:
        v = status_mod.joystick_verdict(status, (600, 512))
    else:
        v = status_mod.override_verdict(status, sending)
    assert v.level == level and text in v.message


# -- the node ---------------------------------------------------------------------------------

rclpy = pytest.importorskip("rclpy")

from diagnostic_msgs.msg import DiagnosticStatus  # noqa: E402
from sensor_msgs.msg import Joy  # noqa: E402
from test_serial_bridge_node import Harness  # noqa: E402

from asgp_ros.nodes import conversions as conv  # noqa: E402

LINK, JOYSTICK, OVERRIDE = ("serial_bridge: link", "serial_bridge: joystick",
                            "serial_bridge: override")
LEVEL = {"OK": DiagnosticStatus.OK, "WARN": DiagnosticStatus.WARN,
         "ERROR": DiagnosticStatus.ERROR, "STALE": DiagnosticStatus.STALE}


class Bridge(Harness):
    """The harness, reading only this bridge's messages: diagnostics by hardware id (the
    board's unique path) and Joy by frame id (``frame_id`` is set to that path too)."""

    def mine(self) -> list[tuple[float, Joy]]:
        return [(t, m) for t, m in self.joy if m.header.frame_id == self.board.port]

    def statuses(self, name: str) -> list[DiagnosticStatus]:
        return [st for arr in self.diag for st in arr.status
                if st.name == name and st.hardware_id == self.board.port]

    def latest(self, name: str) -> DiagnosticStatus | None:
        found = self.statuses(name)
        return found[-1] if found else None

    def wait_level(self, name: str, level: str, timeout: float, text: str = "",
                   each=None) -> DiagnosticStatus:
        def ok() -> bool:
            st = self.latest(name)
            return st is not None and st.level == LEVEL[level] and text in st.message

        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not ok():
            if each is not None:
                each()
            self.executor.spin_once(timeout_sec=0.01)
        st = self.latest(name)
        assert ok(), (name, level, text, st and (st.level, st.message))
        return st

    def joy_count_after(self, t: float) -> int:
        return sum(1 for tt, _ in self.mine() if tt > t)

    def override_publisher(self, forward: float, turn: float, rate: float = 25.0):
        """A function that publishes the override at most at ``rate`` Hz when called (a
        planner's rate; one per spin would crowd the joy callbacks out of the executor)."""
        last = [-1.0]

        def publish() -> None:
            now = time.monotonic()
            if now - last[0] >= 1.0 / rate:
                last[0] = now
                self.override_pub.publish(Joy(axes=[forward, turn]))

        return publish


@pytest.fixture
def bridge(rclpy_context, tmp_path):
    made: list[Bridge] = []

    def make(joystick, board_kw=None, **params) -> Bridge:
        board = SimulatedBoard(joystick, link_path=tmp_path / f"joy{len(made)}", record=True,
                               **(board_kw or {})).start()
        b = Bridge(rclpy_context, board, frame_id=board.port, **params)
        made.append(b)
        assert b.spin_until(lambda: len(b.mine()) > 10, 10.0)
        return b

    yield make
    for b in made:
        b.close()
        b.board.stop()
        assert b.board.error is None, b.board.error


@pytest.mark.ros
def test_adc_fault_withholds_joy_and_is_an_error_from_its_first_sample(bridge):
    # a long diagnostics period: what arrives below was published because of the sample
    b = bridge(lambda t: (0.5, 0.0), diagnostics_period=30.0)
    assert b.wait_level(JOYSTICK, "OK", 2.0)
    b.board.set_raw_override(FAULT_RAW)
    st = b.wait_level(JOYSTICK, "ERROR", 2.0, "ADC_FAULT")
    assert "neutral" in st.message
    first_fault = next(s for s in b.board.sent if proto.Status.ADC_FAULT in s.status)
    values = conv.diagnostic_values(st)
    # published on the first faulty sample itself, before the next one was read
    assert values["sample_seq"] == str(first_fault.seq)
    assert "ADC_FAULT" in values["status"]
    # the board holds the chair neutral, and joy says nothing rather than something false
    assert b.board.output.code_forward == fw.DAC_NEUTRAL
    b.spin_for(0.1)  # Joys published before the fault may still be in flight
    n = len(b.mine())
    b.spin_for(0.4)
    assert len(b.mine()) == n
    assert all(m.axes[0] < 0.9 for _, m in b.mine())  # never the end stop
    assert int(conv.diagnostic_values(b.latest(JOYSTICK))["joy_withheld"]) > 0
    # good samples again: joy resumes and diagnostics recover at once
    b.board.set_raw_override(None)
    t0 = time.monotonic()
    st = b.wait_level(JOYSTICK, "OK", 1.0)
    assert b.spin_until(lambda: b.joy_count_after(t0) > 10, 1.0)
    assert b.mine()[-1][1].axes[0] == pytest.approx(0.479, abs=0.01)


@pytest.mark.ros
def test_clamped_output_joy_stays_the_users_joystick(bridge):
    cal = (fw.AxisCal(limit_pos=500), fw.AxisCal())
    b = bridge(lambda t: (0.8, 0.0), board_kw={"calibration": cal}, diagnostics_period=0.2)
    st = b.wait_level(JOYSTICK, "OK", 2.0, "CLAMPED")
    assert "CLAMPED" in conv.diagnostic_values(st)["status"]
    assert b.board.output.forward == pytest.approx(0.5, abs=2e-3)  # the chair gets less
    raw = round(512 + 0.8 * 205)
    assert b.mine()[-1][1].axes[0] == pytest.approx(AxisCalibration().deflection(raw))


@pytest.mark.ros
def test_override_active_and_neutral_stop(bridge):
    stick = [0.5]
    b = bridge(lambda t: (stick[0], 0.0), diagnostics_period=0.2)

    publish = b.override_publisher(-0.25, 0.6)

    st = b.wait_level(OVERRIDE, "OK", 2.0, "active", each=publish)
    assert "OVERRIDE_ACTIVE" in conv.diagnostic_values(st)["status"]
    assert b.board.output.override_active
    t0 = time.monotonic()
    b.spin_for(0.2, each=publish)
    # joy is the user's joystick, not the override the chair follows
    assert b.joy_count_after(t0) > 5
    assert all(m.axes[0] == pytest.approx(0.479, abs=0.01) for tt, m in b.mine() if tt > t0)
    # the user lets go: the board holds the override off and the chair stops
    stick[0] = 0.0
    st = b.wait_level(OVERRIDE, "WARN", 2.0, "NEUTRAL_STOP", each=publish)
    assert b.board.output.code_forward == fw.DAC_NEUTRAL
    t1 = time.monotonic()
    b.spin_for(0.2, each=publish)
    assert b.joy_count_after(t1) > 5 and b.mine()[-1][1].axes[0] == 0.0
    # and pushes again: the override applies again
    stick[0] = 0.5
    b.wait_level(OVERRIDE, "OK", 2.0, "active", each=publish)


@pytest.mark.ros
def test_watchdog_while_sending_is_a_warning_and_idle_is_fine(bridge):
    b = bridge(lambda t: (0.5, 0.0), diagnostics_period=0.2, mode_release_after=30.0)

    publish = b.override_publisher(0.3, 0.0)

    b.wait_level(OVERRIDE, "OK", 2.0, "active", each=publish)
    # overrides stop: the board passes the user through (WATCHDOG), which is what we want
    st = b.wait_level(OVERRIDE, "OK", 2.0, "WATCHDOG")
    assert "idle" in st.message and b.board.mode == proto.Mode.OVERRIDE
    t0 = time.monotonic()
    b.spin_for(0.2)
    assert b.joy_count_after(t0) > 5
    # overrides sent but not arriving (a deaf board): the user drives, and we say so
    b.board.set_deaf(True)
    try:
        b.wait_level(OVERRIDE, "WARN", 1.0, "WATCHDOG", each=publish)
    finally:
        b.board.set_deaf(False)
    b.wait_level(OVERRIDE, "OK", 2.0, "active", each=publish)


@pytest.mark.ros
def test_host_lost_is_an_error_until_the_board_hears_us_and_overrides_resume(bridge):
    b = bridge(lambda t: (0.5, 0.0), diagnostics_period=0.2)

    publish = b.override_publisher(0.3, 0.0)

    b.wait_level(OVERRIDE, "OK", 2.0, "active", each=publish)
    b.board.set_deaf(True)
    try:
        st = b.wait_level(LINK, "ERROR", 3.0, "HOST_LOST", each=publish)
        assert b.board.mode == proto.Mode.PASSTHROUGH  # the board gave the chair back
        assert conv.diagnostic_values(st)["host_lost_events"] == "1"
        t0 = time.monotonic()
        b.spin_for(0.3, each=publish)
        assert b.joy_count_after(t0) > 10  # the user's joystick is still published
        assert b.latest(LINK).level == DiagnosticStatus.ERROR  # held while unheard
    finally:
        b.board.set_deaf(False)
    b.wait_level(LINK, "OK", 2.0, each=publish)
    # the board is in passthrough now: the node switches it back to override mode
    b.wait_level(OVERRIDE, "OK", 2.0, "active", each=publish)
    assert b.board.output.override_active


@pytest.mark.ros
def test_joy_resumes_after_a_stray_version_frame(bridge):
    b = bridge(lambda t: (0.5, 0.0), diagnostics_period=0.2)
    seq = (b.board._logic.tx_seq + 2) & 0xFF  # just ahead: one behind is dropped, late
    b.board.inject(proto.encode(proto.Version(2, 1, 0, 0, 100, 200), seq))
    t0 = time.monotonic()
    assert b.spin_until(lambda: b.joy_count_after(t0 + 0.05) > 0, 10.0)
    assert b.node.link.stats().unsolicited_versions == 1
    b.spin_for(0.3)
    assert b.node.link.state == LinkState.CONNECTED
    # back to OK once the new handshake's diagnostics are out (under load, the one last
    # published 0.3 s after joy resumed could still be of the handshake: WARN)
    b.wait_level(LINK, "OK", 5.0)
