"""Training time of the automatic ASGP configuration on 120 minutes of data.

Issue target: the automatic configuration (selection + final fit + calibration) of
``asgp train`` takes at most 3 minutes (``--budget-s 180``, the default) for 120 minutes
of 5 Hz data on 2 cores. Prints the time of the selection, of the final fit of the chosen
model and of the calibration, each candidate's held-out scores, and, side by side, the
time of the paper's configuration (s = 4, M = 20/40, all rows) as the reference.

The data: the first six tile recordings of ``--data`` (a directory made by
``asgp dataset``), or, without ``--data``, six 20-minute tile drives simulated into a
temporary directory first (about a minute; not counted).

    python benchmarks/train.py [--data DIR] [--budget-s 180] [--seed 0] [--surface tile]

Prints figures only (no assertions), and the load average, since a shared machine
inflates them.
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from asgp_ros.cli.train import selection_table
from asgp_ros.learning.training import PAPER_OPTIONS, AutoOptions, read_series, train, train_auto

BAG_SUFFIXES = (".bag", ".mcap", ".db3")


def _bags(data: Path, surface: str, count: int) -> list[str]:
    folder = data / surface
    found = sorted(p for p in folder.iterdir()
                   if p.is_dir() or p.suffix in BAG_SUFFIXES) if folder.is_dir() else []
    if len(found) < count:
        sys.exit(f"{folder}: {len(found)} recordings, the benchmark needs {count}")
    return [str(p) for p in found[:count]]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=None,
                    help="dataset directory (asgp dataset); default: simulate one")
    ap.add_argument("--surface", default="tile", choices=("tile", "carpet"))
    ap.add_argument("--budget-s", type=float, default=180.0)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    with tempfile.TemporaryDirectory(prefix="asgp-bench-train-") as tmp:
        data = args.data
        if data is None:
            data = Path(tmp) / "data"
            print("simulating 6 x 20 min of tile and carpet (not timed) ...", flush=True)
            subprocess.run([sys.executable, "-m", "asgp_ros.cli", "dataset", "--out",
                            str(data), "--scale", "1", "--seed", str(args.seed)],
                           check=True, stdout=subprocess.DEVNULL)
        paths = _bags(data, args.surface, 6)
        t0 = time.perf_counter()
        series = read_series(paths)
        t_read = time.perf_counter() - t0
        minutes = sum(float(s.res.t[-1] - s.res.t[0]) for s in series) / 60.0
        print(f"machine: {platform.machine()}, {os.cpu_count()} CPU(s), load average "
              f"{os.getloadavg()[0]:.2f}")
        print(f"data: {len(paths)} {args.surface} recordings, {minutes:.1f} min "
              f"(read and resampled in {t_read:.1f} s, not counted)")

        t0 = time.perf_counter()
        model = train_auto(series, AutoOptions(seed=args.seed, budget_s=args.budget_s),
                           progress=lambda ch, msg: None)
        t_auto = time.perf_counter() - t0
        secs = model.meta["selection"]["seconds"]
        cal = model.meta["calibration"]
        print(f"\nautomatic configuration (budget {args.budget_s:g} s): {t_auto:.1f} s in all")
        print(f"  selection    {secs['selection']:7.1f} s  "
              f"({len(model.meta['selection']['candidates'])} candidates, "
              f"{model.meta['selection']['selection_rows']} rows each)")
        print(f"  final fit    {secs['final_fit']:7.1f} s  "
              f"({model.meta['selection']['final_rows']} rows per channel at most)")
        print(f"  calibration  {cal.get('seconds', 0.0):7.1f} s")
        print(f"  target: at most 180 s for 120 min on 2 cores -> "
              f"{'met' if t_auto <= 180.0 else 'NOT met'} ({t_auto:.1f} s for "
              f"{minutes:.0f} min)")
        print("\ncandidates (held-out success rate of the k-step rollout):")
        for line in selection_table(model):
            print("  " + line)

        t0 = time.perf_counter()
        train(series, PAPER_OPTIONS, progress=lambda ch, msg: None)
        t_paper = time.perf_counter() - t0
        print(f"\nreference: the paper's configuration on all rows: {t_paper:.1f} s "
              f"(automatic / paper = {t_auto / t_paper:.1f}x)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
