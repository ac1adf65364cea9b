"""k-step prediction by the recurrent sliding window (Fan et al., ICRA 2018, Algorithm 1).

Given the last s joystick and velocity samples (up to the current time t0, the time of
the last measured V_{t-1}) and k planned joystick commands j_t .. j_{t+k-1}, the predictor
forms the input row of step t from the window, predicts V_t, shifts the window (the
prediction takes the place of the unknown measurement) and repeats k times (Algorithm 1,
lines 2-6). The velocities [V_{t-1}, V_t, ..., V_{t+k-1}] are then integrated by the
trapezoidal unicycle model from the origin at t0 (eq. 5), giving poses at t0 + dt ..
t0 + k dt. Everything is vectorised over a batch of B candidate joystick sequences (a
planner scores many at once); the loop over the k steps is the only Python loop.

Uncertainty (the paper's future work), ``uncertainty=``:

* ``"linear"`` (default): first-order (EKF-style) propagation of the joint state
  [velocity window (2s), x, y, theta] along the mean rollout. Each step linearises the
  GP mean in its inputs (``predict_with_grad``: V_new ~ m + G dW + e, with
  e ~ N(0, diag(var)) the GP's predictive variance at the mean input), and the unicycle
  step by its Jacobians. It is carried in square-root form: every velocity and pose is
  written as a linear function S e of the 2k independent unit-normal innovations (two per
  step), so covariances S S^T are positive semi-definite by construction and all
  correlations between steps and with the pose are kept. Because the pose does not feed
  back into the GP, the pose part is the exact Jacobian of the trapezoidal integration
  applied after the loop (:func:`asgp_ros.core.unicycle.path_sensitivity`), identical
  to running the EKF on [window, x, y, theta] step by step. Why this rather than Monte
  Carlo or moment matching: it is deterministic (a planner compares candidates without
  sampling noise), costs O(B k^2 s) for the window (one [2, 2s] x [2s, 2j] product per
  step) plus O(B k^2) for the poses, i.e. the same order as the [2s+3]^2 EKF update, and
  needs one GP evaluation per step and channel, cheap enough for planners' batches. Its
  approximation (mean curvature and input-dependent variance neglected over the
  horizon) is tested against ``"mc"`` on a mildly nonlinear model.
* ``"mc"``: Monte Carlo reference: ``n_samples`` trajectories per sequence, each step
  sampling V from the GP predictive N(mean, var) at the sampled window (seeded
  ``numpy.random.Generator``); means and covariances are sample statistics.
* ``"none"``: the mean recursion only (Algorithm 1 as in the paper); covariances are 0.

Each step's predictive variance passes through the model's variance calibration
(:attr:`MotionModel.calibration`, :mod:`asgp_ros.core.calibration`; its regime is the
measured speed V_{t-1} at t0), and is raised to its :attr:`MotionModel.variance_floor`'s
at the same input row where it has one, before it is propagated or sampled.
"""

from __future__ import annotations

import math
import threading
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal, TypeVar, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from asgp_ros.core import posterior
from asgp_ros.core.features import CHANNELS, build_inputs, input_layout
from asgp_ros.core.models import MotionModel
from asgp_ros.core.sparse_gp import SparseGP
from asgp_ros.core.streams import MAX_ABS_SPEED, MAX_ABS_YAW_RATE, vel_in_range
from asgp_ros.core.unicycle import integrate_path, sensitivity_time_major

FloatArray = NDArray[np.float64]
Uncertainty = Literal["linear", "mc", "none"]


