"""Schema migrations of the job store: named steps applied once, in order, at start-up.

``Base.metadata.create_all`` creates missing *tables* (a fresh database gets every column
of the current models), but it never changes an existing table. Each :class:`Migration`
brings an older database up to date; it is applied inside a transaction by
:func:`apply_migrations` (called by :class:`autocal.service.store.JobStore` after
``create_all``) and recorded by name in the ``schema_migrations`` table, so it runs once
per database. Steps are idempotent (a column that already exists, e.g. because
``create_all`` made it, is not added again), on SQLite and PostgreSQL.

A step's name starts with the name of the change that introduced it; append new steps
at the end of :data:`MIGRATIONS` and never rename or reorder the existing ones.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime

from sqlalchemy import (
    JSON,
    Column,
    DateTime,
    Integer,
    MetaData,
    String,
    Table,
    inspect,
    select,
    text,
)
from sqlalchemy.engine import Connection, Engine
from sqlalchemy.types import TypeEngine

logger = logging.getLogger(__name__)

_metadata = MetaData()

#: One row per applied migration step.
schema_migrations = Table(
    "schema_migrations",
    _metadata,
    Column("name", String(128), primary_key=True),
    Column("applied_at", DateTime(timezone=True), nullable=False),
)

#: PostgreSQL advisory-lock key serialising migrations of concurrent starters.
_PG_LOCK_KEY = 0x6175746F63616C  # "autocal"


@dataclass(frozen=True)
class Migration:
    """One named, idempotent schema change.

    Parameters
    ----------
    name
        Unique name, recorded in ``schema_migrations`` once applied.
    apply
        Function changing the schema through the given connection (inside the
        migration's transaction); returns whether it changed anything.
    """

    name: str
    apply: Callable[[Connection], bool]


def add_column(
    table: str, column: str, type_: TypeEngine, default_sql: str | None = None
) -> Callable[[Connection], bool]:
    """Return a step that adds ``column`` to ``table`` unless it exists.

    Parameters
    ----------
    table, column
        Table and new column names.
    type_
        The column's SQLAlchemy type (compiled for the connection's dialect).
    default_sql
        SQL literal of the server default (existing rows get it); ``None``: NULL.

    Returns
    -------
    callable
        The step, for :class:`Migration`.
    """

    def step(conn: Connection) -> bool:
        existing = {c["name"] for c in inspect(conn).get_columns(table)}
        if column in existing:  # a fresh database: create_all made it
            return False
        sql_type = type_.compile(dialect=conn.dialect)
        default = f" DEFAULT {default_sql} NOT NULL" if default_sql is not None else ""
        conn.execute(text(f'ALTER TABLE "{table}" ADD COLUMN "{column}" {sql_type}{default}'))
        return True

    return step


def add_index(name: str, columns: str) -> Callable[[Connection], bool]:
    """Return a step that creates index ``name`` on ``jobs (columns)`` unless it exists.

    Parameters
    ----------
    name
        The index name.
    columns
        The indexed columns, comma-separated, in order.

    Returns
    -------
    callable
        The step, for :class:`Migration`.
    """

    def step(conn: Connection) -> bool:
        existing = {ix["name"] for ix in inspect(conn).get_indexes("jobs")}
        conn.execute(text(f"CREATE INDEX IF NOT EXISTS {name} ON jobs ({columns})"))
        return name not in existing

    return step


def _backfill_job_antennas(conn: Connection) -> bool:
    """Index the antennas of jobs created before the ``job_antennas`` table existed."""
    from autocal.service.job_index import antenna_rows  # the store imports this module

    done = {row[0] for row in conn.execute(text("SELECT DISTINCT job_id FROM job_antennas"))}
    rows = []
    for job_id, created_at, antennas in conn.execute(
        text("SELECT id, created_at, antennas FROM jobs")
    ):
        if job_id not in done:
            rows.extend(antenna_rows(job_id, created_at, antennas))
    if rows:
        conn.execute(
            text(
                "INSERT INTO job_antennas (job_id, antenna, created_at) "
                "VALUES (:job_id, :antenna, :created_at)"
            ),
            rows,
        )
    return bool(rows)


#: Every migration, in the order they are applied.
MIGRATIONS: list[Migration] = [
    # keyset listing of GET /jobs: one index per filter, ordered like the pages
    Migration("h24a_jobs_created_id_index", add_index("ix_jobs_created_id", "created_at, id")),
    Migration(
        "h24a_jobs_state_created_index", add_index("ix_jobs_state_created", "state, created_at, id")
    ),
    Migration(
        "h24a_jobs_kind_created_index", add_index("ix_jobs_kind_created", "kind, created_at, id")
    ),
    Migration(
        "h24a_jobs_night_created_index", add_index("ix_jobs_night_created", "night, created_at, id")
    ),
    # the name of the token that submitted a job
    Migration("h24a_jobs_submitted_by", add_column("jobs", "submitted_by", String(64))),
    # the antenna filter of GET /jobs reads the job_antennas table
    Migration("h24a_job_antennas_backfill", _backfill_job_antennas),
    # graceful releases (SIGTERM) do not count as attempts
    Migration("h24w-jobs-releases", add_column("jobs", "releases", Integer(), "0")),
    # size, time and content fingerprints of the inputs, recorded at submission
    Migration("h24w-jobs-input-fingerprints", add_column("jobs", "input_fingerprints", JSON())),
]


def applied_migrations(engine: Engine) -> list[str]:
    """Return the names of the applied steps: those of :data:`MIGRATIONS` in its order.

    Parameters
    ----------
    engine
        The job store's engine.

    Returns
    -------
    list of str
        Step names (a recorded name unknown to this version comes last).
    """
    _metadata.create_all(engine)
    with engine.connect() as conn:
        recorded = set(conn.scalars(select(schema_migrations.c.name)))
    known = [m.name for m in MIGRATIONS if m.name in recorded]
    return known + sorted(recorded - set(known))


def apply_migrations(engine: Engine, migrations: list[Migration] | None = None) -> list[str]:
    """Apply the steps not yet recorded in ``schema_migrations``; return their names.

    Parameters
    ----------
    engine
        The store's engine (SQLite or PostgreSQL).
    migrations
        The steps (default :data:`MIGRATIONS`).

    Returns
    -------
    list of str
        Names of the steps applied now (empty when the database was up to date).
    """
    steps = MIGRATIONS if migrations is None else migrations
    _metadata.create_all(engine)
    applied: list[str] = []
    changed: list[str] = []
    with engine.begin() as conn:
        if conn.dialect.name == "postgresql":
            # two processes starting at once: the second waits, then finds the steps done
            conn.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": _PG_LOCK_KEY})
        done = set(conn.scalars(select(schema_migrations.c.name)))
        for migration in steps:
            if migration.name in done:
                continue
            if migration.apply(conn):
                changed.append(migration.name)
            conn.execute(
                schema_migrations.insert().values(name=migration.name, applied_at=datetime.now(UTC))
            )
            applied.append(migration.name)
    for name in applied:
        if name in changed:
            logger.info("job store: applied migration %s", name)
        else:
            logger.debug("job store: recorded migration %s (already up to date)", name)
    return applied
