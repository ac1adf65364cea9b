"""The adaptation's two half-lives and its rows' noise, scored on recordings of another floor.

Usage::

    python benchmarks/adapt_half_life.py [MODEL] [--bags BAG ...]
        [--trained-half-lives 1 3 10 30 120] [--half-lives 300 900 1800]
        [--row-noises 0 0.1 0.3 1 3] [--skip 60]

Each recording is replayed through the online predictor from MODEL, adapting
(``asgp_ros.learning.evaluation.evaluate_adaptive``, the default settings but for the one
half-life varied), causally; printed: success (%) and 95 % ellipse coverage (%) at 1.0, 1.4
and 2.0 s of the cases from ``--skip`` seconds into each recording, adapting and as
trained. First the trained data's half-life is varied (the rows' at its default), then the
rows', then the noise added to each absorbed row (``AdaptConfig.row_noise``, A10 of
``asgp_ros.core.adapt``), each with the others at their defaults; an empty list skips one
(``--half-lives`` with no value).

The defaults of ``asgp_ros.core.adaptive`` were chosen this way on the other floor's
*training* bags of the reproduction's dataset (not its test bags)::

    python benchmarks/adapt_half_life.py docs/reproduction/models/carpet_asgp.npz \\
        --bags DATA/tile/tile_01 DATA/tile/tile_02
    python benchmarks/adapt_half_life.py docs/reproduction/models/tile_asgp.npz \\
        --bags DATA/carpet/carpet_01 DATA/carpet/carpet_02

Without ``--bags``: the committed carpet model on a 20-minute tile recording simulated here
(seed 904, which no dataset of seed 0 uses). About a minute per setting and 20-minute
recording on one core. Prints figures only (no assertions).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
from pathlib import Path

import numpy as np
from adapt_data import MODELS, simulate_tile
from threadpoolctl import threadpool_limits

from asgp_ros.core.adaptive import DEFAULT_HALF_LIFE_S, DEFAULT_TRAINED_HALF_LIFE_S, AdaptSettings
from asgp_ros.core.modelfile import load_model
from asgp_ros.learning.evaluation import TestSeries, evaluate_adaptive
from asgp_ros.learning.training import read_series

HORIZONS_S = (1.0, 1.4, 2.0)
CASE_LAGS = 12  # the reproduction's: every model scored on the same cases


def _positive(text: str) -> float:
    value = float(text)
    if not (np.isfinite(value) and value > 0.0):
        raise argparse.ArgumentTypeError(f"a half-life must be a number > 0, got {text}")
    return value


def _non_negative(text: str) -> float:
    value = float(text)
    if not (np.isfinite(value) and value >= 0.0):
        raise argparse.ArgumentTypeError(f"a row noise must be a number >= 0, got {text}")
    return value


def score(model: object, tests: list[TestSeries], settings: AdaptSettings, skip_s: float
          ) -> str:
    """Success / coverage adapting (and success as trained) from ``skip_s`` s in."""
    ev = evaluate_adaptive(model, tests, HORIZONS_S, settings, case_lags=CASE_LAGS)
    tl = ev.timeline
    late = np.asarray(tl["t"]) >= skip_s
    cells = []
    for h in ev.adapted.horizons:
        hit = np.asarray(tl["hit"][h])[late]
        ok = np.isfinite(hit)
        covered = np.asarray(tl["covered"][h])[late][ok]
        plain = np.asarray(tl["hit_plain"][h])[late][ok]
        cells.append(f"{100 * hit[ok].mean():5.1f} / {100 * covered.mean():5.1f} "
                     f"({100 * plain.mean():5.1f})")
    return "   ".join(cells)


def run(args: argparse.Namespace) -> int:
    model = load_model(args.model)
    tests = [TestSeries(s.name, s.res, s.raw)
             for s in read_series(args.bags, resample_config=model.resample_config)]
    base = AdaptSettings()
    print(f"model {args.model}; {len(tests)} recording(s), cases from {args.skip:g} s in")
    print("success / 95% coverage adapting (success as trained), % at "
          f"{' / '.join(f'{h:g}' for h in HORIZONS_S)} s")
    sweeps = (
        ("trained_half_life", args.trained_half_lives, " s",
         f"trained data's half-life (rows' {base.posterior.half_life_s:g} s):"),
        ("half_life_s", args.half_lives, " s",
         f"rows' half-life (trained data's {base.posterior.trained_half_life:g} s):"),
        ("row_noise", args.row_noises, "  ",
         f"rows' noise / sf2 (default {base.posterior.row_noise:g}):"),
    )
    with threadpool_limits(limits=1):
        for field, values, unit, title in sweeps:
            if values:
                print(title)
            for value in values:
                st = dataclasses.replace(base, posterior=dataclasses.replace(
                    base.posterior, **{field: value}))
                print(f"  {value:7g}{unit}   {score(model, tests, st, args.skip)}",
                      flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model", nargs="?", default=str(MODELS / "carpet_asgp.npz"),
                    help="the trained ASGP (default the committed carpet model)")
    ap.add_argument("--bags", nargs="+", help="recordings of another floor (default: one "
                    "simulated 20-minute tile recording)")
    ap.add_argument("--trained-half-lives", nargs="*", type=_positive,
                    default=[1.0, 3.0, DEFAULT_TRAINED_HALF_LIFE_S, 30.0, 120.0])
    ap.add_argument("--half-lives", nargs="*", type=_positive,
                    default=[DEFAULT_HALF_LIFE_S, 900.0, 1800.0])
    ap.add_argument("--row-noises", nargs="*", type=_non_negative,
                    default=[0.0, 0.1, 0.3, 1.0, 3.0])
    ap.add_argument("--skip", type=float, default=60.0, help="score cases from this many "
                    "seconds into each recording (60)")
    args = ap.parse_args(argv)
    if not (np.isfinite(args.skip) and args.skip >= 0.0):
        ap.error(f"--skip must be >= 0, got {args.skip}")
    if args.bags:
        return run(args)
    with tempfile.TemporaryDirectory() as tmp:
        args.bags = simulate_tile(Path(tmp), ((904, 20.0),))
        return run(args)


if __name__ == "__main__":
    sys.exit(main())
