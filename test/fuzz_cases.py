"""The engine of test/test_fuzz.py: valid inputs made once, file mutations, argument
vectors, a forked runner with a time limit, and the checks every case must pass.

Every case runs in a forked child of the test process (modules already imported, so a
case costs milliseconds plus the command's own work) with its own process group, its
output on files, a faulthandler stack dump on demand and an address-space limit. The
parent waits at most ``CASE_TIMEOUT`` seconds, then dumps the child's stacks (where it
hangs) and kills its process group.

What a case must do (issue 16): end with exit code 0 or 2; when it fails (exit 2), print
at most one line on stderr; never print a traceback; finish within the time limit;
leave no process behind; change nothing in the fuzz directory outside the output paths
its arguments name (new parent directories of an output path included). A library call
(``load_model``, ``read_streams``) may only raise its documented error type.

Environment:
    ASGP_FUZZ_EXAMPLES  examples per hypothesis test, times its weight (default 4: the
                        quick profile, about 45 s on 2 cores when nothing fails)
    ASGP_FUZZ_TIMEOUT   seconds per case (default 30: a hang never ends, and on two
                        loaded cores cases that pass alone were reported as hangs at 10 s)
    ASGP_FUZZ_SEED      vary the examples (default: derandomised, the same every run)
    ASGP_FUZZ_COLLECT   JSON-lines file: log every case and do not fail on findings
                        (benchmarks/fuzz.py collects every finding of a long run this way)
    ASGP_FUZZ_KEEP      directory: keep the files of the shortest case of every finding
    ASGP_FUZZ_BUDGET    seconds per target (collect mode): later cases of a target that
                        has used its time are skipped, so that every target gets its turn
    ASGP_FUZZ_MEMORY    address-space limit of a case in bytes (default 6 GiB)
"""

from __future__ import annotations

import contextlib
import faulthandler
import hashlib
import io
import json
import logging
import os
import re
import resource
import select
import shutil
import signal
import stat
import struct
import sys
import tempfile
import time
import traceback
import warnings
import zipfile
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from hypothesis import strategies as st

EXAMPLES = max(1, int(os.environ.get("ASGP_FUZZ_EXAMPLES", "4")))
CASE_TIMEOUT = float(os.environ.get("ASGP_FUZZ_TIMEOUT", "30"))
FUZZ_SEED = os.environ.get("ASGP_FUZZ_SEED")
COLLECT = os.environ.get("ASGP_FUZZ_COLLECT")
KEEP = os.environ.get("ASGP_FUZZ_KEEP")
BUDGET = float(os.environ.get("ASGP_FUZZ_BUDGET", "0"))
MEMORY_LIMIT = int(os.environ.get("ASGP_FUZZ_MEMORY", str(6 * 2**30)))
#: Files at most this large are hashed in a snapshot; larger (sparse) ones by size and time.
HASH_LIMIT = 16 * 2**20

# ----------------------------------------------------------------------------- values
#: Numbers as a user (or a script gone wrong) may type them.
NUMBERS = (
    "0", "-0", "1", "-1", "2", "0.5", "5e-324", "1e-300", "1e20", "1e30", "1e300", "-1e300",
    "1e309", "nan", "NaN", "inf", "-inf", "Infinity", "10000000000",
    "99999999999999999999999999", "9223372036854775808", "-9223372036854775809", "0x10",
    "1_000", "+5", " 3", "3 ",
)
#: Words: empty, whitespace, option-like, separators, very long.
WORDS = (
    "", " ", "-", "--", "x", "\u00e9", "\t", "%s", "{}", ",", "0,1", "1,-0", "0,0", "-1,2",
    "1,99999999999999999999", "a,b", ":=", "a:=b", "/joy", "/vo/twist", "//", "~", "a" * 300,
)
_TEXT = st.text(st.characters(codec="utf-8", exclude_characters="\x00/",
                              exclude_categories=("Cs",)), max_size=12)

#: Input paths for a bag argument (relative to the case directory; see ``MATERIALS``).
BAG_PATHS = (
    "bag_mcap", "bag_sqlite", "bag.bag", "bag_mcap/bag_mcap.mcap",
    "bag_sqlite/bag_sqlite.db3", "linkdir", "fifo", "fifo.bag", "dir", "full_dir",
    "dangling", "loop", "loop.bag", "zero", "/dev/null", "/dev/zero", "empty.bag",
    "huge.bag", "text.txt", "missing", "gp.npz", "dataset", "", ".",
)
#: Input paths for a model argument.
MODEL_PATHS = (
    "fol.npz", "cv.npz", "gp.npz", "mlp.npz", "link.npz", "fifo", "fifo.npz", "dir",
    "dir.npz", "dangling.npz", "loop", "zero.npz", "null.npz", "/dev/null", "/dev/zero",
    "empty.npz", "huge.npz", "text.txt", "missing.npz", "bag_mcap", "bag.bag", "", ".",
)
#: Model paths that can never load (``asgp demo --model``: a loadable one would start ROS).
BROKEN_MODEL_PATHS = tuple(p for p in MODEL_PATHS
                           if p not in ("fol.npz", "cv.npz", "gp.npz", "mlp.npz",
                                        "link.npz", ""))
VALID_BAGS = ("bag_mcap", "bag_sqlite", "bag.bag")
VALID_MODELS = ("fol.npz", "cv.npz", "gp.npz", "mlp.npz")
#: Output paths that do not exist yet.
NEW_OUTPUTS = ("out.npz", "new/sub/out.npz", "out.json", "out_dir", "out.bag")
#: Output paths: new, nested, existing outputs, inputs, special files, through a file.
OUTPUT_PATHS = (
    "out.npz", "new/sub/out.npz", "out.json", "out_dir", "out.bag", "gp.npz", "bag_mcap",
    "bag.bag", "dataset", "text.txt", "fifo", "dir", "full_dir", "dangling", "loop", "zero",
    "/dev/null", ".", "..", "", "text.txt/child", "fifo/child", "-",
)
#: Paths for ``asgp reproduce --data`` that never make it build a dataset (--quick would
#: simulate one into a missing or empty directory, which takes minutes).
DATA_PATHS = ("dataset", "fifo", "text.txt", "dangling", "loop", "zero", "/dev/null",
              "bag_mcap", "full_dir")
#: Ports for ``asgp board --monitor``: nothing that is a serial device.
PORT_PATHS = ("fifo", "dir", "text.txt", "missing", "/dev/null", "dangling", "loop", "zero")


def numbers() -> st.SearchStrategy[str]:
    return st.one_of(st.sampled_from(NUMBERS),
                     st.integers(-(2**70), 2**70).map(str),
                     st.floats(allow_nan=True, allow_infinity=True).map(repr))


def words() -> st.SearchStrategy[str]:
    return st.one_of(st.sampled_from(WORDS), _TEXT)


# ----------------------------------------------------------------------------- the arena
SEED_COMMANDS: tuple[tuple[str, ...], ...] = (
    ("simulate", "--minutes", "0.2", "--seed", "1", "--out", "bag_mcap"),
    ("simulate", "--minutes", "0.2", "--seed", "2", "--storage", "sqlite3",
     "--out", "bag_sqlite"),
    ("simulate", "--minutes", "0.2", "--seed", "3", "--out", "bag.bag"),
    ("train", "--model", "first_order_lag", "bag_mcap", "--out", "fol.npz"),
    ("train", "--model", "constant_velocity", "bag_mcap", "--out", "cv.npz"),
    ("train", "--model", "asgp", "--max-iter", "5", "--inducing-v", "4", "--inducing-w", "4",
     "bag_mcap", "--out", "gp.npz"),
    ("train", "--model", "mlp", "--max-iter", "3", "bag_mcap", "--out", "mlp.npz"),
    ("dataset", "--scale", "0.005", "--jobs", "2", "--out", "dataset"),
)
#: The bag of the dataset that is made unreadable, so that ``asgp reproduce`` always stops
#: after reading (and never trains 15 models).
BROKEN_DATASET_BAG = "carpet/carpet_02"


def _link(target: str) -> Callable[[Path, Path], None]:
    def make(dest: Path, _seed: Path) -> None:
        os.symlink(target, dest)
    return make


def _copy_of(name: str) -> Callable[[Path, Path], None]:
    def make(dest: Path, seed: Path) -> None:
        src = seed / name
        if src.is_dir():
            shutil.copytree(src, dest, symlinks=True)
        else:
            shutil.copy2(src, dest)
    return make


def _fifo(dest: Path, _seed: Path) -> None:
    os.mkfifo(dest)


def _empty_dir(dest: Path, _seed: Path) -> None:
    dest.mkdir()


def _full_dir(dest: Path, _seed: Path) -> None:
    dest.mkdir()
    (dest / "notes.txt").write_text("a user's file\n")


def _bytes(data: bytes) -> Callable[[Path, Path], None]:
    def make(dest: Path, _seed: Path) -> None:
        dest.write_bytes(data)
    return make


def _sparse(dest: Path, _seed: Path) -> None:
    with open(dest, "wb") as fh:  # 1 TiB of holes: nothing may read it
        fh.truncate(2**40)


#: Every relative path an argument vector may name, and how it is made in the case
#: directory (copies of the session's valid files; special files made fresh each case).
MATERIALS: dict[str, Callable[[Path, Path], None]] = {
    **{n: _copy_of(n) for n in ("bag_mcap", "bag_sqlite", "bag.bag", "fol.npz", "cv.npz",
                                "gp.npz", "mlp.npz", "dataset")},
    "link.npz": _link("gp.npz"), "linkdir": _link("bag_mcap"),
    "fifo": _fifo, "fifo.bag": _fifo, "fifo.npz": _fifo,
    "dir": _empty_dir, "dir.npz": _empty_dir, "full_dir": _full_dir,
    "dangling": _link("no-such-target"), "dangling.npz": _link("no-such-target.npz"),
    "loop": _link("loop"), "loop.bag": _link("loop.bag"),
    "zero": _link("/dev/zero"), "zero.npz": _link("/dev/zero"), "null.npz": _link("/dev/null"),
    "empty.npz": _bytes(b""), "empty.bag": _bytes(b""), "text.txt": _bytes(b"plain text\n"),
    "huge.npz": _sparse, "huge.bag": _sparse,
}
_DEPENDS = {"link.npz": ("gp.npz",), "linkdir": ("bag_mcap",)}


