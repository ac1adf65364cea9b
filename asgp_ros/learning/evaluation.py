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
from asgp_ros.core.metrics import CHI2_2DOF_95, THRESHOLD_M, horizon_key
from asgp_ros.core.models import get_kind
from asgp_ros.core.rollout import Uncertainty, rollout
from asgp_ros.core.unicycle import integrate_path

log = logging.getLogger(__name__)

#: Rollouts are batched over test steps in chunks of at most this size...
CHUNK = 4096
#: ... and of at most this many cases times steps squared: the linear rollout's memory
#: grows as cases x k^2 (about 140 bytes each: 11 GB for 2,000 cases of 40 s at 5 Hz in
#: one batch), so that a chunk takes about 0.6 GB whatever the horizon.
CHUNK_CASE_STEPS2 = 1 << 22
#: ... and, with Monte Carlo uncertainty, of at most this many trajectories (cases times
#: MC_SAMPLES): each holds its own kernel rows against the pseudo-inputs (a few kB at
#: M = 120-160), and 4,096 cases of 1,000 took 20 GB; now under 1 GB.
CHUNK_MC_TRAJECTORIES = 1 << 17
#: Monte Carlo trajectories per case (rollout's default).
MC_SAMPLES = 1000


class EvaluationError(ValueError):
    """The evaluation cannot be done as asked (no cases, a horizon longer than the data...)."""


@dataclass
class TestSeries:
    """One test recording on the model's grid (``core.resample.Resampled``)."""

    __test__ = False  # not a pytest test class despite the name

    name: str
    res: Any
    raw: Any = None  # core.streams.RawStreams the grid came from (needed by --adapt)

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


def _uncertainty_for(model: Any) -> Uncertainty:
    """Linearised propagation for probabilistic kinds; deterministic kinds need none.

    A kind that is not registered is propagated (whatever variance it predicts is kept).
    """
    try:
        probabilistic = get_kind(str(getattr(model, "kind", ""))).probabilistic
    except KeyError:
        probabilistic = True
    return "linear" if probabilistic else "none"


