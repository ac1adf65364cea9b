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

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from asgp_ros.core.features import CHANNELS, FeatureConfig
from asgp_ros.core.models import FitBudget, ModelKind, MotionModel, get_kind, trainable_kinds
from asgp_ros.topics import BAG_JOY, BAG_VO_TWIST

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


def read_series(
    paths: Sequence[str],
    *,
    resample_config: Any = None,
    joy_topic: str = BAG_JOY,
    twist_topic: str = BAG_VO_TWIST,
    truth_topic: str | None = None,
    joy_axes: Any = None,
) -> list[Series]:
    """Read bags and resample them onto the grid (raises the bag reader's errors)."""
    from asgp_ros import bags
    from asgp_ros.core.resample import ResampleConfig, resample

    config = resample_config if resample_config is not None else ResampleConfig()
    out = []
    for path in paths:
        kwargs: dict[str, Any] = {"joy_topic": joy_topic, "twist_topic": twist_topic}
        if truth_topic is not None:
            kwargs["truth_topic"] = truth_topic
        if joy_axes is not None:
            kwargs["joy_axes"] = joy_axes
        streams = bags.read_streams(str(path), **kwargs)
        res = resample(streams, config)
        out.append(Series(str(path), res))
    return out


def data_summary(series: Sequence[Series], rows: int | None = None) -> dict[str, Any]:
    """Training-data summary for the model file's meta (bags, samples, segments, stale)."""
    grid = sum(int(s.res.t.shape[0]) for s in series)
    valid = sum(int(np.sum(s.res.valid)) for s in series)
    stale = sum(int(np.sum(s.res.stale)) for s in series)
    segments = sum(len(s.res.segments()) for s in series)
    out: dict[str, Any] = {
        "bags": [s.name for s in series],
        "grid_samples": grid,
        "valid_samples": valid,
        "segments": segments,
        "stale_fraction": float(stale / grid) if grid else 0.0,
        "duration_s": float(sum(s.res.t[-1] - s.res.t[0] for s in series if s.res.t.size)),
    }
    if rows is not None:
        out["training_rows"] = int(rows)
    return out


def design(series: Sequence[Series], channel: int, feature_config: Any) -> tuple[np.ndarray,
                                                                                 np.ndarray]:
    """Stacked design matrix X [N, D] and targets y [N] of one channel over all series."""
    from asgp_ros.core.features import design_matrix

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
    from asgp_ros.core.resample import ResampleConfig

    opts.validate()
    if not series:
        raise TrainingError("no training recordings")
    report = progress or (lambda ch, msg: log.info("%s: %s", ch, msg))
    kind = get_kind(opts.kind)
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
        "training_data": data_summary(series, rows),
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
