"""The persistent job store (SQLAlchemy; SQLite by default, PostgreSQL by URL).

A job's life: ``queued -> running -> succeeded | failed | cancelled``. Workers claim
queued jobs with one atomic ``UPDATE ... WHERE state = 'queued' ... RETURNING`` statement
(PostgreSQL adds ``FOR UPDATE SKIP LOCKED`` so concurrent workers never block or collide;
SQLite serialises writers). A running job belongs to the worker that claimed it and to
its attempt number: heartbeats, progress and the final state are accepted only from that
owner, so a job re-queued after its worker was presumed dead can never be completed twice.
:meth:`JobStore.recover_stale` re-queues (or, after ``max_attempts``, fails) running jobs
whose heartbeat stopped.
"""

from __future__ import annotations

import logging
import math
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime, timedelta
from enum import StrEnum
from typing import Any

from sqlalchemy import (
    JSON,
    Boolean,
    DateTime,
    Float,
    Integer,
    String,
    Text,
    create_engine,
    event,
    func,
    select,
    update,
)
from sqlalchemy.engine import Engine
from sqlalchemy.exc import (
    ArgumentError,
    IntegrityError,
    NoSuchModuleError,
    OperationalError,
    ProgrammingError,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, Session, mapped_column, sessionmaker

from autocal.errors import AutocalError
from autocal.service.migrations import apply_migrations

logger = logging.getLogger(__name__)

#: Lines of log kept per job.
LOG_LINES = 200


class JobState(StrEnum):
    """Lifecycle states of a job."""

    queued = "queued"
    running = "running"
    succeeded = "succeeded"
    failed = "failed"
    cancelled = "cancelled"


FINAL_STATES = {JobState.succeeded.value, JobState.failed.value, JobState.cancelled.value}


class StoreError(AutocalError):
    """A store operation is not allowed (unknown job, wrong state)."""


class Base(DeclarativeBase):
    """SQLAlchemy declarative base."""


def _now() -> datetime:
    return datetime.now(UTC)


class Job(Base):
    """One calibration (or diagnosis) job."""

    __tablename__ = "jobs"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    kind: Mapped[str] = mapped_column(String(32), default="calibrate")
    state: Mapped[str] = mapped_column(String(16), index=True, default=JobState.queued.value)
    config: Mapped[dict[str, Any]] = mapped_column(JSON)
    night: Mapped[int | None] = mapped_column(Integer, index=True, nullable=True)
    antennas: Mapped[list[int] | None] = mapped_column(JSON, nullable=True)
    dedupe_key: Mapped[str | None] = mapped_column(String(128), index=True, nullable=True)
    # The dedupe key while the job is queued, running or succeeded, NULL otherwise: a unique
    # column, so two concurrent identical submissions cannot both create a job (NULLs are
    # distinct in SQLite and PostgreSQL).
    dedupe_active: Mapped[str | None] = mapped_column(String(128), unique=True, nullable=True)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=_now)
    started_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)
    finished_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)
    heartbeat_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    message: Mapped[str] = mapped_column(Text, default="")
    log: Mapped[str] = mapped_column(Text, default="")
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    max_attempts: Mapped[int] = mapped_column(Integer, default=3)
    worker: Mapped[str | None] = mapped_column(String(128), nullable=True)
    cancel_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    result: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    products: Mapped[dict[str, str] | None] = mapped_column(JSON, nullable=True)
    provenance: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    completions: Mapped[int] = mapped_column(Integer, default=0)
    # the name of the API token that submitted the job (None: nightly runner, CLI, tests)
    submitted_by: Mapped[str | None] = mapped_column(String(64), nullable=True)
    # attempts handed back by a worker shutting down (SIGTERM): not counted against
    # max_attempts (added by migration h24w-jobs-releases)
    releases: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    # {path: fingerprint} of the input files, recorded at submission and checked when a
    # worker starts the job (autocal.service.input_check; migration
    # h24w-jobs-input-fingerprints)
    input_fingerprints: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)

    def to_dict(self) -> dict[str, Any]:
        """Return a plain dictionary of the record (datetimes as ISO strings)."""
        out: dict[str, Any] = {}
        for column in self.__table__.columns:
            value = getattr(self, column.name)
            if isinstance(value, datetime):
                value = _aware(value).isoformat()
            out[column.name] = value
        return out


def _aware(value: datetime) -> datetime:
    """SQLite returns naive datetimes; they are UTC."""
    return value if value.tzinfo is not None else value.replace(tzinfo=UTC)


