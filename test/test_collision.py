"""Collision probability (asgp_ros.core.collision) and the simulated scanner and map
(asgp_ros.sim.lidar), against closed forms and a Monte Carlo reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import norm

from asgp_ros.core import collision as C  # noqa: N812 (the module is used a lot)
from asgp_ros.sim.chair import Chair
from asgp_ros.sim.driver import Driver, DriverParams
from asgp_ros.sim.lidar import Lidar, LidarConfig, cast_to_box, room_grid
from asgp_ros.sim.world import Room

HALF = 0.6  # half the default footprint length


def wall_scan(distance: float = 2.0, beams: int = 1081) -> C.Scan:
    """A straight wall x = distance in the scan frame, 270 degrees, 8 m range."""
    a0, inc = -0.75 * math.pi, 1.5 * math.pi / (beams - 1)
    ang = a0 + inc * np.arange(beams)
    with np.errstate(divide="ignore"):
        r = np.where(np.cos(ang) > 1e-9, distance / np.cos(ang), np.inf)
    return C.Scan(np.where(r > 8.0, np.inf, r), a0, inc, 0.05, 8.0)


def one(x: float, y: float = 0.0, yaw: float = 0.0, sd: float = 0.05):
    return np.array([[x, y, yaw]]), np.eye(2)[None] * sd**2


def test_far_from_obstacles_the_probability_is_zero():
    check = C.scan_check(wall_scan())
    per, within = check(*one(0.0))
    assert per[0, 0] == 0.0 and within[0] == 0.0


def test_the_probability_follows_the_gaussian_tail_at_the_footprint_front():
    check = C.scan_check(wall_scan(2.0))
    for gap in (0.15, 0.1, 0.05, 0.0, -0.05, -0.1):  # front of the footprint to the wall
        _, within = check(*one(2.0 - HALF - gap, sd=0.05))
        # exact for a straight wall: P(x_front > 2) = Phi(-gap / sd), to the sample grid
        assert within[0] == pytest.approx(norm.cdf(-gap / 0.05), abs=0.02), gap


def test_probability_is_monotone_in_distance_and_in_uncertainty():
    check = C.scan_check(wall_scan(2.0))
    xs = np.linspace(0.9, 1.5, 13)
    p = [check(*one(x))[1][0] for x in xs]
    assert np.all(np.diff(p) >= 0.0) and p[0] < 0.01 and p[-1] > 0.97  # Phi(2) at 1.5 m
    near = 2.0 - HALF - 0.1
    p_sd = [check(*one(near, sd=sd))[1][0] for sd in (0.01, 0.03, 0.05, 0.1, 0.2)]
    assert np.all(np.diff(p_sd) >= 0.0) and p_sd[0] == 0.0 and p_sd[-1] > 0.2


def test_the_footprint_orientation_matters():
    """1.2 m long, 0.7 m wide: 0.5 m from a wall, nose on it touches, side on it does not."""
    check = C.scan_check(wall_scan(2.0))
    assert check(*one(2.0 - 0.5, sd=0.01))[1][0] == 1.0
    assert check(*one(2.0 - 0.5, yaw=math.pi / 2, sd=0.01))[1][0] == 0.0


def test_against_monte_carlo_on_a_corner():
    """Two walls (a corner) and a correlated covariance: the quasi-random estimate agrees
    with 20,000 plain Monte Carlo draws of the exact rectangle test."""
    pts = np.concatenate([np.stack([np.full(200, 2.0), np.linspace(-3, 3, 200)], 1),
                          np.stack([np.linspace(-3, 3, 200), np.full(200, 1.0)], 1)])
    scan_r = np.hypot(pts[:, 0], pts[:, 1])
    order = np.argsort(np.arctan2(pts[:, 1], pts[:, 0]))
    ang = np.arctan2(pts[:, 1], pts[:, 0])[order]
    # an irregular scan is not representable; test through the field built from points
    fld = C.DistanceField(np.zeros((1, 1)), 0.05, (0.0, 0.0, 0.0), pts[order])
    grid_fld = _field_from_points(pts)
    pose, cov = np.array([[1.3, 0.45, 0.3]]), np.array([[[0.01, 0.006], [0.006, 0.02]]])
    est = C.contact_probability(grid_fld, pose, cov).within[0]
    rng = np.random.default_rng(1)
    draws = rng.multivariate_normal(pose[0, :2], cov[0], 20_000)
    c, s = math.cos(0.3), math.sin(0.3)
    q = (pts[None, :, :] - draws[:, None, :]) @ np.array([[c, -s], [s, c]])  # R^T (o - p)
    hit = ((np.abs(q[..., 0]) <= HALF) & (np.abs(q[..., 1]) <= 0.35)).any(axis=1)
    assert 0.05 < hit.mean() < 0.95
    assert est == pytest.approx(hit.mean(), abs=0.03)
    del fld, scan_r, ang


def _field_from_points(pts: np.ndarray, res: float = 0.02) -> C.DistanceField:
    lo = pts.min(axis=0) - 1.0
    n = np.ceil((pts.max(axis=0) + 1.0 - lo) / res).astype(int)
    mask = np.zeros((n[1], n[0]), bool)
    ij = np.floor((pts - lo) / res).astype(int)
    mask[ij[:, 1], ij[:, 0]] = True
    from asgp_ros.core.collision import _distances

    return C.DistanceField(_distances(mask, res), res, (lo[0], lo[1], 0.0), pts,
                           outside=math.inf)


def test_batches_and_horizon_limits():
    check_fld = C.DistanceField.from_scan(wall_scan(2.0))
    B, k = 5, 8
    pose = np.zeros((B, k, 3))
    pose[..., 0] = np.linspace(0.0, 1.0, k)[None] + np.linspace(0.0, 0.5, B)[:, None]
    cov = np.tile(np.eye(2) * 0.04**2, (B, k, 1, 1)) * np.linspace(1, 3, k)[None, :, None, None]
    c = C.contact_probability(check_fld, pose, cov)
    assert c.per_step.shape == (B, k) and c.within.shape == (B,)
    assert np.all(c.lower <= c.within + 1e-12) and np.all(c.within <= c.upper + 1e-12)
    assert np.all(np.diff(c.within) >= 0.0)  # paths further ahead are more likely to touch
    for b in range(B):  # a batch gives what each path alone gives
        single = C.contact_probability(check_fld, pose[b], cov[b])
        np.testing.assert_array_equal(single.per_step[0], c.per_step[b])


def test_scan_and_grid_agree_on_the_same_wall():
    res, n = 0.05, 200
    data = np.zeros((n, n), np.int8)
    data[:, round((2.0 + 5.0) / res)] = 100  # cells [2.0, 2.05]
    grid = C.Grid(data, res, (-5.0, -5.0, 0.0))
    scan_check, grid_check = C.scan_check(wall_scan(2.0)), C.grid_check(grid)
    for x in (1.0, 1.3, 1.35, 1.4, 1.45):
        assert scan_check(*one(x))[1][0] == pytest.approx(grid_check(*one(x))[1][0], abs=0.03)
    # the map in odom, the chair at (0, 0) facing +y: the same wall is now at y = 2
    data2 = np.zeros((n, n), np.int8)
    data2[round((2.0 + 5.0) / res), :] = 100
    rotated = C.grid_check(C.Grid(data2, res, (-5.0, -5.0, 0.0)), origin=(0.0, 0.0, math.pi / 2))
    assert rotated(*one(1.4))[1][0] == pytest.approx(0.5, abs=0.03)
    # unknown cells are obstacles unless told otherwise
    unknown = C.Grid(np.full((n, n), -1, np.int8), res, (-5.0, -5.0, 0.0))
    assert C.grid_check(unknown)(*one(0.0))[1][0] == 1.0
    assert C.grid_check(unknown, unknown_is_obstacle=False)(*one(0.0))[1][0] == 0.0


def _inside_by_brute_force(points: np.ndarray, x: float, y: float, yaw: float,
                           fp: C.Footprint) -> np.ndarray:
    """Every point's depth inside the rectangle at (x, y, yaw), 0 outside."""
    dx, dy = points[:, 0] - x, points[:, 1] - y
    qx = math.cos(yaw) * dx + math.sin(yaw) * dy - fp.offset
    qy = math.cos(yaw) * dy - math.sin(yaw) * dx
    return np.maximum(np.minimum(0.5 * fp.length - np.abs(qx), 0.5 * fp.width - np.abs(qy)),
                      0.0)


