"""The obstacle memory (asgp_ros.core.obstacle_memory): dead reckoning from VO twists and
the points of earlier scans, against analytic scans of walls and posts."""

from __future__ import annotations

import math

import numpy as np
import pytest

from asgp_ros.core import collision
from asgp_ros.core.obstacle_memory import (
    MemoryConfig,
    Odometer,
    ScanMemory,
    compose,
)

FOV = math.radians(270.0)
BEAMS = 1081


def cast(sensor: tuple[float, float, float], segments: list[tuple[float, float, float, float]],
         stamp: float, fov: float = FOV, beams: int = BEAMS,
         nan_beams: slice | None = None) -> collision.Scan:
    """An exact scan from the scanner pose ``sensor`` (world frame) of line segments
    (x0, y0, x1, y1) in the world frame; +inf where nothing is within 8 m."""
    full = fov >= 2.0 * math.pi - 1e-9
    inc = fov / beams if full else fov / (beams - 1)
    a_min = -math.pi if full else -0.5 * fov
    angles = sensor[2] + a_min + inc * np.arange(beams)
    d = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    o = np.array(sensor[:2])
    ranges = np.full(beams, math.inf)
    for x0, y0, x1, y1 in segments:
        p0, e = np.array([x0, y0]), np.array([x1 - x0, y1 - y0])
        # o + r d = p0 + u e
        den = d[:, 0] * (-e[1]) - d[:, 1] * (-e[0])
        with np.errstate(divide="ignore", invalid="ignore"):
            q = p0 - o
            r = (q[0] * (-e[1]) - q[1] * (-e[0])) / den
            u = (d[:, 0] * q[1] - d[:, 1] * q[0]) / den
        ok = (np.abs(den) > 1e-12) & (r > 0) & (u >= 0) & (u <= 1)
        ranges = np.where(ok & (r < ranges), r, ranges)
    ranges[ranges > 8.0] = math.inf
    if nan_beams is not None:
        ranges[nan_beams] = math.nan
    return collision.Scan(ranges, a_min, inc, 0.05, 8.0, stamp)


WALL_AHEAD = [(1.0, -3.0, 1.0, 3.0)]  # a wall across x = 1 (world frame)


def test_the_odometer_integrates_held_twists_and_interpolates():
    odo = Odometer(max_gap_s=0.5)
    for i in range(11):
        assert odo.feed(0.2 * i, 0.5, 0.3)
    def circle(t: float) -> tuple[float, float, float]:  # radius v / w = 5/3 m
        r = 0.5 / 0.3
        return (r * math.sin(0.3 * t), r * (1.0 - math.cos(0.3 * t)), 0.3 * t)

    assert odo.pose_at(2.0) == pytest.approx(circle(2.0), abs=1e-9)
    assert odo.pose_at(1.1) == pytest.approx(circle(1.1), abs=1e-9)  # between twists
    assert odo.pose_at(2.3) == pytest.approx(circle(2.3), abs=1e-9)  # extrapolated
    # a straight line (w = 0) has no singularity
    straight = Odometer()
    straight.feed(0.0, 1.0, 0.0)
    straight.feed(0.2, 1.0, 0.0)
    assert straight.pose_at(0.3) == pytest.approx((0.3, 0.0, 0.0), abs=1e-12)
    assert odo.pose_at(2.6) is None  # stale: past max_gap_s
    assert odo.stamp == pytest.approx(2.0)
    assert odo.pose_at(-0.1) is None  # before the history


@pytest.mark.parametrize("bad", ["gap", "back", "nan", "absurd"])
def test_the_odometer_starts_a_new_epoch_on_a_break(bad):
    odo = Odometer(max_gap_s=0.5)
    for i in range(5):
        odo.feed(0.2 * i, 0.5, 0.0)
    assert odo.epoch == 0
    if bad == "gap":
        assert odo.feed(2.0, 0.5, 0.0)  # 1.2 s after the last twist
        assert odo.pose_at(2.0) == (0.0, 0.0, 0.0)  # a new frame
    elif bad == "back":
        assert not odo.feed(0.1, 0.5, 0.0)
    elif bad == "nan":
        assert not odo.feed(1.0, math.nan, 0.0)
    else:
        assert not odo.feed(1.0, 1e30, 0.0)
    assert odo.epoch == 1 and odo.breaks == 1
    assert odo.pose_at(0.4) is None  # the old epoch's poses are gone