class JobStore:
    """Access to the job table.

    Parameters
    ----------
    url
        SQLAlchemy database URL (``sqlite:///path`` or ``postgresql+psycopg://...``).
    """

    def __init__(self, url: str) -> None:
        self.url = url
        self.is_sqlite = url.startswith("sqlite")
        kwargs: dict[str, Any] = {"future": True, "pool_pre_ping": True}
        if self.is_sqlite:
            kwargs["connect_args"] = {"timeout": 30, "check_same_thread": False}
        try:
            self.engine: Engine = create_engine(url, **kwargs)
        except (ArgumentError, NoSuchModuleError, ImportError) as err:
            raise StoreError(
                f"the job store's database URL is not usable ({type(err).__name__}: {err}); "
                "set AUTOCAL_DATABASE_URL to sqlite:///PATH or postgresql+psycopg://..."
            ) from None
        if self.is_sqlite:
            event.listen(self.engine, "connect", _sqlite_pragmas)
            event.listen(self.engine, "begin", _sqlite_begin_immediate)
        self._create_tables()
        self._sessions = sessionmaker(self.engine, expire_on_commit=False)

    def _create_tables(self) -> None:
        """Create the tables and apply the migrations; tolerate a concurrent starter."""
        from autocal.service import job_index  # noqa: F401  # registers its table

        for attempt in range(5):
            try:
                Base.metadata.create_all(self.engine)
                apply_migrations(self.engine)
                return
            except (IntegrityError, OperationalError, ProgrammingError):
                if attempt == 4:
                    raise
                time.sleep(0.2 * (attempt + 1))

    @contextmanager
    def session(self) -> Iterator[Session]:
        """Yield a session committed on success and rolled back on error."""
        with self._sessions() as session:
            try:
                yield session
                session.commit()
            except BaseException:
                session.rollback()
                raise

    def db_now(self, session: Session | None = None) -> datetime:
        """Return the database's current time (UTC, timezone-aware).

        Every time the store records or compares -- claims, heartbeats, staleness, the
        per-job time limit -- is read here, so workers whose clocks disagree are judged
        by one clock: PostgreSQL's ``clock_timestamp()``, or for SQLite (an embedded
        database all of whose users share one host) that host's clock.

        Parameters
        ----------
        session
            Session to ask through (default: a new connection).
        """
        if self.is_sqlite:
            query = select(func.strftime("%Y-%m-%d %H:%M:%f", "now"))
        else:
            query = select(func.clock_timestamp())
        if session is not None:
            value = session.scalar(query)
        else:
            with self.engine.connect() as conn:
                value = conn.scalar(query)
        if isinstance(value, str):
            value = datetime.fromisoformat(value)
        assert isinstance(value, datetime)
        return _aware(value)

    def ping(self) -> bool:
        """Whether the database answers."""
        with self.engine.connect() as conn:
            conn.execute(select(1))
        return True

    # submission and queries ------------------------------------------------------------
    def submit(
        self,
        config: dict[str, Any],
        *,
        kind: str = "calibrate",
        night: int | None = None,
        antennas: list[int] | None = None,
        dedupe_key: str | None = None,
        force: bool = False,
        max_attempts: int = 3,
        submitted_by: str | None = None,
        input_fingerprints: dict[str, Any] | None = None,
    ) -> tuple[dict[str, Any], bool]:
        """Queue a job; return ``(job, created)``.

        With ``dedupe_key``, an existing job with the same key that is not failed or
        cancelled is returned instead of a new one (``created`` false), unless ``force``.
        ``submitted_by`` records the name of the API token that asked for it;
        ``input_fingerprints`` (:func:`autocal.service.input_check.fingerprint_config`)
        are checked by the worker before it reads the inputs.
        """
        if dedupe_key is not None and not force:
            existing = self._active_duplicate(dedupe_key)
            if existing is not None:
                return existing, False
        try:
            job = Job(
                id=uuid.uuid4().hex,
                kind=kind,
                state=JobState.queued.value,
                config=config,
                night=night,
                antennas=antennas,
                dedupe_key=dedupe_key,
                dedupe_active=None if force else dedupe_key,
                max_attempts=max_attempts,
                input_fingerprints=input_fingerprints,
                submitted_by=submitted_by,
            )
            return self._insert(job), True
        except IntegrityError:
            # A concurrent identical submission won the race: return its job.
            existing = self._active_duplicate(dedupe_key) if dedupe_key else None
            if existing is None:
                raise
            return existing, False

    def _active_duplicate(self, dedupe_key: str) -> dict[str, Any] | None:
        with self.session() as s:
            existing = s.scalars(
                select(Job)
                .where(Job.dedupe_key == dedupe_key)
                .where(Job.state.in_(["queued", "running", "succeeded"]))
                .order_by(Job.created_at.desc())
            ).first()
            return None if existing is None else existing.to_dict()

    def _insert(self, job: Job) -> dict[str, Any]:
        from autocal.service.job_index import JobAntenna, antenna_rows

        with self.session() as s:
            job.created_at = self.db_now(s)
            s.add(job)
            s.flush()
            rows = antenna_rows(job.id, job.created_at, job.antennas)
            s.add_all(JobAntenna(**row) for row in rows)
            s.flush()
            return job.to_dict()

    def get(self, job_id: str) -> dict[str, Any] | None:
        """Return the job record, or ``None``."""
        with self.session() as s:
            job = s.get(Job, job_id)
            return None if job is None else job.to_dict()

    def list(
        self,
        *,
        state: str | None = None,
        night: int | None = None,
        antenna: int | None = None,
        kind: str | None = None,
        limit: int = 100,
        offset: int = 0,
    ) -> list[dict[str, Any]]:
        """Jobs, newest first, optionally filtered (one page: :meth:`page`)."""
        return self.page(
            state=state, night=night, antenna=antenna, kind=kind, limit=limit, offset=offset
        )[0]

    def page(
        self, *, limit: int = 100, after: tuple[datetime, str] | None = None, **filters: Any
    ) -> tuple[list[dict[str, Any]], tuple[datetime, str] | None]:
        """One page of jobs and the key after it (:func:`autocal.service.job_index.list_page`)."""
        from autocal.service.job_index import list_page

        with self.session() as s:
            jobs, key = list_page(s, limit=limit, after=after, **filters)
            return [j.to_dict() for j in jobs], key

    def count(self, state: str | None = None) -> int:
        """Count jobs (in a state)."""
        with self.session() as s:
            query = select(func.count()).select_from(Job)
            if state is not None:
                query = query.where(Job.state == state)
            return int(s.scalar(query) or 0)

    def request_cancel(self, job_id: str) -> dict[str, Any]:
        """Cancel a queued job at once; ask the worker of a running job to stop."""
        with self.session() as s:
            job = s.get(Job, job_id, with_for_update=not self.is_sqlite)
            if job is None:
                raise StoreError(f"no job {job_id}")
            if job.state == JobState.queued.value:
                job.state = JobState.cancelled.value
                job.dedupe_active = None
                job.finished_at = self.db_now(s)
                job.message = "cancelled before it started"
            elif job.state == JobState.running.value:
                job.cancel_requested = True
                job.message = "cancellation requested"
            else:
                raise StoreError(f"job {job_id} is already {job.state}; nothing to cancel")
            return job.to_dict()

    # the worker side -------------------------------------------------------------------
    def claim(self, worker: str, kinds: list[str] | None = None) -> dict[str, Any] | None:
        """Atomically take the oldest queued job; ``None`` when the queue is empty."""
        with self.session() as s:
            now = self.db_now(s)
            pick = select(Job.id).where(Job.state == JobState.queued.value)
            if kinds:
                pick = pick.where(Job.kind.in_(kinds))
            pick = pick.order_by(Job.created_at).limit(1)
            if not self.is_sqlite:
                pick = pick.with_for_update(skip_locked=True)
            stmt = (
                update(Job)
                .where(Job.id == pick.scalar_subquery())
                .where(Job.state == JobState.queued.value)
                .values(
                    state=JobState.running.value,
                    worker=worker,
                    started_at=now,
                    heartbeat_at=now,
                    attempts=Job.attempts + 1,
                    progress=0.0,
                    message="claimed",
                )
                .returning(Job.id)
            )
            claimed = s.execute(stmt).scalar_one_or_none()
            if claimed is None:
                return None
            job = s.get(Job, claimed)
            assert job is not None
            s.refresh(job)
            return job.to_dict()

    def _owned(self, s: Session, job_id: str, worker: str, attempt: int) -> Job | None:
        job = s.get(Job, job_id, with_for_update=not self.is_sqlite)
        if (
            job is None
            or job.state != JobState.running.value
            or job.worker != worker
            or job.attempts != attempt
        ):
            return None
        return job

    def heartbeat(
        self,
        job_id: str,
        worker: str,
        attempt: int,
        *,
        progress: float | None = None,
        message: str | None = None,
    ) -> bool:
        """Record liveness (and progress); ``False`` if the job should stop.

        ``False`` means the worker no longer owns the job (it was re-queued or failed)
        or cancellation was requested.
        """
        with self.session() as s:
            job = self._owned(s, job_id, worker, attempt)
            if job is None:
                return False
            job.heartbeat_at = self.db_now(s)
            if progress is not None:
                job.progress = float(min(max(progress, 0.0), 1.0))
            if message is not None:
                job.message = message[:500]
            return not job.cancel_requested

    def append_log(self, job_id: str, line: str) -> None:
        """Append a line to the job's log tail."""
        with self.session() as s:
            # locked: a concurrent release or recovery also appends to the log
            job = s.get(Job, job_id, with_for_update=not self.is_sqlite)
            if job is None:
                return
            lines = (job.log.splitlines() if job.log else []) + [line.rstrip()[:1000]]
            job.log = "\n".join(lines[-LOG_LINES:])

    def finish(
        self,
        job_id: str,
        worker: str,
        attempt: int,
        state: JobState,
        *,
        result: dict[str, Any] | None = None,
        products: dict[str, str] | None = None,
        provenance: dict[str, Any] | None = None,
        error: str | None = None,
        message: str | None = None,
    ) -> bool:
        """Close a running job; ``False`` (and nothing changed) if not its owner.

        ``message``: the job's short message (default the state's: ``done``, ``failed``,
        ``cancelled``), e.g. ``done, but ... (mostly flagged): see quality``.
        """
        if state.value not in FINAL_STATES:
            raise StoreError(f"{state.value} is not a final state")
        with self.session() as s:
            job = self._owned(s, job_id, worker, attempt)
            if job is not None:
                self._close(s, job, state, result, products, provenance, error, message)
        if job is None:  # logged outside the session: a log handler may write to the store
            logger.warning("worker %s no longer owns job %s; result discarded", worker, job_id)
            return False
        return True

    def _close(
        self,
        s: Session,
        job: Job,
        state: JobState,
        result: dict[str, Any] | None,
        products: dict[str, str] | None,
        provenance: dict[str, Any] | None,
        error: str | None,
        message: str | None = None,
    ) -> None:
        """Record a job's final state (its owner checked by the caller)."""
        job.state = state.value
        job.finished_at = self.db_now(s)
        if state != JobState.succeeded:
            job.dedupe_active = None
        job.progress = 1.0 if state == JobState.succeeded else job.progress
        job.result = result
        job.products = products
        job.provenance = provenance
        job.error = error
        job.message = (
            message[:500]
            if message
            else {"succeeded": "done", "failed": "failed", "cancelled": "cancelled"}[state.value]
        )
        if state == JobState.succeeded:
            job.completions += 1

    def release(self, job_id: str, worker: str, attempt: int, reason: str) -> bool:
        """Hand a running job back to the queue at once (a worker shutting down).

        The attempt is not counted against ``max_attempts`` (``releases`` is raised with
        ``attempts``, whose value keeps attempt numbers and product folders unique), the
        owner is cleared, so the job can be claimed again at once and a late result of
        this attempt is refused. A job whose cancellation was requested is cancelled.

        Parameters
        ----------
        job_id, worker, attempt
            The job and its owner (as returned by :meth:`claim`).
        reason
            Why it was handed back (the job's message and a log line).

        Returns
        -------
        bool
            ``False`` (nothing changed) if ``worker`` no longer owns the attempt.
        """
        with self.session() as s:
            job = self._owned(s, job_id, worker, attempt)
            if job is None:
                return False
            if job.cancel_requested:
                job.state = JobState.cancelled.value
                job.finished_at = self.db_now(s)
                job.dedupe_active = None
                job.error = "cancelled on request"
                job.message = "cancelled"
            else:
                job.state = JobState.queued.value
                job.releases = (job.releases or 0) + 1
                job.message = f"re-queued: {reason}"[:500]
            job.worker = None
            _log_line(job, f"attempt {attempt} handed back: {reason}")
        logger.info("job %s attempt %d handed back by %s: %s", job_id, attempt, worker, reason)
        return True

    def recover_stale(
        self,
        stale_after_s: float,
        job_timeout_s: float = 0.0,
        alive: tuple[str, int] | None = None,
    ) -> list[dict[str, Any]]:
        """Re-queue or fail running jobs that stopped beating or ran out of time.

        A job whose heartbeat is older than ``stale_after_s`` (by the database clock,
        :meth:`db_now`) is re-queued, or failed once it used ``max_attempts`` counted
        attempts (handed-back ones are not counted). A job whose current attempt started
        more than ``job_timeout_s`` ago is failed with that reason even if it is still
        beating (a hung job whose heartbeat thread is alive); 0 means no time limit.

        Parameters
        ----------
        stale_after_s
            Seconds without heartbeat after which a worker is presumed dead.
        job_timeout_s
            Per-attempt time limit in seconds (``AUTOCAL_JOB_TIMEOUT_S``); 0: none.
        alive
            ``(job id, attempt)`` of a job the caller is running itself and knows alive (a
            worker's heartbeat thread): never re-queued as stale, whatever its last
            heartbeat says (a process starved of CPU for longer than ``stale_after_s``
            must not take its own running job for a dead worker's). Its time limit still
            applies.

        Returns
        -------
        list of dict
            The jobs changed.
        """
        changed = []
        with self.session() as s:
            now = self.db_now(s)
            query = select(Job).where(Job.state == JobState.running.value)
            if not self.is_sqlite:
                query = query.with_for_update(skip_locked=True)
            for job in s.scalars(query):
                stale_after = stale_after_s
                if alive is not None and (job.id, job.attempts) == alive:
                    stale_after = math.inf  # its worker is the caller, and it is running
                if self._recover_one(job, now, stale_after, job_timeout_s):
                    changed.append(job.to_dict())
        for job in changed:
            logger.warning("job %s: %s", job["id"], job["error"] or job["message"])
        return changed

    @staticmethod
    def _recover_one(job: Job, now: datetime, stale_after_s: float, timeout_s: float) -> bool:
        """Re-queue or close one running job if stale or out of time; whether it changed."""
        started = _aware(job.started_at) if job.started_at else None
        beat = _aware(job.heartbeat_at) if job.heartbeat_at else None
        if timeout_s > 0 and started is not None and now - started >= timedelta(seconds=timeout_s):
            reason = (
                f"job exceeded its time limit (AUTOCAL_JOB_TIMEOUT_S={timeout_s:g} s): attempt "
                f"{job.attempts} running since {started.isoformat()} on worker {job.worker}"
            )
            requeue = False
        elif math.isfinite(stale_after_s) and (
            beat is None or now - beat > timedelta(seconds=stale_after_s)
        ):
            reason = (
                f"worker {job.worker} stopped sending heartbeats (last "
                f"{beat.isoformat() if beat else 'never'}; attempt {job.attempts})"
            )
            counted = job.attempts - (job.releases or 0)
            requeue = counted < job.max_attempts and not job.cancel_requested
        else:
            return False
        if requeue:
            job.state = JobState.queued.value
            job.message = f"re-queued: {reason}"[:500]
        else:
            job.state = JobState.cancelled.value if job.cancel_requested else JobState.failed.value
            job.finished_at = now
            job.dedupe_active = None
            job.error = reason
            job.message = job.state
        job.worker = None
        _log_line(job, reason)
        return True


def _log_line(job: Job, line: str) -> None:
    """Append ``line`` to a job's bounded log tail."""
    lines = (job.log.splitlines() if job.log else []) + [line.rstrip()[:1000]]
    job.log = "\n".join(lines[-LOG_LINES:])


def _sqlite_pragmas(dbapi_connection: Any, _record: Any) -> None:
    # let SQLAlchemy, not the sqlite3 module, open transactions (see below)
    dbapi_connection.isolation_level = None
    cursor = dbapi_connection.cursor()
    cursor.execute("PRAGMA journal_mode=WAL")
    cursor.execute("PRAGMA busy_timeout=30000")
    cursor.close()


def _sqlite_begin_immediate(conn: Any) -> None:
    """Open every SQLite transaction with the write lock (``BEGIN IMMEDIATE``).

    The sqlite3 module otherwise runs a session's reads outside any transaction and
    begins one only at its first write, so two read-modify-write sessions (a release
    and a log line, a finish and a recovery) could both read the old row and the later
    write would silently undo the earlier one. Holding the lock from the first read
    serialises them (waiting up to ``busy_timeout``); sessions are short.
    """
    conn.exec_driver_sql("BEGIN IMMEDIATE")
