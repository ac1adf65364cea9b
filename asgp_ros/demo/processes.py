"""Starting, watching and stopping the demo's node processes (Linux).

Every child runs in its own session (so a Ctrl-C in the terminal reaches only the demo,
which then stops the children in order) through :mod:`asgp_ros.demo.child`, which asks
the kernel to send it SIGTERM when the demo process dies (``PR_SET_PDEATHSIG``): even if
the demo is killed outright, no node is left behind.

Stopping: SIGINT to each child's process group (the nodes' normal Ctrl-C path), a
deadline, then SIGTERM, another deadline, then SIGKILL; before SIGKILL each child still
running is sent SIGUSR1 and writes the stacks of its threads to its log. Children are
reaped with ``os.wait4`` so their exact CPU time (user + system) is known; while they run
it is read from ``/proc/<pid>/stat``. Each child keeps when it was first asked to stop, so its
shutdown time (first signal to exit, within the 10 ms the stop loop polls at) is known.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

log = logging.getLogger(__name__)

#: Time given to a child to write its stacks (SIGUSR1) before it is killed (s).
STACK_DUMP_WAIT_S = 0.5

_TICK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def proc_cpu_seconds(pid: int) -> float | None:
    """User + system CPU seconds of a running process from /proc/<pid>/stat (None if gone).

    Fields 14 and 15 (utime, stime) in clock ticks, counted after the parenthesised
    command name (proc(5)).
    """
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    rest = text[text.rindex(")") + 2:].split()
    # rest[0] is field 3 (state): utime is field 14 -> rest[11], stime field 15 -> rest[12]
    return (int(rest[11]) + int(rest[12])) / _TICK


@dataclass
class Child:
    """One node process."""

    name: str
    argv: list[str]
    log_path: Path
    proc: subprocess.Popen[bytes]
    started: float = field(default_factory=time.monotonic)
    ended: float | None = None
    cpu_s: float = 0.0
    returncode: int | None = None
    signal_used: str = ""
    stop_requested: float | None = None  # time.monotonic() of the first stop signal

    @property
    def shutdown_s(self) -> float | None:
        """Seconds from the first stop signal to the exit; None if never signalled or
        still running."""
        if self.stop_requested is None or self.ended is None:
            return None
        return self.ended - self.stop_requested

    @property
    def pid(self) -> int:
        return self.proc.pid

    def sample_cpu(self) -> None:
        if self.returncode is None:
            cpu = proc_cpu_seconds(self.pid)
            if cpu is not None:
                self.cpu_s = cpu

    @property
    def lifetime_s(self) -> float:
        return (self.ended if self.ended is not None else time.monotonic()) - self.started

    def log_tail(self, lines: int = 15) -> str:
        try:
            text = self.log_path.read_text(errors="replace")
        except OSError:
            return ""
        return "\n".join(text.splitlines()[-lines:])


class ProcessGroup:
    """The demo's children (see the module docstring)."""

    def __init__(self, env: dict[str, str], log_dir: Path) -> None:
        self.env = env
        self.log_dir = log_dir
        self.children: list[Child] = []

    def start(self, name: str, entry: str, args: list[str]) -> Child:
        """Run the entry point ``entry`` ("module:function") with ``args`` as a child named
        ``name``; its output goes to ``log_dir/name.log``."""
        self.log_dir.mkdir(parents=True, exist_ok=True)
        log_path = self.log_dir / f"{name}.log"
        argv = [sys.executable, "-m", "asgp_ros.demo.child", str(os.getpid()), entry, *args]
        # the child starts with the stop signals blocked (the mask is inherited through
        # exec): demo.child takes one sent while Python starts as a stop before the node
        # began, not a KeyboardInterrupt in an import (asgp_ros.demo.child)
        stops = {signal.SIGINT, signal.SIGTERM}
        with open(log_path, "wb") as fh:
            mask = signal.pthread_sigmask(signal.SIG_BLOCK, stops)
            try:
                proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=fh,
                                        stderr=subprocess.STDOUT, env=self.env,
                                        start_new_session=True)
            finally:
                signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        child = Child(name, argv, log_path, proc)
        self.children.append(child)
        log.debug("started %s (pid %d): %s", name, proc.pid, " ".join(argv))
        return child

    def _reap(self, child: Child, block: bool) -> bool:
        """Collect the child's exit status and CPU time; True if it has exited."""
        if child.returncode is not None:
            return True
        try:
            pid, status, usage = os.wait4(child.pid, 0 if block else os.WNOHANG)
        except ChildProcessError:
            child.ended = time.monotonic()
            child.returncode = child.proc.returncode if child.proc.returncode is not None else -1
            return True
        if pid == 0:
            return False
        child.ended = time.monotonic()
        child.returncode = os.waitstatus_to_exitcode(status)
        child.proc.returncode = child.returncode  # reaped here, not by Popen
        child.cpu_s = usage.ru_utime + usage.ru_stime
        return True

    def reap(self, child: Child) -> bool:
        """True if ``child`` has exited (its status and CPU time collected); never blocks."""
        return self._reap(child, block=False)

    def poll(self) -> list[Child]:
        """Children that have exited (reaped now or before)."""
        out = []
        for child in self.children:
            child.sample_cpu()
            if self._reap(child, block=False):
                out.append(child)
        return out

    def send(self, child: Child, sig: signal.Signals) -> None:
        """Ask ``child`` to stop with ``sig`` (its process group); the first such signal
        starts its shutdown time."""
        child.sample_cpu()
        if child.stop_requested is None:
            child.stop_requested = time.monotonic()
        child.signal_used = sig.name
        self._signal(child, sig)

    def _signal(self, child: Child, sig: signal.Signals) -> None:
        try:
            os.killpg(child.pid, sig)  # the child's own session: its process group
        except ProcessLookupError:
            pass
        except PermissionError:
            child.proc.send_signal(sig)

    def _dump_stacks(self, children: list[Child]) -> None:
        """SIGUSR1 to each child (its own pid, not its group): :mod:`asgp_ros.demo.child`
        writes every thread's stack to the child's log. Then a moment for the writes."""
        for c in children:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(c.pid, signal.SIGUSR1)
                log.warning("%s (pid %d): stacks of its threads written to %s before SIGKILL",
                            c.name, c.pid, c.log_path)
        time.sleep(STACK_DUMP_WAIT_S)

    def stop_all(self, int_deadline_s: float = 6.0, term_deadline_s: float = 3.0,
                 children: list[Child] | None = None) -> None:
        """SIGINT all (or ``children``), wait; SIGTERM the rest, wait; SIGKILL the rest.
        Never raises."""
        chosen = self.children if children is None else children
        for sig, deadline in ((signal.SIGINT, int_deadline_s),
                              (signal.SIGTERM, term_deadline_s), (signal.SIGKILL, 5.0)):
            alive = [c for c in chosen if not self._reap(c, block=False)]
            if not alive:
                return
            if sig == signal.SIGKILL:
                self._dump_stacks(alive)
                alive = [c for c in alive if not self._reap(c, block=False)]
            for c in alive:
                self.send(c, sig)
            end = time.monotonic() + deadline
            while time.monotonic() < end:
                alive = [c for c in alive if not self._reap(c, block=False)]
                if not alive:
                    break
                time.sleep(0.01)
            for c in alive:
                log.warning("%s (pid %d) did not stop on %s within %.0f s", c.name, c.pid,
                            sig.name, deadline)
