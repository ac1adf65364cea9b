"""The simulated board over a real pty, driven by the host link: samples, overrides, the
200 ms watchdog (measured), the neutral rule, the clamp, bad frames, the host timeout, and
the ``asgp board`` command."""

from __future__ import annotations

import itertools
import math
import os
import signal
import subprocess
import sys
import time

import pytest
import serial

from asgp_ros.serial import protocol as proto
from asgp_ros.serial import safety as fw
from asgp_ros.serial.link import LinkConfig, LinkManager, LinkState
from asgp_ros.sim.board import SimulatedBoard


def wait_until(pred, timeout: float, period: float = 0.005) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(period)
    return bool(pred())


def expected_deflection(raw: float) -> float:
    """Host calibration of the default config, written out independently:
    x = (raw - 512) / 205, dead zone 0.04 removed and rescaled."""
    x = (raw - 512.0) / 205.0
    mag = min(1.0, max(0.0, (abs(x) - 0.04) / 0.96))
    return math.copysign(mag, x) if mag else 0.0


@pytest.fixture
def make_board(tmp_path):
    boards: list[SimulatedBoard] = []

    def make(joystick=None, **kw) -> SimulatedBoard:
        b = SimulatedBoard(joystick, link_path=tmp_path / f"joy{len(boards)}", **kw).start()
        boards.append(b)
        return b

    yield make
    for b in boards:
        b.stop()
        assert b.error is None, b.error


@pytest.fixture
def connect():
    links: list[LinkManager] = []

    def make(board: SimulatedBoard, **kw):
        samples: list = []
        link = LinkManager(LinkConfig(board.port, **kw), on_sample=samples.append)
        link.start()
        links.append(link)
        assert link.wait_for_state(LinkState.CONNECTED, 3.0), link.stats()
        return link, samples

    yield make
    for link in links:
        link.stop()


def test_samples_arrive_in_order_with_correct_calibration(make_board, connect):
    def ramp(t):  # sweeps the whole range, both signs, inside and outside the dead zone
        return ((2.5 * t) % 2.0) - 1.0, -0.8 * math.sin(7.0 * t)

    board = make_board(ramp, record=True)
    link, samples = connect(board)
    assert wait_until(lambda: len(samples) >= 120, 5.0)
    link.stop()
    st = link.stats()
    assert st.frames_lost == 0 and st.crc_errors == 0
    v = link.version
    assert v is not None and (v.sample_rate_hz, v.watchdog_ms) == (100, 200)
    got = samples[:100]
    # in order: consecutive SAMPLE frames of the board, the same raw values it wrote
    sent = {s.seq: s for s in board.sent}
    for a, b in itertools.pairwise(got):
        assert b.t_rx >= a.t_rx
        assert (b.seq - a.seq) % 256 in (1, 2)  # 2 when a heartbeat came in between
    first = [i for i, s in enumerate(board.sent) if s.seq == got[0].seq][-1]
    assert [(s.raw_forward, s.raw_turn) for s in board.sent[first:first + 100]] == \
           [(s.raw_forward, s.raw_turn) for s in got]
    for s in got:
        assert sent[s.seq].raw_forward == s.raw_forward
        assert s.forward == pytest.approx(expected_deflection(s.raw_forward), abs=1e-9)
        assert s.turn == pytest.approx(expected_deflection(s.raw_turn), abs=1e-9)
    assert min(s.forward for s in got) < -0.3 and max(s.forward for s in got) > 0.3


def test_constant_joystick_quantisation(make_board, connect):
    board = make_board(lambda t: (0.5, -0.25))
    _, samples = connect(board)
    assert wait_until(lambda: len(samples) >= 5, 3.0)
    s = samples[-1]
    # 512 + 0.5 * 205 = 614.5 -> 614 (round half even), 512 - 0.25 * 205 = 460.75 -> 461
    assert (s.raw_forward, s.raw_turn) == (614, 461)
    assert s.forward == pytest.approx((102 / 205 - 0.04) / 0.96)
    assert s.turn == pytest.approx(-(51 / 205 - 0.04) / 0.96)
    assert s.status == proto.Status.NONE
    # passthrough: the chair gets the user's deflection per the firmware calibration
    user = fw.AxisCal().adc_to_permille(614)
    assert board.output.code_forward == fw.DAC_NEUTRAL + round(user * fw.DAC_SPAN / 1000)


