"""Parameters of ``vo_node``: one table (name, default, range, description) shared by the
node's declarations and ``config/vo.yaml``, validated into a frozen dataclass (ROS-free)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from asgp_ros.common.paramspec import ParamSpec, ParamValue, check_values
from asgp_ros.common.topics import CAMERA_COLOR, CAMERA_DEPTH, CAMERA_INFO
from asgp_ros.vo.extrinsics import DEFAULT_EXTRINSIC, CameraExtrinsic
from asgp_ros.vo.odometry import VOOptions

_E = DEFAULT_EXTRINSIC
_O = VOOptions()

NODE_PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("color_topic", CAMERA_COLOR,
              "sensor_msgs/Image colour (rgb8, bgr8, mono8; also rgba8, bgra8)"),
    ParamSpec("depth_topic", CAMERA_DEPTH,
              "sensor_msgs/Image depth registered to colour (16UC1 in depth_scale units, "
              "32FC1 metres)"),
    ParamSpec("camera_info_topic", CAMERA_INFO,
              "sensor_msgs/CameraInfo of the colour camera (K used; images must be rectified)"),
    ParamSpec("base_frame", "base_link", "child frame of vo/odom, frame of vo/twist"),
    ParamSpec("odom_frame", "odom", "frame of vo/odom (base_link at the first tracked frame)"),
    ParamSpec("publish_odom", True, "publish vo/odom (nav_msgs/Odometry with covariance)"),
    ParamSpec("sync_tolerance_s", 0.02,
              "s: colour and depth stamps further apart than this are not paired", 0.0, 1.0),
    ParamSpec("stale_timeout_s", 0.5,
              "s: no processed frame for this long -> diagnostics error", 0.01, 60.0),
    ParamSpec("diagnostics_period_s", 1.0, "s: period of diagnostics messages", 0.05, 60.0),
    ParamSpec("camera_x", _E.x, "m: camera position in base_link, x (forward)", -5.0, 5.0),
    ParamSpec("camera_y", _E.y, "m: camera position in base_link, y (left)", -5.0, 5.0),
    ParamSpec("camera_z", _E.z, "m: camera position in base_link, z (up)", -5.0, 5.0),
    ParamSpec("camera_roll", _E.roll, "rad: camera roll in base_link", -math.pi, math.pi),
    ParamSpec("camera_pitch", _E.pitch,
              "rad: camera pitch in base_link (positive tilts the view down)",
              -math.pi / 2, math.pi / 2),
    ParamSpec("camera_yaw", _E.yaw,
              "rad: camera yaw in base_link (pi = looking backward, as in the paper)",
              -2 * math.pi, 2 * math.pi),
)

_VO_DESCRIPTIONS = {
    "num_levels": ("Gaussian pyramid levels", 1, 5),
    "target_pixels_per_feature": ("FAST threshold adapts toward one feature per this many "
                                  "level-0 pixels", 16.0, 1e5),
    "fast_threshold": ("initial FAST threshold", 1.0, 255.0),
    "fast_threshold_min": ("lowest adaptive FAST threshold", 1.0, 255.0),
    "fast_threshold_max": ("highest adaptive FAST threshold", 1.0, 255.0),
    "fast_adaptive_gain": ("exponent of the threshold update (0 = fixed threshold)", 0.0, 5.0),
    "bucket_size": ("px: bucket side for feature bucketing", 8, 1000),
    "max_features_per_bucket": ("strongest features kept per bucket", 1, 1000),
    "min_depth": ("m: nearer depth is no data", 0.01, 100.0),
    "max_depth": ("m: farther depth is no data", 0.02, 100.0),
    "depth_scale": ("m per unit of a 16UC1 depth image (0.001 = millimetres)", 1e-6, 1.0),
    "depth_edge_fraction": ("a feature whose neighbours' depth differs by more than this "
                            "fraction lies on a depth edge and is dropped", 0.0, 1.0),
    "search_radius": ("level px: match search radius around the predicted position",
                      1.0, 200.0),
    "max_descriptor_distance": ("largest mean absolute difference of normalised patches",
                                0.01, 10.0),
    "match_ratio": ("best / second-best descriptor distance must be below this", 0.01, 1.0),
    "max_matches": ("at most this many matches enter the inlier search", 20, 5000),
    "clique_inlier_threshold": ("m: pairwise distance tolerance of the rigidity test",
                                0.001, 1.0),
    "clique_depth_coefficient": ("1/m: tolerance grows by this times z^2 (depth noise)",
                                 0.0, 1.0),
    "min_features_for_estimate": ("fewer features with depth -> insufficient_features",
                                  6, 10000),
    "min_inliers": ("fewer inliers -> insufficient_inliers (a covariance needs 7)", 7, 10000),
    "outlier_reprojection_threshold": ("level px: larger reprojection error -> outlier",
                                       0.05, 20.0),
    "max_mean_reprojection_error": ("level px: larger mean inlier error -> "
                                    "reprojection_error_too_high", 0.01, 20.0),
    "ref_frame_change_threshold": ("fewer inliers -> the current frame becomes the "
                                   "reference (keyframe)", 0, 100000),
    "max_frames_lost": ("untracked frames before re-initialising on the current frame",
                        0, 100000),
    "min_valid_depth_fraction": ("smaller fraction of pixels with depth -> no_depth",
                                 0.0, 1.0),
    "gauss_newton_iterations": ("Gauss-Newton iterations per refinement", 1, 100),
    "max_translation_std": ("m: a less certain motion estimate is rejected", 1e-5, 10.0),
    "max_speed": ("m/s: a faster camera motion is rejected as implausible", 0.01, 100.0),
    "max_angular_speed": ("rad/s: a faster camera rotation is rejected as implausible",
                          0.01, 100.0),
    "max_twist_interval": ("s: no twist from a motion spanning a longer gap (after a loss)",
                           0.001, 100.0),
    "use_prediction": ("predict feature positions from the previous motion", None, None),
}

VO_PARAMS: tuple[ParamSpec, ...] = tuple(
    ParamSpec(f"vo.{name}", getattr(_O, name), *_VO_DESCRIPTIONS[name])
    for name in VOOptions.names())

PARAMS: tuple[ParamSpec, ...] = NODE_PARAMS + VO_PARAMS
SPECS: dict[str, ParamSpec] = {p.name: p for p in PARAMS}


@dataclass(frozen=True)
class VONodeParams:
    color_topic: str
    depth_topic: str
    camera_info_topic: str
    base_frame: str
    odom_frame: str
    publish_odom: bool
    sync_tolerance_s: float
    stale_timeout_s: float
    diagnostics_period_s: float
    extrinsic: CameraExtrinsic
    vo_options: dict[str, Any]


def vo_node_params(values: Mapping[str, object]) -> VONodeParams:
    """Validates parameter values (missing ones take their defaults).

    Raises:
        ValueError: naming the offending parameter.
    """
    v = check_values(PARAMS, values)
    for name in ("color_topic", "depth_topic", "camera_info_topic", "base_frame",
                 "odom_frame"):
        if not str(v[name]).strip():
            raise ValueError(f"{name} must not be empty")
    if v["odom_frame"] == v["base_frame"]:
        raise ValueError(f"odom_frame and base_frame must differ, both are {v['base_frame']!r}")
    options = {spec.name[3:]: v[spec.name] for spec in VO_PARAMS}
    VOOptions(**options)  # cross-field checks (raises ValueError naming the option)
    return VONodeParams(
        color_topic=v["color_topic"], depth_topic=v["depth_topic"],
        camera_info_topic=v["camera_info_topic"], base_frame=v["base_frame"],
        odom_frame=v["odom_frame"], publish_odom=v["publish_odom"],
        sync_tolerance_s=v["sync_tolerance_s"], stale_timeout_s=v["stale_timeout_s"],
        diagnostics_period_s=v["diagnostics_period_s"],
        extrinsic=CameraExtrinsic(x=v["camera_x"], y=v["camera_y"], z=v["camera_z"],
                                  roll=v["camera_roll"], pitch=v["camera_pitch"],
                                  yaw=v["camera_yaw"]),
        vo_options=options)


def params_yaml(node_name: str = "vo_node") -> str:
    """The parameter table as a ROS 2 parameter file (``config/vo.yaml``); the ``vo.*``
    options are nested under ``vo:``."""

    def text(d: ParamValue) -> str:
        if isinstance(d, bool):
            return "true" if d else "false"
        if isinstance(d, float):
            return repr(float(d))
        if isinstance(d, int):
            return str(d)
        return str(d)

    lines = [f"/**/{node_name}:", "  ros__parameters:"]  # in any namespace
    for spec in NODE_PARAMS:
        lines.append(f"    {spec.name}: {text(spec.default)}  # {spec.description}")
    lines.append("    vo:  # the odometry (asgp_ros.vo.VOOptions)")
    for spec in VO_PARAMS:
        lines.append(f"      {spec.name[3:]}: {text(spec.default)}  # {spec.description}")
    return "\n".join(lines) + "\n"
