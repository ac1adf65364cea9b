"""How every node of the package stops: SIGINT and SIGTERM only set a flag.

rclpy's own handlers (``rclpy.init``'s default) shut every context down from a thread of
their own at the signal, and then call the handler they replaced: for SIGINT that was
Python's ``default_int_handler``, which raises ``KeyboardInterrupt`` in whatever the main
thread runs next. Both bit the nodes:

* the exception lands anywhere: in a callback, which it silently cuts short; inside a
  C++ call, where pybind11 turns it into another exception (a ``RuntimeError`` out of
  rclpy's ``take_message``); or inside a finaliser such as ``rclpy.task.Future.__del__``,
  where Python prints "Exception ignored in ..." with a traceback at a node's exit;
* the context is torn down by one thread while the main thread is still in a callback, or
  already destroying the node and shutting the context down itself; the serial bridge's
  reader thread, publishing into the context as it went, crashed natively now and then at
  exit.

``benchmarks/node_signals.py`` (SIGINT in heavy traffic): 2 of 450 VO runs failed under
rclpy's handlers (a SIGSEGV, and that ``RuntimeError``), none of 450 since.

Here rclpy installs no handler (``SignalHandlerOptions.NO``). The signals set a flag
(:class:`StopSignals`), nothing else, and wake the executor: Python writes each signal's
number to a socket (``signal.set_wakeup_fd``) at once, even while the main thread waits
inside rcl, and a small thread reading that socket sets the flag and hands the executor an
empty task. (``Executor.wake`` alone is not enough: ``spin_once`` returns only after running
some work, and a wake-up without any restarts its wait; with no timer due, as on a simulated
clock that stopped, the node then hung on SIGINT until killed.)
:meth:`StopSignals.spin` returns once the flag is set, so the main
thread alone destroys the node and then shuts the context down, in that order, with
nothing else running (:func:`run`, every node's ``main``); the executor never wakes only
to look at the flag. A long start-up (a model being read) polls :func:`stop_requested`. A
signal during start-up is honoured as soon as the node is built.
"""

from __future__ import annotations

import contextlib
import gc
import math
import os
import signal
import socket
import stat
import sys
import tempfile
import threading
import types
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import rclpy
from rclpy.clock import Clock
from rclpy.clock_type import ClockType
from rclpy.exceptions import NameValidationException, ParameterException
from rclpy.executors import Executor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import ok, try_shutdown
from rclpy.validate_namespace import validate_namespace
from rclpy.validate_node_name import validate_node_name
from rosgraph_msgs.msg import Clock as ClockMsg

if TYPE_CHECKING:
    from asgp_ros.core.online import Predictor

__all__ = ["StopSignals", "init", "pacing_clock", "ros_args_problem", "run",
           "settle_garbage_collector", "stop_requested"]

_STOP = threading.Event()  # set by a stop signal; one per process, as signals are
_SIGNALS = (signal.SIGINT, signal.SIGTERM)
_SIGNAL_BYTES = frozenset(int(sig) for sig in _SIGNALS)  # as the wake-up fd writes them

_Handler = Callable[[int, types.FrameType | None], object] | int | None


def stop_requested() -> bool:
    """True once SIGINT or SIGTERM has arrived inside the :class:`StopSignals` block."""
    return _STOP.is_set()


