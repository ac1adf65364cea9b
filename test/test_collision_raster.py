"""The collision probability's fast path (asgp_ros.core.collision, the footprint raster)
against a brute-force reference, heading uncertainty, and hostile inputs.

The reference tests every sample's rectangle against every obstacle point, with the same
fixed draws, so the comparison is sample by sample: a sample the reference finds touching
must be touching for the raster too (never an under-estimate), and one the raster finds
touching must touch the rectangle grown by the returned tolerance.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from asgp_ros.core import collision as C  # noqa: N812 (the module is used a lot)

FP = C.DEFAULT_FOOTPRINT
HALF_FP = abs(FP.offset) + 0.5 * FP.length  # farthest reach of the footprint, ahead


def reference(fld: C.DistanceField, pose: np.ndarray, cov: np.ndarray,
              footprint: C.Footprint = FP, transform=(0.0, 0.0, 0.0), grow: float = 0.0
              ) -> tuple[np.ndarray, np.ndarray]:
    """(per_step [B, k], within [B]) by the exact rectangle test of every sample against
    every obstacle point; the rectangle grown by ``grow`` (m) on every side."""
    pose = np.asarray(pose, float).reshape(-1, pose.shape[-2], 3)
    d = cov.shape[-1]
    cov = np.asarray(cov, float).reshape(pose.shape[0], pose.shape[1], d, d)
    z = C._draws(C.SAMPLES)  # the module's fixed draws [S, 3]
    c0, s0 = math.cos(transform[2]), math.sin(transform[2])
    R = np.array([[c0, -s0], [s0, c0]])
    T = np.eye(d)
    T[:2, :2] = R
    xy = pose[..., :2] @ R.T + np.array(transform[:2])
    yaw = pose[..., 2] + transform[2]
    L = np.linalg.cholesky(T @ cov @ T.T)  # every test covariance is positive definite
    off = np.einsum("bkij,sj->bksi", L, z[:, :d])  # [B, k, S, d]
    p = xy[:, :, None, :] + off[..., :2]
    th = yaw[:, :, None] + (off[..., 2] if d == 3 else 0.0)
    g = grow + fld.grow
    x_lo = footprint.offset - 0.5 * footprint.length - g
    x_hi = footprint.offset + 0.5 * footprint.length + g
    half_w = 0.5 * footprint.width + g
    pts = fld.points
    touch = np.zeros(p.shape[:3], bool)
    c, s = np.cos(th)[..., None], np.sin(th)[..., None]
    for i in range(0, pts.shape[0], 512):  # chunks of points: bounded memory
        dx = pts[i:i + 512, 0] - p[..., :1]  # [B, k, S, m]
        dy = pts[i:i + 512, 1] - p[..., 1:]
        qx, qy = c * dx + s * dy, c * dy - s * dx
        touch |= ((qx >= x_lo) & (qx <= x_hi) & (np.abs(qy) <= half_w)).any(axis=-1)
    if fld.outside == 0.0:
        touch |= ~fld.contains(p)
    return touch.mean(axis=2), touch.any(axis=1).mean(axis=1)


def points_field(pts: np.ndarray, res: float = 0.05, outside: float = math.inf
                 ) -> C.DistanceField:
    """A field of arbitrary obstacle points (a 'scan' that is not a scan)."""
    lo = pts.min(axis=0) - 1.0 if pts.size else np.array([-3.0, -3.0])
    hi = pts.max(axis=0) + 1.0 if pts.size else np.array([3.0, 3.0])
    n = np.ceil((hi - lo) / res).astype(int)
    mask = np.zeros((n[1], n[0]), bool)
    if pts.size:
        ij = np.floor((pts - lo) / res).astype(int)
        mask[ij[:, 1], ij[:, 0]] = True
    return C.DistanceField(C._distances(mask, res), res, (lo[0], lo[1], 0.0), pts,
                           outside=outside)


def random_scene(rng: np.random.Generator) -> C.DistanceField:
    """Walls, boxes and clutter from a scan, a grid, or bare points."""
    kind = rng.integers(3)
    if kind == 0:  # a scan of random ranges with REP-117 specials
        beams = int(rng.integers(50, 400))
        r = rng.uniform(0.3, 4.0, beams)
        r[rng.random(beams) < 0.1] = np.inf
        r[rng.random(beams) < 0.02] = -np.inf
        r[rng.random(beams) < 0.05] = np.nan
        inc = 2 * math.pi / beams
        return C.DistanceField.from_scan(C.Scan(r, -math.pi, inc, 0.1, 5.0))
    if kind == 1:  # an occupancy grid with blobs and unknown cells, rotated origin
        res = float(rng.choice([0.05, 0.1]))
        n = int(rng.integers(20, 60))
        data = np.zeros((n, n), np.int8)
        for _ in range(int(rng.integers(1, 6))):
            i, j = rng.integers(0, n, 2)
            h, w = rng.integers(1, 6, 2)
            data[i:i + h, j:j + w] = rng.choice([-1, 70, 100])
        origin = (float(rng.uniform(-2, 0)), float(rng.uniform(-2, 0)),
                  float(rng.uniform(-math.pi, math.pi)))
        return C.DistanceField.from_grid(C.Grid(data, res, origin),
                                         unknown_is_obstacle=bool(rng.integers(2)))
    segs = []  # wall segments and a cluster of points
    for _ in range(int(rng.integers(1, 4))):
        a, b = rng.uniform(-3, 3, (2, 2))
        segs.append(a + np.linspace(0, 1, int(rng.integers(10, 80)))[:, None] * (b - a))
    segs.append(rng.normal(rng.uniform(-2, 2, 2), 0.2, (int(rng.integers(0, 30)), 2)))
    return points_field(np.concatenate(segs), outside=float(rng.choice([0.0, math.inf])))


def random_paths(rng: np.random.Generator, B: int, k: int, heading: bool
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Poses near the scene (some off the raster) and positive-definite covariances from
    1e-12 to 1e6 (m^2, rad^2)."""
    pose = np.empty((B, k, 3))
    pose[..., :2] = rng.uniform(-4, 4, (B, 1, 2)) + np.cumsum(rng.normal(0, 0.1, (B, k, 2)), 1)
    pose[..., 2] = rng.uniform(-50, 50, (B, 1)) + np.cumsum(rng.normal(0, 0.2, (B, k)), 1)
    d = 3 if heading else 2
    A = rng.normal(size=(B, k, d, d))
    scale = 10.0 ** rng.choice([-12, -6, -4, -3, -2, -1, 0, 6], size=(B, k))
    cov = (A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(d)) * scale[..., None, None]
    if heading:  # a realistic share: headings within a few degrees mostly
        cov[..., 2, :] *= 0.3
        cov[..., :, 2] *= 0.3
    return pose, cov


