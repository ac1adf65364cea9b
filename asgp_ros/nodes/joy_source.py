"""Which joystick stream feeds a node's predictor (ROS-free): the board's output as the
serial bridge measures it (``joy_applied``) while it arrives, else ``joy``, the user's
stick, with the override the board applies modelled on it
(:func:`asgp_ros.core.shared_control.applied_command`).

The bridge publishes both for every sample, with one stamp, ``joy`` first; whichever of the
two a sample's stamp comes in first feeds the predictor, the other is a repeat and is
dropped. A recording without ``joy_applied``, or another joystick driver, leaves ``joy``
feeding.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from asgp_ros.nodes.parameters import topic_name_problem

#: ``joy_applied`` feeds while its newest message is at most this old (s, the node's clock):
#: ten of the bridge's 100 Hz samples.
MEASURED_FRESH_S = 0.1


def check_topics(resolve: Callable[[str], str], **names: str) -> None:
    """Refuse a configuration that names one topic twice among a node's joystick inputs.

    ``joy_applied`` set to the user's own ``joy`` would feed the stick as the board's
    output, so an override would never show in a path; ``joy_override`` set to either would
    take the user's stick for an override. Empty names (the input switched off) are skipped.

    Args:
        resolve: the node's ``resolve_topic_name`` (expansion and remapping).
        names: parameter name -> topic name.

    Raises:
        ValueError: a name that does not resolve, or two that resolve to one topic.
    """
    seen: dict[str, str] = {}
    for param, name in names.items():
        if not name.strip():
            continue
        problem = topic_name_problem(resolve, name)
        if problem is not None:
            raise ValueError(f"{param}: {name!r} is not a valid topic name ({problem})")
        full = resolve(name)
        if full in seen:
            raise ValueError(f"{seen[full]} and {param} name one topic, {full}: they must "
                             "differ (the user's stick, the board's output and the "
                             "overrides sent are three streams)")
        seen[full] = param


class JoySource:
    """The bookkeeping of the two streams; times in seconds."""

    def __init__(self, reset_jump_s: Callable[[], float]) -> None:
        """``reset_jump_s``: the node's present ``reset_jump_s`` (a runtime parameter: read
        at each sample, so that a change reaches this bookkeeping as it reaches the
        predictor's buffers)."""
        self.reset_jump_s = reset_jump_s
        self.measured_arrival = -math.inf  # node clock of the newest joy_applied
        self.last_fed = -math.inf          # stamp of the newest sample fed
        self.measured_samples = 0          # samples fed from joy_applied

    def measured(self, now: float | None) -> bool:
        """``joy_applied`` is arriving: ``joy`` does not feed."""
        return now is not None and 0.0 <= now - self.measured_arrival <= MEASURED_FRESH_S

    def take_measured(self, t: float, now: float | None) -> bool:
        """A ``joy_applied`` sample stamped ``t`` arrived: whether to feed it (not when
        ``joy`` already fed that stamp; a stamp far back is a clock jump, and is fed)."""
        if now is not None:
            self.measured_arrival = now
        return not self.last_fed - self.reset_jump_s() < t <= self.last_fed

    def fed(self, t: float, measured: bool) -> None:
        self.last_fed = t
        self.measured_samples += measured
