"""Benchmark: ``GET /jobs?limit=1`` against the number of jobs in the store.

Fills a fresh job store (SQLite in a temporary folder, or a fresh schema of a PostgreSQL
database with ``--postgres URL``) with N jobs shaped like real ones (a configuration with
inputs, a 60-line log tail, a result), then times ``GET /jobs?limit=1`` and
``GET /jobs?limit=1&state=failed`` through the application (FastAPI's test client, so the
whole request path is timed) and records the peak of Python allocations during one call
(tracemalloc). Median of ``--repeats`` calls. Usage::

    python benchmarks/service_list.py [--sizes 1000,5000,20000] [--repeats 5]
                                      [--postgres postgresql+psycopg://user:pw@host/db]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
import tracemalloc
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

from fastapi.testclient import TestClient
from sqlalchemy import create_engine, insert, text

from autocal.service.app import create_app
from autocal.service.settings import Settings
from autocal.service.store import Job, JobStore

LOG = "\n".join(f"2026-11-27T12:00:{i:02d} step {i}: " + "x" * 80 for i in range(60))
STATES = ("succeeded", "succeeded", "succeeded", "failed", "cancelled")


def _rows(count: int, start: int) -> list[dict[str, Any]]:
    t0 = datetime(2026, 1, 1, tzinfo=UTC)
    rows = []
    for i in range(start, start + count):
        rows.append(
            {
                "id": uuid.uuid4().hex,
                "kind": "calibrate",
                "state": STATES[i % len(STATES)],
                "config": {
                    "inputs": [f"/data/hera/night/zen.{2459000 + i}.{j}.uvh5" for j in range(4)]
                },
                "night": 2459000 + i // 50,
                "antennas": [i % 350, (i + 1) % 350],
                "created_at": t0 + timedelta(seconds=i),
                "log": LOG,
                "result": {"solution": {"chi2": 1.0 + i * 1e-6}},
                "progress": 1.0,
                "message": "done",
                "attempts": 1,
                "max_attempts": 3,
                "cancel_requested": False,
                "completions": 1,
            }
        )
    return rows


def fill(store: JobStore, total: int) -> None:
    """Add jobs until the store holds ``total``."""
    have = store.count()
    with store.engine.begin() as conn:
        for start in range(have, total, 1000):
            conn.execute(insert(Job), _rows(min(1000, total - start), start))


def time_call(client: TestClient, url: str, repeats: int) -> tuple[float, float]:
    """Median seconds of ``repeats`` calls and peak MB allocated by one."""
    client.get(url).raise_for_status()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        client.get(url).raise_for_status()
        times.append(time.perf_counter() - t0)
    tracemalloc.start()
    client.get(url)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return statistics.median(times), peak / 1e6


@contextmanager
def database(postgres: str | None, folder: Path) -> Iterator[str]:
    """Yield an empty database URL."""
    if not postgres:
        yield f"sqlite:///{folder / 'jobs.sqlite'}"
        return
    schema = f"bench_{uuid.uuid4().hex[:10]}"
    admin = create_engine(postgres)
    with admin.begin() as conn:
        conn.execute(text(f'CREATE SCHEMA "{schema}"'))
    try:
        sep = "&" if "?" in postgres else "?"
        yield f"{postgres}{sep}options=-csearch_path%3D{schema}"
    finally:
        with admin.begin() as conn:
            conn.execute(text(f'DROP SCHEMA "{schema}" CASCADE'))
        admin.dispose()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="1000,5000,20000")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--postgres", default="")
    args = parser.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    with tempfile.TemporaryDirectory() as tmp, database(args.postgres, Path(tmp)) as url:
        settings = Settings(state_dir=Path(tmp), data_roots=[Path(tmp)], database_url=url)
        store = JobStore(url)
        client = TestClient(create_app(settings, store))
        backend = "PostgreSQL" if args.postgres else "SQLite"
        print(f"| {backend} jobs | GET /jobs?limit=1 | peak alloc | ?state=failed&limit=1 |")
        print("|---|---|---|---|")
        for size in sizes:
            fill(store, size)
            t_all, mb_all = time_call(client, "/jobs?limit=1", args.repeats)
            t_state, _ = time_call(client, "/jobs?limit=1&state=failed", args.repeats)
            print(
                f"| {size} | {t_all * 1e3:.1f} ms | {mb_all:.1f} MB | {t_state * 1e3:.1f} ms |",
                flush=True,
            )
        store.engine.dispose()


if __name__ == "__main__":
    main()
