"""Shared command-line options for commands that read bags (topics, joystick axes)."""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from asgp_ros.cli import CommandError
from asgp_ros.common.topics import BAG_GROUND_TRUTH, BAG_JOY, BAG_VO_TWIST, JOY_OVERRIDE
from asgp_ros.core.resample import ResampleConfig
from asgp_ros.learning.training import Series, read_series, repeated_series
from asgp_ros.recording.bags import BagError, parse_joy_axes


def _joy_axes(spec: str) -> str:
    """--joy-axes checked as the command line is read (it was only when a bag was, after
    the model and the earlier bags), passed on as given."""
    try:
        parse_joy_axes(spec)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix(f"--joy-axes {spec!r}: ")
                                         ) from None
    return spec


def add_topic_args(parser: argparse.ArgumentParser, *, truth: bool = False) -> None:
    parser.add_argument("--joy-topic", default=BAG_JOY, help="sensor_msgs/Joy topic (%(default)s)")
    parser.add_argument("--twist-topic", default=BAG_VO_TWIST,
                        help="velocity topic: TwistStamped, TwistWithCovarianceStamped, Twist "
                             "or Odometry (%(default)s)")
    parser.add_argument("--joy-axes", default=None, metavar="FWD,TURN", type=_joy_axes,
                        help="Joy.axes indices of the forward and turn deflection, '-' flips a "
                             "sign: '0,1' (default), '1,-0', ...")
    parser.add_argument("--override-topic", default=JOY_OVERRIDE,
                        help="sensor_msgs/Joy overrides sent to the chair (%(default)s, a "
                             "relative name, is taken in --joy-topic's namespace: "
                             "/joy_override, /chair2/joy_override beside /chair2/joy): where "
                             "a bag has them, the grid points they may have driven are not "
                             "used (the joystick is not what drove the chair); '' reads none")
    parser.add_argument("--base-frame", default="base_link",
                        help="the chair's frame (%(default)s): a velocity message's twist in "
                             "another (a camera's) is not the chair's forward and turn rates, "
                             "and is read as a lost sample, as the nodes refuse it")
    if truth:
        parser.add_argument("--truth-topic", default=BAG_GROUND_TRUTH,
                            help="ground-truth nav_msgs/Odometry topic for --truth "
                                 "(%(default)s)")


def read_series_or_fail(paths: Sequence[str], args: argparse.Namespace, *,
                        resample_config: ResampleConfig | None = None, truth: bool = False
                        ) -> list[Series]:
    """Read and resample bags; any reader error becomes a CommandError naming the bag, and
    so do two that are one recording as their messages tell (a copy, repaired or
    converted, or one cut short: :func:`asgp_ros.learning.training.repeated_series`).

    ``--joy-axes`` is passed on as given ("FWD,TURN", '-' flips a sign): the bag reader
    parses it.
    """
    out: list[Series] = []
    for path in paths:
        try:
            out.extend(read_series(
                [path], resample_config=resample_config, joy_topic=args.joy_topic,
                twist_topic=args.twist_topic,
                truth_topic=getattr(args, "truth_topic", None) if truth else None,
                joy_axes=args.joy_axes, override_topic=args.override_topic,
                base_frame=args.base_frame))
        except (BagError, ValueError, OSError, KeyError) as exc:
            msg = str(exc)
            raise CommandError(msg if str(path) in msg else f"{path}: {msg}") from exc
    twice = repeated_series(out)
    if twice is not None:  # its rows or cases would count twice
        raise CommandError(twice)
    return out
