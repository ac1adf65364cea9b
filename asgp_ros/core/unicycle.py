"""Unicycle kinematics with trapezoidal quadrature (Fan et al., ICRA 2018, eq. 5).

The chair's pose (x, y, theta) follows the unicycle model
``dx/dt = v cos(theta)``, ``dy/dt = v sin(theta)``, ``dtheta/dt = omega``. With the
velocities sampled on the grid (period ``dt``), the trapezoidal rule gives, with
``h = dt / 2``::

    theta_{i+1} = theta_i + h (omega_i + omega_{i+1})
    x_{i+1}     = x_i + h (v_i cos(theta_i) + v_{i+1} cos(theta_{i+1}))
    y_{i+1}     = y_i + h (v_i sin(theta_i) + v_{i+1} sin(theta_{i+1}))

Heading is exact for piecewise-linear omega; position has the trapezoid's O(dt^2) global
error. ``theta`` is never wrapped (a continuous heading is what a covariance needs); use
:func:`wrap_angle` for display.

Uncertainty is carried in square-root ("sensitivity") form: a velocity perturbation is
written as ``dV = S_V e`` with ``e`` standard normal [r], and :func:`path_sensitivity` maps
it to the first-order pose perturbation ``dP = S_P e`` (the exact Jacobian of the whole
trapezoidal integration). Covariances are ``S S^T``; correlations between steps (which the
recurrent rollout creates) are kept exactly.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


def wrap_angle(theta: ArrayLike) -> FloatArray:
    """Wrap angles to [-pi, pi)."""
    a = np.asarray(theta, dtype=np.float64)
    return np.asarray((a + np.pi) % (2.0 * np.pi) - np.pi, dtype=np.float64)


def _check_vel(vel: ArrayLike, dt: float) -> FloatArray:
    v = np.asarray(vel, dtype=np.float64)
    if v.ndim < 2 or v.shape[-1] != 2 or v.shape[-2] < 1:
        raise ValueError(f"velocities must have shape [..., n, 2] with n >= 1, got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError("velocities contain NaN or inf")
    if not (np.isfinite(dt) and dt > 0.0):
        raise ValueError(f"dt must be positive and finite, got {dt}")
    return v


def integrate_path(vel: ArrayLike, dt: float, pose0: ArrayLike | None = None) -> FloatArray:
    """Integrate sampled velocities into a pose path (trapezoidal rule, eq. 5).

    Args:
        vel: [..., n, 2] (v, omega) at times t0, t0 + dt, ..., t0 + (n-1) dt.
        dt: sample period (s).
        pose0: [..., 3] or [3] pose (x, y, theta) at t0; the origin if None.

    Returns:
        [..., n, 3] poses at the same times; ``pose[..., 0, :] == pose0``.
    """
    v = _check_vel(vel, dt)
    h = 0.5 * dt
    omega = v[..., 1]
    inc = np.zeros_like(omega)
    inc[..., 1:] = h * (omega[..., :-1] + omega[..., 1:])
    theta = np.cumsum(inc, axis=-1)  # [..., n], relative to theta0
    if pose0 is not None:
        p0 = np.asarray(pose0, dtype=np.float64)
        if p0.shape[-1:] != (3,):
            raise ValueError(f"pose0 must have shape [..., 3], got {p0.shape}")
        if not np.all(np.isfinite(p0)):
            raise ValueError("pose0 contains NaN or inf")
        theta = theta + p0[..., 2:3]
    vc = v[..., 0] * np.cos(theta)
    vs = v[..., 0] * np.sin(theta)
    dx = np.zeros_like(vc)
    dy = np.zeros_like(vs)
    dx[..., 1:] = h * (vc[..., :-1] + vc[..., 1:])
    dy[..., 1:] = h * (vs[..., :-1] + vs[..., 1:])
    out = np.stack([np.cumsum(dx, axis=-1), np.cumsum(dy, axis=-1), theta], axis=-1)
    if pose0 is not None:
        out[..., :2] += p0[..., None, :2]
    return out


def path_sensitivity(vel: ArrayLike, dvel: ArrayLike, dt: float,
                     pose0: ArrayLike | None = None) -> FloatArray:
    """First-order pose perturbations caused by velocity perturbations (Jacobian of eq. 5).

    Linearises :func:`integrate_path` around ``vel``: if the velocities move by
    ``dvel[..., i, :, :] @ e`` for a vector ``e`` [r], the poses move by
    ``dpose[..., i, :, :] @ e``. From the recursion above, with c_i = cos(theta_i),
    s_i = sin(theta_i)::

        dtheta_j = h sum_{i=1..j} (domega_{i-1} + domega_i)
        dx_j     = h sum_{i=1..j} (g_{i-1} + g_i),  g_i = c_i dv_i - v_i s_i dtheta_i
        dy_j     = h sum_{i=1..j} (f_{i-1} + f_i),  f_i = s_i dv_i + v_i c_i dtheta_i

    Args:
        vel: [..., n, 2] nominal velocities (the linearisation point).
        dvel: [..., n, 2, r] velocity sensitivities (columns = independent unit sources).
        dt: sample period (s).
        pose0: [..., 3] nominal start pose (only its heading matters), origin if None.

    Returns:
        [..., n, 3, r] pose sensitivities; the start pose is fixed (row 0 is zero).
    """
    v = _check_vel(vel, dt)
    S = np.asarray(dvel, dtype=np.float64)
    if S.ndim != v.ndim + 1 or S.shape[-2] != 2 or S.shape[-3] != v.shape[-2]:
        raise ValueError(
            f"dvel must have shape [..., n, 2, r] matching vel {v.shape}, got {S.shape}"
        )
    pose = integrate_path(v, dt, pose0)
    return _path_sensitivity(v, pose[..., 2], S, dt)


def _path_sensitivity(v: FloatArray, theta: FloatArray, S: FloatArray, dt: float) -> FloatArray:
    """:func:`path_sensitivity` without checks; theta [..., n] is the nominal heading."""
    Sv = np.moveaxis(S[..., 0, :], -2, 0)  # [n, ..., r]
    Sw = np.moveaxis(S[..., 1, :], -2, 0)
    Sx, Sy, Sth = sensitivity_time_major(np.moveaxis(v[..., 0], -1, 0),
                                         np.moveaxis(theta, -1, 0), Sv, Sw, dt)
    return np.stack([np.moveaxis(a, 0, -2) for a in (Sx, Sy, Sth)], axis=-2)


def _trapezoid_cumsum(term: FloatArray, h: float, out: FloatArray) -> FloatArray:
    """out[0] = 0, out[j] = h sum_{i=1..j} (term[i-1] + term[i]) along axis 0."""
    out[0] = 0.0
    np.add(term[:-1], term[1:], out=out[1:])
    out[1:] *= h
    for j in range(1, out.shape[0]):  # contiguous adds; numpy's cumsum over axis 0 is slower
        out[j] += out[j - 1]
    return out


def sensitivity_time_major(
    v: FloatArray, theta: FloatArray, Sv: FloatArray, Sw: FloatArray, dt: float,
    out: tuple[FloatArray, FloatArray, FloatArray] | None = None,
    scratch: tuple[FloatArray, FloatArray] | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Core of :func:`path_sensitivity` with time on axis 0 (fast for large batches).

    Args:
        v: [n, ...] nominal speeds; theta: [n, ...] nominal headings.
        Sv, Sw: [n, ..., r] sensitivities of v and omega.
        dt: sample period.
        out: optional (Sx, Sy, Stheta) arrays of Sv's shape to write into.
        scratch: optional two more such arrays for intermediate terms (reusing buffers
            avoids page-faulting fresh memory on every call for large batches).

    Returns:
        Sx, Sy, Stheta: [n, ..., r] pose sensitivities (zero at step 0).
    """
    h = 0.5 * dt
    shape = Sv.shape
    Sx, Sy, Sth = out if out is not None else (np.empty(shape), np.empty(shape),
                                                 np.empty(shape))
    g, f = scratch if scratch is not None else (np.empty(shape), np.empty(shape))
    _trapezoid_cumsum(Sw, h, Sth)
    c = np.cos(theta)[..., None]
    s = np.sin(theta)[..., None]
    vs = v[..., None] * s
    vc = v[..., None] * c
    np.multiply(c, Sv, out=g)  # g = c dv - v s dtheta
    np.multiply(vs, Sth, out=f)
    g -= f
    np.multiply(s, Sv, out=f)  # f = s dv + v c dtheta
    np.multiply(vc, Sth, out=Sx)
    f += Sx
    _trapezoid_cumsum(g, h, Sx)
    _trapezoid_cumsum(f, h, Sy)
    return Sx, Sy, Sth


