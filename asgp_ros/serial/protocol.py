"""The board link protocol: frames, messages, CRC-16/CCITT-FALSE and a streaming parser.

Specification: ``docs/serial_protocol.md``. The firmware's ``protocol.h`` defines the same
constants; ``test/test_firmware.py`` parses the header and checks that both agree, and
cross-checks this parser against the C one on random byte streams.

Frame (multi-byte fields little-endian)::

    0xA5 0x5A | LEN | TYPE | SEQ | PAYLOAD[LEN] | CRC16 (lo, hi)

with ``LEN <= 32`` and the CRC over ``LEN, TYPE, SEQ, PAYLOAD``.
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass, fields
from typing import ClassVar, TypeVar, Union

SYNC0 = 0xA5
SYNC1 = 0x5A
SYNC = bytes((SYNC0, SYNC1))
PROTOCOL_VERSION = 1
HEADER_LEN = 5
CRC_LEN = 2
MAX_PAYLOAD = 32
MAX_FRAME = HEADER_LEN + MAX_PAYLOAD + CRC_LEN
PERMILLE = 1000
ADC_MAX = 1023    # 10-bit joystick readings
DAC_MAX = 4095    # 12-bit output codes


class MsgType(enum.IntEnum):
    SAMPLE = 0x01
    OVERRIDE = 0x02
    MODE = 0x03
    HEARTBEAT = 0x04
    HELLO = 0x05
    VERSION = 0x06
    ERROR = 0x07


class Mode(enum.IntEnum):
    PASSTHROUGH = 0
    OVERRIDE = 1


class Status(enum.IntFlag):
    """Status byte of a SAMPLE (``ASGP_ST_*`` in the firmware)."""

    NONE = 0
    MODE_OVERRIDE = 0x01
    OVERRIDE_ACTIVE = 0x02
    WATCHDOG = 0x04
    NEUTRAL_STOP = 0x08
    CLAMPED = 0x10
    ADC_FAULT = 0x20
    HOST_LOST = 0x40


class ErrorCode(enum.IntEnum):
    BAD_CRC = 1
    BAD_LENGTH = 2
    UNKNOWN_TYPE = 3
    VERSION_MISMATCH = 4
    OVERRIDE_RANGE = 5
    NOT_IN_OVERRIDE = 6
    ADC_FAULT = 7
    BAD_MODE = 8


class ProtocolError(ValueError):
    """A frame with a valid CRC whose content is not a valid message."""


def _make_table() -> tuple[int, ...]:
    table = []
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return tuple(table)


CRC16_TABLE = _make_table()


def crc16(data: bytes | bytearray | memoryview, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, xorout 0).

    Table-driven, MSB first (Williams 1993, "A painless guide to CRC error detection
    algorithms", section 10). ``crc16(b"123456789") == 0x29B1`` (the catalogue check value).
    """
    table = CRC16_TABLE
    for byte in data:
        crc = ((crc << 8) & 0xFFFF) ^ table[((crc >> 8) ^ byte) & 0xFF]
    return crc


def encode_frame(msg_type: int, seq: int, payload: bytes = b"") -> bytes:
    """One frame around ``payload`` (at most 32 bytes); ``seq`` is taken modulo 256."""
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}")
    if not 0 <= msg_type <= 0xFF:
        raise ValueError(f"message type {msg_type} is not a byte")
    body = bytes((len(payload), msg_type, seq & 0xFF)) + bytes(payload)
    return SYNC + body + struct.pack("<H", crc16(body))


# --- messages ---------------------------------------------------------------------------


_P = TypeVar("_P", bound="_Packed")


class _Packed:
    """A message whose payload is its fields in order, packed with ``FORMAT``.

    ``RANGES`` gives the documented range of fields narrower than their wire type
    (docs/serial_protocol.md, "Messages"); :meth:`Frame.decode` refuses a frame outside them.
    """

    FORMAT: ClassVar[str]
    RANGES: ClassVar[dict[str, tuple[int, int]]] = {}

    def check(self) -> None:
        """``ProtocolError`` naming the first field outside its documented range."""
        for name, (low, high) in self.RANGES.items():
            value = int(getattr(self, name))
            if not low <= value <= high:
                raise ProtocolError(f"{type(self).__name__} {name}={value} outside "
                                    f"[{low}, {high}]")

    def _fields(self) -> tuple[int, ...]:
        return tuple(int(getattr(self, f.name)) for f in fields(self))  # type: ignore[arg-type]

    def payload(self) -> bytes:
        return struct.pack(self.FORMAT, *self._fields())

    @classmethod
    def unpack(cls: type[_P], p: bytes) -> _P:
        return cls(*struct.unpack(cls.FORMAT, p))


