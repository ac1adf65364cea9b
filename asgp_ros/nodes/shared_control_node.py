"""ROS 2 node: the shared-control safety layer.

Subscribes ``joy`` (the user's stick, from the bridge), the VO (``vo/twist``, or
nav_msgs/Odometry with ``vo_type: odometry``), ``scan`` (sensor_msgs/LaserScan) and/or
``map`` (nav_msgs/OccupancyGrid, in the odometry frame); keeps its own
:class:`~asgp_ros.core.online.Predictor`. At every model grid step it predicts the user's
path with the stick held and the probability of contact within the horizon
(:mod:`asgp_ros.core.collision`); above ``threshold`` it finds the smallest change of the
command that brings it back under (:func:`asgp_ros.core.shared_control.decide`) and
publishes it on ``joy_override`` at ``override_rate_hz`` while it is needed, and nothing
once the danger has passed (while it intervenes, every new scan is judged, once the inputs
waiting have been read: :meth:`SharedControlNode._want_decision`): the
bridge stops writing, and the board's 200 ms watchdog
hands the chair back to the user. The firmware also ignores an override while the user's
stick is neutral (in its neutral window: joy 0), and this node never sends one then; a stick
barely touched (within ``neutral_deadband``), which the board drives, is guarded by stopping
alone.

With ``memory_s`` > 0 (10 s by default; 0 turns it off) the scans' obstacles are remembered
that long (:mod:`asgp_ros.core.obstacle_memory`), carried along by matching each scan to a
keyframe scan (``memory_odometry: scan_matching``, the default: :mod:`asgp_ros.core.scan_match`,
independent of the VO's drift), or by dead
reckoning of the VO's twists or of ``memory_odom_topic``'s (``dead_reckoning``): what has
left the scanner's view, behind the chair, still counts when it turns. A refused match
(too little structure, a corridor), lost tracking or a gap empties the memory; the newest
scan alone is used then.

Publishes ``shared_control/status`` (diagnostic_msgs/DiagnosticStatus, one per decision:
what was done and why, probability before and after, change, solve time) and
``diagnostics``.

The predictor is fed the command the chair actually received: measured, from
``applied_topic`` (``joy_applied``, the serial bridge's reading of the board's output) while
it arrives (:mod:`asgp_ros.nodes.joy_source`); else as far as the layer can tell
(:func:`~asgp_ros.core.shared_control.applied_command`): its last override, until
``OVERRIDE_APPLIED_S`` after it (the bridge re-sends it and the board holds it that long,
also after the layer has stopped) while the user's stick is out of the board's neutral, else
the user's stick. Its velocity comes from the scans matched to each other while they match
and from the VO while they do not (``velocity_source: auto``, the default: a camera loses
its features in front of a wall, where a laser sees best), from the VO alone (``vo``), or
from the scans alone (``scan_matching``: each matched interval's twist, stamped with the
newer scan; a refused match is a lost sample).

The joystick topics, which the bridge publishes at the board's 100 Hz, are read in batches
(:mod:`asgp_ros.nodes.polled`), not by a wake-up of the executor per message: every
``joy_poll_period_s`` (0.25 s) and before every VO and scan message, watchdog check,
diagnostics message and override send (the override timer runs at ``override_rate_hz``,
intervening or not: the joystick is read at least that often), so that an override is never
sent after a neutral stick has arrived (``joy_poll_period_s: 0.0``: a callback per message).

Never on stale data: no prediction (stale joystick or VO, tracking lost), no fresh scan or
map, or an override older than ``hold_s`` (the node stalled) means no override.

With ``adapt.enabled`` (the ``adapt.*`` parameters of ``predictor_node``,
:mod:`asgp_ros.nodes.adaptation`) the predictor adapts online
(:mod:`asgp_ros.core.adaptive`): it learns after each decision has been acted on, nothing
from the steps the layer's overrides may have driven (the command applied is modelled, not
measured: training's rule for a bag's overrides), and ``~/reset_adaptation``
(std_srvs/Trigger) returns it to the trained model.

Run: ``shared_control_node --ros-args --params-file config/shared_control.yaml
-p model_path:=M.npz``
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import math
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import TwistStamped
from nav_msgs.msg import OccupancyGrid, Odometry
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)
from rclpy.subscription import Subscription
from sensor_msgs.msg import Joy, LaserScan
from threadpoolctl import threadpool_limits

from asgp_ros.common import topics
from asgp_ros.common.board import BOARD_NEUTRAL
from asgp_ros.common.paramspec import ParamSpec, check_values
from asgp_ros.core import collision
from asgp_ros.core.modelfile import ModelFileError, load_model
from asgp_ros.core.obstacle_memory import MEMORY_ODOMETRY, MemoryConfig, ScanMemory
from asgp_ros.core.online import Prediction, Predictor, PredictorConfig, horizon_steps
from asgp_ros.core.scan_match import (
    VELOCITY_SOURCES,
    ScanOdometer,
    VelocitySelector,
    memory_odometers,
)
from asgp_ros.core.shared_control import (
    OVERRIDE_APPLIED_S,
    CollisionCheck,
    Decision,
    SharedControlConfig,
    Why,
    applied_command,
    decide,
    is_neutral,
    judge_moved_stick,
)
from asgp_ros.core.streams import joy_problem
from asgp_ros.nodes import adaptation as adapt_params
from asgp_ros.nodes import conversions as conv
from asgp_ros.nodes import runtime
from asgp_ros.nodes.joy_source import JoySource, check_topics
from asgp_ros.nodes.parameters import declare, refuse_at_runtime
from asgp_ros.nodes.polled import Arrival, PolledInputs, period_problem, take_waiting
from asgp_ros.nodes.qos_watch import QosWatch
from asgp_ros.recording.bags import parse_joy_axes

NODE_NAME = "shared_control_node"

#: What a NaN range of the scans may mean (``scan_nan``): REP-117's erroneous reading, or
#: nothing in range (a source that does not follow REP-117's +inf for that).
SCAN_NAN = ("erroneous", "no_return")

#: A scan stamped more than this (s) after the node's clock is refused: a laser whose
#: clock runs ahead would otherwise look fresh long after it stopped, and be placed with
#: the chair's motion of a time that has not come (a clock synchronised by NTP or PTP is
#: within milliseconds).
SCAN_LEAD_S = 0.1
#: Most cells of a map the layer reads (a 100 m square at 5 cm): its distance field and
#: obstacle tree are built in the map's callback, where nothing else runs (1.6 s for 4
#: million unknown cells on a 2-core laptop; 24 s and 3 GB for 49 million).
MAX_MAP_CELLS = 4_000_000
#: Faster than this (m/s, rad/s), a scan whose ranges are bit for bit the last one's is a
#: frozen laser driver's: the scene cannot stand still while the chair moves.
FROZEN_SCAN_SPEED = 0.05
FROZEN_SCAN_YAW_RATE = 0.05
#: ... and has at least this many returns (an open space's scan, no return at all, is the
#: same every time, and holds no obstacle to freeze).
FROZEN_SCAN_RETURNS = 10
#: The user's stick sample is fresh, for re-sending an override, from this far (s) ahead
#: of the node's clock to ``joy_timeout_s`` behind it: one stamped further ahead (a bridge
#: whose clock runs ahead) would look fresh after the stick's messages stopped.
JOY_LEAD_S = 0.1
#: While intervening, a stick moved by more than this (deflection, either axis) since the
#: decision is judged again at the next override send, never the old decision re-sent: a
#: forward push went on after the user pulled the stick back (0.05: above an ADC's noise
#: and a steady hand's tremor, which would only cost a decision).
STICK_CHANGE = 0.05
#: A rise (or fall) of an odometry pose's yaw variance (rad^2) by this much from one message
#: to the next is a re-initialisation (vo_node adds 1.0 after a tracking loss) or a restart:
#: far above what one step of dead reckoning adds. At the first pose a layer sees, a
#: variance this large (x, y or yaw) says the odometry may have re-initialised before.
POSE_JUMP_VARIANCE = 0.25
#: An odometry pose that moved further from the last than POSE_JUMP_M + POSE_JUMP_SPEED x
#: the time between them (m, m/s), or turned by more than POSE_JUMP_RAD + POSE_JUMP_RATE x
#: that time (rad, rad/s), jumped: the odometry restarted (a chair drives under 3 m/s and
#: turns under 4 rad/s; REP-105's odom frame is continuous).
POSE_JUMP_M = 0.5
POSE_JUMP_SPEED = 3.0
POSE_JUMP_RAD = 0.5
POSE_JUMP_RATE = 4.0
#: Before a decision, at most this many messages of each of the VO, odometry and scan
#: topics are read (their queues' depth, the sensor-data QoS's).
INPUT_QUEUE = 5


class StartupError(Exception):
    """The node cannot start (bad model file, inconsistent parameters)."""


def _spec(name: str, default: Any, text: str, low: float | None = None,
          high: float | None = None) -> ParamSpec:
    return ParamSpec(name, default, text, low, high)


_WENT_NEUTRAL = "the stick went neutral before the override was sent"

#: The layer's own parameters (SharedControlParams); the node also takes adapt.*.
LAYER_PARAMS: tuple[ParamSpec, ...] = (
    _spec("model_path", "", "model file from `asgp train` (required)"),
    _spec("horizon_s", 2.0, "prediction horizon (s)", 0.2, 10.0),
    _spec("threshold", 0.05, "probability of contact within the horizon above which the "
          "layer intervenes", 0.001, 0.5),
    _spec("neutral_deadband", 0.05, "a stick within this deflection (barely touched; the "
          "board still drives it) is guarded only by stopping, never steered; at joy 0 (the "
          "board's neutral) nothing is commanded", 0.0, 0.45),
    _spec("progress_weight", 0.5, "weight of forward progress given up (per m^2) against the "
          "command change squared", 0.0, 100.0),
    _spec("depth_tolerance", 0.002, "when every candidate is as likely to touch as the "
          "user's command: how much deeper (m) than the least-deepening candidate the user's "
          "command may take an obstacle into the footprint and still pass", 0.0, 0.5),
    _spec("obstacles", "laser", "obstacle source: 'laser' (scan_topic), 'grid' (map_topic) "
          "or 'both'"),
    _spec("joy_topic", topics.JOY, "the user's joystick (sensor_msgs/Joy)"),
    _spec("joy_axes", "0,1", "Joy axes of the forward and turn (+ left) deflections, "
          "'FWD,TURN', '-' flips a sign"),
    _spec("vo_topic", topics.VO_TWIST, "VO input (TwistStamped, or Odometry with vo_type "
          "odometry)"),
    _spec("vo_type", "twist", "'twist' or 'odometry' (needed with a map)"),
    _spec("scan_topic", topics.SCAN, "laser scan (sensor_msgs/LaserScan)"),
    _spec("map_topic", topics.MAP, "occupancy grid in the odometry frame "
          "(nav_msgs/OccupancyGrid)"),
    _spec("odom_frame", "odom", "frame of the odometry poses; a map must be in it"),
    _spec("base_frame", "base_link", "frame of the chair; VO twists (an odometry's child "
          "frame) in another frame are refused (an empty frame is taken as this one)"),
    _spec("override_topic", topics.JOY_OVERRIDE, "override output (sensor_msgs/Joy)"),
    _spec("applied_topic", topics.JOY_APPLIED, "the board's output as the serial bridge "
          "measures it (sensor_msgs/Joy): while it arrives it feeds the predictor instead of "
          "the user's stick with the modelled override; '' for none"),
    _spec("override_rate_hz", 20.0, "rate at which an override is re-sent while needed",
          5.0, 100.0),
    _spec("hold_s", 0.35, "an override is re-sent at most this long after its decision",
          0.05, 1.0),
    _spec("joy_timeout_s", 0.3, "no intervention when the joystick is older than this",
          0.01, 5.0),
    _spec("vo_timeout_s", 0.5, "no intervention when the VO is older than this", 0.01, 5.0),
    _spec("scan_timeout_s", 0.3, "a scan older than this is no obstacle source", 0.01, 5.0),
    _spec("laser_frame", "", "frame_id of the scans that laser_x/y/yaw describe; scans in "
          "another frame (a second laser on scan_topic) are refused ('': the first scan's, "
          "until scans in a second frame come: then none is taken)"),
    _spec("scan_nan", "erroneous", "what a NaN range of the scans means: 'erroneous' "
          "(REP-117: a reading that failed; a run of them counts as an obstacle at the nearer "
          "of the returns that bound it) or 'no_return' (a scan source that reports nothing "
          "in range as NaN, as depthimage_to_laserscan does: read as +inf, free)"),
    _spec("laser_x", 0.3, "laser position in the base frame, x (m)", -5.0, 5.0),
    _spec("laser_y", 0.0, "laser position in the base frame, y (m)", -5.0, 5.0),
    _spec("laser_yaw", 0.0, "laser yaw in the base frame (rad)", -math.pi, math.pi),
    _spec("laser_upside_down", False, "the laser is mounted upside down (rolled by pi about "
          "its x axis, laser_yaw where its x points): its scans are mirrored"),
    _spec("footprint_length", collision.DEFAULT_FOOTPRINT.length,
          "chair footprint length along x (m)", 0.1, 5.0),
    _spec("footprint_width", collision.DEFAULT_FOOTPRINT.width,
          "chair footprint width (m)", 0.1, 5.0),
    _spec("footprint_offset", collision.DEFAULT_FOOTPRINT.offset,
          "footprint centre ahead of the base frame's origin (m)", -2.5, 2.5),
    _spec("margin", 0.05, "safety margin added to every side of the footprint (m): the "
          "layer keeps the grown footprint off the obstacles", 0.0, 0.5),
    _spec("memory_s", 10.0, "the laser's obstacles are remembered this long, carried along "
          "by memory_odometry, so that what left the scanner's view (behind the chair) still "
          "counts; 0: no memory; none with obstacles 'grid' (a map holds what is behind). "
          "Only for odometry that drifts less than the margin over this time (scan matching "
          "does indoors)", 0.0, 600.0),
    _spec("memory_odometry", "scan_matching", "what carries the memory: 'scan_matching' "
          "(the scans matched to each other, asgp_ros.core.scan_match: millimetres over "
          "seconds indoors; a refused match empties the memory) or 'dead_reckoning' (the "
          "twists of the VO or of memory_odom_topic)"),
    _spec("memory_odom_topic", "", "with memory_odometry 'dead_reckoning': odometry that "
          "carries the memory (nav_msgs/Odometry: its twist; wheel odometry or a filter "
          "fusing it, say); empty: the VO's twists"),
    _spec("velocity_source", "auto", "what the layer's predictor takes the chair's velocity "
          "from: 'auto' (the scans matched to each other while they match, the VO while they "
          "do not or no scan comes: it keeps predicting when the camera loses its features "
          "in front of a wall; with obstacles 'grid', the VO), 'vo' (vo_topic alone) or "
          "'scan_matching' (the laser's scans alone, as for the memory: the twist of each "
          "matched interval, and a refused match is a lost sample, never a made-up one)"),
    _spec("memory_radius_m", 3.0, "remembered obstacles farther than this from the chair are "
          "forgotten", 0.1, 100.0),
    _spec("heading_uncertainty", True, "sample the predicted heading with the position "
          "(the rollout's pose covariance): a turning chair's corner sweep counts"),
    _spec("diagnostics_period_s", 1.0, "diagnostics period", 0.1, 60.0),
    _spec("joy_poll_period_s", 0.25, "the joystick topics (joy_topic, applied_topic: 100 Hz "
          "each from the bridge) are read in batches this often and before every VO and scan "
          "message, decision, override send (override_rate_hz, intervening or not), watchdog "
          "check and diagnostics message, not at each message, which cost the executor's "
          "wake-up; 0 = at each message, else at least 0.005", 0.0, 1.0),
)
#: Every parameter the node declares: its own and the online adaptation's (adapt.*).
PARAMS: tuple[ParamSpec, ...] = (*LAYER_PARAMS, *adapt_params.ADAPT_PARAMS)


@dataclass(frozen=True)
class SharedControlParams:
    """The node's parameters, validated on construction (config/shared_control.yaml)."""

    model_path: str
    horizon_s: float
    threshold: float
    neutral_deadband: float
    progress_weight: float
    depth_tolerance: float
    obstacles: str
    joy_topic: str
    joy_axes: str
    vo_topic: str
    vo_type: str
    scan_topic: str
    map_topic: str
    odom_frame: str
    base_frame: str
    override_topic: str
    applied_topic: str
    override_rate_hz: float
    hold_s: float
    joy_timeout_s: float
    vo_timeout_s: float
    scan_timeout_s: float
    laser_frame: str
    scan_nan: str
    laser_x: float
    laser_y: float
    laser_yaw: float
    laser_upside_down: bool
    footprint_length: float
    footprint_width: float
    footprint_offset: float
    margin: float
    memory_s: float
    memory_odometry: str
    memory_odom_topic: str
    memory_radius_m: float
    velocity_source: str
    heading_uncertainty: bool
    diagnostics_period_s: float
    joy_poll_period_s: float

    def __post_init__(self) -> None:
        if not self.model_path:
            raise ValueError("model_path is required (a model file from `asgp train`)")
        if self.obstacles not in ("laser", "grid", "both"):
            raise ValueError(f"obstacles must be 'laser', 'grid' or 'both', got "
                             f"{self.obstacles!r}")
        required = ["joy_topic", "vo_topic", "override_topic", "base_frame", "odom_frame"]
        required += ["scan_topic"] if self.obstacles != "grid" else []
        required += ["map_topic"] if self.obstacles != "laser" else []
        for name in required:
            if not getattr(self, name).strip():
                raise ValueError(f"{name} must not be empty")
        if self.vo_type not in ("twist", "odometry"):
            raise ValueError(f"vo_type must be 'twist' or 'odometry', got {self.vo_type!r}")
        if self.memory_odometry not in MEMORY_ODOMETRY:
            raise ValueError(f"memory_odometry must be one of {MEMORY_ODOMETRY}, got "
                             f"{self.memory_odometry!r}")
        if self.memory_odom_topic.strip() and (self.memory_odometry != "dead_reckoning"
                                               or self.memory_s == 0.0
                                               or self.obstacles == "grid"):
            # read only by dead reckoning of a laser's memory: set alone, it was ignored in
            # silence (README's advice for better odometry named the topic only)
            raise ValueError(
                f"memory_odom_topic {self.memory_odom_topic!r} is read only with "
                "memory_odometry 'dead_reckoning', memory_s > 0 and obstacles 'laser' or "
                f"'both' (here {self.memory_odometry!r}, {self.memory_s:g} s, "
                f"{self.obstacles!r}): set those, or leave memory_odom_topic empty")
        if self.scan_nan not in SCAN_NAN:
            raise ValueError(f"scan_nan must be one of {SCAN_NAN}, got {self.scan_nan!r}")
        if self.velocity_source not in VELOCITY_SOURCES:
            raise ValueError(f"velocity_source must be one of {VELOCITY_SOURCES}, got "
                             f"{self.velocity_source!r}")
        if self.velocity_source == "scan_matching" and self.obstacles == "grid":
            raise ValueError("velocity_source 'scan_matching' needs the laser: set obstacles "
                             "to 'laser' or 'both'")
        if self.obstacles != "laser" and self.vo_type != "odometry":
            raise ValueError("a map needs the chair's pose in it: set vo_type to 'odometry' and "
                             "vo_topic to the odometry's topic (vo_node publishes it on "
                             f"{topics.VO_ODOM})")
        if (problem := period_problem("joy_poll_period_s", self.joy_poll_period_s)) is not None:
            raise ValueError(problem)
        parse_joy_axes(self.joy_axes, "joy_axes")
        self.config()

    def config(self) -> SharedControlConfig:
        return SharedControlConfig(threshold=self.threshold,
                                   neutral_deadband=self.neutral_deadband,
                                   progress_weight=self.progress_weight,
                                   depth_tolerance=self.depth_tolerance,
                                   heading_uncertainty=self.heading_uncertainty)

    def memory(self) -> MemoryConfig | None:
        """The obstacle memory's settings, None when it is off (memory_s 0, or no laser)."""
        if self.memory_s <= 0.0 or self.obstacles == "grid":
            return None
        return MemoryConfig(max_age_s=self.memory_s, radius_m=self.memory_radius_m,
                            max_gap_s=self.vo_timeout_s)

    def footprint(self) -> collision.Footprint:
        return collision.Footprint(self.footprint_length, self.footprint_width,
                                   self.footprint_offset).grown(self.margin)


