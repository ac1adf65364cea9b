"""The inverse model (asgp_ros.core.inverse): Jacobian, recovery of a reachable path,
bounds, the reference and bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_predictor import linear_model

from asgp_ros.core.features import FeatureConfig, design_matrix
from asgp_ros.core.inverse import path_jacobian, solve
from asgp_ros.core.models import MotionModel
from asgp_ros.core.resample import ResampleConfig, resample
from asgp_ros.core.rollout import rollout
from asgp_ros.core.sparse_gp import SparseGP
from asgp_ros.core.streams import RawStreams


@pytest.fixture(scope="module")
def gp_model() -> MotionModel:
    """A small coupled ASGP on synthetic streams (both axes feed both channels)."""
    from test_predictor import make_streams

    jt, joy, vt, vel = make_streams(60.0)
    res = resample(RawStreams(joy_t=jt, joy=joy, vel_t=vt, vel=vel))
    fc = FeatureConfig(lags=3, coupled=True)
    chans = []
    for c in (0, 1):
        X, y, _ = design_matrix(res, c, fc)
        chans.append(SparseGP(num_inducing=12, seed=0).fit(X, y, max_iter=40))
    return MotionModel(kind="asgp", feature_config=fc, resample_config=ResampleConfig(),
                       channels=tuple(chans))


def _past(model: MotionModel):
    s = model.feature_config.lags
    jp = np.column_stack([np.linspace(0.2, 0.5, s), np.linspace(-0.1, 0.2, s)])
    vp = np.column_stack([np.linspace(0.2, 0.4, s), np.linspace(-0.05, 0.1, s)])
    return jp, vp


@pytest.mark.parametrize("which", ["linear", "gp"])
def test_the_path_jacobian_matches_finite_differences(which, gp_model):
    model = linear_model() if which == "linear" else gp_model
    jp, vp = _past(model)
    rng = np.random.default_rng(0)
    U = rng.uniform(-0.6, 0.6, (6, 2))
    pose, vel, dpose = path_jacobian(model, jp, vp, U)
    ref = rollout(model, jp, vp, U[None], uncertainty="none")
    np.testing.assert_allclose(pose, ref.pose[0], atol=1e-12)
    np.testing.assert_allclose(vel, ref.vel[0], atol=1e-12)
    eps = 1e-6
    fd = np.empty_like(dpose)
    for j in range(U.size):
        dU = np.zeros(U.size)
        dU[j] = eps
        plus = path_jacobian(model, jp, vp, U + dU.reshape(U.shape))[0]
        minus = path_jacobian(model, jp, vp, U - dU.reshape(U.shape))[0]
        fd[..., j] = (plus - minus) / (2 * eps)
    np.testing.assert_allclose(dpose, fd, rtol=1e-4, atol=5e-7)  # central differences
    assert np.abs(dpose).max() > 0.01  # the commands do move the path


@pytest.mark.parametrize("method", ["gauss_newton", "cem"])
def test_a_reachable_path_is_recovered(method, gp_model):
    jp, vp = _past(gp_model)
    k = 8
    t = np.arange(k)
    U_true = np.column_stack([0.6 + 0.2 * np.sin(0.5 * t), 0.3 * np.cos(0.4 * t)])
    target = rollout(gp_model, jp, vp, U_true[None], uncertainty="none").pose[0, :, :2]
    res = solve(gp_model, jp, vp, target, method=method, jerk=0.0, effort=0.0,
                max_iter=60 if method == "cem" else 50)
    assert res.joystick.shape == (k, 2) and res.pose.shape == (k, 3)
    assert res.pos_cov.shape == (k, 2, 2) and res.method == method and res.iterations >= 1
    tol = 0.005 if method == "gauss_newton" else 0.03
    assert res.tracking_error.max() < tol, res.tracking_error
    assert np.all(np.abs(res.joystick) <= 1.0)


def test_bounds_hold_and_the_reference_pulls(gp_model):
    jp, vp = _past(gp_model)
    far = np.column_stack([np.linspace(1.0, 10.0, 6), np.zeros(6)])  # out of reach
    res = solve(gp_model, jp, vp, far)
    assert np.all(np.abs(res.joystick) <= 1.0) and res.joystick[:, 0].mean() > 0.8
    near = rollout(gp_model, jp, vp, np.full((1, 6, 2), 0.5), uncertainty="none").pose[0, :, :2]
    user = np.tile([0.2, -0.3], (6, 1))
    free = solve(gp_model, jp, vp, near, jerk=0.0, effort=0.0)
    pulled = solve(gp_model, jp, vp, near, jerk=0.0, effort=0.0, reference=user,
                   reference_weight=10.0)
    assert np.abs(pulled.joystick - user).mean() < 0.5 * np.abs(free.joystick - user).mean()
    assert pulled.tracking_error.max() > free.tracking_error.max()


def test_cem_takes_an_extra_cost_of_the_sampled_paths(gp_model):
    jp, vp = _past(gp_model)
    straight = np.column_stack([np.linspace(0.1, 0.8, 6), np.zeros(6)])
    seen = []

    def keep_left(pose, cov):
        seen.append(pose.shape)
        return 100.0 * np.maximum(0.0, 0.05 - pose[:, -1, 1])  # end at least 5 cm left

    res = solve(gp_model, jp, vp, straight, method="cem", extra=keep_left, max_iter=10)
    assert seen and seen[0][1:] == (6, 3)
    assert res.pose[-1, 1] > 0.03


def test_bad_input_is_refused(gp_model):
    jp, vp = _past(gp_model)
    target = np.zeros((5, 2))
    with pytest.raises(ValueError, match="NaN"):
        solve(gp_model, jp, vp, np.full((5, 2), math.nan))
    with pytest.raises(ValueError, match="NaN"):
        solve(gp_model, np.full_like(jp, math.nan), vp, target)
    with pytest.raises(ValueError, match="lags"):
        solve(gp_model, jp[:1], vp, target)
    with pytest.raises(ValueError, match="target_xy"):
        solve(gp_model, jp, vp, np.zeros((5, 3)))
    with pytest.raises(ValueError, match="method"):
        solve(gp_model, jp, vp, target, method="newton")
    with pytest.raises(ValueError, match="cem"):
        solve(gp_model, jp, vp, target, extra=lambda p, c: np.zeros(p.shape[0]))
    with pytest.raises(ValueError, match="jerk"):
        solve(gp_model, jp, vp, target, jerk=-1.0)
    with pytest.raises(ValueError, match="reference"):
        solve(gp_model, jp, vp, target, reference=np.zeros((4, 2)), reference_weight=1.0)
    # complex numbers: their imaginary part was dropped with a warning (but in target_xy)
    for name, kw in (("joy_past", {}), ("vel_past", {}), ("reference", {}), ("init", {})):
        args = dict(joy_past=jp, vel_past=vp, reference=None, init=None) | kw
        args[name] = (jp if name == "joy_past" else vp if name == "vel_past"
                      else np.zeros((5, 2))) + 0j
        with pytest.raises(ValueError, match=f"{name} must be real"):
            solve(gp_model, args["joy_past"], args["vel_past"], target,
                  reference=args["reference"], init=args["init"])
    # a reference beyond the stick's range (it saturated the solution); a weight beyond
    # any meaning (1.7e308 overflowed the solver: an infinite cost, the start kept)
    with pytest.raises(ValueError, match="reference holds a command beyond"):
        solve(gp_model, jp, vp, target, reference=np.full((5, 2), 50.0), reference_weight=1.0)
    for name in ("jerk", "effort", "reference_weight"):
        with pytest.raises(ValueError, match=name):
            solve(gp_model, jp, vp, target, **{name: 1.7e308})
        with pytest.raises(ValueError, match=name):
            solve(gp_model, jp, vp, target, **{name: "1"})


def test_the_predictor_solves_on_its_live_buffers():
    from test_predictor import _fed

    pred, (jt, _, vt, _) = _fed(1012.0, horizon_steps=6)
    now = max(jt[-1], vt[-1])
    held = pred.predict(now)
    window, res = pred.solve_inverse(held.pose[:, :2], now, jerk=0.0, effort=0.0)
    assert window.ok and window.t0 == held.t0 and res is not None
    assert res.tracking_error.max() < 1e-3  # the held command's own path is reachable
    np.testing.assert_allclose(window.pose, res.pose)
    stale, none = pred.solve_inverse(held.pose[:, :2], now + 5.0)
    assert not stale.ok and none is None
    # the window is the solution's path as predict gives it: every documented field
    assert window.ellipses.shape == (6, 3) and window.vel.shape == (6, 2)
    assert window.vel_cov.shape == (6, 2, 2) and window.pose_cov.shape == (6, 3, 3)
    np.testing.assert_allclose(window.pos_cov, res.pos_cov, rtol=1e-9, atol=1e-15)
    np.testing.assert_array_equal(window.joy_future, res.joystick)


def test_the_inverse_of_a_model_beyond_physics_is_refused_as_its_prediction_is():
    """solve_inverse gave an ok window moving 2e5 m in 0.2 s from a model that predict()
    refused (model_out_of_range)."""
    from test_predictor import beyond_physics_predictors

    from asgp_ros.core.online import Reason

    for pred, now in beyond_physics_predictors():
        window, res = pred.solve_inverse(np.zeros((5, 2)), now)
        assert not window.ok and window.reason == Reason.MODEL_OUT_OF_RANGE and res is None


def test_the_inverse_window_has_the_odometry_origin():
    from test_predictor import _fed

    pred, (jt, _, vt, _) = _fed(1012.0, horizon_steps=6)
    now = max(jt[-1], vt[-1])
    for t in np.arange(now - 3.0, now, 0.1):
        pred.feed_pose(t, 1.0 + t - now, 2.0, 0.3)
    held = pred.predict(now)
    window, _ = pred.solve_inverse(held.pose[:, :2], now)
    assert held.origin is not None and window.origin is not None
    np.testing.assert_allclose(window.origin, held.origin)