class StopSignals:
    """Context manager (main thread): SIGINT and SIGTERM set the stop flag
    (:func:`stop_requested`) instead of raising or killing, and wake :meth:`spin`. The
    flag starts clear and is cleared again on exit, when the previous handlers and wake-up
    fd come back."""

    def __init__(self) -> None:
        self._previous: dict[int, _Handler] = {}
        self._previous_fd = -1
        self._read: socket.socket | None = None
        self._write: socket.socket | None = None

    def __enter__(self) -> StopSignals:
        _STOP.clear()
        self._read, self._write = socket.socketpair()
        self._write.setblocking(False)
        self._previous_fd = signal.set_wakeup_fd(self._write.fileno(),
                                                 warn_on_full_buffer=False)
        self._previous = {sig: signal.signal(sig, self._on_signal) for sig in _SIGNALS}
        # a stop held while the process started (the demo starts its nodes with the stop
        # signals blocked, asgp_ros.demo.child) is taken now, by these handlers
        signal.pthread_sigmask(signal.SIG_UNBLOCK, _SIGNALS)
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler if handler is not None else signal.SIG_DFL)
        signal.set_wakeup_fd(self._previous_fd)
        for sock in (self._read, self._write):
            if sock is not None:
                sock.close()
        self._read = self._write = None
        _STOP.clear()

    @staticmethod
    def _on_signal(signum: int, frame: types.FrameType | None) -> None:
        del signum, frame
        _STOP.set()

    def spin(self, executor: Executor) -> None:
        """Run ``executor`` until a stop signal (or until its context is shut down)."""
        if self._read is None or self._write is None:
            raise RuntimeError("StopSignals.spin outside its with block")
        read, write = self._read, self._write
        done = threading.Event()

        def wake_on_signal() -> None:
            # A byte per signal (its number) arrives here as the signal does; the main
            # thread may be waiting inside rcl, where Python runs no handler until the wait
            # returns. The flag is set here, not left to the Python handler (which the main
            # thread runs only once CPython notices the signal), and the executor is given
            # a task: spin_once returns only after running some work, and a wake-up with
            # none (Executor.wake) just starts its wait again. With no timer due (a
            # simulated clock that stopped) that wait never returned: the node hung on
            # SIGINT until killed.
            while not done.is_set():
                try:
                    data = read.recv(64)
                except OSError:
                    return
                if not data:
                    return
                if any(b in _SIGNAL_BYTES for b in data):
                    _STOP.set()
                    if not done.is_set():
                        executor.create_task(_nothing)

        waker = threading.Thread(target=wake_on_signal, name="stop_signal_waker",
                                 daemon=True)
        waker.start()
        try:
            while not _STOP.is_set() and ok(context=executor.context):
                executor.spin_once()
        finally:
            done.set()
            with contextlib.suppress(OSError):
                write.send(b"\0")  # ends the waker's recv
            waker.join()


def pacing_clock(node: Node) -> Clock:
    """The clock of a node's own timers (its watchdog, overrides and diagnostics): the
    steady clock, or the node's ROS clock with ``use_sim_time`` (read at the call).

    A timer on the ROS clock backed by the system clock stops when the system clock is set
    back (NTP stepping a laptop whose clock ran ahead, a user setting the time): rcl
    schedules its next call by the system clock and sees no jump, so the timer waits until
    the clock has caught up again, an hour for an hour's step. The shared-control layer
    and the bridge's overrides stopped for that long, and every node's diagnostics. On
    the steady clock they keep their period whatever the system clock does. With
    ``use_sim_time`` (a bag replayed) the timers follow /clock as before: they pause with
    it, and rcl moves them on when /clock jumps (a bag played again).
    """
    if node.get_parameter("use_sim_time").value:
        return node.get_clock()
    return Clock(clock_type=ClockType.STEADY_TIME)


def status_name(node: Node, label: str) -> str:
    """The name of a node's DiagnosticStatus: ``label`` (``"<node>: <what>"``), after the
    node's namespace when it has one (``chair1/predictor_node: prediction``). Two chairs'
    stacks in their namespaces publish on the one /diagnostics, where an aggregator keeps a
    status per name: without it one chair's ERROR was overwritten by the other's OK."""
    namespace = node.get_namespace().strip("/")
    return f"{namespace}/{label}" if namespace else label


def override_readers(node: Node, topic: str) -> tuple[list[str], list[str]]:
    """The other nodes that read ``topic`` (an override topic), as (bridges, others), by
    full name. A bridge is a reader that publishes a sensor_msgs/Joy, as serial_bridge_node
    does (its joy and joy_applied); the predictor, which reads the overrides too, and a bag
    recorder publish none. The layer counts on a bridge reading its overrides (it said OK
    while only the predictor did); a bridge refuses overrides while another bridge reads
    its topic (two chairs followed one layer)."""
    me = (node.get_name(), node.get_namespace())
    bridges: set[str] = set()
    others: set[str] = set()
    for e in node.get_subscriptions_info_by_topic(topic):
        if (e.node_name, e.node_namespace) == me:
            continue
        name = f"{e.node_namespace.rstrip('/')}/{e.node_name}"
        try:
            published = node.get_publisher_names_and_types_by_node(e.node_name,
                                                                   e.node_namespace)
        except Exception:  # (gone from the graph since)
            continue
        if any("sensor_msgs/msg/Joy" in types for _, types in published):
            bridges.add(name)
        else:
            others.add(name)
    return sorted(bridges), sorted(others)


