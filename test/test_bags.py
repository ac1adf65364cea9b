"""Bag writing and reading: ROS 2 mcap/sqlite3 and ROS 1, message types, stamps, errors."""

from __future__ import annotations

import argparse
import hashlib
import shutil
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from asgp_ros.cli._bagargs import add_topic_args, read_series_or_fail
from asgp_ros.learning.training import read_series
from asgp_ros.recording import bags
from asgp_ros.recording.bags import BagError, JoyAxes, parse_joy_axes, read_streams, write_bag
from asgp_ros.sim.sensors import SensorParams
from asgp_ros.sim.simulate import simulate, write_recording

TRUTH = "/ground_truth/odom"
STORE2 = get_typestore(Stores.ROS2_JAZZY)


@pytest.fixture(scope="module")
def rec():
    # A high failure rate so that a 40 s recording contains tracking failures.
    sp = SensorParams(failure_rate_per_min={"tile": 6.0, "carpet": 6.0, "hybrid": 6.0})
    r = simulate("hybrid", 40.0 / 60.0, 7, sensor_params=sp)
    assert r.failures.shape[0] > 0
    return r


@pytest.fixture(scope="module")
def mcap_bag(rec, tmp_path_factory):
    return write_bag(tmp_path_factory.mktemp("m") / "drive", rec)


def _files(path: Path) -> dict[str, str]:
    if path.is_file():
        return {path.name: hashlib.sha256(path.read_bytes()).hexdigest()}
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(path.iterdir())}