@dataclass(frozen=True)
class Sample(_Packed):
    """Joystick sample (board -> host): raw 10-bit ADC readings and what the board output."""

    TYPE: ClassVar[MsgType] = MsgType.SAMPLE
    FORMAT: ClassVar[str] = "<HHBHH"
    RANGES: ClassVar[dict[str, tuple[int, int]]] = {
        "raw_forward": (0, ADC_MAX), "raw_turn": (0, ADC_MAX), "status": (0, 0x7F),
        "out_forward": (0, DAC_MAX), "out_turn": (0, DAC_MAX)}
    raw_forward: int
    raw_turn: int
    status: Status
    out_forward: int  # DAC code written to the chair
    out_turn: int

    @classmethod
    def unpack(cls, p: bytes) -> Sample:
        f, t, s, of, ot = struct.unpack(cls.FORMAT, p)
        return cls(f, t, Status(s), of, ot)


@dataclass(frozen=True)
class Override(_Packed):
    """Override command (host -> board): deflections in per mille, |value| <= 1000."""

    TYPE: ClassVar[MsgType] = MsgType.OVERRIDE
    FORMAT: ClassVar[str] = "<hh"
    RANGES: ClassVar[dict[str, tuple[int, int]]] = {
        "forward": (-PERMILLE, PERMILLE), "turn": (-PERMILLE, PERMILLE)}
    forward: int
    turn: int

    def payload(self) -> bytes:
        for name, v in (("forward", self.forward), ("turn", self.turn)):
            if not -PERMILLE <= v <= PERMILLE:
                raise ValueError(f"override {name}={v} outside [-1000, 1000] per mille")
        return super().payload()

    @classmethod
    def from_deflection(cls, forward: float, turn: float) -> Override:
        """From deflections in [-1, 1] (rounded to per mille; out of range is an error)."""
        values = []
        for name, v in (("forward", forward), ("turn", turn)):
            if not -1.0 <= v <= 1.0:  # also rejects NaN
                raise ValueError(f"override {name}={v!r} outside [-1, 1]")
            values.append(round(v * PERMILLE))
        return cls(*values)


@dataclass(frozen=True)
class SetMode(_Packed):
    TYPE: ClassVar[MsgType] = MsgType.MODE
    FORMAT: ClassVar[str] = "<B"
    RANGES: ClassVar[dict[str, tuple[int, int]]] = {"mode": (0, 1)}
    mode: int


@dataclass(frozen=True)
class Heartbeat(_Packed):
    """Heartbeat (both ways): sender's uptime, frames received, CRC errors seen, its mode."""

    TYPE: ClassVar[MsgType] = MsgType.HEARTBEAT
    FORMAT: ClassVar[str] = "<IHHB"
    RANGES: ClassVar[dict[str, tuple[int, int]]] = {"mode": (0, 1)}
    uptime_ms: int
    rx_frames: int
    rx_crc_errors: int
    mode: int

    def _fields(self) -> tuple[int, ...]:  # the counters wrap
        return (self.uptime_ms & 0xFFFFFFFF, self.rx_frames & 0xFFFF,
                self.rx_crc_errors & 0xFFFF, self.mode)


@dataclass(frozen=True)
class Hello(_Packed):
    """Version handshake request (host -> board)."""

    TYPE: ClassVar[MsgType] = MsgType.HELLO
    FORMAT: ClassVar[str] = "<B"
    protocol_version: int = PROTOCOL_VERSION


@dataclass(frozen=True)
class Version(_Packed):
    """Version handshake reply (board -> host)."""

    TYPE: ClassVar[MsgType] = MsgType.VERSION
    FORMAT: ClassVar[str] = "<BBBBHH"
    RANGES: ClassVar[dict[str, tuple[int, int]]] = {
        "sample_rate_hz": (1, 1000), "watchdog_ms": (1, 60000)}
    protocol_version: int
    fw_major: int
    fw_minor: int
    fw_patch: int
    sample_rate_hz: int
    watchdog_ms: int

    @property
    def firmware(self) -> str:
        return f"{self.fw_major}.{self.fw_minor}.{self.fw_patch}"


@dataclass(frozen=True)
class ErrorReport(_Packed):
    """Error report (board -> host): an ``ErrorCode`` and a detail byte."""

    TYPE: ClassVar[MsgType] = MsgType.ERROR
    FORMAT: ClassVar[str] = "<BB"
    RANGES: ClassVar[dict[str, tuple[int, int]]] = {"code": (1, max(ErrorCode))}
    code: int
    detail: int

    def describe(self) -> str:
        try:
            name = ErrorCode(self.code).name
        except ValueError:
            name = f"code {self.code}"
        return f"{name} (detail {self.detail})"


