"""Which ``joy_override`` command is still fresh enough to drive the chair (ROS-free).

The bridge re-sends the last override to the board while it is fresh and then simply stops,
so that the firmware's 200 ms watchdog hands the chair back to the user. "Fresh" has two
clocks:

* **arrival** (the bridge's monotonic clock): at most ``timeout`` since the command was
  received. This alone bounds how long any one message can drive the chair.
* **stamp** (the ROS clock, when the message carries a header stamp): at most ``timeout``
  since the publisher stamped it. A transport may hand over a message late (a reliable
  stream holds every later sample back until a lost one is resent, up to a heartbeat
  period); by arrival alone such a command would count as new. A stamped command that is
  already older than ``timeout`` when it arrives is refused and counted, and a stamped
  command stops counting as fresh ``timeout`` after its stamp even if it arrived late.

An unstamped command (``header.stamp`` zero, as ``ros2 topic pub`` sends by default) is
judged by arrival alone. A stamp up to ``MAX_AHEAD_S`` ahead of the bridge's clock is
accepted (clocks of two machines differ a little; arrival still bounds it); one further
ahead is of another timeline (a node on a replayed or simulated ``/clock``, judging data
that are not the chair's) and is refused. A publisher whose clock runs behind the
bridge's by more than ``timeout``, or ahead by more than ``MAX_AHEAD_S``, has every
override refused: the user keeps the chair, and the bridge's diagnostics say why.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from asgp_ros.common import board

#: A stamp further ahead of the bridge's clock than this (s) is of another timeline.
MAX_AHEAD_S = 1.0
#: The bridge's default ``override_timeout`` (s): how long a command stays fresh.
DEFAULT_TIMEOUT_S = board.OVERRIDE_TIMEOUT_S


@dataclass
class OverrideGate:
    """The last accepted override and the refusals of stale ones; times in seconds."""

    command: tuple[float, float] | None = None
    arrival: float = -math.inf       # monotonic clock, when the command was accepted
    stamp: float | None = None       # ROS clock, the command's header stamp (None: unstamped)
    refused_stale: int = 0           # stamped commands already stale when they arrived
    last_refusal: float = -math.inf  # monotonic clock of the last such refusal
    last_refused_age: float = math.nan  # how old (by stamp) that refused command was
    refused_older: int = 0           # stamped before the fresh command held: out of order
    timeout: float = math.inf        # the timeout the held command was accepted under

    def offer(self, command: tuple[float, float], stamp: float | None, arrival: float,
              clock_now: float, timeout: float) -> bool:
        """Takes ``command`` received at ``arrival`` (monotonic) with header ``stamp``
        (ROS seconds, None if unstamped) when the ROS clock reads ``clock_now``; returns
        False, counting it, if its stamp is already more than ``timeout`` old, more than
        ``MAX_AHEAD_S`` ahead, or the age is not a finite number."""
        if stamp is not None:
            age = clock_now - stamp
            if not (math.isfinite(age) and -MAX_AHEAD_S <= age <= timeout):
                self.refused_stale += 1
                self.last_refusal = arrival
                self.last_refused_age = age
                return False
            if (self.stamp is not None and stamp < self.stamp
                    and self.fresh(arrival, clock_now, timeout) is not None):
                # older than the command in force (delivered out of order): it would
                # replace a newer decision (a forward push after a reverse one)
                self.refused_older += 1
                return False
        self.command, self.stamp, self.arrival = command, stamp, arrival
        self.timeout = timeout
        return True

    def fresh(self, mono_now: float, clock_now: float, timeout: float
              ) -> tuple[float, float] | None:
        """The command to send now, or None once it is stale on either clock (by the
        shorter of ``timeout`` and the one it was accepted under: a timeout raised at
        runtime does not bring back a command already stale)."""
        timeout = min(timeout, self.timeout)
        if self.command is None or not mono_now - self.arrival <= timeout:
            return None
        if self.stamp is not None and not clock_now - self.stamp <= timeout:
            return None
        return self.command

    def fresh_until(self, timeout: float) -> float:
        """The time (the clock of ``arrival``, which the stamp shares when the caller
        judges both on one clock) after which the command is no longer fresh: ``timeout``
        after the earlier of its arrival and its stamp; -inf without a command."""
        if self.command is None:
            return -math.inf
        start = self.arrival if self.stamp is None else min(self.arrival, self.stamp)
        return start + min(timeout, self.timeout)

    def refusal(self, timeout: float) -> str:
        """Why the last refused command was refused, in words."""
        age = self.last_refused_age
        if math.isfinite(age) and age < 0.0:
            return (f"stamped {-age:.3f} s ahead of this node's clock, more than "
                    f"{MAX_AHEAD_S:g} s (another timeline: a publisher on a replayed or "
                    f"simulated /clock?)")
        return (f"stamped {age:.3f} s before this node's clock, older than override_timeout "
                f"{timeout} s (delivered late, or the publisher's clock is behind)")

    def age(self, mono_now: float) -> float:
        """Seconds since the last accepted command arrived (inf: none yet)."""
        return mono_now - self.arrival

    def refusing(self, mono_now: float, within: float = 1.0) -> bool:
        """Stale commands were refused within the last ``within`` s and none was accepted
        since: someone is trying to override and nothing reaches the chair."""
        return self.last_refusal > self.arrival and mono_now - self.last_refusal <= within
