"""A local pool of reader processes: every core decodes HDF5, without Dask.

HDF5 decodes on one core per process (h5py serialises its calls, so the block reader's
threads cannot decode two blocks at once), so a night of UVH5 files calibrated in one
process leaves the other cores idle. :class:`ProcessReaders` runs the per-file work (the
flagging's reads and the fit's partial sums,
:func:`autocal.pipeline.partials.compute_partial`) in a few worker processes of this
machine and hands the results back **in file order**, with the executor interface of
:class:`autocal.pipeline.scaleout.DaskExecutor` (``map_ordered``, ``describe``,
``worker_peak_rss``), so the pipeline adds them exactly as the in-process run does: the
solution and the flags are the same bit for bit.

:func:`reader_count` decides how many processes a run uses: ``readers=None`` (auto) takes
one per core (at most :data:`MAX_AUTO_READERS`) for UVH5 inputs of at least two files and
:data:`MIN_AUTO_BYTES` on disk, on a machine of at least :data:`MIN_AUTO_CPUS` cores (on two
cores one process with its threads was faster, measured); ``readers=1`` reads in the
calling process (as before the pool existed).

The workers are started with :data:`START_METHOD` (a fresh interpreter, never ``fork``:
the calling process may run threads, e.g. a service worker's heartbeat, and numba's
OpenMP layer is not fork-safe) and warmed up (imports, compiled kernels) while the calling
process scans the inputs and computes Tsky (``forkserver``: ~3 s for two processes where
``spawn`` took ~8 s, both on a loaded machine). Each runs the numeric kernels on
:data:`WORKER_THREADS` thread(s) and reads without read-ahead threads
(:data:`WORKER_READ_AHEAD`): the processes share the cores. A worker that dies (killed,
out of memory) is a :class:`autocal.pipeline.config.PipelineError` naming the file, never
a hang; a worker's own error (a corrupt file) is raised as it is.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from autocal.pipeline.config import PipelineError
from autocal.pipeline.scaleout import peak_rss_bytes

logger = logging.getLogger(__name__)

#: How worker processes are started: ``"forkserver"`` forks them from a fresh server
#: process that has imported the pipeline once (``"spawn"``: each imports it itself).
START_METHOD = "forkserver"
#: Threads of the numeric kernels (fit sums, flagging) in each worker process.
WORKER_THREADS = 1
#: Whether each worker's block reader runs ahead in background threads (HDF5 reads,
#: conversion, SHA-256) while the worker adds the previous block
#: (:data:`autocal.pipeline.partials.READ_AHEAD`). Off: with one process per core the
#: processes already keep every core busy, and the extra threads only compete for them
#: (2 processes, 4 night files: 67 s without against 90 s with, and 93 s with two kernel
#: threads; ``benchmarks/readers.py --steps variants``, a shared machine at load 7-8).
WORKER_READ_AHEAD = False
#: Largest number of processes of the automatic choice (``readers=None``).
MAX_AUTO_READERS = 8
#: Smallest input (bytes on disk) for which the automatic choice starts a pool: smaller
#: nights are calibrated in the calling process, where the pool's start (about a second
#: of CPU per process) would cost more than it saves.
MIN_AUTO_BYTES = 256 * 1024**2
#: Fewest usable CPUs for which the automatic choice starts a pool. One calibrating process
#: already keeps ~1.5 cores busy (HDF5 decoding in its read-ahead thread, the sums' kernels
#: in the other), and on two cores two single-threaded readers were slower: a quarter of
#: the HERA-size night (11 files, quiet machine, ``benchmarks/readers.py --flagging off``)
#: took 111 s in one process (160 s of CPU) and 123 s with two readers (187 s of CPU:
#: pickling, per-process set-up). With four or more cores the readers decode on cores the
#: single process leaves idle (not measured on this two-core machine).
MIN_AUTO_CPUS = 4
#: Modules the workers import before their first file.
WARM_MODULES = ("autocal.pipeline.partials", "autocal.pipeline.flag_partials")


def usable_cpus() -> int:
    """Return the CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        return os.cpu_count() or 1