def assert_bounded(fld, pose, cov, **kw):
    """The raster's per-step and within-horizon probabilities lie between the reference
    and the reference with the rectangle grown by the returned tolerance."""
    fast = C.contact_probability(fld, pose, cov, **({"method": "raster"} | kw))
    assert np.all(np.isfinite(fast.per_step)) and np.all(np.isfinite(fast.within))
    assert 0.0 <= fast.tolerance < 0.2
    lo_step, lo_within = reference(fld, pose, cov)
    hi_step, hi_within = reference(fld, pose, cov, grow=fast.tolerance)
    np.testing.assert_array_less(lo_step - 1e-12, fast.per_step)  # never under
    np.testing.assert_array_less(fast.per_step, hi_step + 1e-12)
    np.testing.assert_array_less(lo_within - 1e-12, fast.within)
    np.testing.assert_array_less(fast.within, hi_within + 1e-12)
    return fast, lo_step


@pytest.mark.parametrize("seed", range(12))
def test_the_raster_is_bounded_by_the_exact_test_on_random_scenes(seed):
    rng = np.random.default_rng(seed)
    fld = random_scene(rng)
    pose, cov = random_paths(rng, 4, 5, heading=bool(seed % 2))
    assert_bounded(fld, pose, cov)
    # a coarse raster and wide heading bins: looser, still never under
    assert_bounded(fld, pose, cov, raster=0.03, heading_bin=math.radians(8.0))


