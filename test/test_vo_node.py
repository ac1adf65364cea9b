"""vo_node: message conversions, parameters, and the node end to end on rendered frames."""

from __future__ import annotations

import math
import sys
import time

import numpy as np
import pytest
import yaml

pytest.importorskip("rclpy")
pytest.importorskip("sensor_msgs")

from asgp_ros.demo import camera
from asgp_ros.nodes import conversions as conv
from asgp_ros.vo.params import PARAMS, params_yaml, vo_node_params

# ---- conversions -------------------------------------------------------------------------


def test_image_round_trips():
    rng = np.random.default_rng(0)
    arrays = [rng.integers(0, 256, (4, 5, 3), dtype=np.uint8),
              rng.integers(0, 256, (4, 5), dtype=np.uint8),
              rng.integers(0, 65535, (4, 5), dtype=np.uint16),
              rng.uniform(0, 6, (4, 5)).astype(np.float32)]
    for a in arrays:
        msg = camera.image_from_array(1.5, a, "camera")
        b = conv.image_to_array(msg)
        assert b.dtype == a.dtype and b.shape == a.shape
        np.testing.assert_array_equal(a, b)


def test_image_encodings_padding_and_byte_order():
    from sensor_msgs.msg import Image

    bgr = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    msg = Image(height=2, width=3, encoding="rgb8", step=12)  # 3 bytes of row padding
    rows = [np.r_[bgr[r, :, ::-1].reshape(-1), [0, 0, 0]] for r in range(2)]
    msg.data = np.concatenate(rows).astype(np.uint8).tobytes()
    np.testing.assert_array_equal(conv.image_to_array(msg), bgr)
    msg = Image(height=2, width=3, encoding="bgra8", step=12)
    msg.data = np.dstack([bgr, np.full((2, 3), 255, np.uint8)]).tobytes()
    np.testing.assert_array_equal(conv.image_to_array(msg), bgr)
    depth = np.array([[1000, 2000, 0]], dtype=">u2")  # big-endian 16UC1
    msg = Image(height=1, width=3, encoding="16UC1", step=6, is_bigendian=1)
    msg.data = depth.tobytes()
    out = conv.image_to_array(msg)
    assert out.dtype == np.uint16 and out.tolist() == [[1000, 2000, 0]]


def test_bad_images_are_refused_with_a_reason():
    from sensor_msgs.msg import Image

    msg = Image(height=2, width=2, encoding="yuv422", step=4, data=bytes(8))
    with pytest.raises(ValueError, match="unsupported image encoding"):
        conv.image_to_array(msg)
    msg = Image(height=2, width=2, encoding="bgr8", step=6, data=bytes(10))
    with pytest.raises(ValueError, match="expected height"):
        conv.image_to_array(msg)
    msg = Image(height=2, width=2, encoding="bgr8", step=4, data=bytes(8))
    with pytest.raises(ValueError, match="step"):
        conv.image_to_array(msg)
    msg = Image(height=0, width=2, encoding="mono8", step=2, data=b"")
    with pytest.raises(ValueError, match="empty"):
        conv.image_to_array(msg)


def test_camera_info_to_matrix():
    K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    msg = camera.camera_info_from_matrix(0.0, K, 640, 480, "camera")
    K2, w, h, distorted = conv.camera_info_to_matrix(msg)
    np.testing.assert_array_equal(K, K2)
    assert (w, h, distorted) == (640, 480, False)
    msg.d = [0.1, 0.0, 0.0, 0.0, 0.0]
    assert conv.camera_info_to_matrix(msg)[3] is True
    msg.k = [0.0] * 9
    with pytest.raises(ValueError, match="unset"):
        conv.camera_info_to_matrix(msg)


@pytest.mark.parametrize(("k", "size", "why"), [
    ([1e30, 0, 319.5, 0, 525.0, 239.5, 0, 0, 1], (640, 480), "focal lengths 1e\\+30"),
    ([525.0, 0, 319.5, 0, 1e-9, 239.5, 0, 0, 1], (640, 480), "focal lengths 525, 1e-09"),
    ([525.0, 0, 1e30, 0, 525.0, 239.5, 0, 0, 1], (640, 480), "principal point beyond"),
    ([525.0, 0, 319.5, 0, 525.0, 239.5, 0, 0, 1], (4_000_000_000, 480), "size 4000000000x480"),
    # within the +-1e6 px range, but outside its own 640x480 image (twists of 3x the speed)
    ([525.0, 0, 3320.0, 0, 525.0, -1760.0, 0, 0, 1], (640, 480), "outside its 640x480"),
    ([525.0, 0, 640.0, 0, 525.0, 239.5, 0, 0, 1], (640, 480), "outside its 640x480"),
])
def test_camera_info_out_of_range_is_refused(k, size, why):
    msg = camera.camera_info_from_matrix(0.0, np.eye(3), 640, 480, "camera")
    msg.k = [float(x) for x in k]
    msg.width, msg.height = size
    with pytest.raises(ValueError, match=why):
        conv.camera_info_to_matrix(msg)


