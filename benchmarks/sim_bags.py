"""Simulator and bag I/O speed: one 20-minute recording simulated, written, read back.

Usage::

    python benchmarks/sim_bags.py                 # 20 min, tile, mcap (targets: < 10 s, < 5 s)
    python benchmarks/sim_bags.py --minutes 5 --surface carpet --storage sqlite3

Prints figures only (no assertions). Timings depend on the machine's load.
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
from pathlib import Path

from asgp_ros.recording.bags import read_streams, write_bag
from asgp_ros.sim.simulate import simulate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=20.0)
    ap.add_argument("--surface", default="tile", choices=("tile", "carpet", "hybrid"))
    ap.add_argument("--storage", default="mcap", choices=("mcap", "sqlite3", "ros1"))
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    print(f"python {platform.python_version()} on {platform.machine()}, "
          f"{args.minutes:g} min {args.surface} recording, {args.storage}")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / ("drive.bag" if args.storage == "ros1" else "drive")
        t0 = time.perf_counter()
        rec = simulate(args.surface, args.minutes, args.seed)
        t1 = time.perf_counter()
        write_bag(path, rec, storage=args.storage)
        t2 = time.perf_counter()
        streams = read_streams(path)
        t3 = time.perf_counter()
        read_streams(path, truth_topic="/ground_truth/odom")
        t4 = time.perf_counter()
        size = sum(p.stat().st_size for p in ([path] if path.is_file() else path.iterdir()))
    n_msgs = rec.joy_t.size + rec.vo_t.size + rec.truth_t[::5].size
    print(f"simulate              {t1 - t0:6.2f} s")
    print(f"write bag             {t2 - t1:6.2f} s  ({n_msgs} messages, {size / 1e6:.1f} MB)")
    print(f"simulate + write      {t2 - t0:6.2f} s  (target < 10 s for 20 min)")
    print(f"read /joy + /vo/twist {t3 - t2:6.2f} s  (target < 5 s; "
          f"{streams.joy_t.size} joystick, {streams.vel_t.size} VO samples)")
    print(f"read incl. truth      {t4 - t3:6.2f} s")


if __name__ == "__main__":
    main()
