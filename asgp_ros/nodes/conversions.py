"""ROS message <-> numpy conversions, the only place nodes touch message fields.

Every function here is pure (no node, no publisher) and tested by building messages
directly. Sections are grouped by message family. The demo's simulated camera (images and
camera info out) is in :mod:`asgp_ros.demo.camera`.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np
from builtin_interfaces.msg import Duration, Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped, TwistStamped
from nav_msgs.msg import OccupancyGrid, Odometry, Path
from numpy.typing import ArrayLike, NDArray
from sensor_msgs.msg import CameraInfo, Image, Joy, LaserScan
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
from visualization_msgs.msg import Marker, MarkerArray

from asgp_ros.core import collision, streams
from asgp_ros.core.online import MAX_PLAN_STEPS
from asgp_ros.core.quaternion import quaternion_to_yaw, yaw_to_quaternion
from asgp_ros.recording.bags import JoyAxes
from asgp_ros.recording.bags import velocity_frame_problem as bags_velocity_frame_problem

FloatArray = NDArray[np.float64]

# --------------------------------------------------------------------------------------
# Predictor: time, Joy, TwistStamped / Odometry, JointTrajectory plans, Path, MarkerArray


def stamp_to_seconds(stamp: Time) -> float:
    """builtin_interfaces/Time -> seconds (float), computed as the bag reader does
    (integer nanoseconds * 1e-9), so live and recorded stamps are bit-identical."""
    return float(int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)) * 1e-9


def seconds_to_stamp(t: float) -> Time:
    """Seconds (>= 0) -> builtin_interfaces/Time (rounded to the nanosecond)."""
    ns = round(t * 1e9)
    if ns < 0:
        raise ValueError(f"cannot stamp a negative time ({t} s)")
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def _quaternion(yaw: float) -> tuple[float, float, float, float]:
    """Yaw -> quaternion (x, y, z, w) as the Python floats message fields take."""
    x, y, z, w = yaw_to_quaternion(yaw)
    return float(x), float(y), float(z), float(w)


def joy_to_sample(msg: Joy, forward_axis: int = 0, turn_axis: int = 1
                  ) -> tuple[float, tuple[float, float]]:
    """sensor_msgs/Joy -> (stamp s, (forward, turn)); stamp 0.0 if the header is unset.

    Raises:
        ValueError: the message has too few axes.
    """
    axes = msg.axes
    if len(axes) <= max(forward_axis, turn_axis):
        raise ValueError(
            f"Joy has {len(axes)} axes; forward axis {forward_axis} and turn axis "
            f"{turn_axis} are needed"
        )
    return (stamp_to_seconds(msg.header.stamp),
            (float(axes[forward_axis]), float(axes[turn_axis])))


def joy_command(msg: Joy, axes: JoyAxes) -> tuple[float, NDArray[np.float64]]:
    """sensor_msgs/Joy -> (stamp s, [forward, turn]) read with ``axes`` (the indices and the
    signs of ``--joy-axes`` / ``joy_axes``: + forward, + left); raises as ``joy_to_sample``."""
    t, (fwd, turn) = joy_to_sample(msg, axes.forward, axes.turn)
    return t, np.array([axes.forward_sign * fwd, axes.turn_sign * turn])


def joy_from_sample(t: float, forward: float, turn: float, frame_id: str = "",
                    axes: JoyAxes | None = None) -> Joy:
    """(stamp s, forward, turn) -> sensor_msgs/Joy with axes [forward, turn], or laid out
    and signed as ``axes`` says (the inverse of :func:`joy_command`: an override written
    in the convention of the ``joy`` it changes)."""
    msg = Joy()
    msg.header.stamp = seconds_to_stamp(t)
    msg.header.frame_id = frame_id
    if axes is None:
        msg.axes = [float(forward), float(turn)]
    else:
        values = [0.0] * (max(axes.forward, axes.turn) + 1)
        values[axes.forward] = axes.forward_sign * float(forward)
        values[axes.turn] = axes.turn_sign * float(turn)
        msg.axes = values
    return msg


def twist_stamped_to_sample(msg: TwistStamped) -> tuple[float, tuple[float, float]]:
    """geometry_msgs/TwistStamped -> (stamp s, (v = linear.x, omega = angular.z))."""
    tw = msg.twist
    return (stamp_to_seconds(msg.header.stamp),
            (float(tw.linear.x), float(tw.angular.z)))


def twist_stamped_from_sample(t: float, v: float, omega: float,
                              frame_id: str = "base_link") -> TwistStamped:
    """(stamp s, v, omega) -> geometry_msgs/TwistStamped."""
    msg = TwistStamped()
    msg.header.stamp = seconds_to_stamp(t)
    msg.header.frame_id = frame_id
    msg.twist.linear.x = float(v)
    msg.twist.angular.z = float(omega)
    return msg


def frame_name(frame_id: str) -> str:
    """A frame_id as tf2 reads it: without a leading slash ('/base_link' is 'base_link')."""
    return frame_id.lstrip("/")


def pose_frame_problem(msg: Odometry, odom_frame: str) -> str | None:
    """Why an Odometry's pose is not one of base_link in ``odom_frame`` (its header frame
    is another, 'map' say: a path labelled odom, or a map, would be placed wrong), or None
    (that frame, or none given)."""
    parent = frame_name(msg.header.frame_id)
    if parent in ("", frame_name(odom_frame)):
        return None
    return f"poses in frame {parent!r}, not odom_frame {odom_frame!r}: not taken"


def velocity_frame(msg: TwistStamped | Odometry) -> str:
    """The frame a VO message's twist is in: a TwistStamped's header frame, an Odometry's
    child frame ('' when the publisher left it empty)."""
    return str(msg.child_frame_id if isinstance(msg, Odometry) else msg.header.frame_id)


def velocity_frame_problem(frame: str, base_frame: str) -> str | None:
    """Why a twist in ``frame`` cannot be read as the chair's forward and turn rates
    (linear.x, angular.z of ``base_frame``), or None: the bags' rule
    (:func:`asgp_ros.recording.bags.velocity_frame_problem`), in a node's words."""
    problem = bags_velocity_frame_problem(frame, base_frame)
    return None if problem is None else \
        f"VO {problem} (set base_frame if that is the chair's frame)"