@dataclass(frozen=True)
class Rollout:
    """Result of :func:`rollout` for B joystick sequences of k steps.

    Attributes:
        vel: [B, k, 2] predicted (v, omega) for steps t .. t+k-1 (times t0 + dt .. t0 + k dt).
        vel_cov: [B, k, 2, 2] covariance of each predicted velocity.
        pose: [B, k, 3] (x, y, theta) at t0 + dt .. t0 + k dt, from the origin at t0.
        pose_cov: [B, k, 3, 3] covariance of the pose.
        pos_cov: [B, k, 2, 2] covariance of (x, y) (the top-left block of pose_cov).
        dt: grid period (s).
        uncertainty: how the covariances were obtained ("linear", "mc" or "none": zeros).
    """

    vel: FloatArray
    vel_cov: FloatArray
    pose: FloatArray
    pose_cov: FloatArray
    pos_cov: FloatArray
    dt: float
    uncertainty: str

    @property
    def batch(self) -> int:
        return int(self.vel.shape[0])

    def problem(self) -> str | None:
        """Why this rollout is no wheelchair's (None: it may be one): a predicted speed or
        yaw rate beyond the physical limits of :mod:`asgp_ros.core.streams`, a velocity
        standard deviation beyond them too, or a covariance that is not finite. A damaged
        or hostile model file, or one far outside its data, does this; such a path is
        never published."""
        vel = np.asarray(self.vel, dtype=np.float64)
        bad = ~vel_in_range(vel.reshape(-1, 2))
        if bad.any():
            v, w = vel.reshape(-1, 2)[int(np.flatnonzero(bad)[0])]
            return (f"the model predicted (v, omega) = ({v:.3g} m/s, {w:.3g} rad/s), beyond "
                    f"the physical limits ({MAX_ABS_SPEED:g} m/s, {MAX_ABS_YAW_RATE:g} rad/s)")
        var = np.diagonal(np.asarray(self.vel_cov, dtype=np.float64), axis1=-2, axis2=-1)
        limit = np.array([MAX_ABS_SPEED, MAX_ABS_YAW_RATE]) ** 2
        if not (np.all(np.isfinite(self.pose_cov)) and np.all(np.isfinite(var))
                and np.all(var <= limit)):
            return ("the model predicted a velocity variance that is not finite or beyond "
                    "the physical limits squared")
        return None

    @property
    def steps(self) -> int:
        return int(self.vel.shape[1])


def _as_window(name: str, a: ArrayLike, s: int) -> FloatArray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim not in (2, 3) or arr.shape[-1] != 2:
        raise ValueError(f"{name} must have shape [s, 2] or [B, s, 2], got {arr.shape}")
    if arr.shape[-2] < s:
        raise ValueError(f"{name} has {arr.shape[-2]} samples, the model needs lags={s}")
    arr = arr[..., arr.shape[-2] - s:, :]
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf")
    return arr


def rollout(model: MotionModel, joy_past: ArrayLike, vel_past: ArrayLike,
            joy_future: ArrayLike, uncertainty: Uncertainty = "linear", *,
            n_samples: int = 1000, rng: np.random.Generator | int | None = 0,
            include_noise: bool = True) -> Rollout:
    """Predict k steps ahead for a batch of joystick sequences (Algorithm 1, batched).

    Args:
        model: the two-channel predictor.
        joy_past: [s, 2] shared or [B, s, 2] per sequence: joystick at t-s .. t-1 (a longer
            window is cut to its last s samples).
        vel_past: [s, 2] or [B, s, 2]: measured (v, omega) at t-s .. t-1; V_{t-1} is the
            velocity at t0, where the pose path starts.
        joy_future: [B, k, 2] (or [k, 2] for B = 1): planned joystick j_t .. j_{t+k-1}.
        uncertainty: "linear" (default), "mc" or "none" (see the module docstring).
        n_samples: Monte Carlo trajectories per sequence ("mc").
        rng: generator or seed for "mc".
        include_noise: propagate the predictive variance of a new observation (as the
            odometry measures it; default) or the latent function's variance.

    Returns:
        :class:`Rollout` with B sequences of k steps.
    """
    s = model.lags
    jp = _as_window("joy_past", joy_past, s)
    vp = _as_window("vel_past", vel_past, s)
    jf = np.asarray(joy_future, dtype=np.float64)
    if jf.ndim == 2:
        jf = jf[None]
    if jf.ndim != 3 or jf.shape[-1] != 2 or jf.shape[1] < 1:
        raise ValueError(f"joy_future must have shape [B, k, 2] with k >= 1, got {jf.shape}")
    if not np.all(np.isfinite(jf)):
        raise ValueError("joy_future contains NaN or inf")
    B, k = jf.shape[0], jf.shape[1]
    for name, arr in (("joy_past", jp), ("vel_past", vp)):
        if arr.ndim == 3 and arr.shape[0] != B:
            raise ValueError(f"{name} has a batch of {arr.shape[0]}, joy_future of {B}")
    if uncertainty not in ("linear", "mc", "none"):
        raise ValueError(f"uncertainty must be 'linear', 'mc' or 'none', got {uncertainty!r}")

    # joystick timeline [B, s+k, 2] and velocity timeline [B, s+k, 2]
    J = np.empty((B, s + k, 2))
    J[:, :s] = jp
    J[:, s:] = jf
    V = np.empty((B, s + k, 2))
    V[:, :s] = vp
    if uncertainty == "mc":
        return _rollout_mc(model, J, V, s, k, n_samples, rng, include_noise)
    return _rollout_linear(model, J, V, s, k, uncertainty == "linear", include_noise)


