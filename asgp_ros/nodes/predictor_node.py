"""ROS 2 node: online k-step motion prediction of the wheelchair.

Subscribes ``joy`` (sensor_msgs/Joy), ``vo/twist`` (geometry_msgs/TwistStamped, or
nav_msgs/Odometry with ``vo_type: odometry``) and ``joy_plan`` (trajectory_msgs/JointTrajectory,
joints ``forward`` and ``turn``: a planner's future joystick commands, stamped with when
they start), ``joy_applied`` (``applied_topic``: the board's output as the serial bridge
measures it, which feeds the predictor instead of ``joy`` while it arrives,
:mod:`asgp_ros.nodes.joy_source`) and ``joy_override`` (``override_topic``: the overrides sent
to the chair; without the measurement and with
``override_paths`` the paths are predicted from the command the board applies, an override
as long as the serial bridge writes it (``override_timeout_s``) and the board's watchdog holds
it, while the user's stick is out of neutral; an adapting predictor learns nothing from the
steps they may have driven); publishes ``predicted_path``
(nav_msgs/Path), ``predicted_path/uncertainty`` (visualization_msgs/MarkerArray, a 95%
position ellipse per step) and ``diagnostics``.

The numerics are :class:`asgp_ros.core.online.Predictor`; this node only converts messages
and wires callbacks. A prediction is made once per grid step of the model (its rate), as
soon as the sample that completes the step arrives (the VO message, usually; a joystick
sample when it is read, below), so the path is published within the prediction's latency of
the data; a timer at the model's rate is the watchdog (staleness, clock jumps, clearing the
RViz ellipses) and another publishes diagnostics. The joystick topics (``joy``,
``joy_applied``; 100 Hz from the serial bridge) wake nothing: they are read in batches
every ``joy_poll_period_s`` and before each VO message, override, watchdog check and
diagnostics message, each message with its own arrival time (:mod:`asgp_ros.nodes.polled`;
half the node's CPU went to rclpy's wake-ups for them), and every 10 ms while a step the VO
completed waits for a joystick sample only. Stale input means no path and a
diagnostic saying why; fresh input resumes prediction without a restart. Input that is not
finite or out of its range (see :mod:`asgp_ros.core.streams`) is refused by the Predictor
with a reason code; the diagnostics count the refusals by code (``rejected``) and give the
newest one (``last_rejected``).

Adaptation (``adapt.enabled``, on by default; an ASGP model only, another kind predicts as
trained, with a warning and ``adapt_unavailable`` in the diagnostics): every completed
grid step that training would accept updates the posterior, with forgetting (``adapt.half_life_s``,
``adapt.trained_floor``), as a correction to the trained function (``adapt.trained_mean``),
and the outcomes of the predictions keep the 95 % ellipses
covering (``adapt.calibrate``, ``adapt.max_rate``); see :mod:`asgp_ros.core.adaptive`.
The diagnostics show the rows absorbed, the effective data size, the variance scale per
speed regime, the recent coverage and the last update's cost. The service
``~/reset_adaptation`` (std_srvs/Trigger) returns to the trained model.

Signals: SIGINT and SIGTERM end the node well within 2 s in every state (tested).
The model is read in a worker thread while the main thread watches the ROS context, so
even a read that blocks (a hung network file system) cannot keep the node alive; a path
that is not a regular file (a FIFO, a device) is refused before it is opened.

Run: ``predictor_node --ros-args --params-file config/predictor.yaml -p model_path:=M.npz``
"""

from __future__ import annotations

import math
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import TwistStamped
from nav_msgs.msg import Odometry, Path
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock
from rclpy.clock_type import ClockType
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import Joy
from threadpoolctl import threadpool_limits
from trajectory_msgs.msg import JointTrajectory
from visualization_msgs.msg import MarkerArray

from asgp_ros.common import topics
from asgp_ros.common.paramspec import ParamSpec, check_value, check_values
from asgp_ros.core import online
from asgp_ros.core.adaptive import (
    DEFAULT_HALF_LIFE_S,
    DEFAULT_TRAINED_FLOOR,
    DEFAULT_TRAINED_HALF_LIFE_S,
    AdaptSettings,
)
from asgp_ros.core.modelfile import ModelFileError, load_model
from asgp_ros.core.models import MotionModel
from asgp_ros.core.online import Prediction, Predictor, PredictorConfig, Reason
from asgp_ros.core.shared_control import BOARD_WATCHDOG_S, applied_command
from asgp_ros.core.streams import joy_problem
from asgp_ros.nodes import adaptation as adapt_params
from asgp_ros.nodes import conversions as conv
from asgp_ros.nodes import runtime
from asgp_ros.nodes.joy_source import JoySource, check_topics
from asgp_ros.nodes.parameters import (
    declare,
    is_change,
    sim_time_change,
    topic_beside,
    topic_name_problem,
)
from asgp_ros.nodes.polled import Arrival, PolledInputs, period_problem
from asgp_ros.nodes.qos_watch import QosWatch
from asgp_ros.recording.bags import parse_joy_axes
from asgp_ros.serial.override_gate import DEFAULT_TIMEOUT_S, OverrideGate

NODE_NAME = "predictor_node"


class StartupError(Exception):
    """The node cannot start (bad model file, inconsistent parameters)."""


class StartupInterruptedError(Exception):
    """Shutdown (SIGINT, SIGTERM) was requested while the node was starting."""


