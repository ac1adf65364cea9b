"""RGB-D renderer and test scenes: exact geometry, the sensor model, the scene layout."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from asgp_ros.sim.render import DepthNoise, RGBDRenderer, default_camera_matrix
from asgp_ros.sim.scene import (
    blank_wall_drive,
    build_scene,
    loop_drive,
    segment_drive,
)
from asgp_ros.sim.world import Room
from asgp_ros.vo.extrinsics import DEFAULT_EXTRINSIC, CameraExtrinsic, invert, rot_rpy


@pytest.fixture(scope="module")
def rich():
    return build_scene(preset="rich", seed=0)


@pytest.fixture(scope="module")
def poor():
    return build_scene(preset="poor", seed=0)


def _look(position, yaw, pitch=0.0) -> np.ndarray:
    """Optical-frame pose at ``position`` looking along heading ``yaw`` (pitch down > 0)."""
    T = np.eye(4)
    T[:3, :3] = rot_rpy(0.0, pitch, yaw) @ np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    T[:3, 3] = position
    return T


def test_depth_of_a_fronto_parallel_wall_is_exact(rich):
    r = RGBDRenderer(rich, noise=DepthNoise.perfect())
    # 2 m in front of the +x wall at x = 6, looking at it, 1.6 m high (above the furniture)
    image, depth = r.render(_look((4.0, 3.5, 2.2), 0.0))
    assert image.shape == (480, 640, 3) and image.dtype == np.uint8
    assert depth.shape == (480, 640) and depth.dtype == np.float32
    assert depth[240, 320] == pytest.approx(2.0, abs=1e-4)


def test_floor_points_back_project_onto_the_floor(rich):
    r = RGBDRenderer(rich, noise=DepthNoise.perfect())
    T = _look((0.0, 0.0, 1.0), 0.3, pitch=math.radians(50))
    _, depth = r.render(T)
    K = r.K
    vs, us = np.mgrid[300:480:20, 0:640:40]
    z = depth[vs, us].astype(float)
    rays = np.stack([(us - K[0, 2]) / K[0, 0], (vs - K[1, 2]) / K[1, 1], np.ones_like(z)], -1)
    world = (rays * z[..., None]) @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(world[..., 2], 0.0, atol=1e-3)


def test_texture_is_consistent_between_views(rich):
    """A world point has the same colour seen from two poses (homography texturing)."""
    r = RGBDRenderer(rich, noise=DepthNoise.perfect())
    Ta = _look((0.0, 0.0, 1.0), math.pi, pitch=math.radians(15))
    Tb = _look((0.2, 0.1, 1.0), math.pi + 0.1, pitch=math.radians(15))
    ia, da = r.render(Ta)
    ib, db = r.render(Tb)
    K = r.K
    rng = np.random.default_rng(1)
    us, vs = rng.integers(60, 580, 200), rng.integers(60, 420, 200)
    z = da[vs, us].astype(float)
    ok = np.isfinite(z)
    rays = np.stack([(us - K[0, 2]) / K[0, 0], (vs - K[1, 2]) / K[1, 1], np.ones_like(z)], -1)
    Xw = (rays * z[:, None]) @ Ta[:3, :3].T + Ta[:3, 3]
    Xb = (Xw - Tb[:3, 3]) @ Tb[:3, :3]
    ub = K[0, 0] * Xb[:, 0] / Xb[:, 2] + K[0, 2]
    vb = K[1, 1] * Xb[:, 1] / Xb[:, 2] + K[1, 2]
    inside = ok & (ub > 2) & (ub < 637) & (vb > 2) & (vb < 477)
    ubi, vbi = np.rint(ub[inside]).astype(int), np.rint(vb[inside]).astype(int)
    visible = np.abs(db[vbi, ubi] - Xb[inside, 2]) < 0.02  # not occluded in view b
    ga = cv2.cvtColor(ia, cv2.COLOR_BGR2GRAY).astype(float)
    gb = cv2.GaussianBlur(cv2.cvtColor(ib, cv2.COLOR_BGR2GRAY), (3, 3), 0).astype(float)
    a = cv2.GaussianBlur(ga, (3, 3), 0)[vs[inside][visible], us[inside][visible]]
    b = gb[vbi[visible], ubi[visible]]
    assert visible.sum() > 100
    assert np.median(np.abs(a - b)) < 8.0


def test_depth_noise_grows_with_z_squared_and_is_quantised(rich):
    noise = DepthNoise(blob_fraction=0.0, dropout_fraction=0.0, edge_fraction=0.0)
    r = RGBDRenderer(rich, noise=noise, seed=3)
    stds = {}
    for dist in (1.5, 4.0):
        _, depth = r.render(_look((6.0 - dist, 3.5, 2.2), 0.0))
        patch = depth[200:280, 280:360].astype(float)
        assert np.all(patch > 0)
        stds[dist] = patch.std()
        # disparity f b / z takes values on a 1/8 px grid
        disp = r.K[0, 0] * noise.baseline / patch
        np.testing.assert_allclose(disp * 8, np.round(disp * 8), atol=1e-3)
    fb = r.K[0, 0] * noise.baseline
    for dist, s in stds.items():
        expected = math.hypot(dist**2 / fb * noise.disparity_sigma,  # noise
                              dist**2 / fb / 8 / math.sqrt(12))  # quantisation
        assert s == pytest.approx(expected, rel=0.35), (dist, s, expected)
    assert stds[4.0] > 4 * stds[1.5]


def test_range_limits_and_holes(rich):
    r = RGBDRenderer(rich, seed=0)
    # the camera 8.6 m from the -x wall: the far wall is out of range
    _, exact = RGBDRenderer(rich, noise=DepthNoise.perfect()).render_chair(3.0, 0.0, 0.0)
    _, depth = r.render_chair(3.0, 0.0, 0.0)
    valid = depth > 0
    assert np.all(depth[valid] >= 0.3) and np.all(depth[valid] <= 6.0)
    far = exact > 6.2
    assert far.any() and not valid[far].any()  # beyond range: no data
    near_ok = (exact > 0.5) & (exact < 5.5)
    hole_fraction = 1.0 - valid[near_ok].mean()
    assert 0.005 < hole_fraction < 0.2


def test_noise_is_seeded(rich):
    a = RGBDRenderer(rich, seed=5).render_chair(0.0, 0.0, 0.0)
    b = RGBDRenderer(rich, seed=5).render_chair(0.0, 0.0, 0.0)
    r = RGBDRenderer(rich, seed=5)
    r.render_chair(0.0, 0.0, 0.0)
    c = r.render_chair(0.0, 0.0, 0.0)  # second frame: new noise
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert not np.array_equal(a[0], c[0])


def test_extrinsic_looks_backward_and_down():
    T = DEFAULT_EXTRINSIC.camera_pose_planar(0.0, 0.0, 0.0)
    axis = T[:3, 2]  # optical z in the world
    np.testing.assert_allclose(axis, [-math.cos(math.radians(15)), 0.0,
                                      -math.sin(math.radians(15))], atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [-0.4, 0.0, 1.0])
    # image x (optical x) points to the chair's left when looking backward
    np.testing.assert_allclose(T[:3, 0], [0.0, 1.0, 0.0], atol=1e-12)


def test_furniture_stays_in_the_band_and_blank_wall_is_blank(rich):
    room = rich.room
    band = room.furniture_band
    for q in rich.quads:
        if "_box" not in q.name:
            continue
        c = q.corners
        d = np.minimum.reduce([c[:, 0] - room.x_min, room.x_max - c[:, 0],
                               c[:, 1] - room.y_min, room.y_max - c[:, 1]])
        assert np.all(d <= band + 1e-9), q.name
    x0, x1, y = rich.blank_wall
    r = RGBDRenderer(rich, seed=0)
    image, depth = r.render(_look(((x0 + x1) / 2, y - 1.2, 1.3), math.pi / 2))
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    corners = cv2.FastFeatureDetector_create(20).detect(gray)
    assert len(corners) < 5
    assert (depth > 0).mean() > 0.8


def test_poor_scene_has_dim_zone(poor, rich):
    x0, x1, y = poor.blank_wall
    pose = _look(((x0 + x1) / 2, y - 2.5, 1.0), math.pi / 2, pitch=0.6)  # floor near the wall
    dim = RGBDRenderer(poor, noise=DepthNoise.perfect()).render(pose)[0].mean()
    lit = RGBDRenderer(rich, noise=DepthNoise.perfect()).render(pose)[0].mean()
    assert poor.dim_zone is not None and rich.dim_zone is None
    assert dim < 0.6 * lit


def test_drives_stay_clear_of_the_furniture_band():
    room = Room()
    for drive in (loop_drive(40.0, 10.0), blank_wall_drive(10.0)):
        clear = [room.footprint_clearance(x, y, th)
                 for x, y, th in zip(drive.x, drive.y, drive.theta, strict=True)]
        assert min(clear) >= room.furniture_band
    d = segment_drive((0.0, 0.0, 0.0), [(0.5, 0.5, 2.0)], 10.0)
    # constant-curvature arc: radius v / omega = 1 m, after 2 s the heading is 1 rad
    assert d.theta[-1] == pytest.approx(1.0)
    assert d.x[-1] == pytest.approx(math.sin(1.0))
    assert d.y[-1] == pytest.approx(1.0 - math.cos(1.0))


def test_custom_size_and_camera_matrix(rich):
    K = default_camera_matrix(320, 240)
    assert K[0, 0] == pytest.approx(262.5, rel=1e-3)
    r = RGBDRenderer(rich, camera_matrix=K, width=320, height=240)
    image, depth = r.render_chair(0.0, 0.0, 0.0)
    assert image.shape == (240, 320, 3) and depth.shape == (240, 320)
    with pytest.raises(ValueError, match="too small"):
        RGBDRenderer(rich, width=8, height=8)
    with pytest.raises(ValueError, match="preset"):
        build_scene(preset="shiny")
    with pytest.raises(ValueError, match="range"):
        DepthNoise(min_range=3.0, max_range=2.0)


def test_extrinsic_twist_round_trip():
    """A unicycle arc of the chair gives back (v, omega) through the camera motion."""
    ext = CameraExtrinsic(x=-0.3, y=0.05, z=0.9, pitch=0.2, yaw=math.pi)
    for v, w in ((0.5, 0.0), (0.4, 0.6), (-0.3, -0.4), (0.0, 0.8)):
        dt = 0.1
        d = segment_drive((1.0, 2.0, 0.4), [(v, w, dt)], 1.0 / dt)
        Ta = ext.camera_pose_planar(d.x[0], d.y[0], d.theta[0])
        Tb = ext.camera_pose_planar(d.x[1], d.y[1], d.theta[1])
        got = ext.planar_twist(invert(Ta) @ Tb, dt)
        assert got == pytest.approx((v, w), abs=1e-9)


def test_extrinsic_and_twist_inputs_are_checked():
    with pytest.raises(ValueError, match="must be finite"):
        CameraExtrinsic(z=math.nan)
    with pytest.raises(ValueError, match="dt must be positive"):
        DEFAULT_EXTRINSIC.planar_twist(np.eye(4), 0.0)
