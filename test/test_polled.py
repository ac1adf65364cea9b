"""Polled subscriptions (asgp_ros.nodes.polled): out of the executor's wait set, drained
in the order received, with each message's arrival, nothing lost below the queue's depth."""

from __future__ import annotations

import time

import pytest

pytest.importorskip("rclpy")

from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Joy

from asgp_ros.nodes import conversions as conv
from asgp_ros.nodes.polled import DEPTH, Arrival, PolledInputs
from asgp_ros.nodes.qos_watch import QosWatch

pytestmark = pytest.mark.ros

RELIABLE = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)


class Rig:
    """A node with polled subscriptions ``a`` and ``b`` and a test node publishing them."""

    def __init__(self, context, period_s: float, sim_time: bool = False,
                 qos: QoSProfile = RELIABLE) -> None:
        import rclpy

        self.node = rclpy.create_node(
            "polled", context=context,
            parameter_overrides=[Parameter("use_sim_time", value=sim_time)])
        self.test = rclpy.create_node("polled_test", context=context)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self.executor.add_node(self.test)
        self.got: list[tuple[str, float, Arrival]] = []
        self.inputs = PolledInputs(self.node, QosWatch(self.node), period_s)
        self.subs = {}
        for name in ("a", "b"):
            self.subs[name] = self.inputs.subscription(
                Joy, name, lambda msg, arrival, name=name: self.got.append(
                    (name, round(conv.stamp_to_seconds(msg.header.stamp), 6), arrival)),
                qos)
        pub_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=2 * DEPTH,
                             reliability=qos.reliability)
        self.pubs = {name: self.test.create_publisher(Joy, name, pub_qos)
                     for name in ("a", "b")}
        self.clock_pub = self.test.create_publisher(Clock, "/clock", QoSProfile(depth=10))
        self.spin_until(lambda: all(p.get_subscription_count() > 0
                                    for p in self.pubs.values()), "discovery")

    def spin_until(self, cond, what: str, timeout: float = 5.0) -> None:
        deadline = time.monotonic() + timeout
        while not cond():
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out waiting for {what}")
            self.executor.spin_once(timeout_sec=0.01)

    def publish(self, name: str, stamp: float) -> None:
        self.pubs[name].publish(conv.joy_from_sample(stamp, 0.5, 0.0))

    def drain_until(self, count: int) -> None:
        """Drain until ``count`` messages were handed over (DDS delivers asynchronously)."""
        deadline = time.monotonic() + 5.0
        while len(self.got) < count:
            assert time.monotonic() < deadline, f"{len(self.got)} of {count} arrived"
            self.inputs.drain()
            time.sleep(0.005)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.test.destroy_node()


def test_the_executor_never_runs_a_polled_subscription(rclpy_context):
    """Spinning hands nothing over (the executor neither waits on nor takes the polled
    messages, and their callback, which raises, never runs); a drain hands over all of them,
    in order."""
    rig = Rig(rclpy_context, period_s=600.0)
    try:
        # what rclpy's executor asks of each entity before putting it in its wait set
        assert not any(rig.executor.can_execute(sub) for sub in rig.subs.values())
        for i in range(20):
            rig.publish("a", 1.0 + i)
        for _ in range(50):
            rig.executor.spin_once(timeout_sec=0.001)
        assert rig.got == []
        rig.drain_until(20)
        assert [stamp for _, stamp, _ in rig.got] == [1.0 + i for i in range(20)]
        assert rig.inputs.taken == 20 and rig.inputs.full_queues == 0
        assert rig.inputs.values() == {"polled_messages": "20", "polled_queue_full": "0"}
    finally:
        rig.close()


def test_the_timer_drains_on_its_own(rclpy_context):
    rig = Rig(rclpy_context, period_s=0.01)
    try:
        rig.publish("a", 1.0)
        rig.spin_until(lambda: len(rig.got) == 1, "the timer's drain")
    finally:
        rig.close()


def test_two_topics_are_handed_over_in_the_order_received(rclpy_context):
    rig = Rig(rclpy_context, period_s=600.0)
    try:
        sent = []
        for i in range(30):
            name = "ab"[i % 3 == 0]
            rig.publish(name, 1.0 + i)
            sent.append((name, 1.0 + i))
            time.sleep(0.001)
        rig.drain_until(30)
        assert [(name, stamp) for name, stamp, _ in rig.got] == sent
    finally:
        rig.close()


def test_each_message_arrives_when_it_was_received_not_when_drained(rclpy_context):
    """On the system clock the arrival is the reception's, not the drain's: two messages
    0.15 s apart, drained together 0.2 s later, keep their times (what the node stamps a
    message sent without a stamp with)."""
    rig = Rig(rclpy_context, period_s=600.0)
    try:
        rig.inputs.drain()
        first = time.time()
        rig.publish("a", 0.0)
        time.sleep(0.15)
        rig.publish("b", 0.0)
        time.sleep(0.2)
        drained = time.time()
        rig.drain_until(2)
        (_, _, a), (_, _, b) = rig.got
        assert a.now is not None and b.now is not None
        assert first - 0.01 <= a.now <= first + 0.05
        assert b.now - a.now == pytest.approx(0.15, abs=0.05)
        assert drained - b.now >= 0.15
        assert b.monotonic - a.monotonic == pytest.approx(b.now - a.now, abs=0.01)
        assert b.perf - a.perf == pytest.approx(b.now - a.now, abs=0.01)
    finally:
        rig.close()