class Arena:
    """The fuzz directory: ``seed/`` (valid inputs made once), ``case/`` (one case's files),
    ``tmp/`` (TMPDIR of the cases). Logs of the runner live outside it."""

    def __init__(self, root: Path, io_dir: Path) -> None:
        self.root = root
        self.seed = root / "seed"
        self.case = root / "case"
        self.tmp = root / "tmp"
        self.io_dir = io_dir
        self.ros_log = io_dir / "ros_log"

    @classmethod
    def build(cls, root: Path, io_dir: Path) -> Arena:
        arena = cls(root, io_dir)
        for d in (arena.seed, arena.tmp, arena.ros_log):
            d.mkdir(parents=True, exist_ok=True)
        for argv in SEED_COMMANDS:
            # the same rule as the cases: a command that forks workers or starts DDS runs
            # as a real process once the test process has other threads
            if _fork_unsafe(argv):
                out = run_subprocess(list(argv), cwd=arena.seed, arena=arena, timeout=120.0)
            else:
                out = run_forked(cli_entry, (list(argv),), cwd=arena.seed, arena=arena,
                                 timeout=120.0)
            if out.code != 0:
                raise RuntimeError(f"making the fuzz inputs failed: asgp {' '.join(argv)}: "
                                   f"exit {out.code}\n{out.stderr[-2000:]}{out.stacks[-4000:]}")
        broken = arena.seed / "dataset" / BROKEN_DATASET_BAG
        shutil.rmtree(broken)
        broken.mkdir()
        (broken / "metadata.yaml").write_text("")
        return arena

    def new_case(self) -> Path:
        self.clear_case()
        self.case.mkdir()
        return self.case

    def clear_case(self) -> None:
        if os.path.lexists(self.case):
            _make_removable(self.case)
            shutil.rmtree(self.case)
        for leftover in self.tmp.iterdir():
            _make_removable(leftover)
            if leftover.is_dir() and not leftover.is_symlink():
                shutil.rmtree(leftover)
            else:
                leftover.unlink()

    def materialise(self, tokens: Iterable[str]) -> None:
        """Make every path the tokens name (``MATERIALS``) in the case directory."""
        for token in tokens:
            for part in _path_candidates(token):
                head = part.split("/", 1)[0]
                if head in MATERIALS and not os.path.lexists(self.case / head):
                    for dep in _DEPENDS.get(head, ()):
                        if not os.path.lexists(self.case / dep):
                            MATERIALS[dep](self.case / dep, self.seed)
                    MATERIALS[head](self.case / head, self.seed)


def _path_candidates(token: str) -> list[str]:
    out = [token]
    if token.startswith("--") and "=" in token:
        out.append(token.split("=", 1)[1])
    return out


def _make_removable(path: Path) -> None:
    """Give the owner write permission on every directory (a case may chmod things)."""
    if path.is_symlink() or not path.is_dir():
        return
    for dirpath, dirnames, _files in os.walk(path):
        with contextlib.suppress(OSError):
            os.chmod(dirpath, stat.S_IMODE(os.lstat(dirpath).st_mode) | stat.S_IRWXU)
        for d in dirnames:
            p = os.path.join(dirpath, d)
            if not os.path.islink(p):
                with contextlib.suppress(OSError):
                    os.chmod(p, stat.S_IMODE(os.lstat(p).st_mode) | stat.S_IRWXU)


# ----------------------------------------------------------------------------- snapshots
def snapshot(root: Path) -> dict[str, tuple]:
    """Every entry under ``root`` (never opening anything but regular files): type, mode,
    and for regular files size, modification time and content hash."""
    out: dict[str, tuple] = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            path = os.path.join(dirpath, name)
            rel = os.path.relpath(path, root)
            try:
                st_ = os.lstat(path)
            except OSError:
                continue
            mode = st_.st_mode
            if stat.S_ISLNK(mode):
                out[rel] = ("link", os.readlink(path))
            elif stat.S_ISDIR(mode):
                out[rel] = ("dir", stat.S_IMODE(mode))
            elif stat.S_ISREG(mode):
                digest = _digest(path) if st_.st_size <= HASH_LIMIT else st_.st_ino
                out[rel] = ("file", stat.S_IMODE(mode), st_.st_size, st_.st_mtime_ns, digest)
            else:
                out[rel] = ("special", stat.S_IFMT(mode), stat.S_IMODE(mode))
    return out


def _digest(path: str) -> str:
    h = hashlib.blake2b(digest_size=16)
    try:
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    except OSError as exc:
        return f"unreadable: {exc}"
    return h.hexdigest()


def touched_outside(before: dict[str, tuple], after: dict[str, tuple],
                    outputs: Sequence[str]) -> list[str]:
    """Entries created, changed or removed that are not an output path (or inside one),
    nor a new directory made to hold one."""
    bad = []
    for rel in sorted(set(before) | set(after)):
        old, new = before.get(rel), after.get(rel)
        if old == new:
            continue
        if any(rel == o or rel.startswith(o + "/") for o in outputs):
            continue
        if old is None and new is not None and new[0] == "dir" and any(
                o.startswith(rel + "/") for o in outputs):
            continue
        what = "created" if old is None else "removed" if new is None else "changed"
        bad.append(f"{what} {rel}")
    return bad


# ----------------------------------------------------------------------------- the runner
@dataclass
class Outcome:
    """How one forked case ended."""

    code: int | None  # exit code; None when killed by a signal
    signum: int | None  # the signal that ended it
    timed_out: bool
    elapsed: float
    stdout: str
    stderr: str
    stacks: str  # faulthandler dump taken before a hung case was killed
    stray: list[str]  # processes of the case's group still running after it ended
    result: Any = None  # what a library call returned (JSON)
    timeout: float = CASE_TIMEOUT


def cli_entry(argv: list[str]) -> int:
    """The ``asgp`` console script in the child: ``sys.exit(main())``."""
    sys.argv = ["asgp", *argv]
    from asgp_ros.cli import main

    return main(argv)


def run_forked(fn: Callable[..., Any], args: tuple, *, cwd: Path, arena: Arena,
               timeout: float = CASE_TIMEOUT) -> Outcome:
    """Run ``fn(*args)`` in a forked child (see the module docstring); never hangs."""
    io_dir = Path(tempfile.mkdtemp(prefix="case-", dir=arena.io_dir))
    files = {k: io_dir / k for k in ("stdout", "stderr", "stacks", "result", "ready")}
    for stream in (sys.stdout, sys.stderr, sys.__stdout__, sys.__stderr__):
        with contextlib.suppress(Exception):
            stream.flush()
    start = time.monotonic()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child
        _child(fn, args, cwd, arena, files, timeout)
    with contextlib.suppress(OSError):
        os.setpgid(pid, pid)
    status: int | None = None
    timed_out = False
    stacks = ""
    try:
        pidfd = os.pidfd_open(pid) if hasattr(os, "pidfd_open") else None
    except OSError:
        pidfd = None
    try:
        while True:
            done, st_ = os.waitpid(pid, os.WNOHANG)
            if done == pid:
                status = st_
                break
            left = timeout - (time.monotonic() - start)
            if left <= 0:
                timed_out = True
                break
            if pidfd is not None:
                select.select([pidfd], [], [], left)
            else:
                time.sleep(min(0.005, left))
        if timed_out:  # where does it hang? (a long system call delays the dump) then end it
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGUSR1)
            until = time.monotonic() + 3.0
            while not stacks and time.monotonic() < until:
                time.sleep(0.1)
                stacks = _read(files["stacks"])
            time.sleep(0.1)
            stacks = _read(files["stacks"])
    finally:
        if status is None:
            with contextlib.suppress(OSError):
                os.killpg(pid, signal.SIGKILL)
            status = os.waitpid(pid, 0)[1]
        if pidfd is not None:
            os.close(pidfd)
    elapsed = time.monotonic() - start
    stray = _reap_group(pid)
    if not files["ready"].exists():
        raise RuntimeError(f"the fuzz child did not start: {_read(files['stderr'])}")
    result = None
    if files["result"].exists():
        with contextlib.suppress(ValueError):
            result = json.loads(_read(files["result"]))
    out = Outcome(
        code=os.waitstatus_to_exitcode(status) if os.WIFEXITED(status) else None,
        signum=os.WTERMSIG(status) if os.WIFSIGNALED(status) else None,
        timed_out=timed_out, elapsed=elapsed, stdout=_read(files["stdout"]),
        stderr=_read(files["stderr"]), stacks=stacks or "", stray=stray, result=result,
        timeout=timeout)
    if out.code is not None and out.code == _CHILD_SETUP_FAILED:
        raise RuntimeError(f"the fuzz child's set-up failed: {out.stderr}")
    shutil.rmtree(io_dir, ignore_errors=True)
    return out


_CHILD_SETUP_FAILED = 121


def _read(path: Path, limit: int = 200_000) -> str:
    try:
        with open(path, "rb") as fh:
            return fh.read(limit).decode("utf-8", "backslashreplace")
    except OSError:
        return ""


def _group_members(pgid: int) -> list[str]:
    """Live (non-zombie) processes in process group ``pgid``: 'pid command'."""
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat", "rb") as fh:
                text = fh.read().decode("utf-8", "replace")
        except OSError:
            continue
        name_end = text.rfind(")")
        fields = text[name_end + 2:].split()
        if len(fields) > 2 and fields[0] != "Z" and int(fields[2]) == pgid:
            found.append(f"{entry} {text[text.find('(') + 1:name_end]}")
    return found


def _reap_group(pgid: int) -> list[str]:
    """Wait up to 2 s for the case's other processes to end; kill and report the rest."""
    deadline = time.monotonic() + 2.0
    members = _group_members(pgid)
    while members and time.monotonic() < deadline:
        time.sleep(0.05)
        members = _group_members(pgid)
    if members:
        with contextlib.suppress(OSError):
            os.killpg(pgid, signal.SIGKILL)
    return members