def guard_sim_clock(node: Node) -> None:
    """Refuse a ``/clock`` message that is no time (negative seconds: a player of a bag
    with bogus stamps, a stray publisher) before rclpy's own clock subscription reads it:
    rclpy raised on it inside the executor, and the node stopped. Logged, and the clock
    stays where it was. (With ``use_sim_time``; the nodes refuse to switch it at runtime,
    so each node calls this once, at start-up, after its parameters are read.)"""
    sub = getattr(getattr(node, "_time_source", None), "_clock_sub", None)
    if sub is None or getattr(sub, "_asgp_guarded", False):
        return
    take = sub.callback
    logger = node.get_logger()

    def checked(msg: ClockMsg) -> None:
        if msg.clock.sec < 0:
            logger.error(f"/clock {msg.clock.sec} s refused: a negative time (a bag with "
                         "bogus stamps played, a stray publisher?); the clock stays",
                         throttle_duration_sec=5.0)
            return
        take(msg)

    sub.callback = checked
    sub._asgp_guarded = True


#: A node's clock read going back by more than this is a step (read at each callback, a
#: ROS clock, system or simulated, goes back only when it is stepped).
CLOCK_STEP_BACK_S = 0.01


class ClockReader:
    """A node's clock in seconds as its callbacks read it (None before a simulated clock
    has started). When it stepped back by more than :data:`CLOCK_STEP_BACK_S` (NTP setting
    a clock that ran ahead, a /clock restarted; rcl's jump callbacks see only a simulated
    clock's jumps), the node's predictor is told (``Predictor.clock_stepped_back``) and
    the log says so."""

    def __init__(self, node: Node, predictor: Callable[[], Predictor]) -> None:
        self._clock = node.get_clock()
        self._logger = node.get_logger()
        self._predictor = predictor  # (made after the reader: the node's, when it steps)
        self._seen = -math.inf
        self.steps_back = 0

    def now(self) -> float | None:
        ns = self._clock.now().nanoseconds
        if ns == 0:
            return None
        now = ns * 1e-9
        if now < self._seen - CLOCK_STEP_BACK_S:
            by, self._seen = self._seen - now, now
            self.steps_back += 1
            self._logger.warning(f"the clock stepped back by {by:.3f} s: the predictor's "
                                 "buffers restart")
            self._predictor().clock_stepped_back(now, by)
        else:
            self._seen = max(self._seen, now)
        return now


def _nothing() -> None:
    """The task that makes :meth:`Executor.spin_once` return after a stop signal."""


def log_dir() -> Path:
    """Where rcl writes a process's log file: ``ROS_LOG_DIR``, else ``ROS_HOME``/log, else
    ~/.ros/log (rcl_logging_get_logging_directory's order)."""
    if os.environ.get("ROS_LOG_DIR"):
        return Path(os.path.expanduser(os.environ["ROS_LOG_DIR"]))
    if os.environ.get("ROS_HOME"):
        return Path(os.path.expanduser(os.environ["ROS_HOME"])) / "log"
    return Path(os.path.expanduser("~")) / ".ros" / "log"


def log_file_arguments() -> tuple[list[str], str]:
    """rcl's arguments that keep ``rclpy.init`` from failing on its log file, and why: none
    while the log directory takes a new file. A disk remounted read-only, or out of inodes,
    or a ``ROS_LOG_DIR`` that cannot be made: rclpy.init raised ("failed to initialize
    logging") and every node refused to start (no bridge, no predictor, no layer, on a
    chair whose disk filled). Then the log file is left out (``--disable-external-lib-logs``):
    the console and /rosout still have every message."""
    where = log_dir()
    try:
        where.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=where, prefix=".asgp_log_check."):
            pass
    except OSError as exc:
        return (["--ros-args", "--disable-external-lib-logs"],
                f"no log file: {where}: {exc.strerror or exc} (the console and /rosout have "
                "every message)")
    return [], ""


def init(args: list[str] | None = None) -> None:
    """``rclpy.init`` without rclpy's signal handlers (use inside :class:`StopSignals`).

    SIGINT and SIGTERM are blocked in the calling thread while rclpy initialises, so the
    thread it starts there (its deferred signal handler, a C++ thread that inherits the
    caller's signal mask) never receives them. A signal delivered to a thread that is not
    the main one runs Python's C handler there, which marks the signal pending but does not
    make the main thread look (CPython recomputes that only when a thread next takes the
    GIL): a main thread busy in Python code alone missed the signal altogether, 11 of 120
    times when the signal followed ``init`` at once. A signal that arrives meanwhile stays
    pending and is delivered when the mask is restored.
    """
    extra, problem = log_file_arguments()
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, _SIGNALS)
    try:
        rclpy.init(args=[*(sys.argv if args is None else args), *extra],
                   signal_handler_options=SignalHandlerOptions.NO)
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)
    if problem:
        rclpy.logging.get_logger("asgp_ros").warning(problem)