def _deepening_by_brute_force(points: np.ndarray, pose: np.ndarray, origin, fp) -> float:
    """Deepest a point goes past its depth at ``origin`` over the poses [k, 3]."""
    now = _inside_by_brute_force(points, *origin, fp)
    return max(0.0, max(float((_inside_by_brute_force(points, *p, fp) - now).max())
                        for p in pose))


def test_the_deepening_of_a_mean_path_is_how_much_deeper_the_obstacles_go():
    fld = C.DistanceField.from_scan(wall_scan(2.0))
    paths = np.array([[[1.0, 0.0, 0.0], [1.5, 0.0, 0.0]],
                      [[1.3, 0.0, 0.0], [1.3, 0.0, 0.0]],
                      [[1.5, 0.0, math.pi / 2], [1.7, 0.0, math.pi / 2]]])
    # the chair now far from the wall: the front 0.1 m past it; 0.1 m short of it; side on,
    # 0.35 + 0.05 m past it
    np.testing.assert_allclose(C.footprint_deepening(fld, paths), [0.1, 0.0, 0.05], atol=2e-3)
    assert C.footprint_deepening(fld, np.array([[1.0, 0.0, 0.0]])).shape == (1,)
    # the chair now 5 cm into the wall (the paths' origin): standing or backing away takes
    # it no deeper; 5 cm more forward does, by 5 cm
    near = C.DistanceField.from_scan(wall_scan(0.55))
    np.testing.assert_allclose(C.footprint_deepening(near, np.array(
        [[[0.0, 0.0, 0.0]], [[-0.2, 0.0, 0.0]], [[0.05, 0.0, 0.0]]])), [0.0, 0.0, 0.05],
        atol=2e-3)
    # the scanner's mount and the chair's motion since the scan move the wall as they
    # move the probability's
    moved = C.scan_check(wall_scan(2.0), mount=(0.3, 0.0, 0.0), base_motion=(0.2, 0.0, 0.0))
    assert moved.deepening(np.array([[[1.5, 0.0, 0.0]]]))[0] == pytest.approx(0.0, abs=2e-3)
    assert moved.deepening(np.array([[[1.6, 0.0, 0.0]]]))[0] == pytest.approx(0.1, abs=2e-3)
    with pytest.raises(C.CollisionError):
        C.footprint_deepening(fld, np.array([[[np.nan, 0.0, 0.0]]]))
    with pytest.raises(C.CollisionError):
        C.footprint_deepening(fld, np.zeros((2, 3, 2)))


