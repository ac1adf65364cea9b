"""Planar odom -> base_link pose and its covariance from the VO results (ROS-free)."""

from __future__ import annotations

import math

import numpy as np

from asgp_ros.vo.extrinsics import CameraExtrinsic, adjoint, invert
from asgp_ros.vo.odometry import VOResult

#: Variance (m^2 and rad^2) added to x, y and yaw when tracking re-initialises: the motion
#: during the gap is unknown, so the held pose is uncertain.
RESET_VARIANCE = 1.0


class PlanarOdometry:
    """Pose of base_link in ``odom`` (= base_link at the first frame) from VO results.

    The pose is the planar projection of T_odom_base = T_bc pose_cam T_bc^-1, the
    covariance of (x, y, yaw) is propagated to first order per tracked step:
    Sigma_k = F Sigma_{k-1} F^T + G Sigma_step G^T (the usual compounding Jacobians,
    Smith, Self & Cheeseman 1990), with Sigma_step the (x, y, yaw) block of the motion
    covariance mapped to base_link by the adjoint of the extrinsic.
    """

    def __init__(self, extrinsic: CameraExtrinsic) -> None:
        self.extrinsic = extrinsic
        self._Tbc = extrinsic.T_base_optical
        self._Ad = adjoint(self._Tbc)
        self.reset()

    def reset(self) -> None:
        self.x = self.y = self.yaw = 0.0
        self.covariance = np.zeros((3, 3))  # [3, 3] of (x, y, yaw)

    def update(self, result: VOResult) -> tuple[float, float, float, np.ndarray]:
        """Fold in one VO result; returns (x, y, yaw, covariance [3, 3])."""
        if result.reset:
            self.covariance = self.covariance + RESET_VARIANCE * np.eye(3)
        if result.ok and result.motion is not None and result.covariance is not None:
            step = self._Tbc @ result.motion @ invert(self._Tbc)
            dx, dy = float(step[0, 3]), float(step[1, 3])
            c, s = math.cos(self.yaw), math.sin(self.yaw)
            F = np.array([[1.0, 0.0, -s * dx - c * dy], [0.0, 1.0, c * dx - s * dy],
                          [0.0, 0.0, 1.0]])
            G = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            cov_b = self._Ad @ result.covariance @ self._Ad.T  # [6, 6] (v, w) in base_link
            q = cov_b[np.ix_([0, 1, 5], [0, 1, 5])]
            self.covariance = F @ self.covariance @ F.T + G @ q @ G.T
        T = self._Tbc @ result.pose @ invert(self._Tbc)
        self.x, self.y = float(T[0, 3]), float(T[1, 3])
        self.yaw = math.atan2(T[1, 0], T[0, 0])
        return self.x, self.y, self.yaw, self.covariance.copy()