Message = Union[Sample, Override, SetMode, Heartbeat, Hello, Version, ErrorReport]  # noqa: UP007

MESSAGE_CLASSES: dict[int, type[Message]] = {
    cls.TYPE: cls for cls in (Sample, Override, SetMode, Heartbeat, Hello, Version, ErrorReport)
}
#: Messages only a host sends: a board never does.
HOST_ONLY: tuple[type[Message], ...] = (Override, SetMode, Hello)
PAYLOAD_LEN: dict[int, int] = {
    t: struct.calcsize(cls.FORMAT) for t, cls in MESSAGE_CLASSES.items()
}


def encode(msg: Message, seq: int) -> bytes:
    """The frame of one message."""
    return encode_frame(int(msg.TYPE), seq, msg.payload())


@dataclass(frozen=True)
class Frame:
    """A frame with a valid CRC, as the parser returns it."""

    type: int
    seq: int
    payload: bytes

    def decode(self) -> Message:
        """The message in this frame; ``ProtocolError`` for an unknown type, a bad length or
        a field outside its documented range (a 10-bit reading of 2000, a mode of 7: a
        frame no board sends, whatever its CRC says)."""
        cls = MESSAGE_CLASSES.get(self.type)
        if cls is None:
            raise ProtocolError(f"unknown message type 0x{self.type:02X}")
        if len(self.payload) != PAYLOAD_LEN[self.type]:
            raise ProtocolError(
                f"{cls.__name__} payload of {len(self.payload)} bytes, "
                f"expected {PAYLOAD_LEN[self.type]}")
        msg: Message = cls.unpack(self.payload)
        msg.check()
        return msg


class StreamParser:
    """Streaming frame parser with resynchronisation.

    The same algorithm as ``asgp_parser_feed`` in the firmware: bytes accumulate in a
    buffer; anything before a sync marker, a length over 32 and a frame whose CRC does not
    match is dropped one byte at a time, so a valid frame that starts inside garbage or
    inside a cut frame is found. ``feed`` never raises on any input.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.frames_ok = 0
        self.crc_errors = 0
        self.bytes_dropped = 0
        # for each frame the last feed or expire returned, in order: how many bytes came
        # after its last byte (0: it ended with the newest byte); the board times each
        # frame by its own last byte with it (``frame_end_ms`` in the firmware)
        self.behind: list[int] = []

    @property
    def pending(self) -> int:
        """Bytes held waiting for the rest of a frame."""
        return len(self._buf)

    def reset(self) -> None:
        """Forget a partial frame (after a reconnection)."""
        self.bytes_dropped += len(self._buf)
        self._buf.clear()

    def expire(self) -> list[Frame]:
        """Gives up the partial frame at the start of the buffer (``asgp_parser_expire``:
        the line went idle, its rest is not coming): drops one byte and rescans, as for a
        bad CRC; returns the complete frames found. Call again while bytes are held."""
        if not self._buf:
            self.behind = []
            return []
        del self._buf[:1]
        self.bytes_dropped += 1
        return self.feed(b"")

    def feed(self, data: bytes | bytearray | memoryview) -> list[Frame]:
        """Frames completed by ``data``, in order."""
        buf = self._buf
        buf += data
        frames: list[Frame] = []
        self.behind = []
        start = 0
        n = len(buf)
        while True:
            # skip to the next sync marker
            i = buf.find(SYNC, start)
            if i < 0:
                # keep a trailing first sync byte: its partner may come with the next read
                keep = 1 if n > start and buf[n - 1] == SYNC0 else 0
                self.bytes_dropped += n - start - keep
                start = n - keep
                break
            self.bytes_dropped += i - start
            start = i
            if n - start < 3:
                break
            length = buf[start + 2]
            if length > MAX_PAYLOAD:
                self.bytes_dropped += 1
                start += 1
                continue
            total = HEADER_LEN + length + CRC_LEN
            if n - start < total:
                break
            body = buf[start + 2:start + HEADER_LEN + length]
            got = buf[start + HEADER_LEN + length] | (buf[start + HEADER_LEN + length + 1] << 8)
            if crc16(body) != got:
                self.crc_errors += 1
                self.bytes_dropped += 1
                start += 1
                continue
            frames.append(Frame(buf[start + 3], buf[start + 4],
                                bytes(buf[start + HEADER_LEN:start + HEADER_LEN + length])))
            self.frames_ok += 1
            self.behind.append(n - start - total)  # the buffer ends with the newest byte
            start += total
        del buf[:start]
        return frames

