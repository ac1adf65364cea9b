"""ROS 2 node: the simulated wheelchair hardware of the demo.

Wraps :class:`asgp_ros.demo.simhw.SimulatedHardware` (driver, joystick board on a pty,
chair, RGB-D camera) and publishes what the real hardware would, plus what only a
simulator knows:

* the board speaks the real protocol on its pty (``port``, a symlink): the serial bridge
  node opens it and publishes ``joy``; the chair follows the board's analog output;
* ``camera/color/image_raw`` (bgr8), ``camera/depth/image_raw`` (16UC1, mm) and
  ``camera/color/camera_info`` at ``camera_rate_hz``, rendered from the chair's true pose
  and stamped with the time of that pose (sensor-data QoS);
* ``ground_truth/odom`` (nav_msgs/Odometry, ``odom`` -> ``base_link``, exact) at
  ``truth_rate_hz`` (reliable);
* ``joy_plan`` (trajectory_msgs/JointTrajectory, joints ``forward`` and ``turn``) once per
  grid step of the predictor (``plan_rate_hz``), published just after the grid time ``g``
  and stamped ``g + 1 / plan_rate_hz``: point r, at ``r / plan_rate_hz`` from the stamp, is
  the joystick the bridge will report at ``g + (r + 1) / plan_rate_hz`` (a look-ahead of
  the driver on a copy of the simulation, see :mod:`asgp_ros.demo.simhw`); ``plan_rows: 0``
  publishes no plan;
* ``scan`` (sensor_msgs/LaserScan, ``laser_frame``) at ``scan_rate_hz`` from the simulated
  2-D scanner (:mod:`asgp_ros.sim.lidar`), and ``map`` (nav_msgs/OccupancyGrid in
  ``odom_frame``, transient local) once: what a shared-control layer looks at;
* ``diagnostics``: simulation lag, camera and plan timing, the chair's contacts with the
  furniture (the driver is inattentive with ``inattention`` > 0).

Time: the drive starts, aligned to the plan grid, once the bridge publishes ``joy`` and the
camera and plan topics have subscribers (or after ``start_timeout_s``); simulation time t
is stamped ``t_start + t`` on the node clock. A thread paces the closed loop (10 ms chair
steps) against the monotonic clock; it hands its outputs to the executor through guard
conditions, so every ROS call happens in the executor thread.

Run: ``python -m asgp_ros.demo.hardware --ros-args -p port:=/tmp/asgp_joystick``
"""

from __future__ import annotations

import math
import signal
import sys
import threading
import time
from collections import deque
from dataclasses import MISSING, dataclass, fields
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import OccupancyGrid, Odometry
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, Image, Joy, LaserScan
from trajectory_msgs.msg import JointTrajectory

from asgp_ros.common import topics
from asgp_ros.common.paramspec import ParamValue
from asgp_ros.demo import camera
from asgp_ros.demo.simhw import STEP_S, HardwareConfig, SimulatedHardware, Snapshot, look_ahead
from asgp_ros.nodes import conversions as conv
from asgp_ros.nodes.runtime import log_file_arguments
from asgp_ros.sim.chair import ChairState
from asgp_ros.sim.lidar import room_grid

NODE_NAME = "demo_hardware"


class StartupError(Exception):
    """The node cannot start (invalid parameters)."""


