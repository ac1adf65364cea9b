"""Fovis-like RGB-D odometry: its geometry kernels, rendered motions, failures and bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from asgp_ros.sim.render import RGBDRenderer
from asgp_ros.sim.scene import build_scene, segment_drive
from asgp_ros.vo import DEFAULT_EXTRINSIC, Status, VisualOdometry, VOOptions
from asgp_ros.vo import odometry as od
from asgp_ros.vo.extrinsics import invert, rot_rpy
from asgp_ros.vo.planar import PlanarOdometry


@pytest.fixture(scope="module")
def scene():
    return build_scene(preset="rich", seed=0)


@pytest.fixture(scope="module")
def poor_scene():
    return build_scene(preset="poor", seed=0)


def _rot_deg(T: np.ndarray) -> float:
    return math.degrees(math.acos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1, 1)))


def _run(renderer, poses, stamps, **options):
    vo = VisualOdometry(renderer.K, **options)
    return vo, [vo.process(*renderer.render(T), t) for T, t in zip(poses, stamps, strict=True)]


def _drive_poses(drive):
    return [DEFAULT_EXTRINSIC.camera_pose_planar(x, y, th)
            for x, y, th in zip(drive.x, drive.y, drive.theta, strict=True)]


# ---- kernels ---------------------------------------------------------------------------


def _random_motion(rng, trans=0.1, rot=0.05):
    return od._se3_exp(np.r_[rng.uniform(-trans, trans, 3), rng.uniform(-rot, rot, 3)])


def test_se3_exp_log_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(20):
        xi = np.r_[rng.normal(0, 0.5, 3), rng.normal(0, 0.8, 3)]
        np.testing.assert_allclose(od._se3_log(od._se3_exp(xi)), xi, atol=1e-9)
    T = _random_motion(rng)
    np.testing.assert_allclose(od._scale_motion(T, 2.0), T @ T, atol=1e-12)


def test_umeyama_recovers_a_rigid_motion():
    rng = np.random.default_rng(1)
    P = rng.uniform(-2, 2, (30, 3)) + np.array([0.0, 0.0, 4.0])
    T = _random_motion(rng, 0.5, 0.3)
    Q = P @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(od._umeyama(P, Q), T, atol=1e-10)


def test_gauss_newton_jacobians_and_convergence():
    rng = np.random.default_rng(2)
    K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    vo = VisualOdometry(K)
    P = np.column_stack([rng.uniform(-2, 2, 60), rng.uniform(-1, 1, 60), rng.uniform(2, 6, 60)])
    T_true = _random_motion(rng)
    Q = P @ T_true[:3, :3].T + T_true[:3, 3]
    uv_ref, uv_cur = vo._project(P), vo._project(Q)
    T0 = _random_motion(rng, 0.02, 0.02) @ T_true
    # analytic Jacobian of the forward reprojection against central differences
    X = P @ T0[:3, :3].T + T0[:3, 3]
    J = od._jac_forward(X, 525.0, 525.0).reshape(-1, 6)
    Jn = np.zeros_like(J)
    for k in range(6):
        d = np.zeros(6)
        d[k] = 1e-6
        Xp = P @ (od._se3_exp(d) @ T0)[:3, :3].T + (od._se3_exp(d) @ T0)[:3, 3]
        Xm = P @ (od._se3_exp(-d) @ T0)[:3, :3].T + (od._se3_exp(-d) @ T0)[:3, 3]
        Jn[:, k] = ((vo._project(Xp) - vo._project(Xm)) / 2e-6).reshape(-1)
    np.testing.assert_allclose(J, Jn, rtol=1e-5, atol=1e-4)
    T, H, cost, ok, _ = vo._gauss_newton(T0, P, Q, uv_ref, uv_cur, np.ones(60))
    assert ok and cost < 1e-12
    np.testing.assert_allclose(T, T_true, atol=1e-9)
    assert np.all(np.linalg.eigvalsh(H) > 0)


def test_clique_keeps_the_rigid_matches():
    rng = np.random.default_rng(3)
    n, bad = 120, 40
    P = rng.uniform(-2, 2, (n, 3)) + np.array([0.0, 0.0, 4.0])
    T = _random_motion(rng, 0.2, 0.1)
    Q = P @ T[:3, :3].T + T[:3, 3] + rng.normal(0, 0.005, (n, 3))
    wrong = rng.choice(n, bad, replace=False)
    Q[wrong] += rng.uniform(-1, 1, (bad, 3))  # mismatches
    inl = od._max_clique(P, Q, 0.05, 0.0)
    truth = np.setdiff1d(np.arange(n), wrong)
    assert len(np.setdiff1d(inl, truth)) <= 1  # at most a lucky mismatch
    assert len(inl) >= 0.95 * len(truth)


def test_clique_is_what_its_docstring_says():
    """Min-degree peeling: the survivors are pairwise consistent, and a match is deleted
    only while it has the fewest partners among the remaining ones."""
    rng = np.random.default_rng(5)
    for _ in range(30):
        n = int(rng.integers(8, 40))
        P = rng.uniform(-2, 2, (n, 3)) + np.array([0.0, 0.0, 4.0])
        Q = P + rng.normal(0, 0.05, (n, 3))  # noisy enough that the graph is not complete
        inl = od._max_clique(P, Q, 0.05, 0.0)
        C = np.abs(od.cdist(P, P) - od.cdist(Q, Q)) < 0.05
        assert len(inl) >= 1 and C[np.ix_(inl, inl)].all()
        alive = np.ones(n, bool)  # replay: each deletion had the minimum degree
        while not C[np.ix_(alive, alive)].all():
            deg = np.where(alive, C[:, alive].sum(axis=1), n + 1)
            alive[int(np.argmin(deg))] = False
        np.testing.assert_array_equal(inl, np.flatnonzero(alive))


def test_bucketing_keeps_the_strongest_per_cell():
    rng = np.random.default_rng(4)
    xy = rng.uniform(0, 160, (500, 2)).astype(np.float32)
    resp = rng.uniform(0, 1, 500).astype(np.float32)
    keep = od._bucket(xy, resp, 80, 25, 160)
    assert len(keep) == 4 * 25
    cells = (xy[:, 1] // 80) * 3 + xy[:, 0] // 80
    for c in np.unique(cells):
        members = np.flatnonzero(cells == c)
        kept = np.intersect1d(members, keep)
        assert np.min(resp[kept]) >= np.sort(resp[members])[-25]


def test_options_and_camera_matrix_are_validated():
    K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    with pytest.raises(TypeError, match="unknown VO options"):
        VisualOdometry(K, fast_treshold=10)
    with pytest.raises(ValueError, match="max_depth"):
        VisualOdometry(K, min_depth=3.0, max_depth=2.0)
    with pytest.raises(ValueError, match="search_radius"):
        VOOptions(search_radius=-1.0)
    with pytest.raises(ValueError, match="3x3"):
        VisualOdometry(np.eye(2))
    with pytest.raises(ValueError, match="pinhole"):
        VisualOdometry(np.zeros((3, 3)))
    # 6 inliers leave a 6-parameter motion no degree of freedom for its covariance: an
    # estimate from exactly 6 divided by zero and ended vo_node with a traceback
    with pytest.raises(ValueError, match="min_inliers must be >= 7"):
        VOOptions(min_inliers=6)
    VOOptions(min_inliers=7)


# ---- rendered motions ----------------------------------------------------------------------


def test_pure_rotation(scene):
    """Camera turning about its own centre: rotation recovered, no translation invented."""
    r = RGBDRenderer(scene, seed=1)
    base = DEFAULT_EXTRINSIC.camera_pose_planar(0.0, 0.0, 0.0)
    step = np.eye(4)
    step[:3, :3] = rot_rpy(0.0, 0.0, 0.0) @ od._se3_exp(np.r_[0, 0, 0, 0, 0.02, 0])[:3, :3]
    poses = [base]
    for _ in range(8):
        poses.append(poses[-1] @ step)  # 0.02 rad per frame about the optical y axis
    _, results = _run(r, poses, np.arange(9) / 30.0)
    assert results[0].status is Status.REFERENCE_SET
    for k, res in enumerate(results[1:], 1):
        assert res.ok, (k, res.status, res.message)
        gt = invert(poses[k - 1]) @ poses[k]
        assert np.linalg.norm(res.motion[:3, 3]) < 0.003
        assert abs(_rot_deg(res.motion) - _rot_deg(gt)) < 0.05
        assert _rot_deg(invert(gt) @ res.motion) < 0.05
    assert _rot_deg(invert(invert(poses[0]) @ poses[-1]) @ results[-1].pose) < 0.1


def test_pure_translation_forward(scene):
    """The chair drives straight forward: the backward camera recedes; v > 0, omega ~ 0."""
    r = RGBDRenderer(scene, seed=2)
    drive = segment_drive((0.0, 0.0, 0.0), [(0.5, 0.0, 0.4)], 30.0)
    poses = _drive_poses(drive)
    _, results = _run(r, poses, drive.t)
    for k, res in enumerate(results[1:], 1):
        assert res.ok, (k, res.status, res.message)
        gt = invert(poses[k - 1]) @ poses[k]
        assert np.linalg.norm(res.motion[:3, 3] - gt[:3, 3]) < 0.003
        assert _rot_deg(invert(gt) @ res.motion) < 0.05
        v, w = res.twist
        assert v == pytest.approx(0.5, abs=0.05)
        assert w == pytest.approx(0.0, abs=0.05)
        assert res.dt == pytest.approx(1.0 / 30.0)
    end = invert(poses[0]) @ poses[-1]
    assert np.linalg.norm(results[-1].pose[:3, 3] - end[:3, 3]) < 0.01


def test_known_arc_recovered_with_covariance(scene):
    """A unicycle arc (v = 0.4 m/s, omega = 0.3 rad/s) at 15 Hz: twist, pose and covariance."""
    r = RGBDRenderer(scene, seed=3)
    drive = segment_drive((1.0, -1.0, 2.5), [(0.4, 0.3, 1.0)], 15.0)
    poses = _drive_poses(drive)
    _, results = _run(r, poses, drive.t)
    planar = PlanarOdometry(DEFAULT_EXTRINSIC)
    twists = []
    for res in results:
        planar.update(res)
        if res.ok:
            twists.append(res.twist)
            C = res.covariance
            assert C.shape == (6, 6)
            np.testing.assert_allclose(C, C.T)
            assert np.all(np.linalg.eigvalsh(C) > 0)
            assert res.twist_covariance.shape == (6, 6)
    assert len(twists) == len(results) - 1
    v, w = np.array(twists).T
    assert np.median(np.abs(v - 0.4)) < 0.02 and np.max(np.abs(v - 0.4)) < 0.06
    assert np.median(np.abs(w - 0.3)) < 0.01 and np.max(np.abs(w - 0.3)) < 0.04
    # base_link pose in odom (base_link at the first frame) against the drive
    c, s = math.cos(drive.theta[0]), math.sin(drive.theta[0])
    dx, dy = drive.x[-1] - drive.x[0], drive.y[-1] - drive.y[0]
    gt = (c * dx + s * dy, -s * dx + c * dy, drive.theta[-1] - drive.theta[0])
    assert planar.x == pytest.approx(gt[0], abs=0.02)
    assert planar.y == pytest.approx(gt[1], abs=0.02)
    assert planar.yaw == pytest.approx(gt[2], abs=0.01)
    assert np.all(np.diag(planar.covariance) > 0)


def _base_motion_camera(dx: float, dy: float, dtheta: float) -> np.ndarray:
    """The camera motion [4, 4] of a planar base_link increment (dx, dy, dtheta)."""
    Tbc = DEFAULT_EXTRINSIC.T_base_optical
    Tb = np.eye(4)
    c, s = math.cos(dtheta), math.sin(dtheta)
    Tb[:2, :2] = [[c, -s], [s, c]]
    Tb[0, 3], Tb[1, 3] = dx, dy
    return invert(Tbc) @ Tb @ Tbc


def test_planar_twist_leaves_a_sideways_displacement_out_of_v():
    """v is the SE(2) logarithm's forward part, not the chord's length: a sideways error
    of a turn on the spot or of a chair standing still is not forward speed (the chord's
    length read 5 mm sideways at 15 Hz as 0.075 m/s forward or backward), and errors of
    either sign average out (the chord's length is biased away from zero)."""
    dt = 1.0 / 15.0
    for dy in (0.005, -0.005):
        v, w = DEFAULT_EXTRINSIC.planar_twist(_base_motion_camera(0.0, dy, 0.0), dt)
        assert v == pytest.approx(0.0, abs=1e-12) and w == pytest.approx(0.0, abs=1e-12)
    # a turn on the spot at 3 rad/s read with a 2 mm error in a random direction
    rng = np.random.default_rng(0)
    v = np.array([DEFAULT_EXTRINSIC.planar_twist(
        _base_motion_camera(*(0.002 * rng.standard_normal(2)), 0.2), dt)[0]
        for _ in range(2000)])
    assert abs(v.mean()) < 3 * v.std() / math.sqrt(len(v))
    # a unicycle arc is read exactly, sideways component or not (it has none)
    for vt, wt in ((0.5, 3.0), (-0.4, 1.0), (0.3, 0.0)):
        h = 0.5 * wt * dt
        chord = vt * dt * (math.sin(h) / h if h else 1.0)
        motion = _base_motion_camera(chord * math.cos(h), chord * math.sin(h), wt * dt)
        assert DEFAULT_EXTRINSIC.planar_twist(motion, dt) == pytest.approx((vt, wt), abs=1e-12)


def test_twist_covariance_is_the_covariance_of_the_reported_twist():
    """The (v, omega) block of VOResult.twist_covariance is J C J^T with J the Jacobian of
    planar_twist's (v, omega) in the camera motion's right perturbation: v is read along the
    interval's mean heading, so on a turn the sideways error of the current frame counts
    (at 0.2 rad per frame, sin 0.1 of it)."""
    dt = 1.0 / 15.0
    rng = np.random.default_rng(1)
    A = rng.standard_normal((6, 6))
    C = A @ A.T * 1e-6 + np.diag([1e-6, 1e-6, 1e-6, 1e-8, 1e-8, 1e-8])
    for vt, wt in ((0.0, 3.0), (0.5, -2.0), (0.4, 0.0)):
        h = 0.5 * wt * dt
        chord = vt * dt * (math.sin(h) / h if h else 1.0)
        motion = _base_motion_camera(chord * math.cos(h), chord * math.sin(h), wt * dt)
        # central differences of (v, omega) in the right perturbation of the camera motion
        J = np.zeros((2, 6))
        for i in range(6):
            d = np.zeros(6)
            d[i] = 1e-6
            a = DEFAULT_EXTRINSIC.planar_twist(motion @ od._se3_exp(d), dt)
            b = DEFAULT_EXTRINSIC.planar_twist(motion @ od._se3_exp(-d), dt)
            J[:, i] = (np.array(a) - np.array(b)) / 2e-6
        want = J @ C @ J.T
        got = DEFAULT_EXTRINSIC.twist_covariance(C, dt, motion)[np.ix_([0, 5], [0, 5])]
        np.testing.assert_allclose(got, want, rtol=2e-3, atol=1e-12)
        if wt:  # the current frame's x is not the direction v is read in
            plain = DEFAULT_EXTRINSIC.twist_covariance(C, dt)
            assert abs(plain[0, 0] / want[0, 0] - 1.0) > 0.01


def test_blank_wall_loss_is_reported_and_tracking_recovers(poor_scene):
    """Turn to the blank, dim wall: failures with no motion, then recovery on texture."""
    x0, x1, y = poor_scene.blank_wall
    quarter = 0.5 * math.pi / 1.2
    drive = segment_drive(((x0 + x1) / 2 - 0.3, y - 1.5, 0.0),
                          [(0.3, 0.0, 0.5), (0.0, -1.2, quarter), (0.0, 0.0, 0.6),
                           (0.0, 1.2, quarter), (0.3, 0.0, 0.8)], 20.0)
    poses = _drive_poses(drive)
    r = RGBDRenderer(poor_scene, seed=4)
    _, results = _run(r, poses, drive.t)
    statuses = [res.status for res in results]
    facing = [k for k, th in enumerate(drive.theta) if abs(th + math.pi / 2) < 0.05]
    assert facing
    for k in facing:
        assert not results[k].ok, k
        assert results[k].motion is None and results[k].twist is None
        assert statuses[k] in (Status.INSUFFICIENT_FEATURES, Status.INSUFFICIENT_INLIERS)
    lost = [k for k, s in enumerate(statuses) if s is not Status.OK and k > 0]
    assert lost
    last_lost = max(lost)
    assert last_lost < len(results) - 8, "tracking did not recover"
    assert all(s is Status.OK for s in statuses[last_lost + 1:])
    # every reported twist is right (nothing invented around the loss), against the true
    # mean velocity since the previous tracked frame; a motion spanning the gap gives none
    errors = []
    prev = 0
    for k, res in enumerate(results):
        if res.reset or res.status is Status.REFERENCE_SET:
            prev = k  # a new reference: the next motion starts here
        if not res.ok:
            continue
        assert res.dt == pytest.approx(drive.t[k] - drive.t[prev])
        if res.dt > 0.5:
            assert res.twist is None  # pose recovered, but no average over the gap
        else:
            gt = DEFAULT_EXTRINSIC.planar_twist(invert(poses[prev]) @ poses[k], res.dt)
            errors.append(np.subtract(res.twist, gt))
        prev = k
    errors = np.abs(np.array(errors))
    assert np.all(errors[:, 0] < 0.15) and np.all(errors[:, 1] < 0.05)
    assert np.median(errors[:, 0]) < 0.02 and np.median(errors[:, 1]) < 0.01
    # poses held while lost
    for k in lost:
        if not results[k].reset:
            np.testing.assert_allclose(results[k].pose, results[k - 1].pose)


# ---- bad input ---------------------------------------------------------------------------


def test_bad_and_degenerate_input_gives_a_status(scene):
    r = RGBDRenderer(scene, seed=5)
    drive = segment_drive((0.0, 0.0, 0.0), [(0.3, 0.0, 0.15)], 30.0)
    frames = [r.render(T) for T in _drive_poses(drive)]
    img, depth = frames[0]
    vo = VisualOdometry(r.K)
    cases = [
        ((np.zeros_like(img), depth), Status.INSUFFICIENT_FEATURES),  # blank image
        ((img, np.zeros_like(depth)), Status.NO_DEPTH),  # all-zero depth
        ((img, np.full_like(depth, np.nan)), Status.NO_DEPTH),
        ((img.astype(np.float32), depth), Status.BAD_INPUT),  # wrong encoding
        ((img[..., :2], depth), Status.BAD_INPUT),
        ((img, depth.astype(np.int32)), Status.BAD_INPUT),
        ((img, depth[:240]), Status.BAD_INPUT),  # mismatched colour / depth
        ((img[:240, :320], depth[:240, :320]), Status.BAD_INPUT),  # wrong size after first
        ((None, depth), Status.BAD_INPUT),
        ((img, depth[..., None]), Status.BAD_INPUT),
    ]
    t = 0.0
    first = vo.process(img, depth, t)
    assert first.status is Status.REFERENCE_SET
    for (a, b), expected in cases:
        t += 0.01
        res = vo.process(a, b, t)
        assert res.status is expected, (expected, res.message)
        assert not res.ok and res.motion is None and res.twist is None
        assert res.message
    # time must advance
    t += 0.01
    assert vo.process(img, depth, t).ok
    assert vo.process(img, depth, t).status is Status.BAD_INPUT
    assert vo.process(img, depth, float("nan")).status is Status.BAD_INPUT
    assert vo.process(img, depth, "soon").status is Status.BAD_INPUT
    # and tracking carries on with good frames (uint16 millimetre depth, grey image)
    # (and grey HxWx1, BGRA and strided views are fine)
    for k, convert in ((1, lambda im: im[..., 1:2]), (2, lambda im: np.dstack([im, im[..., 0]])),
                       (3, lambda im: np.ascontiguousarray(im[:, ::-1])[:, ::-1])):
        t += 1.0 / 30.0
        im, d = frames[k]
        mm = np.rint(d * 1000).astype(np.uint16)
        res = vo.process(convert(im), mm, t)
        assert res.ok, res.message


def test_first_frame_size_must_fit_camera_matrix(scene):
    K = np.array([[525.0, 0, 900.0], [0, 525.0, 239.5], [0, 0, 1]])
    vo = VisualOdometry(K)
    img = np.zeros((480, 640, 3), np.uint8)
    res = vo.process(img, np.ones((480, 640), np.float32), 0.0)
    assert res.status is Status.BAD_INPUT and "principal point" in res.message


def test_an_image_size_given_must_fit_the_camera_matrix_and_the_levels():
    """The size a camera_info gives is checked as the first frame's is (it was not: a
    principal point far outside the image tracked, with twists three times too fast)."""
    K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    VisualOdometry(K, image_size=(640, 480))
    with pytest.raises(ValueError, match="principal point outside the 300x240 image"):
        VisualOdometry(K, image_size=(300, 240))
    with pytest.raises(ValueError, match="too small"):
        VisualOdometry(np.array([[50.0, 0, 10.0], [0, 50.0, 10.0], [0, 0, 1]]),
                       image_size=(20, 20))


@pytest.mark.parametrize("size", [(4480, 56), (5000, 64), (8000, 60)])
def test_a_very_wide_image_never_raises(size):
    """Tracking lost on a very wide image: the rotation guess shrank it to 80 px wide and
    1 px high, and OpenCV raised (cv2.error out of ``process``)."""
    w, h = size
    rng = np.random.default_rng(0)
    K = np.array([[300.0, 0, w / 2], [0, 300.0, h / 2], [0, 0, 1]])
    import cv2

    base = cv2.GaussianBlur(rng.integers(0, 256, (h + 40, w + 40), dtype=np.uint8), (3, 3), 0)
    for given in (None, (w, h)):
        vo = VisualOdometry(K, image_size=given)
        for k in range(5):
            img = (np.ascontiguousarray(base[3 * k:3 * k + h, 5 * k:5 * k + w]) if k < 3
                   else rng.integers(0, 256, (h, w), dtype=np.uint8))
            res = vo.process(img, np.full((h, w), 2.0, np.float32), 1.0 + 0.1 * k)
            assert isinstance(res.status, Status)


def test_restart_holds_the_pose_and_reports_a_reinitialisation(scene):
    """``restart``: the reference is forgotten, the pose held (or the one given), and the
    next frame's reference is a re-initialisation (``reset``), so PlanarOdometry raises
    the pose's variance."""
    r = RGBDRenderer(scene, seed=2)
    drive = segment_drive((0.0, 0.0, 0.0), [(0.5, 0.0, 0.4)], 30.0)
    poses = _drive_poses(drive)
    vo = VisualOdometry(r.K)
    for k in range(6):
        res = vo.process(*r.render(poses[k]), drive.t[k])
    assert res.ok
    pose = vo.pose
    assert not np.allclose(pose, np.eye(4))
    vo.restart()
    res = vo.process(*r.render(poses[6]), drive.t[6])
    assert res.status is Status.REFERENCE_SET and res.reset
    np.testing.assert_array_equal(res.pose, pose)
    res = vo.process(*r.render(poses[7]), drive.t[7])
    assert res.ok and not res.reset
    other = VisualOdometry(r.K)
    other.restart(pose)
    np.testing.assert_array_equal(other.pose, pose)
    with pytest.raises(ValueError, match="4x4"):
        other.restart(np.full((4, 4), np.nan))
