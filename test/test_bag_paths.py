"""The bag paths of the command line under attack (a careless user, a failing disk, a
hostile file): ``--force`` never replaces what is not a bag, outputs never land inside an
input bag, a bag whose files disagree with its metadata is never "intact", a dataset
never reuses a damaged bag or lies about its storage, bag outputs are on the disk before
they are published, a stale joystick reading delivered late never enters the past, and
Ctrl-C while a command starts is no traceback."""

from __future__ import annotations

import contextlib
import io
import json
import shutil
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml

from asgp_ros.cli import main


def run(*args: str) -> SimpleNamespace:
    """``asgp ARGS`` in this process: its exit code, stdout and stderr."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(list(args))
    return SimpleNamespace(returncode=rc, stdout=out.getvalue(), stderr=err.getvalue())

@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 0.1-min simulated mcap bag (334 messages)."""
    d = tmp_path_factory.mktemp("src")
    r = run("simulate", "--minutes", "0.1", "--out", str(d / "b"))
    assert r.returncode == 0, r.stderr
    return d / "b"


def tree(p: Path) -> list[str]:
    return sorted(str(q.relative_to(p)) for q in p.rglob("*"))


def test_a_split_bag_with_a_file_missing_is_damaged(bag: Path, tmp_path: Path) -> None:
    """metadata.yaml names two storage files (twice the messages and the time); the second
    is gone: the bag is damaged, not "intact" (it was, with half its messages lost)."""
    b = tmp_path / "split"
    b.mkdir()
    shutil.copy(bag / "b.mcap", b / "split_0.mcap")
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())
    info = meta["rosbag2_bagfile_information"]
    info["relative_file_paths"] = ["split_0.mcap", "split_1.mcap"]
    f0 = dict(info["files"][0], path="split_0.mcap")
    f1 = dict(info["files"][0], path="split_1.mcap")
    info["files"] = [f0, f1]
    info["message_count"] = 2 * info["message_count"]
    info["duration"]["nanoseconds"] = 2 * info["duration"]["nanoseconds"]
    (b / "metadata.yaml").write_text(yaml.safe_dump(meta))
    r = run("bag", "info", str(b))
    assert r.returncode == 0, r.stderr
    assert "intact" not in r.stdout.splitlines()[0], r.stdout.splitlines()[0]
    r = run("bag", "repair", str(b), str(tmp_path / "rep"))
    assert "intact" not in r.stdout, r.stdout
    assert "split_1.mcap (listed in metadata.yaml) is missing" in r.stdout, r.stdout
    assert f"lost {info['message_count'] // 2} of {info['message_count']}" in r.stdout


def test_a_stray_copy_of_the_storage_file_is_not_intact(
        bag: Path, tmp_path: Path) -> None:
    """A backup copy of the storage file inside the bag directory (not in metadata.yaml)
    is read too (an unlisted split), but a count that disagrees with metadata.yaml is no
    intact bag (it was "intact (mcap, 668 messages)", every message twice)."""
    b = tmp_path / "b"
    shutil.copytree(bag, b)
    shutil.copy(b / "b.mcap", b / "b_backup.mcap")
    r = run("bag", "repair", str(b), str(tmp_path / "rep"))
    assert r.returncode == 0, r.stderr
    assert "intact (mcap, 668 messages)" not in r.stdout, r.stdout
    assert "b_backup.mcap is not listed in metadata.yaml" in r.stdout, r.stdout
    # the bag alone is intact, its count what metadata.yaml says
    assert "intact (mcap, 334 messages)" in run("bag", "repair", str(bag),
                                                str(tmp_path / "rep2")).stdout


def test_force_never_replaces_a_directory_that_only_has_a_metadata_yaml(tmp_path: Path) -> None:
    """``--force`` replaces a ROS 2 bag, not a user's project that happens to hold a file
    named metadata.yaml (its thesis.tex and src/ were deleted)."""
    proj = tmp_path / "proj"
    (proj / "src").mkdir(parents=True)
    (proj / "metadata.yaml").write_text("title: my thesis\n")
    (proj / "thesis.tex").write_text("years of work\n")
    (proj / "src" / "main.c").write_text("int main;\n")
    run("simulate", "--minutes", "0.1", "--out", str(proj), "--force")
    assert (proj / "thesis.tex").exists(), f"deleted; proj now holds {tree(proj)}"


def test_repair_force_never_replaces_a_directory_that_is_no_bag(bag: Path, tmp_path: Path) -> None:
    """The same through ``asgp bag repair IN OUT --force``."""
    proj = tmp_path / "proj"
    proj.mkdir()
    (proj / "metadata.yaml").write_text("title: notes\n")
    (proj / "notes.txt").write_text("keep me\n")
    run("bag", "repair", str(bag), str(proj), "--force")
    assert (proj / "notes.txt").exists(), f"deleted; proj now holds {tree(proj)}"


