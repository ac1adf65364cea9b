"""Raw, irregularly timed sensor streams as they come out of a bag or a live buffer.

This is the hand-over type between the bag reader / simulator and the resampler:

* joystick ``J``: forward and turn deflection in [-1, 1] (+ forward, + left/CCW),
* velocity ``V``: the chair's planar twist (v [m/s], omega [rad/s]) from visual odometry,
* optionally the ground truth of a simulator (pose and twist).

Times are seconds on one clock (header stamps, or bag receive time when a message has
no valid header). Arrays are sorted by time on construction; exact duplicate stamps are
dropped (the first sample wins).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def _sorted_unique(t: FloatArray, *values: FloatArray) -> tuple[FloatArray, ...]:
    order = np.argsort(t, kind="stable")
    t = t[order]
    keep = np.ones(t.shape[0], dtype=bool)
    keep[1:] = np.diff(t) > 0.0
    return (t[keep], *(v[order][keep] for v in values))


def _as_series(name: str, t: object, x: object, width: int) -> tuple[FloatArray, FloatArray]:
    t_arr = np.asarray(t, dtype=np.float64).reshape(-1)
    x_arr = np.asarray(x, dtype=np.float64)
    if x_arr.ndim == 1 and width == 1:
        x_arr = x_arr[:, None]
    if x_arr.ndim != 2 or x_arr.shape != (t_arr.shape[0], width):
        raise ValueError(
            f"{name}: expected values of shape [{t_arr.shape[0]}, {width}] to match "
            f"{t_arr.shape[0]} time stamps, got {x_arr.shape}"
        )
    if not np.all(np.isfinite(t_arr)):
        raise ValueError(f"{name}: time stamps contain NaN or inf")
    return t_arr, x_arr


@dataclass(frozen=True)
class RawStreams:
    """Irregular joystick and velocity series (and optional ground truth).

    Attributes:
        joy_t: [Nj] joystick sample times (s).
        joy: [Nj, 2] (forward, turn) deflection.
        vel_t: [Nv] velocity sample times (s).
        vel: [Nv, 2] (v, omega) in m/s and rad/s.
        vel_ok: [Nv] False where the odometry itself reported a tracking failure.
        truth_t: [Nt] ground-truth times, or empty.
        truth: [Nt, 5] (x, y, theta, v, omega) ground truth, or empty.
        source: where the data came from (a bag path, "live", ...), for messages.
    """

    joy_t: FloatArray
    joy: FloatArray
    vel_t: FloatArray
    vel: FloatArray
    vel_ok: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, dtype=bool))
    truth_t: FloatArray = field(default_factory=lambda: np.zeros(0))
    truth: FloatArray = field(default_factory=lambda: np.zeros((0, 5)))
    source: str = ""

    def __post_init__(self) -> None:
        joy_t, joy = _as_series("joystick", self.joy_t, self.joy, 2)
        vel_t, vel = _as_series("velocity", self.vel_t, self.vel, 2)
        vel_ok = np.asarray(self.vel_ok, dtype=bool).reshape(-1)
        if vel_ok.shape[0] == 0:
            vel_ok = np.ones(vel_t.shape[0], dtype=bool)
        if vel_ok.shape[0] != vel_t.shape[0]:
            raise ValueError(
                f"velocity: {vel_ok.shape[0]} tracking flags for {vel_t.shape[0]} samples"
            )
        truth_t, truth = _as_series("ground truth", self.truth_t, self.truth, 5)
        joy_t, joy = _sorted_unique(joy_t, joy)
        vel_t, vel, vel_ok = _sorted_unique(vel_t, vel, vel_ok)
        truth_t, truth = _sorted_unique(truth_t, truth)
        object.__setattr__(self, "joy_t", joy_t)
        object.__setattr__(self, "joy", joy)
        object.__setattr__(self, "vel_t", vel_t)
        object.__setattr__(self, "vel", vel)
        object.__setattr__(self, "vel_ok", vel_ok)
        object.__setattr__(self, "truth_t", truth_t)
        object.__setattr__(self, "truth", truth)

    @property
    def has_truth(self) -> bool:
        return self.truth_t.shape[0] > 0

    @property
    def duration(self) -> float:
        """Seconds covered by both joystick and velocity (0 if they do not overlap)."""
        if self.joy_t.size == 0 or self.vel_t.size == 0:
            return 0.0
        start = max(self.joy_t[0], self.vel_t[0])
        end = min(self.joy_t[-1], self.vel_t[-1])
        return float(max(0.0, end - start))
