"""Resampling onto the absolute 5 Hz grid: interpolation, gaps, stale odometry, windows."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest

from asgp_ros.core import resample as resample_module
from asgp_ros.core.features import FeatureConfig, design_matrix
from asgp_ros.core.resample import (
    GRID_SILENCE_S,
    RESAMPLE_RANGES,
    ResampleConfig,
    exclude_overridden,
    grid_indices,
    midpoint_stamps,
    resample,
    stale_samples,
)
from asgp_ros.core.streams import RawStreams

#: odometry read at its own stamps: the interpolation's mechanics, free of the midpoint shift
FRAME = ResampleConfig(vel_stamp="frame")


def jittery_times(rng: np.random.Generator, t0: float, t1: float, lo: float,
                  hi: float) -> np.ndarray:
    """Sample times with intervals uniform in [lo, hi]."""
    n = int((t1 - t0) / lo) + 2
    t = t0 + np.cumsum(rng.uniform(lo, hi, n))
    return t[t < t1]


def recording(seed: int = 0, duration: float = 60.0, t0: float = 1000.03) -> RawStreams:
    """Joystick at ~30 Hz and odometry at 4-7 Hz with jitter, smooth noisy signals."""
    rng = np.random.default_rng(seed)
    jt = jittery_times(rng, t0, t0 + duration, 1 / 40, 1 / 24)
    vt = jittery_times(rng, t0, t0 + duration, 1 / 7, 1 / 4)
    joy = np.stack([np.sin(0.5 * jt), 0.8 * np.cos(0.3 * jt)], axis=1)
    vel = np.stack([1.2 * np.sin(0.5 * vt - 0.3), 0.9 * np.cos(0.3 * vt - 0.2)], axis=1)
    vel += rng.normal(0, 0.01, vel.shape)
    return RawStreams(joy_t=jt, joy=joy, vel_t=vt, vel=vel, source="test")


def test_grid_is_absolute_and_covers_the_overlap() -> None:
    s = recording()
    res = resample(s, FRAME)
    assert np.all(np.diff(res.k) == 1)
    np.testing.assert_array_equal(res.t, res.k / 5.0)
    start = max(s.joy_t[0], s.vel_t[0])
    end = min(s.joy_t[-1], s.vel_t[-1])
    assert res.t[0] >= start and res.t[0] - 0.2 < start
    assert res.t[-1] <= end and res.t[-1] + 0.2 > end
    np.testing.assert_array_equal(grid_indices(0.2, 0.6, 5.0), [1, 2, 3])
    np.testing.assert_array_equal(grid_indices(0.21, 0.59, 5.0), [2])
    assert grid_indices(0.21, 0.39, 5.0).size == 0


def test_linear_signals_are_interpolated_exactly() -> None:
    rng = np.random.default_rng(5)
    jt = jittery_times(rng, 10.0, 40.0, 0.02, 0.05)
    vt = jittery_times(rng, 10.0, 40.0, 0.14, 0.25)
    joy = np.stack([0.1 + 0.01 * jt, -0.2 - 0.02 * jt], axis=1)
    vel = np.stack([3.0 - 0.05 * vt, 0.5 + 0.03 * vt], axis=1)
    res = resample(RawStreams(joy_t=jt, joy=joy, vel_t=vt, vel=vel), FRAME)
    t = res.t
    np.testing.assert_allclose(res.joy, np.stack([0.1 + 0.01 * t, -0.2 - 0.02 * t], 1),
                               rtol=0, atol=1e-12)
    np.testing.assert_allclose(res.vel, np.stack([3.0 - 0.05 * t, 0.5 + 0.03 * t], 1),
                               rtol=0, atol=1e-12)
    assert res.valid.all() and len(res.segments()) == 1


def test_exact_hit_returns_the_sample() -> None:
    jt = np.array([0.0, 0.2, 0.4])
    vt = np.array([0.0, 0.1, 0.4])
    joy = np.array([[0.1, 0.0], [0.3, 0.0], [0.7, 0.0]])
    vel = np.array([[1.0, 0.0], [1.1, 0.0], [1.7, 0.3]])
    res = resample(RawStreams(joy_t=jt, joy=joy, vel_t=vt, vel=vel), FRAME)
    np.testing.assert_array_equal(res.k, [0, 1, 2])
    np.testing.assert_array_equal(res.joy[:, 0], [0.1, 0.3, 0.7])
    assert res.vel[2, 0] == 1.7 and res.vel[2, 1] == 0.3
    np.testing.assert_allclose(res.vel[1], [1.1 + 0.6 / 3, 0.1], atol=1e-15)


def test_jittery_timing_tracks_smooth_signals() -> None:
    s = recording(seed=2)
    res = resample(s, FRAME)
    assert res.valid.all() and len(res.segments()) == 1
    t = res.t
    np.testing.assert_allclose(res.joy[:, 0], np.sin(0.5 * t), atol=2e-3)
    np.testing.assert_allclose(res.joy[:, 1], 0.8 * np.cos(0.3 * t), atol=2e-3)
    # odometry: interpolation error (<= (0.25 s)^2 / 8 * 0.3) plus its 0.01 noise
    np.testing.assert_allclose(res.vel[:, 0], 1.2 * np.sin(0.5 * t - 0.3), atol=0.05)


def frame_averages(vt: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """What a frame-to-frame odometry reports for the velocity a + b t: the mean over the
    interval from the previous frame (the first frame: the value at its stamp)."""
    prev = np.concatenate([vt[:1], vt[:-1]])
    mid = 0.5 * (prev + vt)
    return a + b * mid[:, None]


def test_midpoint_stamps_undo_the_frame_lag() -> None:
    rng = np.random.default_rng(6)
    jt = jittery_times(rng, 10.0, 40.0, 0.02, 0.05)
    vt = jittery_times(rng, 10.0, 40.0, 0.14, 0.25)
    a, b = np.array([0.2, -0.1]), np.array([0.05, 0.03])
    streams = RawStreams(joy_t=jt, joy=np.zeros((jt.size, 2)), vel_t=vt,
                         vel=frame_averages(vt, a, b))
    res = resample(streams)  # the default: midpoint
    assert ResampleConfig().vel_stamp == "midpoint"
    np.testing.assert_allclose(res.vel, a + b * res.t[:, None], rtol=0, atol=1e-12)
    assert res.valid.all()
    # read at the frame stamps the same data lag by half an interval (0.07-0.125 s)
    lagged = resample(streams, FRAME)
    lag = (a + b * lagged.t[:, None] - lagged.vel)[:, 0] / b[0]
    assert 0.06 < float(np.median(lag)) < 0.13
    # the grid ends where the last interval's middle is
    assert res.t[-1] <= 0.5 * (vt[-2] + vt[-1]) < res.t[-1] + 0.2


def test_midpoint_stamps_drop_samples_without_a_known_interval() -> None:
    t = np.array([1.0, 1.2, 1.4, 3.0, 3.2, 3.35])
    out, known = midpoint_stamps(t, 0.6)
    np.testing.assert_array_equal(known, [False, True, True, False, True, True])
    np.testing.assert_allclose(out[known], [1.1, 1.3, 3.1, 3.275])
    assert np.all(np.diff(out) > 0)
    assert midpoint_stamps(np.zeros(0), 0.6)[0].size == 0
    assert not midpoint_stamps(np.array([5.0]), 0.6)[1].any()
    # after a gap the grid resumes at the first known middle, never across the gap
    jt = np.arange(0.0, 4.0, 0.03)
    vel = np.stack([0.1 * np.arange(t.size), np.zeros(t.size)], axis=1)  # never repeated
    res = resample(RawStreams(joy_t=jt, joy=np.zeros((jt.size, 2)), vel_t=t, vel=vel))
    assert not res.valid[(res.t > 1.3) & (res.t < 3.1)].any()
    assert res.valid[(res.t >= 3.1) & (res.t <= 3.275)].all()


def test_a_dropped_value_still_marks_its_frame() -> None:
    """An odometry sample whose value is refused (NaN) still ends the next one's interval."""
    t = np.array([0.0, 0.2, 0.4, 0.6, 0.8, 1.0])
    vel = np.ones((t.size, 2))
    vel[2] = np.nan
    jt = np.arange(0.0, 1.2, 0.03)
    res = resample(RawStreams(joy_t=jt, joy=np.zeros((jt.size, 2)), vel_t=t, vel=vel))
    assert res.dropped_vel == 1
    # samples at 0.2 (0.1), 0.6 (0.5), 0.8 (0.7), 1.0 (0.9): the grid runs 0.2 .. 0.8
    np.testing.assert_allclose(res.t, [0.2, 0.4, 0.6, 0.8])


