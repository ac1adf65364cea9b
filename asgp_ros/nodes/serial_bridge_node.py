"""serial_bridge_node: the joystick interface board on ROS 2.

Publishes ``joy`` (sensor_msgs/Joy, axes [forward, turn], + forward / + left, sensor-data
QoS) for every joystick sample the board sends, stamped at reception; subscribes
``joy_override`` and forwards it to the board while it is fresh (then simply stops, so
the firmware's 200 ms watchdog returns the chair to the user); publishes the link state
on ``diagnostics``. The serial work (port, reader thread, reconnection, handshake,
heartbeats) lives in :mod:`asgp_ros.serial.link`; this node only converts and wires.

Each Joy is published straight from the link's reader thread (rclpy publishers are
thread-safe) rather than handed to the executor: that saves the executor's wake-up, the
largest share of the frame-to-Joy latency (benchmarks/serial_bridge.py). Link state
changes reach the executor through a guard condition and publish diagnostics at once.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import replace

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import SetParametersResult
from rclpy.executors import ExternalShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from sensor_msgs.msg import Joy

from asgp_ros.nodes import conversions as conv
from asgp_ros.nodes.parameters import declare
from asgp_ros.serial.link import JoystickSample, LinkManager, LinkState
from asgp_ros.serial.params import PARAMS, SPECS, BridgeParams, bridge_params
from asgp_ros.serial.protocol import Mode

_LEVEL = {
    LinkState.CONNECTED: "OK",
    LinkState.HANDSHAKE: "WARN",
    LinkState.STALE: "ERROR",
    LinkState.CONNECTING: "ERROR",
    LinkState.INCOMPATIBLE: "ERROR",
    LinkState.STOPPED: "STALE",
}


class SerialBridgeNode(Node):
    """See the module docstring. ``link_factory`` lets tests substitute the link."""

    def __init__(self, **kwargs) -> None:
        super().__init__("serial_bridge_node", **kwargs)
        self.params: BridgeParams = bridge_params(declare(self, PARAMS))
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self._joy_pub = self.create_publisher(Joy, "joy", qos_profile_sensor_data)
        self._diag_pub = self.create_publisher(DiagnosticArray, "diagnostics",
                                               QoSProfile(depth=10))
        self.create_subscription(Joy, "joy_override", self._on_override,
                                 QoSProfile(depth=10))

        self._state_gc = self.create_guard_condition(self._publish_diagnostics)
        self._override: tuple[float, float] | None = None
        self._override_t = -float("inf")  # time.monotonic() of the last valid override
        self._override_mode = False       # we asked the board for override mode
        self._override_rejected = 0
        self._last_state_reason = ""
        self._published = 0
        self._last_stamp_ns = 0

        self.link = LinkManager(self.params.link_config(), on_sample=self._on_sample,
                                on_state=self._on_state)
        self.create_timer(1.0 / self.params.override_rate, self._send_override)
        self.create_timer(self.params.diagnostics_period, self._publish_diagnostics)
        self.link.start()
        self.get_logger().info(f"serial bridge on {self.params.port}")

    # -- parameters ----------------------------------------------------------------------

    def _on_set_parameters(self, changes) -> SetParametersResult:
        values = {spec.name: self.get_parameter(spec.name).value for spec in PARAMS}
        for p in changes:
            if p.name in SPECS and not SPECS[p.name].runtime:
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
        # stamped at reception: the node's clock now, minus how long ago the bytes arrived
        age_ns = int((time.monotonic() - s.t_rx) * 1e9)
        stamp_ns = self.get_clock().now().nanoseconds - max(0, age_ns)
        # never backwards by jitter (the clock and time.monotonic() are read a few us apart;
        # a jump of more than 1 s is a clock reset and is followed), never negative
        # (use_sim_time before the first /clock reads 0)
        if 0 < self._last_stamp_ns - stamp_ns < 1_000_000_000:
            stamp_ns = self._last_stamp_ns
        stamp_ns = max(0, stamp_ns)
        self._last_stamp_ns = stamp_ns
        msg = conv.joy_from_sample(stamp_ns * 1e-9, s.forward, s.turn, self.params.frame_id)
        with self._shutdown_guard():
            self._joy_pub.publish(msg)
            self._published += 1

    def _on_state(self, state: LinkState, reason: str) -> None:  # reader thread
        self._last_state_reason = reason
        if state != LinkState.CONNECTED:
            self._override_mode = False  # a new connection starts in passthrough
        with self._shutdown_guard():
            self._state_gc.trigger()

    @contextlib.contextmanager
    def _shutdown_guard(self):
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
            self._override = conv.joy_to_override(msg)
        except ValueError as exc:
            self._override_rejected += 1
            self.get_logger().warn(f"override refused: {exc}", throttle_duration_sec=1.0)
            return
        self._override_t = time.monotonic()

    def _send_override(self) -> None:
        age = time.monotonic() - self._override_t
        if self._override is not None and age <= self.params.override_timeout:
            if not self._override_mode:
                self._override_mode = self.link.set_mode(Mode.OVERRIDE)
            self.link.send_override(*self._override)
        elif (self._override_mode and age > self.params.mode_release_after
              and self.link.set_mode(Mode.PASSTHROUGH)):
            # the firmware already fell back to the user after 200 ms; tidy the mode up
            self._override_mode = False

    # -- diagnostics -------------------------------------------------------------------------

    def _publish_diagnostics(self) -> None:
        st = self.link.stats()
        level = _LEVEL[st.state]
        msg = st.state.value
        if st.state == LinkState.CONNECTED:
            msg = f"connected, firmware {st.firmware}"
            if st.reconnects:
                msg += f", reconnected {st.reconnects} time(s)"
            if st.last_sample_age > self.params.sample_timeout:
                level, msg = "WARN", msg + f", no joystick sample for {st.last_sample_age:.2f} s"
        elif st.state == LinkState.CONNECTING:
            msg = f"disconnected, retrying: {st.last_error}"
        elif st.state == LinkState.STALE:
            msg = f"no heartbeat from the board for {st.last_heartbeat_age:.2f} s"
        elif st.state == LinkState.INCOMPATIBLE:
            msg = st.last_error
        fresh = time.monotonic() - self._override_t <= self.params.override_timeout
        link_status = conv.diagnostic_status(
            "serial_bridge: link", level, msg, st.port, {
                "state": st.state.value, "reason": self._last_state_reason,
                "connects": st.connects, "reconnects": st.reconnects,
                "open_failures": st.open_failures, "firmware": st.firmware,
                "board_rate_hz": st.board_rate_hz, "board_watchdog_ms": st.board_watchdog_ms,
                "frames_rx": st.frames_rx, "samples_rx": st.samples_rx,
                "joy_published": self._published, "frames_lost": st.frames_lost,
                "crc_errors": st.crc_errors, "bytes_dropped": st.bytes_dropped,
                "decode_errors": st.decode_errors, "board_errors": st.board_errors,
                "last_board_error": st.last_board_error,
                "board_crc_errors": st.board_crc_errors,
                "last_sample_age_s": st.last_sample_age,
                "last_heartbeat_age_s": st.last_heartbeat_age,
            })
        board_mode = "override" if st.board_mode == Mode.OVERRIDE else "passthrough"
        override_status = conv.diagnostic_status(
            "serial_bridge: override", "OK",
            f"{'sending' if fresh else 'idle'} (board mode {board_mode})", st.port, {
                "fresh": fresh, "overrides_sent": st.overrides_sent,
                "overrides_refused": self._override_rejected, "board_mode": board_mode,
            })
        self._diag_pub.publish(conv.diagnostic_array(
            self.get_clock().now().nanoseconds * 1e-9, [link_status, override_status]))

    def destroy_node(self) -> None:
        self.link.stop()
        super().destroy_node()


def main(args=None) -> None:
    rclpy.init(args=args)
    node = None
    try:
        node = SerialBridgeNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