@dataclass(frozen=True)
class HardwareNodeParams:
    """The node's parameters (validated on construction)."""

    seed: int = 0
    surface: str = "tile"
    port: str = ""
    camera_rate_hz: float = 15.0
    width: int = 320
    height: int = 240
    truth_rate_hz: float = 50.0
    plan_rate_hz: float = 5.0
    plan_rows: int = 13
    start_timeout_s: float = 60.0
    camera_frame: str = "camera_color_optical_frame"
    odom_frame: str = "odom"
    base_frame: str = "base_link"
    diagnostics_period_s: float = 1.0
    inattention: float = 0.0
    scan_rate_hz: float = 10.0
    laser_frame: str = "laser"

    def __post_init__(self) -> None:
        HardwareConfig(seed=self.seed, surface=self.surface, width=self.width,
                       height=self.height, inattention=self.inattention)
        if not (math.isfinite(self.scan_rate_hz) and 0.0 <= self.scan_rate_hz <= 50.0):
            raise ValueError(f"scan_rate_hz must be in [0, 50], got {self.scan_rate_hz}")
        for name, lo, hi in (("camera_rate_hz", 0.5, 60.0), ("truth_rate_hz", 1.0, 100.0),
                             ("plan_rate_hz", 0.5, 50.0), ("start_timeout_s", 0.0, 600.0),
                             ("diagnostics_period_s", 0.1, 60.0)):
            value = getattr(self, name)
            if not (math.isfinite(value) and lo <= value <= hi):
                raise ValueError(f"{name} must be in [{lo}, {hi}], got {value}")
        for name in ("truth_rate_hz", "plan_rate_hz"):
            steps = 1.0 / (getattr(self, name) * STEP_S)
            if abs(steps - round(steps)) > 1e-6:
                raise ValueError(f"{name} must divide the chair's {1 / STEP_S:g} Hz")
        if not 0 <= self.plan_rows <= 200:
            raise ValueError(f"plan_rows must be in [0, 200], got {self.plan_rows}")

    def every(self, rate_hz: float) -> int:
        """Chair steps per period of ``rate_hz``."""
        return round(1.0 / (rate_hz * STEP_S))


_DESCRIPTIONS = {
    "seed": ("seed of the driver, the chair and the sensor noise", (0, 2**31 - 1)),
    "surface": ("floor of the demo room: tile, carpet or hybrid", None),
    "port": ("path of the board's port (a symlink to its pty); empty: the pty itself", None),
    "camera_rate_hz": ("RGB-D frame rate", (0.5, 60.0)),
    "width": ("image width (px)", (64, 1920)),
    "height": ("image height (px)", (48, 1080)),
    "truth_rate_hz": ("ground-truth odometry rate (divides 100 Hz)", (1.0, 100.0)),
    "plan_rate_hz": ("joy_plan rate = the predictor's grid rate (divides 100 Hz)", (0.5, 50.0)),
    "plan_rows": ("rows of each joy_plan; 0 = no plan (the predictor holds the command)",
                  (0, 200)),
    "start_timeout_s": ("start driving after this long even if bridge, VO or predictor are "
                        "not there yet", (0.0, 600.0)),
    "camera_frame": ("frame_id of the images (optical frame)", None),
    "odom_frame": ("frame of the ground-truth pose", None),
    "base_frame": ("child frame of the ground-truth odometry", None),
    "diagnostics_period_s": ("diagnostics period", (0.1, 60.0)),
    "inattention": ("probability that a bout of the driver is inattentive (heads for the "
                    "furniture, reacts late); 0 = an attentive driver", (0.0, 1.0)),
    "scan_rate_hz": ("2-D laser scan rate; 0 = no scanner", (0.0, 50.0)),
    "laser_frame": ("frame_id of the scans (the scanner's mount on the chair)", None),
}


def _descriptor(name: str, default: ParamValue) -> ParameterDescriptor:
    text, rng = _DESCRIPTIONS[name]
    d = ParameterDescriptor(description=text, read_only=True)
    if rng is not None:
        if isinstance(default, int):
            d.integer_range = [IntegerRange(from_value=int(rng[0]), to_value=int(rng[1]),
                                            step=0)]
        else:
            d.floating_point_range = [FloatingPointRange(from_value=float(rng[0]),
                                                         to_value=float(rng[1]), step=0.0)]
    return d


class _Timing:
    """Durations of a repeated job (ms): count, mean, max."""

    def __init__(self) -> None:
        self.n = 0
        self.total = 0.0
        self.max = 0.0

    def add(self, seconds: float) -> None:
        ms = 1e3 * seconds
        self.n += 1
        self.total += ms
        self.max = max(self.max, ms)

    def mean(self) -> float:
        return self.total / self.n if self.n else float("nan")


