"""Raw 10-bit joystick ADC readings -> deflections in [-1, 1], with a dead zone.

The host-side calibration, configured per chair (``config/bridge.yaml``). It is separate
from the firmware's own fixed calibration (``config.h``), which decides the safety rules
and what the board writes to the chair; the defaults of both describe the same joystick
(2.5 V +- 1.0 V on a 5 V, 10-bit ADC: 512 +- 205 counts). :func:`board_permille` and
:func:`host_deflection` translate between the two: an override in the units of ``joy`` is
sent as the board's output for the stick position the host reads as it, and the board's
output is read back in the units of ``joy``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from asgp_ros.serial.safety import AxisCal

ADC_MAX = 1023


@dataclass(frozen=True)
class AxisCalibration:
    """One axis: ADC counts at full negative, neutral and full positive deflection.

    ``dead_zone`` is a fraction of full deflection around neutral that reads as exactly 0;
    outside it the deflection is rescaled so it is continuous and reaches +-1 at the ends:
    ``d = sign(x) (|x| - dz) / (1 - dz)`` with ``x`` the normalised offset from neutral.
    ``invert`` flips the sign (a joystick wired the other way round).
    """

    neutral: float = 512.0
    minimum: float = 307.0
    maximum: float = 717.0
    dead_zone: float = 0.04
    invert: bool = False

    def __post_init__(self) -> None:
        values = (self.minimum, self.neutral, self.maximum, self.dead_zone)
        if not all(math.isfinite(v) for v in values):
            raise ValueError(f"calibration values must be finite, got {values}")
        if not 0.0 <= self.minimum < self.neutral < self.maximum <= ADC_MAX:
            raise ValueError(
                f"calibration needs 0 <= minimum < neutral < maximum <= {ADC_MAX}, got "
                f"minimum={self.minimum}, neutral={self.neutral}, maximum={self.maximum}")
        if not 0.0 <= self.dead_zone < 0.5:
            raise ValueError(f"dead_zone must be in [0, 0.5), got {self.dead_zone}")

    def deflection(self, raw: float) -> float:
        """Deflection in [-1, 1] of one ADC reading (scalar twin of ``deflection_array``)."""
        if not math.isfinite(raw):
            raise ValueError(f"raw ADC reading must be finite, got {raw}")
        if raw >= self.neutral:
            x = (raw - self.neutral) / (self.maximum - self.neutral)
        else:
            x = (raw - self.neutral) / (self.neutral - self.minimum)
        mag = min(1.0, max(0.0, (abs(x) - self.dead_zone) / (1.0 - self.dead_zone)))
        if mag == 0.0:
            return 0.0
        d = math.copysign(mag, x)
        return -d if self.invert else d

    def raw_for(self, deflection: float) -> float:
        """The ADC reading (counts, unrounded) this calibration reads as ``deflection``: the
        inverse of ``deflection``, the dead zone's edge for the smallest non-zero values and
        the neutral reading for 0."""
        if not (math.isfinite(deflection) and -1.0 <= deflection <= 1.0):
            raise ValueError(f"deflection must be in [-1, 1], got {deflection}")
        s = -deflection if self.invert else deflection
        if s == 0.0:
            return self.neutral
        x = math.copysign(self.dead_zone + abs(s) * (1.0 - self.dead_zone), s)
        span = self.maximum - self.neutral if x > 0.0 else self.neutral - self.minimum
        return self.neutral + x * span

    def deflection_array(self, raw: np.ndarray) -> np.ndarray:
        """Vectorised ``deflection``: raw [N] counts -> [N] deflections in [-1, 1]."""
        raw = np.asarray(raw, dtype=float)
        if not np.all(np.isfinite(raw)):
            raise ValueError("raw ADC readings must be finite")
        x = np.where(raw >= self.neutral,
                     (raw - self.neutral) / (self.maximum - self.neutral),
                     (raw - self.neutral) / (self.neutral - self.minimum))
        mag = np.clip((np.abs(x) - self.dead_zone) / (1.0 - self.dead_zone), 0.0, 1.0)
        d = np.sign(x) * mag
        d = -d if self.invert else d
        return d + 0.0  # no negative zeros


@dataclass(frozen=True)
class JoystickCalibration:
    """Both axes: forward (+ forward) and turn (+ left, counter-clockwise per REP-103)."""

    forward: AxisCalibration = AxisCalibration()
    turn: AxisCalibration = AxisCalibration()

    def __call__(self, raw_forward: float, raw_turn: float) -> tuple[float, float]:
        return self.forward.deflection(raw_forward), self.turn.deflection(raw_turn)


def board_neutral_problem(host: AxisCalibration, board: AxisCal) -> str | None:
    """Why the host's zero does not lie inside the board's neutral window, or its extremes
    not beyond it, or None.

    The firmware reads a stick within ``adc_deadband`` counts of its compiled
    ``adc_neutral`` (``config.h``) as neutral: it drives nothing there, and a neutral stick
    stops any override (the dead-man rule). Every reading the host calibration gives as 0
    (its neutral, widened by its dead zone) must lie in that window: a stick resting
    outside it drives the chair at rest and can never release an override, and a reading
    ``joy`` gives as 0 while the board drives the chair is a false 0 on ``joy`` (the
    predictor and the shared-control layer would take the creeping chair as at rest)."""
    lo_ok = board.adc_neutral - board.adc_deadband
    hi_ok = board.adc_neutral + board.adc_deadband
    window = (f"the board's neutral window {lo_ok}..{hi_ok} counts (ASGP_ADC_NEUTRAL +- "
              "ASGP_ADC_DEADBAND in firmware/asgp_bridge/config.h)")
    if not lo_ok <= host.neutral <= hi_ok:
        return (f"the stick rests at {host.neutral:g} counts, outside {window}: at rest the "
                "board drives the chair, and a neutral stick cannot stop an override; set "
                "ASGP_ADC_NEUTRAL (and its mirror in asgp_ros/serial/safety.py) to the "
                "stick's rest and flash the board again")
    if host.minimum >= lo_ok or host.maximum <= hi_ok:
        # a stick never moved while the monitor ran: its noise made the extremes (512 /
        # 510 / 513), joy jumped between +1 and -0.5 at rest, every push read as full, and
        # every override fell inside the board's neutral: a stop
        return (f"the extremes {host.minimum:g} and {host.maximum:g} counts are not both "
                f"beyond {window}: the stick was not pushed to its extremes; run the "
                "monitor again and move the stick fully forward, back, left and right")
    zero_hi = math.floor(host.neutral + host.dead_zone * (host.maximum - host.neutral) + 1e-9)
    zero_lo = math.ceil(host.neutral - host.dead_zone * (host.neutral - host.minimum) - 1e-9)
    if zero_lo < lo_ok or zero_hi > hi_ok:
        fits = min((hi_ok - host.neutral) / (host.maximum - host.neutral),
                   (host.neutral - lo_ok) / (host.neutral - host.minimum))
        return (f"joy reads 0 from {zero_lo} to {zero_hi} counts (neutral +- dead_zone), "
                f"beyond {window}: there the board drives the chair while joy says the stick "
                f"is at rest; a dead_zone of at most {math.floor(fits * 1000) / 1000:g} fits")
    return None


def board_permille(deflection: float, host: AxisCalibration, board: AxisCal) -> int:
    """What to send the board (per mille) for a command of ``deflection`` in the units of
    ``joy`` (this host calibration, + forward, + left): the output the board gives in
    passthrough for the stick position the host reads as that deflection. An override then
    drives the chair as the user's stick at the same reading does, whatever the two
    calibrations (a joystick wired the other way round, ``invert``, or one that does not
    reach the board's full span). A command of 0 is the board's neutral, a stop, whatever
    the host's calibration (:func:`board_neutral_problem`)."""
    if deflection == 0.0:
        return 0
    raw = round(min(float(ADC_MAX), max(0.0, host.raw_for(deflection))))
    return board.adc_to_permille(raw)


def host_deflection(code: int, host: AxisCalibration, board: AxisCal) -> float:
    """The board's output DAC ``code`` in the units of ``joy``: the deflection this host
    calibration reads for a stick position the board passes through as that code (the
    inverse of :func:`board_permille`, to the board's resolution)."""
    pm = max(-1000, min(1000, round((code - board.dac_neutral) * 1000 / board.dac_span)))
    if pm == 0:
        return host.deflection(board.adc_neutral)
    usable = board.adc_span - board.adc_deadband
    return host.deflection(board.adc_neutral + math.copysign(
        board.adc_deadband + abs(pm) * usable / 1000.0, pm))