@pytest.mark.parametrize("cmd", ["train", "evaluate"])
def test_no_output_inside_a_bag_given_by_its_storage_file(bag: Path, tmp_path: Path,
                                                     cmd: str) -> None:
    """A storage file stands for its bag: ``asgp train B/b.mcap --out B/model.db3`` wrote
    into the input bag (and ``asgp bag info B`` then failed, "both .mcap and .db3")."""
    b = tmp_path / "B"
    shutil.copytree(bag, b)
    before = tree(b)
    if cmd == "train":
        r = run("train", str(b / "b.mcap"), "--out", str(b / "model.db3"),
                "--model", "constant_velocity")
    else:
        m = tmp_path / "m.npz"
        assert run("train", str(bag), "--out", str(m), "--model",
                   "constant_velocity").returncode == 0
        r = run("evaluate", str(m), str(b / "b.mcap"), "--json", str(b / "scores.db3"))
    assert tree(b) == before, f"rc={r.returncode}; input bag dir now holds {tree(b)}; " \
                              f"bag info: {run('bag', 'info', str(b)).stderr.strip()}"


def test_a_dataset_never_reuses_a_cut_bag(tmp_path: Path) -> None:
    """A dataset bag whose storage file was cut (a failing disk, an interrupted copy) is
    simulated again on the next run, not counted "already present"."""
    ds = tmp_path / "ds"
    assert run("dataset", "--out", str(ds), "--scale", "0.005").returncode == 0
    f = ds / "tile" / "tile_01" / "tile_01.mcap"
    with open(f, "r+b") as fh:
        fh.truncate(100)
    r = run("dataset", "--out", str(ds), "--scale", "0.005")
    assert not (r.returncode == 0 and f.stat().st_size == 100), \
        f"rc={r.returncode}, {r.stdout.splitlines()[-1]!r}; tile_01.mcap is 100 bytes"


def test_a_dataset_in_another_storage_is_refused_not_relabelled(tmp_path: Path) -> None:
    """``asgp dataset --storage sqlite3`` over an mcap dataset reused every mcap bag and
    wrote "storage": "sqlite3" into manifest.json: refused now."""
    ds = tmp_path / "ds"
    assert run("dataset", "--out", str(ds), "--scale", "0.005").returncode == 0
    r = run("dataset", "--out", str(ds), "--scale", "0.005", "--storage", "sqlite3")
    manifest = json.loads((ds / "manifest.json").read_text())
    files = sorted(p.name for p in (ds / "tile" / "tile_01").iterdir())
    assert not (r.returncode == 0 and manifest["storage"] == "sqlite3"
                and "tile_01.mcap" in files), f"manifest storage sqlite3, bag holds {files}"


def test_a_ros2_bag_output_is_on_the_disk_before_it_is_published(tmp_path: Path) -> None:
    """Every file of a ROS 2 bag output is fsynced before the rename that publishes it (and,
    with --force, before the old bag is removed): a power cut after the rename finds a
    whole bag, not empty files."""
    code = (
        "import os, sys\n"
        "synced = []\n"
        "real = os.fsync\n"
        "def fsync(fd):\n"
        "    synced.append(os.readlink(f'/proc/self/fd/{fd}')); return real(fd)\n"
        "os.fsync = fsync\n"
        "from asgp_ros.cli import main\n"
        f"rc = main(['simulate', '--minutes', '0.1', '--out', {str(tmp_path / 'o')!r}])\n"
        "print(synced)\n"
        "sys.exit(rc)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0, r.stderr
    synced = r.stdout.strip().splitlines()[-1]
    assert ".mcap" in synced and "metadata.yaml" in synced, f"fsynced: {synced}"


@pytest.mark.parametrize("value", ["true", "-5"])
def test_absurd_metadata_counts_are_no_expectation(bag: Path, tmp_path: Path, value: str) -> None:
    """A metadata.yaml message_count of ``true`` or -5 is no expected count ("lost 0 of True
    messages" was printed)."""
    b = tmp_path / "b"
    shutil.copytree(bag, b)
    with open(b / "b.mcap", "r+b") as fh:
        fh.truncate(50000)
    text = (b / "metadata.yaml").read_text().replace("\n  message_count: 334\n",
                                                     f"\n  message_count: {value}\n")
    (b / "metadata.yaml").write_text(text)
    r = run("bag", "info", str(b))
    assert f"of {value.capitalize()} messages" not in r.stdout, r.stdout.splitlines()[-1]


def test_a_ros1_bag_with_trailing_zeros_keeps_its_count(tmp_path: Path) -> None:
    """A complete ROS 1 bag followed by 1000 zero bytes: every message is recovered and the
    report says the zeros follow the index (it said every byte was lost after the last
    complete record)."""
    rb = tmp_path / "r.bag"
    assert run("simulate", "--minutes", "0.1", "--out", str(rb)).returncode == 0
    size = rb.stat().st_size
    with open(rb, "ab") as fh:
        fh.write(b"\0" * 1000)
    r = run("bag", "info", str(rb))
    damage = r.stdout.splitlines()[-1]
    assert f"{size + 1000} of {size + 1000} bytes after" not in damage, damage
    assert "1000 bytes after the index are no record" in damage, damage
    assert f"1000 of {size + 1000} bytes after the last complete record" in damage, damage


def test_ctrl_c_while_a_command_starts_is_no_traceback(monkeypatch, capsys) -> None:
    """Ctrl-C while a subcommand's modules load (a few tenths of a second) prints
    "interrupted" and exits 130, as it does later on: no traceback."""
    import asgp_ros.cli as cli

    def loading(_name):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "build_parser", loading)
    assert cli.main(["simulate", "--minutes", "0.1", "--out", "x"]) == 130
    assert capsys.readouterr().err == "interrupted\n"


