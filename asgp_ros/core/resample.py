"""Resampling of raw joystick and odometry streams onto the common grid.

The paper resamples both streams by linear interpolation onto a 5 Hz grid (Fan et al.,
ICRA 2018, Sec. IV). Here the grid is absolute: grid point k is at ``t_k = k / rate_hz``
on the streams' clock, so an online sliding buffer and an offline recording give the same
grid points.

Locality (what makes online and offline agree): the value at a grid point depends only on
the two raw samples that bracket it in each stream (``x_i + w (x_{i+1} - x_i)`` with
``w = (t - t_i) / (t_{i+1} - t_i)``; exactly ``x_i`` when ``t == t_i``). Calling
:func:`resample` on any window of raw samples therefore gives bit-identical ``t``, ``joy``
and ``vel`` at every grid point the window covers, and identical gap and tracking flags.
Stale-odometry flags depend on the run of repeated values a point belongs to; they agree
wherever that run lies inside the window (a run cut by the window's edge can only be
judged by what the window holds, as an online buffer must).

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

  The first sample of a run (the last genuine measurement) is kept; the flagged grid
  points are in ``Resampled.stale``.

Non-finite raw samples are dropped before anything else (and counted in
``Resampled.dropped_joy`` / ``dropped_vel``); the hole they leave is then an ordinary gap.
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from asgp_ros.core.streams import RawStreams

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class ResampleConfig:
    """Settings of :func:`resample` (validated on construction).

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
    """

    rate_hz: float = 5.0
    max_gap_joy_s: float = 0.3
    max_gap_vel_s: float = 0.6
    stale_after_s: float = 0.5
    stale_tolerance: float = 1e-9
    stale_joy_threshold: float = 0.2
    stale_still_speed: float = 1e-3
    stale_still_after_s: float = 0.6

    def __post_init__(self) -> None:
        for name in ("rate_hz", "max_gap_joy_s", "max_gap_vel_s", "stale_after_s",
                     "stale_tolerance", "stale_joy_threshold", "stale_still_speed",
                     "stale_still_after_s"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float | np.floating):
                raise ValueError(f"{name} must be a number, got {value!r}")
            object.__setattr__(self, name, float(value))
        if not (math.isfinite(self.rate_hz) and self.rate_hz > 0.0):
            raise ValueError(f"rate_hz must be positive and finite, got {self.rate_hz}")
        for name in ("max_gap_joy_s", "max_gap_vel_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be positive and finite, got {value}")
        if not self.stale_after_s > 0.0 or math.isnan(self.stale_after_s):
            raise ValueError(
                f"stale_after_s must be positive (inf disables), got {self.stale_after_s}"
            )
        if not self.stale_still_after_s > 0.0 or math.isnan(self.stale_still_after_s):
            raise ValueError("stale_still_after_s must be positive (inf disables), got "
                             f"{self.stale_still_after_s}")
        for name in ("stale_tolerance", "stale_joy_threshold", "stale_still_speed"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be non-negative and finite, got {value}")

    @property
    def dt(self) -> float:
        """Grid period (s)."""
        return 1.0 / self.rate_hz

    def to_dict(self) -> dict[str, Any]:
        """JSON-able dict (an infinite duration, i.e. disabled, is stored as None)."""
        d = asdict(self)
        for name in ("stale_after_s", "stale_still_after_s"):
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
        for name in ("stale_after_s", "stale_still_after_s"):
            if name in d and d[name] is None:
                d[name] = math.inf
        return cls(**d)


@dataclass(frozen=True)
class Resampled:
    """Streams on the common grid.

    Attributes:
        t: [T] grid times (s), ``t == k / rate_hz``.
        k: [T] integer grid indices (consecutive).
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
        dropped_joy: number of non-finite joystick samples dropped.
        dropped_vel: number of non-finite odometry samples dropped.
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

    @property
    def dt(self) -> float:
        return 1.0 / self.rate_hz

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


def grid_indices(t_start: float, t_end: float, rate_hz: float) -> IntArray:
    """Integer k with ``t_start <= k / rate_hz <= t_end`` (consecutive, possibly empty)."""
    if not t_end >= t_start:
        return np.zeros(0, dtype=np.int64)
    lo = math.ceil(t_start * rate_hz)
    hi = math.floor(t_end * rate_hz)
    # guard the float rounding of t * rate at both ends
    while (lo - 1) / rate_hz >= t_start:
        lo -= 1
    while lo / rate_hz < t_start:
        lo += 1
    while (hi + 1) / rate_hz <= t_end:
        hi += 1
    while hi / rate_hz > t_end:
        hi -= 1
    if hi < lo:
        return np.zeros(0, dtype=np.int64)
    return np.arange(lo, hi + 1, dtype=np.int64)


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


def resample(streams: RawStreams, config: ResampleConfig | None = None) -> Resampled:
    """Resample raw streams onto the absolute grid ``k / rate_hz`` (linear interpolation).

    The grid covers the time both streams cover (from the later first sample to the
    earlier last sample); an empty :class:`Resampled` results when they do not overlap.
    See the module docstring for validity, staleness and the window property.
    """
    cfg = config if config is not None else ResampleConfig()
    keep_j = _drop_nonfinite(streams.joy_t, streams.joy)
    keep_v = _drop_nonfinite(streams.vel_t, streams.vel)
    dropped_joy = int(keep_j.size - np.count_nonzero(keep_j))
    dropped_vel = int(keep_v.size - np.count_nonzero(keep_v))
    if dropped_joy or dropped_vel:
        logger.debug("%s: dropped %d joystick and %d odometry non-finite samples",
                     streams.source or "streams", dropped_joy, dropped_vel)
    joy_t, joy = streams.joy_t[keep_j], streams.joy[keep_j]
    vel_t, vel, vel_ok = streams.vel_t[keep_v], streams.vel[keep_v], streams.vel_ok[keep_v]

    if joy_t.size and vel_t.size:
        k = grid_indices(max(joy_t[0], vel_t[0]), min(joy_t[-1], vel_t[-1]), cfg.rate_hz)
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
    valid = ~(gap | tracking_lost | stale)

    segment = -np.ones(T, dtype=np.int64)
    starts = valid & np.r_[True, ~valid[:-1]]
    segment[valid] = (np.cumsum(starts) - 1)[valid]

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
        dropped_vel=dropped_vel, source=streams.source,
    )
