"""Soak test: the bridge, the VO and the predictor for a long run with faults injected.

    .venv/bin/python benchmarks/soak.py [--minutes 30] [--out soak-output] [--model M.npz]
        [--shared-control [--inattention 0.1]]

Not part of ``make test``. The three real nodes run as separate processes, started and
stopped by the demo's process management (:mod:`asgp_ros.demo.processes`, each through
:mod:`asgp_ros.demo.child`), on a ROS domain of their own (localhost, UDPv4):

* ``serial_bridge_node`` on the simulated joystick board's pty;
* ``vo_node`` on the rendered RGB-D camera;
* ``predictor_node`` on a model trained as ``asgp demo`` trains it (unless ``--model``),
  with ``diagnostics_period_s`` 0.2 s so that its own latency figure is read after
  nearly every prediction;

with ``--shared-control`` also ``shared_control_node`` on the hardware's simulated scanner
(the driver inattentive, ``--inattention``, so that it intervenes through the bridge);
and a further process, the demo's simulated hardware (:mod:`asgp_ros.demo.hardware`:
driver, board on a pty, chair, camera, joy_plan) extended here by the faults
(:class:`SoakHardwareNode`), which it applies when this script asks on ``soak/fault``
and acknowledges on ``soak/fault_ack``.

Time: the hardware paces its closed loop against the wall clock (the demo machinery has no
faster-than-real-time mode: the board thread samples at 100 Hz of real time and the nodes
stamp with the system clock), so simulated time is real time and ``--minutes`` is both.

Faults, every ``--cycle-s`` (120 s) after a warm-up (min(60 s, 15 % of the run)), at these
offsets into the cycle:

====== ===================================================================================
  0 s  board unplugged (pty closed, the port's symlink removed); replugged at 5 s
 15 s  camera blackout: every frame dropped for 3 s
 25 s  camera frames dropped at random, half of them, for 10 s
 40 s  camera frozen: the same image (new stamps) for 5 s
 55 s  clock jump: every stamp of the hardware (camera, plan, truth) 3 s ahead, back at 60 s
 70 s  clock jump: 3 s behind, forward again at 75 s
 85 s  10x traffic for 12 s: joy at 10x the bridge's 100 Hz (an extra publisher), each
       camera frame and each joy_plan published 10 times
 90 s  SIGINT to one node in the middle of that burst (cycles 1, 2, 3: predictor, VO,
       bridge; cycle 4 with --shared-control: the layer; the middle cycle of a run of
       more than 6 cycles: predictor again), restarted as soon as it has exited
====== ===================================================================================

The run ends in a last burst: SIGINT to every node 4 s into it.

Report (printed, and ``OUT/soak.json``; the node logs in ``OUT/logs``): per time window
the predictor's latency p99 (its own timing, VO callback to publication, from its
diagnostics) and the end-to-end p99 (path arrival here minus the path's t0 stamp), the
paths published and the RSS of every process (VmRSS from /proc/PID/status, sampled every
``--rss-period`` s); the RSS growth of every process (median of the last quarter of its
samples after warm-up against the first quarter, in %); each fault's effect (paths during
it, how long after its end paths resumed); every shutdown (SIGINT to exit); every
exception, traceback and error line in any process's output. The last line compares with
the targets: RSS flat within 5 %, no exception, every shutdown under 2 s.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import rclpy  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from geometry_msgs.msg import TwistStamped  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from nav_msgs.msg import Path as PathMsg  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data  # noqa: E402
from rclpy.signals import SignalHandlerOptions  # noqa: E402
from sensor_msgs.msg import CameraInfo, Joy  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from asgp_ros.common import topics  # noqa: E402
from asgp_ros.core.quaternion import quaternion_to_yaw  # noqa: E402
from asgp_ros.demo import camera, hardware  # noqa: E402
from asgp_ros.demo.hardware import NODE_NAME, HardwareNode  # noqa: E402
from asgp_ros.demo.orchestrator import (  # noqa: E402
    DemoOptions,
    child_env,
    node_commands,
    train_model,
)
from asgp_ros.demo.processes import Child, ProcessGroup, proc_cpu_seconds  # noqa: E402
from asgp_ros.demo.report import ADAPT_KEYS  # noqa: E402
from asgp_ros.demo.simhw import STEP_S  # noqa: E402
from asgp_ros.nodes import conversions as conv  # noqa: E402

FAULT_TOPIC = "soak/fault"
ACK_TOPIC = "soak/fault_ack"
BURST_FRAME = "soak_burst"  #: frame_id of the extra joy messages of a burst
NODES = ("serial_bridge", "vo", "predictor")  #: the nodes under test (names of the demo)
HARNESS = "hardware"
TARGET_RSS_PCT = 5.0
TARGET_SHUTDOWN_S = 2.0
RELIABLE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)


# =============================================================== the hardware with faults

class SoakHardwareNode(HardwareNode):
    """The demo's simulated hardware, with the faults of the soak (module docstring).

    Commands arrive as JSON on ``soak/fault``: ``{"id", "kind", ...}`` with kind
    ``unplug``, ``replug``, ``drop`` (``p``: share of frames dropped, ``s``: duration),
    ``freeze`` (``s``), ``jump`` (``offset``: seconds added to every stamp from now on),
    ``burst`` (``factor``, ``s``). Each is acknowledged on ``soak/fault_ack`` with the
    same id, ``ok`` and, when it failed, ``error``.
    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self._rng = np.random.default_rng(self.params.seed + 7919)
        self._drop_p = 0.0
        self._drop_until = 0.0
        self._freeze_until = 0.0
        self._frozen: tuple[Any, Any] | None = None
        self._offset = 0.0
        self._burst_until = 0.0
        self._burst_factor = 1
        self._burst_credit = 0.0
        self._burst_last = 0.0
        self.soak_counts = {"frames_dropped": 0, "frames_frozen": 0, "burst_joy": 0,
                            "burst_frames": 0, "burst_plans": 0}
        self._ack_pub = self.create_publisher(String, ACK_TOPIC, RELIABLE)
        # a second publisher of joy only while a burst lasts: the bridge refuses overrides
        # while one is on the graph (two chairs on one domain), so it was refused all run
        self._burst_joy_pub: Any = None
        self.create_subscription(String, FAULT_TOPIC, self._on_fault, RELIABLE)
        self.create_timer(0.01, self._on_burst_tick)

    # ---- commands ----------------------------------------------------------------------

    def _on_fault(self, msg: String) -> None:
        cmd = json.loads(msg.data)
        now = time.monotonic()
        ack: dict[str, Any] = {"id": cmd.get("id"), "kind": cmd.get("kind"), "ok": True}
        try:
            kind = cmd["kind"]
            board = self.hw.board
            if kind == "unplug":
                assert board is not None
                board.unplug()
            elif kind == "replug":
                assert board is not None
                board.replug()
            elif kind == "drop":
                self._drop_p, self._drop_until = float(cmd["p"]), now + float(cmd["s"])
            elif kind == "freeze":
                self._freeze_until, self._frozen = now + float(cmd["s"]), None
            elif kind == "jump":
                self._offset = float(cmd["offset"])
            elif kind == "burst":
                if self._burst_joy_pub is None:
                    self._burst_joy_pub = self.create_publisher(Joy, topics.JOY,
                                                                qos_profile_sensor_data)
                self._burst_factor = int(cmd["factor"])
                self._burst_until = now + float(cmd["s"])
                self._burst_last, self._burst_credit = now, 0.0
            else:
                raise ValueError(f"unknown fault {kind!r}")
        except Exception as exc:  # reported to the soak, which lists it
            ack.update(ok=False, error=f"{type(exc).__name__}: {exc}")
        ack["counts"] = dict(self.soak_counts)
        self._ack_pub.publish(String(data=json.dumps(ack)))

    # ---- what the faults change --------------------------------------------------------

    def _stamp(self, t: float) -> float:
        return super()._stamp(t) + self._offset

    def _copies(self) -> int:
        return self._burst_factor if time.monotonic() < self._burst_until else 1

    def _on_camera(self) -> None:  # HardwareNode._on_camera with drops, freezes, bursts
        if self._t_start is None:
            return
        state = self.hw.state
        if state.t <= self._last_frame_t:
            return
        self._last_frame_t = state.t
        now = time.monotonic()
        if now < self._drop_until and self._rng.random() < self._drop_p:
            self.soak_counts["frames_dropped"] += 1
            return
        freezing = now < self._freeze_until
        if freezing and self._frozen is not None:
            image, depth = self._frozen
            self.soak_counts["frames_frozen"] += 1
        else:
            start = time.perf_counter()
            image, depth = self.hw.render(state)
            self.render_time.add(time.perf_counter() - start)
            self._frozen = (image, depth) if freezing else None
        if not self.context.ok():
            return
        t = self._stamp(round(state.t / STEP_S) * STEP_S)
        frame = self.params.camera_frame
        msgs = (camera.image_from_array(t, image, frame),
                camera.image_from_array(t, depth, frame),
                camera.camera_info_from_matrix(t, self.hw.renderer.K, image.shape[1],
                                               image.shape[0], frame))
        copies = self._copies()
        for _ in range(copies):
            self.color_pub.publish(msgs[0])
            self.depth_pub.publish(msgs[1])
            self.info_pub.publish(msgs[2])
        self.soak_counts["burst_frames"] += copies - 1
        self.frames += 1

    def _publish_plan(self) -> None:  # HardwareNode's plan, repeated in a burst
        msg = self._plan_message()
        if msg is None:
            return
        copies = self._copies()
        for _ in range(copies):
            self.plan_pub.publish(msg)
        self.soak_counts["burst_plans"] += copies - 1
        self.plans += 1

    def _on_burst_tick(self) -> None:
        """The extra joy of a burst: (factor - 1) x the bridge's 100 Hz, stamped now."""
        now = time.monotonic()
        if self._burst_joy_pub is not None and now >= self._burst_until + 1.0:
            self.destroy_publisher(self._burst_joy_pub)  # (a second after, its last gone)
            self._burst_joy_pub = None
        if self._t_start is None or now >= self._burst_until or self._burst_joy_pub is None:
            return
        self._burst_credit += 100.0 * (self._burst_factor - 1) * (now - self._burst_last)
        self._burst_last = now
        n = min(int(self._burst_credit), 100)
        self._burst_credit -= int(self._burst_credit)
        if n <= 0:
            return
        fwd, turn = self.hw.path.reported(self.hw.command)
        msg = conv.joy_from_sample(self.get_clock().now().nanoseconds * 1e-9, fwd, turn,
                                   BURST_FRAME)
        for _ in range(n):
            if not self.context.ok():  # a SIGINT mid-burst
                return
            self._burst_joy_pub.publish(msg)
            self.soak_counts["burst_joy"] += 1


