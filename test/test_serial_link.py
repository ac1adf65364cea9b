"""The host link manager over real ptys: opening with retries, unplug/replug with
reconnection inside 1 s, heartbeat supervision, the version handshake, sending."""

from __future__ import annotations

import os
import select
import threading
import time
import tty

import pytest

from asgp_ros.serial import protocol as proto
from asgp_ros.serial.link import LinkConfig, LinkManager, LinkState
from asgp_ros.sim.board import SimulatedBoard


def wait_until(pred, timeout: float, period: float = 0.005) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(period)
    return bool(pred())


class Recorder:
    def __init__(self) -> None:
        self.samples: list = []
        self.states: list[tuple[float, LinkState, str]] = []

    def sample(self, s) -> None:
        self.samples.append(s)

    def state(self, state: LinkState, reason: str) -> None:
        self.states.append((time.monotonic(), state, reason))


@pytest.fixture
def board(tmp_path):
    b = SimulatedBoard(lambda t: (0.4, -0.2), link_path=tmp_path / "asgp_joystick")
    yield b
    b.stop()
    assert b.error is None, b.error


def test_open_retries_until_the_port_appears(board):
    rec = Recorder()
    with LinkManager(LinkConfig(board.port), on_sample=rec.sample, on_state=rec.state) as link:
        assert wait_until(lambda: link.stats().open_failures >= 2, 2.0)
        assert link.state == LinkState.CONNECTING
        assert "could not open" in link.stats().last_error or "No such" in \
            link.stats().last_error
        assert not link.send_override(0.1, 0.0)  # nothing to send to
        board.start()
        # retries go on, at most reconnect_max (0.25 s) apart: how soon it connects is
        # measured by benchmarks/link_timing.py, not asserted here
        assert link.wait_for_state(LinkState.CONNECTED, 10.0)
        assert wait_until(lambda: len(rec.samples) > 10, 10.0)
    assert [s for _, s, _ in rec.states][-3:] == [LinkState.HANDSHAKE, LinkState.CONNECTED,
                                                  LinkState.STOPPED]


def test_a_second_link_on_the_same_board_is_refused_as_in_use(board):
    """A second bridge on the same port (another launch's namespace, the default port) read
    half of the frames and handshook over the first: /joy fell from 100 to 46 Hz and both
    logs filled with "port lost". The port is opened exclusively: the second waits,
    saying the port is in use, and the first keeps every frame."""
    board.start()
    first, second = Recorder(), Recorder()
    with LinkManager(LinkConfig(board.port), on_sample=first.sample,
                     on_state=first.state) as one:
        assert one.wait_for_state(LinkState.CONNECTED, 10.0)
        with LinkManager(LinkConfig(board.port), on_sample=second.sample,
                         on_state=second.state) as two:
            assert wait_until(lambda: two.stats().open_failures >= 2, 5.0)
            assert "in use by another program" in two.stats().last_error
            assert two.state == LinkState.CONNECTING and not second.samples
            n = len(first.samples)
            time.sleep(0.3)
            assert one.state == LinkState.CONNECTED and len(first.samples) > n
        # the first gone, the second takes the port
    with LinkManager(LinkConfig(board.port), on_sample=second.sample) as two:
        assert two.wait_for_state(LinkState.CONNECTED, 10.0)


def test_unplug_and_replug_reconnects(board):
    board.start()
    rec = Recorder()
    with LinkManager(LinkConfig(board.port), on_sample=rec.sample, on_state=rec.state) as link:
        assert link.wait_for_state(LinkState.CONNECTED, 3.0)
        for cycle in range(1, 4):
            n = len(rec.samples)
            board.unplug()
            assert link.wait_for_state(LinkState.CONNECTING, 2.0)
            time.sleep(0.3)  # the device is gone for a while
            board.replug()
            assert link.wait_for_state(LinkState.CONNECTED, 10.0)
            assert wait_until(lambda n=n: len(rec.samples) > n + 10, 10.0)  # samples resume
            st = link.stats()
            assert st.reconnects == cycle
            assert "port lost" in st.last_error or "open failed" in st.last_error
        reasons = [r for _, s, r in rec.states if s == LinkState.CONNECTED]
        assert reasons[-1].startswith("reconnected (3)")
        assert link._thread is not None and link._thread.is_alive()


def test_fast_unplug_cycles_do_not_crash(board):
    board.start()
    with LinkManager(LinkConfig(board.port)) as link:
        assert link.wait_for_state(LinkState.CONNECTED, 3.0)
        for delay in (0.0, 0.01, 0.05, 0.002, 0.1):
            board.unplug()
            time.sleep(delay)
            board.replug()
        assert link.wait_for_state(LinkState.CONNECTED, 2.0)
        assert link._thread is not None and link._thread.is_alive()