def _check_streams(s, rec, truth=True):
    off = rec.epoch_ns * 1e-9
    assert s.joy.shape == rec.joy.shape
    np.testing.assert_allclose(s.joy_t, rec.joy_t + off, rtol=0, atol=1e-6)
    np.testing.assert_allclose(s.joy, rec.joy, rtol=0, atol=1e-6)  # float32 in Joy
    np.testing.assert_allclose(s.vel_t, rec.vo_t + off, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(s.vel, rec.vo)
    if truth:
        ref = rec.to_streams(truth_rate_hz=20.0)
        np.testing.assert_allclose(s.truth_t, ref.truth_t, rtol=0, atol=1e-6)
        np.testing.assert_allclose(s.truth[:, [0, 1, 3, 4]], ref.truth[:, [0, 1, 3, 4]])
        dth = np.angle(np.exp(1j * (s.truth[:, 2] - ref.truth[:, 2])))
        assert np.abs(dth).max() < 1e-9


# ----------------------------------------------------------------------------- round trips
def test_mcap_round_trip(mcap_bag, rec):
    assert (mcap_bag / "metadata.yaml").exists()
    s = read_streams(mcap_bag, truth_topic=TRUTH)
    _check_streams(s, rec)
    # The stale reports of the tracking failures are in the bag as repeated values.
    i = np.flatnonzero(rec.vo_stale)
    assert np.all(s.vel[i] == s.vel[i - 1])
    meta = bags.read_sim_metadata(mcap_bag)
    assert meta["seed"] == 7 and len(meta["vo_failures"]) == rec.failures.shape[0]
    # The storage file inside the bag directory is accepted too.
    s2 = read_streams(mcap_bag / "drive.mcap")
    np.testing.assert_array_equal(s2.vel, s.vel)


def test_sqlite3_and_ros1_read_to_same_arrays(rec, tmp_path):
    sq = write_bag(tmp_path / "sq", rec, storage="sqlite3")
    assert list(sq.glob("*.db3"))
    r1 = write_bag(tmp_path / "drive.bag", rec)
    assert r1.is_file()
    _check_streams(read_streams(sq, truth_topic=TRUTH), rec)
    a = read_streams(r1, truth_topic=TRUTH)
    _check_streams(a, rec)
    b = read_streams(sq, truth_topic=TRUTH)
    for name in ("joy_t", "joy", "vel_t", "vel", "truth_t", "truth"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def test_rosbags_and_rclpy_deserialise_the_same_messages(mcap_bag):
    serialization = pytest.importorskip("rclpy.serialization")
    from geometry_msgs.msg import TwistStamped
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import Joy

    types = {"/joy": Joy, "/vo/twist": TwistStamped, TRUTH: Odometry}
    seen = dict.fromkeys(types, 0)
    with AnyReader([mcap_bag]) as reader:
        for conn, _t, raw in reader.messages():
            if seen[conn.topic] >= 50:
                continue
            seen[conn.topic] += 1
            a = reader.deserialize(raw, conn.msgtype)
            b = serialization.deserialize_message(bytes(raw), types[conn.topic])
            assert (a.header.stamp.sec, a.header.stamp.nanosec) == (
                b.header.stamp.sec, b.header.stamp.nanosec)
            assert a.header.frame_id == b.header.frame_id
            if conn.topic == "/joy":
                assert list(a.axes) == list(b.axes) and len(b.buttons) == 0
            elif conn.topic == "/vo/twist":
                assert b.header.frame_id == "base_link"
                assert a.twist.linear.x == b.twist.linear.x
                assert a.twist.angular.z == b.twist.angular.z
            else:
                assert (b.header.frame_id, b.child_frame_id) == ("odom", "base_link")
                assert a.pose.pose.position.x == b.pose.pose.position.x
                assert a.pose.pose.orientation.z == b.pose.pose.orientation.z
                assert a.twist.twist.angular.z == b.twist.twist.angular.z
    assert all(n == 50 for n in seen.values())


@pytest.mark.parametrize("storage", ["mcap", "ros1"])
def test_batch_serialisation_matches_typestore(rec, tmp_path, storage):
    """Every message written equals the typestore's own serialisation of its content."""
    ros1 = storage == "ros1"
    path = write_bag(tmp_path / ("d.bag" if ros1 else "d"), rec, storage=storage)
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_JAZZY)
    ser = store.serialize_ros1 if ros1 else store.serialize_cdr
    n = 0
    with AnyReader([path]) as reader:
        for conn, _t, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            assert bytes(ser(msg, conn.msgtype)) == bytes(raw), conn.topic
            n += 1
    assert n == rec.joy_t.size + rec.vo_t.size + rec.truth_t[::5].size


@pytest.mark.parametrize("storage", ["mcap", "sqlite3", "ros1"])
def test_same_seed_gives_byte_identical_bags(tmp_path, storage):
    name = "drive.bag" if storage == "ros1" else "drive"
    paths = []
    for k in range(2):
        (tmp_path / str(k)).mkdir()
        paths.append(write_bag(tmp_path / str(k) / name, simulate("carpet", 0.2, 3),
                               storage=storage))
    assert _files(paths[0]) == _files(paths[1])
    (tmp_path / "2").mkdir()
    other = write_bag(tmp_path / "2" / name, simulate("carpet", 0.2, 4), storage=storage)
    assert _files(other) != _files(paths[0])


# ----------------------------------------------------------------------------- other types
def _write_custom(path: Path, twist_type: str, n: int = 20, zero_stamps: bool | str = False,
                  joy_axes=(0.25, -0.5, 0.75), ros1: bool = False,
                  overrides: tuple[int, ...] = (),
                  override_type: str = "sensor_msgs/msg/Joy",
                  variances: dict[int, float] | None = None) -> None:
    """A hand-made bag: /joy + /twist of ``twist_type``, header stamps 20 ms before bag time;
    with ``overrides``, a /joy_override of ``override_type`` 5 ms after the joystick sample
    of each of those indices; ``variances``: the twist variance of those samples (of a type
    with a covariance; else 0.01)."""
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_JAZZY)
    T = store.types
    ser = store.serialize_ros1 if ros1 else store.serialize_cdr

    def header(t_ns: int, frame: str):
        bad = zero_stamps if isinstance(zero_stamps, bool) else (t_ns // 10**8) % 2 == 1
        sec, nsec = divmod(0 if bad else t_ns, 10**9)
        stamp = T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
        if ros1:
            return T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    V3, Tw = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Twist"]

    def twist_msg(i: int, t_ns: int):
        tw = Tw(linear=V3(x=0.1 * i, y=0.0, z=0.0), angular=V3(x=0.0, y=0.0, z=-0.05 * i))
        if twist_type == "geometry_msgs/msg/Twist":
            return tw
        if twist_type == "geometry_msgs/msg/TwistStamped":
            return T[twist_type](header=header(t_ns, "base_link"), twist=tw)
        cov = np.zeros(36)
        cov[0] = cov[35] = (variances or {}).get(i, 0.01)
        twc = T["geometry_msgs/msg/TwistWithCovariance"](twist=tw, covariance=cov)
        if twist_type == "geometry_msgs/msg/TwistWithCovarianceStamped":
            return T[twist_type](header=header(t_ns, "base_link"), twist=twc)
        pose = T["geometry_msgs/msg/PoseWithCovariance"](
            pose=T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
                orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)),
            covariance=np.zeros(36))
        return T[twist_type](header=header(t_ns, "odom"), child_frame_id="base_link",
                             pose=pose, twist=twc)

    base = 1_600_000_000 * 10**9
    w = Writer1(path) if ros1 else Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    with w:
        cj = w.add_connection("/joy", "sensor_msgs/msg/Joy", typestore=store)
        ct = w.add_connection("/twist", twist_type, typestore=store)
        co = (w.add_connection("/joy_override", override_type, typestore=store)
              if overrides else None)
        for i in range(n):
            t_ns = base + i * 100_000_000
            joy = T["sensor_msgs/msg/Joy"](header=header(t_ns, ""),
                                          axes=np.array(joy_axes, dtype=np.float32),
                                          buttons=np.zeros(0, dtype=np.int32))
            w.write(cj, t_ns + 20_000_000, ser(joy, "sensor_msgs/msg/Joy"))
            w.write(ct, t_ns + 20_000_000, ser(twist_msg(i, t_ns), twist_type))
            if co is not None and i in overrides:
                t_o = t_ns + 5_000_000
                over = (T["sensor_msgs/msg/Joy"](header=header(t_o, ""),
                                                 axes=np.array([0.1, 0.0], dtype=np.float32),
                                                 buttons=np.zeros(0, dtype=np.int32))
                        if override_type == "sensor_msgs/msg/Joy" else twist_msg(0, t_o))
                w.write(co, t_o + 20_000_000, ser(over, override_type))


@pytest.mark.parametrize("twist_type", bags.TWIST_TYPES)
def test_twist_types(tmp_path, twist_type):
    path = tmp_path / "b"
    _write_custom(path, twist_type)
    s = read_streams(path, twist_topic="/twist")
    i = np.arange(20)
    np.testing.assert_allclose(s.vel[:, 0], 0.1 * i)
    np.testing.assert_allclose(s.vel[:, 1], -0.05 * i)
    t0 = 1_600_000_000.0
    expect = t0 + 0.1 * i + (0.02 if twist_type == "geometry_msgs/msg/Twist" else 0.0)
    np.testing.assert_allclose(s.vel_t, expect, atol=1e-6)
    np.testing.assert_allclose(s.joy_t, t0 + 0.1 * i, atol=1e-6)  # header stamps


