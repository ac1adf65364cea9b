"""``asgp reproduce``: the paper's Tables I-III, plots and a report from a dataset."""

from __future__ import annotations

import argparse
import shlex
import sys
from collections.abc import Sequence

from asgp_ros.cli import CommandError
from asgp_ros.cli._argtypes import cli_integer
from asgp_ros.cli.dataset import progress_bar


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "reproduce",
        help="train and evaluate every model of the paper's protocol; write Tables I-III",
        description="Train the ASGP in the paper's configuration and in the one `asgp "
                    "train` chooses itself, the paper's MLP, and constant-velocity and "
                    "first-order-lag models on the Tile, Carpet and Both train sets of a "
                    "dataset made by `asgp dataset`, test them on Tile, Carpet and Hybrid at "
                    "1.0, 1.4 and 2.0 s, and write report.md (with the paper's published "
                    "figures beside ours), results.json, tables.json, plots and the model "
                    "files into REPORT (atomically: all or nothing).",
    )
    p.add_argument("--data", required=True, metavar="DIR",
                   help="dataset directory with tile/, carpet/, hybrid/ bags")
    p.add_argument("--out", required=True, metavar="REPORT", help="report directory to write")
    p.add_argument("--quick", action="store_true",
                   help="CI smoke run: builds a small dataset in DIR if it has none, reduced "
                        "training budgets (under a minute on 2 cores)")
    p.add_argument("--jobs", type=cli_integer("jobs"), default=None,
                   help="worker processes (default: min(2, cores))")
    p.add_argument("--seed", type=cli_integer("seed"), default=0,
                   help="training seed (%(default)s)")
    p.add_argument("--force", action="store_true",
                   help="replace an existing report directory at --out (one this command "
                        "wrote; nothing else is replaced)")
    p.set_defaults(func=run)


def command_line(argv: Sequence[str] | None = None) -> str:
    """This command as typed (quoted for a shell), for the report's "Made by" line."""
    return "asgp " + " ".join(shlex.quote(a) for a in (argv if argv is not None
                                                         else sys.argv[1:]))


def run(args: argparse.Namespace) -> int:
    # imported when the command runs: the reproduction's modules are not needed for --help
    from asgp_ros.learning.reproduce.protocol import ReproduceError
    from asgp_ros.learning.reproduce.run import run as reproduce

    if args.jobs is not None and args.jobs < 1:
        raise CommandError("--jobs must be >= 1")
    try:
        summary = reproduce(args.data, args.out, quick=args.quick, jobs=args.jobs,
                            seed=args.seed, command=command_line(), force=args.force,
                            dataset_progress=progress_bar,
                            dataset_built=lambda built: print(built.describe()))
    except ReproduceError as exc:
        raise CommandError(str(exc)) from exc
    for name, tab in summary["tables"].items():
        print(f"{name} (tested on {tab['test_set']}): success rate %")
        for row in tab["rows"]:
            cells = "  ".join(f"{h} s {row[h]['success_rate_pct']:5.1f}"
                              for h in tab["cases"])
            print(f"  {row['train']:<7} {row['model']:<18} {cells}")
    for c in summary["claims"]:
        print(f"{'holds' if c['holds'] else 'does not hold'}: {c['claim']} ({c['evidence']})")
    print(f"wrote {args.out}/report.md in {summary['timing']['total_s']:.0f} s")
    return 0
