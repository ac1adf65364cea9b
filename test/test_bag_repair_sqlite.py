"""The page-by-page scan of rosbag2 SQLite databases against what a failing disk, a killed
recorder, a later edit and a hostile file leave: b-trees with interior pages cut at many
offsets, deleted rows (free pages), loops, pointers out of the file, broken cells and
stray pages. Every recovered message is a true one; nothing crashes or hangs."""

from __future__ import annotations

import shutil
import sqlite3
import struct
from pathlib import Path

import pytest

from asgp_ros.recording import bags
from asgp_ros.recording.bags import BagError, recover_bag

PS = 512  # small pages: deep b-trees and overflow chains from a few thousand rows
SCHEMA = """
CREATE TABLE schema(schema_version INTEGER PRIMARY KEY, ros_distro TEXT NOT NULL);
CREATE TABLE metadata(id INTEGER PRIMARY KEY, metadata_version INTEGER NOT NULL,
  metadata TEXT NOT NULL);
CREATE TABLE topics(id INTEGER PRIMARY KEY, name TEXT NOT NULL, type TEXT NOT NULL,
  serialization_format TEXT NOT NULL, offered_qos_profiles TEXT NOT NULL,
  type_description_hash TEXT NOT NULL);
CREATE TABLE message_definitions(id INTEGER PRIMARY KEY, topic_type TEXT NOT NULL,
  encoding TEXT NOT NULL, encoded_message_definition TEXT NOT NULL,
  type_description_hash TEXT NOT NULL);
CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL,
  timestamp INTEGER NOT NULL, data BLOB NOT NULL);
CREATE INDEX timestamp_idx ON messages (timestamp ASC);
INSERT INTO schema(schema_version, ros_distro) VALUES (4, 'rosbags');
INSERT INTO topics VALUES (1, '/a', 'std_msgs/msg/String', 'cdr', '', '');
INSERT INTO topics VALUES (2, '/b', 'std_msgs/msg/String', 'cdr', '', '');
"""
Row = tuple[str, int, bytes]  # topic, bag time, data


def _record(path: Path, n: int, size: int = 12, batch: int = 50,
            secure_delete: int | None = None) -> list[Row]:
    """A recording as rosbag2 writes it (appended in transactions of ``batch`` rows), with
    ``n`` messages of ``size`` to ``size + 6`` bytes; its messages in order."""
    con = sqlite3.connect(path)
    con.execute(f"PRAGMA page_size={PS}")
    if secure_delete is not None:
        con.execute(f"PRAGMA secure_delete={secure_delete}")
    con.executescript(SCHEMA)
    rows = [(1 + k % 2, 10**18 + k * 1000, bytes((k * 7 + j) % 256 for j in range(size + k % 7)))
            for k in range(n)]
    for i in range(0, n, batch):
        con.executemany("INSERT INTO messages (topic_id, timestamp, data) VALUES (?, ?, ?)",
                        rows[i:i + batch])
        con.commit()
    con.close()
    return [(("/a", "/b")[t - 1], ns, d) for t, ns, d in rows]


def _live(path: Path) -> list[Row]:
    """The messages sqlite itself reads, in time order."""
    con = sqlite3.connect(path)
    out = [(("/a", "/b")[t - 1], ns, d) for t, ns, d in con.execute(
        "SELECT topic_id, timestamp, data FROM messages ORDER BY timestamp")]
    con.close()
    return out


def _got(r: bags.RecoveredBag) -> list[Row]:
    return [(r.connections[c].topic, t, d) for c, t, d in r.messages]


def _roots(path: Path) -> dict[str, int]:
    con = sqlite3.connect(path)
    roots = dict(con.execute("SELECT name, rootpage FROM sqlite_master"))
    con.close()
    return roots


