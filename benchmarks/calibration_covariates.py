"""Could a causal statistic tell the calibration which floor it is on? Measured on recordings.

Usage::

    python benchmarks/calibration_covariates.py DATA [--model both_asgp.npz]
        [--windows 20 50] [--bins 3]

DATA is a dataset of ``asgp dataset`` (the reproduction's: ``--scale 1 --seed 0``); the
model is a committed one (``docs/reproduction/models``, default the Both model, trained on
tile_01-03 and carpet_01-03). Its stored variance calibration holds for the pooled held-out
part of those bags; per floor it does not (``asgp info``: the carpet bags' held-out cases
are covered less than the tile bags'). A static calibration could only tell the floors
apart by something known when the prediction is made. Two candidates, over the last W grid
steps before the prediction, from the model's own one-step predictions of the measured
velocities (r = (measured - mean) / sd per channel, the calibrated one-step variance):

* ``surprise``: mean of |r|^2 / 2 (1 for an honest variance);
* ``bias``: W |mean of r|^2 / 2 (1 for independent errors; larger when the errors persist,
  which is what makes k-step errors outgrow their propagated variance).

For each statistic and window, the held-out cases (the last 20 % of each training bag) are
cut into ``--bins`` equal parts of the statistic, each with the factor on the covariance
that makes its 95 % coverage 95 %; the test bags of each floor (tile_07-08, carpet_07-08,
hybrid_01-02) are then scored: coverage of the 95 % ellipse with the stored calibration and
with the bins' factors, and the factor each bin of that floor would have needed. A
statistic that explains the floors' difference gives each floor's bins different needed
factors (growing with the statistic); one that does not leaves them alike within a floor.
Figures only (no assertions); about a minute on one core.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from asgp_ros.core import metrics
from asgp_ros.core.metrics import CHI2_2DOF_95, mahalanobis_sq
from asgp_ros.core.modelfile import load_model
from asgp_ros.learning.evaluation import reference_path, rollout_cases
from asgp_ros.learning.training import Series, read_series, split_holdout

REPO = Path(__file__).resolve().parents[1]
MODELS = REPO / "docs" / "reproduction" / "models"
TRAIN_BAGS = [f"tile/tile_0{i}" for i in (1, 2, 3)] + [f"carpet/carpet_0{i}" for i in (1, 2, 3)]
TEST_BAGS = {"tile": ["tile/tile_07", "tile/tile_08"],
             "carpet": ["carpet/carpet_07", "carpet/carpet_08"],
             "hybrid": ["hybrid/hybrid_01", "hybrid/hybrid_02"]}
HORIZONS_S = (1.0, 1.4, 2.0)


def residuals(model, res) -> np.ndarray:
    """[T, 2] normalised one-step residuals of every grid step (NaN where none)."""
    s = model.lags
    out = np.full((len(res), 2), np.nan)
    idx = metrics.case_indices(res.segment, s, 1)
    if idx.size:
        mean, var = model.predict_step(metrics.windows(res.joy, idx, -s, s),
                                       metrics.windows(res.vel, idx, -s, s), res.joy[idx])
        out[idx] = (res.vel[idx] - mean) / np.sqrt(var)
    return out


def cases(model, series: list[tuple[Series, np.ndarray]], k: int, window: int
          ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(d2 [N]: squared Mahalanobis distance of the k-step error under the stored
    calibration; the statistics [N] per name) of every case with a full window before it;
    ``series`` with their :func:`residuals`."""
    d2_l: list[np.ndarray] = []
    stats_l: dict[str, list[np.ndarray]] = {"surprise": [], "bias": []}
    for se, resid in series:
        res = se.res
        idx = metrics.case_indices(res.segment, max(model.lags, window + 1), k)
        if idx.size == 0:
            continue
        r = metrics.windows(resid, idx, -window, window)  # [N, W, 2]
        pose, cov, _ = rollout_cases(model, res, idx, k, uncertainty="linear")
        assert cov is not None
        ref = reference_path(metrics.windows(res.vel, idx, -1, k + 1), 1.0 / model.rate_hz)
        d2_l.append(mahalanobis_sq(ref[:, -1, :2] - pose[:, -1, :2], cov[:, -1]))
        stats_l["surprise"].append(0.5 * np.mean(np.sum(r**2, axis=2), axis=1))
        stats_l["bias"].append(0.5 * window * np.sum(np.mean(r, axis=1) ** 2, axis=1))
    d2 = np.concatenate(d2_l)
    stats = {name: np.concatenate(v) for name, v in stats_l.items()}
    ok = np.isfinite(d2) & np.all([np.isfinite(v) for v in stats.values()], axis=0)
    return d2[ok], {name: v[ok] for name, v in stats.items()}


def needed(d2: np.ndarray) -> float:
    """The factor on the covariance that makes these cases' 95 % coverage 95 %."""
    return float(np.quantile(d2, 0.95) / CHI2_2DOF_95) if d2.size >= 50 else float("nan")


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path, help="the dataset (asgp dataset --scale 1 --seed 0)")
    ap.add_argument("--model", type=Path, default=MODELS / "both_asgp.npz")
    ap.add_argument("--windows", type=int, nargs="+", default=[20, 50],
                    help="grid steps before the prediction")
    ap.add_argument("--bins", type=int, default=3)
    args = ap.parse_args(argv)
    if args.bins < 1 or min(args.windows) < 1:
        ap.error("--bins and --windows must be positive")
    model = load_model(args.model)
    rc = model.resample_config
    train = read_series([str(args.data / p) for p in TRAIN_BAGS], resample_config=rc)
    _, held_series = split_holdout(train, 0.2)
    held = [(se, residuals(model, se.res)) for se in held_series]
    tests = {floor: [(se, residuals(model, se.res))
                     for se in read_series([str(args.data / p) for p in paths],
                                           resample_config=rc)]
             for floor, paths in TEST_BAGS.items()}
    print(f"model {args.model.name}; held out: the last 20 % of {', '.join(TRAIN_BAGS)}")
    print("coverage of the 95 % ellipse (%): stored calibration -> with the statistic's "
          "bins; the factor each bin needed")
    for window in args.windows:
        for h in HORIZONS_S:
            k = round(h * model.rate_hz)
            d2h, sh = cases(model, held, k, window)
            test_cases = {floor: cases(model, ser, k, window) for floor, ser in tests.items()}
            for name in ("surprise", "bias"):
                edges = np.quantile(sh[name], np.arange(1, args.bins) / args.bins)
                b = np.searchsorted(edges, sh[name])
                f = np.array([needed(d2h[b == i]) for i in range(args.bins)])
                print(f"W {window:3d} ({window / model.rate_hz:4.1f} s) {h:.1f} s {name:8s} "
                      f"held-out edges {np.round(edges, 2).tolist()} factors "
                      f"{np.round(f, 2).tolist()}")
                for floor, (d2, st) in test_cases.items():
                    bt = np.searchsorted(edges, st[name])
                    now = 100 * np.mean(d2 <= CHI2_2DOF_95)
                    cov = 100 * np.mean(d2 / f[bt] <= CHI2_2DOF_95)
                    need = [needed(d2[bt == i]) for i in range(args.bins)]
                    print(f"    {floor:7s} n {d2.size:6d}  median {np.median(st[name]):5.2f}  "
                          f"{now:5.1f} -> {cov:5.1f}  needed "
                          f"{' '.join(f'{x:4.2f}' for x in need)}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
