"""k-step path-prediction evaluation exactly as the paper (Fan et al., ICRA 2018, Sec. V).

For every test time step t whose s past and k future grid samples lie inside one valid
segment, the model predicts V_t..V_{t+k-1} by the recurrent sliding window (Algorithm 1,
``asgp_ros.core.rollout.rollout``, batched over all test steps at once) from the recorded
past and the recorded future joystick; the unicycle model (eq. 5, trapezoidal) integrates
them from the origin at t0 = t_{t-1}; the (x, y) at the horizon is compared with the path
integrated with the same unicycle from the recorded VO V_{t-1}..V_{t+k-1}. Reported per
horizon: success rate (error <= threshold), number of cases, median (and mean, p90) error,
and for a model with uncertainty the coverage of its predicted 95% position ellipse.
With ``truth=True`` (simulated bags), the same predictions are also scored against the
ground-truth displacement between t_{t-1} and t_{t+k-1}.

Case sets: a model with s lags needs s past samples. To compare models with different s
on identical test steps (the paper's ASGP has s = 4, its MLP s = 10), ``case_lags`` sets
the number of past samples a case must have (the largest s of the models compared); the
model then uses its own last s of them.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from asgp_ros.core import metrics
from asgp_ros.core.metrics import THRESHOLD_M, horizon_key
from asgp_ros.core.models import get_kind
from asgp_ros.core.rollout import rollout
from asgp_ros.core.unicycle import integrate_path

log = logging.getLogger(__name__)

#: Rollouts are batched over test steps in chunks of this size (bounds memory).
CHUNK = 4096


class EvaluationError(ValueError):
    """The evaluation cannot be done as asked (no cases, a horizon longer than the data...)."""


@dataclass
class TestSeries:
    """One test recording on the model's grid (``core.resample.Resampled``)."""

    __test__ = False  # not a pytest test class despite the name

    name: str
    res: Any

    @property
    def has_truth(self) -> bool:
        return bool(np.any(self.res.truth_valid))


@dataclass
class HorizonEvaluation:
    """Scores of one model at one horizon (against VO, and optionally ground truth)."""

    vo: metrics.HorizonResult
    truth: metrics.HorizonResult | None
    errors: np.ndarray  # [N] position errors at the horizon against VO (m)
    examples: dict[str, np.ndarray] | None = None

    def to_json(self) -> dict[str, object]:
        out = self.vo.to_json()
        if self.truth is not None:
            out["truth"] = self.truth.to_json()
        return out


@dataclass
class ModelEvaluation:
    """All horizons of one model on one test set."""

    model: str
    kind: str
    lags: int
    case_lags: int
    threshold_m: float
    test: list[str]
    horizons: dict[str, HorizonEvaluation]

    def to_json(self) -> dict[str, object]:
        return {
            "model": self.model,
            "kind": self.kind,
            "lags": self.lags,
            "case_lags": self.case_lags,
            "threshold_m": self.threshold_m,
            "test": self.test,
            "horizons": {k: v.to_json() for k, v in self.horizons.items()},
        }


def reference_path(vel_ref: np.ndarray, dt: float) -> np.ndarray:
    """Path [N, k, 3] integrated from recorded velocities V_{t-1}..V_{t+k-1} [N, k+1, 2].

    Same trapezoidal unicycle as the rollout (paper eq. 5), from the origin at t_{t-1};
    row i is the pose at t_{t-1} + (i+1) dt, like ``Rollout.pose``.
    """
    return np.asarray(integrate_path(vel_ref, dt))[:, 1:]


def _uncertainty_for(model: Any) -> str:
    """Linearised propagation for probabilistic kinds; deterministic kinds need none.

    A kind that is not registered is propagated (whatever variance it predicts is kept).
    """
    try:
        probabilistic = get_kind(str(getattr(model, "kind", ""))).probabilistic
    except KeyError:
        probabilistic = True
    return "linear" if probabilistic else "none"