def test_the_raster_is_close_to_the_exact_test_where_it_matters():
    """Paths up to a wall with planner-like spreads: the raster's over-estimate is small."""
    rng = np.random.default_rng(7)
    wall = np.stack([np.full(300, 2.0), np.linspace(-3, 3, 300)], 1)
    fld = points_field(wall)
    B, k = 30, 8
    pose = np.zeros((B, k, 3))
    pose[..., 0] = rng.uniform(0.2, 1.0, B)[:, None] * np.linspace(0.3, 2.0, k)
    pose[..., 2] = rng.normal(0, 0.3, B)[:, None] * np.linspace(0.1, 1.0, k)
    cov = np.eye(2) * (np.linspace(0.02, 0.1, k) ** 2)[:, None, None] * np.ones((B, 1, 1, 1))
    fast, exact = assert_bounded(fld, pose, cov)
    assert fast.tolerance < 0.02
    assert np.abs(fast.per_step - exact).max() < 0.1
    assert np.abs(fast.per_step - exact).mean() < 0.01
    np.testing.assert_allclose(C.contact_probability(fld, pose, cov, method="exact").per_step,
                               exact, atol=1e-12)


def test_the_default_is_exact_for_a_path_and_the_raster_for_a_batch():
    wall = np.stack([np.full(300, 2.0), np.linspace(-3, 3, 300)], 1)
    fld = points_field(wall)
    pose = np.zeros((1, 10, 3))
    pose[..., 0] = np.linspace(0.3, 1.6, 10)
    cov = np.tile(np.eye(2) * 0.05**2, (1, 10, 1, 1))
    one = C.contact_probability(fld, pose, cov)
    assert one.tolerance == 0.0 and one.within[0] > 0.3
    np.testing.assert_array_equal(one.per_step, reference(fld, pose, cov)[0])
    many = C.contact_probability(fld, np.repeat(pose, 256, 0), np.repeat(cov, 256, 0))
    assert 0.0 < many.tolerance < 0.03
    assert np.all(many.per_step >= one.per_step)


def test_edge_cases_stay_finite_and_bounded():
    rng = np.random.default_rng(3)
    wall = np.stack([np.full(100, 1.0), np.linspace(-2, 2, 100)], 1)
    for fld in (points_field(wall), points_field(wall, outside=0.0)):
        k = 4
        pose = np.zeros((6, k, 3))
        pose[1, :, 0] = 40.0  # off the raster
        pose[2, :, 2] = 1e5  # a heading of many turns
        cov = np.tile(np.eye(2) * 0.01, (6, k, 1, 1))
        cov[3] *= 1e8  # 1e6 m^2
        cov[4] *= 1e-10  # 1e-12 m^2
        cov[5] = np.array([[1e-4, 0.0], [0.0, 1e-12]])  # nearly singular
        assert_bounded(fld, pose, cov)
        c = C.contact_probability(fld, pose, cov)
        if fld.outside == 0.0:
            assert c.within[1] == 1.0  # off the raster counts as touching
            assert c.within[3] > 0.9  # nearly every sample is off the raster
        else:
            assert c.within[1] == 0.0
        pose3 = np.zeros((2, k, 3))
        cov3 = np.tile(np.eye(3) * 1e-4, (2, k, 1, 1))
        cov3[1, :, 2, 2] = 1e6  # a heading anywhere
        assert_bounded(fld, pose3, cov3)
    # an empty scan (no return within range): clear inside its window, touching outside
    clear = C.DistanceField.from_scan(C.Scan(np.full(90, np.inf), -1.0, 0.02, 0.05, 4.0))
    pose, cov = np.zeros((2, 3, 3)), np.tile(np.eye(2) * 1e-4, (2, 3, 1, 1))
    pose[1, :, 0] = 10.0
    c = C.contact_probability(clear, pose, cov)
    assert c.within.tolist() == [0.0, 1.0]
    assert_bounded(clear, pose, cov)
    # a grid that is all unknown, not an obstacle: nothing to touch
    unknown = C.DistanceField.from_grid(C.Grid(np.full((30, 30), -1, np.int8), 0.1),
                                        unknown_is_obstacle=False)
    assert C.contact_probability(unknown, pose, cov).within.tolist() == [0.0, 0.0]
    del rng