class VelocityFrameCheck:
    """A node's check of its VO messages' frame (:func:`velocity_frame_problem`): how many
    were refused, and why the newest was (cleared by one in the base frame)."""

    def __init__(self, base_frame: str) -> None:
        self.base_frame = base_frame
        self.refused = 0
        self.problem = ""

    def ok(self, msg: TwistStamped | Odometry, logger: Any) -> bool:
        """Whether ``msg``'s twist is in the base frame; if not, it is counted, and the
        reason kept and logged (throttled)."""
        problem = velocity_frame_problem(velocity_frame(msg), self.base_frame)
        if problem is None:
            self.problem = ""
            return True
        self.refused += 1
        self.problem = problem
        logger.warning(problem, throttle_duration_sec=5.0)
        return False

    def values(self) -> dict[str, str]:
        """The diagnostics' values: ``vo_frame`` (the reason, or "ok") and ``vo_other_frame``."""
        return {"vo_frame": self.problem or "ok", "vo_other_frame": str(self.refused)}


#: Odometry twist variance at or above which a velocity is taken as a tracking failure.
ODOM_LOST_VARIANCE = streams.ODOM_LOST_VARIANCE


def odometry_to_sample(msg: Odometry) -> tuple[float, tuple[float, float], bool,
                                              tuple[float, float, float]]:
    """nav_msgs/Odometry -> (stamp s, (v, omega), tracking ok, (x, y, yaw) in the odom frame).

    Tracking is taken as lost when the twist is not finite or the variance of its linear x
    or of its angular z (the two velocities taken) is negative, non-finite or >=
    ``ODOM_LOST_VARIANCE`` (how odometry sources flag an unusable estimate), or when the
    pose's quaternion is not a rotation.
    """
    tw = msg.twist
    v, w = float(tw.twist.linear.x), float(tw.twist.angular.z)
    ok = streams.twist_tracked(v, w, float(tw.covariance[0]), float(tw.covariance[35]))
    p = msg.pose.pose
    q = p.orientation
    yaw, unit = _yaw_of(q)
    # a quaternion that is not a rotation (not of unit length) gives no yaw to trust: the
    # sample is a lost one (no pose, no velocity), as tf2 refuses such a transform
    return (stamp_to_seconds(msg.header.stamp), (v, w), ok and unit,
            (float(p.position.x), float(p.position.y), yaw))


#: How far from 1 a quaternion's length may be (tf2's own limit): a rotation written with
#: a few digits; beyond, it is not a rotation (``quaternion_to_yaw`` assumes one: (0, 0,
#: 0.5, 0.5), 90 degrees half-written, read as 45).
QUATERNION_NORM_TOLERANCE = 0.01