def cov_from_sqrt(S: FloatArray) -> FloatArray:
    """``S @ S^T`` over the last two axes: [..., d, r] -> [..., d, d] (symmetric, PSD)."""
    C = S @ np.swapaxes(S, -1, -2)
    return np.asarray(0.5 * (C + np.swapaxes(C, -1, -2)), dtype=np.float64)


def sqrt_2x2(cov: FloatArray) -> FloatArray:
    """A square root ``L`` with ``L L^T = cov`` of PSD matrices [..., d, d] (eigen-based).

    Tolerates singular matrices (zero variance); raises ValueError on a clearly
    indefinite or non-finite input.
    """
    C = np.asarray(cov, dtype=np.float64)
    if not np.all(np.isfinite(C)):
        raise ValueError("covariance contains NaN or inf")
    C = 0.5 * (C + np.swapaxes(C, -1, -2))
    lam, U = np.linalg.eigh(C)
    scale = np.maximum(np.abs(lam).max(axis=-1, keepdims=True), 1e-300)
    if np.any(lam < -1e-9 * scale):
        raise ValueError("covariance is not positive semi-definite")
    return np.asarray(U * np.sqrt(np.clip(lam, 0.0, None))[..., None, :], dtype=np.float64)


def integrate_path_cov(vel: ArrayLike, vel_cov: ArrayLike, dt: float,
                       pose0: ArrayLike | None = None) -> tuple[FloatArray, FloatArray]:
    """Pose path and its first-order covariance for independent velocity samples.

    Args:
        vel: [..., n, 2] velocity means.
        vel_cov: [..., n, 2, 2] covariance of each sample; samples are independent of each
            other (for correlated velocities, as from a rollout, use
            :func:`path_sensitivity` with their joint square root).
        dt: sample period (s).
        pose0: [..., 3] known start pose, origin if None.

    Returns:
        pose [..., n, 3] (as :func:`integrate_path`) and pose_cov [..., n, 3, 3].
    """
    v = _check_vel(vel, dt)
    C = np.asarray(vel_cov, dtype=np.float64)
    if C.shape != (*v.shape, 2):
        raise ValueError(f"vel_cov must have shape {(*v.shape, 2)}, got {C.shape}")
    n = v.shape[-2]
    L = sqrt_2x2(C)  # [..., n, 2, 2]
    S = np.zeros((*v.shape, 2 * n))
    idx = np.arange(n)
    for col in range(2):
        S[..., idx, :, 2 * idx + col] = L[..., idx, :, col]
    pose = integrate_path(v, dt, pose0)
    S_p = _path_sensitivity(v, pose[..., 2], S, dt)
    return pose, cov_from_sqrt(S_p)
