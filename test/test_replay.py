"""Tests of bag replay (asgp_ros.recording.replay, `asgp replay`).

Message conversion is tested on ROS 1 and ROS 2 bags written here with rosbags (Joy with
a ROS 1 header ``seq``, Odometry with fixed-size covariance arrays, Image with a byte
payload, and a custom type that is not installed). Playback is tested across processes:
``asgp replay`` in a subprocess, a subscriber in the test.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from asgp_ros.recording.replay import ReplayConfig, message_class, to_ros2

N_MSGS = 20
T0_NS = 1_700_000_000_000_000_000
PERIOD_NS = 50_000_000  # 20 Hz: the bags last ~1 s
GIZMO = "uint32 count\nstring label\n"


def _typestore(ros1: bool):
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_JAZZY)
    store.register(get_types_from_msg(GIZMO, "acme_msgs/msg/Gizmo"))
    return store


def _messages(store, ros1: bool):
    """(topic, msgtype, t_ns, message) of the test bags."""
    T = store.types
    Time = T["builtin_interfaces/msg/Time"]

    def header(i: int, t_ns: int, frame: str):
        stamp = Time(sec=t_ns // 10**9, nanosec=t_ns % 10**9)
        if ros1:
            return T["std_msgs/msg/Header"](seq=i, stamp=stamp, frame_id=frame)
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    P, Q, V3 = T["geometry_msgs/msg/Point"], T["geometry_msgs/msg/Quaternion"], \
        T["geometry_msgs/msg/Vector3"]
    for i in range(N_MSGS):
        t = T0_NS + i * PERIOD_NS
        yield "/joy", "sensor_msgs/msg/Joy", t, T["sensor_msgs/msg/Joy"](
            header=header(i, t, "js"), axes=np.array([0.1 * i, -0.5], dtype=np.float32),
            buttons=np.array([i % 2], dtype=np.int32))
        odom = T["nav_msgs/msg/Odometry"](
            header=header(i, t, "odom"), child_frame_id="base_link",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](
                pose=T["geometry_msgs/msg/Pose"](position=P(x=float(i), y=2.0, z=0.0),
                                                 orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0)),
                covariance=np.arange(36, dtype=np.float64)),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](linear=V3(x=0.5, y=0.0, z=0.0),
                                                   angular=V3(x=0.0, y=0.0, z=0.1 * i)),
                covariance=np.zeros(36)))
        yield "/odom", "nav_msgs/msg/Odometry", t + 1000, odom
        if i % 5 == 0:
            yield "/image", "sensor_msgs/msg/Image", t + 2000, T["sensor_msgs/msg/Image"](
                header=header(i, t, "cam"), height=2, width=3, encoding="mono8",
                is_bigendian=0, step=3, data=np.arange(6, dtype=np.uint8) + i)
        yield "/gizmo", "acme_msgs/msg/Gizmo", t + 3000, T["acme_msgs/msg/Gizmo"](
            count=i, label="x")


def write_test_bag(path: Path, ros1: bool) -> Path:
    store = _typestore(ros1)
    if ros1:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
        serialize = store.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
        serialize = store.serialize_cdr
    conns = {}
    with writer:
        for topic, msgtype, t, msg in _messages(store, ros1):
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=store)
            writer.write(conns[topic], t, serialize(msg, msgtype))
    return path


@pytest.fixture(scope="module", params=["ros1", "ros2"])
def bag(request, tmp_path_factory):
    ros1 = request.param == "ros1"
    d = tmp_path_factory.mktemp(request.param)
    return write_test_bag(d / ("test.bag" if ros1 else "test_bag"), ros1)


@pytest.fixture(scope="module")
def ros2_bag(tmp_path_factory):
    return write_test_bag(tmp_path_factory.mktemp("ros2_only") / "bag", ros1=False)


def _read_all(path: Path):
    from rosbags.highlevel import AnyReader

    with AnyReader([path]) as reader:
        for conn, t, raw in reader.messages():
            yield conn, t, reader.deserialize(raw, conn.msgtype)


def test_message_class_maps_ros1_and_ros2_names():
    from sensor_msgs.msg import Joy

    assert message_class("sensor_msgs/msg/Joy") is Joy
    assert message_class("sensor_msgs/Joy") is Joy
    with pytest.raises(ImportError, match="acme_msgs"):
        message_class("acme_msgs/msg/Gizmo")
    with pytest.raises(ImportError, match="Nonexistent"):
        message_class("sensor_msgs/msg/Nonexistent")
    with pytest.raises(ImportError, match="not a message type"):
        message_class("Joy")


def test_conversion_to_installed_classes(bag):
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import Image, Joy

    seen = {"/joy": 0, "/odom": 0, "/image": 0}
    for conn, _t, obj in _read_all(bag):
        if conn.topic == "/gizmo":
            continue
        msg = to_ros2(obj, message_class(conn.msgtype))
        i = seen[conn.topic]
        seen[conn.topic] += 1
        if conn.topic == "/joy":
            assert isinstance(msg, Joy)
            assert msg.header.frame_id == "js"
            assert not hasattr(msg.header, "seq")
            stamp = T0_NS + i * PERIOD_NS
            assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == divmod(stamp, 10**9)
            np.testing.assert_allclose(list(msg.axes), [np.float32(0.1 * i), -0.5])
            assert list(msg.buttons) == [i % 2]
        elif conn.topic == "/odom":
            assert isinstance(msg, Odometry)
            assert msg.pose.pose.position.x == float(i)
            np.testing.assert_array_equal(msg.pose.covariance, np.arange(36.0))
            assert msg.twist.twist.angular.z == pytest.approx(0.1 * i)
            assert msg.child_frame_id == "base_link"
        else:
            assert isinstance(msg, Image)
            assert bytes(msg.data) == bytes(np.arange(6, dtype=np.uint8) + 5 * i)
            assert (msg.height, msg.width, msg.encoding) == (2, 3, "mono8")
    assert seen == {"/joy": N_MSGS, "/odom": N_MSGS, "/image": N_MSGS // 5}


def test_config_validation():
    for bad in ({"rate": 0.0}, {"rate": float("nan")}, {"start_s": -1.0},
                {"clock_rate_hz": -5.0}, {"wait_subscribers_s": -1.0}):
        with pytest.raises(ValueError):
            ReplayConfig(**bad)


def _cli(repo_root, *args, **kw):
    env = dict(os.environ, PYTHONPATH=str(repo_root))
    return subprocess.Popen([sys.executable, "-m", "asgp_ros.cli", "replay", *map(str, args)],
                            cwd=repo_root, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kw)


def test_cli_errors(repo_root, tmp_path, ros2_bag):
    bag = ros2_bag
    proc = _cli(repo_root, tmp_path / "missing_bag")
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 2 and "no such bag" in err
    proc = _cli(repo_root, bag, "--topics", "/nope")
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 2 and "/nope" in err and "/joy" in err
    proc = _cli(repo_root, bag, "--rate", "-1")
    _out, err = proc.communicate(timeout=60)
    assert proc.returncode == 2 and "rate" in err


class _Listener:
    def __init__(self, context):
        import rclpy
        from nav_msgs.msg import Odometry
        from rclpy.qos import QoSProfile
        from rosgraph_msgs.msg import Clock
        from sensor_msgs.msg import Image, Joy

        self.node = rclpy.create_node("replay_listener", context=context)
        self.executor = rclpy.executors.SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self.got: dict[str, list] = {"/joy": [], "/odom": [], "/image": [], "/clock": []}
        qos = QoSProfile(depth=100)
        for topic, cls in (("/joy", Joy), ("/odom", Odometry), ("/image", Image),
                           ("/clock", Clock)):
            self.node.create_subscription(cls, topic, self._cb(topic), qos)

    def _cb(self, topic):
        def cb(msg):
            self.got[topic].append(msg)
        return cb

    def spin_until(self, cond, timeout=30.0, what=""):
        deadline = time.monotonic() + timeout
        while not cond():
            assert time.monotonic() < deadline, f"timed out waiting for {what}"
            self.executor.spin_once(timeout_sec=0.01)

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()


@pytest.mark.e2e
def test_replay_publishes_messages_with_timing_and_clock(rclpy_context, repo_root, bag):
    from asgp_ros.nodes.conversions import stamp_to_seconds

    lis = _Listener(rclpy_context)
    try:
        proc = _cli(repo_root, bag, "--rate", "2", "--wait-subscribers", "20",
                    "--topics", "/joy", "/odom", "/image", "/gizmo")
        lis.spin_until(lambda: proc.poll() is not None and len(lis.got["/joy"]) == N_MSGS
                       and len(lis.got["/odom"]) == N_MSGS, what="all messages")
        out, err = proc.communicate(timeout=10)
        assert proc.returncode == 0, err
        # the custom type is skipped with a warning naming it (log records go to stdout)
        assert "acme_msgs/msg/Gizmo" in out and "not installed" in out
        joy = lis.got["/joy"]
        assert [round(m.axes[0], 4) for m in joy] == [round(0.1 * i, 4) for i in range(N_MSGS)]
        assert lis.got["/image"][1].data.tolist() == list(range(5, 11))
        # /clock runs through the bag's times and never goes back within one pass
        clock = np.array([stamp_to_seconds(c.clock) for c in lis.got["/clock"]])
        assert np.all(np.diff(clock) >= 0)
        assert clock[0] == pytest.approx(T0_NS * 1e-9, abs=1e-3)
        assert clock[-1] == pytest.approx((T0_NS + (N_MSGS - 1) * PERIOD_NS + 3000) * 1e-9,
                                          abs=1e-3)
        # the pacing itself (the recorded timing scaled by --rate) is checked on a fake clock
        # below: the arrival times here depend on the machine's load
    finally:
        lis.close()


def test_replay_paces_the_messages_by_their_recorded_times_over_the_rate(
        rclpy_context, tmp_path, monkeypatch):
    """On a fake clock (time.monotonic advances only by the player's sleeps): each message
    is published at start + (t - t_first) / rate, and /clock ticks between them carry the
    bag time of their moment, never past the next message's."""
    import rclpy

    from asgp_ros.recording import replay
    from asgp_ros.recording.replay import BagReplayer

    class FakeTime:
        def __init__(self) -> None:
            self.now = 1000.0

        def monotonic(self) -> float:
            return self.now

        def sleep(self, s: float) -> None:
            assert s >= 0.0
            self.now += s

    fake = FakeTime()
    monkeypatch.setattr(replay, "time", fake)
    bag = write_test_bag(tmp_path / "bag", ros1=False)
    node = rclpy.create_node("paced_replay", context=rclpy_context)
    sent: list[tuple[str, float]] = []
    ticks: list[tuple[float, int]] = []

    class Recorder:
        def __init__(self, name: str) -> None:
            self.name = name

        def publish(self, msg) -> None:
            if self.name == "/clock":
                ticks.append((fake.now, msg.clock.sec * 1_000_000_000 + msg.clock.nanosec))
            else:
                sent.append((self.name, fake.now))

        def wait_for_all_acked(self, timeout) -> bool:
            return True

    try:
        config = ReplayConfig(rate=2.0, wait_subscribers_s=0.0, clock_rate_hz=100.0,
                              topics=("/joy",))
        with BagReplayer(bag, config, node) as player:
            player.create_publishers()
            for topic in player.topics.values():
                topic.publisher = Recorder(topic.name)
            player._clock_pub = Recorder("/clock")
            assert player.play_once()
    finally:
        node.destroy_node()
    joy = [t for name, t in sent if name == "/joy"]
    assert len(joy) == N_MSGS
    expected = 1000.0 + np.arange(N_MSGS) * PERIOD_NS / 1e9 / 2.0
    np.testing.assert_allclose(joy, expected, atol=1e-9)
    bag_times = np.array([b for _, b in ticks])
    assert np.all(np.diff(bag_times) >= 0)  # the clock never goes back within a pass
    walls = np.array([w for w, _ in ticks])
    # a tick's bag time is the wall time since the start times the rate
    np.testing.assert_allclose((bag_times - T0_NS) / 1e9, (walls - 1000.0) * 2.0, atol=1e-6)
    assert len(ticks) > 40  # 100 Hz of wall time between the messages, and one per message
    # from --start, reading each message taking 2 ms (a large bag): the messages played are
    # paced from the first one played (the reading past the start went into the pacing,
    # and the first messages after it went out in a burst)
    sent.clear()
    node = rclpy.create_node("paced_replay_start", context=rclpy_context)
    try:
        skip = 5
        config = ReplayConfig(rate=2.0, wait_subscribers_s=0.0, publish_clock=False,
                              topics=("/joy",), start_s=(skip * PERIOD_NS - 1) / 1e9)
        with BagReplayer(bag, config, node) as player:
            player.create_publishers()
            for topic in player.topics.values():
                topic.publisher = Recorder(topic.name)
            read = player.reader.messages

            def slow(*args, **kwargs):
                for item in read(*args, **kwargs):
                    fake.now += 0.002
                    yield item

            player.reader.messages = slow
            assert player.play_once()
    finally:
        node.destroy_node()
    joy = np.array([t for name, t in sent if name == "/joy"])
    assert len(joy) == N_MSGS - skip
    np.testing.assert_allclose(np.diff(joy), PERIOD_NS / 1e9 / 2.0, atol=0.0021)


@pytest.mark.e2e
def test_loop_jumps_the_clock_back_and_ctrl_c_is_clean(rclpy_context, repo_root, bag):
    from asgp_ros.nodes.conversions import stamp_to_seconds

    lis = _Listener(rclpy_context)
    try:
        proc = _cli(repo_root, bag, "--rate", "4", "--loop", "--wait-subscribers", "20",
                    "--topics", "/joy")
        lis.spin_until(lambda: len(lis.got["/joy"]) > 2 * N_MSGS + 2, what="two passes")
        proc.send_signal(signal.SIGINT)
        _out, err = proc.communicate(timeout=20)
        assert proc.returncode in (0, 130), err
        assert "Traceback" not in err
        clock = np.array([stamp_to_seconds(c.clock) for c in lis.got["/clock"]])
        assert np.any(np.diff(clock) < -0.5)  # the loop restarted the clock
    finally:
        lis.close()


def test_a_loop_over_a_bag_of_one_message_is_paced(rclpy_context, repo_root, tmp_path):
    """A bag of one message, looped: 49,590 passes in 3 s, each the message, a /clock jump
    back and a log line. A pass lasts at least MIN_LOOP_PASS_S."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from asgp_ros.recording.replay import MIN_LOOP_PASS_S

    store = _typestore(False)
    T = store.types
    path = tmp_path / "one"
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection("/joy", "sensor_msgs/msg/Joy", typestore=store)
        msg = T["sensor_msgs/msg/Joy"](
            header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
                sec=T0_NS // 10**9, nanosec=0), frame_id="js"),
            axes=np.array([0.1, 0.0], dtype=np.float32), buttons=np.array([], dtype=np.int32))
        writer.write(conn, T0_NS, store.serialize_cdr(msg, "sensor_msgs/msg/Joy"))
    lis = _Listener(rclpy_context)
    try:
        proc = _cli(repo_root, path, "--loop", "--wait-subscribers", "20")
        lis.spin_until(lambda: len(lis.got["/joy"]) >= 1, what="the message")
        t0, n0 = time.monotonic(), len(lis.got["/joy"])
        lis.spin_until(lambda: time.monotonic() - t0 > 3.0, what="3 s", timeout=10.0)
        passes = len(lis.got["/joy"]) - n0
        proc.send_signal(signal.SIGINT)
        _out, err = proc.communicate(timeout=20)
        assert "Traceback" not in err
        assert 1 <= passes <= 3.0 / MIN_LOOP_PASS_S + 1, passes
    finally:
        lis.close()


def test_a_second_clock_on_the_domain_stops_the_replay(rclpy_context, repo_root, ros2_bag):
    """A second `asgp replay` (or anything else publishing /clock) on the domain: the two
    clocks interleaved, and a predictor following /clock saw 604 jumps back in 9 s and
    published no path. The replay stops, saying why; with --no-clock it plays on."""
    import rclpy
    from rosgraph_msgs.msg import Clock

    other = rclpy.create_node("another_clock", context=rclpy_context)
    try:
        other.create_publisher(Clock, "/clock", 10)
        proc = _cli(repo_root, ros2_bag, "--loop", "--rate", "4", "--topics", "/joy")
        try:
            _, err = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            pytest.fail("the replay played on beside another /clock")
        assert proc.returncode == 2, err
        assert "another node publishes /clock" in err and "Traceback" not in err
        quiet = _cli(repo_root, ros2_bag, "--no-clock", "--rate", "4", "--topics", "/joy")
        _, err = quiet.communicate(timeout=60)
        assert quiet.returncode == 0, err
    finally:
        other.destroy_node()


@pytest.mark.e2e
def test_start_offset_and_remap(rclpy_context, repo_root, ros2_bag):
    import rclpy
    from rclpy.qos import QoSProfile
    from sensor_msgs.msg import Joy

    node = rclpy.create_node("remap_listener", context=rclpy_context)
    executor = rclpy.executors.SingleThreadedExecutor(context=rclpy_context)
    executor.add_node(node)
    got: list = []
    node.create_subscription(Joy, "/joy_replayed", got.append, QoSProfile(depth=100))
    try:
        proc = _cli(repo_root, ros2_bag, "--rate", "4", "--start", "0.5", "--topics", "/joy",
                    "--remap", "/joy:=/joy_replayed", "--wait-subscribers", "20")
        deadline = time.monotonic() + 30
        while proc.poll() is None or len(got) < N_MSGS - 10:
            assert time.monotonic() < deadline, "timed out"
            executor.spin_once(timeout_sec=0.01)
        _, err = proc.communicate(timeout=10)
        assert proc.returncode == 0, err
        # rcl is not handed asgp's own command line (it took FROM:=TO as a remap of its own)
        assert err == "", err
        # 0.5 s into the bag: the joystick messages from i = 10 on, on the new name
        assert [round(m.axes[0], 4) for m in got] == [round(0.1 * i, 4)
                                                     for i in range(10, N_MSGS)]
    finally:
        executor.shutdown()
        node.destroy_node()


def test_commands_to_the_chair_are_not_played_unless_asked(rclpy_context, tmp_path,
                                                            caplog):
    """A bag recorded with the shared-control layer holds joy_override: replayed, a running
    bridge would write it to the board. It is played only with commands=True (--commands),
    when named in topics, or remapped to a name no bridge listens to; a name rcl resolves
    to an override ({ns}joy_override) is one."""
    import rclpy
    from rosbags.rosbag2 import StoragePlugin, Writer

    from asgp_ros.recording.replay import BagReplayer, ReplayConfig, ReplayError, is_command

    store = _typestore(False)
    T = store.types
    path = tmp_path / "layer_bag"
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        for topic in ("/joy", "/joy_override", "/chair/joy_override", "{ns}joy_override"):
            c = w.add_connection(topic, "sensor_msgs/msg/Joy", typestore=store)
            msg = T["sensor_msgs/msg/Joy"](
                header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
                    sec=1, nanosec=0), frame_id=""),
                axes=np.array([0.1, 0.0], dtype=np.float32), buttons=np.zeros(0, np.int32))
            w.write(c, T0_NS, store.serialize_cdr(msg, "sensor_msgs/msg/Joy"))
    node = rclpy.create_node("replay_commands", context=rclpy_context)
    try:
        def played(**kw) -> tuple[set[str], list[str]]:
            with BagReplayer(path, ReplayConfig(**kw), node) as r:
                return {t.out_name for t in r.topics.values()}, r.skipped_commands

        assert played() == ({"/joy"}, [(t, t) for t in ("/chair/joy_override",
                                                          "/joy_override",
                                                          "{ns}joy_override")])
        assert played(commands=True)[0] == {"/joy", "/joy_override", "/chair/joy_override",
                                            "{ns}joy_override"}
        assert played(topics=("/joy", "/joy_override"))[0] == {"/joy", "/joy_override"}
        assert played(remap=(("/joy_override", "/replayed/override"),))[0] == {
            "/joy", "/replayed/override"}
        # a topic remapped onto a command's name is a command, named as such, even when
        # named in topics; a name rcl resolves to one (a substitution) is one
        with pytest.raises(ReplayError, match="not a command to the chair"):
            played(remap=(("/joy", "/x/joy_override"),))
        # the hint names the bag's topic (it printed "--remap /chair/joy_override (as
        # /y/joy_override):=<other name>")
        with caplog.at_level(logging.WARNING):
            played(remap=(("/chair/joy_override", "/y/joy_override"),))
        said = " ".join(r.getMessage() for r in caplog.records if "not playing" in
                        r.getMessage())
        assert "/chair/joy_override (as /y/joy_override)" in said
        assert "--remap /chair/joy_override:=<other name>" in said, said
        with pytest.raises(ReplayError, match="not a command to the chair"):
            played(topics=("/joy",), remap=(("/joy", "/joy_override"),))
        assert played(topics=("/joy",), remap=(("/joy", "/joy_override"),),
                      commands=True)[0] == {"/joy_override"}
        with pytest.raises(ReplayError, match="not a command to the chair"):
            played(remap=(("/joy", "{ns}joy_override"),))
    finally:
        node.destroy_node()
    assert is_command("joy_override") and is_command("/a/b/joy_override/")
    assert not is_command("/joy_override_replayed") and not is_command("/joy")


# ---- damaged and special files: one clear error, never a traceback or a hang (issue 16) ---

def _corrupt_first_joy(path: Path) -> None:
    """Overwrite the CDR encapsulation header of the bag's first /joy message."""
    store = _typestore(ros1=False)
    _topic, msgtype, _t, msg = next(iter(_messages(store, ros1=False)))
    raw = bytes(store.serialize_cdr(msg, msgtype))
    storage = next(path.glob("*.mcap"))
    data = bytearray(storage.read_bytes())
    at = data.find(raw)
    assert at > 0, "the message is stored uncompressed"
    data[at:at + 4] = b"\xff\xff\xff\xff"
    storage.write_bytes(bytes(data))


def _corrupt_summary(path: Path) -> None:
    """Make the schema name in the mcap summary invalid UTF-8 (fails when opening)."""
    storage = next(path.glob("*.mcap"))
    data = bytearray(storage.read_bytes())
    at = data.rfind(b"sensor_msgs/msg/Joy")
    assert at > 0
    data[at:at + 2] = b"\xff\xfe"
    storage.write_bytes(bytes(data))


def _one_error_line(err: str, bag: Path) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("error: ")]
    assert "Traceback" not in err, err
    assert len(errors) == 1 and str(bag) in errors[0], err
    return errors[0]


