"""``asgp train``: fit a motion predictor (ASGP or a baseline) on bags, save the model file."""

from __future__ import annotations

import argparse
import dataclasses

from asgp_ros.cli import CommandError
from asgp_ros.cli._argtypes import cli_integer, integer, number
from asgp_ros.cli._bagargs import add_topic_args, read_series_or_fail
from asgp_ros.common.fileio import MODEL_FILE, bag_inputs, check_output
from asgp_ros.core.features import LAGS_RANGE
from asgp_ros.core.metrics import horizon_key
from asgp_ros.core.modelfile import ModelFileError, save_model
from asgp_ros.core.models import MotionModel, get_kind, trainable_kinds
from asgp_ros.core.resample import RESAMPLE_RANGES, VEL_STAMPS, ResampleConfig
from asgp_ros.learning.training import (
    BUDGET_RANGE_S,
    PAPER_OPTIONS,
    AutoOptions,
    TrainingError,
    TrainOptions,
    train,
    train_auto,
)
from asgp_ros.recording.bags import same_recording


def _default_lags_help() -> str:
    """The kinds' default lags for --help: "asgp 4, mlp 10, others 1"."""
    lags = {name: get_kind(name).default_lags for name in trainable_kinds()}
    special = [f"{name} {s}" for name, s in lags.items() if s != 1]
    return ", ".join(special + (["others 1"] if len(special) < len(lags) else []))


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "train",
        help="train a motion predictor on bags and save the model file",
        description="Resample the bags to the model grid (5 Hz), build the autoregressive "
                    "features and fit one regressor per channel (v, omega). With no model "
                    "flags the ASGP chooses its own configuration (lags, coupling, "
                    "pseudo-inputs) by the k-step success on the last 20% of each bag, "
                    "and calibrates its variance there; --paper trains the paper's "
                    "configuration instead, and --lags/--coupled/--inducing-* pin values. "
                    "Progress goes to stdout; stderr carries only an error.",
    )
    p.add_argument("bags", nargs="+", metavar="BAG", help="training bags (ROS 1 or ROS 2)")
    p.add_argument("--out", required=True, metavar="MODEL", help="model file to write (.npz)")
    p.add_argument("--force", action="store_true",
                   help="replace an existing model file at --out (nothing else is replaced)")
    p.add_argument("--model", choices=trainable_kinds(), default="asgp",
                   help="model kind (%(default)s)")
    p.add_argument("--paper", action="store_true",
                   help="the paper's ASGP exactly: s = 4, M = 20 (v) / 40 (omega), one axis "
                        "per channel, all data, no selection and no calibration")
    p.add_argument("--lags", type=integer(*LAGS_RANGE), default=None,
                   help=f"s, past samples per input (asgp: chosen; {_default_lags_help()})")
    p.add_argument("--inducing-v", type=cli_integer("inducing"), default=None,
                   help="pseudo-inputs for v (asgp: chosen)")
    p.add_argument("--inducing-w", type=cli_integer("inducing"), default=None,
                   help="pseudo-inputs for omega (asgp: chosen)")
    p.add_argument("--coupled", action=argparse.BooleanOptionalAction, default=None,
                   help="feed both joystick axes and both velocities to each channel "
                        "(asgp: chosen)")
    p.add_argument("--budget-s", type=number(*BUDGET_RANGE_S, unit="s"), default=180.0,
                   help="time the automatic configuration is planned for (%(default)s s "
                        "fits 120 minutes of data on 2 cores); the plan is fixed before "
                        "fitting, so the choice is deterministic for a seed; it has floors "
                        "(1000 rows, 20 iterations, two sizes of M), so a budget of a few "
                        "seconds is overrun, and said")
    p.add_argument("--no-calibration", action="store_true",
                   help="asgp: do not calibrate the variance on the held-out data")
    p.add_argument("--max-iter", type=cli_integer("max_iter"), default=200,
                   help="L-BFGS-B iterations (asgp) or epochs (mlp) (%(default)s)")
    p.add_argument("--seed", type=cli_integer("seed"), default=0,
                   help="random seed (%(default)s)")
    p.add_argument("--rate", type=number(*RESAMPLE_RANGES["rate_hz"], unit="Hz"),
                   default=None, help="grid rate in Hz (default 5)")
    p.add_argument("--vo-stamp", choices=VEL_STAMPS, default="midpoint",
                   help="the time a VO twist describes: the middle of the interval from "
                        "the previous one (%(default)s: a frame-to-frame VO's mean "
                        "velocity), or its own stamp (frame)")
    add_topic_args(p)
    p.set_defaults(func=run)