@pytest.mark.parametrize("twist_type", ["nav_msgs/msg/Odometry",
                                        "geometry_msgs/msg/TwistWithCovarianceStamped"])
def test_a_twist_the_odometry_flags_lost_is_read_as_lost(tmp_path, twist_type):
    """vo_node publishes a lost frame's twist as zero with variance ODOM_LOST_VARIANCE, and
    the nodes take it as lost. Read from a bag it was a valid zero velocity: asgp train and
    asgp adapt learnt the chair standing still while it drove (adapt: 240 of 566 rows)."""
    from asgp_ros.core.resample import resample
    from asgp_ros.core.streams import ODOM_LOST_VARIANCE

    path = tmp_path / "b"
    bad = {5: ODOM_LOST_VARIANCE, 9: float("nan"), 12: -1.0, 15: float("inf")}
    _write_custom(path, twist_type, n=30, variances=bad)
    s = read_streams(path, twist_topic="/twist")
    np.testing.assert_array_equal(np.flatnonzero(~s.vel_ok), sorted(bad))
    res = resample(s)
    assert res.tracking_lost.any() and not res.valid[res.tracking_lost].any()


@pytest.mark.parametrize("ros1", [False, True])
def test_overrides_in_a_bag_invalidate_what_they_drove(tmp_path, ros1):
    """A bag recorded while the shared-control layer overrode the user: the override times
    are read (header stamps), and training takes no row from the points they may have
    driven; '' reads none; an override topic of another type is named."""
    from asgp_ros.learning.training import data_summary

    path = tmp_path / ("b.bag" if ros1 else "b")
    _write_custom(path, "geometry_msgs/msg/TwistStamped", n=60, ros1=ros1,
                  overrides=(30, 31, 32))
    t0 = 1_600_000_000.0
    s = read_streams(path, twist_topic="/twist")
    np.testing.assert_allclose(s.override_t, t0 + 0.1 * np.array([30, 31, 32]) + 0.005,
                               atol=1e-6)
    assert read_streams(path, twist_topic="/twist", override_topic="").override_t.size == 0
    assert read_streams(path, twist_topic="/twist",
                        override_topic="/absent").override_t.size == 0
    series = read_series([str(path)], twist_topic="/twist")
    res = series[0].res
    over = res.t[res.overridden] - t0
    # overrides at 3.005 .. 3.205 s drive the points in [o - 0.2, o + 0.6)
    np.testing.assert_allclose(over, [3.0, 3.2, 3.4, 3.6, 3.8], atol=1e-6)
    assert not res.valid[res.overridden].any() and res.valid[~res.overridden][1:-1].all()
    assert data_summary(series)["overridden_samples"] == 5
    blind = read_series([str(path)], twist_topic="/twist", override_topic="")[0].res
    assert not blind.overridden.any() and blind.valid.sum() == res.valid.sum() + 5
    bad = tmp_path / ("c.bag" if ros1 else "c")
    _write_custom(bad, "geometry_msgs/msg/TwistStamped", ros1=ros1, overrides=(3,),
                  override_type="geometry_msgs/msg/TwistStamped")
    with pytest.raises(BagError, match=r"override topic '/joy_override' has unsupported type"
                       r".*--override-topic"):
        read_streams(bad, twist_topic="/twist")
    assert read_streams(bad, twist_topic="/twist", override_topic=None).override_t.size == 0


def test_a_recording_of_the_boards_output_trains_on_the_overridden_steps(tmp_path):
    """README: a recording that holds /joy_applied (the serial bridge's reading of the board's
    output) trains whole with ``--joy-topic /joy_applied --override-topic ''``: the steps an
    override drove keep their rows, with the command the chair got as their input."""
    from asgp_ros.learning.training import read_series

    src = tmp_path / "src"
    _write_custom(src, "geometry_msgs/msg/TwistStamped", n=60, overrides=(30, 31, 32))
    path = tmp_path / "b"
    store = get_typestore(Stores.ROS2_JAZZY)
    Joy = store.types["sensor_msgs/msg/Joy"]
    with (Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w,
          AnyReader([src], default_typestore=store) as r):
        conns = {c.topic: w.add_connection(c.topic, c.msgtype, typestore=store)
                 for c in r.connections}
        applied = w.add_connection("/joy_applied", "sensor_msgs/msg/Joy", typestore=store)
        for c, t, raw in r.messages():
            w.write(conns[c.topic], t, raw)
            if c.topic == "/joy":  # the board's output: the override while it applies it
                msg = r.deserialize(raw, c.msgtype)
                i = round((t - 1_600_000_000 * 10**9 - 20_000_000) / 1e8)
                axes = ([0.1, 0.0, 0.75] if 30 <= i <= 34 else list(msg.axes))
                out = Joy(header=msg.header, axes=np.array(axes, dtype=np.float32),
                          buttons=msg.buttons)
                w.write(applied, t, store.serialize_cdr(out, c.msgtype))
    user = read_series([str(path)], twist_topic="/twist")[0].res
    whole = read_series([str(path)], twist_topic="/twist", joy_topic="/joy_applied",
                        override_topic="")[0].res
    assert user.overridden.sum() == 5 and not whole.overridden.any()
    np.testing.assert_array_equal(whole.t, user.t)
    assert whole.valid.sum() == user.valid.sum() + 5
    t0 = 1_600_000_000.0
    driven = (whole.t - t0 >= 3.0 - 1e-6) & (whole.t - t0 <= 3.4 + 1e-6)
    assert driven.sum() == 3
    np.testing.assert_allclose(whole.joy[driven], [[0.1, 0.0]] * 3, atol=1e-6)
    np.testing.assert_allclose(whole.joy[~driven & whole.valid & user.valid],
                               user.joy[~driven & whole.valid & user.valid], atol=1e-6)