def test_override_reaches_board_and_watchdog_reverts_after_200ms(make_board, connect):
    board = make_board(lambda t: (0.6, 0.0))
    link, samples = connect(board)
    assert link.set_mode(proto.Mode.OVERRIDE)
    t_last = 0.0
    for _ in range(12):  # 25 Hz for about 0.5 s
        assert link.send_override(-0.3, 0.4)
        t_last = time.monotonic()
        time.sleep(0.04)
    out = board.output
    assert out.override_active
    assert out.forward == pytest.approx(-0.3, abs=1.0 / fw.DAC_SPAN)
    assert out.turn == pytest.approx(0.4, abs=1.0 / fw.DAC_SPAN)
    assert proto.Status.OVERRIDE_ACTIVE in samples[-1].status
    assert samples[-1].out_forward == out.code_forward
    n_before = len(board.revert_events)
    # stop sending: the board must fall back to the user after 200 ms (its clock)
    assert wait_until(lambda: not board.output.override_active, 2.0)
    assert len(board.revert_events) == n_before + 1
    revert_ms, last_override_ms = board.revert_events[-1]
    delay_ms = revert_ms - last_override_ms
    print(f"watchdog revert {delay_ms} ms after the last override (board clock)")
    assert delay_ms >= 200  # never early (how soon after: benchmarks/link_timing.py)
    # seen from the host: the first sample without the override
    assert wait_until(lambda: proto.Status.WATCHDOG in samples[-1].status, 1.0)
    first_user = next(s for s in samples if s.t_rx > t_last
                      and proto.Status.OVERRIDE_ACTIVE not in s.status)
    host_delay = first_user.t_rx - t_last
    print(f"host sees passthrough {host_delay * 1000:.0f} ms after its last override")
    assert 0.15 <= host_delay <= 0.6
    assert board.output.forward == pytest.approx(fw.AxisCal().adc_to_permille(635) / 1000,
                                                 abs=2.0 / fw.DAC_SPAN)


def test_neutral_user_always_stops_even_under_override(make_board, connect):
    board = make_board(lambda t: (0.0, 0.01))  # inside the dead band
    link, _samples = connect(board)
    link.set_mode(proto.Mode.OVERRIDE)

    def pump(n):
        for _ in range(n):
            link.send_override(0.8, 0.5)
            time.sleep(0.03)

    pump(8)
    out = board.output
    assert (out.code_forward, out.code_turn) == (fw.DAC_NEUTRAL, fw.DAC_NEUTRAL)
    assert proto.Status.NEUTRAL_STOP in out.status and not out.override_active
    board.set_joystick(lambda t: (0.3, 0.0))  # the user pushes again: the override applies
    pump(5)
    assert board.output.override_active
    assert board.output.forward == pytest.approx(0.8, abs=1.0 / fw.DAC_SPAN)


def test_outputs_are_clamped_to_the_calibrated_range(make_board, connect):
    cal = (fw.AxisCal(limit_pos=500, limit_neg=300), fw.AxisCal(dac_min=1800, dac_max=2300))
    board = make_board(lambda t: (-0.9, 0.5), calibration=cal)
    link, samples = connect(board)
    assert wait_until(lambda: samples and proto.Status.CLAMPED in samples[-1].status, 2.0)
    assert board.output.forward == pytest.approx(-0.3, abs=1.0 / fw.DAC_SPAN)  # passthrough
    link.set_mode(proto.Mode.OVERRIDE)
    for _ in range(6):
        link.send_override(0.9, -1.0)
        time.sleep(0.03)
    out = board.output
    assert out.override_active and proto.Status.CLAMPED in out.status
    assert out.forward == pytest.approx(0.5, abs=1.0 / fw.DAC_SPAN)
    assert out.code_turn == 1800


def test_bad_frames_are_ignored_and_reported(make_board, connect):
    board = make_board(lambda t: (0.5, 0.0))
    link, _samples = connect(board)
    link.set_mode(proto.Mode.OVERRIDE)
    with serial.Serial(board.slave_path, 115200, timeout=0.1) as raw:  # a second writer
        good = proto.encode(proto.Override(-700, 0), 200)
        corrupted = bytearray(good)
        corrupted[6] ^= 0x10
        out_of_range = proto.encode_frame(proto.MsgType.OVERRIDE, 201,
                                          (1500).to_bytes(2, "little") + bytes(2))
        raw.write(b"\x00\xa5\x5a\xff garbage" + bytes(corrupted) + out_of_range)
        raw.flush()
        # one ERROR per tick, the latest: the out-of-range override
        assert wait_until(lambda: link.stats().board_errors >= 1, 2.0)
        assert link.stats().last_board_error.startswith("OVERRIDE_RANGE")
        assert board.host_crc_errors >= 1
        assert not board.output.override_active  # neither frame was acted on
        raw.write(good)  # and the link still works
        raw.flush()
        assert wait_until(lambda: board.output.override_active, 1.0)
    assert board.output.forward == pytest.approx(-0.7, abs=1.0 / fw.DAC_SPAN)
    assert link.state == LinkState.CONNECTED


