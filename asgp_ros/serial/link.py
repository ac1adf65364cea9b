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
import errno
import logging
import termios
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import serial

from asgp_ros.common.fileio import join_if_started, signals_deferred
from asgp_ros.serial import protocol as proto
from asgp_ros.serial.calibration import JoystickCalibration

#: What a port that has gone (unplugged, reset, its driver gone) raises: pyserial's own
#: error, an OSError from a read, write or ioctl, and ``termios.error``, which is neither
#: (``reset_input_buffer`` on a port unplugged just after it opened raises EIO as one).
PORT_ERRORS: tuple[type[Exception], ...] = (serial.SerialException, OSError, termios.error)
#: What opening a port raises besides (a path pyserial cannot take).
OPEN_ERRORS: tuple[type[Exception], ...] = (*PORT_ERRORS, ValueError)

log = logging.getLogger(__name__)


class LinkState(enum.Enum):
    STOPPED = "stopped"          # not started or stopped
    CONNECTING = "connecting"    # port absent or failing to open; retrying with backoff
    HANDSHAKE = "handshake"      # port open, waiting for the board's VERSION
    CONNECTED = "connected"      # handshake done, board heartbeats arriving
    STALE = "stale"              # port open but no heartbeat within heartbeat_timeout
    INCOMPATIBLE = "incompatible"  # the board keeps answering with another protocol version


#: Consecutive VERSION replies (one per HELLO) with another protocol version that make the
#: link incompatible, and with ours that make an incompatible link usable again. One odd
#: frame (line noise that passes the CRC) never decides.
INCOMPATIBLE_AFTER = 3

#: Frames behind the last sequence number (a frame delivered late, or a repeat) are
#: dropped, not delivered: ``joy`` never goes back in time or says one reading twice. This
#: many frames behind it in a row, each one after the other, are the board's counter
#: starting over (a restart), and the link follows the new count from there.
SEQ_RESTART_AFTER = 3
#: ... and the first of them is this close to a new count's start (a restart's first frames
#: may be lost, or cut by the reset itself).
RESTART_SEQ_BELOW = 16
#: Frames behind in a row, each one after the other, from anywhere in the count: the
#: board's count goes on from there (one frame of line noise that passed the CRC with a SEQ
#: far ahead would otherwise hold every frame back until the count reached it, up to
#: 1.3 s; a board that reorders this many frames is not expected).
SEQ_RESYNC_AFTER = 8

#: Reads after the first that a turn of the reader may make while the OS still holds bytes
#: (each at most 4 KiB): a backlog is taken whole, a device that floods cannot hold the reader.
MAX_DRAIN_READS = 64

#: A partial frame with no byte for this long (s) is given up, as the firmware does
#: (``ASGP_RX_IDLE_MS``): the frames behind it are delivered.
RX_IDLE_S = 0.02

#: A handshake that has not succeeded for this long is an error (a device that is not the
#: board, the wrong baud rate, a boot loader): the diagnostics say what was heard instead.
HANDSHAKE_ERROR_AFTER = 2.0

