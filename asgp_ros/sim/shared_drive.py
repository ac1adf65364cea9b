"""A simulated drive with and without the shared-control layer, offline and fast.

The closed loop of the live system, in one process and faster than real time, for the
same seed with the layer on and off:

* the user (:class:`~asgp_ros.sim.driver.Driver`, inattentive if asked) moves the stick;
* the board runs the firmware's rules (:class:`asgp_ros.serial.safety.Safety`: passthrough,
  overrides only while fresh and only while the stick is out of neutral, 200 ms
  watchdog); the chair (:class:`~asgp_ros.sim.chair.Chair`) follows its output and stops
  against the furniture, counting contacts;
* the layer sees what the nodes see: the stick as the bridge reports it (50 Hz), the
  velocity as a frame-to-frame VO reports it (5 Hz: the body-frame displacement since the
  previous frame over the interval, stamped with the newer frame, with noise), the scanner
  (:class:`~asgp_ros.sim.lidar.Lidar`, 10 Hz); the VO loses tracking as a camera does
  (with ``vo_losses``): in episodes of 0.5-3 s at the recordings' rate for the floor
  (:class:`~asgp_ros.sim.sensors.SensorParams`), and whenever the camera faces something
  nearer than an RGB-D camera's minimum depth (``VO_MIN_DEPTH_M`` over the central
  ``VO_VIEW_RAD`` of the scan, the camera looking forward unless ``camera_yaw`` says
  otherwise: the worst case, losses as the chair heads for a wall; the package's camera looks
  backward), and then reports nothing; it decides at every model grid step
  (:func:`asgp_ros.core.shared_control.decide`), and while it intervenes its override is
  written to the board every 50 ms, as the bridge does.

The result counts what the demo report shows: contacts, minimum clearance, interventions
(count, duration, mean change of the command), the share of time the user's command
passed untouched, and the decision's solve time.

With ``audit``, every decision that computed the probability of contact is checked against
the plant: a copy of the chair, in its state at that moment, drives the user's command held
to the end of the layer's predicted path (the layer's own assumption) and the closest the
footprint comes to the furniture is recorded (:class:`AuditRow`). That tells an
intervention the user's command needed (it would have touched) from a false alarm, shows the
contacts the layer let pass, and checks the probabilities against what happened. Beside the
layer's probability, the audit computes the same check of the same prediction against the
room's true map (:func:`~asgp_ros.sim.lidar.room_grid` at ``AUDIT_MAP_RESOLUTION``, placed by
the chair's true pose at the prediction's origin): what the layer would have said with
perfect obstacles. Where the two disagree, the obstacles the scans gave it are the cause, not
the prediction.
"""

from __future__ import annotations

import copy
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from asgp_ros.core import collision
from asgp_ros.core.adaptive import AdaptSettings
from asgp_ros.core.models import MotionModel
from asgp_ros.core.obstacle_memory import (
    MemoryConfig,
    ScanMemory,
    compose,
)
from asgp_ros.core.online import Prediction, Predictor, PredictorConfig
from asgp_ros.core.scan_match import (
    VELOCITY_SOURCES,
    ScanOdometer,
    VelocitySelector,
    memory_odometers,
)
from asgp_ros.core.shared_control import (
    Decision,
    SharedControlConfig,
    check_covariance,
    decide,
    is_neutral,
)
from asgp_ros.serial import safety as fw
from asgp_ros.serial.protocol import Mode, Status
from asgp_ros.sim.chair import Chair, ChairState
from asgp_ros.sim.driver import Driver, DriverParams
from asgp_ros.sim.lidar import Lidar, LidarConfig, room_grid
from asgp_ros.sim.sensors import SensorParams
from asgp_ros.sim.world import Room, room_for_surface

FloatArray = NDArray[np.float64]