#: How often the main thread checks for a shutdown while the model loads (s).
_LOAD_POLL_S = 0.05
#: How long after a path adaptation's learning waits (at most a quarter of a model step):
#: learning right after the publication took a core from the path's subscribers on a
#: two-core laptop and added to their latency (``benchmarks/predictor_latency.py``).
LEARN_DELAY_S = 0.02
#: Largest n of ``rate_hz`` = the model's rate / n (a path every 200 s at 5 Hz): a smaller
#: rate (1e-300 Hz, say) is refused rather than never predicting.
MAX_DECIMATION = 1000
#: A step the VO completed that waits for a joystick sample only (a joystick slower than
#: the VO) has the joystick read every JOY_WAIT_TICK_S until it comes, for at most
#: JOY_WAIT_MAX_S (or ``joy_poll_period_s`` if shorter), instead of at the next batch.
JOY_WAIT_TICK_S = 0.01
JOY_WAIT_MAX_S = 0.1
#: After a wait the sample did not end (a joystick stamped later than the VO by more than
#: the wait: its driver's clock or transport), none starts for this long: such a stick
#: would otherwise keep the node reading every JOY_WAIT_TICK_S for nothing.
JOY_WAIT_BACKOFF_S = 1.0


@dataclass(frozen=True)
class PredictorNodeParams:
    """The node's parameters, validated on construction (see config/predictor.yaml)."""

    model_path: str = ""
    horizon_steps: int = 0
    horizon_s: float = 2.0
    rate_hz: float = 0.0
    joy_topic: str = topics.JOY
    vo_topic: str = topics.VO_TWIST
    vo_type: str = "twist"
    plan_topic: str = topics.JOY_PLAN
    override_topic: str = topics.JOY_OVERRIDE
    applied_topic: str = topics.JOY_APPLIED
    override_paths: bool = True
    override_timeout_s: float = DEFAULT_TIMEOUT_S
    path_topic: str = topics.PREDICTED_PATH
    joy_axes: str = "0,1"
    joy_timeout_s: float = 0.5
    vo_timeout_s: float = 0.5
    plan_timeout_s: float = 1.0
    buffer_s: float = 10.0
    reset_jump_s: float = 1.0
    base_frame: str = "base_link"
    odom_frame: str = "odom"
    path_frame: str = "base"
    uncertainty: str = "linear"
    publish_uncertainty: bool = True
    diagnostics_period_s: float = 1.0
    joy_poll_period_s: float = 0.25
    # adapt.* (asgp_ros.nodes.adaptation.ADAPT_PARAMS; the same defaults)
    adapt_enabled: bool = True
    adapt_half_life_s: float = DEFAULT_HALF_LIFE_S
    adapt_trained_floor: float = DEFAULT_TRAINED_FLOOR
    adapt_trained_half_life_s: float = DEFAULT_TRAINED_HALF_LIFE_S
    adapt_trained_mean: bool = True
    adapt_calibrate: bool = True
    adapt_max_rate: float = 0.25

    def __post_init__(self) -> None:
        if not self.model_path:
            raise ValueError("model_path is required (a model file from `asgp train`)")
        if not 0 <= self.horizon_steps <= 200:
            raise ValueError(f"horizon_steps must be in [0, 200], got {self.horizon_steps}")
        if not (math.isfinite(self.horizon_s) and 0.0 < self.horizon_s <= 40.0):
            raise ValueError(f"horizon_s must be in (0, 40] s, got {self.horizon_s}")
        if not (math.isfinite(self.rate_hz) and 0.0 <= self.rate_hz <= 100.0):
            raise ValueError(f"rate_hz must be in [0, 100] Hz, got {self.rate_hz}")
        for name in ("joy_topic", "vo_topic", "plan_topic", "path_topic", "base_frame",
                     "odom_frame"):
            if not getattr(self, name).strip():
                raise ValueError(f"{name} must not be empty")
        if self.vo_type not in ("twist", "odometry"):
            raise ValueError(f"vo_type must be 'twist' or 'odometry', got {self.vo_type!r}")
        if self.path_frame not in ("base", "odom"):
            raise ValueError(f"path_frame must be 'base' or 'odom', got {self.path_frame!r}")
        if self.path_frame == "odom" and self.vo_type != "odometry":
            raise ValueError("path_frame 'odom' needs odometry poses: set vo_type to 'odometry' "
                             "and vo_topic to the odometry's topic (vo_node publishes it on "
                             f"{topics.VO_ODOM})")
        parse_joy_axes(self.joy_axes, "joy_axes")
        if not (math.isfinite(self.diagnostics_period_s)
                and 0.1 <= self.diagnostics_period_s <= 60.0):
            raise ValueError(
                f"diagnostics_period_s must be in [0.1, 60] s, got {self.diagnostics_period_s}"
            )
        if (problem := period_problem("joy_poll_period_s", self.joy_poll_period_s)) is not None:
            raise ValueError(problem)
        # the predictor's own settings are validated by PredictorConfig, adaptation's here
        self.predictor_config(5.0)
        self.adapt_settings()

    def adapt_values(self) -> dict[str, Any]:
        """The adapt.* parameters by their ROS names."""
        return {spec.name: getattr(self, _field(spec.name))
                for spec in adapt_params.ADAPT_PARAMS}

    def adapt_settings(self) -> AdaptSettings | None:
        """The online adaptation's settings, or None when ``adapt.enabled`` is false."""
        return adapt_params.adapt_settings(self.adapt_values())

    def steps(self, model_rate_hz: float) -> int:
        """k: horizon_steps, or horizon_s at the model's rate."""
        if self.horizon_steps > 0:
            return self.horizon_steps
        return online.horizon_steps(self.horizon_s, model_rate_hz)

    def predictor_config(self, model_rate_hz: float, min_buffer_s: float = 0.0
                         ) -> PredictorConfig:
        """The predictor's settings; its buffer at least ``min_buffer_s`` (what adaptation
        needs, :meth:`Predictor.buffer_for`)."""
        return PredictorConfig(
            horizon_steps=self.steps(model_rate_hz),
            joy_timeout_s=self.joy_timeout_s,
            vo_timeout_s=self.vo_timeout_s,
            plan_timeout_s=self.plan_timeout_s,
            buffer_s=max(self.buffer_s, min_buffer_s),
            reset_jump_s=self.reset_jump_s,
            uncertainty=self.uncertainty,
        )

    def decimation(self, model_rate_hz: float) -> int:
        """Predict every n-th grid step: n = model rate / rate_hz (rate_hz 0 = every step)."""
        if self.rate_hz == 0.0:
            return 1
        n = model_rate_hz / self.rate_hz
        if not (1.0 - 1e-9 <= n <= MAX_DECIMATION + 1e-6) or abs(n - round(n)) > 1e-6:
            raise ValueError(
                f"rate_hz {self.rate_hz} must be the model's rate ({model_rate_hz} Hz) divided "
                f"by an integer from 1 to {MAX_DECIMATION}, or 0 for the model's rate"
            )
        return round(n)