def test_a_wall_out_of_view_is_remembered_where_it_is():
    mem = ScanMemory(config=MemoryConfig(cell_m=0.01))
    assert mem.add(cast((0, 0, 0), WALL_AHEAD, 0.0), (0.0, 0.0, 0.0)).shape == (0, 2)
    # the chair turns half round on the spot: the wall is behind, outside the 270 deg view
    extra = mem.add(cast((0, 0, math.pi), WALL_AHEAD, 1.0), (0.0, 0.0, math.pi))
    assert extra.shape[0] > 20
    # in the new scan's frame the wall is at x = -1, seen only at bearings beyond 135 deg
    assert np.allclose(extra[:, 0], -1.0, atol=1e-6)
    bearing = np.degrees(np.abs(np.arctan2(extra[:, 1], extra[:, 0])))
    assert bearing.min() > 134.0
    # and the newest scan's own points are not repeated
    assert np.all(np.abs(extra[:, 1]) < 1.0 + 1e-6)


def test_a_beam_that_passes_through_a_remembered_point_clears_it():
    post = [(1.0, -0.05, 1.0, 0.05)]  # a post 1 m ahead: someone standing there
    mem = ScanMemory()
    mem.add(cast((0, 0, 0), post, 0.0), (0.0, 0.0, 0.0))
    assert mem.size > 0
    # they walk away: the beams now reach a wall at 3 m through where they stood
    extra = mem.add(cast((0, 0, 0), [(3.0, -3.0, 3.0, 3.0)], 0.1), (0.0, 0.0, 0.0))
    assert extra.shape == (0, 2)
    assert not np.any(np.abs(mem._xy[:, 0] - 1.0) < 0.1)  # forgotten
    # nothing in range at all (+inf) clears too
    mem.add(cast((0, 0, 0), post, 0.2), (0.0, 0.0, 0.0))
    assert mem.add(cast((0, 0, 0), [], 0.3), (0.0, 0.0, 0.0)).shape == (0, 2)
    assert mem.size == 0


def test_occluded_points_and_nan_beams_keep_what_was_seen():
    far = [(2.0, -0.3, 2.0, 0.3)]
    mem = ScanMemory()
    mem.add(cast((0, 0, 0), far, 0.0), (0.0, 0.0, 0.0))
    seen = mem.size
    # something now stands in front of it: the far wall is hidden, not gone
    extra = mem.add(cast((0, 0, 0), [*far, (1.0, -0.5, 1.0, 0.5)], 0.1), (0.0, 0.0, 0.0))
    assert extra.shape[0] >= seen - 2
    assert np.allclose(extra[:, 0], 2.0, atol=1e-6)
    # every beam erroneous over the post: no reading clears nothing
    mem2 = ScanMemory()
    mem2.add(cast((0, 0, 0), far, 0.0), (0.0, 0.0, 0.0))
    extra = mem2.add(cast((0, 0, 0), [], 0.1, nan_beams=slice(400, 681)), (0.0, 0.0, 0.0))
    assert extra.shape[0] > 0 and np.allclose(extra[:, 0], 2.0, atol=1e-6)


def test_age_radius_and_size_bound_the_memory():
    mem = ScanMemory(config=MemoryConfig(max_age_s=1.0, radius_m=3.0))
    mem.add(cast((0, 0, 0), WALL_AHEAD, 0.0), (0.0, 0.0, 0.0))
    assert mem.add(cast((0, 0, math.pi), WALL_AHEAD, 0.9), (0.0, 0.0, math.pi)).size
    assert not mem.add(cast((0, 0, math.pi), WALL_AHEAD, 2.0), (0.0, 0.0, math.pi)).size
    # driven 5 m away from it: beyond the radius
    mem = ScanMemory(config=MemoryConfig(radius_m=3.0))
    mem.add(cast((0, 0, 0), WALL_AHEAD, 0.0), (0.0, 0.0, 0.0))
    assert not mem.add(cast((-5, 0, math.pi), [], 0.5), (-5.0, 0.0, math.pi)).size
    assert mem.size == 0
    # at most max_points, the newest kept
    mem = ScanMemory(config=MemoryConfig(max_points=50))
    mem.add(cast((0, 0, 0), WALL_AHEAD, 0.0), (0.0, 0.0, 0.0))
    assert mem.size == 50