def _yaw_of(q: Any) -> tuple[float, bool]:
    """(yaw of the normalised quaternion, whether it is of unit length within tolerance)."""
    c = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
    norm = float(np.linalg.norm(c))
    if not (math.isfinite(norm) and abs(norm - 1.0) <= QUATERNION_NORM_TOLERANCE):
        return math.nan, False
    c /= norm
    return float(quaternion_to_yaw(*c)), True


PLAN_JOINTS = ("forward", "turn")
"""Joint names of a ``joy_plan`` trajectory: the two joystick deflections."""


def _duration_s(d: Duration) -> float:
    return float(d.sec) + 1e-9 * float(d.nanosec)


def plan_from_trajectory(msg: JointTrajectory, dt: float, arrival: float | None = None
                         ) -> tuple[float, FloatArray]:
    """trajectory_msgs/JointTrajectory -> (start stamp s, [m, 2] rows dt apart).

    The plan's contract (README, "ROS interface"): ``joint_names`` are ``forward`` and
    ``turn`` (either order), ``positions`` hold the deflections in [-1, 1], and
    ``header.stamp + time_from_start`` is when a point's command starts; it holds until the
    next point's (the last point's is held). The rows are that command sampled at
    ``start + r * dt``, start = the first point's time (zero-order hold, so points dt
    apart map one to one). A zero ``header.stamp`` means "starts on receipt" (the
    trajectory_msgs convention): ``arrival`` (the receiving clock's time) is used instead.

    Raises:
        ValueError: other joint names, no points, positions of the wrong length, times
            not strictly increasing or negative, more than
            ``asgp_ros.core.online.MAX_PLAN_STEPS`` rows (checked before sampling), or
            non-finite values. The values' range is the Predictor's check.
    """
    if not (math.isfinite(dt) and dt > 0.0):
        raise ValueError(f"dt must be a positive number of seconds, got {dt}")
    names = list(msg.joint_names)
    if sorted(names) != sorted(PLAN_JOINTS):
        raise ValueError(f"joy_plan joint_names must be {list(PLAN_JOINTS)}, got {names}")
    order = [names.index(j) for j in PLAN_JOINTS]
    points = list(msg.points)
    if not points:
        raise ValueError("joy_plan has no points")
    if len(points) > MAX_PLAN_STEPS:
        raise ValueError(f"joy_plan has {len(points)} points, more than {MAX_PLAN_STEPS}")
    times = np.array([_duration_s(p.time_from_start) for p in points])
    if times[0] < 0.0 or np.any(np.diff(times) <= 0.0):
        raise ValueError("joy_plan time_from_start must be >= 0 and strictly increasing")
    span = (times[-1] - times[0]) / dt
    if not span < MAX_PLAN_STEPS:
        raise ValueError(f"joy_plan spans {times[-1] - times[0]:.3f} s, more than "
                         f"{MAX_PLAN_STEPS} steps of {dt} s")
    values = np.empty((len(points), 2))
    for i, p in enumerate(points):
        if len(p.positions) != 2:
            raise ValueError(f"joy_plan point {i} has {len(p.positions)} positions, "
                             "expected 2")
        values[i] = [p.positions[j] for j in order]
    if not np.all(np.isfinite(values)):
        raise ValueError("joy_plan contains NaN or inf")
    m = math.floor(span + 1e-6) + 1
    sample = times[0] + dt * np.arange(m)
    which = np.searchsorted(times, sample + 1e-9, side="right") - 1  # [m], >= 0
    start = stamp_to_seconds(msg.header.stamp)
    if start == 0.0 and arrival is not None:
        start = arrival
    return start + float(times[0]), values[which]