def hardware_main() -> int:
    """The soak's hardware process: :func:`asgp_ros.demo.hardware.main` with the faults."""
    return hardware.main(node_class=SoakHardwareNode)


# ============================================================================ schedule

@dataclass
class Action:
    t: float                 # seconds after the start of the soak
    kind: str                # "fault" (to the hardware), "sigint" (one node), "final"
    label: str
    payload: dict[str, Any] = field(default_factory=dict)


@dataclass
class Episode:
    """A fault from its start to its end (for its effect on the paths)."""

    label: str
    start: float
    end: float


def build_schedule(total_s: float, warmup_s: float, cycle_s: float, burst_factor: int,
                   shared_control: bool = False) -> tuple[list[Action], list[Episode]]:
    """The faults of a run of ``total_s`` seconds (module docstring); with
    ``shared_control`` the fourth cycle's SIGINT goes to the shared-control layer."""
    actions: list[Action] = []
    episodes: list[Episode] = []

    def fault(t: float, label: str, **payload: Any) -> None:
        actions.append(Action(t, "fault", label, payload))

    final_burst = total_s - 8.0
    starts = []
    c = warmup_s
    while c + 100.0 <= final_burst - 5.0:
        starts.append(c)
        c += cycle_s
    targets = {0: "predictor", 1: "vo", 2: "serial_bridge"}
    if shared_control:
        targets[3] = "shared_control"
    if len(starts) > 6:
        targets[len(starts) // 2] = "predictor"
    for i, c in enumerate(starts):
        fault(c, "board unplugged", kind="unplug")
        fault(c + 5.0, "board replugged", kind="replug")
        episodes.append(Episode(f"#{i + 1} board unplugged 5 s", c, c + 5.0))
        fault(c + 15.0, "camera blackout 3 s", kind="drop", p=1.0, s=3.0)
        episodes.append(Episode(f"#{i + 1} camera blackout 3 s", c + 15.0, c + 18.0))
        fault(c + 25.0, "camera drops 50 % for 10 s", kind="drop", p=0.5, s=10.0)
        episodes.append(Episode(f"#{i + 1} camera drops 50 % 10 s", c + 25.0, c + 35.0))
        fault(c + 40.0, "camera frozen 5 s", kind="freeze", s=5.0)
        episodes.append(Episode(f"#{i + 1} camera frozen 5 s", c + 40.0, c + 45.0))
        fault(c + 55.0, "stamps jump +3 s", kind="jump", offset=3.0)
        fault(c + 60.0, "stamps jump back to 0", kind="jump", offset=0.0)
        episodes.append(Episode(f"#{i + 1} stamps +3 s for 5 s", c + 55.0, c + 60.0))
        fault(c + 70.0, "stamps jump -3 s", kind="jump", offset=-3.0)
        fault(c + 75.0, "stamps jump forward to 0", kind="jump", offset=0.0)
        episodes.append(Episode(f"#{i + 1} stamps -3 s for 5 s", c + 70.0, c + 75.0))
        fault(c + 85.0, f"{burst_factor}x traffic 12 s", kind="burst", factor=burst_factor,
              s=12.0)
        target = targets.get(i)
        label = f"#{i + 1} {burst_factor}x traffic 12 s"
        if target is not None:
            actions.append(Action(c + 90.0, "sigint", f"SIGINT {target} mid-burst",
                                  {"node": target}))
            label += f", SIGINT {target}"
        episodes.append(Episode(label, c + 85.0, c + 97.0))
    fault(final_burst, f"final {burst_factor}x traffic", kind="burst", factor=burst_factor,
          s=12.0)
    actions.append(Action(total_s - 4.0, "final", "SIGINT to every node mid-burst"))
    actions.sort(key=lambda a: a.t)
    return actions, episodes


# ============================================================================= monitor

@dataclass
class LatencySample:
    t: float          # soak time of the diagnostics message
    paths: int        # the predictor's paths_published then
    own_ms: float     # its last_latency_ms


class SoakMonitor(Node):
    """What the soak watches: paths, diagnostics, joy, twists, the hardware's acks."""

    def __init__(self, t0: float, **kwargs: Any) -> None:
        super().__init__("soak_monitor", **kwargs)
        self.t0 = t0  # time.monotonic() of soak time 0 (moved when the soak starts)
        self.fault_pub = self.create_publisher(String, FAULT_TOPIC, RELIABLE)
        self.create_subscription(String, ACK_TOPIC, self._on_ack, RELIABLE)
        self.create_subscription(PathMsg, topics.PREDICTED_PATH, self._on_path, RELIABLE)
        self.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self._on_diag, RELIABLE)
        self.create_subscription(Joy, topics.JOY, self._on_joy, qos_profile_sensor_data,
                                 raw=True)
        self.create_subscription(TwistStamped, topics.VO_TWIST, self._on_twist,
                                 qos_profile_sensor_data, raw=True)
        self.create_subscription(CameraInfo, topics.CAMERA_INFO, self._on_info,
                                 qos_profile_sensor_data, raw=True)
        self.create_subscription(DiagnosticStatus, topics.SHARED_CONTROL_STATUS,
                                 self._on_layer_status, RELIABLE)
        self.layer_status: list[float] = []  # soak times of the layer's status messages
        self.layer_why: list[tuple[float, str]] = []  # (soak time, why) when it changes
        self.create_subscription(Odometry, topics.GROUND_TRUTH, self._on_truth, RELIABLE)
        self.poses: list[tuple[float, float, float, float]] = []  # (t, x, y, yaw) at 2 Hz
        self.joy_per_s: dict[int, int] = {}  # soak second -> joy messages received
        self.frames_per_s: dict[int, int] = {}  # soak second -> camera_info received
        self.paths: list[tuple[float, float]] = []  # (soak time, arrival - t0 stamp)
        self.bridge_joy: list[float] = []  # soak times of the bridge's joy (thinned)
        self.twists: list[float] = []
        self.joy_count = 0
        self.burst_joy_count = 0
        self.latency: list[LatencySample] = []
        self.diag: dict[str, dict[str, str]] = {}
        self.acks: dict[int, dict[str, Any]] = {}
        self.max_hw_lag_s = 0.0
        self.reasons: dict[str, int] = {}
        self.reason_changes: list[tuple[float, str]] = []  # (soak time, predictor reason)
        self._last_paths = -1
        self._last_joy = -1.0
        self._next_id = 0

    def now(self) -> float:
        return time.monotonic() - self.t0

    def send_fault(self, payload: dict[str, Any]) -> int:
        self._next_id += 1
        self.fault_pub.publish(String(data=json.dumps({"id": self._next_id, **payload})))
        return self._next_id

    def _on_ack(self, msg: String) -> None:
        ack = json.loads(msg.data)
        ack["t"] = self.now()
        self.acks[int(ack["id"])] = ack

    def _on_path(self, msg: PathMsg) -> None:
        now = self.get_clock().now().nanoseconds * 1e-9
        self.paths.append((self.now(), now - conv.stamp_to_seconds(msg.header.stamp)))

    def _on_info(self, _data: bytes) -> None:
        second = math.floor(self.now())
        self.frames_per_s[second] = self.frames_per_s.get(second, 0) + 1

    def _on_joy(self, data: bytes) -> None:
        self.joy_count += 1
        second = math.floor(self.now())
        self.joy_per_s[second] = self.joy_per_s.get(second, 0) + 1
        if BURST_FRAME.encode() in data:
            self.burst_joy_count += 1
            return
        t = self.now()
        if t - self._last_joy >= 0.05:  # 20 Hz is enough to see gaps
            self._last_joy = t
            self.bridge_joy.append(t)

    def _on_twist(self, _data: bytes) -> None:
        self.twists.append(self.now())

    def _on_layer_status(self, msg: DiagnosticStatus) -> None:
        t = self.now()
        self.layer_status.append(t)
        why = conv.diagnostic_values(msg).get("why", "?")
        if not self.layer_why or self.layer_why[-1][1] != why:
            self.layer_why.append((t, why))

    def _on_truth(self, msg: Odometry) -> None:
        t = self.now()
        if self.poses and t - self.poses[-1][0] < 0.5:
            return
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        yaw = float(quaternion_to_yaw(q.x, q.y, q.z, q.w))
        self.poses.append((t, float(p.x), float(p.y), yaw))

    def _on_diag(self, msg: DiagnosticArray) -> None:
        t = self.now()
        for st in msg.status:
            values = conv.diagnostic_values(st)
            values["_message"] = st.message
            self.diag[st.name] = values
            if "predictor_node" in st.name:
                reason = values.get("reason", "?")
                self.reasons[reason] = self.reasons.get(reason, 0) + 1
                if not self.reason_changes or self.reason_changes[-1][1] != reason:
                    self.reason_changes.append((t, reason))
                try:
                    paths = int(values.get("paths_published", "-1"))
                    lat = float(values.get("last_latency_ms", "nan"))
                except ValueError:
                    continue
                if paths < self._last_paths:  # a restarted predictor counts from 0
                    self._last_paths = -1
                if paths > self._last_paths and math.isfinite(lat):
                    self.latency.append(LatencySample(t, paths, lat))
                self._last_paths = paths
            elif NODE_NAME in st.name:
                with contextlib.suppress(ValueError):
                    self.max_hw_lag_s = max(self.max_hw_lag_s, float(values.get("lag_s", 0)))