def rollout_cases(
    model: Any, res: Any, idx: np.ndarray, steps: int, *, uncertainty: Uncertainty
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Roll the model out from every case t in idx over ``steps`` recorded future commands.

    Returns:
        (pose [N, k, 3], pos_cov [N, k, 2, 2] or None, vel [N, k, 2]).
    """
    s = int(model.feature_config.lags)
    poses, covs, vels = [], [], []
    size = max(1, min(CHUNK, CHUNK_CASE_STEPS2 // max(1, steps) ** 2))
    if uncertainty == "mc":
        size = max(1, min(size, CHUNK_MC_TRAJECTORIES // MC_SAMPLES))
    for a in range(0, idx.shape[0], size):
        chunk = idx[a:a + size]
        joy_past = metrics.windows(res.joy, chunk, -s, s)
        vel_past = metrics.windows(res.vel, chunk, -s, s)
        joy_future = metrics.windows(res.joy, chunk, 0, steps)
        out = rollout(model, joy_past, vel_past, joy_future, uncertainty=uncertainty,
                      n_samples=MC_SAMPLES)
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


def _case_setup(model: Any, series: Sequence[TestSeries], horizons_s: Sequence[float],
                threshold_m: float, case_lags: int | None
                ) -> tuple[float, int, int, list[tuple[float, int]]]:
    """Checked common inputs of an evaluation: (grid rate, the model's s, the past samples
    a case needs, the horizons scored: (seconds, k) each, see :func:`_scored_horizons`)."""
    if not series:
        raise EvaluationError("no test recordings")
    if not math.isfinite(threshold_m) or threshold_m <= 0.0:
        raise EvaluationError(f"threshold must be a positive distance, got {threshold_m}")
    rate = float(model.resample_config.rate_hz)
    s = int(model.feature_config.lags)
    need = s if case_lags is None else int(case_lags)
    if need < s:
        raise EvaluationError(f"case_lags={need} is less than the model's {s} lags")
    try:
        steps_list = metrics.horizon_steps(list(horizons_s), rate)
    except ValueError as exc:
        raise EvaluationError(str(exc)) from exc
    return rate, s, need, _scored_horizons(horizons_s, steps_list, rate)


def _scored_horizons(horizons_s: Sequence[float], steps: Sequence[int], rate: float
                     ) -> list[tuple[float, int]]:
    """The horizons as scored, (k / rate, k), once each: a horizon that is no whole number
    of the model's steps is scored, and labelled, at the nearest one (a 2.5 Hz model's
    '1.0 s' was scored at 0.8 s under the label 1.0 s), with a warning."""
    seen: set[int] = set()
    for h, k in zip(horizons_s, steps, strict=True):
        if abs(k / rate - h) > 1e-9 * max(1.0, h):
            log.warning("horizon %g s is %g steps of the model's %g Hz: scored at %g s "
                        "(%d steps)", h, h * rate, rate, k / rate, k)
        if k in seen:
            log.warning("horizon %g s is %d steps, as an earlier one: scored once", h, k)
        seen.add(k)
    return [(h, round(h * rate)) for h in metrics.scored_horizons(horizons_s, rate)]


def evaluate_model(
    model: Any,
    series: Sequence[TestSeries],
    horizons_s: Sequence[float],
    *,
    threshold_m: float = THRESHOLD_M,
    case_lags: int | None = None,
    truth: bool = False,
    uncertainty: Uncertainty | None = None,
    n_examples: int = 0,
    name: str = "",
) -> ModelEvaluation:
    """Score a MotionModel on test series at the given horizons (see module docstring).

    Args:
        model: MotionModel (kind, feature_config.lags, resample_config.rate_hz, channels).
        series: test recordings resampled with the model's resample config.
        horizons_s: horizons in seconds, k = h * rate rounded (half up); one that is no
            whole number of steps is scored and labelled at k / rate.
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
    rate, s, need, scored = _case_setup(model, series, horizons_s, threshold_m, case_lags)
    if truth:
        missing = [ts.name for ts in series if not ts.has_truth]
        if missing:
            raise EvaluationError(f"no ground truth in {', '.join(missing)} (--truth needs "
                                  "simulated bags with a ground-truth topic)")
    unc = uncertainty or _uncertainty_for(model)
    out: dict[str, HorizonEvaluation] = {}
    for h, k in scored:
        out[horizon_key(h)] = _evaluate_horizon(
            model, series, h, k, rate, need, uncertainty=unc, threshold_m=threshold_m,
            truth=truth, n_examples=n_examples, name=name)
    return ModelEvaluation(
        model=name or str(model.kind),
        kind=str(model.kind),
        lags=s,
        case_lags=need,
        threshold_m=float(threshold_m),
        test=[ts.name for ts in series],
        horizons=out,
    )


def _evaluate_horizon(model: Any, series: Sequence[TestSeries], h: float, k: int, rate: float,
                      need: int, *, uncertainty: Uncertainty, threshold_m: float, truth: bool,
                      n_examples: int, name: str) -> HorizonEvaluation:
    """Every case of every series at the horizon h (k steps): the model rolled out, the
    reference path integrated from the recorded VO, the positions at the horizon scored
    (and against ground truth with ``truth``), and ``n_examples`` example cases kept."""
    dt = 1.0 / rate
    preds, refs, covs, truths = [], [], [], []
    ex_pool: list[dict[str, np.ndarray]] = []
    for ts in series:
        res = ts.res
        idx = metrics.case_indices(res.segment, need, k)
        if idx.size == 0:
            continue
        try:
            pose, cov, _ = rollout_cases(model, res, idx, k, uncertainty=uncertainty)
        except (ValueError, ArithmeticError) as exc:  # a model that diverges on this data
            raise EvaluationError(f"{name}: the model's rollout over {h:g} s failed on "
                                  f"{ts.name}: {exc}") from exc
        ref_path = reference_path(metrics.windows(res.vel, idx, -1, k + 1), dt)  # [N, k, 3]
        preds.append(pose[:, -1, :2])
        refs.append(ref_path[:, -1, :2])
        if cov is not None:
            covs.append(cov[:, -1])
        if truth:
            truths.append(_truth_displacement(res, idx, k))
        if n_examples:
            ex_pool.append(_example_candidates(ts, idx, k, pose, cov, ref_path, n_examples))
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
    examples = _pick_examples(ex_pool, n_examples) if n_examples and ex_pool else None
    log.debug("%s @ %s s: %d cases, success %.3f", name or model.kind, h, vo_res.cases,
              vo_res.success_rate)
    return HorizonEvaluation(vo_res, truth_res, errors, examples)