def test_a_stale_joystick_reading_delivered_late_is_dropped(bag: Path, tmp_path: Path) -> None:
    """One /joy message recorded at 3 s but stamped 5 s earlier (full forward): a stale
    reading delivered late is dropped, as the live predictor refuses it, instead of being
    sorted into the past before the bag starts."""
    import numpy as np
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    from asgp_ros.recording.bags import read_streams

    ts = get_typestore(Stores.ROS2_JAZZY)
    out = tmp_path / "glitch"
    with AnyReader([bag], default_typestore=ts) as r, Writer(out, version=9) as w:
        conns = {c.topic: w.add_connection(c.topic, c.msgtype, typestore=ts)
                 for c in r.connections}
        i = 0
        for c, t, raw in r.messages():
            m = r.deserialize(raw, c.msgtype)
            if c.topic == "/joy":
                i += 1
                if i == 90:  # t = 3 s
                    m.header.stamp.sec -= 5
                    m.axes = np.array([1.0, 0.0], dtype=np.float32)
            w.write(conns[c.topic], t, ts.serialize_cdr(m, c.msgtype))
    s = read_streams(out)
    t0 = 1_700_000_000.0
    early = s.joy_t < t0 - 1.0
    assert not early.any(), (f"joystick sample at {s.joy_t[early] - t0} s (before the bag "
                             f"starts) with deflection {s.joy[early]}")


@pytest.mark.parametrize("second", ["same", "symlink", "storage_file", "copy"])
def test_one_recording_given_twice_is_refused(bag: Path, tmp_path: Path, second: str) -> None:
    """``asgp train`` trained on its rows twice (``asgp adapt`` refused a path given twice,
    not a link or a copy); ``asgp evaluate`` counted its cases twice."""
    other = {"same": bag, "symlink": tmp_path / "link", "storage_file": bag / "b.mcap",
             "copy": tmp_path / "copy"}[second]
    if second == "symlink":
        other.symlink_to(bag)
    elif second == "copy":
        shutil.copytree(bag, other)
    out = tmp_path / "m.npz"
    r = run("train", str(bag), str(other), "--out", str(out), "--model", "constant_velocity")
    assert r.returncode == 2 and "the same recording as" in r.stderr, r.stderr
    assert not out.exists()
    assert run("train", str(bag), "--out", str(out), "--model",
               "constant_velocity").returncode == 0
    r = run("evaluate", str(out), str(bag), str(other))
    assert r.returncode == 2 and "the same recording as" in r.stderr, r.stderr


def test_a_dataset_holding_a_recording_twice_is_not_reproduced(tmp_path: Path) -> None:
    """A backup copy of a test bag beside the others put it into the Tile and Both train
    sets: models were tested on data they were trained on, and the report did not say."""
    data = tmp_path / "data"
    assert run("dataset", "--out", str(data), "--scale", "0.005").returncode == 0
    shutil.copytree(data / "tile" / "tile_08", data / "tile" / "tile_08_backup")
    r = run("reproduce", "--data", str(data), "--out", str(tmp_path / "rep"), "--quick")
    assert r.returncode == 2 and "the same recording as" in r.stderr, r.stderr
    assert not (tmp_path / "rep").exists()


def test_a_bag_directory_named_like_a_storage_file_is_the_bag(tmp_path):
    """asgp simulate --out run1.mcap makes a bag directory of that name; taken as an input
    it made its parent "the bag", and every output beside it was refused ("--out
    results/model.npz is inside the input .")."""
    from asgp_ros.common.fileio import MODEL_FILE, OutputError, bag_inputs, check_output

    bag_dir = tmp_path / "run1.mcap"
    bag_dir.mkdir()
    storage = tmp_path / "rec" / "rec_0.mcap"
    storage.parent.mkdir()
    storage.write_bytes(b"")
    assert bag_inputs([bag_dir]) == [str(bag_dir)]
    assert bag_inputs([storage]) == [str(storage), str(storage.parent)]
    check_output(tmp_path / "results" / "m.npz", MODEL_FILE, inputs=bag_inputs([bag_dir]))
    with pytest.raises(OutputError, match="inside the input"):
        check_output(storage.parent / "m.npz", MODEL_FILE, inputs=bag_inputs([storage]))
    with pytest.raises(OutputError, match="inside the input"):
        check_output(bag_dir / "m.npz", MODEL_FILE, inputs=bag_inputs([bag_dir]))
