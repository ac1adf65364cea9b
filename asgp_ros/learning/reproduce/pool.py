"""Worker processes for the jobs of a reproduction, sharing one read-only context.

:func:`pool_map` runs ``fn(context, item)`` for each item on forked workers; ``fn`` and
``context`` reach each worker once, through the pool's initializer, so that the resampled
series are shared with the workers, not copied per job. The module keeps no run state: a
worker's job is set once, in the worker.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

from threadpoolctl import threadpool_limits

from asgp_ros.common.fileio import interruptible_imap, worker_pool

C = TypeVar("C")
T = TypeVar("T")
R = TypeVar("R")


@dataclass(frozen=True)
class _Worker:
    """What one pool worker runs: ``fn(context, item)`` for each item it is sent."""

    fn: Callable[[Any, Any], Any]
    context: Any
    one_thread: bool


#: The worker's job, set once in each pool worker by :func:`_start_worker` (never in the
#: parent process, never changed afterwards).
_WORKER: _Worker | None = None


def _start_worker(worker: _Worker) -> None:
    """Pool initializer: BLAS/OpenMP limits, the worker's job."""
    global _WORKER
    if worker.one_thread:
        # one BLAS/OpenMP thread per worker, for the worker's life: the workers share
        # the cores
        threadpool_limits(1)
    _WORKER = worker


def _run_in_worker(item: Any) -> Any:
    if _WORKER is None:  # pragma: no cover - only pool workers call this
        raise RuntimeError("not a pool worker of pool_map")
    return _WORKER.fn(_WORKER.context, item)


def pool_map(fn: Callable[[C, T], R], context: C, items: Sequence[T], jobs: int, *,
             one_thread: bool = False) -> list[R]:
    """``[fn(context, x) for x in items]``, on up to ``jobs`` worker processes.

    The pool forks; ``fn`` and ``context`` reach each worker once, through the pool's
    initializer; the items and results cross the pool's pipes. A signal or an error stops
    the workers at once. ``one_thread``: limit each worker to one BLAS/OpenMP thread.
    """
    if jobs <= 1 or len(items) <= 1:
        return [fn(context, x) for x in items]

    # Leaving the block on an error or a signal stops the workers at once.
    with worker_pool(min(jobs, len(items)), initializer=_start_worker,
                     initargs=(_Worker(fn, context, one_thread),)) as pool:
        return list(interruptible_imap(pool, _run_in_worker, items))