def _child(fn: Callable[..., Any], args: tuple, cwd: Path, arena: Arena,
           files: dict[str, Path], timeout: float) -> None:  # pragma: no cover - the child
    code = _CHILD_SETUP_FAILED
    try:
        os.setpgid(0, 0)
        flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC
        null = os.open(os.devnull, os.O_RDONLY)
        os.dup2(null, 0)
        os.dup2(os.open(files["stdout"], flags, 0o644), 1)
        os.dup2(os.open(files["stderr"], flags, 0o644), 2)
        stacks = open(files["stacks"], "w")  # noqa: SIM115 - lives until os._exit
        sys.stdin = io.TextIOWrapper(io.FileIO(0, "r", closefd=False))
        sys.stdout = io.TextIOWrapper(io.FileIO(1, "w", closefd=False), encoding="utf-8",
                                      errors="backslashreplace", line_buffering=True)
        sys.stderr = io.TextIOWrapper(io.FileIO(2, "w", closefd=False), encoding="utf-8",
                                      errors="backslashreplace", line_buffering=True)
        sys.__stdout__, sys.__stderr__ = sys.stdout, sys.stderr
        # A fresh interpreter's signal dispositions (pytest and pytest-timeout set some).
        signal.signal(signal.SIGINT, signal.default_int_handler)
        for sig in (signal.SIGTERM, signal.SIGHUP, signal.SIGALRM, signal.SIGCHLD,
                    signal.SIGUSR2, signal.SIGXFSZ):
            signal.signal(sig, signal.SIG_DFL)
        signal.signal(signal.SIGPIPE, signal.SIG_IGN)
        signal.setitimer(signal.ITIMER_REAL, 0)
        faulthandler.disable()
        faulthandler.enable(file=stacks, all_threads=True)
        faulthandler.register(signal.SIGUSR1, file=stacks, all_threads=True)
        resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
        _soft, hard = resource.getrlimit(resource.RLIMIT_AS)
        if hard == resource.RLIM_INFINITY or hard > MEMORY_LIMIT:
            resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, hard))
        # Logging and warnings as a fresh interpreter has them (pytest captures both).
        root = logging.getLogger()
        for handler in list(root.handlers):
            root.removeHandler(handler)
        root.setLevel(logging.WARNING)
        logging.disable(logging.NOTSET)
        warnings.resetwarnings()
        for category in (DeprecationWarning, PendingDeprecationWarning, ImportWarning,
                         ResourceWarning):
            warnings.simplefilter("ignore", category)
        warnings.showwarning = getattr(warnings, "_showwarning_orig", warnings.showwarning)
        np.seterr(all="warn", under="ignore")
        os.environ["TMPDIR"] = str(arena.tmp)
        os.environ["ROS_LOG_DIR"] = str(arena.ros_log)
        tempfile.tempdir = None
        os.chdir(cwd)
        files["ready"].write_text("")
    except BaseException:
        with contextlib.suppress(BaseException):
            traceback.print_exc()
            sys.stderr.flush()
        os._exit(code)
    try:
        ret = fn(*args)
        if isinstance(ret, int) and not isinstance(ret, bool):
            code = ret
        else:
            files["result"].write_text(json.dumps(ret, default=str))
            code = 0
    except SystemExit as exc:
        if exc.code is None:
            code = 0
        elif isinstance(exc.code, int):
            code = exc.code
        else:
            print(exc.code, file=sys.stderr)
            code = 1
    except BaseException:
        traceback.print_exc()
        code = 1
    with contextlib.suppress(BaseException):
        import multiprocessing.util

        multiprocessing.util._exit_function()  # what atexit does for multiprocessing
    with contextlib.suppress(BaseException):
        logging.shutdown()
    with contextlib.suppress(BaseException):
        sys.stdout.flush()
        sys.stderr.flush()
    os._exit(code & 0xFF)


# ----------------------------------------------------------------------------- checks
_TRACEBACK = re.compile(r"Traceback \(most recent call last\)|^Fatal Python error|"
                        r"^Exception ignored in|^Process \w+-\d+:$", re.MULTILINE)
_WARNING = re.compile(r"^\S.*:\d+: \w*Warning: ", re.MULTILINE)
_FRAME = re.compile(r'File "([^"]+)", line (\d+), in (\S+)')
_DUMP_FRAME = re.compile(r'File "([^"]+)", line (\d+) in (\S+)')


def problems_of(out: Outcome, *, library: bool = False) -> list[str]:
    """Everything wrong with one case's outcome (empty: the case passed)."""
    found = []
    if out.timed_out:
        found.append(f"no result within {out.timeout:g} s (hang)")
    elif out.signum is not None:
        found.append(f"killed by {signal.Signals(out.signum).name}")
    elif out.code not in (0, 2) or (library and out.code != 0):
        found.append(f"exit code {out.code}")
    if _TRACEBACK.search(out.stderr):
        found.append("traceback on stderr")
    lines = stderr_lines(out.stderr)
    if out.code == 2 and not out.timed_out and len(lines) > 1:
        found.append(f"{len(lines)} lines on stderr (at most one)")
    if _WARNING.search(out.stderr):
        found.append("Python warning on stderr")
    if out.stray:
        found.append(f"processes left running: {', '.join(out.stray)}")
    return found


def stderr_lines(text: str) -> list[str]:
    """The non-blank lines a terminal shows (what a carriage return overwrote is gone)."""
    return [ln.rsplit("\r", 1)[-1] for ln in text.split("\n") if ln.rsplit("\r", 1)[-1].strip()]


def _innermost(text: str) -> str:
    """'asgp_ros/module.py:function' of the innermost frame of the package in ``text`` (a
    Python traceback, or a faulthandler dump of all threads), else its innermost frame."""
    frames = _FRAME.findall(text.rsplit("Traceback (most recent call last)", 1)[-1])
    if "Traceback (most recent call last)" not in text:
        # faulthandler: one block per thread, most recent call first; prefer the current
        # thread, else the first thread that is in the package
        blocks = re.split(r"^(?=(?:Current thread|Thread) 0x)", text, flags=re.MULTILINE)
        blocks.sort(key=lambda b: (not b.startswith("Current"), "/asgp_ros/" not in b))
        frames = _DUMP_FRAME.findall(blocks[0])[::-1] if blocks else []
    own = [f for f in frames if "/asgp_ros/" in f[0]]

    def name(frame: tuple[str, str, str]) -> str:
        path, _line, func = frame
        for root in ("/asgp_ros/", "/site-packages/", "/lib/python3"):
            if root in path:
                rest = path.split(root, 1)[1]
                rest = rest.split("/", 1)[1] if root == "/lib/python3" else rest
                return f"{'asgp_ros/' if root == '/asgp_ros/' else ''}{rest}:{func}"
        return f"{Path(path).name}:{func}"

    if not frames:
        return "?"
    inner = name(frames[-1])
    return inner if not own or own[-1] == frames[-1] else f"{name(own[-1])} ({inner})"


def _exception_line(stderr: str) -> str:
    tb = stderr.rsplit("Traceback (most recent call last)", 1)[-1]
    for line in reversed(tb.splitlines()):
        if line and not line.startswith((" ", "\t")) and not line.startswith("Traceback"):
            return line.strip()
    return ""


def signature(target: str, out: Outcome, problems: list[str]) -> str:
    """A short key that groups findings with the same cause."""
    if out.timed_out:
        return f"{target}: hang in {_innermost(out.stacks)}"
    if _TRACEBACK.search(out.stderr):
        exc = _exception_line(out.stderr).split(":", 1)[0]
        return f"{target}: {exc or 'traceback'} in {_innermost(out.stderr)}"
    if out.signum is not None:
        return f"{target}: killed by {signal.Signals(out.signum).name}"
    first = problems[0] if problems else ""
    if "lines on stderr" in first:
        # the lines' kinds ("INFO asgp_ros.x", "error", ...), not their details
        lines = stderr_lines(out.stderr)
        shape = " / ".join(_normalise(ln.split(":", 1)[0])[:30] for ln in lines[:3])
        return f"{target}: several lines on stderr ({shape})"
    return f"{target}: {_normalise(first)[:90]}"


def _normalise(text: str) -> str:
    text = re.sub(r"'[^']*'|\"[^\"]*\"", "'...'", text)
    return re.sub(r"\d+", "N", text)


@dataclass
class Finding:
    target: str
    reproducer: str
    problems: list[str]
    signature: str
    outcome: Outcome
    files: dict[str, str] = field(default_factory=dict)  # case file -> what it is
    argv: list[str] | None = None

    def report(self) -> str:
        o = self.outcome
        lines = [f"fuzz finding [{self.signature}]", f"  case: {self.reproducer}"]
        lines += [f"  file {k}: {v}" for k, v in self.files.items()]
        lines.append(f"  problems: {'; '.join(self.problems)}")
        lines.append(f"  exit code {o.code}, signal {o.signum}, {o.elapsed:.1f} s")
        if o.stderr.strip():
            lines.append("  stderr:\n" + _indent(_tail(compact_trace(o.stderr), 40)))
        if o.timed_out and o.stacks.strip():
            lines.append("  stacks when stopped:\n"
                         + _indent(_tail(compact_trace(o.stacks), 40)))
        return "\n".join(lines)

    def to_json(self) -> dict[str, Any]:
        o = self.outcome
        return {"target": self.target, "signature": self.signature,
                "reproducer": self.reproducer, "argv": self.argv, "files": self.files,
                "problems": self.problems, "exit_code": o.code, "signal": o.signum,
                "timed_out": o.timed_out, "seconds": round(o.elapsed, 2),
                "stderr": _tail(compact_trace(o.stderr), 60),
                "stacks": _tail(compact_trace(o.stacks), 60) if o.timed_out else ""}


_HARNESS_FRAME = re.compile(r'File "[^"]*(/test/fuzz_cases\.py|/test/test_fuzz\.py|/_pytest/|'
                            r'/pluggy/|/pytest/|/hypothesis/|<frozen runpy>)')


