"""Single-threaded BLAS for the small matrix products of one update or one prediction.

OpenBLAS threads the products and triangular solves of matrices of a few dozen to a few
hundred rows; on a loaded 2-core machine a threaded call then took 2.5x to 100x longer than
one thread (an online update 10 - 30 ms instead of a fraction of one).  The nodes limit
BLAS to one thread for the whole process; a library call limits it around its own work
only, and skips the switch when BLAS already runs on one thread (a check of about 4-7 us,
and 10 us with the switch, against about 17 us for threadpoolctl's ``limit`` context,
which reads every library's state and sets it twice).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

from threadpoolctl import ThreadpoolController

__all__ = ["single_thread"]

_LIBS: list[object] | None = None


def _blas_libs() -> list[object]:
    """threadpoolctl's controllers of the BLAS libraries loaded when first asked (numpy's
    and scipy's OpenBLAS may be two)."""
    global _LIBS
    if _LIBS is None:
        _LIBS = list(ThreadpoolController().select(user_api="blas").lib_controllers)
    return _LIBS


@contextlib.contextmanager
def single_thread() -> Iterator[None]:
    """Run the block with every BLAS library on one thread, then restore what each had.

    Not thread-safe (BLAS's thread count is global to the process), as threadpoolctl's
    own limits are not.
    """
    libs = _blas_libs()
    before = [lib.num_threads for lib in libs]  # type: ignore[attr-defined]
    # a library that cannot report its count (None) is left as it is: it could not be
    # restored
    changed = [(lib, n) for lib, n in zip(libs, before, strict=True)
               if isinstance(n, int) and n != 1]
    done: list[tuple[object, int]] = []
    try:
        for lib, n in changed:  # inside: a library that fails leaves the others restored
            lib.set_num_threads(1)  # type: ignore[attr-defined]
            done.append((lib, n))
        yield
    finally:
        for lib, n in done:
            lib.set_num_threads(n)  # type: ignore[attr-defined]