def test_gaps_split_segments() -> None:
    s = recording(seed=3, duration=30.0, t0=0.0)
    # remove odometry in (10, 11.5) s and joystick in (20, 20.6) s
    vkeep = (s.vel_t < 10.0) | (s.vel_t > 11.5)
    jkeep = (s.joy_t < 20.0) | (s.joy_t > 20.6)
    s2 = RawStreams(joy_t=s.joy_t[jkeep], joy=s.joy[jkeep], vel_t=s.vel_t[vkeep],
                    vel=s.vel[vkeep])
    res = resample(s2)
    segs = res.segments()
    assert len(segs) == 3
    gap_t = res.t[res.gap]
    assert np.all(((gap_t > 9.8) & (gap_t < 11.7)) | ((gap_t > 19.9) & (gap_t < 20.7)))
    assert np.any((gap_t > 10.0) & (gap_t < 11.5)) and np.any((gap_t > 20.0) & (gap_t < 20.6))
    for sl in segs:
        assert res.valid[sl].all()
        assert np.all(res.segment[sl] == res.segment[sl.start])
    assert np.all(res.segment[~res.valid] == -1)
    assert sorted(set(res.segment[res.valid].tolist())) == [0, 1, 2]
    # a larger limit bridges the odometry gap (but the joystick limit still splits)
    res_wide = resample(s2, ResampleConfig(max_gap_vel_s=2.0))
    assert len(res_wide.segments()) == 2


