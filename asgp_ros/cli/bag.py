"""``asgp bag``: look into a bag and repair one whose recording was killed.

``asgp bag info BAG`` prints the topics, message types, counts, rates, duration and the
gaps in each stream, and for a damaged bag what was lost. ``asgp bag repair IN OUT``
writes a clean, indexed copy of every complete message of IN (which is never written to).
Both read the bag by scanning its storage record by record
(:func:`asgp_ros.recording.bags.recover_bag`), so they work on a bag without its index, its
summary or its metadata.yaml.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from asgp_ros.cli import CommandError, one_line
from asgp_ros.cli._argtypes import number
from asgp_ros.common.fileio import ROS1_BAG, ROS2_BAG, bag_inputs, check_output
from asgp_ros.recording.bags import (
    BagError,
    clock_steps_text,
    message_parts,
    recover_bag,
    repair_bag,
    topic_stats,
)

GAPS_LISTED = 10
"""Gaps listed per topic by ``asgp bag info`` (the rest are counted)."""


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "bag",
        help="show what a bag holds (info) or write a clean copy of a damaged one (repair)",
        description="Inspect a bag, or repair one whose recording was killed (a laptop's "
                    "battery died, the recorder was killed): every complete message is "
                    "recovered from a cut mcap, sqlite3 or ROS 1 bag, and what was lost is "
                    "reported.",
    )
    sub = p.add_subparsers(dest="bag_command", metavar="ACTION")
    sub.required = True
    info = sub.add_parser(
        "info", help="topics, types, counts, rates, duration, gaps and damage of a bag",
        description="Print each topic's message type, count, rate and median period, the "
                    "bag's duration, every gap in a stream (an interval longer than "
                    "--gap-factor times that stream's median period, with its bag times), "
                    "and for a damaged bag what was recovered and what was lost.")
    info.add_argument("bag", metavar="BAG", help="ROS 1 .bag file, ROS 2 bag directory or "
                                                  "its .mcap / .db3 file")
    info.add_argument("--gap-factor", type=number(1.0, 1e6), default=3.0,
                      help="a gap is longer than this many median periods (%(default)s)")
    info.set_defaults(func=run_info)
    repair = sub.add_parser(
        "repair", help="write a clean, indexed copy of every complete message of a bag",
        description="Scan IN record by record (no index, summary or metadata.yaml needed), "
                    "keep every complete message, and write them to OUT as a new indexed "
                    "bag, atomically. A partial record is dropped, never decoded. IN is "
                    "never written to.")
    repair.add_argument("bag", metavar="IN", help="the bag to repair")
    repair.add_argument("out", metavar="OUT",
                        help="the bag to write (a .bag file for ROS 1, else a directory)")
    repair.add_argument("--storage", choices=("mcap", "sqlite3", "ros1"), default=None,
                        help="storage of OUT (default: that of IN; mcap and sqlite3 are "
                             "interchangeable, ROS 1 stays ROS 1)")
    repair.add_argument("--force", action="store_true",
                        help="replace an existing bag at OUT (nothing else is replaced)")
    repair.set_defaults(func=run_repair)


def _seconds(ns: int, origin: int) -> str:
    return f"{(ns - origin) * 1e-9:.3f}"


def info_lines(stats: list[Any], damage: Any) -> list[str]:
    """The report of ``asgp bag info``: a table of topics, their gaps, the damage."""
    start, end = damage.start_ns, damage.end_ns
    lines = [f"bag:      {damage.bag} ({damage.storage}, "
             f"{'intact' if damage.intact else 'DAMAGED'})"]
    if start is None or end is None:
        lines.append("messages: none")
    else:
        lines.append(f"duration: {(end - start) * 1e-9:.3f} s, bag time "
                     f"{start * 1e-9:.3f} .. {end * 1e-9:.3f} (times below are seconds "
                     "from the start)")
        lines.append(f"messages: {damage.messages}")
    width = max([len("topic")] + [len(s.topic) for s in stats])
    twidth = max([len("type")] + [len(s.msgtype) for s in stats])
    lines.append(f"{'topic':<{width}}  {'type':<{twidth}}  {'count':>7}  {'rate Hz':>8}  "
                 f"{'period s':>8}  {'gaps':>5}")
    for s in stats:
        rate = f"{s.rate_hz:8.2f}" if s.rate_hz is not None else f"{'-':>8}"
        period = (f"{s.median_period_s:8.4f}" if s.median_period_s is not None
                  else f"{'-':>8}")
        lines.append(f"{s.topic:<{width}}  {s.msgtype:<{twidth}}  {s.count:>7}  {rate}  "
                     f"{period}  {len(s.gaps):>5}")
    origin = start or 0
    for s in stats:
        for a, b in s.gaps[:GAPS_LISTED]:
            lines.append(f"gap {s.topic}: {_seconds(a, origin)} .. {_seconds(b, origin)} s "
                         f"({(b - a) * 1e-9:.3f} s)")
        if len(s.gaps) > GAPS_LISTED:
            lines.append(f"gap {s.topic}: ... and {len(s.gaps) - GAPS_LISTED} more")
    if not damage.intact:
        lines.append(f"damage:   {damage.summary()}")
    return lines


def run_info(args: argparse.Namespace) -> int:
    try:
        # times only (no message data), in the order written: a clock stepped back shows
        recovered = recover_bag(args.bag, topics=(), record_order=True)
    except BagError as exc:
        raise CommandError(str(exc)) from exc
    times = [m[1] for m in recovered.messages]
    parts = message_parts(recovered.messages)
    recovered.messages.sort(key=lambda m: m[1])
    for line in info_lines(topic_stats(recovered, args.gap_factor), recovered.damage):
        print(one_line(line))  # the bag's topic names: a newline or escape forged rows
    if parts.size and parts[-1]:
        print(one_line(f"clock:    {clock_steps_text(times, parts)}: sorted by time its "
                       f"{int(parts[-1]) + 1} parts interleave (the rates and gaps above); "
                       "asgp train and evaluate read them one after the other"))
    return 0


def run_repair(args: argparse.Namespace) -> int:
    ros1_out = args.storage == "ros1" or Path(args.out).suffix == ".bag"
    out = check_output(args.out, ROS1_BAG if ros1_out else ROS2_BAG,
                       inputs=bag_inputs([args.bag]), force=args.force, option="OUT")
    try:
        recovered = repair_bag(args.bag, out, storage=args.storage)
    except BagError as exc:
        raise CommandError(str(exc)) from exc
    damage = recovered.damage
    print(damage.summary())
    print(f"{out}: wrote {damage.messages} messages on {len(recovered.connections)} "
          f"connections ({args.storage or ('ros1' if ros1_out else damage.storage)}, "
          "indexed)")
    return 0
