"""Benchmark: how long a fresh ``autocal`` process takes to answer ``--help`` or a usage error.

Target (issue 25, item 5): parsing arguments and reporting a usage error take <= 0.5 s in a
fresh process. Each case is run ``--runs`` times as a new ``python -m autocal ...`` process
(``python -c "import autocal"`` for the import alone, ``python -c pass`` for the interpreter
itself), the cases interleaved round by round so that a change of load hits all of them;
min / median / max wall times, the CPU time of each process (user + system, from ``wait4``:
what other processes on a shared machine inflate least), the load average before and after,
and ``-X importtime``'s cumulative figures (wall clock) for the imports of one ``--help`` run
go to
``benchmarks/results/startup.md`` and ``.json``::

    python benchmarks/startup.py                 # this checkout, 7 runs per case
    python benchmarks/startup.py --pythonpath /tmp/old --label before   # another checkout

``--pythonpath`` puts another checkout of autocal first on the path (e.g. the code before a
change, exported with ``git archive``), so before and after are measured by the same script.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"

#: name -> arguments after the interpreter; expected exit status.
CASES: dict[str, tuple[list[str], int]] = {
    "python -c pass (interpreter alone)": (["-c", "pass"], 0),
    "import autocal": (["-c", "import autocal"], 0),
    "autocal --help": (["-m", "autocal", "--help"], 0),
    "autocal calibrate --help": (["-m", "autocal", "calibrate", "--help"], 0),
    "autocal nightly --help": (["-m", "autocal", "nightly", "--help"], 0),
    "unknown option: autocal calibrate x.uvh5 --out o --bogus": (
        ["-m", "autocal", "calibrate", "x.uvh5", "--out", "o", "--bogus"],
        2,
    ),
    "missing argument: autocal calibrate": (["-m", "autocal", "calibrate"], 2),
    "bad value (argparse): autocal tsky --nside abc": (
        ["-m", "autocal", "tsky", "--nside", "abc"],
        2,
    ),
    "bad value (autocal's check): autocal calibrate x.uvh5 --out o --antennas a,b": (
        ["-m", "autocal", "calibrate", "x.uvh5", "--out", "o", "--antennas", "a,b"],
        2,
    ),
    "bad value (configuration's check): autocal calibrate x.uvh5 --out o --nside 3": (
        ["-m", "autocal", "calibrate", "x.uvh5", "--out", "o", "--nside", "3"],
        2,
    ),
}


def _environ(pythonpath: str | None) -> dict[str, str]:
    env = dict(os.environ)
    path = pythonpath or str(ROOT)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (path, env.get("PYTHONPATH")) if p)
    env.setdefault("MPLBACKEND", "Agg")
    return env


def time_once(args: list[str], status: int, env: dict[str, str], cwd: str) -> tuple[float, float]:
    """Wall time and CPU time (user + system, from ``wait4``) of one fresh process (s)."""
    start = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, *args],
        env=env,
        cwd=cwd,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    _, code, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - start
    stderr = proc.stderr.read().decode() if proc.stderr else ""
    if os.waitstatus_to_exitcode(code) != status:
        raise SystemExit(
            f"{args}: exit {os.waitstatus_to_exitcode(code)}, expected {status}\n{stderr}"
        )
    return wall, usage.ru_utime + usage.ru_stime


def import_times(env: dict[str, str], cwd: str, top: int = 12) -> list[dict]:
    """``-X importtime`` of one ``autocal --help``: the largest cumulative imports (ms)."""
    done = subprocess.run(
        [sys.executable, "-X", "importtime", "-m", "autocal", "--help"],
        env=env,
        cwd=cwd,
        capture_output=True,
        text=True,
        check=True,
    )
    rows = []
    for line in done.stderr.splitlines():
        if not line.startswith("import time:") or "cumulative" in line:
            continue
        _, own, cumulative, name = (part.strip() for part in line.replace(":", "|", 1).split("|"))
        rows.append(
            {"module": name, "cumulative_ms": int(cumulative) / 1e3, "self_ms": int(own) / 1e3}
        )
    total = sum(r["self_ms"] for r in rows)
    rows.sort(key=lambda r: -r["cumulative_ms"])
    return [
        {"module": "(all imports, sum of self)", "cumulative_ms": total, "self_ms": total},
        *rows[:top],
    ]


def measure(runs: int, pythonpath: str | None) -> dict:
    """Time every case ``runs`` times, interleaved; return the report."""
    env = _environ(pythonpath)
    cwd = "/tmp"  # not the checkout: only PYTHONPATH decides which autocal is imported
    load_before = os.getloadavg()
    walls: dict[str, list[float]] = {name: [] for name in CASES}
    cpus: dict[str, list[float]] = {name: [] for name in CASES}
    for _ in range(runs):
        for name, (args, status) in CASES.items():
            wall, cpu = time_once(args, status, env, cwd)
            walls[name].append(wall)
            cpus[name].append(cpu)
    load_after = os.getloadavg()
    rows = {
        name: {
            "min_s": min(w),
            "median_s": statistics.median(w),
            "max_s": max(w),
            "cpu_min_s": min(cpus[name]),
            "cpu_median_s": statistics.median(cpus[name]),
            "runs": len(w),
        }
        for name, w in walls.items()
    }
    return {
        "rows": rows,
        "importtime_help": import_times(env, cwd),
        "load_before": load_before,
        "load_after": load_after,
        "machine": {
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
            "platform": platform.platform(),
        },
        "pythonpath": pythonpath or str(ROOT),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
    }


def markdown(reports: dict[str, dict]) -> str:
    """The reports (one per label) as markdown tables."""
    lines = ["# Fresh-process start-up of `autocal` (`python benchmarks/startup.py`)", ""]
    for label, report in reports.items():
        lb, la = report["load_before"], report["load_after"]
        lines += [
            f"## {label}: {report['pythonpath']} ({report['date']})",
            "",
            f"{report['machine']['cpus']} cores, Python {report['machine']['python']}; "
            f"load average {lb[0]:.1f} before, {la[0]:.1f} after (the machine is shared).",
            "",
            "| case | wall min s | wall median s | wall max s | CPU min s | CPU median s | runs |",
            "|---|---|---|---|---|---|---|",
        ]
        for name, row in report["rows"].items():
            lines.append(
                f"| {name} | {row['min_s']:.2f} | {row['median_s']:.2f} | {row['max_s']:.2f} "
                f"| {row.get('cpu_min_s', float('nan')):.2f} "
                f"| {row.get('cpu_median_s', float('nan')):.2f} | {row['runs']} |"
            )
        lines += ["", "`-X importtime` of one `autocal --help` (largest cumulative, ms):", ""]
        lines += ["| module | cumulative ms | self ms |", "|---|---|---|"]
        for row in report["importtime_help"]:
            lines.append(f"| {row['module']} | {row['cumulative_ms']:.0f} | {row['self_ms']:.0f} |")
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=7, help="runs per case (7)")
    parser.add_argument("--pythonpath", help="another checkout of autocal to measure")
    parser.add_argument("--label", default="now", help="name of this measurement (now)")
    parser.add_argument("--results", type=Path, default=RESULTS, help="folder of startup.md/json")
    args = parser.parse_args()
    report = measure(args.runs, args.pythonpath)
    args.results.mkdir(parents=True, exist_ok=True)
    path = args.results / "startup.json"
    reports = json.loads(path.read_text()) if path.exists() else {}
    reports[args.label] = report
    path.write_text(json.dumps(reports, indent=2))
    text = markdown(reports)
    (args.results / "startup.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
