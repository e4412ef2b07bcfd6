"""Scale-out of the calibration over a Dask cluster (dask.distributed).

The calibration's unit of work is one file's partial normal sums
(:func:`autocal.pipeline.partials.compute_partial`: the file read block by block, its blocks
added in order). :class:`DaskExecutor` maps these over the workers of a cluster and
hands the partials back **in file order**, so the pipeline adds them exactly as the
serial run does and the solution is the same bit for bit. At most a window of files is
in flight at once (two per worker by default), so neither the workers nor this process
hold more than a few files' partial sums, whatever the length of the night.

Where the cluster comes from:

- ``"local"``: a :class:`distributed.LocalCluster` of ``workers`` processes (one thread
  each) on this machine, started and stopped with the run;
- an address (``tcp://host:8786`` or ``host:8786``): an existing scheduler, e.g. started
  with ``dask scheduler`` and ``dask worker tcp://host:8786 --nthreads 1`` on each node.
  Workers need autocal installed (same version) and the input files at the same paths.

A scheduler that cannot be reached within :data:`CONNECT_TIMEOUT_S`, or that has no
workers within :data:`WORKER_TIMEOUT_S`, is a :class:`autocal.pipeline.config.PipelineError`
with what to do, never a hang.
"""

from __future__ import annotations

import logging
import os
import resource
import sys
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

from autocal.pipeline.config import PipelineError

logger = logging.getLogger(__name__)

#: The scheduler name that starts a local cluster.
LOCAL = "local"
#: Seconds to wait for a remote scheduler to answer.
CONNECT_TIMEOUT_S = 10.0
#: Seconds to wait for a scheduler to have at least one worker.
WORKER_TIMEOUT_S = 30.0
#: Files in flight per worker.
FILES_PER_WORKER = 2
#: Local clusters run their workers in processes (``False``: threads of this process).
LOCAL_PROCESSES = True
#: Environment variable Dask's nanny sets to 65536 in every worker it starts
#: (``distributed.nanny.pre-spawn-environ``). Setting it fixes glibc's mmap threshold at
#: 128 kB, so every array above that is mapped afresh and its pages faulted in again on
#: each allocation: a HERA-size night file took 10.5-10.7 s instead of 6.3-7.8 s per
#: worker here (two processes side by side, ``benchmarks/malloc_trim.py``). Local clusters
#: are started without it; workers of a remote cluster that have it are reported with the
#: fix.
MALLOC_TRIM_ENV = "MALLOC_TRIM_THRESHOLD_"


def peak_rss_bytes() -> int:
    """Peak resident memory of the calling process in bytes.

    Linux: ``VmHWM`` of ``/proc/self/status``, the high-water mark of this process's
    own address space (``ru_maxrss`` would also carry the RSS of the parent at the
    fork that started a worker process). Elsewhere ``ru_maxrss``.
    """
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    scale = 1 if sys.platform == "darwin" else 1024  # macOS reports bytes, Linux KiB
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * scale


def _address(scheduler: str) -> str:
    """Check a scheduler address and give it a protocol (``tcp://`` by default)."""
    text = scheduler.strip()
    if not text:
        raise PipelineError("the Dask scheduler address is empty: give HOST:PORT or 'local'")
    if "://" not in text:
        text = "tcp://" + text
    protocol, _, rest = text.partition("://")
    if protocol not in {"tcp", "tls", "inproc", "ws", "wss", "ucx"}:
        raise PipelineError(
            f"Dask scheduler address {scheduler!r} has an unknown protocol {protocol!r}: "
            "use tcp://HOST:PORT (or 'local')"
        )
    host, sep, port = rest.rpartition(":")
    if protocol != "inproc" and (not sep or not host or not port.isdigit()):
        raise PipelineError(
            f"Dask scheduler address {scheduler!r} is not HOST:PORT (e.g. tcp://10.0.0.5:8786); "
            "or use 'local' for a cluster on this machine"
        )
    return text