@pytest.mark.parametrize("damage", [_corrupt_first_joy, _corrupt_summary])
def test_replay_of_a_corrupt_mcap_is_one_clear_error(repo_root, tmp_path, damage):
    """Issue 16: `asgp replay` on a corrupt mcap printed a raw ReaderError traceback."""
    bag = write_test_bag(tmp_path / "bag", ros1=False)
    damage(bag)
    proc = _cli(repo_root, bag, "--rate", "1000", "--wait-subscribers", "0",
                "--topics", "/joy", "/odom")
    _out, err = proc.communicate(timeout=60)
    assert proc.returncode == 2, err
    line = _one_error_line(err, bag)
    assert "corrupt" in line


def test_replayer_raises_replay_error_for_corrupt_data(rclpy_context, tmp_path):
    import rclpy

    from asgp_ros.recording.replay import BagReplayer, ReplayError

    bag = write_test_bag(tmp_path / "bag", ros1=False)
    _corrupt_first_joy(bag)
    node = rclpy.create_node("corrupt_replay", context=rclpy_context)
    try:
        config = ReplayConfig(rate=1000.0, wait_subscribers_s=0.0, publish_clock=False,
                              topics=("/joy",))
        with BagReplayer(bag, config, node) as player, \
                pytest.raises(ReplayError, match=r"corrupt message on /joy at 1700000000\.000"):
            player.run()
    finally:
        node.destroy_node()


