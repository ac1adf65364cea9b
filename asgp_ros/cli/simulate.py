"""``asgp simulate``: one simulated recording as a bag."""

from __future__ import annotations

import argparse
import time

from asgp_ros.cli import CommandError
from asgp_ros.cli._argtypes import cli_integer, cli_number
from asgp_ros.common.fileio import bag_kind, check_output
from asgp_ros.recording.bags import BagError
from asgp_ros.sim.simulate import simulate, write_recording


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "simulate",
        help="simulate one wheelchair recording and write it as a bag",
        description="Simulate a user driving the wheelchair in a room (joystick at 30 Hz, "
                    "Fovis-like VO at 4-7 Hz with tracking failures, ground truth) and write "
                    "/joy, /vo/twist and /ground_truth/odom to a bag.",
    )
    p.add_argument("--surface", choices=("tile", "carpet", "hybrid"), default="tile",
                   help="floor: tile, carpet, or the hybrid atrium that changes between them "
                        "(default tile)")
    p.add_argument("--minutes", type=cli_number("minutes", "min"), default=20.0,
                   help="length (default 20)")
    p.add_argument("--seed", type=cli_integer("seed"), default=0,
                   help="random seed (default 0)")
    p.add_argument("--out", required=True,
                   help="bag to write: a ROS 2 bag directory, or FILE.bag for ROS 1")
    p.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap",
                   help="ROS 2 storage (default mcap; ignored for a .bag path)")
    p.add_argument("--no-truth", action="store_true", help="omit /ground_truth/odom")
    p.add_argument("--force", action="store_true",
                   help="replace an existing bag at --out (nothing else is replaced)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    out = check_output(args.out, bag_kind(args.out), force=args.force)
    if args.seed < 0:
        raise CommandError(f"--seed must be >= 0, got {args.seed}")
    start = time.perf_counter()
    try:
        rec = simulate(args.surface, args.minutes, args.seed)
        write_recording(out, rec, storage=args.storage, truth=not args.no_truth)
    except (ValueError, BagError) as exc:
        raise CommandError(str(exc)) from exc
    print(f"{out}: {args.surface}, {args.minutes:g} min, seed {args.seed}: "
          f"{rec.joy_t.size} joystick, {rec.vo_t.size} VO messages, "
          f"{rec.failures.shape[0]} VO tracking failures "
          f"({time.perf_counter() - start:.1f} s)")
    return 0
