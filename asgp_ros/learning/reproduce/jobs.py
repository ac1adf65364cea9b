"""The jobs of a reproduction: read a bag, train a model, evaluate it, check the propagation.

Each job is ``job(context, task)`` with the run's read-only :class:`JobContext`, so that it
runs alike inline or in a worker process (:func:`asgp_ros.learning.reproduce.pool.pool_map`);
a job's errors cross the pool as :class:`~asgp_ros.learning.reproduce.protocol.ReproduceError`
with a plain message.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from asgp_ros.core import metrics
from asgp_ros.core.metrics import CHI2_2DOF_95, horizon_key
from asgp_ros.core.modelfile import load_model, save_model
from asgp_ros.core.rollout import Uncertainty, rollout
from asgp_ros.learning.evaluation import (
    AdaptiveEvaluation,
    TestSeries,
    evaluate_adaptive,
    evaluate_model,
    reference_path,
)
from asgp_ros.learning.reproduce.protocol import (
    ADAPT_FROM_S,
    ADAPT_SETTINGS,
    MODELS,
    QUICK_ADAPT_FROM_S,
    Compared,
    ReproduceError,
    Settings,
)
from asgp_ros.learning.training import AutoOptions, Series, read_series, train, train_auto
from asgp_ros.recording.bags import bag_topics

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class JobContext:
    """The read-only inputs of the training, evaluation and propagation jobs.

    Built once by :func:`asgp_ros.learning.reproduce.run.run` and passed to every job as
    its first argument. In a worker pool it reaches each worker once, through the pool's
    initializer (the pool forks, so the resampled series are shared with the workers, not
    copied per job).

    Attributes:
        settings: budgets, horizons, threshold, seed, workers.
        series: every bag of the dataset, resampled, by path.
        train_sets, test_sets: bag paths by set name.
        case_lags: past samples every test case has (the largest s of the trained
            models; 0 while they are being trained).
        model_dir: where the model files are written.
    """

    settings: Settings
    series: Mapping[str, Series]
    train_sets: Mapping[str, tuple[str, ...]]
    test_sets: Mapping[str, tuple[str, ...]]
    case_lags: int
    model_dir: Path


def read_one(topics: Mapping[str, str], path: str) -> Series:
    """One bag on the grid; ``topics`` by role as in
    :func:`asgp_ros.learning.dataset.manifest_topics`."""
    truth: str | None = topics["truth"]
    if truth not in bag_topics(path):
        truth = None  # recorded on a real chair: no ground truth
    return read_series([path], joy_topic=topics["joy"], twist_topic=topics["twist"],
                       truth_topic=truth)[0]


def train_job(context: JobContext, task: tuple[str, str]) -> dict[str, Any]:
    """Train one (train set, model) pair and save its model file."""
    train_name, name = task
    try:
        return _train_one(context, train_name, MODELS[name])
    except ValueError as exc:  # training errors
        raise _job_error(MODELS[name], train_name, exc) from None


def _job_error(model: Compared, train_name: str, exc: ValueError) -> ReproduceError:
    """A job's error as it crosses the pool: a plain message naming the row and the train
    set."""
    return ReproduceError(f"{model.label} on the {train_name} train set: {exc}")


def model_path(context: JobContext, train_name: str, name: str) -> Path:
    """The model file of the row ``name`` trained on ``train_name``."""
    model = MODELS[name]
    file_of = model.kind if model.adapts else name  # the adapting row reads the ASGP's file
    return context.model_dir / f"{train_name.lower()}_{file_of}.npz"


def _train_one(context: JobContext, train_name: str, model: Compared) -> dict[str, Any]:
    st = context.settings
    t0 = time.perf_counter()
    lines: list[str] = []

    def progress(channel: str, msg: str) -> None:
        lines.append(f"{channel}: {msg}")
        log.info("[%s %s %s] %s", train_name, model.name, channel, msg)

    series = [context.series[p] for p in context.train_sets[train_name]]
    if model.automatic:
        trained = train_auto(series, auto_options(st), progress=progress)
    else:
        trained = train(series, st.options(model), progress=progress)
    path = model_path(context, train_name, model.name)
    save_model(path, trained)
    return {"train": train_name, "kind": model.name, "model_file": path.name,
            "lags": trained.lags, "train_seconds": round(time.perf_counter() - t0, 2),
            "log": lines}


def auto_options(st: Settings) -> AutoOptions:
    """The automatic configuration's options in this run (its seed, its budget)."""
    if st.auto_budget_s is None:
        return AutoOptions(seed=st.seed)
    return AutoOptions(seed=st.seed, budget_s=st.auto_budget_s)


def evaluate_job(context: JobContext, task: tuple[str, str]) -> dict[str, Any]:
    """Evaluate one trained (train set, model) pair, as its file holds it, on every test
    set."""
    train_name, name = task
    try:
        return _evaluate_one(context, train_name, MODELS[name])
    except ValueError as exc:  # evaluation errors
        raise _job_error(MODELS[name], train_name, exc) from None


def _evaluate_one(context: JobContext, train_name: str, model: Compared) -> dict[str, Any]:
    st = context.settings
    t0 = time.perf_counter()
    loaded = load_model(model_path(context, train_name, model.name))
    if model.adapts:
        return _evaluate_adapting(context, train_name, model, loaded, t0)
    evals = {}
    for test_name, paths in context.test_sets.items():
        tests = [TestSeries(p, context.series[p].res) for p in paths]
        truth = all(t.has_truth for t in tests)
        evals[test_name] = evaluate_model(
            loaded, tests, st.horizons, threshold_m=st.threshold_m,
            case_lags=context.case_lags, truth=truth, n_examples=3,
            name=f"{model.label} ({train_name})")
    return {"eval_seconds": round(time.perf_counter() - t0, 2), "meta": loaded.meta,
            "evals": evals}