def reader_count(
    readers: int | None,
    kind: str,
    paths: Sequence[str | os.PathLike[str]],
    cpus: int | None = None,
) -> int:
    """Return how many reader processes a run uses (1: read in the calling process).

    Parameters
    ----------
    readers
        Asked for: ``None`` (auto), ``1`` (in this process) or more (a pool of that many,
        when the input is read file by file).
    kind
        The input format (``"uvh5"``, ``"miriad"``, ``"edges"``): only UVH5 files are
        read file by file.
    paths
        The input files.
    cpus
        Usable CPUs (default :func:`usable_cpus`).

    Raises
    ------
    PipelineError
        For a count below 1.
    """
    if readers is not None and int(readers) < 1:
        raise PipelineError(f"the number of reader processes must be at least 1, got {readers}")
    if kind != "uvh5" or len(paths) < 2:
        if readers is not None and int(readers) > 1:
            logger.info("%s input of %d file(s) is read in this process", kind, len(paths))
        return 1
    if readers is not None:
        return min(int(readers), len(paths))
    cpus = usable_cpus() if cpus is None else cpus
    if cpus < MIN_AUTO_CPUS:
        return 1
    size = sum(Path(p).stat().st_size for p in paths)
    if size < MIN_AUTO_BYTES:
        logger.debug("%d bytes of input: read in this process", size)
        return 1
    return max(1, min(cpus, len(paths), MAX_AUTO_READERS))


def _start_worker(threads: int, read_ahead: bool) -> None:
    """Set a worker's thread counts and import what the first file needs."""
    value = str(int(threads))
    os.environ["AUTOCAL_FIT_THREADS"] = value  # autocal.fit.sums.default_threads
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = value
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(int(threads))
    except Exception:  # pragma: no cover - the BLAS keeps its default
        logger.debug("could not limit the BLAS threads of a reader process")
    import importlib

    for name in WARM_MODULES:
        importlib.import_module(name)
    from autocal.pipeline import partials

    partials.READ_AHEAD = bool(read_ahead)


def _warm() -> int:
    """Return the worker's process id (a first task: the worker is started)."""
    return os.getpid()


def _run(func: Callable[[Any, Any], Any], shared: Any, task: Any) -> tuple[Any, int, int]:
    """Run one task in a worker: its result, the worker's pid and its peak RSS so far."""
    return func(shared, task), os.getpid(), peak_rss_bytes()


