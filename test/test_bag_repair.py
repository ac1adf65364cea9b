"""Recordings that were killed: bags cut at many offsets are read by a scan (never a crash,
never a wrong message, the count monotone in the cut), repaired into indexed bags, and
described by ``asgp bag info``."""

from __future__ import annotations

import shutil
import sqlite3
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from asgp_ros.cli import main
from asgp_ros.recording import bags
from asgp_ros.recording.bags import BagError, read_streams, recover_bag, repair_bag
from asgp_ros.sim.simulate import simulate, write_recording

STORAGES = ("mcap", "sqlite3", "ros1")
COMPRESSED = ("mcap-zstd", "ros1-lz4", "ros1-bz2")  # chunks compressed by the recorder
CUTS = 48  # offsets per format, spread over the whole file


@pytest.fixture(scope="module")
def rec():
    # 100 s: more than one 1 MB chunk in mcap and ROS 1, a few hundred SQLite pages.
    return simulate("hybrid", 100.0 / 60.0, 11)


@pytest.fixture(scope="module")
def written(rec, tmp_path_factory):
    """storage -> (bag, its storage file, the messages per topic as rosbags reads them)."""
    root = tmp_path_factory.mktemp("bags")
    out = {}
    for storage in STORAGES:
        bag = write_recording(root / ("drive.bag" if storage == "ros1" else storage), rec,
                              storage=storage)
        data_file = bag if storage == "ros1" else next(
            p for p in bag.iterdir() if p.suffix in (".mcap", ".db3"))
        out[storage] = (bag, data_file, _indexed_messages(bag))
    for kind in COMPRESSED:
        bag = _write_compressed(root / (kind + (".bag" if kind.startswith("ros1") else "")),
                                rec, kind)
        data_file = bag if bag.is_file() else bag / f"{bag.name}.mcap"
        out[kind] = (bag, data_file, _indexed_messages(bag))
    return out


def _write_compressed(path: Path, rec, kind: str) -> Path:
    """The recording in a bag whose chunks are compressed (zstd mcap, lz4 or bz2 ROS 1)."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
    from rosbags.typesys import Stores, get_typestore

    ros1 = kind.startswith("ros1")
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_JAZZY)
    content = rec.bag_content(store, ros1)
    w: Writer1 | Writer
    if ros1:
        w = Writer1(path)
        w.set_compression(Writer1.CompressionFormat.LZ4 if kind == "ros1-lz4"
                          else Writer1.CompressionFormat.BZ2)
    else:
        w = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
        w.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with w:
        conns = [w.add_connection(t, m, typestore=store) for t, m in content.connections]
        for t, i, data in sorted(content.messages, key=lambda m: m[0]):
            w.write(conns[i], t, data)
    return path


def _indexed_messages(bag: Path) -> dict[str, list[tuple[int, bytes]]]:
    """Per topic, (bag time, raw message) in order, read through the bag's index."""
    per_topic: dict[str, list[tuple[int, bytes]]] = defaultdict(list)
    with AnyReader([bag]) as reader:
        for conn, t, raw in reader.messages():
            per_topic[conn.topic].append((t, bytes(raw)))
    return dict(per_topic)


def _recovered(r: bags.RecoveredBag) -> dict[str, list[tuple[int, bytes]]]:
    per_topic: dict[str, list[tuple[int, bytes]]] = defaultdict(list)
    for cid, t, raw in r.messages:
        per_topic[r.connections[cid].topic].append((t, raw))
    return dict(per_topic)


def _cut_copy(storage: str, bag: Path, data_file: Path, dest: Path, n: int,
              metadata: bool) -> Path:
    data = data_file.read_bytes()[:n]
    if storage == "ros1":
        target = dest.with_suffix(".bag")
        target.write_bytes(data)
        return target
    dest.mkdir()
    (dest / data_file.name).write_bytes(data)
    if metadata:
        shutil.copy(bag / "metadata.yaml", dest / "metadata.yaml")
    return dest