def test_replay_refuses_a_fifo_at_once(repo_root, tmp_path):
    """A FIFO where the bag goes is refused before it is opened (no hang)."""
    fifo = tmp_path / "drive.bag"
    os.mkfifo(fifo)
    proc = _cli(repo_root, fifo, "--wait-subscribers", "0")
    try:
        _out, err = proc.communicate(timeout=60)  # a deadline for the failure, not a timing
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        pytest.fail("asgp replay blocked on a FIFO")
    assert proc.returncode == 2, err
    assert "is a FIFO (named pipe), not a regular file" in _one_error_line(err, fifo)


def test_replay_ranges_are_checked_in_the_config_and_on_the_command_line(repo_root,
                                                                        ros2_bag):
    from asgp_ros.recording.replay import REPLAY_RANGES

    for name, (low, high) in REPLAY_RANGES.items():
        ReplayConfig(**{name: low})
        ReplayConfig(**{name: high})
        for bad in (high * 2 + 1, low - 1.0, float("nan"), float("inf")):
            with pytest.raises(ValueError, match=name):
                ReplayConfig(**{name: bad})
    proc = _cli(repo_root, ros2_bag, "--rate", "1e300")
    _out, err = proc.communicate(timeout=60)
    assert proc.returncode == 2
    assert err.strip().splitlines() == [
        "asgp replay: error: argument --rate: must be in [0.001, 1000], got 1e300 "
        "(see asgp replay --help)"]


