"""Every number that enters the host from a frame or a parameter has a documented finite
range, checked where it enters (docs/serial_protocol.md): a frame with a valid CRC but an
impossible value is refused like a garbled one, and parameters such as 1e30 or NaN are
refused with the parameter's name and the reason."""

from __future__ import annotations

import math
import re
import struct
import time

import pytest

from asgp_ros.serial import protocol as proto
from asgp_ros.serial.calibration import AxisCalibration
from asgp_ros.serial.link import LinkConfig, LinkManager, LinkState
from asgp_ros.serial.params import bridge_params
from asgp_ros.sim.board import SimulatedBoard


def wait_until(pred, timeout: float, period: float = 0.005) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(period)
    return bool(pred())


@pytest.mark.parametrize("msg_type, payload, match", [
    (proto.MsgType.SAMPLE, struct.pack("<HHBHH", 2000, 512, 0, 2048, 2048),
     "raw_forward=2000 outside"),
    (proto.MsgType.SAMPLE, struct.pack("<HHBHH", 512, 1024, 0, 2048, 2048), "raw_turn"),
    (proto.MsgType.SAMPLE, struct.pack("<HHBHH", 512, 512, 0x80, 2048, 2048), "status=128"),
    (proto.MsgType.SAMPLE, struct.pack("<HHBHH", 512, 512, 0, 4096, 2048), "out_forward"),
    (proto.MsgType.SAMPLE, struct.pack("<HHBHH", 512, 512, 0, 2048, 65535), "out_turn"),
    (proto.MsgType.OVERRIDE, struct.pack("<hh", 1001, 0), "forward=1001"),
    (proto.MsgType.MODE, bytes((2,)), "mode=2"),
    (proto.MsgType.HEARTBEAT, struct.pack("<IHHB", 0, 0, 0, 9), "mode=9"),
    (proto.MsgType.VERSION, struct.pack("<BBBBHH", 1, 1, 0, 0, 0, 200), "sample_rate_hz=0"),
    (proto.MsgType.VERSION, struct.pack("<BBBBHH", 1, 1, 0, 0, 100, 0), "watchdog_ms=0"),
    (proto.MsgType.ERROR, bytes((0, 0)), "code=0"),
    (proto.MsgType.ERROR, bytes((99, 0)), "code=99"),
], ids=["raw_forward", "raw_turn", "status", "out_forward", "out_turn", "override", "mode",
        "heartbeat_mode", "sample_rate", "watchdog", "error_code_0", "error_code_99"])
def test_frames_with_values_outside_their_range_are_refused(msg_type, payload, match):
    (frame,) = proto.StreamParser().feed(proto.encode_frame(msg_type, 1, payload))
    with pytest.raises(proto.ProtocolError, match=match):
        frame.decode()


def test_range_edges_decode():
    for msg in (proto.Sample(0, 1023, proto.Status(0x7F), 0, 4095),
                proto.Override(-1000, 1000), proto.SetMode(1), proto.Heartbeat(0, 0, 0, 1),
                proto.Version(1, 0, 0, 0, 1, 60000), proto.Version(1, 0, 0, 0, 1000, 1),
                proto.ErrorReport(1, 0), proto.ErrorReport(8, 255)):
        (frame,) = proto.StreamParser().feed(proto.encode(msg, 3))
        assert frame.decode() == msg


def test_impossible_sample_is_never_delivered(tmp_path):
    """A SAMPLE whose CRC passes but whose reading no 10-bit ADC gives (2000) is dropped and
    counted, not calibrated into a full deflection."""
    board = SimulatedBoard(lambda t: (0.2, 0.0), link_path=tmp_path / "joy").start()
    samples: list = []
    try:
        with LinkManager(LinkConfig(board.port), on_sample=samples.append) as link:
            assert link.wait_for_state(LinkState.CONNECTED, 3.0)
            assert wait_until(lambda: len(samples) > 5, 2.0)
            bad = struct.pack("<HHBHH", 2000, 512, 0, 2048, 2048)
            board.inject(proto.encode_frame(proto.MsgType.SAMPLE, 200, bad))
            assert wait_until(lambda: link.stats().decode_errors == 1, 2.0)
            n = len(samples)
            assert wait_until(lambda: len(samples) > n + 5, 2.0)  # and the stream goes on
            assert "raw_forward=2000" in link.stats().last_error
            assert link.state == LinkState.CONNECTED
    finally:
        board.stop()
    assert all(s.raw_forward <= 1023 for s in samples)
    assert all(s.forward is not None and s.forward < 0.5 for s in samples)