STEP_S = 0.01
JOY_EVERY, VO_EVERY, SCAN_EVERY, OVERRIDE_EVERY = 2, 20, 10, 5  # 50, 5, 10, 20 Hz
VO_NOISE = (0.01, 0.01)  # (m/s, rad/s), one standard deviation
#: The camera sees no depth nearer than this (m; structured-light and stereo RGB-D cameras
#: start at 0.3-0.6 m): with the scan's central ``VO_VIEW_RAD`` (the camera's field of view,
#: about the scanner's) mostly nearer, the VO has no features and reports nothing.
VO_MIN_DEPTH_M = 0.5
VO_VIEW_RAD = math.radians(58.0)
AUDIT_MAP_RESOLUTION = 0.02
"""Cell (m) of the room's map the audit checks the layer's predictions against: its cells
make that check conservative by at most half a cell (the rectangle is grown by it)."""
SHORT_OF_FURNITURE_M = (0.01, 0.02)
"""The audit counts the obstacle points the layer's check gets that lie more than these (m)
short of the furniture, inside the free floor (the scanner's range noise)."""
DEFAULT_MEMORY = MemoryConfig()
"""The memory's settings, the node's default (``memory_s`` 10 s)."""


@dataclass(frozen=True)
class AuditRow:
    """One decision checked against the plant (``drive(..., audit=True)``).

    Attributes:
        t: the decision's time (s).
        p_user: the layer's probability of contact within the horizon, the user's command
            held, for its footprint grown by the margin.
        intervened: the layer changed the command.
        clearance_m: the closest the chair's footprint came to the furniture (m, negative:
            overlap) when a copy of the chair drove the user's command held to the end of
            the layer's path.
        touched: that copy touched (a contact as the chair counts it).
        seconds: how long the copy drove: from now to the last step of the layer's predicted
            path (which starts at the last complete grid step, a little before now).
        p_map: the layer's check of the same prediction, footprint and covariance against the
            room's true map instead of the scans, the path placed by the chair's true pose at
            the prediction's origin (NaN when that pose is not known).
    """

    t: float
    p_user: float
    intervened: bool
    clearance_m: float
    touched: bool
    seconds: float
    p_map: float = math.nan


@dataclass
class DriveResult:
    """What a drive did (see the module docstring)."""

    seconds: float
    layer: bool
    contacts: int = 0
    min_clearance_m: float = math.inf
    interventions: int = 0
    intervention_s: float = 0.0
    changes: list[float] = field(default_factory=list)
    untouched_share: float = 1.0
    solve_ms: list[float] = field(default_factory=list)
    decisions: dict[str, int] = field(default_factory=dict)
    contact_points: list[tuple[float, float]] = field(default_factory=list)
    contact_events: list[dict[str, float | str]] = field(default_factory=list)
    intervention_points: list[tuple[float, float]] = field(default_factory=list)
    path: list[tuple[float, float]] = field(default_factory=list)
    audit: list[AuditRow] = field(default_factory=list)
    obstacle_points: int = 0
    """With ``audit``: the obstacle points the layer's checks got (scan and memory, every
    scan), and how many of them lay short of the furniture by more than each distance of
    ``SHORT_OF_FURNITURE_M`` (``points_short``)."""
    points_short: list[int] = field(default_factory=lambda: [0] * len(SHORT_OF_FURNITURE_M))
    vo_lost_s: float = 0.0
    """With the layer: the time the VO reported nothing (tracking lost)."""
    velocity_switches: int = 0
    """With the layer: how often its velocity changed stream (``velocity_source`` auto)."""
    adaptation: dict[str, float | int] = field(default_factory=dict)
    """With the layer adapting: its predictor's steps learnt and refused, whether the
    adapted posterior is published (1) or the trained one (0), the largest variance scale
    of the speed regimes and the ellipses' recent coverage."""

    def summary(self) -> dict[str, float | int | bool]:
        def solve_ms(q: float) -> float:  # NaN for a drive without the layer's decisions
            return round(float(np.percentile(self.solve_ms, q)), 2) if self.solve_ms \
                else math.nan

        return {
            "layer": self.layer, "minutes": round(self.seconds / 60.0, 2),
            "contacts": self.contacts, "min_clearance_m": round(self.min_clearance_m, 3),
            "interventions": self.interventions,
            "intervention_s": round(self.intervention_s, 1),
            "mean_change": round(float(np.mean(self.changes)), 3) if self.changes else 0.0,
            "untouched_share": round(self.untouched_share, 4),
            "vo_lost_s": round(self.vo_lost_s, 1),
            "velocity_switches": self.velocity_switches,
            "solve_p50_ms": solve_ms(50),
            "solve_p99_ms": solve_ms(99),
        } | self._audit_summary() | {f"adapt_{k}": v for k, v in self.adaptation.items()}

    def _audit_summary(self) -> dict[str, float | int | bool]:
        """Of the interventions, the share whose held user command would have touched; the
        decisions that let a touching command pass (empty without an audit)."""
        if not self.audit:
            return {}
        hits = [r.touched for r in self.audit if r.intervened]
        return {"audit_decisions": len(self.audit), "audit_interventions": len(hits),
                "audit_needed_share": round(float(np.mean(hits)), 4) if hits else math.nan,
                "audit_missed": sum(r.touched and not r.intervened for r in self.audit)}


