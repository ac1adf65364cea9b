"""A simulated joystick interface board on a pseudo-terminal.

It speaks the real link protocol and runs the firmware's rules through
:mod:`asgp_ros.serial.safety` (a line-by-line mirror of the C code, cross-checked against
it byte for byte by the tests): joystick sampled at a fixed rate from a callable, SAMPLE
and HEARTBEAT frames out, HELLO/MODE/OVERRIDE/HEARTBEAT in, the 200 ms override watchdog,
the neutral rule, the clamp. Its analog output (what it writes to the chair) is exposed
as :attr:`SimulatedBoard.output` so a simulated chair can follow it.

The port is the pty's slave device; with ``link_path`` a symlink at that path points to it,
and :meth:`unplug` / :meth:`replug` remove and recreate the pty behind the same path, like a
USB adapter unplugged and plugged back in (udev recreating ``/dev/asgp_joystick``).
"""

from __future__ import annotations

import contextlib
import errno
import logging
import math
import os
import queue
import select
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from asgp_ros.common.fileio import join_if_started, signals_deferred
from asgp_ros.serial import safety as fw
from asgp_ros.serial.protocol import Mode, MsgType, Status
from asgp_ros.sim.chair import Chair, ChairParams
from asgp_ros.sim.driver import Driver
from asgp_ros.sim.world import Room

log = logging.getLogger(__name__)

JoystickSource = Callable[[float], tuple[float, float]]
"""``source(t) -> (forward, turn)``: deflections in [-1, 1] (+ forward, + left) at time
``t`` seconds since the board started (a :meth:`SimulatedBoard.restart` does not reset it)."""


@dataclass(frozen=True)
class BoardOutput:
    """What the board currently writes to the chair."""

    t: float             # the joystick's time (JoystickSource), s
    forward: float       # deflection the chair sees, [-1, 1]
    turn: float          # [-1, 1], + left
    code_forward: int    # DAC codes
    code_turn: int
    user_forward: float  # the user's joystick, per the firmware's calibration
    user_turn: float
    status: Status
    mode: Mode

    @property
    def override_active(self) -> bool:
        return Status.OVERRIDE_ACTIVE in self.status


@dataclass(frozen=True)
class SentSample:
    """A SAMPLE frame as written (for latency and loss measurements)."""

    seq: int
    t_written: float  # time.monotonic() just before the write: latencies measured from it
                      # are conservative (they include the write call itself)
    raw_forward: int
    raw_turn: int
    status: Status = Status.NONE


