"""Outputs on file systems that refuse what a local disk allows: no rename over an existing
file (SMB shares, sshfs without posix-rename), a read-only directory, a full disk or a full
standard output. Errors come before the work where they can be foreseen, name the output
(never its temporary) and lose nothing."""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from asgp_ros.cli import main
from asgp_ros.common import fileio
from asgp_ros.common.fileio import (
    MODEL_FILE,
    SCORES_JSON,
    OutputError,
    atomic_path,
    atomic_write_text,
    check_output,
    write_marker,
)

REPO = Path(__file__).resolve().parents[1]
MODEL = REPO / "docs" / "reproduction" / "models" / "tile_asgp_paper.npz"


def _leftovers(directory: Path, *keep: str) -> list[str]:
    return sorted(p.name for p in directory.iterdir() if p.name not in keep)


@pytest.fixture
def no_rename_over(monkeypatch):
    """``os.replace`` as on a file system without rename-over: it refuses an existing
    target with the errno the test sets (``no_rename_over.errno``); a rename onto a free
    name works."""
    real_replace = os.replace

    state = SimpleNamespace(errno=errno.EEXIST, refused=[])

    def replace(src, dst, **kwargs):
        if os.path.lexists(dst):
            state.refused.append(os.fspath(dst))
            raise OSError(state.errno, os.strerror(state.errno), os.fspath(src), None,
                          os.fspath(dst))
        return real_replace(src, dst, **kwargs)

    monkeypatch.setattr(os, "replace", replace)
    return state


# ------------------------------------------------------------------- D2: no rename-over
@pytest.mark.parametrize("code", [errno.EEXIST, errno.EPERM, errno.EACCES, errno.ENOTSUP])
def test_a_file_is_replaced_where_the_file_system_cannot_rename_over_it(tmp_path,
                                                                        no_rename_over, code):
    """``asgp dataset`` rewrote its manifest and marker with os.replace, which an SMB share
    or sshfs refuses over an existing file: it failed after simulating every bag, and every
    run after that at once. The old file is moved aside, the new one in, the old removed."""
    no_rename_over.errno = code
    final = tmp_path / "manifest.json"
    final.write_text("old\n")
    atomic_write_text(final, "new\n")
    assert no_rename_over.refused == [str(final)]
    assert final.read_text() == "new\n"
    assert _leftovers(tmp_path) == ["manifest.json"]
    write_marker(tmp_path, "dataset")  # the second run's first write
    write_marker(tmp_path, "dataset")
    assert fileio.read_marker(tmp_path) == "dataset"
    assert _leftovers(tmp_path) == [".asgp-output", "manifest.json"]


def test_force_replaces_a_model_where_rename_over_fails(tmp_path, no_rename_over):
    """The same for an approved --force output, through the command line (evaluate --json:
    its table is printed before the JSON is written)."""
    bag = tmp_path / "drive"
    assert main(["simulate", "--minutes", "0.2", "--seed", "4", "--out", str(bag)]) == 0
    out = tmp_path / "e.json"
    out.write_text('{"horizons": {}}\n')
    assert main(["evaluate", str(MODEL), str(bag), "--json", str(out), "--force"]) == 0
    assert no_rename_over.refused == [str(out)]
    assert '"horizons": {\n' in out.read_text() and len(out.read_text()) > 100
    assert _leftovers(tmp_path) == ["drive", "e.json"]


def test_a_permission_error_is_not_taken_for_a_missing_rename_over(tmp_path, monkeypatch):
    """EACCES from a directory that takes no new entry: moving the old file aside fails
    the same way; nothing changes and the error names the output."""
    final = tmp_path / "m.json"
    final.write_text("old\n")
    real_rename = os.rename

    def replace(src, dst, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied", os.fspath(src), None,
                              os.fspath(dst))

    def rename(src, dst, **kwargs):
        if Path(src) == final:
            raise PermissionError(errno.EACCES, "Permission denied", os.fspath(src))
        return real_rename(src, dst, **kwargs)

    monkeypatch.setattr(os, "replace", replace)
    monkeypatch.setattr(os, "rename", rename)
    with pytest.raises(PermissionError) as err:
        atomic_write_text(final, "new\n")
    assert err.value.filename == str(final)
    assert final.read_text() == "old\n" and _leftovers(tmp_path) == ["m.json"]