def test_damaged_overrides_are_named_and_a_missing_topic_is_said(tmp_path, caplog):
    """A /joy_override message that does not decode: one error naming the overrides and the
    way out, not a bare 'corrupt bag'. An override topic asked for and not in the bag is
    said when the bag has another one (a namespace) or when it was not the default."""
    path = tmp_path / "b"
    _write_custom(path, "geometry_msgs/msg/TwistStamped")
    store = get_typestore(Stores.ROS2_JAZZY)
    damaged = tmp_path / "damaged"
    with Writer(damaged, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        with AnyReader([path], default_typestore=store) as r:
            conns = {c.topic: w.add_connection(c.topic, c.msgtype, typestore=store)
                     for c in r.connections}
            for c, t, raw in r.messages():
                w.write(conns[c.topic], t, raw)
        bad = w.add_connection("/joy_override", "sensor_msgs/msg/Joy", typestore=store)
        w.write(bad, 1_600_000_000 * 10**9 + 10**8, b"\x00\x01\x00")
    with pytest.raises(BagError, match=r"in the overrides, /joy_override.*--override-topic ''"):
        read_streams(damaged, twist_topic="/twist")
    assert read_streams(damaged, twist_topic="/twist", override_topic="").joy.shape[0] == 20
    caplog.clear()
    read_streams(path, twist_topic="/twist", override_topic="/joy_overide")
    assert "override topic /joy_overide not found" in caplog.text
    caplog.clear()
    spaced = tmp_path / "spaced"
    _write_custom(spaced, "geometry_msgs/msg/TwistStamped", overrides=(3,))
    renamed = tmp_path / "renamed"
    with (Writer(renamed, version=9, storage_plugin=StoragePlugin.MCAP) as w,
          AnyReader([spaced], default_typestore=store) as r):
        conns = {c.topic: w.add_connection(c.topic.replace("/joy_override",
                                                           "/chair/joy_override"),
                                           c.msgtype, typestore=store)
                 for c in r.connections}
        for c, t, raw in r.messages():
            w.write(conns[c.topic], t, raw)
    assert read_streams(renamed, twist_topic="/twist").override_t.size == 0
    assert "the bag has /chair/joy_override: --override-topic /chair/joy_override" \
        in caplog.text
    assert read_streams(renamed, twist_topic="/twist",
                        override_topic="/chair/joy_override").override_t.size == 1
    caplog.clear()
    read_streams(path, twist_topic="/twist")  # the default, absent: nothing to say
    assert "override" not in caplog.text


def _two_chairs(tmp_path: Path, overrides: dict[str, tuple[int, ...]]) -> Path:
    """One bag as `ros2 bag record -a` holds two chairs: each /chairN/joy, /chairN/twist and
    (``overrides`` of that chair, by namespace) /chairN/joy_override."""
    store = get_typestore(Stores.ROS2_JAZZY)
    out = tmp_path / "two"
    with Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        for ns in ("/chair1", "/chair2"):
            one = tmp_path / ns.strip("/")
            _write_custom(one, "geometry_msgs/msg/TwistStamped",
                          overrides=overrides.get(ns, ()))
            with AnyReader([one], default_typestore=store) as r:
                conns = {c.topic: w.add_connection(ns + c.topic, c.msgtype, typestore=store)
                         for c in r.connections}
                for c, t, raw in r.messages():
                    w.write(conns[c.topic], t, raw)
    return out


def test_the_default_override_topic_is_the_joysticks_chairs(tmp_path, caplog):
    """A recording of two chairs (/chair1/*, /chair2/*): reading /chair2/joy, the default
    override topic is /chair2/joy_override (joy_override in the joystick's namespace, as a
    node there resolves it), not /joy_override; it was, and the warning then told the user
    to read the first in sorted order, /chair1/joy_override: the other chair's overrides
    (a real two-chair bag scored 73.2 % with them, 79.0 % with its own)."""
    two = _two_chairs(tmp_path, {"/chair1": (10, 12), "/chair2": (3,)})
    t0 = 1_600_000_000.0
    s2 = read_streams(two, joy_topic="/chair2/joy", twist_topic="/chair2/twist")
    np.testing.assert_allclose(s2.override_t - t0, [0.305], atol=1e-6)
    s1 = read_streams(two, joy_topic="/chair1/joy", twist_topic="/chair1/twist")
    np.testing.assert_allclose(s1.override_t - t0, [1.005, 1.205], atol=1e-6)
    assert "override" not in caplog.text
    # the command line's default is the same
    parser = argparse.ArgumentParser()
    add_topic_args(parser)
    args = parser.parse_args(["--joy-topic", "/chair2/joy", "--twist-topic", "/chair2/twist"])
    res = read_series_or_fail([str(two)], args)[0].res
    assert res.overridden.sum() == read_series(
        [str(two)], joy_topic="/chair2/joy", twist_topic="/chair2/twist",
        override_topic="/chair2/joy_override")[0].res.overridden.sum() > 0
    # an explicit relative name is taken in the joystick's namespace too; an absolute one
    # as it is
    assert read_streams(two, joy_topic="/chair2/joy", twist_topic="/chair2/twist",
                        override_topic="joy_override").override_t.size == 1
    assert read_streams(two, joy_topic="/chair2/joy", twist_topic="/chair2/twist",
                        override_topic="/chair1/joy_override").override_t.size == 2
    # a misspelt one: the hint names this chair's, not the first in sorted order
    caplog.clear()
    read_streams(two, joy_topic="/chair2/joy", twist_topic="/chair2/twist",
                 override_topic="/chair2/joy_overide")
    assert "--override-topic /chair2/joy_override reads it" in caplog.text
    # only the other chair sent overrides: said, never offered as this chair's
    caplog.clear()
    one = _two_chairs(tmp_path / "one", {"/chair1": (10,)})
    assert read_streams(one, joy_topic="/chair2/joy",
                        twist_topic="/chair2/twist").override_t.size == 0
    assert "/chair1/joy_override" in caplog.text
    assert "none in the joystick /chair2/joy's namespace: not read" in caplog.text
    assert "--override-topic /chair1" not in caplog.text


def test_ros1_custom_bag(tmp_path):
    path = tmp_path / "old.bag"
    _write_custom(path, "geometry_msgs/msg/TwistStamped", ros1=True)
    s = read_streams(path, twist_topic="/twist", joy_axes="1,-0")
    np.testing.assert_allclose(s.joy[0], [-0.5, -0.25])


def test_invalid_header_stamps_fall_back_to_bag_time(tmp_path):
    path = tmp_path / "b"
    _write_custom(path, "geometry_msgs/msg/TwistStamped", zero_stamps=True)
    s = read_streams(path, twist_topic="/twist")
    np.testing.assert_allclose(s.vel_t, 1_600_000_000.02 + 0.1 * np.arange(20), atol=1e-6)
    # Some stamps invalid: those use bag time minus the topic's median latency (20 ms),
    # so the series stays on the header clock.
    mixed = tmp_path / "mixed"
    _write_custom(mixed, "geometry_msgs/msg/TwistStamped", zero_stamps="odd")
    s = read_streams(mixed, twist_topic="/twist")
    np.testing.assert_allclose(s.vel_t, 1_600_000_000.0 + 0.1 * np.arange(20), atol=1e-6)


def test_joy_axes_syntax_and_mapping(tmp_path):
    assert parse_joy_axes("0,1") == JoyAxes()
    assert parse_joy_axes("1,-0") == JoyAxes(forward=1, turn=0, turn_sign=-1.0)
    assert parse_joy_axes(" -3 , 2 ") == JoyAxes(forward=3, turn=2, forward_sign=-1.0)
    assert str(parse_joy_axes("1,-0")) == "1,-0"
    for bad in ("0", "0,0", "a,1", "0,1,2", "-,1", ""):
        with pytest.raises(ValueError, match="joy-axes"):
            parse_joy_axes(bad)
    path = tmp_path / "b"
    _write_custom(path, "geometry_msgs/msg/TwistStamped")
    s = read_streams(path, twist_topic="/twist", joy_axes="2,-1")
    np.testing.assert_allclose(s.joy[0], [0.75, 0.5])
    with pytest.raises(BagError, match=r"needs 4"):
        read_streams(path, twist_topic="/twist", joy_axes="3,0")


# ----------------------------------------------------------------------------- errors
def test_missing_bag_and_not_a_bag(tmp_path):
    with pytest.raises(BagError, match="no such bag"):
        read_streams(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(BagError, match=r"metadata\.yaml"):
        read_streams(tmp_path / "empty")
    (tmp_path / "x.txt").write_text("hello")
    with pytest.raises(BagError, match="not a bag"):
        read_streams(tmp_path / "x.txt")


def test_missing_topic_lists_the_bag_topics(mcap_bag):
    with pytest.raises(BagError) as err:
        read_streams(mcap_bag, twist_topic="/vo/odom")
    msg = str(err.value)
    assert str(mcap_bag) in msg and "/vo/odom" in msg
    assert "/vo/twist [geometry_msgs/msg/TwistStamped]" in msg
    assert "/joy [sensor_msgs/msg/Joy]" in msg


def test_unsupported_type(mcap_bag):
    with pytest.raises(BagError, match="unsupported type sensor_msgs/msg/Joy"):
        read_streams(mcap_bag, twist_topic="/joy")
    with pytest.raises(BagError, match="unsupported type"):
        read_streams(mcap_bag, truth_topic="/vo/twist")


def test_truncated_and_corrupt_bags(mcap_bag, rec, tmp_path, caplog):
    """A cut bag is read as far as its complete messages go, with a warning (see
    test_bag_repair.py); a bag with nothing recoverable is a one-line error."""
    bad = tmp_path / "drive"
    shutil.copytree(mcap_bag, bad)
    data = (bad / "drive.mcap").read_bytes()
    (bad / "drive.mcap").write_bytes(data[: len(data) // 2])
    with caplog.at_level("WARNING", logger="asgp_ros.recording.bags"):
        s = read_streams(bad)
    assert 0 < s.joy_t.size < rec.joy_t.size and "damaged mcap bag" in caplog.text
    r1 = write_bag(tmp_path / "one.bag", rec)
    raw = r1.read_bytes()
    r1.write_bytes(raw[: len(raw) // 3])
    assert 0 < read_streams(r1).joy_t.size < rec.joy_t.size
    r1.write_bytes(raw[:4200])  # the bag header only
    with pytest.raises(BagError, match=r"one\.bag.*nothing recoverable"):
        read_streams(r1)
    (tmp_path / "junk.bag").write_bytes(b"#ROSBAG V2.0\n" + bytes(range(256)) * 8)
    with pytest.raises(BagError, match=r"junk\.bag") as err:
        read_streams(tmp_path / "junk.bag")
    assert "\n" not in str(err.value)


def test_failed_write_leaves_nothing(rec, tmp_path, monkeypatch):
    target = tmp_path / "drive"
    real_write = Writer.write

    def failing_write(self, conn, ts, data):
        if self.counts[conn.id] > 100:
            raise OSError("disk full")
        return real_write(self, conn, ts, data)

    monkeypatch.setattr(Writer, "write", failing_write)
    with pytest.raises(BagError, match="disk full"):
        write_bag(target, rec)
    assert not target.exists()
    assert list(tmp_path.iterdir()) == []
    # the sqlite3 storage on a full disk raises sqlite3's error (it was a traceback)
    import sqlite3

    def full_database(self, conn, ts, data):
        raise sqlite3.OperationalError("database or disk is full")

    monkeypatch.setattr(Writer, "write", full_database)
    with pytest.raises(BagError, match=r"cannot write bag: .*database or disk is full"):
        write_bag(target, rec, storage="sqlite3")
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(BagError, match="storage"):
        write_bag(tmp_path / "x", rec, storage="zip")


# ----------------------------------------------------------------------------- untrusted paths
def _read_with_deadline(call: str, deadline_s: float = 30.0) -> str:
    """Run a reader call in a fresh interpreter; a hang fails the test, not the suite.

    Returns what the call printed (the BagError's message, or "read").
    """
    import subprocess
    import sys

    code = ("import resource\n"  # a reader that slurps a device fails, not the machine
            "resource.setrlimit(resource.RLIMIT_AS, (3 * 2**30, 3 * 2**30))\n"
            "from asgp_ros.recording import bags\n"
            f"try:\n    {call}\n    print('read')\n"
            "except bags.BagError as exc:\n    print(exc)\n")
    try:
        proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                              timeout=deadline_s, check=False)
    except subprocess.TimeoutExpired:
        pytest.fail(f"hung for {deadline_s} s: {call}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout.strip()


def test_a_fifo_bag_is_refused_without_blocking(tmp_path):
    """Issue 16: readers opened FIFOs and blocked forever."""
    import os

    fifo = tmp_path / "drive.bag"
    os.mkfifo(fifo)
    out = _read_with_deadline(f"bags.read_streams({str(fifo)!r})")
    assert out == (f"{fifo}: is a FIFO (named pipe), not a regular file: a bag is a ROS 1 "
                   ".bag file or a ROS 2 bag directory")
    link = tmp_path / "link.bag"
    link.symlink_to(fifo)
    with pytest.raises(BagError, match=r"link\.bag: is a FIFO"):
        bags.bag_topics(link)


def test_a_fifo_storage_file_inside_a_bag_is_refused(mcap_bag, tmp_path):
    import os

    bad = tmp_path / "drive"
    shutil.copytree(mcap_bag, bad)
    (bad / "drive.mcap").unlink()
    os.mkfifo(bad / "drive.mcap")
    for call in (f"bags.read_streams({str(bad)!r})", f"bags.bag_topics({str(bad)!r})",
                 f"bags.read_streams({str(bad / 'drive.mcap')!r})"):
        out = _read_with_deadline(call)
        assert out.startswith(f"{bad / 'drive.mcap'}: is a FIFO (named pipe), not a regular "
                              "file"), call


@pytest.mark.parametrize("kind", ["fifo", "directory", "dev_zero", "huge", "dangling"])
def test_special_metadata_yaml_is_refused(mcap_bag, tmp_path, kind):
    import os

    bad = tmp_path / "drive"
    shutil.copytree(mcap_bag, bad)
    meta = bad / "metadata.yaml"
    meta.unlink()
    if kind == "fifo":
        os.mkfifo(meta)
        why = "is a FIFO"
    elif kind == "directory":
        meta.mkdir()
        why = "is a directory, not a regular file"
    elif kind == "dev_zero":
        meta.symlink_to("/dev/zero")
        why = "is a character device"
    elif kind == "huge":
        with open(meta, "wb") as fh:
            fh.truncate(bags.MAX_BAG_METADATA_BYTES + 1)
        why = "more than the limit"
    else:
        meta.symlink_to(tmp_path / "nowhere")
        why = "not a ROS 2 bag"
    out = _read_with_deadline(f"bags.read_streams({str(bad)!r})")
    assert why in out and (str(meta) in out or str(bad) in out), out
    with pytest.raises(BagError, match=why):
        bags.read_sim_metadata(bad)


def test_devices_and_sockets_are_not_bags(tmp_path):
    import os
    import socket

    dev = tmp_path / "zero.bag"
    dev.symlink_to("/dev/zero")
    assert _read_with_deadline(f"bags.read_streams({str(dev)!r})").startswith(
        f"{dev}: is a character device")
    sock = tmp_path / "s.bag"
    with socket.socket(socket.AF_UNIX) as s:
        s.bind(str(sock))
        with pytest.raises(BagError, match=r"s\.bag: is a socket"):
            read_streams(sock)
    loop = tmp_path / "loop.bag"
    os.symlink(loop.name, loop)
    with pytest.raises(BagError, match=r"loop\.bag: cannot be read"):
        read_streams(loop)


def test_errors_are_one_line_naming_the_bag(mcap_bag, tmp_path):
    bad = tmp_path / "drive"
    shutil.copytree(mcap_bag, bad)
    meta = bad / "metadata.yaml"
    meta.write_text(meta.read_text().replace("rosbag2_bagfile_information:",
                                             "rosbag2_bagfile_information:\x1f", 1))
    for reader in (read_streams, bags.bag_topics, bags.read_sim_metadata):
        with pytest.raises(BagError) as err:
            reader(bad)
        assert "\n" not in str(err.value) and str(bad) in str(err.value)


def test_deeply_nested_simulation_metadata_is_refused(mcap_bag, tmp_path):
    """The simulator's JSON description in metadata.yaml is parsed with bounded depth."""
    import yaml

    bad = tmp_path / "drive"
    shutil.copytree(mcap_bag, bad)
    meta = yaml.safe_load((bad / "metadata.yaml").read_text())
    custom = meta["rosbag2_bagfile_information"]["custom_data"]
    custom[bags.CUSTOM_DATA_KEY] = "[" * 50_000 + "]" * 50_000
    (bad / "metadata.yaml").write_text(yaml.safe_dump(meta))
    with pytest.raises(BagError, match="unreadable simulation description: nested 50000 "
                                       "levels deep"):
        bags.read_sim_metadata(bad)
    custom[bags.CUSTOM_DATA_KEY] = '{"seed": NaN}'
    (bad / "metadata.yaml").write_text(yaml.safe_dump(meta))
    with pytest.raises(BagError, match="not a finite number"):
        bags.read_sim_metadata(bad)


@pytest.mark.parametrize("text", ["", "- 1\n- 2\n", "rosbag2_bagfile_information: 3\n"])
def test_metadata_that_is_not_a_bags_is_named(mcap_bag, tmp_path, text):
    bad = tmp_path / "drive"
    shutil.copytree(mcap_bag, bad)
    (bad / "metadata.yaml").write_text(text)
    with pytest.raises(BagError, match=r"metadata\.yaml: not the metadata of a ROS 2 bag"):
        read_streams(bad)


def test_out_of_range_samples_in_a_bag_are_reported(rec, tmp_path, caplog):
    """Values beyond the physical ranges are dropped by the resampler; the reader says so."""
    import dataclasses

    joy = rec.joy.copy()
    joy[5] = (3.0, 0.0)  # raw counts, a wrong scale...
    bad = write_recording(tmp_path / "scaled", dataclasses.replace(rec, joy=joy), truth=False)
    with caplog.at_level("WARNING", logger="asgp_ros.recording.bags"):
        s = read_streams(bad)
    assert s.joy[5, 0] == 3.0  # read as recorded
    assert "1 of" in caplog.text and "joystick samples on /joy" in caplog.text


def test_a_ros1_bag_without_its_version_line_is_refused_at_once(tmp_path):
    """The ROS 1 reader looks for the end of the version line with readline(): a sparse
    1 TiB file of zeros named .bag made it read for ever."""
    from asgp_ros.recording.bags import BagError, read_streams

    huge = tmp_path / "huge.bag"
    with open(huge, "wb") as fh:
        fh.truncate(1 << 40)  # sparse: takes no disk space
    with pytest.raises(BagError, match="not a ROS 1 bag"):
        read_streams(huge)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
@pytest.mark.parametrize("value", ["&a [*a]", "[1, 2]", "3", "{x: 1}"])
def test_metadata_naming_a_type_that_is_not_text_reads_from_a_scan(rec, tmp_path, storage,
                                                                    value, caplog):
    """A metadata.yaml whose topic type is a YAML alias cycle, a list, a number or a map
    (found by benchmarks/fuzz.py, seed 3317: a TypeError and a traceback) is a damaged
    bag: its storage is scanned as for a killed recording, or a one-line BagError."""
    bag = write_bag(tmp_path / "drive", rec, storage=storage)
    meta = bag / "metadata.yaml"
    text = meta.read_text()
    first = text.index("type: ") + len("type: ")
    end = text.index("\n", first)
    meta.write_text(text[:first] + value + text[end:])
    with caplog.at_level("WARNING", logger="asgp_ros.recording.bags"):
        try:
            s = read_streams(bag)
        except BagError as exc:
            assert "\n" not in str(exc) and "drive" in str(exc)
        else:
            _check_streams(s, rec, truth=False)
            # one warning that says what is damaged, and that the storage itself is whole
            assert "not text" in caplog.text and "its storage is intact" in caplog.text
            assert "damaged" not in caplog.text and ": intact (" not in caplog.text


def test_a_bags_topic_names_cannot_forge_rows_of_bag_info(tmp_path, capsys):
    """A topic name holding a newline and a terminal escape printed a false '/vo/twist ...
    9999' row in asgp bag info."""
    from asgp_ros.cli import main
    from asgp_ros.recording.bags import BagContent

    store = get_typestore(Stores.ROS1_NOETIC)
    data = bytes(store.serialize_ros1(store.types["std_msgs/msg/String"](data="x"),
                                      "std_msgs/msg/String"))
    topic = "/joy\n/vo/twist  geometry_msgs/msg/TwistStamped  9999 \x1b[31m"
    write_bag(tmp_path / "esc.bag", BagContent(
        connections=[(topic, "std_msgs/msg/String")],
        messages=[(1_700_000_000_000_000_000 + i * 10**8, 0, data) for i in range(5)]))
    assert main(["bag", "info", str(tmp_path / "esc.bag")]) == 0
    out = capsys.readouterr().out
    assert "\x1b" not in out and not any(line.startswith("/vo/twist")
                                         for line in out.splitlines()), out


def test_twists_in_a_camera_frame_are_not_read_as_the_chairs(tmp_path, caplog):
    """A backward camera's twists (frame camera_link, linear.x the negated forward speed),
    which the nodes refuse: training read them as the chair's (a forward drive learnt as a
    reverse one, scored 96 % against that VO and 19-25 % against the truth)."""
    import logging

    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    from asgp_ros.recording.bags import BagError, read_streams, write_bag
    from asgp_ros.sim.simulate import simulate

    store = get_typestore(Stores.ROS2_JAZZY)
    clean = write_bag(tmp_path / "clean", simulate("tile", 1.0, 3))
    ref = read_streams(clean)

    def rewrite(dst, camera, frame=lambda n: "camera_link") -> Path:
        with AnyReader([clean], default_typestore=store) as r, Writer(dst, version=9) as w:
            conns = [c for c in r.connections if c.topic in ("/joy", "/vo/twist")]
            out = {c.topic: w.add_connection(c.topic, c.msgtype, typestore=store)
                   for c in conns}
            n = 0
            for c, t, raw in r.messages(connections=conns):
                if c.topic == "/vo/twist":
                    msg = r.deserialize(raw, c.msgtype)
                    if camera(n):
                        msg.header.frame_id = frame(n)
                        msg.twist.linear.x = -msg.twist.linear.x
                    n += 1
                    raw = bytes(store.serialize_cdr(msg, c.msgtype))
                w.write(out[c.topic], t, raw)
        return dst

    every = rewrite(tmp_path / "camera", lambda n: True)
    with pytest.raises(BagError, match="frame 'camera_link', not base_frame 'base_link'"):
        read_streams(every)
    as_camera = read_streams(every, base_frame="camera_link")  # (said to be the chair's)
    np.testing.assert_allclose(as_camera.vel[:, 0], -ref.vel[:, 0])
    # a twist in a distinct, long frame each: the error names a few, not all (it was as
    # long as the bag)
    many = rewrite(tmp_path / "many", lambda n: True, frame=lambda n: f"cam_{n}_" + "x" * 500)
    with pytest.raises(BagError, match="other frames") as info:
        read_streams(many)
    assert len(str(info.value)) < 1000
    some = rewrite(tmp_path / "some", lambda n: n % 10 == 0)
    with caplog.at_level(logging.WARNING):
        got = read_streams(some)
    assert "are in frame 'camera_link'" in caplog.text
    assert np.count_nonzero(~got.vel_ok) >= len(got.vel_ok) // 10 - 1
    assert got.vel.shape == ref.vel.shape  # the others as they were, none negated
    np.testing.assert_array_equal(got.vel[got.vel_ok], ref.vel[got.vel_ok])


def _map_message(store):
    """A 2 x 2 map (for the latched-topic tests)."""
    t = store.types
    stamp = t["builtin_interfaces/msg/Time"](sec=1_700_000_000, nanosec=0)
    extra = {"seq": 0} if "seq" in t["std_msgs/msg/Header"].__dataclass_fields__ else {}
    header = t["std_msgs/msg/Header"](stamp=stamp, frame_id="odom", **extra)
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
    info = t["nav_msgs/msg/MapMetaData"](
        map_load_time=t["builtin_interfaces/msg/Time"](sec=0, nanosec=0), resolution=0.05,
        width=2, height=2, origin=pose)
    return t["nav_msgs/msg/OccupancyGrid"](header=header, info=info,
                                           data=np.zeros(4, dtype=np.int8))


@pytest.mark.parametrize("ros1", [False, True], ids=["ros2", "ros1"])
def test_a_repaired_copy_keeps_a_latched_topic_latched(tmp_path, ros1):
    """`asgp bag repair` of a bag whose /map was recorded latched (ROS 2: offered transient
    local; ROS 1: latching): the copy lost it, and a replay of the copy published the map
    volatile, which the layer (subscribing transient local) never got."""
    from rosbags.highlevel import AnyReader
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import Writer as Writer2
    from rosbags.typesys import Stores, get_typestore

    from asgp_ros.recording.bags import repair_bag
    from asgp_ros.recording.replay import _is_transient_local

    def latched(path: Path) -> dict[str, bool]:
        with AnyReader([path]) as r:
            return {c.topic: _is_transient_local(c) for c in r.connections}

    kind = "nav_msgs/msg/OccupancyGrid"
    if ros1:
        store = get_typestore(Stores.ROS1_NOETIC)
        src = tmp_path / "rec.bag"
        with Writer1(src) as w:
            c = w.add_connection("/map", kind, typestore=store, latching=1)
            w.write(c, 1_700_000_000_000_000_000,
                    store.serialize_ros1(_map_message(store), kind))
    else:
        store = get_typestore(Stores.ROS2_JAZZY)
        qos = Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE,
                  QosDurability.TRANSIENT_LOCAL, QosTime(0, 0), QosTime(0, 0),
                  QosLiveliness.AUTOMATIC, QosTime(0, 0), False)
        src = tmp_path / "rec"
        with Writer2(src, version=9) as w:
            c = w.add_connection("/map", kind, typestore=store, offered_qos_profiles=[qos])
            w.write(c, 1_700_000_000_000_000_000,
                    store.serialize_cdr(_map_message(store), kind))
    assert latched(src) == {"/map": True}
    out = tmp_path / ("fixed.bag" if ros1 else "fixed")
    repair_bag(src, out)
    assert latched(out) == {"/map": True}