def _checked(name: str, mean: FloatArray, var: FloatArray) -> None:
    """Raise on a non-finite prediction or a negative variance (cheap when all is well)."""
    if math.isfinite(float(mean.sum()) + float(var.sum())) and float(var.min()) >= 0.0:
        return
    if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(var))):
        raise ValueError(f"channel {name} predicted NaN or inf")
    raise ValueError(f"channel {name} predicted a negative variance")


_NAMES = CHANNELS


class _Workspace(threading.local):
    """Per-thread scratch arrays reused from one rollout to the next.

    A batch of 1,024 needs several MB of intermediates per rollout; allocating them afresh
    lets the allocator return them to the OS and page-fault them back every call, which
    costs more than the arithmetic. Arrays up to ``limit`` bytes are kept (per name, last
    shape); results handed to the caller never live here.
    """

    limit = 64 * 2**20

    def __init__(self) -> None:
        self.arrays: dict[str, FloatArray] = {}

    def get(self, name: str, shape: tuple[int, ...]) -> FloatArray:
        a = self.arrays.get(name)
        if a is None or a.shape != shape:
            a = np.empty(shape)
            if a.nbytes <= self.limit:
                self.arrays[name] = a
        return a


_WS = _Workspace()


class ChannelStep:
    """One step of both channels: windows -> mean [B, 2], var [B, 2], grads [2][B, D].

    The recursion's unit, shared by the rollouts here and the inverse model's Jacobian
    (:func:`asgp_ros.core.inverse.path_jacobian`): two :class:`SparseGP` channels are
    evaluated together from their stacked posteriors, other kinds channel by channel.
    """

    def __init__(self, model: MotionModel, include_noise: bool, speed: FloatArray,
                 scratch: bool = True) -> None:
        """speed: [B] measured v at the start of each rollout (the calibration's regime);
        scratch: compute in the shared workspace (results valid until the next step)."""
        self.model = model
        self.fc = model.feature_config
        self.include_noise = include_noise
        self.fused = _fused_posterior(model)
        cal = model.calibration
        self.calibrate = None if cal.is_identity else cal.coefficients(speed)
        self.get = _WS.get if scratch else _fresh
        # the floor: both OutsideFloor channels from this step's input rows at once, or any
        # other floor model as a step of its own (after this step's arrays are read, in
        # fresh memory)
        self.floor: ChannelStep | None = None
        self.fused_floor: tuple[posterior.Stacked, FloatArray,
                                tuple[FloatArray, FloatArray] | None] | None = None
        self.floor_shares_kernel = False  # the floor reuses the step's kernel rows
        floor = model.variance_floor
        if floor is not None:
            chans = floor.channels
            if self.fused is not None and all(type(ch) is posterior.OutsideFloor
                                              for ch in chans):
                floors = cast(list[posterior.OutsideFloor], list(chans))
                S, Q = _fused_floor(floors[0], floors[1])
                fcal = floor.calibration
                self.fused_floor = (S, Q, None if fcal.is_identity
                                    else fcal.coefficients(speed))
                # an adapted posterior keeps the trained pseudo-inputs and kernel: the
                # floor's K is the one the step has just computed
                self.floor_shares_kernel = posterior.same_kernel_rows(self.fused, S)
            else:
                self.floor = ChannelStep(floor, include_noise, speed, scratch=False)

    def __call__(self, jp: FloatArray, vp: FloatArray, jn: FloatArray, with_grad: bool
                 ) -> tuple[FloatArray, FloatArray, list[FloatArray]]:
        if self.fused is not None:
            X = self.get("X", (2, jn.shape[0], self.fc.input_dim))
            for c in range(2):
                build_inputs(jp, vp, jn, c, self.fc, validate=False, out=X[c])
            m, v, g, K_step = posterior.predict_with_kernel(
                self.fused, X, self.include_noise, with_grad, scratch=self.get, stacklevel=4)
            K = K_step if self.floor_shares_kernel else None
            mean, var = m.T, v.T
            grad = [] if g is None else [g[0], g[1]]
        else:
            rows = [build_inputs(jp, vp, jn, c, self.fc, validate=False) for c in range(2)]
            mean = np.empty((jn.shape[0], 2))
            var = np.empty((jn.shape[0], 2))
            grad = []
            for c, ch in enumerate(self.model.channels):
                if with_grad:
                    mc, vc, gc = ch.predict_with_grad(rows[c], self.include_noise)
                    gc = np.asarray(gc, dtype=np.float64)
                    if gc.shape != rows[c].shape:
                        raise ValueError(f"channel {_NAMES[c]}: input gradient of shape "
                                         f"{gc.shape}, expected {rows[c].shape}")
                    grad.append(gc)
                else:
                    mc, vc = ch.predict(rows[c], self.include_noise)
                mean[:, c] = mc
                var[:, c] = vc
        if not (math.isfinite(float(mean.sum()) + float(var.sum()))
                and float(var.min()) >= 0.0):
            for c in range(2):
                _checked(_NAMES[c], mean[:, c], var[:, c])
        if self.calibrate is not None:
            var = var * self.calibrate[0] + self.calibrate[1]
        if self.fused_floor is not None:
            S, Q, fcal = self.fused_floor
            floor = posterior.floor_variance(S, Q, X, self.include_noise, K).T  # [B, 2]
            if fcal is not None:
                floor = floor * fcal[0] + fcal[1]
            var = np.maximum(var, floor)
        elif self.floor is not None:
            var = np.maximum(var, self.floor(jp, vp, jn, False)[1])  # (checked finite)
        return mean, var, grad


