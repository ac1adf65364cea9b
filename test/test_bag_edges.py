"""Recordings a user meets on a chair's laptop, read whole and played whole: a SQLite bag
whose last rows are committed in its write-ahead log, a stray copy of a storage file in the
bag, bag times the target format cannot hold or that are not integers, a metadata.yaml whose
times are not the messages', a message past 2038 or at INT64_MAX."""

from __future__ import annotations

import os
import shutil
import sqlite3
from pathlib import Path

import numpy as np
import pytest

from asgp_ros.recording.bags import BagError, read_streams, recover_bag, repair_bag, write_bag
from asgp_ros.sim.simulate import simulate

MINUTES = 0.5


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("edges")
    rec = simulate("tile", MINUTES, 5)
    return {storage: write_bag(d / storage, rec, storage=storage)
            for storage in ("mcap", "sqlite3")}


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def _sql(bag: Path, sql: str, *params: object) -> None:
    con = sqlite3.connect(next(bag.glob("*.db3")))
    con.execute(sql, params)
    con.commit()
    con.close()


def _count(bag: Path) -> int:
    con = sqlite3.connect(next(bag.glob("*.db3")))
    n = int(con.execute("select count(*) from messages").fetchone()[0])
    con.close()
    return n


def _wal_bag(src: Path, dst: Path) -> Path:
    """``src`` with its second half of rows committed in the write-ahead log only: what a
    recorder in WAL mode killed before a checkpoint leaves."""
    work = _copy(src, dst.with_name(dst.name + "_work"))
    db = next(work.glob("*.db3"))
    con = sqlite3.connect(db)
    half = _count(work) // 2
    rows = con.execute("select id, topic_id, timestamp, data from messages where id > ? "
                       "order by id", (half,)).fetchall()
    con.execute("delete from messages where id > ?", (half,))
    con.commit()
    con.execute("vacuum")
    assert con.execute("pragma journal_mode=WAL").fetchone() == ("wal",)
    con.close()
    con = sqlite3.connect(db)
    con.execute("pragma wal_autocheckpoint=0")
    con.executemany("insert into messages(id, topic_id, timestamp, data) values (?,?,?,?)",
                    rows)
    con.commit()
    dst.mkdir()
    for f in os.listdir(work):  # copied before the close checkpoints the log away
        shutil.copy(work / f, dst / f)
    con.close()
    assert (dst / (db.name + "-wal")).stat().st_size > 0
    return dst


def test_rows_committed_in_the_write_ahead_log_are_read(recordings, tmp_path, caplog):
    """rosbags opens SQLite immutable, which ignores the log: evaluate and train read half
    the recording without a word. The bag is read from a scan that applies the log, said."""
    bag = _wal_bag(recordings["sqlite3"], tmp_path / "wal")
    want, got = read_streams(recordings["sqlite3"]), read_streams(bag)
    np.testing.assert_array_equal(got.joy_t, want.joy_t)
    np.testing.assert_array_equal(got.vel, want.vel)
    assert "-wal holds writes not yet in the database" in caplog.text


def test_a_stray_copy_of_a_storage_file_is_not_repaired_into_every_message_twice(
        recordings, tmp_path):
    bag = _copy(recordings["mcap"], tmp_path / "rec")
    storage = next(bag.glob("*.mcap"))
    shutil.copy(storage, bag / (storage.stem + "-copy.mcap"))  # a backup inside the bag
    n = len(recover_bag(recordings["mcap"]).messages)
    got = recover_bag(bag)
    assert len(got.messages) == n
    assert not got.damage.intact
    assert any("repeat another's" in p for p in got.damage.problems), got.damage.problems
    repair_bag(bag, tmp_path / "fixed")
    assert len(recover_bag(tmp_path / "fixed").messages) == n


def test_bag_times_a_format_cannot_hold_are_one_error(recordings, tmp_path):
    """A SQLite bag holds negative times (int64); mcap's are unsigned: the writer raised
    OverflowError (a traceback of `asgp bag repair --storage mcap`)."""
    bag = _copy(recordings["sqlite3"], tmp_path / "neg")
    _sql(bag, "update messages set timestamp = timestamp - ?", 1_700_000_005_000_000_000)
    with pytest.raises(BagError, match="cannot write a message with the bag time -"):
        repair_bag(bag, tmp_path / "out", storage="mcap")
    assert not (tmp_path / "out").exists()


def test_a_row_whose_time_is_not_an_integer_is_damage_not_a_traceback(recordings, tmp_path,
                                                                       caplog):
    """SQLite stores 1.5e30 as REAL in the INTEGER column: read_streams raised OverflowError.
    The row is damaged data, dropped as the scan drops it, and said."""
    bag = _copy(recordings["sqlite3"], tmp_path / "real")
    _sql(bag, "update messages set timestamp = 1.5e30 where id = 5")
    got = read_streams(bag)
    want = read_streams(recordings["sqlite3"])
    assert got.joy_t.size + got.vel_t.size >= want.joy_t.size + want.vel_t.size - 1
    assert "damaged sqlite3 bag" in caplog.text and "lost 1 of" in caplog.text


def test_a_rollback_journal_left_beside_the_database_is_read_from_the_scan(recordings,
                                                                          tmp_path, caplog):
    """A hot journal (the last transaction not finished) is ignored by the immutable reader
    too: the bag is read from the scan, said, and every row of the database is kept."""
    bag = _copy(recordings["sqlite3"], tmp_path / "journal")
    db = next(bag.glob("*.db3"))
    (bag / (db.name + "-journal")).write_bytes(b"\xd9\xd5\x05\xf9\x20\xa1\x63\xd7" + bytes(504))
    want, got = read_streams(recordings["sqlite3"]), read_streams(bag)
    np.testing.assert_array_equal(got.joy_t, want.joy_t)
    np.testing.assert_array_equal(got.vel, want.vel)
    assert "rollback journal" in caplog.text and "read from a scan" in caplog.text
