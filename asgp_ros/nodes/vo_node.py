"""vo_node: Fovis-like RGB-D visual odometry (:mod:`asgp_ros.vo`) on ROS 2.

Subscribes colour, depth (sensor-data QoS) and the colour camera_info; pairs colour and
depth by approximate time (``sync_tolerance_s``); publishes, for every tracked frame,

* ``vo/twist`` (geometry_msgs/TwistStamped, ``base_frame``): linear.x = v, angular.z =
  omega of base_link, from the camera motion and the camera extrinsic (``camera_*``);
* ``vo/odom`` (nav_msgs/Odometry, ``odom_frame`` -> ``base_frame``) with the pose and
  twist covariances (on the first frame tracked after a loss the pose is known but the
  twist is not: it is zero with a variance of ``ODOM_LOST_VARIANCE``, and no vo/twist);

and the tracking state on ``diagnostics``. A frame that is not tracked (no features, no
inliers, no depth, bad input, ...) publishes nothing: never the last twist again. The
diagnostics say why, at once when the state changes and every ``diagnostics_period_s``.

Work flow: the image callbacks only store the message and wake a guard condition; its
callback processes the newest complete colour/depth pair and drops older ones, so a slow
frame never builds a backlog. Parameters are read once at start-up and validated
(:mod:`asgp_ros.vo.params`); runtime changes are refused with a reason.
"""

from __future__ import annotations

import collections
import math
import sys
import time
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TwistStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, Image

from asgp_ros.common import topics
from asgp_ros.nodes import conversions as conv
from asgp_ros.nodes import runtime
from asgp_ros.nodes.parameters import declare, refuse_at_runtime
from asgp_ros.nodes.polled import take_waiting
from asgp_ros.nodes.qos_watch import QosWatch
from asgp_ros.vo.odometry import Status, VisualOdometry, VOResult
from asgp_ros.vo.params import PARAMS, SPECS, VONodeParams, vo_node_params
from asgp_ros.vo.planar import PlanarOdometry

#: Diagnostic level per VO status.
_LEVEL = {
    Status.OK: "OK",
    Status.REFERENCE_SET: "WARN",
    Status.INSUFFICIENT_FEATURES: "WARN",
    Status.INSUFFICIENT_INLIERS: "WARN",
    Status.OPTIMIZATION_FAILURE: "WARN",
    Status.REPROJECTION_ERROR_TOO_HIGH: "WARN",
    Status.NO_DEPTH: "ERROR",
    Status.BAD_INPUT: "ERROR",
}
_BUFFER = 8  # messages kept per image stream while waiting for a partner
_JUMP_BACK_S = 1.0  # stamps going back more than this (bag restart) reset the odometry...
_JUMP_BACK_PAIRS = 3  # ... once this many pairs in a row came on the new timeline
_INFO_CHANGES_WINDOW_S = 10.0  # camera_info changes this recent are said while initialising
#: A pair stamped more than this after the node's clock is refused: one such pair, tracked,
#: would make every later (correct) pair look stamped back in time and reset the odometry,
#: and its own twist divided a frame's motion by the lead (0.4 s ahead: 0.03 m/s for 0.2).
#: As the other nodes' leads (a camera stamps with the host's clock at capture: behind it;
#: ``ros2 bag play --clock HZ`` lags by 1 / HZ).
_AHEAD_S = 0.1


