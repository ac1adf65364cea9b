"""The version handshake over real ptys: a stray VERSION frame in a healthy stream starts a
new handshake instead of condemning the link, the link is declared incompatible only when
the board keeps answering with another version, and HELLOs go on while incompatible."""

from __future__ import annotations

import contextlib
import os
import select
import threading
import time
import tty

import pytest

from asgp_ros.serial import protocol as proto
from asgp_ros.serial.link import INCOMPATIBLE_AFTER, LinkConfig, LinkManager, LinkState
from asgp_ros.sim.board import SimulatedBoard

STRAY = proto.encode(proto.Version(2, 1, 0, 0, 100, 200), 77)  # valid CRC, another version


def wait_until(pred, timeout: float, period: float = 0.005) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(period)
    return bool(pred())


class Journal:
    """Samples and state changes in the order the reader thread reported them."""

    def __init__(self) -> None:
        self.events: list[tuple[float, str, object]] = []

    def sample(self, s) -> None:
        self.events.append((time.monotonic(), "sample", s))

    def state(self, state: LinkState, reason: str) -> None:
        self.events.append((time.monotonic(), "state", state))

    def samples_after(self, t: float) -> int:
        return sum(1 for tt, kind, _ in self.events if kind == "sample" and tt > t)

    def states(self) -> list[LinkState]:
        return [v for _, kind, v in self.events if kind == "state"]  # type: ignore[misc]


@pytest.fixture
def board(tmp_path):
    b = SimulatedBoard(lambda t: (0.4, -0.2), link_path=tmp_path / "asgp_joystick").start()
    yield b
    b.stop()
    assert b.error is None, b.error


@pytest.mark.parametrize("version", [2, proto.PROTOCOL_VERSION])
def test_stray_version_frame_starts_a_new_handshake_and_samples_resume(board, version):
    journal = Journal()
    with LinkManager(LinkConfig(board.port), on_sample=journal.sample,
                     on_state=journal.state) as link:
        assert link.wait_for_state(LinkState.CONNECTED, 3.0)
        assert wait_until(lambda: journal.samples_after(0.0) > 10, 2.0)
        mark = len(journal.events)
        t0 = time.monotonic()
        # a SEQ just ahead of the board's count (one behind it is a late frame, dropped)
        seq = (board._logic.tx_seq + 2) & 0xFF
        board.inject(proto.encode(proto.Version(version, 7, 7, 7, 100, 200), seq))
        assert wait_until(lambda: journal.samples_after(t0) > 20
                          and link.state == LinkState.CONNECTED, 1.0), link.stats()
        after = journal.events[mark:]
        states = [v for _, kind, v in after if kind == "state"]
        assert states == [LinkState.HANDSHAKE, LinkState.CONNECTED], states
        # nothing is delivered while the protocol is unconfirmed
        kinds = [kind if kind == "sample" else v for _, kind, v in after]
        i, j = kinds.index(LinkState.HANDSHAKE), kinds.index(LinkState.CONNECTED)
        assert "sample" not in kinds[i:j]
        st = link.stats()
        assert st.unsolicited_versions == 1
        assert st.firmware == "1.0.0"  # the board's own answer, not the stray frame's
        assert st.connects == 1  # same port, no reopen
        assert LinkState.INCOMPATIBLE not in journal.states()


def test_board_that_keeps_answering_another_version_is_incompatible_and_is_still_asked():
    fake = ScriptedVersionBoard([2] * 100)
    try:
        with LinkManager(LinkConfig(fake.path)) as link:
            assert link.wait_for_state(LinkState.INCOMPATIBLE, 3.0)
            assert fake.hellos >= INCOMPATIBLE_AFTER
            assert "protocol 2" in link.stats().last_error
            n = fake.hellos
            assert wait_until(lambda: fake.hellos > n + 1, 2.0)  # HELLOs go on
            assert link.state == LinkState.INCOMPATIBLE
            assert not link.send_override(0.1, 0.0)
    finally:
        fake.close()