def _stop_within_bound(proc, sig, bound_s: float = 15.0) -> str:
    """Send ``sig``; the command must be gone (``bound_s`` is a hang detector: how soon,
    against the spec's 2 s, depends on the machine's load); returns its stderr."""
    proc.send_signal(sig)
    sent = time.monotonic()
    while proc.poll() is None:
        assert time.monotonic() - sent < bound_s, f"still running {bound_s} s after {sig!r}"
        time.sleep(0.005)
    _out, err = proc.communicate(timeout=10)
    return err


@pytest.mark.e2e
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM],
                         ids=lambda s: signal.Signals(s).name)
@pytest.mark.parametrize("state", ["waiting for subscribers", "playing"])
def test_replay_exits_on_signals_in_every_state(rclpy_context, repo_root, ros2_bag, state,
                                                sig):
    lis = _Listener(rclpy_context)
    if state == "playing":  # a slow replay: the first message, then a long wait
        proc = _cli(repo_root, ros2_bag, "--rate", "0.01", "--wait-subscribers", "20",
                    "--topics", "/joy")
    else:  # nobody subscribes to the topics it publishes: it waits
        proc = _cli(repo_root, ros2_bag, "--wait-subscribers", "3000", "--topics", "/joy",
                    "/odom", "--remap", "/joy:=/nobody_listens", "/odom:=/nobody_either")
    try:
        if state == "playing":
            lis.spin_until(lambda: len(lis.got["/joy"]) >= 1, what="the first message")
        else:  # its publishers exist: it is in the loop that waits for subscribers
            lis.spin_until(lambda: lis.node.count_publishers("/nobody_either") >= 1,
                           what="the replay's publishers")
        err = _stop_within_bound(proc, sig)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        lis.close()
    assert proc.returncode in (0, 130, 128 + signal.SIGTERM), err
    assert "Traceback" not in err, err


