"""The inverse model: the joystick sequence whose predicted path follows a desired path.

The paper's third item of future work ("a mapping from trajectories to joystick
sequences"), ROS-free. Given the measured past on the model's grid and a desired path of
k positions, :func:`solve` finds the commands U = (u_1 .. u_k), each in [-1, 1]^2, that
minimise::

    C(U) = sum_i |p_i(U) - target_i|^2                      tracking (m^2)
         + jerk * sum_i |u_i - u_{i-1}|^2                   (u_0 = the last measured command)
         + effort * sum_i |u_i|^2
         + reference_weight * sum_i |u_i - r_i|^2           (r: e.g. the user's commands)
         + extra(poses, covariances)                        (sampling method only)

where p_i(U) is the mean path of Algorithm 1 (the rollout's recurrent GP means integrated
by the unicycle, eq. 5, from the pose at t0). Two methods:

* ``"gauss_newton"`` (default): the residuals above and their analytic Jacobian, solved by
  scipy's trust-region-reflective least squares within the box. The Jacobian of the path
  follows the recursion forward: each step's GP mean depends on the commands and on the
  earlier predicted velocities through its input row (``features.input_layout``), and the
  mean's input gradient (``predict_with_grad``) chains them; the unicycle's sensitivity
  (``unicycle.path_sensitivity``) turns velocity sensitivities into pose sensitivities.
* ``"cem"``: the cross-entropy method over batched rollouts (``uncertainty="none"``),
  which also accepts a vectorised ``extra`` cost of the sampled paths (a collision
  probability, for example).

Both end with one linearised rollout of the solution for its position covariances.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.optimize
from numpy.typing import ArrayLike, NDArray

from asgp_ros.core.features import input_layout
from asgp_ros.core.models import MotionModel
from asgp_ros.core.rollout import ChannelStep, rollout
from asgp_ros.core.streams import MAX_ABS_POSITION, joy_in_range, vel_in_range
from asgp_ros.core.unicycle import integrate_path, path_sensitivity

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

__all__ = ["METHODS", "InverseResult", "path_jacobian", "solve"]

METHODS = ("gauss_newton", "cem")

ExtraCost = Callable[[FloatArray, FloatArray], FloatArray]
"""``extra(pose [B, k, 3], pos_cov [B, k, 2, 2]) -> [B]`` added to the cost (cem only)."""


@dataclass(frozen=True)
class InverseResult:
    """A solved joystick sequence.

    Attributes:
        joystick: [k, 2] commands in [-1, 1] for t0 + dt .. t0 + k dt.
        pose: [k, 3] their predicted poses (x, y, theta) from the pose at t0.
        pos_cov: [k, 2, 2] predicted position covariances.
        cost: C(U) at the solution (without ``extra``).
        tracking_error: [k] distance of each predicted position from its target (m).
        iterations: solver iterations.
        method: the method used.
    """

    joystick: FloatArray
    pose: FloatArray
    pos_cov: FloatArray
    cost: float
    tracking_error: FloatArray
    iterations: int
    method: str


#: Largest weight of a penalty: beyond it a weight says nothing more (a 1e6 weight already
#: rules the cost) and its squares overflow the solver (1.7e308 gave an infinite cost).
MAX_WEIGHT = 1e9


def _real(name: str, a: ArrayLike) -> FloatArray:
    """``a`` as float64, refusing complex numbers (their imaginary part was dropped with a
    warning)."""
    if np.iscomplexobj(a):
        raise ValueError(f"{name} must be real numbers, got complex ones")
    return np.asarray(a, dtype=np.float64)


def _window(name: str, a: ArrayLike, s: int) -> FloatArray:
    arr = _real(name, a)
    if arr.ndim != 2 or arr.shape[1] != 2 or arr.shape[0] < s:
        raise ValueError(f"{name} must be [s, 2] with s >= {s} (the model's lags), got "
                         f"{arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf")
    arr = arr[arr.shape[0] - s:]
    in_range = joy_in_range(arr) if name == "joy_past" else vel_in_range(arr)
    if not np.all(in_range):
        raise ValueError(f"{name} holds a sample beyond the physical range of "
                         "asgp_ros.core.streams")
    return arr


def _whole(name: str, value: object, low: int, high: int) -> int:
    """``value`` as an int in [low, high], or ValueError naming it (1.5 or NaN iterations
    made scipy's solver run forever)."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer) \
            or not low <= int(value) <= high:
        raise ValueError(f"{name} must be an integer in [{low}, {high}], got {value!r}")
    return int(value)


def _window_columns(model: MotionModel) -> tuple[list[IntArray], list[IntArray]]:
    """Per channel: the positions in a step's flattened window (joystick past [s, 2],
    velocity past [s, 2], joystick now [2], each row-major) that feed its input row, and
    the input columns they feed."""
    fc = model.feature_config
    pos: list[IntArray] = []
    cols: list[IntArray] = []
    for c in range(2):
        lay = input_layout(c, fc)
        flat = np.concatenate([lay.joy_past.ravel(), lay.vel_past.ravel(), lay.joy_now])
        pos.append(np.flatnonzero(flat >= 0))
        cols.append(flat[flat >= 0].astype(np.intp))
    return pos, cols


def path_jacobian(model: MotionModel, joy_past: FloatArray, vel_past: FloatArray,
                  U: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Mean path of the commands ``U`` [k, 2] and its Jacobian (module docstring).

    Forward sensitivities: step t's mean V_t depends on its window W_t = (J[t-s:t],
    V[t-s:t], J[t]) through the mean's input gradient, so dV_t/dU = G_t dW_t/dU with G_t
    the gradient laid out on the window; the joystick rows' sensitivities are constant
    (identity on the commands), the velocity rows' are those of the earlier steps.

    Returns:
        (pose [k, 3], vel [k, 2], dpose [k, 3, 2k]): d pose_i / d U, U flattened row-major
        (column 2 j + a is axis a of command j).
    """
    s, k = model.feature_config.lags, U.shape[0]
    P = 2 * k
    J = np.concatenate([joy_past, U])[None]  # [1, s + k, 2]
    V = np.concatenate([vel_past, np.zeros((k, 2))])[None]
    # sensitivities of every joystick and velocity row: [s + k, 2, P]
    dJ = np.zeros((s + k, 2, P))
    dJ[s:, 0, 0::2] = np.eye(k)
    dJ[s:, 1, 1::2] = np.eye(k)
    dV = np.zeros((s + k, 2, P))
    step = ChannelStep(model, True, V[:, s - 1, 0])
    pos, cols = _window_columns(model)
    G = np.zeros((2, 4 * s + 2))  # d V_t / d (flattened window)
    dW = np.empty((4 * s + 2, P))
    for i in range(k):
        t = s + i
        mean, _, grad = step(J[:, t - s:t], V[:, t - s:t], J[:, t], True)
        V[0, t] = mean[0]
        for c in range(2):
            G[c, pos[c]] = grad[c][0, cols[c]]
        dW[:2 * s] = dJ[t - s:t].reshape(2 * s, P)
        dW[2 * s:4 * s] = dV[t - s:t].reshape(2 * s, P)
        dW[4 * s:] = dJ[t]
        dV[t] = G @ dW
    dt = 1.0 / float(model.resample_config.rate_hz)
    vel = V[0, s - 1:]  # V at t0, then the predicted steps
    pose = integrate_path(vel, dt)[1:]
    dvel = np.concatenate([np.zeros((1, 2, P)), dV[s:]])
    dpose = path_sensitivity(vel, dvel, dt)[1:]
    return pose, V[0, s:].copy(), dpose


def solve(model: MotionModel, joy_past: ArrayLike, vel_past: ArrayLike, target_xy: ArrayLike,
          *, method: str = "gauss_newton", jerk: float = 0.005, effort: float = 0.0,
          reference: ArrayLike | None = None, reference_weight: float = 0.0,
          init: ArrayLike | None = None, max_iter: int = 50,
          extra: ExtraCost | None = None, samples: int = 256, elites: int = 24,
          seed: int = 0) -> InverseResult:
    """The joystick sequence for a desired path (module docstring).

    Args:
        model: the trained predictor.
        joy_past, vel_past: [s, 2] on the model grid, oldest first; V at t-1 is the
            velocity at t0 (a longer window is cut to its last s rows).
        target_xy: [k, 2] desired positions at t0 + i dt, i = 1..k, in the frame of the
            pose at t0 (x forward).
        method: "gauss_newton" or "cem".
        jerk, effort, reference_weight: weights of the penalties (>= 0).
        reference: [k, 2] commands to stay close to (e.g. the user's), with
            ``reference_weight``.
        init: [k, 2] start (default: the last measured command held).
        max_iter: solver iterations (Gauss-Newton: trust-region iterations; CEM: rounds).
        extra: a vectorised cost of sampled paths (``"cem"`` only).
        samples, elites, seed: the CEM's population, elite count and seed.

    Raises:
        ValueError: shapes, NaN or inf, weights out of range, an unknown method, or
            ``extra`` with the Gauss-Newton method.
    """
    s = model.feature_config.lags
    jp = _window("joy_past", joy_past, s)
    vp = _window("vel_past", vel_past, s)
    target = _real("target_xy", target_xy)
    if target.ndim != 2 or target.shape[1] != 2 or not 1 <= target.shape[0] <= 200:
        raise ValueError(f"target_xy must be [k, 2] with 1 <= k <= 200, got {target.shape}")
    if not np.all(np.isfinite(target)):
        raise ValueError("target_xy contains NaN or inf")
    if np.abs(target).max() > MAX_ABS_POSITION:
        raise ValueError(f"target_xy leaves +-{MAX_ABS_POSITION:g} m")
    max_iter = _whole("max_iter", max_iter, 1, 10_000)
    if method == "cem":
        samples = _whole("samples", samples, 2, 1 << 16)
        elites = _whole("elites", elites, 1, samples)
        seed = _whole("seed", seed, 0, (1 << 63) - 1)
    k = target.shape[0]
    for name, w in (("jerk", jerk), ("effort", effort), ("reference_weight", reference_weight)):
        if not (isinstance(w, int | float | np.integer | np.floating)
                and math.isfinite(w) and 0.0 <= w <= MAX_WEIGHT):
            raise ValueError(f"{name} must be a weight in [0, {MAX_WEIGHT:g}], got {w!r}")
    ref = np.zeros((k, 2)) if reference is None else _real("reference", reference)
    if ref.shape != (k, 2) or not np.all(np.isfinite(ref)):
        raise ValueError(f"reference must be finite [k, 2] = [{k}, 2], got {ref.shape}")
    if not np.all(joy_in_range(ref)):
        raise ValueError("reference holds a command beyond the stick's range [-1, 1]")
    u0 = np.clip(np.repeat(jp[-1:], k, axis=0) if init is None
                 else _real("init", init), -1.0, 1.0)
    if u0.shape != (k, 2) or not np.all(np.isfinite(u0)):
        raise ValueError(f"init must be finite [k, 2] = [{k}, 2]")
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    weights = (jerk, effort, reference_weight)
    if method == "gauss_newton":
        if extra is not None:
            raise ValueError("an extra cost needs method='cem' (it has no Jacobian)")
        U, iterations = _gauss_newton(model, jp, vp, target, ref, weights, u0, max_iter)
    else:
        U, iterations = _cem(model, jp, vp, target, ref, weights, u0, max_iter, extra,
                             samples, elites, seed)
    out = rollout(model, jp, vp, U[None], uncertainty="linear")
    pose, cov = out.pose[0], out.pos_cov[0]
    err = np.linalg.norm(pose[:, :2] - target, axis=1)
    cost = float(np.sum(err**2) + _penalty(U[None], jp[-1], ref, weights)[0])
    return InverseResult(U, pose, cov, cost, err, iterations, method)


def _penalty(U: FloatArray, u_last: FloatArray, ref: FloatArray,
             weights: tuple[float, float, float]) -> FloatArray:
    """[B] penalties of commands [B, k, 2]."""
    jerk, effort, w_ref = weights
    dU = np.diff(np.concatenate([np.broadcast_to(u_last, (U.shape[0], 1, 2)), U], axis=1),
                 axis=1)
    total: FloatArray = (jerk * np.sum(dU**2, axis=(1, 2)) + effort * np.sum(U**2, axis=(1, 2))
                         + w_ref * np.sum((U - ref) ** 2, axis=(1, 2)))
    return total


def _gauss_newton(model: MotionModel, jp: FloatArray, vp: FloatArray, target: FloatArray,
                  ref: FloatArray, weights: tuple[float, float, float], u0: FloatArray,
                  max_iter: int) -> tuple[FloatArray, int]:
    k = target.shape[0]
    jerk, effort, w_ref = (math.sqrt(w) for w in weights)
    D = np.eye(2 * k) - np.eye(2 * k, k=-2)  # (u_j - u_{j-1}), u_{-1} folded into the offset
    offset = np.zeros(2 * k)
    offset[:2] = jp[-1]
    cache: dict[bytes, tuple[FloatArray, FloatArray]] = {}

    def path(x: FloatArray) -> tuple[FloatArray, FloatArray]:
        key = x.tobytes()
        if key not in cache:
            cache.clear()
            pose, _, dpose = path_jacobian(model, jp, vp, x.reshape(k, 2))
            cache[key] = (pose, dpose)
        return cache[key]

    def residuals(x: FloatArray) -> FloatArray:
        pose, _ = path(x)
        return np.concatenate([(pose[:, :2] - target).ravel(), jerk * (D @ x - offset),
                               effort * x, w_ref * (x - ref.ravel())])

    def jacobian(x: FloatArray) -> FloatArray:
        _, dpose = path(x)
        return np.vstack([dpose[:, :2, :].reshape(2 * k, 2 * k), jerk * D,
                          effort * np.eye(2 * k), w_ref * np.eye(2 * k)])

    res = scipy.optimize.least_squares(residuals, u0.ravel(), jac=jacobian, bounds=(-1.0, 1.0),
                                       method="trf", max_nfev=max_iter, xtol=1e-6, ftol=1e-6)
    return np.clip(res.x.reshape(k, 2), -1.0, 1.0), int(res.nfev)


def _cem(model: MotionModel, jp: FloatArray, vp: FloatArray, target: FloatArray,
         ref: FloatArray, weights: tuple[float, float, float], u0: FloatArray, rounds: int,
         extra: ExtraCost | None, samples: int, elites: int, seed: int
         ) -> tuple[FloatArray, int]:
    if not 2 <= elites < samples:
        raise ValueError(f"need 2 <= elites < samples, got {elites} and {samples}")
    rng = np.random.default_rng(seed)
    k = target.shape[0]
    mean, sd = u0.copy(), np.full((k, 2), 0.5)
    best, best_cost = u0.copy(), math.inf
    rounds_done = 0
    for it in range(1, max(1, rounds) + 1):
        rounds_done = it
        U = np.clip(mean + sd * rng.standard_normal((samples, k, 2)), -1.0, 1.0)
        U[0] = mean  # the current mean competes too
        out = rollout(model, jp, vp, U, uncertainty="linear" if extra else "none")
        cost = np.sum((out.pose[..., :2] - target) ** 2, axis=(1, 2)) \
            + _penalty(U, jp[-1], ref, weights)
        if extra is not None:
            cost = cost + np.asarray(extra(out.pose, out.pos_cov), dtype=np.float64)
        order = np.argsort(cost)
        if cost[order[0]] < best_cost:
            best, best_cost = U[order[0]].copy(), float(cost[order[0]])
        top = U[order[:elites]]
        mean = top.mean(axis=0)
        sd = np.maximum(top.std(axis=0), 0.02)
        if float(sd.max()) <= 0.021:
            break
    return best, rounds_done
