"""``asgp evaluate``: the paper's k-step path-prediction success rates of a model on bags."""

from __future__ import annotations

import argparse
import json
from typing import Any

from asgp_ros.cli import CommandError
from asgp_ros.cli._argtypes import cli_number, integer
from asgp_ros.cli._bagargs import add_topic_args, read_series_or_fail
from asgp_ros.cli.adapt import learnt_from, learnt_text
from asgp_ros.common.fileio import SCORES_JSON, atomic_write_text, bag_inputs, check_output
from asgp_ros.core.adapt import AdaptConfig, AdaptError
from asgp_ros.core.adaptive import (
    DEFAULT_HALF_LIFE_S,
    DEFAULT_TRAINED_FLOOR,
    DEFAULT_TRAINED_HALF_LIFE_S,
    AdaptSettings,
)
from asgp_ros.core.features import LAGS_RANGE
from asgp_ros.core.metrics import HORIZONS_S, THRESHOLD_M, horizon_key
from asgp_ros.core.modelfile import ModelFileError, load_model
from asgp_ros.learning.evaluation import (
    EvaluationError,
    TestSeries,
    evaluate_adaptive,
    evaluate_model,
)
from asgp_ros.learning.training import series_identity
from asgp_ros.recording.bags import same_recording


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
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
    p.add_argument("--adapt", action="store_true",
                   help="adapt an ASGP online while scoring (asgp_ros.core.adaptive): each bag "
                        "is replayed from the trained model through the online predictor, "
                        "causally (a prediction uses only samples stamped before it is made), "
                        "and scored beside the same model not adapting, on the same cases")
    # (no defaults here: given without --adapt they are refused, not ignored)
    p.add_argument("--adapt-half-life", type=cli_number("half_life_s", "s"),
                   help="with --adapt: forgetting half-life of the rows the adapted posterior "
                        f"absorbs ({DEFAULT_HALF_LIFE_S:g} s)")
    p.add_argument("--adapt-trained-half-life", type=cli_number("half_life_s", "s"),
                   help="with --adapt: half-life of the trained data's weight in the adapted "
                        f"posterior ({DEFAULT_TRAINED_HALF_LIFE_S:g} s)")
    p.add_argument("--adapt-floor", type=cli_number("trained_floor", ""),
                   help="with --adapt: weight the trained data decay to, in [0, 1] "
                        f"({DEFAULT_TRAINED_FLOOR:g})")
    p.add_argument("--adapt-constant-mean", action="store_true", default=None,
                   help="with --adapt: the absorbed rows teach the function against a "
                        "constant prior mean, not a correction to the trained function")
    p.add_argument("--skip", type=cli_number("skip_s", "s"),
                   help="with --adapt: score cases from this many seconds into each bag (0)")
    p.add_argument("--json", metavar="OUT", default=None, help="also write the scores as JSON")
    p.add_argument("--force", action="store_true",
                   help="replace an existing evaluation JSON file at --json")
    add_topic_args(p, truth=True)
    p.set_defaults(func=run)


def format_table(result: dict[str, Any]) -> str:
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


#: The options that only mean something with --adapt.
_ADAPT_ONLY = ("skip", "adapt_half_life", "adapt_trained_half_life", "adapt_floor",
               "adapt_constant_mean")