def _depth(data: bytes, root: int) -> int:
    """Levels of the b-tree at ``root`` (1: a single leaf), down its leftmost path."""
    depth, p = 1, root
    while data[(p - 1) * PS] == 0x05:  # table interior page
        p = struct.unpack_from(">I", data, (p - 1) * PS + 8)[0]
        depth += 1
    return depth


def _scan(tmp_path: Path, data: bytes | bytearray, wal: bytes | None = None
          ) -> bags.RecoveredBag:
    d = tmp_path / f"b{len(list(tmp_path.iterdir()))}"
    d.mkdir()
    (d / "x.db3").write_bytes(bytes(data))
    if wal is not None:
        (d / "x.db3-wal").write_bytes(wal)
    return recover_bag(d / "x.db3")


def _off(p: int) -> int:
    return (p - 1) * PS


@pytest.fixture(scope="module")
def deep(tmp_path_factory) -> tuple[Path, list[Row]]:
    """3000 small messages: the messages table is a b-tree of depth 3."""
    path = tmp_path_factory.mktemp("deep") / "deep.db3"
    return path, _record(path, 3000)


@pytest.mark.parametrize("n, depth", [(300, 2), (3000, 3)])
def test_a_deep_btree_cut_at_many_offsets_gives_only_true_messages(tmp_path, n, depth):
    """Interior pages (depth 2: a root over leaves; depth 3: a root over interior pages)
    that the cut removed leave their leaves unreachable: those are read by themselves;
    only true messages, more for a later cut, all of them for the whole file."""
    path = tmp_path / "rec.db3"
    original = _record(path, n)
    data = path.read_bytes()
    assert _depth(data, _roots(path)["messages"]) == depth
    truth = set(original)
    previous = -1
    for k in range(41):
        cut = len(data) * k // 40
        try:
            got = _got(_scan(tmp_path, data[:cut]))
        except BagError:
            got = []
        assert set(got) <= truth and len(set(got)) == len(got), cut
        assert got == sorted(got, key=lambda m: m[1])
        assert len(got) >= previous, (cut, len(got), previous)
        previous = len(got)
    assert got == original


@pytest.mark.parametrize("journal", ["delete", "wal"])
@pytest.mark.parametrize("secure", [0, 1])
def test_deleted_rows_never_come_back(tmp_path, journal, secure):
    """A recording edited afterwards (rows deleted, some pages freed, new rows reusing
    freed ids), with and without secure_delete, in rollback and write-ahead log mode (the
    log not checkpointed: the free list starts in the log's page 1): exactly the rows
    sqlite reads come back."""
    path = tmp_path / "rec.db3"
    _record(path, 3000)
    con = sqlite3.connect(path)
    con.execute(f"PRAGMA secure_delete={secure}")
    if journal == "wal":
        con.execute("PRAGMA journal_mode=WAL")
        con.execute("PRAGMA wal_autocheckpoint=0")
    for where in ("id BETWEEN 500 AND 1500", "id % 7 = 0", "id > 2800"):
        con.execute(f"DELETE FROM messages WHERE {where}")
        con.commit()
    con.executemany("INSERT INTO messages (topic_id, timestamp, data) VALUES (?, ?, ?)",
                    [(2, 5 + k, b"new %d" % k) for k in range(30)])  # ids 2800..2829 again
    con.commit()
    live = _live(path)
    free = con.execute("PRAGMA freelist_count").fetchone()[0]
    assert free > 50
    killed = tmp_path / "killed"
    killed.mkdir()
    shutil.copy(path, killed / "x.db3")
    if journal == "wal":
        shutil.copy(str(path) + "-wal", killed / "x.db3-wal")
    con.close()
    assert _got(recover_bag(killed / "x.db3")) == live
    db = killed / "x.db3"  # the free list as sqlite counts it (the log's page 1 in WAL mode)
    assert len(bags._SqlitePages(db, db.read_bytes(), "x", bags._Scan()).free_pages()) == free


