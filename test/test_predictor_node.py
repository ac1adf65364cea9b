"""In-process tests of the predictor node (tier 2: rclpy context fixture, DDS, no sleeps).

The node runs with ``use_sim_time``; the test publishes ``/clock`` itself and waits (by
polling the executor with a deadline) until the node has seen each clock value and each
input sample, so the test is deterministic and takes no wall time beyond the spinning.
"""

from __future__ import annotations

import itertools
import math
import re
import subprocess
import sys
import time

import numpy as np
import pytest

pytest.importorskip("rclpy")

from builtin_interfaces.msg import Duration
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import TwistStamped
from nav_msgs.msg import Odometry, Path
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Joy
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
from visualization_msgs.msg import Marker, MarkerArray

from asgp_ros.core.modelfile import load_model
from asgp_ros.core.online import Reason
from asgp_ros.nodes import conversions as conv
from asgp_ros.nodes.predictor_node import (
    LEARN_DELAY_S,
    PredictorNode,
    PredictorNodeParams,
    StartupError,
)

pytestmark = pytest.mark.ros

DT = 0.2
K = 5


def _model_file(directory, vel_stamp: str) -> str:
    """A small ASGP model fitted on synthetic data (see test_predictor.make_streams)."""
    from test_predictor import make_streams

    from asgp_ros.core.features import FeatureConfig, design_matrix
    from asgp_ros.core.modelfile import save_model
    from asgp_ros.core.models import MotionModel
    from asgp_ros.core.resample import ResampleConfig, resample
    from asgp_ros.core.sparse_gp import SparseGP
    from asgp_ros.core.streams import RawStreams

    config = ResampleConfig(vel_stamp=vel_stamp)
    jt, joy, vt, vel = make_streams(60.0)
    res = resample(RawStreams(joy_t=jt, joy=joy, vel_t=vt, vel=vel), config)
    fc = FeatureConfig(lags=4)
    channels = []
    for c in (0, 1):
        X, y, _ = design_matrix(res, c, fc)
        channels.append(SparseGP(num_inducing=10, seed=0).fit(X, y, max_iter=30))
    path = directory / "chair.npz"
    save_model(path, MotionModel(kind="asgp", feature_config=fc,
                                 resample_config=config, channels=tuple(channels)))
    return str(path)


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    """The harness's VO samples the velocity at its stamps: a model reading them as such."""
    return _model_file(tmp_path_factory.mktemp("model"), "frame")


def test_midpoint_stamps_move_the_newest_step_back_by_half_a_vo_interval(
        rclpy_context, tmp_path):
    """The same drive with VO every 0.2 s at x.03: read at the frames' stamps the newest
    path starts at the last VO stamp's grid step (102.0), read at the intervals' middles at
    the step the last middle reaches (101.93 -> 101.8)."""
    for stamp, newest in (("frame", 102.0), ("midpoint", 101.8)):
        h = Harness(rclpy_context, _model_file(tmp_path / stamp, stamp))
        try:
            h.drive(100.0, 102.0)
            h.spin_until(lambda h=h, newest=newest: bool(h.paths)
                         and _t0(h.paths[-1]) > newest - 1e-9, what="paths")
            h.clock(102.1)
            h.joy(102.1, 0.5, 0.0)  # a later joystick sample completes nothing new
            for _ in range(20):
                h.executor.spin_once(timeout_sec=0.01)
            assert abs(_t0(h.paths[-1]) - newest) < 1e-9, stamp
        finally:
            h.close()


class Harness:
    """The node under test plus a test node that publishes inputs and the clock."""

    def __init__(self, context, model_path: str, odometry: bool = False, **params) -> None:
        if odometry:
            params = {"vo_type": "odometry", "path_frame": "odom", **params}
        self.odometry = odometry
        self.vo_frame = "base_link"  # the frame of the VO's twists
        overrides = [Parameter("model_path", value=model_path),
                     Parameter("use_sim_time", value=True),
                     Parameter("horizon_steps", value=K),
                     Parameter("diagnostics_period_s", value=0.5)]
        # the joystick is read in batches; often here, as each sample is waited for (the
        # default 0.05 s would make this file twice as slow)
        params = {"joy_poll_period_s": 0.005, **params}
        overrides += [Parameter(k, value=v) for k, v in params.items()]
        self.node = PredictorNode(context=context, parameter_overrides=overrides)
        self.test = __import__("rclpy").create_node("predictor_test", context=context)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self.executor.add_node(self.test)
        t = self.test
        self.clock_pub = t.create_publisher(Clock, "/clock", QoSProfile(depth=10))
        self.joy_pub = t.create_publisher(Joy, "joy", qos_profile_sensor_data)
        self.vo_pub = t.create_publisher(Odometry if odometry else TwistStamped, "vo/twist",
                                         qos_profile_sensor_data)
        self.plan_pub = t.create_publisher(JointTrajectory, "joy_plan", QoSProfile(depth=10))
        self.paths: list[Path] = []
        self.markers: list[MarkerArray] = []
        self.diags: list[DiagnosticArray] = []
        t.create_subscription(Path, "predicted_path", self.paths.append, QoSProfile(depth=50))
        self.marker_sub = t.create_subscription(
            MarkerArray, "predicted_path/uncertainty", self.markers.append, QoSProfile(depth=50))
        t.create_subscription(DiagnosticArray, "diagnostics", self.diags.append,
                              QoSProfile(depth=50))
        self.now = 0.0
        inputs = [self.joy_pub, self.vo_pub, self.plan_pub]
        if params.get("use_sim_time", True):
            inputs.append(self.clock_pub)
        self.spin_until(lambda: all(p.get_subscription_count() > 0 for p in inputs) and all(
            self.test.count_publishers(n) > 0 for n in (
                "predicted_path", "predicted_path/uncertainty", "diagnostics")),
            what="discovery")

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.test.destroy_node()

    def spin_until(self, cond, timeout: float = 5.0, what: str = "") -> None:
        deadline = time.monotonic() + timeout
        while not cond():
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out waiting for {what}")
            self.executor.spin_once(timeout_sec=0.01)

    def clock(self, t: float) -> None:
        self.now = t
        self.clock_pub.publish(Clock(clock=conv.seconds_to_stamp(t)))
        ns = round(t * 1e9)
        self.spin_until(lambda: self.node.get_clock().now().nanoseconds == ns, what="clock")

    def _seen(self, kind: str) -> int:
        """Samples of ``kind`` the predictor took plus every input it refused."""
        stats = self.node.predictor.stats
        return getattr(stats, f"{kind}_samples") + sum(stats.rejected.values())

    def joy(self, t: float, fwd: float, turn: float) -> None:
        n = self._seen("joy")
        self.joy_pub.publish(conv.joy_from_sample(t, fwd, turn))
        self.spin_until(lambda: self._seen("joy") > n, what="joy")

    def vo(self, t: float, v: float, w: float, lost: bool = False) -> None:
        seen = (self._seen("vo"), self.node._vo_frame.refused)
        if self.odometry:  # the chair drives along x at 0.5 m/s in the odom frame
            msg = conv.odometry_from_pose(t, 0.5 * (t - 100.0), 2.0, 0.0, v, w,
                                          child_frame_id=self.vo_frame)
            msg.twist.covariance[0] = -1.0 if lost else 1e-4
            self.vo_pub.publish(msg)
        else:
            self.vo_pub.publish(conv.twist_stamped_from_sample(t, v, w, self.vo_frame))
        self.spin_until(lambda: (self._seen("vo"), self.node._vo_frame.refused) != seen,
                        what="vo")

    def drive(self, t_from: float, t_to: float, vo: bool = True, joy=None, vel=None,
              joy_nan: bool = False) -> None:
        """Joystick at 10 Hz and VO at 5 Hz (offset 0.03 s) from t_from to t_to."""
        joy = joy or (lambda t: (0.5 + 0.3 * math.sin(t), 0.4 * math.cos(0.5 * t)))
        vel = vel or (lambda t: (0.45 + 0.25 * math.sin(t - 0.3), 0.3 * math.cos(0.5 * t)))
        for i in range(round((t_to - t_from) / 0.1)):
            t = t_from + 0.1 * (i + 1)
            self.clock(t)
            self.joy(t, *((math.nan, 0.0) if joy_nan and i % 3 == 0 else joy(t)))
            if vo and i % 2 == 1:
                self.clock(t + 0.03)
                self.vo(t + 0.03, *vel(t + 0.03))


def _t0(path: Path) -> float:
    return conv.stamp_to_seconds(path.header.stamp)


def _reason(h: Harness) -> str:
    return h.node.diagnostic_status().values[0].value


def test_bad_model_path_refuses_to_start(rclpy_context, tmp_path):
    with pytest.raises(StartupError, match=r"nonexistent\.npz"):
        PredictorNode(context=rclpy_context,
                      parameter_overrides=[Parameter("model_path", value="/nonexistent.npz")])
    corrupt = tmp_path / "corrupt.npz"
    corrupt.write_bytes(b"not a model")
    with pytest.raises(StartupError, match=r"corrupt\.npz"):
        PredictorNode(context=rclpy_context,
                      parameter_overrides=[Parameter("model_path", value=str(corrupt))])
    with pytest.raises(StartupError, match="model_path is required"):
        PredictorNode(context=rclpy_context)


def test_bad_parameters_refuse_to_start(rclpy_context, model_file):
    with pytest.raises(StartupError, match="vo_type"):
        PredictorNode(context=rclpy_context, parameter_overrides=[
            Parameter("model_path", value=model_file), Parameter("vo_type", value="imu")])
    with pytest.raises(StartupError, match="path_frame 'odom' needs odometry"):
        PredictorNode(context=rclpy_context, parameter_overrides=[
            Parameter("model_path", value=model_file), Parameter("path_frame", value="odom")])
    with pytest.raises(StartupError, match="divided by an integer"):
        PredictorNode(context=rclpy_context, parameter_overrides=[
            Parameter("model_path", value=model_file), Parameter("rate_hz", value=3.0)])
    # a rate so small that the model's over it is inf (it raised OverflowError), or one
    # path in more than MAX_DECIMATION steps
    for tiny in (2.5e-308, 1e-300, 0.004):
        with pytest.raises(StartupError, match="divided by an integer from 1 to 1000"):
            PredictorNode(context=rclpy_context, parameter_overrides=[
                Parameter("model_path", value=model_file), Parameter("rate_hz", value=tiny)])
    assert PredictorNodeParams(model_path="m.npz", rate_hz=0.005).decimation(5.0) == 1000


@pytest.mark.parametrize("names", [
    {"applied_topic": "joy"},                       # the stick taken for the board's output
    {"applied_topic": "/joy"},                      # the same topic, fully qualified
    {"override_topic": "joy"},                      # the stick taken for an override
    {"override_topic": "joy_applied"},
    {"joy_topic": "stick", "applied_topic": "/stick"},
])
def test_one_topic_named_twice_refuses_to_start(rclpy_context, model_file, names):
    """The user's stick, the board's output and the overrides are three streams: naming one
    topic twice (after expansion) would feed the stick as the board's output or as an
    override, and paths would never follow an intervention."""
    with pytest.raises(StartupError, match="name one topic"):
        PredictorNode(context=rclpy_context, parameter_overrides=[
            Parameter("model_path", value=model_file),
            *(Parameter(k, value=v) for k, v in names.items())])
    with pytest.raises(StartupError, match="not a valid topic name"):
        PredictorNode(context=rclpy_context, parameter_overrides=[
            Parameter("model_path", value=model_file), Parameter("joy_topic", value="j oy")])
    # in a namespace, a relative name and the fully qualified one are the same topic
    with pytest.raises(StartupError, match="name one topic, /chair/joy"):
        PredictorNode(context=rclpy_context, namespace="/chair", parameter_overrides=[
            Parameter("model_path", value=model_file),
            Parameter("applied_topic", value="/chair/joy")])
    node = PredictorNode(context=rclpy_context, namespace="/chair", parameter_overrides=[
        Parameter("model_path", value=model_file), Parameter("applied_topic", value="/joy")])
    node.destroy_node()
    # an input switched off (empty) is not a name
    node = PredictorNode(context=rclpy_context, parameter_overrides=[
        Parameter("model_path", value=model_file), Parameter("applied_topic", value=""),
        Parameter("override_topic", value="")])
    node.destroy_node()


