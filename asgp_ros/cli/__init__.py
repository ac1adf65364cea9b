"""The ``asgp`` command: one entry point, one module per subcommand.

Every module in this package that defines ``register(subparsers)`` contributes a
subcommand of its own name. ``register`` adds its parser and sets ``func`` (``args -> exit
code``) as the parser default; heavy imports (rclpy, OpenCV, scikit-learn) happen inside
``func`` so that ``asgp --help`` stays fast. A command line that names a subcommand imports
that module alone (``asgp info MODEL`` needs none of the others' imports: scipy's
optimisers and statistics, the simulator, ...); ``asgp --help``, or a name that is not a
subcommand, imports them all.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import pkgutil
import sys
import threading
from collections.abc import Iterable, Sequence
from typing import Any, NoReturn, TextIO, cast

from asgp_ros import __version__
from asgp_ros.common.fileio import (
    OutputError,
    Terminated,
    forget_approved_outputs,
    raise_on_termination,
)


class CommandError(Exception):
    """A user-facing failure: printed as ``error: <message>`` and exit code 2, no traceback.

    :class:`asgp_ros.common.fileio.OutputError` (an output path refused before work starts) and
    unforeseen :class:`OSError` are reported the same way. SIGTERM and SIGHUP end a command
    as Ctrl-C does, so that every temporary is removed (exit 128 + signal number).
    """


def one_line(text: str) -> str:
    """``text`` with every character that is not printable (a newline, a control character,
    the lone surrogate of an undecodable file name) escaped as Python writes it in a string
    literal, so that an error naming a file stays on one line."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


#: Exit code when standard output is closed by its reader (128 + SIGPIPE, as a shell
#: reports a filter that SIGPIPE ended).
EXIT_BROKEN_PIPE = 141


def _silence(stream: TextIO) -> None:
    """Point ``stream`` (standard output or error) at /dev/null, so that the interpreter's
    final flush of a closed pipe or terminal prints nothing and fails nothing."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, stream.fileno())
    except (OSError, ValueError, AttributeError):  # not a real file (tests, embedding)
        pass


class _NamedStream:
    """A text stream (standard output) whose write errors name it: a full disk or a
    failing device under ``asgp ... > FILE`` said only "No space left on device", and the
    user could not tell whether the model, a figure or the printout had failed. Everything
    else is the stream's own."""

    def __init__(self, stream: TextIO, name: str) -> None:
        self._stream = stream
        self._name = name

    def _named(self, exc: OSError) -> OSError:
        if isinstance(exc, BrokenPipeError) or exc.filename is not None or exc.errno is None:
            return exc
        return OSError(exc.errno, exc.strerror or str(exc), self._name)

    def write(self, text: str) -> int:
        try:
            return self._stream.write(text)
        except OSError as exc:
            raise self._named(exc) from None

    def writelines(self, lines: Iterable[str]) -> None:
        try:
            self._stream.writelines(lines)
        except OSError as exc:
            raise self._named(exc) from None

    def flush(self) -> None:
        try:
            self._stream.flush()
        except OSError as exc:
            raise self._named(exc) from None

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


#: How an error names standard output when writing to it failed.
STDOUT_NAME = "standard output"


class _Parser(argparse.ArgumentParser):
    """Usage errors in one line (``asgp train: error: ... (asgp train --help)``), exit 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {one_line(message)} (see {self.prog} --help)\n")


def _commands() -> list[str]:
    """The subcommand modules' names, sorted (without importing them)."""
    return sorted(m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_"))


def _named_command(argv: Sequence[str]) -> str | None:
    """The subcommand ``argv`` names: its first word that is not an option (the top-level
    options take no value), when that is a subcommand; else None (also for the top-level
    help, ``asgp -h info``, which lists every subcommand)."""
    for word in argv:
        if word in ("--", "-h", "--help"):
            return None
        if not word.startswith("-"):
            return word if word in _commands() else None
    return None


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``asgp`` parser with every subcommand, or only ``command``'s (a subcommand's
    name: its module alone is imported)."""
    parser = _Parser(
        prog="asgp",
        description="Smart-wheelchair motion prediction with an autoregressive sparse GP.",
    )
    parser.add_argument("--version", action="version", version=f"asgp_ros {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in [command] if command is not None else _commands():
        module = importlib.import_module(f"{__name__}.{name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    stdout = sys.stdout
    if stdout is not None:  # (None: started with standard output closed)
        sys.stdout = cast(TextIO, _NamedStream(stdout, STDOUT_NAME))
    try:
        return _main(argv)
    finally:
        if isinstance(sys.stdout, _NamedStream):
            sys.stdout = stdout


def _main(argv: Sequence[str] | None) -> int:
    words = list(sys.argv[1:] if argv is None else argv)
    try:
        # a subcommand's imports take a few tenths of a second: Ctrl-C then is no traceback
        parser = build_parser(_named_command(words))
        args = parser.parse_args(words)
    except SystemExit as exc:  # --help, --version, or a usage error (printed, exit 2)
        return exc.code if isinstance(exc.code, int) else 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    try:
        # Progress and log records go to stdout: stderr carries nothing but the one-line
        # error of a failed command (or "interrupted"), so that scripts can rely on it.
        logging.basicConfig(
            level=logging.DEBUG if args.verbose else logging.INFO,
            format="%(levelname)s %(name)s: %(message)s",
            handlers=[logging.StreamHandler(sys.stdout)],
        )
        logging.captureWarnings(True)  # a library's warning is a log record, on stdout
        if threading.current_thread() is threading.main_thread():
            raise_on_termination()  # SIGTERM/SIGHUP run the same clean-up as Ctrl-C
        # A reader that stops early (``asgp info MODEL | head``) ends the command quietly,
        # as for any Unix filter: no logging traceback, no error line.
        logging.raiseExceptions = False
        forget_approved_outputs()  # an earlier command's in this process are not this one's
        return int(args.func(args) or 0)
    except BrokenPipeError:
        _silence(sys.stdout)
        return EXIT_BROKEN_PIPE
    except (CommandError, OutputError) as exc:
        _tell(f"error: {one_line(str(exc))}")
        return 2
    except OSError as exc:
        # A file system failure the command did not foresee (disk full, permission denied):
        # the user needs the path and the reason, not a traceback.
        where = f"{exc.filename}: " if exc.filename else ""
        _tell(f"error: {one_line(f'{where}{exc.strerror or exc}')}")
        return 2
    except MemoryError:
        # numpy names the array it could not allocate; the user needs what to do
        _tell(f"error: out of memory in asgp {args.command}: fewer or shorter inputs, or "
              "shorter horizons, need less")
        return 2
    except Terminated as exc:
        _tell(f"terminated ({one_line(str(exc))})")
        return 128 + exc.signum
    except KeyboardInterrupt:
        _tell("interrupted")
        return 130


def _tell(line: str) -> None:
    """The command's last word, on stderr; none when stderr cannot take it (its terminal
    closed: the SIGHUP that ended the command left it failing with EIO, and the exit was a
    traceback and 1, not 129)."""
    try:
        print(line, file=sys.stderr)
    except OSError:
        _silence(sys.stderr)


if __name__ == "__main__":
    sys.exit(main())
