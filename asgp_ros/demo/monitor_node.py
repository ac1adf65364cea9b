"""The demo's monitoring node: live figures, online success rate, and the run's bag.

Subscribes to what the system publishes (``joy``, ``vo/twist``, ``vo/odom``,
``ground_truth/odom``, ``predicted_path`` and its uncertainty markers, ``joy_plan``,
``diagnostics``, and ``camera/color/camera_info`` for the camera rate) and records all but
the camera info to a ROS 2 bag (mcap, with the ``rosbags`` library: the serialized
messages as received, stamped with their arrival time on the node clock, as ``ros2 bag
record`` does). A topic is subscribed once a publisher of it is discovered, with the
publisher's reliability (like rosbag2's QoS adaptation), so a reliable stream is recorded
without loss and a best-effort one is still received. The figures are computed by
:mod:`asgp_ros.demo.monitor`.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass
from io import BytesIO
from pathlib import Path
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import TwistStamped
from nav_msgs.msg import Odometry
from nav_msgs.msg import Path as PathMsg
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from rosbags.interfaces import Connection
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore
from sensor_msgs.msg import CameraInfo, Joy, LaserScan
from trajectory_msgs.msg import JointTrajectory
from visualization_msgs.msg import Marker, MarkerArray

from asgp_ros.common import topics
from asgp_ros.demo.monitor import (
    LatencyStats,
    OnlineScore,
    PathRecord,
    RateMeter,
    TruthTrack,
)
from asgp_ros.nodes import conversions as conv

log = logging.getLogger(__name__)

#: Topics the monitor records and counts without reading them (the bridge's 100 Hz
#: ``joy_applied``; with ``--shared-control`` the laser and the layer's decisions, so that a
#: contact can be traced to the decisions before it from the run's own bag).
COUNTED_ONLY = frozenset({topics.JOY_APPLIED, topics.SCAN, topics.SHARED_CONTROL_STATUS})

#: topic -> (message class, ROS 2 type name, recorded in the bag)
TOPICS: dict[str, tuple[type, str, bool]] = {
    topics.JOY: (Joy, "sensor_msgs/msg/Joy", True),
    topics.JOY_APPLIED: (Joy, "sensor_msgs/msg/Joy", True),
    topics.VO_TWIST: (TwistStamped, "geometry_msgs/msg/TwistStamped", True),
    topics.VO_ODOM: (Odometry, "nav_msgs/msg/Odometry", True),
    topics.GROUND_TRUTH: (Odometry, "nav_msgs/msg/Odometry", True),
    topics.PREDICTED_PATH: (PathMsg, "nav_msgs/msg/Path", True),
    topics.PREDICTED_PATH_UNCERTAINTY: (MarkerArray, "visualization_msgs/msg/MarkerArray", True),
    topics.JOY_PLAN: (JointTrajectory, "trajectory_msgs/msg/JointTrajectory", True),
    topics.JOY_OVERRIDE: (Joy, "sensor_msgs/msg/Joy", True),
    topics.DIAGNOSTICS: (DiagnosticArray, "diagnostic_msgs/msg/DiagnosticArray", True),
    topics.SCAN: (LaserScan, "sensor_msgs/msg/LaserScan", True),
    topics.SHARED_CONTROL_STATUS: (DiagnosticStatus, "diagnostic_msgs/msg/DiagnosticStatus",
                                   True),
    topics.CAMERA_INFO: (CameraInfo, "sensor_msgs/msg/CameraInfo", False),
}


class BagRecorder:
    """Serialized messages into a ROS 2 bag (mcap) at ``path``; see ``close``.

    A write that fails (a full disk: the rosbags writer raised in the monitor's callback,
    which aborted the demo with the bag unclosed and no report) stops the recording instead:
    ``failure`` says why, ``failed_ns`` when, and the bag is closed as it was after its last
    chunk on disk (the chunk being written, a second or so, is dropped from the file, which
    frees what it took for the bag's index and metadata). Should that close fail too,
    ``closed`` is False: the file keeps every chunk written, readable by a scan (``asgp bag
    repair`` writes a clean copy). Later messages are counted in ``dropped``.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._store = get_typestore(Stores.ROS2_JAZZY)
        self._writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        try:
            self._writer.open()
            storage: Any = self._writer.storage
            storage.bio.flush()  # (its header: the point a failure cuts back to at most)
        except OSError as exc:
            raise OSError(exc.errno, exc.strerror or str(exc),
                          os.fspath(exc.filename or self.file)) from exc
        self._conns: dict[str, Connection] = {}
        self.messages = 0  # recorded (after a failure: those the bag keeps)
        self.failure = ""  # why the recording stopped ("": it did not)
        self.cause = ""  # the same without the file's name
        self.failed_ns: int | None = None
        self.failed_closing = False  # the failure was the close's (the last chunk's write)
        self.closed = False
        self.close_problem = ""  # why a failed recording could not be closed
        self.dropped = 0
        self.kept_ns: tuple[int, int] | None = None  # first and last stamp the bag keeps
        self._chunks = 0
        self._saved = self._snapshot()

    @property
    def file(self) -> Path:
        """The bag's storage file."""
        return self.path / f"{self.path.name}.mcap"

    def add_topic(self, topic: str, msgtype: str) -> None:
        if topic not in self._conns and not self.failure:
            self._conns[topic] = self._writer.add_connection(topic, msgtype,
                                                             typestore=self._store)

    def write(self, topic: str, stamp_ns: int, data: bytes) -> None:
        if self.failure:
            self.dropped += 1
            return
        try:
            self._writer.write(self._conns[topic], stamp_ns, data)
            self.messages += 1
            storage: Any = self._writer.storage  # (the mcap storage's chunks and file)
            if storage is not None and len(storage.chunks) != self._chunks:
                storage.bio.flush()  # the chunk is in the file: a failure keeps it
                self._chunks = len(storage.chunks)
                self._saved = self._snapshot()
        except OSError as exc:
            self._fail(exc, stamp_ns)

    def close(self) -> None:
        """Close the bag (after a failure: nothing more to do); never raises OSError, a
        failure of the close is one of the recording (``failure``)."""
        if self.closed or self.failure:
            return
        try:
            self._writer.close()
        except OSError as exc:
            self.failed_closing = True
            self._fail(exc, self._writer.max_timestamp)
        else:
            self.closed = True
            if self.messages:
                self.kept_ns = (self._writer.min_timestamp, self._writer.max_timestamp)

    def _snapshot(self) -> dict[str, Any]:
        """What the bag holds up to its last chunk on disk (restored by ``_fail``)."""
        w = self._writer
        storage: Any = w.storage
        return {"messages": self.messages, "counts": dict(w.counts),
                "min": w.min_timestamp, "max": w.max_timestamp,
                "end": storage.bio.tell() if storage is not None else 0,
                "stats": dict(storage.channel_stats) if storage is not None else {},
                "start_end": ((storage.message_start_time, storage.message_end_time)
                              if storage is not None else (0, 0))}

    def _fail(self, exc: OSError, stamp_ns: int) -> None:
        """Stop recording: the bag cut back to its last chunk on disk and closed."""
        self.cause = str(exc.strerror or exc)
        self.failure = f"cannot write {exc.filename or self.file}: {self.cause}"
        self.failed_ns = stamp_ns
        saved = self._saved
        self.messages = saved["messages"]
        if self.messages:
            self.kept_ns = (saved["min"], saved["max"])
        storage: Any = self._writer.storage
        if storage is None:  # the storage file was complete: its metadata.yaml failed
            self.close_problem = f"its metadata.yaml: {exc.strerror or exc}"
            return
        try:
            with contextlib.suppress(OSError):  # (what it still holds is cut off below)
                storage.bio.close()
            os.truncate(storage.path, saved["end"])  # frees the part-written chunk
            storage.bio = open(storage.path, "r+b")  # noqa: SIM115 (the writer closes it)
            storage.bio.seek(saved["end"])
            # what was in the dropped chunk is forgotten: the index and metadata.yaml
            # count what the file holds
            del storage.chunks[self._chunks:]
            storage.chunk = type(storage.chunk)(2**63 - 1, 0, BytesIO(), defaultdict(list))
            storage.channel_stats = {c: saved["stats"].get(c, 0) for c in storage.channel_stats}
            storage.message_start_time, storage.message_end_time = saved["start_end"]
            w = self._writer
            w.counts = {c: saved["counts"].get(c, 0) for c in w.counts}
            w.min_timestamp, w.max_timestamp = saved["min"], saved["max"]
            w.close()
        except OSError as err:
            self.close_problem = f"{err.filename or self.file}: {err.strerror or err}"
        else:
            self.closed = True


@dataclass
class DiagEntry:
    level: int
    message: str
    values: dict[str, str]
    arrival: float


class MonitorNode(Node):
    """See the module docstring.

    Args:
        recorder: where to record (None: nothing recorded).
        horizons_s, threshold_m: the online score's settings.
    """

    def __init__(self, recorder: BagRecorder | None = None,
                 score: OnlineScore | None = None, **kwargs: Any) -> None:
        super().__init__("demo_monitor", **kwargs)
        self.recorder = recorder
        self.score = score or OnlineScore()
        self.truth = TruthTrack()
        self.rates = {name: RateMeter() for name in TOPICS}
        self.latency = {name: LatencyStats() for name in (topics.JOY, topics.VO_TWIST,
                                                          topics.PREDICTED_PATH)}
        self.counts = dict.fromkeys(TOPICS, 0)
        self.diag: dict[str, DiagEntry] = {}
        self.overrides: list[float] = []  # stamps of the shared-control layer's overrides
        self.vo_ok: bool | None = None
        self.vo_lost = 0
        self.first_truth_wall: float | None = None
        self._by_t0: dict[int, PathRecord] = {}
        self._subscribed: set[str] = set()
        self.create_timer(0.2, self._discover)
        self._discover()

    # ---- subscriptions following discovery ---------------------------------------------

    def _discover(self) -> None:
        for topic, (cls, msgtype, record) in TOPICS.items():
            if topic in self._subscribed:
                continue
            infos = self.get_publishers_info_by_topic(self.resolve_topic_name(topic))
            if not infos:
                continue
            reliable = all(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE
                           for i in infos)
            qos = QoSProfile(
                history=HistoryPolicy.KEEP_LAST, depth=200,
                reliability=(ReliabilityPolicy.RELIABLE if reliable
                             else ReliabilityPolicy.BEST_EFFORT),
                durability=DurabilityPolicy.VOLATILE)
            if record and self.recorder is not None:
                self.recorder.add_topic(topics.in_bag(topic), msgtype)
            self.create_subscription(cls, topic, self._callback(topic, cls, record), qos,
                                     raw=True)
            self._subscribed.add(topic)
            log.debug("monitor subscribed %s (%s)", topic,
                      "reliable" if reliable else "best effort")

    def _callback(self, topic: str, cls: type, record: bool) -> Callable[[bytes], None]:
        # a topic recorded and counted only is never deserialised; every other has a handler
        handler = (None if topic in COUNTED_ONLY
                   else getattr(self, "_on_" + topic.strip("/").replace("/", "_")))
        bag_topic = topics.in_bag(topic)

        def on_message(data: bytes) -> None:
            now_ns = self.get_clock().now().nanoseconds
            if record and self.recorder is not None:
                self.recorder.write(bag_topic, now_ns, data)
            self.counts[topic] += 1
            self.rates[topic].tick(time.monotonic())
            if handler is not None:
                handler(deserialize_message(data, cls), now_ns * 1e-9)

        return on_message

    # ---- handlers ----------------------------------------------------------------------

    def _on_joy(self, msg: Joy, now: float) -> None:
        self.latency[topics.JOY].add(now - conv.stamp_to_seconds(msg.header.stamp))

    def _on_vo_twist(self, msg: TwistStamped, now: float) -> None:
        self.latency[topics.VO_TWIST].add(now - conv.stamp_to_seconds(msg.header.stamp))

    def _on_vo_odom(self, msg: Odometry, now: float) -> None:
        _, _, ok, _ = conv.odometry_to_sample(msg)
        self.vo_ok = ok
        self.vo_lost += not ok

    def _on_ground_truth_odom(self, msg: Odometry, now: float) -> None:
        t, _, _, (x, y, yaw) = conv.odometry_to_sample(msg)
        if self.first_truth_wall is None:
            self.first_truth_wall = time.monotonic()
        self.truth.add(t, x, y, yaw)
        self.score.update(self.truth)

    def _on_predicted_path(self, msg: PathMsg, now: float) -> None:
        t0 = conv.stamp_to_seconds(msg.header.stamp)
        times, poses = conv.path_to_poses(msg)
        if times.size == 0:
            return
        rec = PathRecord(t0=t0, times=times, pose=poses, arrival=now)
        self.latency[topics.PREDICTED_PATH].add(now - t0)
        self.score.add(rec)
        self._by_t0[round(t0 * 1e6)] = rec
        if len(self._by_t0) > 50:
            self._by_t0.pop(next(iter(self._by_t0)))

    def _on_predicted_path_uncertainty(self, msg: MarkerArray, now: float) -> None:
        first = next((m for m in msg.markers if m.action == Marker.ADD), None)
        if first is None:  # only the DELETEALL: predictions stopped
            return
        rec = self._by_t0.get(round(conv.stamp_to_seconds(first.header.stamp) * 1e6))
        if rec is None:
            return
        rec.ellipses = conv.ellipses_from_markers(msg)

    def _on_joy_override(self, msg: Joy, now: float) -> None:
        self.overrides.append(conv.stamp_to_seconds(msg.header.stamp))

    def _on_joy_plan(self, msg: JointTrajectory, now: float) -> None:
        pass

    def _on_diagnostics(self, msg: DiagnosticArray, now: float) -> None:
        for st in msg.status:
            self.diag[st.name] = DiagEntry(int.from_bytes(st.level, "little")
                                           if isinstance(st.level, bytes) else int(st.level),
                                           st.message, conv.diagnostic_values(st), now)

    def _on_camera_color_camera_info(self, msg: CameraInfo, now: float) -> None:
        pass

    # ---- summaries ---------------------------------------------------------------------

    def rate(self, topic: str) -> float:
        return self.rates[topic].rate(time.monotonic())

    def diag_value(self, name_part: str, key: str) -> str | None:
        """A value of the newest diagnostic status whose name contains ``name_part``."""
        for name, entry in self.diag.items():
            if name_part in name and key in entry.values:
                return entry.values[key]
        return None
