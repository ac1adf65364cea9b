"""Resampling of raw joystick and odometry streams onto the common grid.

The paper resamples both streams by linear interpolation onto a 5 Hz grid (Fan et al.,
ICRA 2018, Sec. IV). Here the grid is absolute: grid point k is at ``t_k = k / rate_hz``
on the streams' clock, so an online sliding buffer and an offline recording give the same
grid points.

Silences: the grid has no points inside a stretch of more than ``GRID_SILENCE_S`` (or
either stream's max gap, if longer) without a joystick or odometry sample, other than the
first and the last grid point inside it. Every point inside such a stretch is invalid
(both streams' samples around it are too far apart), so the points left out could never
form a row; the two kept, invalid too, keep the runs of valid points on either side
apart, as the whole stretch did. A drive recorded with the clock set forward a day, or two
drives days apart in one bag, then costs the memory and time of its data, not of its span
(a 20-day gap was 8.6 million grid points, 1.5 GB, for 2 minutes of data). ``Resampled.k``
is consecutive except across such a stretch; nothing else changes at the points kept.

Locality (what makes online and offline agree): the value at a grid point depends only on
the two raw samples that bracket it in each stream (``x_i + w (x_{i+1} - x_i)`` with
``w = (t - t_i) / (t_{i+1} - t_i)``; exactly ``x_i`` when ``t == t_i``). Calling
:func:`resample` on any window of raw samples therefore gives bit-identical ``t``, ``joy``
and ``vel`` at every grid point the window covers, and identical gap and tracking flags.
Stale-odometry flags depend on the run of repeated (or still) values a point belongs to
and on the joystick since the run began; they agree wherever that run, and the joystick
from its start, lie inside the window (a run cut by the window's edge can only be judged by
what the window holds, as an online buffer must).

Odometry stamps (``ResampleConfig.vel_stamp``): a frame-to-frame visual odometry (Fovis,
:mod:`asgp_ros.vo`) reports the displacement between the previous frame and this one
divided by their interval, stamped with this frame's time: the mean velocity over the
interval, which is the velocity at its middle to second order, not at its end. Read at the
frame's stamp (``"frame"``), the odometry lags the chair by half a frame interval (about
0.1 s at 4-7 Hz), and a path integrated from it falls behind the real one whenever the
speed changes. ``"midpoint"`` (the default) moves every sample to the middle of the
interval from the previous sample, when that interval is at most ``max_gap_vel_s`` (one
frame's, not a gap); the first sample, and the first after a longer interval, have no
known interval and are dropped. Times come from the recorded stamps, so a sample whose
value is dropped (below) still marks its frame. With midpoint stamps a sample's time also
depends on its predecessor; the first sample of a window, which has none there, is
dropped, so the window property below still holds for every grid point the window gives.
Model files record the setting; files from before it existed resample as ``"frame"``.

Validity of a grid point (``Resampled.valid``):

* both streams have a sample at or around it, with the bracketing samples no further
  apart than ``max_gap_joy_s`` / ``max_gap_vel_s`` (no interpolation across a gap);
* no odometry sample it uses reported a tracking failure (``RawStreams.vel_ok``);
* no odometry sample it uses is stale: visual odometry that loses its features keeps
  reporting the last velocity (as Fovis does). Within a run of samples repeating the same
  velocity (within ``stale_tolerance`` of the previous sample), the repeats are stale

  - all of them, if the repeated velocity is not zero (beyond ``stale_still_speed``; real
    odometry never repeats a non-zero reading exactly) and the run lasts at least
    ``stale_after_s``;
  - for a repeated zero (a chair at rest legitimately reads zero), those from the moment
    the joystick has been deflected beyond ``stale_joy_threshold`` for
    ``stale_still_after_s`` since the run began (the chair is driven, the odometry does
    not change).

  The first sample of a run (the last genuine measurement) is kept;
* no odometry sample it uses reads the chair held while it is pushed: within ``held_speed``
  (|v| and |omega|, whatever the odometry's noise) while the joystick has been deflected
  beyond ``held_joy_threshold`` for ``held_after_s`` without a pause, counted from the later
  of the deflection's start and the first still reading. Either the odometry is stuck near
  zero with a little jitter, which the repeat rules above cannot see, or the chair is held
  (against an obstacle, brakes on, drive inhibited); in neither case is it the chair's
  response to the stick, and a row that taught it would make a model, or an adapting
  predictor, expect a chair that does not start. The deflection is large (0.5 by default)
  because at a small one a chair may really creep at a few cm/s. Model files made before
  this rule keep it off (``held_after_s`` inf), so they resample as they were trained.

  The flagged grid points of both rules are in ``Resampled.stale``;
* no override may have driven the chair around it (``Resampled.overridden``, from
  ``RawStreams.override_t``): while the shared-control layer or a planner overrides the
  user through the board, the recorded joystick is not what drove the chair, and a row
  that pairs them would teach the model, or score it on, a response the chair never had.
  An override sent at time o may drive the chair until o + ``override_hold_s``; the
  velocity at grid point t answers the commands of the period before it (and, read at the
  middle of a frame interval, of up to a period after it), so t is overridden when some o
  lies in (t - dt - ``override_hold_s``, t + dt].  Every override sent counts, whether or
  not the board applied it (the firmware ignores one while the stick is neutral; the
  bridge may have been down): a row is refused when in doubt.

Raw samples that are not finite or lie outside the physical ranges of
:mod:`asgp_ros.core.streams` (``MAX_ABS_JOY``, ``MAX_ABS_SPEED_M_S``,
``MAX_ABS_YAW_RATE_RAD_S``) are dropped before anything else (and counted in
``Resampled.dropped_joy`` / ``dropped_vel``); the hole they leave is then an ordinary gap.

Ranges (every setting of :class:`ResampleConfig` is checked against ``RESAMPLE_RANGES`` on
construction, so a model file or a command line cannot bring in a grid the code cannot
handle): the grid rate is 0.5-100 Hz; grid indices stay within ``MAX_GRID_INDEX`` (so
``k / rate_hz`` is exact in float64) and one call makes at most ``MAX_GRID_POINTS`` points
(silences left out); :func:`grid_indices` raises ValueError beyond either.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from asgp_ros.core.streams import RawStreams, joy_in_range, vel_in_range

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

logger = logging.getLogger(__name__)


#: Documented range (inclusive) of every :class:`ResampleConfig` setting. The grid rate
#: spans 2 s steps to the joystick's 100 Hz; durations are at most an hour (a gap or a
#: staleness window longer than that is not a sensor property); the staleness durations
#: in ``RESAMPLE_MAY_BE_INF`` may also be ``math.inf`` (disabled).
RESAMPLE_RANGES: dict[str, tuple[float, float]] = {
    "rate_hz": (0.5, 100.0),
    "max_gap_joy_s": (1e-3, 3600.0),
    "max_gap_vel_s": (1e-3, 3600.0),
    "stale_after_s": (1e-3, 3600.0),
    "stale_tolerance": (0.0, 1.0),
    "stale_joy_threshold": (0.0, 1.0),
    "stale_still_speed": (0.0, 1.0),
    "stale_still_after_s": (1e-3, 3600.0),
    "override_hold_s": (0.0, 3600.0),
    "held_speed": (0.0, 1.0),
    "held_joy_threshold": (0.0, 1.0),
    "held_after_s": (1e-3, 3600.0),
}
RESAMPLE_MAY_BE_INF = ("stale_after_s", "stale_still_after_s", "held_after_s")
#: What an odometry sample's stamp is taken to mean (``ResampleConfig.vel_stamp``).
VEL_STAMPS = ("midpoint", "frame")

#: Largest |t * rate_hz| on the grid: below 2**50 a grid index and ``k / rate_hz`` are exact
#: in float64 (times within ``streams.MAX_ABS_TIME_S`` at 100 Hz are far below it).
MAX_GRID_INDEX = 2**50
#: Most grid points one call may produce (23 days at 5 Hz, 28 hours at 100 Hz): beyond it
#: the arrays of one resample would not fit in a laptop's memory.
MAX_GRID_POINTS = 10_000_000
#: A stretch longer than this (s) without a joystick or odometry sample has no grid points
#: but its first and last (see "Silences" in the module docstring): well above a sensor's
#: dropout, so the grid of a drive without such a stretch is every point of its span.
GRID_SILENCE_S = 10.0


@dataclass(frozen=True)
class ResampleConfig:
    """Settings of :func:`resample` (validated on construction against
    ``RESAMPLE_RANGES``: a value outside its range raises ValueError naming the setting).

    Attributes:
        rate_hz: grid rate; grid points at integer multiples of 1 / rate_hz.
        max_gap_joy_s: no interpolation of the joystick across a longer gap (~30 Hz input).
        max_gap_vel_s: no interpolation of the odometry across a longer gap (4-7 Hz input).
        stale_after_s: a run of repeated odometry readings this long can be stale
            (``math.inf`` disables stale detection).
        stale_tolerance: readings within this (m/s, rad/s, per component) of the previous
            one count as repeated.
        stale_joy_threshold: the joystick counts as moving while max(|fwd|, |turn|) exceeds
            this deflection.
        stale_still_speed: a repeated reading with |v| and |omega| below this is "zero".
        stale_still_after_s: a repeated zero is stale once the joystick has been deflected
            this long since the repeats began (longer than the chair's start-up lag, so a
            chair that has not started moving yet is not flagged; ``math.inf`` disables).
        vel_stamp: the time an odometry velocity describes (see "Odometry stamps" in the
            module docstring): ``"midpoint"`` (default), the middle of the interval from
            the previous sample; ``"frame"``, its own stamp, as recorded.
        override_hold_s: how long an override command may drive the chair after it was
            sent (``RawStreams.override_t``): the bridge re-sends one while it is fresh
            (0.15 s) and the board's watchdog holds the last one sent for 0.2 s.
        held_speed: a reading with |v| (m/s) and |omega| (rad/s) at most this reads the
            chair still, noise included (3 cm/s and 0.03 rad/s: an odometry's noise at
            rest lies below, a chair pushed with ``held_joy_threshold`` moves above).
        held_joy_threshold: the joystick pushes the chair while max(|fwd|, |turn|) exceeds
            this deflection (for the held rule only).
        held_after_s: readings are stale once they have read still this long while the
            joystick was pushed without a pause (``math.inf`` disables; model files from
            before the rule).
    """

    rate_hz: float = 5.0
    max_gap_joy_s: float = 0.3
    max_gap_vel_s: float = 0.6
    stale_after_s: float = 0.5
    stale_tolerance: float = 1e-9
    stale_joy_threshold: float = 0.2
    stale_still_speed: float = 1e-3
    stale_still_after_s: float = 0.6
    vel_stamp: str = "midpoint"
    override_hold_s: float = 0.4
    held_speed: float = 0.03
    held_joy_threshold: float = 0.5
    held_after_s: float = 0.6

    def __post_init__(self) -> None:
        if self.vel_stamp not in VEL_STAMPS:
            raise ValueError(f"vel_stamp must be one of {VEL_STAMPS}, got {self.vel_stamp!r}")
        for name, (low, high) in RESAMPLE_RANGES.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float | np.number):
                raise ValueError(f"{name} must be a number, got {value!r}")
            try:
                value = float(value)
            except OverflowError:  # an integer beyond float's range (a hostile file)
                raise ValueError(f"{name} must be in [{low:g}, {high:g}], got an integer "
                                 "too large for a float") from None
            disabled = name in RESAMPLE_MAY_BE_INF and value == math.inf
            if not (disabled or low <= value <= high):
                extra = " or inf (disabled)" if name in RESAMPLE_MAY_BE_INF else ""
                raise ValueError(f"{name} must be in [{low:g}, {high:g}]{extra}, got {value}")
            object.__setattr__(self, name, value)

    @property
    def dt(self) -> float:
        """Grid period (s)."""
        return 1.0 / self.rate_hz

    def to_dict(self) -> dict[str, Any]:
        """JSON-able dict (an infinite duration, i.e. disabled, is stored as None)."""
        d = asdict(self)
        for name in RESAMPLE_MAY_BE_INF:
            if math.isinf(d[name]):
                d[name] = None
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ResampleConfig:
        names = {f for f in cls.__dataclass_fields__}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown resample settings: {sorted(unknown)}")
        d = dict(d)
        # settings stored before odometry stamps were a setting were resampled as recorded
        d.setdefault("vel_stamp", "frame")
        # settings stored before the held-chair rule resample without it, as trained
        d.setdefault("held_after_s", None)
        for name in RESAMPLE_MAY_BE_INF:
            if name in d and d[name] is None:
                d[name] = math.inf
        return cls(**d)


def learning_config(config: ResampleConfig) -> ResampleConfig:
    """The settings adaptation learns under, for a model resampled with ``config``: the
    same, with the held-chair rule at its default where ``config`` has it off (a model file
    from before the rule, or trained without it). A chair held against an obstacle while
    the stick pushes teaches no model; the rule only invalidates more points, so the rows
    that remain are formed exactly as the model predicts from them."""
    if math.isinf(config.held_after_s):
        return dataclasses.replace(config, held_after_s=ResampleConfig().held_after_s)
    return config


@dataclass(frozen=True)
class Resampled:
    """Streams on the common grid.

    Attributes:
        t: [T] grid times (s), ``t == k / rate_hz``.
        k: [T] integer grid indices, increasing: consecutive except across a silence
            (module docstring), whose kept first and last points are invalid.
        joy: [T, 2] joystick (forward, turn).
        vel: [T, 2] odometry velocity (v, omega).
        valid: [T] usable points (see the module docstring).
        stale: [T] the odometry at this point uses stale (repeated) readings.
        tracking_lost: [T] the odometry at this point uses a reading flagged as a failure.
        gap: [T] a stream has a gap longer than its limit around this point.
        segment: [T] id of the maximal run of valid points (0, 1, ...), -1 if invalid.
        truth: [T, 5] ground truth (x, y, theta, v, omega) interpolated (theta unwrapped
            before interpolation), NaN where ``truth_valid`` is False; [T, 5] of NaN when
            the streams have no ground truth.
        truth_valid: [T] ground truth available around this point.
        rate_hz: grid rate.
        dropped_joy: number of joystick samples dropped (non-finite or out of range).
        dropped_vel: number of odometry samples dropped (non-finite or out of range).
        source: where the streams came from (for messages).
        overridden: [T] an override may have driven the chair around this point (see
            "Validity" in the module docstring); all False when built without it.
    """

    t: FloatArray
    k: IntArray
    joy: FloatArray
    vel: FloatArray
    valid: BoolArray
    stale: BoolArray
    tracking_lost: BoolArray
    gap: BoolArray
    segment: IntArray
    truth: FloatArray
    truth_valid: BoolArray
    rate_hz: float
    dropped_joy: int = 0
    dropped_vel: int = 0
    source: str = field(default="")
    overridden: BoolArray = field(default_factory=lambda: np.zeros(0, dtype=bool))

    def __post_init__(self) -> None:
        if self.overridden.shape[0] != self.t.shape[0]:
            if self.overridden.shape[0]:
                raise ValueError(f"{self.overridden.shape[0]} overridden flags for "
                                 f"{self.t.shape[0]} grid points")
            object.__setattr__(self, "overridden", np.zeros(self.t.shape[0], dtype=bool))

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def segments(self) -> list[slice]:
        """Slices of the maximal runs of valid points, in time order."""
        return segment_slices(self.segment)


def segment_slices(segment: IntArray) -> list[slice]:
    """Slices [start, stop) of the maximal runs of equal non-negative ids in ``segment``."""
    seg = np.asarray(segment)
    if seg.size == 0:
        return []
    starts = np.flatnonzero(np.r_[True, seg[1:] != seg[:-1]])
    stops = np.r_[starts[1:], seg.size]
    return [slice(int(a), int(b)) for a, b in zip(starts, stops, strict=True) if seg[a] >= 0]


def _drop_nonfinite(t: FloatArray, x: FloatArray) -> BoolArray:
    return np.asarray(np.all(np.isfinite(x), axis=1) & np.isfinite(t), dtype=bool)


def grid_indices(t_start: float, t_end: float, rate_hz: float,
                 silences: FloatArray | None = None) -> IntArray:
    """Integer k with ``t_start <= k / rate_hz <= t_end`` (increasing, possibly empty),
    less those strictly inside a silence other than the first and the last there.

    Args:
        silences: [G, 2] sorted, disjoint open intervals (a, b) of time, each inside
            [t_start, t_end] (see "Silences" in the module docstring); None for none: the
            indices are then consecutive.

    Raises:
        ValueError: ``rate_hz`` not positive and finite, ``|t * rate_hz|`` beyond
            ``MAX_GRID_INDEX`` (the grid index would not be exact), or more than
            ``MAX_GRID_POINTS`` points.
    """
    if not (math.isfinite(rate_hz) and rate_hz > 0.0):
        raise ValueError(f"grid rate must be positive and finite, got {rate_hz}")
    if not t_end >= t_start:  # also NaN
        return np.zeros(0, dtype=np.int64)
    for t in (t_start, t_end):
        if not abs(t) * rate_hz <= MAX_GRID_INDEX:
            raise ValueError(f"time {t} s at {rate_hz:g} Hz is beyond the grid's range "
                             f"(|t * rate| <= 2**50)")
    lo = int(_first_at_or_after(np.array([t_start]), rate_hz)[0])
    hi = int(_last_at_or_before(np.array([t_end]), rate_hz)[0])
    if hi < lo:
        return np.zeros(0, dtype=np.int64)
    # stretches [starts, stops] of kept indices: each silence keeps its first grid point
    # (the first after a) and its last (the last before b), and drops those between
    starts = np.array([lo], dtype=np.int64)
    stops = np.array([hi], dtype=np.int64)
    if silences is not None and len(silences):
        gaps = np.asarray(silences, dtype=np.float64).reshape(-1, 2)
        first = _last_at_or_before(gaps[:, 0], rate_hz) + 1
        last = _first_at_or_after(gaps[:, 1], rate_hz) - 1
        drop = last - first >= 2
        starts = np.r_[lo, last[drop]]
        stops = np.r_[first[drop], hi]
    lengths = stops - starts + 1
    total = int(lengths.sum())
    if total > MAX_GRID_POINTS:
        outside = " outside its silences" if starts.size > 1 else ""
        raise ValueError(f"{t_start:.3f} .. {t_end:.3f} s at {rate_hz:g} Hz is "
                         f"{total} grid points{outside}, more than {MAX_GRID_POINTS}")
    if starts.size == 1:
        return np.arange(lo, hi + 1, dtype=np.int64)
    offset = np.repeat(starts - np.r_[0, np.cumsum(lengths)[:-1]], lengths)
    k: IntArray = offset + np.arange(total, dtype=np.int64)
    return k


def _first_at_or_after(t: FloatArray, rate_hz: float) -> IntArray:
    """[N] the least integer k with ``k / rate_hz >= t`` (``|t * rate_hz|`` within
    ``MAX_GRID_INDEX``)."""
    k = np.ceil(t * rate_hz).astype(np.int64)
    # The float rounding of t * rate can put k one index off (never more below
    # MAX_GRID_INDEX); two corrections are always enough.
    for _ in range(2):
        k = np.where((k - 1) / rate_hz >= t, k - 1, np.where(k / rate_hz < t, k + 1, k))
    return k


def _last_at_or_before(t: FloatArray, rate_hz: float) -> IntArray:
    """[N] the greatest integer k with ``k / rate_hz <= t`` (as :func:`_first_at_or_after`)."""
    k = np.floor(t * rate_hz).astype(np.int64)
    for _ in range(2):
        k = np.where((k + 1) / rate_hz <= t, k + 1, np.where(k / rate_hz > t, k - 1, k))
    return k


def find_silences(times: FloatArray, longer_than_s: float) -> FloatArray:
    """[G, 2] the stretches (a, b) between consecutive ``times`` (sorted) more than
    ``longer_than_s`` apart."""
    t = np.asarray(times, dtype=np.float64)
    if t.size < 2:
        return np.zeros((0, 2))
    at = np.flatnonzero(np.diff(t) > longer_than_s)
    return np.stack([t[at], t[at + 1]], axis=1)


class _Bracket:
    """The two samples around each grid time, and the interpolation weight of the second.

    ``i`` is the last sample at or before t, ``j = i + 1`` (or ``i`` at the end); ``w`` is 0
    on an exact hit, so the value is exactly the sample there.
    """

    def __init__(self, ts: FloatArray, t: FloatArray) -> None:
        n = ts.shape[0]
        i = np.searchsorted(ts, t, side="right") - 1
        i = np.clip(i, 0, n - 1)
        j = np.minimum(i + 1, n - 1)
        span = ts[j] - ts[i]
        w = np.zeros(t.shape[0])
        np.divide(t - ts[i], span, out=w, where=span > 0.0)
        hit = t == ts[i]
        w[hit] = 0.0
        self.i, self.j, self.w, self.span, self.hit = i, j, w, span, hit

    def interp(self, x: FloatArray) -> FloatArray:
        x0 = x[self.i]
        x1 = x[self.j]
        out: FloatArray = x0 + self.w[:, None] * (x1 - x0)
        return out

    def within(self, max_gap: float) -> BoolArray:
        return np.asarray(self.hit | (self.span <= max_gap), dtype=bool)

    def uses(self, flag: BoolArray) -> BoolArray:
        """True where a sample with non-zero weight has ``flag`` set."""
        return np.asarray(flag[self.i] | ((self.w > 0.0) & flag[self.j]), dtype=bool)


def midpoint_stamps(vel_t: FloatArray, max_interval_s: float) -> tuple[FloatArray, BoolArray]:
    """The middle of each odometry sample's interval (module docstring, "Odometry stamps").

    Args:
        vel_t: [N] strictly increasing stamps, as recorded (a frame's time).
        max_interval_s: an interval longer than this is not one frame's: the sample after
            it has no known interval.

    Returns:
        ([N] times: ``(t[i-1] + t[i]) / 2``, strictly increasing; [N] known: False for the
        first sample and for a sample after a longer interval, whose time is left as
        recorded and which the caller drops).
    """
    t = np.asarray(vel_t, dtype=np.float64)
    known = np.zeros(t.shape[0], dtype=bool)
    out = t.copy()
    if t.shape[0] > 1:
        gap = np.diff(t)
        known[1:] = gap <= max_interval_s
        out[1:] = np.where(known[1:], t[:-1] + 0.5 * gap, t[1:])
    return out, known


def stale_samples(vel_t: FloatArray, vel: FloatArray, joy_t: FloatArray, joy: FloatArray,
                  config: ResampleConfig) -> BoolArray:
    """Odometry samples that repeat a frozen reading (see the module docstring).

    Args:
        vel_t: [Nv] sorted odometry times; vel: [Nv, 2] finite readings.
        joy_t: [Nj] sorted joystick times; joy: [Nj, 2] finite deflections.

    Returns:
        [Nv] True for the repeats of a stale run (not its first sample).
    """
    n = vel_t.shape[0]
    stale = np.zeros(n, dtype=bool)
    if joy_t.shape[0] > 0 and not math.isinf(config.held_after_s):
        # its own setting: the repeat rules switched off (stale_after_s inf) leave it on
        stale |= held_samples(vel_t, vel, joy_t, joy, config)
    if n < 2 or math.isinf(config.stale_after_s):
        return stale
    same = np.all(np.abs(np.diff(vel, axis=0)) <= config.stale_tolerance, axis=1)  # [Nv-1]
    # runs of repeated readings: a run starts where a sample differs from its predecessor
    is_start = np.r_[True, ~same]
    run = np.cumsum(is_start) - 1  # [Nv] run id of each sample
    starts = np.flatnonzero(is_start)
    ends = np.r_[starts[1:], n] - 1  # inclusive
    repeat = ~is_start  # the first sample of a run is a genuine measurement

    # a repeated non-zero reading: the whole run once it lasts stale_after_s
    moving = np.any(np.abs(vel[starts]) > config.stale_still_speed, axis=1)
    long_run = (vel_t[ends] - vel_t[starts]) >= config.stale_after_s
    stale |= repeat & (moving & long_run)[run]

    # a repeated zero while the chair is driven: from the moment the joystick has been
    # deflected for stale_still_after_s since the run began (zero-order hold)
    if joy_t.shape[0] > 0 and not math.isinf(config.stale_still_after_s):
        active = np.max(np.abs(joy), axis=1) > config.stale_joy_threshold
        cum = np.zeros(joy_t.shape[0])
        cum[1:] = np.cumsum(active[:-1] * np.diff(joy_t))
        cum_v = np.interp(vel_t, joy_t, cum)  # [Nv] active time up to each sample
        driven = (cum_v - cum_v[starts][run]) >= config.stale_still_after_s
        stale |= repeat & ~moving[run] & driven
    return stale


def held_samples(vel_t: FloatArray, vel: FloatArray, joy_t: FloatArray, joy: FloatArray,
                 config: ResampleConfig) -> BoolArray:
    """Odometry samples that read the chair held while it is pushed (module docstring):
    still (within ``held_speed``) since at least ``held_after_s`` ago, while the joystick
    (zero-order hold) has been deflected beyond ``held_joy_threshold`` without a pause for
    as long. A pause of the stick starts the count again: a chair released and pushed once
    more has its start-up lag again.

    Args / Returns: as :func:`stale_samples` (joy_t non-empty).
    """
    still = np.all(np.abs(vel) <= config.held_speed, axis=1)  # [Nv]
    # the time each still sample's stretch of still readings began
    first = still & ~np.r_[False, still[:-1]]
    still_since = np.where(still, np.maximum.accumulate(np.where(first, vel_t, -np.inf)),
                           np.inf)
    pushed = np.max(np.abs(joy), axis=1) > config.held_joy_threshold  # [Nj]
    # the time each joystick sample's stretch of deflection began (inf: not deflected)
    began = np.where(pushed & ~np.r_[False, pushed[:-1]], joy_t, -np.inf)
    began = np.where(pushed, np.maximum.accumulate(began), np.inf)
    j = np.searchsorted(joy_t, vel_t, side="right") - 1  # [Nv] the joystick sample held then
    pushed_since = np.where(j >= 0, began[np.maximum(j, 0)], np.inf)
    held: BoolArray = still & (vel_t - np.maximum(still_since, pushed_since)
                               >= config.held_after_s)
    return held


def resample(streams: RawStreams, config: ResampleConfig | None = None) -> Resampled:
    """Resample raw streams onto the absolute grid ``k / rate_hz`` (linear interpolation).

    The grid covers the time both streams cover (from the later first sample to the
    earlier last sample); an empty :class:`Resampled` results when they do not overlap.
    See the module docstring for validity, staleness and the window property.
    """
    cfg = config if config is not None else ResampleConfig()
    keep_j = joy_in_range(streams.joy)
    keep_v = vel_in_range(streams.vel)
    dropped_joy = int(keep_j.size - np.count_nonzero(keep_j))
    dropped_vel = int(keep_v.size - np.count_nonzero(keep_v))
    if dropped_joy or dropped_vel:
        logger.debug("%s: dropped %d joystick and %d odometry samples (non-finite or out "
                     "of range)", streams.source or "streams", dropped_joy, dropped_vel)
    joy_t, joy = streams.joy_t[keep_j], streams.joy[keep_j]
    vel_t = streams.vel_t
    if cfg.vel_stamp == "midpoint":
        vel_t, known = midpoint_stamps(vel_t, cfg.max_gap_vel_s)
        keep_v &= known
    vel_t, vel, vel_ok = vel_t[keep_v], streams.vel[keep_v], streams.vel_ok[keep_v]

    if joy_t.size and vel_t.size:
        start, end = max(joy_t[0], vel_t[0]), min(joy_t[-1], vel_t[-1])
        quiet = find_silences(np.sort(np.concatenate([joy_t, vel_t])),
                              max(GRID_SILENCE_S, cfg.max_gap_joy_s, cfg.max_gap_vel_s))
        quiet = quiet[(quiet[:, 0] >= start) & (quiet[:, 1] <= end)]
        k = grid_indices(start, end, cfg.rate_hz, quiet)
        if quiet.shape[0]:
            logger.debug("%s: the grid leaves out %d stretch(es) without a sample (the "
                         "longest %.0f s)", streams.source or "streams", quiet.shape[0],
                         float(np.max(quiet[:, 1] - quiet[:, 0])))
    else:
        k = np.zeros(0, dtype=np.int64)
    t = k / cfg.rate_hz
    T = t.shape[0]
    if T == 0:
        empty_b = np.zeros(0, dtype=bool)
        return Resampled(
            t=t, k=k, joy=np.zeros((0, 2)), vel=np.zeros((0, 2)), valid=empty_b,
            stale=empty_b, tracking_lost=empty_b, gap=empty_b,
            segment=np.zeros(0, dtype=np.int64), truth=np.zeros((0, 5)),
            truth_valid=empty_b, rate_hz=cfg.rate_hz, dropped_joy=dropped_joy,
            dropped_vel=dropped_vel, source=streams.source,
        )

    bj = _Bracket(joy_t, t)
    bv = _Bracket(vel_t, t)
    joy_g = bj.interp(joy)
    vel_g = bv.interp(vel)
    gap = ~(bj.within(cfg.max_gap_joy_s) & bv.within(cfg.max_gap_vel_s))
    tracking_lost = bv.uses(~vel_ok)
    stale = bv.uses(stale_samples(vel_t, vel, joy_t, joy, cfg))
    overridden = overridden_points(t, streams.override_t, cfg)
    valid = ~(gap | tracking_lost | stale | overridden)
    segment = segment_ids(valid)

    truth = np.full((T, 5), np.nan)
    truth_valid = np.zeros(T, dtype=bool)
    if streams.has_truth:
        keep_t = _drop_nonfinite(streams.truth_t, streams.truth)
        tt, tv = streams.truth_t[keep_t], streams.truth[keep_t].copy()
        if tt.size:
            tv[:, 2] = np.unwrap(tv[:, 2])
            inside = (t >= tt[0]) & (t <= tt[-1])
            bt = _Bracket(tt, t)
            truth_valid = inside & bt.within(cfg.max_gap_vel_s)
            truth[truth_valid] = bt.interp(tv)[truth_valid]

    return Resampled(
        t=t, k=k, joy=joy_g, vel=vel_g, valid=valid, stale=stale,
        tracking_lost=tracking_lost, gap=gap, segment=segment, truth=truth,
        truth_valid=truth_valid, rate_hz=cfg.rate_hz, dropped_joy=dropped_joy,
        dropped_vel=dropped_vel, source=streams.source, overridden=overridden,
    )


def segment_ids(valid: BoolArray) -> IntArray:
    """``Resampled.segment`` of a validity mask: the id of each point's maximal run of
    valid points (0, 1, ...), -1 where invalid."""
    valid = np.asarray(valid, dtype=bool)
    segment = -np.ones(valid.shape[0], dtype=np.int64)
    starts = valid & np.r_[True, ~valid[:-1]]
    segment[valid] = (np.cumsum(starts) - 1)[valid]
    return segment


def overridden_points(t: FloatArray, override_t: FloatArray, config: ResampleConfig
                      ) -> BoolArray:
    """The grid points ``t`` [T] an override sent at one of ``override_t`` may have driven:
    some o in (t - dt - ``override_hold_s``, t + dt] (see "Validity" in the module
    docstring).  ``override_t`` must be sorted (``RawStreams.override_t`` is)."""
    t = np.asarray(t, dtype=np.float64)
    o = np.asarray(override_t, dtype=np.float64)
    if o.size == 0 or t.size == 0:
        return np.zeros(t.shape[0], dtype=bool)
    dt = config.dt
    lo = np.searchsorted(o, t - dt - config.override_hold_s, side="right")
    hi = np.searchsorted(o, t + dt, side="right")
    return np.asarray(hi > lo, dtype=bool)


def exclude_overridden(res: Resampled, override_t: FloatArray, config: ResampleConfig
                       ) -> Resampled:
    """``res`` with the points overrides sent at ``override_t`` (sorted) may have driven
    marked overridden and invalid, as :func:`resample` marks them when its streams carry the
    overrides (an online buffer predicts from the unmarked grid and learns from this one);
    ``res`` itself when none is."""
    mark = overridden_points(res.t, override_t, config) & ~res.overridden
    if not np.any(mark):
        return res
    valid = res.valid & ~mark
    return dataclasses.replace(res, valid=valid, segment=segment_ids(valid),
                               overridden=res.overridden | mark)
