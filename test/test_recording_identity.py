"""A recording is told by its messages, not its storage's bytes: ``asgp bag repair`` (and
its conversion between mcap and sqlite3) writes the same messages in other bytes, and
``asgp train A A_repaired`` trained on every row twice, ``asgp evaluate MODEL A_repaired``
did not say that A was a training bag. A copy cut short (a repaired copy of an unfinished
one) begins with the other's messages: told too. Two different recordings never share an
identity."""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

import pytest
from test_bag_paths import run

from asgp_ros.sim.simulate import simulate, write_recording


@pytest.fixture(scope="module")
def drives(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A 0.5-min simulated drive as mcap and as a ROS 1 bag, and a model trained on each."""
    d = tmp_path_factory.mktemp("drives")
    rec = simulate("tile", 0.5, 21)
    out = {"mcap": write_recording(d / "a", rec),
           "ros1": _compressed(rec, d / "a.bag")}
    for kind, bag in list(out.items()):
        model = d / f"{kind}.npz"
        r = run("train", str(bag), "--out", str(model), "--model", "first_order_lag")
        assert r.returncode == 0, r.stderr
        out[f"{kind}_model"] = model
    return out


def _compressed(rec: Any, out: Path) -> Path:
    """The recording ``rec`` as a ROS 1 bag with bz2 chunks, as a recorder may write it
    (its repair, uncompressed, is then other bytes; a bag of the package's writer repairs
    byte-for-byte the same)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    content = rec.bag_content(store, True)
    writer = Writer(out)
    writer.set_compression(Writer.CompressionFormat.BZ2)
    with writer:
        conns = [writer.add_connection(t, m, typestore=store) for t, m in content.connections]
        for t, i, data in sorted(content.messages, key=lambda m: m[0]):
            writer.write(conns[i], t, data)
    return out


def _repaired(src: Path, dest: Path, *extra: str) -> Path:
    r = run("bag", "repair", str(src), str(dest), *extra)
    assert r.returncode == 0, r.stderr
    assert (src.read_bytes() if src.is_file() else b"") != (
        dest.read_bytes() if dest.is_file() else b"x")
    return dest


@pytest.mark.parametrize("copy", ["repaired", "sqlite3", "sqlite3_to_mcap", "ros1"])
def test_a_repaired_or_converted_copy_is_the_same_recording(
        drives: dict[str, Path], tmp_path: Path, copy: str) -> None:
    """Trained together, A and its repaired (or converted) copy are refused with a message
    naming both; a model trained on A warns when tested on the copy, and one trained on
    the copy when tested on A."""
    kind = "ros1" if copy == "ros1" else "mcap"
    bag = drives[kind]
    if copy == "ros1":
        other = _repaired(bag, tmp_path / "rep.bag")
    elif copy == "sqlite3_to_mcap":
        other = _repaired(_repaired(bag, tmp_path / "sql", "--storage", "sqlite3"),
                          tmp_path / "back", "--storage", "mcap")
    else:
        other = _repaired(bag, tmp_path / "rep",
                          *(["--storage", "sqlite3"] if copy == "sqlite3" else []))
    model = tmp_path / "m.npz"
    r = run("train", str(bag), str(other), "--out", str(model), "--model", "first_order_lag")
    assert r.returncode == 2 and not model.exists(), r.stdout
    assert f"{other}: the same recording as {bag} (the same messages" in r.stderr, r.stderr
    r = run("evaluate", str(drives[f"{kind}_model"]), str(other))
    assert r.returncode == 0, r.stderr
    assert f"warning: {other} is one of the recordings {drives[f'{kind}_model']} was " \
           "trained on" in r.stdout, r.stdout
    r = run("evaluate", str(drives[f"{kind}_model"]), str(bag), str(other))
    assert r.returncode == 2 and "the same recording as" in r.stderr, r.stderr
    # the other way round: trained on the copy, tested on the original
    assert run("train", str(other), "--out", str(model), "--model",
               "first_order_lag").returncode == 0
    r = run("evaluate", str(model), str(bag))
    assert f"warning: {bag} is one of the recordings {model} was trained on" in r.stdout


def _cut(bag: Path, dest: Path, fraction: float) -> Path:
    """What a recorder killed part way leaves of the mcap ``bag``: its storage file cut at
    ``fraction`` of its bytes, and no metadata.yaml."""
    dest.mkdir()
    data = (bag / f"{bag.name}.mcap").read_bytes()
    (dest / f"{dest.name}.mcap").write_bytes(data[:int(len(data) * fraction)])
    return dest


def test_a_killed_recording_is_its_repair_and_begins_as_the_whole(
        drives: dict[str, Path], tmp_path: Path) -> None:
    """A recording cut short (a copy taken while it was recorded, a disk that filled) and
    its repaired copy are one recording (the reader drops the partial record as the repair
    does); beside the whole recording it is refused as its start, and a model trained on
    the whole recording warns when tested on it."""
    bag = drives["mcap"]
    cut = _cut(bag, tmp_path / "cut", 0.6)
    fixed = _repaired(cut, tmp_path / "fixed")
    model = tmp_path / "m.npz"
    r = run("train", str(cut), str(fixed), "--out", str(model), "--model", "first_order_lag")
    assert r.returncode == 2 and f"{fixed}: the same recording as {cut}" in r.stderr, \
        r.stderr
    r = run("train", str(bag), str(fixed), "--out", str(model), "--model", "first_order_lag")
    assert r.returncode == 2 and not model.exists()
    assert f"{fixed}: begins with the same messages as {bag} (one is the other cut short" \
           in r.stderr, r.stderr
    r = run("evaluate", str(drives["mcap_model"]), str(fixed))
    assert r.returncode == 0, r.stderr
    assert f"warning: {fixed} begins with the same messages as one of the recordings " \
           f"{drives['mcap_model']} was trained on" in r.stdout, r.stdout


def test_different_recordings_never_share_an_identity(tmp_path: Path) -> None:
    """Simulated drives that start at one time, on one floor or with one seed, of one
    length or not, in one storage or not: no two are the same, nor does one begin as
    another."""
    from asgp_ros.learning.training import read_series, series_identity
    from asgp_ros.recording.bags import recording_relation, repeated_recording

    paths = []
    for k, (surface, minutes, seed, storage) in enumerate([
            ("tile", 0.2, 1, "mcap"), ("tile", 0.2, 2, "mcap"), ("tile", 0.4, 1, "mcap"),
            ("carpet", 0.2, 1, "sqlite3"), ("hybrid", 0.2, 1, "ros1"),
            ("carpet", 0.2, 3, "mcap")]):
        paths.append(write_recording(tmp_path / (f"r{k}.bag" if storage == "ros1"
                                                 else f"r{k}"),
                                     simulate(surface, minutes, seed), storage=storage))
    series = read_series([str(p) for p in paths], truth_topic="/ground_truth/odom")
    idents = [series_identity(s) for s in series]
    for a, b in itertools.combinations(idents, 2):
        assert recording_relation(a, b) == "other"
    assert repeated_recording([(s.name, i) for s, i in zip(series, idents, strict=True)]) \
        is None
    for i in idents:  # each is itself, read again
        assert recording_relation(i, i) == "same"


def test_message_digests_and_how_identities_relate() -> None:
    """Messages of one time in another order are the same messages; a start shorter than
    HEAD_MESSAGES is not told; digests of topics not read from both count for nothing;
    a record of another shape (a foreign file's) matches nothing."""
    from asgp_ros.recording.bags import (
        HEAD_MESSAGES,
        find_recording,
        message_digests,
        recording_relation,
    )

    t = [10, 20, 20, 30] * 40
    d = [bytes([i % 251]) * 16 for i in range(len(t))]
    whole = message_digests(t, d)
    swapped = message_digests([t[0], t[2], t[1], *t[3:]], [d[0], d[2], d[1], *d[3:]])
    assert swapped == whole and whole["n"] == len(t)
    assert len(whole["heads"]) == 4  # 16, 32, 64, 128 of 160

    def ident(n: int, **more: dict[str, object]) -> dict[str, object]:
        order = sorted(range(len(t)), key=lambda i: (t[i], d[i]))[:n]
        return {"path": f"/x{n}", "content": f"c{n}",
                "messages": {"/vo/twist": message_digests([t[i] for i in order],
                                                          [d[i] for i in order]), **more}}

    full = ident(len(t))
    assert recording_relation(full, ident(100)) == "start"
    assert recording_relation(ident(HEAD_MESSAGES), full) == "start"
    assert recording_relation(ident(HEAD_MESSAGES - 1), full) == "other"
    other = message_digests(t, [bytes([255 - i % 251]) * 16 for i in range(len(t))])
    assert recording_relation(full, {"messages": {"/vo/twist": other}}) == "other"
    # a topic one read and the other did not: compared on the rest
    assert recording_relation(ident(len(t), **{"/joy": other}), full) == "same"
    # one topic alike, another not: another recording (a simulated joystick may repeat)
    assert recording_relation(ident(len(t), **{"/joy": whole}),
                              ident(len(t), **{"/joy": other})) == "other"
    # no topic in common, or a record without messages (an older model file): the storage
    # digest decides, then the path
    old = {"path": "/x160", "content": "c160"}
    assert recording_relation(full, old) is None
    assert find_recording(full, [old]) == "same"
    assert find_recording(full, [{"path": "/x160", "content": "other"}]) is None
    assert find_recording(full, [{"path": "/x160"}]) == "same"
    for foreign in (None, 3, "x", [], {"messages": 3}, {"messages": {"/vo/twist": 3}},
                    {"messages": {"/vo/twist": {"n": True, "all": "a", "heads": []}}},
                    {"messages": {"/vo/twist": {"n": 5, "all": 5, "heads": []}}}):
        assert find_recording({"messages": full["messages"]}, [foreign]) is None


def test_an_older_model_file_tells_a_byte_copy_not_a_repaired_one(
        drives: dict[str, Path], tmp_path: Path) -> None:
    """A model file written before the messages' digests were kept records the storage
    digest: a byte-for-byte copy of its bag is still told, a repaired one cannot be."""
    import shutil

    from asgp_ros.core.modelfile import load_model, save_model

    model = load_model(drives["mcap_model"])
    for record in model.meta["training_data"]["recordings"]:
        del record["messages"]
    old = tmp_path / "old.npz"
    save_model(old, model)
    copy = tmp_path / "copy"
    shutil.copytree(drives["mcap"], copy)
    r = run("evaluate", str(old), str(copy))
    assert f"warning: {copy} is one of the recordings" in r.stdout, r.stdout
    fixed = _repaired(drives["mcap"], tmp_path / "fixed")
    r = run("evaluate", str(old), str(fixed))
    assert r.returncode == 0 and "warning" not in r.stdout, r.stdout


def test_a_dataset_holding_a_repaired_copy_is_not_reproduced(tmp_path: Path) -> None:
    """A repaired copy of a test bag beside the others went into the train sets, as a
    byte-for-byte copy did before it was refused: models tested on their own data."""
    data = tmp_path / "data"
    assert run("dataset", "--out", str(data), "--scale", "0.005").returncode == 0
    fixed = _repaired(data / "tile" / "tile_08", data / "tile" / "tile_08_fixed",
                      "--storage", "sqlite3")
    r = run("reproduce", "--data", str(data), "--out", str(tmp_path / "rep"), "--quick")
    assert r.returncode == 2 and not (tmp_path / "rep").exists()
    assert f"{fixed}: the same recording as {data / 'tile' / 'tile_08'}" in r.stderr, \
        r.stderr
