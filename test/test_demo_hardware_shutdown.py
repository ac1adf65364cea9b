"""The demo's simulated hardware stops cleanly when a signal lands in a publication.

rclpy's signal handlers shut the context down from their own thread; a callback that is
publishing at that moment gets an RCLError ("publisher's context is invalid"). The soak
test (benchmarks/soak.py) met it: the hardware process ended with a traceback and exit
code 1, which ``asgp demo`` reports as a failed run. Here the race is made certain: while
the diagnostics callback runs, another thread shuts the context down (what rclpy's signal
handler thread does on SIGINT), then the callback publishes.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("rclpy")

pytestmark = pytest.mark.ros

_SCRIPT = """
import sys, threading
from asgp_ros.demo import hardware

original = hardware.HardwareNode._publish_diagnostics

def racing(self):
    # the signal handler's thread shuts the context down...
    shutdown = threading.Thread(target=self.context.try_shutdown)
    shutdown.start()
    shutdown.join(5.0)
    print("context down:", not self.context.ok(), flush=True)
    original(self)  # ...while this callback still publishes

hardware.HardwareNode._publish_diagnostics = racing
sys.exit(hardware.main(["--ros-args", "-p", "port:=" + sys.argv[1], "-p", "width:=64",
                        "-p", "height:=48", "-p", "diagnostics_period_s:=0.2"]))
"""


def test_a_signal_during_a_publication_is_a_clean_stop(repo_root: Path, tmp_path: Path):
    env = dict(os.environ, PYTHONPATH=str(repo_root), PYTHONUNBUFFERED="1")
    proc = subprocess.run([sys.executable, "-c", _SCRIPT, str(tmp_path / "joystick")],
                          cwd=repo_root, env=env, capture_output=True, text=True,
                          timeout=120)
    output = proc.stdout + proc.stderr
    assert "context down: True" in output, output
    assert "Traceback" not in output, output
    assert proc.returncode == 0, output
