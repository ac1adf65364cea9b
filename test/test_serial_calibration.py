"""The host's joystick calibration against the board's: overrides in the units of ``joy``
drive the chair as the user's stick at the same reading does, and the board's output reads
back in those units (asgp_ros.serial.calibration)."""

from __future__ import annotations

import numpy as np
import pytest

from asgp_ros.serial import safety as fw
from asgp_ros.serial.calibration import (
    AxisCalibration,
    board_neutral_problem,
    board_permille,
    host_deflection,
)

BOARD = fw.default_calibration()[0]
HOSTS = {
    "default": AxisCalibration(),
    "inverted": AxisCalibration(invert=True),
    "short stick": AxisCalibration(minimum=380.0, maximum=650.0),
    "off centre, no dead zone, inverted": AxisCalibration(
        neutral=520.0, minimum=300.0, maximum=700.0, dead_zone=0.0, invert=True),
}
DEFLECTIONS = np.round(np.linspace(-1.0, 1.0, 81), 6)


@pytest.mark.parametrize("name", list(HOSTS))
def test_raw_for_inverts_deflection(name):
    host = HOSTS[name]
    for d in DEFLECTIONS:
        assert host.deflection(host.raw_for(float(d))) == pytest.approx(d, abs=1e-9)
    with pytest.raises(ValueError):
        host.raw_for(float("nan"))
    with pytest.raises(ValueError):
        host.raw_for(1.5)


@pytest.mark.parametrize("name", list(HOSTS))
def test_an_override_drives_as_the_stick_at_the_same_reading(name):
    """For every stick position, the override of what the host reads there makes the board
    write the code it writes for the stick itself (to a count of the reading's rounding),
    and that code reads back as the same deflection."""
    host = HOSTS[name]
    for raw in range(0, 1024):
        if not BOARD.adc_fault_low <= raw <= BOARD.adc_fault_high:
            continue
        d = host.deflection(raw)
        passthrough, _ = BOARD.permille_to_dac(BOARD.adc_to_permille(raw))
        override, _ = BOARD.permille_to_dac(board_permille(d, host, BOARD))
        if host.deflection(raw) == 0.0:  # the host's dead zone: an override of 0 is neutral
            assert override == BOARD.dac_neutral
            continue
        if abs(d) == 1.0:  # beyond the host's ends the stick reads 1, the board goes on
            assert np.sign(override - BOARD.dac_neutral) == np.sign(
                passthrough - BOARD.dac_neutral)
            continue
        assert abs(override - passthrough) <= 5, (raw, d, override, passthrough)
        if override != BOARD.dac_neutral and abs(BOARD.adc_to_permille(raw)) < 1000:
            # (within the board's dead band, or beyond its full scale, the board writes the
            # same code for many readings: no reading back then)
            assert host_deflection(override, host, BOARD) == pytest.approx(d, abs=0.005)


def test_an_inverted_stick_is_not_mirrored_by_an_override():
    """+ left on a joystick wired the other way round: the board must write what that stick
    writes when pushed left, below neutral, where the raw per mille would be above."""
    host = HOSTS["inverted"]
    assert host.raw_for(0.5) < host.neutral
    assert board_permille(0.5, host, BOARD) < 0
    code, _ = BOARD.permille_to_dac(board_permille(0.5, host, BOARD))
    assert host_deflection(code, host, BOARD) == pytest.approx(0.5, abs=0.01)


def test_a_short_stick_is_not_overtaken_by_an_override():
    """A stick that reaches only 650 counts (0.66 of the board's span): an override never
    commands more than the stick can, and the user's own reading is never faster."""
    host = HOSTS["short stick"]
    full = board_permille(1.0, host, BOARD)
    assert full == BOARD.adc_to_permille(650) < 700
    for d in DEFLECTIONS[DEFLECTIONS > 0]:
        assert board_permille(float(d), host, BOARD) <= BOARD.adc_to_permille(
            round(host.raw_for(float(d))))


def test_a_host_zero_outside_the_boards_neutral_window_is_refused():
    """The board reads 512 +- 8 counts as neutral (its dead-man rule: a neutral stick stops
    any override). A stick resting at 525 was taken: the board drove the chair at rest, and
    the layer's "stop" (an override of 0, sent as the host's neutral) drove it at 25 per
    mille. A host dead zone reaching past the window made joy read 0 while the board drove
    the chair (0.1: up to 532 counts)."""
    from asgp_ros.serial.params import PARAMS, bridge_params

    for host in HOSTS.values():
        assert board_neutral_problem(host, BOARD) is None
    off = AxisCalibration(neutral=525.0)
    assert "rests at 525 counts" in board_neutral_problem(off, BOARD)
    assert board_permille(0.0, off, BOARD) == 0  # a stop is a stop
    wide = AxisCalibration(dead_zone=0.1)
    problem = board_neutral_problem(wide, BOARD)
    assert "joy reads 0 from 492 to 532 counts" in problem and "at most 0.039" in problem
    assert board_neutral_problem(AxisCalibration(dead_zone=0.039), BOARD) is None
    # a stick never moved while the monitor ran: its noise made the extremes, joy jumped
    # between +1 and -0.5 at rest and every override fell in the board's neutral
    still = AxisCalibration(neutral=512.0, minimum=510.0, maximum=513.0)
    assert "not pushed to its extremes" in board_neutral_problem(still, BOARD)
    assert "not pushed to its extremes" in board_neutral_problem(
        AxisCalibration(neutral=512.0, minimum=100.0, maximum=520.0), BOARD)
    assert board_neutral_problem(
        AxisCalibration(neutral=512.0, minimum=100.0, maximum=521.0, dead_zone=0.0),
        BOARD) is None
    defaults = {spec.name: spec.default for spec in PARAMS}
    for bad, words in (({"calibration.forward.neutral": 525.0}, "rests at 525"),
                       ({"calibration.turn.dead_zone": 0.1}, "joy reads 0"),
                       ({"calibration.turn.minimum": 510.0, "calibration.turn.maximum": 513.0},
                        "not pushed to its extremes")):
        with pytest.raises(ValueError, match=words) as err:
            bridge_params({**defaults, **bad})
        assert str(err.value).startswith(f"calibration.{next(iter(bad)).split('.')[1]}:")
