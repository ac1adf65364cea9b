"""High-rate inputs read in batches instead of one executor wake-up per message.

rclpy's executor wakes for every message of every subscription and, at each wake-up,
builds its wait set over all of a node's entities in Python: about 0.35 ms of CPU per
message in ``predictor_node`` (cProfile), so the serial bridge's ``joy`` and ``joy_applied``
at the board's 100 Hz took 14-16 % of a core there, more than the predictions did
(``benchmarks/predictor_latency.py --clock system --joy-hz 100 --applied``).

The predictor needs the joystick only when it predicts, checks its inputs or reports them.
:class:`PolledInputs` therefore creates those subscriptions in a callback group the
executor never waits on (:class:`_NeverReady`: rclpy leaves out of its wait set every
entity whose group says it cannot execute) and takes their messages itself
(:meth:`PolledInputs.drain`, the take rclpy's own ``wait_for_message`` uses): every
``period_s`` on the steady clock, and wherever the node calls it (before a VO message, an
override, its watchdog and its diagnostics). Nothing is lost between two drains: the
subscriptions keep :data:`DEPTH` messages each, and a drain that finds a queue full counts
it (:attr:`PolledInputs.full_queues`: some of its oldest messages may have been dropped).

Each message is handed over with its arrival as the callback would have seen it: the node's
clock at the drain less how long ago DDS received it (the middleware's reception stamp,
on the system clock; the lag is bounded by the time since the previous drain, so a step of
the system clock cannot throw it), and the same lag on the process's own clocks. A
simulated clock (``use_sim_time``, a bag replayed) may run at any rate or stand still:
there the arrival is never before the clock's time at the previous drain. Messages
of all the polled subscriptions are handed over in the order they were received, so a
sample published on ``joy`` and then on ``joy_applied`` is seen in that order, as the
callbacks saw them.

``period_s`` 0 keeps rclpy's callbacks: each message is handed over as it arrives.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from rclpy.callback_groups import CallbackGroup
from rclpy.clock import Clock, ROSClock
from rclpy.clock_type import ClockType
from rclpy.exceptions import InvalidHandle
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile
from rclpy.subscription import Subscription
from rclpy.timer import Timer

from asgp_ros.nodes.qos_watch import QosWatch

__all__ = ["DEPTH", "MIN_PERIOD_S", "Arrival", "PolledInputs", "period_problem"]

#: Messages each polled subscription keeps until a drain takes them: 10 s of the board's
#: 100 Hz, far beyond the time between two drains.
DEPTH = 1000

#: The shortest period of the drains, half the board's: a wake-up of the executor costs up
#: to 0.35 ms, so at most 7 % of a core. A shorter one woke it at every spin (1e-9 s: an
#: idle node took 66-97 % of a core), for nothing a callback per message (0) would not give.
MIN_PERIOD_S = 0.005


def take_waiting(sub: Subscription, limit: int) -> list[tuple[Any, dict[str, Any]]] | None:
    """The messages waiting in ``sub``'s queue, oldest first, with their message info,
    at most ``limit`` (rclpy's executor takes one a wake-up; a sender faster than the reads
    cannot keep a caller taking); None once the subscription is destroyed (the node is
    shutting down)."""
    taken: list[tuple[Any, dict[str, Any]]] = []
    try:
        with sub.handle:
            while len(taken) < limit:
                got = sub.handle.take_message(sub.msg_type, sub.raw)
                if got is None:
                    break
                taken.append(got)
    except InvalidHandle:
        return None
    return taken


def period_problem(name: str, period_s: float, high: float = 1.0) -> str | None:
    """Why ``period_s`` (the parameter ``name``) is no period of the drains, or None: 0 (a
    callback per message) or in [MIN_PERIOD_S, high] s."""
    if period_s == 0.0 or (math.isfinite(period_s) and MIN_PERIOD_S <= period_s <= high):
        return None
    return (f"{name} must be 0 (a callback per message) or in [{MIN_PERIOD_S:g}, {high:g}] s, "
            f"got {period_s}")


@dataclass(frozen=True)
class Arrival:
    """When a message arrived: on the node's clock (None before a simulated clock has
    started) and on the process's ``time.monotonic`` and ``time.perf_counter``."""

    now: float | None
    monotonic: float
    perf: float


#: What a polled subscription hands each message to.
Handler = Callable[[Any, Arrival], None]


class _NeverReady(CallbackGroup):
    """A callback group the executor never runs: its entities stay out of the wait set."""

    def can_execute(self, entity: Any) -> bool:
        return False

    def beginning_execution(self, entity: Any) -> bool:
        return False

    def ending_execution(self, entity: Any) -> None:
        return None


@dataclass
class _Polled:
    sub: Subscription
    handler: Handler


