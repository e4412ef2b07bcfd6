"""Identification rate of ``autocal diagnose`` on fixed-seed hidden-effect suites.

Every case is simulated with one or two hidden effects (or none), written as UVH5,
read back and diagnosed (:mod:`autocal.diagnosis.hidden`); a case counts as identified when the
diagnosis names exactly the hidden effects, recovers each parameter within 3 sigma of
the truth (final joint fit) and shrinks the gap at every accepted step. Usage::

    python scripts/diagnose_suite.py --out docs/results

writes ``diagnose_suite.json`` (every case) and ``diagnose_suite.md`` (the tables).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from collections import Counter
from pathlib import Path

from autocal.diagnosis.hidden import HiddenGenerator, run_case, suite_cases
from autocal.simulate.mock import SimulationConfig

SKY = "powerlaw:gsm2008@408:-2.55"
SUITES = {
    "dipole": {"beam": "dipole", "noise_dnu_hz": 1e6, "n": 42},
    "hera": {"beam": "hera", "noise_dnu_hz": 1e6, "n": 16},
    "paper_noise": {"beam": "dipole", "noise_dnu_hz": 5e3, "n": 16},
}


def run_suite(name: str, beam: str, noise_dnu_hz: float, n: int) -> dict:
    cfg = SimulationConfig(
        sky=SKY,
        beam=beam,
        channel_width_khz=1000,
        cadence_s=600,
        nside=32,
        noise_dnu_hz=noise_dnu_hz,
    )
    t0 = time.perf_counter()
    gen = HiddenGenerator(cfg)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for case in suite_cases(n):
            rows.append(run_case(gen, case, tmp))
    ok = sum(r["score"]["ok"] for r in rows)
    clean = [r for r in rows if not r["case"]["effects"]]
    false_pos = sum(bool(r["score"]["found"]) for r in clean)
    return {
        "suite": name,
        "simulation": cfg.model_dump(),
        "cases": n,
        "identified": ok,
        "clean_controls": len(clean),
        "false_positives_on_clean": false_pos,
        "runtime_s": round(time.perf_counter() - t0, 1),
        "rows": rows,
    }


def markdown(results: list[dict]) -> str:
    lines = [
        "| suite | beam | dnu dt | cases | identified | clean controls | false positives |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in results:
        sim = r["simulation"]
        bt = sim["noise_dnu_hz"] * sim["noise_dt_s"]
        lines.append(
            f"| {r['suite']} | {sim['beam']} | {bt:.0e} | {r['cases']} | "
            f"{r['identified']} ({100 * r['identified'] / r['cases']:.0f} %) | "
            f"{r['clean_controls']} | {r['false_positives_on_clean']} |"
        )
    lines += ["", "Per hidden effect (identified / cases):", ""]
    for r in results:
        per: Counter = Counter()
        hit: Counter = Counter()
        for row in r["rows"]:
            key = "+".join(row["score"]["hidden"]) or "clean"
            if row["case"]["bandpass"] != "flat":
                key += f" ({row['case']['bandpass']} bandpass)"
            per[key] += 1
            hit[key] += bool(row["score"]["ok"])
        summary = ", ".join(f"{k} {hit[k]}/{per[k]}" for k in sorted(per))
        lines.append(f"- {r['suite']}: {summary}")
    lines += ["", "Cases not identified:", ""]
    for r in results:
        for row in r["rows"]:
            if row["score"]["ok"]:
                continue
            truth = "; ".join(
                f"{e['name']} "
                + ", ".join(
                    f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                    for k, v in e["params"].items()
                )
                for e in row["case"]["effects"]
            )
            pulls = ", ".join(f"{k} {v:+.1f}" for k, v in row["score"]["pulls"].items())
            lines.append(
                f"- {r['suite']} seed {row['case']['seed']}: hidden [{truth or 'none'}], "
                f"found {list(row['score']['found'])}; pulls: {pulls or '-'}"
            )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/results"))
    parser.add_argument("--suites", nargs="+", default=list(SUITES), choices=list(SUITES))
    args = parser.parse_args()
    results = [run_suite(name, **SUITES[name]) for name in args.suites]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "diagnose_suite.json").write_text(json.dumps(results, indent=1, default=str))
    text = markdown(results)
    (args.out / "diagnose_suite.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