@pytest.mark.parametrize("kind", STORAGES + COMPRESSED)
def test_cut_bags_give_only_true_messages_and_more_for_a_later_cut(written, tmp_path, kind):
    bag, data_file, original = written[kind]
    storage = kind.split("-")[0]
    size = data_file.stat().st_size
    total = sum(len(v) for v in original.values())
    offsets = sorted({0, 1, 7, 8, 9, 13, 17, 100, 4096, 4097, size - 1, size}
                     | {size * k // CUTS for k in range(CUTS)})
    previous = -1
    counts = []
    for k, n in enumerate(offsets):
        target = _cut_copy(storage, bag, data_file, tmp_path / f"c{k}", n, metadata=k % 2)
        try:
            r = recover_bag(target)
        except BagError as exc:  # nothing recoverable: a one-line error naming the bag
            assert str(target) in str(exc) and "\n" not in str(exc)
            count = 0
        else:
            got = _recovered(r)
            for topic, msgs in got.items():
                # every recovered message is the original's message at that index
                assert msgs == original[topic][:len(msgs)], (kind, n, topic)
            count = r.damage.messages
            assert count == sum(len(v) for v in got.values())
            with_metadata = storage == "ros1" or bool(k % 2)
            assert r.damage.intact == (n == size and with_metadata), (kind, n, r.damage)
            if n < size:
                assert r.damage.problems and str(target) in r.damage.summary()
        assert count >= previous, (kind, n, count, previous)
        previous = count
        counts.append(count)
    assert counts[-1] == total  # the whole file: everything
    three_quarters = counts[offsets.index(size * (3 * CUTS // 4) // CUTS)]
    assert 0 < three_quarters < total  # part of a file: part of it


@pytest.mark.parametrize("storage", STORAGES)
def test_read_streams_recovers_a_cut_bag_with_a_warning(written, rec, tmp_path, storage,
                                                        caplog):
    bag, data_file, original = written[storage]
    size = data_file.stat().st_size
    target = _cut_copy(storage, bag, data_file, tmp_path / "cut", size * 3 // 5,
                       metadata=True)
    with caplog.at_level("WARNING", logger="asgp_ros.recording.bags"):
        s = read_streams(target, truth_topic="/ground_truth/odom")
    assert "damaged" in caplog.text and "asgp bag repair" in caplog.text
    n = s.joy_t.size
    assert 0 < n < rec.joy_t.size
    np.testing.assert_allclose(s.joy, rec.joy[:n], rtol=0, atol=1e-6)
    np.testing.assert_allclose(s.vel, rec.vo[:s.vel_t.size], rtol=0, atol=0)
    if storage != "ros1":  # the recorder never wrote metadata.yaml
        (target / "metadata.yaml").unlink()
        assert read_streams(target).joy_t.size == n
        assert read_streams(target / data_file.name).joy_t.size == n
        assert set(bags.bag_topics(target)) == set(original)


@pytest.mark.parametrize("storage", STORAGES)
def test_repair_writes_an_indexed_bag_with_the_recovered_messages(written, tmp_path,
                                                                  storage):
    bag, data_file, original = written[storage]
    target = _cut_copy(storage, bag, data_file, tmp_path / "cut",
                       data_file.stat().st_size * 2 // 3, metadata=False)
    out = tmp_path / ("fixed.bag" if storage == "ros1" else "fixed")
    recovered = repair_bag(target, out)
    again = _indexed_messages(out)  # rosbags opens it through its index
    assert again == _recovered(recovered)
    for topic, msgs in again.items():
        assert msgs == original[topic][:len(msgs)]
    assert recover_bag(out).damage.intact
    if storage != "ros1":  # the other ROS 2 storage on request
        other = "sqlite3" if storage == "mcap" else "mcap"
        repair_bag(target, tmp_path / "other", storage=other)
        assert _indexed_messages(tmp_path / "other") == again
        with pytest.raises(BagError, match=r"ROS 1 stays|keeps ROS 1"):
            repair_bag(target, tmp_path / "r1.bag", storage="ros1")


def test_repair_command_refuses_to_overwrite_and_never_writes_its_input(written, tmp_path,
                                                                         capsys):
    bag, data_file, _original = written["mcap"]
    cut = _cut_copy("mcap", bag, data_file, tmp_path / "cut", 300_000, metadata=False)
    before = {p.name: p.read_bytes() for p in cut.iterdir()}
    out = tmp_path / "fixed"
    assert main(["bag", "repair", str(cut), str(out)]) == 0
    printed = capsys.readouterr().out
    assert "damaged mcap bag" in printed and f"{out}: wrote" in printed
    assert main(["bag", "repair", str(cut), str(out)]) == 2
    assert "use --force" in capsys.readouterr().err
    assert main(["bag", "repair", str(cut), str(out), "--force"]) == 0
    assert main(["bag", "repair", str(cut), str(cut)]) == 2
    assert main(["bag", "repair", str(cut / data_file.name), str(cut / "x")]) == 2
    assert "input" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in cut.iterdir()} == before
    junk = tmp_path / "junk"
    junk.mkdir()
    (junk / "junk.mcap").write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)))
    assert main(["bag", "repair", str(junk), str(tmp_path / "j2")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "nothing recoverable" in err and err.count("\n") == 1
    assert not (tmp_path / "j2").exists()


def test_info_lists_topics_rates_gaps_and_damage(written, rec, tmp_path, capsys):
    bag, data_file, original = written["mcap"]
    assert main(["bag", "info", str(bag)]) == 0
    out = capsys.readouterr().out
    assert "(mcap, intact)" in out and "damage:" not in out
    for topic, msgs in original.items():
        line = next(ln for ln in out.splitlines() if ln.startswith(topic + " "))
        assert f" {len(msgs)} " in line
    joy_line = next(ln for ln in out.splitlines() if ln.startswith("/joy "))
    assert "sensor_msgs/msg/Joy" in joy_line and " 30.0" in joy_line  # 30 Hz joystick
    duration = float(out.split("duration: ")[1].split(" s")[0])
    assert abs(duration - rec.duration) < 0.5
    # a bag with a hole in the joystick stream: 2 s without /joy
    import dataclasses

    keep = (rec.joy_t < 20.0) | (rec.joy_t > 22.0)
    holed = dataclasses.replace(rec, joy_t=rec.joy_t[keep], joy=rec.joy[keep],
                                joy_bag_t=rec.joy_bag_t[keep])
    hb = write_recording(tmp_path / "holed", holed, truth=False)
    assert main(["bag", "info", str(hb)]) == 0
    out = capsys.readouterr().out
    gaps = [ln for ln in out.splitlines() if ln.startswith("gap /joy:")]
    assert len(gaps) == 1, out
    a_s, b_s = (float(x) for x in gaps[0].split(":")[1].split(" s")[0].split(".."))
    assert 19.9 < a_s < 20.0 and 22.0 < b_s < 22.1  # seconds from the bag's start
    stats = {s.topic: s for s in bags.topic_stats(recover_bag(hb))}
    (a, b), = stats["/joy"].gaps
    assert 1.9 < (b - a) * 1e-9 < 2.1
    assert stats["/vo/twist"].count == rec.vo_t.size
    # a damaged bag: what was lost
    cut = _cut_copy("mcap", bag, data_file, tmp_path / "cut", 500_000, metadata=True)
    assert main(["bag", "info", str(cut)]) == 0
    out = capsys.readouterr().out
    assert "DAMAGED" in out and "damage:" in out and "lost" in out and " s lost at the end" in out


def test_sqlite_write_ahead_log_of_a_killed_recorder_is_read(written, tmp_path):
    """A recorder in WAL mode that was killed leaves the newest rows in the -wal file: the
    scan applies its valid frames; a cut log gives fewer rows, never wrong ones."""
    bag, data_file, original = written["sqlite3"]
    work = tmp_path / "live"
    shutil.copytree(bag, work)
    db = work / data_file.name
    con = sqlite3.connect(db)
    con.execute("PRAGMA journal_mode=WAL")
    con.execute("PRAGMA wal_autocheckpoint=0")
    topic_id = con.execute("SELECT id FROM topics WHERE name='/joy'").fetchone()[0]
    last = con.execute("SELECT max(timestamp) FROM messages").fetchone()[0]
    extra = [(topic_id, last + k * 1000, bytes([k % 256]) * 40) for k in range(1, 301)]
    for k in range(0, 300, 50):  # six commits
        con.executemany("INSERT INTO messages (topic_id, timestamp, data) VALUES (?, ?, ?)",
                        extra[k:k + 50])
        con.commit()
    killed = tmp_path / "killed"
    killed.mkdir()
    shutil.copy(db, killed / db.name)  # the files as the killed process left them
    wal = Path(str(db) + "-wal").read_bytes()
    con.close()
    (killed / (db.name + "-wal")).write_bytes(wal)
    r = recover_bag(killed)
    got = _recovered(r)
    joy = original["/joy"] + [(t, d) for _i, t, d in extra]
    assert got["/joy"] == joy
    previous = -1
    for n in sorted({len(wal) * k // 12 for k in range(12)} | {31, 32, 33, len(wal) - 1}):
        (killed / (db.name + "-wal")).write_bytes(wal[:n])
        got = _recovered(recover_bag(killed))
        assert got["/joy"] == joy[:len(got["/joy"])]
        assert len(got["/joy"]) >= previous
        previous = len(got["/joy"])


def test_a_scan_keeps_only_the_data_it_is_asked_for(written):
    """read_streams keeps the bytes of its topics only (a camera bag is not held in
    memory); every message is still counted with its time."""
    bag, _data_file, original = written["mcap"]
    r = recover_bag(bag, topics=["/joy"])
    got = _recovered(r)
    assert got["/joy"] == original["/joy"]
    for topic in set(original) - {"/joy"}:
        assert [t for t, _ in got[topic]] == [t for t, _ in original[topic]]
        assert all(data == b"" for _t, data in got[topic])


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_a_killed_camera_recording_gives_only_true_images(tmp_path, storage):
    """A camera recording (images of 9 to 40 kB beside small joystick messages): in SQLite
    an image spans overflow pages, and a table of thousands of rows has interior pages;
    cut at many offsets, the scan gives every message it recovers byte for byte, more for a
    later cut, and the whole file gives all of them."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    Image = store.types["sensor_msgs/msg/Image"]
    Header = store.types["std_msgs/msg/Header"]
    Time = store.types["builtin_interfaces/msg/Time"]
    Joy = store.types["sensor_msgs/msg/Joy"]
    rng = np.random.default_rng(5)
    bag = tmp_path / "camera"
    plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
    with Writer(bag, version=9, storage_plugin=plugin) as w:
        cam = w.add_connection("/camera/color/image_raw", Image.__msgtype__, typestore=store)
        joy = w.add_connection("/joy", Joy.__msgtype__, typestore=store)
        for k in range(240):
            t = 1_700_000_000_000_000_000 + k * 33_000_000
            stamp = Time(sec=t // 10**9, nanosec=t % 10**9)
            header = Header(stamp=stamp, frame_id="camera")
            h, wd = (48, 64) if k % 3 else (120, 110)  # 9 kB, and 40 kB every third
            data = rng.integers(0, 256, size=h * wd * 3, dtype=np.uint8)
            img = Image(header=header, height=h, width=wd, encoding="rgb8", is_bigendian=0,
                        step=wd * 3, data=data)
            w.write(cam, t, store.serialize_cdr(img, Image.__msgtype__))
            for j in range(3):
                js = Joy(header=header, axes=np.array([0.1 * j, -0.2], dtype=np.float32),
                         buttons=np.zeros(0, dtype=np.int32))
                w.write(joy, t + j * 11_000_000, store.serialize_cdr(js, Joy.__msgtype__))
    original = _indexed_messages(bag)
    data_file = next(p for p in bag.iterdir() if p.suffix in (".mcap", ".db3"))
    size = data_file.stat().st_size
    previous = -1
    total = sum(len(v) for v in original.values())
    for k, n in enumerate(sorted({size * i // 40 for i in range(1, 40)} | {size})):
        target = _cut_copy(storage, bag, data_file, tmp_path / f"cut{k}", n, metadata=True)
        try:
            got = _recovered(recover_bag(target))
        except BagError:
            got = {}
        for topic, msgs in got.items():
            assert msgs == original[topic][:len(msgs)], (storage, n, topic)
        count = sum(len(v) for v in got.values())
        assert count >= previous, (storage, n, count, previous)
        previous = count
    assert previous == total