def compact_trace(text: str) -> str:
    """Tracebacks and stack dumps without source lines, carets, the harness's and pytest's
    frames and the list of extension modules; other text as it is."""
    if "Traceback (most recent call last)" not in text and "File \"" not in text:
        return text
    out = []
    for line in text.splitlines():
        stripped = line.strip()
        if stripped.startswith("Extension modules:") or _HARNESS_FRAME.search(line):
            continue
        if stripped.startswith("File \"") or not line.startswith(" ") or not stripped:
            out.append(line.rstrip())
    return "\n".join(out)


def _tail(text: str, n: int) -> str:
    lines = text.rstrip("\n").splitlines()
    return "\n".join(lines[-n:] if len(lines) > n else lines)


def _indent(text: str) -> str:
    return "\n".join("    " + ln for ln in text.splitlines())


# ----------------------------------------------------------------------------- a case
_kept: dict[str, int] = {}  # signature -> size of the kept reproducer
_failed: dict[tuple[str, ...], str] = {}
_started: dict[str, float] = {}  # budget group -> when its first case ran


def run_case(arena: Arena, target: str, *, argv: list[str] | None = None,
             call: tuple[Callable[..., Any], tuple] | None = None,
             prepare: Callable[[Path], dict[str, str]] | None = None,
             timeout: float = CASE_TIMEOUT, tokens: Iterable[str] = (),
             subprocess_run: bool = False, group: str | None = None,
             budget: float = 1.0) -> None:
    """Run one case and check it; a finding fails the test (or, collecting, is logged).

    Args:
        target: what is fuzzed ("cli train", "model file -> load_model", ...).
        argv: the ``asgp`` arguments of a command-line case (its output paths are found
            by parsing them with the real parser), or
        call: (function, args) of a library case (returns a JSON value; may write nothing).
        prepare: makes the case's files in the case directory; returns {path: what it is}.
        tokens: more paths to make from ``MATERIALS`` (every argument is one already).
        subprocess_run: run ``python -m asgp_ros.cli`` instead of forking (slower; the
            real process, for hang and signal behaviour).
        group: what shares one time budget (default: the target), and
        budget: its size in ASGP_FUZZ_BUDGET units.
    """
    group = group or target
    started = _started.setdefault(group, time.monotonic())
    if COLLECT and BUDGET and time.monotonic() - started > BUDGET * budget:
        _log({"target": target, "skipped": True})
        return
    case = arena.new_case()
    arena.materialise([*tokens, *(argv or [])])
    files = prepare(case) if prepare else {}
    key = (target, repr(argv), repr(call), repr(sorted(files.items())))
    if not COLLECT and key in _failed:  # hypothesis replays a failing example: no new run
        arena.clear_case()
        raise AssertionError(_failed[key])
    case_rel = os.path.relpath(case, arena.root)
    outputs: list[str] = []
    if argv is not None:
        reproducer = "asgp " + " ".join(_quote(a) for a in argv)
        for o in output_paths(argv):
            rel = os.path.normpath(os.path.join(case_rel, o)) if o else ""
            if rel == case_rel or rel.startswith(case_rel + "/"):
                outputs.append(rel)
    else:
        assert call is not None
        reproducer = f"{call[0].__name__}{tuple(call[1])!r}"
    before = snapshot(arena.root)
    if argv is not None and not subprocess_run and _fork_unsafe(argv):
        subprocess_run = True
    if argv is not None and subprocess_run:
        outcome = run_subprocess(argv, cwd=case, arena=arena, timeout=timeout)
    elif argv is not None:
        outcome = run_forked(cli_entry, (list(argv),), cwd=case, arena=arena,
                             timeout=timeout)
    else:
        assert call is not None
        outcome = run_forked(call[0], tuple(call[1]), cwd=case, arena=arena,
                             timeout=timeout)
    after = snapshot(arena.root)
    problems = problems_of(outcome, library=argv is None)
    touched = touched_outside(before, after, outputs)
    if touched:
        shown = ", ".join(t.replace(case_rel + "/", "") for t in touched[:6])
        more = f" and {len(touched) - 6} more" if len(touched) > 6 else ""
        problems.append(f"touched outside the output path: {shown}{more}")
    finding = None
    if problems:
        finding = Finding(target, reproducer, problems, signature(target, outcome, problems),
                          outcome, files, list(argv) if argv is not None else None)
    if COLLECT:
        record: dict[str, Any] = {"target": target, "ok": finding is None,
                                  "seconds": round(outcome.elapsed, 3)}
        if finding is not None:
            record["finding"] = finding.to_json()
            size = len(reproducer) + sum(len(k) + len(v) for k, v in files.items())
            if KEEP and size < _kept.get(finding.signature, 1 << 62):
                _kept[finding.signature] = size
                record["finding"]["kept"] = str(_keep(case, finding))
        _log(record)
        arena.clear_case()
        return
    arena.clear_case()
    if finding is not None:
        _failed[key] = finding.report()
        raise AssertionError(_failed[key])


# Commands that start DDS (rclpy) or fork a worker pool of their own.
_FORKING_COMMANDS = frozenset({"replay", "reproduce", "dataset", "demo"})


def _fork_unsafe(argv: Sequence[str]) -> bool:
    """A command that starts DDS or forks workers hangs now and then when it runs in a fork
    of a process with other threads (a lock held by one of them at the fork stays held in
    the child): the test process has such threads once an in-process ROS test has run
    (Fast DDS keeps its participant threads). Such cases then run as a real process."""
    sub = next((a for a in argv if not a.startswith("-")), None)
    if sub not in _FORKING_COMMANDS:
        return False
    try:
        return len(os.listdir("/proc/self/task")) > 1
    except OSError:
        return True


def run_subprocess(argv: Sequence[str], *, cwd: Path, arena: Arena,
                   timeout: float = CASE_TIMEOUT) -> Outcome:
    """``python -m asgp_ros.cli ARGV`` in its own session; on a hang, its stacks (SIGABRT
    with PYTHONFAULTHANDLER) and then the whole session are ended."""
    import subprocess

    env = dict(os.environ, TMPDIR=str(arena.tmp), ROS_LOG_DIR=str(arena.ros_log),
               PYTHONFAULTHANDLER="1")
    start = time.monotonic()
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        proc = subprocess.Popen([sys.executable, "-m", "asgp_ros.cli", *argv], cwd=cwd,
                                env=env, stdin=subprocess.DEVNULL, stdout=out, stderr=err,
                                start_new_session=True)
        timed_out = False
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            timed_out = True
            with contextlib.suppress(OSError):
                proc.send_signal(signal.SIGABRT)
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(2.0)
        finally:
            if proc.poll() is None:
                with contextlib.suppress(OSError):
                    os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
        elapsed = time.monotonic() - start
        stray = _reap_group(proc.pid)
        out.seek(0)
        err.seek(0)
        stdout = out.read(200_000).decode("utf-8", "backslashreplace")
        stderr = err.read(200_000).decode("utf-8", "backslashreplace")
    code = proc.returncode
    return Outcome(code=code if code >= 0 else None, signum=-code if code < 0 else None,
                   timed_out=timed_out, elapsed=elapsed, stdout=stdout,
                   stderr="" if timed_out else stderr, stacks=stderr if timed_out else "",
                   stray=stray, timeout=timeout)


def preload() -> None:
    """Import what the cases use, once, before any fork (a case then costs milliseconds)."""
    import asgp_ros.cli
    import asgp_ros.core.baselines
    import asgp_ros.core.modelfile
    import asgp_ros.learning.evaluation
    import asgp_ros.learning.training
    import asgp_ros.recording.bags  # noqa: F401

    subcommands()
    for name in ("rosbags.highlevel", "rosbags.rosbag1", "rosbags.rosbag2",
                 "rosbags.typesys", "scipy.optimize", "sklearn.neural_network", "yaml",
                 "asgp_ros.recording.replay", "asgp_ros.learning.reproduce.run",
                 "asgp_ros.sim.simulate", "asgp_ros.demo.orchestrator", "asgp_ros.sim.board",
                 "asgp_ros.serial.link",
                 "rclpy", "rclpy.executors"):
        with contextlib.suppress(Exception):
            __import__(name)


def _quote(arg: str) -> str:
    return arg if arg and re.fullmatch(r"[\w@%+=:,./-]+", arg) else repr(arg)


def _log(record: dict[str, Any]) -> None:
    assert COLLECT
    with open(COLLECT, "a") as fh:
        fh.write(json.dumps(record) + "\n")


def _keep(case: Path, finding: Finding) -> Path:
    """Copy the case directory (FIFOs as FIFOs, sparse giants as sparse files) next to the
    finding's JSON; a shorter case of the same finding replaces it."""
    assert KEEP
    dest = Path(KEEP) / hashlib.sha1(finding.signature.encode()).hexdigest()[:12]
    if dest.exists():
        _make_removable(dest)
        shutil.rmtree(dest)
    dest.mkdir(parents=True)
    (dest / "finding.json").write_text(json.dumps(finding.to_json(), indent=2) + "\n")
    copy_tree(case, dest / "case")
    return dest


def copy_tree(src: Path, dest: Path) -> None:
    dest.mkdir()
    for entry in os.scandir(src):
        target = dest / entry.name
        st_ = entry.stat(follow_symlinks=False)
        if entry.is_symlink():
            os.symlink(os.readlink(entry.path), target)
        elif stat.S_ISDIR(st_.st_mode):
            copy_tree(Path(entry.path), target)
        elif stat.S_ISFIFO(st_.st_mode):
            os.mkfifo(target)
        elif stat.S_ISREG(st_.st_mode) and st_.st_size <= HASH_LIMIT:
            shutil.copyfile(entry.path, target)
        elif stat.S_ISREG(st_.st_mode):
            with open(target, "wb") as fh:
                fh.truncate(st_.st_size)


# ----------------------------------------------------------------------------- arguments
OUTPUT_DESTS = ("out", "json", "link")


