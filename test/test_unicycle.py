"""Trapezoidal unicycle integration (paper eq. 5) and its covariance propagation."""

from __future__ import annotations

import numpy as np
import pytest

from asgp_ros.core.unicycle import (
    cov_from_sqrt,
    integrate_path,
    integrate_path_cov,
    path_sensitivity,
    sqrt_2x2,
    wrap_angle,
)


def arc(v: float, w: float, t: np.ndarray) -> np.ndarray:
    """Closed-form constant-curvature arc from the origin, heading +x: [n, 3]."""
    return np.stack([v / w * np.sin(w * t), v / w * (1.0 - np.cos(w * t)), w * t], axis=-1)


def test_straight_line_is_exact() -> None:
    dt = 0.2
    vel = np.tile([1.3, 0.0], (11, 1))
    pose = integrate_path(vel, dt)
    t = np.arange(11) * dt
    np.testing.assert_allclose(pose[:, 0], 1.3 * t, atol=1e-12)
    np.testing.assert_allclose(pose[:, 1:], 0.0, atol=1e-12)


def test_straight_line_from_a_start_pose() -> None:
    dt = 0.2
    vel = np.tile([1.0, 0.0], (6, 1))
    pose = integrate_path(vel, dt, pose0=[1.0, 2.0, np.pi / 2])
    np.testing.assert_allclose(pose[-1], [1.0, 3.0, np.pi / 2], atol=1e-12)


def test_pure_rotation_is_exact() -> None:
    dt = 0.2
    vel = np.tile([0.0, -0.8], (11, 1))
    pose = integrate_path(vel, dt)
    np.testing.assert_allclose(pose[:, :2], 0.0, atol=1e-15)
    np.testing.assert_allclose(pose[:, 2], -0.8 * np.arange(11) * dt, atol=1e-12)


def test_heading_exact_for_linear_omega() -> None:
    # omega(t) = a t: theta = a t^2 / 2, which the trapezoid integrates exactly
    dt, a = 0.2, 0.7
    t = np.arange(8) * dt
    vel = np.stack([np.zeros_like(t), a * t], axis=1)
    np.testing.assert_allclose(integrate_path(vel, dt)[:, 2], 0.5 * a * t**2, atol=1e-12)


@pytest.mark.parametrize(("v", "w"), [(1.0, 0.5), (0.6, -1.5), (-0.8, 0.9)])
def test_constant_curvature_arc_second_order(v: float, w: float) -> None:
    T = 2.0
    errors = []
    for dt in (0.2, 0.1, 0.05):
        n = round(T / dt) + 1
        t = np.arange(n) * dt
        pose = integrate_path(np.tile([v, w], (n, 1)), dt)
        exact = arc(v, w, t)
        np.testing.assert_allclose(pose[:, 2], exact[:, 2], atol=1e-12)
        err = np.max(np.linalg.norm(pose[:, :2] - exact[:, :2], axis=1))
        # trapezoid: global error <= T dt^2 max|d^2/dt^2 (v cos theta)| / 12 = T dt^2 |v| w^2 / 12
        assert err <= T * dt**2 * abs(v) * w**2 / 12.0 * 1.01
        errors.append(err)
    # halving dt divides the error by ~4 (second order)
    assert 3.5 < errors[0] / errors[1] < 4.5
    assert 3.5 < errors[1] / errors[2] < 4.5


def test_batched_matches_one_by_one() -> None:
    rng = np.random.default_rng(3)
    vel = rng.normal(size=(4, 5, 9, 2))
    pose0 = rng.normal(size=(4, 5, 3))
    batch = integrate_path(vel, 0.2, pose0)
    assert batch.shape == (4, 5, 9, 3)
    for i in range(4):
        for j in range(5):
            np.testing.assert_allclose(batch[i, j], integrate_path(vel[i, j], 0.2, pose0[i, j]),
                                       rtol=0, atol=1e-13)


