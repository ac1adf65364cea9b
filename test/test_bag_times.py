"""Recordings whose clock was not well behaved, read for training and scoring: the laptop's
clock stepped back during the recording (NTP setting a clock that ran ahead: the bag times
and the stamps step together, or the recorder's alone), a camera computer whose clock is
not the laptop's, a stray time. Every reader sorts a bag by time, so two timelines after a
step back were interleaved into one and trained on without a word."""

from __future__ import annotations

import logging
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from asgp_ros.recording import bags
from asgp_ros.recording.bags import PART_GAP_S, clock_parts, read_streams, write_bag
from asgp_ros.sim.simulate import simulate

S = 1_000_000_000
STORE = get_typestore(Stores.ROS2_JAZZY)
TOPICS = ("/joy", "/vo/twist")

#: (topic, bag time ns, stamp ns, seconds into the recording) -> (bag time, stamp)
Retime = Callable[[str, int, int, float], tuple[int, int]]


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> Path:
    return write_bag(tmp_path_factory.mktemp("times") / "clean", simulate("tile", 1.5, 3))


def _rewrite(src: Path, dst: Path, storage: str, retime: Retime) -> Path:
    """``src`` written again in its order (as a recorder writes: SQLite row ids, mcap
    records), each message's bag time and header stamp as ``retime`` says."""
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with AnyReader([src], default_typestore=STORE) as r, \
            Writer(dst, version=9, storage_plugin=plugin) as w:
        conns = [c for c in r.connections if c.topic in TOPICS]
        out = {c.topic: w.add_connection(c.topic, c.msgtype, typestore=STORE) for c in conns}
        t0 = None
        for c, t, raw in r.messages(connections=conns):
            t0 = t if t0 is None else t0
            msg = r.deserialize(raw, c.msgtype)
            stamp = msg.header.stamp.sec * S + msg.header.stamp.nanosec
            log_ns, stamp_ns = retime(c.topic, t, stamp, (t - t0) / S)
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), S)
            w.write(out[c.topic], int(log_ns), bytes(STORE.serialize_cdr(msg, c.msgtype)))
    return dst


def _step(at_s: float, by_s: float, *, log: bool = True, stamp: bool = True,
          topic: str | None = None) -> Retime:
    d = round(by_s * S)

    def retime(name: str, t: int, s: int, rel: float) -> tuple[int, int]:
        moved = rel >= at_s and (topic is None or name == topic)
        return t + d * (moved and log), s + d * (moved and stamp)
    return retime


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
@pytest.mark.parametrize("back_s", [30.0, 300.0])
def test_a_clock_stepped_back_is_read_as_two_parts_one_after_the_other(
        clean, tmp_path, caplog, storage, back_s):
    """The clock (bag times and stamps) steps back 30 s / 5 min a minute in: sorted by time,
    the minute before and the half minute after were interleaved (the joystick at twice its
    rate, jumping between two drives). Read in the order written, the two parts follow one
    another, PART_GAP_S apart, with every sample in its order and no sample lost."""
    ref = read_streams(clean)
    bag = _rewrite(clean, tmp_path / "stepped", storage, _step(60.0, -back_s))
    with caplog.at_level(logging.WARNING):
        got = read_streams(bag)
    said = re.search(r"clock stepped back 1 time\(s\) during the recording \(([0-9.]+) s",
                     caplog.text)
    assert said and abs(float(said.group(1)) - back_s) < 1.0, caplog.text
    np.testing.assert_array_equal(got.joy, ref.joy)
    np.testing.assert_array_equal(got.vel, ref.vel)
    gaps = np.diff(got.joy_t)
    assert np.count_nonzero(gaps > 1.0) == 1
    assert PART_GAP_S <= gaps.max() < PART_GAP_S + 1.0
    # each part keeps its own times: the first exactly, the second moved as one
    first = ref.joy_t < ref.joy_t[0] + 60.0
    np.testing.assert_array_equal(got.joy_t[first], ref.joy_t[first])
    shift = got.joy_t[~first] - ref.joy_t[~first]
    assert np.ptp(shift) < 1e-6


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_the_recorders_clock_alone_stepped_back_loses_nothing(clean, tmp_path, caplog,
                                                               storage):
    """Only the recorder's clock steps back 5 s (the bridge and VO stamped on a clock that
    did not): the first minute was dropped as "stale readings delivered late" (judged by one
    latency for the whole recording). Each part is judged on its own latency: every sample
    is kept, on its own stamp."""
    ref = read_streams(clean)
    bag = _rewrite(clean, tmp_path / "recorder", storage, _step(60.0, -5.0, stamp=False))
    with caplog.at_level(logging.WARNING):
        got = read_streams(bag)
    assert "stale" not in caplog.text
    np.testing.assert_array_equal(got.joy_t, ref.joy_t)
    np.testing.assert_array_equal(got.vel_t, ref.vel_t)
    np.testing.assert_array_equal(got.joy, ref.joy)