def _truth_displacement(res: Any, idx: np.ndarray, k: int) -> np.ndarray:
    """[N, 2] ground-truth displacement t_{t-1} -> t_{t+k-1} in the body frame at t_{t-1};
    NaN for cases without ground truth at both ends (left out of that score)."""
    ok = res.truth_valid[idx - 1] & res.truth_valid[idx + k - 1]
    disp = metrics.relative_displacement(res.truth[idx - 1, :3], res.truth[idx + k - 1, :3])
    disp[~ok] = np.nan
    return disp


def _example_candidates(ts: TestSeries, idx: np.ndarray, k: int, pose: np.ndarray,
                        cov: np.ndarray | None, ref_path: np.ndarray, n_examples: int
                        ) -> dict[str, np.ndarray]:
    """Up to 4 n_examples cases of one series for the example plots: a spread of manoeuvres,
    ranked by the recorded heading change ("score")."""
    turn = np.abs(ref_path[:, -1, 2])
    keep = np.argsort(turn, kind="stable")
    keep = keep[np.linspace(0, keep.size - 1, min(4 * n_examples, keep.size)).astype(int)]
    return {
        "pred": pose[keep, :, :2],
        "ref": ref_path[keep, :, :2],
        "cov": cov[keep] if cov is not None else np.zeros((keep.size, k, 2, 2)),
        "score": turn[keep],
        "t": ts.res.t[idx[keep]] - ts.res.t[0],
        "idx": idx[keep],
        "series": np.full(keep.size, ts.name),
    }


def _pick_examples(ex_pool: list[dict[str, np.ndarray]], n_examples: int
                   ) -> dict[str, np.ndarray]:
    """``n_examples`` of the candidates of every series: the quantiles 0.5 .. 1 of the
    heading change (a mild, a medium and the sharpest turn)."""
    allx = {key: np.concatenate([p[key] for p in ex_pool]) for key in ex_pool[0]}
    order = np.argsort(allx["score"], kind="stable")
    q = np.linspace(0.5, 1.0, min(n_examples, order.size))
    pick = order[np.round(q * (order.size - 1)).astype(int)]
    return {key: v[pick] for key, v in allx.items()}


# --------------------------------------------------------------------------- adaptive


@dataclass
class AdaptiveEvaluation:
    """An adapting model scored causally, beside the same model without adaptation.

    ``adapted`` and ``plain`` are scored on the same cases: those where the replayed
    online predictor gave a prediction, from ``skip_s`` into each recording on.
    ``timeline`` holds, per case in time order: ``series`` (index into ``test``),
    ``t`` (seconds since the start of its recording), and per horizon key ``hit``
    (success of the adapted prediction), ``hit_plain``, ``covered`` (inside the adapted
    95 % ellipse), ``covered_plain``, with ``scale`` (the adapted model's online variance
    scale in the case's speed regime when it predicted).  ``adaptation`` is the
    adapter's final state per recording (:func:`asgp_ros.core.adaptive.describe`).
    """

    adapted: ModelEvaluation
    plain: ModelEvaluation
    timeline: dict[str, Any]
    adaptation: list[dict[str, Any]]
    #: per horizon, the cases of the offline evaluation (from ``skip_s`` on) the online
    #: predictor made no prediction for
    missing: dict[str, int]

    def to_json(self) -> dict[str, object]:
        return {"adapted": self.adapted.to_json(), "plain": self.plain.to_json(),
                "adaptation": self.adaptation, "missing_cases": self.missing}


