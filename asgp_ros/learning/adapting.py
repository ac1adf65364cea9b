"""Offline adaptation: a trained ASGP brought to a new floor, chair or user by recordings
made there (``asgp adapt``), written as a model file of its own.

The online adaptation (:mod:`asgp_ros.core.adaptive`) learns while the chair drives and
forgets what it learnt when the node stops. Where the change is lasting (the chair now
lives on carpet, the batteries or the user changed), the same posterior update can be
made once, from recordings, and kept:

1. Each recording's last ``holdout`` is held out (:func:`~asgp_ros.learning.training.
   split_holdout`), as in training.
2. Every row of the training part that training would accept (the same resampler and
   :func:`~asgp_ros.core.features.design_matrix`: the same validity, gap, tracking-loss and
   stale-VO rules, so a lost or stuck VO teaches nothing) is absorbed by each channel's
   FITC posterior (:class:`~asgp_ros.core.adapt.OnlinePosterior`): hyperparameters and
   pseudo-inputs stay as trained, the rows teach a correction to the trained function
   (its mean is the prior mean, A9 of :mod:`asgp_ros.core.adapt`), and none of them is
   forgotten. The trained data keep the weight ``trained_weight``: 0 (the default) lets
   the new rows alone decide where they reach, while the trained function stays the mean
   where they do not; 1 keeps the trained data whole, which is exactly the batch FITC
   posterior of the old and the new rows at the trained hyperparameters (a test checks
   it). Rows farther than ``max_distance`` lengthscales from every pseudo-input are
   refused and counted, as online: measurements beyond the training range never narrow
   the variance there.
3. The variance calibration is fitted again on the held-out part
   (:func:`~asgp_ros.learning.training.calibrate`, cross-validated, kept only where it
   brings the held-out coverage closer to 95 %): the trained one describes the old floor.
   The held-out k-step success of the model as trained and as adapted (on the training
   part) is recorded, so that the gain, or its absence, is visible; the adapted model's
   held-out coverage is the calibration's cross-validated one (each half of the held-out
   cases scored with the map fitted on the other).
4. The held-out rows are absorbed too, and the model is written with the trained
   configuration, the new posterior and calibration, and in its meta what was done
   (``adaptation``).

What it does not do: the hyperparameters (lengthscales, noise) stay as trained, so a floor
whose dynamics need other ones is better served by ``asgp train`` on its recordings
(measured on the reproduction's dataset, README "Adapting once": the carpet model adapted
to 40 minutes of tile, and the tile model to 40 minutes of carpet, are 1.2 and 0.7 points
of k-step success at 2.0 s short of the model trained on that floor).
"""

from __future__ import annotations

import copy
import dataclasses
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from asgp_ros.core.adapt import AdaptConfig, AdaptError, OnlinePosterior
from asgp_ros.core.features import CHANNELS
from asgp_ros.core.metrics import HORIZONS_S, THRESHOLD_M
from asgp_ros.core.models import MotionModel
from asgp_ros.core.sparse_gp import SparseGP
from asgp_ros.learning.evaluation import EvaluationError, TestSeries, evaluate_model
from asgp_ros.learning.training import (
    HOLDOUT_FRACTION,
    AutoOptions,
    Progress,
    Series,
    TrainingError,
    _calibrate_step,
    _scorable_horizons,
    data_summary,
    design,
    split_holdout,
)

__all__ = ["AdaptingError", "OfflineAdaptOptions", "adapt_model", "check_adaptable"]

#: The new rows' forgetting half-life, in rows, of the offline update: none is forgotten
#: (2^(-1/1e15) is 1 to 7e-16, which over a million rows moves a weight by 1e-9).
_NEVER_ROWS = 1e15
#: The trained data's half-life, in rows: their weight is ``trained_weight`` from the first
#: absorbed row on (2^(-1e9) is 0).
_AT_ONCE_ROWS = 1e-9


