"""``asgp dataset``: the paper's recordings, simulated (:mod:`asgp_ros.learning.dataset`)."""

from __future__ import annotations

import argparse
import sys

from asgp_ros.cli import CommandError
from asgp_ros.cli._argtypes import cli_integer, cli_number
from asgp_ros.learning.dataset import STORAGES, DatasetError, DatasetOptionError, build_dataset


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "dataset",
        help="simulate the paper's dataset: 8 tile, 8 carpet, 2 hybrid bags",
        description="Simulate the paper's recordings (20-minute bags: 8 on tile, 8 on "
                    "carpet, 2 in a hybrid atrium) into DIR/{tile,carpet,hybrid}/ with a "
                    "manifest.json.",
    )
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--scale", type=cli_number("scale"), default=1.0,
                   help="bag length = 20 min x scale (default 1; 0.05 gives 1-min bags)")
    p.add_argument("--seed", type=cli_integer("seed"), default=0,
                   help="base seed (default 0)")
    p.add_argument("--jobs", type=cli_integer("jobs"), default=1,
                   help="parallel processes (default 1)")
    p.add_argument("--storage", choices=STORAGES, default=STORAGES[0],
                   help=f"ROS 2 storage of the bags (default {STORAGES[0]})")
    p.add_argument("--force", action="store_true",
                   help="re-simulate bags that exist (only bags are replaced)")
    p.set_defaults(func=run)


def progress_bar(done: int, total: int, label: str, elapsed: float) -> None:
    """The progress line of a dataset being built, rewritten in place on stdout (stderr
    carries only a failed command's error line)."""
    width = 30
    filled = int(width * done / total)
    bar = "#" * filled + "." * (width - filled)
    sys.stdout.write(f"\r[{bar}] {done}/{total} {label:<18} {elapsed:6.1f} s")
    if done == total:
        sys.stdout.write("\n")
    sys.stdout.flush()


def run(args: argparse.Namespace) -> int:
    try:
        built = build_dataset(args.out, scale=args.scale, seed=args.seed, jobs=args.jobs,
                              storage=args.storage, force=args.force, progress=progress_bar)
    except DatasetOptionError as exc:
        raise CommandError(f"--{exc.option} {exc.problem}") from exc
    except DatasetError as exc:
        sys.stdout.write("\n")  # end the progress line
        raise CommandError(str(exc)) from exc
    print(built.describe())
    return 0