def test_what_the_chair_touches_in_front_hides_no_new_contact_behind():
    """The nose 6 cm into a wall now: a turn that sweeps a rear corner 5 cm into a cabinet
    behind is 5 cm of deepening, though no point goes deeper than the nose's 6 cm."""
    front = np.stack([np.full(200, 0.54), np.linspace(-2.0, 2.0, 200)], axis=1)
    cabinet = np.stack([np.linspace(-2.0, -0.3, 200), np.full(200, 0.35 + 0.05 - 0.05)], 1)
    fld = _field_from_points(np.concatenate([front, cabinet]), res=0.02)
    fp = C.DEFAULT_FOOTPRINT
    sweep = np.array([[[-0.02, 0.0, 0.0], [-0.02, 0.05, 0.0]]])  # 5 cm to the left
    got = C.footprint_deepening(fld, sweep, fp)[0]
    want = _deepening_by_brute_force(fld.points, sweep[0], (0.0, 0.0, 0.0), fp)
    assert got == pytest.approx(want, abs=1e-9) and got == pytest.approx(0.05, abs=1e-3)


def test_the_deepening_matches_a_brute_force_test_of_every_point():
    rng = np.random.default_rng(4)
    fp = C.Footprint(1.1, 0.65, 0.15)
    for trial in range(20):
        pts = rng.uniform(-2.0, 2.0, (rng.integers(1, 400), 2))
        fld = _field_from_points(pts, res=0.05)
        pose = np.concatenate([rng.uniform(-1.5, 1.5, (3, 6, 2)),
                               rng.uniform(-4.0, 4.0, (3, 6, 1))], axis=-1)
        got = C.footprint_deepening(fld, pose, fp, transform=(0.2, -0.1, 0.3))
        R = np.array([[math.cos(0.3), -math.sin(0.3)], [math.sin(0.3), math.cos(0.3)]])
        moved = np.concatenate([pose[..., :2] @ R.T + [0.2, -0.1], pose[..., 2:] + 0.3], -1)
        want = [_deepening_by_brute_force(pts, moved[b], (0.2, -0.1, 0.3), fp)
                for b in range(3)]
        np.testing.assert_allclose(got, want, atol=1e-9, err_msg=f"trial {trial}")