def _evaluate_adapting(context: JobContext, train_name: str, model: Compared, loaded: Any,
                       t0: float) -> dict[str, Any]:
    """The adapting row: each test bag replayed from the trained model through the online
    predictor (``ADAPT_SETTINGS``, the defaults), causally, on the
    common cases; and the scores from ``ADAPT_FROM_S`` into each bag beside the model not
    adapting, on the same cases (issue 12's targets)."""
    st = context.settings
    skip = QUICK_ADAPT_FROM_S if st.quick else ADAPT_FROM_S
    evals, late, timelines = {}, {}, {}
    for test_name, paths in context.test_sets.items():
        tests = [TestSeries(p, context.series[p].res, context.series[p].raw) for p in paths]
        ev = evaluate_adaptive(loaded, tests, st.horizons, ADAPT_SETTINGS,
                               threshold_m=st.threshold_m,
                               case_lags=context.case_lags,
                               name=f"{model.label} ({train_name})")
        evals[test_name] = ev.adapted
        late[test_name] = _late_scores(ev, skip)
        timelines[test_name] = _timeline_arrays(ev)
    return {"eval_seconds": round(time.perf_counter() - t0, 2), "meta": loaded.meta,
            "evals": evals, "adaptation": late, "adaptation_timeline": timelines}


#: The per-case columns of an adaptive evaluation's timeline, adapting and not.
_TIMELINE_KEYS = ("hit", "hit_plain", "covered", "covered_plain")


def _late_scores(ev: AdaptiveEvaluation, skip: float) -> dict[str, Any]:
    """Success and 95% coverage, adapting and not, of the cases from ``skip`` seconds into
    each bag (issue 12's targets), with the adapter's final state."""
    tl = ev.timeline
    after = np.asarray(tl["t"]) >= skip
    horizons = {}
    for h in ev.adapted.horizons:
        cols = {key: np.asarray(tl[key][h])[after] for key in _TIMELINE_KEYS}
        ok = np.isfinite(cols["hit"])
        horizons[h] = {"cases": int(ok.sum()),
                       **{key: float(np.mean(v[ok])) if ok.any() else None
                          for key, v in cols.items()}}
    return {"from_s": skip, "horizons": horizons, "missing": ev.missing,
            "state": ev.adaptation}


def _timeline_arrays(ev: AdaptiveEvaluation) -> dict[str, np.ndarray]:
    """The timeline for the adaptation figure: ``t`` and ``<column>@<horizon>`` arrays."""
    tl = ev.timeline
    return {"t": np.asarray(tl["t"]),
            **{f"{key}@{h}": np.asarray(tl[key][h])
               for key in _TIMELINE_KEYS for h in ev.adapted.horizons}}


def propagation_job(context: JobContext, task: tuple[str, str]) -> dict[str, Any]:
    """Coverage of the 95% ellipses of one Both-trained ASGP row on a random subset of one
    test set: linearised propagation (as in the tables), Monte Carlo (the reference), and
    linearised without the observation noise (latent variance only); the model's variance
    calibration, if it has one, applies to all three."""
    name, test = task
    st = context.settings
    model = load_model(model_path(context, "Both", name))
    n_cases, n_samples = (100, 200) if st.quick else (300, 500)
    rng = np.random.default_rng(st.seed)
    s = model.lags
    out: dict[str, Any] = {"model": name, "test": test, "train": "Both", "cases": n_cases,
                           "mc_samples": n_samples}
    for h in (st.horizons[0], st.horizons[-1]):
        k = metrics.horizon_steps([h], model.rate_hz)[0]
        pool = [(p, i) for p in context.test_sets[test]
                for i in metrics.case_indices(context.series[p].res.segment,
                                              context.case_lags, k)]
        pick = rng.choice(len(pool), size=min(n_cases, len(pool)), replace=False)
        coverage = {}
        variants: tuple[tuple[str, Uncertainty, bool], ...] = (
            ("linear", "linear", True), ("mc", "mc", True),
            ("linear_latent_only", "linear", False))
        for label, unc, noise in variants:
            hits = []
            for path in sorted({pool[j][0] for j in pick}):
                res = context.series[path].res
                idx = np.array([pool[j][1] for j in pick if pool[j][0] == path])
                r = rollout(model, metrics.windows(res.joy, idx, -s, s),
                            metrics.windows(res.vel, idx, -s, s),
                            metrics.windows(res.joy, idx, 0, k), uncertainty=unc,
                            n_samples=n_samples, rng=st.seed, include_noise=noise)
                ref = reference_path(metrics.windows(res.vel, idx, -1, k + 1),
                                     model.dt)[:, -1, :2]
                d2 = metrics.mahalanobis_sq(r.pose[:, -1, :2] - ref, r.pos_cov[:, -1])
                hits.append(d2 <= CHI2_2DOF_95)
            coverage[label] = float(np.mean(np.concatenate(hits)))
        out[horizon_key(h)] = coverage
    return out


def schedule(tasks: list[tuple[str, str]]) -> list[tuple[str, str]]:
    """Longest jobs first, so that the workers finish together: the automatic
    configuration, the GPs, then by lags."""
    names = list(MODELS)

    def cost(task: tuple[str, str]) -> tuple[bool, bool, int, int]:
        m = MODELS[task[1]]
        lags = m.options.resolved_lags() if m.options is not None else 0
        return (not m.automatic, not m.model_kind.probabilistic, -lags,
                names.index(m.name))

    return sorted(tasks, key=cost)
