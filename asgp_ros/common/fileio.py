"""Files a user keeps: atomic output, output paths checked before work, temporaries that
go away on signals as they do on exceptions.

The rule every command follows: **nothing is deleted or replaced that the command did not
create, unless the user asked for it** (``--force``), and even then only an output of the
same kind (a model file by a model file, a bag by a bag, a report directory that carries
the report's own marker file). :func:`check_output` enforces it before any work starts;
:func:`atomic_path` never removes anything it did not make itself.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import functools
import json
import logging
import multiprocessing
import multiprocessing.pool
import multiprocessing.process
import os
import shutil
import signal
import stat
import sys
import tempfile
import threading
import time
import zipfile
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import Any, TypeVar

_T = TypeVar("_T")
_R = TypeVar("_R")

MARKER_NAME = ".asgp-output"
"""The marker file a directory output carries: JSON ``{"format": MARKER_FORMAT, "kind": K}``."""
MARKER_FORMAT = "asgp_ros.output"
_MARKER_MAX_BYTES = 4096
_JSON_MAX_BYTES = 64 * 1024 * 1024


class OutputError(Exception):
    """An output path that must not be written: a one-line, user-facing reason."""


class Terminated(KeyboardInterrupt):
    """Raised in the main thread on SIGTERM/SIGHUP, so that ``finally`` blocks (and with
    them every temporary) run as they do on Ctrl-C. ``signum`` says which signal."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


_received: list[int] = []  # the stop signals this process has received, oldest first
_deferring: list[int] = [0]  # depth of signals_deferred() blocks
_worker: list[bool] = [False]  # a pool worker: a stop signal ends it through SystemExit
# The ledger of the pool this process is a worker of (set in the parent before the fork):
# a directory where each worker notes the temporaries it creates, one file per process, so
# that the parent can remove those of a worker it had to kill (SIGKILL runs no ``finally``).
_ledger: list[Path | None] = [None]


def raise_on_termination() -> None:
    """Turn SIGTERM and SIGHUP into :class:`Terminated`, and SIGINT into KeyboardInterrupt,
    in the calling (main) thread, so that ``finally`` blocks remove every temporary.

    A repeated SIGTERM while the clean-up runs is ignored, so that a supervisor that sends
    it twice does not cut the clean-up short; a repeated Ctrl-C interrupts as usual. An
    inherited SIG_IGN is kept: SIGINT for a background job, SIGHUP under ``nohup`` (a
    nohup'ed ``asgp simulate`` was ended when its session closed, its bag not written).

    An exception raised by a signal handler is lost when the signal lands in code whose
    exceptions Python discards (an at-fork hook, a ``__del__``): long waits therefore also
    call :func:`check_signals`, which raises again for a signal already received.
    """
    del _received[:]

    def handler(signum: int, _frame: FrameType | None) -> None:
        first = not _received
        _received.append(signum)
        if _deferring[0]:
            return  # raised when the signals_deferred() block ends
        if signum == signal.SIGINT:
            raise KeyboardInterrupt
        if first:
            raise Terminated(signum)

    for sig in (signal.SIGTERM, signal.SIGHUP, signal.SIGINT):
        if signal.getsignal(sig) is not signal.SIG_IGN:
            signal.signal(sig, handler)


@contextlib.contextmanager
def signals_deferred() -> Iterator[None]:
    """Hold back the exception of a stop signal until the block ends.

    For code that must not be interrupted half-way (creating a temporary and taking
    ownership of it) or whose exceptions Python would discard (forking runs at-fork hooks).
    """
    _deferring[0] += 1
    try:
        yield
    finally:
        _deferring[0] -= 1
    if not _deferring[0]:
        check_signals()


def check_signals() -> None:
    """Raise for a stop signal received earlier whose exception was lost (see
    :func:`raise_on_termination`); do nothing if none was received."""
    if _received:
        if _worker[0]:
            sys.exit(128 + _received[0])
        if _received[0] == signal.SIGINT:
            raise KeyboardInterrupt
        raise Terminated(_received[0])


def join_if_started(thread: threading.Thread, timeout: float) -> None:
    """``thread.join(timeout)``, or nothing for a thread whose ``start()`` never ran.

    An exception (Ctrl-C, a stop signal) can cut ``start()`` short, before or just after
    the thread began; ``join`` then raises "cannot join thread before it is started". The
    thread's own stop flag, set by the caller first, ends one that did begin.
    """
    deadline = time.monotonic() + timeout
    while True:
        try:
            thread.join(max(0.0, deadline - time.monotonic()))
            return
        except RuntimeError:  # begun (it has an ident) but not yet flagged started: wait
            if thread.ident is None or time.monotonic() >= deadline:
                return
            time.sleep(0.005)


_STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)


def quiet_worker_exit() -> None:
    """Pool-worker initialiser: SIGTERM/SIGINT/SIGHUP end the worker through ``SystemExit``.

    ``finally`` blocks run (a worker's own temporaries go), and multiprocessing ends a
    worker on SystemExit without printing a traceback per worker. The stop signals are
    unblocked last (:func:`worker_pool` forks its workers with them blocked): one sent to
    the worker while it started is delivered here, to this handler.

    Inside a :func:`signals_deferred` block (creating a temporary and taking ownership of
    it, committing it, removing it) the exit waits for the block's end, as in the parent:
    a worker stopped between ``mkdtemp`` and the assignment of its result left an empty
    temporary behind.

    A handler runs wherever the main thread is, and an exception raised inside a weakref
    callback or a ``__del__`` (an import's module-lock callback, say) is not propagated:
    Python prints it as "Exception ignored" and goes on. Such a swallowed exit still ends
    the worker, at once and without the traceback (``sys.unraisablehook``).
    """
    previous_hook = sys.unraisablehook
    exiting: list[int] = []

    def handler(signum: int, _frame: FrameType | None) -> None:
        for sig in _STOP_SIGNALS:
            signal.signal(sig, signal.SIG_IGN)
        exiting.append(128 + signum)
        _received.append(signum)
        if _deferring[0]:
            return  # raised when the signals_deferred() block ends (check_signals)
        sys.exit(128 + signum)

    def unraisable(info: Any) -> None:
        if exiting and isinstance(info.exc_value, SystemExit):
            os._exit(exiting[0])  # the handler's exit, swallowed where it was raised
        previous_hook(info)

    sys.unraisablehook = unraisable
    _worker[0] = True
    for sig in _STOP_SIGNALS:
        if signal.getsignal(sig) is not signal.SIG_IGN:  # (the parent's: nohup's SIGHUP)
            signal.signal(sig, handler)
    # A worker is forked inside the parent's signals_deferred() block, with the parent's
    # handler: a stop signal that arrived before this initialiser was only recorded.
    _deferring[0] = 0
    if _received:
        handler(_received[-1], None)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, _STOP_SIGNALS)


PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def die_with_parent(parent: int) -> bool:
    """Ask the kernel for SIGTERM when this process's parent dies (``prctl(PR_SET_PDEATHSIG)``,
    Linux; a warning on stderr where it fails), and whether the parent ``parent`` is still
    there (it may have died before the request)."""
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0) != 0:
        print(f"warning: prctl(PR_SET_PDEATHSIG) failed: {os.strerror(ctypes.get_errno())}",
              file=sys.stderr)
    return os.getppid() == parent


def _start_pool_worker(initializer: Callable[..., object] | None,
                       initargs: tuple[Any, ...], parent: int) -> None:
    # A parent killed outright (SIGKILL, the OOM killer) ran no clean-up: its workers went
    # on with the queue, both cores busy for a minute, writing into a temporary nobody
    # would commit, then printed BrokenPipeError tracebacks. The SIGTERM the kernel sends
    # them now is the stop signal of quiet_worker_exit (blocked until it is in place).
    if not die_with_parent(parent):
        os._exit(128 + signal.SIGTERM)
    quiet_worker_exit()
    if initializer is not None:
        initializer(*initargs)


def interruptible_imap(pool: multiprocessing.pool.Pool, fn: Callable[[_T], _R],
                       items: Iterable[_T]) -> Iterator[_R]:
    """``pool.imap(fn, items)`` that a signal interrupts at once.

    A wait with no timeout in the main thread is not woken by a signal that the kernel
    delivers to another thread, so Ctrl-C or SIGTERM would wait for the next result
    (minutes, for a training job). Waiting in short slices lets the signal's handler run
    within 0.1 s.
    """
    it = pool.imap(fn, items)
    while True:
        check_signals()
        try:
            yield it.next(timeout=0.1)
        except multiprocessing.TimeoutError:
            continue
        except StopIteration:
            return


#: How long the workers of a pool that is being stopped get to end on SIGTERM before
#: they are killed.
POOL_STOP_GRACE_S = 5.0
#: How often a stopping pool looks whether its workers have ended, and how long its
#: ``terminate()`` may still take once they all have.
_POOL_STOP_POLL_S = 0.05
_POOL_STOP_AFTER_KILL_S = 1.0


@contextlib.contextmanager
def worker_pool(processes: int, initializer: Callable[..., object] | None = None,
                initargs: tuple[Any, ...] = ()) -> Iterator[multiprocessing.pool.Pool]:
    """A pool of forked workers that a stop signal ends at any moment, gone when the block ends.

    - The workers are forked with SIGTERM, SIGINT and SIGHUP blocked, and unblock them once
      their handlers are in place (:func:`quiet_worker_exit`, then ``initializer``). A
      signal sent to a worker between its fork and that point stays pending instead of
      being lost: CPython clears the signals a child has received but not yet handled when
      it re-initialises after fork, and a worker that lost its SIGTERM that way waited
      forever for a task while the parent waited for it to end. The pool's own threads in
      the parent inherit the block; threads a worker starts later (BLAS, OpenMP) do not,
      which is why a stopping pool signals each worker's main thread (:func:`_stop_pool`).
    - On success the pool is closed and joined: each worker ends on the pool's own
      sentinel, no signal involved. On an exception (an error, or a stop signal turned into
      one) the pool is terminated: SIGTERM, which :func:`quiet_worker_exit` turns into
      ``SystemExit`` so that the workers' ``finally`` blocks run; workers still alive after
      :data:`POOL_STOP_GRACE_S` are killed. A signal that arrives while the pool starts
      is raised once the pool exists, and stops it the same way.
    - The temporaries a killed worker leaves (:func:`atomic_path`'s, which its workers note
      in a ledger before creating them) are removed when the block ends
      (:func:`_sweep_ledger`).

    Why not ``with pool:``: its ``__exit__`` terminates the pool also after success.
    """
    ctx = multiprocessing.get_context("fork")
    before = set(multiprocessing.active_children())
    pool: multiprocessing.pool.Pool | None = None
    outer = _ledger[0]
    ledger: Path | None = None
    try:
        try:
            with signals_deferred():  # a signal inside fork's hooks would be lost
                with contextlib.suppress(OSError):  # without one, a kill leaves temporaries
                    ledger = Path(tempfile.mkdtemp(prefix="asgp-pool-"))
                # the workers inherit it, also those the pool forks later to replace one;
                # this process's own notes are never swept (it is running)
                _ledger[0] = ledger
                mask = signal.pthread_sigmask(signal.SIG_BLOCK, _STOP_SIGNALS)
                try:
                    pool = ctx.Pool(processes, initializer=_start_pool_worker,
                                    initargs=(initializer, initargs, os.getpid()))
                finally:
                    signal.pthread_sigmask(signal.SIG_SETMASK, mask)
            yield pool
        except BaseException:
            if pool is not None:
                _stop_pool(pool, before)
            raise
        pool.close()
        pool.join()
    finally:
        _ledger[0] = outer
        if ledger is not None:
            _sweep_ledger(ledger)
            shutil.rmtree(ledger, ignore_errors=True)


