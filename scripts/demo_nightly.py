"""Three real nights through the service and the monitoring page (what ``make demo-nightly`` runs).

1. Starts the API (``autocal serve``) and one worker (``autocal worker``) on a fresh SQLite
   store in ``demo-output/nightly``, the data folder's HERA autos as the data root.
2. Submits the nights JD 2458043, 2458044 and 2458045 (7 antennas, 32 minutes each) with
   ``POST /nightly`` and waits for their jobs; the worker records each antenna's values.
3. Prints each night's outliers (``GET /nights/{night}``) and the page's URL (``/ui``).
4. Keeps serving the page until Ctrl-C when run in a terminal (``DEMO_SERVE_S`` seconds
   otherwise, 0 by default), then stops the processes it started.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import shutil
import subprocess
import sys
import time
from pathlib import Path

import httpx
from demo import free_port, stop

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "demo-output" / "nightly"
NIGHTS = (2458043, 2458044, 2458045)


def start(env: dict[str, str], port: int) -> list[subprocess.Popen]:
    logs = OUT / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    commands = {
        "api": ["autocal", "serve", "--host", "127.0.0.1", "--port", str(port)],
        "worker": ["autocal", "worker"],
    }
    return [
        subprocess.Popen(
            command,
            env=env,
            stdout=open(logs / f"{name}.log", "w"),
            stderr=subprocess.STDOUT,
        )
        for name, command in commands.items()
    ]


def wait_healthy(base: str) -> bool:
    for _ in range(120):
        try:
            if httpx.get(f"{base}/health", timeout=2).status_code == 200:
                return True
        except httpx.HTTPError:
            pass
        time.sleep(0.5)
    return False


def run_nights(base: str, headers: dict[str, str]) -> bool:
    job_ids = []
    for night in NIGHTS:
        answer = httpx.post(f"{base}/nightly", json={"night": night}, headers=headers, timeout=60)
        if answer.status_code != 202:
            print(f"night {night} refused: {answer.status_code} {answer.text}", file=sys.stderr)
            return False
        observations = answer.json()["observations"]
        job_ids += [o["job_id"] for o in observations]
        print(f"night {night}: {len(observations)} observation(s) submitted")
    started = time.monotonic()
    while True:
        states = [httpx.get(f"{base}/jobs/{j}", timeout=10).json()["state"] for j in job_ids]
        if all(s in ("succeeded", "failed", "cancelled") for s in states):
            break
        time.sleep(2.0)
    print(f"{len(job_ids)} job(s) finished in {time.monotonic() - started:.0f} s: {states}")
    return True


def report(base: str) -> None:
    for night in NIGHTS:
        detail = httpx.get(f"{base}/nights/{night}", timeout=60).json()
        print(
            f"night {night}: {len(detail['antennas'])} antenna-pol(s) calibrated, "
            f"{len(detail['outliers'])} outlier(s), {len(detail['failed_jobs'])} failed job(s)"
        )
        for outlier in detail["outliers"]:
            print(f"  antenna {outlier['antenna']} {outlier['pol']}: {outlier['reason']}")
        for failed in detail["failed_jobs"]:
            print(f"  failed job {failed['job_id']}: {failed['error']}")
    print(f"monitoring page: {base}/ui   (API: {base}/docs)")


def main() -> int:
    from autocal.io.datasets import data_dir

    root = data_dir()
    if root is None or not list((root / "hera/autos").glob("zen.2458043.*.uvh5")):
        print("the demo needs the data folder (AUTOCAL_DATA_DIR)", file=sys.stderr)
        return 1
    shutil.rmtree(OUT, ignore_errors=True)
    OUT.mkdir(parents=True)
    token, port = secrets.token_hex(16), free_port()
    env = {
        **os.environ,
        "AUTOCAL_STATE_DIR": str(OUT),
        "AUTOCAL_DATABASE_URL": f"sqlite:///{OUT / 'jobs.sqlite'}",
        "AUTOCAL_API_TOKEN": token,
        "AUTOCAL_DATA_ROOTS": json.dumps([str(root / "hera/autos")]),
        "MPLBACKEND": "Agg",
    }
    procs = start(env, port)
    base = f"http://127.0.0.1:{port}"
    try:
        if not wait_healthy(base):
            print(f"the API did not start; see {OUT / 'logs'}", file=sys.stderr)
            return 1
        if not run_nights(base, {"Authorization": f"Bearer {token}"}):
            return 1
        report(base)
        serve_s = float(os.environ.get("DEMO_SERVE_S", "inf" if sys.stdin.isatty() else "0"))
        if serve_s > 0:
            print("serving the page; Ctrl-C stops" if serve_s == float("inf") else "")
            with contextlib.suppress(KeyboardInterrupt):
                time.sleep(min(serve_s, 10**7))
        return 0
    finally:
        stop(procs)


if __name__ == "__main__":
    sys.exit(main())