def held_clearance(chair: Chair, room: Room, command: np.ndarray, seconds: float
                   ) -> tuple[float, bool]:
    """The closest (m) a copy of ``chair`` comes to the furniture driving ``command`` held
    for ``seconds`` (0 or less if it touched), and whether it touched; ``chair`` itself is
    left as it is."""
    twin = copy.deepcopy(chair, {id(room): room})  # its own state and noise, the same room
    before = twin.contacts
    st = twin.state
    closest = room.footprint_clearance(st.x, st.y, st.theta) - room.furniture_band
    for _ in range(round(seconds / STEP_S)):
        st = twin.step(command, STEP_S)
        closest = min(closest, room.footprint_clearance(st.x, st.y, st.theta)
                      - room.furniture_band)
    touched = twin.contacts > before
    # the chair stops against an obstacle one internal step before the overlap: touching is 0
    return (min(closest, 0.0) if touched else closest), touched


def map_probability(fld: collision.DistanceField, pred: Prediction, origin: ChairState,
                    footprint: collision.Footprint, config: SharedControlConfig) -> float:
    """The layer's probability of contact within the horizon for ``pred`` (the covariance
    its check gets), against the obstacles of ``fld`` (the room's frame), the path's base
    frame placed at the true pose ``origin``."""
    c = collision.contact_probability(fld, pred.pose, check_covariance(pred, config),
                                      footprint, (origin.x, origin.y, origin.theta))
    return float(np.ravel(c.within)[0])


def short_of_furniture(points: np.ndarray, room: Room) -> np.ndarray:
    """[m] how far (m) each of ``points`` (in the room) lies inside the free floor, short of
    the furniture's front (0 or less: on or behind it)."""
    x_lo, x_hi, y_lo, y_hi = room.free_box
    x, y = points[:, 0], points[:, 1]
    inside: np.ndarray = np.minimum(np.minimum(x - x_lo, x_hi - x), np.minimum(y - y_lo,
                                                                                y_hi - y))
    return inside


def _truth_at(truth: deque[tuple[int, ChairState]], index: int) -> ChairState | None:
    """The chair's true state after ``index`` steps of ``STEP_S``, if still held."""
    j = len(truth) - 1 - (truth[-1][0] - index) if truth else -1
    return truth[j][1] if 0 <= j < len(truth) and truth[j][0] == index else None


def frame_twist(frame: tuple[float, float, float, float], state: ChairState, t: float,
                rng: np.random.Generator, noise: tuple[float, float] = VO_NOISE
                ) -> tuple[float, float]:
    """The frame-to-frame VO's twist at ``t``: the body-frame displacement since the
    previous frame (x, y, theta, stamp) over the interval, plus Gaussian ``noise``
    (m/s, rad/s)."""
    x0, y0, th0, t_prev = frame
    gap = t - t_prev
    c, s = math.cos(th0), math.sin(th0)
    v = (c * (state.x - x0) + s * (state.y - y0)) / gap + rng.normal(0.0, noise[0])
    w = math.remainder(state.theta - th0, 2.0 * math.pi) / gap + rng.normal(0.0, noise[1])
    return v, w


def _vo_loss_episodes(rng: np.random.Generator, surface: str, seconds: float,
                      enabled: bool) -> FloatArray:
    """The VO's tracking-loss episodes [n, 2] (start, end s) over a drive: lasting
    ``SensorParams.failure_duration_s``, at the floor's rate of the recordings (a Poisson
    process on the drive's time, restarting when tracking recovers); none when not
    ``enabled``."""
    params = SensorParams()
    rate_s = params.failure_rate(surface) / 60.0 if enabled else 0.0
    episodes: list[tuple[float, float]] = []
    t = 0.0
    while rate_s > 0.0:
        t += float(rng.exponential(1.0 / rate_s))
        if t >= seconds:
            break
        end = t + float(rng.uniform(*params.failure_duration_s))
        episodes.append((t, end))
        t = end
    return np.array(episodes, dtype=np.float64).reshape(-1, 2)


