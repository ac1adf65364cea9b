"""Parameters of the serial bridge: one table (name, default, range, description) shared by
the node's declarations and ``config/bridge.yaml``, validated into a frozen dataclass."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

from asgp_ros.common.paramspec import ParamSpec, check_values
from asgp_ros.serial.calibration import (
    AxisCalibration,
    JoystickCalibration,
    board_neutral_problem,
)
from asgp_ros.serial.link import LinkConfig
from asgp_ros.serial.override_gate import DEFAULT_TIMEOUT_S
from asgp_ros.serial.safety import default_calibration

#: The firmware's own calibration of (forward, turn) (config.h), which the host's must fit.
BOARD_CALIBRATION = default_calibration()

PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("port", "/dev/asgp_joystick",
              "serial device of the joystick interface board (a stable udev symlink)"),
    ParamSpec("baud", 115200, "UART speed (ignored by USB CDC and ptys)", 1200, 2_000_000),
    ParamSpec("frame_id", "", "header.frame_id of published Joy messages"),
    ParamSpec("override_timeout", DEFAULT_TIMEOUT_S,
              "s: a joy_override older than this is stale and no longer sent (at least "
              "two periods of override_rate)", 0.02, 1.0,
              runtime=True),
    ParamSpec("override_rate", 25.0,
              "Hz: overrides are re-sent at this rate while fresh (board watchdog 200 ms); "
              "read at start-up (its timer is made then)", 6.0, 200.0),
    ParamSpec("mode_release_after", 1.0,
              "s: after this long without a fresh override the board is set to passthrough",
              0.2, 60.0, runtime=True),
    ParamSpec("heartbeat_period", 0.2, "s: host heartbeat period", 0.02, 5.0),
    ParamSpec("heartbeat_timeout", 0.6, "s: no board heartbeat for this long -> link stale",
              0.05, 30.0),
    ParamSpec("silence_reopen", 2.0, "s: a silent board's port is closed and reopened",
              0.1, 60.0),
    ParamSpec("reconnect_min", 0.05, "s: first retry delay when the port cannot be opened",
              0.001, 10.0),
    ParamSpec("reconnect_max", 0.25, "s: retry delay cap (exponential backoff)", 0.001, 60.0),
    ParamSpec("diagnostics_period", 1.0, "s: period of diagnostics messages", 0.05, 60.0),
    ParamSpec("sample_timeout", 0.1,
              "s: no joystick sample for this long -> diagnostics warn", 0.01, 10.0),
    *(ParamSpec(f"calibration.{axis}.{key}", default, desc, low, high, runtime=True)
      for axis in ("forward", "turn")
      for key, default, desc, low, high in (
          ("neutral", 512.0, "ADC counts at rest", 0.0, 1023.0),
          ("minimum", 307.0, "ADC counts at full " + ("reverse" if axis == "forward"
                                                       else "right"), 0.0, 1023.0),
          ("maximum", 717.0, "ADC counts at full " + ("forward" if axis == "forward"
                                                       else "left"), 0.0, 1023.0),
          ("dead_zone", 0.04, "fraction of full deflection read as 0", 0.0, 0.49),
          ("invert", False, "flip the sign of this axis (a stick wired the other way round)",
           None, None),
      )),
)

SPECS: dict[str, ParamSpec] = {p.name: p for p in PARAMS}


@dataclass(frozen=True)
class BridgeParams:
    port: str
    baud: int
    frame_id: str
    override_timeout: float
    override_rate: float
    mode_release_after: float
    heartbeat_period: float
    heartbeat_timeout: float
    silence_reopen: float
    reconnect_min: float
    reconnect_max: float
    diagnostics_period: float
    sample_timeout: float
    calibration: JoystickCalibration

    def link_config(self) -> LinkConfig:
        return LinkConfig(
            port=self.port, baud=self.baud, heartbeat_period=self.heartbeat_period,
            heartbeat_timeout=self.heartbeat_timeout, silence_reopen=self.silence_reopen,
            reconnect_min=self.reconnect_min, reconnect_max=self.reconnect_max,
            calibration=self.calibration)


def bridge_params(values: Mapping[str, object]) -> BridgeParams:
    """Validates parameter values (missing ones take their defaults).

    Raises:
        ValueError: naming the offending parameter.
    """
    v = check_values(PARAMS, values)
    axes = {}
    for axis in ("forward", "turn"):
        try:
            axes[axis] = AxisCalibration(
                neutral=v[f"calibration.{axis}.neutral"],
                minimum=v[f"calibration.{axis}.minimum"],
                maximum=v[f"calibration.{axis}.maximum"],
                dead_zone=v[f"calibration.{axis}.dead_zone"],
                invert=v[f"calibration.{axis}.invert"])
        except ValueError as exc:
            raise ValueError(f"calibration.{axis}: {exc}") from exc
        problem = board_neutral_problem(axes[axis], BOARD_CALIBRATION[axis == "turn"])
        if problem is not None:
            raise ValueError(f"calibration.{axis}: {problem}")
    if v["reconnect_max"] < v["reconnect_min"]:
        raise ValueError("parameter reconnect_max must be >= reconnect_min")
    if v["override_timeout"] < 2.0 / v["override_rate"]:
        # overrides are written at the rate's ticks only: one that goes stale between two
        # was never written (6 Hz and 0.02 s: 4 of 40 written, the chair back to the user
        # four times in 2 s while the layer intervened)
        raise ValueError(
            f"parameter override_timeout ({v['override_timeout']:g} s) must be at least two "
            f"periods of override_rate ({math.ceil(2e3 / v['override_rate']) / 1e3:g} s at "
            f"{v['override_rate']:g} Hz): overrides are written at its ticks, and one that "
            "went stale between two would never be sent")
    if v["heartbeat_timeout"] <= v["heartbeat_period"]:
        raise ValueError("parameter heartbeat_timeout must exceed heartbeat_period")
    if not v["port"].strip():  # (" ": a port that never opens, retried for ever)
        raise ValueError("parameter port is empty")
    return BridgeParams(
        port=v["port"], baud=v["baud"], frame_id=v["frame_id"],
        override_timeout=v["override_timeout"], override_rate=v["override_rate"],
        mode_release_after=v["mode_release_after"], heartbeat_period=v["heartbeat_period"],
        heartbeat_timeout=v["heartbeat_timeout"], silence_reopen=v["silence_reopen"],
        reconnect_min=v["reconnect_min"], reconnect_max=v["reconnect_max"],
        diagnostics_period=v["diagnostics_period"], sample_timeout=v["sample_timeout"],
        calibration=JoystickCalibration(axes["forward"], axes["turn"]))
