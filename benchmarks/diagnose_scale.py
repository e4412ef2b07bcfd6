"""Benchmark: ``autocal diagnose`` on a whole HERA file (350 antennas) and on 30 of them.

Targets (issue "Performance and scale"): a whole file of the HERA-size night (350 antennas
x 2 pols x 1536 channels x 192 integrations, 206 M samples) diagnosed in <= 8 GB peak RSS
and <= 10 minutes on the 2-core development machine. One command generates the night's
first file if it is absent or was made by another Tsky engine (``benchmarks/night.py
generate --ntimes 192``, ~1 min; ``night.tsky_mismatch``), runs
``autocal diagnose FILE --out DIR`` in a fresh subprocess for each antenna selection
(wall time and the subprocess's peak RSS, ``ru_maxrss`` from ``wait4``, plus a 0.2 s
sampler of its RSS for the timeline's peak phase) and writes
``benchmarks/results/diagnose_scale.json``::

    .venv/bin/python benchmarks/diagnose_scale.py                 # 30 and 350 antennas
    .venv/bin/python benchmarks/diagnose_scale.py --ants 30       # the comparison run only

``--pythonpath DIR --label NAME`` measures another checkout of autocal (e.g. the code
before a change, exported with ``git archive``) under its own label in the same JSON.
The Tsky cache of the runs is ``DATA/tsky-cache`` (the first run of a grid fills it, the
templates of later runs come from it: their time is reported separately).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "diagnose_scale.json"
DEFAULT_DATA = Path("/tmp/autocal-night-350x1536x192")


def _first_file(data: Path) -> Path:
    """Return the night's first file, generating the one-file night if absent or stale."""
    manifest = data / "night.json"
    stale = None
    if manifest.exists():
        sys.path.insert(0, str(ROOT / "benchmarks"))
        from night import tsky_mismatch

        stale = tsky_mismatch(data)
        if stale is not None:
            print(f"the night in {data} was {stale}", flush=True)
    if not manifest.exists() or stale is not None:
        print(f"generating one file of the HERA-size night into {data} ...", flush=True)
        subprocess.run(
            [
                sys.executable,
                str(ROOT / "benchmarks" / "night.py"),
                "generate",
                "--ntimes",
                "192",
                "--data",
                str(data),
                "--regenerate",
            ],
            check=True,
            cwd=ROOT,
        )
    files = json.loads(manifest.read_text())["files"]
    return Path(files[0])


class _RssSampler(threading.Thread):
    """Sample one process's RSS every 0.2 s (peak and when it happened)."""

    def __init__(self, pid: int) -> None:
        super().__init__(daemon=True)
        self.pid = pid
        self.peak = 0
        self.peak_at = 0.0
        self.samples: list[tuple[float, int]] = []
        self._halt = threading.Event()

    def run(self) -> None:
        t0 = time.perf_counter()
        status = Path(f"/proc/{self.pid}/status")
        while not self._halt.is_set():
            try:
                for line in status.read_text().splitlines():
                    if line.startswith("VmRSS:"):
                        rss = int(line.split()[1]) * 1024
                        now = time.perf_counter() - t0
                        self.samples.append((round(now, 1), rss))
                        if rss > self.peak:
                            self.peak, self.peak_at = rss, now
            except OSError:
                break
            self._halt.wait(0.2)

    def stop(self) -> None:
        self._halt.set()
        self.join()