#: Rows absorbed per block (one posterior each): the block's kernel rows take
#: 2 x BLOCK_ROWS x M floats (32 MB at M = 200), whatever the length of the recordings.
BLOCK_ROWS = 10_000


class AdaptingError(TrainingError):
    """The model cannot be adapted as asked (not an ASGP, no usable row, bad options)."""


@dataclass(frozen=True)
class OfflineAdaptOptions:
    """Settings of :func:`adapt_model`.

    Attributes:
        trained_weight: the weight in [0, 1] the trained data keep (0: the new rows alone
            teach the correction; 1: the batch posterior of old and new rows).
        holdout: fraction of each recording held out (its end) for the calibration and
            the held-out scores; 0 absorbs everything and keeps the trained calibration.
        calibrate: fit the variance calibration again on the held-out part (else keep the
            trained one).
        max_distance: rows farther than this many lengthscales from every pseudo-input are
            refused (None: none is).
        horizons_s, threshold_m: the k-step criterion of the held-out scores and the
            calibration's coverage table.
        trained_mean: the rows teach a correction to the trained function (A9, the
            default); False: the function itself, against the constant prior mean (A6, for
            comparisons: ``benchmarks/adapt_data.py``).
    """

    trained_weight: float = 0.0
    holdout: float = HOLDOUT_FRACTION
    calibrate: bool = True
    max_distance: float | None = AdaptConfig.max_distance
    horizons_s: tuple[float, ...] = HORIZONS_S
    threshold_m: float = THRESHOLD_M
    trained_mean: bool = True

    def validate(self) -> None:
        if not (math.isfinite(self.trained_weight) and 0.0 <= self.trained_weight <= 1.0):
            raise AdaptingError(f"the trained data's weight must be in [0, 1], got "
                                f"{self.trained_weight}")
        if not (self.holdout == 0.0 or 0.05 <= self.holdout <= 0.5):
            raise AdaptingError(f"held-out fraction must be 0 or in [0.05, 0.5], got "
                                f"{self.holdout}")
        if self.calibrate and self.holdout == 0.0:
            raise AdaptingError("the calibration needs held-out data (a held-out fraction "
                                "above 0), or keep the trained calibration")
        if self.max_distance is not None and not (math.isfinite(self.max_distance)
                                                  and self.max_distance > 0.0):
            raise AdaptingError(f"max_distance must be > 0, got {self.max_distance}")
        if not self.horizons_s or not all(math.isfinite(h) and h > 0 for h in self.horizons_s):
            raise AdaptingError(f"horizons must be positive, got {self.horizons_s}")

    def config(self) -> AdaptConfig:
        """The online posterior's settings of this update (A7 of :mod:`asgp_ros.core.adapt`)."""
        if self.trained_weight == 1.0:  # nothing forgotten: A6
            return AdaptConfig(max_distance=self.max_distance, trained_mean=self.trained_mean)
        return AdaptConfig(half_life_rows=_NEVER_ROWS, trained_half_life=_AT_ONCE_ROWS,
                           trained_floor=self.trained_weight, max_distance=self.max_distance,
                           trained_mean=self.trained_mean)


def check_adaptable(model: MotionModel) -> tuple[SparseGP, SparseGP]:
    """The model's two SparseGP channels, or AdaptingError saying why it cannot be adapted
    (not an ASGP; a posterior without its LA factor)."""
    v, w = model.channels
    if model.kind != "asgp" or not (isinstance(v, SparseGP) and isinstance(w, SparseGP)):
        raise AdaptingError(f"only an ASGP can be adapted; this model is {model.kind!r}")
    for name, ch in zip(CHANNELS, (v, w), strict=True):
        if ch.posterior.LA is None:
            raise AdaptingError(f"{name}: the model file does not give the posterior's LA "
                                "factor back (written by an old version); train it again")
    return v, w


