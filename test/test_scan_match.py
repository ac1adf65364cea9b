"""Laser odometry (asgp_ros.core.scan_match): known motions recovered from simulated scans,
degenerate and hostile input refused rather than guessed, and the odometer's epochs."""

from __future__ import annotations

import math

import numpy as np
import pytest

from asgp_ros.core.collision import Scan
from asgp_ros.core.obstacle_memory import compose
from asgp_ros.core.scan_match import MatchConfig, Reference, ScanOdometer, _between, match
from asgp_ros.sim.lidar import Lidar
from asgp_ros.sim.world import room_for_surface


@pytest.fixture(scope="module")
def lidar() -> Lidar:
    return Lidar(room_for_surface("tile"), None, seed=4)


def scan_at(lidar: Lidar, pose: tuple[float, float, float], t: float = 0.0) -> Scan:
    r = lidar.scan(*pose)
    return Scan(r.ranges, r.angle_min, r.angle_increment, r.range_min, r.range_max, stamp=t)


def base_points(lidar: Lidar, pose: tuple[float, float, float]) -> np.ndarray:
    odo = ScanOdometer(lidar.config.mount)
    return odo._base_points(scan_at(lidar, pose))


@pytest.mark.parametrize("motion", [(0.08, -0.02, 0.1), (0.0, 0.0, -0.3), (-0.1, 0.03, 0.0),
                                    (0.25, 0.05, 0.2)])
def test_a_known_motion_is_recovered(lidar: Lidar, motion: tuple[float, float, float]) -> None:
    a = (-1.5, 0.7, 0.4)
    b = compose(a, motion)
    res = match(base_points(lidar, a), base_points(lidar, b))  # seeded at no motion
    assert res.ok, res.why
    assert math.hypot(res.pose[0] - motion[0], res.pose[1] - motion[1]) < 0.005
    assert abs(res.pose[2] - motion[2]) < math.radians(0.2)
    assert res.rms < 0.02 and res.constraint > 0.1


def test_a_corridor_is_refused_not_guessed() -> None:
    rng = np.random.default_rng(1)
    x = np.linspace(-5.0, 5.0, 400)
    walls = np.concatenate([np.stack([x, np.full_like(x, 1.0)], 1),
                            np.stack([x, np.full_like(x, -1.0)], 1)])
    ref = walls + rng.normal(0.0, 0.003, walls.shape)
    cur = walls + np.array([0.1, 0.0]) + rng.normal(0.0, 0.003, walls.shape)  # along the axis
    res = match(ref, cur)
    assert not res.ok and "degenerate" in res.why
    assert res.constraint < MatchConfig().min_constraint


def test_hostile_input_never_gives_a_trusted_pose(lidar: Lidar) -> None:
    ref = base_points(lidar, (0.0, 0.0, 0.0))
    rng = np.random.default_rng(2)
    assert not match(ref, rng.uniform(-5, 5, (500, 2))).ok  # unrelated points
    assert not match(ref, ref[:10]).ok  # too few
    assert not match(np.zeros((0, 2)), ref).ok
    bad = ref.copy()
    bad[::2] = np.nan
    res = match(ref, bad)  # NaN points are dropped, the rest still match
    assert res.ok and math.hypot(*res.pose[:2]) < 0.005
    assert not match(ref, ref, seed=(math.nan, 0.0, 0.0)).ok
    assert not match(ref, np.full((500, 2), 1e30)).ok
    # a round room constrains no rotation about its centre: refused, not a pose
    ang = np.linspace(-2.35, 2.35, 1081)
    circle = np.stack([2.0 * np.cos(ang), 2.0 * np.sin(ang)], axis=1)
    res = match(circle, circle)
    assert not res.ok and "degenerate" in res.why
    # a seed in the wrong basin is refused rather than followed far
    far = match(ref, base_points(lidar, (1.0, 0.0, 0.0)), config=MatchConfig(max_step_m=0.3))
    assert not far.ok
    with pytest.raises(ValueError, match="trim"):
        MatchConfig(trim=0.9)
    assert isinstance(Reference(ref), Reference)


def test_the_odometer_follows_a_drive_and_breaks_on_gaps(lidar: Lidar) -> None:
    odo = ScanOdometer(lidar.config.mount)
    pose = (-2.0, 0.0, 0.0)
    t = 0.0
    assert odo.add(scan_at(lidar, pose, t)) == (0.0, 0.0, 0.0)  # the epoch's origin
    start = pose
    errors = []
    for i in range(150):  # 15 s of driving and turning at 10 scans a second
        t += 0.1
        v, w = 0.4 + 0.2 * math.sin(i / 7.0), 0.6 * math.sin(i / 11.0)
        before = pose
        pose = compose(pose, (v * 0.1 * math.cos(0.05 * w), v * 0.1 * math.sin(0.05 * w),
                              0.1 * w))
        est = odo.add(scan_at(lidar, pose, t))
        truth = _between(start, pose)
        errors.append(math.hypot(est[0] - truth[0], est[1] - truth[1]))
        # the matched interval's motion, in the base frame at the previous scan
        assert odo.last_step is not None and odo.last_step[0] == pytest.approx(0.1)
        np.testing.assert_allclose(odo.last_step[1:], _between(before, pose), atol=0.01)
        truth_step = _between(before, pose)
        assert odo.last_twist == pytest.approx((truth_step[0] / 0.1, truth_step[2] / 0.1),
                                               abs=0.1)
    assert odo.epoch == 0, odo.refused
    assert max(errors) < 0.03  # 15 s and about 6 m
    # a gap, then a stamp going back: new epochs, poses restart at the origin, no step
    assert odo.add(scan_at(lidar, pose, t + 2.0)) == (0.0, 0.0, 0.0)
    assert odo.epoch == 1 and odo.last_step is None and odo.last_twist is None
    assert odo.add(scan_at(lidar, pose, t)) == (0.0, 0.0, 0.0)
    assert odo.epoch == 2 and odo.breaks == 2
    # a scan of garbage: refused, a new epoch, never a pose far from the last
    blank = Scan(np.full(1081, np.inf), -2.35, 0.00436, 0.05, 8.0, stamp=t + 0.1)
    assert odo.add(blank) == (0.0, 0.0, 0.0)
    assert odo.epoch == 3