@pytest.mark.parametrize("retime", [_step(0.0, -3.0, log=False, topic="/vo/twist"),
                                    _step(0.0, 3.0, log=False, topic="/vo/twist")],
                         ids=["behind", "ahead"])
def test_a_stream_stamped_on_another_computers_clock_is_read_on_its_bag_times(
        clean, tmp_path, caplog, retime):
    """The VO stamped 3 s behind (or ahead of) the laptop's clock, within the 10 s a stamp
    may lie from its bag time: used as it was, the chair's velocity was learnt 3 s away from
    the stick that drove it, without a word. Its latency is compared with the joystick's
    (stamped on the recorder's computer): off by more than MAX_EXTRA_LATENCY, its bag times
    are used, less the joystick's latency."""
    ref = read_streams(clean)
    bag = _rewrite(clean, tmp_path / "camera", "mcap", retime)
    with caplog.at_level(logging.WARNING):
        got = read_streams(bag)
    assert "not on the recorder's clock" in caplog.text
    assert got.vel_t.shape == ref.vel_t.shape
    assert np.max(np.abs(got.vel_t - ref.vel_t)) < 0.2


def test_a_stamp_the_clock_had_not_reached_is_not_used(clean, tmp_path, caplog):
    """A few VO messages stamped 4 s after they were recorded (a stamp the clock had not
    reached) were placed 4 s in the future; their bag times are used."""
    ref = read_streams(clean)

    def retime(name: str, t: int, s: int, rel: float) -> tuple[int, int]:
        return t, s + 4 * S * (name == "/vo/twist" and 30.0 <= rel < 31.0)
    with caplog.at_level(logging.WARNING):
        got = read_streams(_rewrite(clean, tmp_path / "ahead", "mcap", retime))
    assert "stamped more than 1.0 s later" in caplog.text
    assert np.max(np.abs(got.vel_t - ref.vel_t)) < 0.2


