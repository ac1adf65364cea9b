"""Timing of the joystick interface board and the serial bridge that the host side models
(ROS-free; the serial layer and the core both read it from here).

``WATCHDOG_MS`` is the firmware's ``ASGP_WATCHDOG_MS`` (firmware/asgp_bridge/config.h; a test
checks the two agree through :mod:`asgp_ros.serial.safety`), ``OVERRIDE_TIMEOUT_S`` the serial
bridge's default ``override_timeout`` (:mod:`asgp_ros.serial.params`).
"""

from __future__ import annotations

#: An override frame drives the chair for this long after the board received it (ms).
WATCHDOG_MS = 200
#: The serial bridge writes a ``joy_override`` to the board until this long (s) after the
#: earlier of its stamp and its arrival (the default of its ``override_timeout``).
OVERRIDE_TIMEOUT_S = 0.15
#: The board's neutral rule, in deflection units: its joystick reading is 0 per mille within
#: the ADC deadband (firmware/asgp_bridge/safety.h, rule 2), and an override never drives
#: the chair then. Half a per mille: the smallest reading the board reports is 1.
BOARD_NEUTRAL = 0.5e-3
#: The firmware's joystick reading: the ADC's span (counts from neutral to full deflection)
#: and its neutral deadband (``ASGP_ADC_SPAN``, ``ASGP_ADC_DEADBAND`` in config.h; mirrored
#: and checked through :mod:`asgp_ros.serial.safety`).
ADC_SPAN = 205
ADC_DEADBAND = 8
#: The board's neutral window in deflection units: a stick reading within it drives
#: nothing (the firmware's rule 2, 512 +- 8 counts). The calibrations' "parked chair"
#: (:mod:`asgp_ros.core.adaptive`, :func:`asgp_ros.learning.training.calibrate`) is the
#: stick within it: an undeadzoned joystick reads a few thousandths at rest.
NEUTRAL_WINDOW = ADC_DEADBAND / ADC_SPAN