def _set_clock(rig: Rig, t: float) -> None:
    rig.clock_pub.publish(Clock(clock=conv.seconds_to_stamp(t)))
    rig.spin_until(lambda: rig.node.get_clock().now().nanoseconds == round(t * 1e9), "/clock")


def test_on_a_simulated_clock_a_message_never_arrives_before_the_previous_drain(
        rclpy_context):
    """/clock may stand still or run at any rate: a message received 0.1 s (of the wall
    clock) before a drain, while /clock stood at 500 s, arrived at 500 s; when /clock has
    moved on by 1 s since the previous drain, 0.1 s before it; after /clock went back (a
    bag played again), 0.1 s before the drain."""
    rig = Rig(rclpy_context, period_s=600.0, sim_time=True)
    try:
        for previous, t, want in ((500.0, 500.0, 500.0), (500.0, 501.0, 500.9),
                                  (501.0, 200.0, 199.9)):
            _set_clock(rig, previous)
            rig.inputs.drain()
            _set_clock(rig, t)
            rig.got.clear()
            sent = time.monotonic()
            rig.publish("a", 0.0)
            time.sleep(0.1)
            rig.drain_until(1)
            # (a loaded machine drains late: the message is older by then, by wall clock)
            late = max(time.monotonic() - sent - 0.1, 0.0)
            low = max(want - late, previous) if t >= previous else want - late
            assert low - 0.03 <= rig.got[0][2].now <= want + 0.03, (previous, t, late)
    finally:
        rig.close()


def test_a_full_queue_keeps_the_newest_and_is_counted(rclpy_context, capfd):
    """More than DEPTH messages between two drains: the newest DEPTH are handed over, and
    the drain counts the queue full and says so in the log."""
    rig = Rig(rclpy_context, period_s=600.0)
    try:
        for i in range(DEPTH + 10):
            rig.publish("a", 1.0 + i)
        deadline = time.monotonic() + 5.0
        # wait until the newest one is there (reliable: all are delivered, the oldest go)
        while not rig.got or rig.got[-1][1] != float(DEPTH + 10):
            assert time.monotonic() < deadline
            time.sleep(0.05)
            rig.inputs.drain()
        stamps = [stamp for _, stamp, _ in rig.got]
        assert stamps == [11.0 + i for i in range(DEPTH)]
        assert rig.inputs.full_queues == 1
        assert "/a: 1000 messages waiting at one read, its queue full" in capfd.readouterr().err
    finally:
        rig.close()


def test_a_sender_faster_than_the_reads_cannot_keep_a_drain_going(rclpy_context):
    """A queue refilled as fast as it is read (a flood): one drain takes at most DEPTH
    messages of it, counts the queue full and returns; the rest wait for the next drain."""
    from asgp_ros.nodes.polled import _Polled

    class Endless:  # a subscription handle whose queue is never empty
        taken = 0

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def take_message(self, msg_type, raw):
            Endless.taken += 1
            stamp = conv.seconds_to_stamp(float(Endless.taken))
            msg = Joy()
            msg.header.stamp = stamp
            return msg, {"received_timestamp": time.time_ns()}

    class FakeSub:
        handle = Endless()
        msg_type = Joy
        raw = False
        topic_name = "/flood"

    rig = Rig(rclpy_context, period_s=600.0)
    try:
        got = []
        rig.inputs._polled[:] = [_Polled(FakeSub(), lambda msg, arrival: got.append(msg))]
        assert rig.inputs.drain() == DEPTH
        assert len(got) == DEPTH and rig.inputs.full_queues == 1
        assert rig.inputs.drain() == DEPTH  # the next drain goes on from there
        assert got[-1].header.stamp.sec == 2 * DEPTH
    finally:
        rig.close()


def test_a_polled_subscription_keeps_the_qos_asked_but_its_history(rclpy_context):
    """The subscription is made with the profile asked (here best effort, a deadline),
    its history the last DEPTH messages whatever the profile said (KEEP_ALL, depth 5)."""
    import rclpy
    from rclpy.duration import Duration

    node = rclpy.create_node("polled_qos", context=rclpy_context)
    try:
        asked = QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=5,
                           reliability=ReliabilityPolicy.BEST_EFFORT,
                           deadline=Duration(seconds=2))
        sub = PolledInputs(node, QosWatch(node), 600.0).subscription(
            Joy, "q", lambda msg, arrival: None, asked)
        made = sub.qos_profile
        assert made.history == HistoryPolicy.KEEP_LAST and made.depth == DEPTH
        assert made.reliability == ReliabilityPolicy.BEST_EFFORT
        assert made.deadline == Duration(seconds=2)
    finally:
        node.destroy_node()


def test_period_zero_keeps_a_callback_per_message(rclpy_context):
    rig = Rig(rclpy_context, period_s=0.0)
    try:
        assert rig.inputs.timer is None
        rig.publish("a", 1.0)
        rig.publish("b", 2.0)
        rig.spin_until(lambda: len(rig.got) == 2, "the callbacks")
        assert sorted(stamp for _, stamp, _ in rig.got) == [1.0, 2.0]
        assert rig.inputs.drain() == 0
    finally:
        rig.close()


@pytest.mark.parametrize("period", [-0.1, float("nan")])
def test_a_bad_period_is_refused(rclpy_context, period):
    import rclpy

    node = rclpy.create_node("polled_bad", context=rclpy_context)
    try:
        with pytest.raises(ValueError, match="period_s"):
            PolledInputs(node, QosWatch(node), period)
    finally:
        node.destroy_node()
