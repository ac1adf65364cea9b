"""The link's rule for the board's sequence numbers, over a real pty: what reaches ``joy``
is each reading once, in the board's order. A repeated frame is dropped, a frame behind the
last one (delivered late) is dropped, a board restart (its count and uptime from zero) is
followed without counting frames that were never sent, and the counters say which."""

from __future__ import annotations

import contextlib
import os
import select
import threading
import time
import tty
from collections.abc import Iterator

import numpy as np
import pytest
from test_serial_link import wait_until

from asgp_ros.serial import protocol as proto
from asgp_ros.serial.link import (
    RESTART_SEQ_BELOW,
    SEQ_RESTART_AFTER,
    SEQ_RESYNC_AFTER,
    LinkConfig,
    LinkManager,
    LinkState,
)


def sample(mark: int) -> proto.Sample:
    """A SAMPLE whose raw forward reading names it."""
    return proto.Sample(mark, 512, proto.Status.NONE, 2048, 2048)


class ScriptedBoard:
    """A pty that answers every HELLO with our VERSION (its SEQ one after the last frame
    played) and writes the frames it is given, as given."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self.next_seq = 0
        self.hellos = 0
        self._lock = threading.Lock()
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def play(self, frames: list[tuple[int, proto.Message]]) -> None:
        with self._lock:
            data = b"".join(proto.encode(m, seq) for seq, m in frames)
            os.write(self.master, data)
            self.next_seq = (frames[-1][0] + 1) & 0xFF

    def play_next(self, messages: list[proto.Message]) -> list[tuple[int, proto.Message]]:
        """Play ``messages`` numbered on from the board's count, read and written under the
        lock: a VERSION answering a late HELLO cannot take a SEQ they were given."""
        with self._lock:
            frames = [((self.next_seq + i) & 0xFF, m) for i, m in enumerate(messages)]
            os.write(self.master, b"".join(proto.encode(m, seq) for seq, m in frames))
            self.next_seq = (frames[-1][0] + 1) & 0xFF
        return frames

    def _run(self) -> None:
        parser = proto.StreamParser()
        while not self.stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.01)
            if not ready:
                continue
            try:
                data = os.read(self.master, 1024)
            except OSError:
                continue
            for f in parser.feed(data):
                if f.type == proto.MsgType.HELLO:
                    self.hellos += 1
                    with self._lock, contextlib.suppress(OSError):
                        v = proto.Version(proto.PROTOCOL_VERSION, 9, 9, 9, 100, 200)
                        os.write(self.master, proto.encode(v, self.next_seq))
                        self.next_seq = (self.next_seq + 1) & 0xFF

    def close(self) -> None:
        self.stop.set()
        self.thread.join(1.0)
        os.close(self.master)
        os.close(self.slave)


@pytest.fixture
def linked():
    board = ScriptedBoard()
    marks: list[int] = []
    # long timeouts: the script, not the clock, decides what the link sees
    link = LinkManager(LinkConfig(board.path, heartbeat_timeout=30.0, silence_reopen=30.0),
                       on_sample=lambda s: marks.append(s.raw_forward))
    link.start()
    try:
        assert link.wait_for_state(LinkState.CONNECTED, 5.0)
        yield board, link, marks
    finally:
        link.stop()
        board.close()


def run(board, link, frames) -> None:
    """Plays the frames and waits until the link has read all of them."""
    before = link.stats()
    board.play(frames)
    n = len(frames)
    assert wait_until(lambda: link.stats().frames_rx - before.frames_rx >= n, 5.0)


def advance_to(board, link, target: int) -> None:
    """Steps the count forward, less than half of it at a time, to end at ``target``."""
    cur = (board.next_seq - 1) & 0xFF
    while not 1 <= (target - cur) & 0xFF < 128:
        cur = (cur + 100) & 0xFF
        run(board, link, [(cur, sample(50))])
    run(board, link, [(target, sample(51))])


def frames_of(seqs: list[int], start_mark: int = 100) -> list[tuple[int, proto.Message]]:
    return [(s, sample(start_mark + i)) for i, s in enumerate(seqs)]


@pytest.mark.parametrize("seqs, taken, lost, repeated, late, restarts", [
    # in order, across the wrap of the count
    ([250, 251, 252, 253, 254, 255, 0, 1, 2], range(9), 0, 0, 0, 0),
    # a gap: two frames lost
    ([10, 11, 14, 15], [0, 1, 2, 3], 2, 0, 0, 0),
    # one frame twice: published once
    ([10, 11, 11, 12], [0, 1, 3], 0, 1, 0, 0),
    # one frame delivered after the next: dropped, its SEQ counted lost to joy
    ([10, 12, 11, 13], [0, 1, 3], 1, 0, 1, 0),
    # three late frames in a row, far from a new count's start: late, not a restart
    ([100, 101, 105, 102, 103, 104, 106], [0, 1, 2, 6], 3, 0, 3, 0),
    # the board restarts after SEQ 50: its first frames are behind; SEQ_RESTART_AFTER in
    # a row follow the new count, the ones before the last of them are lost, and samples
    # wait for the protocol to be confirmed again (the firmware may be new)
    ([48, 49, 50, 0, 1, 2, 3, 4], [0, 1, 2], SEQ_RESTART_AFTER - 1, 0, 0, 1),
    # a restart whose first frame was cut by the reset itself
    ([60, 61, 1, 2, 3, 4], [0, 1], SEQ_RESTART_AFTER - 1, 0, 0, 1),
    # one frame of line noise that passed the CRC with a SEQ far ahead: the board's count
    # is followed again after SEQ_RESYNC_AFTER frames (it was held back up to 1.3 s)
    ([40, 41, 140, *range(42, 54)], [0, 1, 2, *range(3 + SEQ_RESYNC_AFTER - 1, 15)],
     98 + SEQ_RESYNC_AFTER - 1, 0, 0, 1),
])
def test_sequence_rule(linked, seqs, taken, lost, repeated, late, restarts):
    board, link, marks = linked
    before = link.stats()
    advance_to(board, link, (seqs[0] - 1) & 0xFF)
    del marks[:]
    st0 = link.stats()
    run(board, link, frames_of(seqs))
    st = link.stats()
    assert marks == [100 + i for i in taken]
    assert st.frames_lost - st0.frames_lost == lost
    assert st.frames_repeated - st0.frames_repeated == repeated
    assert st.frames_late - st0.frames_late == late
    assert st.seq_restarts - st0.seq_restarts == restarts
    # a new count from its start is a board restart, counted once, with a new handshake;
    # a count followed again after noise (from anywhere) is not
    restarted = restarts and seqs[seqs.index(max(seqs)) + 1] < RESTART_SEQ_BELOW
    assert st.board_restarts - before.board_restarts == (1 if restarted else 0)
    assert link.wait_for_state(LinkState.CONNECTED, 5.0)


def test_restart_after_a_high_seq_is_told_by_the_uptime(linked):
    """A restart after SEQ 200 looks like a jump ahead to the new count: 55 SEQs that were
    never sent. The new count's first heartbeat has a smaller uptime: the restart is
    counted, the 55 are taken back, and the protocol is confirmed again (the firmware may
    be new) before samples flow again."""
    board, link, marks = linked
    advance_to(board, link, 197)
    run(board, link, [(198, proto.Heartbeat(60_000, 5, 0, 0)), (199, sample(51)),
                      (200, sample(52))])
    del marks[:]
    st0 = link.stats()
    hellos0 = board.hellos
    # the new count: SEQ 0 is cut by the reset, 1 .. 19 are samples, 20 a heartbeat
    run(board, link, [*frames_of(list(range(1, 20))), (20, proto.Heartbeat(200, 0, 0, 0))])
    st = link.stats()
    assert marks == [100 + i for i in range(19)]
    assert st.board_restarts - st0.board_restarts == 1
    assert st.frames_lost - st0.frames_lost == 1  # SEQ 0, not 201 .. 255
    assert "restarted" in st.last_error
    assert wait_until(lambda: board.hellos > hellos0, 2.0)
    # samples flow again. Numbered by the board itself: under load the host may send a
    # second HELLO, whose VERSION took the SEQ read before the sample was played (the
    # sample came as a repeat); a VERSION mid-stream starts a new handshake, during which
    # a sample is not taken: then the next one is
    for _ in range(3):
        assert link.wait_for_state(LinkState.CONNECTED, 2.0)
        board.play_next([sample(300)])
        if wait_until(lambda: marks[-1] == 300, 1.0):
            break
    assert marks[-1] == 300, marks[-3:]


def test_uptime_wrap_is_no_restart(linked):
    """After 49.7 days the board's uptime (uint32 ms) wraps: no restart."""
    board, link, _ = linked
    s = board.next_seq
    run(board, link, [(s, proto.Heartbeat(0xFFFF_FF00, 1, 0, 0)),
                      ((s + 1) & 0xFF, proto.Heartbeat(0x0000_0010, 2, 0, 0))])
    st = link.stats()
    assert st.board_restarts == 0 and st.state == LinkState.CONNECTED