def output_paths(argv: Sequence[str]) -> list[str]:
    """The output paths an argument vector names, as the real parser reads them (none if
    it does not parse). ``reproduce --quick`` may build its dataset in ``--data``."""
    from asgp_ros.cli import build_parser

    sink = io.StringIO()
    try:
        with contextlib.redirect_stdout(sink), contextlib.redirect_stderr(sink):
            ns = build_parser().parse_args(list(argv))
    except SystemExit:
        return []
    out = [str(getattr(ns, d)) for d in OUTPUT_DESTS if getattr(ns, d, None) is not None]
    if getattr(ns, "command", None) == "reproduce" and getattr(ns, "quick", False):
        out.append(str(ns.data))
    return out


def subcommands() -> dict[str, Any]:
    """name -> argparse parser of every ``asgp`` subcommand."""
    import argparse

    from asgp_ros.cli import build_parser

    parser = build_parser()
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


@dataclass
class Profile:
    """How to fuzz one subcommand without starting long work.

    Attributes:
        positional: strategy for the positional arguments (a list of strings).
        values: option -> strategy of its values (others: by the option's type).
        forced: options put first (later fuzzed ones win): caps that keep valid runs short.
        excluded: option -> why it is never generated.
        timeout: seconds per case.
    """

    positional: st.SearchStrategy[list[str]] = field(default_factory=lambda: st.just([]))
    values: dict[str, st.SearchStrategy[str]] = field(default_factory=dict)
    forced: tuple[str, ...] = ()
    excluded: dict[str, str] = field(default_factory=dict)
    timeout: float = CASE_TIMEOUT


def _paths(options: Sequence[str]) -> st.SearchStrategy[str]:
    return st.sampled_from(list(options))


def _bags(lo: int, hi: int) -> st.SearchStrategy[list[str]]:
    """Bag arguments (one time in ten none): half valid bags, half anything of BAG_PATHS."""
    bags = st.lists(st.one_of(_paths(VALID_BAGS), _paths(BAG_PATHS)), min_size=max(lo, 1),
                    max_size=hi)
    return st.integers(0, 9).flatmap(lambda i: st.just([]) if i == 5 and lo == 0 else bags)


_AXES = st.sampled_from(["0,1", "1,-0", "5,6", "0,0", "-1,2", "99999999999999999999,0",
                         "a,b", "", ",", "1", "0,1,2", " 0 , 1 "])
_TOPICS = st.one_of(st.sampled_from(["/joy", "/vo/twist", "/ground_truth/odom", "/missing",
                                     "", "joy", "/", "//", "/joy/", "/a b"]), words())
_FEW = ("0", "-1", "1", "2", "", "x", "1.5", "1e3")

PROFILES: dict[str, Profile] = {
    "simulate": Profile(
        forced=("--minutes", "0.15"),
        values={"--minutes": st.sampled_from(["0", "-1", "nan", "inf", "-inf", "1e30",
                                              "1e300", "", "x", "0.1", "0.15", "0.09"])}),
    "dataset": Profile(
        forced=("--scale", "0.005"),
        values={"--scale": st.sampled_from(["0", "-1", "nan", "inf", "-inf", "1e30", "1e300",
                                            "", "x", "0.005", "0.0055", "0.004"]),
                "--jobs": st.sampled_from(_FEW)},
        timeout=max(CASE_TIMEOUT, 60.0)),
    "train": Profile(
        positional=_bags(0, 2),
        forced=("--max-iter", "5"),
        values={"--max-iter": st.sampled_from(_FEW), "--joy-axes": _AXES,
                "--joy-topic": _TOPICS, "--twist-topic": _TOPICS}),
    "evaluate": Profile(
        positional=st.tuples(st.one_of(_paths(VALID_MODELS), _paths(MODEL_PATHS)),
                             _bags(0, 2)).map(lambda t: [t[0], *t[1]]),
        values={"--joy-axes": _AXES, "--joy-topic": _TOPICS, "--twist-topic": _TOPICS,
                "--truth-topic": _TOPICS}),
    "adapt": Profile(
        positional=st.tuples(st.one_of(_paths(VALID_MODELS), _paths(MODEL_PATHS)),
                             _bags(0, 2)).map(lambda t: [t[0], *t[1]]),
        values={"--trained-weight": st.sampled_from(["0", "1", "0.5", "-0", "1.0000001", "-1",
                                                     "nan", "inf", "", "x", "1e-300"]),
                "--joy-axes": _AXES, "--joy-topic": _TOPICS, "--twist-topic": _TOPICS}),
    "reproduce": Profile(values={"--data": _paths(DATA_PATHS)}),
    "replay": Profile(
        positional=_bags(1, 1),
        forced=("--rate", "1000", "--wait-subscribers", "0"),
        values={"--rate": st.sampled_from(["0", "-1", "nan", "inf", "-inf", "", "x", "1e300",
                                           "1e6", "1000", "1000", "100", "100", "50"]),
                "--wait-subscribers": st.sampled_from(["0", "-1", "nan", "inf", "-inf", "",
                                                       "x", "0.01", "0", "0", "0.05"]),
                "--topics": _TOPICS,
                "--remap": st.one_of(st.sampled_from(["/joy:=/j", ":=", "a:=", ":=b", "x",
                                                      "/joy:=", "a:=b:=c"]), words())},
        excluded={"--loop": "plays the bag forever by design"}),
    "demo": Profile(
        forced=("--model", "fifo.npz"),
        values={"--model": _paths(BROKEN_MODEL_PATHS),
                "--resolution": st.sampled_from(["320x240", "0x0", "axb", "1e9x1", "",
                                                 "99999999999999999999x2", "32x24x1", "x",
                                                 "-320x240", "320X240"])}),
    "board": Profile(
        forced=("--duration", "0.2"),
        values={"--duration": st.sampled_from(["0", "0.1", "0.3", "-1", "nan", "", "x",
                                               "1e-300"]),
                "--monitor": _paths(PORT_PATHS)}),
}
GENERIC = Profile(positional=st.lists(st.one_of(_paths(MODEL_PATHS), words()), max_size=2))


_CANDIDATES = ("0", "1", "2", "3", "5", "10", "0.1", "0.5", "1.4", "2.5")


def plausible(action: Any) -> st.SearchStrategy[str]:
    """Values a user would type for this option: its choices, or the small numbers its
    type accepts, and its default."""
    if action.choices:
        return st.sampled_from([str(c) for c in action.choices])
    default = [] if action.default in (None, False, True) or isinstance(
        action.default, list) else [str(action.default)]
    convert = action.type if callable(action.type) else None
    if convert is None or convert is str:
        return st.sampled_from(default or ["x"])
    accepted = []
    for text in _CANDIDATES:
        try:
            convert(text)
        except Exception:
            continue
        accepted.append(text)
    return st.sampled_from(accepted + default or ["x"])


def option_value(action: Any, profile: Profile, option: str) -> st.SearchStrategy[str]:
    """A value for ``option``: the profile's, a path for path options, else three times in
    four a plausible one (so that most vectors pass the parser and reach the command's own
    checks) and once an edge case (0, -1, 1e300, nan, inf, huge, empty, words, paths)."""
    if option in profile.values:
        return profile.values[option]
    if action.dest in OUTPUT_DESTS:
        return st.one_of(_paths(NEW_OUTPUTS), _paths(OUTPUT_PATHS))
    if action.type not in (None, str) and not action.choices:
        edge = st.one_of(numbers(), words())
    elif action.choices:
        edge = words()
    else:
        edge = st.one_of(words(), numbers(), _paths(MODEL_PATHS + BAG_PATHS))
    # (hypothesis favours small integers: the rare branches test a middle value)
    return st.integers(0, 3).flatmap(lambda i: edge if i == 2 else plausible(action))


@st.composite
def argv_for(draw: Any, name: str, parser: Any) -> list[str]:
    """A random argument vector for subcommand ``name`` from its parser's real options:
    required options always, others at random, in any order, now and then with
    ``--opt=value``, an unknown option or --help."""
    profile = PROFILES.get(name, GENERIC)
    actions = {opt: a for a in parser._actions for opt in a.option_strings
               if opt not in profile.excluded and opt not in ("-h", "--help")}
    required = sorted({a.option_strings[-1] for a in actions.values() if a.required})
    optional = sorted(o for o, a in actions.items() if not a.required)
    chosen = required + (draw(st.lists(st.sampled_from(optional), max_size=5))
                         if optional else [])
    parts: list[list[str]] = []
    for opt in chosen:
        action = actions[opt]
        if action.nargs == 0:
            parts.append([opt])
            continue
        value = option_value(action, profile, opt)
        if action.nargs in ("+", "*"):
            parts.append([opt, *draw(st.lists(value, min_size=1, max_size=3))])
        elif draw(st.integers(0, 9)) == 4:
            parts.append([f"{opt}={draw(value)}"])
        else:
            parts.append([opt, draw(value)])
    parts += [[p] for p in draw(profile.positional)]
    if draw(st.integers(0, 11)) == 6:  # an unknown option or a stray word
        parts.append([draw(st.sampled_from(["--bogus", "-x", "--", "-", "--out-", "--=1"]))])
    if draw(st.integers(0, 19)) == 9:
        parts.append(["--help"])
    order = draw(st.permutations(range(len(parts))))
    argv = [name, *profile.forced]
    for i in order:
        argv += parts[i]
    return argv


@st.composite
def global_argv(draw: Any, names: Sequence[str]) -> list[str]:
    """Argument vectors without a valid subcommand (or a subcommand's --help)."""
    junk = st.one_of(st.sampled_from(["-v", "--verbose", "--version", "-h", "--help",
                                      "--bogus", "-", "--", "help", "TRAIN", "train_",
                                      "simulat", "info"]), words(), numbers())
    argv = draw(st.lists(junk, max_size=4).filter(lambda a: not set(a) & set(names)))
    if draw(st.booleans()) and names:
        argv += [draw(st.sampled_from(list(names))), "--help"]
    return argv