def plan_to_trajectory(plan: ArrayLike, stamp: float, dt: float) -> JointTrajectory:
    """[m, 2] joystick rows dt apart from ``stamp`` -> trajectory_msgs/JointTrajectory."""
    arr = np.asarray(plan, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2 or arr.shape[0] == 0:
        raise ValueError(f"a plan must be [m, 2] with m >= 1, got {arr.shape}")
    if not (math.isfinite(dt) and dt > 0.0):
        raise ValueError(f"dt must be a positive number of seconds, got {dt}")
    msg = JointTrajectory()
    msg.header.stamp = seconds_to_stamp(stamp)
    msg.joint_names = list(PLAN_JOINTS)
    points = []
    for r, row in enumerate(arr):
        ns = round(r * dt * 1e9)
        points.append(JointTrajectoryPoint(
            positions=[float(row[0]), float(row[1])],
            time_from_start=Duration(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)))
    msg.points = points
    return msg


def path_from_poses(poses: ArrayLike, times: ArrayLike, frame_id: str, stamp: float) -> Path:
    """[k, 3] (x, y, theta) poses at [k] times -> nav_msgs/Path (header at ``stamp``)."""
    pose_arr, time_arr, qz, qw = _path_arrays(poses, times)
    msg = Path()
    msg.header.stamp = seconds_to_stamp(stamp)
    msg.header.frame_id = frame_id
    out = []
    for (x, y, _), t, z, w in zip(pose_arr.tolist(), time_arr.tolist(), qz, qw, strict=True):
        ps = PoseStamped()
        ps.header.stamp = seconds_to_stamp(t)
        ps.header.frame_id = frame_id
        ps.pose.position.x = x
        ps.pose.position.y = y
        ps.pose.orientation.z, ps.pose.orientation.w = z, w
        out.append(ps)
    msg.poses = out
    return msg


def _path_arrays(poses: ArrayLike, times: ArrayLike
                 ) -> tuple[FloatArray, FloatArray, list[float], list[float]]:
    """The poses [k, 3] and times [k] of a path, and its orientations' z and w."""
    pose_arr = np.asarray(poses, dtype=np.float64)
    time_arr = np.asarray(times, dtype=np.float64)
    if pose_arr.ndim != 2 or pose_arr.shape[1] != 3 or time_arr.shape != pose_arr.shape[:1]:
        raise ValueError(f"a path needs poses [k, 3] and times [k], got {pose_arr.shape} "
                         f"and {time_arr.shape}")
    _, _, qz, qw = yaw_to_quaternion(pose_arr[:, 2])
    return pose_arr, time_arr, np.atleast_1d(qz).tolist(), np.atleast_1d(qw).tolist()


#: CDR's encapsulation header: plain CDR, little endian (what rclpy writes on x86 and ARM).
_CDR_LE = b"\x00\x01\x00\x00"


def path_cdr(poses: ArrayLike, times: ArrayLike, frame_id: str, stamp: float) -> bytes:
    """:func:`path_from_poses`'s message, serialized (CDR, as ``rclpy.serialization``
    writes it), for ``Publisher.publish``. Building the message and rclpy's conversion of
    it took 0.3-0.6 ms for ten poses, in each path's latency; this takes a tenth of that.

    Raises:
        ValueError: a negative stamp or one beyond a message's int32 seconds, or poses and
            times of different lengths.
    """
    pose_arr, time_arr, qz, qw = _path_arrays(poses, times)
    frame = frame_id.encode("utf-8") + b"\0"
    header_tail = struct.pack("<I", len(frame)) + frame
    out = bytearray(_CDR_LE)

    def pad(n: int) -> bytes:  # CDR aligns from the end of the encapsulation header
        return bytes(-(len(out) - len(_CDR_LE)) % n)

    out += _cdr_stamp(stamp) + header_tail
    out += pad(4) + struct.pack("<I", pose_arr.shape[0])
    for (x, y, _), t, z, w in zip(pose_arr.tolist(), time_arr.tolist(), qz, qw, strict=True):
        out += pad(4) + _cdr_stamp(t) + header_tail
        out += pad(8) + struct.pack("<7d", x, y, 0.0, 0.0, 0.0, z, w)
    return bytes(out)


#: The last second a message's stamp holds (builtin_interfaces/Time's int32 seconds: 2038).
MAX_STAMP_S = 2**31 - 1


def _cdr_stamp(t: float) -> bytes:
    """builtin_interfaces/Time of ``t`` s as :func:`seconds_to_stamp` makes it, in CDR."""
    stamp = seconds_to_stamp(t)
    if stamp.sec > MAX_STAMP_S:
        raise ValueError(f"cannot stamp {t} s: beyond a message's int32 seconds")
    return struct.pack("<iI", stamp.sec, stamp.nanosec)


def path_to_poses(msg: Path) -> tuple[FloatArray, FloatArray]:
    """nav_msgs/Path -> (times [k], poses [k, 3] (x, y, yaw))."""
    poses = msg.poses
    times = np.array([stamp_to_seconds(p.header.stamp) for p in poses])
    arr = np.array([
        (p.pose.position.x, p.pose.position.y,
         quaternion_to_yaw(p.pose.orientation.x, p.pose.orientation.y,
                           p.pose.orientation.z, p.pose.orientation.w))
        for p in poses
    ]).reshape(-1, 3)
    return times, arr


#: Smallest diameter (m) an ellipse marker is drawn with: RViz shows nothing of a flat
#: cylinder. A smaller axis (a chair at rest: a fraction of a millimetre ahead, microns
#: sideways) is drawn, and read back by ``ellipses_from_markers``, at this size.
MIN_MARKER_DIAMETER_M = 1e-3


def ellipse_markers(centers: ArrayLike, ellipses: ArrayLike, frame_id: str, stamp: float,
                    ns: str = "prediction_95", height: float = 0.02,
                    rgba: tuple[float, float, float, float] = (0.1, 0.5, 1.0, 0.35)
                    ) -> MarkerArray:
    """Position confidence ellipses -> visualization_msgs/MarkerArray for RViz.

    The array starts with a DELETEALL marker, then one flat CYLINDER per step (ids
    0..k-1): RViz never accumulates old ellipses. An empty ``centers`` gives only the
    DELETEALL (clears the display when predictions stop).

    Args:
        centers: [k, 2] ellipse centres (x, y).
        ellipses: [k, 3] (semi-major, semi-minor, angle of the major axis), see
            ``asgp_ros.core.online.confidence_ellipses``.
    """
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 2)
    e = np.asarray(ellipses, dtype=np.float64).reshape(-1, 3)
    header_stamp = seconds_to_stamp(stamp)
    clear = Marker()
    clear.header.frame_id = frame_id
    clear.header.stamp = header_stamp
    clear.ns = ns
    clear.action = Marker.DELETEALL
    markers = [clear]
    for i, ((x, y), (major, minor, angle)) in enumerate(zip(c, e, strict=True)):
        m = Marker()
        m.header.frame_id = frame_id
        m.header.stamp = header_stamp
        m.ns = ns
        m.id = i
        m.type = Marker.CYLINDER
        m.action = Marker.ADD
        m.pose.position.x = float(x)
        m.pose.position.y = float(y)
        q = _quaternion(float(angle))
        m.pose.orientation.z, m.pose.orientation.w = q[2], q[3]
        m.scale.x = max(2.0 * float(major), MIN_MARKER_DIAMETER_M)
        m.scale.y = max(2.0 * float(minor), MIN_MARKER_DIAMETER_M)
        m.scale.z = height
        m.color.r, m.color.g, m.color.b, m.color.a = (float(v) for v in rgba)
        markers.append(m)
    return MarkerArray(markers=markers)