def _stop_pool(pool: multiprocessing.pool.Pool,
               others: set[multiprocessing.process.BaseProcess]) -> None:
    """Terminate ``pool``; kill its workers that outlive the grace period.

    Each worker's main thread is sent SIGTERM first (:func:`signal_main_thread`):
    ``pool.terminate()`` signals the process, and the kernel may hand that signal to any
    of the worker's threads; one taken by a BLAS thread only marks the signal for Python,
    whose handler then waits for the main thread, which, idle between tasks, sleeps in a
    lock the terminating pool never releases. ``pool.terminate()`` runs in a helper
    thread so that a worker that does not end cannot hold up the main thread beyond the
    grace period.

    ``pool.terminate()`` may also fail: it drains the task queue, and a worker stopped
    half-way through reading a task leaves part of a message there (``EOFError: Ran out of
    input`` from the pipe, seen under load). Its failure is not the command's: it is
    swallowed (the pool is being thrown away), and every worker still alive after the grace
    period is killed whether the helper thread ended or not. Or it may never return: once
    every worker is gone, nothing reads the task queue, and a teardown waiting to write
    there waits for good. So the wait ends as soon as the workers have (not at the end of
    the grace period), and the helper thread gets :data:`_POOL_STOP_AFTER_KILL_S` more.
    """
    workers = _pool_workers(pool, others)
    for worker in workers:
        if worker.pid is not None:
            with contextlib.suppress(OSError):  # pool.terminate() below signals it anyway
                signal_main_thread(worker.pid, signal.SIGTERM)

    def terminate() -> None:
        with contextlib.suppress(Exception):  # the teardown of a pool being thrown away
            pool.terminate()

    deadline = time.monotonic() + POOL_STOP_GRACE_S
    stopper = threading.Thread(target=terminate, name="pool-stop", daemon=True)
    stopper.start()
    while time.monotonic() < deadline:
        stopper.join(_POOL_STOP_POLL_S)
        if not stopper.is_alive() or not any(
                w.is_alive() for w in {*workers, *_pool_workers(pool, others)}):
            break
    left = [w for w in {*workers, *_pool_workers(pool, others)} if w.is_alive()]
    if stopper.is_alive() or left:
        for worker in left:  # what is left of the grace period (a failed terminate() ends
            worker.join(max(0.0, deadline - time.monotonic()))  # early), then the kill
            if worker.is_alive():
                worker.kill()
                worker.join(_POOL_STOP_AFTER_KILL_S)  # ended before its temporaries go
        # With every worker gone, terminate() either ends at once or never: it can be
        # stuck for good on the task queue that no worker reads any more (its own task
        # handler blocked in a write; seen by benchmarks/fuzz.py, seed 5151, as a
        # 10-second stop of ``asgp reproduce``). The daemon thread is then left behind.
        stopper.join(_POOL_STOP_AFTER_KILL_S)


def _pool_workers(pool: multiprocessing.pool.Pool,
                  others: set[multiprocessing.process.BaseProcess]
                  ) -> list[multiprocessing.process.BaseProcess]:
    """The pool's worker processes: CPython's ``Pool._pool``; without it, the children
    that were not there before the pool (which may include other children started since)."""
    listed = getattr(pool, "_pool", None)
    if isinstance(listed, list):
        return [w for w in listed if isinstance(w, multiprocessing.process.BaseProcess)]
    return [c for c in multiprocessing.active_children() if c not in others]


def signal_main_thread(pid: int, signum: int) -> None:
    """Send ``signum`` to the main thread of process ``pid``, where Python handles signals.

    ``os.kill`` lets the kernel pick any thread that does not block the signal; Python
    runs its handler only in the main thread, and a main thread asleep in a C call is only
    woken if the signal is delivered to it. Linux's ``tgkill`` (the main thread's id is
    the process id) aims it there; elsewhere, or without ``tgkill``, ``os.kill``. A process
    that is gone is not an error.
    """
    try:
        if sys.platform.startswith("linux"):
            libc = ctypes.CDLL(None, use_errno=True)
            tgkill = getattr(libc, "tgkill", None)
            if tgkill is not None:
                if tgkill(ctypes.c_int(pid), ctypes.c_int(pid), ctypes.c_int(signum)) == 0:
                    return
                err = ctypes.get_errno()
                if err == errno.ESRCH:
                    return
                raise OSError(err, os.strerror(err))
        os.kill(pid, signum)
    except ProcessLookupError:
        pass