# ----------------------------------------------------------------------------- mutations
@dataclass(frozen=True)
class Mutation:
    """A change to a valid file, written as it reads in a reproducer."""

    kind: str
    args: tuple

    def __str__(self) -> str:
        a = self.args
        text = {
            "truncate": lambda: f"truncated at offset {a[0]} (modulo the size)",
            "flip": lambda: "bits flipped: " + ", ".join(
                f"byte {o} (mod size) bit {b}" for o, b in a[0]),
            "overwrite": lambda: f"bytes at offset {a[0]} (mod size) overwritten with "
                                 f"{short(a[1])}",
            "append": lambda: f"{short(a[0])} appended",
            "replace": lambda: f"whole content replaced by {short(a[0])}",
            "extend": lambda: f"extended with holes to {a[0]} bytes",
            "npz_header": lambda: f"npy header of array #{a[0]} (mod count): " + ", ".join(
                f"{k} {v}" for k, v in zip(("shape", "descr", "fortran_order"), a[1:],
                                           strict=True) if v is not None),
            "npz_raw_header": lambda: f"npy header of array #{a[0]} (mod count) replaced by "
                                      f"{short(a[1])}, format version {a[2]}",
            "npz_length_field": lambda: f"npy header length field of array #{a[0]} := {a[1]}",
            "npz_values": lambda: f"array #{a[0]} (mod count): "
                                  f"{'every' if a[2] else 'first'} value := {a[1]!r}",
            "npz_members": lambda: f"archive member #{a[1]} (mod count): {a[0]} "
                                   f"({short(a[2])})",
            "npz_zip": lambda: f"archive: {a[0]}",
            "meta_set": lambda: "__meta__ JSON: " + ", ".join(
                ".".join(map(str, p)) for p in a[0]) + (
                    " removed" if a[1] is None else f" := {short(a[1])}"),
            "meta_replace": lambda: f"__meta__ JSON replaced by {short(a[0])}",
            "json_set": lambda: "JSON: " + ", ".join(".".join(map(str, p)) for p in a[0]) + (
                " removed" if a[1] is None else f" := {short(a[1])}"),
            "yaml_set": lambda: f"YAML: value of '{a[0]}:' (occurrence {a[2]}) := "
                                f"{short(a[1])}",
        }.get(self.kind)
        return text() if text else f"{self.kind}{a!r}"

    def apply(self, data: bytes, dest: Path) -> None:
        """Write the mutated ``data`` to ``dest``."""
        k, a = self.kind, self.args
        if k == "truncate":
            out = data[:a[0] % max(1, len(data))]
        elif k == "flip":
            buf = bytearray(data)
            for offset, bit in a[0]:
                if buf:
                    buf[offset % len(buf)] ^= 1 << bit
            out = bytes(buf)
        elif k == "overwrite":
            at = a[0] % max(1, len(data))
            out = data[:at] + a[1] + data[at + len(a[1]):]
        elif k == "append":
            out = data + a[0]
        elif k == "replace":
            out = a[0]
        elif k == "extend":
            dest.write_bytes(data)
            with open(dest, "r+b") as fh:
                fh.truncate(max(a[0], len(data)))
            return
        elif k in NPZ_MUTATIONS:
            out = NPZ_MUTATIONS[k](data, *a)
        elif k in JSON_MUTATIONS:
            out = JSON_MUTATIONS[k](data, *a)
        else:
            raise ValueError(f"unknown mutation {k}")
        dest.write_bytes(out)


def byte_mutations() -> st.SearchStrategy[Mutation]:
    offsets = st.integers(0, 2**20)
    return st.one_of(
        st.builds(lambda n: Mutation("truncate", (n,)), offsets),
        st.builds(lambda fl: Mutation("flip", (tuple(fl),)),
                  st.lists(st.tuples(offsets, st.integers(0, 7)), min_size=1, max_size=8)),
        st.builds(lambda o, b: Mutation("overwrite", (o, b)), offsets,
                  st.one_of(st.binary(min_size=1, max_size=64),
                            st.sampled_from([b"\xff" * 8, b"\x00" * 8, b"\x7f\xff\xff\xff",
                                             b"\xff\xff\xff\x7f"]))),
        st.builds(lambda b: Mutation("append", (b,)),
                  st.one_of(st.binary(min_size=1, max_size=512),
                            st.sampled_from([b"PK\x05\x06" + b"\xff" * 18,
                                             b"\x00" * 4096]))),
        st.builds(lambda b: Mutation("replace", (b,)),
                  st.one_of(st.binary(max_size=256),
                            st.sampled_from([b"", b"PK\x03\x04", b"\x93NUMPY\x01\x00",
                                             b"#ROSBAG V2.0\n", b"\x89MCAP0\r\n"]))),
        st.builds(lambda n: Mutation("extend", (n,)),
                  st.sampled_from([64 * 2**20 + 1, 2**31, 2**40])),
    )


# npz structure ------------------------------------------------------------------------
def _members(data: bytes) -> list[tuple[str, bytes]]:
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        return [(i.filename, zf.read(i)) for i in zf.infolist()]


def _archive(members: Sequence[tuple[str, bytes]],
             compression: int = zipfile.ZIP_STORED) -> bytes:
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # duplicate names are one of the mutations
        with zipfile.ZipFile(buf, "w", compression=compression) as zf:
            for name, raw in members:
                zf.writestr(name, raw)
    return buf.getvalue()


def _split_npy(raw: bytes) -> tuple[dict[str, Any], bytes]:
    f = io.BytesIO(raw)
    version = np.lib.format.read_magic(f)
    read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
            else np.lib.format.read_array_header_2_0)
    shape, fortran, dtype = read(f)
    return ({"descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": fortran,
             "shape": shape}, raw[f.tell():])


def _npy(header_text: str, data: bytes, version: tuple[int, int] = (1, 0)) -> bytes:
    text = header_text.encode("utf-8")
    length_fmt = "<H" if version == (1, 0) else "<I"
    pre = 8 + struct.calcsize(length_fmt)
    pad = (-(pre + len(text) + 1)) % 64
    text = text + b" " * pad + b"\n"
    return (b"\x93NUMPY" + bytes(version) + struct.pack(length_fmt, len(text)) + text + data)


def _pick(members: list[tuple[str, bytes]], index: int, meta: bool = False) -> int:
    names = [i for i, (n, _) in enumerate(members) if (n == "__meta__.npy") == meta]
    return names[index % len(names)] if names else 0


def _npz_header(data: bytes, index: int, shape: str | None, descr: str | None,
                fortran: bool | None) -> bytes:
    members = _members(data)
    i = _pick(members, index)
    header, body = _split_npy(members[i][1])
    descr = descr if descr is not None else repr(header["descr"])
    order = fortran if fortran is not None else header["fortran_order"]
    shape = shape if shape is not None else repr(header["shape"])
    text = f"{{'descr': {descr}, 'fortran_order': {order}, 'shape': {shape}, }}"
    members[i] = (members[i][0], _npy(text, body))
    return _archive(members)


def _npz_raw_header(data: bytes, index: int, text: str, version: tuple[int, int]) -> bytes:
    members = _members(data)
    i = _pick(members, index)
    _header, body = _split_npy(members[i][1])
    members[i] = (members[i][0], _npy(text, body, version))
    return _archive(members)


def _npz_length_field(data: bytes, index: int, length: int) -> bytes:
    members = _members(data)
    i = _pick(members, index)
    raw = members[i][1]
    members[i] = (members[i][0], raw[:8] + struct.pack("<H", length & 0xFFFF) + raw[10:])
    return _archive(members)


def _npz_values(data: bytes, index: int, value: float, everywhere: bool) -> bytes:
    members = _members(data)
    i = _pick(members, index)
    arr = np.load(io.BytesIO(members[i][1]), allow_pickle=False)
    arr = np.array(arr, dtype=np.float64 if arr.dtype.kind != "f" else arr.dtype)
    if arr.size:
        with np.errstate(all="ignore"):
            if everywhere:
                arr[...] = value
            else:
                arr.reshape(-1)[0] = value
    buf = io.BytesIO()
    np.lib.format.write_array(buf, arr, allow_pickle=False)
    members[i] = (members[i][0], buf.getvalue())
    return _archive(members)


def _npz_members(data: bytes, op: str, index: int, name: str) -> bytes:
    members = _members(data)
    i = _pick(members, index)
    if op == "remove":
        del members[i]
    elif op == "rename":
        members[i] = (name, members[i][1])
    elif op == "duplicate":
        members.append(members[i])
    elif op == "add":
        buf = io.BytesIO()
        np.lib.format.write_array(buf, np.zeros(3))
        members.append((name, buf.getvalue()))
    elif op == "remove_meta":
        members = [m for m in members if m[0] != "__meta__.npy"]
    return _archive(members)


def _npz_zip(data: bytes, op: str) -> bytes:
    members = _members(data)
    if op == "deflate":
        return _archive(members, zipfile.ZIP_DEFLATED)
    if op in ("bzip2", "lzma"):
        return _archive(members, zipfile.ZIP_BZIP2 if op == "bzip2" else zipfile.ZIP_LZMA)
    if op == "encrypted_flag":
        buf = bytearray(_archive(members))
        for sig, at in ((b"PK\x03\x04", 6), (b"PK\x01\x02", 8)):
            pos = buf.find(sig)
            while pos >= 0:
                buf[pos + at] |= 1
                pos = buf.find(sig, pos + 4)
        return bytes(buf)
    if op == "eocd_count":
        buf = bytearray(_archive(members))
        at = buf.rfind(b"PK\x05\x06")
        struct.pack_into("<HH", buf, at + 8, 0xFFFF, 0xFFFF)
        return bytes(buf)
    if op in ("bomb", "bomb_lying"):
        return _bomb(data, op == "bomb_lying")
    raise ValueError(op)


_BOMB_BYTES = 128 * 2**20
_bombs: dict[tuple[bytes, bool], bytes] = {}


def _bomb(data: bytes, lying: bool) -> bytes:
    """An archive whose first array's data inflates to 128 MiB of zeros (``lying``: the
    archive's directory claims the size the array's header declares)."""
    key = (hashlib.sha1(data).digest(), lying)
    if key in _bombs:
        return _bombs[key]
    members = _members(data)
    i = _pick(members, 0)
    name, raw = members[i]
    header, body = _split_npy(raw)
    payload = _npy(repr(header), body + b"\x00" * _BOMB_BYTES)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for j, (n, b) in enumerate(members):
            zf.writestr(zipfile.ZipInfo(n), payload if j == i else b,
                        compress_type=zipfile.ZIP_DEFLATED if j == i else zipfile.ZIP_STORED)
    out = bytearray(buf.getvalue())
    if lying:
        claimed = len(raw)
        encoded = name.encode()
        for sig, size_at, name_at in ((b"PK\x03\x04", 22, 30), (b"PK\x01\x02", 24, 46)):
            pos = out.find(sig)
            while pos >= 0:
                if out[pos + name_at:pos + name_at + len(encoded)] == encoded:
                    struct.pack_into("<I", out, pos + size_at, claimed)
                pos = out.find(sig, pos + 4)
    _bombs[key] = bytes(out)
    return _bombs[key]