def test_a_shutdown_between_checks_is_a_clean_stop(rclpy_context, ros2_bag):
    """What rclpy's SIGINT/SIGTERM handler does -- shut the context down -- may land between
    the player's stop check and its next call into rclpy (which then raises RCLError); the
    command must still end cleanly. The replay runs in this process on rclpy's default
    context, which a helper thread shuts down once the player waits for subscribers."""
    import threading

    import rclpy

    from asgp_ros.cli import build_parser

    args = build_parser().parse_args(
        ["replay", str(ros2_bag), "--wait-subscribers", "3000", "--topics", "/joy", "/odom",
         "--remap", "/joy:=/nobody_listens_here", "/odom:=/nobody_here_either"])
    lis = _Listener(rclpy_context)

    def shut_down_when_waiting() -> None:
        deadline = time.monotonic() + 60
        while lis.node.count_publishers("/nobody_here_either") < 1:
            if time.monotonic() > deadline:
                break
            time.sleep(0.01)
        rclpy.try_shutdown()  # the default context, as the signal handler does

    helper = threading.Thread(target=shut_down_when_waiting)
    helper.start()
    try:
        assert args.func(args) == 0
    finally:
        helper.join()
        lis.close()


def _play(context, bag: Path, name: str) -> int:
    """Messages a whole replay of ``bag`` published (rate 1000, no clock)."""
    import rclpy

    from asgp_ros.recording.replay import BagReplayer

    node = rclpy.create_node(name, context=context)
    try:
        config = ReplayConfig(rate=1000.0, wait_subscribers_s=0.0, publish_clock=False)
        with BagReplayer(bag, config, node) as player:
            player.run()
            return player.published
    finally:
        node.destroy_node()