def _fresh(name: str, shape: tuple[int, ...]) -> FloatArray:
    """A new array (the workspace's signature, for a step that must not share it)."""
    return np.empty(shape)


def _fused_posterior(model: MotionModel) -> posterior.Stacked | None:
    """Both channels' posteriors stacked, for a model of two SparseGP channels; else None.

    The channels are then evaluated together by :func:`asgp_ros.core.posterior.predict`
    (the function behind :meth:`SparseGP.predict`) from the posteriors they hold: a step
    costs one set of numpy calls instead of two, which halves the per-call overhead that
    dominates a planner's single-sequence rollout.  The stack is cached by the identity of
    the two (immutable) posterior objects, so a refit or an online update, which replaces
    a channel's posterior, is picked up by the next rollout.
    """
    chans = model.channels
    if not all(type(ch) is SparseGP for ch in chans):
        return None
    post_v = cast(SparseGP, chans[0]).posterior
    post_w = cast(SparseGP, chans[1]).posterior
    return _cached_pair(_FUSED_CACHE, post_v, post_w, posterior.stack)


def _fused_floor(v: posterior.OutsideFloor, w: posterior.OutsideFloor
                 ) -> tuple[posterior.Stacked, FloatArray]:
    """Both channels' floors stacked (:func:`asgp_ros.core.posterior.stack_floors`),
    cached by the floor objects (an adapter keeps its floors for its lifetime)."""
    return _cached_pair(_FLOOR_CACHE, v, w, posterior.stack_floors)


_K = TypeVar("_K")
_V = TypeVar("_V")


def _cached_pair(cache: weakref.WeakKeyDictionary[_K, tuple[_K, _V]], first: _K,
                 second: _K, build: Callable[[list[_K]], _V]) -> _V:
    """``build([first, second])``, cached by the identity of the two (immutable) objects."""
    hit = cache.get(first)
    if hit is not None and hit[0] is second:
        return hit[1]
    value = build([first, second])
    cache[first] = (second, value)
    return value


#: stacked posteriors by the v channel's posterior: (omega channel's posterior, stack)
_FUSED_CACHE: weakref.WeakKeyDictionary[
    posterior.FitcPosterior, tuple[posterior.FitcPosterior, posterior.Stacked]
] = weakref.WeakKeyDictionary()
#: the same for the floors of an adapted model (MotionModel.variance_floor)
_FLOOR_CACHE: weakref.WeakKeyDictionary[
    posterior.OutsideFloor,
    tuple[posterior.OutsideFloor, tuple[posterior.Stacked, FloatArray]]
] = weakref.WeakKeyDictionary()