@contextlib.contextmanager
def echoing_pty() -> Iterator[str]:
    """A pty whose far end writes back whatever it reads (a loopback adapter); yields the
    path a host opens."""
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    stop = threading.Event()

    def echo() -> None:
        while not stop.is_set():
            ready, _, _ = select.select([master], [], [], 0.02)
            if ready:
                with contextlib.suppress(OSError):
                    os.write(master, os.read(master, 1024))

    th = threading.Thread(target=echo, daemon=True)
    th.start()
    try:
        yield os.ttyname(slave)
    finally:
        stop.set()
        th.join(1.0)
        os.close(master)
        os.close(slave)


def test_frames_only_a_host_sends_are_named():
    """A device that echoes what the host writes (a loopback) never completes the
    handshake, and the link says what it heard."""
    with echoing_pty() as path, LinkManager(LinkConfig(path)) as link:
        assert wait_until(lambda: link.stats().host_frames_heard > 0, 3.0)
        st = link.stats()
        assert st.state == LinkState.HANDSHAKE
        assert "HELLO" in st.last_error and "echo" in st.last_error
        assert st.hellos_unanswered > 0


def test_restart_window_constant_is_below_half_the_count():
    assert SEQ_RESTART_AFTER < SEQ_RESYNC_AFTER < RESTART_SEQ_BELOW < 128


