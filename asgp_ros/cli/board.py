"""``asgp board``: run the simulated joystick interface board on a pty (prints its port),
or ``--monitor PORT`` a real board's raw joystick readings for calibration."""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

from asgp_ros.cli import CommandError
from asgp_ros.cli._argtypes import cli_integer, cli_number
from asgp_ros.serial.calibration import ADC_MAX, AxisCalibration, board_neutral_problem
from asgp_ros.serial.link import JoystickSample, LinkConfig, LinkManager, LinkState
from asgp_ros.serial.params import BOARD_CALIBRATION
from asgp_ros.serial.protocol import Status
from asgp_ros.sim.board import ScriptedJoystick, SimulatedBoard, driver_joystick


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "board", help="simulated Arduino joystick board on a pty (or monitor a real one)",
        description="Start the simulated joystick interface board: it speaks the real link "
                    "protocol on a pseudo-terminal and prints the port path for "
                    "serial_bridge_node's `port` parameter. Ctrl-C stops it.")
    p.add_argument("--link", type=Path, default=None,
                   help="also expose the port as this stable symlink (like a udev name)")
    p.add_argument("--rate", type=cli_number("board_rate_hz", "Hz"), default=100.0,
                   help="sampling rate, Hz (100)")
    p.add_argument("--source", choices=("auto", "driver", "scripted", "neutral"),
                   default="auto",
                   help="joystick: the simulator's driver on a simulated chair that follows "
                        "the board's output, a scripted smooth joystick, or neutral "
                        "(auto: driver if available)")
    p.add_argument("--force", action="store_true",
                   help="replace an existing symlink at --link (nothing else is replaced)")
    p.add_argument("--seed", type=cli_integer("seed"), default=0,
                   help="seed of the driver, the script and the ADC noise (0)")
    p.add_argument("--noise", type=cli_number("noise_counts"), default=0.5,
                   help="ADC noise, counts (0.5)")
    p.add_argument("--duration", type=cli_number("duration_s", "s"), default=None,
                   help="stop after this many s")
    p.add_argument("--status-every", type=cli_number("status_every_s", "s"), default=0.0,
                   help="print the board's output every N s (0: never)")
    p.add_argument("--monitor", metavar="PORT", default=None,
                   help="instead: read a real board on PORT for --duration s (default 10) "
                        "and print its raw joystick range and a calibration block")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.monitor is not None:
        if not args.monitor:  # '' started the simulated board instead
            raise CommandError("--monitor needs the port of a real board, got ''")
        return _monitor(args)
    if not 1.0 <= args.rate <= 1000.0:
        raise CommandError(f"--rate must be in [1, 1000] Hz, got {args.rate}")
    if args.link is not None and not args.link.parent.is_dir():
        # (the pty's name was given as the missing path)
        raise CommandError(f"--link {args.link}: no directory {args.link.parent}")
    if args.link is not None and os.path.lexists(args.link):
        if not args.link.is_symlink():
            raise CommandError(f"--link {args.link} exists and is not a symlink; refusing to "
                               "replace it")
        if not args.force:
            raise CommandError(f"--link {args.link}: a symlink exists there; use --force to "
                               "replace it")
    board = SimulatedBoard(rate_hz=args.rate, link_path=args.link, noise_counts=args.noise,
                           seed=args.seed)
    source_name = args.source
    if args.source in ("auto", "driver"):
        source = driver_joystick(args.seed, board)
        if source is None:
            if args.source == "driver":
                raise CommandError("the simulator's driver (asgp_ros.sim.driver) is not "
                                   "available")
            source_name = "scripted"
            source = ScriptedJoystick(args.seed)
        else:
            source_name = "driver"
    elif args.source == "scripted":
        source = ScriptedJoystick(args.seed)
    else:
        def source(t: float) -> tuple[float, float]:
            return 0.0, 0.0
    board.set_joystick(source)
    try:  # from start() on, stop() runs on every exit: it removes the pty and the link
        board.start()
        print(board.port, flush=True)  # the first line of stdout: scripts read the port here
        print(f"simulated board: {args.rate:g} Hz, joystick {source_name}, pty "
              f"{board.slave_path} (Ctrl-C stops)", flush=True)
        t0 = time.monotonic()
        next_status = t0
        while args.duration is None or time.monotonic() - t0 < args.duration:
            time.sleep(0.05)
            if board.error is not None:
                raise CommandError(f"simulated board stopped: {board.error}")
            if args.status_every > 0 and time.monotonic() >= next_status:
                next_status += args.status_every
                o = board.output
                flags = "|".join(f.name or "" for f in Status if f and f in o.status)
                print(f"t={o.t:7.2f}s user=({o.user_forward:+.2f},{o.user_turn:+.2f}) "
                      f"out=({o.forward:+.2f},{o.turn:+.2f}) mode={o.mode.name.lower()} "
                      f"status={flags.lower() or 'none'}", flush=True)
    finally:
        board.stop()
    return 0