def _replay_series(model: Any, ts: TestSeries, k_max: int, need: int, settings: Any,
                   config: Any) -> dict[str, Any]:
    """Replay one recording's raw samples through an adapting online Predictor.

    Samples (and the overrides sent, ``RawStreams.override_t``) are fed in stamp order;
    whenever a new grid step L completes, the predictor is asked, at the stamp of the
    sample that completed L, for the path under the recorded future joystick (at every
    step, as the node predicts and learns at every step; the paths of the steps where an
    evaluation case starts, L + 1, are kept).  It therefore sees only samples
    stamped at or before that moment: the replay cannot peek.
    """
    # imported when an adaptive evaluation runs (the online predictor and the adapter add
    # a few tenths of a second to every `asgp` command's start-up otherwise)
    from asgp_ros.core.adaptive import describe
    from asgp_ros.core.online import Predictor

    raw, res = ts.raw, ts.res
    if raw is None:
        raise EvaluationError(f"{ts.name}: adaptive evaluation needs the raw streams")
    pred = Predictor(model, config, adapt=settings)
    starts = set(metrics.case_indices(res.segment, need, 1).tolist())
    joy_future_all = np.asarray(res.joy, dtype=np.float64)
    over_t = np.asarray(raw.override_t, dtype=np.float64)
    events = np.concatenate([
        np.stack([raw.joy_t, np.zeros_like(raw.joy_t), np.arange(raw.joy_t.size)], axis=1),
        np.stack([raw.vel_t, np.ones_like(raw.vel_t), np.arange(raw.vel_t.size)], axis=1),
        np.stack([over_t, np.full_like(over_t, 2.0), np.arange(over_t.size)], axis=1)])
    events = events[np.lexsort((events[:, 2], events[:, 1], events[:, 0]))]
    vel_ok = np.asarray(raw.vel_ok, dtype=bool) if raw.vel_ok.size else \
        np.ones(raw.vel_t.size, dtype=bool)
    out: dict[str, list[Any]] = {"idx": [], "pose": [], "cov": [], "scale": []}
    last_step = None
    for t, kind, j in events:
        j = int(j)
        if kind == 0.0:
            pred.feed_joy(t, raw.joy[j])
        elif kind == 1.0:
            pred.feed_vo(t, raw.vel[j], bool(vel_ok[j]))
        else:
            pred.feed_override(t, now=t)
            continue
        step = pred.ready_step()
        if step is None or step == last_step:
            continue
        last_step = step
        # the index in res of L, or of the point before it where the grid leaves out a
        # silence (L is then no case's start, and any finite future serves the learning)
        i = int(np.searchsorted(res.k, step, side="right")) - 1
        if i < 0 or step > res.k[-1]:
            continue
        future = joy_future_all[i + 1:i + 1 + k_max]
        if future.shape[0] == 0:
            future = joy_future_all[i:i + 1]
        if future.shape[0] < k_max:
            future = np.concatenate([future, np.repeat(future[-1:], k_max - future.shape[0], 0)])
        bad = ~np.all(np.isfinite(future), axis=1)
        for r in np.flatnonzero(bad):
            future[r] = future[r - 1] if r > 0 else joy_future_all[i]
        if i + 1 not in starts:  # not scored: any finite future serves the learning
            future = np.nan_to_num(future, nan=0.0, posinf=0.0, neginf=0.0)
        # at every step, as the node does (it learns from each window it predicts from,
        # and checks each prediction), though only the cases are scored
        p = pred.predict(float(t), future, learn=False)
        if i + 1 in starts and p.ok and p.step == step:
            regime = int(model.calibration.regime(p.vel_past[-1, 0]))
            out["idx"].append(i + 1)
            out["pose"].append(p.pose)
            out["cov"].append(p.pos_cov)
            # the scale this prediction used: read before the learning that follows it
            # (100 of 558 cases had the scale after it, up to 22 % off)
            stats = pred.adaptation
            out["scale"].append(stats.scales[regime] if stats is not None else 1.0)
        pred.learn()
    stats = pred.adaptation
    return {"idx": np.asarray(out["idx"], dtype=np.int64),
            "pose": np.asarray(out["pose"]).reshape(-1, k_max, 3),
            "cov": np.asarray(out["cov"]).reshape(-1, k_max, 2, 2),
            "scale": np.asarray(out["scale"]),
            "adaptation": describe(stats) if stats is not None else {}}


