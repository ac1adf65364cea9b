"""Online motion prediction over sliding sensor buffers (ROS-free).

``Predictor`` is the object a planner embeds in its own process and the one the ROS node
wraps: feed it joystick and VO samples as they arrive, optionally a planned joystick
sequence, and ask for the predicted path of the next k steps (paper Algorithm 1 with
linearised uncertainty), or for the paths of a batch of candidate joystick sequences.

Same features as offline, by construction: the buffers are turned into a
``RawStreams`` and resampled with :func:`asgp_ros.core.resample.resample`, on the
absolute-aligned grid ``t_k = k * dt`` of the stream clock, and the rollout
(:func:`asgp_ros.core.rollout.rollout`) builds its inputs with
:func:`asgp_ros.core.features.build_inputs`, exactly as training and evaluation do. Linear
interpolation at a grid point depends only on the samples around it, so a buffer that
holds enough history gives the same grid values, and hence the same features, as the
whole bag.

Indexing (paper Algorithm 1, as in ``rollout``): the *last complete step* ``L`` is the
newest grid point covered by both streams (a joystick and a VO sample at or after
``t_L``; the VO sample's time is the middle of its frame interval with the default
midpoint stamps, see :mod:`asgp_ros.core.resample`). The window ``J_{L-s+1..L}``,
``V_{L-s+1..L}`` is the measured past, ``t0 = t_L`` is the prediction time (origin of
the path) and the predicted poses are at ``t0 + i * dt``, ``i = 1..k``, driven by the
future joystick ``J_{L+1..L+k}``:

* a planner's plans: row ``r`` of a plan received at ``stamp`` is the command over
  ``[stamp + r*dt, stamp + (r+1)*dt)`` (its last row is held); each future grid time
  uses the newest fresh plan issued at or before it, since a plan cannot revise a command
  already executed when it was issued. A plan published just after ``t_L`` with rows
  ``J_{L+1}, J_{L+2}, ...`` therefore maps row r to ``t_{L+1+r}``, and a prediction gives
  the same future whether or not the next plan has already arrived;
* no fresh plan: the newest joystick sample is held (the user keeps the stick where it is).

Time: stamps and ``now`` are seconds on one clock. A stamp or a ``now`` further back than
``reset_jump_s`` from what was seen (a bag replayed in a loop, a restarted clock) resets
the buffers; smaller disorder (out-of-order, duplicate stamps) is tolerated (the
resampler sorts and de-duplicates).

Bad input never drives a prediction: a sample or a plan that is not finite or lies
outside the ranges of :mod:`asgp_ros.core.streams` (time stamps, joystick deflections,
v, omega, poses; plans at most ``MAX_PLAN_STEPS`` rows) is refused, counted in
``PredictorStats.rejected`` under one of the ``Reason.REJECT_*`` codes and described in
``PredictorStats.last_rejected``; a ``now`` that is not a valid time gives a not-ok
prediction with reason ``Reason.INVALID_TIME``.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field, replace
from enum import StrEnum
from typing import Any

import numpy as np
from numpy.typing import NDArray

from asgp_ros.core import inverse, metrics
from asgp_ros.core.adaptive import AdapterStats, AdaptSettings, ModelAdapter
from asgp_ros.core.inverse import InverseResult
from asgp_ros.core.metrics import CHI2_2DOF_95
from asgp_ros.core.models import MotionModel
from asgp_ros.core.resample import (
    ResampleConfig,
    Resampled,
    exclude_overridden,
    learning_config,
    overridden_points,
    resample,
)
from asgp_ros.core.rollout import Rollout, Uncertainty, rollout
from asgp_ros.core.streams import (
    RawStreams,
    joy_in_range,
    joy_problem,
    pose_problem,
    time_problem,
    vel_problem,
)

FloatArray = NDArray[np.float64]


class Reason(StrEnum):
    """Why a prediction is (not) available, or why an input is refused: the one list of
    codes. ``Prediction.reason`` is one of the first group, the keys of
    ``PredictorStats.rejected`` are the ``REJECT_*`` members. Members are strings equal
    to their value, which is the text the node's diagnostics publish (``reason``,
    ``rejected``) and log."""

    # ---- a prediction's reason
    OK = "ok"
    """A path was predicted."""
    NO_INPUT = "no_input"
    """No joystick or no VO sample buffered yet, the detail names which (the node: also
    no clock yet)."""
    STALE_JOYSTICK = "stale_joystick"
    """The newest joystick sample is older than ``joy_timeout_s``."""
    STALE_VO = "stale_vo"
    """The newest VO sample is older than ``vo_timeout_s``."""
    VO_TRACKING_LOST = "vo_tracking_lost"
    """The VO flags its newest sample, or the newest grid step, as a tracking failure."""
    VO_STALE_REPEAT = "vo_stale_repeat"
    """The VO repeats one velocity while the chair is driven (a frozen estimator)."""
    NOT_ENOUGH_HISTORY = "not_enough_history"
    """Fewer than the model's ``s`` lags of valid grid steps in one segment are buffered
    (start-up, or a gap, tracking loss or stale VO inside the window)."""
    CLOCK_RESET = "clock_reset"
    """A stamp or ``now`` jumped back by more than ``reset_jump_s``: buffers cleared."""
    NO_POSE = "no_odometry_pose"
    """The path is wanted in the odometry frame but no odometry pose covers the prediction
    time (set by the node)."""
    INVALID_TIME = "invalid_time"
    """``now`` is not a valid time (:func:`asgp_ros.core.streams.time_problem`)."""
    PREDICTION_ERROR = "prediction_error"
    """The numerics of one step failed (set by the node, which logs the error)."""
    MODEL_OUT_OF_RANGE = "model_out_of_range"
    """The model predicted a speed, yaw rate or variance beyond the physical limits
    (:meth:`asgp_ros.core.rollout.Rollout.problem`): a damaged model file, or inputs far
    outside its data. No path."""

    # ---- an input's refusal (keys of PredictorStats.rejected)
    REJECT_NONFINITE = "nonfinite"
    """A sample, pose, plan or stamp holds NaN or inf."""
    REJECT_TIME = "time_out_of_range"
    """A time stamp outside the range of :mod:`asgp_ros.core.streams`."""
    REJECT_JOY = "joy_out_of_range"
    """A joystick deflection outside [-1, 1]."""
    REJECT_VO = "vo_out_of_range"
    """A velocity beyond the physical limits of :mod:`asgp_ros.core.streams`."""
    REJECT_POSE = "pose_out_of_range"
    """An odometry pose beyond the range of :mod:`asgp_ros.core.streams`."""
    REJECT_PLAN = "plan_out_of_range"
    """A plan with a command out of range or more than ``MAX_PLAN_STEPS`` rows."""


def no_input_detail(no_joystick: bool, no_vo: bool) -> str:
    """The detail of :attr:`Reason.NO_INPUT`: which of the inputs has no sample yet (the
    shared-control layer names a missing stick in the same words)."""
    missing = " and no ".join(f"{name} sample" for name, gone
                              in (("joystick", no_joystick), ("VO", no_vo)) if gone)
    return f"no {missing} yet" if missing else "no input yet"


_EPS_T = 1e-9
PLAN_TOLERANCE_STEPS = 1e-3
"""Plan times within this many grid steps are the same time (see ``plan_future``)."""
MAX_PLANS = 16  # plans kept: only those issued within about one step before now matter
#: Most rows of a plan or of a future joystick sequence (200 s at 5 Hz).
MAX_PLAN_STEPS = 1000
#: Most override times kept (``feed_override``): 25 Hz for the longest buffer, 600 s.
MAX_OVERRIDES = 15_000
#: Most samples per second of ``buffer_s`` a buffer keeps (a 100 Hz joystick uses 5 %): a
#: flood, or a sender stuck on one stamp, drops the oldest samples instead of growing the
#: buffer without bound (counted in ``stats.dropped_overflow``).
MAX_SAMPLE_RATE_HZ = 2000.0

#: Most steps of a predicted path.
MAX_HORIZON_STEPS = 200
#: After the clock stepped back (:meth:`Predictor.clock_stepped_back`), until it is back
#: where it was, a sample stamped more than this ahead of it is the old timeline's ...
STEP_LEAD_S = 0.1
#: ... for at most this long on the clock: the old timeline's samples still in flight are
#: delivered within it (a bag looped with ``--clock 5``, its samples up to 0.2 s ahead of
#: the clock, lost half of them for the whole of the next loop).
STEP_GUARD_S = 1.0


def horizon_steps(horizon_s: float, rate_hz: float) -> int:
    """The steps of a ``horizon_s`` horizon at a model's ``rate_hz``, rounded as
    evaluation rounds them (:func:`asgp_ros.core.metrics.horizon_steps`).

    Raises:
        ValueError: shorter than half a step, or more than MAX_HORIZON_STEPS, naming
            ``horizon_s`` (a 25 Hz model's 10 s is 250 steps).
    """
    (k,) = metrics.horizon_steps([horizon_s], rate_hz)  # evaluation's rounding (half up)
    if k > MAX_HORIZON_STEPS:
        raise ValueError(f"horizon_s {horizon_s:g} s is {k} steps at the model's "
                         f"{rate_hz:g} Hz, more than {MAX_HORIZON_STEPS}")
    return k


class RejectedInputError(ValueError):
    """A plan or a future joystick sequence the Predictor refuses.

    Attributes:
        reason: one of the ``Reason.REJECT_*`` codes.
        detail: why, in words.
    """

    def __init__(self, reason: Reason, detail: str) -> None:
        self.reason = reason
        self.detail = detail
        super().__init__(f"{reason}: {detail}")


@dataclass(frozen=True)
class PredictorConfig:
    """Online prediction settings (validated on construction).

    Attributes:
        horizon_steps: k, steps predicted ahead (k * dt seconds).
        joy_timeout_s: no prediction when the newest joystick sample is older than this.
        vo_timeout_s: no prediction when the newest VO sample is older than this.
        plan_timeout_s: a planner's plan older than this is ignored (hold the command).
        buffer_s: history kept in the buffers, in [1, 600] s here; a :class:`Predictor`
            also refuses one shorter than its model's lags and the resampler's gap and
            stale/held-VO look-back need (:meth:`Predictor.window_history_s`: 3.4 s for
            the committed tile ASGP), or than adaptation needs
            (:attr:`Predictor.min_buffer_s`).
        reset_jump_s: a stamp or clock going back by more than this resets the buffers.
        uncertainty: "linear" (EKF-style), "mc" or "none", passed to the rollout.
    """

    horizon_steps: int = 10
    joy_timeout_s: float = 0.5
    vo_timeout_s: float = 0.5
    plan_timeout_s: float = 1.0
    buffer_s: float = 10.0
    reset_jump_s: float = 1.0
    uncertainty: str = "linear"

    def __post_init__(self) -> None:
        steps = self.horizon_steps
        if isinstance(steps, bool) or int(steps) != steps \
                or not 1 <= int(steps) <= MAX_HORIZON_STEPS:
            raise ValueError(f"horizon_steps must be an integer in [1, {MAX_HORIZON_STEPS}], "
                             f"got {self.horizon_steps}")
        for name in ("joy_timeout_s", "vo_timeout_s", "plan_timeout_s", "reset_jump_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0.0 < value <= 60.0):
                raise ValueError(f"{name} must be in (0, 60] s, got {value}")
        if not (math.isfinite(self.buffer_s) and 1.0 <= self.buffer_s <= 600.0):
            raise ValueError(f"buffer_s must be in [1, 600] s, got {self.buffer_s}")
        if self.uncertainty not in ("linear", "mc", "none"):
            raise ValueError(
                f"uncertainty must be 'linear', 'mc' or 'none', got {self.uncertainty!r}"
            )


@dataclass
class PredictorStats:
    """Counters for diagnostics.

    ``rejected`` counts refused inputs by ``Reason.REJECT_*`` code (non-finite ones are also
    in ``dropped_nonfinite``); ``last_rejected`` is "<code>: <why>" of the newest one.
    """

    joy_samples: int = 0
    vo_samples: int = 0
    dropped_nonfinite: int = 0
    out_of_order: int = 0
    resets: int = 0
    predictions: int = 0
    overrides: int = 0
    overrides_late: int = 0
    dropped_overflow: int = 0
    rejected: dict[Reason, int] = field(default_factory=dict)
    last_rejected: str = ""


@dataclass(frozen=True)
class Prediction:
    """The predicted path of one (or a batch of) future joystick sequence(s).

    ``ok`` False means no prediction: ``reason`` is a :class:`Reason` code and
    ``detail`` says why in words; the arrays are then empty.

    Attributes (single: shapes below; batch: a leading [B]):
        t0: prediction time = grid time of the last complete step (the path's origin).
        step: grid index of t0 (t0 = step * dt).
        times: [k] t0 + i*dt, i = 1..k.
        pose: [k, 3] (x, y, theta) in the base frame at t0.
        pos_cov: [k, 2, 2] covariance of (x, y).
        pose_cov: [k, 3, 3] covariance of (x, y, theta) (``pos_cov`` is its top-left
            block).
        ellipses: [k, 3] 95% position ellipse (semi-major, semi-minor, angle of the major
            axis from x), from ``pos_cov``.
        vel: [k, 2] predicted (v, omega) at t0 + dt .. t0 + k dt, the times of ``times``
            (V_{L+1} .. V_{L+k}; V_L, the last of ``vel_past``, is the velocity at t0), as
            :attr:`asgp_ros.core.rollout.Rollout.vel`.
        vel_cov: [k, 2, 2].
        joy_future: [k, 2] the joystick commands the prediction assumed.
        joy_past, vel_past: [s, 2] the measured window (grid t_{L-s+1} .. t_L).
        origin: (x, y, yaw) of the base frame at t0 in the odometry frame, when odometry
            poses were fed; None otherwise.
        from_plan: True when the future joystick came from a planner's plan.
    """

    ok: bool
    reason: Reason
    detail: str = ""
    t0: float = float("nan")
    step: int = -1
    dt: float = float("nan")
    times: FloatArray = field(default_factory=lambda: np.zeros(0))
    pose: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    pos_cov: FloatArray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    pose_cov: FloatArray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    ellipses: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    vel: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))
    vel_cov: FloatArray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    joy_future: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))
    joy_past: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))
    vel_past: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))
    origin: FloatArray | None = None
    from_plan: bool = False


def confidence_ellipses(cov: FloatArray, chi2: float = CHI2_2DOF_95) -> FloatArray:
    """Semi-axes and orientation of the ``chi2`` confidence ellipses of 2x2 covariances.

    Args:
        cov: [..., 2, 2] symmetric positive semi-definite.
        chi2: squared Mahalanobis radius (5.991 = 95% for 2 dof).

    Returns:
        [..., 3]: (semi-major, semi-minor, angle of the major axis from x, rad).
    """
    cov = np.asarray(cov, dtype=np.float64)
    sym = 0.5 * (cov + np.swapaxes(cov, -1, -2))
    evals, evecs = np.linalg.eigh(sym)  # ascending eigenvalues
    evals = np.clip(evals, 0.0, None)  # round-off only: the rollout returns PSD covariances
    major = np.sqrt(chi2 * evals[..., 1])
    minor = np.sqrt(chi2 * evals[..., 0])
    angle = np.arctan2(evecs[..., 1, 1], evecs[..., 0, 1])
    return np.stack([major, minor, angle], axis=-1)


def to_frame(pose: FloatArray, pos_cov: FloatArray, origin: FloatArray
             ) -> tuple[FloatArray, FloatArray]:
    """Express base-frame poses and covariances in the frame where the base is at ``origin``.

    Args:
        pose: [..., k, 3] (x, y, theta) relative to the base at t0.
        pos_cov: [..., k, 2, 2].
        origin: [3] (x, y, yaw) of the base at t0 in the target frame.

    Returns:
        (pose [..., k, 3], pos_cov [..., k, 2, 2]) in the target frame (R P R^T).
    """
    c, s = math.cos(float(origin[2])), math.sin(float(origin[2]))
    R = np.array([[c, -s], [s, c]])
    xy = pose[..., :2] @ R.T + origin[:2]
    theta = pose[..., 2:3] + origin[2]
    return np.concatenate([xy, theta], axis=-1), R @ pos_cov @ R.T


def interpolate_pose(t: float, stamps: FloatArray, poses: FloatArray) -> FloatArray | None:
    """Pose [3] at ``t`` interpolated linearly (yaw unwrapped) from [N] stamps, [N, 3] poses.

    None when ``t`` is outside the stamps (no extrapolation).
    """
    if stamps.shape[0] == 0 or t < stamps[0] - _EPS_T or t > stamps[-1] + _EPS_T:
        return None
    yaw = np.unwrap(poses[:, 2])
    return np.array([
        np.interp(t, stamps, poses[:, 0]),
        np.interp(t, stamps, poses[:, 1]),
        np.interp(t, stamps, yaw),
    ])


class _Buffer:
    """Time-stamped samples, pruned to a window behind the newest stamp.

    Kept in one float array (a row per sample: stamp, values; in arrival order) so that a
    prediction reads the window without converting thousands of tuples. Rows are only ever
    appended after the live part or dropped before it; the array is replaced, never shifted,
    when it fills.
    """

    _MIN_CAPACITY = 64

    def __init__(self, width: int, max_rows: int) -> None:
        self.width = width
        self.max_rows = max(1, int(max_rows))
        self._data = np.empty((self._MIN_CAPACITY, width + 1))
        self._start = 0  # the live rows are _data[_start:_end]
        self._end = 0
        self.newest = -math.inf
        self.before_newest = -math.inf  # the newest stamp older than ``newest``

    def add(self, t: float, values: tuple[float, ...]) -> bool:
        """Append; True if the stamp was out of order (older than the newest)."""
        if self._end == self._data.shape[0]:
            live = self._data[self._start:self._end]
            data = np.empty((max(self._MIN_CAPACITY, 2 * live.shape[0]), self.width + 1))
            data[:live.shape[0]] = live
            self._data, self._start, self._end = data, 0, live.shape[0]
        row = self._data[self._end]
        row[0] = t
        row[1:] = values
        self._end += 1
        late = t < self.newest
        if t > self.newest:
            self.before_newest, self.newest = self.newest, t
        elif self.before_newest < t < self.newest:
            self.before_newest = t
        return late

    def prune(self, horizon_s: float) -> int:
        """Drop the oldest rows, in arrival order, up to the first one inside the window,
        and beyond ``max_rows`` the oldest of the rest; return how many the cap dropped."""
        cutoff = self.newest - horizon_s
        if self._start < self._end and self._data[self._start, 0] < cutoff:
            inside = self._data[self._start:self._end, 0] >= cutoff
            self._start = (self._end if not inside.any()
                           else self._start + int(np.argmax(inside)))
        over = max(0, self._end - self._start - self.max_rows)
        self._start += over
        return over

    def arrays(self) -> tuple[FloatArray, FloatArray]:
        """Stamps [n] and values [n, width], copies, in arrival order."""
        live = self._data[self._start:self._end].copy()
        return live[:, 0], live[:, 1:]

    def newest_row(self) -> FloatArray:
        """(stamp, values...) of the newest stamp (the last to arrive of equal stamps, as
        the resampler keeps)."""
        live = self._data[self._start:self._end]
        row: FloatArray = live[len(live) - 1 - int(np.argmax(live[::-1, 0]))].copy()
        return row

    def clear(self) -> None:
        self._data = np.empty((self._MIN_CAPACITY, self.width + 1))
        self._start = self._end = 0
        self.newest = -math.inf
        self.before_newest = -math.inf

    def __len__(self) -> int:
        return self._end - self._start


class Predictor:
    """Sliding-buffer k-step motion predictor over a trained ``MotionModel``.

    Args:
        model: a trained ``MotionModel`` (from ``asgp_ros.core.modelfile.load_model``).
        config: online settings.
        adapt: adapt an ASGP online (:mod:`asgp_ros.core.adaptive`): every completed grid
            step that training would accept updates the posterior, and the outcome of each
            prediction the variance scale; None (default) predicts with ``model`` as
            trained.  ``model`` itself is never modified.

    Typical use (a planner at 5 Hz)::

        pred = Predictor(load_model("chair.npz"), PredictorConfig(horizon_steps=10))
        pred.feed_joy(t, (fwd, turn), now=now)  # as they arrive, now: the clock then
        pred.feed_vo(t, (v, omega), now=now)
        result = pred.predict(now)                                 # held command
        batch = pred.predict_batch(candidates, now)                # [B, k, 2] commands
    """

    def __init__(self, model: MotionModel, config: PredictorConfig | None = None,
                 adapt: AdaptSettings | None = None) -> None:
        self._model = model
        self._config = config or PredictorConfig()
        self._adapter: ModelAdapter | None = None
        if adapt is not None:
            self._adapter = ModelAdapter(model, adapt, horizon_steps=self.config.horizon_steps)
        if (problem := self.buffer_problem(model, self.config.horizon_steps, adapt,
                                           self.config.buffer_s)) is not None:
            raise ValueError(problem)
        self.resample_config = model.resample_config
        # Adaptation learns under the held-chair rule even from a model that predicts
        # without it (a model file from before the rule, or trained with it off): a chair
        # held against an obstacle while the stick pushes teaches nothing. Learning only
        # refuses more steps than prediction does; predictions resample as trained.
        self._learn_config: ResampleConfig | None = None
        if self._adapter is not None and \
                (learning := learning_config(model.resample_config)) != model.resample_config:
            self._learn_config = learning
        self.dt = 1.0 / float(model.resample_config.rate_hz)
        self.lags = int(model.feature_config.lags)
        self.stats = PredictorStats()
        rows = self._buffer_rows(self.config)
        self._joy = _Buffer(2, rows)
        self._vo = _Buffer(3, rows)  # v, omega, tracking ok (1.0 / 0.0)
        self._pose = _Buffer(3, rows)
        self._plans: list[tuple[float, FloatArray]] = []  # (stamp, [m, 2]) by stamp
        # times overrides were sent (feed_override), bounded in number as well as in time
        self._overrides: deque[float] = deque(maxlen=MAX_OVERRIDES)
        # the last window, for ``learn``: the grid predicted from (or the streams, to be
        # resampled under ``_learn_config``), the override times then, the complete steps
        self._to_learn: tuple[Resampled | RawStreams, FloatArray, int] | None = None
        self._last_now = -math.inf
        # when each stream was last heard from: the newest of its samples' stamps, each
        # taken no later than the clock at its arrival (when known): a stream stamped ahead
        # of the clock ages from its last arrival, not from its stamps. Samples fed without
        # ``now`` wait in ``_unseen`` (the newest stamp) until the next ``status(now)``, which
        # takes them no later than its ``now``: they arrived by then
        self._heard = {"joystick": -math.inf, "VO": -math.inf}
        self._unseen = dict.fromkeys(self._heard, -math.inf)
        self._stepped_until = -math.inf  # the clock before its last step back
        self.last_reset_detail = ""

    @property
    def config(self) -> PredictorConfig:
        """The settings; a new one (a node's parameters changed at runtime) also sizes the
        buffers' cap on rows for its ``buffer_s`` (``MAX_SAMPLE_RATE_HZ`` per second), and
        an adapting predictor's adaptation to its horizon (ValueError: a buffer shorter
        than :meth:`buffer_for` at that horizon, :meth:`buffer_problem`)."""
        return self._config

    @config.setter
    def config(self, config: PredictorConfig) -> None:
        if (problem := self.buffer_problem(self._model, config.horizon_steps,
                                           self.adapt_settings, config.buffer_s)) is not None:
            raise ValueError(problem)
        if self._adapter is not None:
            # the adaptation checks the predictions of the new horizon (at another it
            # checked none, and the ellipses went uncalibrated); its history grows with it
            self._adapter.set_horizon(config.horizon_steps)
        self._config = config
        rows = self._buffer_rows(config)
        for buf in (self._joy, self._vo, self._pose):
            buf.max_rows = rows

    @staticmethod
    def _buffer_rows(config: PredictorConfig) -> int:
        return max(1, math.ceil(config.buffer_s * MAX_SAMPLE_RATE_HZ))

    @property
    def model(self) -> MotionModel:
        """The model predictions use: the adapted one when adapting (see ``adapt``)."""
        return self._model if self._adapter is None else self._adapter.model

    @property
    def adapt_settings(self) -> AdaptSettings | None:
        """The settings this predictor adapts with; None when it does not adapt."""
        return None if self._adapter is None else self._adapter.settings

    @staticmethod
    def window_history_s(model: MotionModel) -> float:
        """The shortest buffer (s) that gives every window the verdict a full history
        gives, as far as a bounded look-back can: the model's ``lags`` grid steps (the last
        complete step up to one step behind the newest sample), the longest finite look-back
        of the stale/held-VO rules (``stale_after_s``, ``stale_still_after_s``,
        ``held_after_s``; the held-chair rule counted even when the model predicts without
        it, as adaptation learns with it), and two VO intervals (``max_gap_vel_s``): the
        sample bracketing the window's first step, and the buffer's first sample, which has
        no predecessor for its midpoint stamp. 3.4 s for the committed tile ASGP (8 lags
        at 5 Hz, 0.6 s, 0.6 s); with 2 s, stale VO drove paths a 10 s buffer refused (the
        rules saw runs of frozen readings cut short by the buffer's edge)."""
        cfg = learning_config(model.resample_config)
        looks = [v for v in (cfg.stale_after_s, cfg.stale_still_after_s, cfg.held_after_s)
                 if math.isfinite(v)]
        return (int(model.feature_config.lags) / float(cfg.rate_hz) + max(looks, default=0.0)
                + 2.0 * float(cfg.max_gap_vel_s))

    @staticmethod
    def buffer_for(model: MotionModel, horizon_steps: int, adapt: AdaptSettings | None,
                   buffer_s: float = 10.0) -> float:
        """``buffer_s``, or the longer history this model's windows
        (:meth:`window_history_s`) or adaptation with these settings need (see
        :attr:`min_buffer_s`): the buffer of a predictor that has no ``buffer_s`` of its own
        to set, such as the shared-control layer's."""
        need = max(float(buffer_s), Predictor.window_history_s(model))
        if adapt is None:
            return need
        steps = ModelAdapter.history_steps_for(model, adapt, horizon_steps)
        return max(need, (steps + 2) / float(model.resample_config.rate_hz))

    @staticmethod
    def buffer_problem(model: MotionModel, horizon_steps: int, adapt: AdaptSettings | None,
                       buffer_s: float) -> str | None:
        """Why ``buffer_s`` is too short for a predictor of ``model`` at ``horizon_steps``
        adapting with ``adapt`` (None: not adapting), naming the minimum; None when it is
        long enough (:meth:`buffer_for`)."""
        need = Predictor.buffer_for(model, horizon_steps, adapt, 0.0)
        if buffer_s >= need:
            return None
        window = Predictor.window_history_s(model)
        cfg = model.resample_config
        why = (f"the model's {int(model.feature_config.lags)} lags x {1.0 / cfg.rate_hz:g} s "
               "and the stale/held-VO rules' look-back need"
               if need <= window + 1e-9 else
               f"adaptation needs at a horizon of {horizon_steps} steps")
        return f"buffer_s must be at least {need:.2f} s, got {buffer_s:g} s: the history {why}"

    @property
    def min_buffer_s(self) -> float:
        """The shortest ``config.buffer_s`` this predictor works with: its model's
        windows' (:meth:`window_history_s`), longer to adapt (:meth:`buffer_for`)."""
        return self.buffer_for(self._model, self.config.horizon_steps, self.adapt_settings,
                               0.0)

    @property
    def adaptation(self) -> AdapterStats | None:
        """The online adaptation's counters, scales and coverage; None when not adapting
        (made at each call: :attr:`adapting` says whether there are any)."""
        return None if self._adapter is None else self._adapter.stats

    @property
    def adapting(self) -> bool:
        """Whether this predictor adapts online."""
        return self._adapter is not None

    def reset_adaptation(self) -> None:
        """Back to the trained posterior and calibration (no-op when not adapting). A window
        not learnt yet (``predict(..., learn=False)``) predates the reset: it is dropped."""
        self._to_learn = None
        if self._adapter is not None:
            self._adapter.reset()

    # ---- input ---------------------------------------------------------------------

    def reset(self, detail: str = "") -> None:
        """Forget all samples and the plan (a clock jump; a restart of the inputs).

        What an adapting predictor learnt is kept (see :meth:`reset_adaptation`); a window
        not learnt yet is dropped (its rows were of the forgotten samples, and the stream
        the adaptation follows restarts: learnt after the reset they would count twice).
        """
        self._to_learn = None
        self._joy.clear()
        self._vo.clear()
        self._pose.clear()
        self._plans = []
        self._overrides.clear()
        self._last_now = -math.inf
        self._heard = dict.fromkeys(self._heard, -math.inf)
        self._unseen = dict.fromkeys(self._heard, -math.inf)
        self.stats.resets += 1
        self.last_reset_detail = detail
        if self._adapter is not None:
            self._adapter.restart_stream()

    def clock_stepped_back(self, now: float, by: float) -> None:
        """The clock stepped back by ``by`` seconds to ``now`` (a node's clock, read at each
        callback, goes back only when it is stepped: NTP setting a clock that ran ahead, a
        /clock restarted). The buffers are reset, whatever ``reset_jump_s``: their samples
        are stamped up to ``by`` ahead of the clock, and the new ones would be spliced in
        among them, one window holding two moments. Until the clock is back where it was,
        a sample stamped more than :data:`STEP_LEAD_S` ahead of it is the old timeline's
        (sent before the step, delivered after) and refused, for at most
        :data:`STEP_GUARD_S`. (No second reset when none of
        the samples held is ahead of the clock: a step beyond ``reset_jump_s`` has reset the
        buffers already, at the first sample fed after it.)"""
        self._stepped_until = now + min(by, STEP_GUARD_S)
        if self._newest() > now + STEP_LEAD_S:
            self.reset(f"the clock stepped back by {by:.3f} s to {now:.3f} s")

    def _newest(self) -> float:
        return max(self._joy.newest, self._vo.newest)

    def _reject(self, reason: Reason, detail: str) -> None:
        if reason == Reason.REJECT_NONFINITE:
            self.stats.dropped_nonfinite += 1
        self.stats.rejected[reason] = self.stats.rejected.get(reason, 0) + 1
        self.stats.last_rejected = f"{reason}: {detail}"

    def _time_ok(self, t: float, what: str) -> bool:
        problem = time_problem(t)
        if problem is not None:
            self._reject(Reason.REJECT_NONFINITE if not math.isfinite(t)
                         else Reason.REJECT_TIME,
                         f"{what}: {problem}")
        return problem is None

    def _admit(self, t: float, what: str, now: float | None) -> bool:
        """Whether a sample stamped ``t`` is taken. Without ``now``, one stamped more than
        ``reset_jump_s`` behind the newest starts a new timeline (a bag played again): the
        buffers are reset. With ``now`` (a node's clock at its arrival), the clock tells:
        gone back, the buffers are reset first (as ``status`` would); else such a sample,
        and one stamped more than ``reset_jump_s`` ahead of the clock, is refused (one
        mis-stamped message used to clear every buffer)."""
        jump = self.config.reset_jump_s
        if now is None:
            newest = self._newest()
            if t < newest - jump:
                self.reset(f"sample stamped {t:.3f} s is {newest - t:.3f} s behind the newest")
            return True
        self._check_clock(now)
        newest = self._newest()
        if now < self._stepped_until and t > now + STEP_LEAD_S:
            self._reject(Reason.REJECT_TIME, f"{what} stamped {t - now:.3f} s ahead of the "
                                             "clock, which stepped back: of the timeline "
                                             "before the step")
            return False
        if t > now + jump:
            self._reject(Reason.REJECT_TIME, f"{what} stamped {t - now:.3f} s ahead of the "
                                             f"clock ({now:.3f} s)")
            return False
        if t < newest - jump:
            self._reject(Reason.REJECT_TIME, f"{what} stamped {newest - t:.3f} s behind the "
                                             "newest sample, the clock not gone back")
            return False
        return True

    def _note_heard(self, what: str, t: float, now: float | None) -> None:
        if now is None or not math.isfinite(now):  # arrived by the next status(now)
            self._unseen[what] = max(self._unseen[what], t)
        else:
            self._heard[what] = max(self._heard[what], min(t, now))

    def _heard_by(self, now: float, *, keep: bool) -> dict[str, float]:
        """When each stream was last heard from, as of ``now``: samples fed without a
        ``now`` of their own count as heard no later than the first ``now`` that sees them
        (``keep``: remembered so, for the later calls; a status check keeps, a query of
        the ages does not)."""
        heard = {what: max(h, min(self._unseen[what], now)) for what, h in self._heard.items()}
        if keep:
            self._heard = heard
            self._unseen = dict.fromkeys(self._heard, -math.inf)
        return heard

    @staticmethod
    def _pair(what: str, values: tuple[float, float] | FloatArray) -> tuple[float, float]:
        """(a, b) of a two-value sample; ValueError for any other shape (a longer tuple's
        first two values were taken silently)."""
        if np.shape(values) != (2,):
            raise ValueError(f"{what} must be two values, got shape {np.shape(values)}")
        return float(values[0]), float(values[1])

    def feed_joy(self, t: float, joy: tuple[float, float] | FloatArray,
                 now: float | None = None) -> bool:
        """Add a joystick sample (forward, turn) at time t.

        Args:
            joy: (forward, turn), exactly two values.
            now: the clock at its arrival, if known: a sample stamped too far from it, or
                too far behind the newest while the clock did not go back, is refused
                (see ``_admit``); without it such a sample starts a new timeline. The
                stream's age (``joy_timeout_s``) counts from the sample's stamp, or from
                ``now`` when it is stamped ahead of it; without ``now``, from the ``now``
                of the first :meth:`status` (:meth:`predict`, ...) after it when stamped
                ahead of that: the sample arrived by then, and a sender whose stamps run
                ahead of the predictor's clock (no common clock) cannot look fresher.

        Returns:
            False if refused (a stamp or a deflection not finite or out of range; see
            ``stats.last_rejected``).

        Raises:
            ValueError: ``joy`` is not two values.
        """
        values = self._pair("a joystick sample", joy)
        t = float(t)
        if not self._time_ok(t, "joystick"):
            return False
        problem = joy_problem(*values)
        if problem is not None:
            finite = all(math.isfinite(v) for v in values)
            self._reject(Reason.REJECT_JOY if finite else Reason.REJECT_NONFINITE,
                         f"joystick: {problem}")
            return False
        if not self._admit(t, "joystick", now):
            return False
        self._note_heard("joystick", t, now)
        self.stats.joy_samples += 1
        self.stats.out_of_order += self._joy.add(t, values)
        self.stats.dropped_overflow += self._joy.prune(self.config.buffer_s)
        return True

    def feed_vo(self, t: float, vel: tuple[float, float] | FloatArray, ok: bool = True,
                now: float | None = None) -> bool:
        """Add a VO velocity (v, omega) at time t; ``ok`` False = VO reported tracking loss;
        ``now`` (and the stream's age) as for :meth:`feed_joy`.

        A sample with tracking loss carries no velocity: it is kept (as a tracking
        failure, which the resampler invalidates) with zeros whatever its values.

        Returns:
            False if refused (a stamp, or the velocity of a tracked sample, not finite or
            beyond the physical limits; see ``stats.last_rejected``).

        Raises:
            ValueError: ``vel`` is not two values, or ``ok`` not a bool (the string
                "False" read as tracked).
        """
        if not isinstance(ok, bool | np.bool_):
            raise ValueError(f"ok must be a bool, got {ok!r}")
        pair = self._pair("a VO sample", vel)
        t = float(t)
        v, w = pair if ok else (0.0, 0.0)
        if not self._time_ok(t, "VO"):
            return False
        problem = vel_problem(v, w)
        if problem is not None:
            finite = math.isfinite(v) and math.isfinite(w)
            self._reject(Reason.REJECT_VO if finite else Reason.REJECT_NONFINITE,
                         f"VO: {problem}")
            return False
        if not self._admit(t, "VO", now):
            return False
        self._note_heard("VO", t, now)
        self.stats.vo_samples += 1
        self.stats.out_of_order += self._vo.add(t, (v, w, 1.0 if ok else 0.0))
        self.stats.dropped_overflow += self._vo.prune(self.config.buffer_s)
        return True

    def feed_override(self, t: float, now: float | None = None) -> bool:
        """Note that an override command was sent to the chair at time t (the shared-control
        layer's or a planner's ``joy_override``): around it the joystick fed here is not
        what drove the chair, so an adapting predictor learns nothing from the grid steps
        it may have driven (:func:`asgp_ros.core.resample.exclude_overridden`, the rule
        training applies to a bag's overrides), nor checks a prediction against them.
        Predictions themselves are made as before.

        An override that arrives after a step it drove was learnt (later than
        ``adaptive.OVERRIDE_DELAY_S``) cannot undo it: it is counted in
        ``stats.overrides_late``.

        Args:
            t: when it was sent, on the samples' clock.
            now: the clock when it arrived: one stamped more than ``reset_jump_s`` ahead
                is of another timeline and refused (as a plan's start); default: the
                newest sample's stamp.

        Returns:
            False if refused (a stamp that is not a valid time, or one too far ahead).
        """
        t = float(t)
        if not self._time_ok(t, "override"):
            return False
        ref = self._newest() if now is None else float(now)
        if math.isfinite(ref) and t > ref + self.config.reset_jump_s:  # another timeline's
            self._reject(Reason.REJECT_TIME, f"override stamped {t - ref:.3f} s ahead of "
                         f"{'the newest sample' if now is None else 'the clock'}")
            return False
        self.stats.overrides += 1
        if self._adapter is None:
            return True  # nothing learnt: nothing to keep out
        rc = self._model.resample_config
        if self._adapter.absorbed_to is not None:
            first = math.ceil(t * rc.rate_hz - 1.0 - 1e-9)  # the first step it may drive
            # learnt, unless the override before it (in arrival order, mostly the nearest)
            # already kept that step out
            prev = np.array([self._overrides[-1]] if self._overrides else [])
            kept = overridden_points(np.array([first / rc.rate_hz]), prev, rc)[0]
            if first <= self._adapter.absorbed_to and not kept:
                self.stats.overrides_late += 1
        self._overrides.append(t)
        self._prune_overrides()
        return True

    def _prune_overrides(self) -> None:
        """Forget the overrides older than the buffer (their steps are no longer in it)."""
        cutoff = self._newest() - self.config.buffer_s
        while self._overrides and self._overrides[0] < cutoff:
            self._overrides.popleft()

    def feed_pose(self, t: float, x: float, y: float, yaw: float) -> bool:
        """Add an odometry pose of the base in the odom frame (for paths in that frame).

        Returns:
            False if refused (not finite or out of range; see ``stats.last_rejected``).
        """
        t = float(t)
        if not self._time_ok(t, "pose"):
            return False
        problem = pose_problem(float(x), float(y), float(yaw))
        if problem is not None:
            finite = all(math.isfinite(float(v)) for v in (x, y, yaw))
            self._reject(Reason.REJECT_POSE if finite else Reason.REJECT_NONFINITE,
                         problem)
            return False
        self._pose.add(t, (float(x), float(y), float(yaw)))
        self.stats.dropped_overflow += self._pose.prune(self.config.buffer_s)
        return True

    def _check_commands(self, commands: FloatArray, what: str) -> None:
        """Refuse joystick commands [..., k, 2] that are not finite or out of range."""
        if commands.shape[-2] > MAX_PLAN_STEPS:
            raise RejectedInputError(
                Reason.REJECT_PLAN,
                f"{what} has {commands.shape[-2]} steps, more than {MAX_PLAN_STEPS}")
        flat = commands.reshape(-1, 2)
        bad = np.flatnonzero(~joy_in_range(flat))
        if bad.size:
            fwd, turn = flat[bad[0]]
            problem = joy_problem(float(fwd), float(turn))
            index = [int(i) for i in np.unravel_index(bad[0], commands.shape[:-1])]
            where = f"row {index[-1]}" if len(index) == 1 else \
                f"{index[0]} row {index[-1]}"
            finite = bool(np.all(np.isfinite(flat)))
            raise RejectedInputError(Reason.REJECT_PLAN if finite else Reason.REJECT_NONFINITE,
                                     f"{what} {where}: {problem}")

    def set_plan(self, plan: FloatArray, stamp: float, now: float | None = None) -> None:
        """A planner's future joystick commands: [m, 2] rows from ``stamp`` on, dt apart.

        ``now``: the clock when the plan arrived. A plan starting more than
        ``reset_jump_s`` after it is refused, as a sample stamped that far ahead of the
        clock is (its stamps are of another timeline: a clock that jumped ahead, then
        back, would otherwise leave it to drive the future joystick once the clock
        reached it).

        Raises:
            ValueError: wrong shape or empty; :class:`RejectedInputError` (a ValueError,
                counted in ``stats.rejected``) for more than ``MAX_PLAN_STEPS`` rows, a
                value not finite or outside the joystick range, a stamp that is not a
                valid time, or one more than ``reset_jump_s`` ahead of ``now``.
        """
        arr = np.asarray(plan, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != 2 or arr.shape[0] == 0:
            raise ValueError(f"a plan must be [m, 2] joystick commands, got shape {arr.shape}")
        try:
            problem = time_problem(float(stamp))
            if problem is not None:
                reason = Reason.REJECT_TIME if math.isfinite(stamp) else Reason.REJECT_NONFINITE
                raise RejectedInputError(reason, f"plan: {problem}")
            if now is not None and not math.isfinite(now):
                raise ValueError(f"now must be a finite time, got {now}")
            if now is not None and float(stamp) > now + self.config.reset_jump_s:
                raise RejectedInputError(
                    Reason.REJECT_TIME, f"plan starts {float(stamp) - now:.3f} s ahead of "
                    f"the clock (limit reset_jump_s = {self.config.reset_jump_s} s)")
            self._check_commands(arr, "plan")
        except RejectedInputError as exc:
            self._reject(exc.reason, exc.detail)
            raise
        plans = [p for p in self._plans if p[0] != float(stamp)]
        plans.append((float(stamp), arr.copy()))
        plans.sort(key=lambda p: p[0])
        self._plans = plans[-MAX_PLANS:]

    def clear_plan(self) -> None:
        self._plans = []

    # ---- queries -------------------------------------------------------------------

    def newest_velocity(self) -> tuple[float, float, float] | None:
        """(stamp, v, omega) of the newest velocity sample, None without one or when it
        reports tracking loss."""
        if len(self._vo) == 0:
            return None
        t, v, w, ok = self._vo.newest_row()
        return None if ok < 0.5 else (float(t), float(v), float(w))

    def input_ages(self, now: float) -> tuple[float, float]:
        """(joystick age, VO age) at ``now`` (s), as the staleness rule of :meth:`status`
        counts them: since the newest sample's stamp, or its arrival when it was stamped
        ahead of the clock (:meth:`feed_joy`); inf before the first."""
        heard = self._heard_by(now, keep=False)
        return now - heard["joystick"], now - heard["VO"]

    def newest_stamps(self) -> tuple[float, float]:
        """(newest joystick stamp, newest VO stamp); -inf when empty."""
        return self._joy.newest, self._vo.newest

    def ready_step(self) -> int | None:
        """Grid index of the newest point covered by both streams (cheap), or None."""
        if not self._joy or not self._vo:
            return None
        ready = min(self._joy.newest, self._vo_covers())
        if not math.isfinite(ready):
            return None  # one VO sample, whose interval is not known yet
        return math.floor(ready / self.dt + 1e-6)

    def joystick_behind(self, every_n: int = 1) -> bool:
        """Whether the VO covers a newer grid step than the joystick does, one whose index
        is a multiple of ``every_n`` (a node that predicts once the completed steps pass a
        multiple of n): that step waits for a joystick sample only (cheap; a node reading
        the joystick in batches reads it again soon instead of at its next batch)."""
        if every_n < 1:
            raise ValueError(f"every_n must be at least 1, got {every_n}")
        if not self._joy or not self._vo:
            return False
        vo = self._vo_covers()
        if not math.isfinite(vo):
            return False
        joy_step = math.floor(self._joy.newest / self.dt + 1e-6)
        vo_step = math.floor(vo / self.dt + 1e-6)
        return vo_step // every_n * every_n > joy_step

    def _vo_covers(self) -> float:
        """The newest time the VO buffer gives a velocity for: its newest stamp, or with
        midpoint stamps (:mod:`asgp_ros.core.resample`) the middle of the newest interval
        (the previous stamp if that interval is a gap: an upper bound, resampling decides)."""
        t = self._vo.newest
        if self.resample_config.vel_stamp != "midpoint":
            return t
        prev = self._vo.before_newest
        if t - prev <= self.resample_config.max_gap_vel_s:
            return prev + 0.5 * (t - prev)
        return prev

    def plan_future(self, t0: float, now: float, k: int,
                    held: FloatArray | None = None) -> FloatArray | None:
        """[k, 2] commands at t0 + i*dt (i = 1..k) from the fresh plans, or None if none.

        Each grid time uses the newest plan started at or before it (a plan cannot revise
        a command already executed before it started); row r of a plan starting at
        ``stamp`` covers [stamp + r dt, stamp + (r+1) dt), the last row is held. Grid times
        before every fresh plan use ``held`` (default: that plan's first row).

        Times are compared with a tolerance of ``PLAN_TOLERANCE_STEPS`` grid steps: plans
        start on grid times, and at epoch stamps (1.7e9 s) a float64 second has only about
        0.2 us of resolution, so two computations of the same grid time differ by an ulp.
        """
        plans = [p for p in self._plans if now - p[0] <= self.config.plan_timeout_s]
        self._plans = plans
        if not plans:
            return None
        stamps = np.array([p[0] for p in plans])
        times = t0 + self.dt * np.arange(1, k + 1)
        tol = PLAN_TOLERANCE_STEPS
        which = np.searchsorted(stamps, times + tol * self.dt, side="right") - 1  # [k]
        out = np.empty((k, 2))
        for j in range(k):
            if which[j] < 0:
                out[j] = plans[0][1][0] if held is None else held
                continue
            stamp, rows = plans[which[j]]
            r = math.floor((times[j] - stamp) / self.dt + tol)
            out[j] = rows[min(max(r, 0), rows.shape[0] - 1)]
        return out

    def _check_clock(self, now: float) -> Prediction | None:
        jump = self.config.reset_jump_s
        if now < self._last_now - jump or self._newest() > now + jump:
            detail = (f"clock went back from {self._last_now:.3f} s to {now:.3f} s"
                      if now < self._last_now - jump
                      else f"samples stamped up to {self._newest():.3f} s are ahead of "
                           f"the clock ({now:.3f} s)")
            self.reset(detail)
            self._last_now = now
            return Prediction(False, Reason.CLOCK_RESET, f"{detail}: buffers reset")
        self._last_now = max(self._last_now, now)
        return None

    def status(self, now: float) -> Prediction | None:
        """Cheap input check (no resampling): why no prediction is possible, else None.

        Also detects a clock jump (and resets), so a watchdog may call it periodically.
        """
        cfg = self.config
        problem = time_problem(now)
        if problem is not None:
            return Prediction(False, Reason.INVALID_TIME, f"now: {problem}")
        if (reset := self._check_clock(now)) is not None:
            return reset
        # the age of a stream: since its newest sample's stamp, or since that sample
        # arrived when it was stamped ahead of the clock (an unsynchronised sender's stick
        # gone silent drove paths for the lead's length more): ``_heard``; a sample fed
        # without its arrival time arrived by the first ``now`` that sees it
        heard = self._heard_by(now, keep=True)
        if not self._joy or not self._vo:
            return Prediction(False, Reason.NO_INPUT, no_input_detail(not self._joy,
                                                                      not self._vo))
        joy_age = now - heard["joystick"]
        if joy_age > cfg.joy_timeout_s:
            return Prediction(False, Reason.STALE_JOYSTICK,
                              f"joystick is {joy_age:.2f} s old (limit {cfg.joy_timeout_s} s)")
        vo_age = now - heard["VO"]
        if vo_age > cfg.vo_timeout_s:
            return Prediction(False, Reason.STALE_VO,
                              f"VO is {vo_age:.2f} s old (limit {cfg.vo_timeout_s} s)")
        if self._vo.newest_row()[3] < 0.5:
            return Prediction(False, Reason.VO_TRACKING_LOST, "VO reports tracking loss")
        return None

    def _window(self, now: float) -> Prediction | tuple[int, float, FloatArray, FloatArray]:
        """The measured window at the last complete step, or a not-ok Prediction."""
        if (bad := self.status(now)) is not None:
            return bad
        joy_t, joy = self._joy.arrays()
        vo_t, vo = self._vo.arrays()
        streams = RawStreams(joy_t=joy_t, joy=joy, vel_t=vo_t, vel=vo[:, :2],
                             vel_ok=vo[:, 2] > 0.5, source="live")
        res = resample(streams, self.resample_config)
        s = self.lags
        t_ready = min(self._joy.newest, self._vo_covers())
        n = int(np.searchsorted(res.t, t_ready + _EPS_T, side="right"))
        if self._adapter is not None:  # learnt from in ``learn``, after the path is out
            self._prune_overrides()
            self._to_learn = (res if self._learn_config is None else streams,
                              np.sort(np.fromiter(self._overrides, float)), n)
        if n < s:
            return Prediction(False, Reason.NOT_ENOUGH_HISTORY,
                              f"{n} grid steps buffered, the model needs {s}")
        last = n - 1
        window = slice(last - s + 1, last + 1)
        if bool(res.tracking_lost[last]):
            return Prediction(False, Reason.VO_TRACKING_LOST, "VO reported tracking loss")
        if bool(res.stale[last]):
            return Prediction(False, Reason.VO_STALE_REPEAT,
                              "VO repeats itself, or reads the chair held while it is pushed")
        valid = np.asarray(res.valid[window], dtype=bool)
        segment = np.asarray(res.segment[window])
        if not (np.all(valid) and np.all(segment == segment[-1])):
            why = ("tracking loss" if np.any(res.tracking_lost[window])
                   else "stale VO" if np.any(res.stale[window])
                   else "a gap in the input")
            return Prediction(
                False, Reason.NOT_ENOUGH_HISTORY,
                f"only {_trailing_true(valid)} of the last {s} grid steps are valid ({why})",
            )
        t0 = float(res.t[last])
        return (int(res.k[last]), t0, np.asarray(res.joy[window], dtype=np.float64),
                np.asarray(res.vel[window], dtype=np.float64))

    def _rollout(self, joy_past: FloatArray, vel_past: FloatArray, futures: FloatArray
                 ) -> Rollout:
        unc = self.config.uncertainty
        mode: Uncertainty = "mc" if unc == "mc" else "none" if unc == "none" else "linear"
        return rollout(self.model, joy_past, vel_past, futures, uncertainty=mode)

    def learn(self) -> None:
        """Let an adapting predictor learn from the window of the last query (absorb the
        settled steps, check the predictions whose outcomes have arrived); a no-op when not
        adapting or already done.  ``predict``, ``predict_batch`` and ``solve_inverse`` call
        it after predicting unless told not to: a node that publishes first calls it
        afterwards, so that learning is not in the path's latency.
        """
        pending, self._to_learn = self._to_learn, None
        if pending is None or self._adapter is None:
            return
        grid, overrides, complete = pending
        if isinstance(grid, RawStreams):
            assert self._learn_config is not None
            grid = resample(grid, self._learn_config)
        if overrides.size:
            grid = exclude_overridden(grid, overrides, self.resample_config)
        self._adapter.observe(grid, complete)

    def observe(self, now: float) -> None:
        """An adapting predictor's learning at ``now`` without a prediction: the window is
        formed as :meth:`predict` forms it, and learnt from (absorbing the settled steps,
        checking the predictions whose outcomes arrived). A caller that predicts every n-th
        step calls it on the others, so that adaptation absorbs, and its online calibration
        checks, every step. A no-op when not adapting."""
        if self._adapter is None:
            return
        self._window(now)
        self.learn()

    def predict(self, now: float, joy_future: FloatArray | None = None, *,
                learn: bool = True) -> Prediction:
        """The predicted path at the last complete step, or why there is none.

        Args:
            now: current time on the stamps' clock (staleness and clock jumps).
            joy_future: [k, 2] future commands for t0 + dt .. t0 + k*dt; default: a fresh
                plan if any, else the newest joystick sample held.
            learn: when adapting, call :meth:`learn` after predicting.
        """
        try:
            return self._predict(now, joy_future)
        finally:
            if learn:
                self.learn()

    def _predict(self, now: float, joy_future: FloatArray | None) -> Prediction:
        got = self._window(now)
        if isinstance(got, Prediction):
            return got
        step, t0, joy_past, vel_past = got
        k = self.config.horizon_steps
        from_plan = False
        if joy_future is None:
            held = self._joy.newest_row()[1:]
            planned = self.plan_future(t0, now, k, held)
            if planned is not None:
                joy_future, from_plan = planned, True
            else:
                joy_future = np.repeat(held[None, :], k, axis=0)
        future = np.asarray(joy_future, dtype=np.float64)
        if future.ndim != 2 or future.shape[1] != 2 or future.shape[0] == 0:
            raise ValueError(f"joy_future must be [k, 2], got shape {future.shape}")
        self._check_commands(future, "joy_future")
        out = self._rollout(joy_past, vel_past, future[None])
        return self._result(step, t0, joy_past, vel_past, future[None], out, from_plan,
                            batch=False)

    def solve_inverse(self, target_xy: FloatArray, now: float, *, learn: bool = True,
                      **options: Any) -> tuple[Prediction, InverseResult | None]:
        """The joystick sequence whose predicted path follows ``target_xy`` [k, 2] (positions
        at t0 + i dt in the frame of the pose at t0), from the live buffers.

        Returns:
            (the window: ``ok`` with ``t0`` and ``step``, or why there is none; the
            :class:`~asgp_ros.core.inverse.InverseResult`, None without a window).
            ``options`` are those of :func:`asgp_ros.core.inverse.solve`.

        Raises:
            ValueError: a bad target or bad options (see ``solve``).
        """
        got = self._window(now)
        if isinstance(got, Prediction):
            if learn:
                self.learn()
            return got, None
        step, t0, joy_past, vel_past = got
        try:
            result = inverse.solve(self.model, joy_past, vel_past, target_xy, **options)
        finally:
            if learn:
                self.learn()
        # the solution's path as ``predict`` gives it (its uncertainty, ellipses, odometry
        # origin), and the same refusal of a model predicting beyond physics
        futures = result.joystick[None]
        window = self._result(step, t0, joy_past, vel_past, futures,
                              self._rollout(joy_past, vel_past, futures), False, batch=False)
        if not window.ok:
            return window, None
        return replace(window, detail="inverse"), result

    def predict_batch(self, candidates: FloatArray, now: float, *, learn: bool = True
                      ) -> Prediction:
        """Paths for a batch of candidate future joystick sequences (for planners).

        Args:
            candidates: [B, k, 2] commands for t0 + dt .. t0 + k*dt (any k >= 1).
            now: current time.

        Returns:
            A Prediction whose arrays have a leading [B] axis (times, t0 and the measured
            window are shared).
        """
        cand = np.asarray(candidates, dtype=np.float64)
        if cand.ndim != 3 or cand.shape[2] != 2 or cand.shape[0] == 0 or cand.shape[1] == 0:
            raise ValueError(f"candidates must be [B, k, 2], got shape {cand.shape}")
        self._check_commands(cand, "candidates")
        try:
            got = self._window(now)
            if isinstance(got, Prediction):
                return got
            step, t0, joy_past, vel_past = got
            out = self._rollout(joy_past, vel_past, cand)
            return self._result(step, t0, joy_past, vel_past, cand, out, False, batch=True)
        finally:
            if learn:
                self.learn()

    def _result(self, step: int, t0: float, joy_past: FloatArray, vel_past: FloatArray,
                futures: FloatArray, out: Rollout, from_plan: bool, batch: bool) -> Prediction:
        problem = out.problem()
        if problem is not None:
            return Prediction(False, Reason.MODEL_OUT_OF_RANGE, problem)
        pose = np.asarray(out.pose, dtype=np.float64)
        pos_cov = np.asarray(out.pos_cov, dtype=np.float64)
        pose_cov = np.asarray(out.pose_cov, dtype=np.float64)
        vel = np.asarray(out.vel, dtype=np.float64)
        vel_cov = np.asarray(out.vel_cov, dtype=np.float64)
        k = futures.shape[1]
        # its own copy: the caller's joy_future or candidates (refilled by a planner each
        # cycle), or an InverseResult's joystick, stay the caller's
        futures = futures.copy()
        pose_t, pose_v = self._pose.arrays()
        origin = interpolate_pose(t0, pose_t[np.argsort(pose_t)], pose_v[np.argsort(pose_t)])
        if not batch:
            pose, pos_cov, pose_cov, vel, vel_cov, futures = (
                pose[0], pos_cov[0], pose_cov[0], vel[0], vel_cov[0], futures[0])
        self.stats.predictions += 1
        return Prediction(
            ok=True, reason=Reason.OK, t0=t0, step=step, dt=self.dt,
            times=t0 + self.dt * np.arange(1, k + 1),
            pose=pose, pos_cov=pos_cov, pose_cov=pose_cov,
            ellipses=confidence_ellipses(pos_cov),
            vel=vel, vel_cov=vel_cov, joy_future=futures,
            joy_past=joy_past, vel_past=vel_past, origin=origin, from_plan=from_plan,
        )


def _trailing_true(mask: NDArray[np.bool_]) -> int:
    """Length of the run of True at the end of ``mask``."""
    falses = np.flatnonzero(~mask)
    return int(mask.shape[0] if falses.size == 0 else mask.shape[0] - 1 - falses[-1])
