"""shared_control_node: in-process on a simulated clock, and across processes with the
serial bridge and the simulated board (the board's watchdog hands the chair back when
the node dies)."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from collections import deque

import numpy as np
import pytest

pytest.importorskip("rclpy")

from diagnostic_msgs.msg import DiagnosticStatus
from nav_msgs.msg import OccupancyGrid, Odometry
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Joy, LaserScan
from test_predictor_node import model_file  # noqa: F401 (a fixture)

from asgp_ros.nodes import conversions as conv
from asgp_ros.nodes.shared_control_node import SCAN_LEAD_S, SharedControlNode, StartupError
from asgp_ros.serial.protocol import Mode, Status

pytestmark = pytest.mark.ros

LASER_X = 0.3


def wall_scan_msg(t: float, distance: float, beams: int = 541,
                  frame: str = "laser") -> LaserScan:
    """A wall across the way, ``distance`` ahead of the scanner (inf beyond 8 m), with a
    real scanner's millimetre noise (seeded by the stamp): the layer refuses a scan whose
    ranges repeat the last one's bit for bit while the chair moves (a frozen driver)."""
    a0, inc = -0.75 * math.pi, 1.5 * math.pi / (beams - 1)
    ang = a0 + inc * np.arange(beams)
    with np.errstate(divide="ignore"):
        r = np.where(np.cos(ang) > 1e-9, distance / np.cos(ang), np.inf)
    r = r + np.random.default_rng(round(t * 1e3)).normal(0.0, 0.001, beams)
    r = np.where(r > 8.0, np.inf, r)
    return conv.scan_to_msg(r, a0, inc, 0.05, 8.0, t, frame)


