"""serial_bridge_node: the joystick interface board on ROS 2.

Publishes ``joy`` (sensor_msgs/Joy, axes [forward, turn], + forward / + left, sensor-data
QoS) for every joystick sample the board sends that carries a reading, stamped at
reception (a sample with ADC_FAULT carries none: it is withheld, never published as a
deflection), and with each the same sample's ``joy_applied``: what the board drives the
chair with, its output while an override is applied (OVERRIDE_ACTIVE; its DAC codes read
back into the units of ``joy``), else the same axes as ``joy``; subscribes ``joy_override``
(best effort: a lost message is replaced by the next, and none holds later ones back) and
forwards it to the board while it is fresh, in the board's units (the output the board
gives for the stick the host reads as the command: :mod:`asgp_ros.serial.calibration`), by
arrival and, when stamped, by its stamp (:mod:`asgp_ros.serial.override_gate`), then
simply stops, so the firmware's 200 ms watchdog returns the chair to the user;
publishes the link state, the joystick reading's and the override's fate on
``diagnostics`` (:mod:`asgp_ros.serial.status` decides levels and messages). The serial
work (port, reader thread, reconnection, handshake, heartbeats) lives in
:mod:`asgp_ros.serial.link`; this node only converts and wires.

Each Joy is published straight from the link's reader thread (rclpy publishers are
thread-safe) rather than handed to the executor: that saves the executor's wake-up, the
largest share of the frame-to-Joy latency (benchmarks/serial_bridge.py). Diagnostics are
published at once, from that thread too, when a sample changes a diagnostic level (an ADC
fault is an ERROR from its first sample); link state changes reach the executor through a
guard condition and publish diagnostics at once.
"""

from __future__ import annotations

import contextlib
import math
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import replace
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rcl_interfaces.msg import SetParametersResult
from rclpy.exceptions import ParameterException
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from sensor_msgs.msg import Joy

from asgp_ros.common import topics
from asgp_ros.nodes import conversions as conv
from asgp_ros.nodes import runtime
from asgp_ros.nodes.parameters import declare, is_change
from asgp_ros.nodes.qos_watch import QosWatch
from asgp_ros.serial import status as board_status
from asgp_ros.serial.calibration import board_permille, host_deflection
from asgp_ros.serial.link import (
    HANDSHAKE_ERROR_AFTER,
    JoystickSample,
    LinkManager,
    LinkState,
    LinkStats,
)
from asgp_ros.serial.override_gate import OverrideGate
from asgp_ros.serial.params import PARAMS, SPECS, BridgeParams, bridge_params
from asgp_ros.serial.protocol import Mode, Status
from asgp_ros.serial.safety import default_calibration

_LEVEL = {
    LinkState.CONNECTED: "OK",
    LinkState.HANDSHAKE: "WARN",
    LinkState.STALE: "ERROR",
    LinkState.CONNECTING: "ERROR",
    LinkState.INCOMPATIBLE: "ERROR",
    LinkState.STOPPED: "STALE",
}


#: How often (s, at most) the bridge looks at the graph for another bridge on its override
#: topic, a second node of its name or a second publisher of its joy before taking an
#: override (graph queries each time).
CROWD_CHECK_S = 0.5

#: Why the bridge never follows /clock: it drives a real board in real time, and an override
#: is written to the chair only while fresh by its stamp; on a replay's clock, the overrides
#: of a replayed bag (or of a layer judging replayed scans) would be fresh.
SIM_TIME_REFUSED = ("use_sim_time must be false: the bridge drives a real board in real time, "
                    "and on a replayed /clock a replayed or replay-driven joy_override would "
                    "look fresh (replaying a bag into the other nodes: leave the bridge out, "
                    "launch use_bridge:=false)")