# ============================================================================ analysis

def read_rss_kb(pid: int) -> int | None:
    """VmRSS of a process in kB (None if gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return None


def rss_growth(samples: list[tuple[float, int]], warmup_until: float, min_span_s: float
               ) -> tuple[float, float, float] | None:
    """(first-quarter median kB, last-quarter median kB, growth %) of the samples taken
    after ``warmup_until``; None when they span less than ``min_span_s`` or are fewer
    than 8."""
    after = [(t, r) for t, r in samples if t >= warmup_until]
    if len(after) < 8 or after[-1][0] - after[0][0] < min_span_s:
        return None
    q = len(after) // 4
    first = float(np.median([r for _, r in after[:q]]))
    last = float(np.median([r for _, r in after[-q:]]))
    return first, last, 100.0 * (last - first) / first


_TRACEBACK = "Traceback (most recent call last):"
_EXC_NAME = re.compile(r"\b[A-Z][A-Za-z0-9_]*(?:Error|Exception|Warning)\b")
_ROS_STAMP = re.compile(r"\[\d+\.\d+\]")
#: ERROR lines that are the nodes' reaction to a fault the soak makes: a burst's second
#: publisher of joy makes the bridge refuse overrides while it lasts (two chairs on one
#: domain look the same).
_EXPECTED = ("overrides refused: 1 other publisher(s) of /joy",)
_CRASH = ("Segmentation fault", "core dumped", "terminate called", "Fatal Python error",
          "Aborted")


@dataclass
class Finding:
    process: str
    kind: str      # "traceback", "error log", "crash", "warning" (not counted)
    text: str
    line: int
    count: int = 1

    @property
    def counted(self) -> bool:
        return self.kind != "warning"


def scan_log(process: str, text: str) -> list[Finding]:
    """Tracebacks, ERROR/FATAL log lines and crash messages of a process's output;
    warnings that name an exception are listed too (``kind`` "warning"). Repeats of the
    same text (ROS timestamps ignored) are counted, not listed again."""
    lines = text.splitlines()
    found: dict[tuple[str, str], Finding] = {}

    def add(kind: str, body: str, lineno: int) -> None:
        key = (kind, _ROS_STAMP.sub("[t]", body).strip())
        if key in found:
            found[key].count += 1
        else:
            found[key] = Finding(process, kind, key[1], lineno)

    i = 0
    while i < len(lines):
        line = lines[i]
        if _TRACEBACK in line:
            j = i + 1
            frames = []
            while j < len(lines) and (lines[j].startswith((" ", "\t")) or not lines[j]):
                if lines[j].strip().startswith("File "):
                    frames.append(lines[j].strip())
                j += 1
            last = lines[j] if j < len(lines) else "(output ends inside the traceback)"
            where = frames[-1] if frames else ""
            add("traceback", f"{last.strip()}  <- {where}", i + 1)
            i = j + 1
            continue
        if any(e in line for e in _EXPECTED):
            add("warning", line, i + 1)  # (the reaction a fault asks for: listed, not counted)
        elif "[ERROR]" in line or "[FATAL]" in line:
            add("error log", line, i + 1)
        elif any(c in line for c in _CRASH):
            add("crash", line, i + 1)
        elif _EXC_NAME.search(line):
            add("warning", line, i + 1)
        i += 1
    return list(found.values())


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


# ============================================================================== the run

@dataclass
class Incarnation:
    role: str
    child: Child
    started: float                    # soak time
    rss: list[tuple[float, int]] = field(default_factory=list)  # (soak time, kB)
    cpu: list[tuple[float, float]] = field(default_factory=list)  # (soak time, CPU s)


@dataclass
class Shutdown:
    name: str
    context: str
    t: float
    seconds: float | None
    signal: str
    returncode: int | None


class Soak:
    """One soak run (module docstring)."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.total = 60.0 * args.minutes
        self.warmup = min(60.0, 0.15 * self.total)
        self.out = Path(args.out)
        self.actions, self.episodes = build_schedule(self.total, self.warmup, args.cycle_s,
                                                     args.burst_factor, args.shared_control)
        self.nodes = NODES + (("shared_control",) if args.shared_control else ())
        self.incarnations: list[Incarnation] = []
        self.current: dict[str, Incarnation] = {}
        self.shutdowns: list[Shutdown] = []
        self.stopping: dict[str, tuple[Incarnation, str, str]] = {}  # role -> (inc, ctx, sig)
        self.unexpected: list[str] = []
        self.soak_errors: list[str] = []
        self.fault_log: list[tuple[float, str, int | None]] = []
        self.restarts: list[tuple[str, float, float | None]] = []  # (name, t, first output)
        self.dumped: set[str] = set()
        self.load: list[tuple[float, float]] = []  # (soak time, 1-min load average)
        self.t0 = time.monotonic()

    # ---- processes ---------------------------------------------------------------------

    def say(self, text: str) -> None:
        t = time.monotonic() - self.t0
        print(f"[soak {t:7.1f} s] {text}", flush=True)

    def start(self, role: str) -> Incarnation:
        n = sum(1 for inc in self.incarnations if inc.role == role)
        name = role if n == 0 else f"{role}.{n + 1}"
        entry, argv = self.commands[role]
        child = self.group.start(name, entry, argv)
        inc = Incarnation(role, child, time.monotonic() - self.t0)
        self.incarnations.append(inc)
        self.current[role] = inc
        return inc

    def sample_rss(self) -> None:
        t = time.monotonic() - self.t0
        for inc in self.current.values():
            if inc.child.returncode is None:
                kb = read_rss_kb(inc.child.pid)
                cpu = proc_cpu_seconds(inc.child.pid)
                if kb is not None:
                    inc.rss.append((t, kb))
                if cpu is not None:
                    inc.cpu.append((t, cpu))
        with contextlib.suppress(OSError, ValueError, IndexError):
            self.load.append((t, float(Path("/proc/loadavg").read_text().split()[0])))

    def interrupt(self, role: str, context: str) -> None:
        inc = self.current[role]
        if role in self.stopping or inc.child.returncode is not None:
            self.soak_errors.append(f"{context}: {role} was not running")
            return
        self.group.send(inc.child, signal.SIGINT)
        self.stopping[role] = (inc, context, "SIGINT")
        self.say(f"SIGINT to {inc.child.name} (pid {inc.child.pid}): {context}")

    def watch_stops(self, restart: bool) -> None:
        """Collect the nodes being stopped, escalate past the deadlines, restart."""
        now = time.monotonic()
        for role, (inc, context, sig) in list(self.stopping.items()):
            c = inc.child
            if self.group.reap(c):
                del self.stopping[role]
                self.shutdowns.append(Shutdown(c.name, context, c.stop_requested - self.t0,
                                               c.shutdown_s, c.signal_used, c.returncode))
                self.say(f"{c.name} exited in {c.shutdown_s:.3f} s ({c.signal_used}, exit "
                         f"code {c.returncode})")
                if restart:
                    new = self.start(role)
                    self.say(f"restarted {role} as {new.child.name} (pid {new.child.pid})")
                continue
            waited = now - (c.stop_requested or now)
            if waited > TARGET_SHUTDOWN_S + 0.5 and c.name not in self.dumped:
                self.dumped.add(c.name)
                self.say(f"{c.name} still running {waited:.1f} s after SIGINT")
                self.dump_stacks(c)
            elif sig == "SIGINT" and waited > 6.0:
                self.group.send(c, signal.SIGTERM)
                self.stopping[role] = (inc, context, "SIGTERM")
                self.say(f"{c.name} still running {waited:.1f} s after SIGINT: SIGTERM")
            elif sig == "SIGTERM" and waited > 9.0:
                self.group.send(c, signal.SIGKILL)
                self.stopping[role] = (inc, context, "SIGKILL")
                self.say(f"{c.name} still running {waited:.1f} s after SIGINT: SIGKILL")

    def watch_deaths(self) -> None:
        for role, inc in list(self.current.items()):
            if role in self.stopping:
                continue
            if self.group.reap(inc.child):
                c = inc.child
                msg = (f"{c.name} died unasked at {time.monotonic() - self.t0:.1f} s (exit "
                       f"code {c.returncode}):\n{c.log_tail(20)}")
                self.unexpected.append(msg)
                self.say(msg)
                if role != HARNESS:
                    new = self.start(role)
                    self.say(f"restarted {role} as {new.child.name}")

    # ---- run ---------------------------------------------------------------------------

    def run(self) -> int:
        args = self.args
        self.out.mkdir(parents=True, exist_ok=True)
        domain = args.domain_id if args.domain_id is not None else 150 + os.getpid() % 80
        env = child_env(domain)
        env["PYTHONPATH"] = os.pathsep.join([str(Path(__file__).resolve().parent),
                                             env["PYTHONPATH"]])
        for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE",
                    "FASTDDS_BUILTIN_TRANSPORTS", "AMENT_PREFIX_PATH"):
            os.environ[key] = env[key]
        if args.model is not None:
            model = Path(args.model).resolve()
        else:
            model, _ = train_model(self.out, args.seed, args.train_minutes, "tile", self.say)
            model = model.resolve()
        runtime = Path(tempfile.mkdtemp(prefix="asgp-soak-"))
        port = str(runtime / "joystick")
        opts = DemoOptions(minutes=args.minutes, seed=args.seed, domain_id=domain,
                           out=self.out, model=model, train=False,
                           shared_control=args.shared_control,
                           inattention=args.inattention if args.shared_control else 0.0,
                           adapt=args.adapt)
        self.commands = {name: (entry, argv) for name, entry, argv
                         in node_commands(opts, model, port)}
        self.commands[HARNESS] = ("soak:hardware_main", self.commands[HARNESS][1])
        entry, argv = self.commands["predictor"]
        self.commands["predictor"] = (entry, [*argv, "-p", "diagnostics_period_s:=0.2"])
        logs = self.out / "logs"
        if logs.exists():
            shutil.rmtree(logs)
        self.group = ProcessGroup(env, logs)
        context = rclpy.context.Context()
        rclpy.init(args=[], context=context, domain_id=domain,
                   signal_handler_options=SignalHandlerOptions.NO)
        self.mon = SoakMonitor(self.t0, context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(self.mon)
        self.say(f"ROS_DOMAIN_ID={domain}; model {model}; logs in {logs}")
        interrupted = False
        try:
            for role in (HARNESS, *self.nodes):
                self.start(role)
            self._wait_for_start(executor)
            self._loop(executor)
        except KeyboardInterrupt:
            interrupted = True
            self.soak_errors.append("the soak was interrupted (Ctrl-C)")
        finally:
            self._final_stop(executor)
            executor.remove_node(self.mon)
            self.mon.destroy_node()
            executor.shutdown()
            rclpy.try_shutdown(context=context)
            shutil.rmtree(runtime, ignore_errors=True)
        ok = self.report()
        return 130 if interrupted else (0 if ok else 1)

    def _spin_until(self, executor: SingleThreadedExecutor, done: Any, timeout_s: float,
                    what: str) -> bool:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
            self.watch_deaths()
            if done():
                return True
        self.soak_errors.append(f"timed out after {timeout_s:.0f} s waiting for {what}")
        return False

    def _wait_for_start(self, executor: SingleThreadedExecutor) -> None:
        self.say("waiting for discovery and the first predicted path")
        ok = self._spin_until(
            executor, lambda: (self.mon.fault_pub.get_subscription_count() > 0
                               and bool(self.mon.paths)),
            self.args.startup_timeout, "the hardware's fault subscription and a first path")
        if not ok:
            raise RuntimeError("; ".join(self.soak_errors))
        # soak time 0: the system runs
        shift = time.monotonic() - self.t0
        self.t0 += shift
        self.mon.t0 = self.t0
        for inc in self.incarnations:
            inc.started -= shift
            inc.rss = [(t - shift, kb) for t, kb in inc.rss]
            inc.cpu = [(t - shift, c) for t, c in inc.cpu]
        self.load = [(t - shift, x) for t, x in self.load]
        self.mon.paths.clear()
        self.mon.joy_per_s.clear()
        self.mon.frames_per_s.clear()
        self.mon.latency.clear()
        self.mon.bridge_joy.clear()
        self.mon.twists.clear()
        self.say(f"running for {self.args.minutes:g} min with faults every "
                 f"{self.args.cycle_s:g} s after {self.warmup:.0f} s of warm-up")

    def _loop(self, executor: SingleThreadedExecutor) -> None:
        pending = list(self.actions)
        next_rss = 0.0
        next_status = 30.0
        while True:
            executor.spin_once(timeout_sec=0.02)
            t = time.monotonic() - self.t0
            self.watch_stops(restart=True)
            self.watch_deaths()
            if t >= next_rss:
                self.sample_rss()
                next_rss += self.args.rss_period
            while pending and pending[0].t <= t:
                action = pending.pop(0)
                if action.kind == "fault":
                    ident = self.mon.send_fault(action.payload)
                    self.fault_log.append((action.t, action.label, ident))
                    self.say(action.label)
                elif action.kind == "sigint":
                    self.interrupt(action.payload["node"], action.label)
                elif action.kind == "final":
                    self.say(action.label)
                    return
            if t >= next_status:
                next_status += 30.0
                self._status(t)

    def _status(self, t: float) -> None:
        recent = [a for a, _ in self.mon.paths if a > t - 30.0]
        rss = ", ".join(f"{r} {inc.rss[-1][1] / 1024:.0f} MB"
                        for r, inc in self.current.items() if inc.rss)
        pred = self.mon.diag.get("predictor_node: prediction", {})
        self.say(f"paths {len(recent) / 30.0:.1f}/s, predictor: "
                 f"{pred.get('reason', '?')}; RSS {rss}")

    def _final_stop(self, executor: SingleThreadedExecutor) -> None:
        """SIGINT to every node at once (mid-burst), as ``asgp demo`` stops them, with the
        deadlines of :meth:`ProcessGroup.stop_all`; then the hardware."""
        for role in self.nodes:
            inc = self.current.get(role)
            if inc is not None and role not in self.stopping and inc.child.returncode is None:
                self.sample_rss()
                self.interrupt(role, "final SIGINT to every node, mid-burst")
        end = time.monotonic() + 30.0
        while self.stopping and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.01)
            self.watch_stops(restart=False)
        hw = self.current.get(HARNESS)
        if hw is not None:
            t = time.monotonic() - self.t0
            self.group.stop_all(children=[hw.child])
            self.shutdowns.append(Shutdown(hw.child.name + " (harness)", "final", t,
                                           hw.child.shutdown_s, hw.child.signal_used,
                                           hw.child.returncode))
        self.group.stop_all()  # anything left (nothing, normally)

    def dump_stacks(self, child: Child) -> None:
        """The threads of a node that is slow to stop, into logs/NAME.stacks.txt (py-spy if
        installed, else gdb), so that a hang can be explained afterwards."""
        path = child.log_path.with_suffix(".stacks.txt")
        spy = shutil.which("py-spy")
        argv = ([spy, "dump", "--native", "--pid", str(child.pid)] if spy else
                ["gdb", "-p", str(child.pid), "-batch", "-ex", "thread apply all py-bt",
                 "-ex", "thread apply all bt"])
        try:
            proc = subprocess.run(argv, capture_output=True, text=True, timeout=30.0,
                                  check=False)
            path.write_text(proc.stdout + proc.stderr)
            self.say(f"{child.name}: stacks in {path}")
        except (OSError, subprocess.TimeoutExpired) as exc:
            self.say(f"{child.name}: no stacks ({exc})")

    # ---- report ------------------------------------------------------------------------

    def _first_output_after(self, role: str, t: float) -> float | None:
        if role == "predictor":
            times = [a for a, _ in self.mon.paths]
        elif role == "vo":
            times = self.mon.twists
        elif role == "shared_control":
            times = self.mon.layer_status
        else:
            times = self.mon.bridge_joy
        return next((x - t for x in times if x >= t), None)

    def report(self) -> bool:
        mon = self.mon
        a = self.args
        print()
        print(f"== soak: {a.minutes:g} min (real time = simulated time), faults every "
              f"{a.cycle_s:g} s after {self.warmup:.0f} s warm-up, bursts {a.burst_factor}x")

        # -- windows: latency, paths, RSS
        win = a.window_s
        nwin = max(1, math.ceil(self.total / win))
        roles = [*self.nodes, HARNESS]
        print()
        print(f"Per {win:g}-s window: predictor latency in ms (own: VO callback -> "
              "publication, from its diagnostics; e2e: path arrival here - its t0 stamp); "
              "per process RSS at the window's end (MB) and CPU over the window (% of one "
              "core); the machine's 1-min load average")
        head = (f"{'window':>11} {'paths':>6} {'own p99':>8} {'own max':>8} {'e2e p99':>8}  "
                + " ".join(f"{r[:14]:>14}" for r in roles) + f" {'load':>5}  faults")
        print(head)
        print("-" * len(head))
        windows = []
        for w in range(nwin):
            lo, hi = w * win, min((w + 1) * win, self.total)
            own = [s.own_ms for s in mon.latency if lo <= s.t < hi]
            e2e = [d for t, d in mon.paths if lo <= t < hi]
            rss: dict[str, float] = {}
            cpu: dict[str, float] = {}
            for r in roles:
                pts = [(t, kb) for inc in self.incarnations if inc.role == r
                       for t, kb in inc.rss if t < hi]
                rss[r] = pts[-1][1] / 1024.0 if pts else float("nan")
                used = 0.0
                for inc in self.incarnations:
                    if inc.role == r:
                        c = [x for t, x in inc.cpu if lo <= t <= hi]
                        used += c[-1] - c[0] if len(c) > 1 else 0.0
                cpu[r] = 100.0 * used / max(hi - lo, 1e-9)
            loads = [x for t, x in self.load if lo <= t < hi]
            load = loads[-1] if loads else float("nan")
            faults = [lbl for t, lbl, _ in self.fault_log if lo <= t < hi]
            faults += [s.name + " SIGINT" for s in self.shutdowns if lo <= s.t < hi
                       and "final" not in s.context]
            row = {"start": lo, "end": hi, "paths": len(e2e), "own_p99_ms": percentile(own, 99),
                   "own_max_ms": max(own) if own else float("nan"),
                   "e2e_p99_ms": 1e3 * percentile(e2e, 99), "rss_mb": rss,
                   "cpu_pct": cpu, "load": load, "faults": faults}
            windows.append(row)
            print(f"{lo:5.0f}-{hi:<5.0f} {len(e2e):6d} {row['own_p99_ms']:8.2f} "
                  f"{row['own_max_ms']:8.2f} {row['e2e_p99_ms']:8.1f}  "
                  + " ".join(f"{rss[r]:7.1f} {cpu[r]:5.1f}%" for r in roles)
                  + f" {load:5.2f}  {len(faults)}")
        own_all = [s.own_ms for s in mon.latency]
        e2e_all = [d for _, d in mon.paths]
        print(f"{'all':>11} {len(e2e_all):6d} {percentile(own_all, 99):8.2f} "
              f"{(max(own_all) if own_all else float('nan')):8.2f} "
              f"{1e3 * percentile(e2e_all, 99):8.1f}")

        # -- RSS growth
        print()
        print(f"RSS growth per process (median of the last quarter of its samples after "
              f"warm-up vs the first quarter; warm-up {self.warmup:.0f} s of the run, or "
              "60 s after a restart; at least 120 s of samples)")
        print(f"{'process':>18} {'lived s':>8} {'samples':>7} {'first MB':>9} {'last MB':>8} "
              f"{'growth':>8}  verdict")
        growth_rows = []
        worst = None
        for inc in self.incarnations:
            warm = max(self.warmup, inc.started + 60.0)
            g = rss_growth(inc.rss, warm, 120.0)
            end = inc.child.ended - self.t0 if inc.child.ended else self.total
            lived = end - inc.started
            name = inc.child.name + (" (harness)" if inc.role == HARNESS else "")
            if g is None:
                verdict, text = "too short to judge", f"{'':>9} {'':>8} {'':>8}"
            else:
                first, last, pct = g
                flat = abs(pct) <= TARGET_RSS_PCT
                verdict = "flat" if flat else "GROWS" if pct > 0 else "SHRINKS"
                text = f"{first / 1024:9.1f} {last / 1024:8.1f} {pct:+7.2f}%"
                if inc.role != HARNESS and (worst is None or abs(pct) > abs(worst[1])):
                    worst = (inc.child.name, pct)
            growth_rows.append({"process": inc.child.name, "role": inc.role,
                                "lived_s": lived, "samples": len(inc.rss),
                                "growth": g, "verdict": verdict})
            print(f"{name:>18} {lived:8.0f} {len(inc.rss):7d} {text}  {verdict}")

        # -- faults
        print()
        print("Faults: paths published during each, and how long after its end the "
              "paths (and, after an unplug, the bridge's joy) came back")
        print(f"{'t s':>7}  {'fault':<44} {'paths':>6} {'paths back':>11} {'joy back':>9}")
        paths_t = [t for t, _ in mon.paths]
        fault_rows = []
        for ep in self.episodes:
            during = sum(1 for t in paths_t if ep.start <= t < ep.end)
            back = next((t - ep.end for t in paths_t if t >= ep.end), None)
            joy_back = (next((t - ep.end for t in mon.bridge_joy if t >= ep.end), None)
                        if "unplugged" in ep.label else None)
            fault_rows.append({**asdict(ep), "paths_during": during, "paths_back_s": back,
                               "joy_back_s": joy_back})
            print(f"{ep.start:7.1f}  {ep.label:<44} {during:6d} "
                  f"{_fmt_s(back):>11} {_fmt_s(joy_back) if 'unplugged' in ep.label else '':>9}")
        unacked = [f"{lbl} at {t:.1f} s" for t, lbl, ident in self.fault_log
                   if ident not in mon.acks]
        failed = [f"{mon.acks[i]['kind']}: {mon.acks[i].get('error')}"
                  for _, _, i in self.fault_log if i in mon.acks and not mon.acks[i]["ok"]]
        if unacked:
            self.soak_errors.append("faults the hardware never acknowledged: "
                                    + ", ".join(unacked))
        if failed:
            self.soak_errors.append("faults the hardware could not apply: " + ", ".join(failed))
        def rate(bins: dict[int, int], lo: float, hi: float) -> float:
            secs = range(math.ceil(lo), math.floor(hi))
            return sum(bins.get(x, 0) for x in secs) / max(1, len(secs))

        quiet = [(ep.start - 8.0, ep.start - 1.0) for ep in self.episodes
                 if "traffic" in ep.label]
        busy = [(ep.start + 1.0, ep.start + 4.0) for ep in self.episodes
                if "traffic" in ep.label]
        if busy:
            print("traffic received here (per s), 7 s before the bursts -> their first 3 s: "
                  f"joy {np.mean([rate(mon.joy_per_s, *w) for w in quiet]):.0f} -> "
                  f"{np.mean([rate(mon.joy_per_s, *w) for w in busy]):.0f}, camera frames "
                  f"{np.mean([rate(mon.frames_per_s, *w) for w in quiet]):.1f} -> "
                  f"{np.mean([rate(mon.frames_per_s, *w) for w in busy]):.1f}")
        last_ack = max(mon.acks.values(), key=lambda x: x["t"]) if mon.acks else {}
        print(f"hardware counters at the last fault: {last_ack.get('counts', {})}; its "
              f"largest lag behind real time: {mon.max_hw_lag_s:.2f} s")
        print("predictor states seen in its diagnostics (count of 0.2-s reports): "
              + ", ".join(f"{k} {v}" for k, v in sorted(mon.reasons.items(),
                                                          key=lambda kv: -kv[1])))

        # -- stalls: no path for 10 s or more outside the faults' own effect, with the pose
        stalls = []
        times = sorted(t for t, _ in mon.paths)
        for a_t, b_t in zip([self.warmup, *times], [*times, self.total], strict=True):
            if b_t - a_t >= 10.0:
                inside = [p for p in mon.poses if a_t <= p[0] <= b_t]
                moved = (max(math.hypot(p[1] - inside[0][1], p[2] - inside[0][2])
                              for p in inside) if inside else math.nan)
                whys = sorted({w for t, w in mon.layer_why if a_t - 5.0 <= t <= b_t})
                # why the predictor published nothing: its reason as it changed
                states = [(t, r) for t, r in mon.reason_changes if a_t <= t <= b_t]
                stalls.append({"start": a_t, "end": b_t, "pose_start": inside[0][1:]
                               if inside else None, "moved_m": moved, "layer": whys,
                               "predictor": states})
        if stalls:
            print()
            print("Stalls: no path for 10 s or more (the chair's pose from ground truth; the "
                  "layer's decisions around it; the predictor's reasons as they changed)")
            for st in stalls:
                pose = st["pose_start"]
                where = (f"at ({pose[0]:.2f}, {pose[1]:.2f}) heading "
                         f"{math.degrees(pose[2]):.0f} deg" if pose else "pose unknown")
                print(f"  {st['start']:7.1f}-{st['end']:7.1f} s  {where}, moved at most "
                      f"{st['moved_m']:.2f} m; layer: {', '.join(st['layer']) or '-'}")
                print("    predictor: " + (", ".join(f"{t:.1f} s {r}" for t, r in
                                                     st["predictor"]) or "no report"))

        # -- restarts
        restarts = []
        for inc in self.incarnations:
            if inc.child.name == inc.role:
                continue
            first = self._first_output_after(inc.role, inc.started)
            restarts.append({"process": inc.child.name, "t": inc.started,
                             "first_output_s": first})
        if restarts:
            print()
            print("Restarts: time from the restart to the node's first output "
                  "(bridge: joy, VO: vo/twist, predictor: predicted_path, shared control: "
                  "shared_control/status)")
            for r in restarts:
                print(f"  {r['process']:<18} restarted at {r['t']:7.1f} s, output after "
                      f"{_fmt_s(r['first_output_s'])}")

        # -- shutdowns
        print()
        print("Shutdowns (first signal to exit)")
        print(f"{'t s':>7}  {'process':<26} {'seconds':>8} {'signal':>8} {'exit':>5}  context")
        slowest = 0.0
        for s in self.shutdowns:
            sec = s.seconds if s.seconds is not None else float("inf")
            if "harness" not in s.name:
                slowest = max(slowest, sec)
            print(f"{s.t:7.1f}  {s.name:<26} {sec:8.3f} {s.signal:>8} "
                  f"{s.returncode if s.returncode is not None else '-':>5}  {s.context}")
        bad_exit = [s for s in self.shutdowns if "harness" not in s.name
                    and (s.signal != "SIGINT" or s.returncode not in (0, -signal.SIGINT))]

        # -- exceptions
        findings: list[Finding] = []
        for inc in self.incarnations:
            try:
                text = inc.child.log_path.read_text(errors="replace")
            except OSError:
                continue
            findings += scan_log(inc.child.name, text)
        counted = [f for f in findings if f.counted]
        warnings = [f for f in findings if not f.counted]
        print()
        print(f"Exceptions, tracebacks and error lines in the processes' output "
              f"({sum(f.count for f in counted)}):")
        for f in counted:
            print(f"  {f.process} [{f.kind}] x{f.count} (first at line {f.line} of "
                  f"{f.process}.log): {f.text[:400]}")
        if warnings:
            print(f"Warnings naming an exception (handled, not counted) "
                  f"({sum(f.count for f in warnings)}):")
            for f in warnings:
                print(f"  {f.process} x{f.count}: {f.text[:300]}")
        for u in self.unexpected:
            print("  unexpected exit: " + u.splitlines()[0])
        for e in self.soak_errors:
            print("  soak: " + e)

        # -- the predictor's adaptation at the end (its last diagnostics)
        pred = mon.diag.get("predictor_node: prediction", {})
        adaptation = {k: v for k, v in pred.items()
                      if k.startswith("adapt") or k.startswith("overrides_")}
        if a.adapt:
            print("adaptation at the end: " + ", ".join(
                f"{k} {adaptation.get(k, 'n/a')}" for k, _ in ADAPT_KEYS))

        # -- verdict
        judged = [r for r in growth_rows if r["growth"] is not None and r["role"] != HARNESS]
        rss_ok = bool(judged) and all(abs(r["growth"][2]) <= TARGET_RSS_PCT for r in judged)
        n_exc = sum(f.count for f in counted) + len(self.unexpected)
        exc_ok = n_exc == 0
        shut_ok = bool(self.shutdowns) and slowest < TARGET_SHUTDOWN_S and not bad_exit
        result = {
            "minutes": a.minutes, "warmup_s": self.warmup, "cycle_s": a.cycle_s,
            "burst_factor": a.burst_factor, "windows": windows, "rss_growth": growth_rows,
            "rss_samples": {inc.child.name: inc.rss for inc in self.incarnations},
            "faults": fault_rows, "restarts": restarts,
            "shutdowns": [asdict(s) for s in self.shutdowns],
            "findings": [asdict(f) for f in findings], "unexpected_exits": self.unexpected,
            "soak_errors": self.soak_errors, "predictor_states": mon.reasons,
            "latency_own_ms": [(s.t, s.own_ms) for s in mon.latency],
            "paths": mon.paths, "poses": mon.poses, "layer_why": mon.layer_why,
            "stalls": stalls, "targets": {"rss": rss_ok, "exceptions": exc_ok,
                                            "shutdowns": shut_ok},
            "adaptation": adaptation,
        }
        (self.out / "soak.json").write_text(json.dumps(result, indent=1, default=str))
        worst_text = (f"worst {worst[1]:+.2f} % ({worst[0]})" if worst
                      else "no process lived long enough to judge")
        print()
        print(f"TARGETS: RSS flat within {TARGET_RSS_PCT:g} %: "
              f"{'PASS' if rss_ok else 'FAIL'} ({worst_text}); "
              f"no exception: {'PASS' if exc_ok else 'FAIL'} ({n_exc}); "
              f"every shutdown under {TARGET_SHUTDOWN_S:g} s: "
              f"{'PASS' if shut_ok else 'FAIL'} (slowest {slowest:.3f} s of "
              f"{sum('harness' not in s.name for s in self.shutdowns)}"
              + (f"; {len(bad_exit)} not clean on SIGINT" if bad_exit else "") + ")")
        return rss_ok and exc_ok and shut_ok and not self.soak_errors