def test_an_edited_recording_cut_before_its_free_list_gives_no_deleted_rows(tmp_path):
    """Rows deleted at the start and the end: the free list's first trunk is near the end
    of the file. A cut before it leaves freed pages that nothing marks as free: they are
    not read (their rows were deleted), so a cut gives only live rows, more for a later
    cut."""
    path = tmp_path / "rec.db3"
    _record(path, 3000, secure_delete=0)
    con = sqlite3.connect(path)
    con.execute("PRAGMA secure_delete=0")
    con.execute("DELETE FROM messages WHERE id > 2900")
    con.commit()
    con.execute("DELETE FROM messages WHERE id < 500")
    con.commit()
    con.close()
    live, data = _live(path), path.read_bytes()
    assert struct.unpack_from(">I", data, 32)[0] > len(data) // PS // 2  # the first trunk
    previous = -1
    for k in range(1, 21):
        got = _got(_scan(tmp_path, data[:len(data) * k // 20]))
        assert set(got) <= set(live), k
        assert len(got) >= previous
        previous = len(got)
    assert got == live


def test_a_stray_page_of_another_table_shaped_like_messages_never_comes_back(tmp_path):
    """Another table whose rows have the messages table's shape (id, topic id, time,
    data), ids 1..200 and 5001..5200 (messages have 1..3000): its leaves read through its
    b-tree are its own; cut off from it (its root's pointers lost), they are stray pages
    whose ids lie where the messages b-tree is whole, and give no message (nor hide a true
    one)."""
    path = tmp_path / "rec.db3"
    original = _record(path, 3000)
    con = sqlite3.connect(path)
    con.execute("CREATE TABLE other(id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL, "
                "timestamp INTEGER NOT NULL, data BLOB NOT NULL)")
    con.executemany("INSERT INTO other VALUES (?, ?, ?, ?)",  # ids in and past messages'
                    [(k + (1 if k < 200 else 4800), 1, 7 + k, b"not a message %d" % k)
                     for k in range(400)])
    con.commit()
    con.close()
    data = bytearray(path.read_bytes())
    assert _got(_scan(tmp_path, data)) == original
    root = _off(_roots(path)["other"])
    assert data[root] == 0x05  # an interior root: its leaves hang from it
    data[root + 8:root + 12] = bytes(4)  # right pointer and every cell's child: page 0
    for i in range(struct.unpack_from(">H", data, root + 3)[0]):
        cell = struct.unpack_from(">H", data, root + 12 + 2 * i)[0]
        data[root + cell:root + cell + 4] = bytes(4)
    r = _scan(tmp_path, data)
    assert _got(r) == original
    assert any("pointer" in p for p in r.damage.problems)


def test_a_cut_file_is_reported_as_cut_not_as_a_bad_pointer(tmp_path, deep):
    """A file cut at a page boundary: the interior pages' pointers to pages past the cut,
    within the header's size, are the cut (reported as such), not pointers to pages of
    another table (reported before for every page past the cut)."""
    path, original = deep
    data = path.read_bytes()
    r = _scan(tmp_path, data[:_off(len(data) // PS // 2)])
    assert 0 < len(r.messages) < len(original)
    assert any("the file is cut" in p for p in r.damage.problems), r.damage.problems
    assert not any("not one of its table's" in p for p in r.damage.problems), \
        r.damage.problems


def test_interior_pointers_to_itself_an_ancestor_page_0_or_beyond_the_file(tmp_path, deep):
    """The messages root's child pointers turned to the root itself, page 1, page 0 and a
    page past the file: no loop, no crash; the subtrees they lost are read from their
    leaves, so every message comes back, and the damage is reported."""
    path, original = deep
    data = path.read_bytes()
    root = _off(_roots(path)["messages"])
    assert data[root] == 0x05
    for target in (_roots(path)["messages"], 1, 0, 10**6, 2**32 - 1):
        x = bytearray(data)
        x[root + 8:root + 12] = struct.pack(">I", target)
        cell = struct.unpack_from(">H", x, root + 12)[0]
        x[root + cell:root + cell + 4] = struct.pack(">I", target)
        r = _scan(tmp_path, x)
        assert _got(r) == original, target
        assert not r.damage.intact and r.damage.problems


def test_an_interior_cell_past_its_page_is_skipped_not_a_crash(tmp_path, deep):
    """A topics table whose root is an interior page with a cell pointer past the page
    (a _StopError escaped the scan before) and a pointer back to itself: the topics are
    read from the leaf its right pointer names."""
    path, original = deep
    data = bytearray(path.read_bytes())
    topics = _roots(path)["topics"]
    leaf = bytes(data[_off(topics):_off(topics) + PS])
    data += leaf
    new = len(data) // PS
    data[28:32] = struct.pack(">I", new)  # the header's size in pages
    page = bytearray(PS)
    page[0], page[3:5], page[5:7] = 0x05, struct.pack(">H", 2), struct.pack(">H", 500)
    page[8:12] = struct.pack(">I", new)
    page[12:16] = struct.pack(">HH", 509, 500)  # past the page; a cell to itself
    page[500:505] = struct.pack(">IB", topics, 1)
    data[_off(topics):_off(topics) + PS] = page
    r = _scan(tmp_path, data)
    assert _got(r) == original
    assert any("interior page" in p for p in r.damage.problems)


def test_a_looping_overflow_chain_gives_no_message_with_wrong_bytes(tmp_path):
    """Messages of 1.5 kB span overflow pages; one chain turned back on itself (its second
    page pointing at its first, or at itself) once gave a message made of repeated pages.
    That row is dropped and reported; every other message comes back."""
    path = tmp_path / "rec.db3"
    original = _record(path, 40, size=1500, batch=5)
    data = path.read_bytes()
    first = None
    for p in range(2, len(data) // PS + 1):  # an overflowing cell of a messages leaf
        o = _off(p)
        if data[o] != 0x0D or struct.unpack_from(">H", data, o + 3)[0] == 0:
            continue
        cell = struct.unpack_from(">H", data, o + 8)[0]
        size, c = bags._varint(data[o:o + PS], cell)
        _rowid, c = bags._varint(data[o:o + PS], c)
        if size > PS - 35:
            m = (PS - 12) * 32 // 255 - 23
            local = m + (size - m) % (PS - 4)
            first = struct.unpack_from(">I", data, o + c + (local if local <= PS - 35
                                                              else m))[0]
            break
    assert first is not None
    second = struct.unpack_from(">I", data, _off(first))[0]
    assert second
    for target in (first, second):
        x = bytearray(data)
        x[_off(second):_off(second) + 4] = struct.pack(">I", target)
        r = _scan(tmp_path, x)
        got = _got(r)
        assert set(got) <= set(original) and len(got) == len(original) - 1
        assert any("overflow chain" in p for p in r.damage.problems)


def test_free_list_trunks_that_loop_or_point_past_the_file(tmp_path, deep):
    """A free-list trunk pointing at itself, past the file, or claiming more leaves than
    a page holds: the scan ends, every message comes back and the broken list is
    reported."""
    path, original = deep
    data = bytearray(path.read_bytes())
    trunk = len(data) // PS + 1
    data += bytes(PS)
    data[28:32] = struct.pack(">I", trunk)
    data[32:40] = struct.pack(">II", trunk, 1)  # first trunk, free pages
    for nxt, count in ((trunk, 0), (10**6, 0), (0, 2**32 - 1)):
        data[_off(trunk):_off(trunk) + 8] = struct.pack(">II", nxt, count)
        r = _scan(tmp_path, data)
        assert _got(r) == original
        assert any("free list" in p for p in r.damage.problems)


def test_one_broken_leaf_cell_loses_that_row_only(tmp_path, deep):
    """A leaf cell whose pointer runs past the page, whose size or record header claims
    more than the cell has, or whose varints run on for 9 bytes: the other rows of the
    page come back (the whole page was lost before)."""
    path, original = deep
    data = path.read_bytes()
    leaf = next(p for p in range(10, len(data) // PS) if data[_off(p)] == 0x0D)
    o = _off(leaf)
    cell = struct.unpack_from(">H", data, o + 8)[0]
    for at, value in ((o + 8, b"\x01\xff"), (o + cell, b"\x7f"), (o + cell + 2, b"\x7f"),
                      (o + cell, b"\xff" * 9), (o + cell + 1, b"\xff" * 9)):
        x = bytearray(data)
        x[at:at + len(value)] = value
        r = _scan(tmp_path, x)
        got = _got(r)
        assert set(got) <= set(original) and len(got) == len(original) - 1, value
        assert any(f"cell on page {leaf}" in p for p in r.damage.problems)


def test_varints_of_nine_bytes_and_record_headers_past_their_cell():
    assert bags._varint(b"\xff" * 9, 0) == (-1, 9)
    assert bags._varint(b"\x80" * 8 + b"\x01", 0) == (1, 9)
    with pytest.raises(bags._StopError):
        bags._varint(b"\xff" * 8, 0)  # the ninth byte is missing
    assert bags._sqlite_record(b"\x02\x0e\x00") == [b"\x00"]
    for record in (b"\x7f\x01\x02",  # a header longer than the record
                   b"\x03\x01" + b"\xff" * 9,  # a serial type running past the header
                   b"\x0a" + b"\x80" * 8 + b"\x10\x00",  # 9-byte serial type: 2-byte blob
                   b"\x0a" + b"\xff" * 9,  # 9-byte serial type: negative
                   b"\x02\x10\x00", b"\x02\x01", b"\x02\x0a\x00"):
        with pytest.raises(bags._StopError):
            bags._sqlite_record(record)


@pytest.mark.parametrize("field", [0, 1, 256, 1000, 65535])
def test_bad_page_size_fields_give_a_one_line_error(tmp_path, deep, field):
    """A page size of 1 means 65536 (more than this file holds: nothing readable), others
    are not powers of two of at least 512: a BagError with a one-line reason."""
    path, _original = deep
    data = bytearray(path.read_bytes())
    data[16:18] = struct.pack(">H", field)
    with pytest.raises(BagError) as info:
        _scan(tmp_path, data)
    assert "\n" not in str(info.value)
    assert ("page size" in str(info.value)) == (field != 1)


def _wal(frames: list[tuple[int, int, bytes]]) -> bytes:
    """A write-ahead log whose frames (page number, commit size, page) pass their
    checksums."""
    header = struct.pack(">6I", 0x377F0682, 3007000, PS, 0, 7, 9)

    def checksum(data: bytes, s0: int, s1: int) -> tuple[int, int]:
        words = struct.unpack(f"<{len(data) // 4}I", data)
        for i in range(0, len(words), 2):
            s0 = (s0 + words[i] + s1) & 0xFFFFFFFF
            s1 = (s1 + words[i + 1] + s0) & 0xFFFFFFFF
        return s0, s1

    s = checksum(header, 0, 0)
    out = header + struct.pack(">2I", *s)
    for pgno, commit, page in frames:
        s = checksum(struct.pack(">2I", pgno, commit) + page, *s)
        out += struct.pack(">6I", pgno, commit, 7, 9, *s) + page
    return out


def test_write_ahead_log_frames_for_page_0_or_far_past_the_file(tmp_path, deep):
    """Valid frames naming page 0 or page 2**31 (the scan walked every page number up to
    the largest before: a hang) are no page of the database."""
    path, original = deep
    data = path.read_bytes()
    for pgno in (0, 2**31):
        r = _scan(tmp_path, data, _wal([(pgno, 1, data[PS:2 * PS])]))
        assert _got(r) == original
