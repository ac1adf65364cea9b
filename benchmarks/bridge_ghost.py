"""How long a stopped serial_bridge_node stays on the ROS graph, where a restarted bridge
takes it for a second chair's and refuses overrides (``_check_crowd``).

    .venv/bin/python benchmarks/bridge_ghost.py [--domain-id 187] [--timeout 60]

Starts ``serial_bridge_node`` (its port never opens: the node runs, it is not needed here)
on a ROS domain of its own (localhost, UDPv4), waits until a watcher sees it on the graph,
stops it by SIGKILL, SIGINT and SIGTERM in turn, and prints how long the watcher still sees
a node of its name. SIGKILL leaves its DDS participant to expire by its lease (Fast DDS's
default: 20 s); a stop by signal destroys the node and leaves nothing.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--domain-id", type=int, default=187)
    ap.add_argument("--timeout", type=float, default=60.0)
    args = ap.parse_args()
    os.environ.update(ROS_DOMAIN_ID=str(args.domain_id),
                      ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                      FASTDDS_BUILTIN_TRANSPORTS="UDPv4")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])]))
    import rclpy

    rclpy.init()
    watcher = rclpy.create_node("bridge_ghost_watcher")

    def seen() -> bool:
        return ("serial_bridge_node", "/") in watcher.get_node_names_and_namespaces()

    def wait(want: bool) -> float:
        start = time.monotonic()
        while seen() != want and time.monotonic() - start < args.timeout:
            rclpy.spin_once(watcher, timeout_sec=0.1)
        return time.monotonic() - start

    for sig in (signal.SIGKILL, signal.SIGINT, signal.SIGTERM):
        proc = subprocess.Popen(
            [sys.executable, "-m", "asgp_ros.nodes.serial_bridge_node", "--ros-args", "-p",
             f"port:={REPO / 'no_such_port'}"], env=env,
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            wait(True)
            time.sleep(1.0)
            proc.send_signal(sig)
            proc.wait(timeout=args.timeout)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        left = wait(False)
        still = " (still there at the timeout)" if seen() else ""
        print(f"{sig.name}: exit {proc.returncode}, on the graph {left:.1f} s after{still}")
    watcher.destroy_node()
    rclpy.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