def test_a_grid_checks_deepening_with_the_footprint_grown_by_half_a_cell():
    res, n = 0.05, 200
    data = np.zeros((n, n), np.int8)
    data[:, round((2.0 + 5.0) / res)] = 100  # cell centres at x = 2.025
    check = C.grid_check(C.Grid(data, res, (-5.0, -5.0, 0.0)))
    # the front at 1.5 + 0.6 + 0.025 (half a cell) reaches 0.1 past the centres
    assert check.deepening(np.array([[[1.5, 0.0, 0.0]]]))[0] == pytest.approx(0.1, abs=1e-9)
    assert check.deepening(np.array([[[1.35, 0.0, 0.0]]]))[0] == 0.0
    # with a scan: the larger of the two deepenings, and of the two probabilities
    scan = C.scan_check(wall_scan(1.9))
    both = C.PathCheck.either([scan, check])
    assert isinstance(both, C.PathCheck)
    pose = np.array([[[1.5, 0.0, 0.0]]])
    assert both.deepening(pose)[0] == pytest.approx(0.2, abs=2e-3)
    cov = np.eye(2)[None, None] * 0.05**2
    np.testing.assert_array_equal(both(pose, cov)[1], np.maximum(scan(pose, cov)[1],
                                                                  check(pose, cov)[1]))
    # a check that cannot give deepenings makes the pair one that gives none
    plain = C.PathCheck.either([scan, lambda p, c: (np.zeros(p.shape[:2]), np.zeros(1))])
    assert not isinstance(plain, C.PathCheck)
    assert C.PathCheck.either([scan]) is scan
    with pytest.raises(ValueError):
        C.PathCheck.either([])


def test_scan_mount_and_motion_since_the_scan_are_applied():
    # scanner 0.3 m ahead of the base: the wall 2 m from the scanner is 2.3 m from the base
    check = C.scan_check(wall_scan(2.0), mount=(0.3, 0.0, 0.0))
    assert check(*one(2.3 - HALF))[1][0] == pytest.approx(0.5, abs=0.03)
    # the chair moved 0.2 m forward since the scan: the wall is 0.2 m closer
    moved = C.scan_check(wall_scan(2.0), base_motion=(0.2, 0.0, 0.0))
    assert moved(*one(1.8 - HALF))[1][0] == pytest.approx(0.5, abs=0.03)


def test_bad_scans_are_refused_and_never_read_as_clear():
    a0, inc = -1.0, 0.01
    with pytest.raises(C.CollisionError, match="NaN"):
        C.scan_check(C.Scan(np.full(200, np.nan), a0, inc, 0.05, 8.0))
    half_bad = np.where(np.arange(200) % 3 == 0, 2.0, np.nan)
    with pytest.raises(C.CollisionError, match="NaN"):
        C.scan_check(C.Scan(half_bad, a0, inc, 0.05, 8.0))
    # angles beyond a turn of the laser's axis: at 1e17 rad every beam fell on one bearing
    # (float64), and a wall ahead read as clear
    for bad in (dict(ranges=np.zeros(0)), dict(range_min=-1.0), dict(range_max=np.inf),
                dict(angle_min=np.nan), dict(ranges=np.zeros((2, 2))),
                dict(angle_min=1e17), dict(angle_min=-7.0), dict(angle_increment=1.0),
                dict(angle_increment=1e30)):
        kw = dict(ranges=np.ones(10), angle_min=a0, angle_increment=inc, range_min=0.05,
                  range_max=8.0) | bad
        with pytest.raises(C.CollisionError):
            C.Scan(**kw)
    # a full turn, from -pi or from 0, is a scan
    C.Scan(np.ones(360), -np.pi, 2 * np.pi / 360, 0.05, 8.0)
    C.Scan(np.ones(360), 0.0, -2 * np.pi / 360, 0.05, 8.0)
    # -inf (too close to measure) is an obstacle at range_min, not free space
    close = np.full(200, np.inf)
    close[100] = -np.inf
    check = C.scan_check(C.Scan(close, -1.0, 0.01, 0.05, 8.0))
    assert check(*one(0.0, sd=0.01))[1][0] == 1.0
    # all +inf: nothing within range, clear; a path leaving the window counts as touching
    clear = C.scan_check(C.Scan(np.full(200, np.inf), -1.0, 0.01, 0.05, 8.0))
    assert clear(*one(0.0))[1][0] == 0.0
    assert clear(*one(20.0))[1][0] == 1.0
    with pytest.raises(C.CollisionError, match="NaN"):
        clear(np.array([[np.nan, 0.0, 0.0]]), np.eye(2)[None])