def test_odometry_with_covariance():
    P = np.array([[0.01, 0.002, 0.0], [0.002, 0.02, 0.001], [0.0, 0.001, 0.003]])
    T = np.diag([1e-4, 2e-4, 3e-4, 4e-4, 5e-4, 6e-4])
    msg = conv.odometry_with_covariance(2.0, 1.0, -2.0, 0.5, P, 0.4, -0.2, T)
    assert msg.header.frame_id == "odom" and msg.child_frame_id == "base_link"
    cov = np.array(msg.pose.covariance).reshape(6, 6)
    np.testing.assert_allclose(cov[np.ix_([0, 1, 5], [0, 1, 5])], P)
    np.testing.assert_allclose(np.array(msg.twist.covariance).reshape(6, 6), T)
    t, (v, w), ok, (x, y, yaw) = conv.odometry_to_sample(msg)
    assert (t, v, w, ok) == (2.0, 0.4, -0.2, True)
    assert (x, y, yaw) == pytest.approx((1.0, -2.0, 0.5))


# ---- parameters --------------------------------------------------------------------------


def _flatten(d, prefix=""):
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def test_config_file_matches_the_parameter_table(repo_root):
    shipped = yaml.safe_load((repo_root / "config" / "vo.yaml").read_text())
    values = _flatten(shipped["/**/vo_node"]["ros__parameters"])
    assert set(values) == {p.name for p in PARAMS}
    for p in PARAMS:
        assert type(values[p.name]) is type(p.default), p.name
        if isinstance(p.default, float):
            assert values[p.name] == pytest.approx(p.default), p.name
        else:
            assert values[p.name] == p.default, p.name
    assert _flatten(yaml.safe_load(params_yaml())) == _flatten(shipped)
    vo_node_params(values)


def test_parameter_validation_names_the_problem():
    with pytest.raises(ValueError, match="sync_tolerance_s"):
        vo_node_params({"sync_tolerance_s": -1.0})
    with pytest.raises(ValueError, match=r"vo\.num_levels"):
        vo_node_params({"vo.num_levels": 2.5})
    with pytest.raises(ValueError, match="max_depth"):
        vo_node_params({"vo.min_depth": 7.0})
    with pytest.raises(ValueError, match="color_topic"):
        vo_node_params({"color_topic": ""})
    with pytest.raises(ValueError, match="base_frame"):  # blank
        vo_node_params({"base_frame": "  "})
    with pytest.raises(ValueError, match="must differ"):  # every odom read base -> base
        vo_node_params({"odom_frame": "base_link", "base_frame": "base_link"})
    p = vo_node_params({"camera_yaw": 0.0, "vo.max_depth": 4.0})
    assert p.extrinsic.yaw == 0.0 and p.vo_options["max_depth"] == 4.0


# ---- the node ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def frames():
    """Rendered frames of a chair arc (v = 0.4 m/s, omega = 0.25 rad/s) at 15 Hz."""
    from asgp_ros.sim.render import RGBDRenderer
    from asgp_ros.sim.scene import build_scene, segment_drive

    scene = build_scene(preset="rich", seed=0)
    r = RGBDRenderer(scene, seed=7)
    drive = segment_drive((0.0, 0.5, 0.3), [(0.4, 0.25, 1.2)], 15.0)
    out = [r.render_chair(x, y, th)
           for x, y, th in zip(drive.x, drive.y, drive.theta, strict=True)]
    return r.K, drive, out