def test_a_sample_behind_line_noise_is_delivered_when_the_line_goes_idle(linked):
    """Three bytes of noise claiming a 32-byte frame (A5 5A 20), then the board's last
    sample and silence: the sample waited for 39 bytes that never came. A partial frame
    idle for RX_IDLE_S is given up (as the firmware does), and the sample behind it is
    delivered, timed by its last byte."""
    board, link, marks = linked
    advance_to(board, link, 9)
    del marks[:]
    times: list[float] = []
    lost0 = link.stats().frames_lost
    link._on_sample = lambda s: (marks.append(s.raw_forward), times.append(s.t_rx))
    with board._lock:
        t_sent = time.monotonic()
        os.write(board.master, bytes.fromhex("a55a20") + proto.encode(sample(321), 10))
    assert wait_until(lambda: marks == [321], 2.0), marks
    assert times[0] - t_sent < 0.1  # the time its bytes came, not the time it was given
    assert link.stats().frames_lost == lost0



def test_a_backlog_read_at_once_is_timed_at_the_boards_rate(linked):
    """After the reader stalled (a busy host), one read returns up to 2 s of the board's
    samples. Each is timed back from the read by its distance to the newest at the board's
    rate (100 Hz here), the SEQs lost between them counted as samples and other frames
    not, and none before the previous read: a backlog is not the stick's present."""
    board, link, marks = linked
    advance_to(board, link, 9)
    times: list[float] = []
    del marks[:]
    link._on_sample = lambda s: (marks.append(s.raw_forward), times.append(s.t_rx))
    samples = [*range(11, 30), *range(31, 40), *range(42, 60)]  # 30 a heartbeat, 40-41 lost
    frames = frames_of(samples)
    frames.insert(19, (30, proto.Heartbeat(1000, 0, 0, 0)))
    with link._lock:  # the reader stalls on its next read, after one sample
        t_stall = time.monotonic()
        board.play([(10, sample(99))])
        time.sleep(0.6)  # the stall: the backlog (0.47 s at 100 Hz) is written meanwhile
        board.play(frames)
        t_release = time.monotonic()
    assert wait_until(lambda: len(marks) == 1 + len(samples), 5.0), marks
    assert marks == [99, *range(100, 100 + len(samples))]
    backlog = np.array(times[1:])
    steps = np.diff(backlog)
    lost_at = samples.index(42) - 1  # between the samples of SEQ 39 and 42
    np.testing.assert_allclose(np.delete(steps, lost_at), 0.01, rtol=0, atol=1e-9)
    assert steps[lost_at] == pytest.approx(0.03, abs=1e-9)
    assert backlog[-1] >= t_release  # the newest came when the read returned
    assert backlog[0] - (backlog[-1] - 0.47) == pytest.approx(0.0, abs=1e-9)
    assert backlog[0] > times[0] > t_stall  # and after the read before
