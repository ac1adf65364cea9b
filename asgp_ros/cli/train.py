"""``asgp train``: fit a motion predictor (ASGP or a baseline) on bags, save the model file."""

from __future__ import annotations

import argparse

from asgp_ros.cli._argtypes import cli_integer, integer, number
from asgp_ros.cli._bagargs import add_topic_args, read_series_or_fail
from asgp_ros.core.features import LAGS_RANGE
from asgp_ros.core.models import get_kind, trainable_kinds
from asgp_ros.core.resample import RESAMPLE_RANGES


def _default_lags_help() -> str:
    """The kinds' default lags for --help: "asgp 4, mlp 10, others 1"."""
    lags = {name: get_kind(name).default_lags for name in trainable_kinds()}
    special = [f"{name} {s}" for name, s in lags.items() if s != 1]
    return ", ".join(special + (["others 1"] if len(special) < len(lags) else []))


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "train",
        help="train a motion predictor on bags and save the model file",
        description="Resample the bags to the model grid (5 Hz), build the autoregressive "
                    "features and fit one regressor per channel (v, omega). Progress goes "
                    "to stdout; stderr carries only an error.",
    )
    p.add_argument("bags", nargs="+", metavar="BAG", help="training bags (ROS 1 or ROS 2)")
    p.add_argument("--out", required=True, metavar="MODEL", help="model file to write (.npz)")
    p.add_argument("--force", action="store_true",
                   help="replace an existing model file at --out (nothing else is replaced)")
    p.add_argument("--model", choices=trainable_kinds(), default="asgp",
                   help="model kind (%(default)s)")
    p.add_argument("--lags", type=integer(*LAGS_RANGE), default=None,
                   help=f"s, past samples per input ({_default_lags_help()})")
    p.add_argument("--inducing-v", type=cli_integer("inducing"), default=20,
                   help="pseudo-inputs for v (20)")
    p.add_argument("--inducing-w", type=cli_integer("inducing"), default=40,
                   help="pseudo-inputs for omega (40)")
    p.add_argument("--max-iter", type=cli_integer("max_iter"), default=200,
                   help="L-BFGS-B iterations (asgp) or epochs (mlp) (%(default)s)")
    p.add_argument("--coupled", action="store_true",
                   help="feed both joystick axes and both velocities to each channel")
    p.add_argument("--seed", type=cli_integer("seed"), default=0,
                   help="random seed (%(default)s)")
    p.add_argument("--rate", type=number(*RESAMPLE_RANGES["rate_hz"], unit="Hz"),
                   default=None, help="grid rate in Hz (default 5)")
    add_topic_args(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from asgp_ros.cli import CommandError
    from asgp_ros.core.modelfile import save_model
    from asgp_ros.core.resample import ResampleConfig
    from asgp_ros.fileio import MODEL_FILE, check_output
    from asgp_ros.training import TrainingError, TrainOptions, train

    check_output(args.out, MODEL_FILE, inputs=args.bags, force=args.force)
    try:
        rc = ResampleConfig() if args.rate is None else ResampleConfig(rate_hz=args.rate)
        opts = TrainOptions(kind=args.model, lags=args.lags, inducing_v=args.inducing_v,
                            inducing_w=args.inducing_w, max_iter=args.max_iter,
                            coupled=args.coupled, seed=args.seed)
        opts.validate()
    except (TrainingError, ValueError) as exc:
        raise CommandError(str(exc)) from exc
    series = read_series_or_fail(args.bags, args, resample_config=rc)

    def progress(channel: str, message: str) -> None:
        print(f"[{args.model} {channel}] {message}", flush=True)

    try:
        model = train(series, opts, resample_config=rc, progress=progress)
    except (TrainingError, ValueError) as exc:
        raise CommandError(str(exc)) from exc
    save_model(args.out, model)
    summary = model.meta["training_data"]
    print(f"wrote {args.out}: {args.model}, s={opts.resolved_lags()}, "
          f"{summary['training_rows']} rows from {len(summary['bags'])} bag(s), "
          f"{summary['segments']} segments, stale {100 * summary['stale_fraction']:.1f}%")
    return 0