#: rcl's arguments that name a file it opens at ``rclpy.init``.
_FILE_ARGUMENTS = ("--params-file", "--log-config-file")


def _name_remap_problem(rule: str, node: str | None) -> str | None:
    """Why a remap of the node's namespace or name (``-r __ns:=/chair1/``, ``-r
    __node:=1abc``; ``NODE:__ns:=...`` for the node ``node`` only) names no valid
    namespace or node name, in one line, or None. rcl's own words were its parser's
    ("Couldn't parse remap rule: '-r __ns:=chair1'. Error: Expected lexeme type 19, got 18
    at index 6") or, for a namespace ending in '/', which its parser lets through, a
    traceback from the node's creation saying "node name must not start with a number"."""
    lhs, sep, value = rule.partition(":=")
    prefix, _, key = lhs.rpartition(":")
    if not sep or (prefix and node is not None and prefix != node):
        return None  # not a rule, or another node's
    check: Callable[[str], object]
    if key == "__ns":
        what, check = "namespace", validate_namespace
    elif key in ("__node", "__name"):
        what, check = "node name", validate_node_name
    else:
        return None
    try:
        check(value)
    except NameValidationException as exc:
        reason = str(exc).split("\n", 1)[0].removeprefix(f"Invalid {what}: ").rstrip(":")
        fixed = "/" + "/".join(t for t in value.split("/") if t)
        hint = (f" ({key}:={fixed}?)" if key == "__ns" and fixed not in ("/", value)
                and _valid(validate_namespace, fixed) else "")
        return f"-r {rule}: {value!r} is not a valid {what}: {reason}{hint}"
    return None


def _valid(check: Callable[[str], object], name: str) -> bool:
    try:
        check(name)
    except NameValidationException:
        return False
    return True


def ros_args_problem(argv: list[str], node: str | None = None) -> str | None:
    """Why rcl cannot be given ``argv``'s ROS arguments, in one line, or None: a
    ``--params-file`` (or ``--log-config-file``) that is not a readable regular file. rcl
    opens it at ``rclpy.init``: a FIFO blocked there with SIGINT and SIGTERM held back
    (:func:`init`) until killed, and a missing file failed with a traceback. Or a remap of
    the namespace or the name of the node ``node`` (or of every node) to an invalid one
    (:func:`_name_remap_problem`)."""
    inside = False
    for i, arg in enumerate(argv):
        if arg == "--ros-args":
            inside = True
        elif arg == "--":
            inside = False
        elif inside and arg in ("-r", "--remap") and i + 1 < len(argv):
            problem = _name_remap_problem(argv[i + 1], node)
            if problem is not None:
                return problem
        elif inside and arg in _FILE_ARGUMENTS and i + 1 < len(argv):
            path = argv[i + 1]
            try:
                info = os.stat(path)
            except OSError as exc:
                return f"{arg} {path}: {exc.strerror or exc}"
            if not stat.S_ISREG(info.st_mode):
                return f"{arg} {path}: not a regular file"
            if not os.access(path, os.R_OK):
                return f"{arg} {path}: not readable"
    return None


def _ros_file_arguments(argv: list[str], option: str) -> list[str]:
    """The values of ``option`` among ``argv``'s ROS arguments (after ``--ros-args``)."""
    found, inside = [], False
    for i, arg in enumerate(argv):
        if arg == "--ros-args":
            inside = True
        elif arg == "--":
            inside = False
        elif inside and arg == option and i + 1 < len(argv):
            found.append(argv[i + 1])
    return found


def _node_key_matches(key: str, fqn: str) -> bool:
    """Whether a params file's section ``key`` (a node name, from :func:`_node_sections`)
    applies to the node ``fqn`` (rcl's rules: ``/**`` any namespaces, ``*`` one name)."""
    want = [t for t in str(key).split("/") if t]
    have = [t for t in fqn.split("/") if t]

    def match(i: int, j: int) -> bool:
        if i == len(want):
            return j == len(have)
        if want[i] == "**":
            return any(match(i + 1, k) for k in range(j, len(have) + 1))
        return j < len(have) and want[i] in ("*", have[j]) and match(i + 1, j + 1)

    return match(0, 0)