def test_an_erroneous_sector_is_never_read_as_a_way_through():
    """NaN beams (REP-117: erroneous) straight ahead, 40 degrees of a wall 1.5 m away that a
    chair would pass through if they read as free: a run of NaN beams counts as an obstacle
    at the nearer of the returns that bound it; a run between beams with no return gives
    none; a full-turn scan wraps. Scan matching and the memory keep to the returns."""
    scan = wall_scan(1.5)
    ang = scan.angle_min + scan.angle_increment * np.arange(scan.ranges.size)
    gap = np.abs(ang) < math.radians(20)
    holed = C.Scan(np.where(gap, np.nan, scan.ranges), scan.angle_min, scan.angle_increment,
                   scan.range_min, scan.range_max)
    assert C.scan_check(holed)(*one(0.5 - HALF))[1][0] == 0.0  # well short of it
    # through the NaN sector (0.55 m either side at 1.5 m, wider than the chair): touching
    assert C.scan_check(holed)(*one(1.6))[1][0] == 1.0
    assert len(C.scan_points(holed)) == np.count_nonzero(~gap & np.isfinite(scan.ranges))
    pts = C.erroneous_beam_points(holed)
    assert pts.shape == (np.count_nonzero(gap), 2)
    np.testing.assert_allclose(np.hypot(pts[:, 0], pts[:, 1]), 1.5 / math.cos(math.radians(20)),
                               rtol=2e-3)  # the nearer bounding return
    # bounded by a beam too close to measure on one side: range_min
    r = holed.ranges.copy()
    r[np.flatnonzero(gap)[0] - 1] = -np.inf
    near = C.erroneous_beam_points(C.Scan(r, scan.angle_min, scan.angle_increment, 0.05, 8.0))
    np.testing.assert_allclose(np.hypot(near[:, 0], near[:, 1]), 0.05)
    # NaN between beams with no return (open space both sides): nothing to stand in
    open_ = C.Scan(np.where(gap, np.nan, np.inf), scan.angle_min, scan.angle_increment, 0.05,
                   8.0)
    assert C.erroneous_beam_points(open_).shape == (0, 2)
    # NaN at the scan's edges, bounded on one side only
    r = np.full(100, 2.0)
    r[:5] = np.nan
    edge = C.erroneous_beam_points(C.Scan(r, -0.5, 0.01, 0.05, 8.0))
    np.testing.assert_allclose(np.hypot(edge[:, 0], edge[:, 1]), 2.0)
    # a full turn: the first and last beams are neighbours (the last one sees 1 m)
    n = 360
    r = np.full(n, 3.0)
    r[:4] = np.nan
    r[-1] = 1.0
    wrap = C.erroneous_beam_points(C.Scan(r, -math.pi, 2 * math.pi / n, 0.05, 8.0))
    np.testing.assert_allclose(np.hypot(wrap[:, 0], wrap[:, 1]), 1.0)
    assert C.erroneous_beam_points(wall_scan(1.5)).shape == (0, 2)


def test_ranges_to_line_segments():
    from asgp_ros.sim.lidar import cast_to_segments

    ang = np.array([0.0, 0.3, math.pi / 2, math.pi, -0.3])
    r = cast_to_segments(ang, [((2.0, -1.0), (2.0, 1.0)), ((3.0, -5.0), (3.0, 5.0))])
    np.testing.assert_allclose(r[[0, 1, 4]], 2.0 / np.cos(ang[[0, 1, 4]]))  # the nearer
    assert np.all(np.isinf(r[[2, 3]]))  # along the wall's line, and away from both
    assert np.isinf(cast_to_segments(np.array([0.0]), [((-1.0, 0.0), (-1.0, 1.0))])[0])


def test_simulated_scanner_ranges_match_the_room():
    room = Room()
    cfg = LidarConfig(noise_sd=0.0, dropout=0.0, mount=(0.0, 0.0, 0.0))
    lidar = Lidar(room, cfg, seed=0)
    _x_lo, x_hi, _y_lo, y_hi = room.free_box
    s = lidar.scan(1.0, 0.5, 0.0)
    mid = cfg.beams // 2  # straight ahead
    assert s.ranges[mid] == pytest.approx(x_hi - 1.0)
    left = np.argmin(np.abs(cfg.angle_min + cfg.angle_increment * np.arange(cfg.beams)
                            - math.pi / 2))
    assert s.ranges[left] == pytest.approx(y_hi - 0.5, abs=1e-9)
    assert cast_to_box(np.array([100.0, 0.0]), np.zeros(1), room.free_box)[0] == 0.0
    noisy = Lidar(room, LidarConfig(dropout=0.2), seed=1).scan(1.0, 0.5, 0.3)
    assert 0.1 < np.isnan(noisy.ranges).mean() < 0.3
    assert np.all(np.isnan(noisy.ranges) | np.isinf(noisy.ranges) | (noisy.ranges > 0.0))