def _meta_text(members: list[tuple[str, bytes]]) -> tuple[int, str]:
    i = _pick(members, 0, meta=True)
    arr = np.load(io.BytesIO(members[i][1]), allow_pickle=False)
    return i, str(arr[()])


def _with_meta(members: list[tuple[str, bytes]], i: int, text: str) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, np.array(text), allow_pickle=False)
    members[i] = (members[i][0], buf.getvalue())
    return _archive(members)


def _set_json(doc: Any, paths: Sequence[Sequence[Any]], raw: str | None) -> str:
    """``doc`` as JSON with the value at each path replaced by the raw JSON text ``raw``
    (None: removed). A path holds keys, or ints taken modulo the container's size; a
    missing last key is added."""
    sentinel = "\x00fuzz\x00"
    for path in paths:
        parent: Any = None
        key: Any = None
        node = doc
        for step in path:
            if isinstance(node, dict) and isinstance(step, str):
                key = step
            elif isinstance(node, dict) and node and isinstance(step, int):
                key = sorted(node)[step % len(node)]
            elif isinstance(node, list) and node and isinstance(step, int):
                key = step % len(node)
            else:
                parent = None
                break
            parent = node
            node = node.get(key) if isinstance(node, dict) else node[key]
        if parent is None:
            continue
        if raw is not None:
            parent[key] = sentinel
        elif isinstance(parent, dict):
            parent.pop(key, None)
        else:
            del parent[key]
    text = json.dumps(doc, sort_keys=True)
    return text.replace(json.dumps(sentinel), raw if raw is not None else "null")


def _npz_meta_set(data: bytes, paths: tuple, raw: str | None) -> bytes:
    members = _members(data)
    i, text = _meta_text(members)
    return _with_meta(members, i, _set_json(json.loads(text), paths, raw))


def _npz_meta_replace(data: bytes, text: str) -> bytes:
    members = _members(data)
    i, _old = _meta_text(members)
    return _with_meta(members, i, text)


NPZ_MUTATIONS: dict[str, Callable[..., bytes]] = {
    "npz_header": _npz_header, "npz_raw_header": _npz_raw_header,
    "npz_length_field": _npz_length_field, "npz_values": _npz_values,
    "npz_members": _npz_members, "npz_zip": _npz_zip, "meta_set": _npz_meta_set,
    "meta_replace": _npz_meta_replace,
}


def short(value: Any, limit: int = 60) -> str:
    """A value for a reproducer: long ones by their ends and length."""
    if isinstance(value, bytes | str) and len(value) > limit:
        unit = "chars" if isinstance(value, str) else "bytes"
        return f"{value[:24]!r} ... {value[-8:]!r} ({len(value)} {unit})"
    return repr(value)


def deep(n: int, opening: str = "[") -> str:
    closing = {"[": "]", "{": "}"}[opening]
    if opening == "{":
        return '{"a":' * n + "1" + "}" * n
    return opening * n + closing * n


#: JSON values to put anywhere: extreme numbers, wrong types, deep nesting.
JSON_VALUES = (
    "1e300", "-1e300", "1e-300", "0", "-1", "1", "1.5", "10000000000", "1" + "0" * 400,
    "-1" + "0" * 400, "1e400", "NaN", "Infinity", "-Infinity", "null", "true", "false",
    '""', '"x"', '"' + "a" * 10000 + '"', "[]", "{}", "[1e300]", '{"a": 1}', "[[]]",
    deep(100), deep(3000), deep(100000), deep(3000, "{"), "[-1]", "[10000000000]",
    "[1e300, 1e300]", "[0, 0]", '["v", "omega", "x"]', '["omega", "v"]',
)
#: Metadata settings a model cannot do without (groups are set together).
MODEL_KEYS: tuple[tuple[tuple[str, ...], ...], ...] = (
    (("rate_hz",), ("resample", "rate_hz")), (("rate_hz",),), (("resample", "rate_hz"),),
    (("features", "lags"),), (("features", "coupled"),), (("format_version",),),
    (("format",),), (("kind",),), (("channels",),), (("arrays",),), (("kind_params",),),
    (("meta",),), (("resample",),), (("features",),),
    (("resample", "max_gap_joy_s"),), (("resample", "stale_after_s"),),
    (("resample", "stale_tolerance"),), (("resample", "stale_still_speed"),),
    (("kind_params", "channel_class"),),
)


def json_values() -> st.SearchStrategy[str]:
    return st.one_of(st.sampled_from(JSON_VALUES),
                     st.floats(allow_nan=False, allow_infinity=False).map(json.dumps),
                     st.integers(-(2**80), 2**80).map(str),
                     _TEXT.map(json.dumps))


def json_paths(keys: Sequence[tuple[tuple[str, ...], ...]]) -> st.SearchStrategy[tuple]:
    rnd = st.lists(st.integers(0, 63), min_size=1, max_size=4).map(lambda p: (tuple(p),))
    return st.one_of(st.sampled_from(list(keys)), rnd)


def model_mutations() -> st.SearchStrategy[Mutation]:
    idx = st.integers(0, 63)
    shapes = st.sampled_from(["(10000000000,)", "(-1,)", "(2147483648, 2147483648)", "()",
                              "(" + "1, " * 40 + ")", "(4194305,)", "(0,)", "(1, 1)",
                              "(4, 4, 4, 4, 4)", "(True,)", "(1.5,)", "('a',)", "None",
                              "(" + "9" * 30 + ",)"])
    descrs = st.sampled_from(["'|O'", "'<U5'", "\"[('a', '<f8')]\"", "'>f8'", "'<c16'",
                              "'V8'", "'<M8[s]'", "'<f2'", "'|b1'", "'<i8'", "'S5'",
                              "'<f8'", "'x'", "7"])
    return st.one_of(
        byte_mutations(),
        st.builds(lambda i, s: Mutation("npz_header", (i, s, None, None)), idx, shapes),
        st.builds(lambda i, d: Mutation("npz_header", (i, None, d, None)), idx, descrs),
        st.builds(lambda i: Mutation("npz_header", (i, None, None, True)), idx),
        st.builds(lambda i, t, v: Mutation("npz_raw_header", (i, t, v)), idx,
                  st.one_of(st.sampled_from([
                      "{'descr': '<f8', 'fortran_order': False, 'shape': (10**10,), }",
                      "{'descr': '<f8', 'fortran_order': False}", "{}", "[]", "",
                      "{'descr': '<f8', 'fortran_order': False, 'shape': (1,), 'x': 1}",
                      "(" * 100 + ")" * 100, "{'descr': '<f8', " + "'a': 1, " * 400 + "}"]),
                      _TEXT),
                  st.sampled_from([(1, 0), (2, 0), (3, 0), (1, 1), (255, 255)])),
        st.builds(lambda i, n: Mutation("npz_length_field", (i, n)), idx,
                  st.sampled_from([0, 1, 9, 65535, 4096, 4097])),
        st.builds(lambda i, v, e: Mutation("npz_values", (i, v, e)), idx,
                  st.sampled_from([float("nan"), float("inf"), -float("inf"), 1e300, -1e300,
                                   1e16, 0.0, -1.0, 1e-300]), st.booleans()),
        st.builds(lambda op, i, n: Mutation("npz_members", (op, i, n)),
                  st.sampled_from(["remove", "rename", "duplicate", "add", "remove_meta"]),
                  idx, st.sampled_from(["../evil.npy", "a/b.npy", "x.npy", "__meta__",
                                        "v.alpha", "a" * 300 + ".npy", "v.extra.npy",
                                        "__meta__.npy", ".npy", "v..npy"])),
        st.builds(lambda op: Mutation("npz_zip", (op,)),
                  st.sampled_from(["deflate", "bzip2", "lzma", "encrypted_flag",
                                   "eocd_count", "bomb", "bomb_lying"])),
        st.builds(lambda p, v: Mutation("meta_set", (p, v)), json_paths(MODEL_KEYS),
                  json_values()),
        st.builds(lambda p: Mutation("meta_set", (p, None)), json_paths(MODEL_KEYS)),
        st.builds(lambda t: Mutation("meta_replace", (t,)),
                  st.one_of(st.sampled_from(["", "null", "[]", "{}", "1e300", "NaN", "x",
                                             deep(100), deep(100000), deep(400000),
                                             deep(3000, "{"), '"' + "a" * (2**20) + '"']),
                            _TEXT)),
    )


# JSON documents (dataset manifest) -------------------------------------------------------
def _json_set(data: bytes, paths: tuple, raw: str | None) -> bytes:
    return _set_json(json.loads(data), paths, raw).encode()


JSON_MUTATIONS: dict[str, Callable[..., bytes]] = {"json_set": _json_set}
MANIFEST_KEYS: tuple[tuple[tuple[Any, ...], ...], ...] = (
    (("bags",),), (("bags", 0),), (("bags", 0, "path"),), (("bags", 0, "split"),),
    (("bags", 9, "path"),), (("topics",),), (("topics", "joy"),), (("topics", "twist"),),
    (("topics", "truth"),), (("format",),), (("version",),), (("scale",),), (("seed",),),
    (("bag_minutes",),), (("storage",),),
)


def manifest_mutations() -> st.SearchStrategy[Mutation]:
    return st.one_of(
        byte_mutations(),
        st.builds(lambda p, v: Mutation("json_set", (p, v)), json_paths(MANIFEST_KEYS),
                  json_values()),
        st.builds(lambda p: Mutation("json_set", (p, None)), json_paths(MANIFEST_KEYS)),
        st.builds(lambda t: Mutation("replace", (t.encode(),)),
                  st.sampled_from(["", "null", "[]", "{}", "1", deep(100000),
                                   deep(3000, "{"), '{"bags": [1, 2]}', '{"bags": {}}',
                                   '{"bags": [{"path": 1}]}', '{"bags": [{}]}',
                                   '{"topics": 1}', '{"topics": {"joy": 5}}', "\ufeff{}"])),
    )


