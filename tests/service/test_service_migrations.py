"""Schema migrations of the job store (autocal.service.migrations), SQLite and PostgreSQL."""

from __future__ import annotations

from pathlib import Path

from sqlalchemy import inspect, text

from autocal.service.migrations import MIGRATIONS, apply_migrations
from autocal.service.store import JobState, JobStore
from tests.service.test_service_store import db_url  # noqa: F401  (fixture)


def _columns(store: JobStore) -> set[str]:
    return {c["name"] for c in inspect(store.engine).get_columns("jobs")}


def test_an_older_database_is_brought_up_to_date_once(db_url: str) -> None:  # noqa: F811
    names = [m.name for m in MIGRATIONS]
    store = JobStore(db_url)
    assert {"releases", "input_fingerprints"} <= _columns(store)
    old, _ = store.submit({"inputs": ["/d/a.uvh5"]})
    # make it a database of before the migrations: drop their columns and their records
    with store.engine.begin() as conn:
        conn.execute(text('ALTER TABLE jobs DROP COLUMN "releases"'))
        conn.execute(text('ALTER TABLE jobs DROP COLUMN "input_fingerprints"'))
        conn.execute(text("DELETE FROM schema_migrations"))
    store.engine.dispose()

    upgraded = JobStore(db_url)  # start-up applies the missing steps
    assert {"releases", "input_fingerprints"} <= _columns(upgraded)
    with upgraded.engine.connect() as conn:
        recorded = list(conn.scalars(text("SELECT name FROM schema_migrations ORDER BY name")))
    assert sorted(recorded) == sorted(names)
    rec = upgraded.get(old["id"])
    assert rec["releases"] == 0 and rec["input_fingerprints"] is None  # existing rows
    claimed = upgraded.claim("w1")
    assert upgraded.release(claimed["id"], "w1", 1, "restart")
    assert upgraded.get(old["id"])["releases"] == 1
    assert upgraded.get(old["id"])["state"] == JobState.queued.value
    assert apply_migrations(upgraded.engine) == []  # recorded: never applied twice
    upgraded.engine.dispose()


def test_a_fresh_database_records_the_steps_without_changing_anything(tmp_path: Path) -> None:
    store = JobStore(f"sqlite:///{tmp_path / 'jobs.sqlite'}")
    with store.engine.connect() as conn:
        recorded = set(conn.scalars(text("SELECT name FROM schema_migrations")))
    assert recorded == {m.name for m in MIGRATIONS}
    store.engine.dispose()
