"""Listing jobs in pages whose cost does not grow with the table (keyset pagination).

``GET /jobs`` returns jobs newest first, ordered by ``(created_at, id)``. A page ends with an
opaque cursor naming its last job; the next page is the jobs strictly before that key. Every
filter is a ``WHERE`` clause on an index that starts with the filtered column and goes on
with ``(created_at, id)`` (``ix_jobs_state_created``, ``ix_jobs_kind_created``,
``ix_jobs_night_created``, ``ix_jobs_created_id``; see :mod:`autocal.service.migrations`),
and the query ends with ``LIMIT page + 1``, so the database reads about ``limit`` index
entries and rows whatever the number of jobs.

The antenna filter uses the ``job_antennas`` table: one row per antenna a job names, and one
row with antenna :data:`ALL_ANTENNAS` for a job over every antenna of its files (a job over
all antennas concerns any antenna), indexed on ``(antenna, created_at, job_id)``.
"""

from __future__ import annotations

import base64
import binascii
import json
from collections.abc import Iterable
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import DateTime, ForeignKey, Index, Integer, String, select, tuple_
from sqlalchemy.orm import Mapped, Session, mapped_column

from autocal.errors import AutocalError
from autocal.service.store import Base, Job

#: The ``antenna`` of the index row of a job over every antenna.
ALL_ANTENNAS = -1


class CursorError(AutocalError):
    """A pagination cursor that this service did not issue."""


class JobAntenna(Base):
    """One antenna named by a job (:data:`ALL_ANTENNAS` for every antenna)."""

    __tablename__ = "job_antennas"
    __table_args__ = (Index("ix_job_antennas_antenna_created", "antenna", "created_at", "job_id"),)

    job_id: Mapped[str] = mapped_column(
        String(32), ForeignKey("jobs.id", ondelete="CASCADE"), primary_key=True
    )
    antenna: Mapped[int] = mapped_column(Integer, primary_key=True)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True))


def antenna_rows(
    job_id: str, created_at: Any, antennas: Iterable[int] | str | None
) -> list[dict[str, Any]]:
    """Return the ``job_antennas`` rows of a job.

    Parameters
    ----------
    job_id
        The job id.
    created_at
        The job's creation time (as stored).
    antennas
        The job's antennas; ``None`` for all; a JSON text when read by raw SQL.

    Returns
    -------
    list of dict
        ``job_id``, ``antenna``, ``created_at`` per row.
    """
    if isinstance(antennas, str):
        antennas = json.loads(antennas)
    values = sorted({int(a) for a in antennas}) if antennas is not None else [ALL_ANTENNAS]
    return [{"job_id": job_id, "antenna": a, "created_at": created_at} for a in values]


def encode_cursor(created_at: datetime, job_id: str) -> str:
    """Return the opaque cursor after the job ``(created_at, job_id)``."""
    stamp = created_at if created_at.tzinfo else created_at.replace(tzinfo=UTC)
    raw = json.dumps([stamp.isoformat(), job_id], separators=(",", ":")).encode()
    return base64.urlsafe_b64encode(raw).decode().rstrip("=")


def decode_cursor(cursor: str) -> tuple[datetime, str]:
    """Return the ``(created_at, job_id)`` key of a cursor.

    Raises
    ------
    CursorError
        If the cursor was not issued by :func:`encode_cursor`.
    """
    try:
        raw = base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4))
        stamp, job_id = json.loads(raw)
        created = datetime.fromisoformat(stamp)
        if not isinstance(job_id, str) or created.tzinfo is None:
            raise ValueError("malformed key")
    except (ValueError, TypeError, binascii.Error, UnicodeDecodeError):
        raise CursorError(
            "the cursor is not one this service issued: pass the 'next_cursor' of the "
            "previous page unchanged, or omit it for the first page"
        ) from None
    # SQLite stores naive UTC; the comparison must use the same form as the column
    return created.astimezone(UTC), job_id


def list_page(
    session: Session,
    *,
    state: str | None = None,
    night: int | None = None,
    antenna: int | None = None,
    kind: str | None = None,
    limit: int = 100,
    after: tuple[datetime, str] | None = None,
    offset: int = 0,
) -> tuple[list[Job], tuple[datetime, str] | None]:
    """Return one page of jobs, newest first, and the key after its last job.

    Parameters
    ----------
    session
        A store session.
    state, night, antenna, kind
        Filters (``None``: any).
    limit
        Jobs in the page.
    after
        The key of the last job of the previous page (:func:`decode_cursor`).
    offset
        Jobs skipped (the old paging; its cost grows with the offset).

    Returns
    -------
    (list of Job, tuple or None)
        The jobs and the key of the last one when more follow, else ``None``.
    """
    query = select(Job)
    created, ident = Job.created_at, Job.id
    if antenna is not None:  # walk that antenna's index entries, newest first
        query = query.join(JobAntenna, JobAntenna.job_id == Job.id).where(
            JobAntenna.antenna.in_([antenna, ALL_ANTENNAS])
        )
        created, ident = JobAntenna.created_at, JobAntenna.job_id
    if state is not None:
        query = query.where(Job.state == state)
    if night is not None:
        query = query.where(Job.night == night)
    if kind is not None:
        query = query.where(Job.kind == kind)
    if after is not None:
        query = query.where(tuple_(created, ident) < tuple_(*_bind(session, after)))
    query = query.order_by(created.desc(), ident.desc()).limit(limit + 1)
    if offset:
        query = query.offset(offset)
    jobs = list(session.scalars(query))
    if len(jobs) <= limit:
        return jobs, None
    last = jobs[limit - 1]
    return jobs[:limit], (last.created_at, last.id)


def _bind(session: Session, after: tuple[datetime, str]) -> tuple[datetime, str]:
    created, job_id = after
    if session.get_bind().dialect.name == "sqlite":  # stored naive (UTC)
        created = created.astimezone(UTC).replace(tzinfo=None)
    return created, job_id