def driven_stale_recording(value: tuple[float, float], joy_fwd: float,
                           repeat: tuple[float, float] = (20.0, 22.0)) -> RawStreams:
    """Odometry at exactly 5 Hz phase-shifted, frozen at ``value`` during ``repeat``."""
    s = recording(seed=4, duration=40.0, t0=0.0)
    vel = s.vel.copy()
    frozen = (s.vel_t >= repeat[0]) & (s.vel_t <= repeat[1])
    vel[frozen] = value
    joy = s.joy.copy()
    joy[(s.joy_t > repeat[0] - 1) & (s.joy_t < repeat[1] + 1)] = (joy_fwd, 0.0)
    return RawStreams(joy_t=s.joy_t, joy=joy, vel_t=s.vel_t, vel=vel)


def test_stale_odometry_is_flagged() -> None:
    s = driven_stale_recording((0.8, 0.1), joy_fwd=0.6)
    res = resample(s, FRAME)
    frozen_t = s.vel_t[(s.vel_t >= 20.0) & (s.vel_t <= 22.0)]
    inside = (res.t > frozen_t[0]) & (res.t <= frozen_t[-1])
    assert res.stale[inside].all()
    assert not res.valid[inside].any()
    assert np.all(res.segment[inside] == -1)
    # only points that use a repeated reading are stale; the first frozen sample is genuine
    assert not res.stale[res.t < frozen_t[0]].any()
    assert not res.stale[res.t > frozen_t[-1] + 0.3].any()
    assert len(res.segments()) == 2


def test_stale_zero_velocity_only_while_driven() -> None:
    # zero odometry while the joystick is released: a chair at rest, not stale
    rest = resample(driven_stale_recording((0.0, 0.0), joy_fwd=0.0))
    assert not rest.stale.any()
    # the same zeros while the joystick is pushed: the odometry is frozen, flagged once
    # the stick has been deflected for stale_still_after_s (0.6 s) since the zeros began
    s = driven_stale_recording((0.0, 0.0), joy_fwd=0.6)
    first_zero = s.vel_t[s.vel_t >= 20.0][0]
    driven = resample(s)
    assert driven.stale[(driven.t > first_zero + 0.85) & (driven.t < 21.9)].all()
    # (a grid point is flagged when the next odometry sample, <= 0.25 s later, is stale)
    assert not driven.stale[driven.t < first_zero + 0.6 - 0.25].any()
    # a chair that starts late (start-up lag shorter than the limit) is not flagged
    late = resample(s, ResampleConfig(stale_still_after_s=3.0, held_after_s=3.0))
    assert not late.stale.any()