class SerialBridgeNode(Node):
    """See the module docstring."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("serial_bridge_node", **kwargs)
        self.params: BridgeParams = bridge_params(declare(self, PARAMS))
        if self.get_parameter("use_sim_time").value:
            raise ValueError(SIM_TIME_REFUSED)
        self.add_on_set_parameters_callback(self._on_set_parameters)

        # endpoints without rclpy's per-endpoint QoS event handlers, their peers checked at
        # the diagnostics period and named there (a reliable subscriber of the best-effort
        # joy gets nothing: asgp_ros/nodes/qos_watch.py)
        self.qos_watch = watch = QosWatch(self)
        self._joy_pub = watch.publisher(Joy, topics.JOY, qos_profile_sensor_data)
        self._applied_pub = watch.publisher(Joy, topics.JOY_APPLIED, qos_profile_sensor_data)
        self._board = default_calibration()  # the firmware's own (config.h)
        self._diag_pub = watch.publisher(DiagnosticArray, topics.DIAGNOSTICS,
                                         QoSProfile(depth=10))
        self._override_sub = watch.subscription(Joy, topics.JOY_OVERRIDE, self._on_override,
                                                qos_profile_sensor_data)

        self._state_gc = self.create_guard_condition(self._publish_diagnostics)
        self._diag_lock = threading.Lock()  # diagnostics come from two threads
        self._diag_levels: tuple[object, ...] = ()  # levels of the last diagnostics published
        self._gate = OverrideGate()
        self._override_rejected = 0
        self._crowd = ""  # why overrides are refused while others are on the graph
        self._crowd_checked = -math.inf  # (time.monotonic() of the last look)
        self._crowd_refused = 0
        self._last_state_reason = ""
        self._published = 0
        self._withheld = 0                 # samples without a reading (ADC_FAULT)
        self._last_sample: JoystickSample | None = None
        self._last_status_seen: tuple[Status, bool] | None = None  # None: judge the next
        self._last_stamp_ns = 0

        self.link = LinkManager(self.params.link_config(), on_sample=self._on_sample,
                                on_state=self._on_state)
        pacing = runtime.pacing_clock(self)
        self.create_timer(1.0 / self.params.override_rate, self._send_override, clock=pacing)
        self.create_timer(self.params.diagnostics_period, self._on_diagnostics_timer,
                          clock=pacing)
        self.link.start()
        self.get_logger().info(f"serial bridge on {self.params.port}")

    # -- parameters ----------------------------------------------------------------------

    def _on_set_parameters(self, changes: list[Parameter]) -> SetParametersResult:
        values = {spec.name: self.get_parameter(spec.name).value for spec in PARAMS}
        for p in changes:
            if p.name == "use_sim_time" and p.value:
                return SetParametersResult(successful=False, reason=SIM_TIME_REFUSED)
            if p.name in SPECS and not SPECS[p.name].runtime and is_change(self, p):
                return SetParametersResult(
                    successful=False,
                    reason=f"{p.name} is read at start-up: restart the node to change it")
            values[p.name] = p.value
        try:
            new = bridge_params(values)
        except ValueError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        self.params = new
        self.link.config = replace(self.link.config, calibration=new.calibration)
        return SetParametersResult(successful=True)

    # -- link -> ROS -----------------------------------------------------------------------

    def _on_sample(self, s: JoystickSample) -> None:  # reader thread
        self._last_sample = s
        if s.valid:
            self._publish_joy(s)
        else:
            self._withheld += 1  # no reading: saying nothing is the truth, never a deflection
        seen = (s.status, self.link.host_lost)
        if seen != self._last_status_seen:
            self._last_status_seen = seen
            with self._shutdown_guard():
                self._publish_diagnostics(only_if_levels_change=True)

    def _publish_joy(self, s: JoystickSample) -> None:  # reader thread
        if s.forward is None or s.turn is None:
            return  # no reading (callers only pass valid samples)
        # stamped at reception: the node's clock now, minus how long ago the bytes arrived
        age_ns = int((time.monotonic() - s.t_rx) * 1e9)
        stamp_ns = self.get_clock().now().nanoseconds - max(0, age_ns)
        # never backwards by jitter (the clock and time.monotonic() are read a few us apart;
        # a jump of more than 1 s is a clock reset and is followed), never negative
        if 0 < self._last_stamp_ns - stamp_ns < 1_000_000_000:
            stamp_ns = self._last_stamp_ns
        stamp_ns = max(0, stamp_ns)
        self._last_stamp_ns = stamp_ns
        msg = conv.joy_from_sample(stamp_ns * 1e-9, s.forward, s.turn, self.params.frame_id)
        applied = msg
        if Status.OVERRIDE_ACTIVE in s.status:  # the board's output drives, not the stick
            cal = self.params.calibration
            applied = conv.joy_from_sample(
                stamp_ns * 1e-9, host_deflection(s.out_forward, cal.forward, self._board[0]),
                host_deflection(s.out_turn, cal.turn, self._board[1]), self.params.frame_id)
        with self._shutdown_guard():
            self._joy_pub.publish(msg)
            self._applied_pub.publish(applied)
            self._published += 1

    def _on_state(self, state: LinkState, reason: str) -> None:  # reader thread
        self._last_state_reason = reason
        self._last_status_seen = None  # the first sample of a connection is judged afresh
        if state not in (LinkState.CONNECTED, LinkState.STALE):
            # a new connection or handshake (a board restarted, replugged): the last
            # sample's flags are the previous connection's, not this board's state
            self._last_sample = None
        with self._shutdown_guard():
            self._state_gc.trigger()

    @contextlib.contextmanager
    def _shutdown_guard(self) -> Iterator[None]:
        """The reader thread may still deliver a sample between a Ctrl-C (which shuts the
        context down) and ``destroy_node`` stopping the link: drop it then, raise otherwise."""
        try:
            yield
        except _rclpy.RCLError:
            if self.context.ok():
                raise

    # -- ROS -> link -----------------------------------------------------------------------

    def _on_override(self, msg: Joy) -> None:
        try:
            command = conv.joy_to_override(msg)
        except ValueError as exc:
            self._override_rejected += 1
            self.get_logger().warn(f"override refused: {exc}", throttle_duration_sec=1.0)
            return
        if self._check_crowd(time.monotonic()):
            self._crowd_refused += 1
            self.get_logger().error(f"joy_override refused: {self._crowd}",
                                    throttle_duration_sec=5.0)
            return
        stamp = conv.stamp_to_seconds(msg.header.stamp) or None  # zero: unstamped
        if not self._gate.offer(command, stamp, time.monotonic(), self._clock_s(),
                                self.params.override_timeout):
            self.get_logger().warn(
                f"joy_override refused: {self._gate.refusal(self.params.override_timeout)}",
                throttle_duration_sec=1.0)

    def _clock_s(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _check_crowd(self, now: float) -> str:
        """Why no override may drive this chair while the graph holds what it holds, or "":
        another node of this bridge's full name (a second chair's stack started without a
        namespace on this ROS domain: each bridge took the one layer's overrides and drove
        its own chair with them, every status OK), or another publisher of this bridge's
        joy topic (a second chair's bridge, a bag replayed: a layer reading it judges a mix
        of sticks). Looked at once per CROWD_CHECK_S."""
        if now - self._crowd_checked < CROWD_CHECK_S:
            return self._crowd
        self._crowd_checked = now
        me = (self.get_name(), self.get_namespace())
        twins = sum(1 for entry in self.get_node_names_and_namespaces() if entry == me) - 1
        joy = self._joy_pub.topic_name
        others = self.count_publishers(joy) - 1
        override = self._override_sub.topic_name
        bridges, _ = runtime.override_readers(self, override)
        was, self._crowd = self._crowd, ""
        if bridges:
            self._crowd = (f"another bridge reads {override} ({', '.join(bridges[:3])}: it "
                           "subscribes to it and publishes a joystick): both chairs would "
                           "follow these overrides; give each chair its own override topic")
        elif twins > 0:
            self._crowd = (f"{twins} other node(s) named {self.get_fully_qualified_name()} on "
                           "this ROS domain (a second chair started without a namespace, or a "
                           "second bridge?): each would drive its chair with these overrides; "
                           "give each chair a namespace or a ROS_DOMAIN_ID of its own")
        elif others > 0:
            self._crowd = (f"{others} other publisher(s) of {joy} (a second chair's bridge, a "
                           "bag replayed?): the layer would judge a mix of sticks")
        if self._crowd and not was:
            self.get_logger().error(f"overrides refused: {self._crowd}")
        elif was and not self._crowd:
            self.get_logger().info("overrides taken again: the graph is this chair's alone")
        return self._crowd

    def _send_override(self) -> None:
        # the board's mode as its samples report it, not as we last asked: the board may
        # have reset it (HOST_LOST, a restart), and then the next override needs MODE first
        board_mode = self.link.board_mode
        now = time.monotonic()
        age = self._gate.age(now)
        command = self._gate.fresh(now, self._clock_s(), self.params.override_timeout)
        if command is not None and self._check_crowd(now):
            command = None  # (and the board back to the user at once, below)
            age = math.inf
        if command is not None:
            if board_mode != Mode.OVERRIDE:
                self.link.set_mode(Mode.OVERRIDE)
            # in the board's units: what it outputs for the stick the host reads as command
            cal, (fwd, turn) = self.params.calibration, command
            self.link.send_override(board_permille(fwd, cal.forward, self._board[0]) / 1000.0,
                                    board_permille(turn, cal.turn, self._board[1]) / 1000.0)
        elif board_mode == Mode.OVERRIDE and age > self.params.mode_release_after:
            # the firmware already fell back to the user after 200 ms; tidy the mode up
            self.link.set_mode(Mode.PASSTHROUGH)

    # -- diagnostics -------------------------------------------------------------------------

    def _on_diagnostics_timer(self) -> None:
        self.qos_watch.check()  # the peers, from the graph (here only, not from the reader)
        self._check_crowd(time.monotonic())
        self._publish_diagnostics()

    def _publish_diagnostics(self, only_if_levels_change: bool = False) -> None:
        """Publishes the three statuses (link, joystick, override); with
        ``only_if_levels_change`` only when a level differs from the last publication.
        Called from the executor and from the reader thread."""
        with self._diag_lock:
            st = self.link.stats()
            statuses = (self._link_status(st), self._joystick_status(st),
                        self._override_status(st))
            levels = tuple(x.level for x in statuses)
            if only_if_levels_change and levels == self._diag_levels:
                return
            self._diag_levels = levels
            self._diag_pub.publish(conv.diagnostic_array(
                self.get_clock().now().nanoseconds * 1e-9, list(statuses)))

    def _link_status(self, st: LinkStats) -> DiagnosticStatus:
        level = _LEVEL[st.state]
        msg = st.state.value
        if st.state == LinkState.CONNECTED:
            msg = f"connected, firmware {st.firmware}"
            if st.reconnects:
                msg += f", reconnected {st.reconnects} time(s)"
            if st.host_lost:
                level, msg = "ERROR", f"{board_status.HOST_LOST_MESSAGE} ({msg})"
            elif st.last_sample_age > self.params.sample_timeout:
                level, msg = "WARN", msg + f", no joystick sample for {st.last_sample_age:.2f} s"
        elif st.state == LinkState.CONNECTING:
            msg = f"disconnected, retrying: {st.last_error}"
        elif st.state == LinkState.STALE:
            msg = f"no heartbeat from the board for {st.last_heartbeat_age:.2f} s"
        elif st.state == LinkState.INCOMPATIBLE:
            msg = st.last_error
        elif st.state == LinkState.HANDSHAKE and st.state_age > HANDSHAKE_ERROR_AFTER:
            heard = st.last_error or (f"{st.frames_rx} frame(s) received, none a VERSION"
                                      if st.frames_rx else "nothing received")
            level, msg = "ERROR", (
                f"no handshake for {st.state_age:.1f} s, {st.hellos_unanswered} HELLO(s) "
                f"unanswered: {heard}. Is this the joystick board, with the asgp_bridge "
                f"firmware, at {self.params.baud} baud?")
        elif st.state == LinkState.HANDSHAKE and st.unsolicited_versions:
            msg = f"handshake again after an unsolicited VERSION ({st.last_error})"
        elif st.state == LinkState.HANDSHAKE and st.board_restarts:
            msg = f"handshake again: {st.last_error}"
        level, msg = self.qos_watch.escalate(level, msg)
        return conv.diagnostic_status(
            runtime.status_name(self, "serial_bridge: link"), level, msg, st.port, {
                "state": st.state.value, "reason": self._last_state_reason,
                "connects": st.connects, "reconnects": st.reconnects,
                "open_failures": st.open_failures, "firmware": st.firmware,
                "board_rate_hz": st.board_rate_hz, "board_watchdog_ms": st.board_watchdog_ms,
                "frames_rx": st.frames_rx, "samples_rx": st.samples_rx,
                "joy_published": self._published, "frames_lost": st.frames_lost,
                "frames_repeated": st.frames_repeated, "frames_late": st.frames_late,
                "seq_restarts": st.seq_restarts, "board_restarts": st.board_restarts,
                "host_frames_heard": st.host_frames_heard,
                "crc_errors": st.crc_errors, "bytes_dropped": st.bytes_dropped,
                "decode_errors": st.decode_errors, "board_errors": st.board_errors,
                "last_board_error": st.last_board_error,
                "board_crc_errors": st.board_crc_errors,
                "board_rx_frames": st.board_rx_frames,
                "unsolicited_versions": st.unsolicited_versions,
                "version_mismatches": st.version_mismatches,
                "host_lost": st.host_lost, "host_lost_events": st.host_lost_events,
                "last_sample_age_s": st.last_sample_age,
                "last_heartbeat_age_s": st.last_heartbeat_age,
                "qos_mismatch": self.qos_watch.summary(),
            })

    def _joystick_status(self, st: LinkStats) -> DiagnosticStatus:
        s = self._last_sample
        counts = {f"samples_{bit.name.lower()}": st.status_counts.get(bit.name, 0)
                  for bit in board_status.STATUS_BITS if bit.name}
        if s is None or st.state not in (LinkState.CONNECTED, LinkState.STALE) \
                or st.last_sample_age > self.params.sample_timeout:
            level, msg = "STALE", "no recent joystick sample"
            values: dict[str, object] = {"status": "", "sample_seq": ""}
        else:
            verdict = board_status.joystick_verdict(s.status, (s.raw_forward, s.raw_turn))
            level, msg = verdict.level, verdict.message
            values = {"status": board_status.flag_names(s.status), "sample_seq": s.seq,
                      "raw_forward": s.raw_forward, "raw_turn": s.raw_turn,
                      "out_forward": s.out_forward, "out_turn": s.out_turn}
        values.update({"joy_published": self._published, "joy_withheld": self._withheld,
                       **counts})
        return conv.diagnostic_status(runtime.status_name(self, "serial_bridge: joystick"),
                                      level, msg, st.port, values)

    def _override_status(self, st: LinkStats) -> DiagnosticStatus:
        now = time.monotonic()
        gate = self._gate
        fresh = gate.fresh(now, self._clock_s(), self.params.override_timeout) is not None
        board_mode = "override" if st.board_mode == Mode.OVERRIDE else "passthrough"
        # a sample older than sample_timeout says nothing of the board now: on reconnecting
        # after the bridge was suspended, the previous connection's said OK "active: the
        # chair follows joy_override" next to "no joystick sample for 10.00 s"
        s = self._last_sample if st.last_sample_age <= self.params.sample_timeout else None
        flags = ""
        if st.state is not LinkState.CONNECTED:
            # nothing reaches the board, or nothing is heard of it: its last sample's
            # flags are not what becomes of the overrides now (an unplugged board's said
            # OK "sending", a silent one's OK "active")
            board_mode = f"unknown: the link is {st.state.value}"
            verdict = (board_status.Verdict("WARN", f"not reaching the board: the link is "
                                                    f"{st.state.value}; "
                                                    "the user drives")
                       if fresh else board_status.Verdict("OK", "idle"))
        elif s is None:
            verdict = board_status.Verdict("OK", f"{'sending' if fresh else 'idle'}")
        else:
            verdict = board_status.override_verdict(s.status, fresh)
            flags = board_status.flag_names(s.status)
        if not fresh and gate.refusing(now):
            verdict = board_status.Verdict(
                "WARN", f"refused: joy_override arrives "
                        f"{gate.refusal(self.params.override_timeout)}; the user drives")
        if self._crowd:
            verdict = board_status.Verdict("ERROR", f"every override refused: {self._crowd}; "
                                                    "the user drives")
        return conv.diagnostic_status(
            runtime.status_name(self, "serial_bridge: override"), verdict.level,
            f"{verdict.message} (board mode {board_mode})", st.port, {
                "fresh": fresh, "overrides_sent": st.overrides_sent,
                "overrides_refused": self._override_rejected,
                "overrides_stale": gate.refused_stale,
                "overrides_out_of_order": gate.refused_older, "board_mode": board_mode,
                "overrides_refused_crowd": self._crowd_refused,
                "status": flags,
            })

    def destroy_node(self) -> None:
        self.link.stop()
        # rclpy's Node.destroy_node is unannotated; a super() call escapes mypy.ini's
        # untyped_calls_exclude, which matches on names
        super().destroy_node()  # type: ignore[no-untyped-call]


def main(args: list[str] | None = None) -> int:
    """Runs the node until SIGINT or SIGTERM, then stops the link (the board is asked for
    passthrough), destroys the node, shuts rclpy down and returns 0. Exit code 1: a
    parameter refused at start-up (out of its range, NaN, inconsistent), said in one line.

    SIGINT and SIGTERM only set a flag (:mod:`asgp_ros.nodes.runtime`): the link's reader
    thread publishes ``joy``, and rclpy's own handlers, which shut the context down at the
    signal, let it publish into, and end after, a context already shut down, which crashed
    the process natively now and then at exit. Once the flag is set the link stops while
    the context is still up. A signal while the node is being built is honoured as soon
    as it is built."""
    return runtime.run(SerialBridgeNode, args, name="serial_bridge_node",
                       refused=(ValueError, ParameterException))


if __name__ == "__main__":
    sys.exit(main())
