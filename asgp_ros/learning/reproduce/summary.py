"""``results.json`` of a reproduction: settings, data, models, Tables I-III, claims, timing."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from asgp_ros.core.baselines import MLP_LEARNING_RATES, MLP_PATIENCE
from asgp_ros.core.metrics import horizon_key
from asgp_ros.core.models import get_kind
from asgp_ros.core.resample import ResampleConfig
from asgp_ros.learning.reproduce.claims import (
    adaptation_summary,
    calibration_summary,
    check_claims,
)
from asgp_ros.learning.reproduce.jobs import auto_options
from asgp_ros.learning.reproduce.protocol import TEST_SETS, Settings, case_lags
from asgp_ros.learning.reproduce.tables import tables
from asgp_ros.learning.training import PAPER_OPTIONS, Series, recorded_s

PAPER_NOTE = ("Our data are simulated (`asgp dataset`: a simulated chair, VO and drivers); "
              "the 'paper' columns are the published figures of Fan et al. (ICRA 2018), "
              "Tables I-III, measured on a real chair (Permobil M300, Fovis VO), beside our "
              "rows of the models the paper ran (its ASGP configuration and its MLP) for the "
              "same test set, train set and horizon. The paper's tables are one per horizon; "
              "here they are rearranged one per test set. Compare trends, not digits: the "
              "chair, the sensors and the drives differ.")


def summarise(results: list[dict[str, Any]], st: Settings, train_paths: dict[str, list[Path]],
              test_paths: dict[str, list[Path]], series: dict[str, Series],
              timing: dict[str, float], command: str | None) -> dict[str, Any]:
    """The results of a run, as written to ``results.json`` (the propagation check and the
    dataset's description are added by the run)."""
    hk = [horizon_key(h) for h in st.horizons]
    table_set = tables(results, hk)
    return {
        "command": command,
        "quick": st.quick,
        "settings": _settings(results, st),
        "train_sets": {k: [Path(p).name for p in v] for k, v in train_paths.items()},
        "test_sets": {k: [Path(p).name for p in v] for k, v in test_paths.items()},
        "data": _data(series),
        "models": [_model(r) for r in results],
        "evaluations": [{"train": r["train"], "kind": r["kind"],
                         "tests": {t: ev.to_json() for t, ev in r["evals"].items()}}
                        for r in results],
        "tables": table_set,
        "claims": check_claims(results, hk, _mean_speeds(test_paths, series)),
        "calibration": calibration_summary(results, hk),
        "adaptation": adaptation_summary(results, hk),
        "paper_note": PAPER_NOTE,
        "timing": timing,
    }


def _settings(results: list[dict[str, Any]], st: Settings) -> dict[str, Any]:
    """The run's settings and the configurations of the fixed rows."""
    return {
        "horizons_s": list(st.horizons), "threshold_m": st.threshold_m,
        "asgp_paper": {"lags": PAPER_OPTIONS.resolved_lags(),
                       "inducing_v": PAPER_OPTIONS.inducing_v,
                       "inducing_w": PAPER_OPTIONS.inducing_w,
                       "coupled": PAPER_OPTIONS.coupled, "max_iter": st.asgp_max_iter},
        "asgp": {"budget_s": auto_options(st).budget_s},
        "mlp": {"lags": get_kind("mlp").default_lags, "hidden": [30, 30, 30], "batch": 100,
                "max_epochs": st.mlp_max_epochs, "early_stopping": "10% validation",
                "patience": MLP_PATIENCE, "learning_rates": list(MLP_LEARNING_RATES)},
        "case_lags": case_lags([r["lags"] for r in results]), "seed": st.seed,
        "jobs": st.jobs, "cpus": os.cpu_count(),
        "vel_stamp": ResampleConfig().vel_stamp,
    }


def _data(series: dict[str, Series]) -> dict[str, Any]:
    """Per bag: minutes (its gaps of more than RECORDING_GAP_S left out, as training's
    duration), valid and stale fractions of its grid points, segments, mean |v|."""
    return {Path(p).name: {"minutes": round(recorded_s(s) / 60, 2),
                           "valid_fraction": round(float(np.mean(s.res.valid)), 4),
                           "stale_fraction": round(float(np.mean(s.res.stale)), 4),
                           "segments": len(s.res.segments()),
                           "mean_abs_v": round(float(np.mean(np.abs(
                               s.res.vel[s.res.valid, 0]))), 3)}
            for p, s in series.items()}


def _model(r: dict[str, Any]) -> dict[str, Any]:
    """One trained model: its file, lags, times and what its meta says of its training."""
    return {"train": r["train"], "kind": r["kind"], "file": r["model_file"],
            "lags": r["lags"],
            "train_seconds": r["train_seconds"], "eval_seconds": r["eval_seconds"],
            "training": r["meta"].get("training", {}),
            "training_data": r["meta"].get("training_data", {}),
            **{k: r["meta"][k] for k in ("selection", "calibration") if k in r["meta"]}}


def _mean_speeds(test_paths: dict[str, list[Path]], series: dict[str, Series]
                 ) -> dict[str, float]:
    """Mean |v| of each test set (the claim "tile easier" quotes it)."""
    return {te: float(np.mean([np.mean(np.abs(series[str(p)].res.vel[series[str(p)].res.valid,
                                                                     0]))
                               for p in test_paths[te]])) for te in TEST_SETS}
