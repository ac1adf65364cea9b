"""What reading the VO at the middle of its frame interval is worth, against ground truth.

A frame-to-frame VO reports the mean velocity since the previous frame, stamped with the
newer frame (``asgp_ros.core.resample``, "Odometry stamps"). On simulated tile drives, for
both conventions (``ResampleConfig.vel_stamp`` "frame" and "midpoint"), prints:

* how far the path integrated from the resampled VO ends from the true path after 1.0 and
  2.0 s (median and p90 over every valid step of a held-out bag);
* an ASGP (s = 10, coupled, M = 80, `asgp train --vo-stamp ...`) trained on the training
  bags and scored by `asgp evaluate --truth` on the held-out bag: success and median error
  at 2.0 s against the VO's own path and against the true path.

Usage: benchmarks/vo_stamps.py [--train-minutes 30] [--bags 2] [--test-minutes 30] [--keep DIR]
(the defaults are the figures in README.md, "VO stamps"; a few minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from asgp_ros.common.topics import BAG_GROUND_TRUTH
from asgp_ros.core import metrics
from asgp_ros.core.resample import VEL_STAMPS, ResampleConfig
from asgp_ros.learning.evaluation import reference_path
from asgp_ros.learning.training import read_series


def _asgp(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "asgp_ros.cli", *args], check=True,
                   stdout=subprocess.DEVNULL)


def vo_path_errors(bag: str, stamp: str, steps: tuple[int, ...]) -> dict[int, np.ndarray]:
    """Error (m) of the VO-integrated path against the true one after each of ``steps``."""
    config = ResampleConfig(vel_stamp=stamp)
    res = read_series([bag], resample_config=config, truth_topic=BAG_GROUND_TRUTH)[0].res
    k = max(steps)
    segment = np.where(res.truth_valid, res.segment, -1)
    idx = metrics.case_indices(segment, 1, k)
    path = reference_path(metrics.windows(res.vel, idx, -1, k + 1), config.dt)
    out = {}
    for n in steps:
        true = metrics.relative_displacement(res.truth[idx - 1, :3], res.truth[idx - 1 + n, :3])
        out[n] = np.hypot(*(path[:, n - 1, :2] - true[:, :2]).T)
    return out


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--train-minutes", type=float, default=30.0)
    ap.add_argument("--bags", type=int, default=2)
    ap.add_argument("--test-minutes", type=float, default=30.0)
    ap.add_argument("--keep", help="directory for the bags and models (default: temporary)")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.keep or tmp)
        work.mkdir(parents=True, exist_ok=True)
        train = [str(work / f"train_{i}") for i in range(args.bags)]
        test = str(work / "test")
        for i, bag in enumerate(train):
            if not Path(bag).exists():
                _asgp("simulate", "--surface", "tile", "--minutes", str(args.train_minutes),
                      "--seed", str(101 + i), "--out", bag)
        if not Path(test).exists():
            _asgp("simulate", "--surface", "tile", "--minutes", str(args.test_minutes),
                  "--seed", "104", "--out", test)
        print(f"tile, {args.bags} x {args.train_minutes:g} min to train, "
              f"{args.test_minutes:g} min held out")
        print("VO-integrated path against the true path (cm): stamp | 1.0 s median / p90 "
              "| 2.0 s median / p90")
        for stamp in VEL_STAMPS:
            err = vo_path_errors(test, stamp, (5, 10))
            print(f"  {stamp:8s} | " + " | ".join(
                f"{100 * np.median(e):5.2f} / {100 * np.percentile(e, 90):5.2f}"
                for e in err.values()))
        print("ASGP s = 10, coupled, M = 80 at 2.0 s: stamp | vs VO success, median "
              "| vs truth success, median")
        for stamp in VEL_STAMPS:
            model, scores = work / f"{stamp}.npz", work / f"{stamp}.json"
            _asgp("train", *train, "--lags", "10", "--coupled", "--inducing-v", "80",
                  "--inducing-w", "80", "--vo-stamp", stamp, "--out", str(model), "--force")
            _asgp("evaluate", str(model), test, "--truth", "--json", str(scores), "--force")
            h = json.loads(scores.read_text())["horizons"]["2.0"]
            t = h["truth"]
            print(f"  {stamp:8s} | {100 * h['success_rate']:5.1f} %, "
                  f"{100 * h['median_error_m']:4.2f} cm | {100 * t['success_rate']:5.1f} %, "
                  f"{100 * t['median_error_m']:4.2f} cm")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
