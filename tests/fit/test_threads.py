"""Compiled loops on Python threads (autocal.fit.threads), and safe across fork().

The kernels of the solver, the expected jackknife and the RFI flagger run on a thread pool
rather than numba's OpenMP layer, which aborts a process that forks after using it.
"""

from __future__ import annotations

import multiprocessing

import numpy as np
import pytest

from autocal.fit.threads import in_threads
from autocal.pipeline.rfi import frequency_flags


@pytest.mark.parametrize(("n", "threads"), [(0, 2), (1, 2), (7, 1), (7, 2), (1000, 3)])
def test_every_item_is_done_once(n: int, threads: int) -> None:
    done = np.zeros(n, int)

    def run(lo: int, hi: int) -> None:
        done[lo:hi] += 1

    in_threads(run, n, threads)
    assert (done == 1).all()


def _flag_in_child() -> None:
    rng = np.random.default_rng(1)
    data = 1 + 1e-3 * rng.standard_normal((4, 2, 5, 64))
    frequency_flags(data, np.zeros(data.shape, bool), np.ones((4, 2, 64)))


def test_a_process_forked_after_the_kernels_can_run_them() -> None:
    _flag_in_child()  # the kernels have run (and started their threads) in this process
    child = multiprocessing.get_context("fork").Process(target=_flag_in_child)
    child.start()
    child.join(120)
    assert child.exitcode == 0


def test_a_call_inside_a_range_runs_inline_and_an_error_leaves_the_caller_unmarked() -> None:
    """Nested calls run in the calling worker (no second pool on the same cores); a range
    that raises reaches the caller, whose later calls still use a pool of threads."""
    import threading

    seen: list[set[str]] = []

    def inner(lo: int, hi: int) -> None:
        seen[-1].add(threading.current_thread().name)

    def outer(lo: int, hi: int) -> None:
        for _ in range(lo, hi):
            seen.append({threading.current_thread().name})
            in_threads(inner, 8, 2)

    in_threads(outer, 4, 2)
    assert len(seen) == 4 and all(len(names) == 1 for names in seen)  # inner: same thread

    def failing(lo: int, hi: int) -> None:
        raise RuntimeError("a range failed")

    with pytest.raises(RuntimeError, match="a range failed"):
        in_threads(failing, 4, 2)
    names: set[str] = set()

    def where(lo: int, hi: int) -> None:
        names.add(threading.current_thread().name)
        threading.Event().wait(0.01)

    in_threads(where, 8, 2)  # from the main thread (never marked): a pool of two
    assert threading.current_thread().name not in names and len(names) == 2
