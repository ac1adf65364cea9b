"""`make bench` runs every benchmark script of benchmarks/, and only those."""

from __future__ import annotations

import shutil
import subprocess

import pytest


@pytest.mark.skipif(shutil.which("make") is None, reason="no make")
def test_make_bench_runs_the_benchmarks_and_not_the_echo_node(repo_root):
    """benchmarks/echo_node.py is the reference node predictor_latency.py starts and stops;
    run by `make bench` it answered on the user's domain until stopped, and no benchmark
    after it ran. The loop is run with each script echoed instead of run (and the set-up
    stamps emptied: nothing is installed)."""
    if not (repo_root / "Makefile").is_file():
        pytest.skip("not a source checkout")
    out = subprocess.run(
        ["make", "-s", "bench", "BENCH_RUN=echo", "STAMP=", "SYSSTAMP=", "DATA=/data"],
        cwd=repo_root, capture_output=True, text=True, timeout=60, check=True).stdout
    ran = {line.split()[1] for line in out.splitlines() if line.startswith("== ")}
    scripts = {f"benchmarks/{p.name}" for p in (repo_root / "benchmarks").glob("*.py")}
    assert ran == scripts - {"benchmarks/echo_node.py"}
    assert "benchmarks/calibration_regimes.py docs/reproduction/models/tile_asgp.npz " \
           "/data/tile/tile_07 /data/tile/tile_08" in out