@pytest.fixture(scope="module")
def sim_bags(tmp_path_factory):
    from asgp_ros.recording.bags import write_bag
    from asgp_ros.sim.simulate import simulate

    d = tmp_path_factory.mktemp("sim_replay")
    rec = simulate("tile", 0.25, 6)
    return {s: write_bag(d / s, rec, storage=s) for s in ("mcap", "sqlite3")}


def _sql(bag: Path, sql: str, *params) -> None:
    import sqlite3

    con = sqlite3.connect(next(bag.glob("*.db3")))
    con.execute(sql, params)
    con.commit()
    con.close()


def test_replay_plays_from_the_first_message_not_from_metadata(rclpy_context, sim_bags,
                                                               tmp_path):
    """metadata.yaml copied from another recording, or edited, starting 30 s later: the
    first 30 s were not played, unsaid. The messages' own times count."""
    import shutil

    whole = _play(rclpy_context, sim_bags["mcap"], "replay_whole")
    bag = Path(shutil.copytree(sim_bags["mcap"], tmp_path / "late"))
    meta = bag / "metadata.yaml"
    text = meta.read_text()
    assert "nanoseconds_since_epoch: 1700000000000000000" in text
    meta.write_text(text.replace("nanoseconds_since_epoch: 1700000000000000000",
                                 "nanoseconds_since_epoch: 1700000010000000000"))
    assert _play(rclpy_context, bag, "replay_late") == whole


