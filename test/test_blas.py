"""asgp_ros.core.blas: BLAS on one thread around an update, and as it was after."""

from __future__ import annotations

import numpy as np
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from asgp_ros.core import blas


def _blas_threads() -> list[int]:
    return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]


def test_one_thread_inside_and_each_library_restored_after():
    if not _blas_threads():
        pytest.skip("no BLAS library that threadpoolctl can see")
    with threadpool_limits(limits=2, user_api="blas"):
        assert set(_blas_threads()) == {2}
        with blas.single_thread():
            assert set(_blas_threads()) == {1}
            a = np.random.default_rng(0).standard_normal((50, 50))
            a @ a.T  # BLAS runs
        assert set(_blas_threads()) == {2}
        with pytest.raises(RuntimeError), blas.single_thread():  # restored on an error too
            raise RuntimeError("boom")
        assert set(_blas_threads()) == {2}


class _Lib:
    def __init__(self, n):
        self.n, self.calls = n, []

    @property
    def num_threads(self):
        return self.n

    def set_num_threads(self, n):
        self.calls.append(n)
        self.n = n


def test_libraries_already_on_one_thread_or_silent_about_it_are_left_alone(monkeypatch):
    """No switch when BLAS already runs on one thread (the nodes limit the process), and a
    library that cannot report its count is not touched: it could not be restored."""
    one, unknown, four = _Lib(1), _Lib(None), _Lib(4)
    monkeypatch.setattr(blas, "_LIBS", [one, unknown, four])
    with blas.single_thread():
        assert (one.n, unknown.n, four.n) == (1, None, 1)
    assert one.calls == [] and unknown.calls == [] and four.calls == [1, 4]


class _Failing(_Lib):
    def set_num_threads(self, n):
        raise OSError("cannot set")


def test_a_library_that_cannot_be_set_leaves_the_others_restored(monkeypatch):
    first, bad = _Lib(4), _Failing(2)
    monkeypatch.setattr(blas, "_LIBS", [first, bad])
    with pytest.raises(OSError), blas.single_thread():
        pass
    assert first.n == 4 and first.calls == [1, 4]