def _fmt_s(x: float | None) -> str:
    return "never" if x is None else f"{x:.2f} s"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=30.0,
                    help="length of the run, simulated = real time (default 30)")
    ap.add_argument("--out", default="soak-output", help="logs and soak.json go here")
    ap.add_argument("--model", help="model file (default: trained as `asgp demo` does)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--train-minutes", type=float, default=10.0)
    ap.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID (default 150 + pid %% 80)")
    ap.add_argument("--cycle-s", type=float, default=120.0, help="period of the faults")
    ap.add_argument("--burst-factor", type=int, default=10)
    ap.add_argument("--window-s", type=float, help="latency / RSS table window "
                    "(default 60 s, 30 s for runs under 10 minutes)")
    ap.add_argument("--rss-period", type=float, default=2.0, help="RSS sampling period (s)")
    ap.add_argument("--startup-timeout", type=float, default=120.0)
    ap.add_argument("--shared-control", action="store_true",
                    help="run shared_control_node too (on the hardware's scanner; the "
                         "fourth cycle's SIGINT goes to it)")
    ap.add_argument("--inattention", type=float, default=0.1,
                    help="with --shared-control: the simulated driver's inattention, so "
                         "that the layer intervenes (0.1)")
    ap.add_argument("--adapt", action=argparse.BooleanOptionalAction, default=True,
                    help="the predictor adapts online (adapt.enabled, the default; "
                         "--no-adapt: as trained); its adaptation state "
                         "at the end is in the report")
    args = ap.parse_args(argv)
    if not (math.isfinite(args.minutes) and 1.0 <= args.minutes <= 600.0):
        ap.error("--minutes must be in [1, 600]")
    if args.cycle_s < 100.0:
        ap.error("--cycle-s must be at least 100 (the faults of a cycle take 97 s)")
    if not 2 <= args.burst_factor <= 50:
        ap.error("--burst-factor must be in [2, 50]")
    if args.window_s is None:
        args.window_s = 60.0 if args.minutes >= 10.0 else 30.0
    return Soak(args).run()


if __name__ == "__main__":
    sys.exit(main())