def test_room_map_matches_the_geometry_and_the_scan():
    room = Room()
    g = room_grid(room, 0.05)
    res = g.resolution

    def cell(x: float, y: float) -> int:
        return int(g.data[int((y - g.origin[1]) / res), int((x - g.origin[0]) / res)])

    assert cell(0.0, 0.0) == 0 and cell(room.x_max - 0.2, 0.0) == 100
    assert cell(room.x_max + 0.3, 0.0) == -1
    # the chair near the east furniture: scan and map give the same probability
    x_hi = room.free_box[1]
    lidar = Lidar(room, LidarConfig(noise_sd=0.0, dropout=0.0), seed=0)
    for x in (x_hi - HALF - 0.2, x_hi - HALF, x_hi - HALF + 0.1):
        scan = C.Scan(*(lidar.scan(x, 0.0, 0.0).__dict__.values()))
        p_scan = C.scan_check(scan, mount=lidar.config.mount)(*one(0.0))[1][0]
        p_map = C.grid_check(C.Grid(g.data, g.resolution, g.origin),
                             origin=(x, 0.0, 0.0))(*one(0.0))[1][0]
        assert p_scan == pytest.approx(p_map, abs=0.05), x


def test_the_chair_stops_at_the_furniture_and_counts_contacts():
    room = Room()
    chair = Chair.for_room(room, seed=0, blocked=room.overlap)
    chair.reset((room.free_box[1] - 2.0, 0.0, 0.0))
    for _ in range(1000):  # 10 s full forward at the east furniture
        state = chair.step((1.0, 0.0), 0.01)
    assert not room.contact(state.x, state.y, state.theta)
    assert room.footprint_clearance(state.x, state.y, state.theta) - room.furniture_band \
        < 0.05
    assert chair.contacts == 1 and abs(state.v) < 0.05
    for _ in range(300):  # backing away is allowed
        state = chair.step((-1.0, 0.0), 0.01)
    assert state.x < room.free_box[1] - 1.0


def _drive(params: DriverParams, seconds: float, seed: int = 3) -> tuple[int, int]:
    room = Room()
    chair = Chair.for_room(room, seed=seed, blocked=room.overlap)
    state = chair.reset((0.0, 0.0, 0.0))
    driver = Driver(seed, room, params=params)
    for n in range(int(seconds * 100)):
        cmd = driver.command(n * 0.01, state)
        state = chair.step(cmd, 0.01)
    return chair.contacts, driver.inattentive_bouts


def test_an_inattentive_driver_bumps_into_furniture_an_attentive_one_does_not():
    contacts, bouts = _drive(DriverParams(), 180.0)
    assert contacts == 0 and bouts == 0
    contacts, bouts = _drive(DriverParams(inattention=0.3), 180.0)
    assert bouts >= 3 and contacts >= 2
    assert _drive(DriverParams(inattention=0.3), 60.0, seed=5) == \
        _drive(DriverParams(inattention=0.3), 60.0, seed=5)  # deterministic for a seed
    with pytest.raises(ValueError):
        DriverParams(inattention=1.5)


def test_the_exact_test_of_a_large_batch_keeps_its_memory_bounded():
    """Regression: the exact test worked in chunks of up to 4 M elements per intermediate
    array (32 MB each): one decision of the layer next to furniture peaked at 160 MB, and the
    soak saw the node's RSS swing by 50 MB. These 256 paths peaked at 174 MB; in chunks of
    64 k elements, 57 MB (mostly the samples' own arrays)."""
    import tracemalloc

    fld = C.DistanceField.from_scan(wall_scan(1.2))
    rng = np.random.default_rng(0)
    B, k = 256, 10
    x = np.linspace(0.1, 1.0, k)[None, :] + rng.uniform(-0.1, 0.1, (B, 1))
    pose = np.stack([x, rng.uniform(-0.3, 0.3, (B, k)), np.zeros((B, k))], axis=-1)
    cov = np.broadcast_to(np.eye(2) * 0.05**2, (B, k, 2, 2)).copy()
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        res = C.contact_probability(fld, pose, cov, method="exact")
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    front = C.DEFAULT_FOOTPRINT.offset + 0.5 * C.DEFAULT_FOOTPRINT.length
    assert np.all(res.within[x[:, -1] > 1.2 - front + 0.2] > 0.9)  # those reach the wall
    assert peak < 80e6, f"the exact test of {B} paths peaked at {peak / 1e6:.0f} MB"  # 174 before