def _lost_at(episodes: FloatArray) -> Callable[[float], bool]:
    """Whether a time falls in one of the (sorted, disjoint) ``episodes``."""
    starts, ends = episodes[:, 0].copy(), episodes[:, 1].copy()

    def lost(when: float) -> bool:
        i = int(np.searchsorted(starts, when, side="right")) - 1
        return i >= 0 and when < ends[i]
    return lost


def _camera_in_view(camera_yaw: float, lidar: LidarConfig) -> bool:
    """Whether the scanner's field of view holds the camera's whole view
    (``VO_VIEW_RAD`` around ``camera_yaw``)."""
    if not math.isfinite(camera_yaw):
        return False
    if lidar.fov_deg >= 360.0:
        return True
    off = abs(math.remainder(camera_yaw - lidar.mount[2], 2.0 * math.pi))
    return off + VO_VIEW_RAD / 2 <= math.radians(lidar.fov_deg) / 2


def _camera_blind(scan: collision.Scan, mount: tuple[float, float, float],
                  camera_yaw: float = 0.0) -> bool:
    """Whether the camera (looking ``camera_yaw`` from the chair's forward, about at the
    scanner) sees mostly nearer than ``VO_MIN_DEPTH_M`` across ``VO_VIEW_RAD``, as the
    scanner sees that way: no depth, no features, no VO."""
    angles = (scan.angle_min + scan.angle_increment * np.arange(scan.ranges.size) + mount[2]
              - camera_yaw)
    view = np.abs(np.remainder(angles + math.pi, 2.0 * math.pi) - math.pi) <= VO_VIEW_RAD / 2
    near = scan.ranges[view]
    near = np.where(np.isfinite(near), near, np.inf)  # dropouts: no return, far
    return near.size > 0 and float(np.median(near)) < VO_MIN_DEPTH_M


def _scan_check_for(scan: collision.Scan | None, extra: np.ndarray | None, now: float,
                    footprint: collision.Footprint, mount: tuple[float, float, float]
                    ) -> Callable[[Prediction], collision.CollisionCheck | None]:
    """The layer's check of a prediction against the newest scan (and the memory's
    points), as the node builds it; None when the scan is stale."""

    def build(pred: Prediction) -> collision.CollisionCheck | None:
        if scan is None or now - scan.stamp > 0.3:
            return None
        v0, w0 = (float(x) for x in pred.vel_past[-1])
        return collision.scan_check(scan, footprint, mount=mount,
                                    base_motion=collision.constant_twist_motion(
                                        v0, w0, pred.t0 - scan.stamp),
                                    extra=extra)

    return build


def _known_points(scan: collision.Scan, extra: np.ndarray | None, state: ChairState,
                  mount: tuple[float, float, float]) -> np.ndarray:
    """[m, 2] the obstacle points the layer's check gets from ``scan`` (and the memory's
    ``extra``), placed in the room by the chair's true pose when the scan was taken."""
    pts = collision.scan_points(scan)
    if extra is not None and extra.size:
        pts = np.concatenate([pts, extra])
    sx, sy, sth = compose((state.x, state.y, state.theta), mount)
    c, s = math.cos(sth), math.sin(sth)
    out: np.ndarray = pts @ np.array([[c, s], [-s, c]]) + (sx, sy)
    return out


def _footprint_distance(points: np.ndarray, state: ChairState) -> float:
    """Distance (m) from the chair's footprint at ``state`` to the nearest of ``points``
    (inf without any): how close to the touching chair the layer knew of an obstacle."""
    if points.shape[0] == 0:
        return math.inf
    fp = collision.DEFAULT_FOOTPRINT
    c, s = math.cos(state.theta), math.sin(state.theta)
    d = points - (state.x, state.y)
    along = d[:, 0] * c + d[:, 1] * s - fp.offset
    across = -d[:, 0] * s + d[:, 1] * c
    gap = np.hypot(np.maximum(np.abs(along) - 0.5 * fp.length, 0.0),
                   np.maximum(np.abs(across) - 0.5 * fp.width, 0.0))
    return float(gap.min())