def evaluate_adaptive(
    model: Any,
    series: Sequence[TestSeries],
    horizons_s: Sequence[float],
    settings: Any = None,
    *,
    threshold_m: float = THRESHOLD_M,
    case_lags: int | None = None,
    skip_s: float = 0.0,
    name: str = "",
) -> AdaptiveEvaluation:
    """Score an ASGP that adapts online, causally, beside the same model not adapting.

    Each recording is replayed from the trained model through the online predictor with
    ``settings`` (:class:`asgp_ros.core.adaptive.AdaptSettings`, default settings when
    None); see :func:`_replay_series`.  Only cases at least ``skip_s`` seconds into their
    recording are scored (adaptation runs from the start).

    Raises:
        EvaluationError: as :func:`evaluate_model`, or series without raw streams, or a
            model that cannot adapt.
    """
    from asgp_ros.core.adapt import AdaptError  # see _replay_series
    from asgp_ros.core.adaptive import AdaptSettings
    from asgp_ros.core.online import Predictor, PredictorConfig

    if not (math.isfinite(skip_s) and skip_s >= 0.0):
        raise EvaluationError(f"skip must be a non-negative number of seconds, got {skip_s}")
    rate, s, need, scored = _case_setup(model, series, horizons_s, threshold_m, case_lags)
    dt = 1.0 / rate
    k_max = max(k for _, k in scored)
    settings = settings if settings is not None else AdaptSettings()
    try:
        # the history adaptation needs grows with the horizon (the node sizes it alike)
        config = PredictorConfig(horizon_steps=k_max,
                                 buffer_s=Predictor.buffer_for(model, k_max, settings))
    except ValueError as exc:  # the online predictor's horizon is bounded
        raise EvaluationError(f"horizon {max(horizons_s):g} s ({k_max} steps) is longer than "
                              f"the online predictor predicts: {exc}") from exc
    replays = []
    for ts in series:
        try:
            replays.append(_replay_series(model, ts, k_max, need, settings, config))
        except AdaptError as exc:
            raise EvaluationError(str(exc)) from exc
    timeline, keep_all = _timeline_of_cases(series, replays, skip_s)
    horizons_a: dict[str, HorizonEvaluation] = {}
    horizons_p: dict[str, HorizonEvaluation] = {}
    for h, k in scored:
        adapted, plain, columns = _score_adaptive_horizon(
            model, series, replays, keep_all, h, k, need, dt, threshold_m=threshold_m,
            skip_s=skip_s, name=name)
        horizons_a[horizon_key(h)] = adapted
        horizons_p[horizon_key(h)] = plain
        for key, col in columns.items():
            timeline.setdefault(key, {})[horizon_key(h)] = col
    timeline["series"] = np.concatenate(timeline["series"])
    timeline["t"] = np.concatenate(timeline["t"])
    timeline["scale"] = np.concatenate(timeline["scale"])

    def evaluation(label: str, horizons: dict[str, HorizonEvaluation]) -> ModelEvaluation:
        return ModelEvaluation(model=label, kind=str(model.kind), lags=s, case_lags=need,
                               threshold_m=float(threshold_m), test=[ts.name for ts in series],
                               horizons=horizons)

    # the cases of the offline evaluation, at each horizon from skip_s on, that the online
    # predictor made no prediction for
    missing = {}
    for h, k in scored:
        offline = 0
        for ts in series:
            idx = metrics.case_indices(ts.res.segment, need, k)
            offline += int(np.count_nonzero(ts.res.t[idx - 1] - ts.res.t[0] >= skip_s))
        missing[horizon_key(h)] = offline - horizons_a[horizon_key(h)].vo.cases
    label = name or str(model.kind)
    return AdaptiveEvaluation(
        adapted=evaluation(f"{label} + adapt", horizons_a), plain=evaluation(label, horizons_p),
        timeline=timeline, adaptation=[rep["adaptation"] for rep in replays],
        missing=missing)