def test_a_heading_free_3x3_covariance_gives_the_2x2_result():
    rng = np.random.default_rng(5)
    fld = random_scene(np.random.default_rng(2))
    pose, cov = random_paths(rng, 5, 4, heading=False)
    cov3 = np.zeros((5, 4, 3, 3))
    cov3[..., :2, :2] = cov
    a = C.contact_probability(fld, pose, cov)
    b = C.contact_probability(fld, pose, cov3)
    np.testing.assert_array_equal(a.per_step, b.per_step)
    np.testing.assert_array_equal(a.within, b.within)


def corner_scene() -> C.DistanceField:
    """Two walls meeting at (1.0, 0.8): x = 1.0 for y >= 0.8 and y = 0.8 for x <= 1.0."""
    wall_x = np.stack([np.full(200, 1.0), np.linspace(0.8, 3.0, 200)], 1)
    wall_y = np.stack([np.linspace(-3.0, 1.0, 300), np.full(300, 0.8)], 1)
    return points_field(np.concatenate([wall_x, wall_y]), res=0.02)


def monte_carlo(pts, mean, cov, n=20_000, seed=1) -> float:
    """Plain Monte Carlo of (x, y, heading) with the exact rectangle test."""
    draws = np.random.default_rng(seed).multivariate_normal(mean, cov, n)
    c, s = np.cos(draws[:, 2:]), np.sin(draws[:, 2:])
    dx, dy = pts[:, 0] - draws[:, :1], pts[:, 1] - draws[:, 1:2]
    qx, qy = c * dx + s * dy, c * dy - s * dx
    return float(((np.abs(qx) <= 0.6) & (np.abs(qy) <= 0.35)).any(axis=1).mean())


def test_heading_uncertainty_counts_the_corner_sweep_of_a_turning_chair():
    """The chair's front-left corner 4 cm from a wall, turning towards it: with the mean
    heading only, almost no sample touches; with the heading's variance the corner's
    sweep does, as much as a plain Monte Carlo of (x, y, heading) says."""
    fld = corner_scene()
    pose = np.array([[0.25, 0.41, 0.0]])  # the left side 4 cm below y = 0.8
    pos = np.diag([0.01**2, 0.01**2])
    cov3 = np.zeros((1, 3, 3))
    cov3[0, :2, :2] = pos
    cov3[0, 2, 2] = 0.08**2  # heading sd 4.6 degrees
    cov3[0, 1, 2] = cov3[0, 2, 1] = 0.5 * 0.01 * 0.08  # correlated, as in a turn
    p2 = C.contact_probability(fld, pose, pos[None]).within[0]
    p3 = C.contact_probability(fld, pose, cov3).within[0]
    mc = monte_carlo(fld.points, pose[0], cov3[0])
    assert p2 < 0.01 and p3 > 0.3
    assert p3 == pytest.approx(mc, abs=0.03)
    assert C.contact_probability(fld, pose, cov3, method="exact").within[0] == \
        pytest.approx(mc, abs=0.03)
    # and through a check built from a scan of the same corner (3x3 accepted too)
    assert_bounded(fld, pose, cov3)