def _longest_standstill(params: DriverParams, seconds: float, chair_seed: int,
                        driver_seed: int) -> float:
    """The longest time (s) the chair stays within 0.3 m and 0.5 rad of where it stood,
    from the end of the driver's lead-in (its rest) to the end of the drive."""
    room = Room()
    chair = Chair.for_room(room, seed=chair_seed, blocked=room.overlap)
    state = chair.reset((0.0, 0.0, 0.0))
    driver = Driver(driver_seed, room, params=params)
    cmd = np.zeros(2)
    anchor, since, longest = (0.0, 0.0, 0.0), 0.0, 0.0
    for n in range(int(seconds * 100)):
        t = n * 0.01
        if n % 2 == 0:
            cmd = driver.command(t, state)
        state = chair.step(cmd, 0.01)
        if (math.hypot(state.x - anchor[0], state.y - anchor[1]) > 0.3
                or abs(state.theta - anchor[2]) > 0.5 or driver.mode == "rest"):
            anchor, since = (state.x, state.y, state.theta), t
        longest = max(longest, t - since)
    return longest


def test_an_inattentive_driver_never_stands_still_for_long():
    """Regression: after an inattentive bout the simulated user's avoidance could stand
    still for minutes (a creep of 0.1 inside the chair's dead zone; lined up with its goal
    along a wall; backing off into the furniture of a corner), which stalled the soak's
    chair for 400 s. This seed stood still 43 s in its first 2 minutes, and for 27-77 s six
    times in 30 minutes."""
    assert _longest_standstill(DriverParams(inattention=0.1), 150.0, 1, 1001) < 20.0


def test_a_long_range_scan_gets_a_bounded_raster_and_the_same_answer():
    """A scan's range_max (up to 1000 m, from a message) sets the raster's extent: at 5 cm
    cells a 1000 m scanner would need 40,000 cells a side (gigabytes, at every decision).
    The raster is capped; the probabilities stay those of the short-range scan."""
    near = wall_scan(2.0)
    far = C.Scan(np.where(np.isinf(near.ranges),
                          2.0 / np.maximum(np.cos(near.angle_min + near.angle_increment
                                                  * np.arange(near.ranges.size)), 1e-9),
                          near.ranges), near.angle_min, near.angle_increment, 0.05, 1000.0)
    fld = C.DistanceField.from_scan(far)
    assert max(fld.dist.shape) <= C.MAX_SCAN_FIELD_SIDE
    assert C.DistanceField.from_scan(near).resolution == 0.05  # short range: unchanged
    x = np.linspace(0.0, 1.5, 10)
    pose = np.stack([x, np.zeros(10), np.zeros(10)], axis=1)[None]
    cov = np.tile(np.eye(2) * 0.05**2, (1, 10, 1, 1))
    a = C.scan_check(near, C.DEFAULT_FOOTPRINT)(pose, cov)
    b = C.scan_check(far, C.DEFAULT_FOOTPRINT)(pose, cov)
    assert a[1][0] > 0.5
    np.testing.assert_allclose(b[0], a[0], atol=1e-12)


def test_constant_twist_motion_moves_a_scan_into_the_prediction_frame() -> None:
    """The pose after dt at a constant twist is the unicycle's; dt < 0 is its inverse, so
    going forward and then back composes to the identity; dt = 0 is the identity."""
    from asgp_ros.core.unicycle import integrate_path

    v, w, dt = 0.6, 0.8, 0.35
    ahead = C.constant_twist_motion(v, w, dt)
    np.testing.assert_allclose(ahead, integrate_path(np.array([[v, w], [v, w]]), dt)[-1])
    assert ahead[0] > 0.0 and ahead[1] > 0.0 and math.isclose(ahead[2], w * dt)
    back = C.constant_twist_motion(v, w, -dt)
    assert back == C.inverse_pose(ahead)
    c, s = math.cos(ahead[2]), math.sin(ahead[2])  # compose ahead then back
    x = ahead[0] + c * back[0] - s * back[1]
    y = ahead[1] + s * back[0] + c * back[1]
    np.testing.assert_allclose([x, y, ahead[2] + back[2]], 0.0, atol=1e-12)
    assert C.constant_twist_motion(v, w, 0.0) == (0.0, 0.0, 0.0)


@pytest.mark.parametrize("shape, obstacles", [((324, 324), 300), ((7, 400), 1),
                                              ((1, 1), 1), ((900, 300), 3)])