def _timeline_of_cases(series: Sequence[TestSeries], replays: list[dict[str, Any]],
                       skip_s: float) -> tuple[dict[str, Any], list[np.ndarray]]:
    """The timeline's per-case columns ``series``, ``t`` and ``scale`` (lists of one array
    per recording), and per recording which of its predicted cases lie ``skip_s`` or more
    into it."""
    timeline: dict[str, Any] = {"series": [], "t": [], "scale": []}
    keep_all = []
    for si, (ts, rep) in enumerate(zip(series, replays, strict=True)):
        t_rel = ts.res.t[rep["idx"] - 1] - ts.res.t[0] if rep["idx"].size else np.zeros(0)
        keep = t_rel >= skip_s
        keep_all.append(keep)
        timeline["series"].append(np.full(int(keep.sum()), si))
        timeline["t"].append(t_rel[keep])
        timeline["scale"].append(rep["scale"][keep])
    return timeline, keep_all


def _score_adaptive_horizon(model: Any, series: Sequence[TestSeries],
                            replays: list[dict[str, Any]], keep_all: list[np.ndarray],
                            h: float, k: int, need: int, dt: float, *, threshold_m: float,
                            skip_s: float, name: str
                            ) -> tuple[HorizonEvaluation, HorizonEvaluation,
                                       dict[str, np.ndarray]]:
    """The online predictions at the horizon h (k steps) and the model not adapting on the
    same cases, both scored against the VO reference; and the timeline's per-case columns
    ``hit``, ``hit_plain``, ``covered`` and ``covered_plain`` (NaN where the case is too
    short for this horizon)."""
    cols: dict[str, list[np.ndarray]] = {"pa": [], "pp": [], "ref": [], "ca": [], "cp": []}
    masks = []
    for ts, rep, keep in zip(series, replays, keep_all, strict=True):
        res = ts.res
        valid_k = np.isin(rep["idx"], metrics.case_indices(res.segment, need, k))
        use = keep & valid_k
        masks.append(valid_k[keep])
        idx = rep["idx"][use]
        if idx.size == 0:
            continue
        plain_pose, plain_cov, _ = rollout_cases(model, res, idx, k, uncertainty="linear")
        ref = reference_path(metrics.windows(res.vel, idx, -1, k + 1), dt)
        cols["pa"].append(rep["pose"][use][:, k - 1, :2])
        cols["ca"].append(rep["cov"][use][:, k - 1])
        cols["pp"].append(plain_pose[:, -1, :2])
        assert plain_cov is not None
        cols["cp"].append(plain_cov[:, -1])
        cols["ref"].append(ref[:, -1, :2])
    if not cols["pa"]:
        raise EvaluationError(f"no case at the {h} s horizon was predicted online "
                              f"{skip_s:g} s or more into a recording")
    pa, pp, ref, ca, cp = (np.concatenate(cols[c]) for c in ("pa", "pp", "ref", "ca", "cp"))
    try:
        res_a, err_a = metrics.score(pa, ref, horizon_s=h, steps=k, threshold_m=threshold_m,
                                     pos_cov=ca)
        res_p, err_p = metrics.score(pp, ref, horizon_s=h, steps=k, threshold_m=threshold_m,
                                     pos_cov=cp)
    except ValueError as exc:
        raise EvaluationError(f"{name or model.kind} (adapting) at {h} s: {exc}") from exc
    # per case of the timeline (NaN where the case is too short for this horizon)
    mask = np.concatenate(masks)
    columns = {}
    for key, value in (("hit", err_a <= threshold_m), ("hit_plain", err_p <= threshold_m),
                       ("covered", metrics.mahalanobis_sq(pa - ref, ca) <= CHI2_2DOF_95),
                       ("covered_plain", metrics.mahalanobis_sq(pp - ref, cp) <= CHI2_2DOF_95)):
        col = np.full(mask.shape[0], np.nan)
        col[mask] = value
        columns[key] = col
    return (HorizonEvaluation(res_a, None, err_a), HorizonEvaluation(res_p, None, err_p),
            columns)