def test_heading_variance_only_adds_probability_next_to_a_corner():
    fld = corner_scene()
    rng = np.random.default_rng(11)
    pose = np.zeros((40, 1, 3))
    pose[:, 0, 0] = rng.uniform(-0.5, 0.2, 40)
    pose[:, 0, 1] = rng.uniform(0.3, 0.4, 40)
    pose[:, 0, 2] = rng.normal(0.0, 0.1, 40)
    pos = np.tile(np.eye(2) * 0.02**2, (40, 1, 1, 1))
    prev = C.contact_probability(fld, pose, pos, method="exact").within
    for sd in (0.02, 0.05, 0.1, 0.2):
        cov3 = np.zeros((40, 1, 3, 3))
        cov3[..., :2, :2] = pos
        cov3[..., 2, 2] = sd**2
        now = C.contact_probability(fld, pose, cov3, method="exact").within
        # not a theorem per sample, but for a chair beside a wall: more spread, more contact
        assert now.mean() >= prev.mean()
        prev = now
    assert prev.mean() > 0.2


@pytest.mark.parametrize("bad", [
    dict(pose=np.full((1, 2, 3), np.nan)),
    dict(pose=np.full((1, 2, 3), np.inf)),
    dict(pose=np.full((1, 2, 3), 1e30)),
    dict(cov=np.full((1, 2, 2, 2), 1e30)),
    dict(cov=np.full((1, 2, 3, 3), np.nan)),
    dict(cov=np.tile(np.eye(3), (1, 2, 1, 1)) * 1e30),
    dict(cov=np.zeros((1, 2, 4, 4))),
    dict(cov=np.zeros((1, 3, 2, 2))),
    dict(pose=np.zeros((1, 2, 2))),
    dict(transform=(0.0, math.nan, 0.0)),
    dict(transform=(1e30, 0.0, 0.0)),
])
def test_hostile_inputs_are_refused(bad):
    fld = points_field(np.array([[1.0, 0.0], [1.0, 0.1]]))
    args = dict(pose=np.zeros((1, 2, 3)), cov=np.tile(np.eye(2), (1, 2, 1, 1)) * 1e-3) | bad
    with pytest.raises(C.CollisionError):
        C.contact_probability(fld, **args)
    with pytest.raises(C.CollisionError):
        C.contact_probability(fld, **args, method="exact")


def test_bad_options_are_refused():
    fld = points_field(np.array([[1.0, 0.0]]))
    pose, cov = np.zeros((1, 3)), np.eye(2)[None] * 1e-3
    for kw in (dict(method="fast"), dict(raster=0.0), dict(raster=math.nan),
               dict(heading_bin=0.0), dict(heading_bin=4.0), dict(samples=100)):
        with pytest.raises(ValueError):
            C.contact_probability(fld, pose, cov, **kw)


def test_checks_take_the_full_pose_covariance():
    angles = np.linspace(-1.2, 1.2, 241)
    wall = C.Scan(0.65 / np.cos(angles), -1.2, 0.01, 0.05, 8.0)  # x = 0.65, 5 cm ahead
    check = C.scan_check(wall)
    pose = np.array([[[0.0, 0.0, 0.0]]])
    cov2 = np.eye(2)[None, None] * 0.01**2
    cov3 = np.zeros((1, 1, 3, 3))
    cov3[..., :2, :2] = cov2
    per2, within2 = check(pose, cov2)
    per3, within3 = check(pose, cov3)
    assert within2[0] == within3[0] and per2.shape == per3.shape == (1, 1)
    cov3[..., 2, 2] = 0.3**2  # turning, the front corners reach the wall
    assert within2[0] == 0.0 and check(pose, cov3)[1][0] > 0.3


