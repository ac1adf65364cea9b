"""Planar heading <-> REP-103 unit quaternion (x, y, z, w), the one definition of both.

The chair moves in the plane, so its orientation is a rotation about +z by the yaw
(heading) theta: q = (0, 0, sin(theta / 2), cos(theta / 2)). The yaw of any quaternion is
the z angle of its ZYX (yaw-pitch-roll) decomposition,
theta = atan2(2 (w z + x y), 1 - 2 (y^2 + z^2)), which is exact for a planar rotation.

Both functions take scalars or arrays (elementwise, broadcasting); a scalar gives numpy
float64 scalars, which are Python floats.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


def yaw_to_quaternion(yaw: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Yaw (rad) -> quaternion (x, y, z, w) of the rotation about +z (REP-103)."""
    half = 0.5 * np.asarray(yaw, dtype=np.float64)
    zero = np.zeros_like(half)
    return zero[()], zero[()], np.sin(half)[()], np.cos(half)[()]


def quaternion_to_yaw(x: ArrayLike, y: ArrayLike, z: ArrayLike, w: ArrayLike) -> FloatArray:
    """Yaw (rad, in [-pi, pi]) of a quaternion (x, y, z, w): its ZYX z angle."""
    xa, ya, za, wa = (np.asarray(c, dtype=np.float64) for c in (x, y, z, w))
    return np.arctan2(2.0 * (wa * za + xa * ya), 1.0 - 2.0 * (ya * ya + za * za))[()]
