"""Link protocol codec, streaming parser, calibration and bridge parameters (pure Python)."""

from __future__ import annotations

import math
import re

import pytest
import yaml

from asgp_ros.serial import protocol as proto
from asgp_ros.serial.calibration import AxisCalibration, JoystickCalibration
from asgp_ros.serial.params import PARAMS, bridge_params

ALL_MESSAGES = [
    proto.Sample(512, 1023, proto.Status.CLAMPED | proto.Status.WATCHDOG, 0, 4095),
    proto.Override(-1000, 1000),
    proto.SetMode(proto.Mode.OVERRIDE),
    proto.Heartbeat(0xFFFFFFFF, 65535, 3, 1),
    proto.Hello(1),
    proto.Version(1, 2, 3, 4, 100, 200),
    proto.ErrorReport(proto.ErrorCode.BAD_MODE, 9),
]


def _vectors(repo_root):
    crcs, frames = [], []
    for line in (repo_root / "firmware/test/vectors.txt").read_text().splitlines():
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        if parts[0] == "crc":
            crcs.append((b"" if parts[1] == "-" else bytes.fromhex(parts[1]), int(parts[2], 16)))
        elif parts[0] == "frame":
            payload = b"" if parts[3] == "-" else bytes.fromhex(parts[3])
            frames.append((int(parts[1], 16), int(parts[2]), payload, bytes.fromhex(parts[4])))
    return crcs, frames


def test_crc_is_ccitt_false():
    assert proto.crc16(b"123456789") == 0x29B1  # catalogue check value
    assert proto.crc16(b"") == 0xFFFF
    # the table is the bitwise algorithm, byte by byte
    def bitwise(data):
        crc = 0xFFFF
        for b in data:
            crc ^= b << 8
            for _ in range(8):
                crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
        return crc
    for data in (b"\x00", b"\xa5\x5a\x09", bytes(range(256))):
        assert proto.crc16(data) == bitwise(data)


def test_shared_vectors(repo_root):
    crcs, frames = _vectors(repo_root)
    assert len(crcs) >= 3 and len(frames) >= 7
    for data, crc in crcs:
        assert proto.crc16(data) == crc, data.hex()
    for msg_type, seq, payload, frame in frames:
        assert proto.encode_frame(msg_type, seq, payload) == frame
        (got,) = proto.StreamParser().feed(frame)
        assert (got.type, got.seq, got.payload) == (msg_type, seq, payload)
        got.decode()  # every vector is a valid message


def test_doc_vectors_are_the_shared_ones(repo_root):
    doc = (repo_root / "docs/serial_protocol.md").read_text()
    shared = set((repo_root / "firmware/test/vectors.txt").read_text().splitlines())
    quoted = [ln for ln in doc.splitlines() if re.match(r"^(crc|frame) [0-9A-F-]+ ", ln)]
    assert len(quoted) >= 5
    assert set(quoted) <= shared


@pytest.mark.parametrize("msg", ALL_MESSAGES, ids=lambda m: type(m).__name__)
def test_roundtrip_every_message(msg):
    frame = proto.encode(msg, 77)
    assert frame[:2] == b"\xa5\x5a" and frame[2] == len(msg.payload()) and frame[4] == 77
    (f,) = proto.StreamParser().feed(frame)
    assert f.decode() == msg


def test_payload_lengths_match_the_spec():
    assert proto.PAYLOAD_LEN == {1: 9, 2: 4, 3: 1, 4: 9, 5: 1, 6: 8, 7: 2}


def test_override_range_and_rounding():
    assert proto.Override.from_deflection(0.5004, -0.25) == proto.Override(500, -250)
    for bad in ((1.01, 0.0), (0.0, -1.2), (math.nan, 0.0), (0.0, math.inf)):
        with pytest.raises(ValueError, match="outside"):
            proto.Override.from_deflection(*bad)
    with pytest.raises(ValueError, match="per mille"):
        proto.Override(1001, 0).payload()


def test_encode_rejects_oversized_payload():
    with pytest.raises(ValueError, match="exceeds 32"):
        proto.encode_frame(1, 0, bytes(33))
    assert proto.encode_frame(1, 256 + 5, b"")[4] == 5  # seq modulo 256
    with pytest.raises(ValueError, match="not a byte"):
        proto.encode_frame(256, 0, b"")


def test_error_report_names_unknown_codes():
    assert proto.ErrorReport(int(proto.ErrorCode(1)), 7).describe() == \
        f"{proto.ErrorCode(1).name} (detail 7)"
    assert proto.ErrorReport(200, 3).describe() == "code 200 (detail 3)"


