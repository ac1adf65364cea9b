"""ROS-free sparse-feature RGB-D visual odometry (Fovis-like) on OpenCV.

:class:`VisualOdometry` tracks RGB-D frames (:mod:`asgp_ros.vo.odometry`),
:class:`CameraExtrinsic` mounts the camera on base_link and turns camera motion into the
chair's planar twist (:mod:`asgp_ros.vo.extrinsics`), :class:`PlanarOdometry` keeps the
odom -> base_link pose and its covariance (:mod:`asgp_ros.vo.planar`).
"""

from asgp_ros.vo.extrinsics import DEFAULT_EXTRINSIC, CameraExtrinsic
from asgp_ros.vo.odometry import Status, VisualOdometry, VOOptions, VOResult
from asgp_ros.vo.planar import PlanarOdometry

__all__ = ["DEFAULT_EXTRINSIC", "CameraExtrinsic", "PlanarOdometry", "Status", "VOOptions",
           "VOResult", "VisualOdometry"]
