"""``asgp evaluate``: the paper's k-step path-prediction success rates of a model on bags."""

from __future__ import annotations

import argparse
import json

from asgp_ros.cli import CommandError
from asgp_ros.cli._argtypes import cli_number, integer
from asgp_ros.cli._bagargs import add_topic_args, read_series_or_fail
from asgp_ros.core.features import LAGS_RANGE
from asgp_ros.core.metrics import HORIZONS_S, THRESHOLD_M, horizon_key
from asgp_ros.core.modelfile import ModelFileError, load_model
from asgp_ros.evaluation import EvaluationError, TestSeries, evaluate_model
from asgp_ros.fileio import SCORES_JSON, atomic_write_text, check_output


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "evaluate",
        help="score a model's k-step path predictions on bags (success rate, median error)",
        description="For every test step with s past and k future samples in one valid "
                    "segment: roll the model out over the recorded future joystick, "
                    "integrate the unicycle model and compare (x, y) at the horizon with the "
                    "path integrated from the recorded VO.",
    )
    p.add_argument("model", metavar="MODEL", help="model file (.npz) from asgp train")
    p.add_argument("bags", nargs="+", metavar="BAG", help="test bags")
    p.add_argument("--horizons", type=cli_number("horizon_s", "s"), nargs="+",
                   default=list(HORIZONS_S), metavar="SECONDS",
                   help=f"prediction horizons ({' '.join(map(horizon_key, HORIZONS_S))})")
    p.add_argument("--threshold", type=cli_number("threshold_m", "m"), default=THRESHOLD_M,
                   help="success threshold on the position error in m (%(default)s)")
    p.add_argument("--case-lags", type=integer(*LAGS_RANGE), default=None,
                   help="past samples a test step needs (default the model's s; set it to "
                        "the largest s of models you compare for identical case sets)")
    p.add_argument("--truth", action="store_true",
                   help="also score against ground truth (simulated bags)")
    p.add_argument("--uncertainty", choices=("linear", "mc", "none"), default=None,
                   help="uncertainty propagation (default linear for asgp, none otherwise)")
    p.add_argument("--json", metavar="OUT", default=None, help="also write the scores as JSON")
    p.add_argument("--force", action="store_true",
                   help="replace an existing evaluation JSON file at --json")
    add_topic_args(p, truth=True)
    p.set_defaults(func=run)


def format_table(result: dict) -> str:
    """Plain-text table of an evaluation's JSON form."""
    head = f"{'horizon':>8} {'steps':>5} {'cases':>7} {'success':>8} {'median':>8} {'p90':>8}"
    has_cov = any(h.get("coverage_95") is not None for h in result["horizons"].values())
    has_truth = any("truth" in h for h in result["horizons"].values())
    if has_cov:
        head += f" {'cov95':>6}"
    if has_truth:
        head += f" {'succ(gt)':>8} {'med(gt)':>8}"
    lines = [head]
    for key, h in result["horizons"].items():
        line = (f"{key + ' s':>8} {h['steps']:>5d} {h['cases']:>7d} "
                f"{100 * h['success_rate']:>7.1f}% {100 * h['median_error_m']:>6.1f}cm "
                f"{100 * h['p90_error_m']:>6.1f}cm")
        if has_cov:
            cov = h.get("coverage_95")
            line += f" {'-' if cov is None else f'{100 * cov:.1f}%':>6}"
        if has_truth:
            t = h["truth"]
            line += f" {100 * t['success_rate']:>7.1f}% {100 * t['median_error_m']:>6.1f}cm"
        lines.append(line)
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    if args.json:
        check_output(args.json, SCORES_JSON, inputs=[args.model, *args.bags],
                     force=args.force, option="--json")
    try:
        model = load_model(args.model)
    except (ModelFileError, OSError, ValueError) as exc:
        raise CommandError(str(exc)) from exc
    series = read_series_or_fail(args.bags, args, resample_config=model.resample_config,
                                 truth=args.truth)
    tests = [TestSeries(s.name, s.res) for s in series]
    try:
        ev = evaluate_model(model, tests, args.horizons, threshold_m=args.threshold,
                            case_lags=args.case_lags, truth=args.truth,
                            uncertainty=args.uncertainty, name=str(args.model))
    except EvaluationError as exc:
        raise CommandError(str(exc)) from exc
    result = ev.to_json()
    print(f"{args.model} ({ev.kind}, s={ev.lags}) on {len(tests)} bag(s), threshold "
          f"{100 * args.threshold:.0f} cm")
    print(format_table(result))
    if args.json:
        atomic_write_text(args.json, json.dumps(result, indent=2) + "\n")
    return 0