# ----------------------------------------------------------------------------- atomic output
@contextlib.contextmanager
def atomic_path(final: str | os.PathLike[str], *, directory: bool = False,
                replace: bool = True) -> Iterator[Path]:
    """Yield a temporary path next to ``final``; move it into place only on success.

    The temporary path is in the same directory as ``final`` (so the rename is atomic on
    POSIX) and does not exist yet when yielded: the caller creates the file (or, with
    ``directory=True``, the directory, e.g. a ROS 2 bag) there. On an exception, or on a
    signal turned into one (:func:`raise_on_termination`), the temporary is removed and
    ``final`` is left untouched; a signal during the final rename(s), or while the
    temporary is removed, is raised once they are done.

    What may be replaced: with ``directory=False``, an existing regular file (unless
    ``replace=False``). With ``directory=True``, an existing directory only when
    ``replace=True`` and only after the new one is complete: the old directory is moved
    aside, the new one moved in, and the old one removed last (moved back if the move in
    fails). Anything of another kind at ``final`` (a directory where a file goes, a file
    where a directory goes, a FIFO, a device) raises :class:`FileExistsError` before the
    caller writes anything. Whether the user allowed a replacement at all is
    :func:`check_output`'s business; this function is the last line of defence: the
    commit replaces only what was at ``final`` when :func:`check_output` approved it (or,
    for a path it did not check, when this function was entered), unchanged. Anything that
    appeared there meanwhile, or changed (a file added to a directory), is left alone and
    :class:`FileExistsError` raised: a directory of notes made at ``--out`` while a
    simulation ran was deleted at its end, with or without ``--force``.
    """
    final = Path(final)
    parent = final.parent if str(final.parent) else Path(".")
    _refuse_other_kind(final, directory=directory, replace=replace)
    key = _output_key(final)
    if key not in _approved:  # (check_output says it for the paths it approves)
        _warn_stray_temporaries(final)
    expected = _approved.get(key, _identity(final))
    made = _make_parents(parent)
    tmpdir: Path | None = None
    committed = body = False
    try:
        try:
            with signals_deferred():  # no signal between creating and owning tmpdir
                tmpdir = _temporary_directory(parent, final)
            tmp = tmpdir / final.name
            body = True  # an error there that names no file is not this function's to name
            yield tmp
            body = False
            if not tmp.exists():
                raise FileNotFoundError(f"nothing was written to {tmp} for {final}")
            if directory != tmp.is_dir():
                raise FileExistsError(f"{tmp} is not the "
                                      f"{'directory' if directory else 'file'} expected for "
                                      f"{final}")
            _fsync_tree(tmp)  # on the disk before it is published (and the old one removed)
            # The commit, whole or not at all: a signal between the two renames of a
            # replacement would leave the old directory in the temporary removed below.
            with signals_deferred():
                _refuse_other_kind(final, directory=directory, replace=replace)
                if _identity(final) != expected:
                    raise FileExistsError(
                        f"{final} appeared or changed while it was being written; it was "
                        "not replaced")
                if expected is None:  # nothing to replace: nor anything that appears now
                    _rename_no_replace(tmp, final)
                elif directory:
                    _replace_moving_aside(tmp, final, tmpdir / _REPLACED)
                else:
                    _replace_file(tmp, final, tmpdir / _REPLACED)
                committed = True  # (before a signal deferred meanwhile is raised)
            _fsync_directory(parent)  # the rename itself, before a replaced one is removed
        except OSError as exc:
            # the user knows the output, not its temporary (".m.npz.<hex>.tmp/m.npz")
            raise _named_for_output(exc, tmpdir, final, unnamed=not body) from None
        if key in _approved:  # this command's own output now (it may write it again)
            _approved[key] = _identity(final)
    finally:
        if tmpdir is not None:
            with signals_deferred():  # raised once the temporary is gone
                if committed or not _stranded(tmpdir / _REPLACED, final):
                    shutil.rmtree(tmpdir, ignore_errors=True)
                if not committed:  # a failed write leaves no directory it made either
                    for d in reversed(made):
                        try:
                            os.rmdir(d)
                        except OSError:
                            break


#: What a file system that cannot rename a file over an existing one says to
#: ``os.replace``: EEXIST (a FUSE or SMB server without it), EPERM (sshfs without the
#: posix-rename extension: SFTP's plain rename refuses an existing target), EACCES (SMB,
#: the target open elsewhere), ENOTSUP, EBUSY. Where the error has another cause (a
#: directory that takes no new entry, an immutable file), moving the old file aside fails
#: the same way, with nothing changed.
_NO_RENAME_OVER = frozenset({errno.EEXIST, errno.EPERM, errno.EACCES, errno.ENOTSUP,
                             errno.EOPNOTSUPP, errno.EBUSY})


def _replace_file(tmp: Path, final: Path, aside: Path) -> None:
    """``os.replace(tmp, final)``; where the file system cannot rename over an existing
    file (:data:`_NO_RENAME_OVER`), the old file is moved aside first, as a directory is
    (:func:`_replace_moving_aside`): for a moment ``final`` is missing, both files kept."""
    try:
        os.replace(tmp, final)
        return
    except OSError as exc:
        if exc.errno not in _NO_RENAME_OVER or not os.path.lexists(final):
            raise
        try:
            os.rename(final, aside)
        except OSError:
            # not even moved aside (a directory that takes no new entry, an immutable
            # file): nothing changed, and the first error is the one to tell
            raise exc from None
        _log.debug("%s: %s; replaced by moving the old file aside", final,
                   os.strerror(exc.errno or 0))
    _move_in(tmp, final, aside)


def _replace_moving_aside(tmp: Path, final: Path, aside: Path) -> None:
    """Move ``final`` to ``aside`` (inside the temporary), then ``tmp`` to ``final``."""
    os.rename(final, aside)
    _move_in(tmp, final, aside)


def _move_in(tmp: Path, final: Path, aside: Path) -> None:
    """Move ``tmp`` to ``final``, whose old content is at ``aside``; if that fails, move
    ``aside`` back. If that fails too, ``aside`` stays, and the temporary holding it is
    kept (:func:`_stranded`): both the old and the new, never neither."""
    try:
        os.rename(tmp, final)
    except BaseException:
        with contextlib.suppress(OSError):  # kept where it is otherwise (_stranded)
            os.rename(aside, final)
        raise


def _stranded(aside: Path, final: Path) -> bool:
    """Whether ``aside``, the output a failed commit had moved aside, is still there (and
    must not be removed with its temporary). It is moved back once more if ``final`` is
    free; if it stays, the error says where it is."""
    if not os.path.lexists(aside):
        return False
    if not os.path.lexists(final):
        with contextlib.suppress(OSError):
            os.rename(aside, final)
            return False
    _log.error("%s: the output it held is kept at %s (it could not be moved back): move it "
               "back by hand", final, aside)
    return True


