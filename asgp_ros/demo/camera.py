"""The demo's simulated camera on ROS: numpy images and a pinhole matrix -> sensor_msgs.

The inverse of :func:`asgp_ros.nodes.conversions.image_to_array` and
:func:`~asgp_ros.nodes.conversions.camera_info_to_matrix`, which the VO node reads; only
the simulated hardware (and the tests that feed the VO node) build camera messages.
"""

from __future__ import annotations

import sys

import numpy as np
from numpy.typing import ArrayLike
from sensor_msgs.msg import CameraInfo, Image

from asgp_ros.nodes.conversions import seconds_to_stamp

#: numpy image layout -> sensor_msgs/Image encoding (REP-118 depth: 16UC1 mm, 32FC1 m).
_IMAGE_ENCODINGS = {("uint8", 3): "bgr8", ("uint8", 1): "mono8", ("uint16", 1): "16UC1",
                    ("float32", 1): "32FC1"}


def image_from_array(t: float, image: ArrayLike, frame_id: str) -> Image:
    """[h, w, 3] uint8 BGR, [h, w] uint8 grey, [h, w] uint16 depth (mm) or [h, w] float32
    depth (m) -> sensor_msgs/Image (bgr8, mono8, 16UC1, 32FC1), native byte order.

    Raises:
        ValueError: any other dtype or shape.
    """
    arr = np.ascontiguousarray(image)
    channels = 1 if arr.ndim == 2 else (arr.shape[2] if arr.ndim == 3 else 0)
    encoding = _IMAGE_ENCODINGS.get((str(arr.dtype), channels))
    if encoding is None:
        raise ValueError(f"no image encoding for a {arr.dtype} array of shape {arr.shape}")
    msg = Image()
    msg.header.stamp = seconds_to_stamp(t)
    msg.header.frame_id = frame_id
    msg.height, msg.width = int(arr.shape[0]), int(arr.shape[1])
    msg.encoding = encoding
    msg.is_bigendian = int(sys.byteorder == "big")
    msg.step = int(arr.shape[1] * channels * arr.dtype.itemsize)
    msg.data = arr.tobytes()
    return msg


def camera_info_from_matrix(t: float, camera_matrix: ArrayLike, width: int, height: int,
                            frame_id: str) -> CameraInfo:
    """Pinhole K [3, 3] of an undistorted image -> sensor_msgs/CameraInfo (plumb_bob with
    zero distortion, R = I, P = [K | 0])."""
    K = np.asarray(camera_matrix, dtype=np.float64).reshape(3, 3)
    msg = CameraInfo()
    msg.header.stamp = seconds_to_stamp(t)
    msg.header.frame_id = frame_id
    msg.width, msg.height = int(width), int(height)
    msg.distortion_model = "plumb_bob"
    msg.d = [0.0] * 5
    msg.k = K.reshape(-1).tolist()
    msg.r = np.eye(3).reshape(-1).tolist()
    msg.p = np.hstack([K, np.zeros((3, 1))]).reshape(-1).tolist()
    return msg