@pytest.mark.parametrize(("noise_bytes", "expected_active"),
                         [(40, []), (8, [185, 195, 205])],
                         ids=["line-never-quiet", "parked-then-quiet"])
def test_an_override_behind_line_noise_drives_only_while_fresh_by_its_own_last_byte(
        noise_bytes, expected_active):
    """Three bytes of noise claiming a 39-byte frame (A5 5A 20), the host's last override
    right behind them (its last byte at 10 ms), then one byte of line noise every 19 ms:
    the line is never idle for RX_IDLE_MS, and the override is found only when the 39 bytes
    are in (485 ms, the candidate rejected) or after the line goes quiet (the idle expiry at
    185 ms). It was timed by the newest byte, not its own last one, and drove the chair until
    675 ms, or 355 ms: up to 665 ms after its last byte. Each frame is timed by its own last
    byte: found 475 ms late the override is stale and the user drives; found 175 ms late it
    drives for the 25 ms left (the mirror of the firmware: test_firmware.py runs the C)."""
    board = fw.BoardLogic(lambda frame: None)
    stick = (700, 512)
    user = (board.cal[0].adc_to_permille(stick[0]), board.cal[1].adc_to_permille(stick[1]))
    board.rx(proto.encode(proto.SetMode(proto.Mode.OVERRIDE), 1), 0)
    board.tick(stick, 5)
    last_byte_ms = 10
    board.rx(bytes.fromhex("a55a20") + proto.encode(proto.Override(900, 0), 2), last_byte_ms)
    noise_at = {last_byte_ms + 19 * (k + 1) for k in range(noise_bytes)}
    active = []
    for t in range(last_byte_ms + 1, 1000):
        if t in noise_at:
            board.rx(b"\x11", t)
        if t % 10 == 5:
            out = board.tick(stick, t)
            if proto.Status.OVERRIDE_ACTIVE in out.status:
                active.append(t)
                assert out.out_pm == (900, 0)
            else:
                assert out.out_pm == user and proto.Status.WATCHDOG in out.status, (t, out)
    assert all(t - last_byte_ms < fw.WATCHDOG_MS for t in active), active
    assert active == expected_active


def test_host_silent_for_1s_resets_the_mode(make_board):
    board = make_board(lambda t: (0.5, 0.0))
    with serial.Serial(board.port, 115200, timeout=0.1) as raw:
        raw.write(proto.encode(proto.Hello(), 0) + proto.encode(proto.SetMode(1), 1)
                  + proto.encode(proto.Override(200, 0), 2))
        raw.flush()
        assert wait_until(lambda: board.mode == proto.Mode.OVERRIDE, 5.0)
        assert wait_until(lambda: board.mode == proto.Mode.PASSTHROUGH, 10.0)
    # on the board's own clock: never before 1 s without a byte from the host (how long
    # after is a matter of scheduling: benchmarks/link_timing.py measures it)
    assert len(board.host_lost_events) == 1
    reset_ms, last_host_ms = board.host_lost_events[0]
    assert reset_ms - last_host_ms >= fw.HOST_TIMEOUT_MS