def test_one_odd_answer_does_not_make_the_link_incompatible():
    fake = ScriptedVersionBoard([2] * (INCOMPATIBLE_AFTER - 1) + [1] * 100)
    journal = Journal()
    try:
        with LinkManager(LinkConfig(fake.path), on_sample=journal.sample,
                         on_state=journal.state) as link:
            assert link.wait_for_state(LinkState.CONNECTED, 3.0)
            assert LinkState.INCOMPATIBLE not in journal.states()
            assert wait_until(lambda: journal.samples_after(0.0) > 5, 2.0)
    finally:
        fake.close()


def test_incompatible_link_recovers_only_after_as_many_good_answers():
    fake = ScriptedVersionBoard([2] * INCOMPATIBLE_AFTER + [1] * 100)
    journal = Journal()
    try:
        with LinkManager(LinkConfig(fake.path, handshake_timeout=0.05),
                         on_sample=journal.sample, on_state=journal.state) as link:
            assert link.wait_for_state(LinkState.CONNECTED, 3.0)
            states = journal.states()
            assert states.index(LinkState.INCOMPATIBLE) < states.index(LinkState.CONNECTED)
            assert fake.hellos >= 2 * INCOMPATIBLE_AFTER
            assert wait_until(lambda: journal.samples_after(0.0) > 5, 2.0)
    finally:
        fake.close()


def test_late_answer_to_an_earlier_hello_does_not_restart_the_handshake():
    # the board answers 0.35 s after each HELLO: the host has asked twice when the first
    # answer connects, and the second answer arrives once connected
    fake = ScriptedVersionBoard([1] * 100, reply_delay=0.35)
    journal = Journal()
    try:
        with LinkManager(LinkConfig(fake.path), on_sample=journal.sample,
                         on_state=journal.state) as link:
            assert link.wait_for_state(LinkState.CONNECTED, 3.0)
            assert wait_until(lambda: journal.samples_after(0.0) > 30, 2.0)
            assert wait_until(lambda: fake.answered == 2, 2.0)
            t = time.monotonic()
            assert wait_until(lambda: journal.samples_after(t) > 10, 2.0)
            assert journal.states() == [LinkState.HANDSHAKE, LinkState.CONNECTED]
            assert link.stats().unsolicited_versions == 0
    finally:
        fake.close()


class ScriptedVersionBoard:
    """A pty that answers the n-th HELLO with VERSION ``versions[n]`` after ``reply_delay``
    seconds and streams samples and heartbeats."""

    def __init__(self, versions: list[int], reply_delay: float = 0.0) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self.versions = list(versions)
        self.delay = reply_delay
        self.hellos = 0
        self.answered = 0
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        parser = proto.StreamParser()
        seq = 0
        tick = 0
        due: list[tuple[float, proto.Version]] = []
        while not self.stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.01)
            out: list[proto.Message] = []
            now = time.monotonic()
            while due and due[0][0] <= now:
                out.append(due.pop(0)[1])
                self.answered += 1
            if ready:
                try:
                    data = os.read(self.master, 1024)
                except OSError:
                    data = b""
                for f in parser.feed(data):
                    if f.type == proto.MsgType.HELLO:
                        v = self.versions[min(self.hellos, len(self.versions) - 1)]
                        self.hellos += 1
                        due.append((now + self.delay, proto.Version(v, 9, 9, 9, 100, 200)))
            out.append(proto.Sample(600, 500, proto.Status.NONE, 2048, 2048))
            tick += 1
            if tick % 20 == 0:
                out.append(proto.Heartbeat(tick * 10, 0, 0, 0))
            for msg in out:
                with contextlib.suppress(OSError):
                    os.write(self.master, proto.encode(msg, seq))
                seq += 1

    def close(self) -> None:
        self.stop.set()
        self.thread.join(1.0)
        os.close(self.master)
        os.close(self.slave)