def run_one(file: Path, nants: int, data: Path, pythonpath: str | None) -> dict:
    """Diagnose the first ``nants`` antennas of ``file`` in a fresh ``autocal`` process."""
    out = data / "diagnose" / f"ants{nants}"
    # the measured autocal: this checkout, or --pythonpath (run outside the checkout, so
    # that "python -m" does not put it first on the path)
    paths = [pythonpath or str(ROOT), os.environ.get("PYTHONPATH", "")]
    env = dict(
        os.environ,
        AUTOCAL_CACHE_DIR=str(data / "tsky-cache"),
        PYTHONPATH=os.pathsep.join(p for p in paths if p),
    )
    cmd = [sys.executable, "-m", "autocal", "diagnose", str(file), "--out", str(out)]
    if nants < 350:
        cmd += ["--antennas", ",".join(str(a) for a in range(nants))]
    print(f"diagnosing {nants} antennas: {' '.join(cmd[2:4])} ... --out {out}", flush=True)
    load = os.getloadavg()
    t0 = time.perf_counter()
    log = (data / f"diagnose-ants{nants}.log").open("w")
    proc = subprocess.Popen(cmd, cwd=data, env=env, stdout=log, stderr=subprocess.STDOUT)
    sampler = _RssSampler(proc.pid)
    sampler.start()
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    sampler.stop()
    log.close()
    row: dict = {
        "antennas": nants,
        "samples": nants * 2 * 1536 * 192,
        "exit_status": os.waitstatus_to_exitcode(status),
        "wall_s": round(wall, 1),
        "peak_rss_gb": round(usage.ru_maxrss * 1024 / 1e9, 2),
        "sampled_peak_rss_gb": round(sampler.peak / 1e9, 2),
        "sampled_peak_at_s": round(sampler.peak_at, 1),
        "cpu_user_s": round(usage.ru_utime, 1),
        "cpu_system_s": round(usage.ru_stime, 1),
        "load_avg_1_5_15_before": [round(x, 2) for x in load],
        "load_avg_1_5_15_after": [round(x, 2) for x in os.getloadavg()],
        "command": " ".join(["autocal", *cmd[3:]]),
        "pythonpath": env["PYTHONPATH"],
        "log": str(data / f"diagnose-ants{nants}.log"),
    }
    summary = out / "summary.json"
    if row["exit_status"] == 0 and summary.exists():
        doc = json.loads(summary.read_text())
        diagnosis = json.loads((out / "diagnosis.json").read_text())
        row["timings_s"] = doc.get("timings_s")
        row["effects"] = doc.get("effects")
        row["negligible"] = diagnosis.get("negligible")
        row["final_reduced_chi2"] = (doc.get("final_gap") or {}).get("reduced_chi2")
        row["outlier_rounds"] = diagnosis["config"].get("outlier_flagging", {}).get("rounds")
        row["screening"] = diagnosis["config"].get("screening")
    print(
        f"  {row['wall_s']} s, peak RSS {row['peak_rss_gb']} GB, exit {row['exit_status']}",
        flush=True,
    )
    return row


def machine() -> dict:
    """Describe the machine (CPU, cores, RAM, versions)."""
    import numpy as np

    cpu, mem = "unknown", 0
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                mem = int(line.split()[1]) * 1024
    except OSError:
        pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "ram_gb": round(mem / 1e9, 1),
        "python": platform.python_version(),
        "numpy": np.__version__,
    }


def main() -> None:
    """Run the benchmark (see the module docstring)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ants", default="30,350", help="antenna counts (30,350)")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="night folder")
    parser.add_argument("--results", type=Path, default=RESULTS, help="JSON to update")
    parser.add_argument("--label", default="current", help="key of the runs in the JSON")
    parser.add_argument("--pythonpath", help="PYTHONPATH of the measured autocal")
    args = parser.parse_args()
    file = _first_file(args.data)
    report = json.loads(args.results.read_text()) if args.results.exists() else {}
    report["file"] = str(file)
    report["machine"] = machine()
    report.setdefault("runs", {})
    runs = report["runs"].setdefault(args.label, {})
    for nants in (int(a) for a in args.ants.split(",")):
        runs[str(nants)] = run_one(file, nants, args.data, args.pythonpath)
        args.results.parent.mkdir(parents=True, exist_ok=True)
        args.results.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {args.results}")


if __name__ == "__main__":
    main()