def _contact_event(t: float, state: ChairState, user: np.ndarray,
                   applied: tuple[float, float], active: bool, decision: Decision | None,
                   age: float) -> dict[str, float | str]:
    """What the layer knew and did when the chair touched (for inspecting a drive)."""
    event: dict[str, float | str] = {
        "t": round(t, 2), "x": round(state.x, 3), "y": round(state.y, 3),
        "theta_deg": round(math.degrees(state.theta), 1),
        "v": round(state.v, 3), "omega": round(state.omega, 3),
        "user_forward": round(float(user[0]), 3), "user_turn": round(float(user[1]), 3),
        "applied_forward": round(applied[0], 3), "applied_turn": round(applied[1], 3),
        "override": "active" if active else "none"}
    if decision is not None:
        event |= {"decision": decision.why.value, "decision_age_s": round(age, 2),
                  "p_user": round(decision.p_user, 4), "p_command": round(decision.p_command, 4)}
    return event


def drive(model: MotionModel, seconds: float, seed: int, *, layer: bool,
          inattention: float = 0.1, surface: str = "tile",
          config: SharedControlConfig | None = None, horizon_s: float = 2.0,
          lidar: LidarConfig | None = None, margin: float = 0.05,
          memory: MemoryConfig | None = DEFAULT_MEMORY,
          memory_odometry: str = "scan_matching", audit: bool = False,
          vo_noise: tuple[float, float] = VO_NOISE,
          velocity_source: str = "auto", vo_losses: bool = True,
          adapt: AdaptSettings | None = None, camera_yaw: float = 0.0) -> DriveResult:
    """One drive (module docstring); the same ``seed`` gives the same user and floor.
    ``memory``: the layer remembers earlier scans (as the node by default, 10 s; None: the
    newest scan alone), carried along by matching the scans (:mod:`asgp_ros.core.scan_match`,
    ``memory_odometry`` "scan_matching", the node's default) or by dead reckoning of the VO's
    twists ("dead_reckoning"). ``audit``: check the decisions against the plant (module
    docstring; slower). ``vo_noise``: the frame-to-frame VO's noise (m/s, rad/s, one standard
    deviation per twist). ``velocity_source``: where the layer's predictor takes the velocity
    from, as ``shared_control_node``'s ``velocity_source``
    (:class:`~asgp_ros.core.scan_match.VelocitySelector`): "auto" (the matched scans' twists,
    the VO's while they do not match), "vo" or "scan_matching". ``vo_losses``: the VO loses
    tracking (module docstring); False: never. ``camera_yaw``: where the VO's camera looks,
    from the chair's forward (rad): 0, forward, is the worst case for the layer, the losses
    coming as the chair heads for something; the package's camera
    (``vo.extrinsics.DEFAULT_EXTRINSIC``, config/vo.yaml) looks backward, pi. ``adapt``: the
    layer's predictor adapts online (``shared_control_node``'s ``adapt.*``): it learns after
    each decision, nothing from the steps the layer's overrides drove (each is fed to it as it
    goes to the board, at the next step; the node feeds it before learning, and learning takes
    only steps 0.8 s old or more, so the two learn the same)."""
    if velocity_source not in VELOCITY_SOURCES:
        raise ValueError(f"velocity_source must be one of {VELOCITY_SOURCES}, got "
                         f"{velocity_source!r}")
    if not (len(vo_noise) == 2 and all(math.isfinite(x) and 0.0 <= x <= 10.0
                                       for x in vo_noise)):
        raise ValueError(f"vo_noise must be two numbers in [0, 10], got {vo_noise!r}")
    scanner_config = lidar or LidarConfig()
    if vo_losses and not _camera_in_view(camera_yaw, scanner_config):
        # (its losses are read from the scans: a view no beam covers was never blinded)
        raise ValueError(f"camera_yaw {camera_yaw!r}: the camera's view ({VO_VIEW_RAD:.2f} "
                         f"rad wide) is not within the scanner's {scanner_config.fov_deg:g} "
                         "degrees, whose scans tell when it is blinded (a scanner seeing all "
                         "round, fov 360, covers a backward camera)")
    config = config or SharedControlConfig()
    room = room_for_surface(surface)
    ss = np.random.SeedSequence([seed, 21])
    s_chair, s_driver, s_scan, s_vo, s_loss = (int(s.generate_state(1)[0])
                                               for s in ss.spawn(5))
    chair = Chair.for_room(room, seed=s_chair, blocked=room.overlap)
    state = chair.reset((0.0, 0.0, 0.0))
    driver = Driver(s_driver, room, params=DriverParams(inattention=inattention))
    scanner = Lidar(room, lidar, seed=s_scan)
    vo_rng = np.random.default_rng(s_vo)
    cal = fw.default_calibration()
    board = fw.Safety()
    board.set_mode(Mode.OVERRIDE if layer else Mode.PASSTHROUGH, 0)
    if layer:
        collision.prepare()  # as the node at start-up: no import in a decision's time
    rate = float(model.resample_config.rate_hz)
    predictor = Predictor(model, PredictorConfig(horizon_steps=max(1, round(horizon_s * rate))),
                          adapt=adapt)
    mount = scanner.config.mount
    footprint = collision.DEFAULT_FOOTPRINT.grown(margin)
    odometer, scan_odometer = memory_odometers(memory, memory_odometry, mount)
    scan_memory = ScanMemory(mount, memory) if memory is not None else None
    velocity = VelocitySelector(velocity_source)
    velocity_odometer: ScanOdometer | None = None
    if velocity.uses_scans:
        velocity_odometer = scan_odometer or ScanOdometer(mount)
    vo_lost_at = _lost_at(_vo_loss_episodes(np.random.default_rng(s_loss), surface, seconds,
                                            vo_losses))
    camera_blind = False
    extra: np.ndarray | None = None
    known: np.ndarray | None = None  # what the layer's newest check knows, in the room
    true_map: collision.DistanceField | None = None
    if audit:
        g = room_grid(room, AUDIT_MAP_RESOLUTION)
        true_map = collision.DistanceField.from_grid(collision.Grid(g.data, g.resolution,
                                                                    g.origin))
    truth: deque[tuple[int, ChairState]] = deque([(0, state)], maxlen=round(2.0 / STEP_S))

    out = DriveResult(seconds=seconds, layer=layer)
    stick = np.zeros(2)
    scan: collision.Scan | None = None
    decision: Decision | None = None
    decision_t = -math.inf
    sent: np.ndarray | None = None
    last_step: int | None = None
    overriding_steps = 0
    active_before = False
    vo_frame: tuple[float, float, float, float] | None = None  # the VO's previous frame
    n_steps = round(seconds / STEP_S)
    for n in range(n_steps):
        t = n * STEP_S
        scan_fed = False
        now_ms = round(t * 1000)
        if n % JOY_EVERY == 0:
            stick = driver.command(t, state)
        codes = [int(min(1023, max(0, round(c.adc_neutral + min(1.0, max(-1.0, float(d)))
                                            * c.adc_span))))
                 for c, d in zip(cal, stick, strict=True)]
        raw = (codes[0], codes[1])
        user = np.array([cal[0].adc_to_permille(raw[0]), cal[1].adc_to_permille(raw[1])]) \
            / 1000.0

        if layer:
            board.host_alive(now_ms)
            if n % SCAN_EVERY == 0:
                r = scanner.scan(state.x, state.y, state.theta)
                scan = collision.Scan(r.ranges, r.angle_min, r.angle_increment, r.range_min,
                                      r.range_max, stamp=t)
                scan_pose = None
                matcher = scan_odometer or velocity_odometer  # each scan matched once
                if matcher is not None:
                    scan_pose = matcher.add(scan)
                if scan_memory is not None and odometer is not None:
                    extra = scan_memory.add(scan, odometer.pose_at(t), odometer.epoch)
                elif scan_memory is not None and scan_odometer is not None:
                    extra = scan_memory.add(scan, scan_pose, scan_odometer.epoch)
                if vo_losses:
                    camera_blind = _camera_blind(scan, mount, camera_yaw)
                if velocity_odometer is not None:  # as the node: the matched interval's twist
                    give, twist = velocity.scan(t, velocity_odometer.last_twist)
                    if give and twist is None:
                        predictor.feed_vo(t, (math.nan, math.nan), ok=False)
                    elif give and twist is not None:
                        predictor.feed_vo(t, twist)
                    scan_fed = give
                known = _known_points(scan, extra, state, mount)
                if audit:
                    short = short_of_furniture(known, room)
                    out.obstacle_points += short.size
                    for i, d in enumerate(SHORT_OF_FURNITURE_M):
                        out.points_short[i] += int(np.count_nonzero(short > d))
            if decision is not None and decision.command is not None and \
                    t - decision_t <= 0.35 and not is_neutral(user, config.neutral_deadband):
                if n % OVERRIDE_EVERY == 0:
                    c = decision.command
                    board.set_override(round(1000 * c[0]), round(1000 * c[1]),
                                       now_ms)
                    sent = c
                    predictor.feed_override(t, t)
            else:
                sent = None
        output = board.step(cal, raw, now_ms)
        active = bool(output.status & Status.OVERRIDE_ACTIVE)
        applied = (cal[0].dac_to_deflection(output.out_code[0]),
                   cal[1].dac_to_deflection(output.out_code[1]))
        if active:
            overriding_steps += 1
            out.intervention_s += STEP_S
            if not active_before:
                out.interventions += 1
                out.intervention_points.append((state.x, state.y))
        active_before = active
        contacts_before = chair.contacts
        state = chair.step(applied, STEP_S)
        truth.append((n + 1, state))
        if chair.contacts > contacts_before:
            out.contact_points.append((state.x, state.y))
            out.contact_events.append(_contact_event(t, state, user, applied, active,
                                                     decision, t - decision_t))
            if known is not None:
                out.contact_events[-1]["known_obstacle_m"] = round(
                    _footprint_distance(known, state), 3)
        out.min_clearance_m = min(out.min_clearance_m, room.footprint_clearance(
            state.x, state.y, state.theta) - room.furniture_band)
        if n % 50 == 0:
            out.path.append((state.x, state.y))

        if not layer:
            continue
        # the layer's inputs, as the nodes receive them
        if n % JOY_EVERY == 0:
            fed = sent if (sent is not None and active) else user
            predictor.feed_joy(t, fed)
        vel_fed = scan_fed
        if n % VO_EVERY == 3:
            tracking = not (camera_blind or vo_lost_at(t))
            if not tracking:
                out.vo_lost_s += VO_EVERY * STEP_S
            if vo_frame is not None and tracking:  # a lost VO reports nothing
                v, w = frame_twist(vo_frame, state, t, vo_rng, vo_noise)
                if velocity.vo(t):
                    predictor.feed_vo(t, (v, w))
                    vel_fed = True
                if odometer is not None:
                    odometer.feed(t, v, w)
            vo_frame = (state.x, state.y, state.theta, t) if tracking else None
        if vel_fed:
            step = predictor.ready_step()
            if step is not None and (last_step is None or step > last_step):
                last_step = step

                start = time.perf_counter()
                decision = decide(predictor, t, user, None, config,
                                  check_for=_scan_check_for(scan, extra, t, footprint, mount),
                                  learn=False)
                out.solve_ms.append(1e3 * (time.perf_counter() - start))
                predictor.learn()  # as the node: after the decision
                decision_t = t
                out.decisions[decision.why.value] = out.decisions.get(decision.why.value, 0) + 1
                if decision.command is not None:
                    out.changes.append(decision.change)
                if audit and math.isfinite(decision.p_user) and decision.prediction is not None:
                    # the layer's path starts at its last complete grid step, before now: the
                    # replay covers what is left of it, to its last predicted step
                    ahead = max(0.0, float(decision.prediction.times[-1]) - t)
                    closest, touched = held_clearance(chair, room, decision.user, ahead)
                    origin = _truth_at(truth, round(decision.prediction.t0 / STEP_S))
                    p_map = math.nan if origin is None or true_map is None else \
                        map_probability(true_map, decision.prediction, origin, footprint,
                                        config)
                    out.audit.append(AuditRow(t, decision.p_user, decision.command is not None,
                                              closest, touched, ahead, p_map))
    out.contacts = chair.contacts
    out.velocity_switches = velocity.switches
    if (stats := predictor.adaptation) is not None:
        out.adaptation = {"rows_absorbed": stats.rows_absorbed,
                          "steps_refused": stats.steps_refused,
                          "adapted_published": int(stats.published == "adapted"),
                          "scale_max": round(max(stats.scales), 3),
                          "coverage_95": round(stats.coverage, 4)}
    out.untouched_share = 1.0 - overriding_steps / max(n_steps, 1)
    return out
