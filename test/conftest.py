"""Test-suite wide set-up.

ROS 2 isolation: every test run talks DDS on its own domain, restricted to this machine,
over UDPv4 only, so concurrent runs (or a demo) never see each other; under ``pytest -n N``
(pytest-xdist, as ``make test`` runs it) each worker has a domain of its own. Subprocesses
started by tests inherit these variables.
"""

from __future__ import annotations

import importlib.util
import os
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import pytest

REPO = Path(__file__).resolve().parents[1]


def _run_domain_id() -> int:
    forced = os.environ.get("ASGP_TEST_DOMAIN_ID")
    if forced:
        return int(forced)
    # 1..232: domain 0 is the default everybody uses, 233+ do not work with Fast DDS ports.
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")  # "gw0", "gw1", ... under pytest -n
    if worker.startswith("gw") and worker[2:].isdigit():
        # the workers of one run: consecutive domains from the controller's process id
        return 1 + (os.getppid() * 8 + int(worker[2:])) % 232
    return 1 + os.getpid() % 232


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