def test_no_pose_or_a_new_epoch_empties_the_memory():
    mem = ScanMemory()
    mem.add(cast((0, 0, 0), WALL_AHEAD, 0.0), (0.0, 0.0, 0.0))
    assert mem.add(cast((0, 0, math.pi), WALL_AHEAD, 0.1), None).shape == (0, 2)
    assert mem.size == 0 and mem.resets == 1
    mem.add(cast((0, 0, 0), WALL_AHEAD, 0.2), (0.0, 0.0, 0.0), epoch=0)
    assert not mem.add(cast((0, 0, math.pi), WALL_AHEAD, 0.3), (0.0, 0.0, math.pi),
                       epoch=1).size
    mem.add(cast((0, 0, 0), WALL_AHEAD, 0.4), (0.0, 0.0, 0.0), epoch=1)
    assert not mem.add(cast((0, 0, math.pi), WALL_AHEAD, 0.3), (0.0, 0.0, math.pi),
                       epoch=1).size  # the scans' clock went back
    assert not mem.add(cast((0, 0, math.pi), WALL_AHEAD, 0.5), (0.0, math.nan, 0.0),
                       epoch=1).size


def test_a_full_circle_scan_wraps_its_beams():
    mem = ScanMemory()
    ring = [(1.0, -3.0, 1.0, 3.0), (-1.0, -3.0, -1.0, 3.0)]
    mem.add(cast((0, 0, 0), ring, 0.0, fov=2 * math.pi, beams=1440), (0.0, 0.0, 0.0))
    assert mem.size > 0
    # a 360 deg scanner sees everything the memory holds: nothing is extra
    extra = mem.add(cast((0, 0, 2.0), ring, 0.1, fov=2 * math.pi, beams=1440),
                    (0.0, 0.0, 2.0))
    assert extra.shape == (0, 2)
    # and the walls gone (a sweep of +inf) clears all of it, across the seam at 180 deg
    assert not mem.add(cast((0, 0, 0), [], 0.2, fov=2 * math.pi, beams=1440),
                       (0.0, 0.0, 0.0)).size
    assert mem.size == 0


def test_a_mounted_scanner_places_points_in_its_own_frame():
    mount = (0.3, 0.05, 0.1)
    mem = ScanMemory(mount)
    pose0 = (0.0, 0.0, 0.0)
    mem.add(cast(compose(pose0, mount), WALL_AHEAD, 0.0), pose0)
    pose1 = (0.2, -0.1, math.pi)
    sensor1 = compose(pose1, mount)
    extra = mem.add(cast(sensor1, WALL_AHEAD, 0.5), pose1)
    assert extra.shape[0] > 0
    c, s = math.cos(sensor1[2]), math.sin(sensor1[2])
    world_x = sensor1[0] + c * extra[:, 0] - s * extra[:, 1]
    assert np.allclose(world_x, 1.0, atol=1e-6)


def turning_rear_corner_case():
    """A chair turning on the spot with furniture close behind its left rear corner."""
    furniture = [(-0.85, -2.0, -0.85, 2.0)]  # 5 cm behind the footprint, square on
    mount = (0.3, 0.0, 0.0)
    mem = ScanMemory(mount)
    # earlier: the chair faced the furniture and saw it
    before = (0.0, 0.0, math.pi)
    mem.add(cast(compose(before, mount), furniture, 0.0), before)
    now = (0.0, 0.0, 0.0)  # turned round: it is behind, out of view
    scan = cast(compose(now, mount), furniture, 1.5)
    extra = mem.add(scan, now)
    # the path: turning on the spot (a quarter turn in 2 s), the footprint's rear sweeps
    k = 10
    theta = np.linspace(0.16, 1.6, k)
    pose = np.stack([np.zeros(k), np.zeros(k), theta], axis=1)[None]
    cov = np.tile(np.diag([1e-4, 1e-4, 1e-3]), (1, k, 1, 1))
    footprint = collision.Footprint(length=1.2, width=0.7, offset=-0.2)
    return scan, extra, pose, cov, footprint, mount


def test_the_memory_makes_a_turn_into_unseen_furniture_count():
    scan, extra, pose, cov, footprint, mount = turning_rear_corner_case()
    alone = collision.scan_check(scan, footprint, mount=mount)
    remembered = collision.scan_check(scan, footprint, mount=mount, extra=extra)
    assert alone(pose, cov)[1][0] < 0.01  # the scan alone: clear
    assert remembered(pose, cov)[1][0] > 0.9  # with the memory: the rear corner hits