def _options(args: argparse.Namespace) -> TrainOptions | AutoOptions:
    """What to train: the paper's ASGP, an automatic ASGP, or a kind with its options."""
    pins = [flag for flag, value in (("--lags", args.lags), ("--coupled", args.coupled),
                                     ("--inducing-v", args.inducing_v),
                                     ("--inducing-w", args.inducing_w)) if value is not None]
    if args.paper:
        if args.model != "asgp" or pins or args.no_calibration:
            raise CommandError("--paper is the paper's ASGP: it takes no --model, "
                               f"{', '.join(pins) or '--no-calibration'}")
        return dataclasses.replace(PAPER_OPTIONS, max_iter=args.max_iter, seed=args.seed)
    if args.model == "asgp":
        return AutoOptions(seed=args.seed, budget_s=args.budget_s, lags=args.lags,
                           coupled=args.coupled, inducing_v=args.inducing_v,
                           inducing_w=args.inducing_w, max_iter=args.max_iter,
                           calibrate=not args.no_calibration)
    ignored = [p for p in pins if p != "--lags"] + (["--no-calibration"]
                                                   if args.no_calibration else [])
    if ignored:
        raise CommandError(f"{', '.join(ignored)} only apply to --model asgp")
    return TrainOptions(kind=args.model, lags=args.lags, max_iter=args.max_iter,
                        seed=args.seed)


def selection_table(model: MotionModel) -> list[str]:
    """The candidates of an automatic configuration and their held-out scores, one line
    each (empty for a model that was not configured automatically)."""
    sel = model.meta.get("selection")
    if not isinstance(sel, dict):
        return []
    hs = [horizon_key(h) for h in sel.get("horizons_s", [])]
    lines = [f"{'stage':<9} {'s':>3} {'inputs':<8} {'M v/w':>7}  "
             + "  ".join(f"{h + ' s':>7}" for h in hs) + f"  {'mean':>6}  {'fit s':>6}"]
    chosen = sel.get("chosen")
    for row in sel.get("candidates", []):
        c = row["candidate"]
        if c is None:
            lines.append(f"{row['stage']:<9} {row['skipped']}")
            continue
        head = (f"{row['stage']:<9} {c['lags']:>3} {'coupled' if c['coupled'] else 'per-axis':<8} "
                f"{c['inducing'][0]:>3}/{c['inducing'][1]:<3}")
        if "skipped" in row:
            lines.append(f"{head}  skipped: {row['skipped']}")
            continue
        mark = "  <- chosen" if c == chosen else ""
        lines.append(head + "  " + "  ".join(
            f"{100 * row['horizons'][h]['success']:6.1f}%" for h in hs)
            + f"  {100 * row['score']:5.1f}%  {row['seconds']:6.1f}{mark}")
    return lines


def run(args: argparse.Namespace) -> int:
    check_output(args.out, MODEL_FILE, inputs=bag_inputs(args.bags), force=args.force)
    twice = same_recording(args.bags)
    if twice is not None:  # its rows would count twice
        raise CommandError(f"{twice[1]}: the same recording as {twice[0]}; give each once")
    try:
        rc = ResampleConfig(vel_stamp=args.vo_stamp) if args.rate is None else \
            ResampleConfig(rate_hz=args.rate, vel_stamp=args.vo_stamp)
        opts = _options(args)
        opts.validate()
    except (TrainingError, ValueError) as exc:
        raise CommandError(str(exc)) from exc
    series = read_series_or_fail(args.bags, args, resample_config=rc)
    label = "asgp auto" if isinstance(opts, AutoOptions) else ("asgp paper" if args.paper
                                                               else args.model)

    def progress(channel: str, message: str) -> None:
        print(f"[{label} {channel}] {message}", flush=True)

    try:
        if isinstance(opts, AutoOptions):
            model = train_auto(series, opts, resample_config=rc, progress=progress)
        else:
            model = train(series, opts, resample_config=rc, progress=progress)
    except (TrainingError, ValueError) as exc:
        raise CommandError(str(exc)) from exc
    try:
        save_model(args.out, model)
    except ModelFileError as exc:  # a model the loader would refuse is not written
        raise CommandError(f"the trained model is not saved: {exc}") from exc
    for line in selection_table(model):
        print(line)
    summary = model.meta["training_data"]
    fc = model.feature_config
    print(f"wrote {args.out}: {model.kind}, s={fc.lags}"
          f"{', coupled' if fc.coupled else ''}, {summary['training_rows']} rows from "
          f"{len(summary['bags'])} bag(s), {summary['segments']} segments, stale "
          f"{100 * summary['stale_fraction']:.1f}%"
          + (f", {summary['overridden_samples']} grid points overridden (not trained on)"
             if summary.get("overridden_samples") else ""))
    cal = model.meta.get("calibration", {})
    if cal.get("fitted") and not cal.get("applied", True):
        print(f"calibration {cal['reason']}")
    elif cal.get("fitted"):
        # the pooled figure after the map is the map's own fit (95.0 % by construction):
        # what it says of data it was not fitted on is the cross-validated one per horizon
        cv = "cross-validated" if cal.get("cross_validated") else "in-sample"
        per_h = [f"{h} s {100 * c['raw']:.1f}% -> {100 * c['calibrated']:.1f}%"
                 for h, c in (cal.get("by_horizon") or {}).items()
                 if isinstance(c, dict) and c.get("raw") is not None
                 and c.get("calibrated") is not None]
        print(f"calibrated on {cal['cases']} held-out cases; 95% ellipse coverage raw -> "
              f"calibrated ({cv}): {', '.join(per_h) or '-'} (asgp info MODEL shows it per "
              "regime and bag)")
    elif cal.get("reason"):
        print(f"not calibrated: {cal['reason']}")
    return 0