def _with_num_data(gp: SparseGP, num_data: float) -> SparseGP:
    """A copy of ``gp`` whose number of data is ``num_data`` (rounded)."""
    state = gp.get_state()
    state["num_data"] = np.asarray(float(round(num_data)), dtype=np.float64)
    return SparseGP.from_state(state)


class _Absorber:
    """Both channels' online posteriors over copies of the trained channels."""

    def __init__(self, model: MotionModel, opts: OfflineAdaptOptions) -> None:
        self.model = model
        v, w = check_adaptable(model)
        self.chans = (copy.deepcopy(v), copy.deepcopy(w))
        try:
            self.online = [OnlinePosterior.from_sparse_gp(ch, opts.config())
                           for ch in self.chans]
        except AdaptError as exc:
            raise AdaptingError(str(exc)) from exc
        self.rows = [0, 0]

    def absorb(self, series: Sequence[Series]) -> None:
        fc = self.model.feature_config
        for c, online in enumerate(self.online):
            try:
                X, y = design(series, c, fc)
            except TrainingError:
                continue  # no valid row in these pieces
            self.rows[c] += int(X.shape[0])
            for start in range(0, X.shape[0], BLOCK_ROWS):  # bounded memory per block
                online.absorb_rows(X[start:start + BLOCK_ROWS], y[start:start + BLOCK_ROWS])

    def adapted(self) -> MotionModel:
        """The model with the channels' current posteriors (copies: later rows leave it)."""
        chans = tuple(copy.deepcopy(ch) for ch in self.chans)
        return dataclasses.replace(self.model, channels=(chans[0], chans[1]))


def _held_out_scores(model: MotionModel, held: Sequence[Series], opts: OfflineAdaptOptions
                     ) -> dict[str, Any] | None:
    """Success rate, median error and 95 % coverage per horizon on the held-out part (the
    horizons it has a case for), or None when it has none."""
    auto = AutoOptions(horizons_s=opts.horizons_s, threshold_m=opts.threshold_m)
    horizons = _scorable_horizons(held, auto, model.resample_config, model.lags)
    if not horizons:
        return None
    try:
        ev = evaluate_model(model, [TestSeries(s.name, s.res) for s in held], horizons,
                            threshold_m=opts.threshold_m)
    except EvaluationError:
        return None
    # keyed as scored: a horizon off the model's grid is scored (and labelled) at the
    # nearest step, and two that round to one step are scored once
    return {key: {"success": r.vo.success_rate, "median_error_m": r.vo.median_error_m,
                  "coverage_95": r.vo.coverage_95, "cases": r.vo.cases}
            for key, r in ev.horizons.items()}


#: The earlier adaptations' records a model keeps (the newest).
MAX_EARLIER_ADAPTATIONS = 20


def _calibration_label(cal_meta: dict[str, Any]) -> str:
    """What the adapted model's calibration is, in words (for its meta and the output)."""
    if not cal_meta.get("fitted"):
        return "kept as trained"
    if cal_meta.get("applied", True):
        return "fitted on the held-out part"
    return ("none (the posterior's own variance): the map fitted on the held-out part moved "
            "its coverage away from 95 %, cross-validated, as training decides")