def _rollout_linear(model: MotionModel, J: FloatArray, V: FloatArray, s: int, k: int,
                    with_cov: bool, include_noise: bool) -> Rollout:
    B = J.shape[0]
    fc = model.feature_config
    dt = model.dt
    step = ChannelStep(model, include_noise, V[:, s - 1, 0])
    if with_cov:
        # S[b, i, c, r]: sensitivity of V_{t-s+i}[c] to innovation r (2 per step);
        # the measured past rows stay 0 (Algorithm 1 treats them as given).
        S = _WS.get("S", (B, s + k, 2, 2 * k))
        S[:, :s] = 0.0
        G = np.zeros((B, 2, s, 2))  # d V_new[c] / d window[lag, comp]
        Gw = G.reshape(B, 2, 2 * s)  # the same memory, window flattened as (lag, comp)
        where = []  # per channel: window positions and the input columns feeding them
        for c in range(2):
            lay = input_layout(c, fc).vel_past.reshape(-1)  # [2s] column or -1
            where.append((np.flatnonzero(lay >= 0), lay[lay >= 0]))
        rows = np.array([0, 1])
    for j in range(k):
        mean, var, grad = step(J[:, j:j + s], V[:, j:j + s], J[:, s + j], with_cov)
        V[:, s + j] = mean
        if with_cov:
            for c in range(2):
                pos, cols = where[c]
                Gw[:, c, pos] = grad[c][:, cols]
            if j > 0:
                window = S[:, j:j + s, :, :2 * j].reshape(B, 2 * s, 2 * j)
                S[:, s + j, :, :2 * j] = Gw @ window
            S[:, s + j, :, 2 * j:] = 0.0
            S[:, s + j, rows, 2 * j + rows] = np.sqrt(var)

    path_v = V[:, s - 1:]  # [B, k+1, 2]: V_{t-1} (measured) .. V_{t+k-1}
    pose_full = integrate_path(path_v, dt)  # [B, k+1, 3], pose_full[:, 0] = origin
    pose = pose_full[:, 1:]
    if with_cov:
        # time-major sensitivities [k+1, B, 2k] (cumulative sums along time are contiguous)
        shape = (k + 1, B, 2 * k)
        Sv, Sw, Sx, Sy, Sth, g, f = (_WS.get(name, shape) for name in
                                     ("Sv", "Sw", "Sx", "Sy", "Sth", "g", "f"))
        np.copyto(Sv, S[:, s - 1:, 0, :].transpose(1, 0, 2))
        np.copyto(Sw, S[:, s - 1:, 1, :].transpose(1, 0, 2))
        sensitivity_time_major(np.ascontiguousarray(path_v[..., 0].T),
                               np.ascontiguousarray(pose_full[..., 2].T), Sv, Sw, dt,
                               out=(Sx, Sy, Sth), scratch=(g, f))
        vel_cov = _gram([Sv[1:], Sw[1:]])
        pose_cov = _gram([Sx[1:], Sy[1:], Sth[1:]])
    else:
        vel_cov = np.zeros((B, k, 2, 2))
        pose_cov = np.zeros((B, k, 3, 3))
    return Rollout(vel=V[:, s:].copy(), vel_cov=vel_cov, pose=pose, pose_cov=pose_cov,
                   pos_cov=pose_cov[..., :2, :2].copy(), dt=dt,
                   uncertainty="linear" if with_cov else "none")


def _gram(rows: list[FloatArray]) -> FloatArray:
    """Covariances from time-major square roots: d arrays [k, B, r] -> [B, k, d, d]."""
    d = len(rows)
    k, B = rows[0].shape[:2]
    out = np.empty((B, k, d, d))
    for a in range(d):
        for b in range(a, d):
            np.einsum("kbr,kbr->bk", rows[a], rows[b], out=out[:, :, a, b])
            if b != a:
                out[:, :, b, a] = out[:, :, a, b]
    return out


def _rollout_mc(model: MotionModel, J: FloatArray, V: FloatArray, s: int, k: int,
                n_samples: int, rng: np.random.Generator | int | None,
                include_noise: bool) -> Rollout:
    if isinstance(n_samples, bool) or not isinstance(n_samples, int | np.integer) \
            or n_samples < 2:
        raise ValueError(f"n_samples must be an integer >= 2, got {n_samples!r}")
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    B = J.shape[0]
    n = int(n_samples)
    dt = model.dt
    Js = np.repeat(J, n, axis=0)  # [B*n, s+k, 2], sample-major within each sequence
    Vs = np.repeat(V, n, axis=0)
    step = ChannelStep(model, include_noise, Vs[:, s - 1, 0])
    for j in range(k):
        z = gen.standard_normal((B * n, 2))
        mean, var, _ = step(Js[:, j:j + s], Vs[:, j:j + s], Js[:, s + j], False)
        Vs[:, s + j] = mean + np.sqrt(var) * z
    pose = integrate_path(Vs[:, s - 1:], dt)[:, 1:].reshape(B, n, k, 3)
    vel = Vs[:, s:].reshape(B, n, k, 2)

    def mean_cov(x: FloatArray) -> tuple[FloatArray, FloatArray]:
        mu = x.mean(axis=1)
        d = x - mu[:, None]
        cov = np.einsum("bnki,bnkj->bkij", d, d) / (n - 1)
        return mu, cov

    vel_mu, vel_cov = mean_cov(vel)
    pose_mu, pose_cov = mean_cov(pose)
    return Rollout(vel=vel_mu, vel_cov=vel_cov, pose=pose_mu, pose_cov=pose_cov,
                   pos_cov=pose_cov[..., :2, :2].copy(), dt=dt, uncertainty="mc")