@pytest.mark.parametrize(("field", "value", "why"), [
    ("horizon_steps", 201, "horizon_steps"), ("horizon_steps", -1, "horizon_steps"),
    ("horizon_s", 0.0, "horizon_s"), ("horizon_s", math.nan, "horizon_s"),
    ("horizon_s", 1e30, "horizon_s"), ("rate_hz", -1.0, "rate_hz"),
    ("rate_hz", math.inf, "rate_hz"), ("joy_topic", " ", "joy_topic must not be empty"),
    ("odom_frame", "", "odom_frame must not be empty"), ("path_frame", "map", "path_frame"),
    ("joy_axes", "0", "axes"), ("diagnostics_period_s", 0.01, "diagnostics_period_s"),
    ("diagnostics_period_s", math.nan, "diagnostics_period_s"),
    ("joy_timeout_s", math.nan, "joy_timeout_s"), ("reset_jump_s", -1.0, "reset_jump_s"),
    ("uncertainty", "exact", "uncertainty"), ("adapt_half_life_s", -5.0, "adapt"),
    ("adapt_max_rate", math.nan, "adapt"), ("joy_poll_period_s", -0.01, "joy_poll_period_s"),
    ("joy_poll_period_s", math.nan, "joy_poll_period_s"),
    ("joy_poll_period_s", 1e30, "joy_poll_period_s"),
])
def test_every_bad_parameter_is_named(field, value, why):
    """Each parameter out of its range (NaN, inf, 1e30, empty names) refuses with its name,
    whether or not adaptation is on."""
    PredictorNodeParams(model_path="m.npz")  # the defaults are valid
    with pytest.raises(ValueError, match=why):
        PredictorNodeParams(model_path="m.npz", **{field: value})


