"""The variance calibration of a model fitted again on the held-out part of its bags, with
its coverage per speed regime, joystick steadiness and both together.

    .venv/bin/python benchmarks/calibration_regimes.py MODEL BAG... [--holdout 0.5]
                                                       [--case-lags 12]

For a model trained before the report crossed the speed regimes with the joystick's
steadiness: the model's calibration is set aside, the last ``--holdout`` of each bag is
held out, and :func:`asgp_ros.learning.training.calibrate` fits the map again there and
reports the held-out coverage of the 95 % ellipse, raw and calibrated (cross-validated:
each half of the cases scored with the map fitted on the other), as ``asgp info`` prints
it. Give bags the model was not trained on: a trained model's posterior is conditioned on
all of its training data, the part ``asgp train`` held out included, so on its own bags
these figures would be partly in-sample.

Prints figures only (no assertions).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from asgp_ros.cli.info import coverage_lines
from asgp_ros.core.calibration import VarianceCalibration
from asgp_ros.core.modelfile import load_model
from asgp_ros.learning.training import AutoOptions, calibrate, read_series, split_holdout


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("bags", nargs="+")
    ap.add_argument("--holdout", type=float, default=0.5,
                    help="fraction of each bag held out, its end (0.05-0.5)")
    ap.add_argument("--case-lags", type=int, default=12,
                    help="past samples a case needs (asgp train: the largest s it tries)")
    args = ap.parse_args()
    model = load_model(args.model)
    model = dataclasses.replace(model, calibration=VarianceCalibration())
    opts = AutoOptions(holdout=args.holdout)
    series = read_series(args.bags, resample_config=model.resample_config)
    _, held = split_holdout(series, opts.holdout)
    cal, report = calibrate(model, held, opts, max(args.case_lags, model.feature_config.lags))
    print(f"{args.model} on the held-out {100 * opts.holdout:.0f} % of {len(held)} bag(s): "
          f"speed regimes split at {', '.join(f'{e:.3f}' for e in cal.speed_edges)} m/s")
    for line in coverage_lines(report):
        print(line)


if __name__ == "__main__":
    main()