def test_the_support_points_have_the_extent_of_all_points():
    """The raster's windows are cut by the obstacle points' extent in each heading bin's
    frame, taken over their convex hull's vertices: in every direction it must be the extent
    of all the points (a cloud, a wall on a line, duplicates, a few points)."""
    rng = np.random.default_rng(11)
    line = np.stack([np.full(200, 2.0), np.linspace(-3, 3, 200)], 1)
    clouds = [rng.uniform(-4, 4, (3000, 2)), line, np.repeat(line[:7], 5, axis=0),
              rng.normal(0, 1, (5, 2)), np.stack([3 * np.cos(a := rng.uniform(0, 7, 900)),
                                                  2 * np.sin(a)], 1) + 1e3]
    phi = np.linspace(0.0, 2.0 * np.pi, 1441)
    for pts in clouds:
        sup = C._support_points(pts)
        assert {tuple(p) for p in sup} <= {tuple(p) for p in pts}
        for a, b in ((np.cos(phi), np.sin(phi)), (-np.sin(phi), np.cos(phi))):
            every = a[:, None] * pts[None, :, 0] + b[:, None] * pts[None, :, 1]
            some = a[:, None] * sup[None, :, 0] + b[:, None] * sup[None, :, 1]
            np.testing.assert_allclose(some.min(axis=1), every.min(axis=1), rtol=0, atol=1e-9)
            np.testing.assert_allclose(some.max(axis=1), every.max(axis=1), rtol=0, atol=1e-9)
    assert C._support_points(rng.uniform(-4, 4, (3000, 2))).shape[0] < 100


def test_the_raster_gives_the_same_probabilities_from_the_hull_as_from_every_point(
        monkeypatch):
    """The windows cut by the hull's vertices give the probabilities and the tolerance that
    every obstacle point's box gave (a cloud, a wall, a room; position and pose
    covariances; one path and a batch)."""
    rng = np.random.default_rng(5)
    a = rng.uniform(0, 2 * np.pi, 900)
    scenes = [rng.uniform(-4, 4, (2000, 2)),
              np.stack([np.full(400, 1.8), np.linspace(-3, 3, 400)], 1),
              np.stack([3 * np.cos(a), 2 * np.sin(a)], 1)]
    k = 10
    for n, pts in enumerate(scenes):
        fld = points_field(pts)
        B = (1, 64)[n % 2]
        pose = np.zeros((B, k, 3))
        pose[..., 0] = rng.uniform(0.2, 1.0, B)[:, None] * np.linspace(0.3, 2.0, k)
        pose[..., 1] = rng.normal(0, 0.3, B)[:, None] * np.linspace(0.1, 1.0, k)
        pose[..., 2] = rng.normal(0, 0.5, B)[:, None] * np.linspace(0.1, 1.0, k)
        pos = np.eye(2) * (np.linspace(0.02, 0.1, k) ** 2)[:, None, None] * np.ones((B, 1, 1, 1))
        full = np.zeros((B, k, 3, 3))
        full[..., :2, :2] = pos
        full[..., 2, 2] = np.linspace(0.01, 0.2, k) ** 2
        for cov in (pos, full):
            hull = C.contact_probability(fld, pose, cov, method="raster")
            with monkeypatch.context() as m:
                m.setattr(C, "_support_points", lambda p: p)
                every = C.contact_probability(fld, pose, cov, method="raster")
            np.testing.assert_array_equal(hull.per_step, every.per_step)
            assert hull.tolerance == every.tolerance


@pytest.mark.parametrize("seed", range(4))
def test_without_opencv_the_raster_gives_the_same_probabilities(seed, monkeypatch):
    """The summed-area table by numpy's running sums (where OpenCV cannot be imported)
    equals cv2.integral's, table and probabilities, to the last bit: its entries are whole
    numbers."""
    rng = np.random.default_rng(100 + seed)
    diff = rng.integers(-3, 4, (rng.integers(1, 60), rng.integers(1, 60))).astype(np.float32)
    with_cv2 = C._summed_area(diff)
    fld = random_scene(rng)
    pose, cov = random_paths(rng, 4, 5, heading=bool(seed % 2))
    fast = C.contact_probability(fld, pose, cov, method="raster")
    monkeypatch.setattr(C, "_opencv", lambda: None)  # as when ``import cv2`` failed
    table = C._summed_area(diff)
    assert table.dtype == np.float32 and table.shape == (diff.shape[0] + 1, diff.shape[1] + 1)
    np.testing.assert_array_equal(table, with_cv2)
    np.testing.assert_array_equal(table[1:, 1:], np.cumsum(np.cumsum(diff, 0), 1))
    slow = C.contact_probability(fld, pose, cov, method="raster")
    np.testing.assert_array_equal(slow.per_step, fast.per_step)
    np.testing.assert_array_equal(slow.within, fast.within)
    assert slow.tolerance == fast.tolerance