def test_stray_times_are_no_clock_step():
    """One message logged in 1970 or in 2100 among the others, or a step back in the last
    two messages, is no step of the recorder's clock; a step back followed by more is."""
    t = np.arange(100, dtype=np.int64) * (S // 10) + 1_700_000_000 * S
    assert not clock_parts(t).any()
    for stray in (0, 4_100_000_000 * S):
        odd = t.copy()
        odd[50] = stray
        assert not clock_parts(odd).any()
    jitter = t + np.random.default_rng(0).integers(-S // 5, S // 5, t.size)  # 0.2 s
    assert not clock_parts(jitter).any()
    stepped = t.copy()
    stepped[60:] -= 30 * S
    parts = clock_parts(stepped)
    assert parts[:60].tolist() == [0] * 60 and parts[60:].tolist() == [1] * 40
    late = t.copy()
    late[98:] -= 30 * S
    assert not clock_parts(late).any()


def test_the_scan_reads_what_rosbags_reads_when_the_clock_did_not_step(clean, monkeypatch):
    """A recording whose clock never stepped back is read by rosbags, as before; the check
    reads the bag times alone."""
    scanned: list[object] = []
    real = bags.recover_bag

    def spy(*args: object, **kwargs: object) -> bags.RecoveredBag:
        scanned.append(kwargs.get("topics"))
        return real(*args, **kwargs)  # type: ignore[arg-type]
    monkeypatch.setattr(bags, "recover_bag", spy)
    read_streams(clean)
    assert scanned == [()]


def test_the_held_out_part_is_the_last_fifth_of_the_data_across_a_clock_step_forward(
        clean, tmp_path):
    """The clock steps forward 5 minutes half-way through a 1.5-minute recording: cut on
    the grid's span, the "last 20 %" held out 78 % of the data."""
    from asgp_ros.learning.training import data_summary, read_series, split_holdout

    bag = _rewrite(clean, tmp_path / "forward", "mcap", _step(45.0, 300.0))
    for series in (read_series([str(clean)]), read_series([str(bag)])):
        train_part, held = split_holdout(series, 0.2)
        n_train = int(train_part[0].res.valid.sum())
        n_held = int(held[0].res.valid.sum())
        assert abs(n_held / (n_train + n_held) - 0.2) < 0.01
        # the training data's duration leaves the 5 minutes without a sample out (it read
        # 6.5 minutes for a drive of 1.5)
        assert 88.0 < data_summary(series)["duration_s"] < 90.5
        # so does the reproduction's summary of its bags
        from asgp_ros.learning.reproduce.summary import _data

        (minutes,) = [d["minutes"] for d in _data({"b": series[0]}).values()]
        assert 88.0 / 60 < minutes < 90.5 / 60


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_bag_info_says_the_clock_stepped_back_and_repair_keeps_the_order(
        clean, tmp_path, capsys, storage):
    """`asgp bag info` called a bag whose clock stepped back 30 s "intact" at 32.7 Hz of a
    30 Hz joystick, without a word; `asgp bag repair` wrote it sorted by time, which erased
    the only record of its two parts. Info says so; the repaired copy keeps the order its
    messages were written in, and reads as the original does."""
    from asgp_ros.cli import main

    bag = _rewrite(clean, tmp_path / "stepped", storage, _step(60.0, -30.0))
    assert main(["bag", "info", str(bag)]) == 0
    assert "clock:    the recorder's clock stepped back 1 time(s)" in capsys.readouterr().out
    out = tmp_path / "repaired"
    assert main(["bag", "repair", str(bag), str(out)]) == 0
    assert main(["bag", "info", str(out)]) == 0
    assert "stepped back 1 time(s)" in capsys.readouterr().out
    a, b = read_streams(bag), read_streams(out)
    np.testing.assert_array_equal(a.joy_t, b.joy_t)
    np.testing.assert_array_equal(a.vel, b.vel)


def _messages(src: Path) -> list[tuple[str, str, int, bytes]]:
    with AnyReader([src], default_typestore=STORE) as r:
        conns = [c for c in r.connections if c.topic in TOPICS]
        return [(c.topic, c.msgtype, t, bytes(raw))
                for c, t, raw in r.messages(connections=conns)]


def _write_in_order(dst: Path, msgs: list[tuple[str, str, int, bytes]],
                    storage: str = "mcap") -> Path:
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(dst, version=9, storage_plugin=plugin) as w:
        conns: dict[str, object] = {}
        for topic, msgtype, t, raw in msgs:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msgtype, typestore=STORE)
            w.write(conns[topic], int(t), raw)
    return dst


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_a_bag_written_topic_by_topic_is_no_clock_step(clean, tmp_path, caplog, capsys,
                                                       storage):
    """A valid bag written one topic after another (a conversion script): its order of
    records goes back at each topic's start, which was read as the clock stepping back
    (the topics read as parts, asgp bag info saying so). A step must show in the most
    frequent topic's own messages."""
    from asgp_ros.cli import main

    msgs = sorted(_messages(clean), key=lambda m: TOPICS.index(m[0]))  # stable
    bag = _write_in_order(tmp_path / "by_topic", msgs, storage)
    ref = read_streams(clean)
    with caplog.at_level(logging.WARNING):
        got = read_streams(bag)
    assert "stepped back" not in caplog.text
    np.testing.assert_array_equal(got.joy_t, ref.joy_t)
    np.testing.assert_array_equal(got.vel_t, ref.vel_t)
    assert main(["bag", "info", str(bag)]) == 0
    assert "stepped back" not in capsys.readouterr().out


def test_a_killed_split_recording_is_read_in_the_order_of_its_files(clean, tmp_path,
                                                                     caplog):
    """A recording split into 12 files and killed before its metadata.yaml: the files were
    taken in the order of their names as text (rec_10, rec_11 before rec_2), a step back of
    the clock; they are taken by their numbers."""
    import shutil

    msgs = _messages(clean)
    bag = tmp_path / "rec"
    bag.mkdir()
    per = -(-len(msgs) // 12)
    for i in range(12):
        part = _write_in_order(tmp_path / f"p{i}", msgs[i * per:(i + 1) * per])
        shutil.move(str(next(part.glob("*.mcap"))), bag / f"rec_{i}.mcap")
    ref = read_streams(clean)
    with caplog.at_level(logging.WARNING):
        got = read_streams(bag)
    assert "stepped back" not in caplog.text
    np.testing.assert_array_equal(got.joy_t, ref.joy_t)


def test_a_stray_storage_file_beside_an_intact_bag_is_not_read(clean, tmp_path):
    """An older recording's .mcap left in an intact bag's directory (metadata.yaml lists
    only the bag's own file): the clock check scanned every storage file, took the stray
    one's times for a step back, and read the other drive into the bag as its second
    part. An intact bag is what its metadata.yaml lists."""
    import shutil

    other = write_bag(tmp_path / "other", simulate("carpet", 0.5, 4))
    bag = Path(shutil.copytree(clean, tmp_path / "bag"))
    shutil.copy(next(other.glob("*.mcap")), bag / "zz_backup.mcap")
    np.testing.assert_array_equal(read_streams(bag).joy_t, read_streams(clean).joy_t)


def test_a_stream_without_stamps_follows_the_joystick_across_a_recorder_step(clean,
                                                                             tmp_path):
    """The recorder's clock alone steps back 5 s; the VO is a plain Twist (no header: read
    on its bag times). The joystick went on on its stamps while the VO, on bag times, fell
    5 s behind it in the second part; now a stream without stamps is read on the
    joystick's clock (its bag times less the joystick's latency)."""
    from rosbags.typesys.stores.ros2_jazzy import geometry_msgs__msg__Twist as Twist
    from rosbags.typesys.stores.ros2_jazzy import geometry_msgs__msg__Vector3 as Vector3

    msgs = []
    for topic, msgtype, t, raw in _messages(clean):
        if topic == "/vo/twist":
            m = STORE.deserialize_cdr(raw, msgtype)
            tw = Twist(linear=Vector3(x=m.twist.linear.x, y=0.0, z=0.0),
                       angular=Vector3(x=0.0, y=0.0, z=m.twist.angular.z))
            msgtype, raw = "geometry_msgs/msg/Twist", bytes(
                STORE.serialize_cdr(tw, "geometry_msgs/msg/Twist"))
        msgs.append((topic, msgtype, t, raw))
    plain = _write_in_order(tmp_path / "plain", msgs)
    t0 = msgs[0][2]
    stepped = _write_in_order(tmp_path / "stepped", [
        (topic, msgtype, t - 5 * S * (t - t0 >= 60 * S), raw)
        for topic, msgtype, t, raw in msgs])
    ref, got = read_streams(plain), read_streams(stepped)
    np.testing.assert_array_equal(got.joy_t, ref.joy_t)
    np.testing.assert_allclose(got.vel_t, ref.vel_t, atol=0.05)


def test_the_times_of_an_sqlite_bag_are_read_from_the_database_in_the_order_written(
        clean, tmp_path):
    """The clock check reads an SQLite bag's rows by id from the database (a scan of the
    pages follows every camera image's overflow pages): the same order and times as the
    scan of its records."""
    from asgp_ros.recording.bags import recover_bag, written_times

    bag = _rewrite(clean, tmp_path / "stepped", "sqlite3", _step(60.0, -30.0))
    quick = written_times(bag)
    scan = recover_bag(bag, topics=(), record_order=True).messages
    assert [t for _, t, _ in quick] == [t for _, t, _ in scan]
    assert bags.message_parts(quick).tolist() == bags.message_parts(scan).tolist()
    assert bags.message_parts(quick)[-1] == 1


def test_a_first_minute_recorded_in_1970_is_read_on_a_grid_of_its_data(clean, tmp_path):
    """The first 30 s recorded before NTP set the clock (bag times and stamps in 1970): the
    grid over 54 years was refused as "850000 ... grid points", which named no cause. The
    grid leaves out the 54 years without a sample: both parts are read, nothing joined
    across them."""
    from asgp_ros.learning.training import read_series

    def retime(name: str, t: int, s: int, rel: float) -> tuple[int, int]:
        back = 1_690_000_000 * S * (rel < 30.0)
        return t - back, s - back
    bag = _rewrite(clean, tmp_path / "boot", "mcap", retime)
    res = read_series([str(bag)])[0].res
    assert len(res) <= 5 * 90 + 4
    assert len(res.segments()) >= 2
    assert res.t[res.valid].min() < 1e8 < res.t[res.valid].max()


@pytest.fixture(scope="module")
def forward(clean, tmp_path_factory) -> dict[float, Path]:
    """``clean`` with its clock set forward by 60 s and by 20 days 45 s in."""
    d = tmp_path_factory.mktemp("forward")
    return {by: _rewrite(clean, d / f"by{by:.0f}", "mcap", _step(45.0, by))
            for by in (60.0, 20 * 86400.0)}


def test_a_clock_set_forward_20_days_costs_the_grid_of_its_data(forward):
    """A clock set forward 20 days during a 90 s drive: the grid spanned the 20 days, 8.6
    million points (1.5 GB in training and 3 GB in asgp evaluate), every one of them
    invalid. The grid holds the drive's points, and everything read from it is as with
    the clock set forward by a minute: the valid points, the rows, the held-out part, the
    training data's summary, the trained model and its scores, offline and adapting."""
    from asgp_ros.core.features import FeatureConfig, design_matrix
    from asgp_ros.core.modelfile import load_model
    from asgp_ros.learning.evaluation import TestSeries, evaluate_adaptive, evaluate_model
    from asgp_ros.learning.training import (
        TrainOptions,
        data_summary,
        read_series,
        split_holdout,
        train,
    )

    minute, days = (read_series([str(forward[by])])[0] for by in sorted(forward))
    arrays = ("joy", "vel", "valid", "stale", "tracking_lost", "gap", "segment", "truth",
              "truth_valid", "overridden")
    size = sum(getattr(days.res, a).nbytes for a in ("t", "k", *arrays))
    assert len(days.res) <= 5 * 90 + 4 and size < 100_000, (len(days.res), size)
    assert len(days.res) == len(minute.res)
    across = days.res.gap  # interpolated across the silence: the values differ, unused
    for a in arrays:
        np.testing.assert_array_equal(getattr(days.res, a)[~across],
                                      getattr(minute.res, a)[~across], a)
    for c in (0, 1):
        X, y, idx = design_matrix(days.res, c, FeatureConfig(lags=4, coupled=True))
        Xm, ym, idxm = design_matrix(minute.res, c, FeatureConfig(lags=4, coupled=True))
        assert X.shape[0] > 300
        np.testing.assert_array_equal(X, Xm)
        np.testing.assert_array_equal(y, ym)
        np.testing.assert_array_equal(idx, idxm)
    (train_d,), (held_d,) = split_holdout([days], 0.2)
    (train_m,), (held_m,) = split_holdout([minute], 0.2)
    assert int(held_d.res.valid.sum()) == int(held_m.res.valid.sum()) > 0
    assert int(train_d.res.valid.sum()) == int(train_m.res.valid.sum())
    summary_d, summary_m = data_summary([days]), data_summary([minute])
    for key in ("grid_samples", "valid_samples", "segments", "stale_fraction"):
        assert summary_d[key] == summary_m[key], key
    assert summary_d["duration_s"] == pytest.approx(summary_m["duration_s"], abs=1.0)
    assert summary_d["duration_s"] < 100.0

    fitted = train([minute], TrainOptions(kind="first_order_lag"))
    scores = [evaluate_model(fitted, [TestSeries("drive", s.res)], [1.0, 2.0]).to_json()
              for s in (days, minute)]
    assert scores[0] == scores[1]
    model = load_model(Path(__file__).parents[1] / "docs" / "reproduction" / "models"
                       / "tile_asgp.npz")
    adapting = [evaluate_adaptive(model, [TestSeries("drive", s.res, s.raw)], [1.0])
                for s in (days, minute)]
    assert adapting[0].adapted.to_json() == adapting[1].adapted.to_json()
    assert adapting[0].plain.to_json() == adapting[1].plain.to_json()
    assert adapting[0].missing == adapting[1].missing


def test_a_recording_of_thousands_of_clock_steps_is_read_in_a_few_lines(clean, tmp_path,
                                                                        caplog):
    """The clock stepped back a second every 0.2 s (a hostile or broken recorder: 445 steps
    in 90 s): every part was said on a line of its own (5,928 lines for a 20-minute bag).
    The recording is read, and said in a few lines."""
    import math

    def retime(name: str, t: int, s: int, rel: float) -> tuple[int, int]:
        back = math.floor(rel / 0.2) * S
        return t - back, s - back
    bag = _rewrite(clean, tmp_path / "many", "mcap", retime)
    with caplog.at_level(logging.WARNING):
        got = read_streams(bag)
    assert got.joy_t.size == read_streams(clean).joy_t.size
    assert "parts overlapped the parts before them" in caplog.text
    assert len(caplog.records) < 10, caplog.text[-2000:]