def test_a_failed_move_in_puts_the_old_file_back(tmp_path, no_rename_over, monkeypatch):
    final = tmp_path / "m.json"
    final.write_text("old\n")
    real_rename = os.rename

    def rename(src, dst, **kwargs):
        if Path(dst) == final and Path(src).name == "m.json":  # the new file moving in
            raise OSError(errno.EIO, "Input/output error", os.fspath(src), None,
                          os.fspath(dst))
        return real_rename(src, dst, **kwargs)

    monkeypatch.setattr(os, "rename", rename)
    with pytest.raises(OSError, match="Input/output") as err:
        atomic_write_text(final, "new\n")
    assert err.value.filename == str(final)  # not the temporary's
    assert final.read_text() == "old\n" and _leftovers(tmp_path) == ["m.json"]


@pytest.mark.parametrize("directory", [False, True])
def test_an_old_output_that_cannot_be_moved_back_is_kept_and_named(tmp_path, monkeypatch,
                                                                   no_rename_over, caplog,
                                                                   directory):
    """Both renames back fail (the share went away): the old output stays in the
    temporary, which is not removed (it was, with the old directory in it), the error says
    where it is, and the next run writing there says so again: never neither."""
    final = tmp_path / "out"
    if directory:
        final.mkdir()
        (final / "x").write_text("old\n")
    else:
        final.write_text("old\n")
    real_rename = os.rename

    def rename(src, dst, **kwargs):
        if Path(dst) == final:  # the new one moving in, and the old one moving back
            raise OSError(errno.EIO, "Input/output error", os.fspath(src), None,
                          os.fspath(dst))
        return real_rename(src, dst, **kwargs)

    monkeypatch.setattr(os, "rename", rename)
    with pytest.raises(OSError, match="Input/output"), \
            atomic_path(final, directory=directory) as tmp:
        if directory:
            tmp.mkdir()
            (tmp / "y").write_text("new\n")
        else:
            tmp.write_text("new\n")
    monkeypatch.undo()
    kept = [p for p in tmp_path.iterdir() if p.name != "out"]
    assert len(kept) == 1, _leftovers(tmp_path)
    aside = kept[0] / ".replaced"
    assert (aside / "x" if directory else aside).read_text() == "old\n"
    assert str(aside) in caplog.text
    caplog.clear()
    check_output(final, SCORES_JSON if not directory else fileio.DATASET_DIR)
    assert "holds the one it was replacing" in caplog.text


# --------------------------------------------------------- D6: a read-only directory
@pytest.fixture
def read_only_dir(tmp_path, monkeypatch):
    """A directory where, as on a read-only mount, nothing can be created (for root too:
    access() says yes there)."""
    ro = tmp_path / "ro"
    ro.mkdir()
    real_open, real_mkdir = os.open, os.mkdir

    def inside(path) -> bool:
        return os.path.abspath(os.fsdecode(path)).startswith(str(ro) + os.sep)

    def fake_open(path, flags, *args, **kwargs):
        if flags & os.O_CREAT and inside(path):
            raise OSError(errno.EROFS, "Read-only file system", os.fspath(path))
        return real_open(path, flags, *args, **kwargs)

    def fake_mkdir(path, *args, **kwargs):
        if inside(path):
            raise OSError(errno.EROFS, "Read-only file system", os.fspath(path))
        return real_mkdir(path, *args, **kwargs)

    monkeypatch.setattr(os, "open", fake_open)
    monkeypatch.setattr(os, "mkdir", fake_mkdir)
    return ro


@pytest.mark.parametrize("name", ["m.npz", "new/sub/m.npz"])
def test_check_output_refuses_a_directory_that_takes_no_file(read_only_dir, name):
    """It was refused only when the temporary could not be made, after all the work
    (train 41-72 s), naming the temporary."""
    out = read_only_dir / name
    with pytest.raises(OutputError) as err:
        check_output(out, MODEL_FILE)
    assert str(err.value) == (f"--out {out}: no file can be made in {read_only_dir}: "
                              "Read-only file system")


