"""Run a node's entry point as a child of the demo that dies with it.

    python -m asgp_ros.demo.child PARENT_PID MODULE:FUNCTION [ARGS...]

Asks the kernel for SIGTERM when the parent dies (``prctl(PR_SET_PDEATHSIG)``, Linux),
checks that the parent is still there (it may have died before the request), then calls
``FUNCTION()`` with ``sys.argv = [MODULE, *ARGS]`` (how a console script runs) and exits
with its return value.

The demo starts it with SIGINT and SIGTERM blocked, and they stay so until the node's own
handlers are in place (``nodes.runtime.StopSignals``, or rclpy's in the demo's hardware
node): a stop that comes while Python starts and the node's module is imported (about
0.7 s) is held; one held when the import is done ends the child with exit code 0 before the
node starts, one that comes after it is the node's (Python's own SIGINT raised
KeyboardInterrupt in the middle of an import: a traceback and exit code 1, which the demo
took for the node's failure; one noted by a handler of this module after it was lost).

SIGUSR1 writes the stack of every thread to stderr (the node's log) and nothing else
(:mod:`faulthandler`, which needs no lock and works while the main thread is stuck in C
code): the demo sends it before killing a node that did not stop, so the log says where
it was.
"""

from __future__ import annotations

import faulthandler
import importlib
import signal
import sys

from asgp_ros.common.fileio import die_with_parent


def main() -> int:
    if len(sys.argv) < 3 or ":" not in sys.argv[2]:
        print("usage: python -m asgp_ros.demo.child PARENT_PID MODULE:FUNCTION [ARGS...]",
              file=sys.stderr)
        return 2
    parent = int(sys.argv[1])
    module, function = sys.argv[2].split(":", 1)
    if not die_with_parent(parent):
        print(f"the demo (pid {parent}) is gone; not starting {module}", file=sys.stderr)
        return 1
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    sys.argv = [module, *sys.argv[3:]]
    entry = getattr(importlib.import_module(module), function)
    held = signal.sigpending() & set(_STOPS)
    if held:
        print(f"stopped ({signal.Signals(min(held)).name}) before {module} started",
              file=sys.stderr)
        return 0
    rc = entry()
    return int(rc or 0)


_STOPS = (signal.SIGINT, signal.SIGTERM)


if __name__ == "__main__":
    sys.exit(main())
