"""Raw, irregularly timed sensor streams as they come out of a bag or a live buffer.

This is the hand-over type between the bag reader / simulator and the resampler:

* joystick ``J``: forward and turn deflection in [-1, 1] (+ forward, + left/CCW),
* velocity ``V``: the chair's planar twist (v [m/s], omega [rad/s]) from visual odometry,
* optionally the ground truth of a simulator (pose and twist).

Times are seconds on one clock (header stamps, or bag receive time when a message has
no valid header). Arrays are sorted by time on construction; of exact duplicate stamps
the last to arrive is kept (a sensor's newer reading: a joystick bridge that read a
backlog at once, a driver that republished).

Ranges (inclusive; defined here and nowhere else). A sample outside them is not data
about a wheelchair: the resampler drops it as it drops a non-finite one, and the online
``Predictor`` refuses it with a reason code.

* time stamps: ``|t| <= MAX_ABS_TIME_S`` = 1e10 s (Unix time until 2286; keeps
  ``t * rate`` exact on the grid);
* joystick deflections: ``|j| <= MAX_ABS_JOY`` = 1 + ``JOY_TOLERANCE`` (0.05 of stick
  calibration overshoot beyond [-1, 1]);
* forward speed: ``|v| <= MAX_ABS_SPEED`` = 5 m/s (powered wheelchairs are limited to
  about 4 m/s, 15 km/h);
* yaw rate: ``|omega| <= MAX_ABS_YAW_RATE`` = 10 rad/s (a chair spinning on the spot turns
  at 2-3 rad/s);
* odometry poses: ``|x|, |y| <= MAX_ABS_POSITION`` = 1e6 m (1000 km from the odometry
  origin), ``|yaw| <= MAX_ABS_YAW`` = 1e4 rad (yaw unwrapped over 1500 turns).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: Largest |time stamp| (s) accepted anywhere.
MAX_ABS_TIME_S = 1e10
#: How far a joystick deflection may overshoot [-1, 1] (calibration of a real stick).
JOY_TOLERANCE = 0.05
#: Largest |deflection| accepted (forward and turn).
MAX_ABS_JOY = 1.0 + JOY_TOLERANCE
#: Largest |v| (m/s) accepted: beyond any powered wheelchair.
MAX_ABS_SPEED = 5.0
#: Largest |omega| (rad/s) accepted: beyond any powered wheelchair.
MAX_ABS_YAW_RATE = 10.0
#: Largest |x|, |y| (m) of an odometry pose accepted.
MAX_ABS_POSITION = 1e6
#: Largest |yaw| (rad) of an odometry pose accepted.
MAX_ABS_YAW = 1e4
#: Twist variance at or above which odometry reports a tracking failure (vo_node publishes
#: a lost frame's twist as zero with this variance).
ODOM_LOST_VARIANCE = 1e6


def twist_tracked(v: float, omega: float, var_v: float, var_omega: float) -> bool:
    """Whether a twist with covariance (nav_msgs/Odometry,
    geometry_msgs/TwistWithCovarianceStamped) reports tracking: its v and omega finite and
    their variances (``covariance[0]``, ``[35]``) finite, non-negative and below
    ``ODOM_LOST_VARIANCE``. The one rule of the nodes and of reading a bag."""
    return (math.isfinite(v) and math.isfinite(omega)
            and all(math.isfinite(var) and 0.0 <= var < ODOM_LOST_VARIANCE
                    for var in (var_v, var_omega)))


def joy_in_range(joy: object) -> BoolArray:
    """[N] True where the [N, 2] deflections are finite and within ``MAX_ABS_JOY``."""
    arr = np.asarray(joy, dtype=np.float64).reshape(-1, 2)
    with np.errstate(invalid="ignore"):
        return np.asarray(np.all(np.abs(arr) <= MAX_ABS_JOY, axis=1), dtype=bool)


def vel_in_range(vel: object) -> BoolArray:
    """[N] True where the [N, 2] (v, omega) are finite and within the physical limits."""
    arr = np.asarray(vel, dtype=np.float64).reshape(-1, 2)
    with np.errstate(invalid="ignore"):
        ok = (np.abs(arr[:, 0]) <= MAX_ABS_SPEED) & (np.abs(arr[:, 1]) <= MAX_ABS_YAW_RATE)
    return np.asarray(ok, dtype=bool)


def joy_problem(forward: float, turn: float) -> str | None:
    """Why a joystick sample is refused (non-finite or out of range), or None."""
    for name, value in (("forward", forward), ("turn", turn)):
        if not math.isfinite(value):
            return f"{name} deflection is {value}"
        if abs(value) > MAX_ABS_JOY:
            return f"{name} deflection {value:g} is outside [-{MAX_ABS_JOY:g}, {MAX_ABS_JOY:g}]"
    return None


def vel_problem(v: float, omega: float) -> str | None:
    """Why a velocity sample is refused (non-finite or beyond physical limits), or None."""
    for name, value, limit, unit in (("v", v, MAX_ABS_SPEED, "m/s"),
                                     ("omega", omega, MAX_ABS_YAW_RATE, "rad/s")):
        if not math.isfinite(value):
            return f"{name} is {value}"
        if abs(value) > limit:
            return f"|{name}| = {abs(value):g} {unit} is beyond {limit:g} {unit}"
    return None


def pose_problem(x: float, y: float, yaw: float) -> str | None:
    """Why an odometry pose is refused (non-finite or beyond the ranges), or None."""
    for name, value, limit in (("x", x, MAX_ABS_POSITION), ("y", y, MAX_ABS_POSITION),
                               ("yaw", yaw, MAX_ABS_YAW)):
        if not math.isfinite(value):
            return f"pose {name} is {value}"
        if abs(value) > limit:
            return f"pose |{name}| = {abs(value):g} is beyond {limit:g}"
    return None


def time_problem(t: float) -> str | None:
    """Why a time stamp is refused (non-finite or beyond ``MAX_ABS_TIME_S``), or None."""
    if not math.isfinite(t):
        return f"time stamp is {t}"
    if abs(t) > MAX_ABS_TIME_S:
        return f"time stamp {t:g} s is beyond +-{MAX_ABS_TIME_S:g} s"
    return None


def _sorted_unique(t: FloatArray, *values: FloatArray) -> tuple[FloatArray, ...]:
    order = np.argsort(t, kind="stable")
    t = t[order]
    keep = np.ones(t.shape[0], dtype=bool)
    keep[:-1] = np.diff(t) > 0.0  # of equal stamps, the last to arrive (the sort is stable)
    return (t[keep], *(v[order][keep] for v in values))


def _as_times(name: str, t: object) -> FloatArray:
    t_arr = np.asarray(t, dtype=np.float64).reshape(-1)
    if not np.all(np.isfinite(t_arr)):
        raise ValueError(f"{name}: time stamps contain NaN or inf")
    if t_arr.size and float(np.max(np.abs(t_arr))) > MAX_ABS_TIME_S:
        raise ValueError(f"{name}: time stamps beyond +-{MAX_ABS_TIME_S:g} s")
    return t_arr


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
    return _as_times(name, t_arr), x_arr


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
        override_t: [No] times at which an override command (``joy_override``) was sent
            to the chair, or empty: around them the joystick is not what drove the chair
            (:mod:`asgp_ros.core.resample`, "Validity").
        digests: by topic, digests of the messages read from a bag (what identifies the
            recording in any storage: :func:`asgp_ros.recording.bags.recording_identity`);
            empty for data not read from a bag.
    """

    joy_t: FloatArray
    joy: FloatArray
    vel_t: FloatArray
    vel: FloatArray
    vel_ok: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, dtype=bool))
    truth_t: FloatArray = field(default_factory=lambda: np.zeros(0))
    truth: FloatArray = field(default_factory=lambda: np.zeros((0, 5)))
    source: str = ""
    override_t: FloatArray = field(default_factory=lambda: np.zeros(0))
    digests: Mapping[str, Any] = field(default_factory=dict)

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
        override_t = np.unique(_as_times("override", self.override_t))
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
        object.__setattr__(self, "override_t", override_t)

    @property
    def has_truth(self) -> bool:
        return cast(bool, self.truth_t.shape[0] > 0)

    @property
    def duration(self) -> float:
        """Seconds covered by both joystick and velocity (0 if they do not overlap)."""
        if self.joy_t.size == 0 or self.vel_t.size == 0:
            return 0.0
        start = max(self.joy_t[0], self.vel_t[0])
        end = min(self.joy_t[-1], self.vel_t[-1])
        return float(max(0.0, end - start))