def run(args: argparse.Namespace) -> int:
    if not args.adapt:  # before anything is read: given alone they would be ignored
        given = [f"--{name.replace('_', '-')}" for name in _ADAPT_ONLY
                 if getattr(args, name) is not None]
        if given:
            raise CommandError(f"{', '.join(given)} need{'s' if len(given) == 1 else ''} "
                               "--adapt")
    elif args.truth:
        raise CommandError("--truth is not scored with --adapt")
    elif args.uncertainty not in (None, "linear"):
        raise CommandError("--adapt propagates the uncertainty linearly")
    if args.json:
        check_output(args.json, SCORES_JSON, inputs=[args.model, *bag_inputs(args.bags)],
                     force=args.force, option="--json")
    twice = same_recording(args.bags)
    if twice is not None:  # its cases would count twice
        raise CommandError(f"{twice[1]}: the same recording as {twice[0]}; give each once")
    try:
        model = load_model(args.model)
    except (ModelFileError, OSError, ValueError) as exc:
        raise CommandError(str(exc)) from exc
    series = read_series_or_fail(args.bags, args, resample_config=model.resample_config,
                                 truth=args.truth)
    # scored on the data it learnt, a model looks better than it is: told by the messages
    # read (a repaired or converted copy too), or the storage for an older model file
    for bag, s in zip(args.bags, series, strict=True):
        learnt = learnt_from(model, series_identity(s))
        if learnt is not None:
            print(f"warning: {learnt_text(bag, args.model, learnt)}: its scores are not a "
                  "test on data the model has not seen", flush=True)
    tests = [TestSeries(s.name, s.res, s.raw) for s in series]
    if args.adapt:
        return _run_adaptive(args, model, tests)
    try:
        ev = evaluate_model(model, tests, args.horizons, threshold_m=args.threshold,
                            case_lags=args.case_lags, truth=args.truth,
                            uncertainty=args.uncertainty, name=str(args.model))
    except EvaluationError as exc:
        raise CommandError(str(exc)) from exc
    result = ev.to_json()
    overridden = sum(int(t.res.overridden.sum()) for t in tests)
    print(f"{args.model} ({ev.kind}, s={ev.lags}) on {len(tests)} bag(s), threshold "
          f"{100 * args.threshold:.0f} cm"
          + (f"; {overridden} grid points overridden (not scored)" if overridden else ""))
    print(format_table(result))
    if args.json:
        atomic_write_text(args.json, json.dumps(result, indent=2) + "\n")
    return 0


def _run_adaptive(args: argparse.Namespace, model: object, tests: list[TestSeries]) -> int:
    """``--adapt``: the adapting model and the same model as trained, on the same cases."""
    for name, default in (("skip", 0.0), ("adapt_half_life", DEFAULT_HALF_LIFE_S),
                          ("adapt_trained_half_life", DEFAULT_TRAINED_HALF_LIFE_S),
                          ("adapt_floor", DEFAULT_TRAINED_FLOOR),
                          ("adapt_constant_mean", False)):
        if getattr(args, name) is None:
            setattr(args, name, default)
    try:
        settings = AdaptSettings(AdaptConfig(half_life_s=args.adapt_half_life,
                                             trained_floor=args.adapt_floor,
                                             trained_half_life=args.adapt_trained_half_life,
                                             trained_mean=not args.adapt_constant_mean))
        ev = evaluate_adaptive(model, tests, args.horizons, settings,
                               threshold_m=args.threshold, case_lags=args.case_lags,
                               skip_s=args.skip, name=str(args.model))
    except (AdaptError, EvaluationError) as exc:
        raise CommandError(str(exc)) from exc
    result: dict[str, Any] = ev.to_json()
    print(f"{args.model} adapting online (half-life {args.adapt_half_life:g} s, trained data "
          f"{args.adapt_trained_half_life:g} s, trained floor "
          f"{args.adapt_floor:g}, {'constant' if args.adapt_constant_mean else 'trained'} "
          f"prior mean) on {len(tests)} bag(s), cases from {args.skip:g} s into each"
          f" bag, threshold {100 * args.threshold:.0f} cm")
    print("adapted:")
    print(format_table(result["adapted"]))
    print("as trained (same cases):")
    print(format_table(result["plain"]))
    for ts, state in zip(tests, ev.adaptation, strict=True):
        scales = "/".join(f"{x:.2f}" for x in state["scales"])
        print(f"{ts.name}: {state['rows_absorbed']} steps absorbed, {state['steps_refused']} "
              f"refused, variance scale {scales}, published at the end: {state['published']} "
              f"({state['switches']} change(s) of the published posterior)")
    if any(ev.missing.values()):
        print(" / ".join(str(n) for n in ev.missing.values()) + " case(s) at "
              + " / ".join(f"{h} s" for h in ev.missing) + " of the offline evaluation got "
              "no online prediction (the replayed predictor refused: stale or lost VO at the "
              "live edge)")
    if args.json:
        atomic_write_text(args.json, json.dumps(result, indent=2) + "\n")
    return 0