def _named_for_output(exc: OSError, tmpdir: Path | None, final: Path, *,
                      unnamed: bool) -> OSError:
    """``exc`` naming the output (``final``, or the file inside it) where it names a path in
    the temporary ``tmpdir``, and, with ``unnamed``, ``final`` where it names no file."""
    if exc.errno is None:
        return exc  # one of this module's own messages, which name ``final`` already

    def shown(name: Any) -> Any:
        if name is None or tmpdir is None:
            return name
        try:
            rel = Path(os.path.abspath(os.fsdecode(name))).relative_to(os.path.abspath(tmpdir))
        except (TypeError, ValueError):
            return name
        if rel.parts[:1] == (final.name,):
            return str(final.joinpath(*rel.parts[1:]))
        return str(final)  # the temporary itself, or the old output moved aside in it

    first, second = shown(exc.filename), shown(exc.filename2)
    if first is None and unnamed:
        first = str(final)
    if (first, second) == (exc.filename, exc.filename2):
        return exc
    return OSError(exc.errno, exc.strerror or str(exc), first, None, second)


@contextlib.contextmanager
def naming(path: str | os.PathLike[str]) -> Iterator[None]:
    """A block whose :class:`OSError` that names no file (a full disk while a figure or a
    JSON file is written: "No space left on device") names ``path``."""
    try:
        yield
    except OSError as exc:
        if exc.filename is not None or exc.errno is None:
            raise
        raise OSError(exc.errno, exc.strerror or str(exc), os.fspath(path)) from exc


#: Longest output name: its temporary's (``.NAME.<12 hex>.tmp``) must fit in 255 bytes.
MAX_OUTPUT_NAME_BYTES = 255 - len("..") - 12 - len(".tmp")

def _make_parents(parent: Path) -> list[Path]:
    """Make ``parent`` and its missing ancestors; the directories this call made, in the
    order made (one that exists, or appears meanwhile, is not among them, whatever the
    path's ``..`` say: ``missing/../keep`` makes ``missing`` only)."""
    missing: list[Path] = []
    p = parent
    while str(p) not in ("", ".") and not os.path.lexists(p) and p != p.parent:
        missing.append(p)
        p = p.parent
    made: list[Path] = []
    try:
        for d in reversed(missing):
            try:
                os.mkdir(d)
            except FileExistsError:
                continue
            made.append(d)
        if not parent.is_dir():
            parent.mkdir(parents=True, exist_ok=True)  # (raises what the system says)
    except BaseException:
        for d in reversed(made):
            with contextlib.suppress(OSError):
                os.rmdir(d)
        raise
    return made


#: What :func:`check_output` saw at each output path it approved (:func:`_identity`), by
#: :func:`_output_key`: all :func:`atomic_path` may replace there.
_approved: dict[str, tuple[int, ...] | None] = {}


def forget_approved_outputs() -> None:
    """Forget what :func:`check_output` approved: a new command starts (in one process)."""
    _approved.clear()


def _output_key(path: Path) -> str:
    """An output path, absolute, its parent's symlinks resolved (not its own)."""
    parent = path.parent if str(path.parent) else Path(".")
    return os.path.join(os.path.realpath(parent), path.name)


def _identity(path: Path) -> tuple[int, ...] | None:
    """What is at ``path`` (not followed): None for nothing, else its device, inode, type
    and, as they change with a write or with an entry added to a directory, its
    modification time and size."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return None
    return (st.st_dev, st.st_ino, st.st_mode, st.st_mtime_ns, st.st_size)


_RENAME_NOREPLACE = 1
_AT_FDCWD = -100


@functools.cache
def _libc() -> Any:
    """The C library (errno kept), or None where it cannot be loaded by name."""
    try:
        return ctypes.CDLL(None, use_errno=True)
    except OSError:
        return None


def _rename_no_replace(src: Path, dst: Path) -> None:
    """Rename ``src`` to ``dst`` unless something is at ``dst`` (FileExistsError): Linux's
    renameat2(RENAME_NOREPLACE), atomic; where the C library or the filesystem lacks it,
    a check and a rename (a file: a hard link and an unlink, atomic too)."""
    renameat2 = getattr(_libc(), "renameat2", None)
    if renameat2 is not None:
        if renameat2(_AT_FDCWD, os.fsencode(src), _AT_FDCWD, os.fsencode(dst),
                     _RENAME_NOREPLACE) == 0:
            return
        err = ctypes.get_errno()
        if err == errno.EEXIST:
            raise FileExistsError(errno.EEXIST, f"{dst} appeared while it was being written; "
                                  "it was not replaced", str(dst))
        if err not in (errno.EINVAL, errno.ENOSYS, errno.ENOTSUP):
            raise OSError(err, os.strerror(err), str(dst))
    if not src.is_dir():
        try:
            os.link(src, dst)  # fails if dst exists
        except FileExistsError:
            raise FileExistsError(errno.EEXIST, f"{dst} appeared while it was being "
                                  "written; it was not replaced", str(dst)) from None
        except OSError:  # no hard links here (FAT): the check below, then a rename
            pass
        else:
            os.unlink(src)
            return
    if os.path.lexists(dst):
        raise FileExistsError(errno.EEXIST, f"{dst} appeared while it was being written; it "
                              "was not replaced", str(dst))
    os.rename(src, dst)


def _fsync_directory(path: Path) -> None:
    """Flushes a directory's entries (a rename in it). Some filesystems cannot fsync a
    directory (EINVAL): their renames are as durable as they get."""
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    except OSError as exc:
        if exc.errno not in (errno.EINVAL, errno.ENOTSUP):
            raise
    finally:
        os.close(fd)


def _fsync_tree(path: Path) -> None:
    """Flushes a written file, or every file and directory of a written directory (a ROS 2
    bag), to the disk: a power cut after the publishing rename then finds them whole."""
    if not path.is_dir():
        with open(path, "rb+") as fh:
            os.fsync(fh.fileno())
        return
    for root, dirs, files in os.walk(path):
        for name in files:
            f = Path(root) / name
            if f.is_file() and not f.is_symlink():
                with open(f, "rb") as fh:
                    os.fsync(fh.fileno())
        _fsync_directory(Path(root))
        dirs[:] = [d for d in dirs if not (Path(root) / d).is_symlink()]


#: The name atomic_path gives the aside copy of a directory it replaces, in its temporary.
_REPLACED = ".replaced"

_log = logging.getLogger(__name__)


def _temporary_directory(parent: Path, final: Path) -> Path:
    """``tempfile.mkdtemp`` next to ``final`` (``.<name>.<random>.tmp``), noted first in the
    pool's ledger when this process is a pool worker (see :func:`_sweep_ledger`)."""
    ledger = _ledger[0]
    for _ in range(100):
        path = parent / f".{final.name}.{os.urandom(6).hex()}.tmp"
        if ledger is not None:  # noted before it exists: a kill in between leaves nothing
            # the ledger is a courtesy, never a failure
            with (contextlib.suppress(OSError),
                  open(ledger / str(os.getpid()), "a", encoding="utf-8") as fh):
                fh.write(json.dumps([str(path.absolute()), str(final.absolute())]) + "\n")
        try:
            os.mkdir(path, 0o700)
        except FileExistsError:
            continue
        except OSError as exc:  # (the user knows the output, not its temporary)
            raise OSError(exc.errno, exc.strerror or str(exc), str(final)) from exc
        return path
    raise FileExistsError(f"no free temporary name next to {final}")