def test_asgp_board_command_prints_a_working_port(repo_root, tmp_path):
    link_path = tmp_path / "asgp_joystick"
    env = dict(os.environ, PYTHONPATH=str(repo_root))
    proc = subprocess.Popen(
        [sys.executable, "-m", "asgp_ros.cli", "board", "--link", str(link_path),
         "--source", "scripted", "--duration", "20"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=repo_root, env=env,
        # a shell without job control starts background jobs with SIGINT ignored, and the
        # child would keep it: give the command the SIGINT a terminal would deliver
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        port = proc.stdout.readline().strip()
        assert port == str(link_path)
        samples: list = []
        with LinkManager(LinkConfig(port), on_sample=samples.append) as link:
            assert link.wait_for_state(LinkState.CONNECTED, 5.0)
            assert wait_until(lambda: len(samples) >= 20, 3.0)
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(10)
    assert proc.returncode in (0, 130)
    assert not link_path.exists()  # the board removed its symlink


def test_board_as_a_context_manager_removes_its_pty_and_link(tmp_path):
    link_path = tmp_path / "joystick"
    with SimulatedBoard(lambda t: (0.0, 0.0), link_path=link_path) as board:
        assert os.path.realpath(link_path) == board.slave_path
    assert not link_path.exists()
    assert board.error is None


def test_a_board_whose_start_was_cut_short_still_stops_and_removes_its_link(
        tmp_path, monkeypatch):
    # Ctrl-C inside Thread.start(), before the thread ran: stop() used to raise "cannot
    # join thread before it is started" and leave the link behind.
    import threading

    def interrupted(self):
        raise KeyboardInterrupt

    link_path = tmp_path / "joystick"
    board = SimulatedBoard(lambda t: (0.0, 0.0), link_path=link_path)
    monkeypatch.setattr(threading.Thread, "start", interrupted)
    with pytest.raises(KeyboardInterrupt):
        board.start()
    monkeypatch.undo()
    board.stop()
    assert not os.path.lexists(link_path)

    link = LinkManager(LinkConfig(str(tmp_path / "no_port")))
    monkeypatch.setattr(threading.Thread, "start", interrupted)
    with pytest.raises(KeyboardInterrupt):
        link.start()
    monkeypatch.undo()
    link.stop()
    assert link.state is LinkState.STOPPED


_SIGTERM_IN_START = """
import os, signal, sys, threading
from pathlib import Path
from asgp_ros.common.fileio import Terminated, raise_on_termination
from asgp_ros.sim.board import SimulatedBoard

raise_on_termination()
real_start = threading.Thread.start

def start_after_a_sigterm(self):
    os.kill(os.getpid(), signal.SIGTERM)  # the handler runs before the thread starts
    real_start(self)

threading.Thread.start = start_after_a_sigterm
board = SimulatedBoard(lambda t: (0.0, 0.0), link_path=Path(sys.argv[1]))
try:
    board.start()
except Terminated:
    print("alive" if board._thread is not None and board._thread.is_alive() else "dead")
finally:
    board.stop()
"""


def test_a_stop_signal_during_the_boards_start_waits_until_it_is_up(repo_root, tmp_path):
    # asgp board's SIGTERM between the link's creation and the thread's start: the
    # exception is held until start() is done, so that stop() joins a started thread.
    link_path = tmp_path / "joystick"
    proc = subprocess.run([sys.executable, "-c", _SIGTERM_IN_START, str(link_path)],
                          capture_output=True, text=True, timeout=60, cwd=repo_root,
                          env=dict(os.environ, PYTHONPATH=str(repo_root)))
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.strip() == "alive"
    assert not os.path.lexists(link_path)


def test_board_rejects_bad_configuration():
    with pytest.raises(ValueError, match="rate_hz"):
        SimulatedBoard(rate_hz=0.5)
    with pytest.raises(ValueError, match="dead band"):
        fw.AxisCal(adc_deadband=300)


def test_driver_joystick_closes_the_loop_through_the_board_output():
    from asgp_ros.sim.board import driver_joystick

    pytest.importorskip("asgp_ros.sim.driver")
    board = SimulatedBoard()  # not started: its output stays neutral, so the chair rests
    source = driver_joystick(3, board)
    assert source is not None
    values = [source(0.01 * k) for k in range(1500)]
    assert all(-1.0 <= f <= 1.0 and -1.0 <= t <= 1.0 for f, t in values)
    assert values[0] == (0.0, 0.0)  # every drive starts with the stick released
    assert any(abs(f) > 0.2 or abs(t) > 0.2 for f, t in values)  # and then drives
    assert source.state.v == 0.0  # the chair follows the board's (neutral) output


@pytest.mark.parametrize("rest_counts", [0, 13])
def test_asgp_board_monitor_prints_a_calibration_block(tmp_path, capsys, rest_counts):
    """``asgp board --monitor PORT`` on the simulated board: rest first, then the extremes.
    A stick resting 13 counts off the board's neutral (outside its +-8 window: the board
    drives the chair at rest, and the dead-man rule cannot fire) was printed as an ordinary
    block; it is warned about, as the bridge refuses it."""
    from asgp_ros.cli import main

    rest = rest_counts / fw.ADC_SPAN

    def stick(t: float) -> tuple[float, float]:
        # at rest well past the first fifth of the samples (the monitor's neutral), then
        # the four extremes in turn
        return (rest, 0.0) if t < 2.5 else (math.copysign(1.0, math.sin(8.0 * t)),
                                            math.copysign(1.0, math.cos(8.0 * t)))

    with SimulatedBoard(stick, link_path=tmp_path / "joy") as board:
        assert main(["board", "--monitor", board.port, "--duration", "4"]) == 0
    captured = capsys.readouterr()
    out = captured.out
    if rest_counts:
        assert "warning: forward: the stick rests at 525 counts" in captured.err, captured.err
        assert "turn" not in captured.err
    else:
        assert "warning" not in captured.err, captured.err
    block = out[out.index("calibration:"):]
    values = {}
    for axis in ("forward", "turn"):
        part = block[block.index(f"  {axis}:"):].splitlines()[1:4]
        values[axis] = {line.split(":")[0].strip(): float(line.split(":")[1]) for line in part}
    for axis, v in values.items():
        assert v["minimum"] < v["neutral"] < v["maximum"], (axis, v)
        assert abs(v["neutral"] - fw.ADC_NEUTRAL) <= 20, (axis, v)


@pytest.mark.parametrize(("push", "said"), [
    (0.0, "the stick was not pushed to its extremes"),
    (0.15, "was the stick pushed all the way?")])
def test_asgp_board_monitor_tells_a_stick_not_pushed_to_its_extremes(tmp_path, capsys, push,
                                                                      said):
    """A stick left at rest while the monitor ran: its ADC noise made the extremes (512 /
    510 / 513), printed as an ordinary block without a word, which the bridge took (joy
    jumped between +1 and -0.5 at rest). Pushed a little only: every fuller push would read
    as full deflection."""
    from asgp_ros.cli import main

    def stick(t: float) -> tuple[float, float]:
        return (0.0, 0.0) if t < 1.5 else (push * math.copysign(1.0, math.sin(8.0 * t)),
                                           push * math.copysign(1.0, math.cos(8.0 * t)))

    with SimulatedBoard(stick, link_path=tmp_path / "joy") as board:
        assert main(["board", "--monitor", board.port, "--duration", "3"]) == 0
    err = capsys.readouterr().err
    for axis in ("forward", "turn"):
        assert f"warning: {axis}: " in err and said in err, err


def test_asgp_board_monitor_without_a_board_fails_with_a_message(tmp_path, capsys):
    from asgp_ros.cli import main

    assert main(["board", "--monitor", str(tmp_path / "nothing"), "--duration", "0.1"]) == 2
    assert "no board answered" in capsys.readouterr().err
    # an empty port started the simulated board instead; a link in a missing directory
    # was reported with the pty's name
    assert main(["board", "--monitor", "", "--duration", "0.1"]) == 2
    assert "--monitor needs the port" in capsys.readouterr().err
    assert main(["board", "--link", str(tmp_path / "nodir" / "port"), "--duration",
                 "0.1"]) == 2
    assert f"no directory {tmp_path / 'nodir'}" in capsys.readouterr().err


def test_the_link_is_made_without_touching_a_file_beside_it(tmp_path):
    """The board made its link through PATH.tmp and deleted a user's file of that name."""
    precious = tmp_path / "asgp_joystick.tmp"
    precious.write_text("the user's data\n")
    with SimulatedBoard(link_path=tmp_path / "asgp_joystick") as board:
        assert os.readlink(board.port) == board.slave_path
    assert precious.read_text() == "the user's data\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["asgp_joystick.tmp"]


def test_a_board_that_stops_leaves_a_link_it_no_longer_owns(tmp_path):
    """A second board took the link over; the first one's exit removed it while the second
    ran."""
    link = tmp_path / "asgp_joystick"
    first = SimulatedBoard(link_path=link).start()
    try:
        with SimulatedBoard(link_path=link) as second:
            assert os.readlink(link) == second.slave_path
            first.stop()
            assert os.readlink(link) == second.slave_path
        assert not os.path.lexists(link)  # its own link, removed
    finally:
        first.stop()


def test_a_slow_board_keeps_its_link_supervised(tmp_path):
    """Heartbeats came every 20 ticks whatever the rate: at 10 Hz every 2 s, and the host,
    which expects one within 0.6 s, saw the link stale half the time. They come at 5 Hz."""
    with SimulatedBoard(rate_hz=10.0) as board, LinkManager(LinkConfig(board.port)) as link:
        assert link.wait_for_state(LinkState.CONNECTED, 5.0)
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            assert link.state == LinkState.CONNECTED, link.stats()
            time.sleep(0.05)