def test_extra_points_only_add_to_the_probability():
    rng = np.random.default_rng(3)
    scan = cast((0.3, 0.0, 0.0), WALL_AHEAD, 0.0)
    footprint = collision.DEFAULT_FOOTPRINT
    for _ in range(5):
        extra = rng.uniform(-3, 3, (40, 2))
        pose = np.concatenate([rng.uniform(-1, 1, (4, 10, 2)),
                               rng.uniform(-3, 3, (4, 10, 1))], axis=2)
        cov = np.tile(np.diag([4e-3, 4e-3]), (4, 10, 1, 1))
        a = collision.scan_check(scan, footprint, mount=(0.3, 0, 0))(pose, cov)
        b = collision.scan_check(scan, footprint, mount=(0.3, 0, 0), extra=extra)(pose, cov)
        assert np.all(b[0] >= a[0] - 1e-12) and np.all(b[1] >= a[1] - 1e-12)


@pytest.mark.parametrize("bad", [math.nan, math.inf, 1e30])
def test_non_finite_or_absurd_extra_points_are_refused(bad):
    scan = cast((0.0, 0.0, 0.0), WALL_AHEAD, 0.0)
    with pytest.raises(collision.CollisionError):
        collision.scan_check(scan, extra=np.array([[0.5, bad]]))


def test_extra_points_beyond_the_scan_window_are_left_out():
    scan = cast((0.0, 0.0, 0.0), WALL_AHEAD, 0.0)
    fld = collision.DistanceField.from_scan(scan, extra=np.array([[100.0, 0.0], [-2.0, 0.0]]))
    assert fld.obstacles == collision.scan_points(scan).shape[0] + 1


@pytest.mark.parametrize("bad", [dict(max_age_s=-1.0), dict(radius_m=math.nan),
                                 dict(cell_m=0.0), dict(max_points=0),
                                 dict(max_gap_s=math.inf)])
def test_invalid_memory_settings_are_refused(bad):
    with pytest.raises(ValueError):
        MemoryConfig(**bad)


def test_a_scan_sweeping_clockwise_is_read_the_same():
    """angle_increment < 0 (a scanner mounted upside down): the same beams reversed."""
    ccw = cast((0, 0, 0), [(1.0, -0.2, 1.0, 0.2)], 0.0)
    cw = collision.Scan(ccw.ranges[::-1].copy(), -ccw.angle_min, -ccw.angle_increment,
                        ccw.range_min, ccw.range_max, 0.0)
    for first, second in ((ccw, ccw), (cw, cw), (ccw, cw)):
        mem = ScanMemory()
        mem.add(first, (0.0, 0.0, 0.0))
        assert mem.size > 0
        # the post gone: every beam of the second scan (either sweep) clears it
        empty = collision.Scan(np.full(second.ranges.size, math.inf), second.angle_min,
                               second.angle_increment, second.range_min, second.range_max,
                               0.1)
        mem.add(empty, (0.0, 0.0, 0.0))
        assert mem.size == 0


@pytest.mark.parametrize("stamp", [math.nan, math.inf])
def test_a_scan_without_a_finite_stamp_empties_the_memory(stamp):
    mem = ScanMemory()
    mem.add(cast((0, 0, 0), WALL_AHEAD, 0.0), (0.0, 0.0, 0.0))
    bad = cast((0, 0, math.pi), WALL_AHEAD, stamp)
    assert mem.add(bad, (0.0, 0.0, math.pi)).shape == (0, 2) and mem.size == 0


def test_a_flood_of_twists_keeps_the_odometer_bounded():
    from asgp_ros.core.obstacle_memory import MAX_HISTORY

    odo = Odometer(max_gap_s=0.5, history_s=5.0)
    for i in range(3 * MAX_HISTORY):  # 100 kHz for a while
        odo.feed(1e-5 * i, 0.5, 0.0)
    assert len(odo._history) == MAX_HISTORY
    t = 1e-5 * (3 * MAX_HISTORY - 1)
    assert odo.pose_at(t)[0] == pytest.approx(0.5 * t, abs=1e-9)  # still integrated
    assert odo.pose_at(0.0) is None  # the oldest went first
