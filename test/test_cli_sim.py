"""``asgp simulate`` and ``asgp dataset`` end to end, on tiny durations."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from asgp_ros.cli import main
from asgp_ros.recording.bags import read_sim_metadata, read_streams


def _asgp(repo_root, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "asgp_ros.cli", *args], cwd=repo_root,
                          capture_output=True, text=True, timeout=120)


def test_simulate_end_to_end(repo_root, tmp_path):
    out = tmp_path / "drive"
    r = _asgp(repo_root, "simulate", "--surface", "carpet", "--minutes", "0.2", "--seed", "5",
              "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert "carpet" in r.stdout and str(out) in r.stdout
    s = read_streams(out, truth_topic="/ground_truth/odom")
    assert s.duration > 11.0 and s.has_truth
    assert read_sim_metadata(out)["seed"] == 5
    # An existing bag is not replaced silently.
    r = _asgp(repo_root, "simulate", "--minutes", "0.2", "--out", str(out))
    assert r.returncode == 2 and "exists" in r.stderr and "Traceback" not in r.stderr


def test_simulate_storages_and_bad_input(tmp_path, capsys):
    assert main(["simulate", "--minutes", "0.15", "--storage", "sqlite3",
                 "--out", str(tmp_path / "sq")]) == 0
    assert list((tmp_path / "sq").glob("*.db3"))
    assert main(["simulate", "--minutes", "0.15", "--out", str(tmp_path / "r1.bag")]) == 0
    assert (tmp_path / "r1.bag").is_file()
    capsys.readouterr()
    assert main(["simulate", "--minutes", "0", "--out", str(tmp_path / "z")]) == 2
    assert "minutes" in capsys.readouterr().err
    assert not (tmp_path / "z").exists()
    assert main(["simulate", "--surface", "grass", "--out", str(tmp_path / "g")]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "invalid choice: 'grass'" in err


def test_dataset_layout_manifest_and_resume(repo_root, tmp_path):
    out = tmp_path / "data"
    r = _asgp(repo_root, "dataset", "--out", str(out), "--scale", "0.006", "--seed", "2",
              "--jobs", "2")
    assert r.returncode == 0, r.stderr
    assert "18/18" in r.stdout and r.stderr == ""  # progress bar
    counts = {s: sorted(p.name for p in (out / s).iterdir()) for s in ("tile", "carpet",
                                                                      "hybrid")}
    assert counts["tile"] == [f"tile_{k:02d}" for k in range(1, 9)]
    assert len(counts["carpet"]) == 8 and len(counts["hybrid"]) == 2
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["scale"] == 0.006 and len(manifest["bags"]) == 18
    seeds = [b["seed"] for b in manifest["bags"]]
    assert len(set(seeds)) == 18
    splits = [(b["surface"], b["split"]) for b in manifest["bags"]]
    assert splits.count(("tile", "train")) == 6 and splits.count(("hybrid", "test")) == 2
    for b in manifest["bags"]:
        meta = read_sim_metadata(out / b["path"])
        assert (meta["seed"], meta["surface"]) == (b["seed"], b["surface"])
        assert meta["duration_s"] == pytest.approx(0.006 * 20 * 60)
    # Bags differ from one another (distinct seeds: 7 s bags are all lead-in and tail,
    # but the sensor timing differs).
    a = read_streams(out / "tile/tile_01")
    b = read_streams(out / "tile/tile_02")
    assert a.joy_t.shape != b.joy_t.shape or not np.array_equal(a.joy_t, b.joy_t)
    # A second run keeps the bags it already has.
    mtime = (out / "tile/tile_01/tile_01.mcap").stat().st_mtime_ns
    r = _asgp(repo_root, "dataset", "--out", str(out), "--scale", "0.006", "--seed", "2")
    assert r.returncode == 0, r.stderr
    assert "18 already present" in r.stdout
    assert (out / "tile/tile_01/tile_01.mcap").stat().st_mtime_ns == mtime
    # ... but refuses to mix datasets.
    r = _asgp(repo_root, "dataset", "--out", str(out), "--scale", "0.006", "--seed", "3")
    assert r.returncode == 2 and "--force" in r.stderr


def test_dataset_bad_arguments(tmp_path, capsys):
    assert main(["dataset", "--out", str(tmp_path / "d"), "--scale", "0.001"]) == 2
    assert "scale" in capsys.readouterr().err
    assert main(["dataset", "--out", str(tmp_path / "d"), "--jobs", "0"]) == 2


def test_a_command_imports_its_own_module_alone(repo_root):
    """``asgp info MODEL`` imports the info command's module (and what it needs), not the
    other commands' (the simulator, the demo, scipy's optimisers: a second and more of
    start-up); ``asgp --help`` and a mistyped command still see every command."""
    model = repo_root / "docs" / "reproduction" / "models" / "tile_asgp.npz"
    code = ("import sys\n"
            "from asgp_ros.cli import main\n"
            f"rc = main(['-v', 'info', {str(model)!r}])\n"
            "print('loaded', rc, *sorted(m for m in sys.modules if m.startswith(('asgp_ros.cli.',"
            " 'scipy.optimize', 'scipy.cluster', 'asgp_ros.sim'))))\n")
    r = subprocess.run([sys.executable, "-c", code], cwd=repo_root, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    loaded = r.stdout.splitlines()[-1].split()
    assert loaded[:2] == ["loaded", "0"] and "asgp_ros.cli.info" in loaded
    assert not any(m.startswith(("asgp_ros.cli.demo", "asgp_ros.cli.reproduce",
                                 "asgp_ros.cli.simulate", "scipy.optimize", "scipy.cluster",
                                 "asgp_ros.sim")) for m in loaded), loaded
    every = ["adapt", "bag", "board", "dataset", "demo", "evaluate", "info", "replay",
             "reproduce", "simulate", "train"]
    for top in (["--help"], ["-h", "info"], ["-v", "--help", "train"]):
        r = _asgp(repo_root, *top)
        assert r.returncode == 0 and all(name in r.stdout for name in every), top
    r = _asgp(repo_root, "-v", "infoo", "x")
    assert r.returncode == 2 and "invalid choice: 'infoo'" in r.stderr
    assert all(f"'{name}'" in r.stderr for name in every)


def test_every_help_text_reads_as_printed():
    """Each command's --help (and its subcommands'): argparse %-formats an argument's help
    but not a description, so a doubled percent sign there was printed as "%%"."""
    import argparse

    from asgp_ros.cli import build_parser

    def parsers(parser: argparse.ArgumentParser):
        yield parser
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub in action.choices.values():
                    yield from parsers(sub)

    seen = 0
    for parser in parsers(build_parser()):
        text = parser.format_help()
        assert "%%" not in text and "%(" not in text, (parser.prog, text)
        # and every option says what it does
        bare = [a.option_strings for a in parser._actions if a.option_strings and not a.help]
        assert not bare, (parser.prog, bare)
        seen += 1
    assert seen >= 12