def ellipses_from_markers(msg: MarkerArray) -> FloatArray:
    """[k, 3] (semi-major, semi-minor, angle) from ``ellipse_markers``' message, in the
    order of the marker ids (the path's steps). The ellipses as drawn: an axis under half
    of :data:`MIN_MARKER_DIAMETER_M` reads as that (0.5 mm), so a read ellipse holds the
    computed one and exceeds it by at most 0.5 mm per axis. A model without uncertainty
    publishes all its ellipses at that size: its markers say nothing of coverage."""
    cyl = sorted((m for m in msg.markers if m.action == Marker.ADD), key=lambda m: m.id)
    out = np.empty((len(cyl), 3))
    for n, m in enumerate(cyl):
        q = m.pose.orientation
        out[n, 0] = 0.5 * float(m.scale.x)
        out[n, 1] = 0.5 * float(m.scale.y)
        out[n, 2] = float(quaternion_to_yaw(q.x, q.y, q.z, q.w))
    return out


# --------------------------------------------------------------------------------------
# Serial bridge: joystick overrides in, diagnostics out


def joy_to_override(msg: Joy, axes: JoyAxes | None = None) -> tuple[float, float]:
    """sensor_msgs/Joy on ``joy_override`` -> (forward, turn) deflections in [-1, 1]: axes
    [forward, turn] (the bridge's own), or read as ``axes`` says (a node's ``joy_axes``:
    the overrides are in the convention of the ``joy`` they change).

    Raises:
        ValueError: too few axes, a non-finite value or one outside [-1, 1] (an override
            is refused, never clipped: a bad command is a bug upstream).
    """
    a = axes or JoyAxes()
    values = msg.axes
    need = max(a.forward, a.turn) + 1
    if len(values) < need:
        raise ValueError(f"joy_override needs {need} axes (forward {a.forward}, turn "
                         f"{a.turn}), got {len(values)} axes")
    fwd = a.forward_sign * float(values[a.forward])
    turn = a.turn_sign * float(values[a.turn])
    for name, v in (("forward", fwd), ("turn", turn)):
        if not (math.isfinite(v) and -1.0 <= v <= 1.0):
            raise ValueError(f"joy_override {name} deflection {v} is not in [-1, 1]")
    return fwd, turn