def test_memory_odometers_pick_what_carries_the_memory():
    from asgp_ros.core.obstacle_memory import MemoryConfig, Odometer
    from asgp_ros.core.scan_match import ScanOdometer, memory_odometers

    mount = (0.3, 0.0, 0.0)
    memory = MemoryConfig()
    odo, scan = memory_odometers(memory, "dead_reckoning", mount)
    assert isinstance(odo, Odometer) and scan is None
    odo, scan = memory_odometers(memory, "scan_matching", mount)
    assert odo is None and isinstance(scan, ScanOdometer)
    assert memory_odometers(None, "scan_matching", mount) == (None, None)
    with pytest.raises(ValueError, match="memory_odometry must be one of"):
        memory_odometers(None, "gps", mount)


def test_a_scan_repeating_the_previous_ones_ranges_is_a_stuck_driver(lidar: Lidar) -> None:
    """A driver that re-stamps its last scan would read as a standstill: the exact repeat
    starts a new epoch with no twist; the scanner's next real scan matches again."""
    odo = ScanOdometer(lidar.config.mount)
    pose = (-2.0, 0.0, 0.0)
    odo.add(scan_at(lidar, pose, 0.0))
    moved = compose(pose, (0.05, 0.0, 0.0))
    stuck = scan_at(lidar, moved, 0.1)
    odo.add(stuck)
    assert odo.last_twist is not None and odo.epoch == 0
    again = Scan(stuck.ranges.copy(), stuck.angle_min, stuck.angle_increment,
                 stuck.range_min, stuck.range_max, stamp=0.2)
    assert odo.add(again) == (0.0, 0.0, 0.0)
    assert odo.last_twist is None and odo.epoch == 1
    assert odo.refused == {"repeated ranges": 1}
    # the scanner's own noise, standing still: never bit-identical, a twist of about zero
    odo.add(scan_at(lidar, moved, 0.3))
    assert odo.epoch == 1 and odo.last_twist == pytest.approx((0.0, 0.0), abs=0.05)


def test_a_driver_filling_one_buffer_in_place_is_not_a_stuck_one(lidar: Lidar) -> None:
    """The repeat check compares values, not the array object: scans built on one buffer
    that the driver refills in place still match."""
    odo = ScanOdometer(lidar.config.mount)
    first = scan_at(lidar, (-2.0, 0.0, 0.0), 0.0)
    buf = first.ranges.copy()
    for i in range(1, 6):
        buf[:] = scan_at(lidar, (-2.0 + 0.04 * i, 0.0, 0.0), 0.1 * i).ranges
        odo.add(Scan(buf, first.angle_min, first.angle_increment, first.range_min,
                     first.range_max, stamp=0.1 * i))
    assert odo.epoch == 0 and odo.refused == {}, odo.refused
    assert odo.last_twist == pytest.approx((0.4, 0.0), abs=0.05)


def test_the_velocity_selector_takes_the_scans_while_they_match_and_the_vo_else() -> None:
    from asgp_ros.core.scan_match import VelocitySelector

    vo = VelocitySelector("vo")
    assert not vo.uses_scans and vo.scan(0.0, (1.0, 0.0)) == (False, None) and vo.vo(0.0)
    scans = VelocitySelector("scan_matching")
    assert scans.scan(0.0, (1.0, 0.1)) == (True, (1.0, 0.1))
    assert scans.scan(0.1, None) == (True, None)  # a refused match: a tracking loss
    assert not scans.vo(0.2) and not scans.vo(5.0)  # the VO never, however long
    auto = VelocitySelector("auto", fallback_s=0.3)
    assert auto.vo(0.0) and auto.current == "vo"  # no scan yet: the VO
    assert auto.scan(0.1, (1.0, 0.0)) == (True, (1.0, 0.0)) and auto.current == "scans"
    assert not auto.vo(0.2) and not auto.vo(0.35)  # the scans match: no VO
    assert auto.scan(0.5, None) == (False, None)  # a refused match gives nothing...
    assert auto.vo(0.55) and auto.current == "vo"  # ...and the VO's next twist is taken
    assert auto.scan(0.6, (0.9, 0.0)) == (True, (0.9, 0.0)) and not auto.vo(0.65)
    assert auto.vo(0.95)  # the laser went silent for more than fallback_s
    assert auto.switches == 4 and auto.describe() == "auto (vo; 4 switches)"
    # the clock goes back (a bag replayed again): a scan matched "in the future" does not
    # hold the VO off; a VO stamp a little older than the newest scan is still held off
    assert auto.scan(100.0, (0.9, 0.0))[0] and not auto.vo(99.9)
    assert auto.vo(50.0)
    assert auto.vo(math.nan)  # passed on: the predictor refuses a stamp that is not finite
    assert scans.describe() == "scan_matching"
    with pytest.raises(ValueError, match="velocity_source"):
        VelocitySelector("wheels")
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="fallback_s"):
            VelocitySelector("auto", fallback_s=bad)