def test_parser_reset_drops_a_partial_frame():
    msg = proto.Heartbeat(uptime_ms=1234, rx_frames=5, rx_crc_errors=0, mode=1)
    frame = proto.encode_frame(msg.TYPE, 9, msg.payload())
    parser = proto.StreamParser()
    assert parser.feed(frame[:-2]) == []
    parser.reset()
    assert parser.bytes_dropped == len(frame) - 2
    assert parser.feed(frame[-2:]) == []  # the tail alone is no frame
    assert [f.decode() for f in parser.feed(frame)] == [msg]


def test_parser_byte_by_byte_and_split_chunks():
    frames = b"".join(proto.encode(m, i) for i, m in enumerate(ALL_MESSAGES))
    p = proto.StreamParser()
    got = [f for b in frames for f in p.feed(bytes((b,)))]
    assert [f.decode() for f in got] == ALL_MESSAGES
    for cut in range(1, len(frames)):
        p = proto.StreamParser()
        got = p.feed(frames[:cut]) + p.feed(frames[cut:])
        assert len(got) == len(ALL_MESSAGES)
        assert p.crc_errors == 0 and p.bytes_dropped == 0


def test_resync_after_garbage_and_cut_frame():
    good = proto.encode(proto.Override(300, -100), 5)
    stream = (b"\x00\xa5\x13\xa5\x5a\xff"   # fake sync, impossible length
              + good[:6]                    # a frame cut by an unplug
              + good + b"\xa5")             # the next one intact, then a dangling sync byte
    p = proto.StreamParser()
    got = p.feed(stream)
    assert [f.decode() for f in got] == [proto.Override(300, -100)]
    assert p.crc_errors == 1
    assert p.pending == 1  # the trailing 0xA5 is kept: its partner may come next
    assert p.feed(good[1:]) and p.frames_ok == 2


def test_frames_hidden_inside_a_corrupt_frame_are_found_in_order():
    a = proto.encode(proto.SetMode(1), 1)
    b = proto.encode(proto.SetMode(0), 2)
    stream = b"\xa5\x5a\x14\x01\x00" + a + b + b"\x11" * 10  # claims 20 payload bytes
    got = proto.StreamParser().feed(stream)
    assert [f.seq for f in got] == [1, 2]