@pytest.mark.parametrize("method", ["exact", "raster"])
def test_a_dense_scan_is_merged_and_stays_conservative(method):
    """A scan of 24,000 beams (a 3-D lidar flattened at 0.011 degrees) of a room with a
    pillar: its points are merged on a lattice to at most MAX_SCAN_POINTS (each test's
    cost grows with the points in reach: 100,000 beams took 0.19 s a path), and the
    probabilities stay between the exact test against every one of the scan's points and
    that test with the footprint grown by the returned tolerance, which says the merge."""
    beams = 24_000
    a0, inc = -0.75 * math.pi, 1.5 * math.pi / (beams - 1)
    ang = a0 + inc * np.arange(beams)
    c, s = np.cos(ang), np.sin(ang)
    with np.errstate(divide="ignore", invalid="ignore"):  # walls x = 2.2, y = +-1.5
        r = np.fmin(np.where(c > 1e-9, 2.2 / c, np.inf), np.where(np.abs(s) > 1e-9,
                                                                    1.5 / np.abs(s), np.inf))
        # a pillar of radius 0.15 m at (1.0, 0.45)
        b = c * 1.0 + s * 0.45
        disc = b * b - (1.0 + 0.45**2 - 0.15**2)
        hit = np.where(disc >= 0.0, b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
    r = np.fmin(r, np.where(hit > 0.0, hit, np.inf))
    scan = C.Scan(np.where(r > 8.0, np.inf, r), a0, inc, 0.05, 8.0)
    fld = C.DistanceField.from_scan(scan)
    every = C.scan_points(scan)
    assert every.shape[0] == beams and fld.obstacles <= C.MAX_SCAN_POINTS
    assert 0.0 < fld.merge < 0.01  # walls: a fine lattice suffices
    # every point of the scan lies within ``merge`` of a point that stands for it
    assert fld._tree.query(every)[0].max() <= fld.merge + 1e-12
    rng = np.random.default_rng(3)
    B, k = (1, 8) if method == "exact" else (4, 6)
    pose = np.zeros((B, k, 3))
    pose[..., 0] = rng.uniform(0.3, 1.0, B)[:, None] * np.linspace(0.3, 2.0, k)
    pose[..., 1] = rng.normal(0.0, 0.3, B)[:, None]
    pose[..., 2] = rng.normal(0, 0.3, B)[:, None] * np.linspace(0.1, 1.0, k)
    pose[0, :, :2] = np.stack([np.linspace(0.0, 0.8, k), np.full(k, 0.2)], axis=1)
    pose[0, :, 2] = 0.0  # towards the pillar's side
    cov = np.eye(2) * (np.linspace(0.02, 0.1, k) ** 2)[:, None, None] * np.ones((B, 1, 1, 1))
    got = C.contact_probability(fld, pose, cov, method=method)
    assert 2.0 * fld.merge <= got.tolerance < 0.05
    # the scan's own points, those within reach of a sample (the reference's cost)
    reach = np.abs(pose[..., :2]).max() + 0.5 + math.hypot(HALF_FP, 0.5 * FP.width)
    whole = dataclasses.replace(fld, points=every[np.abs(every).max(axis=1) < reach],
                                merge=0.0)
    lo_step, lo_within = reference(whole, pose, cov)
    hi_step, hi_within = reference(whole, pose, cov, grow=got.tolerance)
    assert lo_within.max() > 0.3  # the paths do reach the pillar or a wall
    np.testing.assert_array_less(lo_step - 1e-12, got.per_step)  # never under
    np.testing.assert_array_less(got.per_step, hi_step + 1e-12)
    np.testing.assert_array_less(lo_within - 1e-12, got.within)
    np.testing.assert_array_less(got.within, hi_within + 1e-12)
    # a scan of the usual size is not merged
    assert C.DistanceField.from_scan(C.Scan(r[::24], a0, inc * 24, 0.05, 8.0)).merge == 0.0
