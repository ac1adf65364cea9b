"""Link manager: the host end of the serial link to the joystick interface board.

One reader thread owns the port: it opens it (retrying with exponential backoff while the
device is absent), performs the version handshake, parses frames, hands joystick samples
to a callback with their reception time, sends heartbeats and supervises the board's,
and reopens the port when it fails (USB unplug) or goes silent. Other threads send
override and mode commands through :meth:`LinkManager.send_override` /
:meth:`LinkManager.set_mode`. No ROS here: the node wires the callbacks to topics.
"""

from __future__ import annotations

import enum
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import serial

from asgp_ros.serial import protocol as proto
from asgp_ros.serial.calibration import JoystickCalibration

log = logging.getLogger(__name__)


class LinkState(enum.Enum):
    STOPPED = "stopped"          # not started or stopped
    CONNECTING = "connecting"    # port absent or failing to open; retrying with backoff
    HANDSHAKE = "handshake"      # port open, waiting for the board's VERSION
    CONNECTED = "connected"      # handshake done, board heartbeats arriving
    STALE = "stale"              # port open but no heartbeat within heartbeat_timeout
    INCOMPATIBLE = "incompatible"  # the board speaks another protocol version


@dataclass(frozen=True)
class LinkConfig:
    """Link parameters (seconds). ``port`` may be a stable udev symlink."""

    port: str
    baud: int = 115200
    read_timeout: float = 0.02
    handshake_timeout: float = 0.3
    heartbeat_period: float = 0.2
    heartbeat_timeout: float = 0.6
    silence_reopen: float = 2.0
    reconnect_min: float = 0.05
    reconnect_max: float = 0.25
    calibration: JoystickCalibration = field(default_factory=JoystickCalibration)

    def __post_init__(self) -> None:
        if not self.port:
            raise ValueError("serial port path is empty")
        if self.baud <= 0:
            raise ValueError(f"baud must be positive, got {self.baud}")
        for name in ("read_timeout", "handshake_timeout", "heartbeat_period",
                     "heartbeat_timeout", "silence_reopen", "reconnect_min", "reconnect_max"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0 s, got {getattr(self, name)}")
        if self.reconnect_max < self.reconnect_min:
            raise ValueError("reconnect_max must be >= reconnect_min")
        if self.heartbeat_timeout <= self.heartbeat_period:
            raise ValueError("heartbeat_timeout must exceed heartbeat_period")


@dataclass(frozen=True)
class JoystickSample:
    """One SAMPLE frame as received: ``t_rx`` is ``time.monotonic()`` when its bytes arrived."""

    t_rx: float
    seq: int
    raw_forward: int
    raw_turn: int
    forward: float       # calibrated deflection in [-1, 1], + forward
    turn: float          # calibrated deflection in [-1, 1], + left
    status: proto.Status
    out_forward: int     # DAC codes the board wrote to the chair
    out_turn: int


@dataclass(frozen=True)
class LinkStats:
    """A consistent snapshot of the link for diagnostics."""

    state: LinkState
    port: str
    connects: int
    reconnects: int
    open_failures: int
    frames_rx: int
    samples_rx: int
    frames_lost: int           # gaps in the board's sequence numbers
    crc_errors: int
    bytes_dropped: int
    decode_errors: int
    board_errors: int          # ERROR frames received
    last_board_error: str
    last_error: str
    firmware: str
    board_rate_hz: int
    board_watchdog_ms: int
    board_mode: int
    board_crc_errors: int      # CRC errors the board saw in our frames
    overrides_sent: int
    last_sample_age: float     # s, inf if none
    last_heartbeat_age: float  # s, inf if none


class LinkManager:
    """Owns the serial port in a reader thread; see the module docstring.

    ``on_sample(JoystickSample)`` and ``on_state(LinkState, reason)`` run in the reader
    thread: keep them short (store, or wake another thread).
    """

    def __init__(self, config: LinkConfig,
                 on_sample: Callable[[JoystickSample], None] | None = None,
                 on_state: Callable[[LinkState, str], None] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.config = config
        self._on_sample = on_sample
        self._on_state = on_state
        self._clock = clock
        self._lock = threading.Lock()        # counters and state
        self._write_lock = threading.Lock()  # the port's write side
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._ser: serial.Serial | None = None
        self._parser = proto.StreamParser()
        self._tx_seq = 0
        self._state = LinkState.STOPPED
        self._connects = 0
        self._open_failures = 0
        self._frames_rx = 0
        self._samples_rx = 0
        self._frames_lost = 0
        self._crc_base = 0
        self._dropped_base = 0
        self._decode_errors = 0
        self._board_errors = 0
        self._last_board_error = ""
        self._last_error = ""
        self._version: proto.Version | None = None
        self._board_mode = proto.Mode.PASSTHROUGH
        self._board_crc_errors = 0
        self._overrides_sent = 0
        self._last_seq: int | None = None
        self._last_sample_t = -float("inf")
        self._last_heartbeat_t = -float("inf")
        self._last_rx_t = -float("inf")

    # -- public API --------------------------------------------------------------------

    @property
    def state(self) -> LinkState:
        return self._state

    @property
    def version(self) -> proto.Version | None:
        return self._version

    def start(self) -> None:
        if self._thread is not None:
            raise RuntimeError("link already started")
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="asgp-serial-link", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        """Stops the reader; asks the board for passthrough first if connected."""
        if self._state in (LinkState.CONNECTED, LinkState.STALE):
            self.set_mode(proto.Mode.PASSTHROUGH)
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            if self._thread.is_alive():
                log.warning("serial reader thread did not stop within %.1f s", timeout)
            self._thread = None
        self._set_state(LinkState.STOPPED, "stopped")

    def __enter__(self) -> LinkManager:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def wait_for_state(self, state: LinkState, timeout: float) -> bool:
        """Polls until the link is in ``state`` (tests and tools)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self._state == state:
                return True
            time.sleep(0.005)
        return self._state == state

    def send_override(self, forward: float, turn: float) -> bool:
        """Sends one override (deflections in [-1, 1]); False if the link is not up.

        The board only uses it in override mode and for ``watchdog_ms`` (200 ms): the
        caller repeats it while its command is fresh and simply stops when it is not.
        """
        msg = proto.Override.from_deflection(forward, turn)
        ok = self._send(msg)
        if ok:
            with self._lock:
                self._overrides_sent += 1
        return ok

    def set_mode(self, mode: proto.Mode) -> bool:
        return self._send(proto.SetMode(int(mode)))

    def stats(self) -> LinkStats:
        now = self._clock()
        with self._lock:
            v = self._version
            return LinkStats(
                state=self._state, port=self.config.port, connects=self._connects,
                reconnects=max(0, self._connects - 1), open_failures=self._open_failures,
                frames_rx=self._frames_rx, samples_rx=self._samples_rx,
                frames_lost=self._frames_lost,
                crc_errors=self._crc_base + self._parser.crc_errors,
                bytes_dropped=self._dropped_base + self._parser.bytes_dropped,
                decode_errors=self._decode_errors, board_errors=self._board_errors,
                last_board_error=self._last_board_error, last_error=self._last_error,
                firmware=v.firmware if v else "", board_rate_hz=v.sample_rate_hz if v else 0,
                board_watchdog_ms=v.watchdog_ms if v else 0, board_mode=int(self._board_mode),
                board_crc_errors=self._board_crc_errors, overrides_sent=self._overrides_sent,
                last_sample_age=now - self._last_sample_t,
                last_heartbeat_age=now - self._last_heartbeat_t,
            )

    # -- internals ---------------------------------------------------------------------

    def _set_state(self, state: LinkState, reason: str) -> None:
        with self._lock:
            if state == self._state:
                return
            self._state = state
        log.info("serial link %s: %s (%s)", self.config.port, state.value, reason)
        if self._on_state is not None:
            self._on_state(state, reason)

    def _send(self, msg: proto.Message) -> bool:
        with self._write_lock:
            ser = self._ser
            if ser is None or self._state not in (LinkState.CONNECTED, LinkState.STALE,
                                                  LinkState.HANDSHAKE):
                return False
            frame = proto.encode(msg, self._tx_seq)
            self._tx_seq = (self._tx_seq + 1) & 0xFF
            try:
                ser.write(frame)
            except (serial.SerialException, OSError) as exc:
                # the reader thread notices the dead port on its next read and reopens it
                log.debug("write to %s failed: %s", self.config.port, exc)
                return False
        return True

    def _run(self) -> None:
        delay = self.config.reconnect_min
        while not self._stop.is_set():
            try:
                ser = serial.Serial(self.config.port, self.config.baud,
                                    timeout=self.config.read_timeout, write_timeout=0.2)
            except (serial.SerialException, OSError, ValueError) as exc:
                with self._lock:
                    self._open_failures += 1
                    self._last_error = f"open failed: {exc}"
                self._set_state(LinkState.CONNECTING, f"cannot open {self.config.port}")
                self._stop.wait(delay)
                delay = min(2.0 * delay, self.config.reconnect_max)
                continue
            delay = self.config.reconnect_min
            try:
                self._serve(ser)
            except (serial.SerialException, OSError) as exc:
                with self._lock:
                    self._last_error = f"port lost: {exc}"
                log.warning("serial port %s lost: %s", self.config.port, exc)
                self._set_state(LinkState.CONNECTING, "port lost")
            finally:
                with self._write_lock:
                    self._ser = None
                try:
                    ser.close()
                except (serial.SerialException, OSError) as exc:
                    log.debug("closing %s: %s", self.config.port, exc)

    def _serve(self, ser: serial.Serial) -> None:
        """Runs one connection until the port fails, goes silent, or stop() is called."""
        cfg = self.config
        ser.reset_input_buffer()  # bytes the board sent while nobody listened
        with self._lock:
            self._crc_base += self._parser.crc_errors
            self._dropped_base += self._parser.bytes_dropped
            self._parser = proto.StreamParser()
            self._last_seq = None
            self._version = None
            self._connects += 1
        with self._write_lock:
            self._ser = ser
        self._set_state(LinkState.HANDSHAKE, f"opened {cfg.port}")
        t_open = self._clock()
        self._last_rx_t = t_open
        t_hello = -float("inf")
        t_beat = -float("inf")
        while not self._stop.is_set():
            now = self._clock()
            state = self._state
            if state in (LinkState.HANDSHAKE, LinkState.INCOMPATIBLE):
                if now - t_hello >= cfg.handshake_timeout:
                    self._send(proto.Hello(proto.PROTOCOL_VERSION))
                    t_hello = now
            elif now - t_beat >= cfg.heartbeat_period:
                self._send(proto.Heartbeat(int(now * 1000) & 0xFFFFFFFF, self._frames_rx & 0xFFFF,
                                       self._parser.crc_errors & 0xFFFF, 0))
                t_beat = now
            if state == LinkState.CONNECTED and now - self._last_heartbeat_t > \
                    cfg.heartbeat_timeout:
                self._set_state(LinkState.STALE, "no heartbeat from the board")
            if now - self._last_rx_t > cfg.silence_reopen:
                with self._lock:
                    self._last_error = f"board silent for {cfg.silence_reopen:.1f} s"
                self._set_state(LinkState.CONNECTING, "silent board, reopening")
                return
            data = ser.read(max(1, ser.in_waiting))
            if not data:
                continue
            t_rx = self._clock()
            self._last_rx_t = t_rx
            with self._lock:
                frames = self._parser.feed(data)
            for frame in frames:
                self._handle(frame, t_rx)

    def _handle(self, frame: proto.Frame, t_rx: float) -> None:
        try:
            msg = frame.decode()
        except proto.ProtocolError as exc:
            with self._lock:
                self._decode_errors += 1
                self._last_error = str(exc)
            log.debug("undecodable frame: %s", exc)
            return
        with self._lock:
            self._frames_rx += 1
            if self._last_seq is not None:
                self._frames_lost += (frame.seq - self._last_seq - 1) & 0xFF
            self._last_seq = frame.seq
        if isinstance(msg, proto.Sample):
            if self._state not in (LinkState.CONNECTED, LinkState.STALE):
                return  # protocol not confirmed yet
            cal = self.config.calibration
            sample = JoystickSample(
                t_rx=t_rx, seq=frame.seq, raw_forward=msg.raw_forward, raw_turn=msg.raw_turn,
                forward=cal.forward.deflection(msg.raw_forward),
                turn=cal.turn.deflection(msg.raw_turn), status=msg.status,
                out_forward=msg.out_forward, out_turn=msg.out_turn)
            with self._lock:
                self._samples_rx += 1
                self._last_sample_t = t_rx
                self._board_mode = (proto.Mode.OVERRIDE if proto.Status.MODE_OVERRIDE in msg.status
                                    else proto.Mode.PASSTHROUGH)
            if self._on_sample is not None:
                self._on_sample(sample)
        elif isinstance(msg, proto.Heartbeat):
            with self._lock:
                self._last_heartbeat_t = t_rx
                self._board_crc_errors = msg.rx_crc_errors
            if self._state == LinkState.STALE:
                self._set_state(LinkState.CONNECTED, "heartbeat back")
        elif isinstance(msg, proto.Version):
            if msg.protocol_version != proto.PROTOCOL_VERSION:
                with self._lock:
                    self._last_error = (f"board speaks protocol {msg.protocol_version}, "
                                        f"host {proto.PROTOCOL_VERSION}")
                self._set_state(LinkState.INCOMPATIBLE, self._last_error)
                return
            with self._lock:
                self._version = msg
                self._last_heartbeat_t = t_rx  # the handshake counts as a heartbeat
            if self._state == LinkState.HANDSHAKE:
                reason = (f"firmware {msg.firmware}, {msg.sample_rate_hz} Hz, "
                          f"watchdog {msg.watchdog_ms} ms")
                if self._connects > 1:
                    reason = f"reconnected ({self._connects - 1}), " + reason
                self._set_state(LinkState.CONNECTED, reason)
        elif isinstance(msg, proto.ErrorReport):
            with self._lock:
                self._board_errors += 1
                self._last_board_error = msg.describe()
            log.debug("board reports %s", msg.describe())