def rollout_cases(
    model: Any, res: Any, idx: np.ndarray, steps: int, *, uncertainty: str
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Roll the model out from every case t in idx over ``steps`` recorded future commands.

    Returns:
        (pose [N, k, 3], pos_cov [N, k, 2, 2] or None, vel [N, k, 2]).
    """
    s = int(model.feature_config.lags)
    poses, covs, vels = [], [], []
    for a in range(0, idx.shape[0], CHUNK):
        chunk = idx[a:a + CHUNK]
        joy_past = metrics.windows(res.joy, chunk, -s, s)
        vel_past = metrics.windows(res.vel, chunk, -s, s)
        joy_future = metrics.windows(res.joy, chunk, 0, steps)
        out = rollout(model, joy_past, vel_past, joy_future, uncertainty=uncertainty)
        poses.append(np.asarray(out.pose))
        vels.append(np.asarray(out.vel))
        if uncertainty != "none" and getattr(out, "pos_cov", None) is not None:
            covs.append(np.asarray(out.pos_cov))
    pose = np.concatenate(poses) if poses else np.zeros((0, steps, 3))
    vel = np.concatenate(vels) if vels else np.zeros((0, steps, 2))
    cov = np.concatenate(covs) if covs else None
    return pose, cov, vel


def longest_segment_s(series: Sequence[TestSeries], rate_hz: float) -> float:
    runs = [b - a for ts in series for a, b in metrics.segment_runs(ts.res.segment)]
    return (max(runs) if runs else 0) / rate_hz


def evaluate_model(
    model: Any,
    series: Sequence[TestSeries],
    horizons_s: Sequence[float],
    *,
    threshold_m: float = THRESHOLD_M,
    case_lags: int | None = None,
    truth: bool = False,
    uncertainty: str | None = None,
    n_examples: int = 0,
    name: str = "",
) -> ModelEvaluation:
    """Score a MotionModel on test series at the given horizons (see module docstring).

    Args:
        model: MotionModel (kind, feature_config.lags, resample_config.rate_hz, channels).
        series: test recordings resampled with the model's resample config.
        horizons_s: horizons in seconds, k = round(h * rate).
        case_lags: past samples a case needs (>= the model's s; default the model's s).
        truth: also score against ground truth (every series must have it).
        uncertainty: "linear", "mc" or "none" (default: "linear" for a probabilistic kind,
            "none" for the deterministic baselines).
        n_examples: keep this many example cases per horizon for plots (from a mild to the
            sharpest recorded turn).

    Raises:
        EvaluationError: no series, a horizon with no case in any series (longer than every
        segment), or truth asked for on series without ground truth.
    """
    if not series:
        raise EvaluationError("no test recordings")
    if not math.isfinite(threshold_m) or threshold_m <= 0.0:
        raise EvaluationError(f"threshold must be a positive distance, got {threshold_m}")
    rate = float(model.resample_config.rate_hz)
    dt = 1.0 / rate
    s = int(model.feature_config.lags)
    need = s if case_lags is None else int(case_lags)
    if need < s:
        raise EvaluationError(f"case_lags={need} is less than the model's {s} lags")
    if truth:
        missing = [ts.name for ts in series if not ts.has_truth]
        if missing:
            raise EvaluationError(f"no ground truth in {', '.join(missing)} (--truth needs "
                                  "simulated bags with a ground-truth topic)")
    try:
        steps_list = metrics.horizon_steps(list(horizons_s), rate)
    except ValueError as exc:
        raise EvaluationError(str(exc)) from exc
    unc = uncertainty or _uncertainty_for(model)
    out: dict[str, HorizonEvaluation] = {}
    for h, k in zip(horizons_s, steps_list, strict=True):
        preds, refs, covs, truths = [], [], [], []
        ex_pool: list[dict[str, np.ndarray]] = []
        for ts in series:
            res = ts.res
            idx = metrics.case_indices(res.segment, need, k)
            if idx.size == 0:
                continue
            pose, cov, _ = rollout_cases(model, res, idx, k, uncertainty=unc)
            ref_path = reference_path(metrics.windows(res.vel, idx, -1, k + 1), dt)  # [N, k, 3]
            preds.append(pose[:, -1, :2])
            refs.append(ref_path[:, -1, :2])
            if cov is not None:
                covs.append(cov[:, -1])
            if truth:
                # Ground-truth displacement t_{t-1} -> t_{t+k-1} in the body frame at t_{t-1};
                # cases without ground truth at both ends are left out of this score.
                ok = res.truth_valid[idx - 1] & res.truth_valid[idx + k - 1]
                disp = metrics.relative_displacement(res.truth[idx - 1, :3],
                                                     res.truth[idx + k - 1, :3])
                disp[~ok] = np.nan
                truths.append(disp)
            if n_examples:
                # a spread of manoeuvres: cases ranked by the recorded heading change
                turn = np.abs(ref_path[:, -1, 2])
                keep = np.argsort(turn, kind="stable")
                keep = keep[np.linspace(0, keep.size - 1, min(4 * n_examples, keep.size))
                            .astype(int)]
                ex_pool.append({
                    "pred": pose[keep, :, :2],
                    "ref": ref_path[keep, :, :2],
                    "cov": cov[keep] if cov is not None else np.zeros((keep.size, k, 2, 2)),
                    "score": turn[keep],
                    "t": res.t[idx[keep]] - res.t[0],
                    "idx": idx[keep],
                    "series": np.full(keep.size, ts.name),
                })
        if not preds:
            raise EvaluationError(
                f"horizon {h} s ({k} steps) with {need} past samples is longer than every "
                f"valid segment of the test data (longest {longest_segment_s(series, rate):.1f}"
                " s)")
        pred_xy = np.concatenate(preds)
        ref_xy = np.concatenate(refs)
        pos_cov = np.concatenate(covs) if len(covs) == len(preds) and covs else None
        try:
            vo_res, errors = metrics.score(pred_xy, ref_xy, horizon_s=h, steps=k,
                                           threshold_m=threshold_m, pos_cov=pos_cov)
            truth_res = None
            if truth:
                gt = np.concatenate(truths)
                ok = np.all(np.isfinite(gt), axis=1)
                truth_res, _ = metrics.score(
                    pred_xy[ok], gt[ok], horizon_s=h, steps=k, threshold_m=threshold_m,
                    pos_cov=None if pos_cov is None else pos_cov[ok])
        except ValueError as exc:
            raise EvaluationError(f"{name or model.kind} at {h} s: {exc}") from exc
        examples = None
        if n_examples and ex_pool:
            allx = {key: np.concatenate([p[key] for p in ex_pool]) for key in ex_pool[0]}
            # Quantiles 0.5 .. 1 of the heading change: a mild, a medium and the sharpest turn.
            order = np.argsort(allx["score"], kind="stable")
            q = np.linspace(0.5, 1.0, min(n_examples, order.size))
            pick = order[np.round(q * (order.size - 1)).astype(int)]
            examples = {key: v[pick] for key, v in allx.items()}
        out[horizon_key(h)] = HorizonEvaluation(vo_res, truth_res, errors, examples)
        log.debug("%s @ %s s: %d cases, success %.3f", name or model.kind, h, vo_res.cases,
                  vo_res.success_rate)
    return ModelEvaluation(
        model=name or str(model.kind),
        kind=str(model.kind),
        lags=s,
        case_lags=need,
        threshold_m=float(threshold_m),
        test=[ts.name for ts in series],
        horizons=out,
    )