def _process_ended(pid: int) -> bool:
    """Process ``pid`` runs no more (gone, or a zombie). A pid in use by another process
    since reads as running: what its worker left then stays, which is the safe side."""
    try:
        stat_line = Path(f"/proc/{pid}/stat").read_text()
        return stat_line.rsplit(")", 1)[1].split()[0] in ("Z", "X")
    except FileNotFoundError:
        return True
    except (OSError, IndexError):
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        except OSError:
            return False
        return False


def _sweep_ledger(ledger: Path) -> None:
    """Remove what the ended workers of a pool noted in ``ledger`` and left behind.

    A worker removes its own temporaries on an exception or a stop signal; one killed after
    the grace period cannot. Each noted temporary still there is removed; a directory it
    was replacing, moved aside into it when the kill came between the two renames of the
    commit, is moved back first when nothing has taken its place. Only paths this pool's
    workers noted, of the form ``.<name>.<random>.tmp``, are touched, and only once the
    worker that noted them has ended.
    """
    try:
        notes = sorted(ledger.iterdir())
    except OSError:
        return
    for note in notes:
        if not (note.name.isdigit() and _process_ended(int(note.name))):
            continue
        try:
            lines = note.read_text(encoding="utf-8").splitlines()
        except (OSError, ValueError):
            continue
        for line in lines:
            try:
                tmp_name, final_name = json.loads(line)
                tmp, final = Path(tmp_name), Path(final_name)
            except (ValueError, TypeError):
                continue  # a line cut short by the kill
            if not (tmp.name.startswith(f".{final.name}.") and tmp.name.endswith(".tmp")
                    and tmp.is_dir() and not tmp.is_symlink()):
                continue
            with signals_deferred():
                aside = tmp / _REPLACED
                if (not aside.is_symlink() and (aside.is_dir() or aside.is_file())
                        and not os.path.lexists(final)):
                    with contextlib.suppress(OSError):
                        os.rename(aside, final)
                shutil.rmtree(tmp, ignore_errors=True)


def _refuse_other_kind(final: Path, *, directory: bool, replace: bool) -> None:
    if not os.path.lexists(final):
        return
    if final.is_symlink():
        raise FileExistsError(f"{final} is a symbolic link; refusing to replace it")
    mode = os.stat(final).st_mode
    wanted = stat.S_ISDIR(mode) if directory else stat.S_ISREG(mode)
    if not wanted:
        raise FileExistsError(f"{final} exists and is {describe_kind(final)}, not a "
                              f"{'directory' if directory else 'regular file'}")
    if not replace and not (directory and not any(final.iterdir())):
        # (an empty directory is taken as a new directory output, as check_output takes
        # it: refused here, a report failed only after all its work)
        raise FileExistsError(f"{final} exists")


def atomic_write_bytes(final: str | os.PathLike[str], data: bytes) -> None:
    # (a full disk said only "No space left on device": the user needs the file)
    with naming(final), atomic_path(final) as tmp:
        tmp.write_bytes(data)


def atomic_write_text(final: str | os.PathLike[str], text: str) -> None:
    atomic_write_bytes(final, text.encode("utf-8"))


def write_marker(directory: str | os.PathLike[str], kind: str, **extra: Any) -> None:
    """Mark ``directory`` as an output of ``kind`` (so that ``--force`` may replace it)."""
    atomic_write_text(Path(directory) / MARKER_NAME,
                      json.dumps({"format": MARKER_FORMAT, "kind": kind, **extra}) + "\n")


def read_marker(directory: str | os.PathLike[str]) -> str | None:
    """The kind named by ``directory``'s marker file, or None (absent, not ours, unreadable)."""
    data = _small_json(Path(directory) / MARKER_NAME, _MARKER_MAX_BYTES)
    if isinstance(data, dict) and data.get("format") == MARKER_FORMAT:
        kind = data.get("kind")
        return kind if isinstance(kind, str) else None
    return None


