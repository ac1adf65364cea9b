"""Raw 10-bit joystick ADC readings -> deflections in [-1, 1], with a dead zone.

The host-side calibration, configured per chair (``config/bridge.yaml``). It is separate
from the firmware's own fixed calibration (``config.h``), which only decides the safety
rules; the defaults of both describe the same joystick (2.5 V +- 1.0 V on a 5 V, 10-bit
ADC: 512 +- 205 counts).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

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
