"""Running a compiled loop over a range of items on a pool of Python threads.

The compiled kernels (:mod:`autocal.fit.solve_kernel`, :mod:`autocal.fit.jackknife_kernel`,
:mod:`autocal.pipeline.rfi_kernel`) release the GIL (``nogil=True``) and take the range of
items to do, so threads run them side by side. They are not numba ``parallel=True``
kernels: numba's OpenMP layer is not fork-safe (a process that forks after using it, e.g.
a ``multiprocessing`` pool, aborts), and its thread count would ignore
``OMP_NUM_THREADS`` / ``AUTOCAL_FIT_THREADS``, which Dask workers set
(:func:`autocal.fit.sums.default_threads`).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

from autocal.fit.sums import default_threads

#: Ranges per thread: a few, so that uneven ranges still share out evenly.
RANGES_PER_THREAD = 4

_worker = threading.local()  # ``busy`` while a thread runs a range of in_threads


def in_threads(run: Callable[[int, int], None], n: int, threads: int | None = None) -> None:
    """Call ``run(lo, hi)`` over ``[0, n)`` in ranges, on ``threads`` threads.

    Parameters
    ----------
    run
        Does items ``lo`` to ``hi - 1`` (a ``nogil`` compiled loop).
    n
        Number of items.
    threads
        Threads (default :func:`~autocal.fit.sums.default_threads`). Called from a range
        of an outer call, ``run`` is called at once for all items in the calling thread.
    """
    nthreads = default_threads() if threads is None else max(1, int(threads))
    if n <= 0:
        return
    if nthreads == 1 or getattr(_worker, "busy", False):
        run(0, n)  # inside a range of an outer call: its threads already fill the cores
        return
    nranges = min(n, nthreads * RANGES_PER_THREAD)
    edges = [n * i // nranges for i in range(nranges + 1)]

    def one(i: int) -> None:
        _worker.busy = True
        try:
            run(edges[i], edges[i + 1])
        finally:
            _worker.busy = False

    with ThreadPoolExecutor(min(nthreads, nranges)) as pool:
        list(pool.map(one, range(nranges)))
