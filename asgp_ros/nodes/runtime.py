"""Process start-up shared by the nodes whose stop is rclpy's own signal handling.

rclpy's SIGINT handler shuts every context down from its own thread (which ends a spin, and
a start-up that polls ``context.ok()``) and then calls the handler it replaced. That was
Python's ``default_int_handler``, which raises ``KeyboardInterrupt`` in whatever Python code
the main thread runs next: inside a callback, inside rclpy's executor, or inside a
finaliser such as ``rclpy.task.Future.__del__``, where Python prints "Exception ignored
in ..." with a traceback on stderr (about once in a few hundred SIGINTs during tracking).
The exception adds nothing, since the context shutdown already stops the node, so the
Python-level handler is replaced by one that raises nothing before rclpy installs its own.
"""

from __future__ import annotations

import signal
import types

import rclpy

__all__ = ["init_rclpy"]


def _signal_received(signum: int, frame: types.FrameType | None) -> None:
    """Python-level SIGINT handler under rclpy's: the context is already shutting down."""
    del signum, frame


def init_rclpy(args: list[str] | None = None) -> None:
    """``rclpy.init`` with rclpy's SIGINT and SIGTERM handlers, and no ``KeyboardInterrupt``:
    a signal shuts the context down and raises nothing in the main thread."""
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, _signal_received)  # before init: rclpy chains to it
    rclpy.init(args=args)
