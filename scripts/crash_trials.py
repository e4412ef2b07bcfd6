"""Crash trials of the service: workers killed (-9) or stopped (SIGTERM/SIGINT) mid-job.

Starts a real API (``autocal serve``, loopback) and worker processes (``autocal worker``)
on a temporary state folder and a SQLite or PostgreSQL job store, submits jobs over HTTP
on a small simulated observation, then, trial after trial, signals a worker that is
running a job at a random moment of it and starts a replacement. A client polls the API
all along. At the end the queue is drained and the script prints, as one JSON line:

- ``trials``, ``kills``, ``stops``: signals sent (SIGKILL; SIGTERM or SIGINT);
- ``jobs``, ``succeeded``, ``lost`` (jobs that did not succeed), ``duplicated`` (extra
  completions), ``releases`` and ``counted_attempts``;
- ``requests`` and ``server_errors`` (5xx answers of the API);
- ``orphans_before`` / ``orphans_after``: ``.staging-*`` folders and ``*.part`` files in
  the products folder before and after the janitor of a new worker.

Bounded by ``--trials`` and ``--timeout``; every process is stopped at the end. Example::

    python scripts/crash_trials.py --backend sqlite --trials 20 --jobs 12 --mode mixed
    python scripts/crash_trials.py --backend postgresql \\
        --database-url postgresql+psycopg://autocal:autocal@127.0.0.1:5432/autocal_test
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx

TOKEN = "crash-trials-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
FINAL = {"succeeded", "failed", "cancelled"}


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _observation(folder: Path) -> Path:
    from autocal.io.uvh5 import write_uvh5
    from autocal.simulate.mock import SimulationConfig, simulate

    obs, _ = simulate(
        SimulationConfig(beam="dipole", channel_width_khz=4000, duration_h=4, cadence_s=900)
    )
    return write_uvh5(obs, folder / "zen.2458098.50000.HH.uvh5")


class Cluster:
    """The API and worker processes of one run, sharing a state folder and a store."""

    def __init__(self, root: Path, url: str, data: Path, max_attempts: int) -> None:
        self.root = root
        self.port = _free_port()
        self.base = f"http://127.0.0.1:{self.port}"
        self.env = {k: v for k, v in os.environ.items() if not k.startswith("AUTOCAL_")}
        self.env.update(
            AUTOCAL_STATE_DIR=str(root / "state"),
            AUTOCAL_DATABASE_URL=url,
            AUTOCAL_DATA_ROOTS=str(data),
            AUTOCAL_API_TOKEN=TOKEN,
            AUTOCAL_HEARTBEAT_S="0.5",
            AUTOCAL_STALE_AFTER_S="3",
            AUTOCAL_MAX_ATTEMPTS=str(max_attempts),
            AUTOCAL_CACHE_DIR="off",
            MPLBACKEND="Agg",
        )
        self.logs = root / "logs"
        self.logs.mkdir(parents=True)
        self.api: subprocess.Popen | None = None
        self.workers: dict[str, subprocess.Popen] = {}
        self.count = 0

    def _spawn(self, name: str, *args: str, env: dict[str, str] | None = None) -> subprocess.Popen:
        log = open(self.logs / f"{name}.log", "wb")  # noqa: SIM115 (the process owns it)
        return subprocess.Popen(
            [sys.executable, "-m", "autocal.cli.main", *args],
            env={**self.env, **(env or {})},
            stdout=log,
            stderr=subprocess.STDOUT,
        )

    def start_api(self) -> None:
        self.api = self._spawn("api", "serve", "--port", str(self.port))
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline:
            try:
                if httpx.get(f"{self.base}/health", timeout=2).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        raise RuntimeError(f"the API did not start (see {self.logs / 'api.log'})")

    def start_worker(self, *args: str, **env: str) -> str:
        self.count += 1
        name = f"w{self.count}"
        cmd = ["worker", "--id", name, "--poll", "0.2", *args]
        self.workers[name] = self._spawn(name, *cmd, env=env)
        return name

    def stop_all(self) -> None:
        procs = [*self.workers.values(), *([self.api] if self.api else [])]
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
        for proc in procs:
            proc.wait(30)


class Poller(threading.Thread):
    """A client reading the job list and every job while the trials run."""

    def __init__(self, base: str, ids: list[str]) -> None:
        super().__init__(daemon=True)
        self.base, self.ids = base, ids
        self.requests = self.server_errors = self.transport_errors = 0
        self.stop = threading.Event()

    def run(self) -> None:
        with httpx.Client(base_url=self.base, timeout=30) as http:
            while not self.stop.wait(0.2):
                for path in ["/jobs?limit=50", *(f"/jobs/{i}" for i in self.ids)]:
                    self.requests += 1
                    try:
                        if http.get(path).status_code >= 500:
                            self.server_errors += 1
                    except httpx.TransportError:  # no complete answer at all
                        self.transport_errors += 1


def _orphans(products: Path) -> int:
    if not products.is_dir():
        return 0
    staging = [p for p in products.glob("*/attempt-*/.staging-*")]
    partial = [p for p in products.glob("*/attempt-*/*.part")]
    return len(staging) + len(partial)


def _running_on(store: Any, names: set[str]) -> list[str]:
    return [j["worker"] for j in store.list(state="running", limit=1000) if j["worker"] in names]


def _trials(args: argparse.Namespace, cluster: Cluster, store: Any, rng: random.Random) -> dict:
    kills = stops = slow_stops = 0
    deadline = time.monotonic() + args.timeout
    for _ in range(args.trials):
        busy: list[str] = []
        while not busy and time.monotonic() < deadline:
            busy = _running_on(store, set(cluster.workers))
            if store.count("queued") == 0 and not busy:
                break
            time.sleep(0.1)
        if not busy:
            break
        victim = rng.choice(busy)
        time.sleep(rng.uniform(0.0, args.max_delay))
        mode = args.mode if args.mode != "mixed" else rng.choice(["kill", "term"])
        proc = cluster.workers.pop(victim)
        if mode == "kill":
            proc.kill()
            kills += 1
        else:
            proc.send_signal(rng.choice([signal.SIGTERM, signal.SIGINT]))
            stops += 1
        try:  # the job is handed back at once; the process exits at the job's next checkpoint
            proc.wait(args.grace)
        except subprocess.TimeoutExpired:  # as systemd after TimeoutStopSec
            proc.kill()
            proc.wait(60)
            slow_stops += 1
        cluster.start_worker()
    return {
        "trials": kills + stops,
        "kills": kills,
        "stops": stops,
        "killed_after_grace": slow_stops,
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Run the trials; return the figures."""
    from autocal.service.store import JobStore

    rng = random.Random(args.seed)
    root = Path(tempfile.mkdtemp(prefix="autocal-crash-"))
    data = root / "data"
    data.mkdir()
    obs = _observation(data)
    url = args.database_url or f"sqlite:///{root / 'jobs.sqlite'}"
    store = JobStore(url)
    cluster = Cluster(root, url, data, args.max_attempts)
    poller: Poller | None = None
    try:
        cluster.start_api()
        ids = []
        for i in range(args.jobs):
            body = {"inputs": [str(obs)], "beam": "dipole", "nside": 128, "tgnd_k": 200 + i}
            answer = httpx.post(f"{cluster.base}/jobs", json=body, headers=AUTH, timeout=60)
            answer.raise_for_status()
            ids.append(answer.json()["id"])
        poller = Poller(cluster.base, ids)
        poller.start()
        for _ in range(args.workers):
            cluster.start_worker()
        figures = _trials(args, cluster, store, rng)
        deadline = time.monotonic() + args.timeout
        while time.monotonic() < deadline and any(store.get(i)["state"] not in FINAL for i in ids):
            time.sleep(0.5)
        poller.stop.set()
        poller.join(30)
        orphans_before = _orphans(root / "state" / "jobs")
        janitor = cluster.start_worker("--once", AUTOCAL_JANITOR_AFTER_S="0.001")
        cluster.workers[janitor].wait(120)
        jobs = [store.get(i) for i in ids]
        figures.update(
            backend=store.engine.dialect.name,
            jobs=len(jobs),
            succeeded=sum(j["state"] == "succeeded" for j in jobs),
            lost=sum(j["state"] != "succeeded" for j in jobs),
            duplicated=sum(max(j["completions"] - 1, 0) for j in jobs),
            releases=sum(j["releases"] for j in jobs),
            counted_attempts=sum(j["attempts"] - j["releases"] for j in jobs),
            requests=poller.requests,
            server_errors=poller.server_errors,
            transport_errors=poller.transport_errors,
            orphans_before=orphans_before,
            orphans_after=_orphans(root / "state" / "jobs"),
            errors=sorted({j["error"] for j in jobs if j["error"]}),
        )
        return figures
    finally:
        if poller is not None:
            poller.stop.set()
        cluster.stop_all()
        store.engine.dispose()
        if not args.keep:
            import shutil

            shutil.rmtree(root, ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    """Parse the options, run the trials, print the figures; exit 1 on a lost job."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--backend", choices=["sqlite", "postgresql"], default="sqlite")
    parser.add_argument("--database-url", default="", help="PostgreSQL URL (a fresh schema)")
    parser.add_argument("--trials", type=int, default=20)
    parser.add_argument("--jobs", type=int, default=12)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--mode", choices=["kill", "term", "mixed"], default="mixed")
    parser.add_argument("--max-delay", type=float, default=3.0, help="seconds before a signal")
    parser.add_argument("--max-attempts", type=int, default=50)
    parser.add_argument("--grace", type=float, default=120.0, help="seconds before SIGKILL")
    parser.add_argument("--timeout", type=float, default=900.0)
    parser.add_argument("--seed", type=int, default=24)
    parser.add_argument("--keep", action="store_true", help="keep the temporary folder")
    args = parser.parse_args(argv)
    if args.backend == "postgresql":
        if not args.database_url:
            parser.error("--backend postgresql needs --database-url")
        from tests.service.test_service_store import postgres_schema

        with postgres_schema(args.database_url) as url:
            args.database_url = url
            figures = run(args)
    else:
        args.database_url = ""
        figures = run(args)
    print(json.dumps(figures))
    return 0 if figures["lost"] == 0 and figures["duplicated"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