def _monitor(args: argparse.Namespace) -> int:
    duration = 10.0 if args.duration is None else args.duration
    raws: list[tuple[int, int]] = []
    faulty = [0]

    def on_sample(s: JoystickSample) -> None:
        # A faulty reading (open or shorted stick, ADC_FAULT) is no end stop of the stick.
        if s.valid:
            raws.append((s.raw_forward, s.raw_turn))
        else:
            faulty[0] += 1

    link = LinkManager(LinkConfig(args.monitor), on_sample=on_sample)
    print(f"reading {args.monitor} for {duration:g} s: leave the joystick at rest for the "
          f"first {duration / 5:.1f} s, then push it to all four extremes", flush=True)
    with link:
        if not link.wait_for_state(LinkState.CONNECTED, 5.0):
            raise CommandError(f"no board answered on {args.monitor}: "
                               f"{link.stats().last_error or link.state.value}")
        print(f"connected: firmware {link.stats().firmware}", flush=True)
        time.sleep(duration)
    if faulty[0]:
        print(f"skipped {faulty[0]} samples the board flagged as faulty (ADC_FAULT: check the "
              "joystick wiring)", flush=True)
    if len(raws) < 10:
        raise CommandError(f"only {len(raws)} valid samples received")
    r = np.asarray(raws, dtype=float)  # [N, 2]
    rest = r[: max(1, len(r) // 5)]
    print("calibration:")
    problems = []
    for i, axis in enumerate(("forward", "turn")):
        neutral, low, high = float(np.median(rest[:, i])), r[:, i].min(), r[:, i].max()
        print(f"  {axis}:\n    neutral: {neutral:.1f}\n"
              f"    minimum: {low:.1f}\n    maximum: {high:.1f}")
        try:
            cal = AxisCalibration(neutral=round(neutral, 1), minimum=low, maximum=high)
        except ValueError as exc:  # the stick was not pushed both ways, say
            problems.append(f"{axis}: the stick was not pushed to its extremes ({exc}); run "
                            "the monitor again and move it fully forward, back, left and "
                            "right")
            continue
        if (problem := board_neutral_problem(cal, BOARD_CALIBRATION[i])) is not None:
            problems.append(f"{axis}: {problem}")
        elif (short := _short_side(cal)) is not None:
            problems.append(f"{axis}: {short}")
    for problem in problems:
        # the bridge refuses this calibration: said here, where it is measured
        print(f"warning: {problem}", file=sys.stderr, flush=True)
    return 0


#: A side of an axis the stick was pushed less than this fraction of the way from its rest
#: to the ADC's end (0 or ADC_MAX) is told: a stick's travel spans most of it, and a
#: calibration of a short push reads every fuller push as full deflection.
SHORT_SIDE = 0.25


def _short_side(cal: AxisCalibration) -> str | None:
    """Why one side of a measured axis looks like a stick not pushed all the way, or None."""
    for side, span, room in (("maximum", cal.maximum - cal.neutral, ADC_MAX - cal.neutral),
                             ("minimum", cal.neutral - cal.minimum, cal.neutral)):
        if room > 0 and span < SHORT_SIDE * room:
            return (f"the {side} is {span:.0f} counts from the rest, {100 * span / room:.0f} % "
                    "of the way to the ADC's end: was the stick pushed all the way? (each "
                    "fuller push would read as full deflection)")
    return None
