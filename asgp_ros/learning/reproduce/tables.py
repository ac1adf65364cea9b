"""Tables I-III of a reproduction, and the look-up of one cell of the results.

The results are one dict per trained (train set, model) pair, as the jobs return them
(:mod:`asgp_ros.learning.reproduce.jobs`), with its evaluation on every test set.
"""

from __future__ import annotations

from typing import Any

from asgp_ros.learning.evaluation import HorizonEvaluation, ModelEvaluation
from asgp_ros.learning.reproduce.protocol import TABLE_OF_TEST, TEST_SETS, paper_rate


def _pct(x: float | None) -> float | None:
    return None if x is None else round(100.0 * x, 1)


def _cell(he: HorizonEvaluation, model: str, test: str, train: str, h: str) -> dict[str, Any]:
    """One cell: our success rate, median error and 95% coverage against VO, the success
    rate against ground truth, and the paper's figure beside it (percent, cm)."""
    return {
        "success_rate_pct": _pct(he.vo.success_rate),
        "median_error_cm": round(100 * he.vo.median_error_m, 2),
        "coverage_95_pct": _pct(he.vo.coverage_95),
        "truth_success_rate_pct": _pct(he.truth.success_rate) if he.truth else None,
        "paper_success_rate_pct": paper_rate(model, test, train, h),
    }


def tables(results: list[dict[str, Any]], hk: list[str]) -> dict[str, Any]:
    """Table I (tested on Tile), II (Carpet), III (Hybrid): a row per train set x model, a
    cell per horizon key of ``hk``, and the number of cases per horizon."""
    out: dict[str, Any] = {}
    for test in TEST_SETS:
        rows = []
        cases = {}
        for r in results:
            ev: ModelEvaluation = r["evals"][test]
            row: dict[str, Any] = {"train": r["train"], "model": r["kind"]}
            for h in hk:
                he = ev.horizons[h]
                cases[h] = he.vo.cases
                row[h] = _cell(he, r["kind"], test, r["train"], h)
            rows.append(row)
        out[f"Table {TABLE_OF_TEST[test]}"] = {"test_set": test, "cases": cases, "rows": rows}
    return out


def cell_success_rate(results: list[dict[str, Any]], kind: str, train: str, test: str,
                      h: str) -> float:
    """The success rate (0..1) of the row ``kind`` trained on ``train``, tested on ``test``,
    at the horizon key ``h``."""
    for r in results:
        if r["kind"] == kind and r["train"] == train:
            return float(r["evals"][test].horizons[h].vo.success_rate)
    raise KeyError((kind, train, test, h))


def cell_coverage(results: list[dict[str, Any]], kind: str, train: str, test: str,
                  h: str) -> float | None:
    """The 95% ellipse coverage (0..1) of that cell; None for a model without variance."""
    for r in results:
        if r["kind"] == kind and r["train"] == train:
            value = r["evals"][test].horizons[h].vo.coverage_95
            return None if value is None else float(value)
    raise KeyError((kind, train, test, h))