def _field(name: str) -> str:
    """The PredictorNodeParams field of a ROS parameter ('adapt.enabled' -> adapt_enabled)."""
    return name.replace(".", "_")


def _spec(name: str, description: str, low: float | None = None, high: float | None = None,
          runtime: bool = False) -> ParamSpec:
    default = PredictorNodeParams.__dataclass_fields__[_field(name)].default
    assert isinstance(default, bool | int | float | str), name
    return ParamSpec(name, default, description, low, high, runtime)


PARAMS: tuple[ParamSpec, ...] = (
    _spec("model_path", "model file (.npz) written by `asgp train`"),
    _spec("horizon_steps", "k, steps predicted ahead; 0 = use horizon_s", 0, 200, runtime=True),
    _spec("horizon_s", "prediction horizon in seconds when horizon_steps is 0", 0.1, 40.0,
          runtime=True),
    _spec("rate_hz", "prediction rate; 0 = the model's grid rate, else that rate / an integer",
          0.0, 100.0),
    _spec("joy_topic", "joystick input (sensor_msgs/Joy)"),
    _spec("vo_topic", "VO velocity input (TwistStamped, or Odometry with vo_type odometry)"),
    _spec("vo_type", "'twist' (geometry_msgs/TwistStamped) or 'odometry' (nav_msgs/Odometry)"),
    _spec("plan_topic", "planned future joystick (trajectory_msgs/JointTrajectory, joints "
          "forward and turn)"),
    _spec("override_topic", "overrides sent to the chair (sensor_msgs/Joy, the shared-control "
          "layer's or a planner's): adaptation learns nothing from the steps they may have "
          "driven; '' for none"),
    _spec("applied_topic", "the board's output as the serial bridge measures it "
          "(sensor_msgs/Joy): while it arrives it feeds the predictor instead of joy_topic "
          "and the modelled override; '' for none"),
    _spec("override_paths", "predict from the override while the board applies it (as the "
          "serial bridge and the board's watchdog would), not from the user's stick",
          runtime=True),
    _spec("override_timeout_s", "the serial bridge's override_timeout: it writes an override "
          "to the board until this long after the earlier of its stamp and its arrival",
          0.02, 1.0, runtime=True),
    _spec("path_topic", "predicted path output; ellipses on <path_topic>/uncertainty"),
    _spec("joy_axes", "Joy axes of the forward and turn (+ left) deflections, 'FWD,TURN', '-' "
          "flips a sign (as `asgp train --joy-axes`)"),
    _spec("joy_timeout_s", "no prediction when the joystick is older than this", 0.01, 60.0,
          runtime=True),
    _spec("vo_timeout_s", "no prediction when VO is older than this", 0.01, 60.0, runtime=True),
    _spec("plan_timeout_s", "ignore a plan older than this (hold the command)", 0.01, 60.0,
          runtime=True),
    _spec("buffer_s", "history kept for resampling; at least the model's lags x dt, the "
          "stale/held-VO rules' look-back and two VO gaps (3.4 s for the committed tile "
          "model; a shorter one is refused), more while adapting at a long horizon",
          1.0, 600.0, runtime=True),
    _spec("reset_jump_s", "a clock or stamp going back by more than this resets the buffers",
          0.01, 60.0, runtime=True),
    _spec("base_frame", "frame of the chair (paths in it are relative to the pose at t0); "
          "VO twists in another frame are refused (an empty frame is taken as this one)"),
    _spec("odom_frame", "odometry frame"),
    _spec("path_frame", "'base' (base_frame at the prediction time) or 'odom' (needs odometry)"),
    _spec("uncertainty", "'linear', 'mc' or 'none' uncertainty propagation", runtime=True),
    _spec("publish_uncertainty", "publish the 95% ellipses", runtime=True),
    _spec("diagnostics_period_s", "diagnostics period", 0.1, 60.0),
    _spec("joy_poll_period_s", "the joystick topics are read in batches this often (and "
          "before every VO message, override and watchdog check, and every 10 ms while a "
          "step waits for the joystick only), not at each message, which cost the "
          "executor's wake-up; 0 = at each message, else at least 0.005", 0.0, 1.0),
    *adapt_params.ADAPT_PARAMS,
)
SPECS: dict[str, ParamSpec] = {spec.name: spec for spec in PARAMS}


class _RateMeter:
    """Arrivals per second over the last few seconds (for diagnostics)."""

    def __init__(self, window_s: float = 5.0) -> None:
        self.window_s = window_s
        self.times: deque[float] = deque()

    def tick(self, t: float) -> None:
        self.times.append(t)
        while self.times and self.times[0] < t - self.window_s:
            self.times.popleft()

    def rate(self, now: float) -> float:
        """The arrivals' rate, measured up to ``now``: it falls once they stop (over the
        span of the arrivals kept, it read the old rate until the last left the window)."""
        while self.times and self.times[0] < now - self.window_s:
            self.times.popleft()
        if len(self.times) < 2:
            return 0.0
        return (len(self.times) - 1) / max(now - self.times[0], self.times[-1] - self.times[0],
                                           1e-9)