def test_sensitivity_matches_finite_differences() -> None:
    rng = np.random.default_rng(0)
    n, dt = 8, 0.2
    vel = rng.normal(size=(n, 2)) * [1.0, 0.8]
    # one column per velocity entry: the full Jacobian d pose / d vel
    eye = np.eye(2 * n).reshape(n, 2, 2 * n)
    J = path_sensitivity(vel, eye, dt, pose0=[0.0, 0.0, 0.3])  # [n, 3, 2n]
    eps = 1e-6
    for col in range(2 * n):
        d = eye[:, :, col] * eps
        fd = (integrate_path(vel + d, dt, [0, 0, 0.3]) - integrate_path(vel - d, dt, [0, 0, 0.3]))
        np.testing.assert_allclose(J[:, :, col], fd / (2 * eps), atol=1e-7)
    assert np.all(J[0] == 0.0)


def test_integrate_path_cov_against_monte_carlo() -> None:
    rng = np.random.default_rng(1)
    n, dt = 11, 0.2
    vel = np.tile([1.0, 0.4], (n, 1))
    sd = np.array([0.03, 0.02])
    vel_cov = np.tile(np.diag(sd**2), (n, 1, 1))
    vel_cov[0] = 0.0  # the first (measured) sample is known
    pose, pose_cov = integrate_path_cov(vel, vel_cov, dt)
    np.testing.assert_allclose(pose, integrate_path(vel, dt))
    samples = vel + rng.standard_normal((20000, n, 2)) * sd
    samples[:, 0] = vel[0]
    mc = integrate_path(samples, dt)
    mc_cov = np.cov(mc[:, -1].T)
    np.testing.assert_allclose(pose_cov[-1], mc_cov, rtol=0.05, atol=1e-6)
    assert np.all(pose_cov[0] == 0.0)
    # symmetric positive semi-definite at every step
    np.testing.assert_array_equal(pose_cov, np.swapaxes(pose_cov, -1, -2))
    assert np.all(np.linalg.eigvalsh(pose_cov) > -1e-15)


def test_cov_from_sqrt_and_wrap() -> None:
    S = np.array([[1.0, 2.0], [0.0, 3.0]])
    np.testing.assert_allclose(cov_from_sqrt(S), S @ S.T)
    np.testing.assert_allclose(wrap_angle([np.pi, -np.pi, 3 * np.pi / 2]),
                               [-np.pi, -np.pi, -np.pi / 2])


@pytest.mark.parametrize("bad", [np.zeros((5, 3)), np.zeros(4), np.array([[0.0, np.nan]])])
def test_bad_velocities_raise(bad: np.ndarray) -> None:
    with pytest.raises(ValueError, match="velocities"):
        integrate_path(bad, 0.2)


def test_bad_dt_and_cov_raise() -> None:
    with pytest.raises(ValueError, match="dt"):
        integrate_path(np.zeros((3, 2)), 0.0)
    with pytest.raises(ValueError, match="vel_cov"):
        integrate_path_cov(np.zeros((3, 2)), np.zeros((3, 2)), 0.2)
    with pytest.raises(ValueError, match="positive semi-definite"):
        integrate_path_cov(np.zeros((1, 2)), -np.eye(2)[None], 0.2)


def test_integrate_path_cov_batched_matches_one_by_one() -> None:
    rng = np.random.default_rng(4)
    vel = rng.normal(size=(3, 6, 2))
    A = rng.normal(size=(3, 6, 2, 2)) * 0.1
    vel_cov = A @ np.swapaxes(A, -1, -2)
    pose, cov = integrate_path_cov(vel, vel_cov, 0.2, pose0=[0.0, 0.0, 0.5])
    for b in range(3):
        p1, c1 = integrate_path_cov(vel[b], vel_cov[b], 0.2, pose0=[0.0, 0.0, 0.5])
        np.testing.assert_allclose(pose[b], p1, rtol=1e-13)
        np.testing.assert_allclose(cov[b], c1, rtol=1e-11, atol=1e-16)


def test_bad_start_pose_and_sensitivities_are_refused() -> None:
    vel = np.zeros((4, 2))
    with pytest.raises(ValueError, match=r"pose0 must have shape"):
        integrate_path(vel, 0.1, np.zeros(2))
    with pytest.raises(ValueError, match="pose0 contains NaN"):
        integrate_path(vel, 0.1, np.array([0.0, np.nan, 0.0]))
    with pytest.raises(ValueError, match="dvel must have shape"):
        path_sensitivity(vel, np.zeros((4, 3, 1)), 0.1)
    with pytest.raises(ValueError, match="covariance contains NaN"):
        sqrt_2x2(np.full((2, 2), np.nan))
