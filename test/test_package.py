"""The package installs both ways users install it: ``pip install .`` and colcon."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

_SOURCES = ("asgp_ros", "config", "launch", "resource", "test", "package.xml", "setup.py",
            "setup.cfg", "pytest.ini", "ruff.toml", "mypy.ini")


def _copy_package(repo: Path, dest: Path) -> Path:
    pkg = dest / "src" / "asgp_ros"
    pkg.mkdir(parents=True)
    for name in _SOURCES:
        src = repo / name
        if src.is_dir():
            shutil.copytree(src, pkg / name, ignore=shutil.ignore_patterns("__pycache__"))
        elif src.exists():
            shutil.copy2(src, pkg / name)
    return pkg


def test_pip_install_puts_data_files_and_entry_points(repo_root, tmp_path):
    target = tmp_path / "prefix"
    r = subprocess.run(
        [sys.executable, "-m", "pip", "install", "--no-deps", "--no-build-isolation", "--quiet",
         "--ignore-installed",  # never touch the venv's own (editable) install
         "--prefix", str(target), str(repo_root)],
        capture_output=True, text=True, cwd=tmp_path,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    assert (target / "share/ament_index/resource_index/packages/asgp_ros").exists()
    assert (target / "share/asgp_ros/package.xml").exists()
    for exe in ("asgp", "predictor_node", "vo_node", "serial_bridge_node"):
        assert (target / "bin" / exe).exists(), exe


@pytest.mark.skipif(shutil.which("colcon", path=os.path.dirname(sys.executable)) is None,
                    reason="colcon is installed by `make test` (colcon-common-extensions)")
def test_colcon_build_and_test(repo_root, tmp_path):
    """colcon build installs the executables where ``ros2 run`` looks; colcon test runs pytest.

    The colcon test run is limited to the fast lint-free core tests so that the suite does
    not run itself twice; it proves the ament_python test harness works and that a failing
    test makes ``--return-code-on-test-failure`` fail.
    """
    colcon = shutil.which("colcon", path=os.path.dirname(sys.executable))
    ws = tmp_path / "ws"
    _copy_package(repo_root, ws)
    env = dict(os.environ)
    build = subprocess.run([colcon, "build", "--symlink-install"], cwd=ws, env=env,
                           capture_output=True, text=True)
    assert build.returncode == 0, build.stdout + build.stderr
    lib = ws / "install/asgp_ros/lib/asgp_ros"
    for exe in ("asgp", "predictor_node", "vo_node", "serial_bridge_node"):
        assert (lib / exe).exists(), f"{exe} not in {lib}"
    assert (ws / "install/asgp_ros/share/asgp_ros/package.xml").exists()

    test = subprocess.run(
        [colcon, "test", "--return-code-on-test-failure", "--pytest-args",
         "-k", "unicycle", "-p", "no:cacheprovider"],
        cwd=ws, env=env, capture_output=True, text=True,
    )
    assert test.returncode == 0, test.stdout + test.stderr
    report = (ws / "build/asgp_ros/pytest.xml").read_text()
    ran = re.search(r'tests="(\d+)"', report)
    assert ran is not None and int(ran.group(1)) > 0, report[:500]

    # a failing test must fail the colcon run
    (ws / "src/asgp_ros/test/test_zz_must_fail.py").write_text(
        "def test_unicycle_must_fail():\n    assert False\n")
    failing = subprocess.run(
        [colcon, "test", "--return-code-on-test-failure", "--pytest-args", "-k", "must_fail"],
        cwd=ws, env=env, capture_output=True, text=True,
    )
    assert failing.returncode != 0
