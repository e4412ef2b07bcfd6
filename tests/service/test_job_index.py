"""Listing jobs page by page (autocal.service.job_index) and the store's migrations.

The cost of ``GET /jobs`` must not grow with the table: the tests count the job rows the
store loads for one page and read SQLite's query plan (an index, no sort of the table),
rather than timing anything (``benchmarks/service_list.py`` measures the time).
"""

from __future__ import annotations

from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from sqlalchemy import Column, MetaData, Table, create_engine, event, inspect, update

from autocal.service.job_index import (
    CursorError,
    JobAntenna,
    decode_cursor,
    encode_cursor,
    list_page,
)
from autocal.service.migrations import MIGRATIONS, applied_migrations, apply_migrations
from autocal.service.store import Job, JobStore
from tests.service.test_service_store import database_url


@pytest.fixture(params=["sqlite", "postgresql"])
def store(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[JobStore]:
    with database_url(request.param, tmp_path / "db") as url:
        s = JobStore(url)
        yield s
        s.engine.dispose()


def _fill(store: JobStore, count: int) -> list[dict]:
    """Queue ``count`` jobs: kinds, nights and antennas vary, every 5th over all antennas."""
    jobs = []
    for i in range(count):
        job, _ = store.submit(
            {"i": i},
            kind="diagnose" if i % 3 == 0 else "calibrate",
            night=2459000 + i % 4,
            antennas=None if i % 5 == 0 else [i % 7, 10 + i % 2],
        )
        jobs.append(job)
    return jobs


class LoadCounter:
    """Count the Job rows the ORM loads (each one a row read from the table)."""

    def __init__(self) -> None:
        self.count = 0

    def __call__(self, *_args: object) -> None:
        self.count += 1


def test_one_page_loads_only_its_rows(store: JobStore) -> None:
    _fill(store, 60)
    counter = LoadCounter()
    event.listen(Job, "load", counter)
    try:
        for filters in ({}, {"state": "queued"}, {"kind": "calibrate"}, {"antenna": 3}):
            counter.count = 0
            jobs = store.list(limit=1, **filters)
            assert len(jobs) == 1
            # the page and the one row that tells whether another page follows
            assert counter.count <= 2, (filters, counter.count)
    finally:
        event.remove(Job, "load", counter)


def _plan(store: JobStore, **filters: object) -> str:
    """SQLite's query plan of the listing statement with ``filters``."""
    statements: list[tuple[str, object]] = []

    def capture(_conn, _cursor, statement, parameters, _context, _many) -> None:
        if "FROM jobs" in statement and "ORDER BY" in statement:
            statements.append((statement, parameters))

    event.listen(store.engine, "before_cursor_execute", capture)
    try:
        store.list(limit=5, **filters)
    finally:
        event.remove(store.engine, "before_cursor_execute", capture)
    statement, parameters = statements[-1]
    assert "LIMIT" in statement
    with store.engine.connect() as conn:
        rows = conn.exec_driver_sql(f"EXPLAIN QUERY PLAN {statement}", parameters).fetchall()
    return "\n".join(str(row[-1]) for row in rows)


@pytest.mark.parametrize(
    ("filters", "index"),
    [
        ({}, "ix_jobs_created_id"),
        ({"state": "queued"}, "ix_jobs_state_created"),
        ({"kind": "diagnose"}, "ix_jobs_kind_created"),
        ({"night": 2459001}, "ix_jobs_night_created"),
        ({"antenna": 3}, "ix_job_antennas_antenna_created"),
    ],
)
def test_the_listing_walks_an_index_without_sorting(
    tmp_path: Path, filters: dict, index: str
) -> None:
    store = JobStore(f"sqlite:///{tmp_path / 'jobs.sqlite'}")
    _fill(store, 30)
    plan = _plan(store, **filters)
    assert index in plan, plan
    if "antenna" not in filters:  # two index ranges (the antenna and 'all') are merged
        assert "TEMP B-TREE" not in plan, plan
    store.engine.dispose()


@pytest.mark.parametrize(
    "filters",
    [{}, {"state": "queued"}, {"kind": "calibrate"}, {"night": 2459002}, {"antenna": 3}],
)
def test_pages_cover_every_matching_job_once_newest_first(store: JobStore, filters: dict) -> None:
    jobs = _fill(store, 23)
    # jobs created at the same instant are ordered by id, so no page boundary loses one
    same = datetime(2026, 1, 1, tzinfo=UTC)
    tied = [job["id"] for job in jobs[5:12]]
    with store.engine.begin() as conn:
        conn.execute(update(Job).where(Job.id.in_(tied)).values(created_at=same))
        conn.execute(update(JobAntenna).where(JobAntenna.job_id.in_(tied)).values(created_at=same))
    expected = [j["id"] for j in store.list(limit=1000, **filters)]
    seen, after = [], None
    for _ in range(len(jobs) + 1):
        page, after = store.page(limit=4, after=after, **filters)
        seen += [j["id"] for j in page]
        if after is None:
            break
        after = decode_cursor(encode_cursor(*after))  # through the client and back
    assert seen == expected
    assert len(set(seen)) == len(seen)
    antenna = filters.get("antenna")
    matching = [
        j
        for j in jobs
        if all(j[k] == v for k, v in filters.items() if k != "antenna")
        and (antenna is None or j["antennas"] is None or antenna in j["antennas"])
    ]
    assert sorted(seen) == sorted(j["id"] for j in matching)


def test_a_cursor_not_issued_by_the_service_is_refused() -> None:
    stamp = datetime(2026, 11, 27, 12, tzinfo=UTC)
    assert decode_cursor(encode_cursor(stamp, "abc")) == (stamp, "abc")
    for bad in ("", "!!!", "bm90IGpzb24", encode_cursor(stamp, "x")[:-3]):
        with pytest.raises(CursorError, match="cursor"):
            decode_cursor(bad)


# migrations -------------------------------------------------------------------------------


def _old_schema(url: str) -> None:
    """Create the jobs table as it was before the migrations (no columns or indexes of theirs)."""
    engine = create_engine(url)
    metadata = MetaData()
    columns = [
        Column(c.name, c.type, primary_key=c.primary_key, nullable=c.nullable)
        for c in Job.__table__.columns
        if c.name not in {"submitted_by", "releases", "input_fingerprints"}
    ]
    old = Table("jobs", metadata, *columns)
    metadata.create_all(engine)
    t0 = datetime(2026, 1, 1, tzinfo=UTC)
    with engine.begin() as conn:
        for i, antennas in enumerate([[1, 2], None, [2, 3]]):
            conn.execute(
                old.insert().values(
                    id=f"old{i}",
                    kind="calibrate",
                    state="succeeded",
                    config={},
                    antennas=antennas,
                    created_at=t0 + timedelta(minutes=i),
                    progress=1.0,
                    message="",
                    log="",
                    attempts=1,
                    max_attempts=3,
                    cancel_requested=False,
                    completions=1,
                )
            )
    engine.dispose()


def test_an_existing_store_is_migrated_once(tmp_path: Path) -> None:
    for backend in ("sqlite", "postgresql"):
        try:
            context = database_url(backend, tmp_path / backend)
            url = context.__enter__()
        except pytest.skip.Exception:
            continue
        try:
            _old_schema(url)
            store = JobStore(url)
            names = [m.name for m in MIGRATIONS]
            assert applied_migrations(store.engine) == names
            inspector = inspect(store.engine)
            assert "submitted_by" in {c["name"] for c in inspector.get_columns("jobs")}
            indexes = {i["name"] for i in inspector.get_indexes("jobs")}
            assert {"ix_jobs_created_id", "ix_jobs_state_created"} <= indexes
            # the old jobs' antennas were indexed: antenna 2 is in old0 and old2, and old1
            # is over every antenna
            assert [j["id"] for j in store.list(antenna=2)] == ["old2", "old1", "old0"]
            assert [j["id"] for j in store.list(antenna=1)] == ["old1", "old0"]
            job, _ = store.submit({}, antennas=[5], submitted_by="alice")
            assert store.get(job["id"])["submitted_by"] == "alice"
            store.engine.dispose()
            again = JobStore(url)  # a restart applies nothing
            assert apply_migrations(again.engine) == []
            assert applied_migrations(again.engine) == names
            again.engine.dispose()
        finally:
            context.__exit__(None, None, None)


def test_a_new_store_records_every_step(tmp_path: Path) -> None:
    store = JobStore(f"sqlite:///{tmp_path / 'jobs.sqlite'}")
    assert applied_migrations(store.engine) == [m.name for m in MIGRATIONS]
    store.engine.dispose()


def test_listing_uses_the_helpers_index_rows(tmp_path: Path) -> None:
    store = JobStore(f"sqlite:///{tmp_path / 'jobs.sqlite'}")
    _fill(store, 6)
    with store.session() as s:
        page, after = list_page(s, antenna=10, limit=100)
    assert after is None
    assert all(j.antennas is None or 10 in j.antennas for j in page)
    store.engine.dispose()
