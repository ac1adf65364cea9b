"""Checked number arguments for the ``asgp`` subcommands (argparse ``type=`` callables).

A number from the command line is parsed and range-checked where it enters: a value that
is not a number, not finite or outside its range is a usage error in one line and exit
code 2 (``asgp train: error: argument --rate: must be in [0.5, 100] Hz, got 1e+20``).

Ranges that bound a structure of the package live next to it and are used from there
(``RESAMPLE_RANGES`` of :mod:`asgp_ros.core.resample` for ``--rate``, ``LAGS_RANGE`` of
:mod:`asgp_ros.core.features` for ``--lags``, ``REPLAY_RANGES`` of
:mod:`asgp_ros.recording.replay`); the ranges of arguments that exist only on the command line are
in ``CLI_RANGES`` below.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable

#: Ranges (inclusive) of the arguments that exist only on the command line.
CLI_RANGES: dict[str, tuple[float, float]] = {
    # random seeds (numpy seeds; the simulator derives per-bag seeds from them)
    "seed": (0, 2**32 - 1),
    # pseudo-inputs of a channel: the model file holds M x M matrices of at most
    # modelfile.MAX_ARRAY_ELEMENTS = 2048**2 elements
    "inducing": (1, 2048),
    # optimiser iterations (asgp) or epochs (mlp)
    "max_iter": (1, 100_000),
    # prediction horizons (s) and the success threshold (m) of an evaluation
    "horizon_s": (0.01, 3600.0),
    "threshold_m": (0.001, 100.0),
    # length of one simulated recording (min) and the dataset's scale of 20-minute bags
    "minutes": (0.1, 600.0),
    "scale": (0.005, 30.0),
    # worker processes
    "jobs": (1, 64),
    # the simulated board: sampling rate (Hz), ADC noise (counts of 0..1023), run time
    # and status period (s)
    "board_rate_hz": (1.0, 1000.0),
    "noise_counts": (0.0, 100.0),
    "duration_s": (0.0, 30 * 86400.0),
    "status_every_s": (0.0, 3600.0),
    # online adaptation (asgp evaluate --adapt): forgetting half-life (s), the trained
    # data's floor weight, and the seconds of each bag left unscored
    "half_life_s": (1.0, 86400.0),
    "trained_floor": (0.0, 1.0),
    "skip_s": (0.0, 86400.0),
}


def _format(x: float) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


def number(low: float, high: float, unit: str = "") -> Callable[[str], float]:
    """A ``type=`` for a finite float in ``[low, high]``."""
    suffix = f" {unit}" if unit else ""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
        if not (math.isfinite(value) and low <= value <= high):
            raise argparse.ArgumentTypeError(
                f"must be in [{_format(low)}, {_format(high)}]{suffix}, got {text}")
        return value

    parse.__name__ = "number"  # argparse names the type in its messages
    return parse


def integer(low: int, high: int) -> Callable[[str], int]:
    """A ``type=`` for an integer in ``[low, high]``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"must be in [{low}, {high}], got {text}")
        return value

    parse.__name__ = "integer"
    return parse


def cli_number(name: str, unit: str = "") -> Callable[[str], float]:
    """``number`` over the range ``CLI_RANGES[name]``."""
    low, high = CLI_RANGES[name]
    return number(float(low), float(high), unit)


def cli_integer(name: str) -> Callable[[str], int]:
    """``integer`` over the range ``CLI_RANGES[name]``."""
    low, high = CLI_RANGES[name]
    return integer(int(low), int(high))