def test_single_bit_errors_are_never_accepted():
    frame = proto.encode(proto.Sample(600, 400, proto.Status.NONE, 2100, 2000), 9)
    for bit in range(len(frame) * 8):
        bad = bytearray(frame)
        bad[bit // 8] ^= 1 << (bit % 8)
        assert proto.StreamParser().feed(bytes(bad)) == []


def test_decode_errors_name_the_problem():
    with pytest.raises(proto.ProtocolError, match="unknown message type 0x42"):
        proto.Frame(0x42, 0, b"").decode()
    with pytest.raises(proto.ProtocolError, match="Override payload of 3 bytes, expected 4"):
        proto.Frame(proto.MsgType.OVERRIDE, 0, b"\x00\x00\x00").decode()


# -- calibration ----------------------------------------------------------------------------


def test_calibration_reference_points():
    cal = AxisCalibration(neutral=500.0, minimum=300.0, maximum=720.0, dead_zone=0.1)
    assert cal.deflection(500) == 0.0
    assert cal.deflection(500 + 0.1 * 220) == 0.0          # edge of the dead zone
    assert cal.deflection(500 - 0.1 * 200) == 0.0
    assert cal.deflection(720) == pytest.approx(1.0)
    assert cal.deflection(300) == pytest.approx(-1.0)
    assert cal.deflection(1023) == 1.0 and cal.deflection(0) == -1.0  # beyond: saturate
    # halfway between the dead zone edge and full deflection -> 0.5 (rescaled dead zone)
    assert cal.deflection(500 + 220 * 0.55) == pytest.approx(0.5)
    assert cal.deflection(500 - 200 * 0.55) == pytest.approx(-0.5)
    # continuous at the dead-zone edge
    assert cal.deflection(500 + 220 * 0.1 + 1e-6) == pytest.approx(0.0, abs=1e-6)
    inv = AxisCalibration(neutral=500.0, minimum=300.0, maximum=720.0, dead_zone=0.1,
                          invert=True)
    assert inv.deflection(720) == pytest.approx(-1.0)


def test_joystick_calibration_axes():
    cal = JoystickCalibration(forward=AxisCalibration(dead_zone=0.0),
                              turn=AxisCalibration(dead_zone=0.0, invert=True))
    f, t = cal(512 + 205, 512 + 102.5)
    assert f == pytest.approx(1.0) and t == pytest.approx(-0.5)


@pytest.mark.parametrize("kwargs, match", [
    ({"minimum": 600.0}, "minimum < neutral"),
    ({"maximum": 2000.0}, "maximum <= 1023"),
    ({"dead_zone": 0.5}, "dead_zone"),
    ({"neutral": math.nan}, "finite"),
])
def test_calibration_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        AxisCalibration(**kwargs)


def test_calibration_rejects_nonfinite_raw():
    with pytest.raises(ValueError, match="finite"):
        AxisCalibration().deflection(math.nan)
    with pytest.raises(ValueError, match="finite"):
        AxisCalibration().deflection_array([512.0, math.inf])


# -- parameters -----------------------------------------------------------------------------


def _flatten(d, prefix=""):
    for k, v in d.items():
        if isinstance(v, dict):
            yield from _flatten(v, f"{prefix}{k}.")
        else:
            yield f"{prefix}{k}", v


def test_bridge_yaml_matches_declared_parameters(repo_root):
    doc = yaml.safe_load((repo_root / "config/bridge.yaml").read_text())
    values = dict(_flatten(doc["/**/serial_bridge_node"]["ros__parameters"]))
    assert set(values) == {p.name for p in PARAMS}
    for p in PARAMS:  # same types as declared, or rclpy refuses the file
        assert type(values[p.name]) is type(p.default), p.name
    assert bridge_params(values) == bridge_params({})


@pytest.mark.parametrize("values, match", [
    ({"baud": 0}, "baud"),
    ({"override_rate": 5.0}, "override_rate"),
    ({"calibration.turn.minimum": 600.0}, "calibration.turn"),
    ({"reconnect_min": 1.0, "reconnect_max": 0.5}, "reconnect_max"),
    ({"heartbeat_timeout": 0.1, "heartbeat_period": 0.2}, "heartbeat_timeout"),
    ({"port": ""}, "port"),
    ({"port": " "}, "port"),
    ({"calibration.forward.invert": 1}, "invert"),
    ({"override_timeout": math.nan}, "override_timeout"),
    # written at the rate's ticks only: 6 Hz with 0.02 s sent 4 of 40 overrides
    ({"override_rate": 6.0, "override_timeout": 0.02}, "two periods of override_rate"),
    ({"override_rate": 6.0, "override_timeout": 0.3}, "two periods of override_rate"),
    ({"override_rate": 25.0, "override_timeout": 0.05}, "two periods of override_rate"),
])
def test_bad_parameters_are_refused_by_name(values, match):
    with pytest.raises(ValueError, match=match):
        bridge_params(values)


# -- conversions ----------------------------------------------------------------------------


def test_override_and_diagnostic_conversions():
    sensor_msgs = pytest.importorskip("sensor_msgs.msg")
    from asgp_ros.nodes import conversions as conv

    msg = sensor_msgs.Joy(axes=[0.25, -0.5, 0.9])
    assert conv.joy_to_override(msg) == (0.25, -0.5)
    for axes in ([0.1], [1.5, 0.0], [0.0, math.nan]):
        with pytest.raises(ValueError, match="joy_override"):
            conv.joy_to_override(sensor_msgs.Joy(axes=axes))
    st = conv.diagnostic_status("link", "WARN", "msg", "port", {"a": 1, "b": 0.123456})
    assert st.level == st.WARN and conv.diagnostic_values(st) == {"a": "1", "b": "0.1235"}
    with pytest.raises(ValueError, match="level"):
        conv.diagnostic_status("x", "BAD", "")
    arr = conv.diagnostic_array(12.5, [st])
    assert arr.header.stamp.sec == 12 and arr.status[0].name == "link"


def test_scalar_and_vector_calibration_agree():
    np = pytest.importorskip("numpy")
    raw = np.arange(0, 1024, dtype=float)
    for cal in (AxisCalibration(), AxisCalibration(neutral=480.0, minimum=250.0, maximum=760.0,
                                                   dead_zone=0.2, invert=True)):
        vec = cal.deflection_array(raw)
        assert np.array_equal(vec, [cal.deflection(r) for r in raw])
        assert np.all(np.diff(vec) * (-1 if cal.invert else 1) >= 0)  # monotonic


def test_the_override_timeout_said_to_be_enough_is_taken():
    """At 6 Hz the refusal said '(0.333 s) must be at least ... (0.333 s)': the minimum it
    names, rounded up, is taken."""
    with pytest.raises(ValueError, match=r"\(0\.334 s at 6 Hz\)"):
        bridge_params({"override_rate": 6.0, "override_timeout": 0.333})
    assert bridge_params({"override_rate": 6.0, "override_timeout": 0.334}) is not None


def test_an_override_timeout_of_two_rate_periods_is_taken():
    assert bridge_params({"override_rate": 6.0, "override_timeout": 2 / 6.0}) is not None
    assert bridge_params({"override_rate": 25.0, "override_timeout": 0.08}) is not None
