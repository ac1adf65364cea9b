"""The development set-up: `make bench` runs every benchmark script of benchmarks/ and only
those; concurrent test runs never share a ROS domain."""

from __future__ import annotations

import os
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


def test_two_test_runs_never_share_a_ros_domain(repo_root, tmp_path):
    """The domains of test processes were 1 + (ppid * 8 + worker) % 232: two runs whose
    controllers' process ids are equal modulo 29 shared all their domains, and their nodes
    got each other's messages. Each domain is now claimed by a lock file: two workers of
    the same name under one parent (the worst case) get two domains."""
    import sys

    child = ("import importlib.util, os, sys\n"
             f"spec = importlib.util.spec_from_file_location('c', {str(repo_root)!r} "
             "+ '/test/conftest.py')\n"
             "spec.loader.exec_module(importlib.util.module_from_spec(spec))\n"
             "print(os.environ['ROS_DOMAIN_ID'], flush=True)\n"
             "sys.stdin.read()\n")
    env = {k: v for k, v in os.environ.items() if k != "ASGP_TEST_DOMAIN_ID"}
    env["PYTEST_XDIST_WORKER"] = "gw0"
    procs = [subprocess.Popen([sys.executable, "-c", child], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True, env=env, cwd=tmp_path)
             for _ in range(2)]
    try:
        domains = [int(p.stdout.readline()) for p in procs]
    finally:
        for p in procs:
            p.communicate("", timeout=30)
    assert domains[0] != domains[1] and all(1 <= d <= 232 for d in domains)