class Harness:
    """The node on a simulated clock; a test node publishes joy, VO, scans and the clock."""

    def __init__(self, context, model: str, **params) -> None:
        # the joystick read every 5 ms (each of drive()'s samples is awaited)
        params = {"joy_poll_period_s": 0.005, **params}
        overrides = [Parameter("model_path", value=model),
                     Parameter("use_sim_time", value=True),
                     Parameter("laser_x", value=LASER_X)]
        overrides += [Parameter(k, value=v) for k, v in params.items()]
        self.node = SharedControlNode(context=context, parameter_overrides=overrides)
        import rclpy

        self.test = rclpy.create_node("sc_test", context=context)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self.executor.add_node(self.test)
        t = self.test
        self.clock_pub = t.create_publisher(Clock, "/clock", QoSProfile(depth=10))
        self.joy_pub = t.create_publisher(Joy, "joy", qos_profile_sensor_data)
        from geometry_msgs.msg import TwistStamped

        self.vo_pub = t.create_publisher(TwistStamped, "vo/twist", qos_profile_sensor_data)
        self.scan_pub = t.create_publisher(LaserScan, "scan", qos_profile_sensor_data)
        self.odom_pub = t.create_publisher(Odometry, "vo/odom", qos_profile_sensor_data)
        self.map_pub = t.create_publisher(OccupancyGrid, "map", QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.overrides: list[Joy] = []
        self.status: list[DiagnosticStatus] = []
        self.x = 0.0  # the chair's odometry x (m), integrated by drive()
        t.create_subscription(Joy, "joy_override", self.overrides.append, QoSProfile(depth=100))
        # (the bridge this node plays publishes a joystick, as serial_bridge_node does
        # joy and joy_applied: the layer counts such a reader of its overrides as a bridge)
        self.bridge_applied = t.create_publisher(Joy, "joy_applied", qos_profile_sensor_data)
        t.create_subscription(DiagnosticStatus, "shared_control/status", self.status.append,
                              QoSProfile(depth=100))
        # the publishers of the node's inputs (with obstacles 'grid' it has no laser, with
        # vo_type 'odometry' its VO is vo/odom)
        np_ = self.node.params
        inputs = [self.clock_pub, self.joy_pub,
                  self.odom_pub if np_.vo_type == "odometry" else self.vo_pub]
        inputs += [self.scan_pub] if np_.obstacles in ("laser", "both") else []
        inputs += [self.map_pub] if np_.obstacles in ("grid", "both") else []
        self.spin_until(lambda: all(p.get_subscription_count() > 0 for p in inputs)
                        and t.count_publishers("joy_override") > 0, what="discovery")

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.test.destroy_node()

    def spin_until(self, cond, timeout: float = 5.0, what: str = "") -> None:
        deadline = time.monotonic() + timeout
        while not cond():
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out waiting for {what}")
            self.executor.spin_once(timeout_sec=0.01)

    def clock(self, t: float) -> None:
        self.clock_pub.publish(Clock(clock=conv.seconds_to_stamp(t)))
        ns = round(t * 1e9)
        self.spin_until(lambda: self.node.get_clock().now().nanoseconds == ns, what="clock")

    def drive(self, t_from: float, t_to: float, fwd: float = 0.8, wall: float | None = None,
              vo: bool = True, scan: bool = True, scan_lead: float = 0.0,
              speed: float | None = None, scan_frame: str = "laser",
              frozen: bool = False) -> None:
        """Joystick ``fwd`` at 20 Hz; the chair moving along x at ``speed`` (default the
        model's steady speed, 0.9 ``fwd``); VO at 5 Hz with a VO's noise (an exact repeat
        is a frozen VO): twists, or with vo_type 'odometry' the pose integrated from x = 0
        and the twist; scans of a wall ``wall`` ahead at 10 Hz (stamped ``scan_lead``
        seconds after the clock, in ``scan_frame``; each is awaited as taken or as
        refused); ``frozen``: every scan is the first one's ranges again, re-stamped (a
        frozen laser driver)."""
        stats = self.node.predictor.stats
        rng = np.random.default_rng(int(t_from * 10))
        speed = 0.9 * fwd if speed is None else speed
        odometry = self.node.params.vo_type == "odometry"
        first = None
        for i in range(round((t_to - t_from) / 0.05)):
            t = t_from + 0.05 * (i + 1)
            self.x += 0.05 * speed
            self.clock(t)
            n = stats.joy_samples
            self.joy_pub.publish(conv.joy_from_sample(t, fwd, 0.0))
            self.spin_until(lambda n=n: stats.joy_samples > n, what="joy")
            if vo and i % 4 == 3:
                n = self.node._vo_messages
                v = speed + rng.normal(0.0, 0.003)
                if odometry:
                    self.odom_pub.publish(conv.odometry_from_pose(t, self.x, 0.0, 0.0, v, 0.0))
                else:
                    self.vo_pub.publish(conv.twist_stamped_from_sample(t, v, 0.0))
                self.spin_until(lambda n=n: self.node._vo_messages > n, what="vo")
            if scan and wall is not None and i % 2 == 1:
                seen = self._scan_state()
                msg = wall_scan_msg(t + scan_lead, wall, frame=scan_frame)
                if frozen:
                    first = msg.ranges if first is None else first
                    msg.ranges = first
                self.scan_pub.publish(msg)
                self.spin_until(lambda s=seen: self._scan_state() != s, what="scan")
        self.settle()

    def settle(self) -> None:
        """Until the decisions the inputs so far asked for are made (at the executor's
        turn after them)."""
        n = self.node
        self.spin_until(lambda: not (n._step_wanted or n._scan_wanted), what="decisions")

    def _scan_state(self) -> tuple[object, int, int, int, int]:
        """What a scan changes in the node: the stored scan, or a refusal's count."""
        n = self.node
        return (n._scan, n._scans_ahead, n._scans_other_frame, n._scans_two_frames,
                n._scans_frozen)

    def last(self) -> dict[str, str]:
        return conv.diagnostic_values(self.status[-1]) if self.status else {}


@pytest.fixture
def harness(rclpy_context, model_file):  # noqa: F811
    made: list[Harness] = []

    def make(**params) -> Harness:
        made.append(Harness(rclpy_context, model_file, **params))
        return made[-1]

    yield make
    for h in made:
        h.close()


def test_no_intervention_when_the_way_is_clear(harness):
    h = harness()
    h.drive(100.0, 104.0, wall=20.0)  # nothing within the scanner's 8 m
    assert h.status and {conv.diagnostic_values(s)["why"] for s in h.status[-5:]} == {"clear"}
    assert h.overrides == []
    assert float(h.last()["p_before"]) == 0.0


def test_an_intervention_slows_the_chair_before_a_wall(harness):
    h = harness()
    h.drive(100.0, 103.0, wall=20.0)
    assert h.overrides == []
    h.drive(103.0, 104.0, wall=1.6)  # the user's path runs into it within 2 s
    last = h.last()
    assert last["why"] == "intervening", last
    assert float(last["p_before"]) > 0.05 >= float(last["p_after"])
    assert float(last["command_forward"]) < 0.8 and float(last["change"]) > 0.0
    assert h.overrides, "no override was sent"
    fwd, turn = conv.joy_to_override(h.overrides[-1])
    assert 0.0 <= fwd < 0.8 and (fwd, turn) == pytest.approx(
        (float(last["command_forward"]), float(last["command_turn"])), abs=1e-3)
    diag = conv.diagnostic_values(h.node.diagnostic_status())
    assert int(diag["interventions"]) >= 1 and diag["solve_p99_ms"] != "nan"
    # the wall is gone (it was a person who stepped aside): the overrides stop with the
    # first scan that shows it (at 104.1 s), not at the next grid step
    h.drive(104.0, 105.0, wall=20.0)
    assert h.last()["why"] == "clear"
    last_sent = max(conv.stamp_to_seconds(m.header.stamp) for m in h.overrides)
    assert last_sent < 104.1 + 1e-6
    # its predictor is fed what the board drives with: the last override while the bridge
    # re-sends it and the board holds it (0.35 s after it), the user's stick after
    command = conv.joy_to_override(h.overrides[-1])
    stamps, joy = h.node.predictor._joy.arrays()
    held = (stamps > last_sent) & (stamps <= last_sent + 0.35 - 1e-6)
    after = stamps > last_sent + 0.35 + 1e-6
    assert held.sum() >= 6 and after.sum() >= 6
    assert np.allclose(joy[held], command, atol=1e-6)
    assert np.allclose(joy[after], (0.8, 0.0))
    # a stick sample that arrived before the override was sent (read in a later batch) is
    # what the user drove with, and that override is kept
    stick = np.array([0.8, 0.0])
    assert np.allclose(h.node._applied(stick, last_sent - 0.01), stick)
    assert np.allclose(h.node._applied(stick, last_sent + 0.1), command)
    # a clock gone back forgets that override: it is not of the new time line
    h.clock(last_sent - 2.0)
    assert np.allclose(h.node._applied(stick, last_sent - 1.9), stick)
    assert np.allclose(h.node._applied(stick, last_sent + 0.1), stick)


def test_joy_axes_signs_and_the_boards_measured_output(harness):
    """joy_axes '0,-1' flips the turn (it was ignored: the layer read the user's turn, and
    built its overrides, mirrored); joy_applied, the board's output as the bridge measures
    it, feeds the layer's predictor while it arrives, the user's stick still deciding."""
    h = harness(joy_axes="0,-1")
    h.drive(100.0, 101.0, wall=20.0)
    node = h.node
    pub = h.test.create_publisher(Joy, "joy_applied", qos_profile_sensor_data)
    h.spin_until(lambda: pub.get_subscription_count() > 0, what="discovery")

    def newest() -> list[float]:
        return [round(float(x), 6) for x in node.predictor._joy.arrays()[1][-1]]

    h.clock(101.1)
    h.joy_pub.publish(conv.joy_from_sample(101.1, 0.5, 0.3))
    h.spin_until(lambda: node._user[0] == pytest.approx(101.1), what="joy")
    assert [round(float(x), 6) for x in node._user[1]] == [0.5, -0.3]
    assert newest() == [0.5, -0.3]
    h.clock(101.15)
    pub.publish(conv.joy_from_sample(101.15, 0.4, 0.3))  # as on joy: '-' applies
    h.spin_until(lambda: node._joy_source.measured_samples == 1, what="joy_applied")
    assert newest() == [0.4, -0.3]
    h.joy_pub.publish(conv.joy_from_sample(101.15, 0.5, 0.3))
    h.spin_until(lambda: node._user[0] == pytest.approx(101.15), what="joy")
    assert newest() == [0.4, -0.3]  # the user's stick decides, the measurement feeds


def _reads_stopped(h: Harness) -> None:
    """Stop the node's read timer: only its own reads (before a VO or scan message, an
    override, ...) take the joystick now; and check that the executor never would."""
    node = h.node
    assert node.polled.timer is not None
    node.polled.timer.cancel()
    for _ in range(20):  # the timers due at the clock (their reads find nothing)
        h.executor.spin_once(timeout_sec=0.005)
    subs = [polled.sub for polled in node.polled._polled]
    assert sorted(sub.topic_name for sub in subs) == ["/joy", "/joy_applied"]
    assert not any(sub.callback_group.can_execute(sub) for sub in subs)


@pytest.mark.parametrize("trigger", ["vo", "scan"])
def test_the_joystick_is_read_before_a_vo_message_or_a_scan(harness, trigger):
    """The joystick topics are read in batches (joy_poll_period_s): what waits when a VO
    message or a scan comes, either of which may bring a decision, is read first, in the
    order received (the board's output before the stick's sample of the same stamp: it
    feeds, and the stick's, a repeat, does not)."""
    h = harness(joy_poll_period_s=1.0)
    node = h.node
    h.drive(100.0, 101.0, wall=20.0)
    applied = h.test.create_publisher(Joy, "joy_applied", qos_profile_sensor_data)
    h.spin_until(lambda: applied.get_subscription_count() > 0, what="discovery")
    h.clock(101.02)
    _reads_stopped(h)
    taken = node.polled.taken
    applied.publish(conv.joy_from_sample(101.02, 0.4, 0.0))
    time.sleep(0.02)
    h.joy_pub.publish(conv.joy_from_sample(101.02, 0.6, 0.0))
    time.sleep(0.05)  # both delivered to the node's queues
    assert node.polled.taken == taken
    if trigger == "vo":
        n = node._vo_messages
        h.vo_pub.publish(conv.twist_stamped_from_sample(101.02, 0.72, 0.0))
        h.spin_until(lambda: node._vo_messages > n, what="vo")
    else:
        seen = h._scan_state()
        h.scan_pub.publish(wall_scan_msg(101.02, 20.0))
        h.spin_until(lambda: h._scan_state() != seen, what="scan")
    assert node.polled.taken == taken + 2
    assert node._user[0] == pytest.approx(101.02)
    assert node._joy_source.measured_samples == 1
    assert [round(float(x), 6) for x in node.predictor._joy.arrays()[1][-1]] == [0.4, 0.0]
    values = conv.diagnostic_values(node.diagnostic_status())
    assert int(values["polled_messages"]) == node.polled.taken
    assert values["polled_queue_full"] == "0"


def test_a_neutral_stick_waiting_stops_the_override_before_it_is_sent(harness):
    """The stick released while the layer intervenes: its sample, not yet read, is read
    before the next override would be sent, and none is."""
    h = harness(joy_poll_period_s=1.0)
    node = h.node
    h.drive(100.0, 103.0, wall=20.0)
    h.drive(103.0, 104.0, wall=1.6)
    assert h.last()["why"] == "intervening" and h.overrides
    _reads_stopped(h)
    sent = node._overrides_sent
    h.joy_pub.publish(conv.joy_from_sample(104.0, 0.0, 0.0))
    time.sleep(0.05)
    node._send_override()  # as its timer would
    assert node._overrides_sent == sent
    assert node._user[1].tolist() == [0.0, 0.0] and node._decision is None


def test_an_older_pushed_stick_after_the_neutral_one_takes_no_override_up(harness):
    """Two publishers on joy (the bridge, and a relay delivering 20 ms late): the neutral
    stick stops the override, then the relay's older sample of the stick still pushed
    arrives. It was taken as the user's stick, and the next decision sent an override
    again, after the neutral stick had arrived."""
    h = harness()
    node = h.node
    h.drive(100.0, 103.0, wall=20.0)
    h.drive(103.0, 104.0, wall=1.6)
    assert h.last()["why"] == "intervening" and h.overrides
    relay = h.test.create_publisher(Joy, "joy", qos_profile_sensor_data)
    h.spin_until(lambda: relay.get_subscription_count() > 0, what="discovery")
    h.clock(104.22)
    h.joy_pub.publish(conv.joy_from_sample(104.21, 0.0, 0.0))
    h.spin_until(lambda: node._user is not None and node._user[0] == pytest.approx(104.21),
                 what="the neutral stick")
    assert node._decision is None
    sent = len(h.overrides)
    taken = node.polled.taken
    relay.publish(conv.joy_from_sample(104.19, 0.8, 0.0))
    h.spin_until(lambda: node.polled.taken > taken, what="the late sample")
    n = node._decisions
    h.vo_pub.publish(conv.twist_stamped_from_sample(104.22, 0.721, 0.0))
    h.spin_until(lambda: node._decisions > n, what="a decision")
    for _ in range(20):
        h.executor.spin_once(timeout_sec=0.01)
    assert node._user[1].tolist() == [0.0, 0.0]
    assert len(h.overrides) == sent


def test_the_override_timer_reads_the_joystick_when_not_intervening_too(harness):
    """The override timer (override_rate_hz, 20 Hz) reads what waits whether or not the
    layer intervenes: the joystick is read at least that often, which is why the read
    timer's own period (joy_poll_period_s, 0.25 s by default) may be long."""
    h = harness(joy_poll_period_s=1.0)
    node = h.node
    h.drive(100.0, 101.0, wall=20.0)
    assert node._decision is None or node._decision.command is None
    _reads_stopped(h)
    taken = node.polled.taken
    h.joy_pub.publish(conv.joy_from_sample(101.0, 0.3, 0.0))
    time.sleep(0.05)  # in the node's queue
    assert node.polled.taken == taken
    node._send_override()  # as its timer would: nothing to send
    assert node.polled.taken == taken + 1
    assert node._user[1].tolist() == pytest.approx([0.3, 0.0])


def test_a_stick_gone_neutral_while_deciding_is_what_the_status_says(harness):
    """The read before an intervening decision's override finds the stick neutral (it
    came while the decision was made): nothing is sent, and the decision's status says
    neutral_stick, not intervening."""
    h = harness(joy_poll_period_s=1.0)
    node = h.node
    h.drive(100.0, 103.0, wall=20.0)
    h.drive(103.0, 104.0, wall=1.6)
    assert h.last()["why"] == "intervening"
    _reads_stopped(h)
    send = node._send_override
    armed = [False]

    def send_after_a_neutral_read() -> str | None:
        if armed[0]:  # as if the read in _send_override took a neutral sample
            armed[0] = False
            node._user = (node._user[0], np.zeros(2))
        return send()

    node._send_override = send_after_a_neutral_read
    h.clock(104.2)
    for _ in range(20):  # the timers due at the new clock
        h.executor.spin_once(timeout_sec=0.005)
    sent, statuses = node._overrides_sent, len(h.status)
    armed[0] = True
    h.joy_pub.publish(conv.joy_from_sample(104.2, 0.8, 0.0))
    time.sleep(0.05)  # in the queue when the VO message comes
    h.vo_pub.publish(conv.twist_stamped_from_sample(104.2, 0.72, 0.0))
    h.spin_until(lambda: len(h.status) > statuses, what="a decision")
    last = h.last()
    assert not armed[0], "the decision did not intervene"
    assert last["why"] == "neutral_stick" and last["command_forward"] == "", last
    assert "before the override was sent" in h.status[-1].message
    assert node._overrides_sent == sent and not node._was_intervening
    assert node._decision is not None and node._decision.why.value == "neutral_stick"


def test_the_joystick_by_a_callback_per_message(harness):
    """joy_poll_period_s 0: rclpy's callback for each joystick message."""
    h = harness(joy_poll_period_s=0.0)
    node = h.node
    assert node.polled.timer is None and node.polled._polled == []
    h.drive(100.0, 101.0, wall=20.0)
    pub = h.test.create_publisher(Joy, "joy_applied", qos_profile_sensor_data)
    h.spin_until(lambda: pub.get_subscription_count() > 0, what="discovery")
    h.clock(101.01)
    pub.publish(conv.joy_from_sample(101.01, 0.4, 0.0))
    h.spin_until(lambda: node._joy_source.measured_samples == 1, what="joy_applied")
    assert conv.diagnostic_values(node.diagnostic_status())["polled_messages"] == "0"


def test_neutral_stick_never_commands_motion(harness):
    h = harness()
    h.drive(100.0, 103.0, fwd=0.0, wall=0.9)  # a wall right ahead, stick released
    assert h.overrides == []
    assert h.last()["why"] == "neutral_stick"


def test_stale_scan_or_vo_means_no_intervention_with_a_diagnostic(harness):
    h = harness(scan_timeout_s=0.3)
    h.drive(100.0, 103.0, wall=1.6)
    assert h.overrides and h.last()["why"] == "intervening"
    # the scanner stops: within scan_timeout_s the layer stops judging and intervening
    h.drive(103.0, 104.0, wall=1.6, scan=False)
    assert h.last()["why"] == "no_obstacle_source"
    n = len(h.overrides)
    h.drive(104.0, 104.5, wall=1.6, scan=False)
    assert len(h.overrides) == n
    assert "no_obstacle_source" in h.node.diagnostic_status().message
    # the VO stops (scans continue): no prediction, no intervention
    h.drive(104.5, 106.0, wall=1.6, vo=False)
    assert h.last()["why"] == "stale_input"
    assert len(h.overrides) == n


def test_no_joystick_yet_is_said_so_not_a_nan_stick(harness):
    """VO and scans, no joystick ever: the layer's status said "stale_input: the user's
    command: forward deflection is nan" (the missing stick passed as NaN). It says there is
    no joystick sample yet, as the predictor does, and sends nothing."""
    h = harness()
    rng = np.random.default_rng(3)
    for i in range(40):  # 2 s: VO at 5 Hz, scans at 10 Hz, the layer's watchdog decides
        t = 100.0 + 0.05 * (i + 1)
        h.clock(t)
        if i % 4 == 3:
            n = h.node._vo_messages
            h.vo_pub.publish(conv.twist_stamped_from_sample(t, rng.normal(0.0, 0.003), 0.0))
            h.spin_until(lambda n=n: h.node._vo_messages > n, what="vo")
        if i % 2 == 1:
            h.scan_pub.publish(wall_scan_msg(t, 3.0))
        h.executor.spin_once(timeout_sec=0.01)
    h.spin_until(lambda: bool(h.status), what="a decision")
    messages = {s.message for s in h.status}
    assert messages == {"stale_input: the user's command: no joystick sample yet"}, messages
    assert (h.last()["user_forward"], h.last()["user_turn"]) == ("", ""), h.last()
    assert "nan" not in h.node.diagnostic_status().message.lower()
    assert h.overrides == []


def test_scans_stamped_ahead_of_the_clock_are_refused(harness):
    """A laser whose clock runs 5 s ahead: its scans would look fresh for 5 s after the
    laser stopped, placed with motion that has not happened. They are refused (counted,
    and the diagnostics say why); the layer has no obstacle source and the user drives.
    Scans on time again: the layer judges them at once."""
    h = harness()
    h.drive(100.0, 103.0, wall=1.6, scan_lead=5.0)  # a wall 1.6 m ahead, scans 5 s early
    assert h.node._scan is None and h.node._scans_ahead == 30
    assert h.overrides == [] and h.last()["why"] == "no_obstacle_source"
    diag = conv.diagnostic_values(h.node.diagnostic_status())
    assert "after the node's clock" in diag["scan"] and diag["scans_ahead_of_clock"] == "30"
    # a lead within SCAN_LEAD_S (clocks synchronised to a few ms) is accepted
    h.clock(103.05)
    h.scan_pub.publish(wall_scan_msg(103.05 + 0.5 * SCAN_LEAD_S, 1.6))
    h.spin_until(lambda: h.node._scan is not None, what="scan on time")
    h.drive(103.05, 104.0, wall=1.6)
    assert h.last()["why"] == "intervening" and h.overrides
    assert conv.diagnostic_values(h.node.diagnostic_status())["scan"] == "received"
    # the clock steps back 0.5 s (less than the predictor's reset_jump_s): the scan it
    # holds now leads the clock and is no obstacle source, rather than one placed with
    # motion that has not happened
    h.clock(103.5)
    h.node._decide(103.5)
    assert h.node._decision.why.value == "no_obstacle_source", h.node._decision


def corridor_scan_msg(t: float, ahead: float, half_width: float = 1.0,
                      beams: int = 541) -> LaserScan:
    """A corridor of side walls ``half_width`` either side, closed by a wall ``ahead`` of
    the scanner: geometry a scan matcher can fix in x, y and heading."""
    a0, inc = -0.75 * math.pi, 1.5 * math.pi / (beams - 1)
    ang = a0 + inc * np.arange(beams)
    c, s = np.cos(ang), np.sin(ang)
    with np.errstate(divide="ignore", invalid="ignore"):
        front = np.where(c > 1e-9, ahead / c, np.inf)
        side = np.where(np.abs(s) > 1e-9, half_width / np.abs(s), np.inf)
    r = np.minimum(front, side)
    r = np.where(r > 8.0, np.inf, r)
    return conv.scan_to_msg(r, a0, inc, 0.05, 8.0, t, "laser")


def _drive_down_a_corridor(h, t_from: float, t_to: float, wall_at: float, speed: float,
                           vo: bool) -> None:
    """Joystick 0.8 at 20 Hz; the chair moving at ``speed`` towards a wall ``wall_at``
    metres ahead at ``t_from``; scans at 10 Hz that show it; VO at 5 Hz only if ``vo``."""
    stats = h.node.predictor.stats
    for i in range(round((t_to - t_from) / 0.05)):
        t = t_from + 0.05 * (i + 1)
        h.clock(t)
        n = stats.joy_samples
        h.joy_pub.publish(conv.joy_from_sample(t, 0.8, 0.0))
        h.spin_until(lambda n=n: stats.joy_samples > n, what="joy")
        if vo and i % 4 == 3:
            n = stats.vo_samples
            h.vo_pub.publish(conv.twist_stamped_from_sample(t, speed, 0.0))
            h.spin_until(lambda n=n: stats.vo_samples > n, what="vo")
        if i % 2 == 1:
            arrived = h.node._scan
            h.scan_pub.publish(corridor_scan_msg(t, wall_at - speed * (t - t_from)))
            h.spin_until(lambda a=arrived: h.node._scan is not a, what="scan")


@pytest.mark.parametrize("source", ["scan_matching", "auto"])
@pytest.mark.parametrize("memory_s", [0.0, 10.0])  # its own scan odometer, the memory's
def test_the_scans_as_the_velocity_source_keep_the_layer_acting_without_vo(
        harness, memory_s, source):
    """The camera loses its features as the chair heads for a wall: with velocity_source
    'vo' the layer's input goes stale and it lets go; with 'scan_matching' or 'auto' (the
    default) it keeps predicting from the matched scans and intervenes."""
    vo = harness(memory_s=memory_s, velocity_source="vo")
    _drive_down_a_corridor(vo, 100.0, 102.0, wall_at=6.0, speed=0.72, vo=False)
    assert vo.last()["why"] == "stale_input" and vo.overrides == []
    scans = harness(velocity_source=source, memory_s=memory_s)
    _drive_down_a_corridor(scans, 100.0, 103.0, wall_at=3.2, speed=0.72, vo=False)
    assert scans.overrides, scans.last()
    assert scans.node.predictor.stats.vo_samples >= 20  # from the scans, none from a VO
    diag = conv.diagnostic_values(scans.node.diagnostic_status())
    assert diag["velocity_source"].startswith(
        "scan_matching" if source == "scan_matching" else "auto (scans; 0 switches)")
    # the velocities it took are the chair's: 0.72 m/s ahead, no turn
    last = scans.node._decision
    assert last is not None and last.prediction is not None
    assert last.prediction.vel_past[-1] == pytest.approx((0.72, 0.0), abs=0.03)


def test_a_joystick_stamped_ahead_of_the_clock_is_not_a_fresh_user(harness):
    """The layer re-sends its override only while the user's joystick is fresh. A stick
    sample stamped 0.8 s ahead of the clock (a bridge whose clock runs ahead) looked fresh
    for 0.8 s more after the stick's messages stopped: the chair kept being driven by an
    override of a command the user may no longer give. Such a sample is not fresh."""
    h = harness()
    h.drive(100.0, 102.0, wall=1.6)
    assert h.overrides and h.last()["why"] == "intervening"
    stats = h.node.predictor.stats
    n = stats.joy_samples + sum(stats.rejected.values())
    h.joy_pub.publish(conv.joy_from_sample(102.8, 0.8, 0.0))  # 0.8 s ahead
    h.spin_until(lambda: stats.joy_samples + sum(stats.rejected.values()) > n, what="joy")
    sent = h.node._overrides_sent
    for i in range(1, 5):  # the clock goes on; no joystick comes
        h.clock(102.0 + 0.05 * i)
        h.node._send_override()
    assert h.node._overrides_sent == sent, "overrides re-sent on a stick stamped ahead"


def test_vo_in_another_frame_than_the_base_is_refused(harness):
    """The layer's predictor takes the VO's linear.x and angular.z as the chair's forward
    and turn rates: a twist in another frame (a camera's) is refused and named; the layer
    then has stale input and lets the user drive."""
    h = harness()
    h.drive(100.0, 101.0, wall=3.0)
    n = h.node.predictor.stats.vo_samples
    h.vo_pub.publish(conv.twist_stamped_from_sample(101.0, 0.72, 0.0, "camera_link"))
    h.spin_until(lambda: h.node._vo_frame.refused == 1, what="refused twist")
    assert h.node.predictor.stats.vo_samples == n
    values = conv.diagnostic_values(h.node.diagnostic_status())
    assert values["vo_frame"].startswith("VO twists in frame 'camera_link' refused")
    h.drive(101.0, 102.0, wall=1.6, vo=False)
    assert h.last()["why"] == "stale_input" and not h.overrides


def test_scans_of_a_second_laser_on_the_topic_are_refused(harness):
    """laser_x/y/yaw describe one laser: scans in another frame on the same topic (a rear
    laser, a merger's output) would be placed with its mount, moving the rear laser's
    obstacles ahead of the chair. ``laser_frame`` names the laser's frame, and scans in
    others are refused, counted and named. Unset, the first scan's frame is taken only
    until scans in a second frame come: which of the two is the laser's is then unknown
    (the first may have been the rear one), so no scan is taken until a restart."""
    front = harness(laser_frame="laser")
    front.drive(100.0, 101.0, wall=3.0)
    assert front.node._laser_frame == "laser" and not front.overrides
    # the rear laser sees a wall 1.6 m behind; with the front laser's mount it is ahead
    front.drive(101.0, 102.0, wall=1.6, scan_frame="rear_laser")
    assert front.overrides == []
    diag = conv.diagnostic_values(front.node.diagnostic_status())
    assert diag["scans_other_frame"] == "10" and diag["laser_frame"] == "laser"
    assert diag["scan"].startswith("scans in frame 'rear_laser' refused"), diag["scan"]
    front.drive(102.0, 103.0, wall=1.6)  # the front laser's wall is acted on
    assert front.overrides and front.last()["why"] == "intervening"
    # named by the parameter: the front laser's scans are the refused ones, and with no
    # scan of its own the layer has no obstacle source and lets the user drive
    rear = harness(laser_frame="rear_laser")
    rear.drive(100.0, 102.0, wall=1.6)
    assert rear.node._scans_other_frame == 20 and rear.overrides == []
    assert rear.last()["why"] == "no_obstacle_source"
    # '/laser' is 'laser' (as tf2 reads it); a scan without a frame_id is another laser's
    # as far as the node can tell
    slash = harness(laser_frame="/laser")
    slash.drive(100.0, 100.5, wall=3.0)
    slash.drive(100.5, 101.0, wall=3.0, scan_frame="/laser")
    slash.drive(101.0, 101.5, wall=1.6, scan_frame="")
    assert slash.node._scans_other_frame == 5 and slash.overrides == []
    assert "frame '' refused" in conv.diagnostic_values(slash.node.diagnostic_status())["scan"]


def test_scans_in_two_frames_with_laser_frame_unset_are_all_refused(harness):
    """laser_frame unset and the rear laser's scans first (its wall 1.6 m behind, placed
    ahead): the layer intervened on them, and kept doing so once the front laser's scans
    came, refusing those instead. Now the second frame ends the guess: the scans taken are
    forgotten, the override stops at once, nothing is taken any more, and the diagnostics
    say ERROR and why."""
    h = harness()
    h.drive(100.0, 101.0, wall=1.6, scan_frame="rear_laser")
    assert h.node._laser_frame == "rear_laser" and h.overrides  # the guess: wrong here
    h.drive(101.0, 101.1, wall=3.0)  # the front laser's first scan, at 101.1 s
    assert h.node._scan is None
    h.drive(101.1, 103.0, wall=1.6, scan_frame="rear_laser")
    h.drive(103.0, 104.0, wall=3.0)
    for _ in range(20):  # the overrides in flight arrive
        h.executor.spin_once(timeout_sec=0.01)
    last = max(conv.stamp_to_seconds(j.header.stamp) for j in h.overrides)
    assert last <= 101.1 + 1e-6, f"overrides until {last} s, after the second frame"
    assert h.last()["why"] == "no_obstacle_source"
    diag = h.node.diagnostic_status()
    values = conv.diagnostic_values(diag)
    assert diag.level == DiagnosticStatus.ERROR and "set laser_frame" in diag.message
    assert values["scan"].startswith("scans in two frames on /scan ('rear_laser', 'laser')")
    assert values["scans_other_frame"] == "11" and values["scans_two_frames"] == "19"


def test_decisions_follow_each_step_after_the_clock_goes_back(harness):
    """The clock goes back 90 s (a bag played again; the system clock set back): the
    predictor restarts its buffers and the layer decides at each new step again. It kept
    the newest step of the old timeline and decided only when its watchdog found the last
    decision 1.5 steps old (17 decisions in the 4 s after the jump, 30 now)."""
    h = harness()
    h.drive(100.0, 103.0, wall=20.0)
    h.drive(103.0, 104.0, wall=1.6)
    assert h.last()["why"] == "intervening"
    n = len(h.status)
    h.drive(10.0, 13.0, wall=20.0)
    h.drive(13.0, 14.0, wall=1.6)
    whys = [conv.diagnostic_values(st)["why"] for st in h.status[n:]]
    assert h.node.predictor.stats.resets >= 1
    assert len(whys) >= 22, whys  # 20 steps, and the scans judged at once while intervening
    assert whys[-1] == "intervening"


@pytest.mark.parametrize("source", ["scan_matching", "auto"])
def test_a_scan_delivered_twice_is_taken_once(harness, source):
    """A scan that comes again with the same stamp (a relay or a second recorder on the
    topic, a replay overlapping a live laser) is the same scan. Matched again it read as a
    lost match: 'scan_matching' gave the predictor a tracking loss beside the twist, and
    'auto' (the default) took the VO's next twist instead of the scans'."""
    h = harness(velocity_source=source, memory_s=10.0)
    stats = h.node.predictor.stats
    t_from, speed, scans = 100.0, 0.72, 0
    for i in range(60):
        t = t_from + 0.05 * (i + 1)
        h.clock(t)
        n = stats.joy_samples
        h.joy_pub.publish(conv.joy_from_sample(t, 0.8, 0.0))
        h.spin_until(lambda n=n: stats.joy_samples > n, what="joy")
        if source == "auto" and i % 4 == 2 and i > 4:  # the VO too, once scans match
            n = h.node._vo_messages
            h.vo_pub.publish(conv.twist_stamped_from_sample(t, speed, 0.0))
            h.spin_until(lambda n=n: h.node._vo_messages > n, what="vo")
        if i % 2 == 1:
            msg = corridor_scan_msg(t, 3.2 - speed * (t - t_from))
            arrived = h.node._scan
            h.scan_pub.publish(msg)
            h.spin_until(lambda a=arrived: h.node._scan is not a, what="scan")
            scans += 1
            assert h.node.memory is not None
            size, repeated = h.node.memory.size, h.node._scans_repeated
            h.scan_pub.publish(msg)
            h.spin_until(lambda r=repeated: h.node._scans_repeated > r, what="repeat")
            assert h.node.memory.size == size
            scan = conv.diagnostic_values(h.node.diagnostic_status())["scan"]
            assert scan.startswith("a scan came again with the newest one's stamp"), scan
    assert h.node._scans_repeated == scans
    assert h.node.velocity_odometer is not None and h.node.velocity_odometer.breaks == 0
    assert h.node.velocity.switches == 0 and h.node.velocity.current == "scans"
    if source == "scan_matching":
        # the first scan's sample (nothing to match yet: a loss), then one twist per
        # matched interval; nothing for a repeat
        assert stats.vo_samples == scans
    assert conv.diagnostic_values(h.node.diagnostic_status())["scans_repeated"] == str(scans)
    assert h.overrides, h.last()  # and the layer acts on the scans' velocities


def test_a_frozen_laser_driver_drives_no_override(harness):
    """A laser driver that froze and re-stamps its last scan while the VO shows the chair
    driving on: the frozen wall 1.6 m ahead kept the layer slowing the user until 2 m past
    it (69 overrides in 2 s), its diagnostics OK. Such scans are refused and said; the
    last good one goes stale, and the layer lets the user drive."""
    h = harness()
    node = h.node
    h.drive(100.0, 103.0, wall=20.0)
    h.drive(103.0, 103.5, wall=1.6)
    assert h.last()["why"] == "intervening" and h.overrides
    h.drive(103.5, 106.0, wall=1.6, frozen=True)
    diag = conv.diagnostic_values(node.diagnostic_status())
    assert int(diag["scans_frozen"]) >= 10
    assert "frozen laser driver" in diag["scan"], diag["scan"]
    late = [m for m in h.overrides if conv.stamp_to_seconds(m.header.stamp) > 104.5]
    assert not late
    # standing still, a noise-free laser may repeat itself: taken
    frozen = node._scans_frozen
    h.drive(106.0, 107.0, fwd=0.0, speed=0.0, wall=1.6, frozen=True)
    assert node._scans_frozen <= frozen + 2  # (the first, while the VO still moved)


def test_a_frozen_laser_is_refused_when_the_scans_give_the_velocity(harness):
    """velocity_source 'scan_matching': the predictor's velocity comes from the scans
    themselves, and frozen scans match as the chair standing still; 25 of 30 frozen scans
    were taken while the VO said 0.72 m/s. The VO's twists say the chair moves."""
    h = harness(velocity_source="scan_matching")
    node = h.node
    h.drive(100.0, 103.0, wall=20.0)
    h.drive(103.0, 106.0, wall=1.6, frozen=True)
    diag = conv.diagnostic_values(node.diagnostic_status())
    assert int(diag["scans_frozen"]) >= 28, diag["scans_frozen"]
    assert "frozen laser driver" in diag["scan"], diag["scan"]


def test_auto_takes_the_vo_while_the_scans_do_not_match(harness, rclpy_context,
                                                        model_file):  # noqa: F811
    """'auto', the default: a scanner that sees nothing to match (a straight wall: along
    it no scan pins the motion down) gives no velocity, and the VO's twists are the
    predictor's; the layer acts on them."""
    h = harness()
    h.drive(100.0, 103.0, wall=1.6)
    assert h.last()["why"] == "intervening" and h.overrides
    diag = conv.diagnostic_values(h.node.diagnostic_status())
    assert diag["velocity_source"].startswith("auto (vo; 0 switches)"), diag
    last = h.node._decision
    assert last is not None and last.prediction is not None
    assert last.prediction.vel_past[-1][0] == pytest.approx(0.72, abs=0.02)  # the VO's
    assert h.node.velocity_odometer is not None
    assert sum(h.node.velocity_odometer.refused.values()) >= 20
    # with the laser only for a map ('grid'), 'auto' is the VO without a scan odometer
    grid = SharedControlNode(context=rclpy_context, parameter_overrides=[
        Parameter("model_path", value=model_file), Parameter("obstacles", value="grid"),
        Parameter("vo_type", value="odometry"), Parameter("vo_topic", value="vo/odometry")])
    try:
        assert grid.velocity_odometer is None and grid.velocity.describe() == "vo"
    finally:
        grid.destroy_node()


def wall_map_msg(wall_x: float | None, frame: str = "odom") -> OccupancyGrid:
    """A 5 cm map of 24 m x 8 m around the odometry origin, free, with a wall across the
    way at x = ``wall_x`` (none when None)."""
    res = 0.05
    data = np.zeros((160, 480), dtype=np.int8)  # y from -4 m, x from -4 m
    if wall_x is not None:
        col = round((wall_x + 4.0) / res)
        data[:, col:col + 3] = 100
    return conv.grid_to_msg(data, res, (-4.0, -4.0, 0.0), 0.0, frame)


def _publish_map(h, msg: OccupancyGrid) -> None:
    grid, problem, bad = h.node._grid, h.node._grid_problem, h.node._bad_messages
    h.map_pub.publish(msg)
    h.spin_until(lambda: h.node._grid is not grid or h.node._grid_problem != problem
                 or h.node._bad_messages != bad, what="map")


def test_a_map_as_the_obstacle_source(harness):
    """obstacles 'grid': the map, in the odometry frame, placed with the odometry pose at
    each prediction's t0; clear, then a wall ahead (an intervention), then a map in another
    frame or a malformed one (no obstacle source: the user drives, and the diagnostics
    say why)."""
    h = harness(obstacles="grid", vo_type="odometry", vo_topic="vo/odom")
    assert h.node.velocity.describe() == "vo"
    _publish_map(h, wall_map_msg(None, frame="/odom"))  # ('odom', as tf2 reads it: it was
    h.drive(100.0, 103.0)                               # refused as another frame)
    assert h.last()["why"] == "clear" and h.overrides == []
    assert conv.diagnostic_values(h.node.diagnostic_status())["map"] == "received"
    # a wall 1.2 m ahead of the chair's front (x = 2.16 m at 103 s): the chair's path
    # runs into it within 2 s
    _publish_map(h, wall_map_msg(3.2 + 0.72 * 0.4))
    h.drive(103.0, 103.6)
    last = h.last()
    assert last["why"] == "intervening", last
    assert float(last["p_before"]) > 0.05 >= float(last["p_after"])
    assert h.overrides and 0.0 <= conv.joy_to_override(h.overrides[-1])[0] < 0.8
    # the same wall in the frame of the map server's 'map': not the chair's poses' frame
    n = len(h.overrides)
    _publish_map(h, wall_map_msg(3.6, frame="map"))
    assert "frame 'map'" in h.node._grid_problem
    h.drive(103.6, 104.2, fwd=0.3, speed=0.0)
    assert h.last()["why"] == "no_obstacle_source"
    diag = h.node.diagnostic_status()
    assert "frame 'map'" in conv.diagnostic_values(diag)["map"]
    sent = len(h.overrides)
    h.drive(104.2, 104.8, fwd=0.3, speed=0.0)
    assert len(h.overrides) == sent >= n  # none sent while there is no obstacle source
    # a map whose data do not fill its size: refused and counted
    bad = wall_map_msg(3.6)
    bad.info.width = 481
    _publish_map(h, bad)
    assert h.node._grid is None and h.node._bad_messages == 1
    assert "bad map" in conv.diagnostic_values(h.node.diagnostic_status())["map"]


def test_laser_and_map_together_take_the_nearer_obstacle(harness):
    """obstacles 'both': a clear scan does not hide the map's wall, nor a clear map the
    scan's."""
    h = harness(obstacles="both", vo_type="odometry", vo_topic="vo/odom")
    _publish_map(h, wall_map_msg(None))
    h.drive(100.0, 103.0, wall=20.0)
    assert h.last()["why"] == "clear" and h.overrides == []
    _publish_map(h, wall_map_msg(3.2 + 0.72 * 0.4))  # the map's wall, the scan clear
    h.drive(103.0, 103.6, wall=20.0)
    assert h.last()["why"] == "intervening", h.last()
    _publish_map(h, wall_map_msg(None))  # the map clear, the scan's wall
    h.overrides.clear()
    h.drive(103.6, 104.0, wall=1.2)
    assert h.last()["why"] == "intervening", h.last()
    assert h.overrides


def test_a_velocity_source_that_cannot_work_is_refused(harness):
    with pytest.raises(StartupError, match="velocity_source"):
        harness(velocity_source="wheels")
    with pytest.raises(StartupError, match="velocity_source"):
        harness(velocity_source="scan_matching", obstacles="grid", vo_type="odometry")


@pytest.mark.parametrize("scan_nan", ["erroneous", "no_return"])
def test_scan_nan_says_what_a_nan_range_means(harness, scan_nan):
    """REP-117's NaN is an erroneous reading, counted as an obstacle at the returns that
    bound it (a doorway of NaN between walls is closed); a source that reports nothing in
    range as NaN (depthimage_to_laserscan) would close every doorway onto a space beyond
    range_max: ``scan_nan: no_return`` reads its NaN as +inf."""
    h = harness(scan_nan=scan_nan)
    try:
        h.clock(100.0)
        msg = wall_scan_msg(100.0, 2.0)
        ranges = np.array(msg.ranges, dtype=np.float64)
        ranges[260:280] = np.nan
        msg.ranges = ranges.astype(np.float32).tolist()
        h.scan_pub.publish(msg)
        h.spin_until(lambda: h.node._scan is not None, what="scan")
        got = h.node._scan[1].ranges[260:280]
        assert np.all(np.isnan(got)) if scan_nan == "erroneous" else np.all(np.isinf(got))
    finally:
        h.close()
    with pytest.raises(StartupError, match="scan_nan"):
        harness(scan_nan="free")


def test_a_stick_barely_touched_is_stopped_before_a_wall(harness):
    """The stick at 0.04 (within neutral_deadband, yet the board drives it) creeping into a
    wall: the node sends the layer's stop, and keeps sending it (it stopped overriding at
    every stick within the deadband, so the stop was never sent)."""
    h = harness()
    h.drive(100.0, 103.0, fwd=0.04, wall=20.0)
    assert h.overrides == []
    h.drive(103.0, 104.0, fwd=0.04, wall=0.4)  # the grown footprint 5 cm from it
    last = h.last()
    assert last["why"] in ("intervening", "no_safe_command"), last
    assert h.overrides, "no override was sent"
    assert conv.joy_to_override(h.overrides[-1]) == (0.0, 0.0)


@pytest.mark.parametrize("obstacles", ["laser", "both"])
def test_within_the_margin_a_stick_pushing_on_into_the_wall_is_overridden(harness, obstacles):
    """The grown footprint already 5 cm into a wall, every candidate certain to touch: the
    node let the user's command pass, on into the wall. The depth of the mean paths decides
    now (with a map too: the two sources' check gives the depth of both)."""
    params = dict(obstacles=obstacles, vo_type="odometry", vo_topic="vo/odom") if (
        obstacles == "both") else {}
    h = harness(**params)
    if obstacles == "both":
        _publish_map(h, wall_map_msg(None))
    h.drive(100.0, 103.0, fwd=0.3, wall=20.0)
    assert h.overrides == []
    h.drive(103.0, 104.0, fwd=0.3, wall=0.3)
    last = h.last()
    assert last["why"] == "no_safe_command" and "deep" in h.status[-1].message, last
    assert h.overrides, "no override was sent"
    fwd, _ = conv.joy_to_override(h.overrides[-1])
    assert 0.0 <= fwd < 0.3


def test_bad_parameters_and_messages(harness, rclpy_context, model_file):  # noqa: F811
    with pytest.raises(StartupError, match="obstacles"):
        SharedControlNode(context=rclpy_context, parameter_overrides=[
            Parameter("model_path", value=model_file), Parameter("obstacles", value="lidar")])
    with pytest.raises(StartupError, match="vo_type"):
        SharedControlNode(context=rclpy_context, parameter_overrides=[
            Parameter("model_path", value=model_file), Parameter("obstacles", value="grid")])
    with pytest.raises(StartupError, match="model"):
        SharedControlNode(context=rclpy_context, parameter_overrides=[
            Parameter("model_path", value="/nonexistent.npz")])
    with pytest.raises(StartupError, match="memory_odometry"):
        SharedControlNode(context=rclpy_context, parameter_overrides=[
            Parameter("model_path", value=model_file),
            Parameter("memory_odometry", value="scan")])
    # the layer's inputs and its output cannot be switched off (a traceback before)
    for name in ("joy_topic", "vo_topic", "override_topic", "scan_topic", "base_frame"):
        with pytest.raises(StartupError, match=f"{name} must not be empty"):
            SharedControlNode(context=rclpy_context, parameter_overrides=[
                Parameter("model_path", value=model_file), Parameter(name, value=" ")])
    for value in (-0.01, math.nan, 2.0, 1e30):
        with pytest.raises(StartupError, match="joy_poll_period_s"):
            SharedControlNode(context=rclpy_context, parameter_overrides=[
                Parameter("model_path", value=model_file),
                Parameter("joy_poll_period_s", value=value)])
    for name, topic in (("applied_topic", "/joy"), ("override_topic", "joy_applied")):
        with pytest.raises(StartupError, match="name one topic"):
            SharedControlNode(context=rclpy_context, parameter_overrides=[
                Parameter("model_path", value=model_file), Parameter(name, value=topic)])
    h = harness()
    h.clock(100.0)
    bad = wall_scan_msg(100.0, 2.0)
    bad.ranges = []
    h.scan_pub.publish(bad)
    h.spin_until(lambda: h.node._bad_messages == 1, what="bad scan counted")
    assert h.node._scan is None


def test_the_board_hands_the_chair_back_when_the_node_dies(repo_root, model_file, tmp_path):  # noqa: F811
    """Bridge and simulated board in their own processes (as on the chair), the layer in
    its own: it overrides before a wall; SIGKILL it, and the bridge stops forwarding, the
    board's 200 ms watchdog hands the chair back and it follows the user's stick again.
    (How soon, stale timeout plus watchdog, is measured by benchmarks/link_timing.py.)"""
    import rclpy
    from geometry_msgs.msg import TwistStamped

    from asgp_ros.sim.board import SimulatedBoard

    board = SimulatedBoard(lambda t: (0.8, 0.0), link_path=str(tmp_path / "joystick"))
    board.start()
    env = dict(os.environ, PYTHONPATH=str(repo_root))
    logs = {name: open(tmp_path / f"{name}.log", "w")  # noqa: SIM115 (closed below)
            for name in ("bridge", "layer")}
    procs = {
        "bridge": subprocess.Popen(
            [sys.executable, "-m", "asgp_ros.nodes.serial_bridge_node", "--ros-args",
             "-p", f"port:={board.port}"], env=env, stdout=logs["bridge"],
            stderr=subprocess.STDOUT),
        "layer": subprocess.Popen(
            [sys.executable, "-m", "asgp_ros.nodes.shared_control_node", "--ros-args",
             "-p", f"model_path:={model_file}", "-p", f"laser_x:={LASER_X}"], env=env,
            stdout=logs["layer"], stderr=subprocess.STDOUT),
    }
    context = rclpy.context.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("sc_e2e", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    vo_pub = node.create_publisher(TwistStamped, "vo/twist", qos_profile_sensor_data)
    scan_pub = node.create_publisher(LaserScan, "scan", qos_profile_sensor_data)
    joy: list[Joy] = []
    node.create_subscription(Joy, "joy", joy.append, qos_profile_sensor_data)

    def spin_until(cond, timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        next_pub = 0.0
        rng = np.random.default_rng(0)
        while not cond():
            for name, p in procs.items():
                if p.poll() is not None and not (name == "layer" and killed):
                    raise AssertionError(f"{name} exited: "
                                         f"{(tmp_path / f'{name}.log').read_text()}")
            assert time.monotonic() < deadline, f"timed out waiting for {what}"
            now = time.monotonic()
            if now >= next_pub:  # VO at 10 Hz, scans at 10 Hz: a wall 1.4 m ahead
                next_pub = now + 0.1
                t = node.get_clock().now().nanoseconds * 1e-9
                vo_pub.publish(conv.twist_stamped_from_sample(t, 0.72 + rng.normal(0, 3e-3),
                                                              0.0))
                scan_pub.publish(wall_scan_msg(t, 1.4))
            executor.spin_once(timeout_sec=0.01)

    killed = False
    try:
        spin_until(lambda: len(joy) > 20 and board.output.override_active, 30.0,
                   "the layer to override the board")
        out = board.output
        assert out.forward < out.user_forward - 0.05  # slower than the stick asks
        n_reverts = len(board.revert_events)
        procs["layer"].send_signal(signal.SIGKILL)
        killed = True
        spin_until(lambda: not board.output.override_active, 20.0, "the board to revert")
        assert len(board.revert_events) == n_reverts + 1  # by the watchdog, not a neutral stop
        revert_ms, last_override_ms = board.revert_events[-1]
        status = board.revert_status[-1]
        if Status.WATCHDOG in status:  # never early on the board's clock
            assert revert_ms - last_override_ms >= 200, (revert_ms, last_override_ms, status)
        else:  # the simulated board's thread (in this process) starved for a second under
            # load reads the bridge's last override frames and its MODE release after 1 s in
            # one go, or meets the host timeout first (HOST_LOST) and then reads them: a
            # revert 1 ms after "the last override". The user has the chair all the same
            assert board.output.mode == Mode.PASSTHROUGH, (status, board.output)
        assert board.output.forward == pytest.approx(board.output.user_forward, abs=2e-3)
        # and it stays handed back: nothing left in the bridge re-engages the override
        settle = time.monotonic() + 1.0
        spin_until(lambda: time.monotonic() > settle or board.output.override_active, 20.0,
                   "a second")
        assert not board.output.override_active
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
        for p in procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in procs.values():
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                p.kill()
        for f in logs.values():
            f.close()
        board.stop()


def post_scan_msg(t: float, centre: tuple[float, float], radius: float = 0.05,
                  beams: int = 1081) -> LaserScan:
    """A 270-degree scan of a post (a disc at ``centre`` in the scanner's frame), with a
    real scanner's millimetre noise (as ``wall_scan_msg``)."""
    a0, inc = -0.75 * math.pi, 1.5 * math.pi / (beams - 1)
    ang = a0 + inc * np.arange(beams)
    d = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    c = np.asarray(centre)
    along = d @ c
    miss = along**2 - (c @ c - radius**2)
    with np.errstate(invalid="ignore"):
        r = np.where((miss >= 0.0) & (along > 0.0), along - np.sqrt(miss), np.inf)
    r = r + np.random.default_rng(round(t * 1e3)).normal(0.0, 0.001, beams)
    return conv.scan_to_msg(r, a0, inc, 0.05, 8.0, t, "laser")


def drive_past_post(h: Harness, post: np.ndarray, vo_scale: float = 1.0,
                    wheel: object | None = None) -> float:
    """4 s past ``post`` at 0.72 m/s: joystick at 20 Hz, twists at 5 Hz (the VO's scaled
    by ``vo_scale``; exact ones on the publisher ``wheel`` too, if given), scans at 10 Hz
    drawn from the exact twists. Returns the chair's x at the end."""
    stats = h.node.predictor.stats
    rng = np.random.default_rng(5)
    x, t_twist, v = 0.0, None, 0.0
    t = 100.0
    for i in range(80):
        t = 100.0 + 0.05 * (i + 1)
        h.clock(t)
        n = stats.joy_samples
        h.joy_pub.publish(conv.joy_from_sample(t, 0.8, 0.0))
        h.spin_until(lambda n=n: stats.joy_samples > n, what="joy")
        if i % 4 == 3:
            v = 0.72 + rng.normal(0.0, 0.003)
            if t_twist is not None:
                x += v * (t - t_twist)
            t_twist = t
            n = stats.vo_samples
            h.vo_pub.publish(conv.twist_stamped_from_sample(t, vo_scale * v, 0.0))
            h.spin_until(lambda n=n: stats.vo_samples > n, what="vo")
            if wheel is not None:
                wheel.publish(conv.odometry_from_pose(t, x, 0.0, 0.0, v, 0.0))
                h.spin_until(lambda t=t: abs((h.node.odometer.stamp or 0.0) - t) < 1e-6,
                             what="wheel odometry")
        if i % 2 == 1:
            at = x + v * (t - t_twist) if t_twist is not None else 0.0
            arrived = h.node._scan
            h.scan_pub.publish(post_scan_msg(t, (post[0] - at - LASER_X, post[1])))
            h.spin_until(lambda a=arrived: h.node._scan is not a, what="scan")
    return x + v * (t - t_twist)


def remembered_post_gap(h: Harness, post: np.ndarray, chair_x: float) -> np.ndarray:
    """Distance of each remembered point from the post's centre (scanner frame)."""
    sensor_x = chair_x + LASER_X
    assert math.degrees(math.atan2(post[1], post[0] - sensor_x)) > 140.0  # out of view
    _, _, extra = h.node._scan
    assert extra is not None and extra.shape[0] >= 3
    return np.hypot(extra[:, 0] - (post[0] - sensor_x), extra[:, 1] - post[1])


def test_the_memory_keeps_a_post_the_chair_drove_past(harness):
    """Driving past a post: once it is behind, out of the 270-degree view, the node still
    holds it where it is, carried along by the VO's twists (``dead_reckoning``; the scans
    here are drawn from the same twists, so any error is the node's)."""
    h = harness(memory_s=10.0, memory_odometry="dead_reckoning")
    post = np.array([2.0, 0.6])  # in the frame of the chair's pose at the first twist
    chair_x = drive_past_post(h, post)
    gap = remembered_post_gap(h, post, chair_x)
    assert np.all(np.abs(gap - 0.05) < 0.02), gap  # on the post's surface
    diag = conv.diagnostic_values(h.node.diagnostic_status())
    assert int(diag["memory_points"]) >= 3 and diag["odometry_breaks"] == "0"
    # the VO stops: the next scan has no pose, the memory is emptied, never moved blind
    sensor_x = chair_x + LASER_X
    for i in range(12):
        t = 104.05 + 0.05 * i
        h.clock(t)
        if i % 2 == 1:
            arrived = h.node._scan
            h.scan_pub.publish(post_scan_msg(t, (post[0] - sensor_x, post[1])))
            h.spin_until(lambda a=arrived: h.node._scan is not a, what="scan")
    assert h.node._scan[2].shape == (0, 2) and h.node.memory.size == 0


def test_the_memory_can_follow_other_odometry(harness):
    """With ``memory_odom_topic`` the memory is carried by that odometry (wheel odometry,
    say), not by the VO: here the VO over-reads the speed by 20 %, which would misplace
    the post by about half a metre, and the wheel odometry is exact."""
    from nav_msgs.msg import Odometry

    h = harness(memory_s=10.0, memory_odometry="dead_reckoning",
                memory_odom_topic="wheel/odom")
    wheel = h.test.create_publisher(Odometry, "wheel/odom", qos_profile_sensor_data)
    h.spin_until(lambda: wheel.get_subscription_count() > 0, what="discovery")
    post = np.array([2.0, 0.6])
    chair_x = drive_past_post(h, post, vo_scale=1.2, wheel=wheel)
    gap = remembered_post_gap(h, post, chair_x)
    assert np.all(np.abs(gap - 0.05) < 0.02), gap
    # lost tracking on that odometry (a huge twist variance) empties the memory
    lost = conv.odometry_from_pose(104.1, 0.0, 0.0, 0.0, 0.0, 0.0)
    lost.twist.covariance[0] = 1e12
    wheel.publish(lost)
    h.spin_until(lambda: h.node.odometer.breaks == 1, what="odometry break")


def test_scan_matching_carries_the_memory_whatever_the_vo_says(harness):
    """``memory_odometry: scan_matching`` (the default): the simulated room's scans, 2 s of
    driving at 0.72 m/s away from a wall, the VO over-reading the speed by 30 %. The walls
    that left the scanner's view, the one behind included, are remembered where they are
    (matched scans, not the VO's twists, which would put the wall behind 40 cm off); scans
    with nothing to match (all beyond range) empty the memory, counted."""
    from asgp_ros.sim.lidar import Lidar
    from asgp_ros.sim.world import room_for_surface

    room = room_for_surface("tile")
    lidar = Lidar(room, None, seed=7)
    assert lidar.config.mount[0] == LASER_X
    h = harness(memory_s=10.0, velocity_source="vo")  # the predictor takes the VO's twists
    assert h.node.odometer is None and h.node.scan_odometer is not None
    stats = h.node.predictor.stats
    x0, y0 = room.free_box[0] + 1.0, room.free_box[2] + 0.9  # a wall behind, one right
    t = 100.0
    x = x0
    for i in range(40):
        t = 100.0 + 0.05 * (i + 1)
        x = x0 + 0.72 * (t - 100.0)
        h.clock(t)
        n = stats.joy_samples
        h.joy_pub.publish(conv.joy_from_sample(t, 0.8, 0.0))
        h.spin_until(lambda n=n: stats.joy_samples > n, what="joy")
        if i % 4 == 3:
            n = stats.vo_samples
            h.vo_pub.publish(conv.twist_stamped_from_sample(t, 1.3 * 0.72, 0.0))
            h.spin_until(lambda n=n: stats.vo_samples > n, what="vo")
        if i % 2 == 1:
            r = lidar.scan(x, y0, 0.0)
            arrived = h.node._scan
            h.scan_pub.publish(conv.scan_to_msg(r.ranges, r.angle_min, r.angle_increment,
                                                r.range_min, r.range_max, t, "laser"))
            h.spin_until(lambda a=arrived: h.node._scan is not a, what="scan")
    _, _, extra = h.node._scan
    assert extra is not None and extra.shape[0] > 20
    sensor = np.array([x + LASER_X, y0])
    world = extra + sensor  # the chair faces +x: the scanner frame is the world's, shifted
    x_lo, x_hi, y_lo, y_hi = room.free_box
    depth = np.minimum.reduce([world[:, 0] - x_lo, x_hi - world[:, 0],
                               world[:, 1] - y_lo, y_hi - world[:, 1]])
    # on the furniture's front (range noise and the 2 cm cells), not inside the floor
    assert np.all(depth < 0.04), np.sort(depth)[-5:]
    behind = np.degrees(np.abs(np.arctan2(extra[:, 1], extra[:, 0]))) > 140.0
    assert np.sum(behind & (world[:, 0] < x_lo + 0.05)) > 10  # the wall behind
    diag = conv.diagnostic_values(h.node.diagnostic_status())
    assert diag["odometry_breaks"] == "0" and int(diag["memory_points"]) > 20
    # a scan with nothing to match: the matcher refuses, the memory is emptied
    h.clock(t + 0.1)
    arrived = h.node._scan
    h.scan_pub.publish(conv.scan_to_msg(np.full(r.ranges.shape, np.inf), r.angle_min,
                                        r.angle_increment, r.range_min, r.range_max,
                                        t + 0.1, "laser"))
    h.spin_until(lambda a=arrived: h.node._scan is not a, what="scan")
    assert h.node.memory.size == 0
    assert conv.diagnostic_values(h.node.diagnostic_status())["odometry_breaks"] == "1"


def test_the_memory_is_on_by_default_and_carried_by_scan_matching(harness):
    """The default since the offline drives measured it (README): remembered for 10 s,
    carried by the scans themselves, not by the VO; a map (obstacles 'grid') has no scan to
    remember and starts without it instead of refusing."""
    from asgp_ros.nodes.shared_control_node import LAYER_PARAMS, SharedControlParams

    h = harness()
    assert h.node.memory is not None and h.node.scan_odometer is not None
    assert h.node.odometer is None and h.node.params.memory_s == 10.0
    defaults = {spec.name: spec.default for spec in LAYER_PARAMS} | {"model_path": "chair.npz"}
    grid = SharedControlParams(**(defaults | {"obstacles": "grid", "vo_type": "odometry"}))
    assert grid.memory() is None
    assert SharedControlParams(**(defaults | {"memory_s": 0.0})).memory() is None
    # memory_odom_topic set alone (as README's advice for better odometry read) was ignored
    # in silence: the default scan matching carried the memory, no subscription was made
    wheel = {"memory_odom_topic": "wheel/odom"}
    for other in ({}, {"memory_odometry": "dead_reckoning", "memory_s": 0.0},
                  {"memory_odometry": "dead_reckoning", "obstacles": "grid",
                   "vo_type": "odometry"}):
        with pytest.raises(ValueError, match="memory_odom_topic 'wheel/odom' is read only "
                                             "with memory_odometry 'dead_reckoning'"):
            SharedControlParams(**(defaults | wheel | other))
    SharedControlParams(**(defaults | wheel | {"memory_odometry": "dead_reckoning"}))


def test_the_memory_can_be_turned_off(harness):
    h = harness(memory_s=0.0)
    h.drive(100.0, 101.0, wall=3.0)
    assert h.node.memory is None and h.node._scan[2] is None
    assert conv.diagnostic_values(h.node.diagnostic_status())["memory_points"] == "off"


def test_the_layer_adapts_learns_after_acting_and_not_from_its_own_overrides(harness):
    """adapt.enabled: the layer's own predictor adapts online (a chair slower than the
    model was trained for), its diagnostics say so, it learns after the override is out
    (never before it), nothing its overrides drove is learnt, and the service returns it
    to the trained model. On by default."""
    from std_srvs.srv import Trigger

    # a value rclpy refuses (out of the declared range, NaN): one line naming it
    for bad in (0.0, math.nan):
        with pytest.raises(StartupError, match=r"parameter adapt\.max_rate: "):
            harness(**{"adapt.max_rate": bad})
    # a horizon whose adaptation needs more history than the default buffer: the layer
    # (which has no buffer_s) sizes its predictor's buffer for it
    long = harness(**{"adapt.enabled": True, "horizon_s": 10.0})
    assert long.node.predictor.config.buffer_s >= long.node.predictor.min_buffer_s > 10.0
    # a misspelt key is not silently a default (it was, with one warning): the node does
    # not start, naming it
    from asgp_ros.nodes.parameters import unknown_overrides

    with pytest.raises(StartupError, match=r"misspelt\?\): adapt\.enable, adapt\.halflife_s"):
        harness(**{"adapt.enable": False, "adapt.halflife_s": 3.0})
    with pytest.raises(StartupError, match="footprint_widht"):
        harness(footprint_widht=0.9)
    on = harness()
    assert on.node.predictor.adaptation is not None
    assert unknown_overrides(on.node) == []
    assert conv.diagnostic_values(on.node.diagnostic_status())["adapt"] == "on"
    off = harness(**{"adapt.enabled": False})
    assert off.node.predictor.adaptation is None
    assert conv.diagnostic_values(off.node.diagnostic_status())["adapt"] == "off"

    h = harness(**{"adapt.enabled": True, "adapt.half_life_s": 10.0})
    node = h.node
    events: list[str] = []
    publish, learn, status = node.override_pub.publish, node.predictor.learn, \
        node.status_pub.publish
    check_for = node._check_for

    def record(what, call):
        def recorded(*args):
            events.append(what)
            return call(*args)
        return recorded

    node.override_pub.publish = record("override", publish)
    node.predictor.learn = record("learn", learn)
    node.status_pub.publish = record("status", status)
    node._check_for = record("decide", check_for)  # made as a decision starts
    h.drive(100.0, 110.0, wall=20.0, speed=0.4)  # the model expects 0.72 m/s at 0.8
    stats = node.predictor.adaptation
    assert stats is not None and stats.rows_absorbed >= 30
    values = conv.diagnostic_values(node.diagnostic_status())
    assert values["adapt"] == "on" and int(values["adapt_rows_absorbed"]) >= 30
    assert values["adapt_published"] in ("trained", "adapted")
    assert node.predictor.stats.overrides == 0

    absorbed, refused = stats.rows_absorbed, stats.steps_refused
    events.clear()
    h.drive(110.0, 111.5, wall=1.2, speed=0.4)  # the user's path runs into it
    assert h.overrides and node.predictor.stats.overrides == node._overrides_sent > 0
    # each decision: nothing learnt until it is out (its override sent, its status
    # published), then learning
    decisions = [events[i:events.index("status", i) + 2]
                 for i, e in enumerate(events) if e == "decide" and "status" in events[i:]]
    assert decisions and any("override" in d for d in decisions)
    assert all("learn" not in d[:-1] and d[-1] == "learn" for d in decisions), decisions
    h.drive(111.5, 114.0, wall=20.0, speed=0.4)  # overrides stop; the steps settle
    stats = node.predictor.adaptation
    assert stats.steps_refused - refused >= 3  # the overridden steps were not learnt
    assert stats.rows_absorbed > absorbed  # the others were
    values = conv.diagnostic_values(node.diagnostic_status())
    assert values["overrides_seen"] == str(node._overrides_sent)
    assert values["overrides_late"] == "0"

    client = h.test.create_client(Trigger, "/shared_control_node/reset_adaptation")
    h.spin_until(client.service_is_ready, what="reset service")
    future = client.call_async(Trigger.Request())
    h.spin_until(future.done, what="reset reply")
    assert future.result().success and node.predictor.adaptation.rows_absorbed == 0


def test_no_event_handler_per_endpoint_and_the_peers_checked(harness):
    """As predictor_node's (asgp_ros.nodes.qos_watch): rclpy's per-endpoint QoS event
    handlers are off, and the graph check finds nothing wrong with the test's peers."""
    h = harness()
    node = h.node
    mine = [e for e in [*node.subscriptions, *node.publishers]
            if e.topic_name not in ("/parameter_events", "/rosout", "/clock")]
    assert len(mine) >= 7 and all(not e.event_handlers for e in mine), [
        e.topic_name for e in mine if e.event_handlers]
    assert node.qos_watch.check() == []
    node._publish_diagnostics()
    assert conv.diagnostic_values(node.diagnostic_status())["qos_mismatch"] == "none"


_FIRST_DECISION_CHECK = """
import json, sys
import rclpy
from rclpy.parameter import Parameter
from asgp_ros.core import collision
from asgp_ros.nodes.shared_control_node import SharedControlNode, StartupError
def state():
    return {"cv2": collision._opencv.cache_info().currsize == 1 and "cv2" in sys.modules,
            "draws": collision.SAMPLES in collision._NORMAL_DRAWS}
before = state()
rclpy.init()
try:
    SharedControlNode(parameter_overrides=[Parameter("model_path", value="/nonexistent.npz")])
except StartupError:
    refused = state()
node = SharedControlNode(parameter_overrides=[Parameter("model_path", value=%r)])
after = state()
node.destroy_node()
rclpy.shutdown()
print(json.dumps({"before": before, "refused": refused, "after": after}))
"""


def test_the_node_loads_the_checks_parts_at_start_up_not_at_its_first_decision(
        repo_root, model_file):  # noqa: F811
    """OpenCV and the collision check's Sobol draws (scipy.stats' import: 0.4 s) are loaded
    when the node starts, not by its first decision, which they would delay; and only once
    its model is loaded, so that a refused model file is reported without that wait."""
    import json
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-c", _FIRST_DECISION_CHECK % str(model_file)],
                       cwd=repo_root, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout.splitlines()[-1])
    assert out == {"before": {"cv2": False, "draws": False},
                   "refused": {"cv2": False, "draws": False},
                   "after": {"cv2": True, "draws": True}}, out


# ---- from an attack on the layer: each a break found, now a regression test ----------


def _intervene(h) -> None:
    h.drive(100.0, 103.0, wall=20.0)
    h.drive(103.0, 104.0, wall=1.6)
    assert h.last()["why"] == "intervening" and h.overrides


def _spin(h, n: int = 20) -> None:
    for _ in range(n):
        h.executor.spin_once(timeout_sec=0.005)


def test_a_moved_stick_is_judged_again_not_sent_the_old_override(harness):
    """The layer slows a forward drive; the user pulls the stick back. The old decision's
    forward command was sent again, twice, after the reverse stick was read: now each
    override sent was decided with the stick the node held when it sent it."""
    h = harness()
    _intervene(h)
    node = h.node
    sends = []
    publish = node.override_pub.publish

    def record(msg):
        sends.append((float(msg.axes[0]), float(node._user[1][0])))
        publish(msg)
    node.override_pub.publish = record
    h.drive(104.0, 104.5, fwd=-0.8, wall=1.6, speed=0.5)
    _spin(h)
    assert node._user[1][0] == pytest.approx(-0.8)
    assert not [(cmd, user) for cmd, user in sends if user < 0.0 and cmd > 0.0], sends


def _triangle(phase: float, amp: float = 0.6, step: float = 0.12) -> float:
    """A triangle wave in [-amp, amp] advancing ``step`` per unit of ``phase``."""
    period = 4 * amp / step
    ph = (phase % period) / period
    return amp * (4 * ph - 1) if ph < 0.5 else amp * (3 - 4 * ph)


@pytest.mark.parametrize(("hand_moves", "solve_s"), [(False, 0.0), (True, 0.0), (True, 0.06)],
                         ids=["hand-steady", "hand-moving", "hand-moving-slow-decisions"])
def test_a_stick_moving_while_the_layer_decides_still_gets_overrides(harness, monkeypatch,
                                                                    hand_moves, solve_s):
    """The chair drives at a wall 1.2 m ahead; the layer intervenes while the user sweeps
    the turn (2.4 deflection/s, a live demo's hand). Each decision takes time, in which the
    stick moves on by more than STICK_CHANGE: the send found the stick moved and sent
    nothing, the next decision the same, so no override went out for as long as the hand
    moved (live: 1.4 s), the status saying 'intervening', and the board drove the user's
    stick into the furniture. Now the newest stick is judged at once (it, the decision's
    command within it, stopping: judge_moved_stick), and what is judged is sent.

    With decisions of 60 ms, judging the moved stick at every tick of the override timer
    takes the node's whole time (live: its inputs refused as stale on arrival, the layer
    letting go); those decisions wait for half of it now, the overrides still going out."""
    from asgp_ros.nodes import shared_control_node as scn

    h = harness()
    _intervene(h)
    node = h.node
    real_decide = scn.decide
    state = {"phase": 0.0, "t": 104.0}

    def slow_decide(*args, **kwargs):
        d = real_decide(*args, **kwargs)
        time.sleep(solve_s)
        state["phase"] += 0.5 if hand_moves else 0.0  # the hand during the solve
        h.joy_pub.publish(conv.joy_from_sample(state["t"], 0.8, _triangle(state["phase"])))
        time.sleep(0.03)  # in the node's reader before the send drains it
        return d

    monkeypatch.setattr(scn, "decide", slow_decide)
    sent_before, statuses_before = len(h.overrides), len(h.status)
    sends: list[tuple[float, float]] = []
    publish = node.override_pub.publish

    def record(msg):
        sends.append((float(msg.axes[0]), float(node._user[1][0])))
        publish(msg)
    node.override_pub.publish = record
    rng = np.random.default_rng(1)
    for i in range(40):  # 2 s at 20 Hz
        t = 104.0 + 0.05 * (i + 1)
        state["phase"] += 1.0
        state["t"] = t
        h.x += 0.05 * 0.5
        h.clock(t)
        h.joy_pub.publish(conv.joy_from_sample(t, 0.8, _triangle(state["phase"])))
        h.spin_until(lambda t=t: node._user is not None and node._user[0] >= t - 1e-9,
                     what="joy")
        if i % 4 == 3:
            n = node._vo_messages
            h.vo_pub.publish(conv.twist_stamped_from_sample(t, 0.5 + rng.normal(0, 0.003),
                                                            0.0))
            h.spin_until(lambda n=n: node._vo_messages > n, what="vo")
        if i % 2 == 1:
            seen = h._scan_state()
            h.scan_pub.publish(wall_scan_msg(t, 1.2))
            h.spin_until(lambda s=seen: h._scan_state() != s, what="scan")
        _spin(h, 3)
    _spin(h)
    whys = [conv.diagnostic_values(st).get("why") for st in h.status[statuses_before:]]
    assert whys.count("intervening") >= 8, whys  # (at least the steps: 5 Hz)
    # an override at least every hold_s (0.35 s) of the 2 s
    assert len(h.overrides) - sent_before >= 2.0 / 0.35
    assert not [(cmd, user) for cmd, user in sends if cmd > user + 1e-6], sends
    values = conv.diagnostic_values(node.diagnostic_status())
    if hand_moves:
        assert int(values["moved_stick_judgements"]) > 0
    if solve_s:  # (the harness's clock runs faster than the wall: a bound, not a rate)
        assert int(values["decisions_deferred"]) > 0


def test_a_stick_pulled_back_while_deciding_is_judged_and_said(harness, monkeypatch):
    """Intervening before a wall; while the next decision is made the user pulls the stick
    back (-0.6). The decision's forward command was sent scaled to a stop (pinning the
    chair where backing away is clear), and the status said 'intervening' with the
    decision's command. The pulled-back stick is judged at once: clear, nothing is sent,
    and the status says so."""
    from asgp_ros.nodes import shared_control_node as scn

    h = harness()
    _intervene(h)
    node = h.node
    real_decide = scn.decide
    state = {"armed": True, "pending": False, "status": None}

    def decide_then_pull_back(*args, **kwargs):
        d = real_decide(*args, **kwargs)
        if state["armed"] and d.command is not None:
            state["armed"], state["pending"] = False, True
            h.joy_pub.publish(conv.joy_from_sample(104.1, -0.6, 0.0))
            time.sleep(0.05)  # in the node's reader before the send drains it
        return d

    monkeypatch.setattr(scn, "decide", decide_then_pull_back)
    sends = []
    publish, status_publish = node.override_pub.publish, node.status_pub.publish

    def record(msg):
        sends.append((float(msg.axes[0]), float(node._user[1][0])))
        publish(msg)

    def record_status(msg):
        if state["pending"]:
            state["pending"], state["status"] = False, conv.diagnostic_values(msg)
        status_publish(msg)
    node.override_pub.publish, node.status_pub.publish = record, record_status
    h.clock(104.1)
    h.joy_pub.publish(conv.joy_from_sample(104.1, 0.8, 0.0))
    h.spin_until(lambda: node._user[0] >= 104.1 - 1e-9, what="joy")
    seen = h._scan_state()
    h.scan_pub.publish(wall_scan_msg(104.1, 1.55))  # judged at once while intervening
    h.spin_until(lambda: h._scan_state() != seen, what="scan")
    h.spin_until(lambda: state["status"] is not None, what="the decision's status")
    _spin(h)
    assert not [s for s in sends if s[1] < 0.0], sends  # none for the reversed stick
    st = state["status"]
    assert st["why"] == "clear" and float(st["user_forward"]) == pytest.approx(-0.6), st
    assert st["command_forward"] == ""


def test_a_decision_deferred_is_counted_once_however_many_ticks_it_waits():
    from types import SimpleNamespace

    from asgp_ros.nodes.shared_control_node import SharedControlNode

    node = SimpleNamespace(_decided_at=time.monotonic(), _decide_s=10.0,
                           _decisions_deferred=0, _deferred_counted=False)
    assert not SharedControlNode._may_decide(node)  # type: ignore[arg-type]
    assert not SharedControlNode._may_decide(node)  # type: ignore[arg-type]
    assert node._decisions_deferred == 1


def test_a_stale_or_out_of_order_scan_is_refused(harness):
    """A scan stamped 5 s back (a buffered or replayed one on the topic) replaced the fresh
    one, restarted the scan matching and emptied the obstacle memory, and the diagnostics
    said 'received'. Now it is refused, counted and named."""
    h = harness()
    _drive_down_a_corridor(h, 100.0, 103.0, wall_at=3.2, speed=0.72, vo=False)
    node = h.node
    before = (node.memory.size, node.scan_odometer.breaks, node.memory.resets)
    assert before[0] > 0
    fresh = node._scan
    h.scan_pub.publish(corridor_scan_msg(98.0, 3.2))
    h.spin_until(lambda: node._scans_old == 1, what="the old scan refused")
    assert node._scan is fresh
    assert (node.memory.size, node.scan_odometer.breaks, node.memory.resets) == before
    values = conv.diagnostic_values(node.diagnostic_status())
    assert "stale on arrival" in values["scan"] and values["scans_old"] == "1"
    # within scan_timeout_s, but older than the newest scan taken: out of order
    h.scan_pub.publish(corridor_scan_msg(fresh[1].stamp - 0.05, 3.2))
    h.spin_until(lambda: node._scans_old == 2, what="the out-of-order scan refused")
    assert node._scan is fresh and "out of order" in node._scan_problem


def test_a_map_whose_orientation_is_not_a_rotation_is_refused():
    """(0, 0, 0.5, 0.5) is 90 degrees half-written: read as 45, it turned a wall ahead into
    'clear'. A map origin that is not a unit quaternion is refused; an odometry pose with
    one is a lost sample (no pose, no velocity); within tf2's 1 % it is normalised."""
    data = np.zeros((10, 10), dtype=np.int8)
    msg = conv.grid_to_msg(data, 0.1, (0.0, 0.0, math.pi / 2), 0.0, "odom")
    o = msg.info.origin.orientation
    o.x, o.y, o.z, o.w = 0.0, 0.0, 0.5, 0.5
    with pytest.raises(ValueError, match="not a unit quaternion"):
        conv.grid_from_msg(msg)
    o.z, o.w = 0.0, 0.0
    with pytest.raises(ValueError, match="not a unit quaternion"):
        conv.grid_from_msg(msg)
    o.z = o.w = math.sqrt(0.5) * 1.005
    assert conv.grid_from_msg(msg).origin[2] == pytest.approx(math.pi / 2)
    odom = conv.odometry_from_pose(1.0, 0.0, 0.0, math.pi / 2, 0.5, 0.0)
    assert conv.odometry_to_sample(odom)[2]
    q = odom.pose.pose.orientation
    q.z, q.w = 0.5, 0.5
    _, _, ok, (_, _, yaw) = conv.odometry_to_sample(odom)
    assert not ok and math.isnan(yaw)


def test_a_malformed_scan_is_named_in_the_diagnostics(harness):
    """Only malformed scans come (range_min > range_max): the decision says there is no
    obstacle source, and the diagnostics' scan value says why (it said 'received')."""
    h = harness()
    _intervene(h)
    node = h.node
    bad = wall_scan_msg(104.05, 1.6)
    bad.range_min, bad.range_max = 9.0, 8.0
    n = node._bad_messages
    h.scan_pub.publish(bad)
    h.spin_until(lambda: node._bad_messages > n, what="the malformed scan")
    values = conv.diagnostic_values(node.diagnostic_status())
    assert values["scan"].startswith("malformed scan:") and "range limits" in values["scan"]


def test_the_override_stops_when_the_only_map_is_dropped(harness):
    """Obstacles from the map, intervening; a map in another frame drops it. The
    intervention is judged again at once (without an obstacle source: no override), as a
    dropped scan's is; overrides went on until the next step."""
    h = harness(obstacles="grid", vo_type="odometry", vo_topic="vo/odom")
    _publish_map(h, wall_map_msg(None))
    h.drive(100.0, 103.0)
    _publish_map(h, wall_map_msg(3.2 + 0.72 * 0.4))
    h.drive(103.0, 103.6)
    assert h.last()["why"] == "intervening"
    decisions = h.node._decisions
    _publish_map(h, wall_map_msg(3.6, frame="map"))
    assert h.node._grid is None and h.node._decisions == decisions + 1
    assert h.node._decision is None or not h.node._decision.intervening
    dropped = h.node._now()
    h.drive(103.6, 104.2)
    _spin(h)
    late = [conv.stamp_to_seconds(m.header.stamp) for m in h.overrides]
    assert max(late) <= dropped + 1e-9 and h.last()["why"] == "no_obstacle_source"


def test_a_map_too_big_to_read_in_a_callback_is_refused(harness):
    """A map of 49 million cells, within the field's own limit, held the layer's executor
    for 24 s (3 GB): no override, watchdog or diagnostics meanwhile. A map of more than
    MAX_MAP_CELLS is refused before it is read, and said; the last read's time is in the
    diagnostics."""
    from asgp_ros.nodes.shared_control_node import MAX_MAP_CELLS

    h = harness(obstacles="grid", vo_type="odometry", vo_topic="vo/odom")
    _publish_map(h, wall_map_msg(None))
    assert float(conv.diagnostic_values(h.node.diagnostic_status())["map_read_ms"]) >= 0.0
    big = OccupancyGrid()
    big.header.frame_id = "odom"
    big.info.resolution = 0.05
    big.info.width, big.info.height = 2001, MAX_MAP_CELLS // 2000
    big.info.origin.orientation.w = 1.0
    big.data = bytes([255]) * (big.info.width * big.info.height)  # all unknown
    _publish_map(h, big)
    diag = conv.diagnostic_values(h.node.diagnostic_status())
    assert h.node._grid is None and "at most 4,000,000" in diag["map"], diag["map"]


def test_decisions_go_on_after_the_clock_steps_back_less_than_a_second(harness):
    """use_sim_time, intervening; /clock steps back 0.8 s (less than the predictor's
    reset_jump_s) and the inputs go on. The watchdog took a decision 'ahead' of the clock
    for a recent one: no decision, status or override for a second."""
    h = harness()
    _intervene(h)
    n_status = len(h.status)
    h.drive(103.2, 104.2, wall=1.6)
    _spin(h)
    assert len(h.status) - n_status >= 5


def test_an_out_of_range_board_output_is_no_measurement(harness):
    """joy_applied at forward 3.0 (finite, out of range) was taken as the board's measured
    output arriving, so the stick's own samples stopped feeding the layer's predictor. It
    is refused and counted, and the stick goes on feeding."""
    h = harness()
    node = h.node
    h.drive(100.0, 101.0, wall=20.0)
    applied = h.test.create_publisher(Joy, "joy_applied", qos_profile_sensor_data)
    h.spin_until(lambda: applied.get_subscription_count() > 0, what="discovery")
    bad = node._bad_messages
    applied.publish(conv.joy_from_sample(101.0, 3.0, 0.0))
    h.spin_until(lambda: node.polled.drain() >= 0 and node._bad_messages > bad,
                 what="the sample refused")
    assert node._joy_source.measured_samples == 0
    fed = node.predictor.stats.joy_samples
    h.drive(101.0, 101.5, wall=20.0)
    assert node.predictor.stats.joy_samples > fed


def test_odometry_poses_in_another_frame_do_not_place_the_map(harness):
    """The VO's poses in 'map' would place the map's obstacles wrong: they are not taken
    (counted, logged); their velocities, in the chair's frame, still are."""
    h = harness(obstacles="grid", vo_type="odometry", vo_topic="vo/odom")
    node = h.node
    h.spin_until(lambda: h.odom_pub.get_subscription_count() > 0, what="discovery")
    h.clock(100.0)
    msg = conv.odometry_from_pose(100.0, 50.0, 0.0, 0.0, 0.5, 0.0)
    msg.header.frame_id = "map"
    n = node._vo_messages
    h.odom_pub.publish(msg)
    h.spin_until(lambda: node._vo_messages > n, what="odometry")
    assert node._poses_other_frame == 1 and node.predictor.stats.vo_samples == 1
    assert conv.diagnostic_values(node.diagnostic_status())["poses_other_frame"] == "1"


def test_a_map_is_read_off_the_executor(harness, monkeypatch):
    """A map's field is computed in a worker (1.6 s at MAX_MAP_CELLS, during which the
    layer's executor ran nothing: no scan, watchdog, decision or override). While a map is
    read the layer goes on deciding with the map it holds; a newer map supersedes one being
    read, and a map dropped meanwhile (another frame) is not brought back by the read."""
    import threading

    from asgp_ros.core import collision

    h = harness(obstacles="grid", vo_type="odometry", vo_topic="vo/odom")
    _publish_map(h, wall_map_msg(None))
    held = h.node._grid
    gate = threading.Event()
    real = collision.DistanceField.from_grid

    def slow(grid, *args, **kwargs):
        assert gate.wait(30.0)
        return real(grid, *args, **kwargs)

    monkeypatch.setattr(collision.DistanceField, "from_grid", staticmethod(slow))
    wall = wall_map_msg(3.2 + 0.72 * 0.4)  # the chair's path runs into it after 103 s
    h.map_pub.publish(wall)
    h.spin_until(lambda: h.node._map_reading, what="the map's read to start")
    decisions = h.node._decisions
    h.drive(100.0, 103.0)  # decided meanwhile, with the map held
    assert h.node._decisions > decisions and h.node._grid is held
    assert h.last()["why"] == "clear" and h.overrides == []
    values = conv.diagnostic_values(h.node.diagnostic_status())
    assert values["map"] == "received; a map is being read", values["map"]
    gate.set()
    h.spin_until(lambda: h.node._grid is not held, what="the map read")
    assert not h.node._map_reading and h.node._grid.points.shape[0] > 0
    h.drive(103.0, 103.6)
    assert h.last()["why"] == "intervening"
    # three maps while the worker is busy: the newest (clear) is the one held, and the one
    # superseded while it waited is not read at all
    gate.clear()
    reads = []
    monkeypatch.setattr(collision.DistanceField, "from_grid", staticmethod(
        lambda grid, *a, **kw: reads.append(grid) or slow(grid, *a, **kw)))
    wall_grid = h.node._grid
    h.map_pub.publish(wall_map_msg(3.0))
    # inside its read (the worker may not have begun when _map_reading is set: maps
    # published before it does supersede this one unread, which is right but not this case)
    h.spin_until(lambda: len(reads) == 1, what="the map's read to start")
    for wall_x in (2.5, None):
        generation = h.node._map_generation
        h.map_pub.publish(wall_map_msg(wall_x))
        h.spin_until(lambda g=generation: h.node._map_generation > g, what="the next map")
    gate.set()
    h.spin_until(lambda: not h.node._map_reading, what="the reads")
    assert h.node._grid is not wall_grid and h.node._grid.points.shape[0] == 0
    assert len(reads) == 2  # the first (already being read) and the newest
    # a map being read, then one in another frame: the read one is not installed
    gate.clear()
    h.map_pub.publish(wall_map_msg(3.0))
    h.spin_until(lambda: h.node._map_reading, what="the map's read to start")
    _publish_map(h, wall_map_msg(3.0, frame="map"))
    assert h.node._grid is None and not h.node._map_reading
    gate.set()
    h.node._map_worker.shutdown(wait=True)  # the read done, handed over
    h.spin_until(lambda: h.node._map_read is None, what="the read handed over")
    assert h.node._grid is None and "frame 'map'" in h.node._grid_problem


@pytest.mark.parametrize("step", [0.0, 0.9])
def test_no_decision_on_the_timeline_before_a_clock_step_back(harness, step):
    """The user slows from 0.8 to a crawl as a wall comes near, and at that moment the clock
    steps back 0.9 s (less than reset_jump_s: an NTP step, every stream stamped by it). The
    layer kept the old timeline's stick (0.8, stamped ahead of the new ones) and window: it
    decided on them, and said the stick had gone neutral while it was at 0.15. The step
    restarts the predictor and the stick is the new one: no override, no such decision."""
    h = harness()
    wall = 3.6

    def drive(t_from: float, t_to: float, fwd: float, speed: float, shift: float) -> None:
        stats = h.node.predictor.stats
        users = []
        rng = np.random.default_rng(int(t_from * 10))
        for i in range(round((t_to - t_from) / 0.05)):
            t = t_from + 0.05 * (i + 1)
            s = t - shift
            h.x += 0.05 * speed
            h.clock(s)
            n = stats.joy_samples + sum(stats.rejected.values())
            h.joy_pub.publish(conv.joy_from_sample(s, fwd, 0.0))
            h.spin_until(lambda n=n: stats.joy_samples + sum(stats.rejected.values()) > n,
                         what="joy")
            users.append(float(h.node._user[1][0]))  # the stick the layer holds the user's
            if i % 4 == 3:
                n = h.node._vo_messages
                h.vo_pub.publish(conv.twist_stamped_from_sample(
                    s, speed + rng.normal(0.0, 0.003), 0.0))
                h.spin_until(lambda n=n: h.node._vo_messages > n, what="vo")
            if i % 2 == 1:
                seen = h._scan_state()
                h.scan_pub.publish(wall_scan_msg(s, wall - h.x - 0.3))
                h.spin_until(lambda s_=seen: h._scan_state() != s_, what="scan")
        return users

    drive(100.0, 102.0, 0.8, 0.72, 0.0)
    n_status, n_overrides = len(h.status), len(h.overrides)
    users = drive(102.0, 104.0, 0.15, 0.135, step)
    assert len(h.overrides) == n_overrides
    assert users == [pytest.approx(0.15)] * len(users)  # it held 0.8 for 0.9 s
    # the stick was never neutral (0.8, then 0.15)
    after = [conv.diagnostic_values(st) for st in h.status[n_status:]]
    assert not [v for v in after if v["why"] == "neutral_stick"]


def test_the_mean_change_is_kept_in_constant_memory(harness):
    """The diagnostics' mean_change averaged a list of every intervening decision's change,
    which grew by 15 a second of intervening (54,000 an hour) and was averaged whole at each
    diagnostics period. It is a running sum: the same figure, in constant memory."""
    h = harness()
    changes = []
    decide = h.node._decide_now

    def recorded(now):
        decide(now)
        d = h.node._decision
        if d is not None and d.intervening:
            changes.append(d.change)
    h.node._decide_now = recorded
    _intervene(h)
    h.drive(104.0, 105.0, wall=1.4)
    assert len(changes) >= 10
    growing = [k for k, v in vars(h.node).items() if len(changes) <= (
        len(v) if isinstance(v, list) or (isinstance(v, deque) and v.maxlen is None) else 0)]
    assert not growing, growing
    diag = conv.diagnostic_values(h.node.diagnostic_status())
    assert float(diag["mean_change"]) == pytest.approx(np.mean(changes), abs=1e-3)


def test_a_decision_older_than_hold_s_is_not_sent_and_the_status_says_why(harness,
                                                                          monkeypatch):
    """A decision that took longer than hold_s (a dense scan on a loaded CPU) is rightly
    not sent; the status blamed a neutral stick, with the stick held at 0.3."""
    from asgp_ros.nodes import shared_control_node as scn

    h = harness()
    h.drive(100.0, 103.0, fwd=0.3, wall=20.0)
    node, real_now, lag = h.node, h.node._now, [0.0]
    node._now = lambda: None if (t := real_now()) is None else t + lag[0]
    real_decide = scn.decide

    def slow_decide(*args, **kwargs):
        out = real_decide(*args, **kwargs)
        lag[0] = 0.5  # the clock ran on while the decision was made (> hold_s 0.35)
        return out

    real_decide_now = node._decide_now

    def decide_now(now):
        try:
            real_decide_now(now)
        finally:
            lag[0] = 0.0

    monkeypatch.setattr(scn, "decide", slow_decide)
    node._decide_now = decide_now
    sent = len(h.overrides)
    h.drive(103.0, 104.0, fwd=0.3, wall=0.7)  # the stick at 0.3 throughout
    assert len(h.overrides) == sent
    messages = [s.message for s in h.status[-5:]]
    assert not any("neutral" in m for m in messages), messages
    # (no stick sample came in the half second the decision took: it is stale too)
    acted = [m for m in messages if not m.startswith("clear")]
    assert acted and all("went stale" in m or "beyond hold_s" in m for m in acted), messages


def test_slow_decisions_do_not_starve_the_layers_inputs(rclpy_context, model_file,  # noqa: F811
                                                        monkeypatch):
    """On the system clock, inputs at their real rates (joystick 20 Hz, VO 5 Hz, scans
    10 Hz), a wall 1.6 m ahead after 2 s, and every intervening decision taking 0.1 s (a
    loaded 2-core laptop). Each VO step and each scan decided in its own callback: 1.5 s
    of deciding a second, the executor fell behind its inputs, the scans it reached were
    stale, and the layer let go in the middle of the intervention ('no fresh scan or map',
    8 times in 5 s). The decisions asked for are made once the waiting inputs are read."""
    import threading

    import rclpy
    from geometry_msgs.msg import TwistStamped

    from asgp_ros.nodes import shared_control_node as scn

    node = SharedControlNode(context=rclpy_context, parameter_overrides=[
        Parameter("model_path", value=model_file), Parameter("laser_x", value=LASER_X),
        Parameter("joy_poll_period_s", value=0.005)])
    feeder = rclpy.create_node("sc_feeder", context=rclpy_context)
    probe = rclpy.create_node("sc_probe", context=rclpy_context)
    executor = SingleThreadedExecutor(context=rclpy_context)
    executor.add_node(node)
    executor.add_node(probe)
    joy = feeder.create_publisher(Joy, "joy", qos_profile_sensor_data)
    vo = feeder.create_publisher(TwistStamped, "vo/twist", qos_profile_sensor_data)
    scan = feeder.create_publisher(LaserScan, "scan", qos_profile_sensor_data)
    whys: list[str] = []
    probe.create_subscription(DiagnosticStatus, "shared_control/status",
                              lambda m: whys.append(conv.diagnostic_values(m)["why"]),
                              QoSProfile(depth=200))
    deadline = time.monotonic() + 10.0
    while not all(p.get_subscription_count() > 0 for p in (joy, vo, scan)):
        assert time.monotonic() < deadline, "discovery"
        executor.spin_once(timeout_sec=0.01)
    real_decide = scn.decide

    def slow_decide(*args, **kwargs):
        d = real_decide(*args, **kwargs)
        if d.command is not None:
            time.sleep(0.1)
        return d

    monkeypatch.setattr(scn, "decide", slow_decide)
    stop = threading.Event()

    def feed() -> None:
        rng = np.random.default_rng(0)
        start, i = time.monotonic(), 0
        while not stop.is_set():
            now = node.get_clock().now().nanoseconds * 1e-9
            joy.publish(conv.joy_from_sample(now, 0.8, 0.0))
            if i % 4 == 0:
                vo.publish(conv.twist_stamped_from_sample(now, 0.5 + rng.normal(0, 0.003), 0.0))
            if i % 2 == 0:
                scan.publish(wall_scan_msg(now, 20.0 if i < 40 else 1.6))
            i += 1
            time.sleep(max(0.0, start + 0.05 * i - time.monotonic()))

    thread = threading.Thread(target=feed)
    thread.start()
    try:
        end = time.monotonic() + 6.0
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.01)
    finally:
        stop.set()
        thread.join()
        executor.shutdown()
        feeder.destroy_node()
        probe.destroy_node()
    values = conv.diagnostic_values(node.diagnostic_status())
    node.destroy_node()
    assert "intervening" in whys, whys
    after = whys[whys.index("intervening"):]
    assert after.count("intervening") >= 15, after
    assert not [w for w in after if w in ("stale_input", "no_obstacle_source")], after
    assert values["scans_old"] == "0", values


# ---- from an attack on the diagnostics: each a false value found, now a regression test --


def test_no_safe_command_is_a_warning_in_the_diagnostics_too(harness):
    """Every candidate likely to touch: shared_control/status said WARN, /diagnostics OK
    for the same decision."""
    h = harness()
    h.drive(100.0, 103.0, fwd=0.3, wall=20.0)
    h.drive(103.0, 104.0, fwd=0.3, wall=0.3)
    assert h.last()["why"] == "no_safe_command", h.last()
    assert h.status[-1].level == DiagnosticStatus.WARN
    assert h.node.diagnostic_status().level == DiagnosticStatus.WARN


def test_a_stick_released_while_intervening_is_said_not_starting(harness):
    """The user lets go while the layer intervenes: the diagnostics said 'no decision
    yet', why 'starting', after dozens of decisions."""
    h = harness()
    _intervene(h)
    h.joy_pub.publish(conv.joy_from_sample(104.0, 0.0, 0.0))
    stats = h.node.predictor.stats
    n = stats.joy_samples
    h.spin_until(lambda: stats.joy_samples > n, what="neutral joy")
    status = h.node.diagnostic_status()
    values = conv.diagnostic_values(status)
    assert values["why"] == "neutral_stick", (status.message, values["why"])
    assert "override stopped" in status.message


@pytest.mark.parametrize(("then", "said"), [
    ((103.0, 105.0), "stale: the last taken 2.0"),
    ((50.0, 52.0), "the last taken is stamped 5")], ids=["silent", "clock-back"])
def test_the_scan_value_says_why_the_scan_held_is_not_used(harness, then, said):
    """The laser goes silent for 2 s (or /clock steps back 54 s and it is silent): why
    'no_obstacle_source', and 'scan: received'. The scan held is stale, or stamped ahead
    of the clock, and the value says so."""
    h = harness(scan_timeout_s=0.3)
    h.drive(100.0, 104.0 if then[0] < 100.0 else 103.0, wall=1.6)
    h.drive(*then, wall=1.6, scan=False)
    values = conv.diagnostic_values(h.node.diagnostic_status())
    assert values["why"] == "no_obstacle_source"
    assert values["scan"].startswith(said), values["scan"]


def test_overriding_s_is_the_time_the_overrides_cover(harness):
    """overriding_s (the demo report's time overriding, and from it the share of the
    drive untouched) was overrides_sent / override_rate_hz: 3.5 s in 2 s of intervening,
    an override being sent at each decision too, besides the 20 Hz timer."""
    h = harness()
    _intervene(h)
    before = float(conv.diagnostic_values(h.node.diagnostic_status())["overriding_s"])
    sent = h.node._overrides_sent
    h.drive(104.0, 106.0, wall=1.6)  # 2 s more
    assert h.last()["why"] == "intervening"
    values = conv.diagnostic_values(h.node.diagnostic_status())
    assert int(values["overrides_sent"]) - sent > 2.0 * h.node.params.override_rate_hz
    assert 1.5 <= float(values["overriding_s"]) - before <= 2.0 + 0.05


def test_overrides_that_reach_no_one_are_an_error(harness):
    """override_topic misspelt (or no bridge running): the layer intervened before a wall,
    counted its overrides as sent, and its diagnostics said OK."""
    h = harness()
    h.drive(100.0, 103.0, wall=20.0)
    assert h.node.diagnostic_status().level == DiagnosticStatus.OK
    (sub,) = [s for s in h.test.subscriptions if s.topic_name == "/joy_override"]
    h.test.destroy_subscription(sub)  # the bridge gone
    h.spin_until(lambda: h.node.override_pub.get_subscription_count() == 0, what="no reader")
    status = h.node.diagnostic_status()
    assert status.level == DiagnosticStatus.WARN and "nothing subscribes" in status.message
    h.drive(103.0, 104.5, wall=1.6)
    assert h.last()["why"] == "intervening"
    status = h.node.diagnostic_status()
    assert status.level == DiagnosticStatus.ERROR, status.message
    assert conv.diagnostic_values(status)["override_subscribers"] == "0"


def test_a_reader_of_the_overrides_that_is_no_bridge_is_not_counted_as_one(harness):
    """The layer in /chair1, the bridge in / (its override topic left in the namespace):
    the predictor that the launch file starts beside it reads /chair1/joy_override too, and
    the layer counted it: OK, 'intervening', while no override reached the board. A reader
    counts as a bridge when it also publishes a joystick, as serial_bridge_node does."""
    h = harness()
    h.drive(100.0, 103.0, wall=20.0)
    assert h.node.diagnostic_status().level == DiagnosticStatus.OK
    assert conv.diagnostic_values(h.node.diagnostic_status())["override_bridges"] == "1"
    from rclpy import create_node

    reader = create_node("predictor_node", namespace="chair1", context=h.test.context)
    reader.create_subscription(Joy, "/joy_override", lambda _: None, 10)
    h.executor.add_node(reader)
    (sub,) = [s for s in h.test.subscriptions if s.topic_name == "/joy_override"]
    h.test.destroy_subscription(sub)  # the bridge's gone; the predictor still reads
    h.test.destroy_publisher(h.bridge_applied)
    from asgp_ros.nodes.runtime import override_readers

    h.spin_until(lambda: override_readers(h.node, "/joy_override")
                 == ([], ["/chair1/predictor_node"]), what="the reader alone")
    status = h.node.diagnostic_status()
    assert status.level == DiagnosticStatus.WARN, status.message
    assert "no bridge subscribes" in status.message and "/chair1/predictor_node" in \
        status.message
    h.drive(103.0, 104.5, wall=1.6)
    assert h.last()["why"] == "intervening"
    status = h.node.diagnostic_status()
    assert status.level == DiagnosticStatus.ERROR, status.message
    values = conv.diagnostic_values(status)
    assert values["override_subscribers"] == "1" and values["override_bridges"] == "0"
    h.executor.remove_node(reader)
    reader.destroy_node()


# ---- from an attack on units, frames and signs: each a break found, now a test ----------


def _drive_turning(h, t_from: float, t_to: float, raw_fwd: float, raw_turn: float,
                   wall: float) -> None:
    """As Harness.drive, with the stick's raw turn axis ``raw_turn`` on joy."""
    stats = h.node.predictor.stats
    rng = np.random.default_rng(int(t_from * 10))
    for i in range(round((t_to - t_from) / 0.05)):
        t = t_from + 0.05 * (i + 1)
        h.clock(t)
        n = stats.joy_samples
        h.joy_pub.publish(conv.joy_from_sample(t, raw_fwd, raw_turn))
        h.spin_until(lambda n=n: stats.joy_samples > n, what="joy")
        if i % 4 == 3:
            n = h.node._vo_messages
            h.vo_pub.publish(conv.twist_stamped_from_sample(
                t, 0.9 * raw_fwd + rng.normal(0, 0.003), rng.normal(0, 0.003)))
            h.spin_until(lambda n=n: h.node._vo_messages > n, what="vo")
        if i % 2 == 1:
            seen = h._scan_state()
            h.scan_pub.publish(wall_scan_msg(t, wall))
            h.spin_until(lambda s=seen: h._scan_state() != s, what="scan")
    h.settle()


def test_overrides_are_written_in_the_convention_of_joy(harness):
    """joy_axes '0,-1' (this joy reads + right): the user turns left (joy -0.2) towards a
    wall; the layer kept the turn, +0.2 left in its own units, and wrote it as joy +0.2,
    which the bridge (its joy's units) drove as a right turn."""
    h = harness(joy_axes="0,-1")
    _drive_turning(h, 100.0, 103.0, 0.8, -0.2, wall=20.0)
    assert h.overrides == []
    _drive_turning(h, 103.0, 104.0, 0.8, -0.2, wall=1.6)
    last = h.last()
    assert last["why"] == "intervening" and h.overrides, last
    assert float(last["user_turn"]) == pytest.approx(0.2)
    command_turn = float(last["command_turn"])
    assert command_turn > 0.0  # (left, as the user's)
    assert float(h.overrides[-1].axes[1]) == pytest.approx(-command_turn, abs=1e-3)


def test_an_override_is_read_and_written_through_joy_axes():
    from asgp_ros.recording.bags import parse_joy_axes

    for spec in ("0,1", "0,-1", "1,0", "-2,0"):
        axes = parse_joy_axes(spec)
        msg = conv.joy_from_sample(1.0, 0.6, -0.25, axes=axes)
        assert conv.joy_to_override(msg, axes) == pytest.approx((0.6, -0.25))
        assert conv.joy_command(msg, axes)[1] == pytest.approx([0.6, -0.25])


def _drive_odometry(h, t_from: float, t_to: float, x_true: float, offset: float,
                    pose_var: float, fwd: float = 0.8) -> float:
    """The joystick at 20 Hz; vo/odom at 5 Hz as vo_node publishes it: the pose ``offset``
    behind the chair's true x, its covariance ``pose_var``; the true x at the end."""
    stats = h.node.predictor.stats
    rng = np.random.default_rng(int(t_from * 10))
    for i in range(round((t_to - t_from) / 0.05)):
        t = t_from + 0.05 * (i + 1)
        x_true += 0.05 * 0.9 * fwd
        h.clock(t)
        n = stats.joy_samples
        h.joy_pub.publish(conv.joy_from_sample(t, fwd, 0.0))
        h.spin_until(lambda n=n: stats.joy_samples > n, what="joy")
        if i % 4 == 3:
            n = h.node._vo_messages
            h.odom_pub.publish(conv.odometry_with_covariance(
                t, x_true - offset, 0.0, 0.0, np.diag(np.full(3, pose_var)),
                0.9 * fwd + rng.normal(0.0, 0.003), 0.0, np.eye(6) * 1e-4))
            h.spin_until(lambda n=n: h.node._vo_messages > n, what="vo")
    h.settle()
    return x_true


def test_a_map_is_dropped_when_the_odometry_re_initialises(harness):
    """obstacles 'grid': the VO loses tracking and re-initialises; vo_node held its pose
    while the chair moved (1 m here) and added 1 m^2 to the pose's variance. The map, placed
    with that pose, put a wall 1.2 m ahead of the chair 1 m further on: judged clear, p 0,
    diagnostics OK. The jump drops the map: no obstacle source, and the diagnostics say why."""
    h = harness(obstacles="grid", vo_type="odometry", vo_topic="vo/odom")
    _publish_map(h, wall_map_msg(None))
    x = _drive_odometry(h, 100.0, 102.0, 0.0, 0.0, 1e-4)
    wall_x = x + 0.5 + 1.0 + 0.6 + 1.2  # 1.2 m ahead of the front after 0.5 s and the gap
    old_map = wall_map_msg(wall_x)
    old_map.header.stamp = conv.seconds_to_stamp(102.0)  # made with the poses before
    _publish_map(h, old_map)
    x = _drive_odometry(h, 102.0, 102.5, x, 0.0, 1e-4)
    assert h.last()["why"] == "clear"
    x += 1.0  # the tracking gap: the chair moved 1 m, the pose held
    x = _drive_odometry(h, 102.5, 103.1, x, 1.0, 1.0 + 1e-4)
    last = h.last()
    assert last["why"] == "no_obstacle_source", last
    values = conv.diagnostic_values(h.node.diagnostic_status())
    assert "re-initialised" in values["map"] and values["odometry_reinitialised"] == "1"
    # the mapper sends the same map again (stamped before the re-initialisation): it was
    # installed again, and the wall judged clear again
    _publish_map(h, old_map)
    assert h.node._grid is None and "before the odometry re-initialised" in h.node._grid_problem
    # a map of the new alignment (stamped after) is taken
    new_map = wall_map_msg(wall_x - 1.0)
    new_map.header.stamp = conv.seconds_to_stamp(103.1)
    _publish_map(h, new_map)
    assert h.node._grid is not None


def test_an_upside_down_laser_is_read_mirrored(harness):
    """A laser mounted upside down (rolled by pi) has no yaw that describes it: a wall on
    the chair's right, which it reports at positive angles, was placed on the left."""
    msg = wall_scan_msg(100.0, 1.0)
    a0, inc = float(msg.angle_min), float(msg.angle_increment)
    ranges = np.full(len(msg.ranges), np.inf)
    beams = a0 + inc * np.arange(ranges.size)
    ranges[np.abs(beams - 1.2) < 0.05] = 0.8  # a post at +1.2 rad in the laser's own frame
    msg.ranges = ranges.tolist()
    for upside_down, side in ((False, 1.0), (True, -1.0)):
        scan = conv.scan_from_msg(msg, upside_down=upside_down)
        angles = scan.angle_min + scan.angle_increment * np.arange(scan.ranges.size)
        at = angles[np.isfinite(scan.ranges)]
        assert at.size and np.all(np.abs(at - side * 1.2) < 0.06), (upside_down, at)
    h = harness(laser_upside_down=True)
    assert h.node.params.laser_upside_down
    h.clock(100.0)
    seen = h._scan_state()
    msg.header.stamp = conv.seconds_to_stamp(100.0)
    h.scan_pub.publish(msg)
    h.spin_until(lambda: h._scan_state() != seen, what="scan")
    held = h.node._scan[1]
    angles = held.angle_min + held.angle_increment * np.arange(held.ranges.size)
    assert np.all(np.abs(angles[np.isfinite(held.ranges)] + 1.2) < 0.06)


def test_a_pose_said_lost_by_a_variance_that_is_no_number_drops_the_map(harness):
    """A source that marks its tracking loss with an infinite pose variance, then returns
    to a small one, re-initialised as surely as vo_node's +1 m^2: the rise was not seen (a
    non-finite variance was skipped, the old baseline kept) and the map, placed with the
    poses before, kept a wall 1.2 m ahead judged clear. Now dropped at the loss; a map
    stamped before the return is refused, one after it taken. A source whose variance is
    never a number (-1, 'unknown') keeps its map."""
    h = harness(obstacles="grid", vo_type="odometry", vo_topic="vo/odom")
    _publish_map(h, wall_map_msg(None))
    x = _drive_odometry(h, 100.0, 102.0, 0.0, 0.0, 1e-4)
    wall_x = x + 0.5 + 1.0 + 0.6 + 1.2
    old_map = wall_map_msg(wall_x)
    old_map.header.stamp = conv.seconds_to_stamp(102.0)
    _publish_map(h, old_map)
    x = _drive_odometry(h, 102.0, 102.5, x, 0.0, 1e-4)
    assert h.last()["why"] == "clear"
    x = _drive_odometry(h, 102.5, 102.7, x, 0.0, math.inf)  # lost: the pose held
    assert h.node._grid is None and "lost its pose" in h.node._grid_problem
    x += 1.0
    x = _drive_odometry(h, 102.7, 103.3, x, 1.0, 1e-4)  # back, 1 m off its old alignment
    assert h.last()["why"] == "no_obstacle_source", h.last()
    values = conv.diagnostic_values(h.node.diagnostic_status())
    assert values["odometry_reinitialised"] == "1"
    _publish_map(h, old_map)
    assert h.node._grid is None and "before the odometry re-initialised" in h.node._grid_problem
    new_map = wall_map_msg(wall_x - 1.0)
    new_map.header.stamp = conv.seconds_to_stamp(103.3)
    _publish_map(h, new_map)
    assert h.node._grid is not None

    unknown = harness(obstacles="grid", vo_type="odometry", vo_topic="vo/odom")
    _publish_map(unknown, wall_map_msg(None))
    _drive_odometry(unknown, 100.0, 101.0, 0.0, 0.0, -1.0)
    assert unknown.node._grid is not None
    assert conv.diagnostic_values(unknown.node.diagnostic_status())[
        "odometry_reinitialised"] == "0"


@pytest.mark.parametrize("restart", ["jump", "variance_falls"])
def test_a_map_is_dropped_when_the_odometry_restarts(harness, restart):
    """vo_node restarted starts its odometry again at (0, 0, 0) with no variance: only a
    rise of the variance was a new alignment, and the map, placed with the poses before,
    was kept: a wall judged clear (p 0) until the chair was 0.3 m into it. A pose that
    jumps further than the chair can move, or a variance that falls at once, drops it."""
    h = harness(obstacles="grid", vo_type="odometry", vo_topic="vo/odom")
    _publish_map(h, wall_map_msg(None))
    offset = 0.0 if restart == "variance_falls" else -3.0  # (the pose 3 m ahead of x)
    x = _drive_odometry(h, 100.0, 102.0, 0.0, offset, 2.0)
    wall_x = x - offset + 0.5 + 0.6 + 1.2 + 10.0  # far ahead of the old alignment's chair
    old_map = wall_map_msg(wall_x)
    old_map.header.stamp = conv.seconds_to_stamp(102.0)
    _publish_map(h, old_map)
    x = _drive_odometry(h, 102.0, 102.5, x, offset, 2.0)
    assert h.last()["why"] == "clear" and h.node._grid is not None
    # restarted: its origin where the chair is now (the pose jumps back 3 m; or, in place,
    # only its variance falls from 2.0 to 0)
    x = _drive_odometry(h, 102.5, 103.1, x, x if restart == "jump" else offset, 1e-4)
    assert h.node._grid is None, h.node._grid_problem
    assert ("jumped" if restart == "jump" else "fell by") in h.node._grid_problem
    assert h.last()["why"] == "no_obstacle_source", h.last()
    values = conv.diagnostic_values(h.node.diagnostic_status())
    assert values["odometry_reinitialised"] == "1"
    _publish_map(h, old_map)  # sent again: refused
    assert h.node._grid is None and "before the odometry re-initialised" in h.node._grid_problem


def test_a_layer_started_after_a_re_initialisation_refuses_a_map_made_before(harness):
    """A layer restarted after the odometry re-initialised took back the map (latched,
    stamped before) that the layer before had dropped: clear until the chair was 0.4 m
    into the wall. The first pose's variance of 0.25 or more says the odometry may have
    re-initialised before: a map stamped before it is refused, one after it taken; with a
    small variance the older map is taken."""
    h = harness(obstacles="grid", vo_type="odometry", vo_topic="vo/odom")
    old_map = wall_map_msg(30.0)
    old_map.header.stamp = conv.seconds_to_stamp(90.0)
    _publish_map(h, old_map)  # latched: it arrives before any pose
    assert h.node._grid is not None
    _drive_odometry(h, 100.0, 100.5, 0.0, 0.0, 1.0 + 1e-4)
    assert h.node._grid is None and "may have re-initialised before" in h.node._grid_problem
    assert conv.diagnostic_values(h.node.diagnostic_status())["odometry_reinitialised"] == "0"
    _publish_map(h, old_map)
    assert h.node._grid is None
    new_map = wall_map_msg(30.0)
    new_map.header.stamp = conv.seconds_to_stamp(100.5)
    _publish_map(h, new_map)
    assert h.node._grid is not None

    fresh = harness(obstacles="grid", vo_type="odometry", vo_topic="vo/odom")
    _publish_map(fresh, old_map)
    _drive_odometry(fresh, 100.0, 100.5, 0.0, 0.0, 1e-4)
    assert fresh.node._grid is not None, fresh.node._grid_problem


def test_vo_nodes_own_pose_covariance_never_reads_as_a_re_initialisation(harness):
    """vo_node's pose covariance over a drive with one tracking loss (its +1 rad^2 of yaw),
    forward then reversing: the position's variance grows with the distance times the yaw's
    (0.27 m^2 a pose 0.9 m after the loss) and falls when the chair reverses (2.28 at
    once); the layer took either for a re-initialisation and dropped the map, at every pose
    from then on. Only the yaw's variance counts: the map made after the loss is kept."""
    from asgp_ros.vo.extrinsics import CameraExtrinsic
    from asgp_ros.vo.odometry import Status, VOResult
    from asgp_ros.vo.planar import PlanarOdometry

    h = harness(obstacles="grid", vo_type="odometry", vo_topic="vo/odom")
    ext = CameraExtrinsic()
    planar = PlanarOdometry(ext)
    Tbc = ext.T_base_optical
    pose = np.eye(4)
    stats = h.node.predictor.stats
    k = 0
    largest = 0.0
    for i in range(int(16.0 / 0.05)):
        t = 100.0 + 0.05 * (i + 1)
        fwd = 0.8 if i < 160 else -0.8  # 8 s forward, then 8 s back
        h.clock(t)
        n = stats.joy_samples
        h.joy_pub.publish(conv.joy_from_sample(t, fwd, 0.0))
        h.spin_until(lambda n=n: stats.joy_samples > n, what="joy")
        if i % 4 != 3:
            continue
        step = np.eye(4)
        step[0, 3] = 0.2 * 0.9 * fwd
        motion = np.linalg.inv(Tbc) @ step @ Tbc
        pose = pose @ motion
        k += 1
        x, y, yaw, cov = planar.update(VOResult(
            status=Status.OK, stamp=t, pose=pose.copy(), motion=motion,
            covariance=np.diag([1e-6] * 3 + [1e-7] * 3), dt=0.2, reset=(k == 5)))
        largest = max(largest, float(cov[1, 1]))
        n = h.node._vo_messages
        h.odom_pub.publish(conv.odometry_with_covariance(t, x, y, yaw, cov, 0.9 * fwd, 0.0,
                                                         np.eye(6) * 1e-4))
        h.spin_until(lambda n=n: h.node._vo_messages > n, what="vo")
        if k == 8:  # a map of the alignment after the loss
            new_map = wall_map_msg(None)
            new_map.header.stamp = conv.seconds_to_stamp(t)
            _publish_map(h, new_map)
        if k >= 8:
            assert h.node._grid is not None, (k, h.node._grid_problem)
    assert largest > 10.0  # (the lateral variance did grow, with the yaw's 1 rad^2)
    assert conv.diagnostic_values(h.node.diagnostic_status())["odometry_reinitialised"] == "1"
