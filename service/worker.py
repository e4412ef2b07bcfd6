"""The job worker: claim queued jobs from the store and run them.

One :class:`Worker` runs one job at a time; run several worker processes (on one machine
or many, sharing a PostgreSQL store) for parallelism. A job's life in the worker:

1. :meth:`JobStore.claim` atomically moves the oldest queued job to ``running`` and makes
   this worker and the job's attempt number its owner.
2. A heartbeat thread calls :meth:`JobStore.heartbeat` every ``settings.heartbeat_s`` with
   the latest progress. When the store answers ``False`` (cancellation requested, or the
   job was re-queued because this worker was presumed dead) the job's ``should_stop``
   flag is raised and the pipeline stops at its next checkpoint.
3. The job's kind (:data:`KNOWN_KINDS`) picks what runs: ``calibrate`` ->
   :func:`autocal.calibrate` (:func:`autocal.pipeline.calibrate.calibrate`), ``diagnose`` ->
   :func:`autocal.diagnosis.run.run_diagnosis`. It writes the products into
   ``settings.products_dir / job_id / "attempt-N"`` (all or nothing); progress lines and
   warnings go to the job's log.
4. The job is closed by :meth:`JobStore.finish` (accepted only from its owner): succeeded
   with the summary (the run's ``summary.json``), product paths and provenance, and the
   message ``done`` (``done, but <flagged> of <total> channels flagged (mostly flagged):
   see quality`` for a solution that is fully or mostly flagged: :func:`done_message`);
   cancelled; or failed with a one-line reason (``"ExceptionType: message"``; the
   traceback goes to the worker's own log).

A worker asked to shut down (:meth:`Worker.request_stop`, e.g. on SIGTERM or SIGINT)
stops claiming and hands its running job back at once (:meth:`JobStore.release`: queued
again, owner cleared, the attempt not counted against ``max_attempts``), then aborts the
job at its next checkpoint; any later result of that attempt is refused. Graceful
restarts therefore never fail a healthy job. A worker that dies (kill -9, power cut)
stops beating; :meth:`JobStore.recover_stale`, called periodically by every worker,
re-queues its job (or fails it after ``max_attempts``) and fails any attempt running
longer than ``AUTOCAL_JOB_TIMEOUT_S`` even if it still beats. A job is therefore never
lost and, because ``finish`` checks owner and attempt, never completed twice.

Before a job reads its inputs, :func:`autocal.service.input_check.check_inputs`
re-resolves them under the data roots and compares them with the fingerprints recorded
at submission. The janitor (:func:`autocal.service.janitor.sweep`) runs at start-up and
every ``AUTOCAL_JANITOR_INTERVAL_S``.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import socket
import threading
import time
import uuid
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from autocal.service.history import record_job_safely
from autocal.service.input_check import InputChangedError, check_inputs
from autocal.service.janitor import sweep
from autocal.service.settings import Settings, get_settings
from autocal.service.store import JobState, JobStore

logger = logging.getLogger(__name__)

#: Job kinds this worker knows how to run.
KNOWN_KINDS = ("calibrate", "diagnose")


def default_worker_id() -> str:
    """Return a worker name unique across hosts and processes (``host:pid:random``)."""
    return f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:6]}"


def jsonable(value: Any) -> Any:
    """Return ``value`` as plain JSON data (strict JSON: no NaN or infinity).

    NumPy scalars and arrays become Python numbers and lists, non-finite floats become
    ``None`` (PostgreSQL's ``json`` type rejects ``NaN``), paths and other objects become
    strings.

    Parameters
    ----------
    value
        Any nesting of mappings, sequences and scalars.

    Returns
    -------
    Any
        The converted value.
    """
    if value is None or isinstance(value, bool | int | str):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Mapping):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple | set):
        return [jsonable(v) for v in value]
    if hasattr(value, "tolist"):  # numpy scalars and arrays
        return jsonable(value.tolist())
    if isinstance(value, Path):
        return str(value)
    return str(value)


def describe_error(err: BaseException) -> str:
    """Return a one-line reason for a failed job (``"Type: message"``, no traceback).

    Parameters
    ----------
    err
        The exception.

    Returns
    -------
    str
        The reason, at most 2000 characters.
    """
    from pydantic import ValidationError

    if isinstance(err, ValidationError):
        problems = "; ".join(
            f"{'.'.join(str(x) for x in e['loc']) or 'config'}: {e['msg']}" for e in err.errors()
        )
        text = f"invalid job configuration: {problems}"
    else:
        text = " ".join(str(err).split()) or repr(err)
    return f"{type(err).__name__}: {text}"[:2000]


def done_message(summary: Mapping[str, Any]) -> str:
    """Return a succeeded job's message: ``done``, or what makes its result no calibration.

    A calibration whose solution is fully or mostly flagged (its ``quality`` block, judged by
    :func:`autocal.pipeline.quality.flagged_verdict`, the decision behind ``autocal
    calibrate``'s exit status 3) is ``done, but <flagged> of <total> channels flagged
    (mostly flagged): see quality``.

    Parameters
    ----------
    summary
        The run's summary (``summary.json``).

    Returns
    -------
    str
        The message.
    """
    if not summary.get("quality"):  # a diagnosis: nothing is judged
        return "done"
    # the science stack, loaded by the calibration that wrote the summary
    from autocal.pipeline.quality import flagged_verdict

    verdict = flagged_verdict(summary["quality"])
    return "done" if verdict is None else f"done, but {verdict}: see quality"


class _JobLogHandler(logging.Handler):
    """Copy warnings logged by the job's thread into the job's log."""

    def __init__(self, store: JobStore, job_id: str, thread_id: int) -> None:
        super().__init__(level=logging.WARNING)
        self.store = store
        self.job_id = job_id
        self.thread_id = thread_id

    def emit(self, record: logging.LogRecord) -> None:
        if record.thread != self.thread_id:
            return
        with contextlib.suppress(Exception):  # never let logging break the job
            self.store.append_log(
                self.job_id, f"{record.levelname} {record.name}: {record.getMessage()}"
            )


class _Run:
    """The state of one running job shared by the job thread and its heartbeat thread."""

    def __init__(self, worker: Worker, job: dict[str, Any]) -> None:
        self.worker = worker
        self.store = worker.store
        self.job_id: str = job["id"]
        self.attempt: int = int(job["attempts"])
        self.progress_value = 0.0
        self.message = "claimed"
        self.stop_flag = threading.Event()  # the store said stop (cancel / lost ownership)
        self.released = False  # handed back to the queue by a shutdown
        self.release_lock = threading.Lock()
        self.done = threading.Event()
        self.lock = threading.Lock()
        self.thread = threading.Thread(
            target=self._beat_loop, name=f"heartbeat-{self.job_id[:8]}", daemon=True
        )

    # called by the pipeline (job thread) -------------------------------------------------
    def progress(self, fraction: float, message: str) -> None:
        """Record progress; it is sent with the next heartbeat."""
        with self.lock:
            self.progress_value = float(fraction)
            self.message = message
        self.log(f"{100 * fraction:3.0f}% {message}")

    def should_stop(self) -> bool:
        """Whether the job must stop (cancelled, ownership lost, or worker shutting down)."""
        return self.stop_flag.is_set() or self.worker.stopping

    def log(self, line: str) -> None:
        """Append a line to the job's log (errors are logged, not raised)."""
        try:
            self.store.append_log(self.job_id, line)
        except Exception as err:
            logger.warning("job %s: could not append to its log: %s", self.job_id, err)

    # heartbeat thread --------------------------------------------------------------------
    def start(self) -> None:
        """Start the heartbeat thread."""
        self.thread.start()

    def stop(self) -> None:
        """Stop the heartbeat thread and wait for it."""
        self.done.set()
        self.thread.join()

    def _beat_loop(self) -> None:
        interval = self.worker.settings.heartbeat_s
        while not self.done.wait(interval):
            self.beat()
            # this job is alive (its heartbeat thread is here) even if the last beat was
            # late: only other workers' jobs can be stale
            self.worker.maybe_recover(alive=(self.job_id, self.attempt))

    def beat(self) -> bool:
        """Send one heartbeat; raise the stop flag when the store says stop."""
        with self.lock:
            fraction, message = self.progress_value, self.message
        try:
            keep_going = self.store.heartbeat(
                self.job_id, self.worker.worker_id, self.attempt, progress=fraction, message=message
            )
        except Exception as err:  # database briefly unavailable: try again next beat
            logger.warning("job %s: heartbeat failed: %s", self.job_id, err)
            return True
        if not keep_going and not self.stop_flag.is_set():
            logger.info("job %s: the store asks this worker to stop it", self.job_id)
            self.stop_flag.set()
        return keep_going


class Worker:
    """Claims jobs from a :class:`JobStore` and runs them, one at a time.

    Parameters
    ----------
    store
        The job store (default: the one named by ``settings``).
    settings
        Service settings (default: :func:`get_settings`); uses ``products_dir``,
        ``heartbeat_s``, ``stale_after_s`` and ``dask_scheduler``.
    worker_id
        This worker's name in the store (default: ``host:pid:random``).
    """

    def __init__(
        self,
        store: JobStore | None = None,
        settings: Settings | None = None,
        worker_id: str | None = None,
    ) -> None:
        self.settings = settings or get_settings()
        self.store = store or JobStore(self.settings.resolved_database_url())
        self.worker_id = worker_id or default_worker_id()
        self.stop_event = threading.Event()
        self.current: _Run | None = None
        self._recover_lock = threading.Lock()
        self._last_recover = -math.inf
        self._last_sweep = -math.inf

    # control -----------------------------------------------------------------------------
    @property
    def stopping(self) -> bool:
        """Whether a shutdown was requested."""
        return self.stop_event.is_set()

    def request_stop(self) -> None:
        """Stop claiming jobs, hand the current job back and abort it at its next checkpoint.

        The job is re-queued at once (:meth:`JobStore.release`; the attempt is not
        counted). Never call it from a signal handler: it takes locks and queries the
        store, which the interrupted thread may hold (:func:`autocal.service.shutdown.
        stop_on_signals` calls it from a watcher thread).
        """
        self.stop_event.set()
        run = self.current
        if run is not None:
            self.release(run)

    def release(self, run: _Run) -> bool:
        """Hand ``run``'s job back to the queue (once; later calls wait for it, then return).

        Called by the stopping thread and by the job thread at its checkpoint: the lock
        makes the job thread (and so the process's exit) wait for a release under way.
        """
        with run.release_lock:
            if run.released:
                return False
            try:
                done = self.store.release(
                    run.job_id, self.worker_id, run.attempt, f"worker {self.worker_id} shut down"
                )
            except Exception as err:  # the store is unreachable: stale recovery will do it
                logger.warning("job %s: could not hand it back (%s)", run.job_id, err)
                return False
            run.released = True
        if done:
            logger.warning(
                "job %s attempt %d: handed back to the queue (worker %s shutting down)",
                run.job_id,
                run.attempt,
                self.worker_id,
            )
        return done

    @property
    def recover_interval_s(self) -> float:
        """Seconds between two stale-job recoveries by this worker."""
        return max(min(self.settings.stale_after_s / 2, 30.0), 0.2)

    def maybe_recover(
        self, force: bool = False, alive: tuple[str, int] | None = None
    ) -> list[dict[str, Any]]:
        """Re-queue or fail stale jobs, at most once per :attr:`recover_interval_s`.

        ``alive``: ``(job id, attempt)`` of the job this worker is running, never taken for
        stale (:meth:`JobStore.recover_stale`).
        """
        with self._recover_lock:
            now = time.monotonic()
            if not force and now - self._last_recover < self.recover_interval_s:
                return []
            self._last_recover = now
        try:
            changed = self.store.recover_stale(
                self.settings.stale_after_s, self.settings.job_timeout_s, alive=alive
            )
        except Exception as err:
            logger.warning("stale-job recovery failed: %s", err)
            return []
        for job in changed:
            logger.warning("recovered stale job %s -> %s", job["id"], job["state"])
        return changed

    def maybe_sweep(self, force: bool = False) -> None:
        """Run the janitor, at most once per ``settings.janitor_interval_s``."""
        now = time.monotonic()
        if not force and now - self._last_sweep < self.settings.janitor_interval_s:
            return
        self._last_sweep = now
        try:
            sweep(self.store, self.settings)
        except Exception as err:  # never let cleaning stop the worker
            logger.warning("janitor failed: %s", err)

    # the loop ----------------------------------------------------------------------------
    def run_once(self) -> bool:
        """Claim one queued job and run it to its end.

        Returns
        -------
        bool
            ``False`` when the queue was empty (or the worker is stopping).
        """
        if self.stopping:
            return False
        job = self.store.claim(self.worker_id)
        if job is None:
            return False
        self.run_job(job)
        return True

    def run_forever(self, poll_s: float = 2.0, stop_event: threading.Event | None = None) -> None:
        """Run jobs until ``stop_event`` (or :meth:`request_stop`) is set.

        Parameters
        ----------
        poll_s
            Seconds to wait before looking again when the queue is empty.
        stop_event
            Optional event that stops the loop (also aborts the current job at its next
            checkpoint; it is handed back to the queue).
        """
        if stop_event is not None:
            self.stop_event = stop_event
        logger.info(
            "worker %s started (store %s, products in %s)",
            self.worker_id,
            self.store.engine.url.render_as_string(hide_password=True),
            self.settings.products_dir,
        )
        while not self.stopping:
            self.maybe_recover()
            self.maybe_sweep()
            try:
                ran = self.run_once()
            except Exception as err:  # the store is unreachable: wait and retry
                logger.error("worker %s: cannot claim a job: %s", self.worker_id, err)
                ran = False
            if not ran:
                self.stop_event.wait(poll_s)
        logger.info("worker %s stopped", self.worker_id)

    # one job -----------------------------------------------------------------------------
    def run_job(self, job: dict[str, Any]) -> str | None:
        """Run a claimed job and close it in the store.

        Parameters
        ----------
        job
            The record returned by :meth:`JobStore.claim`.

        Returns
        -------
        str or None
            The final state written, or ``None`` when the job was left for recovery
            (shutdown) or this worker no longer owned it.
        """
        run = _Run(self, job)
        self.current = run
        handler = _JobLogHandler(self.store, run.job_id, threading.get_ident())
        logging.getLogger().addHandler(handler)
        run.start()
        started = time.perf_counter()
        logger.info("job %s (%s) attempt %d: started", run.job_id, job["kind"], run.attempt)
        run.log(f"attempt {run.attempt} started by worker {self.worker_id}")
        try:
            state = self._execute(run, job)
            if state == JobState.succeeded.value:  # the per-antenna history across nights
                record_job_safely(self.store, run.job_id)
            return state
        finally:
            run.stop()
            logging.getLogger().removeHandler(handler)
            self.current = None
            logger.info(
                "job %s attempt %d: ended after %.1f s",
                run.job_id,
                run.attempt,
                time.perf_counter() - started,
            )

    def _finish(self, run: _Run, state: JobState, **fields: Any) -> str | None:
        if state != JobState.succeeded:
            run.log(f"{state.value}: {fields.get('error') or ''}".rstrip(": "))
        else:
            note = fields.get("message")
            run.log("succeeded" if note in (None, "done") else f"succeeded: {note}")
        try:
            ok = self.store.finish(run.job_id, self.worker_id, run.attempt, state, **fields)
        except Exception:
            logger.exception("job %s: could not record its end (%s)", run.job_id, state.value)
            return None
        if not ok:
            logger.warning(
                "job %s attempt %d: no longer owned by %s; %s not recorded",
                run.job_id,
                run.attempt,
                self.worker_id,
                state.value,
            )
            return None
        return state.value

    def _run_kind(
        self, kind: str, config: dict[str, Any], out: Path, run: _Run
    ) -> tuple[dict[str, Any], dict[str, str]]:
        """Run a job of ``kind`` into ``out``; return its summary and product paths."""
        if kind == "diagnose":
            # the science stack is imported by the job that needs it: a worker that only
            # claims jobs, or the API importing this module, stays light
            from autocal.diagnosis.run import DiagnoseConfig, read_summary, run_diagnosis

            folder = run_diagnosis(
                DiagnoseConfig(**config), out, progress=run.progress, should_stop=run.should_stop
            )
            summary = read_summary(folder)
            return summary, dict(summary.get("products") or {})
        from autocal.pipeline.calibrate import calibrate, read_summary
        from autocal.pipeline.config import CalibrationConfig

        calibrate(  # autocal.calibrate: the same function as the CLI's and a notebook's
            CalibrationConfig(**config),
            out=out,
            progress=run.progress,
            should_stop=run.should_stop,
            dask_scheduler=self.settings.dask_scheduler or None,
            readers=self.settings.readers or None,
        )
        summary = read_summary(out)
        return summary, dict(summary["products"])

    def _execute(self, run: _Run, job: dict[str, Any]) -> str | None:
        if job["kind"] not in KNOWN_KINDS:
            return self._finish(
                run,
                JobState.failed,
                error=f"unknown job kind {job['kind']!r} (this worker runs: "
                f"{', '.join(KNOWN_KINDS)})",
            )
        if self.stopping:  # stopped between the claim and now
            return self._stopped(run, RuntimeError("worker shutting down"))
        try:  # the inputs are still where (and what) they were at submission
            check_inputs(job["config"] or {}, job.get("input_fingerprints"), self.settings)
        except InputChangedError as err:
            return self._finish(run, JobState.failed, error=describe_error(err))
        out = self.settings.products_dir / run.job_id / f"attempt-{run.attempt}"
        try:
            run_summary, products = self._run_kind(job["kind"], job["config"] or {}, out, run)
        except Exception as err:
            if run.should_stop():
                return self._stopped(run, err)
            logger.error(
                "job %s attempt %d failed", run.job_id, run.attempt, exc_info=True
            )  # the traceback stays in the worker's log
            return self._finish(run, JobState.failed, error=describe_error(err))
        provenance = dict(run_summary.get("provenance") or {})
        provenance["service"] = {
            "job_id": run.job_id,
            "attempt": run.attempt,
            "worker": self.worker_id,
            "products_dir": str(out),
        }
        if self.settings.dask_scheduler and job["kind"] == "calibrate":
            # the per-file normal sums ran on the Dask cluster (autocal.pipeline.scaleout)
            provenance["dask_scheduler"] = self.settings.dask_scheduler
        summary = dict(run_summary)
        summary["provenance"] = provenance
        message = done_message(summary)
        if message != "done":  # the worker's log and, from the job's thread, the job's log
            logger.warning(
                "job %s: %s (%s)", run.job_id, message, summary["quality"].get("message")
            )
        return self._finish(
            run,
            JobState.succeeded,
            result=jsonable(summary),
            products=jsonable(products),
            provenance=jsonable(provenance),
            message=message,
        )

    def _stopped(self, run: _Run, err: BaseException) -> str | None:
        """Close (or hand back) a job stopped at a checkpoint: cancelled, lost, or shutdown."""
        if run.stop_flag.is_set() and not self.stopping:
            # Either cancellation was requested (we still own it: record cancelled) or
            # the job was re-queued/failed behind our back (finish refuses; fine).
            logger.info("job %s attempt %d: stopped (%s)", run.job_id, run.attempt, err)
            return self._finish(run, JobState.cancelled, error="cancelled on request")
        self.release(run)  # usually done at once by request_stop; idempotent
        run.log(f"worker {self.worker_id} shut down during attempt {run.attempt}")
        return None