class ScriptedJoystick:
    """A smooth, bounded, seeded joystick for standalone runs: drive bouts and stops.

    Sums of slow sinusoids (0.03-0.25 Hz) for forward and turn, forward mostly positive,
    with a 3 s stop (neutral) every 20 s so that the chair also comes to rest.
    """

    def __init__(self, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        self._f = rng.uniform(0.03, 0.25, size=(2, 3))
        self._ph = rng.uniform(0.0, 2.0 * math.pi, size=(2, 3))
        self._amp = np.array([[0.25, 0.15, 0.1], [0.35, 0.2, 0.1]])

    def __call__(self, t: float) -> tuple[float, float]:
        if t % 20.0 < 3.0:
            return 0.0, 0.0
        waves = self._amp * np.sin(2.0 * math.pi * self._f * t + self._ph)  # [2, 3]
        fwd, turn = waves.sum(axis=1)
        return float(np.clip(0.45 + fwd, -1.0, 1.0)), float(np.clip(turn, -1.0, 1.0))


class SimulatedBoard:
    """The board on a pty; see the module docstring.

    Args:
        joystick: the user's joystick (default: neutral).
        rate_hz: sampling rate (the firmware's is ``safety.SAMPLE_RATE_HZ``).
        link_path: optional stable path, a symlink to the current pty.
        calibration: the firmware's (forward, turn) calibration.
        noise_counts: standard deviation of ADC noise in counts, in [0, 100] (0: none).
        record: keep a log of every SAMPLE written (:attr:`sent`).
    """

    def __init__(self, joystick: JoystickSource | None = None, *, rate_hz: float = 100.0,
                 link_path: str | os.PathLike[str] | None = None,
                 calibration: tuple[fw.AxisCal, fw.AxisCal] | None = None,
                 noise_counts: float = 0.0, seed: int = 0, record: bool = False) -> None:
        if not 1.0 <= rate_hz <= 1000.0:  # also refuses NaN
            raise ValueError(f"rate_hz must be in [1, 1000], got {rate_hz}")
        if not 0.0 <= noise_counts <= 100.0:
            raise ValueError(f"noise_counts must be in [0, 100] counts, got {noise_counts}")
        self._joystick: JoystickSource = joystick or (lambda t: (0.0, 0.0))
        self.rate_hz = float(rate_hz)
        self.link_path = Path(link_path) if link_path is not None else None
        self._cal = calibration or fw.default_calibration()
        self._noise = float(noise_counts)
        self._rng = np.random.default_rng(seed)
        self._record = record
        self.sent: list[SentSample] = []
        self.frames_dropped = 0       # frames the pty could not take (nobody reading)
        self.revert_events: list[tuple[int, int]] = []  # (revert ms, last override ms)
        # the status of each revert's tick: WATCHDOG set for a revert by the watchdog, not
        # for one by a MODE frame (the host handing the chair back, or its link resetting);
        # HOST_LOST for one by the host timeout
        self.revert_status: list[Status] = []
        # host-loss resets to passthrough, on the board's clock: (reset ms, last host ms)
        self.host_lost_events: list[tuple[int, int]] = []
        self.error: BaseException | None = None
        self._logic = fw.BoardLogic(self._write, self._cal, round(rate_hz), fw.WATCHDOG_MS)
        self._lock = threading.Lock()
        self._requests: queue.Queue[tuple[str | tuple[str, bytes], threading.Event]] = \
            queue.Queue()
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_w, False)
        self._master: int | None = None
        self._slave: int | None = None
        self._slave_path = ""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._t0 = time.monotonic()    # the joystick's time
        self._boot = self._t0           # the firmware's uptime counts from here
        self._silent = False
        self._deaf = False
        self._raw_override: tuple[int, int] | None = None
        self._held: list[bytes] | None = None  # a tick's frames, until its output is set
        self._output = BoardOutput(0.0, 0.0, 0.0, fw.DAC_NEUTRAL, fw.DAC_NEUTRAL, 0.0, 0.0,
                                   Status.NONE, Mode.PASSTHROUGH)

    # -- public API --------------------------------------------------------------------

    @property
    def port(self) -> str:
        """The path a host opens: the stable link if configured, else the pty slave."""
        return str(self.link_path) if self.link_path is not None else self._slave_path

    @property
    def slave_path(self) -> str:
        return self._slave_path

    @property
    def output(self) -> BoardOutput:
        with self._lock:
            return self._output

    @property
    def mode(self) -> Mode:
        return Mode(self._logic.safety.mode)

    @property
    def host_crc_errors(self) -> int:
        """CRC errors seen in the host's frames."""
        return self._logic.parser.crc_errors

    def set_joystick(self, joystick: JoystickSource) -> None:
        self._joystick = joystick

    def set_silent(self, silent: bool) -> None:
        """Stop (or resume) sending anything while keeping the port open: a hung board."""
        self._silent = silent

    def set_deaf(self, deaf: bool) -> None:
        """Ignore (or again act on) everything the host sends while still sampling and
        sending: a broken host -> board wire."""
        self._deaf = deaf

    def set_raw_override(self, raw: tuple[int, int] | None) -> None:
        """Replace the joystick's ADC readings by fixed counts (0..1023), e.g. ``(1023, 512)``
        for a forward wire shorted to 5 V; ``None`` reconnects the joystick."""
        if raw is not None:
            if len(raw) != 2 or not all(isinstance(r, int) and 0 <= r <= 1023 for r in raw):
                raise ValueError(f"raw ADC readings must be two integers in [0, 1023], "
                                 f"got {raw!r}")
            raw = (int(raw[0]), int(raw[1]))
        self._raw_override = raw

    def inject(self, data: bytes, timeout: float = 2.0) -> None:
        """Write ``data`` to the host between two ticks (never inside a frame the board is
        sending): a frame from a reset or line noise that happens to pass the CRC."""
        self._request(("inject", bytes(data)), timeout)

    def start(self) -> SimulatedBoard:
        if self._thread is not None:
            raise RuntimeError("board already started")
        # A stop signal's exception (asgp board) waits until the pty, the link and the thread
        # are all up, so that stop() finds a started thread to join.
        with signals_deferred():
            self._open_pty()
            self._t0 = self._boot = time.monotonic()
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="asgp-sim-board",
                                            daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._wake()
        if self._thread is not None:
            join_if_started(self._thread, 2.0)
            self._thread = None
        self._close_pty()
        for fd in (self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._wake_r = self._wake_w = -1

    def __enter__(self) -> SimulatedBoard:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def restart(self, timeout: float = 2.0) -> None:
        """The board resets (its watchdog, a brown-out, a reflash): the firmware starts over
        in passthrough, with its sequence numbers, counters and uptime from zero. The port
        stays (the USB-serial adapter is not the MCU) and the joystick goes on."""
        self._request("restart", timeout)

    def unplug(self, timeout: float = 2.0) -> None:
        """The device disappears: pty closed (the host's reads fail), symlink removed."""
        self._request("unplug", timeout)

    def replug(self, timeout: float = 2.0) -> None:
        """A new pty appears behind the same ``link_path``."""
        self._request("replug", timeout)

    # -- internals ---------------------------------------------------------------------

    def _request(self, what: str | tuple[str, bytes], timeout: float) -> None:
        if self._thread is None:
            raise RuntimeError("board not started")
        done = threading.Event()
        self._requests.put((what, done))
        self._wake()
        if not done.wait(timeout):
            name = what if isinstance(what, str) else what[0]
            raise TimeoutError(f"simulated board did not {name} within {timeout} s")

    def _wake(self) -> None:
        with contextlib.suppress(OSError):
            os.write(self._wake_w, b"x")

    def _open_pty(self) -> None:
        master, slave = os.openpty()
        tty.setraw(master)
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self._slave_path = os.ttyname(slave)
        if self.link_path is not None:
            # a temporary name of its own (a fixed PATH.tmp deleted a user's file there),
            # then the atomic rename over the link
            for _ in range(100):
                tmp = self.link_path.with_name(
                    f".{self.link_path.name}.{os.getpid()}.{os.urandom(4).hex()}.tmp")
                try:
                    os.symlink(self._slave_path, tmp)
                except FileExistsError:
                    continue
                break
            else:
                raise FileExistsError(f"no free temporary name next to {self.link_path}")
            os.replace(tmp, self.link_path)
        log.debug("simulated board on %s", self.port)

    def _close_pty(self) -> None:
        # the link only if it is still this board's (another board may have taken it over)
        if self.link_path is not None and self.link_path.is_symlink():
            with contextlib.suppress(OSError):
                if os.readlink(self.link_path) == self._slave_path:
                    self.link_path.unlink()
        for fd in (self._master, self._slave):
            if fd is not None:
                os.close(fd)
        self._master = self._slave = None

    def _now_ms(self) -> int:
        """The firmware's clock: milliseconds since it started."""
        return int((time.monotonic() - self._boot) * 1000.0) & 0xFFFFFFFF

    def _write(self, frame: bytes) -> None:
        if self._held is not None:
            self._held.append(frame)
            return
        if self._master is None or self._silent:
            self.frames_dropped += 1
            return
        t_write = time.monotonic()
        # recorded before the write, so that whoever reads the frame finds it in ``sent``
        record = self._record and frame[3] == MsgType.SAMPLE
        if record:
            self.sent.append(SentSample(frame[4], t_write,
                                        frame[5] | frame[6] << 8, frame[7] | frame[8] << 8,
                                        Status(frame[9])))
        try:
            n = os.write(self._master, frame)
        except OSError as exc:
            if exc.errno not in (errno.EAGAIN, errno.EIO):
                raise
            n = 0
        if n != len(frame):
            self.frames_dropped += 1  # a UART with nobody reading: bytes are simply lost
            if record:
                self.sent.pop()

    def _raw(self, deflection: float, axis: int) -> int:
        if not math.isfinite(deflection):
            raise ValueError(f"joystick source returned a non-finite deflection {deflection}")
        d = min(1.0, max(-1.0, deflection))
        cal = self._cal[axis]
        raw = cal.adc_neutral + d * cal.adc_span
        if self._noise > 0.0:
            raw += self._rng.normal(0.0, self._noise)
        return int(min(1023, max(0, round(raw))))

    def _tick(self) -> None:
        now_ms = self._now_ms()
        t = time.monotonic() - self._t0
        fwd, turn = self._joystick(t)
        raw = self._raw_override or (self._raw(fwd, 0), self._raw(turn, 1))
        before = self._logic.out.status
        self._held = []
        try:
            out = self._logic.tick(raw, now_ms)
        except BaseException:
            self._held = None
            raise
        if Status.OVERRIDE_ACTIVE in before and Status.OVERRIDE_ACTIVE not in out.status \
                and Status.NEUTRAL_STOP not in out.status:
            self.revert_events.append((now_ms, self._logic.safety.override_ms))
            self.revert_status.append(out.status)
        if Status.HOST_LOST in out.status and Status.HOST_LOST not in before:
            self.host_lost_events.append((now_ms, self._logic.safety.host_ms))
        cal = self._cal
        output = BoardOutput(
            t=t, forward=cal[0].dac_to_deflection(out.out_code[0]),
            turn=cal[1].dac_to_deflection(out.out_code[1]), code_forward=out.out_code[0],
            code_turn=out.out_code[1], user_forward=out.user_pm[0] / 1000.0,
            user_turn=out.user_pm[1] / 1000.0, status=out.status,
            mode=Mode(self._logic.safety.mode))
        with self._lock:
            self._output = output
        # the frames go out once ``output`` says what the chair got: whoever reads a SAMPLE
        # finds the same tick's output there
        frames, self._held = self._held, None
        for frame in frames:
            self._write(frame)

    def _service_requests(self) -> None:
        while True:
            try:
                what, done = self._requests.get_nowait()
            except queue.Empty:
                return
            if what == "unplug":
                self._close_pty()
            elif what == "restart":
                self._boot = time.monotonic()
                self._logic = fw.BoardLogic(self._write, self._cal, round(self.rate_hz),
                                            fw.WATCHDOG_MS)
            elif what == "replug" and self._master is None:
                self._open_pty()
            elif isinstance(what, tuple) and what[0] == "inject" and self._master is not None:
                with contextlib.suppress(OSError):
                    os.write(self._master, what[1])
            done.set()

    def _run(self) -> None:
        period = 1.0 / self.rate_hz
        next_tick = time.monotonic()
        try:
            while not self._stop.is_set():
                self._service_requests()
                timeout = max(0.0, next_tick - time.monotonic())
                fds = [self._wake_r] + ([self._master] if self._master is not None else [])
                ready, _, _ = select.select(fds, [], [], timeout)
                if self._wake_r in ready:
                    os.read(self._wake_r, 4096)
                if self._master is not None and self._master in ready:
                    try:
                        data = os.read(self._master, 4096)
                    except OSError as exc:  # EIO: no process has the slave open
                        if exc.errno not in (errno.EIO, errno.EAGAIN):
                            raise
                        data = b""
                    if data and not (self._silent or self._deaf):
                        self._logic.rx(data, self._now_ms())
                now = time.monotonic()
                if now >= next_tick:
                    self._tick()
                    next_tick += period
                    if now - next_tick > 5 * period:  # fell far behind: resynchronise
                        next_tick = now + period
        except Exception as exc:  # the thread's top level: keep the reason for the owner
            self.error = exc
            log.exception("simulated board stopped")


class DriverJoystick:
    """The wheelchair simulator's driver, closed loop on a simulated chair.

    The chair (``asgp_ros.sim.chair``, tile preset) follows ``chair_input()`` -- normally
    the board's analog output, so overrides move it -- and the driver
    (``asgp_ros.sim.driver.Driver``) steers by the chair's state, as a person would.
    """

    def __init__(self, seed: int, chair_input: Callable[[], tuple[float, float]]) -> None:
        self._driver = Driver(seed, Room())
        self._chair = Chair(ChairParams.preset("tile"), seed=seed)
        self._input = chair_input
        self._t: float | None = None
        self.state = self._chair.step((0.0, 0.0), 0.0)

    def __call__(self, t: float) -> tuple[float, float]:
        dt = 0.0 if self._t is None else max(0.0, t - self._t)
        self._t = t
        self.state = self._chair.step(self._input(), dt)
        fwd, turn = self._driver.command(t, self.state)
        return float(fwd), float(turn)


def driver_joystick(seed: int, board: SimulatedBoard) -> JoystickSource | None:
    """A :class:`DriverJoystick` whose chair follows ``board``'s output, or None when the
    simulator's driver is not installed (callers fall back to :class:`ScriptedJoystick`)."""
    try:
        return DriverJoystick(seed, lambda: (board.output.forward, board.output.turn))
    except ImportError as exc:
        log.info("simulated driver not available (%s)", exc)
        return None
