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
from sqlalchemy.exc import IntegrityError, OperationalError, ProgrammingError
from sqlalchemy.orm import DeclarativeBase, Mapped, Session, mapped_column, sessionmaker

from autocal.errors import AutocalError

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
        self.engine: Engine = create_engine(url, **kwargs)
        if self.is_sqlite:
            event.listen(self.engine, "connect", _sqlite_pragmas)
        self._create_tables()
        self._sessions = sessionmaker(self.engine, expire_on_commit=False)

    def _create_tables(self) -> None:
        """Create the table; tolerate another process creating it at the same moment."""
        from autocal.service import job_index  # noqa: F401  # registers its table
        from autocal.service.migrations import apply_migrations

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
    ) -> tuple[dict[str, Any], bool]:
        """Queue a job; return ``(job, created)``.

        With ``dedupe_key``, an existing job with the same key that is not failed or
        cancelled is returned instead of a new one (``created`` false), unless ``force``.
        ``submitted_by`` records the name of the API token that asked for it.
        """
        if dedupe_key is not None and not force:
            existing = self._active_duplicate(dedupe_key)
            if existing is not None:
                return existing, False
        try:
            return self._insert(
                config, kind, night, antennas, dedupe_key, force, max_attempts, submitted_by
            ), True
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

    def _insert(
        self,
        config: dict[str, Any],
        kind: str,
        night: int | None,
        antennas: list[int] | None,
        dedupe_key: str | None,
        force: bool,
        max_attempts: int,
        submitted_by: str | None = None,
    ) -> dict[str, Any]:
        from autocal.service.job_index import JobAntenna, antenna_rows

        with self.session() as s:
            job = Job(
                id=uuid.uuid4().hex,
                kind=kind,
                state=JobState.queued.value,
                config=config,
                night=night,
                antennas=antennas,
                dedupe_key=dedupe_key,
                dedupe_active=None if force else dedupe_key,
                created_at=_now(),
                max_attempts=max_attempts,
                submitted_by=submitted_by,
            )
            s.add(job)
            s.flush()
            s.add_all(JobAntenna(**row) for row in antenna_rows(job.id, job.created_at, antennas))
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
                job.finished_at = _now()
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
        now = _now()
        with self.session() as s:
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
            job.heartbeat_at = _now()
            if progress is not None:
                job.progress = float(min(max(progress, 0.0), 1.0))
            if message is not None:
                job.message = message[:500]
            return not job.cancel_requested

    def append_log(self, job_id: str, line: str) -> None:
        """Append a line to the job's log tail."""
        with self.session() as s:
            job = s.get(Job, job_id)
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
    ) -> bool:
        """Close a running job; ``False`` (and nothing changed) if not its owner."""
        if state.value not in FINAL_STATES:
            raise StoreError(f"{state.value} is not a final state")
        with self.session() as s:
            job = self._owned(s, job_id, worker, attempt)
            if job is None:
                logger.warning("worker %s no longer owns job %s; result discarded", worker, job_id)
                return False
            job.state = state.value
            job.finished_at = _now()
            if state != JobState.succeeded:
                job.dedupe_active = None
            job.progress = 1.0 if state == JobState.succeeded else job.progress
            job.result = result
            job.products = products
            job.provenance = provenance
            job.error = error
            job.message = {"succeeded": "done", "failed": "failed", "cancelled": "cancelled"}[
                state.value
            ]
            if state == JobState.succeeded:
                job.completions += 1
            return True

    def recover_stale(self, stale_after_s: float) -> list[dict[str, Any]]:
        """Re-queue or fail running jobs whose heartbeat is older than ``stale_after_s``."""
        cutoff = _now() - timedelta(seconds=stale_after_s)
        changed = []
        with self.session() as s:
            query = select(Job).where(Job.state == JobState.running.value)
            if not self.is_sqlite:
                query = query.with_for_update(skip_locked=True)
            for job in s.scalars(query):
                beat = _aware(job.heartbeat_at) if job.heartbeat_at else None
                if beat is not None and beat >= cutoff:
                    continue
                reason = (
                    f"worker {job.worker} stopped sending heartbeats (last "
                    f"{beat.isoformat() if beat else 'never'}; attempt {job.attempts})"
                )
                if job.attempts < job.max_attempts and not job.cancel_requested:
                    job.state = JobState.queued.value
                    job.message = f"re-queued: {reason}"
                else:
                    job.state = (
                        JobState.cancelled.value if job.cancel_requested else JobState.failed.value
                    )
                    job.finished_at = _now()
                    job.dedupe_active = None
                    job.error = reason
                    job.message = job.state
                job.worker = None
                lines = (job.log.splitlines() if job.log else []) + [reason]
                job.log = "\n".join(lines[-LOG_LINES:])
                changed.append(job.to_dict())
        for job in changed:
            logger.warning("job %s: %s", job["id"], job["message"] or job["error"])
        return changed


def _sqlite_pragmas(dbapi_connection: Any, _record: Any) -> None:
    cursor = dbapi_connection.cursor()
    cursor.execute("PRAGMA journal_mode=WAL")
    cursor.execute("PRAGMA busy_timeout=30000")
    cursor.close()