@pytest.mark.parametrize("kwargs, match", [
    ({"read_timeout": math.inf}, "read_timeout"),
    ({"read_timeout": 5.0}, "read_timeout"),
    ({"silence_reopen": 1e30}, "silence_reopen"),
    ({"heartbeat_period": math.nan}, "heartbeat_period"),
    ({"reconnect_max": math.inf}, "reconnect_max"),
    ({"baud": 10**12}, "baud"),
    ({"baud": 115200.5}, "baud"),
])
def test_link_config_refuses_non_finite_and_huge_values(kwargs, match):
    with pytest.raises(ValueError, match=match):
        LinkConfig("/dev/null", **kwargs)


@pytest.mark.parametrize("name", [
    "calibration.forward.neutral", "calibration.turn.maximum", "calibration.forward.dead_zone",
    "override_timeout", "override_rate", "heartbeat_period", "silence_reopen",
    "diagnostics_period", "sample_timeout", "reconnect_min"])
@pytest.mark.parametrize("value, reason", [(1e30, "outside"), (-1e30, "outside"),
                                          (math.nan, "finite"), (math.inf, "finite")])
def test_bridge_parameters_refuse_huge_and_non_finite_values(name, value, reason):
    with pytest.raises(ValueError, match=rf"parameter {name}.*{reason}"):
        bridge_params({name: value})


@pytest.mark.parametrize("kwargs", [{"neutral": math.nan}, {"maximum": math.inf},
                                    {"minimum": -1e30}, {"dead_zone": math.nan}])
def test_calibration_refuses_non_finite_values(kwargs):
    with pytest.raises(ValueError, match=r"finite|minimum"):
        AxisCalibration(**kwargs)


def test_simulated_board_refuses_bad_numbers():
    with pytest.raises(ValueError, match="noise_counts"):
        SimulatedBoard(noise_counts=math.nan)
    with pytest.raises(ValueError, match="rate_hz"):
        SimulatedBoard(rate_hz=math.inf)
    board = SimulatedBoard()
    for raw in ((1024, 512), (-1, 512), (512.5, 512), (512,)):
        with pytest.raises(ValueError, match="raw ADC"):
            board.set_raw_override(raw)


@pytest.mark.ros
def test_node_refuses_huge_and_non_finite_parameters_at_runtime(rclpy_context, tmp_path):
    pytest.importorskip("rclpy")
    from rclpy.parameter import Parameter

    from asgp_ros.nodes.serial_bridge_node import SerialBridgeNode

    node = SerialBridgeNode(context=rclpy_context, parameter_overrides=[
        Parameter("port", value=str(tmp_path / "absent"))])
    try:
        for name, value in (("calibration.forward.neutral", 1e30),
                            ("calibration.turn.minimum", math.nan),
                            ("override_timeout", math.inf), ("override_rate", -1e30)):
            (r,) = node.set_parameters([Parameter(name, value=value)])
            # rclpy's range check (from the declared descriptor) or ours answers first
            assert not r.successful and name in r.reason, r.reason
            assert re.search("out of range|outside|finite", r.reason), r.reason
        assert node.params.calibration.forward.neutral == 512.0  # unchanged
    finally:
        node.destroy_node()


@pytest.mark.parametrize("kwargs, match", [
    ({"adc_neutral": 5000}, "adc_neutral"), ({"adc_span": 0}, "span"),
    ({"dac_max": 70000}, "dac_max"), ({"adc_fault_high": 100}, "window"),
    ({"adc_neutral": 512.5}, "integer"), ({"limit_pos": 2000}, "limits"),
    ({"dac_min": 2100, "dac_neutral": 2048}, "DAC window"),
])
def test_firmware_mirror_calibration_ranges(kwargs, match):
    from asgp_ros.serial import safety as fw

    with pytest.raises(ValueError, match=match):
        fw.AxisCal(**kwargs)


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.parametrize("param, name", [
    ("calibration.forward.neutral:=1e30", "calibration.forward.neutral"),
    ("calibration.turn.dead_zone:=.nan", "calibration.turn.dead_zone"),
    ("reconnect_max:=0.01", "reconnect_max"),
])
def test_node_process_refuses_bad_startup_parameters_in_one_line(repo_root, param, name):
    import os
    import subprocess
    import sys

    r = subprocess.run(
        [sys.executable, "-m", "asgp_ros.nodes.serial_bridge_node", "--ros-args",
         "-p", "port:=/nonexistent/asgp_joystick", "-p", param],
        cwd=repo_root, env=dict(os.environ, PYTHONPATH=str(repo_root)),
        capture_output=True, text=True, timeout=60)
    out = r.stdout + r.stderr
    assert r.returncode == 1, out
    assert "refusing to start" in out and name in out, out
    assert "Traceback" not in out, out
