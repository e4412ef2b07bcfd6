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
