"""What the host makes of a SAMPLE's status bits (docs/serial_protocol.md, "What the host
does with each status bit").

The board has already acted on every condition by the time the host hears of it; the host's
job is to say the truth downstream. ``joy`` carries the user's joystick as read, or nothing
when there is no reading (ADC_FAULT); sensor_msgs/Joy has no status field, so everything
else is said on ``diagnostics``. These functions decide the level and the message of the
bridge's ``joystick`` and ``override`` diagnostic statuses; the node only converts them.
No ROS here.
"""

from __future__ import annotations

from dataclasses import dataclass

from asgp_ros.serial.protocol import Status

LEVELS = ("OK", "WARN", "ERROR", "STALE")

#: Every status bit, in the order the diagnostics list them.
STATUS_BITS: tuple[Status, ...] = (
    Status.MODE_OVERRIDE, Status.OVERRIDE_ACTIVE, Status.WATCHDOG, Status.NEUTRAL_STOP,
    Status.CLAMPED, Status.ADC_FAULT, Status.HOST_LOST)


@dataclass(frozen=True)
class Verdict:
    level: str    # one of LEVELS
    message: str


def flag_names(status: Status) -> str:
    """``"WATCHDOG|CLAMPED"``, or ``"NONE"``."""
    names = [bit.name or "" for bit in STATUS_BITS if bit in status]
    return "|".join(names) or "NONE"


def joystick_verdict(status: Status, raw: tuple[int, int]) -> Verdict:
    """The ``joystick`` diagnostic status for the latest sample: the reading and the output."""
    if Status.ADC_FAULT in status:
        return Verdict("ERROR", f"ADC_FAULT: joystick reading implausible (raw {raw[0]}, "
                                f"{raw[1]}: open wire or short); the board holds the chair "
                                "neutral; joy is withheld until the reading is good")
    if Status.CLAMPED in status:
        if Status.OVERRIDE_ACTIVE in status:
            return Verdict("WARN", "CLAMPED: the override was limited to the safe output "
                                   "range; the chair gets less than commanded")
        return Verdict("OK", "CLAMPED: the output is limited to the safe range; joy is the "
                             "joystick as read, the chair gets less")
    return Verdict("OK", "joystick reading good")


def override_verdict(status: Status, sending: bool) -> Verdict:
    """The ``override`` diagnostic status: what became of the host's overrides.

    ``sending``: the node has a fresh ``joy_override`` and is sending it.
    """
    if Status.OVERRIDE_ACTIVE in status:
        return Verdict("OK", "active: the chair follows joy_override")
    if Status.NEUTRAL_STOP in status:
        return Verdict("WARN", "NEUTRAL_STOP: the user let go of the joystick; the override "
                               "is held off and the chair is stopped")
    if Status.WATCHDOG in status:
        if sending:
            return Verdict("WARN", "WATCHDOG: overrides do not reach the board in time; the "
                                   "user drives")
        return Verdict("OK", "idle: board still in override mode, no fresh override, the user "
                             "drives (WATCHDOG)")
    if sending:
        if Status.ADC_FAULT in status:
            return Verdict("WARN", "not applied: ADC_FAULT holds the chair neutral")
        return Verdict("OK", "sending: switching the board to override mode")
    return Verdict("OK", "idle: the user drives")


HOST_LOST_MESSAGE = ("HOST_LOST: the board heard nothing from the host for 1 s and gave the "
                     "chair back to the user (passthrough); until it hears the host again")