_UP = (LinkState.CONNECTED, LinkState.STALE)
_STATUS_BITS = tuple(bit for bit in proto.Status if bit)
_ASKING = (LinkState.HANDSHAKE, LinkState.INCOMPATIBLE)


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
        if isinstance(self.baud, bool) or not isinstance(self.baud, int) \
                or not 1200 <= self.baud <= 2_000_000:
            raise ValueError(f"baud must be an integer in [1200, 2000000], got {self.baud!r}")
        for name in ("read_timeout", "handshake_timeout", "heartbeat_period",
                     "heartbeat_timeout", "silence_reopen", "reconnect_min", "reconnect_max"):
            value = getattr(self, name)
            high = 0.5 if name == "read_timeout" else 60.0  # the reader checks stop() this often
            if not 0.0 < value <= high:  # also refuses NaN and infinity
                raise ValueError(f"{name} must be in (0, {high:g}] s, got {value!r}")
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
    forward: float | None  # calibrated deflection in [-1, 1], + forward; None: no reading
    turn: float | None     # calibrated deflection in [-1, 1], + left; None: no reading
    status: proto.Status
    out_forward: int     # DAC codes the board wrote to the chair
    out_turn: int

    @property
    def valid(self) -> bool:
        """The raw counts are a joystick position. False with ADC_FAULT (open wire, short):
        the counts are no deflection at all, ``forward`` and ``turn`` are None and the board
        drives the chair neutral."""
        return proto.Status.ADC_FAULT not in self.status


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
    frames_repeated: int       # frames with the last frame's SEQ again (dropped)
    frames_late: int           # frames behind the last SEQ, delivered late (dropped)
    seq_restarts: int          # the board's SEQ started over (SEQ_RESTART_AFTER in a row)
    board_restarts: int        # the board restarted: its count started over, or its uptime
                               # went back (counted once)
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
    board_rx_frames: int       # valid frames the board received from us (its last heartbeat)
    overrides_sent: int
    unsolicited_versions: int  # VERSION frames that answered no HELLO (each -> new handshake)
    version_mismatches: int    # replies with another protocol version
    last_status: proto.Status  # status byte of the last SAMPLE
    last_sample_seq: int       # its SEQ, -1 if none
    host_lost: bool            # the board reported HOST_LOST and has not heard us since
    host_lost_events: int
    status_counts: dict[str, int]  # samples received with each status bit, by bit name
    last_sample_age: float     # s, inf if none
    last_heartbeat_age: float  # s, inf if none
    hellos_unanswered: int     # HELLOs of the current handshake without a reply
    state_age: float           # s in the current state
    host_frames_heard: int     # frames only a host sends, received (the port echoes?)


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
        self._frames_repeated = 0
        self._frames_late = 0
        self._seq_restarts = 0
        self._board_restarts = 0
        self._host_frames_heard = 0
        self._behind_seq: int | None = None  # the last frame behind _last_seq, and how many
        self._behind_run = 0                 # such frames in a row, each one after the other
        self._behind_start = 0               # the first of them
        self._last_uptime: int | None = None  # the board's uptime in its last heartbeat
        self._past_end = 0  # lost SEQs counted at the end of a count since that heartbeat
        self._count_restarted = False  # _in_sequence followed a new count from its start
        self._restart_seen = False     # a restart counted since the last heartbeat
        self._state_t = clock()
        self._crc_base = 0
        self._dropped_base = 0
        self._decode_errors = 0
        self._board_errors = 0
        self._last_board_error = ""
        self._last_error = ""
        self._version: proto.Version | None = None
        self._board_mode = proto.Mode.PASSTHROUGH
        self._board_crc_errors = 0
        self._board_rx_frames: int | None = None
        self._overrides_sent = 0
        self._unsolicited_versions = 0
        self._version_mismatches = 0
        self._last_status = proto.Status.NONE
        self._last_sample_seq = -1
        self._host_lost = False
        self._host_lost_rx: int | None = None  # board's frame count when it lost us
        self._host_lost_events = 0
        self._status_counts = [0] * len(_STATUS_BITS)
        # handshake: HELLOs are sent by the reader thread at _t_hello; each VERSION reply is
        # judged once per HELLO (_hello_judged); _streak counts consecutive replies that
        # disagree with the current state (mismatches while asking, matches while incompatible)
        self._t_hello = -float("inf")
        self._hellos_unanswered = 0
        self._hello_judged = True
        self._streak = 0
        self._last_seq: int | None = None
        self._last_sample_t = -float("inf")
        self._last_heartbeat_t = -float("inf")
        self._last_rx_t = -float("inf")
        # no byte of the next read came before this time (see _drain)
        self._rx_floor = -float("inf")

    # -- public API --------------------------------------------------------------------

    @property
    def state(self) -> LinkState:
        return self._state

    @property
    def version(self) -> proto.Version | None:
        return self._version

    @property
    def board_mode(self) -> proto.Mode:
        """The board's mode as its latest SAMPLE reports it (passthrough until one came)."""
        return self._board_mode

    @property
    def host_lost(self) -> bool:
        """The board reported HOST_LOST and its heartbeats show it has not heard us since."""
        return self._host_lost

    def start(self) -> None:
        if self._thread is not None:
            raise RuntimeError("link already started")
        self._stop.clear()
        with signals_deferred():  # a stop signal's exception waits until the thread is up
            self._thread = threading.Thread(target=self._run, name="asgp-serial-link",
                                            daemon=True)
            self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        """Stops the reader; asks the board for passthrough first if connected."""
        if self._state in _UP:
            self.set_mode(proto.Mode.PASSTHROUGH)
        self._stop.set()
        if self._thread is not None:
            join_if_started(self._thread, timeout)
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
                board_crc_errors=self._board_crc_errors,
                board_rx_frames=self._board_rx_frames or 0,
                overrides_sent=self._overrides_sent,
                unsolicited_versions=self._unsolicited_versions,
                version_mismatches=self._version_mismatches,
                last_status=self._last_status, last_sample_seq=self._last_sample_seq,
                host_lost=self._host_lost, host_lost_events=self._host_lost_events,
                status_counts={bit.name or "": n for bit, n in
                               zip(_STATUS_BITS, self._status_counts, strict=True)},
                last_sample_age=now - self._last_sample_t,
                last_heartbeat_age=now - self._last_heartbeat_t,
                frames_repeated=self._frames_repeated, frames_late=self._frames_late,
                seq_restarts=self._seq_restarts, board_restarts=self._board_restarts,
                hellos_unanswered=self._hellos_unanswered, state_age=now - self._state_t,
                host_frames_heard=self._host_frames_heard,
            )

    # -- internals ---------------------------------------------------------------------

    def _set_state(self, state: LinkState, reason: str) -> None:
        with self._lock:
            if state == self._state:
                return
            self._state = state
            self._state_t = self._clock()
        log.info("serial link %s: %s (%s)", self.config.port, state.value, reason)
        if self._on_state is not None:
            self._on_state(state, reason)

    def _send(self, msg: proto.Message) -> bool:
        """Writes one frame: HELLO while asking for the version, anything else only once the
        board's protocol is confirmed."""
        allowed = _ASKING if isinstance(msg, proto.Hello) else _UP
        with self._write_lock:
            ser = self._ser
            if ser is None or self._state not in allowed:
                return False
            frame = proto.encode(msg, self._tx_seq)
            self._tx_seq = (self._tx_seq + 1) & 0xFF
            try:
                ser.write(frame)
            except PORT_ERRORS as exc:
                # the reader thread notices the dead port on its next read and reopens it
                log.debug("write to %s failed: %s", self.config.port, exc)
                return False
        return True

    def _run(self) -> None:
        delay = self.config.reconnect_min
        while not self._stop.is_set():
            try:
                # exclusive (flock): a second bridge on the same board (another launch's
                # namespace) read half of the frames and handshook over this one's
                ser = serial.Serial(self.config.port, self.config.baud,
                                    timeout=self.config.read_timeout, write_timeout=0.2,
                                    exclusive=True)
            except OPEN_ERRORS as exc:
                in_use = getattr(exc, "errno", None) in (errno.EAGAIN, errno.EWOULDBLOCK)
                with self._lock:
                    self._open_failures += 1
                    self._last_error = (
                        "open failed: the port is in use by another program (a second bridge "
                        "on this board?)" if in_use else f"open failed: {exc}")
                self._set_state(LinkState.CONNECTING, f"cannot open {self.config.port}"
                                + (": in use by another program" if in_use else ""))
                self._stop.wait(delay)
                delay = min(2.0 * delay, self.config.reconnect_max)
                continue
            delay = self.config.reconnect_min
            try:
                self._serve(ser)
            except PORT_ERRORS as exc:
                with self._lock:
                    self._last_error = f"port lost: {exc}"
                log.warning("serial port %s lost: %s", self.config.port, exc)
                self._set_state(LinkState.CONNECTING, "port lost")
            finally:
                with self._write_lock:
                    self._ser = None
                try:
                    ser.close()
                except PORT_ERRORS as exc:
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
            self._behind_seq = None
            self._last_uptime = None
            self._past_end = 0
            self._count_restarted = self._restart_seen = False
            self._version = None
            self._connects += 1
            self._board_rx_frames = None
            self._host_lost = False
            self._board_mode = proto.Mode.PASSTHROUGH
        with self._write_lock:
            self._ser = ser
        self._begin_handshake(f"opened {cfg.port}")
        t_open = self._clock()
        self._last_rx_t = self._rx_floor = t_open
        t_beat = -float("inf")
        while not self._stop.is_set():
            now = self._clock()
            state = self._state
            if state in _ASKING:
                if now - self._t_hello >= cfg.handshake_timeout:
                    self._t_hello = now
                    self._hello_judged = False
                    if self._send(proto.Hello(proto.PROTOCOL_VERSION)):
                        self._hellos_unanswered += 1
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
                if self._parser.pending and self._clock() - self._last_rx_t >= RX_IDLE_S:
                    self._expire_partial()
                continue
            previous = self._last_rx_t
            data, t_rx, t_before = self._drain(ser, data)
            if t_rx - previous > cfg.silence_reopen:
                # no byte for longer than a silent board may take: the board was silent, or
                # this reader stalled (a busy host) and what waits is a backlog older than
                # the limit; either way, reopened as after a silence (its input flushed).
                # Judged on the drain's own time: a reader stopped after its read returned
                # and before it took the time, read the stall's backlog as fresh
                quiet = t_rx - previous
                with self._lock:
                    self._last_error = (f"no byte read for {quiet:.1f} s (a silent board, or "
                                        "this reader stalled): the bytes waiting are dropped")
                self._set_state(LinkState.CONNECTING, "silent board or stalled reader, "
                                                      "reopening")
                return
            with self._lock:
                frames = self._parser.feed(data)
            for frame, t in zip(frames, self._arrival_times(frames, t_rx, t_before),
                                strict=True):
                self._handle(frame, t)

    def _drain(self, ser: serial.Serial, data: bytes) -> tuple[bytes, float, float]:
        """(``data`` and all that the OS holds now, as one read; its time; the time before
        which none of its bytes came). A stall ends inside the read before this, which
        returned one byte, and the OS hands over at most 4 KiB a read.

        The last bound is taken before the check that found nothing more waiting, not
        after the read's time: a reader stalled between that check and its clock (a busy
        host stops it anywhere) took that late time as the bound of the next read, and the
        whole backlog of the stall was clamped onto one stamp."""
        floor: float | None = None
        for _ in range(MAX_DRAIN_READS):
            t_check = self._clock()
            waiting = ser.in_waiting
            if not waiting:
                floor = t_check  # what comes next arrived after this
                break
            data += ser.read(waiting)
        t_rx = self._clock()
        t_before = self._rx_floor
        self._last_rx_t = t_rx
        # (with bytes still waiting after the last read, they may be older than it: the
        # bound stays)
        self._rx_floor = floor if floor is not None else t_before
        return data, t_rx, t_before

    def _arrival_times(self, frames: list[proto.Frame], t_rx: float, t_before: float
                       ) -> list[float]:
        """When each frame of one read came. One read (with what followed it at once)
        returns what the OS buffered since the last: after the reader stalled (a busy
        host), up to 2 s of the board's samples at once. Its newest sample came at
        ``t_rx``; one n samples before it (counting the SEQs lost between them as samples)
        came n periods of the board's rate before, and none before the previous read
        (``t_before``). Other frames are timed at ``t_rx``. Without the board's rate
        (before its VERSION), all at ``t_rx``.

        This holds while the OS buffer (4 KiB on Linux) did not overflow: at the
        firmware's 100 Hz, some 2.5 s of backlog, beyond the 2 s without a byte read after
        which the link is reopened and its backlog dropped."""
        times = [t_rx] * len(frames)
        v = self._version
        rate = v.sample_rate_hz if v is not None else 0
        if rate <= 0:
            return times
        slot = -1
        later_seq: int | None = None
        for i in range(len(frames) - 1, -1, -1):
            f = frames[i]
            if later_seq is not None:
                gap = (later_seq - f.seq) & 0xFF
                if 1 < gap < 128:  # SEQs missing between this frame and the next
                    slot += gap - 1
            later_seq = f.seq
            if f.type == proto.MsgType.SAMPLE:
                slot += 1
                times[i] = max(t_before, t_rx - slot / rate)
        return times

    def _expire_partial(self) -> None:
        """The line went idle inside a frame (its rest is not coming: noise claimed a long
        frame, or the board stopped mid-frame): the frames parked behind the partial one
        are delivered, timed by their last byte, as the firmware does (a sample was held
        until more bytes came)."""
        with self._lock:
            frames: list[proto.Frame] = []
            while self._parser.pending:
                frames += self._parser.expire()
        for frame in frames:
            self._handle(frame, self._last_rx_t)

    def _begin_handshake(self, reason: str) -> None:
        """(Re)starts the version handshake: the next loop turn sends HELLO; samples are
        withheld until the board answers with our protocol version."""
        self._t_hello = -float("inf")
        self._hellos_unanswered = 0
        self._hello_judged = True
        self._streak = 0
        self._set_state(LinkState.HANDSHAKE, reason)

    def _handle(self, frame: proto.Frame, t_rx: float) -> None:
        try:
            msg = frame.decode()
        except proto.ProtocolError as exc:
            with self._lock:
                self._decode_errors += 1
                self._last_error = str(exc)
            log.debug("undecodable frame: %s", exc)
            return
        if isinstance(msg, proto.HOST_ONLY):
            with self._lock:
                self._host_frames_heard += 1
                self._last_error = (f"received a {msg.TYPE.name} frame, which only a host "
                                    "sends: does the device echo what is written to it?")
            return
        with self._lock:
            self._frames_rx += 1
            back = isinstance(msg, proto.Heartbeat) and self._uptime_back(msg.uptime_ms)
            if back:
                self._last_seq, self._behind_seq, self._behind_run = frame.seq, None, 0
            elif not self._in_sequence(frame.seq):
                return
            # a restart is counted once: by its frame count starting over, or by its first
            # heartbeat's uptime (a board up for less than 0.2 s shows only the first)
            restarted = False
            if self._count_restarted:
                self._count_restarted = False
                restarted = self._restart_seen = True
                self._last_error = "the board restarted (its frame count started over)"
            if isinstance(msg, proto.Heartbeat):
                if back and not self._restart_seen:
                    restarted = True
                    self._last_error = (f"the board restarted (uptime {msg.uptime_ms} ms, "
                                        f"{self._last_uptime} ms before)")
                self._restart_seen = False
                self._last_uptime = msg.uptime_ms
                if back:  # SEQs after the old count's last were never sent, not lost
                    self._frames_lost -= self._past_end
                self._past_end = 0
            if restarted:
                self._board_restarts += 1
        if restarted and self._state in _UP:
            # its firmware may have changed (a reflash): confirm the protocol again
            log.warning("serial link %s: %s; new handshake", self.config.port,
                        self._last_error)
            self._begin_handshake("the board restarted: new handshake")
        if isinstance(msg, proto.Sample):
            if self._state not in _UP:
                return  # protocol not confirmed yet
            cal = self.config.calibration
            fault = proto.Status.ADC_FAULT in msg.status
            sample = JoystickSample(
                t_rx=t_rx, seq=frame.seq, raw_forward=msg.raw_forward, raw_turn=msg.raw_turn,
                # a faulty reading (open wire, short) is no deflection: never calibrate it
                forward=None if fault else cal.forward.deflection(msg.raw_forward),
                turn=None if fault else cal.turn.deflection(msg.raw_turn), status=msg.status,
                out_forward=msg.out_forward, out_turn=msg.out_turn)
            with self._lock:
                self._samples_rx += 1
                self._last_sample_t = t_rx
                self._last_status = msg.status
                self._last_sample_seq = frame.seq
                if msg.status:
                    for i, bit in enumerate(_STATUS_BITS):
                        if bit in msg.status:
                            self._status_counts[i] += 1
                self._board_mode = (proto.Mode.OVERRIDE if proto.Status.MODE_OVERRIDE in msg.status
                                    else proto.Mode.PASSTHROUGH)
                if proto.Status.HOST_LOST in msg.status:
                    self._host_lost = True
                    self._host_lost_rx = self._board_rx_frames
                    self._host_lost_events += 1
            if self._on_sample is not None:
                self._on_sample(sample)
        elif isinstance(msg, proto.Heartbeat):
            with self._lock:
                self._last_heartbeat_t = t_rx
                self._board_crc_errors = msg.rx_crc_errors
                self._board_rx_frames = msg.rx_frames
                if self._host_lost and msg.rx_frames != self._host_lost_rx:
                    self._host_lost = False  # the board hears us again
            if self._state == LinkState.STALE:
                self._set_state(LinkState.CONNECTED, "heartbeat back")
        elif isinstance(msg, proto.Version):
            self._on_version(msg, t_rx)
        elif isinstance(msg, proto.ErrorReport):
            with self._lock:
                self._board_errors += 1
                self._last_board_error = msg.describe()
            log.debug("board reports %s", msg.describe())

    def _uptime_back(self, uptime_ms: int) -> bool:
        """Whether a heartbeat's uptime is behind the last one's: the board restarted (its
        SEQ starts over too). Wrap-safe: the uint32 of milliseconds wraps after 49.7 days,
        and an uptime more than half the counter behind is ahead. Under ``_lock``."""
        last = self._last_uptime
        return last is not None and (uptime_ms - last) & 0xFFFFFFFF >= 1 << 31

    def _in_sequence(self, seq: int) -> bool:
        """Whether a frame with this SEQ is taken (under ``_lock``); counts the verdict.

        A frame after the last one (at most half the counter ahead) is taken, and the SEQs
        it skipped are lost frames. The last SEQ again is a repeat, and one behind it a
        frame delivered late: neither is taken. SEQ_RESTART_AFTER frames behind in a row,
        each one after the other and the first of them among the first RESTART_SEQ_BELOW of
        a count, are the board's counter starting over (SEQ_RESYNC_AFTER from anywhere: a
        noise frame took the count ahead): the last of them is taken and the others count
        as lost. A restart after a SEQ above 127 looks like a jump to a new
        count: the next heartbeat's uptime, at most 0.2 s later, tells, and the SEQs counted
        lost past the old count's last frame are taken back (``_past_end``).
        """
        last = self._last_seq
        if last is None:
            self._last_seq = seq
            return True
        ahead = (seq - last) & 0xFF
        if ahead == 0:
            self._frames_repeated += 1
            return False
        if ahead < 128:
            self._frames_lost += ahead - 1
            if seq < RESTART_SEQ_BELOW <= last:  # into a new count: a wrap, or a restart
                self._past_end = ahead - 1 - seq  # counted lost: SEQs last+1 .. 255
            self._last_seq, self._behind_seq, self._behind_run = seq, None, 0
            return True
        follows = self._behind_seq is not None and seq == (self._behind_seq + 1) & 0xFF
        if follows:
            self._behind_run += 1
        else:  # a new run
            self._behind_run, self._behind_start = 1, seq
        self._behind_seq = seq
        need = SEQ_RESTART_AFTER if self._behind_start < RESTART_SEQ_BELOW else SEQ_RESYNC_AFTER
        if self._behind_run < need:
            self._frames_late += 1
            return False
        self._seq_restarts += 1
        self._count_restarted = self._behind_start < RESTART_SEQ_BELOW  # (not a noise jump)
        self._frames_late -= self._behind_run - 1  # those were the new count's first frames
        self._frames_lost += self._behind_run - 1
        self._last_seq, self._behind_seq, self._behind_run = seq, None, 0
        return True

    def _on_version(self, msg: proto.Version, t_rx: float) -> None:
        """The handshake (docs/serial_protocol.md, "HELLO / VERSION").

        The board sends VERSION only in reply to HELLO. Outside the handshake a VERSION is a
        board that restarted its conversation or line noise that passed the CRC: either way
        the protocol is confirmed again with a new handshake (samples are withheld for the
        few milliseconds it takes). While asking, each HELLO's reply is judged once; the link
        is incompatible only after INCOMPATIBLE_AFTER consecutive replies with another
        version, and usable again only after as many with ours.
        """
        ours = msg.protocol_version == proto.PROTOCOL_VERSION
        state = self._state
        if state in _UP:
            if (ours and msg == self._version and self._hellos_unanswered > 0
                    and t_rx - self._t_hello <= 2.0 * self.config.handshake_timeout):
                self._hellos_unanswered -= 1  # a late reply to one of our HELLOs
                return
            with self._lock:
                self._unsolicited_versions += 1
                self._last_error = (f"unsolicited VERSION (protocol {msg.protocol_version}, "
                                    f"firmware {msg.firmware}) while {state.value}")
            log.warning("serial link %s: %s; new handshake", self.config.port,
                        self._last_error)
            self._begin_handshake("unsolicited VERSION: new handshake")
            return
        if state not in _ASKING:
            return
        if self._hello_judged:
            if not ours:  # a second answer to the same HELLO, or noise: not a new vote
                with self._lock:
                    self._unsolicited_versions += 1
                return
            if state == LinkState.INCOMPATIBLE:
                return
        self._hello_judged = True
        self._hellos_unanswered = max(0, self._hellos_unanswered - 1)
        if not ours:
            with self._lock:
                self._version_mismatches += 1
                self._last_error = (f"board speaks protocol {msg.protocol_version}, "
                                    f"host {proto.PROTOCOL_VERSION}")
            if state == LinkState.INCOMPATIBLE:
                self._streak = 0
                return
            self._streak += 1
            if self._streak >= INCOMPATIBLE_AFTER:
                self._streak = 0
                self._set_state(LinkState.INCOMPATIBLE,
                                f"{self._last_error} ({INCOMPATIBLE_AFTER} replies)")
            return
        if state == LinkState.INCOMPATIBLE:
            self._streak += 1
            if self._streak < INCOMPATIBLE_AFTER:
                return
        self._streak = 0
        with self._lock:
            self._version = msg
            self._last_heartbeat_t = t_rx  # the handshake counts as a heartbeat
        reason = (f"firmware {msg.firmware}, {msg.sample_rate_hz} Hz, "
                  f"watchdog {msg.watchdog_ms} ms")
        if self._connects > 1:
            reason = f"reconnected ({self._connects - 1}), " + reason
        self._set_state(LinkState.CONNECTED, reason)
