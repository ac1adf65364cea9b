"""Camera-to-base_link extrinsic and the camera-motion -> planar-twist conversion.

Frames (REP-103 / REP-105):

* ``base_link``: x forward, y left, z up, origin on the ground below the drive-wheel axle.
* camera body frame: x along the optical axis, y left, z up (REP-103 "camera_link").
* camera optical frame: z along the optical axis, x right, y down (what OpenCV and the VO
  use; every ``motion``/``pose`` of :mod:`asgp_ros.vo` is in optical frames).

The paper's RGB-D camera sits behind the seat and looks backward. The default here is
0.4 m behind the axle, on the centre line, 1.0 m above the ground, looking backward
(yaw = pi) and tilted 15 degrees down so that the floor fills the lower half of the image.

The renderer (:mod:`asgp_ros.sim.render`) and the odometry use the same
:class:`CameraExtrinsic`, so simulated images and the recovered twist agree on one mounting.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# Rotation from the optical frame to the camera body frame: columns are the optical axes
# (x right, y down, z forward) expressed in the body frame (x forward, y left, z up).
R_BODY_OPTICAL = np.array([[0.0, 0.0, 1.0],
                           [-1.0, 0.0, 0.0],
                           [0.0, -1.0, 0.0]])


def rot_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rotation matrix [3, 3] R = Rz(yaw) Ry(pitch) Rx(roll) (REP-103 fixed-axis rpy)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    R: np.ndarray = rz @ ry @ rx
    return R


def planar_pose(x: float, y: float, theta: float) -> np.ndarray:
    """Homogeneous pose [4, 4] of a planar body (x, y, heading theta) in 3-D, z = 0."""
    T = np.eye(4)
    c, s = math.cos(theta), math.sin(theta)
    T[:2, :2] = [[c, -s], [s, c]]
    T[0, 3], T[1, 3] = x, y
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform [4, 4]."""
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


def adjoint(T: np.ndarray) -> np.ndarray:
    """Adjoint [6, 6] of a rigid transform for twists ordered (v, w): Ad = [[R, [t]x R], [0, R]].

    A twist xi_b in frame b maps to frame a by xi_a = Ad(T_ab) xi_b (Murray, Li & Sastry 1994,
    eq. 2.58, with linear part first).
    """
    R, t = T[:3, :3], T[:3, 3]
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[:3, 3:] = tx @ R
    A[3:, 3:] = R
    return A


@dataclass(frozen=True)
class CameraExtrinsic:
    """Pose of the camera (body frame, REP-103) in base_link.

    Attributes:
        x, y, z: camera position in base_link, metres.
        roll, pitch, yaw: camera body orientation in base_link, radians (fixed-axis rpy);
            yaw = pi looks backward, positive pitch tilts the optical axis down.
    """

    x: float = -0.4
    y: float = 0.0
    z: float = 1.0
    roll: float = 0.0
    pitch: float = math.radians(15.0)
    yaw: float = math.pi

    def __post_init__(self) -> None:
        values = (self.x, self.y, self.z, self.roll, self.pitch, self.yaw)
        if not all(math.isfinite(v) for v in values):
            raise ValueError(f"camera extrinsic must be finite, got {values}")

    @property
    def T_base_optical(self) -> np.ndarray:  # noqa: N802 (T_ab notation)
        """Pose [4, 4] of the camera optical frame in base_link (maps optical -> base)."""
        T = np.eye(4)
        T[:3, :3] = rot_rpy(self.roll, self.pitch, self.yaw) @ R_BODY_OPTICAL
        T[:3, 3] = (self.x, self.y, self.z)
        return T

    def camera_pose(self, T_world_base: np.ndarray) -> np.ndarray:
        """Pose [4, 4] of the optical frame in the world from the chair pose T_world_base."""
        T: np.ndarray = np.asarray(T_world_base, float) @ self.T_base_optical
        return T

    def camera_pose_planar(self, x: float, y: float, theta: float) -> np.ndarray:
        """Pose [4, 4] of the optical frame in the world for a chair at (x, y, theta)."""
        return self.camera_pose(planar_pose(x, y, theta))

    def base_motion(self, camera_motion: np.ndarray) -> np.ndarray:
        """Motion of base_link [4, 4] from the motion of the optical frame.

        ``camera_motion`` is the pose of the current camera in the previous camera frame;
        the result is the pose of the current base_link in the previous base_link frame:
        T_b0_b1 = T_bc T_c0_c1 T_bc^-1.
        """
        Tbc = self.T_base_optical
        T: np.ndarray = Tbc @ np.asarray(camera_motion, float) @ invert(Tbc)
        return T

    def planar_twist(self, camera_motion: np.ndarray, dt: float) -> tuple[float, float]:
        """Chair velocities (v m/s, omega rad/s) over dt from one camera motion [4, 4].

        The base motion is projected on the ground plane and read as a unicycle arc by the
        SE(2) logarithm: heading change dtheta, and v dt = (dtheta / 2) / sin(dtheta / 2)
        times the component of the displacement (dx, dy) along the interval's mean heading
        dtheta / 2 (the logarithm's forward part), so a constant (v, omega) over dt is
        recovered exactly. The sideways part, which a unicycle cannot have, is left out: it
        is estimation error (a chair turning on the spot has none), and taking the chord's
        length instead read it as forward speed, away from zero whatever its sign.
        """
        if not (dt > 0.0 and math.isfinite(dt)):
            raise ValueError(f"dt must be positive and finite, got {dt}")
        Tb = self.base_motion(camera_motion)
        dx, dy = float(Tb[0, 3]), float(Tb[1, 3])
        dtheta = math.atan2(Tb[1, 0], Tb[0, 0])
        half = 0.5 * dtheta
        factor = half / math.sin(half) if abs(half) > 1e-9 else 1.0
        along = dx * math.cos(half) + dy * math.sin(half)
        return factor * along / dt, dtheta / dt

    def twist_covariance(self, camera_covariance: np.ndarray, dt: float,
                         camera_motion: np.ndarray | None = None) -> np.ndarray:
        """Covariance [6, 6] of the base_link twist (v, w order) from a camera-motion one.

        ``camera_covariance`` is the covariance of the body-frame perturbation of the camera
        motion (linear first, in the current optical frame); mapped with the adjoint of
        T_base_optical and divided by dt^2 (first order). With ``camera_motion``, the
        linear part is that of :meth:`planar_twist`'s v: the displacement error in the
        current base_link frame turned back by half the heading change (to the interval's
        mean heading, along which v is read) and times the arc factor
        (dtheta / 2) / sin(dtheta / 2); without it, the current frame's (the same for a
        motion without a turn).
        """
        A = adjoint(self.T_base_optical)
        if camera_motion is not None:
            Tb = self.base_motion(camera_motion)
            half = 0.5 * math.atan2(Tb[1, 0], Tb[0, 0])
            factor = half / math.sin(half) if abs(half) > 1e-9 else 1.0
            c, s = math.cos(half), math.sin(half)
            M = np.eye(6)
            M[:3, :3] = factor * np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            A = M @ A
        C: np.ndarray = A @ np.asarray(camera_covariance, float) @ A.T / (dt * dt)
        return C


DEFAULT_EXTRINSIC = CameraExtrinsic()
