"""Test-suite wide set-up.

ROS 2 isolation: every test run talks DDS on its own domain, restricted to this machine,
over UDPv4 only, so concurrent runs (or a demo) never see each other; under ``pytest -n N``
(pytest-xdist, as ``make test`` runs it) each worker has a domain of its own. Subprocesses
started by tests inherit these variables.
"""

from __future__ import annotations

import fcntl
import importlib.util
import os
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import pytest

REPO = Path(__file__).resolve().parents[1]


#: Lock files of the domains claimed by the test processes running on this machine.
_DOMAIN_LOCKS = Path(tempfile.gettempdir()) / "asgp_ros_test_domains"
_held_locks: list[int] = []  # held open (and so locked) for the process's life


def _claim_domain(domain: int) -> bool:
    """Lock ``domain`` for this process; False when another process holds it (or the lock
    file cannot be made: another user's, a read-only temp dir)."""
    try:
        _DOMAIN_LOCKS.mkdir(exist_ok=True)
        fd = os.open(_DOMAIN_LOCKS / f"{domain}.lock", os.O_RDWR | os.O_CREAT, 0o666)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return False
    _held_locks.append(fd)
    return True


def _run_domain_id() -> int:
    """This process's domain: ASGP_TEST_DOMAIN_ID when given, else the first free one from
    a start taken from the process ids, claimed by a lock file, so that concurrent runs on
    the machine (their process ids equal modulo 29 gave two runs the same 8 domains) and
    the workers of one run never share a domain."""
    forced = os.environ.get("ASGP_TEST_DOMAIN_ID")
    if forced:
        _claim_domain(int(forced))  # (best effort: other runs then pass it by)
        return int(forced)
    # 1..232: domain 0 is the default everybody uses, 233+ do not work with Fast DDS ports.
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")  # "gw0", "gw1", ... under pytest -n
    if worker.startswith("gw") and worker[2:].isdigit():
        # the workers of one run: consecutive domains from the controller's process id
        start = (os.getppid() * 8 + int(worker[2:])) % 232
    else:
        start = os.getpid() % 232
    for i in range(232):
        if _claim_domain(1 + (start + i) % 232):
            return 1 + (start + i) % 232
    return 1 + start  # every domain taken (or no lock file possible): as before


os.environ["ROS_DOMAIN_ID"] = str(_run_domain_id())
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ["FASTDDS_BUILTIN_TRANSPORTS"] = "UDPv4"
os.environ.setdefault("AMENT_PREFIX_PATH", sys.prefix)
os.environ.setdefault("MPLBACKEND", "Agg")


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO


@pytest.fixture(scope="session")
def load_benchmark() -> Callable[[str], ModuleType]:
    """A loader of a script of benchmarks/ as a module (``load_benchmark("rollout")``), for
    the tests of its parts; skips the test outside a source checkout (an installed or
    colcon-copied package has no benchmarks/)."""
    loaded: dict[str, ModuleType] = {}

    def load(name: str) -> ModuleType:
        if name in loaded:
            return loaded[name]
        path = REPO / "benchmarks" / f"{name}.py"
        if not path.is_file():
            pytest.skip(f"{path} is not here (not a source checkout)")
        spec = importlib.util.spec_from_file_location(f"_bench_{name}", path)
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = module  # its dataclasses look their module up
        spec.loader.exec_module(module)
        loaded[name] = module
        return module

    return load


@pytest.fixture
def rclpy_context():
    """An rclpy context of its own for an in-process node test; shut down afterwards."""
    rclpy = pytest.importorskip("rclpy")
    context = rclpy.context.Context()
    rclpy.init(context=context)
    try:
        yield context
    finally:
        rclpy.try_shutdown(context=context)
