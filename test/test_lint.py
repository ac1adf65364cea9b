"""Linters are tests: ruff at 99 columns; mypy --strict on the whole package."""

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


def test_mypy_strict(repo_root):
    """mypy.ini says where rclpy is let off."""
    pytest.importorskip("mypy")
    r = _run("mypy", "--strict", "asgp_ros", cwd=repo_root)
    assert r.returncode == 0, r.stdout + r.stderr


def test_core_and_friends_are_ros_free(repo_root):
    """Nothing under core/, sim/, vo/, serial/, common/ or learning/ imports rclpy
    (architecture rule)."""
    offenders = []
    for sub in ("core", "sim", "vo", "serial", "common", "learning"):
        for path in (repo_root / "asgp_ros" / sub).rglob("*.py"):
            for line in path.read_text().splitlines():
                stripped = line.strip()
                if stripped.startswith(("import rclpy", "from rclpy")):
                    offenders.append(f"{path.relative_to(repo_root)}: {stripped}")
    assert not offenders, offenders


#: The subpackages each subpackage of asgp_ros may import (the cli imports them all): the
#: folder tree is the architecture, and the imports only go down it.
LAYERS = {
    "common": set(),
    "core": {"common"},
    "vo": {"common"},
    "serial": {"common"},
    "recording": {"common", "core"},
    "sim": {"common", "core", "recording", "serial", "vo"},
    "learning": {"common", "core", "recording", "sim"},
    "nodes": {"common", "core", "recording", "serial", "vo"},
    "demo": {"common", "core", "learning", "nodes", "recording", "serial", "sim"},
}


def test_subpackages_import_only_the_layers_below(repo_root):
    """Bag I/O never imports the simulator, the core never the learning side, and so on."""
    import ast

    package = repo_root / "asgp_ros"
    offenders = []
    for sub, allowed in LAYERS.items():
        for path in sorted((package / sub).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.ImportFrom) and node.module:
                    names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
                elif isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                else:
                    continue
                used = {n.split(".")[1] for n in names
                        if n.startswith("asgp_ros.") and n.split(".")[1] in LAYERS}
                offenders += [f"{path.relative_to(repo_root)}:{node.lineno} imports {u}"
                              for u in sorted(used - allowed - {sub})]
    assert not offenders, offenders