# YAML (ROS 2 bag metadata) ---------------------------------------------------------------
BILLION_LAUGHS = "\n".join(
    ["a: &a [\"lol\",\"lol\",\"lol\",\"lol\",\"lol\",\"lol\",\"lol\",\"lol\",\"lol\"]"]
    + [f"{chr(98 + i)}: &{chr(98 + i)} [" + ",".join([f"*{chr(97 + i)}"] * 9) + "]"
       for i in range(8)]
    + ["rosbag2_bagfile_information: *i", ""])
YAML_VALUES = (
    "-1", "0", "1e300", "18446744073709551616", "1" + "0" * 400, ".nan", ".inf", "null",
    "''", "x", "[]", "{}", "[1, 2]", "'../../no/such/file.mcap'", "'/dev/zero'",
    "'metadata.yaml'", "!!binary AAAA", "&a [*a]", "'" + "a" * 5000 + "'",
)
YAML_KEYS = ("version", "storage_identifier", "duration", "nanoseconds", "message_count",
             "relative_file_paths", "files", "path", "topics_with_message_count", "name",
             "type", "serialization_format", "offered_qos_profiles", "custom_data",
             "starting_time", "nanoseconds_since_epoch", "compression_format",
             "compression_mode", "asgp_ros.simulation", "type_description_hash")


def _yaml_set(data: bytes, key: str, value: str, occurrence: int) -> bytes:
    """Replace the value of the ``occurrence``-th ``key:`` line (a textual edit, so the
    result may be anything a hand-edited file can be)."""
    lines = data.decode("utf-8", "replace").splitlines()
    hits = [i for i, ln in enumerate(lines)
            if re.match(rf"^\s*(- )?{re.escape(key)}:", ln)]
    if hits:
        i = hits[occurrence % len(hits)]
        head = lines[i].split(":", 1)[0]
        lines[i] = f"{head}: {value}"
        j = i + 1  # drop the old block value (more indented lines)
        indent = len(lines[i]) - len(lines[i].lstrip(" -"))
        while j < len(lines) and (len(lines[j]) - len(lines[j].lstrip(" ")) > indent):
            del lines[j]
    return ("\n".join(lines) + "\n").encode()


JSON_MUTATIONS["yaml_set"] = _yaml_set


def yaml_mutations() -> st.SearchStrategy[Mutation]:
    return st.one_of(
        byte_mutations(),
        st.builds(lambda k, v, n: Mutation("yaml_set", (k, v, n)),
                  st.sampled_from(YAML_KEYS), st.sampled_from(YAML_VALUES),
                  st.integers(0, 7)),
        st.builds(lambda t: Mutation("replace", (t.encode(),)),
                  st.sampled_from(["", "null", "[]", "x: 1", BILLION_LAUGHS,
                                   "rosbag2_bagfile_information: 1",
                                   "rosbag2_bagfile_information: {version: 9}",
                                   "rosbag2_bagfile_information:\n" + "  " * 200 + "a: 1",
                                   "[" * 10000 + "]" * 10000])),
    )


# ----------------------------------------------------------------------------- special files
def _special(kind: str, dest: Path) -> None:
    """Put a ``kind`` special file at ``dest`` (replacing what is there)."""
    if os.path.lexists(dest):
        if dest.is_dir() and not dest.is_symlink():
            shutil.rmtree(dest)
        else:
            dest.unlink()
    dest.parent.mkdir(parents=True, exist_ok=True)
    if kind == "fifo":
        os.mkfifo(dest)
    elif kind == "empty directory":
        dest.mkdir()
    elif kind == "directory with a file":
        _full_dir(dest, dest)
    elif kind == "dangling symlink":
        os.symlink("no-such-target", dest)
    elif kind == "symlink loop":
        os.symlink(dest.name, dest)
    elif kind == "symlink to /dev/zero":
        os.symlink("/dev/zero", dest)
    elif kind == "symlink to a fifo":
        os.mkfifo(dest.parent / ".fifo-target")
        os.symlink(".fifo-target", dest)
    elif kind == "empty file":
        dest.write_bytes(b"")
    elif kind == "1 TiB sparse file":
        _sparse(dest, dest)
    else:
        raise ValueError(kind)


SPECIAL_KINDS = ("fifo", "empty directory", "directory with a file", "dangling symlink",
                 "symlink loop", "symlink to /dev/zero", "symlink to a fifo", "empty file",
                 "1 TiB sparse file")
_REPLAY = ("--rate", "1000", "--wait-subscribers", "0")
#: Where a file goes: slot -> (argv with X for the path, the path X, kinds not to use and
#: why). Inputs first, then outputs.
SLOTS: dict[str, tuple[tuple[str, ...], str]] = {
    "model (evaluate)": (("evaluate", "X", "bag_mcap"), "m.npz"),
    "model (demo --model)": (("demo", "--model", "X", "--out", "demo_out"), "m.npz"),
    "ROS 1 bag (train)": (("train", "--model", "first_order_lag", "X", "--out", "o.npz"),
                          "b.bag"),
    "ROS 2 bag (train)": (("train", "--model", "first_order_lag", "X", "--out", "o.npz"), "b"),
    "ROS 2 mcap storage file (train)": (
        ("train", "--model", "first_order_lag", "bag_mcap", "--out", "o.npz"),
        "bag_mcap/bag_mcap.mcap"),
    "ROS 2 metadata.yaml (train)": (
        ("train", "--model", "first_order_lag", "bag_mcap", "--out", "o.npz"),
        "bag_mcap/metadata.yaml"),
    "ROS 2 sqlite3 storage file (evaluate)": (("evaluate", "fol.npz", "bag_sqlite"),
                                              "bag_sqlite/bag_sqlite.db3"),
    "storage file named directly (evaluate)": (("evaluate", "fol.npz", "X"),
                                               "bag_mcap/bag_mcap.mcap"),
    "ROS 2 mcap storage file (replay)": (("replay", "bag_mcap", *_REPLAY),
                                         "bag_mcap/bag_mcap.mcap"),
    "ROS 2 metadata.yaml (replay)": (("replay", "bag_mcap", *_REPLAY),
                                     "bag_mcap/metadata.yaml"),
    "ROS 1 bag (replay)": (("replay", "X", *_REPLAY), "b.bag"),
    "ROS 2 bag (replay)": (("replay", "X", *_REPLAY), "b"),
    "dataset manifest.json (reproduce)": (("reproduce", "--data", "dataset", "--out", "r"),
                                          "dataset/manifest.json"),
    "dataset bag (reproduce)": (("reproduce", "--data", "dataset", "--out", "r"),
                                "dataset/carpet/carpet_01"),
    "dataset directory (reproduce --data)": (("reproduce", "--data", "X", "--out", "r"),
                                             "ds"),
    "dataset directory (reproduce --quick --data)": (
        ("reproduce", "--quick", "--data", "X", "--out", "r"), "ds"),
    "train --out": (("train", "--model", "first_order_lag", "bag_mcap", "--out", "X"),
                    "o.npz"),
    "train --out --force": (("train", "--model", "first_order_lag", "bag_mcap", "--out", "X",
                             "--force"), "o.npz"),
    "simulate --out (ROS 2)": (("simulate", "--minutes", "0.15", "--out", "X"), "o"),
    "simulate --out (ROS 1) --force": (("simulate", "--minutes", "0.15", "--out", "X",
                                        "--force"), "o.bag"),
    "evaluate --json": (("evaluate", "fol.npz", "bag_mcap", "--json", "X"), "o.json"),
    "evaluate --json --force": (("evaluate", "fol.npz", "bag_mcap", "--json", "X",
                                 "--force"), "o.json"),
    "dataset --out": (("dataset", "--scale", "0.005", "--out", "X"), "o"),
    "reproduce --out": (("reproduce", "--data", "dataset", "--out", "X"), "o"),
    "board --link": (("board", "--duration", "0.2", "--link", "X"), "o"),
    "board --link --force": (("board", "--duration", "0.2", "--link", "X", "--force"), "o"),
    "board --monitor": (("board", "--duration", "0.2", "--monitor", "X"), "port"),
    "demo --out": (("demo", "--model", "fifo.npz", "--out", "X"), "o"),
}
#: Combinations that would start long work by design, not a reading or writing problem:
#: --quick simulates a dataset into an empty directory (minutes).
SKIP_COMBINATIONS = {("dataset directory (reproduce --quick --data)", "empty directory")}


def special_cases() -> list[tuple[str, str]]:
    return [(slot, kind) for slot in SLOTS for kind in SPECIAL_KINDS
            if (slot, kind) not in SKIP_COMBINATIONS]


def special_case_argv(slot: str) -> tuple[list[str], str]:
    argv, where = SLOTS[slot]
    return [where if a == "X" else a for a in argv], where


# ----------------------------------------------------------------------------- library calls
def call_load_model(path: str) -> dict[str, Any]:
    """load_model: a model, or ModelFileError (the documented failure)."""
    from asgp_ros.core.modelfile import ModelFileError, load_model

    try:
        model = load_model(path)
    except ModelFileError as exc:
        return {"refused": str(exc)[:300]}
    return {"loaded": model.kind}


def call_read_bag(path: str, truth: bool) -> dict[str, Any]:
    """read_streams and bag_topics: streams, or BagError (the documented failure)."""
    from asgp_ros.recording.bags import BagError, bag_topics, read_streams

    out: dict[str, Any] = {}
    try:
        out["topics"] = sorted(bag_topics(path))
    except BagError as exc:
        out["topics_refused"] = str(exc)[:300]
    try:
        s = read_streams(path, truth_topic="/ground_truth/odom" if truth else None)
        out["streams"] = [int(s.joy_t.size), int(s.vel_t.size)]
    except BagError as exc:
        out["refused"] = str(exc)[:300]
    return out