# ----------------------------------------------------------------------------- output kinds
def describe_kind(path: str | os.PathLike[str]) -> str:
    """'a directory', 'a regular file', 'a FIFO', ... for an existing path."""
    try:
        mode = os.lstat(path).st_mode
    except OSError:
        return "missing"
    for test, name in ((stat.S_ISLNK, "a symbolic link"), (stat.S_ISDIR, "a directory"),
                       (stat.S_ISREG, "a regular file"), (stat.S_ISFIFO, "a FIFO"),
                       (stat.S_ISSOCK, "a socket"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device")):
        if test(mode):
            return name
    return "a special file"


def is_model_file(path: Path) -> bool:
    """A regular file that is a zip archive holding the model file's ``__meta__`` member."""
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            return False
        with zipfile.ZipFile(path) as zf:
            return "__meta__.npy" in zf.namelist()
    except (OSError, zipfile.BadZipFile, ValueError, EOFError):
        return False


ROS1_MAGIC = b"#ROSBAG V2.0\n"
"""The first line of a ROS 1 bag (format version 2.0)."""


def is_ros1_bag(path: Path) -> bool:
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            return False
        with open(path, "rb") as fh:
            return fh.read(len(ROS1_MAGIC)) == ROS1_MAGIC
    except OSError:
        return False


#: What a ROS 2 bag directory holds besides metadata.yaml: its storage files (mcap,
#: SQLite with its journal files, zstd-compressed files).
_BAG_FILE_SUFFIXES = (".mcap", ".db3", ".db3-wal", ".db3-shm", ".db3-journal", ".zstd")


def is_ros2_bag(path: Path) -> bool:
    """A ROS 2 bag directory: a metadata.yaml that rosbag2 wrote (its top-level key) and
    nothing but storage files beside it. A directory that merely has a metadata.yaml (a
    project with its notes) is not one, and ``--force`` never replaces it."""
    meta = path / "metadata.yaml"
    try:
        st = os.lstat(meta)
        if not (path.is_dir() and stat.S_ISREG(st.st_mode)) or st.st_size > 16 * 2**20:
            return False
        with open(meta, "rb") as fh:
            head = fh.read(4096)
        if not any(line.rstrip() == b"rosbag2_bagfile_information:"
                   for line in head.splitlines()):
            return False
        for entry in os.scandir(path):
            if entry.name != "metadata.yaml" and not (
                    entry.is_file(follow_symlinks=False)
                    and entry.name.endswith(_BAG_FILE_SUFFIXES)):
                return False
    except OSError:
        return False
    return True


def _small_json(path: Path, max_bytes: int) -> Any:
    """The JSON in ``path`` if it is a regular file (symlinks not followed) of at most
    ``max_bytes``; None if it is anything else or not JSON."""
    try:
        st = os.lstat(path)
        if not stat.S_ISREG(st.st_mode) or st.st_size > max_bytes:
            return None
        return json.loads(path.read_bytes())
    except (OSError, ValueError, RecursionError):
        return None


def is_json_object_with(path: Path, key: str) -> bool:
    """A regular JSON file (at most 64 MB) holding an object with ``key``."""
    data = _small_json(path, _JSON_MAX_BYTES)
    return isinstance(data, dict) and key in data


@dataclass(frozen=True)
class OutputKind:
    """What a command writes at an output path.

    Attributes:
        name: how messages call it ("model file", "bag", ...).
        directory: True for a directory, False for a regular file, None if either (a bag:
            a ROS 2 bag directory or a ROS 1 ``.bag`` file).
        same_kind: recognises an existing output of this kind (``--force`` may replace
            it; nothing else is ever replaced).
        resumable: an existing output of this kind is reused without ``--force`` (the
            command adds to it and replaces nothing in it that is not its own).
    """

    name: str
    directory: bool | None
    same_kind: Callable[[Path], bool]
    resumable: bool = False

    @property
    def a_name(self) -> str:
        """The name with its article ("a model file", "an evaluation JSON file")."""
        return f"{'an' if self.name[:1] in 'aeiou' else 'a'} {self.name}"


def marked(kind: str) -> Callable[[Path], bool]:
    return lambda p: p.is_dir() and not p.is_symlink() and read_marker(p) == kind


MODEL_FILE = OutputKind("model file", False, is_model_file)
ROS1_BAG = OutputKind("ROS 1 bag", False, is_ros1_bag)
ROS2_BAG = OutputKind("ROS 2 bag", True, is_ros2_bag)


def bag_kind(path: str | os.PathLike[str]) -> OutputKind:
    """The bag written at ``path``: a ROS 1 file for a ``.bag`` name, else a ROS 2 directory."""
    return ROS1_BAG if Path(path).suffix == ".bag" else ROS2_BAG


def _is_scores_json(path: Path) -> bool:
    """``asgp evaluate --json``'s output: its horizons, or with ``--adapt`` the adapted and
    the plain model's (``--force`` could not replace the latter)."""
    data = _small_json(path, _JSON_MAX_BYTES)
    if not isinstance(data, dict):
        return False
    return "horizons" in data or all(isinstance(data.get(key), dict)
                                     and "horizons" in data[key] for key in ("adapted", "plain"))


SCORES_JSON = OutputKind("evaluation JSON file", False, _is_scores_json)
REPORT_DIR = OutputKind("reproduction report directory", True, marked("reproduce-report"))
DEMO_DIR = OutputKind("demo output directory", True, marked("demo"))


def _is_dataset(p: Path) -> bool:
    if not p.is_dir() or p.is_symlink():
        return False
    if read_marker(p) == "dataset":
        return True
    data = _small_json(p / "manifest.json", _JSON_MAX_BYTES)
    return isinstance(data, dict) and data.get("format") == "asgp_ros.dataset"


DATASET_DIR = OutputKind("dataset directory", True, _is_dataset, resumable=True)


def bag_inputs(paths: Iterable[str | os.PathLike[str]]) -> list[str]:
    """Input paths for :func:`check_output`: each one and, for a ROS 2 storage file
    (``.mcap`` / ``.db3``), its directory, which it stands for when it is a bag's (a
    recorder that was killed leaves a bag directory without metadata.yaml, so any such
    directory is taken for one): an output written into it would damage the bag. A bag
    directory named like a storage file (``asgp simulate --out run1.mcap``) is the bag
    itself: its parent is not (every output beside it was refused)."""
    out: list[str] = []
    for raw in paths:
        out.append(str(raw))
        if Path(raw).suffix in (".mcap", ".db3") and not os.path.isdir(raw):
            out.append(str(Path(raw).parent))
    return out


def _absolute(path: Path) -> Path:
    """Absolute, with '..' and symlinks of existing parts resolved."""
    return Path(os.path.realpath(path))


def check_output(path: str | os.PathLike[str], kind: OutputKind, *,
                 inputs: Iterable[str | os.PathLike[str]] = (), force: bool = False,
                 option: str = "--out") -> Path:
    """Check an output path before any work starts; return it as a Path.

    Refused, with a one-line :class:`OutputError`:
    - a path equal to, inside or containing one of ``inputs`` (symlinks resolved);
    - a path whose parent is not a directory (``m.npz/x.npz`` with a file ``m.npz``);
    - an existing symbolic link at the path itself;
    - an existing path of another kind (a directory where a file goes, a FIFO, a file
      where a directory goes, a directory that is not this kind's);
    - an existing output of the same kind, unless ``force`` (or the kind is resumable).
    An existing empty directory is taken as a new directory output.
    """
    out = _check_output(path, kind, inputs, force, option)
    _approved[_output_key(out)] = _identity(out)  # all the commit may replace there
    _warn_stray_temporaries(out)
    return out


def _warn_stray_temporaries(out: Path) -> None:
    for stray in stray_temporaries(out):
        aside = " (it holds the one it was replacing: move that back)" if os.path.lexists(
            stray / _REPLACED) else ""
        _log.warning("%s is the temporary of %s that a killed run left (SIGKILL, power) or a "
                     "run writing it now is using%s; it is kept: delete it if no run is",
                     stray, out, aside)


def stray_temporaries(final: str | os.PathLike[str]) -> list[Path]:
    """The temporaries of :func:`atomic_path` beside ``final`` (``.NAME.<12 hex>.tmp``
    directories): a run writing it killed where it could not remove its own, or a run
    writing it now."""
    final = Path(final)
    parent = final.parent if str(final.parent) else Path(".")
    found = []
    with contextlib.suppress(OSError):
        for entry in os.scandir(parent):
            middle = entry.name[len(final.name) + 2:-len(".tmp")]
            if (entry.name.startswith(f".{final.name}.") and entry.name.endswith(".tmp")
                    and len(middle) == 12 and all(c in "0123456789abcdef" for c in middle)
                    and entry.is_dir(follow_symlinks=False)):
                found.append(parent / entry.name)
    return sorted(found)


def _check_output(path: str | os.PathLike[str], kind: OutputKind,
                  inputs: Iterable[str | os.PathLike[str]], force: bool, option: str) -> Path:
    out = _check_output_path(path, kind, inputs, force, option)
    # Where the output will be made: its directory (the nearest that exists), or, for a
    # resumable directory output that exists, that directory. Tried for real (a file made
    # and removed): access() says yes to root, and on a read-only mount.
    where = out.parent if str(out.parent) else Path(".")
    if kind.resumable and out.is_dir() and not out.is_symlink():
        where = out
    while not os.path.lexists(where) and where != where.parent:
        where = where.parent
    problem = _new_file_problem(where)
    if problem is not None:
        raise OutputError(f"{option} {os.fspath(path)}: no file can be made in {where}: "
                          f"{problem}")
    return out


def _new_file_problem(directory: Path) -> str | None:
    """Why no new file can be made in ``directory`` (the system's words), or None."""
    for _ in range(100):
        probe = directory / f".asgp-probe.{os.urandom(6).hex()}"
        with signals_deferred():  # no signal between making it and removing it
            try:
                fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            except FileExistsError:
                continue
            except OSError as exc:
                return exc.strerror or str(exc)
            os.close(fd)
            with contextlib.suppress(OSError):
                os.unlink(probe)
        return None
    return None  # (a hundred names taken: the write itself will say what is wrong)


def _check_output_path(path: str | os.PathLike[str], kind: OutputKind,
                       inputs: Iterable[str | os.PathLike[str]], force: bool,
                       option: str) -> Path:
    raw = os.fspath(path)
    if not raw or "\0" in raw:
        raise OutputError(f"{option}: empty or invalid path {raw!r}")
    out = Path(raw)
    if out.name in ("", ".", ".."):
        raise OutputError(f"{option} {raw}: names a directory, not {kind.a_name}"
                          if kind.directory is not True
                          else f"{option} {raw}: give the {kind.name} a name of its own")
    if len(os.fsencode(out.name)) > MAX_OUTPUT_NAME_BYTES:
        # found only after the work, when the temporary could not be made
        raise OutputError(f"{option} {raw}: a name of {len(os.fsencode(out.name))} bytes; at "
                          f"most {MAX_OUTPUT_NAME_BYTES} (its temporary, .NAME.<12 hex>.tmp, "
                          "must fit a file name's 255)")
    here = _absolute(out)
    for item in inputs:
        there = _absolute(Path(item))
        if here == there:
            raise OutputError(f"{option} {raw} is the input {item}; refusing to overwrite it")
        if there in here.parents:
            raise OutputError(f"{option} {raw} is inside the input {item}")
        if here in there.parents:
            raise OutputError(f"{option} {raw} contains the input {item}")
    for parent in out.parents:
        if os.path.lexists(parent) and not parent.is_dir():
            raise OutputError(f"{option} {raw}: {parent} exists and is not a directory")
    if not os.path.lexists(out):
        return out
    if out.is_symlink():
        raise OutputError(f"{option} {raw} is a symbolic link; refusing to write through it")
    what = describe_kind(out)
    if kind.directory is not False and out.is_dir() and not any(out.iterdir()):
        return out
    if kind.directory is True and not out.is_dir():
        raise OutputError(f"{option} {raw} exists and is {what}, not {kind.a_name}")
    if kind.directory is False and not stat.S_ISREG(os.stat(out).st_mode):
        raise OutputError(f"{option} {raw} exists and is {what}, not {kind.a_name}")
    if not kind.same_kind(out):
        raise OutputError(f"{option} {raw} exists and is not {kind.a_name} ({what}); "
                          f"refusing to replace it, even with --force")
    if kind.resumable or force:
        return out
    raise OutputError(f"{option} {raw}: {kind.a_name} exists there; use --force to replace "
                      f"it")