def test_node_process_exits_nonzero_with_a_clear_message(repo_root):
    proc = subprocess.run(
        [sys.executable, "-m", "asgp_ros.nodes.predictor_node", "--ros-args",
         "-p", "model_path:=/nonexistent/chair.npz"],
        cwd=repo_root, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1
    assert "refusing to start" in proc.stderr and "/nonexistent/chair.npz" in proc.stderr


@pytest.mark.parametrize("poll", [0.005, 0.0], ids=["polled", "callbacks"])
def test_paths_published_per_step_with_k_poses_and_ellipses(rclpy_context, model_file, poll):
    """The joystick read in batches (joy_poll_period_s) or by a callback per message."""
    h = Harness(rclpy_context, model_file, joy_poll_period_s=poll)
    try:
        h.drive(100.0, 103.0)
        h.spin_until(lambda: len(h.paths) >= 8, what="paths")
        steps = []
        for path in h.paths:
            times, poses = conv.path_to_poses(path)
            t0 = conv.stamp_to_seconds(path.header.stamp)
            assert path.header.frame_id == "base_link"
            assert len(path.poses) == K and poses.shape == (K, 3)
            np.testing.assert_allclose(times, t0 + DT * np.arange(1, K + 1), atol=1e-9)
            assert np.all(np.isfinite(poses))
            steps.append(round(t0 / DT))
        # one path per grid step, none skipped, in order
        assert steps == list(range(steps[0], steps[0] + len(steps)))
        m = h.markers[-1].markers
        assert m[0].action == Marker.DELETEALL
        assert [x.id for x in m[1:]] == list(range(K))
        assert all(x.scale.x >= x.scale.y > 0 for x in m[1:])
        # the ellipses grow along the horizon
        assert m[K].scale.x > m[1].scale.x
        assert _reason(h) == Reason.OK
        h.spin_until(lambda: h.diags, what="diagnostics")
        keys = {kv.key for kv in h.diags[-1].status[0].values}
        assert {"joy_rate_hz", "vo_rate_hz", "joy_age_s", "vo_age_s",
                "last_latency_ms", "reason"} <= keys
        values = {kv.key: kv.value for kv in h.diags[-1].status[0].values}
        # the latency (VO callback -> path published), its parts over the same paths, and
        # the ellipses' message that follows
        parts = [float(values[k]) for k in ("latency_p99_ms", "predict_p99_ms", "path_p99_ms",
                                            "ellipses_p99_ms")]
        assert all(0.0 < x < 1e4 for x in parts)
        assert parts[1] <= parts[0] and parts[2] <= parts[0]
        # every joystick sample was taken in a drain, or none with callbacks
        polled = int(values["polled_messages"])
        assert polled == (h.node.predictor.stats.joy_samples if poll else 0) and polled >= 0
        assert values["polled_queue_full"] == "0"
    finally:
        h.close()


def test_joystick_messages_without_a_stamp_keep_their_arrival_times(rclpy_context,
                                                                    model_file):
    """On the system clock a Joy sent with a zero stamp is stamped with its arrival, and read
    in a batch it keeps the time it was received: three sent 30 ms apart and read together
    0.2 s later are 30 ms apart in the buffer, not stamped with the read's time."""
    h = Harness(rclpy_context, model_file, use_sim_time=False, joy_poll_period_s=1.0)
    node = h.node
    try:
        node.polled.drain()
        sent = []
        for _ in range(3):
            sent.append(time.time())
            h.joy_pub.publish(conv.joy_from_sample(0.0, 0.5, 0.0))
            time.sleep(0.03)
        time.sleep(0.2)
        deadline = time.monotonic() + 5.0
        while node.predictor.stats.joy_samples < 3:
            assert time.monotonic() < deadline, "the three samples were not fed"
            node.polled.drain()
            time.sleep(0.005)
        stamps = node.predictor._joy.arrays()[0]
        np.testing.assert_allclose(stamps, sent, rtol=0.0, atol=0.015)
    finally:
        h.close()


@pytest.mark.parametrize("trigger", ["vo", "override"])
def test_the_joystick_is_read_before_a_vo_message_or_an_override(rclpy_context, model_file,
                                                                 trigger):
    """The joystick waiting when a VO message or an override comes is fed before it (here
    joy_poll_period_s is 1 s, so no timer reads it first): the samples of a step are in
    when the VO message completes it, and an override never overtakes the stick
    readings that came before it."""
    h = Harness(rclpy_context, model_file, joy_poll_period_s=1.0)
    pred = h.node.predictor
    order: list[str] = []

    def recording(name: str):
        real = getattr(pred, name)

        def recorded(*args, **kwargs):
            order.append(name)
            return real(*args, **kwargs)
        return recorded

    for name in ("feed_joy", "feed_vo", "feed_override"):
        setattr(pred, name, recording(name))
    override_pub = h.test.create_publisher(Joy, "joy_override", QoSProfile(depth=10))
    try:
        h.spin_until(lambda: override_pub.get_subscription_count() > 0, what="discovery")
        h.clock(100.0)
        for _ in range(20):  # the timers due at the new clock (they read the joystick too)
            h.executor.spin_once(timeout_sec=0.005)
        assert order == []
        for i in range(3):
            h.joy_pub.publish(conv.joy_from_sample(99.97 + 0.01 * i, 0.5, 0.0))
        if trigger == "vo":
            h.vo_pub.publish(conv.twist_stamped_from_sample(100.0, 0.4, 0.0, "base_link"))
        else:
            override_pub.publish(conv.joy_from_sample(100.0, 0.1, 0.0))
        fed = f"feed_{trigger}"
        h.spin_until(lambda: fed in order, what=trigger)
        assert order == ["feed_joy"] * 3 + [fed]
    finally:
        h.close()


def test_a_step_waiting_for_the_joystick_reads_it_before_the_next_batch(
        rclpy_context, model_file, monkeypatch):
    """A joystick slower than the VO: the VO message comes first and its step waits for the
    stick only. The node reads the joystick again every JOY_WAIT_TICK_S (here the batch
    timer is stopped, so nothing else would read it) and the path of that step comes from
    the sample's handler; then the quick reads stop. A VO message whose step the joystick
    already covers, or a silent stick, starts none."""
    import asgp_ros.nodes.predictor_node as pn

    monkeypatch.setattr(pn, "JOY_WAIT_MAX_S", 30.0)  # the window: joy_poll_period_s, 1 s
    h = Harness(rclpy_context, model_file, joy_poll_period_s=1.0)
    node = h.node
    try:
        h.drive(100.0, 102.0)
        h.spin_until(lambda: h.paths and abs(_t0(h.paths[-1]) - 102.0) < 1e-9, what="paths")
        assert node.polled.timer is not None
        node.polled.timer.cancel()
        waits = node._joy_waits
        h.clock(102.05)
        h.vo(102.03, 0.4, 0.1)  # the joystick covers 102.0 already: no new step, no wait
        assert node._joy_waits == waits and node._joy_wait_timer.is_canceled()
        h.clock(102.23)
        h.vo(102.23, 0.4, 0.1)  # step 102.2 waits for the stick (newest 102.0)
        assert node._joy_waits == waits + 1
        assert not node._joy_wait_timer.is_canceled()
        n = len(h.paths)
        h.joy_pub.publish(conv.joy_from_sample(102.21, 0.5, 0.0))
        h.spin_until(lambda: len(h.paths) > n, what="the waiting step's path")
        assert abs(_t0(h.paths[-1]) - 102.2) < 1e-9
        h.spin_until(lambda: node._joy_wait_timer.is_canceled(), what="the reads to stop")
        # a stick silent for longer than joy_timeout_s: no quick reads for it
        h.clock(102.83)
        h.vo(102.83, 0.4, 0.1)
        assert node._joy_waits == waits + 1 and node._joy_wait_timer.is_canceled()
        values = {kv.key: kv.value for kv in node.diagnostic_status().values}
        assert (values["joy_waits"], values["joy_wait_timeouts"]) == (str(waits + 1), "0")
        # a stick whose sample does not come within the wait: it ends, counted, and none
        # starts for JOY_WAIT_BACKOFF_S (here until the test lifts it)
        h.clock(103.0)
        h.joy(102.99, 0.5, 0.0)
        monkeypatch.setattr(pn, "JOY_WAIT_MAX_S", 0.02)
        h.clock(103.23)
        h.vo(103.23, 0.4, 0.1)  # step 103.2 waits for the stick (newest 102.99)
        assert node._joy_waits == waits + 2
        h.spin_until(lambda: node._joy_wait_timer.is_canceled(), what="the wait to end")
        assert node._joy_wait_timeouts == 1
        h.clock(103.43)
        h.vo(103.43, 0.4, 0.1)  # the stick is still fresh, but the last wait was in vain
        assert node._joy_waits == waits + 2 and node._joy_wait_timer.is_canceled()
        node._joy_wait_blocked_until = 0.0
        # a fresh sample, behind the next VO message's step (read here: no timer reads it)
        n = node.predictor.stats.joy_samples
        h.joy_pub.publish(conv.joy_from_sample(103.45, 0.5, 0.0))
        h.spin_until(lambda: node.polled.drain() >= 0 and node.predictor.stats.joy_samples > n,
                     what="the sample")
        h.clock(103.63)
        h.vo(103.63, 0.4, 0.1)
        assert node._joy_waits == waits + 3
    finally:
        h.close()


def test_with_decimation_only_a_predicted_step_waits_for_the_joystick(
        rclpy_context, model_file, monkeypatch):
    """rate_hz = half the model's: the node predicts every second grid step. A VO message
    whose new step is one it skips starts no quick reads (a wait for it would predict
    nothing, and one in vain would block the next predicted step's wait); one whose new
    steps include a predicted step does, and that step's path comes from the sample."""
    import asgp_ros.nodes.predictor_node as pn

    monkeypatch.setattr(pn, "JOY_WAIT_MAX_S", 30.0)  # the window: joy_poll_period_s, 1 s
    h = Harness(rclpy_context, model_file, joy_poll_period_s=1.0, rate_hz=2.5)
    node = h.node
    try:
        assert node.every_n == 2
        h.drive(100.0, 102.0)  # step 510 (102.0 s) is predicted
        h.spin_until(lambda: h.paths and abs(_t0(h.paths[-1]) - 102.0) < 1e-9, what="paths")
        assert node.polled.timer is not None
        node.polled.timer.cancel()
        waits = node._joy_waits
        h.clock(102.23)
        h.vo(102.23, 0.4, 0.1)  # step 511 (skipped) waits for the stick: no reads
        assert node._joy_waits == waits and node._joy_wait_timer.is_canceled()
        h.clock(102.43)
        h.vo(102.43, 0.4, 0.1)  # steps 511 and 512 (predicted) wait: reads
        assert node._joy_waits == waits + 1 and not node._joy_wait_timer.is_canceled()
        n = len(h.paths)
        h.joy_pub.publish(conv.joy_from_sample(102.21, 0.5, 0.0))
        h.joy_pub.publish(conv.joy_from_sample(102.41, 0.5, 0.0))
        h.spin_until(lambda: len(h.paths) > n, what="the waiting step's path")
        assert abs(_t0(h.paths[-1]) - 102.4) < 1e-9
        h.spin_until(lambda: node._joy_wait_timer.is_canceled(), what="the reads to stop")
        assert node._joy_wait_timeouts == 0 and len(h.paths) == n + 1
    finally:
        h.close()


@pytest.mark.parametrize("phase", [0, 1])
def test_with_decimation_a_vo_completing_two_steps_at_once_still_gives_paths(
        rclpy_context, model_file, phase):
    """rate_hz = half the model's, and a VO every 0.4 s (a 5 Hz camera losing every other
    frame, within max_gap_vel_s): each VO message completes two grid steps, and the newest
    step may be odd every time. A path comes whenever the completed steps pass a multiple of
    2 (it was made only when the newest step was one: none at all in one phase)."""
    h = Harness(rclpy_context, model_file, rate_hz=2.5)
    try:
        for i in range(40):  # joystick 10 Hz, VO at t + 0.03 on every fourth sample
            t = 100.0 + 0.1 * (i + 1)
            h.clock(t)
            h.joy(t, 0.5 + 0.3 * math.sin(t), 0.4 * math.cos(0.5 * t))
            if i % 4 == 2 * phase + 1:
                h.clock(t + 0.03)
                h.vo(t + 0.03, 0.45 + 0.25 * math.sin(t - 0.3), 0.3 * math.cos(0.5 * t))
        h.spin_until(lambda: len(h.paths) >= 5, what="paths at 2.5 Hz")
        steps = [round(_t0(path) / DT) for path in h.paths]
        assert all(b - a == 2 for a, b in itertools.pairwise(steps)), steps
    finally:
        h.close()


def test_with_decimation_a_wait_for_the_joystick_ends_in_a_path_past_the_multiple(
        rclpy_context, model_file, monkeypatch):
    """rate_hz = half the model's. The joystick covers step 509, the VO step 511: the wait
    is for step 510, and the sample that ends it completes 510 and 511 at once. The path
    comes from that sample (at 511), not never."""
    import asgp_ros.nodes.predictor_node as pn

    monkeypatch.setattr(pn, "JOY_WAIT_MAX_S", 30.0)  # the window: joy_poll_period_s, 1 s
    h = Harness(rclpy_context, model_file, joy_poll_period_s=1.0, rate_hz=2.5)
    node = h.node
    try:
        h.drive(100.0, 101.8)  # the joystick at 101.8 (step 509), the VO at 101.83
        h.spin_until(lambda: h.paths and abs(_t0(h.paths[-1]) - 101.6) < 1e-9, what="paths")
        assert node.polled.timer is not None
        node.polled.timer.cancel()
        h.clock(101.95)
        got = node.predictor.stats.joy_samples  # still step 509 (read here: no timer does)
        h.joy_pub.publish(conv.joy_from_sample(101.95, 0.5, 0.0))
        h.spin_until(lambda: node.polled.drain() >= 0
                     and node.predictor.stats.joy_samples > got, what="the sample")
        waits, n = node._joy_waits, len(h.paths)
        h.clock(102.23)
        h.vo(102.23, 0.4, 0.1)  # steps 510 and 511 wait for the stick
        assert node._joy_waits == waits + 1
        h.joy_pub.publish(conv.joy_from_sample(102.21, 0.5, 0.0))
        h.spin_until(lambda: len(h.paths) > n, what="the path the wait was for")
        assert abs(_t0(h.paths[-1]) - 102.2) < 1e-9
        h.spin_until(lambda: node._joy_wait_timer.is_canceled(), what="the reads to stop")
        assert node._joy_wait_timeouts == 0
    finally:
        h.close()


def test_ellipses_switched_off_at_runtime_are_cleared(rclpy_context, model_file):
    """publish_uncertainty set to false while RViz shows the ellipses: one DELETEALL, so
    the last path's ellipses do not stay beside the new paths; none after it."""
    h = Harness(rclpy_context, model_file)
    node = h.node
    try:
        h.drive(100.0, 101.0)
        h.spin_until(lambda: h.paths and h.markers, what="paths and ellipses")
        assert node.set_parameters([Parameter("publish_uncertainty", value=False)])[0].successful
        n_paths, n_markers = len(h.paths), len(h.markers)
        h.drive(101.0, 102.0)
        h.spin_until(lambda: len(h.paths) >= n_paths + 4 and len(h.markers) > n_markers,
                     what="paths and the clearing")
        for _ in range(20):
            h.executor.spin_once(timeout_sec=0.01)
        assert len(h.markers) == n_markers + 1
        assert [m.action for m in h.markers[-1].markers] == [Marker.DELETEALL]
        values = {kv.key: kv.value for kv in node.diagnostic_status().values}
        assert values["ellipses_p99_ms"] == "nan"
    finally:
        h.close()


def test_the_ellipses_time_is_not_reported_once_the_viewer_left_and_paths_stopped(
        rclpy_context, model_file):
    """The viewer leaves while no path comes (stale inputs): ellipses_p99_ms is nan, not
    the times of the ellipses it was sent."""
    h = Harness(rclpy_context, model_file)
    node = h.node
    try:
        h.drive(100.0, 101.0)
        h.spin_until(lambda: h.paths and h.markers, what="paths and ellipses")
        h.clock(102.0)  # inputs stale: no path
        h.spin_until(lambda: _reason(h) != Reason.OK, what="stale inputs")
        values = {kv.key: kv.value for kv in node.diagnostic_status().values}
        assert float(values["ellipses_p99_ms"]) > 0  # the viewer is still there
        h.test.destroy_subscription(h.marker_sub)
        h.spin_until(lambda: node.marker_pub.get_subscription_count() == 0, what="gone")
        values = {kv.key: kv.value for kv in node.diagnostic_status().values}
        assert values["ellipses_p99_ms"] == "nan"
    finally:
        h.close()


def test_the_ellipses_are_made_only_while_something_subscribes(rclpy_context, model_file):
    """No subscriber of predicted_path/uncertainty (no RViz on the chair): the paths go on,
    no ellipse message is made; one that subscribes gets them from the next path."""
    h = Harness(rclpy_context, model_file)
    node = h.node
    try:
        h.drive(100.0, 101.0)
        h.spin_until(lambda: h.paths and h.markers, what="paths and ellipses")
        h.test.destroy_subscription(h.marker_sub)
        h.spin_until(lambda: node.marker_pub.get_subscription_count() == 0,
                     what="the subscriber gone")
        made, n = node._markers_made, len(h.paths)
        h.drive(101.0, 102.0)
        h.spin_until(lambda: len(h.paths) >= n + 4, what="paths")
        assert node._markers_made == made
        # their time is not reported while none are made; the count says how many were
        values = {kv.key: kv.value for kv in node.diagnostic_status().values}
        assert values["ellipses_p99_ms"] == "nan"
        assert values["ellipses_published"] == str(made) and int(values["paths_published"]) > made
        markers: list[MarkerArray] = []
        h.test.create_subscription(MarkerArray, "predicted_path/uncertainty", markers.append,
                                   QoSProfile(depth=50))
        h.spin_until(lambda: node.marker_pub.get_subscription_count() == 1,
                     what="the subscriber back")
        h.drive(102.0, 102.6)
        h.spin_until(lambda: bool(markers), what="ellipses again")
        assert len(markers[-1].markers) == K + 1
        assert node._markers_made > made and float(
            {kv.key: kv.value for kv in node.diagnostic_status().values}["ellipses_p99_ms"]) > 0
    finally:
        h.close()


def test_no_quick_reads_when_the_batches_come_every_tick(rclpy_context, model_file):
    """joy_poll_period_s no longer than a quick read's tick: the batches already read that
    often, and each wait would end in a counted timeout and a second's block."""
    import asgp_ros.nodes.predictor_node as pn

    h = Harness(rclpy_context, model_file, joy_poll_period_s=pn.JOY_WAIT_TICK_S)
    try:
        assert h.node.polled.timer is not None and h.node._joy_wait_timer is None
        h.drive(100.0, 101.0)
        h.spin_until(lambda: bool(h.paths), what="paths")
        assert h.node._joy_waits == 0
    finally:
        h.close()


def test_staleness_stops_paths_and_they_resume(rclpy_context, model_file):
    h = Harness(rclpy_context, model_file, vo_timeout_s=0.5)
    try:
        h.drive(100.0, 102.0)
        h.spin_until(lambda: len(h.paths) >= 3, what="first paths")
        # VO goes silent for 1.5 s; the joystick keeps coming
        h.drive(102.0, 103.5, vo=False)
        h.executor.spin_once(timeout_sec=0.05)
        n_stale = len(h.paths)
        assert _reason(h) == Reason.STALE_VO
        # the watchdog cleared the ellipses
        h.spin_until(lambda: len(h.markers[-1].markers) == 1, what="DELETEALL")
        h.spin_until(lambda: any("stale_vo" in s.message for d in h.diags for s in d.status),
                     what="stale diagnostic")
        # no path was made from the stale input
        last_t0 = conv.stamp_to_seconds(h.paths[-1].header.stamp)
        assert last_t0 <= 102.0 + 1e-9
        # fresh VO returns: prediction resumes without restart
        h.drive(103.5, 105.5)
        h.spin_until(lambda: len(h.paths) > n_stale + 2, what="resumed paths")
        assert conv.stamp_to_seconds(h.paths[-1].header.stamp) > 104.5
        assert _reason(h) == Reason.OK
    finally:
        h.close()


@pytest.mark.parametrize("odometry", [False, True], ids=["twist", "odometry"])
def test_vo_in_another_frame_than_the_base_is_refused(rclpy_context, model_file, odometry):
    """A VO publishing its twist in the camera's frame (whose x is not the chair's forward
    direction) would feed the model wrong rates: refused, counted and named, and the
    paths stop as on stale VO; with base_frame naming that frame the twists are taken."""
    h = Harness(rclpy_context, model_file, odometry=odometry, vo_timeout_s=0.5)
    try:
        h.drive(100.0, 102.0)
        h.spin_until(lambda: len(h.paths) >= 3, what="first paths")
        h.vo_frame = "camera_link"
        h.drive(102.0, 104.0)
        n = len(h.paths)
        h.drive(104.0, 105.0)
        assert len(h.paths) == n and _reason(h) == Reason.STALE_VO
        values = conv.diagnostic_values(h.node.diagnostic_status())
        assert values["vo_other_frame"] == "15"
        assert values["vo_frame"].startswith("VO twists in frame 'camera_link' refused")
        h.vo_frame = ""  # a publisher that leaves the frame empty: taken as the base's
        h.drive(105.0, 107.0)
        h.spin_until(lambda: len(h.paths) > n, what="paths again")
        assert conv.diagnostic_values(h.node.diagnostic_status())["vo_frame"] == "ok"
        h.vo_frame = "/base_link"  # the base as tf2 reads it
        h.drive(107.0, 108.0)
        assert h.node._vo_frame.refused == 15
    finally:
        h.close()
    named = Harness(rclpy_context, model_file, odometry=odometry, base_frame="camera_link")
    try:
        named.vo_frame = "camera_link"
        named.drive(100.0, 102.0)
        named.spin_until(lambda: len(named.paths) >= 3, what="paths")
        assert named.node._vo_frame.refused == 0
    finally:
        named.close()


def test_nan_inputs_are_dropped_and_prediction_continues(rclpy_context, model_file):
    h = Harness(rclpy_context, model_file)
    try:
        h.drive(100.0, 103.0, joy_nan=True)
        h.spin_until(lambda: len(h.paths) >= 5, what="paths")
        dropped = h.node.predictor.stats.dropped_nonfinite
        assert dropped == 10
        status = {kv.key: kv.value for kv in h.node.diagnostic_status().values}
        assert status["dropped_nonfinite"] == "10"
        for path in h.paths:
            assert np.all(np.isfinite(conv.path_to_poses(path)[1]))
    finally:
        h.close()


def test_out_of_range_inputs_are_refused_with_reasons_in_diagnostics(rclpy_context,
                                                                     model_file):
    """Issue 16: joystick or plan values of 1e30 were accepted silently."""
    h = Harness(rclpy_context, model_file)
    try:
        h.drive(100.0, 102.0)
        h.spin_until(lambda: h.paths and _t0(h.paths[-1]) > 102.0 - 1e-9, what="paths")
        good = h.node._last_result
        h.joy(102.05, 1e30, 0.0)
        h.joy(102.06, 0.2, -1.3)
        h.vo(102.07, 6.0, 0.0)  # faster than any wheelchair
        h.vo(102.08, 0.3, 1e30)
        n_plans = h.node.predictor.stats.rejected.get(Reason.REJECT_PLAN, 0)
        h.plan_pub.publish(conv.plan_to_trajectory(np.array([[0.2, 0.0], [1e30, 0.0]]), 102.1,
                                                   DT))
        h.spin_until(lambda: h.node.predictor.stats.rejected.get(Reason.REJECT_PLAN, 0)
                     > n_plans, what="plan")
        status = {kv.key: kv.value for kv in h.node.diagnostic_status().values}
        assert status["rejected"] == ("joy_out_of_range=2, plan_out_of_range=1, "
                                      "vo_out_of_range=2")
        assert status["last_rejected"].startswith(
            "plan_out_of_range: plan row 1: forward deflection 1e+30 is outside")
        assert status["dropped_nonfinite"] == "0"
        # nothing of it reached the buffers: the next step predicts from the good data
        assert h.node.predictor.newest_stamps() == (102.0, 102.03)
        h.drive(102.0, 103.0)
        h.spin_until(lambda: _t0(h.paths[-1]) > 103.0 - 1e-9, what="paths")
        result = h.node._last_result
        assert result.ok and not result.from_plan
        assert np.all(np.abs(result.joy_past) <= 1.0) and np.all(np.abs(result.vel_past) < 1.0)
        assert good.ok
    finally:
        h.close()


def test_joy_plan_changes_the_path(rclpy_context, model_file):
    h = Harness(rclpy_context, model_file)
    try:
        def still(t):
            return (0.0, 0.0)

        h.drive(100.0, 102.0, joy=still, vel=still)
        h.spin_until(lambda: h.paths and _t0(h.paths[-1]) > 102.0 - 1e-9, what="paths")
        held = conv.path_to_poses(h.paths[-1])[1]
        assert np.max(np.abs(held[:, :2])) < 0.05  # standing still, stick centred
        plan = np.tile([[1.0, 0.8]], (K + 2, 1))
        h.plan_pub.publish(conv.plan_to_trajectory(plan, 0.0, DT))  # zero stamp: starts now
        h.spin_until(lambda: h.node.predictor.plan_future(h.now, h.now, 1) is not None,
                     what="plan")
        h.drive(102.0, 102.6, joy=still, vel=still)
        h.spin_until(lambda: _t0(h.paths[-1]) > 102.4 - 1e-9, what="planned path")
        planned = conv.path_to_poses(h.paths[-1])[1]
        assert planned[-1, 0] > held[-1, 0] + 0.05  # full forward: the chair moves ahead
        assert planned[-1, 2] > held[-1, 2] + 0.02  # turn left: heading increases
        values = {kv.key: kv.value for kv in h.node.diagnostic_status().values}
        assert values["plan_used"] == "True"
        # a malformed plan is refused with a warning and does not replace the good one
        bad = conv.plan_to_trajectory(plan, 0.0, DT)
        bad.joint_names = ["forward", "steer"]
        h.plan_pub.publish(bad)
        h.spin_until(lambda: h.node._bad_messages == 1, what="bad plan")
    finally:
        h.close()


def test_runtime_parameter_changes_are_validated(rclpy_context, model_file):
    h = Harness(rclpy_context, model_file)
    try:
        ok = h.node.set_parameters([Parameter("vo_timeout_s", value=0.8),
                                    Parameter("horizon_steps", value=7)])
        assert all(r.successful for r in ok)
        assert h.node.predictor.config.vo_timeout_s == 0.8
        assert h.node.predictor.config.horizon_steps == 7
        bad = h.node.set_parameters([Parameter("uncertainty", value="ukf")])[0]
        assert not bad.successful and "uncertainty" in bad.reason
        assert h.node.predictor.config.uncertainty == "linear"
        ro = h.node.set_parameters([Parameter("model_path", value="other.npz")])[0]
        assert not ro.successful
        out_of_range = h.node.set_parameters([Parameter("joy_timeout_s", value=-1.0)])[0]
        assert not out_of_range.successful
    finally:
        h.close()


def test_clock_jump_back_resets_and_predicts_again(rclpy_context, model_file):
    h = Harness(rclpy_context, model_file)
    try:
        h.drive(100.0, 102.0)
        h.spin_until(lambda: len(h.paths) >= 3, what="paths")
        resets = h.node.predictor.stats.resets
        # the bag loops: time goes back by 2 s
        h.drive(98.0, 100.0)
        assert h.node.predictor.stats.resets > resets
        h.spin_until(lambda: conv.stamp_to_seconds(h.paths[-1].header.stamp) < 100.0,
                     what="paths after the jump")
        t0s = [conv.stamp_to_seconds(p.header.stamp) for p in h.paths]
        after = [t for t in t0s if t < 100.0]
        assert after == sorted(after) and len(after) >= 3
    finally:
        h.close()


def test_odometry_input_gives_paths_in_odom_and_tracking_loss_stops_them(rclpy_context,
                                                                          model_file):
    h = Harness(rclpy_context, model_file, odometry=True)
    try:
        h.drive(100.0, 102.0)
        h.spin_until(lambda: h.paths and abs(
            conv.stamp_to_seconds(h.paths[-1].header.stamp) - 102.0) < 1e-9, what="paths")
        path = h.paths[-1]
        assert path.header.frame_id == "odom"
        t0 = conv.stamp_to_seconds(path.header.stamp)
        _, poses = conv.path_to_poses(path)
        # the path starts from the odometry pose at t0 (x = 0.5 (t0 - 100), y = 2)
        first_step = np.linalg.norm(poses[0, :2] - [0.5 * (t0 - 100.0), 2.0])
        assert first_step < 0.3
        assert h.markers[-1].markers[1].header.frame_id == "odom"
        # VO reports tracking loss (negative twist variance): no path, reason given
        n = len(h.paths)
        h.clock(102.13)
        h.vo(102.13, 0.4, 0.0, lost=True)
        h.executor.spin_once(timeout_sec=0.05)
        assert _reason(h) == Reason.VO_TRACKING_LOST
        assert len(h.paths) == n
    finally:
        h.close()


# ---- conversions used by the node (built directly, no DDS) --------------------------


def test_stamp_conversion_matches_the_bag_reader():
    from builtin_interfaces.msg import Time

    for sec, nsec in ((1_700_000_000, 123_456_789), (0, 1), (12, 999_999_999)):
        t = conv.stamp_to_seconds(Time(sec=sec, nanosec=nsec))
        assert t == float(sec * 1_000_000_000 + nsec) * 1e-9  # asgp_ros.recording.bags' formula
        back = conv.seconds_to_stamp(t)
        assert abs((back.sec * 10**9 + back.nanosec) - (sec * 10**9 + nsec)) <= 256
    with pytest.raises(ValueError, match="negative"):
        conv.seconds_to_stamp(-1.0)


def test_plan_conversion_and_validation():
    plan = np.array([[0.1, -0.2], [0.3, 0.4], [1.0, 0.0]])
    msg = conv.plan_to_trajectory(plan, 12.2, 0.2)
    assert list(msg.joint_names) == ["forward", "turn"]
    assert [p.time_from_start.nanosec for p in msg.points] == [0, 200_000_000, 400_000_000]
    start, back = conv.plan_from_trajectory(msg, 0.2)
    assert start == pytest.approx(12.2, abs=1e-9)
    np.testing.assert_array_equal(back, plan)  # float64 end to end
    # joints in the other order; points 0.3 s apart from 0.1 s on, sampled every 0.2 s
    # (zero-order hold); a zero stamp starts on arrival
    msg = JointTrajectory(joint_names=["turn", "forward"])
    msg.points = [JointTrajectoryPoint(positions=[0.5, 0.1],
                                       time_from_start=Duration(sec=0, nanosec=ns))
                  for ns in (100_000_000, 400_000_000, 700_000_000)]
    msg.points[1].positions = [0.6, 0.2]
    msg.points[2].positions = [0.7, 0.3]
    start, rows = conv.plan_from_trajectory(msg, 0.2, arrival=50.0)
    assert start == pytest.approx(50.1)
    # samples at 0.1, 0.3, 0.5, 0.7 s after the stamp
    np.testing.assert_array_equal(rows, [[0.1, 0.5], [0.1, 0.5], [0.2, 0.6], [0.3, 0.7]])
    assert conv.plan_from_trajectory(msg, 0.2)[0] == pytest.approx(0.1)  # no arrival given

    def broken(**change):
        m = conv.plan_to_trajectory(np.zeros((3, 2)), 5.0, 0.2)
        for key, value in change.items():
            if key == "times":
                for p, ns in zip(m.points, value, strict=True):
                    p.time_from_start = Duration(sec=0, nanosec=ns)
            elif key == "positions":
                m.points[1].positions = value
            else:
                setattr(m, key, value)
        return m

    for bad, why in ((broken(joint_names=["forward"]), "joint_names"),
                     (broken(joint_names=["forward", "angular"]), "joint_names"),
                     (broken(points=[]), "no points"),
                     (broken(positions=[0.0]), "1 positions"),
                     (broken(positions=[0.0, float("nan")]), "NaN"),
                     (broken(times=[0, 300_000_000, 300_000_000]), "strictly increasing"),
                     (broken(times=[0, 400_000_000, 100_000_000]), "strictly increasing"),
                     (conv.plan_to_trajectory(np.zeros((1001, 2)), 5.0, 0.2), "1001 points"),
                     (conv.plan_to_trajectory(np.zeros((2, 2)), 5.0, 300.0), "spans")):
        with pytest.raises(ValueError, match=why):
            conv.plan_from_trajectory(bad, 0.2)
    with pytest.raises(ValueError, match="dt"):
        conv.plan_from_trajectory(msg, float("nan"))


def test_a_path_serialized_by_hand_is_the_message_rclpy_reads():
    """The node publishes its path already serialized (conv.path_cdr: rclpy's message and
    conversion took 0.3-0.6 ms of each path's latency). rclpy must read it as the message
    path_from_poses builds, whatever the length of the frame id (CDR's padding before each
    pose's doubles depends on it) and of the path, and refuse what it would."""
    from rclpy.serialization import deserialize_message

    rng = np.random.default_rng(4)
    for frame in ("", "b", "od", "odo", "odom", "base_link", "map_ünïcode", "x" * 37):
        for k in (1, 2, 3, 10, 40):
            poses = rng.normal(scale=[3.0, 3.0, 2.0], size=(k, 3))
            t0 = float(rng.uniform(0.0, 2e9))
            times = t0 + 0.2 * np.arange(1, k + 1) + 1e-10 * rng.uniform(size=k)
            want = conv.path_from_poses(poses, times, frame, t0)
            got = deserialize_message(conv.path_cdr(poses, times, frame, t0), Path)
            assert got == want, (frame, k)
    with pytest.raises(ValueError, match="negative"):
        conv.path_cdr(np.zeros((1, 3)), [1.0], "odom", -1.0)
    with pytest.raises(ValueError, match="int32"):
        conv.path_cdr(np.zeros((1, 3)), [2.0**31], "odom", 1.0)
    with pytest.raises(ValueError, match="poses"):
        conv.path_cdr(np.zeros((2, 3)), [1.0], "odom", 1.0)


def test_path_and_markers_conversion():
    poses = np.array([[0.1, 0.0, 0.05], [0.25, 0.01, 0.1], [0.4, 0.03, -3.0]])
    times = 10.0 + 0.2 * np.arange(1, 4)
    msg = conv.path_from_poses(poses, times, "base_link", 10.0)
    assert msg.header.frame_id == "base_link" and len(msg.poses) == 3
    t, back = conv.path_to_poses(msg)
    np.testing.assert_allclose(t, times, atol=1e-9)
    np.testing.assert_allclose(back, poses, atol=1e-12)
    ell = np.array([[0.2, 0.1, 0.3], [0.3, 0.0, 0.0], [0.4, 0.2, -1.0]])
    arr = conv.ellipse_markers(poses[:, :2], ell, "odom", 10.0)
    assert arr.markers[0].action == Marker.DELETEALL
    assert [m.id for m in arr.markers[1:]] == [0, 1, 2]
    assert arr.markers[1].scale.x == pytest.approx(0.4)
    assert arr.markers[2].scale.y == pytest.approx(1e-3)  # degenerate axis still drawn
    assert len(conv.ellipse_markers(np.zeros((0, 2)), np.zeros((0, 3)), "odom", 0.0)
               .markers) == 1
    # read back (the demo's monitor): in id order, as drawn (the 0 axis at the floor)
    arr.markers[1:] = arr.markers[:0:-1]  # delivered in any order
    back = conv.ellipses_from_markers(arr)
    np.testing.assert_allclose(back[:, :2], np.maximum(ell[:, :2], 5e-4), atol=1e-12)
    np.testing.assert_allclose(np.cos(back[:, 2] - ell[:, 2]), 1.0, atol=1e-12)
    # a chair at rest: 0.6 mm ahead, microns sideways; the truth at the centre is held
    rest = conv.ellipses_from_markers(conv.ellipse_markers(
        np.array([[1e-4, 1e-7]]), np.array([[6e-4, 2e-7, 0.0]]), "odom", 0.0))
    np.testing.assert_allclose(rest, [[6e-4, 5e-4, 0.0]], atol=1e-12)
    assert conv.ellipses_from_markers(conv.ellipse_markers(
        np.zeros((0, 2)), np.zeros((0, 3)), "odom", 0.0)).shape == (0, 3)


def test_odometry_and_joy_conversion():
    msg = conv.odometry_from_pose(5.0, 1.0, 2.0, 0.7, 0.3, -0.1)
    t, vel, ok, pose = conv.odometry_to_sample(msg)
    assert t == 5.0 and vel == (0.3, -0.1) and ok
    np.testing.assert_allclose(pose, (1.0, 2.0, 0.7))
    for cov in (-1.0, 1e9, float("nan")):
        msg.twist.covariance[0] = cov
        assert not conv.odometry_to_sample(msg)[2]
    msg.twist.covariance[0] = 0.01
    msg.twist.twist.linear.x = float("nan")
    assert not conv.odometry_to_sample(msg)[2]
    joy = conv.joy_from_sample(3.0, 0.5, -0.25)
    assert conv.joy_to_sample(joy) == (3.0, (0.5, -0.25))
    assert conv.joy_to_sample(joy, 1, 0) == (3.0, (-0.25, 0.5))
    with pytest.raises(ValueError, match="2 axes"):
        conv.joy_to_sample(joy, 0, 3)


def test_adaptation_learns_shows_itself_in_diagnostics_and_resets(rclpy_context, model_file):
    """adapt.enabled: the chair is slower than the model was trained for; the node absorbs
    the completed steps, the diagnostics show it, the service returns to the trained model
    and a runtime buffer too short for adaptation is refused."""
    from std_srvs.srv import Trigger

    h = Harness(rclpy_context, model_file, **{"adapt.enabled": True,
                                              "adapt.half_life_s": 10.0})
    try:
        def slow(t: float) -> tuple[float, float]:
            return 0.3 + 0.2 * math.sin(t - 0.3), 0.2 * math.cos(0.5 * t)

        h.drive(100.0, 112.0, vel=slow)
        stats = h.node.predictor.adaptation
        assert stats is not None and stats.rows_absorbed >= 40
        assert h.node.predictor.model.channels[0].posterior is not \
            load_model(model_file).channels[0].posterior
        h.spin_until(lambda: h.diags and any(
            kv.key == "adapt_rows_absorbed" and int(kv.value) > 0
            for kv in h.diags[-1].status[0].values), what="adaptation diagnostics")
        values = {kv.key: kv.value for kv in h.diags[-1].status[0].values}
        assert values["adapt"] == "on"
        for key in ("adapt_effective_size", "adapt_variance_scale", "adapt_last_update_ms",
                    "adapt_coverage_95", "adapt_steps_refused", "adapt_choice_t",
                    "adapt_switches"):
            assert values[key]
        assert values["adapt_published"] in ("trained", "adapted")
        assert "nan" not in values["adapt_choice_t"]  # before the evidence: said in words
        short = h.node.set_parameters([Parameter("buffer_s", value=2.0)])[0]
        assert not short.successful and "adaptation needs" in short.reason
        client = h.test.create_client(Trigger, "/predictor_node/reset_adaptation")
        h.spin_until(client.service_is_ready, what="reset service")
        future = client.call_async(Trigger.Request())
        h.spin_until(future.done, what="reset reply")
        assert future.result().success
        assert h.node.predictor.adaptation.rows_absorbed == 0
    finally:
        h.close()


def test_a_reduced_rate_still_adapts_and_checks_every_step(rclpy_context, model_file):
    """rate_hz 1 on a 5 Hz model (a path every 5th step): adaptation learnt only on the
    predicted steps, and its online calibration checked none (adapt_checked 0, the trained
    posterior and its ellipses kept on a chair that had changed). Every step is learnt and
    checked now, as at the model's rate."""
    h = Harness(rclpy_context, model_file, rate_hz=1.0,
                **{"adapt.enabled": True, "adapt.half_life_s": 10.0})
    try:
        def slow(t: float) -> tuple[float, float]:
            return 0.3 + 0.2 * math.sin(t - 0.3), 0.2 * math.cos(0.5 * t)

        h.drive(100.0, 140.0, vel=slow)
        stats = h.node.predictor.adaptation
        assert stats is not None and h.node._paths_published > 0
        steps = 40.0 * 5  # the drive's grid steps
        assert stats.rows_absorbed >= 0.8 * steps - 30  # less the lags and the settling
        assert stats.checked >= 0.6 * steps, stats.checked
        assert h.node._paths_published <= steps / 5 + 1
    finally:
        h.close()


def _drive_with_overrides(h: Harness, t_from: float, t_to: float) -> None:
    """h.drive's inputs, with an override published at every joystick sample (a planner or
    the shared-control layer overriding the user the whole time)."""
    pub = h.test.create_publisher(Joy, "joy_override", QoSProfile(depth=10))
    for i in range(round((t_to - t_from) / 0.1)):
        t = t_from + 0.1 * (i + 1)
        h.clock(t)
        h.joy(t, 0.5 + 0.3 * math.sin(t), 0.4 * math.cos(0.5 * t))
        if pub.get_subscription_count():
            n = h.node.predictor.stats.overrides + sum(h.node.predictor.stats.rejected.values())
            pub.publish(conv.joy_from_sample(t, 0.1, 0.0))
            h.spin_until(lambda n=n: h.node.predictor.stats.overrides
                         + sum(h.node.predictor.stats.rejected.values()) > n, what="override")
        if i % 2 == 1:
            h.clock(t + 0.03)
            h.vo(t + 0.03, 0.45 + 0.25 * math.sin(t - 0.27), 0.3 * math.cos(0.5 * t + 0.015))


def test_paths_are_predicted_from_the_override_the_board_applies(rclpy_context,
                                                                   model_file):
    """While an override drives the chair as the serial bridge and the board would apply it
    (written until override_timeout_s after the earlier of its stamp and its arrival, each
    frame held for the board's 0.2 s watchdog; the stick out of neutral), the joystick
    samples the predictor gets are the override, not the user's stick. Not after it, not
    with a neutral stick, not for a sample read before it arrived, not from an override the
    bridge refuses (stamped too long ago, too far ahead or negative, out of range), not
    with override_paths false, and not after the clock went back."""
    h = Harness(rclpy_context, model_file)
    pub = h.test.create_publisher(Joy, "joy_override", QoSProfile(depth=10))
    user = [0.8, 0.3]

    def override(stamp: float | None, *axes: float, sec: int | None = None) -> None:
        stats = h.node.predictor.stats

        def taken() -> int:  # kept out of learning, refused by the predictor, or malformed
            return stats.overrides + sum(stats.rejected.values()) + h.node._bad_messages
        n = taken()
        msg = conv.joy_from_sample(stamp or 0.0, 0.0, 0.0)
        if sec is not None:
            msg.header.stamp.sec = sec
        msg.axes = [float(a) for a in axes]
        pub.publish(msg)
        h.spin_until(lambda: taken() > n, what="override")

    def fed(t: float, fwd: float, turn: float, clock: float | None = None) -> list[float]:
        h.clock(t if clock is None else clock)
        h.joy(t, fwd, turn)
        stamps, joy = h.node.predictor._joy.arrays()
        assert stamps[-1] == pytest.approx(t)
        return [round(float(x), 6) for x in joy[-1]]

    try:
        h.drive(100.0, 103.0)
        h.spin_until(lambda: h.node.count_subscribers("joy_override") > 0, what="discovery")
        paths = len(h.paths)
        h.clock(103.0)
        override(103.0, 0.1, -0.2)  # written until 103.15, held by the board until 103.35
        assert fed(103.1, *user) == [0.1, -0.2]
        assert fed(103.2, 0.0, 0.0) == [0.0, 0.0]  # the stick let go: the board stops
        assert fed(103.3, *user) == [0.1, -0.2]
        assert fed(103.4, *user) == user  # the user drives again
        h.vo(103.43, 0.5, 0.1)
        h.spin_until(lambda: len(h.paths) > paths, what="a path")

        h.clock(103.5)
        override(None, 0.2, 0.0)  # unstamped: by its arrival, until 103.85
        assert fed(103.6, *user) == [0.2, 0.0]
        override(103.4, 0.3, 0.0)  # stamped 0.2 s before it arrives: the bridge refuses it
        override(104.8, 0.3, 0.0)  # stamped 1.2 s ahead: refused
        override(None, 0.3, 0.0, sec=-5)  # a negative stamp: refused
        override(None, 0.3)  # one axis: refused
        override(None, 1.5, 0.0)  # out of range: refused
        assert fed(103.7, *user) == [0.2, 0.0]
        assert h.node._bad_messages == 2

        h.clock(103.9)
        override(103.8, 0.4, 0.0)  # stamped 0.1 s ago: written until 103.95, held to 104.15
        assert fed(104.1, *user) == [0.4, 0.0]
        assert fed(104.2, *user) == user
        h.clock(104.3)
        override(104.3, 0.5, 0.0)
        h.node.set_parameters([Parameter("override_paths", value=False)])
        assert fed(104.4, *user) == user
        h.node.set_parameters([Parameter("override_paths", value=True)])
        assert fed(104.5, *user) == [0.5, 0.0]

        h.clock(104.9)
        override(104.9, 0.1, 0.0)
        assert fed(104.85, *user, clock=105.0) == user  # read before the override came
        assert fed(105.0, *user) == [0.1, 0.0]
        assert fed(103.2, *user) == user  # the clock went back
        assert fed(104.95, *user) == user  # and that override was forgotten
        h.clock(105.5)
        h.spin_until(lambda: h.diags and conv.diagnostic_values(
            h.diags[-1].status[0]).get("joy_overridden") == "7",
            what="the count of overridden samples")
    finally:
        h.close()


def test_the_boards_measured_output_feeds_while_it_arrives(rclpy_context, model_file):
    """joy_applied (the serial bridge's measurement of what the board drives with) feeds the
    predictor while it arrives; joy's samples are dropped then, the one of the same stamp
    included; 0.1 s after the last one, joy feeds again."""
    h = Harness(rclpy_context, model_file)
    pub = h.test.create_publisher(Joy, "joy_applied", qos_profile_sensor_data)
    node = h.node

    def applied(t: float, fwd: float, turn: float) -> None:
        h.clock(t)
        n = node.polled.taken
        pub.publish(conv.joy_from_sample(t, fwd, turn))
        h.spin_until(lambda: node.polled.taken > n, what="joy_applied")
        # on the simulated clock, standing at t, it arrived within a drain's period of t
        assert t - 0.5 <= node._joy_source.measured_arrival <= t

    def joy(t: float, fwd: float, turn: float) -> None:
        h.clock(t)
        n = len(node._joy_rate.times)
        h.joy_pub.publish(conv.joy_from_sample(t, fwd, turn))
        h.spin_until(lambda: len(node._joy_rate.times) > n, what="joy")

    def newest() -> tuple[float, list[float]]:
        stamps, values = node.predictor._joy.arrays()
        return round(float(stamps[-1]), 6), [round(float(x), 6) for x in values[-1]]

    try:
        h.drive(100.0, 103.0)
        h.spin_until(lambda: node.count_subscribers("joy_applied") > 0, what="discovery")
        applied(103.1, 0.2, 0.1)
        assert newest() == (103.1, [0.2, 0.1])
        joy(103.1, 0.8, 0.3)  # the user's stick of the same sample: not fed
        joy(103.15, 0.8, 0.3)  # joy_applied is arriving: not fed
        assert newest() == (103.1, [0.2, 0.1])
        applied(103.2, 0.25, 0.1)
        assert newest() == (103.2, [0.25, 0.1])
        joy(103.4, 0.8, 0.3)  # no joy_applied for 0.2 s: joy feeds again
        assert newest() == (103.4, [0.8, 0.3])
        # a joy_applied that is no measurement (NaN) is refused and does not silence joy
        n = node.predictor.stats.dropped_nonfinite
        h.clock(103.5)
        pub.publish(conv.joy_from_sample(103.5, math.nan, 0.1))
        h.spin_until(lambda: node.predictor.stats.dropped_nonfinite > n, what="NaN refused")
        joy(103.55, 0.7, 0.3)
        assert newest() == (103.55, [0.7, 0.3])
        assert node._joy_source.measured_samples == 2
        h.clock(104.0)
        h.spin_until(lambda: h.diags and conv.diagnostic_values(
            h.diags[-1].status[0]).get("joy_measured") == "2",
            what="diagnostics")
    finally:
        h.close()


@pytest.mark.parametrize("override_topic", ["joy_override", ""])
def test_adaptation_learns_nothing_an_override_drove(rclpy_context, model_file,
                                                      override_topic):
    """Overrides on joy_override (the shared-control layer overriding the user): the
    predictor keeps publishing paths but learns none of the steps they may have driven,
    and its diagnostics count them; with override_topic '' it does not listen."""
    h = Harness(rclpy_context, model_file, override_topic=override_topic,
                **{"adapt.enabled": True})
    try:
        h.drive(100.0, 106.0)
        stats = h.node.predictor.adaptation
        assert stats is not None and stats.rows_absorbed >= 15
        refused, paths = stats.steps_refused, len(h.paths)
        if override_topic:
            h.spin_until(lambda: h.node.count_subscribers("joy_override") > 0,
                         what="override discovery")
        _drive_with_overrides(h, 106.0, 112.0)
        h.drive(112.0, 118.0)
        stats = h.node.predictor.adaptation
        assert len(h.paths) - paths >= 50  # paths all along
        h.spin_until(lambda: h.diags and "overrides_seen" in {
            kv.key for kv in h.diags[-1].status[0].values}, what="diagnostics")
        seen = {kv.key: kv.value for kv in h.diags[-1].status[0].values}["overrides_seen"]
        if override_topic:
            assert h.node.predictor.stats.overrides == 60 and seen == "60"
            assert stats.steps_refused - refused >= 6 * 5  # the 6 s of overrides, + lags
        else:
            assert h.node.predictor.stats.overrides == 0 and seen == "0"
            assert stats.steps_refused == refused
    finally:
        h.close()


def test_a_forward_clock_jump_keeps_what_adaptation_learnt(rclpy_context, model_file):
    """The simulated clock jumps an hour ahead (a bag played on from later, a machine's
    clock set): the first row after it decayed what was learnt by the whole hour, 2^-12 at
    a half-life of 300 s (weight 131.8 -> 8.0), and the trained data's to nothing. Only
    time with rows forgets now; the jump counts as one second."""
    h = Harness(rclpy_context, model_file, **{"adapt.enabled": True,
                                              "adapt.half_life_s": 300.0})
    try:
        h.drive(100.0, 130.0)
        h.clock(h.now + 0.3)
        online = h.node.predictor._adapter._online[0]
        h.spin_until(lambda: online.stats.data_weight > 50, 5.0, "rows learnt")
        before = online.stats.data_weight
        h.drive(3700.0, 3704.0)
        h.clock(h.now + 0.3)
        h.spin_until(lambda: online.stats.data_weight > before, 5.0,
                     "rows learnt after the jump, adding to the weight")
        assert h.node.predictor.stats.resets == 0  # forward: nothing to reset
        assert online.stats.data_weight >= 0.99 * before
    finally:
        h.close()


def test_adaptation_learns_after_the_path_is_out(rclpy_context, model_file):
    """Learning waits a moment (LEARN_DELAY_S on the node's clock) after each path, so the
    path's subscribers are not kept from a core by it; it still comes once per path, before
    the next step's path, and none of the settled steps is lost."""
    h = Harness(rclpy_context, model_file, **{"adapt.enabled": True})
    events: list[tuple[str, float]] = []
    node = h.node
    now = lambda: node.get_clock().now().nanoseconds * 1e-9  # noqa: E731
    publish, learn = node.path_pub.publish, node.predictor.learn

    def on_publish(msg):
        events.append(("path", now()))
        publish(msg)

    def on_learn():
        events.append(("learn", now()))
        learn()

    node.path_pub.publish, node.predictor.learn = on_publish, on_learn
    try:
        h.drive(100.0, 106.0)
        h.clock(h.now + 0.1)
        h.spin_until(lambda: events and events[-1][0] == "learn", what="the last learning")
    finally:
        h.close()
    paths = [t for kind, t in events if kind == "path"]
    assert len(paths) >= 20
    # (a step without a path, while the buffers fill, learns at once)
    events = events[[kind for kind, _ in events].index("path"):]
    # after each path, one learning, at least LEARN_DELAY_S later on the clock, before the
    # next path
    kinds = [kind for kind, _ in events]
    assert kinds == ["path", "learn"] * len(paths), kinds
    for (_, t_path), (_, t_learn) in zip(events[::2], events[1::2], strict=True):
        assert t_learn - t_path >= LEARN_DELAY_S - 1e-9
    # every step absorbed but the last horizon's, as when learning follows at once
    assert node.predictor.adaptation.rows_absorbed >= len(paths) - K


class _LearnAtOnce:
    """In place of the node's one-shot learn timer: learning right after each path."""

    def __init__(self, node: PredictorNode) -> None:
        self.node = node

    def is_canceled(self) -> bool:
        return True

    def reset(self) -> None:
        self.node._learn()

    def cancel(self) -> None:
        pass


def _drive_in_bursts(context, model_file: str, at_once: bool) -> tuple[int, int, int]:
    """40 s of driving whose samples arrive a second's worth at a time (a replay catching
    up, or /clock published coarsely): (paths, rows absorbed, predictions checked)."""
    h = Harness(context, model_file, **{"adapt.enabled": True, "joy_timeout_s": 3.0,
                                        "vo_timeout_s": 3.0})
    if at_once:
        h.node._learn_timer.cancel()
        h.node._learn_timer = _LearnAtOnce(h.node)
    try:
        for second in range(40):
            end = 101.0 + second
            h.clock(end)
            for i in range(10):
                t = end - 1.0 + 0.1 * (i + 1)
                h.joy(t, 0.5 + 0.3 * math.sin(t), 0.4 * math.cos(0.5 * t))
                if i % 2 == 1:
                    u = t - 0.07
                    h.vo(u, 0.45 + 0.25 * math.sin(u - 0.3), 0.3 * math.cos(0.5 * u))
        h.clock(end + 0.05)
        h.spin_until(lambda: h.node._learn_timer.is_canceled(), what="the last learning")
        stats = h.node.predictor.adaptation
        return h.node._paths_published, stats.rows_absorbed, stats.checked
    finally:
        h.close()


def test_paths_closer_than_the_learning_delay_learn_as_at_once(rclpy_context, model_file):
    """Paths less than LEARN_DELAY_S apart on the node's clock: each one's learning comes
    before the next prediction, so every prediction is checked against its outcome (the
    online calibration) and every step absorbed, as when learning followed each path at
    once. (Learning only the newest of several paths checked 2 of about 190.)"""
    at_once = _drive_in_bursts(rclpy_context, model_file, at_once=True)
    deferred = _drive_in_bursts(rclpy_context, model_file, at_once=False)
    assert at_once[0] >= 150 and at_once[2] >= 100
    assert deferred == at_once


def test_a_model_that_cannot_adapt_predicts_as_trained_and_says_why(rclpy_context, tmp_path):
    """Adaptation is on by default; a model of another kind (here the constant-velocity
    baseline) starts, predicts from the model as trained, warns, and its diagnostics say
    why it does not adapt."""
    from asgp_ros.core.baselines import ConstantVelocityChannel, probe_columns
    from asgp_ros.core.features import FeatureConfig
    from asgp_ros.core.modelfile import save_model
    from asgp_ros.core.models import MotionModel
    from asgp_ros.core.resample import ResampleConfig

    fc = FeatureConfig(lags=4)
    D = fc.input_dim
    channels = tuple(ConstantVelocityChannel(D, probe_columns(c, fc)[1]) for c in (0, 1))
    path = tmp_path / "cv.npz"
    save_model(path, MotionModel(kind="constant_velocity", feature_config=fc,
                                 resample_config=ResampleConfig(), channels=channels))
    for explicit in ([], [Parameter("adapt.enabled", value=True)]):
        node = PredictorNode(context=rclpy_context, parameter_overrides=[
            Parameter("model_path", value=str(path)), *explicit])
        try:
            assert node.predictor.adaptation is None
            values = conv.diagnostic_values(node.diagnostic_status())
            assert values["adapt"] == "off"
            assert "only an ASGP adapts" in values["adapt_unavailable"]
        finally:
            node.destroy_node()
    node = PredictorNode(context=rclpy_context, parameter_overrides=[
        Parameter("model_path", value=str(path)), Parameter("adapt.enabled", value=False)])
    try:
        values = conv.diagnostic_values(node.diagnostic_status())
        assert values["adapt"] == "off" and "adapt_unavailable" not in values
    finally:
        node.destroy_node()
    # the reset service says why, not that adapt.enabled is off
    from std_srvs.srv import Trigger

    h = Harness(rclpy_context, str(path))
    try:
        client = h.test.create_client(Trigger, "/predictor_node/reset_adaptation")
        h.spin_until(client.service_is_ready, what="reset service")
        future = client.call_async(Trigger.Request())
        h.spin_until(future.done, what="reset reply")
        assert not future.result().success
        assert "does not adapt: only an ASGP adapts" in future.result().message
    finally:
        h.close()


def test_an_asgp_adapts_by_default(rclpy_context, model_file):
    node = PredictorNode(context=rclpy_context, parameter_overrides=[
        Parameter("model_path", value=model_file)])
    try:
        assert node.predictor.adaptation is not None
        assert conv.diagnostic_values(node.diagnostic_status())["adapt"] == "on"
    finally:
        node.destroy_node()


def test_a_long_horizon_raises_the_buffer_adaptation_needs(rclpy_context, model_file):
    """Adapting by default, a horizon whose adaptation needs more history than buffer_s
    (10 s) starts with the buffer raised to what it needs (it refused to start); a runtime
    change of another parameter keeps it; buffer_s set below it at runtime is refused."""
    node = PredictorNode(context=rclpy_context, parameter_overrides=[
        Parameter("model_path", value=model_file), Parameter("horizon_s", value=30.0)])
    try:
        need = node.predictor.min_buffer_s
        assert need > 10.0 and node.predictor.config.buffer_s >= need
        assert node.predictor.config.horizon_steps == 150
        assert node.set_parameters([Parameter("plan_timeout_s", value=0.4)])[0].successful
        assert node.predictor.config.buffer_s >= need
        short = node.set_parameters([Parameter("buffer_s", value=need - 1.0)])[0]
        assert not short.successful and "adaptation needs" in short.reason
        assert node.set_parameters([Parameter("buffer_s", value=need + 5.0)])[0].successful
        assert node.predictor.config.buffer_s == need + 5.0
    finally:
        node.destroy_node()
    # not adapting, buffer_s is what it says
    node = PredictorNode(context=rclpy_context, parameter_overrides=[
        Parameter("model_path", value=model_file), Parameter("horizon_s", value=30.0),
        Parameter("adapt.enabled", value=False)])
    try:
        assert node.predictor.config.buffer_s == 10.0
    finally:
        node.destroy_node()


def test_a_buffer_too_short_for_the_window_is_refused_at_start_and_at_runtime(
        rclpy_context, model_file):
    """buffer_s 2 s let stale VO drive paths (the stale-VO rule's look-back cut by the
    buffer): below the model's lags x dt, the rules' look-back and two VO gaps (2.6 s for
    this 4-lag model) it is refused, at start-up and as a runtime change, the minimum
    named; not adapting too (min_buffer_s said 1.0)."""
    with pytest.raises(StartupError, match=r"at least 2\.60 s, got 2 s: .*4 lags"):
        PredictorNode(context=rclpy_context, parameter_overrides=[
            Parameter("model_path", value=model_file), Parameter("adapt.enabled", value=False),
            Parameter("buffer_s", value=2.0)])
    node = PredictorNode(context=rclpy_context, parameter_overrides=[
        Parameter("model_path", value=model_file), Parameter("adapt.enabled", value=False)])
    try:
        assert node.predictor.min_buffer_s == pytest.approx(2.6)
        short = node.set_parameters([Parameter("buffer_s", value=2.0)])[0]
        assert not short.successful and "at least 2.60 s" in short.reason
        assert "look-back" in short.reason and node.predictor.config.buffer_s == 10.0
        assert node.set_parameters([Parameter("buffer_s", value=3.0)])[0].successful
        assert node.predictor.config.buffer_s == 3.0
    finally:
        node.destroy_node()


def test_adapt_parameters_reach_the_adaptation_settings():
    """adapt.trained_mean (on by default) and the half-lives reach the AdaptConfig."""
    on = PredictorNodeParams(model_path="chair.npz", adapt_enabled=True).adapt_settings()
    assert on is not None and on.posterior.trained_mean
    off = PredictorNodeParams(model_path="chair.npz", adapt_enabled=True,
                              adapt_trained_mean=False, adapt_half_life_s=60.0).adapt_settings()
    assert off is not None and not off.posterior.trained_mean
    assert off.posterior.half_life_s == 60.0
    assert PredictorNodeParams(model_path="chair.npz").adapt_settings() is not None
    assert PredictorNodeParams(model_path="chair.npz",
                               adapt_enabled=False).adapt_settings() is None


def test_the_adapt_parameters_defaults_are_the_dataclass_defaults():
    """The node declares adapt.* from the shared table (asgp_ros.nodes.adaptation), which
    the shared-control layer declares too; its dataclass must default alike."""
    from asgp_ros.nodes.adaptation import ADAPT_PARAMS
    from asgp_ros.nodes.predictor_node import PARAMS

    fields = PredictorNodeParams.__dataclass_fields__
    for spec in ADAPT_PARAMS:
        assert spec in PARAMS
        assert fields[spec.name.replace(".", "_")].default == spec.default, spec.name


@pytest.mark.parametrize("name, value", [("adapt.half_life_s", math.nan),
                                         ("adapt.trained_floor", -0.5),
                                         ("horizon_s", 1e30)])
def test_a_value_rclpy_refuses_is_one_line_naming_the_parameter(rclpy_context, model_file,
                                                               name, value):
    """Out of the declared range, or not finite: rclpy refuses it at the declaration; the
    node refuses to start with one line naming the parameter, not a traceback."""
    from asgp_ros.nodes.predictor_node import PredictorNode, StartupError

    with pytest.raises(StartupError, match=re.escape(f"parameter {name}: ")):
        PredictorNode(context=rclpy_context, parameter_overrides=[
            Parameter("model_path", value=model_file), Parameter(name, value=value)])


def test_no_event_handler_per_endpoint_and_unmatched_peers_are_reported(rclpy_context,
                                                                        model_file):
    """rclpy's default QoS event handlers are off (they cost CPU at every message); a
    publisher that cannot be matched is found from the graph, logged, named in the
    diagnostics while it is there (the status WARN though paths are published), and
    forgotten when it goes."""
    from rclpy.qos import ReliabilityPolicy

    h = Harness(rclpy_context, model_file)
    try:
        node = h.node
        # rclpy's own endpoints keep theirs (/parameter_events; /clock with use_sim_time)
        mine = [e for e in [*node.subscriptions, *node.publishers]
                if e.topic_name not in ("/parameter_events", "/rosout", "/clock")]
        assert len(mine) == 8 and all(not e.event_handlers for e in mine), [
            e.topic_name for e in mine if e.event_handlers]

        h.spin_until(lambda: bool(node.qos_watch.check() == []), what="no mismatch")
        assert node.qos_watch.summary() == "none"
        h.drive(100.0, 102.0)
        h.spin_until(lambda: len(h.paths) >= 3, what="paths")
        status = node.diagnostic_status()
        assert (status.level, status.message.startswith("predicting")) == (
            DiagnosticStatus.OK, True)
        # a best-effort plan publisher cannot reach the node's reliable subscription
        bad = h.test.create_publisher(
            JointTrajectory, "joy_plan",
            QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
        h.spin_until(lambda: bool(node.qos_watch.check()), what="the mismatch")
        (problem,) = node.qos_watch.problems
        assert problem.startswith("/joy_plan: publisher of /predictor_test: incompatible QoS")
        assert "best effort publisher and reliable subscription" in problem.lower()
        node._publish_diagnostics()
        status = node.diagnostic_status()
        values = {kv.key: kv.value for kv in status.values}
        assert values["qos_mismatch"] == problem
        # the paths go on, but a planner's plans cannot reach the node: not OK
        assert status.level == DiagnosticStatus.WARN
        assert status.message.startswith("predicting") and problem in status.message
        # a compatible publisher on the same topic is not reported
        h.test.create_publisher(JointTrajectory, "joy_plan", QoSProfile(depth=10))
        h.spin_until(lambda: h.test.count_publishers("joy_plan") == 3, what="discovery")
        assert node.qos_watch.check() == [problem]
        h.test.destroy_publisher(bad)
        h.spin_until(lambda: node.qos_watch.check() == [], what="the mismatch gone")
        assert node.qos_watch.summary() == "none"
        assert "cannot be matched" not in node.diagnostic_status().message
        assert not node.qos_watch._warned  # a peer that comes back is logged again
    finally:
        h.close()


def test_unmatched_peers_are_looked_for_on_the_remapped_topic(rclpy_context, model_file):
    """The graph queries remap their argument: given the remapped name, a chain of rules
    (joy_plan -> /planner/plan -> /elsewhere) would send the check to the wrong topic."""
    import rclpy
    from rclpy.qos import ReliabilityPolicy

    node = PredictorNode(context=rclpy_context, cli_args=[
        "--ros-args", "-r", "joy_plan:=/planner/plan", "-r", "/planner/plan:=/elsewhere"],
        parameter_overrides=[Parameter("model_path", value=model_file)])
    test = rclpy.create_node("remap_test", context=rclpy_context)
    executor = SingleThreadedExecutor(context=rclpy_context)
    executor.add_node(node)
    executor.add_node(test)
    try:
        best_effort = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
        test.create_publisher(JointTrajectory, "/planner/plan", best_effort)
        test.create_publisher(JointTrajectory, "/elsewhere", best_effort)
        deadline = time.monotonic() + 5.0
        while not node.qos_watch.check():
            assert time.monotonic() < deadline, "the mismatch was not found"
            executor.spin_once(timeout_sec=0.01)
        executor.spin_once(timeout_sec=0.05)
        (problem,) = node.qos_watch.check()
        assert problem.startswith("/planner/plan: publisher of /remap_test: incompatible QoS")
    finally:
        executor.shutdown()
        node.destroy_node()
        test.destroy_node()


def test_qos_watch_names_a_peer_of_another_type():
    from rclpy.qos import qos_profile_sensor_data as sensor

    from asgp_ros.nodes.qos_watch import _Endpoint, _mismatch, message_type_name

    assert message_type_name(Joy) == "sensor_msgs/msg/Joy"
    ep = _Endpoint(True, "/joy", "sensor_msgs/msg/Joy", "joy")
    assert _mismatch(ep, "std_msgs/msg/String", sensor, None) == (
        "type std_msgs/msg/String, not sensor_msgs/msg/Joy")
    assert _mismatch(ep, "sensor_msgs/msg/Joy", sensor, sensor) is None
    # the node's best-effort subscription takes a reliable publisher
    assert _mismatch(ep, "sensor_msgs/msg/Joy", QoSProfile(depth=10), sensor) is None
    # its reliable publisher reaches best-effort subscriptions; not the other way round
    reliable = QoSProfile(depth=10)
    out = _Endpoint(False, "/predicted_path", "nav_msgs/msg/Path", "predicted_path")
    assert _mismatch(out, "nav_msgs/msg/Path", sensor, reliable) is None
    out = _Endpoint(False, "/joy", "sensor_msgs/msg/Joy", "joy")
    assert _mismatch(out, "sensor_msgs/msg/Joy", reliable, sensor).startswith(
        "incompatible QoS")
    # without the graph's report of the node's own QoS, only the type is judged
    assert _mismatch(out, "sensor_msgs/msg/Joy", reliable, None) is None


# ---- from an attack on the node's inputs: each a break found, now a regression test ----


def _values(h: Harness) -> dict[str, str]:
    return conv.diagnostic_values(h.node.diagnostic_status())


def _spin(h: Harness, n: int = 20) -> None:
    for _ in range(n):
        h.executor.spin_once(timeout_sec=0.01)


@pytest.mark.parametrize("stamp", [101.5, 105.0], ids=["late", "ahead"])
def test_one_mis_stamped_joystick_message_is_refused_not_a_new_timeline(
        rclpy_context, model_file, stamp):
    """One joy message stamped 1.5 s behind the newest sample (the clock normal), or 2 s
    ahead of the clock, cleared every buffer (plans and overrides too), and the next second
    gave one path instead of five. Now it is refused with its reason; the clock tells a
    new timeline (a bag played again) from a mis-stamped message."""
    h = Harness(rclpy_context, model_file)
    try:
        h.drive(100.0, 103.0)
        h.spin_until(lambda: h.paths and _t0(h.paths[-1]) > 103.0 - 1e-9, what="paths")
        resets = h.node.predictor.stats.resets
        n = h.node.predictor.stats.rejected.get(Reason.REJECT_TIME, 0)
        h.joy_pub.publish(conv.joy_from_sample(stamp, 0.5, 0.0))
        h.spin_until(lambda: h.node.predictor.stats.rejected.get(Reason.REJECT_TIME, 0) > n,
                     what="the message refused")
        paths = len(h.paths)
        h.drive(103.0, 104.0)
        _spin(h)
        assert h.node.predictor.stats.resets == resets and len(h.paths) - paths >= 4
    finally:
        h.close()


def test_an_out_of_range_board_output_does_not_silence_the_stick(rclpy_context, model_file):
    """joy_applied at forward 3.0 (finite, out of range) was taken as the board's measured
    output arriving, so the good joy stream was dropped, and no path came for 2 s. Such a
    sample is no measurement, as a NaN one was not."""
    h = Harness(rclpy_context, model_file)
    applied = h.test.create_publisher(Joy, "joy_applied", qos_profile_sensor_data)
    h.spin_until(lambda: applied.get_subscription_count() > 0, what="discovery")
    try:
        h.drive(100.0, 102.0)
        h.spin_until(lambda: h.paths and _t0(h.paths[-1]) > 102.0 - 1e-9, what="paths")
        paths = len(h.paths)
        joy = h.joy

        def joy_and_bad_applied(t, fwd, turn):
            applied.publish(conv.joy_from_sample(t, 3.0, 0.0))
            joy(t, fwd, turn)
        h.joy = joy_and_bad_applied
        h.drive(102.0, 104.0)
        _spin(h)
        assert len(h.paths) - paths >= 8 and _values(h)["reason"] == Reason.OK
    finally:
        h.close()


def test_odometry_poses_in_another_frame_are_not_taken(rclpy_context, model_file):
    """path_frame odom, and the VO's poses in 'map' (50 m away): paths were published
    labelled odom from them. They are not taken (counted, logged), so no path in odom."""
    h = Harness(rclpy_context, model_file, odometry=True)
    publish = h.vo_pub.publish

    def publish_in_map(msg):
        msg.header.frame_id = "map"
        msg.pose.pose.position.x += 50.0
        publish(msg)
    h.vo_pub.publish = publish_in_map
    try:
        h.drive(100.0, 102.0)
        _spin(h)
        assert not h.paths
        values = _values(h)
        assert int(values["poses_other_frame"]) > 5 and values["reason"] == Reason.NO_POSE
    finally:
        h.close()


def test_an_override_the_bridge_refuses_does_not_stop_learning(rclpy_context, model_file):
    """An override with a NaN axis, which the bridge never writes, was fed to the predictor
    as sent: every step it 'may have driven' was kept out of learning (0 rows absorbed in
    12 s instead of 46). It is refused first, and learning goes on."""
    h = Harness(rclpy_context, model_file)
    pub = h.test.create_publisher(Joy, "joy_override", qos_profile_sensor_data)
    h.spin_until(lambda: pub.get_subscription_count() > 0, what="discovery")
    try:
        vo = h.vo

        def vo_and_bad_override(t, v, w, lost=False):
            msg = Joy()
            msg.header.stamp = conv.seconds_to_stamp(t)
            msg.axes = [math.nan, 0.0]
            n = h.node._bad_messages
            pub.publish(msg)
            h.spin_until(lambda: h.node._bad_messages > n, what="the override refused")
            vo(t, v, w, lost)
        h.vo = vo_and_bad_override
        h.drive(100.0, 112.0)
        _spin(h)
        assert h.node.predictor.stats.overrides == 0
        assert int(_values(h)["adapt_rows_absorbed"]) > 20
    finally:
        h.close()


def test_odometry_whose_angular_variance_flags_a_loss_is_a_lost_sample(
        rclpy_context, model_file):
    """twist.covariance[35] (omega's variance) -1 or NaN was taken as good tracking: only
    [0] was read. Either flags the sample lost; a malformed plan is named in the
    diagnostics (only bad_messages counted it)."""
    h = Harness(rclpy_context, model_file, odometry=True)
    publish = h.vo_pub.publish

    def lost_omega(msg):
        msg.twist.covariance[35] = -1.0
        publish(msg)
    try:
        h.drive(100.0, 102.0)
        h.spin_until(lambda: h.paths and _t0(h.paths[-1]) > 102.0 - 1e-9, what="paths")
        h.vo_pub.publish = lost_omega
        paths = len(h.paths)
        h.drive(102.0, 103.0)
        _spin(h)
        assert len(h.paths) == paths and _values(h)["reason"] != Reason.OK
        plan = conv.plan_to_trajectory(np.array([[math.nan, 0.0]]), 103.0, DT)
        n = h.node._bad_messages
        h.plan_pub.publish(plan)
        h.spin_until(lambda: h.node._bad_messages > n or _values(h)["plan_problem"] != "none",
                     what="the plan refused")
        assert _values(h)["plan_problem"] != "none"
    finally:
        h.close()


def test_adapting_a_model_whose_calibration_factor_is_at_its_limit(rclpy_context, tmp_path):
    """A loadable model with a speed factor of 1e6 (FACTOR_RANGE's top) and its ellipses too
    small: raising the online scale made every publication of the adapted model raise
    (factor above 1e6), learning failed at every step with a throttled log line, and the
    scale ran on. The scale now stops where the factor does."""
    from dataclasses import replace as dc_replace

    from asgp_ros.core.calibration import FACTOR_RANGE, VarianceCalibration
    from asgp_ros.core.modelfile import save_model

    model = load_model(_model_file(tmp_path, "frame"))
    cal = VarianceCalibration(scale=(1e-7, 1e-7), floor=(0.0, 0.0), speed_factors=(1e6,))
    path = str(tmp_path / "edge.npz")
    save_model(path, dc_replace(model, calibration=cal))
    h = Harness(rclpy_context, path)
    errors: list[str] = []
    learn = h.node.predictor.learn

    def learn_and_record() -> None:
        try:
            learn()
        except Exception as exc:
            errors.append(repr(exc))
            raise
    h.node.predictor.learn = learn_and_record
    try:
        h.drive(100.0, 124.0)
        _spin(h)
        assert not errors, errors[:1]
        assert int(_values(h)["adapt_rows_absorbed"]) > 0
        factors = h.node.predictor.model.calibration.speed_factors
        assert all(FACTOR_RANGE[0] <= f <= FACTOR_RANGE[1] for f in factors)
    finally:
        h.close()


def _path_end(path: Path) -> float:
    p = path.poses[-1].pose.position
    return math.hypot(p.x, p.y)


def test_reset_jump_s_changed_at_runtime_reaches_the_measured_joystick(rclpy_context,
                                                                       model_file):
    """``reset_jump_s`` lowered to 0.5 s at runtime, then the clock steps back 0.8 s: the
    predictor restarts its buffers, and the board's measured output stamped after the step
    feeds them. The bookkeeping of ``joy_applied`` kept the start-up 1.0 s and took those
    samples for repeats of ones already fed: no joystick reached the predictor (``joy`` is
    not fed while ``joy_applied`` arrives) until the clock had caught up."""
    h = Harness(rclpy_context, model_file)
    pub = h.test.create_publisher(Joy, "joy_applied", qos_profile_sensor_data)
    node = h.node

    def applied(t: float, fwd: float) -> None:
        h.clock(t)
        n = node.polled.taken
        pub.publish(conv.joy_from_sample(t, fwd, 0.0))
        h.spin_until(lambda: node.polled.taken > n, what="joy_applied")

    try:
        h.drive(100.0, 103.0)
        h.spin_until(lambda: node.count_subscribers("joy_applied") > 0, what="discovery")
        assert node.set_parameters([Parameter("reset_jump_s", value=0.5)])[0].successful
        applied(103.1, 0.2)
        applied(102.3, 0.6)  # the clock stepped back 0.8 s
        stamps, values = node.predictor._joy.arrays()
        assert round(float(stamps[-1]), 6) == 102.3
        assert round(float(values[-1][0]), 6) == 0.6
        assert node.predictor.stats.resets >= 1
        assert node._joy_source.measured_samples == 2
    finally:
        h.close()


@pytest.mark.parametrize("step", [0.0, 0.9])
def test_no_stale_path_after_a_small_clock_step_back(rclpy_context, model_file, step):
    """The clock steps back 0.9 s (less than reset_jump_s: NTP setting a clock that ran
    ahead, every stream stamped by it) as the user lets go and the chair stops. The buffers
    kept the old timeline, stamped up to 0.9 s ahead of the clock, and the new samples were
    spliced in among them: paths with t0 at the clock's present predicted the chair driving
    on, 0.9 s after it had stopped. The step restarts the buffers; no path is stale."""
    h = Harness(rclpy_context, model_file)

    def drive(phys_from: float, phys_to: float, shift: float) -> list[tuple[float, int]]:
        # joystick 10 Hz, VO 5 Hz; forward until physical 110 s, then at rest within 0.3 s;
        # stamps on the clock, ``shift`` behind physical time from 110 s on
        seen = []
        for i in range(round((phys_to - phys_from) / 0.1)):
            t = phys_from + 0.1 * (i + 1)
            s = t - (shift if t >= 110.0 - 1e-9 else 0.0)
            fwd = 0.9 if t < 110.0 - 1e-9 else 0.0
            v = 1.0 if t < 110.0 else max(0.0, 1.0 - (t - 110.0) / 0.3)
            h.clock(s)
            h.joy(s, fwd, 0.0)
            if i % 2 == 1:
                h.clock(s + 0.03)
                h.vo(s + 0.03, v + 0.002 * math.sin(7 * t), 0.0)
            for _ in range(3):
                h.executor.spin_once(timeout_sec=0.005)
            seen.append((t, len(h.paths)))
        return seen

    try:
        drive(100.0, 110.0, 0.0)
        moving = _path_end(h.paths[-1])  # (the test model's horizon: 0.27 m at 1 m/s)
        assert moving > 0.2
        seen = drive(110.0, 113.0, step)
        first = next(n for t, n in seen if t >= 110.5)  # the chair at rest for 0.2 s
        ends = [round(_path_end(p), 3) for p in h.paths[first:]]
        assert ends, "no path after the stop"
        stale = [e for e in ends if e > 0.5 * moving]
        assert not stale, f"{len(stale)} path(s) predict the chair still driving: {ends}"
        if step:
            assert h.node.predictor.stats.resets >= 1
            assert "stepped back" in h.node.predictor.last_reset_detail
    finally:
        h.close()


def _drive_with_a_lead(h: Harness, t_from: float, t_to: float, joy_lead: float,
                       joy_until: float) -> None:
    for i in range(round((t_to - t_from) / 0.1)):
        t = t_from + 0.1 * (i + 1)
        h.clock(t)
        if t <= joy_until + 1e-9:
            h.joy(t + joy_lead, 0.5 + 0.3 * math.sin(t), 0.4 * math.cos(0.5 * t))
        if i % 2 == 1:
            h.clock(t + 0.03)
            h.vo(t + 0.03, 0.45 + 0.25 * math.sin(t - 0.3), 0.3 * math.cos(0.5 * t))
        for _ in range(3):
            h.executor.spin_once(timeout_sec=0.005)


def test_a_joystick_stamped_ahead_of_the_clock_stops_the_paths_a_timeout_after_it(
        rclpy_context, model_file):
    """Stamps 0.9 s ahead of the node's clock (another machine's, unsynchronised): paths
    held the silent stick's last command for 0.9 s more than joy_timeout_s (0.5 s)."""
    h = Harness(rclpy_context, model_file, **{"adapt.enabled": False})
    try:
        _drive_with_a_lead(h, 100.0, 110.0, 0.9, 110.0)
        assert h.paths
        n = len(h.paths)
        _drive_with_a_lead(h, 110.0, 113.0, 0.9, 110.0)  # silent from 110.0 s (clock)
        late = [round(_t0(p), 2) for p in h.paths[n:]]
        assert all(t <= 110.5 + 1e-9 for t in late), late
    finally:
        h.close()


def test_a_path_reaching_past_2038_is_refused_not_a_crash(rclpy_context, model_file):
    """Inputs stamped in the last seconds a message stamp holds (int32 seconds, 2038; a
    bag's bogus stamps): a path whose last poses lie beyond it raised out of the VO callback
    and ended the node. It is refused, with the reason."""
    h = Harness(rclpy_context, model_file, **{"adapt.enabled": False, "horizon_steps": 20})
    try:
        start = conv.MAX_STAMP_S - 6.0
        h.drive(start, start + 5.5)  # every input stamped before the end, the paths not
        assert h.paths
        result = h.node._last_result
        assert result.reason == Reason.INVALID_TIME and "2038" in result.detail, result
    finally:
        h.close()


def test_the_ellipses_are_cleared_whatever_stops_the_paths(rclpy_context, model_file):
    """A frozen VO (vo_stale_repeat) stops the paths, which the watchdog's cheap status
    does not see: the last path's ellipses stayed in RViz."""
    h = Harness(rclpy_context, model_file, **{"adapt.enabled": False})
    try:
        h.drive(100.0, 102.0)
        h.spin_until(lambda: h.paths and h.markers, what="paths and ellipses")
        h.drive(102.0, 105.0, vel=lambda t: (0.42, 0.11))  # the VO frozen on one reading
        for _ in range(30):
            h.executor.spin_once(timeout_sec=0.01)
        assert h.node._last_result.reason == Reason.VO_STALE_REPEAT
        assert _t0(h.paths[-1]) < 103.0  # the paths stopped
        assert [m.action for m in h.markers[-1].markers] == [Marker.DELETEALL]
    finally:
        h.close()


def test_a_horizon_changed_at_runtime_is_the_one_adaptation_checks(rclpy_context, model_file):
    """horizon_steps set from 100 to 5 at runtime while adapting: the paths had 5 steps,
    the adaptation went on checking 100-step predictions, and checked none (its ellipses
    uncalibrated); a longer horizon set at runtime grows the buffer with it."""
    h = Harness(rclpy_context, model_file, **{"adapt.enabled": True, "horizon_steps": 100})
    try:
        assert h.node.set_parameters([Parameter("horizon_steps", value=5)])[0].successful
        assert h.node.predictor.config.horizon_steps == 5
        h.drive(100.0, 112.0)
        h.clock(h.now + 0.3)
        for _ in range(30):
            h.executor.spin_once(timeout_sec=0.01)
        values = conv.diagnostic_values(h.node.diagnostic_status())
        assert len(h.paths[-1].poses) == 5
        assert int(values["adapt_checked"]) > 0, values  # 12 s of 1 s paths
        buffer_5 = h.node.predictor.config.buffer_s
        assert h.node.set_parameters([Parameter("horizon_steps", value=150)])[0].successful
        assert h.node.predictor.config.buffer_s > buffer_5 >= h.node.params.buffer_s
        assert h.node.predictor._adapter.horizon_steps == 150
        short = h.node.set_parameters([Parameter("buffer_s", value=2.0)])[0]
        assert not short.successful and "at least" in short.reason
    finally:
        h.close()


def test_predictions_slower_than_their_period_are_a_warning(rclpy_context, model_file):
    """uncertainty 'mc' over a 40 s horizon took 950 ms a path at 5 Hz, and the diagnostics
    said OK: the paths fell behind unsaid. Predictions whose median time exceeds the time
    between paths are a WARN naming it."""
    h = Harness(rclpy_context, model_file, **{"adapt.enabled": False})
    try:
        h.drive(100.0, 103.0)
        status = h.node.diagnostic_status()
        assert status.level == DiagnosticStatus.OK, status.message
        h.node._predict_ms.extend([950.0] * 20)  # as such predictions measured
        status = h.node.diagnostic_status()
        assert status.level == DiagnosticStatus.WARN
        assert "longer than the 200 ms between paths" in status.message, status.message
    finally:
        h.close()


# ---- from an attack on the diagnostics: each a false value found, now a regression test --


def test_an_input_rate_falls_once_the_input_stops():
    """joy_rate_hz read 17.2 Hz three seconds after the last joystick message: the rate was
    taken over the span of the arrivals kept, not up to now."""
    from asgp_ros.nodes.predictor_node import _RateMeter

    meter = _RateMeter(window_s=5.0)
    for i in range(41):  # 20 Hz for 2 s
        meter.tick(100.0 + 0.05 * i)
    assert meter.rate(102.0) == pytest.approx(20.0, rel=0.03)
    assert meter.rate(105.0) < 10.0  # 3 s of silence: 40 arrivals in 5 s
    assert meter.rate(107.5) == 0.0  # all out of the window


def test_input_ages_are_the_staleness_rules(rclpy_context, model_file):
    """A joystick stamped 0.9 s ahead of the clock goes silent: the status said 'joystick
    is 0.83 s old' and joy_age_s -0.070 (its stamp's age). The ages are those the staleness
    rule counts: from the arrival of a sample stamped ahead."""
    h = Harness(rclpy_context, model_file, **{"adapt.enabled": False})
    try:
        _drive_with_a_lead(h, 100.0, 105.0, 0.9, 105.0)
        _drive_with_a_lead(h, 105.0, 105.8, 0.9, 105.0)  # silent from 105.0 s
        status = h.node.diagnostic_status()
        values = conv.diagnostic_values(status)
        assert values["reason"] == "stale_joystick"
        assert float(values["joy_age_s"]) == pytest.approx(0.8, abs=0.06), status.message
        assert f"{float(values['joy_age_s']):.2f}" in status.message
        assert 0.0 <= float(values["vo_age_s"]) <= 0.2
    finally:
        h.close()


def test_no_ellipses_and_no_coverage_claimed_without_an_uncertainty(rclpy_context,
                                                                    model_file):
    """uncertainty 'none': the node published ellipses of no size as the 95 % ellipses,
    and adapt_coverage_95 0.777 (the linear ellipses' coverage) beside them."""
    h = Harness(rclpy_context, model_file, uncertainty="none",
                **{"adapt.enabled": True, "adapt.half_life_s": 10.0})
    try:
        h.drive(100.0, 112.0)
        assert h.paths
        added = [m for arr in h.markers for m in arr.markers if m.action == Marker.ADD]
        assert not added
        values = conv.diagnostic_values(h.node.diagnostic_status())
        assert int(values["adapt_checked"]) > 0
        assert values["adapt_coverage_95"].startswith("n/a"), values["adapt_coverage_95"]
    finally:
        h.close()


def test_coverage_after_a_reset_is_not_the_old_posteriors(rclpy_context, model_file):
    """~/reset_adaptation: adapt_coverage_95 and adapt_coverage_one_step still gave the
    reset posterior's coverage (0.365 / 0.413) beside the trained model at scale 1."""
    from std_srvs.srv import Trigger

    h = Harness(rclpy_context, model_file, **{"adapt.enabled": True,
                                              "adapt.half_life_s": 10.0})
    try:
        h.drive(100.0, 112.0, vel=lambda t: (0.3 + 0.2 * math.sin(t - 0.3),
                                             0.2 * math.cos(0.5 * t)))
        before = conv.diagnostic_values(h.node.diagnostic_status())
        assert before["adapt_coverage_95"] != "nan"
        client = h.test.create_client(Trigger, "/predictor_node/reset_adaptation")
        h.spin_until(client.service_is_ready, what="reset service")
        future = client.call_async(Trigger.Request())
        h.spin_until(future.done, what="reset reply")
        assert future.result().success
        after = conv.diagnostic_values(h.node.diagnostic_status())
        assert after["adapt_coverage_95"] == after["adapt_coverage_one_step"] == "nan", after
    finally:
        h.close()


def test_a_negative_clock_message_is_refused_not_the_end_of_the_node(rclpy_context,
                                                                      model_file):
    """A /clock message of -5 s (a bag with bogus stamps played): rclpy's clock
    subscription raised inside the executor, and the node stopped."""
    from builtin_interfaces.msg import Time as TimeMsg

    h = Harness(rclpy_context, model_file, **{"adapt.enabled": False})
    try:
        h.drive(100.0, 104.0)
        n = len(h.paths)
        h.clock_pub.publish(Clock(clock=TimeMsg(sec=-5, nanosec=0)))
        for _ in range(20):
            h.executor.spin_once(timeout_sec=0.01)  # (raised ValueError here)
        assert h.node.get_clock().now().nanoseconds == round(104.03 * 1e9)
        h.drive(104.0, 106.0)
        assert len(h.paths) > n
    finally:
        h.close()