class ProcessReaders:
    """Map the calibration's per-file work over local processes, results in task order.

    Parameters
    ----------
    processes
        Worker processes (at least 1).
    start_method
        ``multiprocessing`` start method (default :data:`START_METHOD`).
    threads
        Threads of each worker's numeric kernels (default :data:`WORKER_THREADS`).
    read_ahead
        Whether each worker's block reader runs ahead in background threads (default
        :data:`WORKER_READ_AHEAD`).
    """

    def __init__(
        self,
        processes: int,
        *,
        start_method: str | None = None,
        threads: int | None = None,
        read_ahead: bool | None = None,
    ) -> None:
        if int(processes) < 1:
            raise PipelineError(f"a pool needs at least 1 reader process, got {processes}")
        self.processes = int(processes)
        self.start_method = start_method or START_METHOD
        self.threads = WORKER_THREADS if threads is None else int(threads)
        self.read_ahead = WORKER_READ_AHEAD if read_ahead is None else bool(read_ahead)
        started = time.perf_counter()
        context = multiprocessing.get_context(self.start_method)
        if self.start_method == "forkserver":
            context.set_forkserver_preload(list(WARM_MODULES))
        self._pool = ProcessPoolExecutor(
            self.processes,
            mp_context=context,
            initializer=_start_worker,
            initargs=(self.threads, self.read_ahead),
        )
        self._peaks: dict[int, int] = {}
        # started now, so the workers import while the caller scans and computes Tsky
        self._warming = [self._pool.submit(_warm) for _ in range(self.processes)]
        self._started = started

    def describe(self) -> dict[str, Any]:
        """JSON-serialisable description (processes, start method, threads, start-up)."""
        return {
            "processes": self.processes,
            "start_method": self.start_method,
            "threads_per_process": self.threads,
            "read_ahead": self.read_ahead,
        }

    def map_ordered(
        self,
        func: Callable[[Any, Any], Any],
        shared: Any,
        tasks: Sequence[Any],
        window: int | None = None,
    ) -> Iterator[Any]:
        """Yield ``func(shared, task)`` for every task, in task order.

        At most ``window`` tasks (default: one per process and one more, so a process
        that finishes finds its next file waiting) are in flight ahead of the one being
        yielded, so neither the workers nor this process hold more than a few files'
        results. Closing the iterator early cancels what has not started.

        Raises
        ------
        PipelineError
            If a worker process died (killed, out of memory) while a task ran.
        """
        window = window or self.processes + 1
        pending: deque[tuple[int, Future]] = deque()
        queue = iter(enumerate(tasks))

        def submit_next() -> None:
            item = next(queue, None)
            if item is not None:
                index, task = item
                pending.append((index, self._submit(func, shared, task)))

        try:
            for _ in range(window):
                submit_next()
            while pending:
                index, future = pending.popleft()
                result = self._result(future, tasks[index])
                submit_next()
                yield result
        finally:
            for _, future in pending:
                future.cancel()

    def _submit(self, func: Callable[[Any, Any], Any], shared: Any, task: Any) -> Future:
        """Submit one task; a pool already broken is a :class:`PipelineError`."""
        try:
            return self._pool.submit(_run, func, shared, task)
        except BrokenProcessPool as err:
            raise self._died(task, err) from None

    def _result(self, future: Future, task: Any) -> Any:
        """Return a task's result, recording its worker's peak memory."""
        try:
            result, pid, peak = future.result()
        except BrokenProcessPool as err:
            raise self._died(task, err) from None
        self._peaks[pid] = max(self._peaks.get(pid, 0), peak)
        return result

    def _died(self, task: Any, err: BaseException) -> PipelineError:
        """Return the error for a worker process that died while ``task`` was in flight."""
        codes = sorted({p.exitcode for p in self._processes()} - {None, 0})
        what = getattr(task, "file", None)
        name = getattr(what, "path", what)
        return PipelineError(
            f"a reader process ended unexpectedly while reading {name or 'a file'}"
            + (f" (exit code {', '.join(map(str, codes))})" if codes else "")
            + f": {err or 'killed'}; was it out of memory? Run again with fewer reader "
            "processes (--readers 1 reads in one process)"
        )

    def _processes(self) -> list[Any]:
        """Return the pool's worker processes (``multiprocessing.Process``; none once broken).

        ``ProcessPoolExecutor`` keeps them in a private attribute: read defensively.
        """
        processes = getattr(self._pool, "_processes", None) or {}
        return list(processes.values())

    def worker_peak_rss(self) -> dict[str, int]:
        """Peak resident memory of each worker process so far (bytes, by pid)."""
        return {str(pid): peak for pid, peak in sorted(self._peaks.items())}

    def startup_seconds(self) -> float:
        """Wait for every worker to have started; return the seconds since the pool was made."""
        for future in self._warming:
            try:
                future.result()
            except BrokenProcessPool as err:
                raise self._died(None, err) from None
        return time.perf_counter() - self._started

    def close(self, *, abort: bool = False) -> None:
        """Stop the workers: after their tasks, or at once (``abort``: after an error)."""
        if abort:
            processes = self._processes()
            self._pool.shutdown(wait=False, cancel_futures=True)
            for process in processes:  # a file in flight need not be finished
                if process.is_alive():
                    process.terminate()
            for process in processes:
                process.join(timeout=5)
        else:
            self._pool.shutdown(wait=True, cancel_futures=True)


@contextmanager
def process_readers(
    processes: int,
    *,
    start_method: str | None = None,
    threads: int | None = None,
    read_ahead: bool | None = None,
) -> Iterator[ProcessReaders]:
    """Start a pool of reader processes for one run; stop it on exit.

    The parameters are :class:`ProcessReaders`'s.

    Yields
    ------
    ProcessReaders
        The executor. On an error (or an interrupt) its workers are stopped at once.
    """
    pool = ProcessReaders(
        processes, start_method=start_method, threads=threads, read_ahead=read_ahead
    )
    logger.info(
        "reading the files in %d processes (%s, %d thread(s) each)",
        pool.processes,
        pool.start_method,
        pool.threads,
    )
    try:
        yield pool
    except BaseException:
        pool.close(abort=True)
        raise
    pool.close()