def adapt_model(model: MotionModel, series: Sequence[Series],
                opts: OfflineAdaptOptions | None = None, *,
                progress: Progress | None = None) -> MotionModel:
    """``model`` (an ASGP) adapted to recordings ``series`` (see the module docstring);
    ``model`` itself is not modified.

    Raises:
        AdaptingError: not an ASGP, bad options, or no row of ``series`` usable.
    """
    opts = opts or OfflineAdaptOptions()
    opts.validate()
    if not series:
        raise AdaptingError("no recordings to adapt to")
    report = progress or (lambda ch, msg: None)
    t_start = time.perf_counter()
    absorber = _Absorber(model, opts)
    if opts.holdout > 0.0:
        fit_on, held = split_holdout(series, opts.holdout)
    else:
        fit_on, held = list(series), []
    absorber.absorb(fit_on)
    if not any(absorber.rows):
        raise AdaptingError(
            "no usable row: no valid segment of the recordings is longer than the model's "
            f"{model.lags} lags + 1 (or every one lies in the held-out part)")
    report("absorb", f"{absorber.rows[0]} rows of the training part (last "
                     f"{100 * opts.holdout:.0f}% of each recording held out)")
    before = after = None
    calibration = model.calibration
    cal_meta: dict[str, Any] = {"fitted": False, "reason": "kept as trained"}
    if held:
        adapted_fit = absorber.adapted()
        before = _held_out_scores(model, held, opts)
        if opts.calibrate:
            auto = AutoOptions(holdout=max(opts.holdout, 0.05), horizons_s=opts.horizons_s,
                               threshold_m=opts.threshold_m)
            calibration, cal_meta = _calibrate_step(adapted_fit, held, auto, model.lags,
                                                    report)
            # fewer held-out cases than training.MIN_CALIBRATION_CASES: not fitted
            if not cal_meta.get("fitted"):
                calibration = model.calibration
                cal_meta["reason"] = (f"{cal_meta.get('reason', 'not fitted')}; the trained "
                                      "calibration is kept")
        after = _held_out_scores(dataclasses.replace(adapted_fit, calibration=calibration),
                                 held, opts)
        if after is not None and cal_meta.get("fitted") and cal_meta.get("applied", True):
            # the map was fitted on these cases: their coverage is the cross-validated one
            # (each half scored with the map of the other), not the in-sample figure
            cv = cal_meta.get("by_horizon", {})
            for key, row in after.items():
                row["coverage_95"] = cv.get(key, {}).get("calibrated")
                row["coverage_cross_validated"] = bool(cal_meta.get("cross_validated"))
        absorber.absorb(held)
    stats = [online.stats for online in absorber.online]
    for name, st in zip(CHANNELS, stats, strict=True):
        if st.rows_absorbed == 0:  # every block refused: the model would be the trained one
            refused = ", ".join(f"{v} {k}" for k, v in st.rejected.items() if v) or "none"
            raise AdaptingError(f"{name}: no row could be absorbed (refused: {refused})")
    # the number of data says what the posterior now holds (its effective size)
    v, w = (_with_num_data(ch, st.effective_size)
            for ch, st in zip(absorber.chans, stats, strict=True))
    adapted = dataclasses.replace(model, channels=(v, w))
    meta = dict(model.meta)
    meta["adaptation"] = {
        "data": data_summary(series, max(absorber.rows)),
        "trained_weight": opts.trained_weight,
        "holdout_fraction": opts.holdout,
        "max_distance": opts.max_distance,
        "channels": {name: {"rows": absorber.rows[c], "absorbed": st.rows_absorbed,
                            "refused": {k: v for k, v in st.rejected.items() if v},
                            "effective_size": st.effective_size}
                     for c, (name, st) in enumerate(zip(CHANNELS, stats, strict=True))},
        "held_out": {"trained": before, "adapted": after},
        "calibration": _calibration_label(cal_meta),
        "seconds": round(time.perf_counter() - t_start, 2),
    }
    # a model adapted again keeps the record of what it was adapted to before (its rows
    # are in the posterior too), oldest first
    earlier = model.meta.get("adaptation")
    if isinstance(earlier, dict):
        before_that = earlier.get("earlier")
        records = [r for r in (before_that if isinstance(before_that, list) else [])
                   if isinstance(r, dict)]
        records.append({key: value for key, value in earlier.items() if key != "earlier"})
        meta["adaptation"]["earlier"] = records[-MAX_EARLIER_ADAPTATIONS:]
    if cal_meta.get("fitted"):
        meta["calibration"] = cal_meta
    return dataclasses.replace(adapted, calibration=calibration, meta=meta)