def test_a_chair_held_while_pushed_is_stale() -> None:
    """A chair held (against an obstacle) while the stick pushes, or an odometry stuck near
    zero with a little jitter: the readings never repeat, but they read still (within
    held_speed) while the stick is pushed beyond held_joy_threshold. Flagged after
    held_after_s; at rest, at a small deflection (a chair that creeps), or a chair that
    starts, not; a pause of the stick starts the count again; a model file from before the
    rule (no held_after_s) resamples without it."""
    rng = np.random.default_rng(3)
    s = driven_stale_recording((0.0, 0.0), joy_fwd=0.8)
    vel = s.vel.copy()
    held = (s.vel_t >= 20.0) & (s.vel_t <= 22.0)
    vel[held] = rng.normal(0.0, 0.008, (int(held.sum()), 2))  # noise at rest, never repeated
    jitter = RawStreams(joy_t=s.joy_t, joy=s.joy, vel_t=s.vel_t, vel=vel)
    first = s.vel_t[held][0]
    res = resample(jitter)
    assert res.stale[(res.t > first + 0.85) & (res.t < 21.9)].all()
    assert not res.stale[res.t < first + 0.6 - 0.25].any()
    assert not res.valid[(res.t > first + 0.85) & (res.t < 21.9)].any()

    def with_joy(fwd: float, when: tuple[float, float] = (19.0, 23.0)) -> RawStreams:
        joy = s.joy.copy()
        joy[(s.joy_t >= when[0]) & (s.joy_t < when[1])] = (fwd, 0.0)
        return RawStreams(joy_t=s.joy_t, joy=joy, vel_t=s.vel_t, vel=vel)

    # its own setting: switching the repeat rules off leaves it on
    norepeat = resample(jitter, ResampleConfig(stale_after_s=math.inf))
    assert norepeat.stale[(norepeat.t > first + 0.85) & (norepeat.t < 21.9)].all()
    assert not resample(with_joy(0.0)).stale.any()  # at rest
    assert not resample(with_joy(0.3)).stale.any()  # a small push: a chair may creep
    # a chair that starts: still for 0.4 s after the push, then moving (and noisy)
    start = vel.copy()
    moving = held & (s.vel_t > first + 0.4)
    start[moving, 0] = 0.3 + rng.normal(0.0, 0.02, int(moving.sum()))
    assert not resample(RawStreams(joy_t=s.joy_t, joy=s.joy, vel_t=s.vel_t,
                                   vel=start)).stale.any()
    # held, released (still reading still), pushed again: the new push has its start-up
    # lag again, counted from when it began
    joy = s.joy.copy()
    joy[(s.joy_t >= 20.9) & (s.joy_t < 21.3)] = 0.0
    again = resample(RawStreams(joy_t=s.joy_t, joy=joy, vel_t=s.vel_t, vel=vel))
    assert again.stale[(again.t > first + 0.85) & (again.t < 20.6)].all()
    assert not again.stale[(again.t > 21.2) & (again.t < 21.3 + 0.6 - 0.25)].any()
    assert again.stale[(again.t > 21.3 + 0.85) & (again.t < 21.9)].all()
    # a model file from before the rule: resampled as it was trained
    old = ResampleConfig.from_dict({k: v for k, v in ResampleConfig().to_dict().items()
                                    if not k.startswith("held_")})
    assert math.isinf(old.held_after_s) and not resample(jitter, old).stale.any()
    assert ResampleConfig.from_dict(ResampleConfig().to_dict()) == ResampleConfig()


def test_a_small_frozen_reading_is_still_a_frozen_reading() -> None:
    """Odometry frozen at a small non-zero reading (2 cm/s, within held_speed) is caught
    by the repeat rule whatever the stick does, as before the held rule."""
    s = driven_stale_recording((0.02, 0.01), joy_fwd=0.0)
    res = resample(s)
    frozen_t = s.vel_t[(s.vel_t >= 20.0) & (s.vel_t <= 22.0)]
    assert res.stale[(res.t > frozen_t[0] + 0.1) & (res.t <= frozen_t[-1])].all()


def test_short_repeats_and_tolerance() -> None:
    short = resample(driven_stale_recording((0.8, 0.1), 0.6, repeat=(20.0, 20.3)))
    assert not short.stale.any()
    # nearly repeated readings: flagged only when within the configured tolerance
    s = driven_stale_recording((0.8, 0.1), joy_fwd=0.6)
    vel = s.vel.copy()
    frozen = (s.vel_t >= 20.0) & (s.vel_t <= 22.0)
    vel[frozen, 0] += np.arange(frozen.sum()) * 1e-7
    s2 = RawStreams(joy_t=s.joy_t, joy=s.joy, vel_t=s.vel_t, vel=vel)
    assert not resample(s2).stale.any()
    assert resample(s2, ResampleConfig(stale_tolerance=1e-6)).stale.any()
    # detection can be switched off
    assert not resample(s, ResampleConfig(stale_after_s=math.inf)).stale.any()


def test_stale_samples_marks_repeats_not_the_first() -> None:
    vt = np.arange(10) * 0.2
    vel = np.tile([0.5, 0.0], (10, 1))
    vel[:3] = [[0.1, 0], [0.2, 0], [0.3, 0]]  # samples 3..9 repeat 0.5
    stale = stale_samples(vt, vel, np.array([0.0, 2.0]), np.zeros((2, 2)), ResampleConfig())
    np.testing.assert_array_equal(stale, [False] * 4 + [True] * 6)