def params_file_problem(argv: list[str], fqn: str) -> str | None:
    """Why a ``--params-file`` given to the node ``fqn`` sets nothing for it, or None: no
    section of the file applies to the node (a misspelt node name,
    ``/**/shared_contrl_node``; a file of another node), or the file is empty. rcl applies
    no section then, without a word, and the node ran on every default."""
    import yaml

    for path in _ros_file_arguments(argv, "--params-file"):
        try:
            with open(path, encoding="utf-8") as fh:
                data = yaml.safe_load(fh)
        except RecursionError:  # (yaml's parser recurses per level: 2,000 levels)
            return f"--params-file {path}: nested too deeply to read"
        except (OSError, ValueError, yaml.YAMLError) as exc:
            return f"--params-file {path}: {' '.join(str(exc).split())}"
        keys = list(_node_sections(data)) if isinstance(data, dict) else []
        if not any(_node_key_matches(k, fqn) for k in keys):
            name = fqn.rsplit("/", 1)[-1]
            hint = (f" ('{name}' is the node in / only: '/**/{name}' is the node in any "
                    "namespace)" if f"/{name}" in keys else "")
            return (f"--params-file {path} has no section for this node ({fqn}): its "
                    f"sections are {keys or 'none'}{hint}")
    return None


def _node_sections(data: dict[object, object]) -> Iterator[str]:
    """The node names of a params file's sections (the keys above each
    ``ros__parameters``, a namespace's nested ones joined: ``chair1: {predictor_node:
    ...}`` is ``/chair1/predictor_node``), walked without recursion."""
    stack: list[tuple[dict[object, object], str]] = [(data, "")]
    while stack:
        level, prefix = stack.pop()
        for key, value in level.items():
            if key == "ros__parameters":
                yield prefix or "/"
            elif isinstance(value, dict):
                # (a bare node name at the top is the node in / only, as rcl applies it:
                # under a namespace the node ran on its defaults without a word)
                stack.append((value, f"{prefix}/{str(key).strip('/')}"))


def settle_garbage_collector() -> None:
    """Collect the start-up's garbage, then exempt every object left (the modules, the
    model, the node) from Python's cyclic garbage collector for good (``gc.freeze``).

    A full collection visits every tracked object. After rclpy, numpy, scipy and a model
    are loaded that is over 60,000 objects, and the collection the interpreter starts now
    and then when enough new objects have survived took 26-64 ms (a loaded 2-core
    machine): in one callback, a path that late. Frozen, they are never visited; the
    collector only looks at what the node made since.
    """
    gc.collect()
    gc.freeze()


def run(build: Callable[[], Node], args: list[str] | None, *, name: str,
        refused: tuple[type[Exception], ...],
        interrupted: tuple[type[Exception], ...] = ()) -> int:
    """A node's ``main``: build it and spin it until SIGINT or SIGTERM, then destroy it and
    shut rclpy down, all in the calling (main) thread.

    Args:
        build: makes the node (after ``rclpy.init``).
        name: the logger of the start-up refusal.
        refused: what ``build`` raises for a bad parameter or file: logged as
            "refusing to start: ...", exit code 1.
        interrupted: what ``build`` raises when a stop signal cut it short: exit code 0.

    Returns:
        0 after a stop signal, 1 when the node refused to start.
    """
    logger = rclpy.logging.get_logger(name)
    with StopSignals() as stops:
        problem = ros_args_problem(sys.argv if args is None else args, name)
        if problem is None:
            try:
                init(args)
            except RuntimeError as exc:  # rclpy's RCLError: arguments rcl refused
                problem = " ".join(str(exc).split()).split(", at /")[0]
        if problem is not None:
            logger.fatal(f"refusing to start: {problem}")
            return 1
        executor = SingleThreadedExecutor()
        node: Node | None = None
        refusals: tuple[type[Exception], ...] = (
            *refused, ParameterException, NameValidationException)
        try:
            try:
                node = build()
            except refusals as exc:
                # (rclpy's own: use_sim_time:=1 given to Node.__init__, say)
                logger.fatal(f"refusing to start: {' '.join(str(exc).split())}")
                return 1
            except RuntimeError as exc:
                # rclpy's RCLError from rcl_node_init: a name or namespace rcl's argument
                # parser took and the node's creation refused (those ros_args_problem
                # knows are said before); anything else stays a traceback
                words = " ".join(str(exc).split()).split(", at /")[0]
                if not words.startswith("error creating node"):
                    raise
                logger.fatal(f"refusing to start: {words}")
                return 1
            except interrupted:
                return 0
            problem = params_file_problem(sys.argv if args is None else args,
                                          node.get_fully_qualified_name())
            if problem is not None:
                logger.fatal(f"refusing to start: {problem}")
                return 1
            executor.add_node(node)
            settle_garbage_collector()
            stops.spin(executor)
        finally:
            executor.shutdown()
            if node is not None:
                node.destroy_node()  # before the context goes: a node's own threads stop
            try_shutdown()
    return 0