class _Harness:
    """The node under test plus a driver node in one executor, polled with deadlines."""

    def __init__(self, context, overrides=()):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import TwistStamped
        from nav_msgs.msg import Odometry
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.parameter import Parameter
        from rclpy.qos import QoSProfile, qos_profile_sensor_data
        from sensor_msgs.msg import CameraInfo, Image

        from asgp_ros.nodes.vo_node import VONode

        params = [Parameter("diagnostics_period_s", value=0.2), *overrides]
        self.node = VONode(context=context, parameter_overrides=params)
        self.driver = rclpy.create_node("vo_test_driver", context=context)
        self.color = self.driver.create_publisher(Image, "camera/color/image_raw",
                                                  qos_profile_sensor_data)
        self.depth = self.driver.create_publisher(Image, "camera/depth/image_raw",
                                                  qos_profile_sensor_data)
        self.info = self.driver.create_publisher(CameraInfo, "camera/color/camera_info",
                                                 qos_profile_sensor_data)
        self.twists, self.odoms, self.diags = [], [], []
        self.driver.create_subscription(TwistStamped, "vo/twist", self.twists.append,
                                        QoSProfile(depth=100))
        self.driver.create_subscription(Odometry, "vo/odom", self.odoms.append,
                                        QoSProfile(depth=100))
        self.driver.create_subscription(DiagnosticArray, "diagnostics", self.diags.append,
                                        QoSProfile(depth=100))
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self.executor.add_node(self.driver)

    def spin_until(self, predicate, timeout=5.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate():
                return True
            self.executor.spin_once(timeout_sec=0.02)
        return predicate()

    def connect(self, K):
        ok = self.spin_until(lambda: self.color.get_subscription_count() >= 1
                             and self.depth.get_subscription_count() >= 1
                             and self.info.get_subscription_count() >= 1
                             and self.node._twist_pub.get_subscription_count() >= 1
                             and self.node._diag_pub.get_subscription_count() >= 1)
        assert ok, "discovery timed out"
        for _ in range(20):
            self.info.publish(camera.camera_info_from_matrix(0.0, K, 640, 480, "camera"))
            if self.spin_until(lambda: self.node.vo is not None, 0.5):
                return
        raise AssertionError("camera_info never arrived")

    def send(self, t, color_msg, depth_msg) -> None:
        """Publish one pair and spin until the node has processed it (re-sent if lost)."""
        before = self.node.stats["frames"]
        for _ in range(10):
            color_msg.header.stamp = conv.seconds_to_stamp(t)
            depth_msg.header.stamp = conv.seconds_to_stamp(t)
            self.color.publish(color_msg)
            self.depth.publish(depth_msg)
            if self.spin_until(lambda: self.node.stats["frames"] > before, 1.0):
                # let the outputs of this frame arrive
                self.spin_until(lambda: False, 0.05)
                return
        raise AssertionError(f"frame at {t} was never processed")

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()
        self.driver.destroy_node()


def _level(status) -> int:
    lv = status.level  # a byte field: bytes in rclpy
    return int.from_bytes(lv, "little") if isinstance(lv, bytes) else int(lv)


def _levels(diags, name="vo_node: tracking"):
    """[(level 0 OK / 1 WARN / 2 ERROR, message, values)] of the VO tracking status."""
    return [(_level(s), s.message, conv.diagnostic_values(s))
            for d in diags for s in d.status if s.name == name]


@pytest.mark.ros
def test_node_publishes_the_chair_twist_and_reports_failures(rclpy_context, frames):
    K, drive, images = frames
    h = _Harness(rclpy_context)
    try:
        h.connect(K)
        t0 = 100.0
        for k, (img, depth) in enumerate(images):
            mm = np.rint(depth * 1000).astype(np.uint16)  # 16UC1 millimetres, as drivers do
            h.send(t0 + drive.t[k], camera.image_from_array(0.0, img, "camera"),
                   camera.image_from_array(0.0, mm, "camera"))
        n = len(images)
        assert len(h.twists) == n - 1  # every frame but the first (the reference)
        for msg in h.twists:
            assert msg.header.frame_id == "base_link"
            assert msg.twist.linear.x == pytest.approx(0.4, abs=0.04)
            assert msg.twist.angular.z == pytest.approx(0.25, abs=0.03)
        stamps = [conv.stamp_to_seconds(m.header.stamp) for m in h.twists]
        np.testing.assert_allclose(stamps, t0 + drive.t[1:], atol=1e-6)
        assert len(h.odoms) == n - 1
        last = h.odoms[-1]
        assert (last.header.frame_id, last.child_frame_id) == ("odom", "base_link")
        _, _, ok, (x, y, yaw) = conv.odometry_to_sample(last)
        assert ok and yaw == pytest.approx(drive.theta[-1] - drive.theta[0], abs=0.02)
        dist = math.hypot(drive.x[-1] - drive.x[0], drive.y[-1] - drive.y[0])
        assert math.hypot(x, y) == pytest.approx(dist, abs=0.03)
        assert np.array(last.pose.covariance)[0] > 0
        assert any(level == 0 for level, _, _ in _levels(h.diags))  # OK while tracking

        # failures: bad encoding, no depth, mismatched sizes, a blank image -> no twist
        img, depth = images[-1]
        mm = np.rint(depth * 1000).astype(np.uint16)
        bad = camera.image_from_array(0.0, img, "camera")
        bad.encoding = "yuv422"
        t = t0 + drive.t[-1]
        dt = 1.0 / 15.0

        def noisy(n):  # the last frame again, with a camera's noise (a repeat is frozen)
            out = img.copy()
            out.flat[n] ^= 1
            return camera.image_from_array(0.0, out, "camera")
        cases = [
            (bad, camera.image_from_array(0.0, mm, "camera"), "bad_input"),
            (noisy(1), camera.image_from_array(0.0, np.zeros_like(mm), "camera"), "no_depth"),
            (noisy(2), camera.image_from_array(0.0, mm[:240, :320].copy(), "camera"),
             "bad_input"),
            (camera.image_from_array(0.0, np.zeros_like(img), "camera"),
             camera.image_from_array(0.0, depth, "camera"), "insufficient_features"),
        ]
        count = len(h.twists)
        for color_msg, depth_msg, status in cases:
            t += dt
            h.send(t, color_msg, depth_msg)
            assert h.node.last_result.status.value == status
            assert len(h.twists) == count  # never the last twist again
            assert h.spin_until(lambda s=status: any(
                vals.get("status") == s and level > 0 for level, _, vals in _levels(h.diags)))
        levels = {vals["status"]: (level, msg) for level, msg, vals in _levels(h.diags)}
        assert levels["bad_input"][0] == 2 and "no twist published" in levels["bad_input"][1]
        assert levels["insufficient_features"][0] == 1
        # texture and depth return: tracking against the last good reference again
        t += dt
        h.send(t, camera.image_from_array(0.0, img, "camera"),
               camera.image_from_array(0.0, depth, "camera"))  # 32FC1 metres this time
        assert h.node.last_result.ok
        assert len(h.twists) == count + 1
        assert h.twists[-1].twist.linear.x == pytest.approx(0.0, abs=0.05)  # same pose
        assert h.node.stats["bad_input"] == 2 and h.node.stats["lost"] == 4
        # the same colour image again, bit for bit (a frozen camera driver re-stamping its
        # last frame): it was tracked as the chair stopped, with a tiny variance
        t += dt
        h.send(t, camera.image_from_array(0.0, img, "camera"),
               camera.image_from_array(0.0, depth, "camera"))
        assert h.node.last_result.status.value == "bad_input"
        assert "frozen camera" in h.node.last_result.message
        assert len(h.twists) == count + 1 and h.node.stats["frozen"] == 1
    finally:
        h.close()


@pytest.mark.ros
def test_stamps_going_back_restart_the_odometry_and_a_repeated_pair_is_ignored(
        rclpy_context, frames):
    """A bag played again (stamps 3 s back): the odometry restarts once three pairs in a
    row came on the new timeline (a reference, no twist), then tracks again; a pair
    stamped at or before the last one but within ``_JUMP_BACK_S`` (a repeat, a late pair)
    publishes nothing."""
    K, drive, images = frames
    h = _Harness(rclpy_context)

    def msgs(k):
        img, depth = images[k]
        return (camera.image_from_array(0.0, img, "camera"),
                camera.image_from_array(0.0, depth, "camera"))

    try:
        h.connect(K)
        t0 = 100.0
        for k in range(4):
            h.send(t0 + drive.t[k], *msgs(k))
        assert len(h.twists) == 3 and h.node.stats["resets"] == 0
        # the last pair again, and one half a frame older: nothing processed
        frames_before = h.node.stats["frames"]
        for dt in (0.0, -0.03):
            c, d = msgs(3)
            stamp = conv.seconds_to_stamp(t0 + drive.t[3] + dt)
            c.header.stamp = d.header.stamp = stamp
            h.color.publish(c)
            h.depth.publish(d)
            h.spin_until(lambda: False, 0.3)
        assert h.node.stats["frames"] == frames_before and len(h.twists) == 3
        assert h.node.stats["not_newer"] == 2
        # the diagnostics say that pairs come but their stamps do not advance
        assert h.spin_until(lambda: any(
            level == 2 and "none stamped after the last one processed" in msg
            for level, msg, _ in _levels(h.diags)), 3.0)
        # 3 s back: one stray pair is refused (it reset the odometry to the origin
        # mid-drive); the third pair in a row on the new timeline restarts it there
        t1 = t0 + drive.t[3] - 3.0
        not_newer = h.node.stats["not_newer"]
        for k in range(2):
            c, d = msgs(k)
            c.header.stamp = d.header.stamp = conv.seconds_to_stamp(t1 + drive.t[k])
            h.color.publish(c)
            h.depth.publish(d)
            assert h.spin_until(lambda n=not_newer + k + 1: h.node.stats["not_newer"] >= n)
        assert h.node.stats["resets"] == 0
        h.send(t1 + drive.t[2], *msgs(2))
        assert h.node.stats["resets"] == 1 and len(h.twists) == 3  # a reference, no twist
        for k in range(3, 6):
            h.send(t1 + drive.t[k], *msgs(k))
        assert len(h.twists) == 6
        assert h.twists[-1].twist.linear.x == pytest.approx(0.4, abs=0.04)
        assert conv.stamp_to_seconds(h.twists[-1].header.stamp) == pytest.approx(
            t1 + drive.t[5], abs=1e-6)
        _, _, ok, (x, y, yaw) = conv.odometry_to_sample(h.odoms[-1])
        dist = math.hypot(drive.x[5] - drive.x[2], drive.y[5] - drive.y[2])
        assert ok and math.hypot(x, y) == pytest.approx(dist, abs=0.03)  # from the restart
        assert yaw == pytest.approx(drive.theta[5] - drive.theta[2], abs=0.02)
    finally:
        h.close()


def test_a_camera_clock_stepped_back_less_than_a_second_gives_no_false_twist(
        rclpy_context, frames):
    """The camera's clock steps back 0.4 s (under _JUMP_BACK_S: no restart). The pairs at or
    before the last one processed are ignored; the first one past it was tracked against a
    frame 7 periods older and its motion divided by one period: a twist of 1.4 m/s for
    0.2 m/s, with a covariance calling it certain. It restarts tracking, pose held, now."""
    K, drive, images = frames
    h = _Harness(rclpy_context)

    def send(k, t):
        img, depth = images[k]
        h.send(t, camera.image_from_array(0.0, img, "camera"),
               camera.image_from_array(0.0, depth, "camera"))

    try:
        h.connect(K)
        t0, back = 100.0, 6 / 15.0
        for k in range(4):
            send(k, t0 + drive.t[k])
        assert len(h.twists) == 3
        for k in range(4, 10):  # at or before the last pair processed: ignored
            img, depth = images[k]
            c = camera.image_from_array(0.0, img, "camera")
            d = camera.image_from_array(0.0, depth, "camera")
            c.header.stamp = d.header.stamp = conv.seconds_to_stamp(t0 + drive.t[k] - back)
            n = h.node.stats["not_newer"]
            h.color.publish(c)
            h.depth.publish(d)
            assert h.spin_until(lambda n=n: h.node.stats["not_newer"] > n)
        for k in range(10, 14):
            send(k, t0 + drive.t[k] - back)
        assert h.node.stats["resyncs"] == 1 and len(h.twists) == 6  # k = 10: a reference
        for m in h.twists[3:]:
            assert m.twist.linear.x == pytest.approx(0.4, abs=0.05), m.twist
        _, _, ok, (x, y, _) = conv.odometry_to_sample(h.odoms[-1])
        # the pose held through the restart (frames 0-3 then 10-13: 0.16 m), not reset to
        # the origin (0.08 m); the motion of frames 3-10 is unknown
        assert ok and math.hypot(x, y) == pytest.approx(0.16, abs=0.02)
    finally:
        h.close()


def _msgs(images, k, colour_frame="camera", depth_frame="camera"):
    img, depth = images[k]
    return (camera.image_from_array(0.0, img, colour_frame),
            camera.image_from_array(0.0, depth, depth_frame))


@pytest.mark.ros
def test_a_pair_stamped_before_the_epoch_or_ahead_of_the_clock_is_refused(
        rclpy_context, frames):
    """A negative stamp (int32 seconds allow it) crashed the node when its twist was
    stamped; one stamped far ahead of the node's clock (one glitched frame), tracked, made
    every later pair look stamped back in time, and the odometry restarted at the origin.
    Both are refused as bad input, and the track goes on."""
    from builtin_interfaces.msg import Time

    K, drive, images = frames
    h = _Harness(rclpy_context)
    try:
        h.connect(K)
        t0 = h.node.get_clock().now().nanoseconds * 1e-9 - 10.0  # a live camera's stamps
        for k in range(4):
            h.send(t0 + drive.t[k], *_msgs(images, k))
        assert len(h.twists) == 3
        bad = h.node.stats["bad_input"]
        c, d = _msgs(images, 4)
        c.header.stamp = d.header.stamp = Time(sec=-10, nanosec=0)
        h.color.publish(c)
        h.depth.publish(d)
        assert h.spin_until(lambda: h.node.stats["bad_input"] == bad + 1)
        assert "before the clock's epoch" in h.node.last_result.message
        c, d = _msgs(images, 4)
        c.header.stamp = d.header.stamp = conv.seconds_to_stamp(t0 + drive.t[4] + 3600.0)
        h.color.publish(c)  # an hour ahead
        h.depth.publish(d)
        assert h.spin_until(lambda: h.node.stats["bad_input"] == bad + 2)
        assert "after this node's clock" in h.node.last_result.message
        # one glitched pair 0.4 s ahead (it was tracked: its twist 0.03 m/s for 0.2)
        c, d = _msgs(images, 4)
        now = h.node.get_clock().now().nanoseconds * 1e-9
        c.header.stamp = d.header.stamp = conv.seconds_to_stamp(now + 0.4)
        h.color.publish(c)
        h.depth.publish(d)
        assert h.spin_until(lambda: h.node.stats["bad_input"] == bad + 3)
        assert "after this node's clock" in h.node.last_result.message
        bad += 1
        # while only such pairs come (a camera on its own clock), the diagnostics say why
        h.diags.clear()
        assert h.spin_until(lambda: any(
            level == 2 and "no colour/depth pair" in msg and "after this node's clock" in msg
            for level, msg, _ in _levels(h.diags)), 5.0)
        for k in range(5, 8):
            h.send(t0 + drive.t[k], *_msgs(images, k))
        assert h.node.stats["resets"] == 0 and len(h.twists) == 6
        _, _, ok, (x, y, _) = conv.odometry_to_sample(h.odoms[-1])
        dist = math.hypot(drive.x[7] - drive.x[0], drive.y[7] - drive.y[0])
        assert ok and math.hypot(x, y) == pytest.approx(dist, abs=0.03)  # not restarted
    finally:
        h.close()


@pytest.mark.ros
def test_pairs_refused_from_the_start_are_said_not_waited_for(rclpy_context, frames):
    """Every pair refused from the first (a camera on its own clock, an hour ahead): the
    diagnostics said "waiting for colour/depth pairs" forever; and a pair stamped past a
    message's int32 seconds (2038) is refused whatever the node's clock (at 0 under
    use_sim_time before /clock, its twist went out stamped 1901)."""
    from builtin_interfaces.msg import Time

    K, _, images = frames
    h = _Harness(rclpy_context)
    try:
        h.connect(K)
        c, d = _msgs(images, 0)
        c.header.stamp = d.header.stamp = Time(sec=2**31 - 1, nanosec=999_999_999)
        h.color.publish(c)
        h.depth.publish(d)
        assert h.spin_until(lambda: h.node.stats["bad_input"] == 1)
        assert "int32" in h.node.last_result.message
        now = h.node.get_clock().now().nanoseconds * 1e-9
        c, d = _msgs(images, 1)
        c.header.stamp = d.header.stamp = conv.seconds_to_stamp(now + 3600.0)
        h.color.publish(c)
        h.depth.publish(d)
        assert h.spin_until(lambda: h.node.stats["bad_input"] == 2)
        h.diags.clear()
        assert h.spin_until(lambda: any(
            level == 2 and "every colour/depth pair refused" in msg
            and "after this node's clock" in msg for level, msg, _ in _levels(h.diags)), 5.0)
        assert not h.twists
    finally:
        h.close()


@pytest.mark.ros
def test_a_new_camera_calibration_restarts_tracking_with_the_pose_held(rclpy_context, frames):
    """camera_info changes mid-stream (the driver restarted): the chair has not moved, so
    vo/odom goes on from the pose it had, its variance raised as after a tracking loss, and
    the restart is counted; it used to start again at the origin, as sure as before."""
    from asgp_ros.vo.planar import RESET_VARIANCE

    K, drive, images = frames
    h = _Harness(rclpy_context)
    try:
        h.connect(K)
        for k in range(6):
            h.send(100.0 + drive.t[k], *_msgs(images, k))
        _, _, _, (x0, y0, _) = conv.odometry_to_sample(h.odoms[-1])
        var0 = h.odoms[-1].pose.covariance[0]
        K2 = np.array(K, dtype=float)
        K2[0, 0] *= 1.001
        h.info.publish(camera.camera_info_from_matrix(0.0, K2, 640, 480, "camera"))
        assert h.spin_until(lambda: h.node.stats["resets"] == 1)
        for k in range(6, 10):
            h.send(100.0 + drive.t[k], *_msgs(images, k))
        assert h.node.last_result.ok
        _, _, ok, (x, y, _) = conv.odometry_to_sample(h.odoms[-1])
        moved = math.hypot(drive.x[9] - drive.x[6], drive.y[9] - drive.y[6])
        assert ok and math.hypot(x - x0, y - y0) == pytest.approx(moved, abs=0.03)
        assert h.odoms[-1].pose.covariance[0] >= var0 + RESET_VARIANCE
    finally:
        h.close()


@pytest.mark.ros
def test_a_refused_camera_info_says_why_and_unpaired_images_are_counted(
        rclpy_context, frames):
    """The diagnostics give the reason a camera_info is refused (they said "waiting for
    camera_info" while it came, refused, ten times a second), count the images that went
    without a partner, and say when colour and depth come from different frames (depth not
    registered to the colour camera)."""
    K, drive, images = frames
    h = _Harness(rclpy_context)
    try:
        assert h.spin_until(lambda: h.info.get_subscription_count() >= 1)
        h.info.publish(camera.camera_info_from_matrix(0.0, np.zeros((3, 3)), 640, 480,
                                                      "camera"))
        assert h.spin_until(lambda: any(
            level == 2 and "refused" in msg and "uncalibrated" in msg
            for level, msg, _ in _levels(h.diags)))
        h.connect(K)
        for i in range(12):  # depth 40 ms after colour: beyond sync_tolerance_s
            c, d = _msgs(images, i % 3)
            c.header.stamp = conv.seconds_to_stamp(100.0 + i / 15.0)
            d.header.stamp = conv.seconds_to_stamp(100.04 + i / 15.0)
            h.color.publish(c)
            h.depth.publish(d)
            h.spin_until(lambda: False, 0.02)
        assert h.spin_until(lambda: h.node.stats["evicted"] >= 8)
        assert h.spin_until(lambda: any(
            "went without a partner within sync_tolerance_s" in msg
            for _, msg, _ in _levels(h.diags)[-2:]))
        for k in range(3):
            h.send(101.0 + drive.t[k], *_msgs(images, k, depth_frame="camera_depth"))
        assert len(h.twists) == 2
        h.diags.clear()
        assert h.spin_until(lambda: any(
            level == 1 and "colour and depth frames differ" in msg
            for level, msg, _ in _levels(h.diags)))
    finally:
        h.close()


@pytest.mark.ros
def test_node_refuses_runtime_changes_and_bad_start_values(rclpy_context):
    from rclpy.parameter import Parameter

    from asgp_ros.nodes.vo_node import VONode

    node = VONode(context=rclpy_context)
    try:
        res = node.set_parameters([Parameter("sync_tolerance_s", value=0.05)])
        assert not res[0].successful and "restart" in res[0].reason
        assert node.get_parameter("sync_tolerance_s").value == pytest.approx(0.02)
    finally:
        node.destroy_node()
    with pytest.raises(ValueError, match="max_depth"):
        VONode(context=rclpy_context,
               parameter_overrides=[Parameter("vo.min_depth", value=7.0)])
    with pytest.raises(ValueError, match="min_inliers"):  # 6: a covariance divided by zero
        VONode(context=rclpy_context,
               parameter_overrides=[Parameter("vo.min_inliers", value=6)])


@pytest.mark.ros
def test_newest_pair_is_processed_and_older_frames_dropped(rclpy_context):
    from sensor_msgs.msg import Image

    from asgp_ros.nodes.vo_node import VONode

    node = VONode(context=rclpy_context)
    try:
        msgs = {t: Image() for t in (1.0, 1.1, 1.2, 1.3)}
        node._color.extend((t, m) for t, m in msgs.items())
        node._depth.extend([(1.005, Image()), (1.105, Image()), (1.203, Image())])
        stamp, cmsg, _ = node._take_pair()
        assert stamp == 1.2 and cmsg is msgs[1.2]  # 1.3 has no depth partner yet
        assert node.stats["dropped"] == 2
        assert [t for t, _ in node._color] == [1.3] and not node._depth
        assert node._take_pair() is None
    finally:
        node.destroy_node()


@pytest.mark.ros
def test_pairs_queued_behind_a_slow_frame_are_skipped_for_the_newest(rclpy_context, frames):
    """rclpy's executor takes one message per subscription per wake-up, and the node chose
    a pair after each: five pairs queued while it was busy were processed oldest first
    (each about five frame periods late at 15 Hz). The newest only is processed now."""
    K, _, images = frames
    h = _Harness(rclpy_context)
    try:
        h.connect(K)
        t0 = 100.0
        h.send(t0, *_msgs(images, 0))
        for k in range(1, 6):  # delivered while the node does not spin (busy)
            c, d = _msgs(images, k)
            c.header.stamp = d.header.stamp = conv.seconds_to_stamp(t0 + k / 15.0)
            h.color.publish(c)
            h.depth.publish(d)
        time.sleep(2.0)  # (into the subscriptions' queues; nothing is timed)
        processed = []
        real = h.node.vo.process

        def spy(image, depth, stamp):
            processed.append(round(stamp - t0, 4))
            return real(image, depth, stamp)
        h.node.vo.process = spy
        h.spin_until(lambda: False, 1.0)
        assert processed == [round(5 / 15.0, 4)], processed
        assert h.node.stats["dropped"] >= 4
    finally:
        h.close()


@pytest.mark.ros
def test_camera_info_that_keeps_changing_is_said(rclpy_context, frames):
    """Two calibrations alternating on camera_info (two cameras' drivers in one namespace):
    each change restarts tracking, no twist ever comes, and the diagnostics said only
    'initialising'."""
    K, drive, images = frames
    K2 = np.array(K, float)
    K2[0, 0] *= 1.01
    h = _Harness(rclpy_context)
    try:
        h.connect(K)
        for k in range(6):
            h.info.publish(camera.camera_info_from_matrix(0.0, K2 if k % 2 else K, 640, 480,
                                                          "camera"))
            h.spin_until(lambda k=k: h.node.stats["resets"] >= k, 1.0)
            h.send(100.0 + drive.t[k], *_msgs(images, k))
        h.diags.clear()
        assert h.spin_until(lambda: len(_levels(h.diags)) >= 1, 3.0)
        _, msg, _ = _levels(h.diags)[-1]
        assert len(h.twists) == 0 and "camera_info changed" in msg, msg
    finally:
        h.close()


@pytest.mark.ros
def test_images_of_the_old_timeline_are_dropped_when_the_stamps_go_back(rclpy_context):
    """A colour image waiting for its depth partner when the stamps went back 3 s (a bag
    restarted, the camera's clock stepped) is never paired with an image of the new
    timeline that carries the same stamp 3 s later: it goes once three pairs' images in a
    row came on the new timeline. One stray image stamped far back drops nothing (it
    dropped the images waiting for their partners)."""
    from sensor_msgs.msg import Image

    from asgp_ros.nodes.vo_node import VONode

    def image(t):
        msg = Image()
        msg.header.stamp = conv.seconds_to_stamp(t)
        return msg

    node = VONode(context=rclpy_context)
    try:
        stale = image(12.9)
        node._on_color(image(12.8))
        node._on_depth(image(12.8))
        node._on_color(stale)  # its depth never comes (dropped by the camera)
        assert node._take_pair()[0] == 12.8 and [t for t, _ in node._color] == [12.9]
        dropped = node.stats["dropped"]
        node._on_depth(image(10.0))  # the stamps go back
        node._on_color(image(10.0))
        assert node._take_pair()[0] == 10.0
        for t in (10.25, 10.5):
            node._on_depth(image(t))
            assert [c for c, _ in node._color] == [12.9]  # not yet: maybe a stray
            node._on_color(image(t))
            if t == 10.25:
                assert node._take_pair()[0] == t
        # the sixth image in a row on the new timeline: the old colour image goes
        assert [t for t, _ in node._color] == [10.5] and node.stats["dropped"] == dropped + 1
        assert node._take_pair()[0] == 10.5
        for t in (11.0, 12.0):
            node._on_depth(image(t))
            node._on_color(image(t))
            assert node._take_pair()[0] == t
        fresh = image(12.9)
        node._on_depth(image(12.9))
        node._on_color(fresh)
        stamp, cmsg, _ = node._take_pair()
        assert stamp == 12.9 and cmsg is fresh
        # an image a little older than the buffered ones (out of order) drops nothing
        node._on_color(image(13.0))
        node._on_depth(image(12.5))
        assert len(node._color) == 1 and len(node._depth) == 1
        assert node._take_pair() is None
        # one stray image (and a stray pair) stamped far back: the colour image waiting
        # for its depth partner stays, and is paired when the partner comes
        dropped = node.stats["dropped"]
        node._on_depth(image(9.0))
        node._on_color(image(9.0))
        assert sorted(t for t, _ in node._color) == [9.0, 13.0]
        node._on_depth(image(13.0))
        assert node._take_pair()[0] == 13.0
        assert not node._color and not node._depth
        assert node.stats["dropped"] == dropped + 1  # the stray colour image, as older
    finally:
        node.destroy_node()


@pytest.mark.e2e
@pytest.mark.slow
def test_vo_node_process_starts_with_the_shipped_config(repo_root, tmp_path):
    """The console entry point runs with config/vo.yaml and shuts down on SIGINT."""
    import signal
    import subprocess

    proc = subprocess.Popen(
        [sys.executable, "-c", "from asgp_ros.nodes.vo_node import main; main()",
         "--ros-args", "--params-file", str(repo_root / "config" / "vo.yaml"),
         "-r", "__node:=vo_node"],
        cwd=repo_root, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 30
        out = ""
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            out += line
            if "VO on /camera/color/image_raw" in line or proc.poll() is not None:
                break
        assert "VO on /camera/color/image_raw" in out, out
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    assert proc.returncode in (0, -signal.SIGINT), proc.returncode


@pytest.mark.ros
def test_no_event_handler_per_endpoint_and_an_unmatched_peer_is_reported(rclpy_context):
    """As predictor_node's (asgp_ros.nodes.qos_watch): rclpy's per-endpoint QoS event
    handlers are off on the VO's endpoints, and a peer that cannot be matched (a
    subscription of the twist that asks for transient-local durability) is named in the
    diagnostics until it goes."""
    from geometry_msgs.msg import TwistStamped
    from rclpy.qos import DurabilityPolicy, QoSProfile

    h = _Harness(rclpy_context)
    node = h.node
    try:
        mine = [e for e in [*node.subscriptions, *node.publishers]
                if e.topic_name not in ("/parameter_events", "/rosout", "/clock")]
        assert len(mine) == 6 and all(not e.event_handlers for e in mine), [
            e.topic_name for e in mine if e.event_handlers]
        assert h.spin_until(lambda: node.qos_watch.check() == [])
        latched = QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        wrong = h.driver.create_subscription(TwistStamped, "vo/twist", lambda _: None, latched)

        def newest() -> str:
            found = _levels(h.diags)
            return found[-1][2].get("qos_mismatch", "") if found else ""

        # the node's own check, at its diagnostics period, finds it
        assert h.spin_until(lambda: newest().startswith(
            "/vo/twist: subscription of /vo_test_driver: incompatible")), newest()
        assert node.qos_watch.problems == [newest()]
        level, message, _ = _levels(h.diags)[-1]
        assert level >= 1 and message.endswith(f"; cannot be matched: {newest()}")
        h.driver.destroy_subscription(wrong)
        assert h.spin_until(lambda: newest() == "none")
        assert "cannot be matched" not in _levels(h.diags)[-1][1]
    finally:
        h.close()


@pytest.mark.ros
def test_a_stopped_camera_says_stale_not_the_last_twist(rclpy_context, frames):
    """The camera stops: ERROR 'no colour/depth pair ... no twist published', while the
    values said status 'ok' with the last twist's v and omega."""
    K, drive, images = frames
    h = _Harness(rclpy_context)
    try:
        h.connect(K)
        for k, (img, depth) in enumerate(images[:6]):
            mm = np.rint(depth * 1000).astype(np.uint16)
            h.send(100.0 + drive.t[k], camera.image_from_array(0.0, img, "camera"),
                   camera.image_from_array(0.0, mm, "camera"))
        h.spin_until(lambda: False, h.node.params.stale_timeout_s + 0.6)  # silent
        level, message, values = _levels(h.diags)[-1]
        assert level == 2 and "no twist published" in message
        assert values.get("status") == "stale" and "v" not in values, values
    finally:
        h.close()