def diagnostic_status(name: str, level: str, message: str, hardware_id: str = "",
                      values: Mapping[str, object] | None = None) -> DiagnosticStatus:
    """-> diagnostic_msgs/DiagnosticStatus; ``level`` is "OK", "WARN", "ERROR" or "STALE",
    ``values`` a mapping whose items become KeyValue strings (floats with 4 significant
    digits)."""
    levels = {"OK": DiagnosticStatus.OK, "WARN": DiagnosticStatus.WARN,
              "ERROR": DiagnosticStatus.ERROR, "STALE": DiagnosticStatus.STALE}
    if level not in levels:
        raise ValueError(f"diagnostic level must be one of {sorted(levels)}, got {level!r}")
    st = DiagnosticStatus()
    st.level = levels[level]
    st.name = name
    st.message = message
    st.hardware_id = hardware_id
    st.values = [KeyValue(key=str(k), value=f"{v:.4g}" if isinstance(v, float) else str(v))
                 for k, v in (values or {}).items()]
    return st


def diagnostic_array(t: float, statuses: Iterable[DiagnosticStatus]) -> DiagnosticArray:
    """(stamp s, [DiagnosticStatus]) -> diagnostic_msgs/DiagnosticArray."""
    msg = DiagnosticArray()
    msg.header.stamp = seconds_to_stamp(t)
    msg.status = list(statuses)
    return msg


def diagnostic_values(status: DiagnosticStatus) -> dict[str, str]:
    """diagnostic_msgs/DiagnosticStatus -> {key: value} (for tests and monitors)."""
    return {kv.key: kv.value for kv in status.values}


# --------------------------------------------------------------------------------------
# Odometry out (the VO's estimate; the demo's ground truth)

def odometry_from_pose(t: float, x: float, y: float, yaw: float, v: float, omega: float,
                       frame_id: str = "odom", child_frame_id: str = "base_link"
                       ) -> Odometry:
    """Planar pose (x, y, yaw) and body twist (v, omega) -> nav_msgs/Odometry (exact:
    zero covariance)."""
    msg = Odometry()
    msg.header.stamp = seconds_to_stamp(t)
    msg.header.frame_id = frame_id
    msg.child_frame_id = child_frame_id
    msg.pose.pose.position.x = float(x)
    msg.pose.pose.position.y = float(y)
    q = _quaternion(float(yaw))
    o = msg.pose.pose.orientation
    o.x, o.y, o.z, o.w = q
    msg.twist.twist.linear.x = float(v)
    msg.twist.twist.angular.z = float(omega)
    return msg


# --------------------------------------------------------------------------------------
# Visual odometry: Image / CameraInfo in, Odometry with covariance out (TwistStamped via
# twist_stamped_from_sample)

#: sensor_msgs/Image encoding -> (numpy dtype, channels) accepted by image_to_array.
_IMAGE_DECODINGS = {"bgr8": ("uint8", 3), "rgb8": ("uint8", 3), "bgra8": ("uint8", 4),
                    "rgba8": ("uint8", 4), "mono8": ("uint8", 1), "8UC1": ("uint8", 1),
                    "8UC3": ("uint8", 3), "16UC1": ("uint16", 1), "mono16": ("uint16", 1),
                    "32FC1": ("float32", 1)}