class DaskExecutor:
    """Map the calibration's per-file work over a Dask client, results in task order.

    Parameters
    ----------
    client
        A connected :class:`distributed.Client`.
    description
        What the cluster is (for the run's summary).
    """

    def __init__(self, client: Any, description: dict[str, Any]) -> None:
        self.client = client
        self._description = description

    @property
    def nworkers(self) -> int:
        """Number of workers the scheduler knows."""
        return len(self.client.scheduler_info().get("workers", {}))

    def describe(self) -> dict[str, Any]:
        """JSON-serialisable description (scheduler, workers, threads)."""
        return {**self._description, "workers": self.nworkers}

    def map_ordered(
        self,
        func: Callable[[Any, Any], Any],
        shared: Any,
        tasks: Sequence[Any],
        window: int | None = None,
    ) -> Iterator[Any]:
        """Yield ``func(shared, task)`` for every task, in task order.

        ``shared`` is sent to the workers once; at most ``window`` tasks (default
        :data:`FILES_PER_WORKER` per worker) are submitted ahead of the one being
        yielded. Closing the iterator early cancels what is still in flight.
        """
        client = self.client
        window = window or FILES_PER_WORKER * max(self.nworkers, 1)
        token = f"{os.getpid()}-{time.time_ns()}"
        [shared_future] = client.scatter([shared], broadcast=True, hash=False)
        pending: deque[Any] = deque()
        queue = iter(enumerate(tasks))

        def submit_next() -> None:
            item = next(queue, None)
            if item is None:
                return
            index, task = item
            [task_future] = client.scatter([task], hash=False)
            pending.append(
                client.submit(
                    func,
                    shared_future,
                    task_future,
                    key=f"autocal-file-{index}-{token}",
                    pure=False,
                )
            )

        try:
            for _ in range(window):
                submit_next()
            while pending:
                future = pending.popleft()
                result = future.result()
                future.release()
                submit_next()
                yield result
        finally:
            for future in pending:
                future.cancel()
            shared_future.release()

    def worker_peak_rss(self) -> dict[str, int]:
        """Peak resident memory of each worker process so far (bytes)."""
        try:
            return {str(k): int(v) for k, v in self.client.run(peak_rss_bytes).items()}
        except Exception as err:  # pragma: no cover - diagnostics only
            logger.warning("could not ask the workers for their memory use: %s", err)
            return {}


def _worker_malloc_env() -> str | None:
    """``MALLOC_TRIM_THRESHOLD_`` of the calling process (run on every worker)."""
    return os.environ.get(MALLOC_TRIM_ENV)


def _check_worker_malloc(client: Any, description: dict[str, Any]) -> None:
    """Record the workers' ``MALLOC_TRIM_THRESHOLD_`` and warn, with the fix, if set."""
    try:
        values = client.run(_worker_malloc_env)
    except Exception as err:  # pragma: no cover - diagnostics only
        logger.debug("could not ask the workers for their environment: %s", err)
        return
    if found := sorted({v for v in values.values() if v is not None}):
        description["worker_malloc_trim_threshold"] = found
        logger.warning(
            "%d of %d Dask workers run with %s=%s (the nanny's default), which makes "
            "glibc map and fault in every large array afresh (~1.3-1.7x slower calibration); "
            "start them without it: `MALLOC_TRIM_THRESHOLD_: null` under "
            "distributed.nanny.pre-spawn-environ in the workers' Dask config (e.g. "
            "~/.config/dask/autocal.yaml), or `dask worker --no-nanny`",
            sum(v is not None for v in values.values()),
            len(values),
            MALLOC_TRIM_ENV,
            ",".join(found),
        )