class HardwareNode(Node):
    """See the module docstring."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        for f in fields(HardwareNodeParams):
            if f.default is MISSING:
                raise TypeError(f"HardwareNodeParams.{f.name} has no default")
            self.declare_parameter(f.name, f.default, _descriptor(f.name, f.default))
        try:
            self.params = HardwareNodeParams(**{
                f.name: self.get_parameter(f.name).value for f in fields(HardwareNodeParams)})
        except (ValueError, TypeError) as exc:
            raise StartupError(f"invalid parameters: {exc}") from exc
        p = self.params
        self.hw = SimulatedHardware(
            HardwareConfig(seed=p.seed, surface=p.surface, width=p.width, height=p.height,
                           inattention=p.inattention),
            link_path=p.port or None)
        self.hw.renderer  # build the textured room now, not in the first frame  # noqa: B018

        sensor = qos_profile_sensor_data
        reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.color_pub = self.create_publisher(Image, topics.CAMERA_COLOR, sensor)
        self.depth_pub = self.create_publisher(Image, topics.CAMERA_DEPTH, sensor)
        self.info_pub = self.create_publisher(CameraInfo, topics.CAMERA_INFO, sensor)
        self.truth_pub = self.create_publisher(Odometry, topics.GROUND_TRUTH, reliable)
        self.plan_pub = self.create_publisher(JointTrajectory, topics.JOY_PLAN, reliable)
        self.diag_pub = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, reliable)
        self.scan_pub = self.create_publisher(LaserScan, topics.SCAN, sensor)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.map_pub = self.create_publisher(OccupancyGrid, topics.MAP, latched)
        grid = room_grid(self.hw.room)
        self.map_pub.publish(conv.grid_to_msg(grid.data, grid.resolution, grid.origin,
                                              self.get_clock().now().nanoseconds * 1e-9,
                                              p.odom_frame))
        self.scans = 0
        self._joy_sub = self.create_subscription(Joy, topics.JOY, self._on_joy, sensor)

        self._joy_seen = False
        self._t_start: float | None = None  # node-clock seconds of simulation time 0
        self._created = time.monotonic()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._truth: deque[tuple[float, ChairState]] = deque(maxlen=1000)
        self._snaps: deque[Snapshot] = deque(maxlen=4)
        self._truth_gc = self.create_guard_condition(self._publish_truth)
        self._plan_gc = self.create_guard_condition(self._publish_plan)
        self._last_frame_t = -1.0
        self.frames = 0
        self.plans = 0
        self.plans_skipped = 0
        self.render_time = _Timing()
        self.plan_time = _Timing()
        self.max_lag_s = 0.0
        self.lag_s = 0.0
        self.sim_error: BaseException | None = None
        self._start_timer = self.create_timer(0.1, self._check_start)
        self.create_timer(1.0 / p.camera_rate_hz, self._on_camera)
        if p.scan_rate_hz > 0.0:
            self.create_timer(1.0 / p.scan_rate_hz, self._on_scan)
        self.create_timer(p.diagnostics_period_s, self._publish_diagnostics)
        # the board (its pty and the link to it) last, and taken down if the start-up is cut
        # short: a signal while the room was built left the link behind, pointing at
        # whichever pty next took its number (and `asgp board --link` then refused it)
        try:
            port = self.hw.start_board()
            self.get_logger().info(f"simulated joystick board on {port}")
        except BaseException:
            self.hw.stop()
            self.destroy_node()  # (off the graph: a later demo on the domain saw it there)
            raise

    # ---- start-up --------------------------------------------------------------------

    def _on_joy(self, _msg: Joy) -> None:
        if not self._joy_seen:
            self._joy_seen = True
            self.get_logger().info("the serial bridge publishes joy: the board link is up")
            self.destroy_subscription(self._joy_sub)

    def _missing(self) -> list[str]:
        missing = []
        if not self._joy_seen:
            missing.append("joy from the serial bridge")
        if self.color_pub.get_subscription_count() == 0:
            missing.append("a camera subscriber (VO)")
        if self.params.plan_rows and self.plan_pub.get_subscription_count() == 0:
            missing.append("a joy_plan subscriber (predictor)")
        return missing

    def _check_start(self) -> None:
        missing = self._missing()
        waited = time.monotonic() - self._created
        if missing and waited < self.params.start_timeout_s:
            return
        if missing:
            self.get_logger().warning(
                f"starting the drive after {waited:.1f} s without {', '.join(missing)}")
        self._start_timer.cancel()
        self.destroy_timer(self._start_timer)
        self._start_drive()

    def _start_drive(self) -> None:
        grid = 1.0 / self.params.plan_rate_hz
        now = self.get_clock().now().nanoseconds * 1e-9
        # simulation time 0 on a grid time, so grid times are whole chair steps
        self._t_start = (math.floor(now / grid) + 2) * grid
        mono0 = time.monotonic() + (self._t_start - now)
        self.get_logger().info(
            f"driving from t = {self._t_start:.1f} s (seed {self.params.seed}, "
            f"{self.params.surface})")
        self._thread = threading.Thread(target=self._run, args=(mono0,),
                                        name="asgp-demo-sim", daemon=True)
        self._thread.start()

    # ---- the paced closed loop (its own thread) -------------------------------------

    def _run(self, mono0: float) -> None:
        p = self.params
        truth_every = p.every(p.truth_rate_hz)
        plan_every = p.every(p.plan_rate_hz)
        hw = self.hw
        try:
            while not self._stop.is_set():
                target = math.floor((time.monotonic() - mono0) / STEP_S)
                self.lag_s = max(0.0, (target - hw.step_index) * STEP_S)
                self.max_lag_s = max(self.max_lag_s, self.lag_s)
                while hw.step_index <= target and not self._stop.is_set():
                    n = hw.step_index
                    if p.plan_rows and n % plan_every == 0:
                        self._snaps.append(hw.snapshot())
                        self._plan_gc.trigger()
                    if n % truth_every == 0:
                        self._truth.append((hw.t, hw.state))
                        self._truth_gc.trigger()
                    hw.step()
                delay = mono0 + hw.step_index * STEP_S - time.monotonic()
                if delay > 0.0:
                    self._stop.wait(delay)
        except Exception as exc:  # the thread's top level: report, the node goes silent
            self.sim_error = exc
            self.get_logger().error(f"simulation stopped: {type(exc).__name__}: {exc}")

    # ---- publishing (executor thread) ------------------------------------------------

    def _stamp(self, t: float) -> float:
        assert self._t_start is not None
        return self._t_start + t

    def _publish_truth(self) -> None:
        p = self.params
        while self._truth:
            t, s = self._truth.popleft()
            self.truth_pub.publish(conv.odometry_from_pose(
                self._stamp(t), s.x, s.y, s.theta, s.v, s.omega, p.odom_frame, p.base_frame))

    def _publish_plan(self) -> None:
        msg = self._plan_message()
        if msg is not None:
            self.plan_pub.publish(msg)
            self.plans += 1

    def _plan_message(self) -> JointTrajectory | None:
        """The newest look-ahead as a stamped plan (older queued ones are skipped), or None
        when there is none or the context is shutting down."""
        if not self._snaps:
            return None
        snap = self._snaps.pop()
        self.plans_skipped += len(self._snaps)
        self._snaps.clear()
        start = time.perf_counter()
        plan = look_ahead(snap, self.hw.path, 1.0 / self.params.plan_rate_hz,
                          self.params.plan_rows)
        self.plan_time.add(time.perf_counter() - start)
        if not self.context.ok():
            return None
        grid = 1.0 / self.params.plan_rate_hz
        stamp = self._stamp(snap.step * STEP_S + grid)  # row 0 is the stick at g + grid
        return conv.plan_to_trajectory(plan, stamp, grid)

    def _on_camera(self) -> None:
        if self._t_start is None or self.hw.step_index == 0:
            return  # not before the drive's first step: its stamp would lead the clock
        state = self.hw.state
        if state.t <= self._last_frame_t:
            return
        self._last_frame_t = state.t
        start = time.perf_counter()
        image, depth = self.hw.render(state)
        self.render_time.add(time.perf_counter() - start)
        if not self.context.ok():  # shut down by a signal while rendering
            return
        t = self._stamp(round(state.t / STEP_S) * STEP_S)
        frame = self.params.camera_frame
        K = self.hw.renderer.K
        self.color_pub.publish(camera.image_from_array(t, image, frame))
        self.depth_pub.publish(camera.image_from_array(t, depth, frame))
        self.info_pub.publish(camera.camera_info_from_matrix(t, K, image.shape[1],
                                                           image.shape[0], frame))
        self.frames += 1

    def _on_scan(self) -> None:
        if self._t_start is None or self.hw.step_index == 0:
            return  # not before the drive's first step: its stamp would lead the clock
        state = self.hw.state
        scan = self.hw.lidar.scan(state.x, state.y, state.theta)
        t = self._stamp(round(state.t / STEP_S) * STEP_S)
        self.scan_pub.publish(conv.scan_to_msg(
            scan.ranges, scan.angle_min, scan.angle_increment, scan.range_min,
            scan.range_max, t, self.params.laser_frame, 1.0 / self.params.scan_rate_hz))
        self.scans += 1

    def _publish_diagnostics(self) -> None:
        running = self._t_start is not None and self.sim_error is None
        if self.sim_error is not None:
            level, msg = "ERROR", f"simulation stopped: {self.sim_error}"
        elif not running:
            level, msg = "WARN", "waiting for " + ", ".join(self._missing() or ["start"])
        else:
            level, msg = "OK", f"driving, t = {self.hw.t:.1f} s"
            if self.lag_s > 0.1:
                level, msg = "WARN", msg + f", {self.lag_s:.2f} s behind real time"
        values = {
            "sim_time_s": self.hw.t, "driver_mode": self.hw.driver.mode,
            "lag_s": self.lag_s, "max_lag_s": self.max_lag_s, "port": self.hw.port,
            "frames": self.frames, "render_mean_ms": self.render_time.mean(),
            "render_max_ms": self.render_time.max, "plans": self.plans,
            "plans_skipped": self.plans_skipped, "plan_mean_ms": self.plan_time.mean(),
            "plan_max_ms": self.plan_time.max,
            "board_frames_dropped": 0 if self.hw.board is None else self.hw.board.frames_dropped,
            "contacts": self.hw.contacts, "scans": self.scans,
            "min_clearance_m": round(self.hw.min_clearance, 3),
        }
        status = conv.diagnostic_status(f"{self.get_name()}: simulation", level, msg,
                                        self.hw.port, values)
        self.diag_pub.publish(conv.diagnostic_array(
            self.get_clock().now().nanoseconds * 1e-9, [status]))

    def destroy_node(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        self.hw.stop()
        super().destroy_node()  # type: ignore[no-untyped-call]


def main(args: list[str] | None = None,
         node_class: type[HardwareNode] = HardwareNode) -> int:
    """Runs the node (or ``node_class``, a subclass) until SIGINT or SIGTERM; exit code 0,
    1 when its parameters are refused.

    rclpy's signal handlers shut the context down from their own thread, whatever the
    executor is doing: a publication under way in a callback then fails (RCLError,
    "publisher's context is invalid"). After a shutdown that is the stop it looks like,
    not a crash (as in vo_node and predictor_node)."""
    extra, problem = log_file_arguments()  # (a read-only log directory: no file)
    rclpy.init(args=[*(sys.argv if args is None else args), *extra])
    if problem:
        rclpy.logging.get_logger("demo_hardware").warning(problem)
    # a stop held while the process started (the demo starts it with the stop signals
    # blocked, asgp_ros.demo.child) is taken now, by rclpy's handlers
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
    node: HardwareNode | None = None
    try:
        node = node_class()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except StartupError as exc:
        rclpy.logging.get_logger(NODE_NAME).fatal(f"refusing to start: {exc}")
        return 1
    except Exception:
        if rclpy.utilities.ok():
            raise
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.utilities.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