def test_the_distance_field_is_the_exact_euclidean_transform_and_never_more(shape,
                                                                            obstacles):
    """The field's clearances (OpenCV's transform) against scipy's exact Euclidean
    distance transform as the reference: the same to 1e-5 of the distance, never larger,
    less half a cell; inf everywhere without an obstacle."""
    import scipy.ndimage

    from asgp_ros.core.collision import _distances

    rng = np.random.default_rng(obstacles)
    mask = np.zeros(shape, bool)
    mask[rng.integers(0, shape[0], obstacles), rng.integers(0, shape[1], obstacles)] = True
    res = 0.05
    want = np.maximum(scipy.ndimage.distance_transform_edt(~mask) * res - 0.5 * res, 0.0)
    got = _distances(mask, res)
    assert got.dtype == np.float64 and got.shape == shape
    assert np.all(got <= want)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-7)
    assert np.all(got[mask] == 0.0)
    assert np.all(np.isinf(_distances(np.zeros(shape, bool), res)))


_CORE_CHECK = """
import importlib, json, pkgutil, sys
blocked = {blocked!r}
for name in blocked:
    sys.modules[name] = None  # an import of it raises ImportError
before = set(sys.modules)  # the interpreter's own start-up (site hooks) is not the core's
import numpy as np
import asgp_ros.core
for m in pkgutil.iter_modules(asgp_ros.core.__path__):
    importlib.import_module("asgp_ros.core." + m.name)
from importlib.metadata import packages_distributions
installed = packages_distributions()  # top-level import name -> its distributions
loaded = {{n.split(".")[0] for n, mod in sys.modules.items()
          if mod is not None and n not in before}}
third = sorted(loaded & set(installed) - {{"asgp_ros", "numpy", "scipy", "threadpoolctl"}})
cv2_at_import = "cv2" in sys.modules and sys.modules["cv2"] is not None
from asgp_ros.core.collision import _distances
import scipy.ndimage
rng = np.random.default_rng(5)
mask = np.zeros((120, 90), bool)
mask[rng.integers(0, 120, 40), rng.integers(0, 90, 40)] = True
want = np.maximum(scipy.ndimage.distance_transform_edt(~mask) * 0.05 - 0.025, 0.0)
got = _distances(mask, 0.05)
print(json.dumps({{"third": third, "cv2_at_import": cv2_at_import,
                  "cv2_used": sys.modules.get("cv2") is not None,
                  "exact": bool(np.array_equal(got, want)),
                  "close": bool(np.all(got <= want) and np.allclose(got, want, rtol=1e-5))}}))
"""


@pytest.mark.parametrize("blocked", [(), ("cv2", "rclpy", "sklearn", "matplotlib", "rosbags",
                                          "serial")])
def test_the_core_needs_numpy_and_scipy_alone(repo_root, blocked):
    """Every module of asgp_ros.core imports with numpy, scipy and threadpoolctl alone (the
    others blocked): OpenCV is imported at the first distance field, not with the core, and
    where it cannot be, the field is scipy's exact transform itself."""
    import json
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-c", _CORE_CHECK.format(blocked=list(blocked))],
                       cwd=repo_root, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout.splitlines()[-1])
    assert out["third"] == [] and not out["cv2_at_import"], out
    assert out["close"], out
    if blocked:
        assert out["exact"] and not out["cv2_used"], out
    else:
        assert out["cv2_used"], out


def test_a_path_of_zero_steps_is_refused_never_read_as_clear():
    # a Prediction that is not ok (a stale joystick) carries pose (0, 3) and pos_cov
    # (0, 2, 2): every check read it as p = 0, "clear", against a map occupied everywhere
    grid = C.Grid(np.full((40, 40), 100, dtype=np.int8), 0.05, (-1.0, -1.0, 0.0))
    fld = C.DistanceField.from_grid(grid)
    pose, cov = np.zeros((0, 3)), np.zeros((0, 2, 2))
    for check in (C.scan_check(wall_scan(1.0)), C.grid_check(grid)):
        for p, c in ((pose, cov), (pose[None], cov[None]), (np.zeros((3, 0, 3)),
                                                             np.zeros((3, 0, 3, 3)))):
            with pytest.raises(C.CollisionError, match="zero steps"):
                check(p, c)
            with pytest.raises(C.CollisionError, match="zero steps"):
                check.deepening(p if p.ndim == 3 else p[None])
    with pytest.raises(C.CollisionError, match="zero steps"):
        C.contact_probability(fld, pose, cov)
    with pytest.raises(C.CollisionError, match="zero steps"):
        C.footprint_deepening(fld, pose)
    # one step is a path, and the occupied map reads as touching
    assert C.grid_check(grid)(*one(0.0))[1][0] == 1.0
