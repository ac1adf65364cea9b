"""``asgp reproduce``: the steps of a reproduction in order, written as one report directory.

:func:`run` checks the output, finds (or with ``--quick`` builds) the dataset, reads every
bag onto the grid, trains every compared model, evaluates them all on the same cases, runs
the propagation check, and writes ``results.json``, ``tables.json``, ``report.md``, the
figures and the model files into a temporary directory that replaces the output only when
complete.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from types import MappingProxyType
from typing import Any

from asgp_ros.common.fileio import (
    REPORT_DIR,
    OutputError,
    atomic_path,
    check_output,
    naming,
    read_marker,
    write_marker,
)
from asgp_ros.learning.dataset import BuiltDataset, manifest_topics
from asgp_ros.learning.dataset import Progress as DatasetProgress
from asgp_ros.learning.reproduce.data import (
    build_quick_dataset,
    dataset_options,
    discover,
    discover_safe,
    read_manifest,
    split,
    unfinished_dataset,
)
from asgp_ros.learning.reproduce.jobs import (
    JobContext,
    evaluate_job,
    propagation_job,
    read_one,
    schedule,
    train_job,
)
from asgp_ros.learning.reproduce.plots import write_plots
from asgp_ros.learning.reproduce.pool import pool_map
from asgp_ros.learning.reproduce.protocol import (
    ASGP_ROWS,
    MODELS,
    TEST_SETS,
    TRAIN_SETS,
    ReproduceError,
    Settings,
    case_lags,
)
from asgp_ros.learning.reproduce.report import markdown
from asgp_ros.learning.reproduce.summary import summarise
from asgp_ros.learning.training import Series, series_identity
from asgp_ros.recording.bags import (
    BagError,
    repeated_recording,
    repeated_text,
    same_recording,
)

log = logging.getLogger(__name__)


def run(data: str | os.PathLike[str], out: str | os.PathLike[str], *, quick: bool = False,
        jobs: int | None = None, seed: int = 0, command: str | None = None,
        force: bool = False, dataset_progress: DatasetProgress | None = None,
        dataset_built: Callable[[BuiltDataset], None] | None = None) -> dict[str, Any]:
    """Run the protocol on the dataset in ``data``; write the report directory ``out``.

    ``out`` is checked first (:func:`asgp_ros.common.fileio.check_output`): it must not be,
    hold or lie inside ``data``, and an existing report directory (one carrying the report's
    marker file) is replaced only with ``force``; anything else there is refused.
    Everything is written into a temporary directory that replaces ``out`` only when
    complete. With ``quick``, a small dataset is simulated into ``data`` if it has no bags
    (``dataset_progress`` follows it, ``dataset_built`` is told the result), and training
    budgets are reduced (stated in the report). ``command`` is the command line quoted in
    the report.

    Returns:
        The results dictionary also written as ``results.json``.
    """
    try:
        check_output(out, REPORT_DIR, inputs=[data], force=force)
    except OutputError as exc:
        raise ReproduceError(str(exc)) from exc
    t_start = time.perf_counter()
    st = Settings.for_mode(quick, jobs, seed)
    data = Path(data)
    # a new dataset, or one an interrupted run began (its marker, and no manifest or one
    # saying it is unfinished): --quick resumes it, else it is refused
    unfinished = data.is_dir() and read_marker(data) == "dataset" and (
        not (data / "manifest.json").exists() or unfinished_dataset(read_manifest(data)))
    if quick and (not data.is_dir() or not any(discover_safe(data).values()) or unfinished):
        built = build_quick_dataset(data, progress=dataset_progress)
        if dataset_built is not None:
            dataset_built(built)
    elif unfinished:
        raise ReproduceError(f"{data} is a dataset whose `asgp dataset` run did not finish"
                             f"{dataset_options(read_manifest(data), data)}: run it again to "
                             "finish it (the bags made are kept)")
    manifest = read_manifest(data)
    found = discover(data)
    twice = same_recording([p for bags in found.values() for p in bags])
    if twice is not None:  # trained twice on it, or tested on data a model was trained on
        raise ReproduceError(f"{twice[1]} is the same recording as {twice[0]} (a copy, or a "
                             "link): a dataset holds each recording once")
    train_paths, test_paths = split(found, manifest)
    t_data = time.perf_counter()
    series = _read_dataset(manifest, train_paths, test_paths, st.jobs)
    again = repeated_recording([(name, series_identity(s)) for name, s in series.items()])
    if again is not None:  # a repaired or converted copy, told by its messages
        raise ReproduceError(f"{repeated_text(again, advice=False)}: a dataset holds each "
                             "recording once")
    t_read = time.perf_counter()

    with atomic_path(out, directory=True, replace=force) as tmp:
        tmp.mkdir(parents=True)
        write_marker(tmp, "reproduce-report")
        (tmp / "models").mkdir()
        context = JobContext(
            settings=st, series=MappingProxyType(series),
            train_sets=MappingProxyType({k: tuple(str(p) for p in v)
                                         for k, v in train_paths.items()}),
            test_sets=MappingProxyType({k: tuple(str(p) for p in v)
                                        for k, v in test_paths.items()}),
            case_lags=0, model_dir=tmp / "models")
        context, results = _train_and_evaluate(context)
        t_models = time.perf_counter()
        names = list(MODELS)
        results.sort(key=lambda r: (TRAIN_SETS.index(r["train"]), names.index(r["kind"])))
        timing = {
            "dataset_s": round(t_data - t_start, 1),
            "read_s": round(t_read - t_data, 1),
            "train_and_evaluate_s": round(t_models - t_read, 1),
        }
        summary = summarise(results, st, train_paths, test_paths, series, timing, command)
        summary["dataset"] = {k: (manifest or {}).get(k) for k in ("format", "seed", "scale",
                                                                   "bag_minutes", "storage")}
        log.info("uncertainty propagation check (linear vs Monte Carlo)")
        summary["calibration"]["propagation_check"] = pool_map(
            propagation_job, context, [(name, test) for name in ASGP_ROWS
                                       for test in TEST_SETS], st.jobs)
        write_plots(tmp, results, series)
        timing["report_s"] = round(time.perf_counter() - t_models, 1)
        timing["total_s"] = round(time.perf_counter() - t_start, 1)
        summary["timing"] = timing
        _write_results(tmp, summary)
    return summary


def _read_dataset(manifest: dict[str, Any] | None, train_paths: dict[str, list[Path]],
                  test_paths: dict[str, list[Path]], jobs: int) -> dict[str, Series]:
    """Every bag of the train and test sets on the grid, by path (on ``jobs`` workers)."""
    all_paths = sorted({str(p) for lst in (*train_paths.values(), *test_paths.values())
                        for p in lst})
    log.info("reading %d bags", len(all_paths))
    try:
        read = pool_map(read_one, manifest_topics(manifest), all_paths, jobs)
    except (BagError, ValueError, OSError, KeyError) as exc:
        raise ReproduceError(f"reading the dataset failed: {exc}") from exc
    return dict(zip(all_paths, read, strict=True))


def _train_and_evaluate(context: JobContext) -> tuple[JobContext, list[dict[str, Any]]]:
    """Train every (train set, model) pair, then evaluate them all on the same cases (those
    with the largest s of the trained models, set in the context returned); the adapting
    rows score the automatic ASGP's files. One result per pair, in the order of the tasks."""
    st = context.settings
    tasks = schedule([(t, m) for t in TRAIN_SETS for m in MODELS
                      if not MODELS[m].adapts])
    log.info("training %d models on %d worker(s)", len(tasks), st.jobs)
    trained = pool_map(train_job, context, tasks, st.jobs, one_thread=True)
    # every model scored on the same cases: those with the largest s of all the models
    context = replace(context, case_lags=case_lags([r["lags"] for r in trained]))
    # the adapting rows score the automatic ASGP's files
    for t in TRAIN_SETS:
        for m in MODELS.values():
            if m.adapts:
                base = next(r for r in trained if r["train"] == t and r["kind"] == m.kind)
                tasks.append((t, m.name))
                trained.append({**base, "kind": m.name, "train_seconds": 0.0, "log": []})
    log.info("evaluating them on %d case lags", context.case_lags)
    results = [{**r, **ev} for r, ev in zip(
        trained, pool_map(evaluate_job, context, tasks, st.jobs, one_thread=True),
        strict=True)]
    return context, results


def _write_results(tmp: Path, summary: dict[str, Any]) -> None:
    """results.json, tables.json and report.md into the report directory being written."""
    for name, text in (("results.json", json.dumps(summary, indent=2) + "\n"),
                       ("tables.json", json.dumps(summary["tables"], indent=2) + "\n"),
                       ("report.md", markdown(summary))):
        with naming(tmp / name):  # (a full disk named no file)
            (tmp / name).write_text(text)