class PolledInputs:
    """A node's high-rate subscriptions, drained in batches (see the module docstring)."""

    def __init__(self, node: Node, watch: QosWatch, period_s: float) -> None:
        problem = period_problem("period_s", period_s, high=math.inf)
        if problem is not None:
            raise ValueError(problem)
        self._node = node
        self._watch = watch
        self.period_s = float(period_s)
        self._group = _NeverReady()
        self._polled: list[_Polled] = []
        self._last_drain = time.monotonic()
        self._last_clock_ns = node.get_clock().now().nanoseconds
        self.taken = 0
        self.full_queues = 0
        #: the drain's timer (None with ``period_s`` 0)
        self.timer: Timer | None = None
        if self.period_s > 0.0:
            # the steady clock, with use_sim_time too: messages arrive on the wall clock,
            # and a paused /clock must not leave them waiting
            self.timer = node.create_timer(self.period_s, self.drain,
                                            clock=Clock(clock_type=ClockType.STEADY_TIME))

    def subscription(self, msg_type: Any, topic: str, handler: Handler,
                     qos: QoSProfile) -> Subscription:
        """Subscribe ``topic``; ``handler(msg, arrival)`` gets every message, in a drain
        (``qos``'s depth raised to :data:`DEPTH`), or as it arrives with ``period_s`` 0."""
        if self.period_s == 0.0:
            return self._watch.subscription(
                msg_type, topic, lambda msg: handler(msg, self._arrival()), qos)
        # ``qos`` with a history of the last DEPTH messages (bounded whatever it asked)
        deep = QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=DEPTH, reliability=qos.reliability,
            durability=qos.durability, lifespan=qos.lifespan, deadline=qos.deadline,
            liveliness=qos.liveliness, liveliness_lease_duration=qos.liveliness_lease_duration,
            avoid_ros_namespace_conventions=qos.avoid_ros_namespace_conventions)
        sub = self._watch.subscription(msg_type, topic, _never_called, deep,
                                       callback_group=self._group)
        self._polled.append(_Polled(sub, handler))
        return sub

    def _arrival(self) -> Arrival:
        """Now, for a message handed over as it arrives."""
        ns = self._node.get_clock().now().nanoseconds
        return Arrival(None if ns == 0 else ns * 1e-9, time.monotonic(), time.perf_counter())

    def drain(self) -> int:
        """Hand the waiting messages to their handlers, in the order received, at most
        :data:`DEPTH` of each subscription (a sender faster than the reads cannot keep one
        going: the rest wait for the next); the number handed over."""
        if not self._polled:
            return 0
        taken: list[tuple[int, int, Any, Handler]] = []
        for polled in self._polled:
            sub = polled.sub
            waiting = take_waiting(sub, DEPTH) or []
            for msg, info in waiting:
                received = int(info.get("received_timestamp", 0) or 0)
                taken.append((received, len(taken), msg, polled.handler))
            count = len(waiting)
            if count >= DEPTH:
                self.full_queues += 1
                self._node.get_logger().warning(
                    f"{sub.topic_name}: {count} messages waiting at one read, its queue full: "
                    f"the oldest may have been lost ({self.full_queues} full so far)",
                    throttle_duration_sec=5.0)
        mono = time.monotonic()
        since_last = max(0.0, mono - self._last_drain)
        self._last_drain = mono
        clock = self._node.get_clock()
        clock_ns = clock.now().nanoseconds
        # the node's clock at the previous drain: on a simulated clock (a bag replayed), which
        # may run at any rate or stand still, no message arrived before it (unless the
        # clock went back since: a bag played again)
        floor_ns = self._last_clock_ns if self._last_clock_ns <= clock_ns else 0
        self._last_clock_ns = clock_ns
        if not taken:
            return 0
        self.taken += len(taken)
        taken.sort(key=lambda item: (item[0], item[1]))
        simulated = isinstance(clock, ROSClock) and clock.ros_time_is_active
        wall_ns = time.time_ns()
        perf = time.perf_counter()
        for received, _, msg, handler in taken:
            # how long ago DDS received it (0 when the middleware gives no stamp), at most
            # the time since the previous drain
            lag = min(max(0.0, (wall_ns - received) * 1e-9), since_last) if received else 0.0
            now = None
            if clock_ns != 0:
                now = clock_ns * 1e-9 - lag
                if simulated:
                    now = max(now, floor_ns * 1e-9)
            handler(msg, Arrival(now, mono - lag, perf - lag))
        return len(taken)

    def values(self) -> dict[str, str]:
        """Diagnostics: the messages taken in drains, and drains that found a queue full."""
        return {"polled_messages": str(self.taken), "polled_queue_full": str(self.full_queues)}


def _never_called(msg: Any) -> None:  # pragma: no cover - the group never executes
    raise AssertionError("a polled subscription's callback ran")