@pytest.mark.parametrize("edit", ["after_2038", "int64_max"])
def test_a_message_past_2038_is_refused_whatever_metadata_says(rclpy_context, sim_bags,
                                                                tmp_path, edit):
    """Rows past 2^31 s while metadata.yaml ends in 2023: /clock's int32 seconds wrapped to
    1901; one row at INT64_MAX: a replay at rate 1000 of a 15 s bag waited 7.5e6 s for it.
    Each message's time is checked before it is played."""
    import shutil

    from asgp_ros.recording.replay import ReplayError

    bag = Path(shutil.copytree(sim_bags["sqlite3"], tmp_path / edit))
    if edit == "after_2038":
        _sql(bag, "update messages set timestamp = timestamp + ? where id > 10",
             (2**31 - 1_700_000_000) * 10**9)
    else:
        _sql(bag, "update messages set timestamp = 9223372036854775807 where id = 5")
    with pytest.raises(ReplayError, match="2038"):
        _play(rclpy_context, bag, f"replay_{edit}")


def test_replay_refuses_rows_left_in_a_write_ahead_log(rclpy_context, sim_bags, tmp_path):
    """The indexed reader leaves a SQLite log's committed rows out: refused, saying what
    writes a clean copy."""
    import shutil

    from asgp_ros.recording.replay import ReplayError

    bag = Path(shutil.copytree(sim_bags["sqlite3"], tmp_path / "wal"))
    db = next(bag.glob("*.db3"))
    (bag / (db.name + "-wal")).write_bytes(b"\0" * 64)
    with pytest.raises(ReplayError, match="bag repair"):
        _play(rclpy_context, bag, "replay_wal")