class PredictorNode(Node):
    """The online predictor (see the module docstring).

    Raises:
        StartupError: missing or invalid model file, invalid parameters.
    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self._clock_reader = runtime.ClockReader(self, lambda: self.predictor)
        try:
            self._setup()
        except (StartupError, StartupInterruptedError):
            self.destroy_node()
            raise

    def _setup(self) -> None:
        try:
            values = declare(self, PARAMS)
            self.params = PredictorNodeParams(
                **{_field(k): v for k, v in check_values(PARAMS, values).items()})
            check_topics(self.resolve_topic_name, joy_topic=self.params.joy_topic,
                         applied_topic=self.params.applied_topic,
                         override_topic=self.params.override_topic)
            # beside the path as remapped ('-r predicted_path:=/viz/path' moves both)
            ellipses = topic_beside(self.resolve_topic_name, self.params.path_topic,
                                    "uncertainty")
            if (problem := topic_name_problem(self.resolve_topic_name, ellipses)) is not None:
                # (a valid path_topic of 245 characters: its ellipses' topic is too long)
                raise ValueError(f"parameter path_topic: the ellipses' topic {ellipses!r} is "
                                 f"not a valid topic name ({problem})")
        except (ValueError, TypeError) as exc:
            raise StartupError(f"invalid parameters: {exc}") from exc
        p = self.params

        self.model = self._load_model(p.model_path)
        rate = float(self.model.resample_config.rate_hz)
        self.joy_axes = parse_joy_axes(p.joy_axes, "joy_axes")
        try:
            self.every_n = p.decimation(rate)
            k = p.steps(rate)
            # a buffer too short for the model's window and stale-VO rules is refused (a
            # 2 s one let stale VO drive paths)
            if (problem := Predictor.buffer_problem(self.model, k, None, p.buffer_s)):
                raise ValueError(problem)
            # adapting, the buffer holds at least the history adaptation needs (a long
            # horizon needs more than the default buffer_s)
            self.predictor, self._adapt_unavailable = adapt_params.make_predictor(
                self, lambda adapt: Predictor(self.model, p.predictor_config(
                    rate, Predictor.buffer_for(self.model, k, adapt, 0.0)), adapt=adapt),
                p.adapt_settings())
            if self.predictor.config.buffer_s > p.buffer_s:
                self.get_logger().info(
                    f"buffer_s {p.buffer_s:g} s raised to {self.predictor.config.buffer_s:.1f}"
                    " s: the history adaptation needs at this horizon")
        except ValueError as exc:
            raise StartupError(str(exc)) from exc

        self._last_step: int | None = None  # newest grid step a prediction was tried for
        self._last_result: Prediction = Prediction(False, Reason.NO_INPUT, "starting")
        self._published_step: int | None = None
        self._markers_shown = False
        self._latency_ms: deque[float] = deque(maxlen=1000)
        # VO callback -> path published, two of its parts (the prediction; the path's
        # message made and published) and what follows it (the ellipses' message)
        self._predict_ms: deque[float] = deque(maxlen=1000)
        self._path_ms: deque[float] = deque(maxlen=1000)
        self._ellipses_ms: deque[float] = deque(maxlen=1000)
        self._joy_rate = _RateMeter()
        self._vo_rate = _RateMeter()
        self._paths_published = 0
        self._markers_made = 0
        self._poses_other_frame = 0  # odometry poses not taken: another parent frame
        self._plan_problem = ""  # why the last plan was not taken, if it was not
        self._bad_messages = 0
        self._vo_frame = conv.VelocityFrameCheck(p.base_frame)  # twists in another frame
        self._resets_seen = 0
        # the overrides as the serial bridge takes them (on this node's clock)
        self._gate = OverrideGate()
        self._joy_overridden = 0  # joystick samples replaced by an override
        self._joy_source = JoySource(lambda: self.predictor.config.reset_jump_s)

        reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        # endpoints without rclpy's per-endpoint event handlers, their peers checked at the
        # diagnostics period instead (qos_watch: the handlers cost CPU at every message)
        self.qos_watch = watch = QosWatch(self)
        self.path_pub = watch.publisher(Path, p.path_topic, reliable)
        self.marker_pub = watch.publisher(MarkerArray, ellipses, reliable)
        self.diag_pub = watch.publisher(DiagnosticArray, topics.DIAGNOSTICS, reliable)
        # the joystick topics at the board's 100 Hz: read in batches (polled)
        self.polled = PolledInputs(self, watch, p.joy_poll_period_s)
        # the topics as the node uses them (namespace and remaps applied), by parameter: what
        # it says names these (the parameters' own names were said under a remap)
        self._topic: dict[str, str] = {"path_topic": self.path_pub.topic_name}
        self._topic["joy_topic"] = self.polled.subscription(
            Joy, p.joy_topic, self._on_joy, qos_profile_sensor_data).topic_name
        # the quick reads of a step waiting for the joystick (_await_joystick); one at a time
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        # (none when the batches come every tick anyway: each wait would end in a timeout)
        quick = self.polled.timer is not None and self.polled.period_s > JOY_WAIT_TICK_S
        self._joy_wait_timer = None if not quick else self.create_timer(
            JOY_WAIT_TICK_S, self._on_joy_wait, clock=steady, autostart=False)
        self._joy_wait_until = 0.0
        self._joy_wait_blocked_until = 0.0
        self._joy_waits = 0
        self._joy_wait_timeouts = 0
        if p.applied_topic.strip():
            self._topic["applied_topic"] = self.polled.subscription(
                Joy, p.applied_topic, self._on_joy_applied, qos_profile_sensor_data
            ).topic_name
        if p.vo_type == "twist":
            vo_sub = watch.subscription(TwistStamped, p.vo_topic, self._on_twist,
                                        qos_profile_sensor_data)
        else:
            vo_sub = watch.subscription(Odometry, p.vo_topic, self._on_odometry,
                                        qos_profile_sensor_data)
        self._topic["vo_topic"] = vo_sub.topic_name
        self._topic["plan_topic"] = watch.subscription(
            JointTrajectory, p.plan_topic, self._on_plan, reliable).topic_name
        if p.override_topic.strip():
            self._topic["override_topic"] = watch.subscription(
                Joy, p.override_topic, self._on_override, qos_profile_sensor_data).topic_name
        runtime.guard_sim_clock(self)
        pacing = runtime.pacing_clock(self)
        self.watchdog = self.create_timer(1.0 / rate, self._on_watchdog, clock=pacing)
        self.diag_timer = self.create_timer(p.diagnostics_period_s, self._publish_diagnostics,
                                            clock=pacing)
        # adaptation's learning, a moment after each path (see _maybe_predict); one-shot
        self._learn_timer = self.create_timer(min(LEARN_DELAY_S, 0.25 / rate),
                                              self._on_learn_timer, clock=pacing,
                                              autostart=False)
        adapt_params.reset_service(self, self.predictor, self._adapt_unavailable)
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        adapting = adapt_params.describe(p.adapt_values(), self.predictor.adapt_settings)
        if adapting:
            self.get_logger().info(adapting)
        self.get_logger().info(
            f"model {p.model_path} ({self.model.kind}, lags {self.model.feature_config.lags}, "
            f"{rate:g} Hz); horizon {self.predictor.config.horizon_steps} steps; "
            f"inputs {self._topic['joy_topic']}, {self._topic['vo_topic']} ({p.vo_type}), "
            f"plan {self._topic['plan_topic']}; output {self._topic['path_topic']} (ellipses "
            f"{self.marker_pub.topic_name}) in "
            f"{p.base_frame if p.path_frame == 'base' else p.odom_frame}"
        )

    def _load_model(self, path: str) -> MotionModel:
        """``load_model`` in a worker thread; the main thread returns as soon as a stop
        signal arrives or the context shuts down, whatever the read is doing.

        Raises:
            StartupError: the file does not load. StartupInterruptedError: shutdown requested.
        """
        self.get_logger().info(f"loading model {path}")
        loaded: list[MotionModel] = []
        failed: list[BaseException] = []  # handed to the main thread
        done = threading.Event()

        def work() -> None:
            try:
                loaded.append(load_model(path))
            except BaseException as exc:
                failed.append(exc)
            finally:
                done.set()

        threading.Thread(target=work, name="model_loader", daemon=True).start()
        while not done.wait(_LOAD_POLL_S):
            if not self.context.ok() or runtime.stop_requested():
                raise StartupInterruptedError(f"shutdown requested while loading {path}")
        if failed:
            error = failed[0]
            if isinstance(error, ModelFileError | OSError | ValueError):
                raise StartupError(f"cannot load the model: {error}") from error
            raise error
        return loaded[0]

    # ---- parameters ------------------------------------------------------------------

    def _validate_parameters(self, params: list[Parameter]) -> SetParametersResult:
        why = sim_time_change(self, params)
        if why is not None:
            return SetParametersResult(successful=False, reason=why)
        changes = {prm.name: prm.value for prm in params
                   if prm.name in SPECS and (SPECS[prm.name].runtime or is_change(self, prm))}
        if not changes:
            return SetParametersResult(successful=True)
        try:
            for name, value in changes.items():
                if not SPECS[name].runtime:
                    raise ValueError(f"{name} is read at start-up: restart the node to change it")
                changes[name] = check_value(SPECS[name], value)
            candidate = replace(self.params, **{_field(k): v for k, v in changes.items()})
            rate = self.model.resample_config.rate_hz
            # the model's window and stale-VO look-back, and adaptation at the new horizon
            if "buffer_s" in changes and (problem := Predictor.buffer_problem(
                    self.model, candidate.steps(rate), self.predictor.adapt_settings,
                    candidate.buffer_s)) is not None:
                raise ValueError(problem)
            candidate.predictor_config(rate)
        except (ValueError, TypeError) as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _apply_parameters(self, params: list[Parameter]) -> None:
        changes = {prm.name: check_value(SPECS[prm.name], prm.value)
                   for prm in params if prm.name in SPECS}
        if not changes:
            return
        self.params = replace(self.params, **{_field(k): v for k, v in changes.items()})
        rate = self.model.resample_config.rate_hz
        # adapting, a longer horizon needs a longer history: the buffer grows with it
        self.predictor.config = self.params.predictor_config(rate, Predictor.buffer_for(
            self.model, self.params.steps(rate), self.predictor.adapt_settings, 0.0))
        self.get_logger().info(f"parameters changed: {changes}")

    # ---- input -----------------------------------------------------------------------

    def _now(self) -> float | None:
        """Node clock in seconds; None before a simulated clock has started. A step back
        of the clock resets the predictor (``runtime.ClockReader``)."""
        return self._clock_reader.now()

    def _warn_rejected(self) -> None:
        stats = self.predictor.stats
        self.get_logger().warning(
            f"refusing input: {stats.last_rejected} ({sum(stats.rejected.values())} refused "
            "so far)", throttle_duration_sec=5.0)

    def _stamp(self, t: float, now: float | None) -> float:
        """Header stamp, or the arrival time when the sender left the stamp at zero."""
        if t > 0.0 or now is None:
            return t
        return now

    def _read_joy(self, msg: Joy, topic: str, now: float | None
                  ) -> tuple[float, np.ndarray] | None:
        """(stamp, [forward, turn]) of a Joy message with ``joy_axes``, or None (counted)."""
        try:
            t, command = conv.joy_command(msg, self.joy_axes)
        except ValueError as exc:
            self._bad_messages += 1
            self.get_logger().warning(f"{topic}: {exc}", throttle_duration_sec=5.0)
            return None
        return self._stamp(t, now), command

    def _on_joy(self, msg: Joy, arrival: Arrival) -> None:
        now = arrival.now
        read = self._read_joy(msg, self._topic["joy_topic"], now)
        if read is None:
            return
        t, command = read
        self._joy_rate.tick(arrival.monotonic)
        if self._joy_source.measured(now):
            return  # the board's measured output feeds (_on_joy_applied)
        applied = self._applied(command, t, now)
        if applied is not None and np.all(np.isfinite(command)):
            command = applied
            self._joy_overridden += 1
        self._feed_joy(t, command, arrival, measured=False)

    def _on_joy_applied(self, msg: Joy, arrival: Arrival) -> None:
        """What the board drives the chair with, measured: it feeds while it arrives."""
        now = arrival.now
        read = self._read_joy(msg, self._topic["applied_topic"], now)
        if read is None:
            return
        if joy_problem(*read[1]) is not None:  # no measurement (NaN, 3.0): refused and
            self._feed_joy(*read, arrival, measured=True)  # counted, and joy goes on feeding
        elif self._joy_source.take_measured(read[0], now):
            self._feed_joy(*read, arrival, measured=True)

    def _feed_joy(self, t: float, command: np.ndarray, arrival: Arrival,
                  measured: bool) -> None:
        if not self.predictor.feed_joy(t, command, now=arrival.now):
            self._warn_rejected()
            return
        self._joy_source.fed(t, measured)
        self._maybe_predict(arrival.now, arrival.perf)

    def _applied(self, user: np.ndarray, t: float, now: float | None) -> np.ndarray | None:
        """The override the board drives with instead of ``user`` read at ``t``, or None:
        the bridge writes it while fresh, the board applies each frame for its watchdog."""
        gate = self._gate
        if not self.params.override_paths or gate.command is None or now is None:
            return None
        if now < gate.arrival:  # the clock went back: that override is of another time
            self._gate = OverrideGate()
            return None
        until = gate.fresh_until(self.params.override_timeout_s) + BOARD_WATCHDOG_S
        return applied_command(user, np.array(gate.command), t - gate.arrival,
                               until - gate.arrival)

    def _on_override(self, msg: Joy) -> None:
        """An override sent to the chair. Paths are predicted from it while the board may
        apply it (``override_paths``); when adapting, the steps it may have driven are
        not learnt from (what drove the chair is modelled, not measured)."""
        now = self._now()
        # the joystick samples that came before it go first, with the gate they came under
        # (read after now: every sample read later arrived after it, on either clock)
        self.polled.drain()
        try:  # what the bridge writes to the board: it refuses the same messages, so a
            # malformed one never drove the chair (read as joy is: joy_axes)
            command = conv.joy_to_override(msg, self.joy_axes)
        except ValueError as exc:
            self._bad_messages += 1
            self.get_logger().warning(f"ignoring {self._topic['override_topic']}: {exc}",
                                      throttle_duration_sec=5.0)
            return
        stamp = conv.stamp_to_seconds(msg.header.stamp)
        if not self.predictor.feed_override(self._stamp(stamp, now), now=now):
            self._warn_rejected()
            return  # not kept out of learning, so not predicted from either
        if now is None:
            return
        # as the bridge: stamped too long ago or too far ahead, it is never written
        self._gate.offer(command, stamp if stamp != 0.0 else None, now, now,
                         self.params.override_timeout_s)

    def _on_twist(self, msg: TwistStamped) -> None:
        arrival = time.perf_counter()
        self.polled.drain()  # the step's joystick samples
        if not self._vo_frame.ok(msg, self.get_logger()):
            return
        now = self._now()
        t, vel = conv.twist_stamped_to_sample(msg)
        self._vo_rate.tick(time.monotonic())
        if not self.predictor.feed_vo(self._stamp(t, now), vel, now=now):
            self._warn_rejected()
            return
        self._maybe_predict(now, arrival)
        self._await_joystick(now)

    def _joystick_behind(self, now: float) -> bool:
        """A step the node will predict from (a multiple of ``every_n``, see
        ``_maybe_predict``) waits for a joystick sample only, and the joystick is not stale
        (a silent stick is the watchdog's to report, not worth reads every tick)."""
        joy_newest, _ = self.predictor.newest_stamps()
        return (self.predictor.joystick_behind(self.every_n)
                and now - joy_newest <= self.params.joy_timeout_s)

    def _await_joystick(self, now: float | None) -> None:
        """After a VO message: if its step waits for the joystick only, read the joystick
        every JOY_WAIT_TICK_S until the sample comes (its handler predicts), not at the
        next batch, ``joy_poll_period_s`` away."""
        timer = self._joy_wait_timer
        wall = time.monotonic()
        if timer is None or now is None or not timer.is_canceled() \
                or wall < self._joy_wait_blocked_until or not self._joystick_behind(now):
            return
        self._joy_waits += 1
        self._joy_wait_until = wall + min(JOY_WAIT_MAX_S, self.polled.period_s)
        timer.reset()

    def _on_joy_wait(self) -> None:
        self.polled.drain()
        now = self._now()
        wall = time.monotonic()
        behind = now is not None and self._joystick_behind(now)
        if behind and wall < self._joy_wait_until:
            return
        assert self._joy_wait_timer is not None
        self._joy_wait_timer.cancel()
        if behind:  # the sample did not come in time: a later stick, not a slower one
            self._joy_wait_timeouts += 1
            self._joy_wait_blocked_until = wall + JOY_WAIT_BACKOFF_S

    def _on_odometry(self, msg: Odometry) -> None:
        arrival = time.perf_counter()
        self.polled.drain()  # the step's joystick samples
        if not self._vo_frame.ok(msg, self.get_logger()):
            return
        now = self._now()
        t, vel, ok, pose = conv.odometry_to_sample(msg)
        t = self._stamp(t, now)
        self._vo_rate.tick(time.monotonic())
        # poses in another frame are not taken (the velocities are the child frame's)
        problem = conv.pose_frame_problem(msg, self.params.odom_frame) if ok else None
        if problem is not None:
            self._poses_other_frame += 1
            self.get_logger().warning(f"{self._topic['vo_topic']}: {problem}",
                                      throttle_duration_sec=5.0)
        elif ok and not self.predictor.feed_pose(t, *pose):
            self._warn_rejected()
        if not self.predictor.feed_vo(t, vel, ok=ok, now=now):
            self._warn_rejected()
            return
        self._maybe_predict(now, arrival)
        self._await_joystick(now)

    def _on_plan(self, msg: JointTrajectory) -> None:
        now = self._now()
        if now is None:
            return
        try:
            start, plan = conv.plan_from_trajectory(msg, self.predictor.dt, arrival=now)
        except ValueError as exc:  # malformed message
            self._bad_messages += 1
            self._plan_problem = f"malformed plan: {exc}"
            self.get_logger().warning(f"ignoring {self._topic['plan_topic']}: {exc}",
                                      throttle_duration_sec=5.0)
            return
        try:
            self.predictor.set_plan(plan, start, now=now)
            self._plan_problem = ""
        except online.RejectedInputError as exc:  # counted with its reason by the predictor
            self._plan_problem = f"plan refused: {exc}"
            self._warn_rejected()
        except ValueError as exc:
            self._bad_messages += 1
            self._plan_problem = f"plan refused: {exc}"
            self.get_logger().warning(f"ignoring {self._topic['plan_topic']}: {exc}",
                                      throttle_duration_sec=5.0)

    # ---- prediction ------------------------------------------------------------------

    def _maybe_predict(self, now: float | None, arrival: float) -> None:
        """Predict once per newly completed grid step; with rate_hz (every n-th step), once
        the completed steps reach a multiple of n (the newest step may have passed it: a
        VO slower than the grid, or a lost frame, completes two steps at once)."""
        if now is None:
            return
        if self.predictor.stats.resets != self._resets_seen:
            self._resets_seen = self.predictor.stats.resets
            self._last_step = None
            self._published_step = None
        step = self.predictor.ready_step()
        if step is None or (self._last_step is not None and step <= self._last_step):
            return
        last = step - 1 if self._last_step is None else self._last_step
        self._last_step = step
        if step // self.every_n == last // self.every_n:  # no multiple in (last, step]
            if self.predictor.adapting:
                # adaptation learns from every step, predicted or not: with only the
                # predicted ones (rate_hz 1 at 5 Hz), its online calibration checked none
                if not self._learn_timer.is_canceled():
                    self._on_learn_timer()
                self._observe(now)
            return
        if not self._learn_timer.is_canceled():
            # the last path's learning is still to come (a step closer than LEARN_DELAY_S
            # after it: a replay catching up): it comes first, as each prediction is
            # checked against its outcome only if learnt before the next one
            self._on_learn_timer()
        started = time.perf_counter()
        try:
            result = self.predictor.predict(now, learn=False)
        except (ValueError, np.linalg.LinAlgError) as exc:  # a numerical failure of one step
            result = Prediction(False, Reason.PREDICTION_ERROR, f"{type(exc).__name__}: {exc}")
            self.get_logger().error(f"prediction failed at step {step}: {result.detail}",
                                    throttle_duration_sec=5.0)
        predicted = time.perf_counter()
        if result.ok and result.times[-1] >= conv.MAX_STAMP_S + 1:
            # a clock (or a bag's stamps) within a horizon of 2038: no message can stamp it
            result = replace(result, ok=False, reason=Reason.INVALID_TIME,
                             detail=f"the path ends at {result.times[-1]:.1f} s, beyond a "
                                    "message stamp's int32 seconds (2038)")
        self._last_result = result
        if not result.ok:  # paths stopped: the last one's ellipses go (RViz), whatever why
            self._clear_markers(now)
        if not result.ok or (self._published_step is not None
                             and result.step <= self._published_step):
            self._learn()
            return
        path_out = self._publish(result)
        self._published_step = result.step
        if path_out is not None:
            self._latency_ms.append(1e3 * (path_out - arrival))
            self._predict_ms.append(1e3 * (predicted - started))
            self._path_ms.append(1e3 * (path_out - predicted))
        if not self.predictor.adapting:
            self._learn()  # nothing to learn: no timer wakes the node for it
            return
        # learning (a few ms with adaptation) waits a moment: the path's subscribers, woken
        # by it, get the CPU first; it always comes before the next step's prediction
        self._learn_timer.reset()

    def _on_learn_timer(self) -> None:
        self._learn_timer.cancel()
        self._learn()

    def _observe(self, now: float) -> None:
        """Adaptation's work at a step not predicted (``rate_hz`` below the model's)."""
        try:
            self.predictor.observe(now)
        except (ValueError, np.linalg.LinAlgError) as exc:  # never let learning stop paths
            self.get_logger().error(f"adaptation failed: {type(exc).__name__}: {exc}",
                                    throttle_duration_sec=5.0)

    def _learn(self) -> None:
        """Adaptation's work for the steps so far (absorbing the settled ones, checking the
        predictions whose outcomes arrived); never in a path's latency."""
        try:
            self.predictor.learn()
        except (ValueError, np.linalg.LinAlgError) as exc:  # never let learning stop paths
            self.get_logger().error(f"adaptation failed: {type(exc).__name__}: {exc}",
                                    throttle_duration_sec=5.0)

    def _publish(self, result: Prediction) -> float | None:
        """Publish the path, then its ellipses; the ``perf_counter`` time when the path was
        out (None when there was no path to publish)."""
        p = self.params
        pose, cov = result.pose, result.pos_cov
        frame = p.base_frame
        if p.path_frame == "odom":
            if result.origin is None:
                self._last_result = replace(result, ok=False, reason=Reason.NO_POSE,
                                            detail="no odometry pose at the prediction time")
                self._clear_markers(result.t0)
                return None
            pose, cov = online.to_frame(pose, cov, result.origin)
            frame = p.odom_frame
        self.path_pub.publish(conv.path_cdr(pose, result.times, frame, result.t0))
        path_out = time.perf_counter()
        self._paths_published += 1
        # the ellipses are made and sent only while something subscribes to them (RViz
        # on a laptop beside the chair, say): their message took up to 1.4 ms (p99) after
        # each path
        if self._making_ellipses():
            ellipses = online.confidence_ellipses(cov)
            self.marker_pub.publish(
                conv.ellipse_markers(pose[:, :2], ellipses, frame, result.t0))
            self._markers_shown = True
            self._markers_made += 1
            self._ellipses_ms.append(1e3 * (time.perf_counter() - path_out))
        else:  # publish_uncertainty switched off (or 'none'): the last path's ellipses go
            self._clear_markers(result.t0)
        return path_out

    def _making_ellipses(self) -> bool:
        """Ellipses are made for each path: publish_uncertainty, an uncertainty propagated
        (with 'none' the covariances are zero: no 95 % ellipse is known), and something
        subscribes."""
        return self.params.publish_uncertainty and self.params.uncertainty != "none" \
            and self.marker_pub.get_subscription_count() > 0

    def _clear_markers(self, stamp: float) -> None:
        """Clear the ellipses last sent (in RViz), once."""
        if self._markers_shown:
            self.marker_pub.publish(conv.ellipse_markers(
                np.zeros((0, 2)), np.zeros((0, 3)), self._output_frame(), stamp))
            self._markers_shown = False

    def _on_watchdog(self) -> None:
        self.polled.drain()
        now = self._now()
        if now is None:
            self._last_result = Prediction(False, Reason.NO_INPUT, "waiting for /clock")
            return
        bad = self.predictor.status(now)
        if bad is not None:
            self._last_result = bad
            self._clear_markers(now)  # the last path's ellipses, in RViz
            return
        self._maybe_predict(now, time.perf_counter())

    def _output_frame(self) -> str:
        return self.params.base_frame if self.params.path_frame == "base" else \
            self.params.odom_frame

    # ---- diagnostics -----------------------------------------------------------------

    def diagnostic_status(self) -> DiagnosticStatus:
        """The node's state: prediction, why none, input rates and ages, latency."""
        now = self._now()
        result = self._last_result
        if result.ok and now is not None:  # the inputs may have gone bad since that path
            result = self.predictor.status(now) or result
        stats = self.predictor.stats
        joy_age, vo_age = self.predictor.input_ages(now) if now is not None \
            else (math.inf, math.inf)
        lat = np.asarray(self._latency_ms)
        wall = time.monotonic()
        if not self._making_ellipses():  # ellipses_p99_ms: nan, not a past viewer's times
            self._ellipses_ms.clear()

        def age(seconds: float) -> str:
            return f"{seconds:.3f}" if math.isfinite(seconds) else "inf"

        values = {
            "reason": result.reason.value,
            "joy_rate_hz": f"{self._joy_rate.rate(wall):.1f}",
            "vo_rate_hz": f"{self._vo_rate.rate(wall):.1f}",
            "joy_age_s": age(joy_age),
            "vo_age_s": age(vo_age),
            "last_latency_ms": f"{lat[-1]:.3f}" if lat.size else "nan",
            "latency_p99_ms": _p99(self._latency_ms),
            "predict_p99_ms": _p99(self._predict_ms),
            "path_p99_ms": _p99(self._path_ms),
            "ellipses_p99_ms": _p99(self._ellipses_ms),
            "paths_published": str(self._paths_published),
            "ellipses_published": str(self._markers_made),
            "poses_other_frame": str(self._poses_other_frame),
            "plan_problem": self._plan_problem or "none",
            "horizon_steps": str(self.predictor.config.horizon_steps),
            "dropped_nonfinite": str(stats.dropped_nonfinite),
            "dropped_overflow": str(stats.dropped_overflow),
            "rejected": ", ".join(f"{code}={n}" for code, n in sorted(stats.rejected.items()))
            or "none",
            "last_rejected": stats.last_rejected,
            "out_of_order": str(stats.out_of_order),
            "bad_messages": str(self._bad_messages),
            **self._vo_frame.values(),
            "buffer_resets": str(stats.resets),
            "overrides_seen": str(stats.overrides),
            "joy_overridden": str(self._joy_overridden),
            "joy_measured": str(self._joy_source.measured_samples),
            "overrides_late": str(stats.overrides_late),
            "last_reset": self.predictor.last_reset_detail,
            "plan_used": str(result.from_plan),
            "qos_mismatch": self.qos_watch.summary(),
            **self.polled.values(),
            "joy_waits": str(self._joy_waits),
            "joy_wait_timeouts": str(self._joy_wait_timeouts),
        }
        values.update(adapt_params.diagnostic_values(
            self.predictor.adaptation, self._adapt_unavailable,
            ellipses=self.params.uncertainty != "none"))
        message = (f"predicting (t0 {result.t0:.2f} s)" if result.ok
                   else f"no path: {result.reason}: {result.detail}")
        level = "OK" if result.ok else "WARN"
        recent = list(self._predict_ms)[-20:]
        period_ms = 1e3 * self.every_n * self.predictor.dt
        if len(recent) >= 5 and float(np.median(recent)) > period_ms:
            # (uncertainty 'mc' over a 40 s horizon took 950 ms a path, at 5 Hz)
            level = "WARN"
            message += (f"; a prediction takes {float(np.median(recent)):.0f} ms, longer than "
                        f"the {period_ms:.0f} ms between paths: they fall behind (a long "
                        "horizon, uncertainty 'mc'?)")
        level, message = self.qos_watch.escalate(level, message)
        return conv.diagnostic_status(
            runtime.status_name(self, f"{self.get_name()}: prediction"), level, message,
                                      hardware_id=self.params.model_path, values=values)

    def _publish_diagnostics(self) -> None:
        self.polled.drain()
        self.qos_watch.check()
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.status = [self.diagnostic_status()]
        self.diag_pub.publish(msg)


def _p99(ms: deque[float]) -> str:
    return f"{np.percentile(np.asarray(ms), 99):.3f}" if ms else "nan"


def main(args: list[str] | None = None) -> int:
    """Run the node until SIGINT or SIGTERM (:func:`asgp_ros.nodes.runtime.run`); a signal
    while the model loads ends the start-up. Exit code 1: a refused model or parameter."""
    # The rollout works on small matrices: extra BLAS threads only add contention with the
    # other nodes on the wheelchair laptop (a loaded 2-core machine ran batched rollouts
    # about twice as slowly with OpenBLAS's default two threads).
    threadpool_limits(limits=1)
    return runtime.run(PredictorNode, args, name=NODE_NAME, refused=(StartupError,),
                       interrupted=(StartupInterruptedError,))


if __name__ == "__main__":
    sys.exit(main())
