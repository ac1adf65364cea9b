"""How every node of the package stops: SIGINT and SIGTERM only set a flag.

rclpy's own handlers (``rclpy.init``'s default) shut every context down from a thread of
their own at the signal, and then call the handler they replaced: for SIGINT that was
Python's ``default_int_handler``, which raises ``KeyboardInterrupt`` in whatever the main
thread runs next. Both bit the nodes:

* the exception lands anywhere: in a callback, inside rclpy's executor, or inside a
  finaliser such as ``rclpy.task.Future.__del__``, where Python prints "Exception ignored
  in ..." with a traceback at a node's exit;
* the context is torn down by one thread while the main thread is still in a callback, or
  already destroying the node and shutting the context down itself: the VO node crashed
  natively (SIGSEGV) at 1 of 150 SIGINTs under traffic (``benchmarks/node_signals.py``),
  and the serial bridge's reader thread, publishing into the context as it went, now and
  then at exit.

Here rclpy installs no handler (``SignalHandlerOptions.NO``). The signals set a flag
(:class:`StopSignals`), nothing else; :func:`spin` runs the executor in short slices and
returns once the flag is set, so the main thread alone destroys the node and then shuts
the context down, in that order, with nothing else running. A long start-up (a model
being read) polls :func:`stop_requested`. A signal during start-up is honoured as soon as
the node is built.
"""

from __future__ import annotations

import signal
import threading
import types
from collections.abc import Callable

import rclpy
from rclpy.executors import Executor
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import ok

__all__ = ["SPIN_SLICE_S", "StopSignals", "init", "spin", "stop_requested"]

#: Longest wait of the executor between two looks at the stop flag (s): the bound on how
#: late a stop signal is seen when no message arrives.
SPIN_SLICE_S = 0.05

_STOP = threading.Event()  # set by a stop signal; one per process, as signals are
_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def stop_requested() -> bool:
    """True once SIGINT or SIGTERM has arrived inside the :class:`StopSignals` block."""
    return _STOP.is_set()


class StopSignals:
    """Context manager: SIGINT and SIGTERM set the stop flag (:func:`stop_requested`)
    instead of raising or killing. The flag starts clear and is cleared again on exit,
    when the previous handlers come back."""

    def __init__(self) -> None:
        self._previous: dict[int, Callable[[int, types.FrameType | None], object] | int
                             | None] = {}

    def __enter__(self) -> StopSignals:
        _STOP.clear()
        self._previous = {sig: signal.signal(sig, self._on_signal) for sig in _SIGNALS}
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler if handler is not None else signal.SIG_DFL)
        _STOP.clear()

    @staticmethod
    def _on_signal(signum: int, frame: types.FrameType | None) -> None:
        del signum, frame
        _STOP.set()


def init(args: list[str] | None = None) -> None:
    """``rclpy.init`` without rclpy's signal handlers (use inside :class:`StopSignals`)."""
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)


def spin(executor: Executor, slice_s: float = SPIN_SLICE_S) -> None:
    """Run ``executor`` until a stop signal (or until its context is shut down)."""
    while not _STOP.is_set() and ok(context=executor.context):
        executor.spin_once(timeout_sec=slice_s)
