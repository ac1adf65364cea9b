"""``asgp replay BAG``: publish a ROS 1 or ROS 2 bag into ROS 2 with /clock."""

from __future__ import annotations

import argparse
import logging

from asgp_ros.cli import CommandError
from asgp_ros.cli._argtypes import number
from asgp_ros.recording.replay import (
    REPLAY_RANGES,
    BagReplayer,
    ReplayConfig,
    ReplayError,
    summary,
)

LOG = logging.getLogger(__name__)


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "replay",
        help="publish a bag into ROS 2 with /clock (ros2 bag play for ROS 1 and ROS 2 bags)",
        description=(
            "Publish a ROS 1 .bag or a ROS 2 bag (sqlite3, mcap) into ROS 2 with its original "
            "timing scaled by --rate, and /clock so that nodes with use_sim_time follow it. "
            "Topics whose message types are not installed are skipped with a warning."
        ),
    )
    p.add_argument("bag", help="ROS 1 .bag file or ROS 2 bag directory")
    p.add_argument("--rate", type=number(*REPLAY_RANGES["rate"]), default=1.0,
                   help="playback speed factor (default 1)")
    p.add_argument("--loop", action="store_true", help="restart at the end (clock jumps back)")
    p.add_argument("--topics", nargs="+", default=[], metavar="TOPIC",
                   help="only these topics (default: all with installed types)")
    p.add_argument("--start", type=number(*REPLAY_RANGES["start_s"], unit="s"), default=0.0,
                   metavar="S",
                   help="skip the first S seconds of the bag")
    p.add_argument("--clock-rate", type=number(*REPLAY_RANGES["clock_rate_hz"], unit="Hz"),
                   default=100.0, metavar="HZ",
                   help="/clock updates per second between messages (default 100)")
    p.add_argument("--no-clock", action="store_true", help="do not publish /clock")
    p.add_argument("--commands", action="store_true",
                   help="also play the commands to the chair the bag holds (joy_override, "
                        "in any namespace), which a running serial bridge would write to the "
                        "board; by default they are not played, unless named in --topics or "
                        "remapped to another name")
    p.add_argument("--remap", nargs="+", default=[], metavar="FROM:=TO",
                   help="publish bag topic FROM on topic TO")
    p.add_argument("--wait-subscribers",
                   type=number(*REPLAY_RANGES["wait_subscribers_s"], unit="s"), default=0.5,
                   metavar="S",
                   help="wait up to S seconds until every played topic has a subscriber "
                        "(default 0.5; 0 = do not wait)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    remap = []
    for item in args.remap:
        src, sep, dst = item.partition(":=")
        if not sep:
            raise CommandError(f"--remap {item!r}: expected FROM:=TO")
        remap.append((src, dst))
    try:
        config = ReplayConfig(
            rate=args.rate,
            loop=args.loop,
            topics=tuple(args.topics),
            start_s=args.start,
            clock_rate_hz=args.clock_rate,
            publish_clock=not args.no_clock,
            wait_subscribers_s=args.wait_subscribers,
            remap=tuple(remap),
            commands=args.commands,
        )
    except ValueError as exc:
        raise CommandError(str(exc)) from exc

    # rclpy (optional, slow to import) only when a bag is played: `asgp --help` stays fast.
    import rclpy
    from rclpy.executors import ExternalShutdownException

    # args=[]: not sys.argv, whose asgp options (e.g. --remap FROM:=TO) rcl would take as its
    # own. Its handlers turn SIGINT/SIGTERM into a shutdown the player polls.
    from asgp_ros.nodes.runtime import log_file_arguments

    extra, problem = log_file_arguments()  # (a read-only log directory: no file)
    rclpy.init(args=extra)
    if problem:
        print(f"warning: {problem}")
    node = None
    try:
        node = rclpy.create_node("asgp_replay")
        with BagReplayer(args.bag, config, node,
                         should_stop=lambda: not rclpy.utilities.ok()) as player:
            for line in summary(player):
                print(f"replaying {line}")
            player.run()
            print(f"published {player.published} messages")
    except ReplayError as exc:
        raise CommandError(str(exc)) from exc
    except ExternalShutdownException:
        pass
    except Exception:
        if rclpy.utilities.ok():
            raise
        # SIGINT/SIGTERM shut the context down between a check and a publish: a stop
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.utilities.try_shutdown()
    return 0
