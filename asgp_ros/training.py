"""Training of the motion predictors from recordings: the ASGP and the baselines.

Pipeline (Fan et al., ICRA 2018, Sec. IV): raw joystick and VO streams from each bag are
resampled onto the common 5 Hz grid (``core.resample``), the autoregressive design
matrices are built per output channel (``core.features.design_matrix``, eq. 3-4; rows
never cross a segment gap), and one regressor per channel is fitted:

* ``asgp``: SPGP / FITC sparse GP with M = 20 (v) and 40 (omega) pseudo-inputs, s = 4;
* ``mlp``: three hidden layers of 30 ReLU units, Adam, batch 100, s = 10;
* ``constant_velocity``: V_t = V_{t-1} (nothing to fit), s = 1;
* ``first_order_lag``: V_t = a V_{t-1} + b j_t + c by least squares, s = 1.

The result is a ``core.models.MotionModel`` whose meta records a training-data summary.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

KINDS = ("asgp", "mlp", "constant_velocity", "first_order_lag")
CHANNELS = ("v", "omega")

#: Default number of lags per kind (the paper's s = 4 for the ASGP, 10 for the MLP).
DEFAULT_LAGS = {"asgp": 4, "mlp": 10, "constant_velocity": 1, "first_order_lag": 1}

#: progress(channel name, message) for a CLI's progress lines.
Progress = Callable[[str, str], None]


class TrainingError(ValueError):
    """Training cannot proceed (no usable data, bad options); the message says why."""


@dataclass(frozen=True)
class TrainOptions:
    kind: str = "asgp"
    lags: int | None = None  # None: DEFAULT_LAGS[kind]
    inducing_v: int = 20
    inducing_w: int = 40
    max_iter: int = 200
    coupled: bool = False
    seed: int = 0

    def resolved_lags(self) -> int:
        return int(self.lags if self.lags is not None else DEFAULT_LAGS[self.kind])

    def validate(self) -> None:
        if self.kind not in KINDS:
            raise TrainingError(f"unknown model kind {self.kind!r}; choose from {KINDS}")
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
    joy_topic: str = "/joy",
    twist_topic: str = "/vo/twist",
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


def _fit_channel(kind: str, channel: int, X: np.ndarray, y: np.ndarray, feature_config: Any,
                 opts: TrainOptions, progress: Progress) -> tuple[Any, dict[str, Any]]:
    from asgp_ros.core import baselines

    name = CHANNELS[channel]
    t0 = time.perf_counter()
    info: dict[str, Any] = {"rows": int(X.shape[0])}
    if kind == "asgp":
        from asgp_ros.core.sparse_gp import SparseGP

        M = opts.inducing_v if channel == 0 else opts.inducing_w
        if X.shape[0] < M:
            raise TrainingError(f"channel {name}: {X.shape[0]} training rows < {M} "
                                "pseudo-inputs; record more data or lower --inducing-*")
        every = max(1, opts.max_iter // 10)

        def cb(it: int, lml: float) -> None:
            if it % every == 0:
                progress(name, f"iteration {it:4d}  log likelihood {lml:.2f}")

        gp = SparseGP(num_inducing=M, seed=opts.seed).fit(X, y, max_iter=opts.max_iter,
                                                          callback=cb)
        res = gp.optimiser_result
        info.update(num_inducing=M, log_likelihood=float(gp.log_marginal_likelihood()),
                    iterations=int(getattr(res, "nit", -1)) if res is not None else -1,
                    noise_std=float(np.sqrt(gp.noise_variance)),
                    lengthscales=[float(v) for v in gp.lengthscales])
        progress(name, f"done: {info['iterations']} iterations, log likelihood "
                 f"{info['log_likelihood']:.2f}, noise std {info['noise_std']:.4f}")
        model: Any = gp
    elif kind == "mlp":
        model, mlp_info = baselines.MLPChannel.fit(X, y, max_iter=opts.max_iter, seed=opts.seed)
        info.update(mlp_info)
        progress(name, f"done: {mlp_info['epochs']} epochs, loss {mlp_info['final_loss']:.4f}"
                 f", validation R^2 {mlp_info['best_validation_score']:.4f}")
    else:
        dim, vel_col, joy_col = baselines.probe_columns(channel, feature_config)
        if kind == "constant_velocity":
            model = baselines.ConstantVelocityChannel(dim, vel_col)
            progress(name, "constant velocity: nothing to fit")
        else:
            model = baselines.FirstOrderLagChannel.fit(X, y, dim, vel_col, joy_col)
            tau = model.time_constant_steps
            info.update(coef=[model.a, model.b, model.c],
                        time_constant_steps=tau if np.isfinite(tau) else None)
            progress(name, f"V_t = {model.a:.4f} V_t-1 + {model.b:.4f} j_t + {model.c:.4f}")
        mean, _ = model.predict(X)
        info["train_rmse"] = float(np.sqrt(np.mean((mean - y) ** 2)))
    info["seconds"] = round(time.perf_counter() - t0, 3)
    return model, info


def train(
    series: Sequence[Series],
    opts: TrainOptions,
    *,
    resample_config: Any = None,
    progress: Progress | None = None,
) -> Any:
    """Fit both channels of a model of kind ``opts.kind`` on the series; return a MotionModel."""
    from asgp_ros.core import baselines  # noqa: F401  (registers the baseline kinds)
    from asgp_ros.core.features import FeatureConfig
    from asgp_ros.core.models import MotionModel
    from asgp_ros.core.resample import ResampleConfig

    opts.validate()
    if not series:
        raise TrainingError("no training recordings")
    report = progress or (lambda ch, msg: log.info("%s: %s", ch, msg))
    fc = FeatureConfig(lags=opts.resolved_lags(), coupled=opts.coupled)
    rc = resample_config if resample_config is not None else ResampleConfig()
    channels = []
    infos = {}
    rows = 0
    for c in (0, 1):
        X, y = design(series, c, fc)
        rows = max(rows, X.shape[0])
        report(CHANNELS[c], f"{X.shape[0]} rows x {X.shape[1]} features")
        model, info = _fit_channel(opts.kind, c, X, y, fc, opts, report)
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
