"""Benchmark: what each stage of ``autocal calibrate`` costs on one whole HERA file.

One file of the HERA-size night (350 antennas x 2 pols x 1536 channels x 192 integrations,
``python benchmarks/night.py generate --ntimes 192``), Tsky cached, the floor and five
calls as fresh processes side by side, interleaved over ``--repeats`` rounds (one
unmeasured round first: page cache, numba's cache):

* the streamed decode floor (issue 25): h5py decoding the visibilities in the reader's
  blocks plus one numpy pass (``benchmarks/readers.py``'s ``floor``), in a fresh process;
* ``--products hdf5 --no-rfi-flagging``: the fit and its uncertainty alone;
* ``--products calh5,hdf5 --no-rfi-flagging``: with the per-time calh5;
* ``--products hdf5``: with band edges and RFI flagged before the fit (the default);
* ``--products calh5,hdf5``: issue 25's item 1 (the whole call, Tsky cached, products
  calh5 + hdf5; target 1.3x the floor);
* the default products (``calh5,hdf5,png``): with the figures too.

Targets: flagging costs at most 0.5x of the call without it (it was 12x: 471 s against 36 s
with scipy's sliding rank filter), and the default products fit in 4 GB (they ran out of
13 GB before the calh5 was built antenna by antenna). Reports wall and CPU time, peak RSS
(``wait4``'s ``ru_maxrss``) and the run's own stage timings (``timings_s`` and ``cpu_s`` of
``summary.json``), and item 1's call stage by stage against the least wall time its CPU
allows on this machine's cores::

    python benchmarks/file_stages.py --file /tmp/autocal-night-350x1536x192/zen.*.uvh5

Results go to ``benchmarks/results/file_stages.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from user_vs_autocal import run_child  # the same fresh-process measurement

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
RUNS = {
    "no flagging, hdf5": ["--products", "hdf5", "--no-rfi-flagging"],
    "no flagging, calh5 + hdf5": ["--products", "calh5,hdf5", "--no-rfi-flagging"],
    "flagging, hdf5": ["--products", "hdf5"],
    "flagging, calh5 + hdf5": ["--products", "calh5,hdf5"],
    "flagging, default products": [],
}
FLOOR = "decode floor (h5py, the reader's blocks, one numpy pass)"
#: Issue 25's item 1: the whole call, Tsky cached, products calh5 + hdf5.
ITEM_1 = "flagging, calh5 + hdf5"


def _floor_argv(path: str) -> list[str]:
    here = str(Path(__file__).resolve().parent)
    code = f"import sys; sys.path.insert(0, {here!r}); from readers import floor; floor([{path!r}])"
    return [sys.executable, "-c", code]


def main() -> None:
    """Run the floor and the calls interleaved and write the report."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--file", required=True, help="one night file (uvh5)")
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    env = dict(os.environ)
    results: dict[str, list[dict]] = {name: [] for name in [FLOOR, *RUNS]}
    with tempfile.TemporaryDirectory() as tmp:
        for round_ in range(args.repeats + 1):
            run = run_child(_floor_argv(args.file), env)
            run["timings_s"], run["stage_cpu_s"] = {}, {}
            if round_:
                results[FLOOR].append(run)
            print(f"round {round_} floor: {run['wall_s']:.1f} s", flush=True)
            for name, extra in RUNS.items():
                out = Path(tmp) / f"{round_}-{len(results[name])}-{name.replace(' ', '_')}"
                argv = [sys.executable, "-m", "autocal", "calibrate", args.file, "--out", str(out)]
                run = run_child([*argv, *extra], env)
                summary = json.loads((out / "summary.json").read_text())
                run["timings_s"], run["stage_cpu_s"] = summary["timings_s"], summary["cpu_s"]
                if round_:  # the first round warms the caches
                    results[name].append(run)
                print(f"round {round_} {name}: {run['wall_s']:.1f} s", flush=True)
    base = statistics.median(r["wall_s"] for r in results["no flagging, hdf5"])
    floor_s = statistics.median(r["wall_s"] for r in results[FLOOR])
    rows = []
    for name, runs in results.items():
        wall = statistics.median(r["wall_s"] for r in runs)
        keys = runs[0]["timings_s"]
        stages = {k: statistics.median(r["timings_s"][k] for r in runs) for k in keys}
        stage_cpu = {k: statistics.median(r["stage_cpu_s"][k] for r in runs) for k in keys}
        rows.append(
            {
                "run": name,
                "wall_s": round(wall, 1),
                "cpu_s": round(statistics.median(r["cpu_s"] for r in runs), 1),
                "peak_rss_gb": round(max(r["peak_rss_gb"] for r in runs), 2),
                "over_no_flagging": round(wall / base, 2),
                "over_floor": round(wall / floor_s, 2),
                "stages_s": {k: round(v, 1) for k, v in stages.items()},
                "stages_cpu_s": {k: round(v, 1) for k, v in stage_cpu.items()},
            }
        )
    report = {
        "file": args.file,
        "repeats": args.repeats,
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "load_at_end": os.getloadavg()[0],
        "rows": rows,
    }
    lines = [
        "# One HERA file, stage by stage",
        "",
        f"`python benchmarks/file_stages.py --file {args.file}` ({args.repeats} rounds, "
        f"median; load {report['load_at_end']:.1f} at the end)",
        "",
        "| run | wall (s) | CPU (s) | peak RSS (GB) | over the floor | over no flagging "
        "| stages (s) |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        stages = ", ".join(f"{k} {v}" for k, v in row["stages_s"].items())
        lines.append(
            f"| {row['run']} | {row['wall_s']} | {row['cpu_s']} | {row['peak_rss_gb']} | "
            f"{row['over_floor']}x | {row['over_no_flagging']}x | {stages} |"
        )
    lines += _budget(rows, floor_s, os.cpu_count() or 1)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "file_stages.json").write_text(json.dumps(report, indent=1) + "\n")
    (RESULTS / "file_stages.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def _budget(rows: list[dict], floor_s: float, cores: int) -> list[str]:
    """Item 1's call stage by stage: wall, CPU, busy cores, and the bound the CPU sets.

    The process's time outside the run's stages (interpreter start, imports, exit) is the
    process's wall and CPU minus the run's ``total_s``. All of the call's CPU spread evenly
    over every core is the least wall time that CPU allows.
    """
    row = next(r for r in rows if r["run"] == ITEM_1)
    wall, cpu = row["stages_s"], row["stages_cpu_s"]
    names = [k for k in wall if k != "total_s"]
    outside = (row["wall_s"] - wall["total_s"], row["cpu_s"] - cpu["total_s"])
    lines = [
        "",
        f"Item 1's call (`{ITEM_1}`) stage by stage (`timings_s` and `cpu_s` of its "
        "`summary.json`, medians; the process outside the stages is its wall and CPU minus "
        "`total_s`):",
        "",
        "| stage | wall (s) | CPU (s) | busy cores |",
        "|---|---|---|---|",
    ]
    for name, (w, c) in [*((k, (wall[k], cpu[k])) for k in names), ("outside", outside)]:
        busy = f"{c / w:.2f}" if w > 0.05 else "-"
        lines.append(f"| {name} | {w:.1f} | {c:.1f} | {busy} |")
    least = row["cpu_s"] / cores
    busy_all = row["cpu_s"] / row["wall_s"]
    lines += [
        f"| whole process | {row['wall_s']} | {row['cpu_s']} | {busy_all:.2f} |",
        "",
        f"Its {row['cpu_s']} s of CPU on {cores} cores take at least {least:.1f} s of wall, "
        f"{least / floor_s:.2f}x the floor of {floor_s:.1f} s (the target is 1.3x: "
        f"{1.3 * floor_s:.1f} s, {1.3 * floor_s * cores:.1f} s of CPU at best).",
    ]
    return lines


if __name__ == "__main__":
    main()