def image_to_array(msg: Image) -> NDArray[np.generic]:
    """sensor_msgs/Image -> numpy, honouring ``step`` (row padding) and ``is_bigendian``.

    Colour comes back as [h, w, 3] uint8 BGR (rgb8/rgba8 are reordered, alpha dropped),
    mono8 as [h, w] uint8, 16UC1/mono16 as [h, w] uint16 (depth in sensor units, mm for
    REP-118), 32FC1 as [h, w] float32 (depth in metres). The array owns its memory.

    Raises:
        ValueError: unsupported encoding, empty image, or a data size that does not match
            height x step.
    """
    enc = str(msg.encoding)
    if enc not in _IMAGE_DECODINGS:
        raise ValueError(f"unsupported image encoding {enc!r}; expected one of "
                         f"{sorted(_IMAGE_DECODINGS)}")
    dtype_name, channels = _IMAGE_DECODINGS[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0:
        raise ValueError(f"empty {enc} image ({w}x{h})")
    dtype = np.dtype(dtype_name).newbyteorder(">" if msg.is_bigendian else "<")
    row = w * channels * dtype.itemsize
    if step < row:
        raise ValueError(f"{enc} image step {step} < {row} bytes for width {w}")
    try:  # array.array / bytes: no copy
        buf = np.frombuffer(msg.data, dtype=np.uint8)
    except TypeError:  # a plain sequence of ints
        buf = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    if buf.size != h * step:
        raise ValueError(f"{enc} image data has {buf.size} bytes, expected height {h} x "
                         f"step {step} = {h * step}")
    rows = buf.reshape(h, step)[:, :row]
    arr = np.ascontiguousarray(rows).view(dtype).reshape((h, w) if channels == 1
                                                       else (h, w, channels))
    arr = arr.astype(dtype.newbyteorder("="), copy=True)
    if enc in ("rgb8", "rgba8"):
        arr = np.ascontiguousarray(arr[..., 2::-1])
    elif enc == "bgra8":
        arr = np.ascontiguousarray(arr[..., :3])
    return arr


#: Ranges of a CameraInfo the VO accepts: image sides (px, 0 = unknown), focal lengths and
#: the principal point's coordinates (px). Real cameras are far inside them.
CAMERA_MAX_SIDE_PX = 100_000
CAMERA_FOCAL_RANGE_PX = (1.0, 1e6)
CAMERA_MAX_ABS_CENTRE_PX = 1e6


def camera_info_to_matrix(msg: CameraInfo) -> tuple[FloatArray, int, int, bool]:
    """sensor_msgs/CameraInfo -> (K [3, 3] float64, width, height, has_distortion).

    Raises:
        ValueError: K unset (all zero), not finite, not a pinhole matrix, or a focal length,
            principal point or image side outside ``CAMERA_FOCAL_RANGE_PX``,
            ``CAMERA_MAX_ABS_CENTRE_PX``, ``CAMERA_MAX_SIDE_PX``; a principal point outside
            the image the message gives the size of.
    """
    K = np.asarray(msg.k, dtype=np.float64).reshape(3, 3)
    if not np.all(np.isfinite(K)) or not np.any(K):
        raise ValueError("CameraInfo K is unset or not finite (uncalibrated camera)")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1.0 or np.any(K[2, :2] != 0):
        raise ValueError(f"CameraInfo K is not a pinhole matrix: {K.reshape(-1).tolist()}")
    low, high = CAMERA_FOCAL_RANGE_PX
    if not (low <= K[0, 0] <= high and low <= K[1, 1] <= high):
        raise ValueError(f"CameraInfo focal lengths {K[0, 0]:g}, {K[1, 1]:g} px are outside "
                         f"[{low:g}, {high:g}]")
    if np.any(np.abs(K[:2, 1:]) > CAMERA_MAX_ABS_CENTRE_PX):
        raise ValueError(f"CameraInfo skew or principal point beyond "
                         f"+-{CAMERA_MAX_ABS_CENTRE_PX:g} px: {K.reshape(-1).tolist()}")
    if not (0 <= int(msg.width) <= CAMERA_MAX_SIDE_PX
            and 0 <= int(msg.height) <= CAMERA_MAX_SIDE_PX):
        raise ValueError(f"CameraInfo size {msg.width}x{msg.height} is beyond "
                         f"{CAMERA_MAX_SIDE_PX} px")
    if msg.width and msg.height and not (0.0 <= K[0, 2] < msg.width
                                         and 0.0 <= K[1, 2] < msg.height):
        raise ValueError(f"CameraInfo principal point ({K[0, 2]:g}, {K[1, 2]:g}) px lies "
                         f"outside its {msg.width}x{msg.height} image: K does not fit")
    d = np.asarray(msg.d, dtype=np.float64)
    return K, int(msg.width), int(msg.height), bool(d.size and np.any(d != 0))


def odometry_with_covariance(t: float, x: float, y: float, yaw: float, pose_cov: ArrayLike,
                             v: float, omega: float, twist_cov: ArrayLike,
                             frame_id: str = "odom",
                             child_frame_id: str = "base_link") -> Odometry:
    """Planar VO estimate -> nav_msgs/Odometry with covariances.

    Args:
        pose_cov: [3, 3] covariance of (x, y, yaw) in ``frame_id``; z, roll and pitch are
            fixed by the planar model and get a variance of 1e-6.
        twist_cov: [6, 6] covariance of the body twist (vx, vy, vz, wx, wy, wz) in
            ``child_frame_id``; the message carries v = vx and omega = wz.
    """
    P3 = np.asarray(pose_cov, dtype=np.float64).reshape(3, 3)
    T6 = np.asarray(twist_cov, dtype=np.float64).reshape(6, 6)
    P6 = np.diag([0.0, 0.0, 1e-6, 1e-6, 1e-6, 0.0])
    idx = [0, 1, 5]
    P6[np.ix_(idx, idx)] = P3
    msg = odometry_from_pose(t, x, y, yaw, v, omega, frame_id, child_frame_id)
    msg.pose.covariance = P6.reshape(-1).tolist()
    msg.twist.covariance = T6.reshape(-1).tolist()
    return msg


# --------------------------------------------------------------------------------------
# Shared control: LaserScan, OccupancyGrid


def scan_from_msg(msg: LaserScan, nan_is_free: bool = False,
                  upside_down: bool = False) -> collision.Scan:
    """sensor_msgs/LaserScan -> :class:`asgp_ros.core.collision.Scan` (stamp in seconds).
    ``nan_is_free``: a NaN range is read as +inf, nothing in range (a source that reports
    no return as NaN); by default NaN is an erroneous reading (REP-117). ``upside_down``:
    the laser is mounted upside down (its frame rolled by pi about its x axis): a beam at
    angle a in its frame is at -a in an upright one, so the scan is mirrored (read as it
    is, a wall on the right was placed on the left).

    Raises:
        ValueError (:class:`~asgp_ros.core.collision.CollisionError`): no beams, more than
            100,000, non-finite limits or angles.
    """
    ranges = np.asarray(msg.ranges, dtype=np.float64)
    if nan_is_free:
        ranges = np.where(np.isnan(ranges), np.inf, ranges)
    angle_min, increment = float(msg.angle_min), float(msg.angle_increment)
    if upside_down and ranges.size:  # beam i at -(angle_min + i inc), the last one first
        ranges = ranges[::-1].copy()
        angle_min = -(angle_min + increment * (ranges.size - 1))
    return collision.Scan(ranges, angle_min, increment, float(msg.range_min),
                          float(msg.range_max), stamp_to_seconds(msg.header.stamp))


def grid_from_msg(msg: OccupancyGrid) -> collision.Grid:
    """nav_msgs/OccupancyGrid -> :class:`asgp_ros.core.collision.Grid` (origin x, y, yaw).

    Raises:
        ValueError: ``data`` does not hold ``width`` x ``height`` cells, or the grid is
            refused by :class:`~asgp_ros.core.collision.Grid`.
    """
    w, h = int(msg.info.width), int(msg.info.height)
    if w * h == 0 or len(msg.data) != w * h:
        raise ValueError(f"map data holds {len(msg.data)} cells, info says {w} x {h}")
    o = msg.info.origin
    q = o.orientation
    yaw, unit = _yaw_of(q)
    if not unit:
        raise ValueError(f"map origin orientation ({q.x:g}, {q.y:g}, {q.z:g}, {q.w:g}) is not "
                         "a unit quaternion")
    data = np.asarray(msg.data, dtype=np.int8).reshape(h, w)
    return collision.Grid(data, float(msg.info.resolution),
                          (float(o.position.x), float(o.position.y), yaw))


def scan_to_msg(ranges: ArrayLike, angle_min: float, angle_increment: float,
                range_min: float, range_max: float, stamp: float, frame_id: str,
                scan_time: float = 0.0) -> LaserScan:
    """A scan's arrays -> sensor_msgs/LaserScan (float32 ranges, REP-117 inf/NaN kept)."""
    msg = LaserScan()
    msg.header.stamp = seconds_to_stamp(stamp)
    msg.header.frame_id = frame_id
    r = np.asarray(ranges, dtype=np.float32)
    msg.angle_min = float(angle_min)
    msg.angle_increment = float(angle_increment)
    msg.angle_max = float(angle_min + angle_increment * (r.size - 1))
    msg.range_min, msg.range_max = float(range_min), float(range_max)
    msg.scan_time = float(scan_time)
    msg.ranges = r.tolist()
    return msg


def grid_to_msg(data: ArrayLike, resolution: float, origin: tuple[float, float, float],
                stamp: float, frame_id: str) -> OccupancyGrid:
    """[height, width] int8 cells -> nav_msgs/OccupancyGrid."""
    d = np.asarray(data, dtype=np.int8)
    if d.ndim != 2:
        raise ValueError(f"a grid must be [height, width], got {d.shape}")
    msg = OccupancyGrid()
    msg.header.stamp = seconds_to_stamp(stamp)
    msg.header.frame_id = frame_id
    msg.info.map_load_time = msg.header.stamp
    msg.info.resolution = float(resolution)
    msg.info.height, msg.info.width = int(d.shape[0]), int(d.shape[1])
    msg.info.origin.position.x, msg.info.origin.position.y = float(origin[0]), float(origin[1])
    x, y, z, w = _quaternion(origin[2])
    o = msg.info.origin.orientation
    o.x, o.y, o.z, o.w = x, y, z, w
    msg.data = d.reshape(-1).tolist()
    return msg