class SharedControlNode(Node):
    """The shared-control layer (module docstring).

    Raises:
        StartupError: missing or invalid model file, invalid parameters.
    """

    #: the map worker, made for the first map (the node may fail before that)
    _map_worker: concurrent.futures.ThreadPoolExecutor | None = None

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self._clock_reader = runtime.ClockReader(self, lambda: self.predictor)
        try:
            values = check_values(PARAMS, declare(self, PARAMS))
            adapt_values = {name: values.pop(name) for name in adapt_params.ADAPT_NAMES}
            self.params = SharedControlParams(**values)
            adapt = adapt_params.adapt_settings(adapt_values)
            check_topics(self.resolve_topic_name, joy_topic=self.params.joy_topic,
                         applied_topic=self.params.applied_topic,
                         override_topic=self.params.override_topic)
        except (ValueError, TypeError) as exc:
            self.destroy_node()
            raise StartupError(f"invalid parameters: {exc}") from exc
        self.add_on_set_parameters_callback(
            refuse_at_runtime(self, {spec.name for spec in PARAMS}, NODE_NAME))
        p = self.params
        try:
            self.model = load_model(p.model_path)
        except (ModelFileError, OSError, ValueError) as exc:
            self.destroy_node()
            raise StartupError(f"cannot load the model: {exc}") from exc
        # OpenCV and the draws: loaded at start-up, not at the first decision (after the
        # model, so that a refused model file is reported without waiting for them)
        collision.prepare()
        rate = float(self.model.resample_config.rate_hz)
        self.joy_axes = parse_joy_axes(p.joy_axes, "joy_axes")
        try:
            k = horizon_steps(p.horizon_s, rate)
            self.predictor, self._adapt_unavailable = adapt_params.make_predictor(
                self, lambda settings: Predictor(self.model, PredictorConfig(
                    horizon_steps=k, joy_timeout_s=p.joy_timeout_s,
                    vo_timeout_s=p.vo_timeout_s,
                    buffer_s=Predictor.buffer_for(self.model, k, settings)), adapt=settings),
                adapt)
        except ValueError as exc:
            self.destroy_node()
            raise StartupError(str(exc)) from exc
        self.config = p.config()
        self.footprint = p.footprint()
        memory = p.memory()
        mount = (p.laser_x, p.laser_y, p.laser_yaw)
        self.odometer, self.scan_odometer = memory_odometers(memory, p.memory_odometry, mount)
        self.memory = ScanMemory(mount, memory) if memory is not None else None
        # which stream gives the predictor its velocity ('auto' without a laser is the VO)
        source = "vo" if p.velocity_source == "auto" and p.obstacles == "grid" \
            else p.velocity_source
        self.velocity = VelocitySelector(source, fallback_s=p.scan_timeout_s)
        # the scan odometer that gives it the scans' twists (the memory's, if it has one:
        # each scan is matched once)
        self.velocity_odometer: ScanOdometer | None = None
        if self.velocity.uses_scans:
            self.velocity_odometer = self.scan_odometer or ScanOdometer(
                mount, max_gap_s=p.vo_timeout_s)

        self._user: tuple[float, np.ndarray] | None = None  # (stamp, [2]) newest user command
        self._vo_newest: tuple[float, float, float] | None = None  # (stamp, v, omega)
        # (arrival, scan with its stamp, remembered points outside its view)
        self._scan: tuple[float, collision.Scan, np.ndarray | None] | None = None
        self._grid: collision.DistanceField | None = None
        self._grid_problem = ""
        self._map_read_ms = math.nan  # how long the last map's field took (in the worker)
        # A map's field is computed off the executor (1.6 s at MAX_MAP_CELLS, while scans,
        # the watchdog and the overrides go on with the map held); the newest map wins.
        self._map_lock = threading.Lock()
        self._map_generation = 0  # of the newest map received (or dropped)
        self._map_read: tuple[int, collision.DistanceField | None, str, float] | None = None
        self._map_reading = False
        self._map_ready = self.create_guard_condition(self._install_map)
        self._decision: Decision | None = None
        self._decision_t = -math.inf  # node clock of the decision
        # what the diagnostics say while no decision is held: the last one, its override
        # stopped since (the stick went neutral or stale; None before the first decision)
        self._stopped: Decision | None = None
        self._overriding_s = 0.0  # the time the overrides sent cover (node clock)
        self._override_until = -math.inf  # ... up to here (the last send + its period)
        self._last_step: int | None = None
        self._resets_seen = 0  # the predictor's buffer resets, as last seen
        # the newest override sent and when (node clock), for what the board applies
        self._sent_t = -math.inf
        self._joy_source = JoySource(lambda: self.predictor.config.reset_jump_s)
        self._sent: np.ndarray | None = None
        self._overrides_sent = 0
        self._moved_judged = 0  # sticks judged at once, moved since the decision
        self._deferred_counted = False  # a decision deferred since the last one was taken
        self._interventions = 0  # interventions (runs of decisions that changed the command)
        self._was_intervening = False
        self._decisions = 0
        self._solve_ms: deque[float] = deque(maxlen=1000)
        # the sum and count of the changes of the decisions that changed the command (a
        # list of them grew by 15 a second of intervening, 54,000 an hour, and was averaged
        # whole at every diagnostics period)
        self._change_sum, self._change_count = 0.0, 0
        self._bad_messages = 0
        self._scans_ahead = 0  # scans refused: stamped more than SCAN_LEAD_S ahead
        self._scans_repeated = 0  # scans that came again with the newest one's stamp
        self._scans_frozen = 0  # scans with the last one's ranges while the chair moved
        self._vo_messages = 0  # VO twists or odometry received (on the clock)
        self._vo_frame = conv.VelocityFrameCheck(p.base_frame)  # twists in another frame
        self._scans_other_frame = 0  # scans refused: another frame than the laser's
        # the laser's frame: the parameter, else the first scan's (None until one comes)
        self._laser_frame_set = bool(conv.frame_name(p.laser_frame))  # else guessed from the scans
        self._laser_frame: str | None = conv.frame_name(p.laser_frame) or None
        # laser_frame unset and scans in a second frame: which laser laser_x/y/yaw describe
        # is unknown, so no scan is taken until a restart (None: one frame so far)
        self._second_frame: str | None = None
        self._scans_two_frames = 0  # scans of the first frame refused since then
        self._scans_old = 0  # scans refused as stale on arrival or out of order
        self._poses_other_frame = 0  # odometry poses not taken: another parent frame
        self._pose_variance: np.ndarray | None = None  # the last pose's x, y, yaw variance
        self._pose_jumps = 0  # re-initialisations of the odometry seen (_note_pose_variance)
        self._reinitialised_t = -math.inf  # the stamp of the pose that showed the last one
        self._pose_lost = False  # the last pose's variance was not a number, after finite ones
        self._pose_last: tuple[float, float, float, float] | None = None  # (t, x, y, yaw)
        self._scan_problem = ""
        self._deciding = False  # inside _decide (its override send must not decide again)
        self._decided_at = -math.inf  # monotonic time the last decision ended
        self._decide_s = 0.0  # how long it took (s)
        self._decisions_deferred = 0  # optional decisions left for later (_may_decide)
        # Decisions asked for by a VO step or a scan are made once the inputs waiting have
        # been read (_want_decision), not in the input's callback
        self._step_wanted = False  # a VO step came: decide if it completed a grid step
        self._scan_wanted = False  # a scan came while intervening: judge it
        self._decisions_merged = 0  # requests answered by a decision made for another
        self._inputs: list[tuple[Subscription, Callable[[Any], None]]] = []  # (read first)

        reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        # endpoints without rclpy's per-endpoint event handlers, their peers checked at the
        # diagnostics period instead (qos_watch: the handlers cost CPU at every message)
        self.qos_watch = watch = QosWatch(self)
        self.override_pub = watch.publisher(Joy, p.override_topic, reliable)
        self.status_pub = watch.publisher(DiagnosticStatus, topics.SHARED_CONTROL_STATUS,
                                          reliable)
        self.diag_pub = watch.publisher(DiagnosticArray, topics.DIAGNOSTICS, reliable)
        # the joystick topics at the board's 100 Hz: read in batches (polled), and before
        # every override sent (a neutral stick read there stops it)
        self.polled = PolledInputs(self, watch, p.joy_poll_period_s)
        # the topics as the node uses them (namespace and remaps applied), by parameter: what
        # it says names these (the parameters' own names were said under a remap)
        self._topic: dict[str, str] = {"override_topic": self.override_pub.topic_name}
        self._topic["joy_topic"] = self.polled.subscription(
            Joy, p.joy_topic, self._on_joy, qos_profile_sensor_data).topic_name
        if p.applied_topic.strip():
            self._topic["applied_topic"] = self.polled.subscription(
                Joy, p.applied_topic, self._on_joy_applied, qos_profile_sensor_data
            ).topic_name
        inputs: list[tuple[Any, str, Callable[[Any], None], str]] = []
        if p.vo_type == "twist":
            inputs.append((TwistStamped, p.vo_topic, self._on_twist, "vo_topic"))
        else:
            inputs.append((Odometry, p.vo_topic, self._on_odometry, "vo_topic"))
        if self.odometer is not None and p.memory_odom_topic:
            inputs.append((Odometry, p.memory_odom_topic, self._on_memory_odom,
                           "memory_odom_topic"))
        if p.obstacles in ("laser", "both"):
            inputs.append((LaserScan, p.scan_topic, self._on_scan, "scan_topic"))
        for msg_type, topic, callback, param in inputs:
            sub = watch.subscription(msg_type, topic, callback, qos_profile_sensor_data)
            self._inputs.append((sub, callback))
            self._topic[param] = sub.topic_name
        self._decision_wanted = self.create_guard_condition(self._decide_wanted)
        if p.obstacles in ("grid", "both"):
            self._topic["map_topic"] = watch.subscription(
                OccupancyGrid, p.map_topic, self._on_map, latched).topic_name
        runtime.guard_sim_clock(self)
        pacing = runtime.pacing_clock(self)
        self.create_timer(1.0 / p.override_rate_hz, self._send_override, clock=pacing)
        self.create_timer(1.0 / rate, self._on_watchdog, clock=pacing)
        self.create_timer(p.diagnostics_period_s, self._publish_diagnostics, clock=pacing)
        adapt_params.reset_service(self, self.predictor, self._adapt_unavailable)
        adapting = adapt_params.describe(adapt_values, self.predictor.adapt_settings)
        if adapting:
            self.get_logger().info(adapting)
        self.get_logger().info(
            f"model {p.model_path}; horizon {self.predictor.config.horizon_steps} steps; "
            f"threshold {p.threshold}; obstacles from {p.obstacles} ("
            f"{', '.join(self._topic[k] for k in ('scan_topic', 'map_topic') if k in self._topic)}"
            f"); inputs {self._topic['joy_topic']}, {self._topic['vo_topic']}; overrides on "
            f"{self._topic['override_topic']}")

    # ---- time and input ---------------------------------------------------------------

    def _now(self) -> float | None:
        """Node clock in seconds; None before a simulated clock has started. A step back
        of the clock resets the predictor (``runtime.ClockReader``)."""
        return self._clock_reader.now()

    @staticmethod
    def _stamp(t: float, now: float) -> float:
        return t if t > 0.0 else now

    def _applied(self, user: np.ndarray, now: float) -> np.ndarray:
        """What the firmware drives with when the stick ``user`` arrived at ``now``: the last
        override sent, for OVERRIDE_APPLIED_S after it (also when the layer has stopped: the
        bridge and the board keep it that long) while the stick is out of the board's
        neutral, else the stick (also when it arrived before that override was sent, and
        was read in a later batch)."""
        clock = self._now()
        if clock is not None and clock < self._sent_t:
            # the clock went back: that override is of another time
            self._sent, self._sent_t = None, -math.inf
        applied = applied_command(user, self._sent, now - self._sent_t, OVERRIDE_APPLIED_S)
        return user if applied is None else applied

    def _on_joy(self, msg: Joy, arrival: Arrival) -> None:
        now = arrival.now
        if now is None:
            return
        read = self._read_joy(msg, self._topic["joy_topic"], now)
        if read is None:
            return
        t, user = read
        newest = self._user
        if newest is None or t >= newest[0] \
                or newest[0] - t > self.predictor.config.reset_jump_s \
                or newest[0] > now + JOY_LEAD_S:
            # the newest stick by its stamp (a restarted stream's too): an older sample
            # (a second publisher, delivered late) is not what the user holds now. A pushed
            # one took an override up again after the neutral stick had stopped it. One
            # stamped ahead of the clock is of the timeline before the clock stepped back.
            self._user = (t, user)
        if is_neutral(user, BOARD_NEUTRAL):
            # now (read before every override), not at the next decision
            self._stop_overriding(Why.NEUTRAL, "the stick went neutral: the override stopped")
        if not self._joy_source.measured(now):  # else the board's output feeds
            self._feed_joy(t, self._applied(user, now), measured=False, now=now)

    def _on_joy_applied(self, msg: Joy, arrival: Arrival) -> None:
        """What the board drives the chair with, measured: it feeds while it arrives."""
        now = arrival.now
        if now is None:
            return
        read = self._read_joy(msg, self._topic["applied_topic"], now)
        if read is None:
            return
        if joy_problem(*read[1]) is not None:  # no measurement (3.0): refused, counted,
            self._bad_messages += 1  # and joy goes on feeding
            return
        if self._joy_source.take_measured(read[0], now):
            self._feed_joy(*read, measured=True, now=now)

    def _read_joy(self, msg: Joy, topic: str, now: float) -> tuple[float, np.ndarray] | None:
        """(stamp, [forward, turn]) of a Joy message with ``joy_axes``, or None (counted:
        too few axes, a value that is not finite)."""
        try:
            t, command = conv.joy_command(msg, self.joy_axes)
        except ValueError as exc:
            self._bad_messages += 1
            self.get_logger().warning(f"{topic}: {exc}", throttle_duration_sec=5.0)
            return None
        if not np.all(np.isfinite(command)):
            self._bad_messages += 1
            return None
        return self._stamp(t, now), command

    def _feed_joy(self, t: float, command: np.ndarray, measured: bool,
                  now: float | None = None) -> None:
        if self.predictor.feed_joy(t, command, now=now):
            self._joy_source.fed(t, measured)

    def _on_twist(self, msg: TwistStamped) -> None:
        self.polled.drain()  # the step's joystick samples
        now = self._now()
        if now is None:
            return
        self._vo_messages += 1
        if not self._vo_frame.ok(msg, self.get_logger()):
            return
        t, vel = conv.twist_stamped_to_sample(msg)
        t = self._stamp(t, now)
        self._note_vo(t, vel)
        if self.odometer is not None and not self.params.memory_odom_topic:
            self.odometer.feed(t, float(vel[0]), float(vel[1]))
        if self.velocity.vo(t) and self.predictor.feed_vo(t, vel, now=now):
            self._want_decision(step=True)

    def _on_odometry(self, msg: Odometry) -> None:
        self.polled.drain()  # the step's joystick samples
        now = self._now()
        if now is None:
            return
        self._vo_messages += 1
        if not self._vo_frame.ok(msg, self.get_logger()):
            return
        t, vel, ok, pose = conv.odometry_to_sample(msg)
        t = self._stamp(t, now)
        self._note_vo(t, vel, ok)
        # poses in another frame would place the map wrong: not taken
        problem = conv.pose_frame_problem(msg, self.params.odom_frame) if ok else None
        if problem is not None:
            self._poses_other_frame += 1
            self.get_logger().warning(f"{self._topic['vo_topic']}: {problem}",
                                      throttle_duration_sec=5.0)
        elif ok:
            self._note_pose_variance(msg, t, pose)
            self.predictor.feed_pose(t, *pose)
        if self.odometer is not None and not self.params.memory_odom_topic:
            self._feed_odometer(t, vel, ok)
        if self.velocity.vo(t) and self.predictor.feed_vo(t, vel, ok=ok, now=now):
            self._want_decision(step=True)

    def _note_pose_variance(self, msg: Odometry, t: float,
                            pose: tuple[float, float, float]) -> None:
        """A pose whose yaw variance rose at once by POSE_JUMP_VARIANCE or more
        is of a new alignment: the odometry re-initialised after a tracking loss (vo_node
        holds its pose through the gap while the chair moves, and adds 1 m^2 and 1 rad^2).
        The map held, placed with the poses before, would put its walls where the chair
        was (a wall 1.2 m ahead was judged clear): dropped, until a new map comes.

        So is a pose whose yaw variance fell by as much at once, or that jumped further than
        the chair can move (POSE_JUMP_M + POSE_JUMP_SPEED x the time since the last, or the
        same in yaw): the odometry restarted (vo_node restarted starts again at (0, 0, 0)
        with no variance, and the map was kept, a wall judged clear until the chair was in
        it); REP-105's odom frame never jumps otherwise. A source that marks the loss with
        a variance that is not a number (infinite, NaN or negative) after finite ones has
        lost its pose: the map is dropped then, and the first finite variance after is a new
        alignment (maps stamped before it refused). A source that never gives a finite
        variance never drops a map by the variance rules.

        The first pose the layer sees: with a variance of POSE_JUMP_VARIANCE or more the
        odometry may have re-initialised before the layer started (a layer restarted after
        one took back the map the layer before had dropped): a map stamped before that pose
        is refused. With less, a map made before it is off by less than that."""
        cov = msg.pose.covariance
        var = np.array([cov[0], cov[7], cov[35]], dtype=np.float64)
        last, self._pose_last = self._pose_last, (t, *pose)
        if last is not None and t > last[0] and self._pose_jumped(last, (t, *pose)):
            self._new_alignment(t, f"the odometry's pose jumped from ({last[1]:.2f}, "
                                   f"{last[2]:.2f}) to ({pose[0]:.2f}, {pose[1]:.2f}) m at once "
                                   "(it restarted: its poses are of a new alignment)")
        if not np.all(np.isfinite(var) & (var >= 0.0)):
            if self._pose_variance is not None:
                self._pose_variance, self._pose_lost = None, True
                self._drop_reinitialised(
                    "the odometry's pose variance is not a finite number (it lost its pose)")
            return
        before, self._pose_variance = self._pose_variance, var
        if before is None:
            if self._pose_lost:  # the first pose after a loss: a new alignment
                self._pose_lost = False
                self._new_alignment(t, "the odometry's pose came back after a loss (its "
                                       "poses are of a new alignment)")
            elif last is None and np.any(var >= POSE_JUMP_VARIANCE):
                self._reinitialised_t = t  # (not counted: not seen)
                self._drop_reinitialised(
                    f"the odometry's pose variance is {np.max(var):.2f} at the first pose "
                    "this layer saw (it may have re-initialised before: a map made before "
                    "may be of the poses before it)")
            return
        # the yaw's variance (rad^2) alone: dead reckoning only adds to it, a little a step,
        # while the position's grows with the distance times the yaw's (0.27 m^2 a pose,
        # 0.9 m after one tracking loss of vo_node, and every pose after: the map dropped
        # for the rest of the drive) and falls when the chair reverses (2.28 at once)
        rise = float(var[2] - before[2])
        if rise >= POSE_JUMP_VARIANCE:
            self._new_alignment(t, f"the odometry's yaw variance rose by {rise:.2f} at once "
                                   "(it re-initialised after a tracking loss: its poses are "
                                   "of a new alignment)")
        elif -rise >= POSE_JUMP_VARIANCE:
            self._new_alignment(t, f"the odometry's yaw variance fell by {-rise:.2f} at once "
                                   "(it restarted: its poses are of a new alignment)")

    @staticmethod
    def _pose_jumped(last: tuple[float, ...], now: tuple[float, ...]) -> bool:
        """Whether the pose moved further between two stamps than a chair can."""
        dt = now[0] - last[0]
        moved = math.hypot(now[1] - last[1], now[2] - last[2])
        turned = abs(math.remainder(now[3] - last[3], math.tau))
        return (moved > POSE_JUMP_M + POSE_JUMP_SPEED * dt
                or turned > POSE_JUMP_RAD + POSE_JUMP_RATE * dt)

    def _new_alignment(self, t: float, why: str) -> None:
        if self._reinitialised_t == t:
            return  # (one re-initialisation, seen by two rules)
        self._pose_jumps += 1
        self._reinitialised_t = t
        self._drop_reinitialised(why)

    def _drop_reinitialised(self, why: str) -> None:
        if self._grid is not None or self._map_reading:
            self._map_generation += 1  # (a map being read was placed with the old poses)
            self._drop_map(f"{why}: the map, placed with the poses before, is dropped until "
                           "a new one comes")

    def _on_memory_odom(self, msg: Odometry) -> None:
        now = self._now()
        if now is None or not self._vo_frame.ok(msg, self.get_logger()):
            return
        t, vel, ok, _ = conv.odometry_to_sample(msg)
        self._feed_odometer(self._stamp(t, now), vel, ok)

    def _feed_odometer(self, t: float, vel: tuple[float, float], ok: bool) -> None:
        assert self.odometer is not None
        if ok:
            self.odometer.feed(t, float(vel[0]), float(vel[1]))
        else:
            self.odometer.lost()  # no twist to carry the memory along

    def _on_scan(self, msg: LaserScan) -> None:
        self.polled.drain()  # a scan may bring a decision
        now = self._now()
        if now is None:
            return
        try:
            scan = conv.scan_from_msg(msg, nan_is_free=self.params.scan_nan == "no_return",
                                      upside_down=self.params.laser_upside_down)
        except ValueError as exc:
            self._bad_messages += 1
            self._refuse_scan(f"malformed scan: {exc}")
            return
        frame = conv.frame_name(msg.header.frame_id)  # an empty one is a frame of its own
        if self._laser_frame is None:
            self._laser_frame = frame
        elif frame != self._laser_frame:
            # another laser on the topic: its points placed with this laser's mount would
            # move obstacles (or hide them)
            self._scans_other_frame += 1
            if self._laser_frame_set:
                self._refuse_scan(f"scans in frame {frame!r} refused: laser_x/y/yaw "
                                  f"describe {self._laser_frame!r} (laser_frame)")
                return
            if self._second_frame is None:
                self._second_frame = frame
                self._forget_scans(now)
        if self._second_frame is not None:
            # laser_frame unset: the first frame seen was a guess, and the scans taken so
            # far may have been the other laser's (a rear laser's wall ahead of the chair)
            if frame == self._laser_frame:
                self._scans_two_frames += 1
            self._refuse_scan(f"scans in two frames on {self._topic['scan_topic']} "
                              f"({self._laser_frame!r}, {self._second_frame!r}) and "
                              "laser_frame unset: laser_x/y/yaw describe one laser, which "
                              "is unknown, so none is used; set laser_frame")
            return
        if scan.stamp <= 0.0:
            scan = dataclasses.replace(scan, stamp=now)
        lead = scan.stamp - now
        if lead > SCAN_LEAD_S:
            self._scans_ahead += 1
            self._refuse_scan(f"scans stamped {lead:.3f} s after the node's clock (limit "
                              f"{SCAN_LEAD_S} s): is the laser's clock synchronised?")
            return
        if now - scan.stamp > self.params.scan_timeout_s:
            self._scans_old += 1
            self._refuse_scan(f"scans stamped {now - scan.stamp:.3f} s before the node's "
                              f"clock (scan_timeout_s {self.params.scan_timeout_s:g} s): stale "
                              "on arrival")
            return
        if self._scan is not None and scan.stamp < self._scan[1].stamp <= now + SCAN_LEAD_S:
            # older than the newest scan taken, on the same timeline (the clock did not go
            # back past it): taken, it would replace the fresh one and break the scan
            # matching and the obstacle memory
            self._scans_old += 1
            self._refuse_scan(f"a scan stamped {self._scan[1].stamp - scan.stamp:.3f} s "
                              "before the newest one taken: out of order")
            return
        self._scan_problem = ""
        if self._scan is not None and scan.stamp == self._scan[1].stamp:
            # The same scan again (a relay or a second recorder on the topic, a replay
            # overlapping the live laser): matched again it would read as a lost match,
            # a tracking loss for the predictor, and the memory would take it twice.
            self._scans_repeated += 1
            self._scan_problem = (f"a scan came again with the newest one's stamp "
                                  f"({self._scans_repeated} so far): a second publisher on "
                                  f"{self._topic['scan_topic']}, or stamps that do not advance?")
            return
        if self._scan is not None \
                and np.count_nonzero(np.isfinite(scan.ranges)) >= FROZEN_SCAN_RETURNS \
                and np.array_equal(self._scan[1].ranges, scan.ranges, equal_nan=True):
            moving = self._moving(now)
            if moving is not None:
                # the chair moves and the scene does not: a laser driver repeating its last
                # scan with new stamps. Taken, the frozen obstacles kept the layer slowing
                # the user 2 m past where the wall had been, its diagnostics OK
                self._scans_frozen += 1
                self._refuse_scan(f"scans repeat their last ranges bit for bit while the "
                                  f"chair moves ({moving}; {self._scans_frozen} so far): a "
                                  "frozen laser driver? Its obstacles are not used")
                return
        extra = None
        matcher = self.scan_odometer or self.velocity_odometer  # each scan matched once
        scan_pose = matcher.add(scan) if matcher is not None else None
        if self.memory is not None and self.odometer is not None:
            extra = self.memory.add(scan, self.odometer.pose_at(scan.stamp),
                                    self.odometer.epoch)
        elif self.memory is not None and self.scan_odometer is not None:
            assert scan_pose is not None
            extra = self.memory.add(scan, scan_pose, self.scan_odometer.epoch)
        self._scan = (now, scan, extra)
        if self.velocity_odometer is not None:
            self._feed_scan_velocity(scan.stamp, now)
        if self._decision is not None and self._decision.intervening:
            self._want_decision(scan=True)  # while intervening, every new scan is judged

    def _forget_scans(self, now: float) -> None:
        """No scan taken so far is an obstacle source any more (the memory included)."""
        self._scan = None
        if self.memory is not None:
            self.memory.reset()
        if self._decision is not None and self._decision.intervening:
            self._decide(now)  # no obstacle source: the override stops now

    def _moving(self, now: float) -> str | None:
        """How the chair moves, by the newest fresh velocity sample (within vo_timeout_s)
        of the predictor's or of the VO's (whatever the velocity source: with
        'scan_matching' the frozen scans themselves made the predictor's samples, which
        read the chair still), when faster than FROZEN_SCAN_SPEED or FROZEN_SCAN_YAW_RATE;
        else None (still, or not known: a noise-free simulated laser repeats itself while
        the chair stands)."""
        for newest in (self.predictor.newest_velocity(), self._vo_newest):
            if newest is None or abs(now - newest[0]) > self.params.vo_timeout_s:
                continue  # (not fresh, or of another timeline)
            _, v, w = newest
            if abs(v) > FROZEN_SCAN_SPEED or abs(w) > FROZEN_SCAN_YAW_RATE:
                return f"{v:.2f} m/s, {w:.2f} rad/s"
        return None

    def _note_vo(self, t: float, vel: tuple[float, float] | np.ndarray, ok: bool = True
                 ) -> None:
        """The VO's last tracked twist (stamp, v, omega), for :meth:`_moving`."""
        v, w = float(vel[0]), float(vel[1])
        if ok and math.isfinite(v) and math.isfinite(w):
            self._vo_newest = (t, v, w)

    def _refuse_scan(self, problem: str) -> None:
        """A scan not taken: the diagnostics' ``scan`` value and the log say why."""
        self._scan_problem = problem
        self.get_logger().warning(f"ignoring {self._topic['scan_topic']}: {problem}",
                                  throttle_duration_sec=5.0)

    def _feed_scan_velocity(self, stamp: float, now: float) -> None:
        """The predictor's velocity sample from the newest scan match (velocity_source
        'scan_matching' or 'auto'): the forward and turn rates of the matched interval,
        stamped with the newer scan (a frame-to-frame odometry, as a VO's twist); a scan
        that did not match gives a lost sample ('scan_matching') or nothing ('auto': the
        VO's twists are taken)."""
        assert self.velocity_odometer is not None
        give, twist = self.velocity.scan(stamp, self.velocity_odometer.last_twist)
        if not give:
            return
        if twist is None:
            self.predictor.feed_vo(stamp, (math.nan, math.nan), ok=False)
        elif self.predictor.feed_vo(stamp, twist):
            self._want_decision(step=True)

    def _on_map(self, msg: OccupancyGrid) -> None:
        self._map_generation += 1  # a map being read is superseded by this one
        frame = conv.frame_name(msg.header.frame_id)  # ('/odom' is 'odom', as in tf2)
        if frame and frame != conv.frame_name(self.params.odom_frame):
            self._drop_map(f"map in frame {msg.header.frame_id!r}, the chair's poses are in "
                           f"{self.params.odom_frame!r}")
            return
        stamp = conv.stamp_to_seconds(msg.header.stamp)
        now = self._now()
        if now is not None and now < self._reinitialised_t:
            self._reinitialised_t = -math.inf  # (the clock went back: another timeline)
        if 0.0 < stamp < self._reinitialised_t:
            # the map dropped at the re-initialisation, sent again (a mapper re-publishing
            # what it has): of the poses before it, it put the walls where the chair was
            self._drop_map(f"a map stamped {self._reinitialised_t - stamp:.2f} s before the "
                           "odometry re-initialised (of the poses before it): refused")
            return
        cells = int(msg.info.width) * int(msg.info.height)
        if cells > MAX_MAP_CELLS:
            self._bad_messages += 1
            self._drop_map(f"a map of {msg.info.width} x {msg.info.height} cells: at most "
                           f"{MAX_MAP_CELLS:,} (its field took 1.6 s at 4 million cells, 24 s "
                           "at 49 million, and 3 GB); give the layer a local costmap around "
                           "the chair")
            return
        try:
            grid = conv.grid_from_msg(msg)
        except ValueError as exc:
            self._bad_messages += 1
            self._drop_map(f"bad map: {exc}")
            return
        if self._map_worker is None:
            self._map_worker = concurrent.futures.ThreadPoolExecutor(
                max_workers=1, thread_name_prefix="map_read")
        self._map_reading = True
        self._map_worker.submit(self._read_map, self._map_generation, grid)

    def _read_map(self, generation: int, grid: collision.Grid) -> None:
        """(The map worker.) The field of ``grid``, handed to the executor; none for a map
        superseded while it waited (a burst of maps: the newest is read, not each)."""
        if generation != self._map_generation:
            return
        field: collision.DistanceField | None = None
        problem = ""
        start = time.perf_counter()
        try:
            field = collision.DistanceField.from_grid(grid)
        except ValueError as exc:
            problem = f"bad map: {exc}"
        except Exception as exc:  # MemoryError, ...: said, not a dead worker
            problem = f"map not read: {type(exc).__name__}: {exc}"
        with self._map_lock:
            self._map_read = (generation, field, problem, 1e3 * (time.perf_counter() - start))
        self._map_ready.trigger()

    def _install_map(self) -> None:
        """(The executor.) The field read by the worker, unless a newer map came since."""
        with self._map_lock:
            done, self._map_read = self._map_read, None
        if done is None:
            return
        generation, field, problem, ms = done
        if generation != self._map_generation:
            return  # superseded (its successor is being read, or was dropped)
        self._map_reading = False
        self._map_read_ms = ms
        if field is None:
            self._bad_messages += 1
            self._drop_map(problem)
            return
        self._grid, self._grid_problem = field, ""

    def destroy_node(self) -> None:
        if self._map_worker is not None:
            self._map_worker.shutdown(wait=False, cancel_futures=True)
        super().destroy_node()  # type: ignore[no-untyped-call]

    def _drop_map(self, problem: str) -> None:
        """The map held is dropped: an intervention it drove is judged again now (it went
        on without an obstacle source until the next step or scan)."""
        self._map_reading = False
        self._grid, self._grid_problem = None, problem
        self.get_logger().error(problem)
        now = self._now()
        if now is not None and self._decision is not None and self._decision.intervening:
            self._decide(now)

    # ---- deciding -----------------------------------------------------------------------

    def _check_for(self, now: float) -> Callable[[Prediction], CollisionCheck | None]:
        """The collision check of the fresh obstacle sources for a prediction, or None.

        A scan is placed relative to the path's origin with the chair's motion between
        the scan's stamp and t0 (the velocity at t0, held: a few centimetres); a map needs
        the odometry pose at t0 (``Prediction.origin``)."""
        p = self.params

        def build(pred: Prediction) -> CollisionCheck | None:
            checks: list[CollisionCheck] = []
            if self._scan is not None:
                _, scan, extra = self._scan
                if -SCAN_LEAD_S <= now - scan.stamp <= p.scan_timeout_s:  # fresh
                    v, w = (float(x) for x in pred.vel_past[-1])
                    motion = collision.constant_twist_motion(v, w, pred.t0 - scan.stamp)
                    checks.append(collision.scan_check(
                        scan, self.footprint, mount=(p.laser_x, p.laser_y, p.laser_yaw),
                        base_motion=motion, extra=extra))
            if self._grid is not None and pred.origin is not None:
                origin = (float(pred.origin[0]), float(pred.origin[1]), float(pred.origin[2]))
                checks.append(collision.grid_check(self._grid, self.footprint, origin=origin))
            return collision.PathCheck.either(checks) if checks else None

        return build

    def _want_decision(self, step: bool = False, scan: bool = False) -> None:
        """Ask for a decision: for a VO step (``step``: made if it completed a grid step)
        or for a scan taken while intervening (``scan``). It is made by
        :meth:`_decide_wanted` at the executor's next turn, after the inputs waiting then
        have been read, once for all the requests so far. Decided in each input's callback,
        the decisions of 0.1 s an intervention costs on a loaded laptop (every scan at 10 Hz
        and every step at 5 Hz) took more than the node's whole time: its executor fell
        behind its own inputs, the scans were refused as stale on arrival, and the layer let
        go in the middle of interventions ('no fresh scan or map')."""
        if self._step_wanted or self._scan_wanted:
            self._decisions_merged += 1
        else:
            self._decision_wanted.trigger()
        self._step_wanted |= step
        self._scan_wanted |= scan

    def _decide_wanted(self) -> None:
        """(The guard condition of :meth:`_want_decision`.) Read every input waiting (the
        joystick, the VO, the scans: newer data and more requests), then make the one
        decision asked for."""
        self.polled.drain()
        for sub, callback in self._inputs:
            waiting = take_waiting(sub, INPUT_QUEUE)
            if waiting is None:  # (destroyed: the node is shutting down)
                return
            for msg, _info in waiting:
                callback(msg)
        step, scan = self._step_wanted, self._scan_wanted
        self._step_wanted = self._scan_wanted = False
        now = self._now()
        if now is None or not (step or scan):
            return
        if not (step and self._maybe_decide(now)) and scan \
                and self._decision is not None and self._decision.intervening:
            self._decide(now)

    def _maybe_decide(self, now: float) -> bool:
        """Decide if the predictor has completed a grid step since the last decision made
        for one; whether it did."""
        if self.predictor.stats.resets != self._resets_seen:
            # the predictor restarted its buffers (its clock went back: a bag played again,
            # the system clock set back): the steps count from the new samples
            self._resets_seen = self.predictor.stats.resets
            self._last_step = None
        step = self.predictor.ready_step()
        if step is None or (self._last_step is not None and step <= self._last_step):
            return False
        self._last_step = step
        self._decide(now)
        return True

    def _decide(self, now: float) -> None:
        self._deciding = True
        start = time.monotonic()
        try:
            self._decide_now(now)
        finally:
            self._deciding = False
            self._decided_at = time.monotonic()
            self._decide_s = self._decided_at - start
            self._deferred_counted = False

    def _may_decide(self) -> bool:
        """Whether a stick moved since the decision may be judged again now (the override
        timer, 20 Hz): only after as long as the last decision took has passed since it
        ended, so that at most half the node's time goes to judging a moving hand; until
        then the moved stick is judged at once (:func:`judge_moved_stick`). Decisions of
        0.1 s at every tick of a moving hand left the executor behind its own inputs (scans
        refused as 0.3-0.45 s stale on arrival, VO stale: the layer let go in the middle of
        interventions). Steps and scans (:meth:`_want_decision`), the watchdog and an
        obstacle source lost always decide."""
        if time.monotonic() - self._decided_at >= self._decide_s:
            return True
        if not self._deferred_counted:  # one deferred decision, however many ticks it waits
            self._decisions_deferred += 1
            self._deferred_counted = True
        return False

    def _decide_now(self, now: float) -> None:
        user = self._user[1] if self._user is not None else None
        decision = decide(self.predictor, now, user, None, self.config,
                          check_for=self._check_for(now), learn=False)
        self._decision, self._decision_t = decision, now
        self._decisions += 1
        if decision.solve_s > 0.0:
            self._solve_ms.append(1e3 * decision.solve_s)
        if decision.intervening:
            why_not = self._send_override()
            if self._decision is not None and self._decision is not decision:
                decision = self._decision  # the stick moved: judged again with it
            if self._decision is None:
                # dropped before it was sent (the stick read before the send, which came
                # while this decision was made, is neutral or stale; or the decision took
                # longer than hold_s): nothing was sent, and the status says why
                neutral = why_not == _WENT_NEUTRAL
                decision = dataclasses.replace(
                    decision, why=Why.NEUTRAL if neutral else Why.STALE_INPUT, command=None,
                    p_command=math.nan, change=0.0, detail=why_not or "not sent")
                self._decision = decision
        if decision.intervening:
            if not self._was_intervening:  # a new intervention begins
                self._interventions += 1
            self._change_sum += decision.change
            self._change_count += 1
        else:
            self._stop_overriding()
        self._was_intervening = decision.intervening
        self.status_pub.publish(self._status(decision))
        self._learn()

    def _learn(self) -> None:
        """An adapting predictor's work for the steps so far, after the decision has been
        acted on (absorbing the settled steps, checking predictions against outcomes)."""
        try:
            self.predictor.learn()
        except (ValueError, np.linalg.LinAlgError) as exc:  # never let learning stop the layer
            self.get_logger().error(f"adaptation failed: {type(exc).__name__}: {exc}",
                                    throttle_duration_sec=5.0)

    def _on_watchdog(self) -> None:
        """At the model rate: stale inputs end an intervention even when no new step
        arrives, and without new steps the layer still decides (and says why not)."""
        self.polled.drain()
        now = self._now()
        if now is None:
            return
        period = self.predictor.dt
        late = not 0.0 <= now - self._decision_t <= 1.5 * period  # (or the clock went back)
        intervening = self._decision is not None and self._decision.intervening
        if late or (intervening and (self.predictor.status(now) is not None
                                     or not now - self._decision_t <= self.params.hold_s)):
            self._decide(now)

    # ---- output -------------------------------------------------------------------------

    def _stop_overriding(self, why: Why = Why.STALE_INPUT, detail: str = "") -> None:
        """No override is sent from now until a decision intervenes again; the diagnostics
        say ``why``, ``detail`` (not 'no decision yet')."""
        d = self._decision
        if d is not None and d.intervening:
            self._decision = None
            self._stopped = dataclasses.replace(
                d, why=why, command=None, p_command=math.nan, change=0.0,
                detail=detail or "the override stopped")

    def _send_override(self) -> str | None:
        """Send the decision's override, or say why not (None: sent)."""
        # the joystick waiting first: an override is never sent after a neutral stick that
        # has arrived (read before now: every sample read later arrived after this send)
        self.polled.drain()
        now = self._now()
        d = self._decision
        if now is None or d is None or d.command is None:
            return "no clock, or nothing to send"
        user = self._user
        why_not = None
        if user is None or not -JOY_LEAD_S <= now - user[0] <= self.params.joy_timeout_s:
            why_not = "the stick went stale before the override was sent"
        elif is_neutral(user[1], BOARD_NEUTRAL):
            why_not = _WENT_NEUTRAL
        elif not 0.0 <= now - self._decision_t <= self.params.hold_s:
            # (a decision "ahead" of the clock: it went back)
            why_not = (f"the decision is {now - self._decision_t:.2f} s old, beyond hold_s "
                       f"({self.params.hold_s:g} s): not sent")
        if why_not is not None or user is None:
            self._stop_overriding(Why.NEUTRAL if why_not == _WENT_NEUTRAL else Why.STALE_INPUT,
                                  why_not or "")
            return why_not
        if float(np.max(np.abs(user[1] - d.user))) > STICK_CHANGE:
            # the user moved the stick since the decision: never the old decision sent again.
            # From the timer, decided again; inside the decision (the stick moved while it
            # was made), or with the layer busy deciding (_may_decide), judged at once with
            # the newest stick: it, the decision's command within it, or stopping
            if not self._deciding and self._may_decide():
                self._decide(now)
                return "the stick moved since the decision: judged again"
            d = self._judge_moved(now, d, user[1])
            if d.command is None:
                self._stop_overriding()
                return f"the stick moved: {d.why.value}: {d.detail}"
        command = d.command
        assert command is not None  # (checked above, and by the judgement)
        # in the convention of the joy it changes (joy_axes), as the bridge reads it: with
        # joy_axes '0,-1' a left turn kept was written as a right one
        self.override_pub.publish(conv.joy_from_sample(now, float(command[0]),
                                                       float(command[1]), axes=self.joy_axes))
        self._sent, self._sent_t = command, now
        self._overrides_sent += 1
        # each override holds until the next, at most a period of the timer: the time
        # covered (overrides_sent / rate counted the sends at decisions too: 3.5 s in 2 s)
        period = 1.0 / self.params.override_rate_hz
        self._overriding_s += max(0.0, now + period - max(now, self._override_until))
        self._override_until = now + period
        # an adapting predictor learns nothing from the steps an override may have driven
        # (training's rule for a bag's overrides): what the board applied is only modelled
        self.predictor.feed_override(now, now)
        return None

    def _judge_moved(self, now: float, d: Decision, stick: np.ndarray) -> Decision:
        """``judge_moved_stick`` for a stick that moved since ``d``: its result becomes the
        decision (from now, for the newest stick), said in the status when the timer asked
        (a decision publishes its own)."""
        judged = judge_moved_stick(self.predictor, now, d, stick, self.config,
                                   self._check_for(now))
        self._moved_judged += 1
        if judged.solve_s > 0.0:
            self._solve_ms.append(1e3 * judged.solve_s)
        self._decision, self._decision_t = judged, now
        if not self._deciding:
            if judged.intervening and not self._was_intervening:
                self._interventions += 1
            if judged.intervening:
                self._change_sum += judged.change
                self._change_count += 1
            self._was_intervening = judged.intervening
            self.status_pub.publish(self._status(judged))
        return judged

    def _status(self, d: Decision) -> DiagnosticStatus:
        values = {
            "why": d.why.value,
            # (blank without a stick: no joystick sample yet)
            "user_forward": f"{d.user[0]:.3f}" if np.isfinite(d.user[0]) else "",
            "user_turn": f"{d.user[1]:.3f}" if np.isfinite(d.user[1]) else "",
            "command_forward": f"{d.command[0]:.3f}" if d.command is not None else "",
            "command_turn": f"{d.command[1]:.3f}" if d.command is not None else "",
            "p_before": f"{d.p_user:.4f}",
            "p_after": f"{d.p_command:.4f}",
            "change": f"{d.change:.3f}",
            "solve_ms": f"{1e3 * d.solve_s:.2f}",
            "candidates": str(d.candidates),
        }
        return conv.diagnostic_status(
            runtime.status_name(self, f"{self.get_name()}: decision"), _level(d.why),
                                      f"{d.why.value}: {d.detail}", values=values)

    def diagnostic_status(self) -> DiagnosticStatus:
        d = self._decision or self._stopped
        why = d.why.value if d is not None else "starting"
        now = self._now()
        scan_age = 0.0 if self._scan is None or now is None else now - self._scan[1].stamp
        solve = np.asarray(self._solve_ms)
        values = {
            "why": why,
            "decisions": str(self._decisions),
            "interventions": str(self._interventions),
            "overrides_sent": str(self._overrides_sent),
            "moved_stick_judgements": str(self._moved_judged),
            "decisions_deferred": str(self._decisions_deferred),
            "decisions_merged": str(self._decisions_merged),
            "overriding_s": f"{self._overriding_s:.2f}",
            "mean_change": (f"{self._change_sum / self._change_count:.3f}"
                            if self._change_count else "0"),
            "solve_p50_ms": f"{np.percentile(solve, 50):.2f}" if solve.size else "nan",
            "solve_p99_ms": f"{np.percentile(solve, 99):.2f}" if solve.size else "nan",
            # the scan held, as _check_for judges it: fresh, or too old, or stamped ahead
            # of the clock (it went back: a bag played again, an NTP step)
            "scan": self._scan_problem or (
                "none" if self._scan is None
                else f"stale: the last taken {scan_age:.2f} s ago"
                if scan_age > self.params.scan_timeout_s
                else f"the last taken is stamped {-scan_age:.2f} s ahead of the clock "
                "(it went back)" if scan_age < -SCAN_LEAD_S else "received"),
            "scans_ahead_of_clock": str(self._scans_ahead),
            "scans_repeated": str(self._scans_repeated),
            "scans_frozen": str(self._scans_frozen),
            "scans_old": str(self._scans_old),
            "poses_other_frame": str(self._poses_other_frame),
            "odometry_reinitialised": str(self._pose_jumps),
            "laser_frame": "none yet" if self._laser_frame is None
            else self._laser_frame or "(empty frame_id)",
            "scans_other_frame": str(self._scans_other_frame),
            "scans_two_frames": str(self._scans_two_frames),
            "memory_points": "off" if self.memory is None else str(self.memory.size),
            "memory_resets": "off" if self.memory is None else str(self.memory.resets),
            "odometry_breaks": str(self.odometer.breaks) if self.odometer is not None else
            str(self.scan_odometer.breaks) if self.scan_odometer is not None else "off",
            "map": (self._grid_problem or ("received" if self._grid is not None else "none"))
            + ("; a map is being read" if self._map_reading else ""),
            "map_read_ms": f"{self._map_read_ms:.0f}",
            "vo_messages": str(self._vo_messages),
            **self._vo_frame.values(),
            "velocity_source": self.velocity.describe() + (
                f" ({self.velocity_odometer.breaks} breaks)"
                if self.velocity_odometer is not None else ""),
            "bad_messages": str(self._bad_messages),
            # its own overrides, given to its predictor (see predictor_node's)
            "joy_measured": str(self._joy_source.measured_samples),
            **self.polled.values(),
            "overrides_seen": str(self.predictor.stats.overrides),
            "overrides_late": str(self.predictor.stats.overrides_late),
            **adapt_params.diagnostic_values(self.predictor.adaptation,
                                             self._adapt_unavailable),
            "qos_mismatch": self.qos_watch.summary(),
        }
        message = "no decision yet" if d is None else f"{d.why.value}: {d.detail}"
        level = "WARN" if d is None else _level(d.why)
        bridges, others = runtime.override_readers(self, self.override_pub.topic_name)
        listeners = len(bridges) + len(others)
        values["override_subscribers"] = str(listeners)
        values["override_bridges"] = str(len(bridges))
        if not bridges:  # (a misspelt override_topic: OK, 'intervening', and no effect)
            # ERROR while it would be intervening, else WARN at least
            level = "ERROR" if self._was_intervening or level == "ERROR" else "WARN"
            if listeners == 0:
                message = (f"nothing subscribes to {self.override_pub.topic_name}: no override "
                           "reaches the board (the bridge not running, or override_topic "
                           f"misspelt?); {message}")
            else:
                named = ", ".join(others[:3]) + (f" and {len(others) - 3} more"
                                                 if len(others) > 3 else "")
                message = (f"no bridge subscribes to {self.override_pub.topic_name} (none of "
                           f"its subscribers, {named}, publishes a joystick, as the serial "
                           "bridge does its joy and joy_applied): no "
                           "override reaches the board (the bridge not running, or in another "
                           f"namespace, or override_topic misspelt?); {message}")
        if self._second_frame is not None:  # no laser until a restart: set laser_frame
            level, message = "ERROR", self._scan_problem
        level, message = self.qos_watch.escalate(level, message)
        return conv.diagnostic_status(
            runtime.status_name(self, f"{self.get_name()}: shared control"), level, message,
                                      hardware_id=self.params.model_path, values=values)

    def _publish_diagnostics(self) -> None:
        self.polled.drain()
        self.qos_watch.check()
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.status = [self.diagnostic_status()]
        self.diag_pub.publish(msg)


def _level(why: Why) -> str:
    """A decision's level: OK when the layer judged and acted (clear, a neutral stick,
    intervening); WARN when it could not judge (stale or missing input, a failed check) or
    no command is clear of obstacles (``no_safe_command``: every candidate likely to
    touch)."""
    return "OK" if why in (Why.CLEAR, Why.NEUTRAL, Why.INTERVENING) else "WARN"


def main(args: list[str] | None = None) -> int:
    """Run the node until SIGINT or SIGTERM (:func:`asgp_ros.nodes.runtime.run`).
    Exit code 1: a refused model or parameter."""
    threadpool_limits(limits=1)  # small matrices: BLAS threads only add contention
    return runtime.run(SharedControlNode, args, name=NODE_NAME, refused=(StartupError,))


if __name__ == "__main__":
    sys.exit(main())
