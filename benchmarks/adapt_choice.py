"""How the adaptive predictor chooses the posterior it publishes, compared on recordings.

Usage::

    python benchmarks/adapt_choice.py DATA [--rules test:0.05 test:0.10 test:0.01 leader]
        [--validation] [--skip 60] [--jobs 2]

DATA is a dataset of ``asgp dataset`` (the reproduction's: ``--scale 1 --seed 0``); the
models are the committed ones (``docs/reproduction/models``). Each recording is replayed
through the online predictor from the model, adapting with the default settings
(``asgp_ros.learning.evaluation.evaluate_adaptive``, causally), once per rule:

* ``test:LEVEL``: :class:`asgp_ros.core.adaptive.PosteriorChoice` at that level (the
  default, 0.05, is what the package ships);
* ``leader``: the rule it replaced: publish the other posterior when its recent mean
  squared k-step error (exponentially weighted, the same half-life) is 5 % smaller.

Cells: the nine of the reproduction (train Tile / Carpet / Both x test Tile / Carpet /
Hybrid, the test bags), or with ``--validation`` the two the adaptation's half-lives were
chosen on (the carpet model on tile_01-02, the tile model on carpet_01-02: training bags
of the other floor). Printed per cell and rule: success (%) at 1.0 / 1.4 / 2.0 s of the
cases from ``--skip`` seconds into each recording, adapting, and the model as trained on
the same cases. About 20 s per cell and rule on one core. Figures only (no assertions).
"""

from __future__ import annotations

import argparse
import math
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
MODELS = REPO / "docs" / "reproduction" / "models"
TEST_BAGS = {"Tile": ["tile/tile_07", "tile/tile_08"],
             "Carpet": ["carpet/carpet_07", "carpet/carpet_08"],
             "Hybrid": ["hybrid/hybrid_01", "hybrid/hybrid_02"]}
VALIDATION = [("Carpet", "tile (tile_01-02)", ["tile/tile_01", "tile/tile_02"]),
              ("Tile", "carpet (carpet_01-02)", ["carpet/carpet_01", "carpet/carpet_02"])]
LEADER_MARGIN = 0.05
HORIZONS = (1.0, 1.4, 2.0)


def _use_leader() -> None:
    """Replace the test by the earlier follow-the-leader rule (in this process only)."""
    from asgp_ros.core import adaptive

    check_case = adaptive.ModelAdapter._check_case

    def leader(self: Any, speed: float, snap: Any, out: Any, cfg: Any) -> None:
        select = self.settings.select
        object.__setattr__(self.settings, "select", False)  # the recent errors, no choice
        try:
            check_case(self, speed, snap, out, cfg)
        finally:
            object.__setattr__(self.settings, "select", select)
        if select:
            other = 1 - self._published
            if self._errors[other] < (1.0 - LEADER_MARGIN) * self._errors[self._published]:
                self._published = other
                self._choice.switches += 1  # counted where the diagnostics read it

    adaptive.ModelAdapter._check_case = leader  # type: ignore[method-assign]


def _cell(job: tuple[str, str, str, list[str], str, float]) -> tuple[Any, ...]:
    rule, train, test, bags, data, skip = job
    from asgp_ros.core import adaptive
    from asgp_ros.core.modelfile import load_model
    from asgp_ros.learning.evaluation import TestSeries, evaluate_adaptive
    from asgp_ros.learning.training import read_series

    if rule == "leader":
        _use_leader()
    else:
        adaptive.SELECT_LEVEL = float(rule.split(":", 1)[1])
    model = load_model(MODELS / f"{train.lower()}_asgp.npz")
    series = read_series([str(Path(data) / b) for b in bags],
                         resample_config=model.resample_config)
    ev = evaluate_adaptive(model, [TestSeries(s.name, s.res, s.raw) for s in series],
                           HORIZONS, case_lags=10, skip_s=skip)
    rate = [[100.0 * h.vo.success_rate for h in e.horizons.values()]
            for e in (ev.adapted, ev.plain)]
    return rule, train, test, rate[0], rate[1], [a["switches"] for a in ev.adaptation]


def _rule(text: str) -> str:
    if text == "leader":
        return text
    kind, _, level = text.partition(":")
    try:
        ok = kind == "test" and 0.0 < float(level) < 1.0 and math.isfinite(float(level))
    except ValueError:
        ok = False
    if not ok:
        raise argparse.ArgumentTypeError(f"a rule is test:LEVEL (0 < LEVEL < 1) or leader, "
                                         f"got {text!r}")
    return text


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", help="a dataset of asgp dataset (tile/, carpet/, hybrid/)")
    ap.add_argument("--rules", nargs="+", type=_rule,
                    default=["test:0.05", "test:0.10", "test:0.01", "leader"])
    ap.add_argument("--validation", action="store_true",
                    help="the two cells the half-lives were chosen on, not the nine")
    ap.add_argument("--skip", type=float, default=60.0)
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args()
    if args.validation:
        cells = VALIDATION
    else:
        cells = [(tr, te, TEST_BAGS[te]) for tr in ("Tile", "Carpet", "Both")
                 for te in ("Tile", "Carpet", "Hybrid")]
    jobs = [(rule, tr, te, bags, args.data, args.skip) for rule in args.rules
            for tr, te, bags in cells]
    with ProcessPoolExecutor(max(1, args.jobs)) as pool:
        results = list(pool.map(_cell, jobs))
    print(f"success (%) at {' / '.join(f'{h:g}' for h in HORIZONS)} s from {args.skip:g} s "
          "into each recording: adapting | as trained; changes of the published posterior "
          "per recording")
    for rule, train, test, adapted, plain, switches in results:
        a = " / ".join(f"{x:5.1f}" for x in adapted)
        p = " / ".join(f"{x:5.1f}" for x in plain)
        print(f"{rule:>10}  {train:>6} -> {test:<22} {a} | {p}  "
              f"(2.0 s {np.subtract(adapted, plain)[-1]:+.2f}; switches {switches})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
