"""Schema migrations of the job store: named steps applied once, in order, at start-up.

``Base.metadata.create_all`` creates missing tables but never changes an existing one, so a
new column or index on a table that already holds jobs is a *step* here: a name and a
function of a connection. :func:`apply_migrations` runs every step not yet recorded in the
``schema_migrations`` table, each in its own transaction together with the row that records
it, so a step is applied exactly once even when several processes (the API and workers)
start at the same moment: the second one's insert of the same name waits for the first's
transaction and then fails on the primary key, and it skips the step. Steps are written to
be harmless on a database created from the current models (``IF NOT EXISTS``, a column
added only when it is missing), SQLite and PostgreSQL alike.

Step names are prefixed by the helper (branch) that wrote them; never rename or reorder an
applied step, append new ones.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from datetime import UTC, datetime

from sqlalchemy import Connection, inspect, text
from sqlalchemy.engine import Engine
from sqlalchemy.exc import IntegrityError

logger = logging.getLogger(__name__)

#: The table recording applied steps.
MIGRATIONS_TABLE = "schema_migrations"


def _index(name: str, columns: str) -> Callable[[Connection], None]:
    def step(conn: Connection) -> None:
        conn.execute(text(f"CREATE INDEX IF NOT EXISTS {name} ON jobs ({columns})"))

    return step


def _add_submitted_by(conn: Connection) -> None:
    columns = {c["name"] for c in inspect(conn).get_columns("jobs")}
    if "submitted_by" not in columns:
        conn.execute(text("ALTER TABLE jobs ADD COLUMN submitted_by VARCHAR(64)"))


def _backfill_job_antennas(conn: Connection) -> None:
    """Index the antennas of jobs created before the ``job_antennas`` table existed."""
    from autocal.service.job_index import antenna_rows

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


#: The ordered steps: (name, function of a connection inside the step's transaction).
STEPS: list[tuple[str, Callable[[Connection], None]]] = [
    ("h24a_jobs_created_id_index", _index("ix_jobs_created_id", "created_at, id")),
    ("h24a_jobs_state_created_index", _index("ix_jobs_state_created", "state, created_at, id")),
    ("h24a_jobs_kind_created_index", _index("ix_jobs_kind_created", "kind, created_at, id")),
    ("h24a_jobs_night_created_index", _index("ix_jobs_night_created", "night, created_at, id")),
    ("h24a_jobs_submitted_by", _add_submitted_by),
    ("h24a_job_antennas_backfill", _backfill_job_antennas),
]


def _ensure_table(engine: Engine) -> None:
    with engine.begin() as conn:
        conn.execute(
            text(
                f"CREATE TABLE IF NOT EXISTS {MIGRATIONS_TABLE} "
                "(name VARCHAR(128) PRIMARY KEY, applied_at VARCHAR(40) NOT NULL)"
            )
        )


def applied_migrations(engine: Engine) -> list[str]:
    """Return the names of the applied steps, in the order they were applied.

    Parameters
    ----------
    engine
        The job store's engine.

    Returns
    -------
    list of str
        Step names.
    """
    _ensure_table(engine)
    with engine.connect() as conn:
        rows = conn.execute(text(f"SELECT name FROM {MIGRATIONS_TABLE} ORDER BY applied_at"))
        return [row[0] for row in rows]


def apply_migrations(
    engine: Engine, steps: list[tuple[str, Callable[[Connection], None]]] | None = None
) -> list[str]:
    """Apply the steps not yet recorded, each in one transaction with its record.

    Parameters
    ----------
    engine
        The job store's engine (tables already created).
    steps
        The steps (default :data:`STEPS`).

    Returns
    -------
    list of str
        The names of the steps this call applied (empty when the schema is current).
    """
    _ensure_table(engine)
    applied: list[str] = []
    done = set(applied_migrations(engine))
    for name, step in STEPS if steps is None else steps:
        if name in done:
            continue
        try:
            with engine.begin() as conn:
                # the record first: a concurrent start-up blocks here, then fails on the key
                conn.execute(
                    text(f"INSERT INTO {MIGRATIONS_TABLE} (name, applied_at) VALUES (:n, :t)"),
                    {"n": name, "t": datetime.now(UTC).isoformat()},
                )
                step(conn)
        except IntegrityError:
            logger.info("schema migration %s was applied by another process", name)
            continue
        logger.info("applied schema migration %s", name)
        applied.append(name)
    return applied
