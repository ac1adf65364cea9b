"""``asgp demo``: the whole smart-wheelchair system live on simulated hardware."""

from __future__ import annotations

import argparse
from pathlib import Path

from asgp_ros.cli import CommandError
from asgp_ros.core.scan_match import VELOCITY_SOURCES
from asgp_ros.demo.common import DemoError
from asgp_ros.demo.orchestrator import DemoOptions, run_demo


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "demo",
        help="run the whole system live on simulated hardware and report how well it predicts",
        description="Train a model on a simulated drive (unless --model), start the simulated "
                    "chair, joystick board and camera, the serial bridge, VO and predictor "
                    "nodes as separate ROS 2 processes on a demo-only domain, drive for "
                    "--minutes with a live status line, then write a report (figure, success "
                    "rates online and offline on the recorded bag, CPU and latencies) to "
                    "--out. Ctrl-C stops everything cleanly. Exit code 0 only when every node "
                    "produced output and the report was written.",
    )
    p.add_argument("--minutes", type=float, default=2.0,
                   help="live driving time (%(default)s)")
    p.add_argument("--out", default="demo-output",
                   help="output directory: model, bag, report, logs (%(default)s)")
    p.add_argument("--seed", type=int, default=0, help="seed of the live drive (%(default)s)")
    p.add_argument("--no-train", action="store_true",
                   help="do not train: use --model, or OUT/model.npz from an earlier run (whose "
                        "other outputs in OUT are then replaced)")
    p.add_argument("--model", default=None,
                   help="model file (.npz from asgp train) to use instead of training")
    p.add_argument("--domain-id", type=int, default=None,
                   help="ROS_DOMAIN_ID of the run, 1-232 (default: 150 + pid %% 80)")
    p.add_argument("--train-minutes", type=float, default=10.0,
                   help="length of the simulated training drive (%(default)s)")
    p.add_argument("--surface", choices=("tile", "carpet", "hybrid"), default="tile",
                   help="floor of the demo room (%(default)s)")
    p.add_argument("--camera-rate", type=float, default=15.0,
                   help="RGB-D frame rate in Hz (%(default)s)")
    p.add_argument("--resolution", default="320x240", metavar="WxH",
                   help="camera image size (%(default)s; larger images are often lost over "
                        "UDP between processes)")
    p.add_argument("--no-plan", action="store_true",
                   help="publish no joy_plan: the predictor holds the last command")
    p.add_argument("--shared-control", action="store_true",
                   help="also run shared_control_node on the simulated laser scanner; the "
                        "report compares the drive with the same drive without the layer")
    p.add_argument("--inattention", type=float, default=None,
                   help="probability that a bout of the simulated driver is inattentive "
                        "(heads for the furniture, reacts late); default 0.1 with "
                        "--shared-control, else 0")
    p.add_argument("--velocity-source", choices=VELOCITY_SOURCES, default="auto",
                   help="with --shared-control: where the layer takes the chair's velocity "
                        "from (shared_control_node's velocity_source; %(default)s)")
    p.add_argument("--force", action="store_true",
                   help="replace the output of an earlier demo in --out (a directory the "
                        "demo wrote; anything else there is refused)")
    p.add_argument("--adapt", action=argparse.BooleanOptionalAction, default=True,
                   help="the predictor adapts its model online (adapt.enabled, the nodes' "
                        "default), and so does the shared-control layer's own predictor with "
                        "--shared-control; the report shows what the predictor learnt and "
                        "what it refused (the steps the layer's overrides drove); "
                        "--no-adapt: both predict from the model as trained")
    p.add_argument("--startup-timeout", type=float, default=120.0,
                   help="seconds the nodes have to come up (%(default)s)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    try:
        w, h = (int(v) for v in args.resolution.lower().split("x"))
    except ValueError:
        raise CommandError(
            f"--resolution must be WxH, e.g. 320x240, got {args.resolution!r}") from None
    opts = DemoOptions(
        minutes=args.minutes, out=Path(args.out), seed=args.seed,
        train=not args.no_train and args.model is None,
        model=Path(args.model) if args.model else None, domain_id=args.domain_id,
        train_minutes=args.train_minutes, camera_rate_hz=args.camera_rate, width=w, height=h,
        plan=not args.no_plan, startup_timeout_s=args.startup_timeout, surface=args.surface,
        force=args.force, shared_control=args.shared_control,
        inattention=args.inattention if args.inattention is not None
        else (0.1 if args.shared_control else 0.0),
        velocity_source=args.velocity_source, adapt=args.adapt)
    try:
        return run_demo(opts, say=lambda line: print(line, flush=True))
    except DemoError as exc:
        raise CommandError(str(exc)) from exc
