"""The ROS topic names of the system, defined once (no rclpy: importable everywhere).

Nodes use the relative names, so that a namespace applies (``ros2 run ... --ros-args -r
__ns:=/chair``); bags recorded from the root namespace hold the absolute names
(``BAG_*``), which the bag commands read by default. The YAML files in ``config/`` and the
README's ROS interface table name the same topics (checked by test/test_single_source.py).
"""

from __future__ import annotations

#: sensor_msgs/Joy: axes[0] forward deflection, axes[1] turn deflection (bridge ->).
JOY = "joy"
#: sensor_msgs/Joy: the same axes, written to the chair while fresh (-> bridge).
JOY_OVERRIDE = "joy_override"
#: sensor_msgs/Joy: the same axes, what the board drives the chair with, sample by sample:
#: its output while an override is applied, else the user's stick as on ``joy`` (bridge ->).
JOY_APPLIED = "joy_applied"
#: trajectory_msgs/JointTrajectory: future joystick commands, joints forward and turn,
#: header.stamp = when the plan starts (planner -> predictor).
JOY_PLAN = "joy_plan"
#: geometry_msgs/TwistStamped: v and omega in base_link (vo ->).
VO_TWIST = "vo/twist"
#: nav_msgs/Odometry: odom -> base_link with covariance (vo ->).
VO_ODOM = "vo/odom"
#: nav_msgs/Path: the k predicted poses (predictor ->).
PREDICTED_PATH = "predicted_path"
#: visualization_msgs/MarkerArray: position covariance ellipses (predictor ->).
PREDICTED_PATH_UNCERTAINTY = PREDICTED_PATH + "/uncertainty"
#: diagnostic_msgs/DiagnosticArray (all nodes): absolute, as ROS's diagnostic_updater
#: publishes it, so that one aggregator hears every namespace's nodes (their status names
#: carry the namespace: ``runtime.status_name``).
DIAGNOSTICS = "/diagnostics"
#: sensor_msgs/LaserScan: the chair's 2-D laser scanner (-> shared control).
SCAN = "scan"
#: nav_msgs/OccupancyGrid: the map, in the odometry frame (-> shared control).
MAP = "map"
#: diagnostic_msgs/DiagnosticStatus: one per shared-control decision (shared control ->).
SHARED_CONTROL_STATUS = "shared_control/status"
#: sensor_msgs/Image, colour (-> vo).
CAMERA_COLOR = "camera/color/image_raw"
#: sensor_msgs/Image, depth registered to colour (-> vo).
CAMERA_DEPTH = "camera/depth/image_raw"
#: sensor_msgs/CameraInfo of the colour camera (-> vo).
CAMERA_INFO = "camera/color/camera_info"
#: nav_msgs/Odometry: the simulator's true pose and velocity (simulated hardware ->).
GROUND_TRUTH = "ground_truth/odom"


def is_override(name: str) -> bool:
    """A topic of commands to the chair: ``joy_override``, in any namespace."""
    return name.rstrip("/").rsplit("/", 1)[-1] == JOY_OVERRIDE


def in_bag(name: str) -> str:
    """The absolute name under which a topic is recorded from the root namespace."""
    return name if name.startswith("/") else "/" + name


def namespace_of(topic: str) -> str:
    """The namespace of an absolute topic name: ``/chair2`` for ``/chair2/joy``, ``/`` for
    ``/joy``."""
    return in_bag(topic).rsplit("/", 1)[0] or "/"


def beside(topic: str, name: str) -> str:
    """``name`` resolved as a node in ``topic``'s namespace resolves it: a relative name
    beside ``topic`` (``joy_override`` beside ``/chair2/joy`` is ``/chair2/joy_override``),
    an absolute one as it is."""
    if name.startswith("/"):
        return name
    return namespace_of(topic).rstrip("/") + "/" + name


#: The bag topics the offline commands read by default (``asgp train``, ``evaluate``, ...).
BAG_JOY = in_bag(JOY)
BAG_VO_TWIST = in_bag(VO_TWIST)
BAG_GROUND_TRUTH = in_bag(GROUND_TRUTH)
BAG_JOY_OVERRIDE = in_bag(JOY_OVERRIDE)
