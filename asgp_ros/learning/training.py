"""Training of the motion predictors from recordings: the ASGP and the baselines.

Pipeline (Fan et al., ICRA 2018, Sec. IV): raw joystick and VO streams from each bag are
resampled onto the common 5 Hz grid (``core.resample``), the autoregressive design
matrices are built per output channel (``core.features.design_matrix``, eq. 3-4; rows
never cross a segment gap), and one regressor per channel is fitted:

the model kind's own trainer (``fit`` of its :class:`~asgp_ros.core.models.ModelKind`;
the kinds, their default lags and trainers are listed once, in :mod:`asgp_ros.core.models`):
the ASGP (SPGP / FITC with M = 20 (v) and 40 (omega) pseudo-inputs, s = 4), the paper's
MLP (s = 10) and the simple baselines (constant velocity, first-order lag, s = 1).

The result is a ``core.models.MotionModel`` whose meta records a training-data summary.
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import logging
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple, cast

import numpy as np

from asgp_ros.common.board import NEUTRAL_WINDOW
from asgp_ros.common.topics import BAG_JOY, BAG_VO_TWIST, JOY_OVERRIDE
from asgp_ros.core import metrics
from asgp_ros.core.calibration import (
    BASIS,
    MIN_REGIME_CASES,
    TARGET_COVERAGE,
    CalibrationError,
    CalibrationFit,
    VarianceCalibration,
    combine,
    coverage,
    fit_calibration,
)
from asgp_ros.core.features import CHANNELS, LAGS_RANGE, FeatureConfig, design_matrix
from asgp_ros.core.metrics import HORIZONS_S, THRESHOLD_M, horizon_key
from asgp_ros.core.modelfile import probe_problem
from asgp_ros.core.models import FitBudget, ModelKind, MotionModel, get_kind, trainable_kinds
from asgp_ros.core.resample import ResampleConfig, Resampled, resample
from asgp_ros.core.sparse_gp import SparseGP
from asgp_ros.learning.evaluation import (
    EvaluationError,
    TestSeries,
    evaluate_model,
    reference_path,
    rollout_cases,
)
from asgp_ros.recording import bags

log = logging.getLogger(__name__)

#: progress(channel name, message) for a CLI's progress lines.
Progress = Callable[[str, str], None]


class TrainingError(ValueError):
    """Training cannot proceed (no usable data, bad options); the message says why."""


@dataclass(frozen=True)
class TrainOptions:
    kind: str = "asgp"
    lags: int | None = None  # None: the kind's default_lags
    inducing_v: int = 20
    inducing_w: int = 40
    max_iter: int = 200
    coupled: bool = False
    seed: int = 0

    def resolved_lags(self) -> int:
        return int(self.lags if self.lags is not None else get_kind(self.kind).default_lags)

    def budget(self) -> FitBudget:
        return FitBudget(max_iter=self.max_iter, inducing=(self.inducing_v, self.inducing_w),
                         seed=self.seed)

    def validate(self) -> None:
        if self.kind not in trainable_kinds():
            raise TrainingError(f"unknown model kind {self.kind!r}; choose from "
                                f"{trainable_kinds()}")
        if self.resolved_lags() < 1:
            raise TrainingError(f"lags must be >= 1, got {self.lags}")
        if self.inducing_v < 1 or self.inducing_w < 1:
            raise TrainingError("the numbers of pseudo-inputs must be >= 1")
        if self.max_iter < 1:
            raise TrainingError(f"max_iter must be >= 1, got {self.max_iter}")


@dataclass
class Series:
    """One recording on the grid: its name and the resampled data (with ground truth if any)."""

    name: str
    res: Any  # core.resample.Resampled
    raw: Any = None  # core.streams.RawStreams it was resampled from


def read_series(
    paths: Sequence[str],
    *,
    resample_config: Any = None,
    joy_topic: str = BAG_JOY,
    twist_topic: str = BAG_VO_TWIST,
    truth_topic: str | None = None,
    joy_axes: Any = None,
    override_topic: str | None = JOY_OVERRIDE,
    base_frame: str = "base_link",
) -> list[Series]:
    """Read bags and resample them onto the grid (raises the bag reader's errors).

    The overrides on ``override_topic`` (when a bag has it; None or '' for none; a relative
    name is resolved in ``joy_topic``'s namespace) make the grid points they may have driven
    invalid (:mod:`asgp_ros.core.resample`, "Validity").
    """
    config = resample_config if resample_config is not None else ResampleConfig()
    out = []
    for path in paths:
        kwargs: dict[str, Any] = {"joy_topic": joy_topic, "twist_topic": twist_topic,
                                  "override_topic": override_topic, "base_frame": base_frame}
        if truth_topic is not None:
            kwargs["truth_topic"] = truth_topic
        if joy_axes is not None:
            kwargs["joy_axes"] = joy_axes
        streams = bags.read_streams(str(path), **kwargs)
        res = resample(streams, config)
        out.append(Series(str(path), res, streams))
    return out


def data_summary(series: Sequence[Series], rows: int | None = None) -> dict[str, Any]:
    """Training-data summary for the model file's meta (bags, samples, segments, stale)."""
    grid = sum(int(s.res.t.shape[0]) for s in series)
    valid = sum(int(np.sum(s.res.valid)) for s in series)
    stale = sum(int(np.sum(s.res.stale)) for s in series)
    overridden = sum(int(np.sum(s.res.overridden)) for s in series)
    segments = sum(len(s.res.segments()) for s in series)
    out: dict[str, Any] = {
        "bags": [s.name for s in series],
        # the real path, storage and messages of each (asgp adapt and evaluate tell a bag
        # trained on, from any directory, and its copies, repaired or converted too)
        "recordings": [series_identity(s) for s in series],
        "grid_samples": grid,
        "valid_samples": valid,
        "segments": segments,
        "stale_fraction": float(stale / grid) if grid else 0.0,
        "overridden_samples": overridden,
        "duration_s": float(sum(recorded_s(s) for s in series)),
    }
    if rows is not None:
        out["training_rows"] = int(rows)
    return out


def series_identity(s: Series) -> dict[str, Any]:
    """What identifies the recording ``s`` was read from
    (:func:`asgp_ros.recording.bags.recording_identity`, with the digests of the messages
    read); empty for data not read from a bag."""
    digests = getattr(s.raw, "digests", None) or {}
    if os.path.exists(s.name):
        return bags.recording_identity(s.name, digests)
    return {"messages": {str(t): dict(d) for t, d in digests.items()}} if digests else {}


def repeated_series(series: Sequence[Series]) -> str | None:
    """Why ``series`` are not each a different recording (two read from one recording, a
    copy of it, repaired or converted, or from copies of which one was cut short: its rows
    would count twice, or a model would be tested on its own data), naming both; None."""
    twice = bags.repeated_recording([(s.name, series_identity(s)) for s in series])
    return None if twice is None else bags.repeated_text(twice)


#: A stretch this long (s) without any joystick or velocity sample is no recording time
#: (a clock set forward, a recorder paused): training data's duration leaves it out.
RECORDING_GAP_S = 10.0


def recorded_s(s: Series) -> float:
    """How long a recording's samples span, its gaps of more than RECORDING_GAP_S left out
    (a 6-minute drive with the clock set forward a day read 1446 minutes); the grid's span
    for a series without its raw streams."""
    raw = s.raw
    if raw is not None and raw.joy_t.size + raw.vel_t.size > 1:
        t = np.sort(np.concatenate([raw.joy_t, raw.vel_t]))
        dt = np.diff(t)
        return float(dt[dt <= RECORDING_GAP_S].sum())
    return float(s.res.t[-1] - s.res.t[0]) if s.res.t.size else 0.0


def canonical_order(series: Sequence[Series]) -> list[Series]:
    """The series in an order of their data alone (a digest of each grid's times, joystick,
    velocities and validity), not of the order the recordings were given in: the rows are
    stacked, subsampled and split in this order, so ``asgp train A B`` and ``asgp train B
    A`` fit and choose the same model (they chose s = 6 and s = 4)."""
    def key(s: Series) -> bytes:
        h = hashlib.sha256()
        for a in (s.res.t, s.res.joy, s.res.vel, s.res.valid):
            arr = np.ascontiguousarray(a)
            h.update(str((arr.dtype.str, arr.shape)).encode())
            h.update(arr.tobytes())
        return h.digest()
    return sorted(series, key=key)


def design(series: Sequence[Series], channel: int, feature_config: Any) -> tuple[np.ndarray,
                                                                                 np.ndarray]:
    """Stacked design matrix X [N, D] and targets y [N] of one channel over all series."""
    Xs, ys = [], []
    for s in series:
        X, y, _ = design_matrix(s.res, channel, feature_config)
        if X.shape[0]:
            Xs.append(np.asarray(X))
            ys.append(np.asarray(y))
    if not Xs:
        raise TrainingError(
            f"no training rows for channel {CHANNELS[channel]}: no valid segment is longer "
            f"than {feature_config.lags} lags + 1 in {', '.join(s.name for s in series)}")
    return np.concatenate(Xs), np.concatenate(ys)


#: The four signals of a row, named for messages: (0 for the joystick or 1 for the
#: odometry, column, name, advice).
_SIGNALS = ((0, 0, "the joystick's forward axis (axis 0)", "driving forward and back"),
            (0, 1, "the joystick's turn axis (axis 1)", "turning"),
            (1, 0, "the odometry's forward speed v", "the chair driving forward and back"),
            (1, 1, "the odometry's turn rate omega", "the chair turning"))


#: A signal whose standard deviation over the valid points is below this never changes for
#: training: 0.001 of the stick's full deflection (a fifth of one count of a 10-bit ADC), or
#: 1 mm/s and 1 mrad/s of odometry (below any VO's noise).
MIN_SIGNAL_STD = 1e-3


def check_signals(series: Sequence[Series], part: str = "") -> None:
    """Refuse recordings in which one of the four signals never changes over the valid grid
    points (a stick never turned, a chair that only spun on the spot, odometry stuck at
    zero; :data:`MIN_SIGNAL_STD`): a GP learns nothing about what it never saw, and cannot
    standardise a constant input. The message names the signal and what to record, not a
    feature column; ``part`` names the part of the recordings checked, if not all."""
    for which, col, name, advice in _SIGNALS:
        values = np.concatenate([(s.res.joy, s.res.vel)[which][s.res.valid, col]
                                 for s in series])
        if values.size == 0:
            return  # no valid point at all: design() says so, per channel
        if not float(values.std()) >= MIN_SIGNAL_STD:
            where = f"{part} of " if part else ""
            raise TrainingError(
                f"{name} never changes in {where}{', '.join(s.name for s in series)} "
                f"(standard deviation {float(values.std()):.2g} over the valid points, around "
                f"{float(np.median(values)):.3g}): a model cannot learn a motion the "
                f"recordings never show; record driving that includes {advice} (a few "
                "minutes of ordinary driving, with turns, stops and reversals)")


def _fit_channel(kind: ModelKind, channel: int, X: np.ndarray, y: np.ndarray,
                 feature_config: Any, opts: TrainOptions, progress: Progress
                 ) -> tuple[Any, dict[str, Any]]:
    name = CHANNELS[channel]
    if kind.fit is None:
        raise TrainingError(f"model kind {kind.name!r} cannot be trained")
    t0 = time.perf_counter()
    info: dict[str, Any] = {"rows": int(X.shape[0])}
    try:
        model, fit_info = kind.fit(channel, X, y, feature_config, opts.budget(),
                                   lambda msg: progress(name, msg))
    except ValueError as exc:
        raise TrainingError(str(exc)) from exc
    info.update(fit_info)
    info["seconds"] = round(time.perf_counter() - t0, 3)
    return model, info


def train(
    series: Sequence[Series],
    opts: TrainOptions,
    *,
    resample_config: Any = None,
    progress: Progress | None = None,
) -> MotionModel:
    """Fit both channels of a model of kind ``opts.kind`` on the series; return a MotionModel."""
    opts.validate()
    if not series:
        raise TrainingError("no training recordings")
    given, series = series, canonical_order(series)
    report = progress or (lambda ch, msg: log.info("%s: %s", ch, msg))
    kind = get_kind(opts.kind)
    if opts.kind == "asgp":
        check_signals(series)
    fc = FeatureConfig(lags=opts.resolved_lags(), coupled=opts.coupled)
    rc = resample_config if resample_config is not None else ResampleConfig()
    channels = []
    infos = {}
    rows = 0
    for c in (0, 1):
        X, y = design(series, c, fc)
        rows = max(rows, X.shape[0])
        report(CHANNELS[c], f"{X.shape[0]} rows x {X.shape[1]} features")
        model, info = _fit_channel(kind, c, X, y, fc, opts, report)
        channels.append(model)
        infos[CHANNELS[c]] = info
    meta = {
        "training_data": data_summary(given, rows),
        "training": {
            "kind": opts.kind,
            "lags": fc.lags,
            "coupled": bool(opts.coupled),
            "seed": opts.seed,
            "max_iter": opts.max_iter,
            "channels": infos,
        },
    }
    return MotionModel(kind=opts.kind, feature_config=fc, resample_config=rc,
                       channels=(channels[0], channels[1]), meta=meta)


# ------------------------------------------------------------ automatic configuration

#: The paper's ASGP (Fan et al., ICRA 2018, Sec. V): s = 4, M = 20 (v) / 40 (omega), one
#: joystick axis and one velocity per channel; trained on all the data, no calibration.
PAPER_OPTIONS = TrainOptions(kind="asgp", lags=4, inducing_v=20, inducing_w=40, coupled=False,
                             max_iter=200)

#: Lags s tried by the automatic configuration.
AUTO_LAGS: tuple[int, ...] = (2, 4, 6, 8, 10, 12)
#: Pseudo-inputs M per channel tried (the same M for v and omega), as far as the budget
#: allows (:meth:`AutoOptions.affordable_inducing`).
AUTO_INDUCING: tuple[int, ...] = (20, 40, 80, 120, 160, 200, 300)
#: M while the structure (s, coupling) is chosen.
AUTO_STRUCTURE_INDUCING = 40
#: Structures scored again at the capacity stage's largest M: the best of the structure
#: stage and its runners-up, this many in all. At M = 40 the structures' held-out scores
#: are often within a few tenths of a point (a longer past needs pseudo-inputs to use it),
#: so the structure stage alone can pick a short s that a larger M does not favour.
REFINE_STRUCTURES = 3
#: The fewest held-out cases in which the chair moves at least the success distance that
#: the selection needs: over fewer, a success rate moves in steps of more than 5 points and
#: cannot tell the candidates apart, and a chair at rest is predicted by anything (a
#: held-out end of the chair parked scored every candidate 100 %, and the tie-break chose
#: one that drove far worse).
MIN_SELECTION_MOVING_CASES = 20
#: Fraction of each training recording held out (its end) for selection and calibration.
HOLDOUT_FRACTION = 0.2
#: The fewest held-out cases (k-step rollouts) a variance calibration is fitted on: one
#: speed regime's minimum (:data:`asgp_ros.core.calibration.MIN_REGIME_CASES`). With
#: fewer (a recording of a few minutes: consecutive cases overlap, and a short held-out
#: end may hold nothing but the chair at rest) the map is noise, and the model is left
#: uncalibrated, saying so; ``asgp adapt`` keeps the trained calibration by the same rule.
MIN_CALIBRATION_CASES = MIN_REGIME_CASES
#: L-BFGS-B iterations of a candidate's fit during the selection: at most
#: SELECTION_MAX_ITER, fewer for a small budget (SELECTION_ITER_PER_BUDGET_S per second).
SELECTION_MAX_ITER = 100
SELECTION_MIN_ITER = 20
SELECTION_ITER_PER_BUDGET_S = 2.0
#: Range of the time budget (s) of the automatic configuration.
BUDGET_RANGE_S = (1.0, 86400.0)
#: Rows per channel a candidate is fitted on, per second of budget. The plan (rows of the
#: candidates' fits, rows of the final fit) is fixed by the budget before anything is
#: fitted, never by the clock, so that the choice is deterministic for a seed. Measured
#: (benchmarks/train.py) on 2 cores: 180 s of budget fits 120 minutes of 5 Hz data.
ROWS_PER_BUDGET_S = 60
MIN_SELECTION_ROWS = 1000
MAX_SELECTION_ROWS = 20000
#: The final fit uses this many times the selection's rows (at most all training rows).
FINAL_ROWS_FACTOR = 2
#: Cost model of a fit, seconds per (row x M^2 x iteration) per channel pair, measured by
#: benchmarks/train.py on a 2-core machine; it decides which M the budget affords, before
#: anything is fitted (so the plan, and the choice, do not depend on the clock).
FIT_COST_S = 6e-10
#: Share of the budget the final fit may take.
FINAL_FIT_SHARE = 0.4


@dataclass(frozen=True)
class AutoOptions:
    """Automatic configuration of the ASGP (:func:`train_auto`).

    Attributes:
        seed: seeds the row subsets and the fits; equal seeds give equal choices.
        budget_s: the time the plan is sized for (see :data:`ROWS_PER_BUDGET_S`).
        lags, coupled, inducing_v, inducing_w: pin a value (None: chosen).
        max_iter: L-BFGS-B iterations of the final fit.
        holdout: fraction of each recording held out (its end) for selection and calibration.
        horizons_s: horizons of the k-step criterion; threshold_m: its success distance.
        calibrate: fit the variance calibration on the held-out part.
    """

    seed: int = 0
    budget_s: float = 180.0
    lags: int | None = None
    coupled: bool | None = None
    inducing_v: int | None = None
    inducing_w: int | None = None
    max_iter: int = 200
    holdout: float = HOLDOUT_FRACTION
    horizons_s: tuple[float, ...] = HORIZONS_S
    threshold_m: float = THRESHOLD_M
    calibrate: bool = True

    def validate(self) -> None:
        lo, hi = BUDGET_RANGE_S
        if not (math.isfinite(self.budget_s) and lo <= self.budget_s <= hi):
            raise TrainingError(f"budget must be {lo:g} .. {hi:g} s, got {self.budget_s}")
        if self.lags is not None and not LAGS_RANGE[0] <= self.lags <= LAGS_RANGE[1]:
            raise TrainingError(f"lags must be in {list(LAGS_RANGE)}, got {self.lags}")
        for m in (self.inducing_v, self.inducing_w):
            if m is not None and m < 1:
                raise TrainingError("the numbers of pseudo-inputs must be >= 1")
        if self.max_iter < 1:
            raise TrainingError(f"max_iter must be >= 1, got {self.max_iter}")
        if not 0.05 <= self.holdout <= 0.5:
            raise TrainingError(f"held-out fraction must be in [0.05, 0.5], got {self.holdout}")
        if not self.horizons_s or not all(math.isfinite(h) and h > 0 for h in self.horizons_s):
            raise TrainingError(f"horizons must be positive, got {self.horizons_s}")

    @property
    def selection_rows(self) -> int:
        # a pinned M needs 2 M rows to fit on: a subset sized by the budget alone skipped
        # every candidate, and the model fell back to the paper's, uncalibrated
        pinned = max((m for m in (self.inducing_v, self.inducing_w) if m is not None),
                     default=0)
        by_budget = min(MAX_SELECTION_ROWS,
                        max(MIN_SELECTION_ROWS, round(self.budget_s * ROWS_PER_BUDGET_S)))
        return int(max(by_budget, 2 * pinned))

    @property
    def selection_max_iter(self) -> int:
        per_budget = round(self.budget_s * SELECTION_ITER_PER_BUDGET_S)
        return int(min(SELECTION_MAX_ITER, max(SELECTION_MIN_ITER, per_budget)))

    @property
    def final_rows(self) -> int:
        return FINAL_ROWS_FACTOR * self.selection_rows

    def affordable_inducing(self) -> tuple[int, ...]:
        """The M of :data:`AUTO_INDUCING` whose final fit the budget affords (by the cost
        model :data:`FIT_COST_S`; at least the smallest two)."""
        cap = FINAL_FIT_SHARE * self.budget_s
        ok = tuple(m for m in AUTO_INDUCING
                   if FIT_COST_S * self.final_rows * m * m * self.max_iter <= cap)
        return ok if len(ok) >= 2 else AUTO_INDUCING[:2]


@dataclass(frozen=True)
class Candidate:
    """One ASGP configuration: lags, coupling and pseudo-inputs per channel."""

    lags: int
    coupled: bool
    inducing: tuple[int, int]

    @property
    def name(self) -> str:
        return (f"s={self.lags} {'coupled' if self.coupled else 'per-axis'} "
                f"M={self.inducing[0]}/{self.inducing[1]}")

    def features(self) -> FeatureConfig:
        return FeatureConfig(lags=self.lags, coupled=self.coupled)

    def to_json(self) -> dict[str, Any]:
        return {"lags": self.lags, "coupled": self.coupled, "inducing": list(self.inducing)}


def slice_resampled(res: Resampled, start: int, stop: int) -> Resampled:
    """The grid samples [start, stop) of a resampled recording, as a recording of its own."""
    cut = slice(start, stop)
    return dataclasses.replace(
        res, t=res.t[cut], k=res.k[cut], joy=res.joy[cut], vel=res.vel[cut],
        valid=res.valid[cut], stale=res.stale[cut], tracking_lost=res.tracking_lost[cut],
        gap=res.gap[cut], segment=res.segment[cut], truth=res.truth[cut],
        truth_valid=res.truth_valid[cut], overridden=res.overridden[cut])


def split_holdout(series: Sequence[Series], fraction: float
                  ) -> tuple[list[Series], list[Series]]:
    """(training, held-out): each recording cut in time, its last ``fraction`` held out:
    of its valid grid points (a gap in the recording, a clock stepped forward a day, holds
    no data: cut on the grid's span, it moved the held-out share to 36-67 %).

    The pieces share no grid sample, so no held-out row (nor any sample of its window)
    is ever a training row: rows are built inside each piece (``design_matrix`` never
    crosses a piece's ends).
    """
    train_part, held = [], []
    for s in series:
        n = len(s.res)
        valid = np.flatnonzero(s.res.valid)
        cut = (int(valid[math.floor((1.0 - fraction) * valid.size)])
               if valid.size and fraction > 0.0 else math.floor((1.0 - fraction) * n))
        train_part.append(Series(s.name, slice_resampled(s.res, 0, cut)))
        held.append(Series(s.name, slice_resampled(s.res, cut, n)))
    return train_part, held


def _subsample(X: np.ndarray, y: np.ndarray, n: int, rng: np.random.Generator
               ) -> tuple[np.ndarray, np.ndarray]:
    if X.shape[0] <= n:
        return X, y
    idx = np.sort(rng.choice(X.shape[0], size=n, replace=False))
    return X[idx], y[idx]


def _fit_asgp_channel(X: np.ndarray, y: np.ndarray, M: int, rows: int, max_iter: int,
                      seed: int, X_post: np.ndarray, y_post: np.ndarray,
                      start: SparseGP | None = None) -> tuple[SparseGP, dict[str, Any]]:
    """Fit hyperparameters and pseudo-inputs on a seeded subset of at most ``rows`` rows
    (from ``start``'s, when given), then the FITC posterior at those parameters on all of
    (X_post, y_post)."""
    Xs, ys = _subsample(X, y, rows, np.random.default_rng(seed))
    if Xs.shape[0] < 2 * M:
        raise TrainingError(f"{Xs.shape[0]} rows are too few for M = {M} pseudo-inputs")
    fitted = SparseGP(num_inducing=M, seed=seed).fit(Xs, ys, max_iter=max_iter, start=start)
    gp = SparseGP.from_params(X_post, y_post, fitted.inducing_inputs, fitted.lengthscales,
                              fitted.signal_variance, fitted.noise_variance,
                              jitter=fitted.jitter)
    res = fitted.optimiser_result
    info = {"num_inducing": M, "fit_rows": int(Xs.shape[0]), "rows": int(X_post.shape[0]),
            "iterations": int(getattr(res, "nit", -1)) if res is not None else -1,
            "log_likelihood_fit_rows": float(fitted.log_marginal_likelihood()),
            "noise_std": float(np.sqrt(fitted.noise_variance)),
            "lengthscales": [float(v) for v in fitted.lengthscales]}
    return gp, info


def _fit_candidate(cand: Candidate, fit_on: Sequence[Series], post_on: Sequence[Series],
                   rows: int, max_iter: int, seed: int, rc: Any,
                   start: MotionModel | None = None) -> tuple[MotionModel, dict[str, Any]]:
    """``cand`` fitted on ``fit_on`` (its channels' optimisers started from ``start``'s
    parameters when given: the same candidate fitted before), its posterior on ``post_on``."""
    fc = cand.features()
    chans, infos = [], {}
    for c in (0, 1):
        X, y = design(fit_on, c, fc)
        Xp, yp = (X, y) if post_on is fit_on else design(post_on, c, fc)
        first = cast(SparseGP, start.channels[c]) if start is not None else None
        gp, info = _fit_asgp_channel(X, y, cand.inducing[c], rows, max_iter, seed + c, Xp, yp,
                                     first)
        chans.append(gp)
        infos[CHANNELS[c]] = info
    model = MotionModel(kind="asgp", feature_config=fc, resample_config=rc,
                        channels=(chans[0], chans[1]))
    return model, infos


def _score(model: MotionModel, held: Sequence[Series], opts: AutoOptions, case_lags: int
           ) -> dict[str, Any]:
    """The k-step criterion on the held-out pieces: success rate and median error per
    horizon, their means (the score: mean success rate over the horizons)."""
    ev = evaluate_model(model, [TestSeries(s.name, s.res) for s in held], opts.horizons_s,
                        threshold_m=opts.threshold_m, case_lags=case_lags, uncertainty="none")
    per = {key: {"success": h.vo.success_rate, "median_error_m": h.vo.median_error_m,
                 "cases": h.vo.cases} for key, h in ev.horizons.items()}
    return {"score": float(np.mean([p["success"] for p in per.values()])),
            "mean_median_error_m": float(np.mean([p["median_error_m"] for p in per.values()])),
            "horizons": per}


def _better(a: dict[str, Any], b: dict[str, Any] | None) -> bool:
    """Higher mean success wins; then lower median error (no tie is left to order)."""
    if b is None:
        return True
    return (a["score"], -a["mean_median_error_m"]) > (b["score"], -b["mean_median_error_m"])


def _structures(opts: AutoOptions) -> list[tuple[int, bool]]:
    lags = AUTO_LAGS if opts.lags is None else (opts.lags,)
    coupled = (False, True) if opts.coupled is None else (opts.coupled,)
    return [(s, c) for s in lags for c in coupled]


def _inducing(opts: AutoOptions, m: int) -> tuple[int, int]:
    return (opts.inducing_v if opts.inducing_v is not None else m,
            opts.inducing_w if opts.inducing_w is not None else m)


def train_auto(
    series: Sequence[Series],
    opts: AutoOptions | None = None,
    *,
    resample_config: Any = None,
    progress: Progress | None = None,
) -> MotionModel:
    """Train the ASGP with its configuration chosen on held-out data, and calibrate it.

    1. Each recording's last ``opts.holdout`` is held out (:func:`split_holdout`).
    2. Structure: every (s, coupled) of :data:`AUTO_LAGS` x {per-axis, coupled} at
       M = :data:`AUTO_STRUCTURE_INDUCING`, plus the paper's configuration, is fitted on
       a seeded subset of the training part (:attr:`AutoOptions.selection_rows` rows,
       :attr:`AutoOptions.selection_max_iter` iterations), its posterior formed on the
       whole training part, and scored by the k-step criterion on the held-out part: the
       success rate of the rolled-out path at ``opts.horizons_s``, averaged (the paper's
       measure of what a planner needs), with the median error as tie-break. All
       candidates are scored on the same cases (those with the largest s of the past
       samples).
    3. Capacity: M of :data:`AUTO_INDUCING` for the best structure, as far as the budget
       affords (:meth:`AutoOptions.affordable_inducing`); then the runners-up of step 2
       (:data:`REFINE_STRUCTURES` structures in all) at the largest of those M. The best
       held-out score of all the candidates wins.
    4. The chosen configuration is fitted again on more rows of the training part
       (:attr:`AutoOptions.final_rows`, ``opts.max_iter`` iterations), its optimiser
       started from the candidate's selection fit (a warm start: the selection's
       iterations are not spent again, and cost nothing more), the variance
       calibration fitted on the held-out part (:mod:`asgp_ros.core.calibration`), and
       the shipped posterior formed on all the data at the fitted parameters.

    Values pinned in ``opts`` are not searched. The model's meta records the candidates'
    scores (``selection``) and the calibration with its held-out coverage
    (``calibration``).
    """
    opts = opts or AutoOptions()
    opts.validate()
    if not series:
        raise TrainingError("no training recordings")
    given, series = series, canonical_order(series)
    check_signals(series)
    report = progress or (lambda ch, msg: log.info("%s: %s", ch, msg))
    rc = resample_config if resample_config is not None else ResampleConfig()
    t_start = time.perf_counter()
    aligned = metrics.scored_horizons(opts.horizons_s, rc.rate_hz)
    if aligned != tuple(opts.horizons_s):
        # scored where they are, as asgp evaluate does (a 1 Hz grid: 1.4 s is 1.0 s)
        report("select", f"the horizons {list(opts.horizons_s)} s on the {rc.rate_hz:g} Hz "
                         f"grid: scoring {list(aligned)} s")
        opts = dataclasses.replace(opts, horizons_s=aligned)
    fit_on, held = split_holdout(series, opts.holdout)
    # the candidates are fitted on the first part alone: a motion only in the held-out end
    # is one they never see
    check_signals(fit_on, f"the first {100 * (1 - opts.holdout):g} % (the part fitted on)")
    structures = _structures(opts)
    case_lags = max(max(s for s, _ in structures), PAPER_OPTIONS.resolved_lags())
    search = _Search(fit_on, held, opts, rc, report, case_lags)

    # horizons the held-out part can score (every candidate on the same cases)
    usable = _scorable_horizons(held, opts, rc, case_lags)
    if not usable:
        search.table.append({"candidate": None, "stage": "check", "skipped":
                             f"no held-out segment holds {case_lags} past samples and "
                             f"{opts.horizons_s[0]} s ahead"})
        return _fallback(given, opts, rc, search.table, report)
    if usable != opts.horizons_s:
        report("select", f"the held-out data are too short for the horizons "
                         f"{[h for h in opts.horizons_s if h not in usable]} s; scoring "
                         f"{list(usable)} s")
        opts = search.opts = dataclasses.replace(opts, horizons_s=usable)
    moving = _moving_cases(held, rc, case_lags, opts)
    if moving < MIN_SELECTION_MOVING_CASES:
        search.table.append({"candidate": None, "stage": "check", "skipped":
                             f"{moving} held-out cases move the chair "
                             f"{100 * opts.threshold_m:g} cm or more in "
                             f"{max(opts.horizons_s):g} s, fewer than the "
                             f"{MIN_SELECTION_MOVING_CASES} that tell the candidates apart "
                             "(the chair stands through most of the held-out part, the end "
                             "of each recording)"})
        return _fallback(given, opts, rc, search.table, report)
    chosen = search.run(structures)
    if chosen is None:
        return _fallback(given, opts, rc, search.table, report)
    assert search.best is not None
    report("select", f"chosen: {chosen.name} (held-out mean success "
                     f"{100 * search.best['score']:.1f}%)")
    t_select = time.perf_counter() - t_start

    # final fit on the training part; calibration on the held-out part
    t0 = time.perf_counter()
    report("fit", f"{chosen.name} on up to {opts.final_rows} rows per channel, "
                  f"{opts.max_iter} iterations, from its selection fit")
    try:
        model_tr, infos = _fit_candidate(chosen, fit_on, fit_on, opts.final_rows,
                                         opts.max_iter, opts.seed, rc, start=search.best_model)
    except ValueError as exc:
        raise TrainingError(str(exc)) from exc
    t_fit = time.perf_counter() - t0
    calibration, cal_meta = _calibrate_step(model_tr, held, opts, case_lags, report)
    chans = _conditioned_on_all(series, chosen, model_tr, infos)
    fc = chosen.features()
    seconds = {"selection": round(t_select, 2), "final_fit": round(t_fit, 2),
               "total": round(time.perf_counter() - t_start, 2)}
    if seconds["total"] > opts.budget_s:
        # the plan has floors whatever the budget (MIN_SELECTION_ROWS rows,
        # SELECTION_MIN_ITER iterations, two sizes of M), and the final fit runs max_iter
        report("select", f"took {seconds['total']:.1f} s, more than the {opts.budget_s:g} s "
                         "planned: the plan's floors (at least "
                         f"{MIN_SELECTION_ROWS} rows, {SELECTION_MIN_ITER} iterations and "
                         "two sizes of M for the best structure) and the final fit's "
                         f"{opts.max_iter} iterations do not shrink with it")
    model = MotionModel(kind="asgp", feature_config=fc, resample_config=rc,
                        channels=(chans[0], chans[1]), calibration=calibration)
    if not calibration.is_identity and (problem := probe_problem(model)) is not None \
            and probe_problem(dataclasses.replace(model, calibration=VarianceCalibration())) \
            is None:
        # a map fitted on very noisy odometry (its omega scale 28) made the model predict
        # variances beyond a wheelchair's, one on a degenerate held-out part could shrink
        # the model's own variance beyond MAX_CALIBRATION_SHRINK: files load_model refuses
        reason = f"not applied: a model file with it is refused ({problem})"
        report("calibrate", reason)
        cal_meta = {**cal_meta, "applied": False, "reason": reason}
        model = dataclasses.replace(model, calibration=VarianceCalibration())
    meta = _automatic_meta(given, opts, chosen, infos, search.table, case_lags, seconds,
                           cal_meta)
    return dataclasses.replace(model, meta=meta)


def _automatic_meta(series: Sequence[Series], opts: AutoOptions, chosen: Candidate,
                    infos: dict[str, dict[str, Any]], candidates: list[dict[str, Any]],
                    case_lags: int, seconds: dict[str, float], cal_meta: dict[str, Any]
                    ) -> dict[str, Any]:
    """The model file's meta of an automatically configured ASGP: its training data and
    channels, how the configuration was chosen (criterion, plan, pinned values, every
    candidate's scores, times) and its calibration."""
    fc = chosen.features()
    total_rows = max(info["posterior_rows"] for info in infos.values())
    return {
        "training_data": data_summary(series, total_rows),
        "training": {"kind": "asgp", "lags": fc.lags, "coupled": fc.coupled,
                     "seed": opts.seed, "max_iter": opts.max_iter, "channels": infos,
                     "configuration": "automatic"},
        "selection": {
            "criterion": "mean over the horizons of the held-out success rate of the "
                         "k-step rollout (error <= threshold), tie-break median error",
            "horizons_s": list(opts.horizons_s), "threshold_m": opts.threshold_m,
            "holdout_fraction": opts.holdout, "case_lags": case_lags,
            "selection_rows": opts.selection_rows,
            "selection_max_iter": opts.selection_max_iter,
            "final_rows": opts.final_rows, "budget_s": opts.budget_s,
            "final_fit_start": "the chosen candidate's selection fit",
            "pinned": {k: v for k, v in (("lags", opts.lags), ("coupled", opts.coupled),
                                         ("inducing_v", opts.inducing_v),
                                         ("inducing_w", opts.inducing_w)) if v is not None},
            "chosen": chosen.to_json(), "candidates": candidates,
            "seconds": seconds,
        },
        "calibration": cal_meta,
    }


class _Search:
    """The candidates of :func:`train_auto` (its steps 2 and 3), each fitted on the
    training part and scored on the held-out part; ``table`` holds one row per candidate
    (or why it was skipped), ``best`` the best score."""

    def __init__(self, fit_on: Sequence[Series], held: Sequence[Series], opts: AutoOptions,
                 rc: ResampleConfig, report: Progress, case_lags: int) -> None:
        self.fit_on, self.held, self.opts, self.rc = fit_on, held, opts, rc
        self.report, self.case_lags = report, case_lags
        self.table: list[dict[str, Any]] = []
        self.best: dict[str, Any] | None = None
        self.best_cand: Candidate | None = None
        self.best_model: MotionModel | None = None  # best_cand as fitted for the selection

    def run(self, structures: Sequence[tuple[int, bool]]) -> Candidate | None:
        """The paper's configuration (unless a pin excludes it), every structure at
        M = AUTO_STRUCTURE_INDUCING, then the affordable M for the best structure and the
        leading structures at the largest of them; the chosen candidate, or None when none
        could be scored."""
        opts = self.opts
        paper = Candidate(PAPER_OPTIONS.resolved_lags(), False,
                          (PAPER_OPTIONS.inducing_v, PAPER_OPTIONS.inducing_w))
        if (opts.lags in (None, paper.lags) and opts.coupled in (None, False)
                and opts.inducing_v in (None, paper.inducing[0])
                and opts.inducing_w in (None, paper.inducing[1])):
            self.consider(paper, "paper")
        for s, coupled in structures:
            self.consider(Candidate(s, coupled, _inducing(opts, AUTO_STRUCTURE_INDUCING)),
                          "structure")
        if self.best_cand is None:
            return None
        if opts.inducing_v is None or opts.inducing_w is None:
            s, coupled = self.best_cand.lags, self.best_cand.coupled
            capacity = opts.affordable_inducing()
            for m in capacity:
                self.consider(Candidate(s, coupled, _inducing(opts, m)), "capacity")
            for s, coupled in self.leading_structures(REFINE_STRUCTURES):
                self.consider(Candidate(s, coupled, _inducing(opts, capacity[-1])), "refine")
        return self.best_cand

    def leading_structures(self, n: int) -> list[tuple[int, bool]]:
        """The ``n`` best (s, coupled) of the structure stage, best first."""
        rows = [r for r in self.table if r["stage"] == "structure" and "score" in r]
        rows.sort(key=lambda r: (-r["score"], r["mean_median_error_m"]))
        return [(r["candidate"]["lags"], r["candidate"]["coupled"]) for r in rows[:n]]

    def consider(self, cand: Candidate, stage: str) -> None:
        """Fit, score and record one candidate (once)."""
        if any(row["candidate"] == cand.to_json() for row in self.table):
            return
        opts = self.opts
        t0 = time.perf_counter()
        try:
            model, _ = _fit_candidate(cand, self.fit_on, self.fit_on, opts.selection_rows,
                                      opts.selection_max_iter, opts.seed, self.rc)
            result = _score(model, self.held, opts, self.case_lags)
        except (TrainingError, EvaluationError, ValueError) as exc:
            self.report("select", f"{cand.name}: skipped ({exc})")
            self.table.append({"candidate": cand.to_json(), "stage": stage,
                               "skipped": str(exc)})
            return
        row = {"candidate": cand.to_json(), "stage": stage, **result,
               "seconds": round(time.perf_counter() - t0, 2)}
        self.table.append(row)
        self.report("select", f"{cand.name}: held-out success "
                    + " ".join(f"{k} s {100 * v['success']:.1f}%"
                               for k, v in result["horizons"].items())
                    + f" ({row['seconds']:.1f} s)")
        if _better(result, self.best):
            self.best, self.best_cand, self.best_model = result, cand, model


def _moving_cases(held: Sequence[Series], rc: ResampleConfig, case_lags: int,
                  opts: AutoOptions) -> int:
    """The held-out cases of the longest horizon in which the chair gets at least the
    success distance from where it started (by the path integrated from the VO)."""
    k = max(metrics.horizon_steps(list(opts.horizons_s), rc.rate_hz))
    dt = 1.0 / rc.rate_hz
    moving = 0
    for s in held:
        idx = metrics.case_indices(s.res.segment, case_lags, k)
        if idx.size == 0:
            continue
        ref = reference_path(metrics.windows(s.res.vel, idx, -1, k + 1), dt)
        reach = np.max(np.hypot(ref[..., 0], ref[..., 1]), axis=1)
        moving += int(np.count_nonzero(reach >= opts.threshold_m))
    return moving


def _scorable_horizons(held: Sequence[Series], opts: AutoOptions, rc: ResampleConfig,
                       case_lags: int) -> tuple[float, ...]:
    """The horizons of ``opts`` for which some held-out segment has a case."""
    steps = metrics.horizon_steps(list(opts.horizons_s), rc.rate_hz)
    return tuple(h for h, k in zip(opts.horizons_s, steps, strict=True)
                 if any(metrics.case_indices(s.res.segment, case_lags, k).size for s in held))


def _calibrate_step(model: MotionModel, held: Sequence[Series], opts: AutoOptions,
                    case_lags: int, report: Progress
                    ) -> tuple[VarianceCalibration, dict[str, Any]]:
    """:func:`calibrate` when ``opts.calibrate``, reported; identity when it cannot be."""
    if not opts.calibrate:
        return VarianceCalibration(), {"fitted": False}
    t0 = time.perf_counter()
    calibration = VarianceCalibration()
    try:
        calibration, cal_meta = calibrate(model, held, opts, case_lags)
    except (CalibrationError, EvaluationError) as exc:
        report("calibrate", f"not calibrated: {exc}")
        cal_meta = {"fitted": False, "reason": str(exc)}
    else:
        report("calibrate", cal_meta["reason"] if not cal_meta["applied"] else
                            f"scale v {calibration.scale[0]:.3g}, omega "
                            f"{calibration.scale[1]:.3g}; floor v "
                            f"{calibration.floor[0]:.3g}, omega {calibration.floor[1]:.3g}; "
                            f"held-out coverage {100 * cal_meta['raw_coverage']:.1f}% -> "
                            f"{100 * cal_meta['coverage']:.1f}%")
    cal_meta["seconds"] = round(time.perf_counter() - t0, 2)
    return calibration, cal_meta


def _conditioned_on_all(series: Sequence[Series], chosen: Candidate, model: MotionModel,
                        infos: dict[str, dict[str, Any]]) -> list[SparseGP]:
    """The shipped posterior: each channel's fitted parameters conditioned on all the data
    (``infos[channel]["posterior_rows"]`` is set)."""
    fc = chosen.features()
    chans = []
    for c, fitted in enumerate(model.channels):
        X, y = design(series, c, fc)
        gp = cast(SparseGP, fitted)
        chans.append(SparseGP.from_params(X, y, gp.inducing_inputs, gp.lengthscales,
                                          gp.signal_variance, gp.noise_variance,
                                          jitter=gp.jitter))
        infos[CHANNELS[c]]["posterior_rows"] = int(X.shape[0])
    return chans


def _fallback(series: Sequence[Series], opts: AutoOptions, rc: ResampleConfig,
              table: list[dict[str, Any]], report: Progress) -> MotionModel:
    """Too little held-out data to choose: the paper's configuration (with what is pinned),
    fitted on all the data, uncalibrated; the model's meta says so."""
    fallback = TrainOptions(
        kind="asgp", lags=opts.lags if opts.lags is not None else PAPER_OPTIONS.lags,
        coupled=bool(opts.coupled),
        inducing_v=opts.inducing_v if opts.inducing_v is not None else PAPER_OPTIONS.inducing_v,
        inducing_w=opts.inducing_w if opts.inducing_w is not None else PAPER_OPTIONS.inducing_w,
        max_iter=opts.max_iter, seed=opts.seed)
    why = next((row["skipped"] for row in table if "skipped" in row), "no candidate")
    report("select", "no candidate could be fitted and scored on the held-out data ("
                     + why + f"); training s={fallback.resolved_lags()} M={fallback.inducing_v}/"
                     f"{fallback.inducing_w}{' coupled' if fallback.coupled else ''} on all the "
                     "data, without calibration")
    model = train(series, fallback, resample_config=rc, progress=report)
    meta = dict(model.meta)
    meta["training"] = {**meta["training"], "configuration": "fallback"}
    meta["selection"] = {"fallback": why, "candidates": table,
                         "holdout_fraction": opts.holdout, "budget_s": opts.budget_s}
    meta["calibration"] = {"fitted": False,
                           "reason": "no candidate could be fitted and scored on the held-out "
                                     f"data ({why})"}
    return dataclasses.replace(model, meta=meta)


def calibrate(model: MotionModel, held: Sequence[Series], opts: AutoOptions, case_lags: int
              ) -> tuple[VarianceCalibration, dict[str, Any]]:
    """Fit the variance calibration of ``model`` on held-out series; return it with a
    JSON-able report of the held-out coverage of the 95 % ellipse, raw and calibrated,
    per horizon, per speed regime, per joystick steadiness, per regime and steadiness
    together, and per recording.

    The calibrated figures are cross-validated: the held-out cases are cut in two halves
    in time (the first and second half of each recording's held-out part); each half is
    scored with the map fitted on the other, so no figure is scored on the data its map
    was fitted on. The map stored is fitted on both halves. Fitted, judged and reported
    on all but the parked cases (``still_cases``): the stick within the board's neutral
    window throughout, and neither the chair nor its prediction got the success distance
    from where it started.
    """
    steps = metrics.horizon_steps(list(opts.horizons_s), model.rate_hz)
    cases = _held_out_cases(model, held, case_lags, max(steps))
    N = cases.err.shape[0]
    if N < MIN_CALIBRATION_CASES:
        raise CalibrationError(f"{N} held-out cases, fewer than the {MIN_CALIBRATION_CASES} "
                               "a calibration needs (record longer)")
    # A case in which the chair stays within the success distance says nothing of how
    # wrong a moving chair's prediction gets: fitted on a held-out part of the chair parked
    # (a recorder left running), the map shrank the variance 600,000-fold, and on driving
    # the ellipses held 1-2 % of the positions. Only cases that move the chair count
    # towards the minimum, and the map is fitted on all but the parked cases (as the
    # online calibration checks them): ten minutes parked among
    # thirty of driving took the slow regime's factor from 1.16 to 0.65, and on other
    # drives the ellipses of the chair starting from rest held 84 % instead of 90 %.
    moving = int(np.count_nonzero(cases.reach >= opts.threshold_m))
    if moving < MIN_CALIBRATION_CASES:
        raise CalibrationError(
            f"{moving} of the {N} held-out cases move the chair {100 * opts.threshold_m:g} "
            f"cm or more, fewer than the {MIN_CALIBRATION_CASES} a calibration needs: the "
            "chair stands through most of the held-out part (the end of each recording); "
            "record longer, or end the recordings while driving")
    # the parked cases: nothing commanded (the stick within the board's neutral window
    # throughout), and neither the chair nor its prediction moved the success distance
    fitted = ~cases.quiet | (cases.reach >= opts.threshold_m) \
        | (cases.pred_reach >= opts.threshold_m)
    fit = cases.fit(fitted)
    cal = fit.calibration
    cov_cv, cross_validated = _cross_validated_covariances(cases, cal, fitted)
    # the coverage the map is judged and reported by is that of the same cases: at rest
    # every ellipse holds, and a parked part pulled a regime's raw figure towards 95 %
    still = N - int(np.count_nonzero(fitted))
    cases, cov_cv, N = cases.subset(fitted), cov_cv[fitted], int(np.count_nonzero(fitted))
    cov_raw = cases.parts[0] + cases.parts[1]
    coverage_table = _CoverageTable(cases, cov_raw, cov_cv, opts.horizons_s, steps)
    by_speed = coverage_table.by_speed(cal.speed_edges)
    # keep the map only if, cross-validated, it brings the coverage closer to the target
    # where it matters: in every speed regime at every horizon (mean absolute deviation)
    def deviation(which: str) -> float:
        vals = [t[horizon_key(h)][which] for t in by_speed.values() for h in opts.horizons_s]
        vals = [v for v in vals if v is not None]
        return float(np.mean(np.abs(np.array(vals) - TARGET_COVERAGE))) if vals else math.nan
    dev_raw, dev_cal = deviation("raw"), deviation("calibrated")
    applied = not (cross_validated and dev_cal > dev_raw)
    steady = cases.change <= np.median(cases.change)
    bag = np.array(cases.names)
    table = coverage_table.table
    report = {
        "fitted": True,
        "applied": applied,
        "deviation_raw": dev_raw, "deviation_calibrated": dev_cal,
        "method": "per-channel var' = (scale * var + floor) * factor(speed regime); scale "
                  "and floor by the Gaussian likelihood of the held-out k-step position "
                  "errors, one factor per speed regime for 95% coverage in each",
        "cases": int(N), "still_cases": still, "steps": int(cases.K), "pairs": fit.cases,
        "ml_theta": list(fit.ml_theta),
        "raw_coverage": fit.raw_coverage, "coverage": fit.coverage,
        "cross_validated": cross_validated,
        "by_horizon": table(np.ones(N, dtype=bool)),
        "by_speed": by_speed,
        "by_steadiness": {"steady joystick": table(steady), "changing joystick": table(~steady)},
        "by_speed_and_steadiness": coverage_table.by_speed_and(
            cal.speed_edges, {"steady": steady, "changing": ~steady}),
        "by_recording": {name: table(bag == name) for name in dict.fromkeys(cases.names)},
    }
    if not applied:
        report["reason"] = (f"not applied: cross-validated, the map moved the coverage away "
                            f"from 95% (mean deviation over speed regimes and horizons "
                            f"{100 * dev_raw:.2f} points raw, {100 * dev_cal:.2f} calibrated)")
        return VarianceCalibration(), report
    return cal, report


class _HeldOutCases(NamedTuple):
    """The held-out cases of a calibration: N cases of K steps, in recording order."""

    parts: np.ndarray  # [4, N, K, 2, 2] position covariances under the calibration BASIS
    err: np.ndarray  # [N, K, 2] position errors, reference - prediction
    names: list[str]  # [N] the recording of each case
    speed: np.ndarray  # [N] |v| at the start of the case (its speed regime)
    change: np.ndarray  # [N] largest change of the future joystick over the case
    half: np.ndarray  # [N] in the second half of its recording's held-out part
    K: int
    reach: np.ndarray  # [N] farthest the chair got from the case's start (m), by the VO
    pred_reach: np.ndarray  # [N] farthest the predicted path got from the start (m)
    quiet: np.ndarray  # [N] the stick within the board's neutral window, past and future

    def subset(self, mask: np.ndarray) -> _HeldOutCases:
        """The cases of ``mask``."""
        return _HeldOutCases(self.parts[:, mask], self.err[mask],
                             [n for n, m in zip(self.names, mask, strict=True) if m],
                             self.speed[mask], self.change[mask], self.half[mask], self.K,
                             self.reach[mask], self.pred_reach[mask], self.quiet[mask])

    def fit(self, mask: np.ndarray) -> CalibrationFit:
        """The variance map fitted on the cases of ``mask`` (all their steps)."""
        n, K = int(mask.sum()), self.K
        return fit_calibration(self.parts[:, mask].reshape(4, n * K, 2, 2),
                               self.err[mask].reshape(n * K, 2),
                               np.repeat(self.speed[mask], K),
                               raw=(self.parts[0, mask] + self.parts[1, mask]).reshape(
                                   n * K, 2, 2),
                               steps_per_case=K)


def _held_out_cases(model: MotionModel, held: Sequence[Series], case_lags: int, K: int
                    ) -> _HeldOutCases:
    """Every held-out case of K steps with ``case_lags`` past samples, rolled out with each
    calibration of the BASIS (linearised propagation) and compared with the path
    integrated from the recorded VO."""
    dt = 1.0 / model.rate_hz
    parts_l, err_l, names, speed_l, change_l, half_l, reach_l, pred_l, quiet_l = \
        [], [], [], [], [], [], [], [], []
    for s in held:
        idx = metrics.case_indices(s.res.segment, case_lags, K)
        if idx.size == 0:
            continue
        covs = []
        pose = None
        for basis in BASIS:
            m = dataclasses.replace(model, calibration=basis)
            pose, cov, _ = rollout_cases(m, s.res, idx, K, uncertainty="linear")
            assert cov is not None
            covs.append(cov)
        assert pose is not None
        ref = reference_path(metrics.windows(s.res.vel, idx, -1, K + 1), dt)
        parts_l.append(np.stack(covs))  # [4, N, K, 2, 2]
        err_l.append(ref[..., :2] - pose[..., :2])  # [N, K, 2]
        reach_l.append(np.max(np.hypot(ref[..., 0], ref[..., 1]), axis=1))
        pred_l.append(np.max(np.hypot(pose[..., 0], pose[..., 1]), axis=1))
        stick = metrics.windows(s.res.joy, idx, -model.lags, model.lags + K)
        quiet_l.append(np.all(np.abs(np.nan_to_num(stick, nan=1.0)) <= NEUTRAL_WINDOW,
                              axis=(1, 2)))
        names.extend([s.name] * idx.size)
        speed_l.append(np.abs(s.res.vel[idx - 1, 0]))
        future = metrics.windows(s.res.joy, idx, -1, K + 1)  # [N, K+1, 2]
        change_l.append(np.max(np.abs(future - future[:, :1]), axis=(1, 2)))
        half_l.append(idx >= np.median(idx))
    if not err_l:
        raise CalibrationError(f"no held-out case of {K} steps with {case_lags} past samples")
    return _HeldOutCases(np.concatenate(parts_l, axis=1), np.concatenate(err_l), names,
                         np.concatenate(speed_l), np.concatenate(change_l),
                         np.concatenate(half_l), K, np.concatenate(reach_l),
                         np.concatenate(pred_l), np.concatenate(quiet_l))


def _cross_validated_covariances(cases: _HeldOutCases, cal: VarianceCalibration,
                                 fitted: np.ndarray) -> tuple[np.ndarray, bool]:
    """[N, K, 2, 2] calibrated covariances, each half of the cases with the map fitted on the
    cases of ``fitted`` in the other half (``cal``, the map of all of them, where a half
    cannot be fitted; then the figures are not cross-validated, the flag returned)."""
    cov_cv = np.empty_like(cases.parts[0])
    cross_validated = True
    for h in (False, True):
        try:
            other = cases.fit((cases.half != h) & fitted).calibration
        except CalibrationError:
            cross_validated = False
            other = cal
        theta = np.array([*other.scale, *other.floor])
        cov_cv[cases.half == h] = (combine(cases.parts[:, cases.half == h], theta)
                                   * other.factor(cases.speed[cases.half == h])[:, None, None,
                                                                                 None])
    return cov_cv, cross_validated


class _CoverageTable:
    """Held-out coverage of the 95% ellipse, raw and calibrated, per horizon, for a subset
    of the cases."""

    def __init__(self, cases: _HeldOutCases, cov_raw: np.ndarray, cov_cv: np.ndarray,
                 horizons_s: Sequence[float], steps: Sequence[int]) -> None:
        self.cases, self.cov_raw, self.cov_cv = cases, cov_raw, cov_cv
        self.horizons_s, self.steps = horizons_s, steps

    def table(self, mask: np.ndarray) -> dict[str, Any]:
        """{"cases": n, horizon key: {"raw": coverage, "calibrated": coverage}} of ``mask``
        (a coverage is None where it cannot be computed)."""
        out: dict[str, Any] = {"cases": int(np.sum(mask))}
        for h, k in zip(self.horizons_s, self.steps, strict=True):
            e = self.cases.err[mask, k - 1]
            out[horizon_key(h)] = {"raw": _coverage_figure(e, self.cov_raw[mask, k - 1]),
                                   "calibrated": _coverage_figure(e, self.cov_cv[mask, k - 1])}
        return out

    def by_speed(self, speed_edges: Sequence[float]) -> dict[str, Any]:
        """A table per speed regime of the calibration (its ``speed_edges``)."""
        return {name: self.table(mask) for name, mask in self._regimes(speed_edges)}

    def by_speed_and(self, speed_edges: Sequence[float],
                     groups: dict[str, np.ndarray]) -> dict[str, Any]:
        """A table per speed regime and group (``groups``: name -> mask), regime by
        regime: the regime's over-confidence can depend on the group within it."""
        return {f"{name}, {group}": self.table(mask & inside)
                for name, mask in self._regimes(speed_edges)
                for group, inside in groups.items()}

    def _regimes(self, speed_edges: Sequence[float]) -> list[tuple[str, np.ndarray]]:
        speed = self.cases.speed
        edges = (0.0, *speed_edges, math.inf)
        return [(f"|v| {lo:.2f}-{hi:.2f} m/s" if math.isfinite(hi) else f"|v| >= {lo:.2f} m/s",
                 (speed >= lo) & (speed < hi)) for lo, hi in itertools.pairwise(edges)]


def _coverage_figure(e: np.ndarray, c: np.ndarray) -> float | None:
    """The coverage of errors ``e`` by covariances ``c``, rounded; None where undefined."""
    v = coverage(e, c)
    return None if math.isnan(v) else round(v, 4)
