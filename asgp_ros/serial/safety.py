"""Python mirror of the firmware's safety and link logic (``firmware/asgp_bridge``).

The simulated board (:mod:`asgp_ros.sim.board`) runs this code so that it behaves like
the real board: the same integer arithmetic, the same rules, the same frames out.
``test/test_firmware.py`` checks the constants against ``config.h``/``protocol.h`` and runs
random scenarios through both this module and the compiled C (``proto_tool``), requiring
byte-identical output. The rules (docs/serial_protocol.md, "Safety rules"):

1. A joystick reading outside [ADC_FAULT_LOW, ADC_FAULT_HIGH] -> neutral output.
2. The user's joystick inside the dead band on both axes -> neutral output in every mode:
   letting go is a stop request that no override can overrule.
3. Mode override and an override younger than WATCHDOG_MS -> the override is the output;
   otherwise the user's joystick is passed through.
4. Every output is limited per axis and clamped to the DAC's safe window.
5. No valid frame from the host for HOST_TIMEOUT_MS -> mode passthrough.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

from asgp_ros.common import board
from asgp_ros.serial import protocol as proto
from asgp_ros.serial.protocol import ErrorCode, Mode, MsgType, Status

# config.h
FW_VERSION = (1, 0, 0)
BAUD = 115200
SAMPLE_RATE_HZ = 100
HEARTBEAT_EVERY = 20
WATCHDOG_MS = board.WATCHDOG_MS
HOST_TIMEOUT_MS = 1000
RX_IDLE_MS = 20
ADC_NEUTRAL = 512
ADC_SPAN = board.ADC_SPAN
ADC_DEADBAND = board.ADC_DEADBAND
ADC_FAULT_LOW = 41
ADC_FAULT_HIGH = 982
DAC_NEUTRAL = 2048
DAC_SPAN = 819
DAC_MIN = 1229
DAC_MAX = 2867
FWD_LIMIT_POS = 1000
FWD_LIMIT_NEG = 1000
TURN_LIMIT_POS = 1000
TURN_LIMIT_NEG = 1000

_U32 = 0xFFFFFFFF


def _cdiv(a: int, b: int) -> int:
    """C integer division (truncates toward zero), unlike Python's floor division."""
    q = abs(a) // abs(b)
    return q if (a >= 0) == (b >= 0) else -q