def test_tracking_failures_are_invalid() -> None:
    s = recording(seed=6, duration=20.0, t0=0.0)
    ok = np.ones(s.vel_t.shape[0], dtype=bool)
    ok[(s.vel_t > 8.0) & (s.vel_t < 9.0)] = False
    res = resample(RawStreams(joy_t=s.joy_t, joy=s.joy, vel_t=s.vel_t, vel=s.vel, vel_ok=ok))
    lost = res.tracking_lost
    assert lost[(res.t > 8.3) & (res.t < 8.7)].all()
    assert not lost[(res.t < 7.7) | (res.t > 9.3)].any()
    assert not res.valid[lost].any()
    assert not res.stale.any()


def test_overrides_invalidate_the_points_they_may_have_driven() -> None:
    """An override sent at o may drive the chair until o + override_hold_s; a grid point t
    answers the commands of (t - dt, t] (and up to a period later, read at a frame's
    middle): t is overridden when some o lies in (t - dt - hold, t + dt]."""
    s = recording(seed=6, duration=20.0, t0=0.0)
    over = np.array([8.05, 8.09, 8.13, 12.5])  # a burst (the layer's 25 Hz) and a lone one
    cfg = ResampleConfig(override_hold_s=0.4)
    res = resample(RawStreams(joy_t=s.joy_t, joy=s.joy, vel_t=s.vel_t, vel=s.vel,
                              override_t=over), cfg)
    plain = resample(s, cfg)
    t = res.t
    expect = np.zeros(t.shape[0], dtype=bool)
    for o in over:
        expect |= (o > t - 0.2 - 0.4) & (o <= t + 0.2)
    np.testing.assert_array_equal(res.overridden, expect)
    # by hand: t in [o - 0.2, o + 0.6) for each o
    assert np.round(t[res.overridden], 6).tolist() == [8.0, 8.2, 8.4, 8.6,
                                                       12.4, 12.6, 12.8, 13.0]
    assert not res.valid[res.overridden].any()
    np.testing.assert_array_equal(res.valid, plain.valid & ~expect)
    # nothing else changes, and no training row spans an overridden point
    np.testing.assert_array_equal(res.vel, plain.vel)
    np.testing.assert_array_equal(res.joy, plain.joy)
    fc = FeatureConfig(lags=3)
    _, _, index = design_matrix(res, 0, fc)
    _, _, index_plain = design_matrix(plain, 0, fc)
    spans = np.stack([index - i for i in range(4)], axis=1)  # the points of each row
    assert not res.overridden[spans].any()
    assert set(index) < set(index_plain)
    assert len(index_plain) - len(index) >= 3 + 4 + 3 + 4  # both holes and their lags
    # a sliding buffer learns from the same points: the grid first, the overrides after
    np.testing.assert_array_equal(exclude_overridden(plain, over, cfg).valid, res.valid)
    np.testing.assert_array_equal(exclude_overridden(plain, over, cfg).segment, res.segment)
    assert exclude_overridden(plain, np.zeros(0), cfg) is plain
    assert exclude_overridden(res, over, cfg) is res


def test_non_finite_samples_are_dropped_and_counted() -> None:
    s = recording(seed=7, duration=20.0, t0=0.0)
    joy = s.joy.copy()
    vel = s.vel.copy()
    joy[5, 1] = np.nan
    vel[(s.vel_t > 10.0) & (s.vel_t < 11.0)] = np.inf  # a 1 s hole -> a gap
    res = resample(RawStreams(joy_t=s.joy_t, joy=joy, vel_t=s.vel_t, vel=vel))
    assert res.dropped_joy == 1
    assert res.dropped_vel == int(((s.vel_t > 10.0) & (s.vel_t < 11.0)).sum())
    assert np.all(np.isfinite(res.joy)) and np.all(np.isfinite(res.vel))
    assert res.gap[(res.t > 10.2) & (res.t < 10.8)].all()
    assert len(res.segments()) == 2


def test_no_overlap_gives_an_empty_result() -> None:
    s = RawStreams(joy_t=[0.0, 1.0], joy=np.zeros((2, 2)), vel_t=[2.0, 3.0],
                   vel=np.zeros((2, 2)))
    res = resample(s)
    assert len(res) == 0 and res.segments() == []
    assert res.joy.shape == (0, 2)


def test_ground_truth_interpolated_with_unwrapped_heading() -> None:
    s = recording(seed=8, duration=10.0, t0=0.0)
    tt = np.arange(0.0, 10.0, 0.01)
    theta = np.mod(2.0 * tt + np.pi, 2 * np.pi) - np.pi  # wraps every pi s
    truth = np.stack([tt, -tt, theta, np.ones_like(tt), 2.0 * np.ones_like(tt)], 1)
    res = resample(RawStreams(joy_t=s.joy_t, joy=s.joy, vel_t=s.vel_t, vel=s.vel,
                              truth_t=tt, truth=truth))
    ok = res.truth_valid
    assert ok.sum() >= len(res) - 1
    np.testing.assert_allclose(res.truth[ok, 0], res.t[ok], atol=1e-9)
    wrapped = np.mod(res.truth[ok, 2] - 2.0 * res.t[ok] + np.pi, 2 * np.pi) - np.pi
    np.testing.assert_allclose(wrapped, 0.0, atol=1e-9)
    assert np.all(np.isnan(res.truth[~ok]))