@contextmanager
def dask_client(
    scheduler: str,
    workers: int | None = None,
    *,
    connect_timeout: float | None = None,
    worker_timeout: float | None = None,
    processes: bool | None = None,
) -> Iterator[DaskExecutor]:
    """Connect to (or start) a Dask cluster for one run.

    Parameters
    ----------
    scheduler
        ``"local"`` or a scheduler address (``tcp://host:port`` or ``host:port``).
    workers
        Local cluster only: number of worker processes (default: the CPUs).
    connect_timeout
        Seconds to wait for a remote scheduler (default :data:`CONNECT_TIMEOUT_S`).
    worker_timeout
        Seconds to wait for a scheduler to have a worker (default
        :data:`WORKER_TIMEOUT_S`).
    processes
        Local cluster only: workers in processes or threads of this process (default
        :data:`LOCAL_PROCESSES`).

    Yields
    ------
    DaskExecutor
        The executor; the client (and a local cluster) are closed on exit.

    Raises
    ------
    PipelineError
        For a malformed address, an unreachable scheduler, a scheduler without workers,
        or a worker count below 1.
    """
    distributed = _distributed()
    if workers is not None and int(workers) < 1:
        raise PipelineError(f"the number of Dask workers must be at least 1, got {workers}")
    connect_timeout = CONNECT_TIMEOUT_S if connect_timeout is None else connect_timeout
    worker_timeout = WORKER_TIMEOUT_S if worker_timeout is None else worker_timeout
    cluster = None
    started = time.perf_counter()
    if scheduler.strip().lower() == LOCAL:
        cluster, client, description = _start_local(
            distributed, workers, processes, connect_timeout
        )
    else:
        client, description = _connect(distributed, scheduler, workers, connect_timeout)
    try:
        try:
            client.wait_for_workers(1, timeout=worker_timeout)
        except (OSError, TimeoutError) as err:
            raise PipelineError(
                f"the Dask scheduler at {description['address' if cluster else 'scheduler']} "
                f"has no workers after {worker_timeout:g} s ({err}); start some with "
                "`dask worker ADDRESS`"
            ) from None
        description["startup_s"] = round(time.perf_counter() - started, 3)
        _check_worker_malloc(client, description)
        yield DaskExecutor(client, description)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _distributed() -> Any:
    """Return the ``distributed`` module (imported here: only scale-out needs it)."""
    try:
        import distributed  # optional heavy dependency, used on the Dask path only
    except ImportError as err:  # pragma: no cover - a declared dependency
        raise PipelineError(
            "Dask scale-out needs the 'distributed' package: pip install distributed"
        ) from err
    return distributed


def _start_local(
    distributed: Any, workers: int | None, processes: bool | None, connect_timeout: float
) -> tuple[Any, Any, dict[str, Any]]:
    """Start a local cluster and connect to it: the cluster, the client, its description."""
    import dask  # optional heavy dependency, used on the Dask path only

    nworkers = int(workers or os.cpu_count() or 1)
    processes = LOCAL_PROCESSES if processes is None else processes
    logger.info("starting a local Dask cluster of %d worker(s)", nworkers)
    # None unsets the nanny's MALLOC_TRIM_THRESHOLD_ (see MALLOC_TRIM_ENV)
    with dask.config.set({f"distributed.nanny.pre-spawn-environ.{MALLOC_TRIM_ENV}": None}):
        cluster = distributed.LocalCluster(
            n_workers=nworkers,
            threads_per_worker=1,
            processes=processes,
            dashboard_address=None,
            silence_logs=logging.WARNING,
            **({"host": "127.0.0.1"} if processes else {}),
        )
    description: dict[str, Any] = {
        "scheduler": LOCAL,
        "address": cluster.scheduler_address,
        "processes": processes,
    }
    try:
        client = distributed.Client(cluster, timeout=connect_timeout)
    except BaseException:
        cluster.close()
        raise
    return cluster, client, description


def _connect(
    distributed: Any, scheduler: str, workers: int | None, connect_timeout: float
) -> tuple[Any, dict[str, Any]]:
    """Connect to a running scheduler: the client and its description."""
    address = _address(scheduler)
    if workers is not None:
        logger.info("--dask-workers applies to 'local' only; %s has its own workers", address)
    try:
        client = distributed.Client(address, timeout=connect_timeout)
    except (OSError, TimeoutError) as err:
        raise PipelineError(
            f"cannot reach the Dask scheduler at {address} within {connect_timeout:g} s "
            f"({type(err).__name__}: {err}). Start one (`dask scheduler`, then "
            f"`dask worker {address}` on each node), check the address and firewall, "
            "or use 'local'."
        ) from None
    return client, {"scheduler": address, "processes": True}