@dataclass(frozen=True)
class AxisCal:
    """Calibration of one analog channel (``asgp_axis_cal_t``)."""

    adc_neutral: int = ADC_NEUTRAL
    adc_span: int = ADC_SPAN
    adc_deadband: int = ADC_DEADBAND
    adc_fault_low: int = ADC_FAULT_LOW
    adc_fault_high: int = ADC_FAULT_HIGH
    limit_pos: int = 1000
    limit_neg: int = 1000
    dac_neutral: int = DAC_NEUTRAL
    dac_span: int = DAC_SPAN
    dac_min: int = DAC_MIN
    dac_max: int = DAC_MAX

    def __post_init__(self) -> None:
        for name in ("adc_neutral", "adc_span", "adc_deadband", "adc_fault_low",
                     "adc_fault_high", "limit_pos", "limit_neg", "dac_neutral", "dac_span",
                     "dac_min", "dac_max"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise ValueError(f"{name} must be an integer (the firmware's arithmetic), "
                                 f"got {value!r}")
        for name, high in (("adc_neutral", proto.ADC_MAX), ("adc_span", proto.ADC_MAX),
                           ("adc_fault_low", proto.ADC_MAX), ("adc_fault_high", proto.ADC_MAX),
                           ("dac_neutral", proto.DAC_MAX), ("dac_span", proto.DAC_MAX),
                           ("dac_min", proto.DAC_MAX), ("dac_max", proto.DAC_MAX)):
            if not 0 <= getattr(self, name) <= high:
                raise ValueError(f"{name} must be in [0, {high}], got {getattr(self, name)}")
        if self.adc_span < 1 or self.dac_span < 1:
            raise ValueError("adc_span and dac_span must be at least 1")
        if not self.adc_fault_low <= self.adc_neutral <= self.adc_fault_high:
            raise ValueError("the plausible ADC window must contain the neutral reading")
        if not 0 <= self.adc_deadband < self.adc_span:
            raise ValueError(f"dead band {self.adc_deadband} must be in [0, {self.adc_span})")
        if not self.dac_min <= self.dac_neutral <= self.dac_max:
            raise ValueError("DAC window must contain the neutral code")
        if not (0 <= self.limit_pos <= 1000 and 0 <= self.limit_neg <= 1000):
            raise ValueError("per-axis limits must be in [0, 1000] per mille")

    def adc_to_permille(self, raw: int) -> int:
        d = raw - self.adc_neutral
        mag = abs(d)
        if mag <= self.adc_deadband:
            return 0
        usable = self.adc_span - self.adc_deadband
        pm = min(_cdiv((mag - self.adc_deadband) * 1000 + usable // 2, usable), 1000)
        return -pm if d < 0 else pm

    def permille_to_dac(self, pm: int) -> tuple[int, bool]:
        """DAC code for a deflection in per mille, and whether it was clamped."""
        clamped = False
        v = pm
        if v > self.limit_pos:
            v, clamped = self.limit_pos, True
        elif v < -self.limit_neg:
            v, clamped = -self.limit_neg, True
        num = v * self.dac_span
        off = _cdiv(num + 500 if num >= 0 else num - 500, 1000)
        code = self.dac_neutral + off
        if code > self.dac_max:
            code, clamped = self.dac_max, True
        elif code < self.dac_min:
            code, clamped = self.dac_min, True
        return code, clamped

    def dac_to_deflection(self, code: int) -> float:
        """What a DAC code means to the chair, as a deflection in [-1, 1]."""
        return max(-1.0, min(1.0, (code - self.dac_neutral) / self.dac_span))


def default_calibration() -> tuple[AxisCal, AxisCal]:
    """(forward, turn) calibration of ``asgp_default_calibration``."""
    return (AxisCal(limit_pos=FWD_LIMIT_POS, limit_neg=FWD_LIMIT_NEG),
            AxisCal(limit_pos=TURN_LIMIT_POS, limit_neg=TURN_LIMIT_NEG))


@dataclass(frozen=True)
class Output:
    """One control step's result (``asgp_output_t``)."""

    user_pm: tuple[int, int] = (0, 0)
    out_pm: tuple[int, int] = (0, 0)
    out_code: tuple[int, int] = (DAC_NEUTRAL, DAC_NEUTRAL)
    status: Status = Status.NONE


@dataclass
class Safety:
    """The safety state machine (``asgp_safety_t`` and its functions)."""

    mode: int = Mode.PASSTHROUGH
    have_override: bool = False
    override_pm: tuple[int, int] = (0, 0)
    override_ms: int = 0
    host_seen: bool = False
    host_ms: int = 0

    def host_alive(self, now_ms: int) -> None:
        self.host_seen = True
        self.host_ms = now_ms & _U32

    def set_mode(self, mode: int, now_ms: int) -> int:
        if mode not in (Mode.PASSTHROUGH, Mode.OVERRIDE):
            return ErrorCode.BAD_MODE
        if mode != self.mode:
            self.have_override = False
        self.mode = mode
        return 0

    def set_override(self, fwd_pm: int, turn_pm: int, now_ms: int) -> int:
        if not (-1000 <= fwd_pm <= 1000 and -1000 <= turn_pm <= 1000):
            return ErrorCode.OVERRIDE_RANGE
        if self.mode != Mode.OVERRIDE:
            return ErrorCode.NOT_IN_OVERRIDE
        self.override_pm = (fwd_pm, turn_pm)
        self.override_ms = now_ms & _U32
        self.have_override = True
        return 0

    def step(self, cal: tuple[AxisCal, AxisCal], raw: tuple[int, int], now_ms: int) -> Output:
        now_ms &= _U32
        status = Status.NONE
        if (self.mode == Mode.OVERRIDE and self.host_seen
                and ((now_ms - self.host_ms) & _U32) >= HOST_TIMEOUT_MS):
            self.mode = Mode.PASSTHROUGH
            self.have_override = False
            status |= Status.HOST_LOST
        if self.mode == Mode.OVERRIDE:
            status |= Status.MODE_OVERRIDE
        fault = any(r < c.adc_fault_low or r > c.adc_fault_high
                    for r, c in zip(raw, cal, strict=True))
        user = (cal[0].adc_to_permille(raw[0]), cal[1].adc_to_permille(raw[1]))
        if self.have_override and ((now_ms - self.override_ms) & _U32) >= WATCHDOG_MS:
            self.have_override = False  # stale once is stale for good (2^32 ms later too)
        fresh = self.mode == Mode.OVERRIDE and self.have_override
        if self.mode == Mode.OVERRIDE and not fresh:
            status |= Status.WATCHDOG
        if fault:
            status |= Status.ADC_FAULT
            out = (0, 0)
        elif user == (0, 0):
            if fresh:
                status |= Status.NEUTRAL_STOP
            out = (0, 0)
        elif fresh:
            status |= Status.OVERRIDE_ACTIVE
            out = self.override_pm
        else:
            out = user
        c0, k0 = cal[0].permille_to_dac(out[0])
        c1, k1 = cal[1].permille_to_dac(out[1])
        if k0 or k1:
            status |= Status.CLAMPED
        return Output(user, out, (c0, c1), status)


_EXPECTED_LEN = {MsgType.OVERRIDE: 4, MsgType.MODE: 1, MsgType.HEARTBEAT: 9, MsgType.HELLO: 1}


@dataclass
class BoardLogic:
    """The board's link logic (``asgp_board_t``): bytes in, ticks -> frames out.

    ``write`` receives every frame the board sends. Time is the board's millisecond clock.
    """

    write: Callable[[bytes], None]
    cal: tuple[AxisCal, AxisCal] = field(default_factory=default_calibration)
    sample_rate_hz: int = SAMPLE_RATE_HZ
    watchdog_ms: int = WATCHDOG_MS

    def __post_init__(self) -> None:
        self.parser = proto.StreamParser()
        self.safety = Safety()
        self.out = Output()
        self.tx_seq = 0
        self.pending_error = 0
        self.pending_detail = 0
        self.rx_frames = 0
        self.tick_count = 0
        self.pending_version = False
        self.last_rx_ms = 0
        # when each of the last MAX_FRAME bytes came (``rx_ms``): a frame is timed by its
        # own last byte, however late the parser finds it
        self.rx_ms: deque[int] = deque(maxlen=proto.MAX_FRAME)
        # heartbeats at the firmware's 5 Hz whatever the simulated rate (every 20 ticks at
        # 100 Hz: at 10 Hz, every 20 ticks let the host's 0.6 s supervision go stale)
        self.heartbeat_every = max(1, round(self.sample_rate_hz * HEARTBEAT_EVERY
                                            / SAMPLE_RATE_HZ))

    def _send(self, msg_type: int, payload: bytes) -> None:
        self.write(proto.encode_frame(msg_type, self.tx_seq, payload))
        self.tx_seq = (self.tx_seq + 1) & 0xFF

    def _report(self, code: int, detail: int) -> None:
        self.pending_error, self.pending_detail = int(code), detail & 0xFF

    def rx(self, data: bytes, now_ms: int) -> None:
        """Bytes from the host; complete frames are acted on at once."""
        if data:
            self.last_rx_ms = now_ms & _U32
        for byte in data:  # byte by byte, so a CRC error is reported like the firmware does
            self.rx_ms.append(now_ms & _U32)
            crc_before = self.parser.crc_errors
            frames = self.parser.feed(bytes((byte,)))
            if self.parser.crc_errors != crc_before:
                self._report(ErrorCode.BAD_CRC, 0)
            self._handle_all(frames)

    def _handle_all(self, frames: list[proto.Frame]) -> None:
        """The frames the parser just returned, each timed by its own last byte
        (``frame_end_ms``): not by the byte that completed, or the tick that gave up, the
        candidate in front of it, up to 39 bytes (at 19 ms each) later."""
        for f, behind in zip(frames, self.parser.behind, strict=True):
            self._handle(f, self.rx_ms[-1 - behind])

    def _handle(self, f: proto.Frame, now_ms: int) -> None:
        if f.type not in _EXPECTED_LEN:
            self._report(ErrorCode.UNKNOWN_TYPE, f.type)
            return
        if len(f.payload) != _EXPECTED_LEN[MsgType(f.type)]:
            self._report(ErrorCode.BAD_LENGTH, f.type)
            return
        self.rx_frames = (self.rx_frames + 1) & 0xFFFF
        self.safety.host_alive(now_ms)
        err = 0
        if f.type == MsgType.HELLO:
            self.pending_version = True  # at the next tick: one VERSION a tick
            if f.payload[0] != proto.PROTOCOL_VERSION:
                self._report(ErrorCode.VERSION_MISMATCH, f.payload[0])
        elif f.type == MsgType.MODE:
            err = self.safety.set_mode(f.payload[0], now_ms)
        elif f.type == MsgType.OVERRIDE:
            o = proto.Override.unpack(f.payload)
            err = self.safety.set_override(o.forward, o.turn, now_ms)
        if err:
            self._report(err, f.seq)

    def tick(self, raw: tuple[int, int], now_ms: int) -> Output:
        """One control tick: a partial frame idle for RX_IDLE_MS given up, safety step,
        SAMPLE (+ HEARTBEAT, VERSION, ERROR) frames out."""
        if self.parser.pending and ((now_ms - self.last_rx_ms) & _U32) >= RX_IDLE_MS:
            self._expire()
        was_fault = Status.ADC_FAULT in self.out.status
        self.out = self.safety.step(self.cal, raw, now_ms)
        if Status.ADC_FAULT in self.out.status and not was_fault:
            self._report(ErrorCode.ADC_FAULT, 0)
        self._send(MsgType.SAMPLE, proto.Sample(raw[0] & 0xFFFF, raw[1] & 0xFFFF, self.out.status,
                                            *self.out.out_code).payload())
        self.tick_count += 1
        if self.tick_count >= self.heartbeat_every:
            self.tick_count = 0
            self._send(MsgType.HEARTBEAT, proto.Heartbeat(
                now_ms, self.rx_frames, self.parser.crc_errors, self.safety.mode).payload())
        if self.pending_version:
            self.pending_version = False
            major, minor, patch = FW_VERSION
            self._send(MsgType.VERSION, proto.Version(
                proto.PROTOCOL_VERSION, major, minor, patch, self.sample_rate_hz,
                self.watchdog_ms).payload())
        if self.pending_error:
            self._send(MsgType.ERROR, bytes((self.pending_error, self.pending_detail)))
            self.pending_error = 0
        return self.out

    def _expire(self) -> None:
        """The partial frame held is given up (``expire_rx``): frames found behind it are
        acted on, each timed by its own last byte."""
        crc_before = self.parser.crc_errors
        while self.parser.pending:
            self._handle_all(self.parser.expire())
        if self.parser.crc_errors != crc_before:
            self._report(ErrorCode.BAD_CRC, 0)