def test_a_recording_whose_clock_stepped_back_is_not_played_interleaved(rclpy_context,
                                                                        sim_bags, tmp_path):
    """The clock stepped back 5 s half-way through a 15 s recording (the rows after it
    written 5 s earlier in time): played by time, two drives went out interleaved on one
    /clock, the joystick out of its order hundreds of times, without a word. Refused,
    saying why; stepped back further than the part before it lasted, the two parts do not
    overlap, and play one after the other."""
    import shutil

    from asgp_ros.recording.replay import ReplayError

    bag = Path(shutil.copytree(sim_bags["sqlite3"], tmp_path / "stepped"))
    _sql(bag, "update messages set timestamp = timestamp - ? where id > "
         "(select count(*) / 2 from messages)", 5 * 10**9)
    with pytest.raises(ReplayError, match="clock stepped back 1 time"):
        _play(rclpy_context, bag, "replay_stepped")
    apart = Path(shutil.copytree(sim_bags["sqlite3"], tmp_path / "apart"))
    _sql(apart, "update messages set timestamp = timestamp - ? where id > "
         "(select count(*) / 2 from messages)", 30 * 10**9)
    assert _play(rclpy_context, apart, "replay_apart") == _play(
        rclpy_context, sim_bags["sqlite3"], "replay_whole")


def test_a_gap_of_decades_in_the_bag_times_is_not_waited_out(rclpy_context, sim_bags,
                                                             tmp_path):
    """The first messages recorded before NTP set the clock (bag times in 1970): the replay
    waited the 53 years to the next one (19 days at rate 1000). A gap of more than
    MAX_WAIT_GAP_S of bag time is played on at once."""
    import shutil

    import rclpy

    from asgp_ros.recording.replay import BagReplayer

    whole = _play(rclpy_context, sim_bags["sqlite3"], "replay_no_gap")
    bag = Path(shutil.copytree(sim_bags["sqlite3"], tmp_path / "boot1970"))
    _sql(bag, "update messages set timestamp = timestamp - ? where id <= 10",
         1_600_000_000 * 10**9)
    deadline = time.monotonic() + 60.0
    node = rclpy.create_node("replay_gap", context=rclpy_context)
    try:
        config = ReplayConfig(rate=1000.0, wait_subscribers_s=0.0, publish_clock=False)
        with BagReplayer(bag, config, node,
                         should_stop=lambda: time.monotonic() > deadline) as player:
            player.run()
            assert player.published == whole
    finally:
        node.destroy_node()