def messy_recording() -> RawStreams:
    """A jittery recording with a gap, a tracking failure and a stale run."""
    s = driven_stale_recording((0.8, 0.1), joy_fwd=0.6, repeat=(20.0, 22.0))
    keep = (s.vel_t < 9.0) | (s.vel_t > 10.0)
    ok = np.ones(int(keep.sum()), dtype=bool)
    vt = s.vel_t[keep]
    ok[(vt > 30.0) & (vt < 31.0)] = False
    return RawStreams(joy_t=s.joy_t, joy=s.joy, vel_t=vt, vel=s.vel[keep], vel_ok=ok)


def window(s: RawStreams, a: float, b: float) -> RawStreams:
    jk = (s.joy_t >= a) & (s.joy_t <= b)
    vk = (s.vel_t >= a) & (s.vel_t <= b)
    return RawStreams(joy_t=s.joy_t[jk], joy=s.joy[jk], vel_t=s.vel_t[vk], vel=s.vel[vk],
                      vel_ok=s.vel_ok[vk])


def common(whole_k: np.ndarray, part_k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    _, iw, ip = np.intersect1d(whole_k, part_k, return_indices=True)
    return iw, ip


@pytest.mark.parametrize(("a", "b"), [(5.37, 14.91), (15.0, 25.0), (28.11, 35.0),
                                      (0.0, 40.0), (20.9, 21.3), (20.9, 21.8)])
def test_window_equals_whole_recording(a: float, b: float) -> None:
    s = messy_recording()
    whole = resample(s)
    part = resample(window(s, a, b))
    assert len(part) > 0
    iw, ip = common(whole.k, part.k)
    assert ip.size == len(part)  # every grid point of the window is in the whole
    for name in ("t", "joy", "vel", "gap", "tracking_lost"):
        np.testing.assert_array_equal(getattr(part, name), getattr(whole, name)[iw], name)
    # stale flags agree wherever the window holds the whole run of repeated readings
    frozen = s.vel_t[(s.vel_t >= 20.0) & (s.vel_t <= 22.0)]
    run_inside = a <= frozen[0] and frozen[-1] <= b
    run_outside = b < frozen[0] or a > frozen[-1] + 0.3
    if run_inside or run_outside:
        np.testing.assert_array_equal(part.stale, whole.stale[iw])
        np.testing.assert_array_equal(part.valid, whole.valid[iw])
        # the same segmentation (ids may be numbered differently)
        assert [(sl.stop - sl.start) for sl in part.segments()][1:-1] == [
            (sl.stop - sl.start) for sl in whole.segments()
            if whole.k[sl.start] > part.k[0] and whole.k[sl.stop - 1] < part.k[-1]
        ]
    else:
        # a run cut by the window edge: values identical, and the window can only see
        # less of the run: its flags are a subset of the whole recording's
        assert whole.stale[iw].all()
        assert np.all(~part.stale | whole.stale[iw])
        if b - a < ResampleConfig().stale_after_s:
            assert not part.stale.any()


def test_online_sliding_windows_reproduce_offline_values() -> None:
    s = recording(seed=9, duration=30.0, t0=500.0)
    whole = resample(s)
    for end in np.arange(505.0, 530.0, 0.37):
        part = resample(window(s, end - 3.0, end))
        iw, _ = common(whole.k, part.k)
        np.testing.assert_array_equal(part.vel, whole.vel[iw])
        np.testing.assert_array_equal(part.joy, whole.joy[iw])
        np.testing.assert_array_equal(part.valid, whole.valid[iw])


@pytest.mark.parametrize(("field", "value"), [
    ("rate_hz", 0.0), ("rate_hz", math.inf), ("max_gap_joy_s", -1.0),
    ("max_gap_vel_s", math.nan), ("stale_after_s", 0.0), ("stale_tolerance", -1e-3),
    ("stale_still_after_s", -1.0),
    ("rate_hz", "5"), ("rate_hz", True),
])
def test_config_validation(field: str, value: object) -> None:
    with pytest.raises(ValueError, match=field):
        ResampleConfig(**{field: value})  # type: ignore[arg-type]


def test_config_round_trip() -> None:
    cfg = ResampleConfig(rate_hz=10, stale_after_s=math.inf, stale_still_after_s=math.inf)
    assert cfg.dt == 0.1
    d = cfg.to_dict()
    assert d["stale_after_s"] is None and d["stale_still_after_s"] is None
    assert ResampleConfig.from_dict(d) == cfg
    with pytest.raises(ValueError, match="unknown"):
        ResampleConfig.from_dict({"rate": 5})
    assert ResampleConfig.from_dict(FRAME.to_dict()) == FRAME
    # settings stored before odometry stamps were a setting: read as recorded
    old = cfg.to_dict()
    del old["vel_stamp"]
    assert ResampleConfig.from_dict(old).vel_stamp == "frame"
    for bad in ("end", "", None, 1):
        with pytest.raises(ValueError, match="vel_stamp"):
            ResampleConfig(vel_stamp=bad)  # type: ignore[arg-type]


# ---- ranges: nothing from a user, a file or a message can make the grid hang ----------

def _run_with_deadline(code: str, deadline_s: float = 20.0) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh interpreter; a hang fails the test instead of the suite."""
    try:
        return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                              timeout=deadline_s, check=False)
    except subprocess.TimeoutExpired:
        pytest.fail(f"hung for {deadline_s} s: {code}")


@pytest.mark.parametrize("rate", [1e20, 1e300, 1e-300, 0.1, 1000.0])
def test_rate_outside_its_documented_range_is_refused(rate: float) -> None:
    low, high = RESAMPLE_RANGES["rate_hz"]
    assert not low <= rate <= high
    with pytest.raises(ValueError, match=r"rate_hz must be in \[0.5, 100\]"):
        ResampleConfig(rate_hz=rate)


def test_every_setting_accepts_its_bounds_and_refuses_beyond() -> None:
    for name, (low, high) in RESAMPLE_RANGES.items():
        assert math.isfinite(low) and math.isfinite(high)
        assert getattr(ResampleConfig(**{name: low}), name) == low
        assert getattr(ResampleConfig(**{name: high}), name) == high
        for bad in (high * 2 + 1, -1.0, math.nan, -math.inf):
            with pytest.raises(ValueError, match=name):
                ResampleConfig(**{name: bad})
    for name in ("stale_after_s", "stale_still_after_s"):  # inf disables
        assert getattr(ResampleConfig(**{name: math.inf}), name) == math.inf
    with pytest.raises(ValueError, match="max_gap_vel_s"):
        ResampleConfig(max_gap_vel_s=math.inf)


@pytest.mark.parametrize("call", [
    "grid_indices(1.7e9, 1.7e9 + 10.0, 1e20)",  # a bag's clock at an absurd rate
    "grid_indices(1e300, 1e300, 5.0)",          # an absurd time at the paper's rate
    "grid_indices(0.0, 1e12, 5.0)",             # more points than memory holds
])
def test_grid_indices_refuses_instead_of_hanging(call: str) -> None:
    proc = _run_with_deadline(
        "from asgp_ros.core.resample import grid_indices\n"
        f"try:\n    {call}\nexcept ValueError as exc:\n    print('refused:', exc)\n")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("refused:"), proc.stdout


def silent_recording(silence_s: float) -> RawStreams:
    """The messy recording with nothing from either stream for ``silence_s`` after 25 s:
    its second part (a stale run, a tracking failure) moved later by ``silence_s``."""
    s = messy_recording()
    jt = s.joy_t + silence_s * (s.joy_t > 25.0)
    vt = s.vel_t + silence_s * (s.vel_t > 25.0)
    return RawStreams(joy_t=jt, joy=s.joy, vel_t=vt, vel=s.vel, vel_ok=s.vel_ok)


@pytest.mark.parametrize("rate", [0.5, 5.0, 100.0])
@pytest.mark.parametrize("silence_s", [GRID_SILENCE_S + 0.1, 60.0, 20 * 86400.0])
def test_a_silence_has_no_grid_points_but_its_first_and_last(monkeypatch, rate: float,
                                                             silence_s: float) -> None:
    """Every point inside a silence is invalid: the grid leaves them out (a 20-day gap was
    8.6 million points at 5 Hz), keeping the first and the last, and every point it keeps
    is as the grid over the whole span has it: the rows and the cases are the same."""
    s = silent_recording(silence_s)
    cfg = ResampleConfig(rate_hz=rate)
    res = resample(s, cfg)
    monkeypatch.setattr(resample_module, "GRID_SILENCE_S", math.inf)
    full = resample(s, cfg) if silence_s < 3600.0 else None
    monkeypatch.undo()

    jumps = np.flatnonzero(np.diff(res.k) > 1)
    assert len(res) <= 46.0 * rate + 4  # the data's 46 s, not the silence
    assert jumps.size == (1 if silence_s * rate > 3 else 0)
    for j in jumps:  # the points kept on either side of what is left out: inside, invalid
        assert 24.0 < res.t[j] < res.t[j + 1] < 26.0 + silence_s
        assert res.gap[j] and res.gap[j + 1] and not (res.valid[j] or res.valid[j + 1])
    if full is None:
        return
    keep = np.isin(full.k, res.k)
    assert keep.sum() == len(res)
    assert not full.valid[~keep].any()
    for name in ("t", "k", "joy", "vel", "valid", "stale", "tracking_lost", "gap",
                 "segment", "truth_valid", "overridden"):
        np.testing.assert_array_equal(getattr(res, name), getattr(full, name)[keep], name)
    for lags in (1, 4):
        for c in (0, 1):
            X, y, idx = design_matrix(res, c, FeatureConfig(lags=lags))
            Xf, yf, idxf = design_matrix(full, c, FeatureConfig(lags=lags))
            np.testing.assert_array_equal(X, Xf)
            np.testing.assert_array_equal(y, yf)
            np.testing.assert_array_equal(res.k[idx], full.k[idxf])


def test_windows_across_a_silence_equal_the_whole_recording() -> None:
    """The window property holds across a silence: a window holding it leaves out the same
    points, one starting after it begins at its end."""
    s = silent_recording(86400.0)
    whole = resample(s)
    for a, b in [(20.0, 86400.0 + 30.0), (86400.0 + 25.0, 86400.0 + 40.0), (0.0, 1e6)]:
        part = resample(window(s, a, b))
        iw, ip = common(whole.k, part.k)
        assert ip.size == len(part) > 0
        for name in ("t", "joy", "vel", "gap", "tracking_lost"):
            np.testing.assert_array_equal(getattr(part, name), getattr(whole, name)[iw], name)


def test_grid_indices_leave_out_the_inside_of_silences() -> None:
    np.testing.assert_array_equal(
        grid_indices(0.0, 10.0, 1.0, np.array([[2.0, 8.0]])), [0, 1, 2, 3, 7, 8, 9, 10])
    np.testing.assert_array_equal(  # the first and last strictly inside are kept
        grid_indices(0.0, 10.0, 1.0, np.array([[1.5, 8.5]])), [0, 1, 2, 8, 9, 10])
    np.testing.assert_array_equal(  # three points inside: only the middle one goes
        grid_indices(0.0, 10.0, 1.0, np.array([[1.5, 4.5], [5.0, 6.0]])),
        [0, 1, 2, 4, 5, 6, 7, 8, 9, 10])
    k = grid_indices(1.7e9, 1.7e9 + 60.0 + 20 * 86400.0, 5.0,
                     np.array([[1.7e9 + 30.0, 1.7e9 + 30.0 + 20 * 86400.0]]))
    assert k.size == 2 + 2 * 151 and np.all(np.diff(k) > 0)
    with pytest.raises(ValueError, match="outside its silences"):
        grid_indices(0.0, 1e8, 5.0, np.array([[1.0, 2.0], [3.0, 4.0]]))


def test_grid_indices_is_exact_near_the_range_limit() -> None:
    t = 1e10  # MAX_ABS_TIME_S at the highest rate: |t * rate| = 1e12 << 2**50
    k = grid_indices(t, t + 0.05, 100.0)
    assert k.tolist() == [10**12 + i for i in range(6)]
    assert np.all(k / 100.0 >= t) and np.all(k / 100.0 <= t + 0.05)
    with pytest.raises(ValueError, match="rate"):
        grid_indices(0.0, 1.0, math.nan)


def test_out_of_range_samples_are_dropped_like_non_finite_ones() -> None:
    s = recording(seed=3, duration=20.0, t0=0.0)
    joy, vel = s.joy.copy(), s.vel.copy()
    joy[7, 0] = 1e30
    joy[9, 1] = -1.2
    joy[11, 0] = 1.04  # calibration overshoot within JOY_TOLERANCE: kept
    vel[3, 0] = 6.0  # faster than any wheelchair
    vel[4, 1] = -1e30
    res = resample(RawStreams(joy_t=s.joy_t, joy=joy, vel_t=s.vel_t, vel=vel))
    assert (res.dropped_joy, res.dropped_vel) == (2, 2)
    assert np.all(np.abs(res.joy) <= 1.05) and np.all(np.abs(res.vel) <= 10.0)


def test_time_stamps_beyond_the_range_are_refused() -> None:
    with pytest.raises(ValueError, match="joystick: time stamps beyond"):
        RawStreams(joy_t=[0.0, 1e11], joy=np.zeros((2, 2)), vel_t=[0.0], vel=[[0.0, 0.0]])
