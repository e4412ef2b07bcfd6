"""The main job end to end through the service (what ``make demo`` runs).

1. Picks the input: the real HERA observation JD 2458116 (antenna 23, 31 minutes) when the
   data folder is present, otherwise a simulated one made with ``autocal simulate``.
2. Starts the API (``autocal serve``) and one worker (``autocal worker``) on a private
   SQLite store in ``demo-output/service``.
3. Submits the calibration over HTTP (``POST /jobs`` with the API token), polls
   ``GET /jobs/{id}`` until it finishes, prints the result summary (``GET
   /jobs/{id}/results``) and where the products are.
4. Stops the processes it started.
"""

from __future__ import annotations

import json
import os
import secrets
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "demo-output" / "service"


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def stop(procs: list[subprocess.Popen]) -> None:
    """Stop the API and worker processes (SIGTERM, then kill after 20 s)."""
    for proc in procs:
        proc.send_signal(signal.SIGTERM)
    for proc in procs:
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
    print("stopped the API and the worker")


def pick_inputs(env: dict[str, str]) -> tuple[list[str], dict]:
    from autocal.io.datasets import data_dir

    root = data_dir()
    if root is not None and list((root / "hera/autos").glob("zen.2458116.*.HH.uvh5")):
        files = sorted(str(p) for p in (root / "hera/autos").glob("zen.2458116.*.HH.uvh5"))
        refs = sorted(
            str(p)
            for p in (root / "hera/reference_gains").glob("zen.2458116.*.flagged_abs.calfits")
        )
        print(f"input: real HERA data JD 2458116 ({len(files)} files), reference: abscal")
        return files, {"antennas": [23], "freq_range_mhz": [110.0, 190.0], "reference": refs}
    sim = OUT / "inputs" / "mock.uvh5"
    if not sim.exists():
        subprocess.run(
            [
                "autocal",
                "simulate",
                "--beam",
                "dipole",
                "--antennas",
                "0,1",
                "--pols",
                "ee,nn",
                "--duration",
                "8",
                "--channel-width",
                "1000",
                "--out",
                str(sim),
            ],
            check=True,
            env=env,
        )
    print(f"input: simulated observation {sim}")
    return [str(sim)], {"beam": "dipole"}


def main() -> int:
    OUT.mkdir(parents=True, exist_ok=True)
    token = secrets.token_hex(16)
    port = free_port()
    env = {
        **os.environ,
        "AUTOCAL_STATE_DIR": str(OUT),
        "AUTOCAL_DATABASE_URL": f"sqlite:///{OUT / 'jobs.sqlite'}",
        "AUTOCAL_API_TOKEN": token,
        "AUTOCAL_HEARTBEAT_S": "2",
        "MPLBACKEND": "Agg",
    }
    inputs, options = pick_inputs(env)
    roots = {str(Path(p).resolve().parent) for p in inputs + options.get("reference", [])}
    env["AUTOCAL_DATA_ROOTS"] = json.dumps(sorted(roots))
    logs = OUT / "logs"
    logs.mkdir(exist_ok=True)
    procs = [
        subprocess.Popen(
            ["autocal", "serve", "--host", "127.0.0.1", "--port", str(port)],
            env=env,
            stdout=open(logs / "api.log", "w"),  # noqa: SIM115
            stderr=subprocess.STDOUT,
        ),
        subprocess.Popen(
            ["autocal", "worker"],
            env=env,
            stdout=open(logs / "worker.log", "w"),  # noqa: SIM115
            stderr=subprocess.STDOUT,
        ),
    ]
    base = f"http://127.0.0.1:{port}"
    headers = {"Authorization": f"Bearer {token}"}
    try:
        for _ in range(120):
            try:
                if httpx.get(f"{base}/health", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            time.sleep(0.5)
        else:
            print(f"the API did not start; see {logs / 'api.log'}", file=sys.stderr)
            return 1
        print(f"API on {base} (docs: {base}/docs), worker started; store {OUT / 'jobs.sqlite'}")
        body = {"kind": "calibrate", "inputs": inputs, "force": True, **options}
        response = httpx.post(f"{base}/jobs", json=body, headers=headers, timeout=30)
        if response.status_code != 202:
            print(f"submission refused: {response.status_code} {response.text}", file=sys.stderr)
            return 1
        job_id = response.json()["id"]
        print(f"submitted job {job_id}")
        last = ""
        while True:
            job = httpx.get(f"{base}/jobs/{job_id}", timeout=10).json()
            done = 100 * (job.get("progress") or 0)
            line = f"  {job['state']:<9} {done:5.1f}%  {job.get('message', '')}"
            if line != last:
                print(line[:110])
                last = line
            if job["state"] in ("succeeded", "failed", "cancelled"):
                break
            time.sleep(1.0)
        if job["state"] != "succeeded":
            print(f"job {job['state']}: {job.get('error')}", file=sys.stderr)
            return 1
        results = httpx.get(f"{base}/jobs/{job_id}/results", timeout=30).json()
        print(json.dumps(results.get("summary", results.get("solution", {})), indent=2)[:2000])
        for sol in results.get("solutions", []):
            if sol.get("separation"):
                print(sol["separation"]["message"])
        for row in (results.get("comparison") or {}).get("per_antenna_pol", []):
            stable = {True: "stable", False: "UNSTABLE", None: "untested"}[row["reference_stable"]]
            print(
                f"|g| / abscal, ant {row['antenna']} {row['pol']}: mean {row['ratio_mean']:.3f}, "
                f"offset {row['offset']:+.3f} +- {row['offset_error']:.3f} "
                f"({row['offset_sigma']:+.1f} sigma); reference {stable} "
                f"(drift {100 * (row['reference_drift'] or 0):+.0f} %)"
            )
        folder = OUT / "jobs" / job_id / f"attempt-{job['attempts']}"
        print(f"products in {folder}:")
        for name, url in sorted((job.get("products") or {}).items()):
            print(f"  {name:<14} {base}{url}")
        print(f"job record: {base}/jobs/{job_id}")
        return 0
    finally:
        stop(procs)


if __name__ == "__main__":
    sys.exit(main())