def test_a_port_gone_as_it_opens_is_reopened(board, monkeypatch):
    """A port unplugged just after it opened: pyserial's reset_input_buffer raises
    termios.error (EIO), which is neither a SerialException nor an OSError. The link
    thread died of it (a bridge deaf until restarted); now the port is reopened."""
    import termios

    import serial

    calls = []
    reset = serial.Serial.reset_input_buffer

    def failing_once(self):
        calls.append(1)
        if len(calls) == 1:
            raise termios.error(5, "Input/output error")
        return reset(self)

    monkeypatch.setattr(serial.Serial, "reset_input_buffer", failing_once)
    board.start()
    with LinkManager(LinkConfig(board.port)) as link:
        assert link.wait_for_state(LinkState.CONNECTED, 5.0)
        assert len(calls) >= 2 and link._thread is not None and link._thread.is_alive()
        assert "port lost" in link.stats().last_error


def test_silent_board_goes_stale_then_recovers_or_is_reopened(board):
    board.start()
    rec = Recorder()
    cfg = LinkConfig(board.port, heartbeat_timeout=0.4, silence_reopen=1.0)
    with LinkManager(cfg, on_sample=rec.sample, on_state=rec.state) as link:
        assert link.wait_for_state(LinkState.CONNECTED, 3.0)
        board.set_silent(True)
        assert link.wait_for_state(LinkState.STALE, 10.0)
        board.set_silent(False)
        assert link.wait_for_state(LinkState.CONNECTED, 10.0)
        assert link.stats().reconnects == 0  # heartbeat back on the same connection
        board.set_silent(True)
        assert wait_until(lambda: link.stats().connects == 2, 10.0)  # reopened
        board.set_silent(False)
        assert link.wait_for_state(LinkState.CONNECTED, 10.0)


class FakeBoard:
    """A pty that answers HELLO with a given protocol version and streams samples."""

    def __init__(self, protocol_version: int) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        self.path = os.ttyname(self.slave)
        self.version = protocol_version
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        parser = proto.StreamParser()
        seq = 0
        while not self.stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.01)
            if ready:
                for f in parser.feed(os.read(self.master, 1024)):
                    if f.type == proto.MsgType.HELLO:
                        os.write(self.master, proto.encode(
                            proto.Version(self.version, 9, 9, 9, 100, 200), seq))
                        seq += 1
            os.write(self.master, proto.encode(
                proto.Sample(600, 500, proto.Status.NONE, 2048, 2048), seq & 0xFF))
            seq += 1

    def close(self) -> None:
        self.stop.set()
        self.thread.join(1.0)
        os.close(self.master)
        os.close(self.slave)


def test_incompatible_protocol_version_is_refused():
    fake = FakeBoard(protocol_version=2)
    rec = Recorder()
    try:
        with LinkManager(LinkConfig(fake.path), on_sample=rec.sample) as link:
            assert link.wait_for_state(LinkState.INCOMPATIBLE, 2.0)
            assert "protocol 2" in link.stats().last_error
            time.sleep(0.1)
            assert rec.samples == []  # nothing from a board we do not understand
            assert not link.send_override(0.2, 0.0)
    finally:
        fake.close()


def test_compatible_fake_board_and_counters():
    fake = FakeBoard(protocol_version=proto.PROTOCOL_VERSION)
    rec = Recorder()
    try:
        with LinkManager(LinkConfig(fake.path), on_sample=rec.sample) as link:
            assert link.wait_for_state(LinkState.CONNECTED, 2.0)
            assert wait_until(lambda: len(rec.samples) > 5, 2.0)
            st = link.stats()
            assert st.firmware == "9.9.9" and st.frames_lost == 0
            assert rec.samples[-1].raw_forward == 600
            assert st.last_sample_age < 0.5
    finally:
        fake.close()


@pytest.mark.parametrize("kwargs, match", [
    ({"port": ""}, "port"),
    ({"port": "x", "baud": 0}, "baud"),
    ({"port": "x", "reconnect_min": 1.0, "reconnect_max": 0.5}, "reconnect_max"),
    ({"port": "x", "heartbeat_timeout": 0.1}, "heartbeat_timeout"),
    ({"port": "x", "read_timeout": 0.0}, "read_timeout"),
])
def test_link_config_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        LinkConfig(**kwargs)


def test_override_values_are_checked_before_sending():
    link = LinkManager(LinkConfig("/nonexistent"))
    with pytest.raises(ValueError, match="outside"):
        link.send_override(1.5, 0.0)
    assert not link.send_override(0.5, 0.0)  # not started: not sent