def test_a_late_failure_names_the_output_not_its_temporary(read_only_dir):
    """Made read-only after the check (a remount): the error names the output."""
    final = read_only_dir / "e.json"
    with pytest.raises(OSError) as err:
        atomic_write_text(final, "{}\n")
    assert err.value.filename == str(final) and err.value.errno == errno.EROFS


def test_a_full_disk_at_the_commit_names_the_output(tmp_path, monkeypatch):
    final = tmp_path / "e.json"

    def fsync(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", fsync)
    with pytest.raises(OSError) as err, atomic_path(final) as tmp:
        tmp.write_text("{}\n")
    assert err.value.filename == str(final)
    assert _leftovers(tmp_path) == []


def test_evaluate_refuses_a_read_only_json_before_its_table(read_only_dir, capsys,
                                                            tmp_path):
    bag = tmp_path / "drive"
    assert main(["simulate", "--minutes", "0.2", "--seed", "4", "--out", str(bag)]) == 0
    capsys.readouterr()
    out = read_only_dir / "e.json"
    assert main(["evaluate", str(MODEL), str(bag), "--json", str(out)]) == 2
    captured = capsys.readouterr()
    assert captured.err == (f"error: --json {out}: no file can be made in {read_only_dir}: "
                            "Read-only file system\n")
    assert "1.0 s" not in captured.out  # no table: nothing was evaluated


@pytest.mark.skipif(os.geteuid() != 0 or shutil.which("mount") is None,
                    reason="a read-only bind mount needs root")
def test_train_refuses_a_read_only_mount_before_any_work(tmp_path, capsys):
    src, ro = tmp_path / "src", tmp_path / "ro"
    src.mkdir()
    ro.mkdir()
    if subprocess.run(["mount", "--bind", str(src), str(ro)]).returncode != 0:
        pytest.skip("mount --bind failed")
    try:
        if subprocess.run(["mount", "-o", "remount,bind,ro", str(ro)]).returncode != 0:
            pytest.skip("remount read-only failed")
        bag = tmp_path / "drive"
        assert main(["simulate", "--minutes", "0.2", "--seed", "4", "--out", str(bag)]) == 0
        capsys.readouterr()
        out = ro / "m.npz"
        rc = main(["train", "--model", "first_order_lag", str(bag), "--out", str(out)])
        err = capsys.readouterr().err
        assert rc == 2
        assert err == (f"error: --out {out}: no file can be made in {ro}: Read-only file "
                       "system\n")
    finally:
        subprocess.run(["umount", str(ro)])


# --------------------------------------------------- D7: write errors that name no file
class _FullStream:
    """A text stream on a full device."""

    encoding = "utf-8"

    def write(self, text):
        raise OSError(errno.ENOSPC, "No space left on device")

    def flush(self):
        pass


def test_a_full_standard_output_is_named(capsys, monkeypatch):
    monkeypatch.setattr(sys, "stdout", _FullStream())
    assert main(["info", str(MODEL)]) == 2
    assert capsys.readouterr().err == ("error: standard output: No space left on device\n")
    assert isinstance(sys.stdout, _FullStream)  # given back as it was


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="no /dev/full")
def test_standard_output_on_dev_full_is_named():
    with open("/dev/full", "w") as full:
        proc = subprocess.run([sys.executable, "-m", "asgp_ros.cli", "info", str(MODEL)],
                              stdout=full, stderr=subprocess.PIPE, text=True, timeout=120,
                              cwd=REPO)
    assert proc.returncode == 2
    assert proc.stderr == "error: standard output: No space left on device\n"


def test_a_plot_on_a_full_disk_is_named_in_the_report(tmp_path, monkeypatch):
    """``asgp reproduce`` on a full disk said only "error: No space left on device"
    (matplotlib's savefig writes through a file object): it names the plot, in the
    report directory the user asked for."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.figure import Figure

    from asgp_ros.learning.reproduce import plots

    def savefig(self, fname, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Figure, "savefig", savefig)
    out = tmp_path / "rep"
    fig = plt.figure()
    try:
        with pytest.raises(OSError) as err, atomic_path(out, directory=True) as tmp:
            tmp.mkdir()
            plots._save(fig, tmp / "error_distributions.png", dpi=100)
    finally:
        plt.close(fig)
    assert err.value.filename == str(out / "error_distributions.png")
    assert _leftovers(tmp_path) == []
