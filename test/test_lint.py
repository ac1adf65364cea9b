"""Linters are tests: ruff at 99 columns; mypy --strict on the core and the nodes."""

from __future__ import annotations

import subprocess
import sys

import pytest


def _run(*args: str, cwd) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", *args], cwd=cwd, capture_output=True, text=True)


def test_ruff(repo_root):
    pytest.importorskip("ruff")
    r = _run("ruff", "check", "asgp_ros", "test", "benchmarks", "launch", cwd=repo_root)
    assert r.returncode == 0, r.stdout + r.stderr


def test_mypy_strict_core_and_nodes(repo_root):
    """mypy.ini says where rclpy and the not-yet-strict vo/ and sim/ are let off."""
    pytest.importorskip("mypy")
    r = _run("mypy", "--strict", "asgp_ros/core", "asgp_ros/nodes", cwd=repo_root)
    assert r.returncode == 0, r.stdout + r.stderr


def test_core_and_friends_are_ros_free(repo_root):
    """Nothing under core/, sim/, vo/, serial/ imports rclpy (architecture rule)."""
    offenders = []
    for sub in ("core", "sim", "vo", "serial"):
        for path in (repo_root / "asgp_ros" / sub).rglob("*.py"):
            for line in path.read_text().splitlines():
                stripped = line.strip()
                if stripped.startswith(("import rclpy", "from rclpy")):
                    offenders.append(f"{path.relative_to(repo_root)}: {stripped}")
    assert not offenders, offenders