class VONode(Node):
    """See the module docstring."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("vo_node", **kwargs)
        # raises ValueError naming the parameter: the node does not start with bad values
        self.params: VONodeParams = vo_node_params(declare(self, PARAMS))
        self.add_on_set_parameters_callback(refuse_at_runtime(self, SPECS, "vo_node"))
        p = self.params
        reliable = QoSProfile(depth=10)
        # endpoints without rclpy's per-endpoint QoS event handlers (waitables at every
        # wake-up, three image streams' worth of them); the peers are checked at the
        # diagnostics period instead (asgp_ros/nodes/qos_watch.py)
        self.qos_watch = watch = QosWatch(self)
        self._twist_pub = watch.publisher(TwistStamped, topics.VO_TWIST, reliable)
        self._odom_pub = (watch.publisher(Odometry, topics.VO_ODOM, reliable)
                          if p.publish_odom else None)
        self._diag_pub = watch.publisher(DiagnosticArray, topics.DIAGNOSTICS, reliable)
        self._color: collections.deque[tuple[float, Image]] = collections.deque(maxlen=_BUFFER)
        self._depth: collections.deque[tuple[float, Image]] = collections.deque(maxlen=_BUFFER)
        self._wake = self.create_guard_condition(self._process_newest)
        # (kept: the images waiting in them are taken before each pair is chosen)
        self._image_subs = (
            (watch.subscription(Image, p.color_topic, self._on_color, qos_profile_sensor_data),
             self._on_color),
            (watch.subscription(Image, p.depth_topic, self._on_depth, qos_profile_sensor_data),
             self._on_depth))
        info_sub = watch.subscription(CameraInfo, p.camera_info_topic, self._on_info,
                                      qos_profile_sensor_data)
        # the topics as the node reads them (namespace and remaps applied), for everything
        # that names them to the user: the parameters' names were said under a remap
        self._color_topic = self._image_subs[0][0].topic_name
        self._depth_topic = self._image_subs[1][0].topic_name
        self._info_topic = info_sub.topic_name
        runtime.guard_sim_clock(self)
        self.create_timer(p.diagnostics_period_s, self._on_diagnostics_timer,
                          clock=runtime.pacing_clock(self))

        self.vo: VisualOdometry | None = None
        self.planar = PlanarOdometry(p.extrinsic)
        self._K: np.ndarray | None = None
        self._info_size: tuple[int, int] | None = None
        self._last_stamp: float | None = None  # last processed pair (colour stamp)
        self._last_processed_wall: float | None = None  # time.monotonic() of the last pair
        self.last_result: VOResult | None = None
        self._last_problem = ""  # why the last pair was refused (bad image, bad stamp), if it was
        self._elapsed: collections.deque[float] = collections.deque(maxlen=100)
        self.stats = {"frames": 0, "tracked": 0, "lost": 0, "bad_input": 0, "dropped": 0,
                      "twists": 0, "resets": 0, "camera_info_errors": 0, "not_newer": 0,
                      "colour_images": 0, "depth_images": 0, "evicted": 0, "frozen": 0,
                      "resyncs": 0}
        self._last_colour: Image | None = None  # the last processed colour image
        self._behind: list[float] = []  # stamps of the pairs in a row far behind the last
        # a pair came stamped before the last processed one (the camera's clock stepped
        # back, a pair delivered late): the next pair's motion spans an unknown time
        self._resync = False
        self._back_images = 0  # images in a row stamped far behind the newest buffered one
        # when camera_info last changed (time.monotonic), the newest few
        self._info_changes: collections.deque[float] = collections.deque(maxlen=100)
        self._evicted_since_pair = 0  # images pushed out of a full buffer since a pair
        self._info_problem = ""  # why the last camera_info was refused, if it was
        self._frames = ("", "")  # frame_id of the last colour and depth image paired
        self._not_newer_since_processed = 0  # pairs not newer than the last processed one
        self.get_logger().info(
            f"VO on {self._color_topic} + {self._depth_topic} ({self._info_topic}); camera at "
            f"({p.extrinsic.x:.2f}, {p.extrinsic.y:.2f}, {p.extrinsic.z:.2f}) m, yaw "
            f"{p.extrinsic.yaw:.2f} rad, pitch {p.extrinsic.pitch:.2f} rad in {p.base_frame}")

    # -- input ---------------------------------------------------------------------------

    def _on_color(self, msg: Image) -> None:
        self.stats["colour_images"] += 1
        self._buffer(msg, colour=True)

    def _on_depth(self, msg: Image) -> None:
        self.stats["depth_images"] += 1
        self._buffer(msg, colour=False)

    def _buffer(self, msg: Image, colour: bool) -> None:
        t = conv.stamp_to_seconds(msg.header.stamp)
        self._drop_old_timeline(t)  # (may replace the queues)
        queue = self._color if colour else self._depth
        if len(queue) == _BUFFER:  # its oldest image goes, unpaired and unprocessed
            self.stats["evicted"] += 1
            self._evicted_since_pair += 1
        queue.append((t, msg))
        self._wake.trigger()

    def _drop_old_timeline(self, t: float) -> None:
        """Images stamped more than ``_JUMP_BACK_S`` before a buffered one, as many in a row
        as ``_JUMP_BACK_PAIRS`` pairs have: the stamps went back (a bag restarted, the
        camera's clock stepped). The buffered images stamped after them belong to the old
        timeline; kept, one waiting for its partner would be paired, once the new stamps
        reach its own, with an image of another moment. One stray image stamped far back
        drops nothing (it dropped the images waiting for their partners): it is older than
        the pairs to come, and goes when one of them is taken."""
        newest = max((s for s, _ in (*self._color, *self._depth)), default=-math.inf)
        if not t < newest - _JUMP_BACK_S:
            self._back_images = 0
            return
        self._back_images += 1
        if self._back_images < 2 * _JUMP_BACK_PAIRS:
            return
        n = len(self._color) + len(self._depth)
        self._color = collections.deque((c for c in self._color if c[0] <= t), maxlen=_BUFFER)
        self._depth = collections.deque((d for d in self._depth if d[0] <= t), maxlen=_BUFFER)
        self.stats["dropped"] += n - len(self._color) - len(self._depth)
        self._back_images = 0

    def _on_info(self, msg: CameraInfo) -> None:
        try:
            K, w, h, distorted = conv.camera_info_to_matrix(msg)
            if self._K is not None and np.allclose(K, self._K) and self._info_size == (w, h):
                self._info_problem = ""
                return
            size = (w, h) if w > 0 and h > 0 else None
            vo = VisualOdometry(K, extrinsic=self.params.extrinsic, image_size=size,
                                **self.params.vo_options)
        except ValueError as exc:
            self.stats["camera_info_errors"] += 1
            self._info_problem = str(exc)
            self.get_logger().warn(f"camera_info refused: {exc}", throttle_duration_sec=5.0)
            return
        self._info_problem = ""
        if distorted:
            self.get_logger().warn("camera_info has non-zero distortion: vo_node expects "
                                   "rectified images (image_rect) and uses K only")
        if self.vo is not None:
            # a new calibration of the same camera (a driver restarted): the chair has not
            # moved, so the pose is held, and re-initialised with its variance
            # (PlanarOdometry), as after a tracking loss
            self.get_logger().warn("camera_info changed: tracking restarts, pose held",
                                   throttle_duration_sec=5.0)
            self._info_changes.append(time.monotonic())
            vo.restart(self.vo.pose)
            self.stats["resets"] += 1
        self._K, self._info_size = K, (w, h)
        self.vo = vo
        self._last_stamp = None
        self._wake.trigger()

    def _take_pair(self) -> tuple[float, Image, Image] | None:
        """Newest colour message with a depth partner within tolerance; drops older ones."""
        tol = self.params.sync_tolerance_s
        if not self._color or not self._depth:
            return None
        depth = list(self._depth)
        for tc, cmsg in sorted(self._color, key=lambda x: x[0], reverse=True):
            td, dmsg = min(depth, key=lambda x: abs(x[0] - tc))
            if abs(td - tc) <= tol:
                older = [c for c in self._color if c[0] < tc]
                self.stats["dropped"] += len(older)
                self._color = collections.deque((c for c in self._color if c[0] > tc),
                                                maxlen=_BUFFER)
                self._depth = collections.deque((d for d in self._depth if d[0] > td),
                                                maxlen=_BUFFER)
                return tc, cmsg, dmsg
        return None

    # -- processing ------------------------------------------------------------------------

    def _take_waiting_images(self) -> None:
        """Buffer the images still waiting in the subscriptions' queues. rclpy's executor
        takes one message per subscription per wake-up, and this node's guard ran after
        each: with pairs queued behind a slow frame it processed them oldest first (each
        about 5 frame periods late at 15 Hz) instead of only the newest."""
        for sub, handler in self._image_subs:
            # (the QoS keeps fewer than _BUFFER: a bound, not a limit)
            for msg, _info in take_waiting(sub, _BUFFER) or []:
                handler(msg)

    def _process_newest(self) -> None:
        if self.vo is None:
            return  # waiting for camera_info; images stay buffered (bounded)
        self._take_waiting_images()
        pair = self._take_pair()
        if pair is None:
            return
        stamp, cmsg, dmsg = pair
        self._evicted_since_pair = 0
        self._frames = (cmsg.header.frame_id, dmsg.header.frame_id)
        problem = self._stamp_problem(stamp)
        if problem:  # refused before it could reset the odometry or time a twist
            self.stats["bad_input"] += 1
            self._last_problem = problem
            self._report(VOResult(status=Status.BAD_INPUT, stamp=stamp, pose=self.vo.pose,
                                  message=problem))
            return
        if self._last_stamp is not None and stamp <= self._last_stamp:
            far = stamp < self._last_stamp - _JUMP_BACK_S
            if far and self._behind and stamp > self._behind[-1]:
                self._behind.append(stamp)  # one more pair on the new timeline
            elif far:
                self._behind = [stamp]
            if far and len(self._behind) >= _JUMP_BACK_PAIRS:
                self.get_logger().warn(f"image stamps jumped back by "
                                       f"{self._last_stamp - stamp:.2f} s: odometry restarts")
                self.vo.reset()
                self.planar.reset()
                self.stats["resets"] += 1
                self._resync = False
            else:  # an old or repeated pair (or one stray pair stamped far back: it reset
                # the odometry to the origin mid-drive): counted, the diagnostics say so if
                # it lasts
                self.stats["not_newer"] += 1
                self._not_newer_since_processed += 1
                # behind (not a repeat): the camera's clock may have stepped back, and the
                # first pair past the last stamp came longer after the last frame than its
                # stamp says (0.4 s back gave a twist of 1.4 m/s for 0.2 m/s, with a
                # covariance that called it certain)
                self._resync |= stamp < self._last_stamp
                return
        self._behind = []
        if self._resync:  # that pair's motion is over an unknown time: no twist from it
            self._resync = False
            self.vo.restart()
            self.stats["resyncs"] += 1
        self._last_stamp = stamp
        self._not_newer_since_processed = 0
        self._last_processed_wall = time.monotonic()
        self.stats["frames"] += 1
        try:
            image = conv.image_to_array(cmsg)
            depth = conv.image_to_array(dmsg)
            if image.dtype != np.uint8:
                raise ValueError(f"colour image has encoding {cmsg.encoding!r}")
            if depth.dtype == np.uint8:
                raise ValueError(f"depth image has encoding {dmsg.encoding!r}")
            if depth.ndim != 2:
                raise ValueError(f"depth image must have one channel, got {dmsg.encoding!r}")
            previous, self._last_colour = self._last_colour, cmsg
            if previous is not None and (previous.encoding, previous.step) == (
                    cmsg.encoding, cmsg.step) and previous.data == cmsg.data:
                # a real camera's noise never repeats: a driver re-sending its last frame
                # with new stamps. Tracked, it read as the chair stopped, with a twist
                # variance of 1e-7 (m/s)^2, while the chair drove on
                self.stats["frozen"] += 1
                raise ValueError("the colour image is the last one again, bit for bit: a "
                                 "frozen camera driver?")
        except ValueError as exc:
            self.stats["bad_input"] += 1
            self.stats["lost"] += 1
            self._last_problem = str(exc)
            self._report(VOResult(status=Status.BAD_INPUT, stamp=stamp, pose=self.vo.pose,
                                  message=str(exc)))
            return
        self._last_problem = ""
        result = self.vo.process(image, depth, stamp)
        self._elapsed.append(result.elapsed)
        if result.status is Status.BAD_INPUT:
            self.stats["bad_input"] += 1
        x, y, yaw, pose_cov = self.planar.update(result)
        p = self.params
        if result.ok:
            self.stats["tracked"] += 1
            if result.twist is not None and result.twist_covariance is not None:
                v, w = result.twist
                twist_cov = result.twist_covariance
                self._twist_pub.publish(conv.twist_stamped_from_sample(stamp, v, w,
                                                                       p.base_frame))
                self.stats["twists"] += 1
            else:
                # tracked again after a gap: the pose is known, the current twist is not
                v, w = 0.0, 0.0
                twist_cov = np.eye(6) * conv.ODOM_LOST_VARIANCE
            if self._odom_pub is not None:
                self._odom_pub.publish(conv.odometry_with_covariance(
                    stamp, x, y, yaw, pose_cov, v, w, twist_cov, p.odom_frame, p.base_frame))
        elif result.status is not Status.REFERENCE_SET:
            self.stats["lost"] += 1
        self._report(result)

    def _stamp_problem(self, stamp: float) -> str:
        """Why a pair's stamp cannot be a frame's time, or "": before the clock's epoch (a
        twist could not be stamped), or more than _AHEAD_S after the node's clock (a
        camera stamping with another clock, or one glitched frame)."""
        if stamp < 0.0:
            return f"image stamp {stamp:.3f} s is before the clock's epoch"
        if stamp >= conv.MAX_STAMP_S + 1:  # (the node's clock at 0: no other check)
            return (f"image stamp {stamp:.3f} s is beyond a message stamp's int32 seconds "
                    "(2038): its twist could not be stamped")
        now = self.get_clock().now().nanoseconds * 1e-9
        if now > 0.0 and stamp > now + _AHEAD_S:
            return (f"image stamped {stamp - now:.3f} s after this node's clock (is the "
                    "camera driver stamping with the host's clock?)")
        return ""

    def _report(self, result: VOResult) -> None:
        previous = self.last_result
        self.last_result = result
        if previous is None or previous.status is not result.status:
            if not result.ok:
                self.get_logger().warn(f"VO {result.status.value}: {result.message}",
                                       throttle_duration_sec=1.0)
            self._publish_diagnostics()

    # -- diagnostics -----------------------------------------------------------------------

    def _on_diagnostics_timer(self) -> None:
        self.qos_watch.check()  # the peers, from the graph (not at every state change)
        self._publish_diagnostics()

    def _publish_diagnostics(self) -> None:
        p = self.params
        r = self.last_result
        age = (time.monotonic() - self._last_processed_wall
               if self._last_processed_wall is not None else None)
        n = self.stats
        unpaired = (f" ({self._evicted_since_pair} images went without a partner within "
                    f"sync_tolerance_s {p.sync_tolerance_s:g} s)"
                    if self._evicted_since_pair else "")
        if self.vo is None and self._info_problem:
            level, msg = "ERROR", (f"camera_info on {self._info_topic} refused: "
                                   f"{self._info_problem}")
        elif self.vo is None:
            level, msg = "WARN", f"waiting for camera_info on {self._info_topic}"
        elif (r is None or age is None) and self._last_problem:
            # every pair so far refused (a camera on its own clock, say): not "waiting"
            level, msg = "ERROR", (f"every colour/depth pair refused, the last one: "
                                   f"{self._last_problem}: no twist published")
        elif r is None or age is None:
            level, msg = "WARN", (f"waiting for colour/depth pairs on {self._color_topic} "
                                  f"({n['colour_images']} received), {self._depth_topic} "
                                  f"({n['depth_images']} received){unpaired}")
        elif age > p.stale_timeout_s and self._not_newer_since_processed:
            level, msg = "ERROR", (
                f"{self._not_newer_since_processed} colour/depth pairs in {age:.2f} s, none "
                "stamped after the last one processed (is the camera driver stamping its "
                "images?): no twist published")
        elif age > p.stale_timeout_s:
            # pairs refused on their stamps do not count as processed: say why they were
            refused = f" (the last one refused: {self._last_problem})" if self._last_problem \
                else ""
            level, msg = "ERROR", (f"no colour/depth pair for {age:.2f} s{unpaired}{refused}: "
                                   "no twist published")
        elif r.ok:
            level, msg = "OK", f"tracking ({r.num_inliers} inliers)"
        elif r.status is Status.REFERENCE_SET:
            level, msg = "WARN", "initialising: reference frame set, no twist yet"
            recent = [t for t in self._info_changes
                      if time.monotonic() - t <= _INFO_CHANGES_WINDOW_S]
            if len(recent) > 1:  # two calibrations alternating on the topic restart it
                msg += (f"; camera_info changed {len(recent)} times in the last "
                        f"{_INFO_CHANGES_WINDOW_S:g} s, each a restart: two cameras or "
                        f"drivers on {self._info_topic}?")
        else:
            level = _LEVEL[r.status]
            msg = f"tracking lost ({r.status.value}): {r.message}; no twist published"
        values: dict[str, object] = dict(self.stats)
        # the last pair's result, and its twist only while it is the one published: with no
        # pair for stale_timeout_s the status is 'stale' (it said 'ok' with the old twist)
        stale = age is not None and age > p.stale_timeout_s
        values["status"] = "none" if r is None else "stale" if stale else r.status.value
        if r is not None:
            values.update({"features": r.num_features, "matches": r.num_matches,
                           "inliers": r.num_inliers,
                           "reprojection_error_px": float(r.reprojection_error),
                           "keyframe_changed": r.keyframe_changed})
            if r.ok and r.twist is not None and not stale:
                values["v"], values["omega"] = float(r.twist[0]), float(r.twist[1])
        if self._elapsed:
            values["process_ms_mean"] = 1e3 * float(np.mean(self._elapsed))
            values["process_ms_max"] = 1e3 * float(np.max(self._elapsed))
        if age is not None:
            values["last_frame_age_s"] = float(age)
        if self._info_problem:
            values["camera_info_problem"] = self._info_problem
        colour_frame, depth_frame = self._frames
        if colour_frame != depth_frame and level == "OK":
            # depth not registered to the colour camera: its pixels are not the colour's
            level, msg = "WARN", (f"{msg}; colour and depth frames differ ({colour_frame!r}, "
                                  f"{depth_frame!r}): vo_node needs depth registered to the "
                                  "colour camera")
        values["qos_mismatch"] = self.qos_watch.summary()
        level, msg = self.qos_watch.escalate(level, msg)
        status = conv.diagnostic_status(
            runtime.status_name(self, f"{self.get_name()}: tracking"), level, msg,
            self._color_topic, values)
        self._diag_pub.publish(conv.diagnostic_array(
            self.get_clock().now().nanoseconds * 1e-9, [status]))


def main(args: list[str] | None = None) -> int:
    """Run the node until SIGINT or SIGTERM, which only set a flag: the main thread then
    destroys the node and shuts rclpy down itself (:func:`asgp_ros.nodes.runtime.run`).
    Exit code 1: bad parameters."""
    return runtime.run(VONode, args, name="vo_node", refused=(ValueError,))


if __name__ == "__main__":
    sys.exit(main())
