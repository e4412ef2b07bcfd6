"""How ``autocal diagnose`` does on data written by an independent forward model.

Every case of :func:`tests.independent_effects.suite_plan` is simulated by
``tests/independent_sim.py`` (its own GSM2008 handling, AltAz per pixel at nside 32, its
own dipole / HERA beam, a hard horizon, its own UVH5 writer) with zero, one or two hidden
effects, diagnosed by autocal's stage function
:func:`autocal.diagnosis.run.run_diagnosis` with the true ``Trxr(nu)`` as a per-channel
CSV prior, and scored by exact names: the effects named must be the hidden set, no
extras. Usage::

    python scripts/diagnose_independent_suite.py --out docs/results/diagnose_independent
    python scripts/diagnose_independent_suite.py --out /tmp/x --only clean_day --keep
    python scripts/diagnose_independent_suite.py --out OUT --merge A/suite.json B/suite.json

writes ``suite.json`` (every case: hidden effects and true parameters, named effects,
exact or not, extras, misses, initial/final reduced chi2, the diagnosis's steps with their
statistics, timings) and ``suite.md`` (the tables), and prints a short summary.
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import math
import os
import platform
import sys
import tempfile
import time
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from autocal.diagnosis.impact import (  # noqa: E402
    FORWARD_MODEL_ACCURACY,
    FORWARD_MODEL_ACCURACY_BY_BEAM,
)
from tests import independent_effects as ie  # noqa: E402


def _fmt(value: Any, spec: str = ".3g") -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return format(value, spec)


def _params_text(params: dict[str, Any]) -> str:
    parts = []
    for k, v in params.items():
        if k == "seed":
            continue
        parts.append(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}")
    return ", ".join(parts)


def _hidden_text(row: dict[str, Any]) -> str:
    items = row["case"]["hidden"]
    if not items:
        return "clean"
    return "; ".join(f"{h['name']} ({_params_text(h['params'])})" for h in items)


def _step_text(step: dict[str, Any]) -> str:
    pars = ", ".join(
        f"{k}={_fmt(v['value'], '.4g')}+-{_fmt(v['sigma'], '.2g')}"
        for k, v in step["parameters"].items()
        if k not in ("order", "max_abs")
    )
    basis = f"/{step['time_basis']}" if step.get("time_basis") else ""
    dropped = " [dropped]" if step.get("dropped_in_backward_pass") else ""
    dropped += " [negligible]" if step.get("negligible") else ""
    if step.get("absorbed_by_unexplained") is not None:
        dropped += " [part of the unexplained remainder]"
    if step.get("below_model_accuracy"):
        dropped += f" [below the model's accuracy: {_fmt(step.get('signal_rms'), '.1e')}]"
    return (
        f"{step['name']}{basis} dBIC={_fmt(step['statistic'], '.1f')} "
        f"p={_fmt(step['p_value'], '.2g')} c={_fmt(step['overdispersion'], '.3f')} "
        f"({pars}){dropped}"
    )


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Exact fractions overall, per effect, per span and beam; clean controls; false names.

    Parameters
    ----------
    rows
        :func:`tests.independent_effects.run_case` results.

    Returns
    -------
    dict
        The summary.
    """
    n = len(rows)
    exact = sum(r["exact"] for r in rows)
    per_effect: dict[str, Counter] = defaultdict(Counter)
    for r in rows:
        for name in r["hidden"]:
            alone = len(r["hidden"]) == 1
            visible = name in r["visible"]
            per_effect[name]["cases"] += 1
            per_effect[name]["exact"] += int(r["exact"])
            per_effect[name]["named"] += int(name in r["named"])
            per_effect[name]["negligible"] += int(name in r["negligible"])
            per_effect[name]["visible"] += int(visible)
            per_effect[name]["named_when_visible"] += int(visible and name in r["named"])
            per_effect[name]["alone_cases"] += int(alone)
            per_effect[name]["alone_exact"] += int(alone and r["exact"])
    groups: dict[str, Counter] = defaultdict(Counter)
    for r in rows:
        c = r["case"]
        kind = "clean" if not r["hidden"] else ("single" if len(r["hidden"]) == 1 else "pair")
        for key in (f"span={c['span']}", f"beam={c['beam']}", f"kind={kind}"):
            groups[key]["cases"] += 1
            groups[key]["exact"] += int(r["exact"])
            groups[key]["exact_visible"] += int(r["exact_visible"])
            groups[key]["exact_matters"] += int(r.get("exact_matters", r["exact"]))
            groups[key]["correct"] += int(r["correct"])
    clean = [r for r in rows if not r["hidden"]]
    false_names = []
    for r in rows:
        for name in r["extras"]:
            step = next((s for s in r["steps"] if s["name"] == name), None)
            false_names.append(
                {
                    "case": r["case"]["name"],
                    "hidden": r["hidden"],
                    "name": name,
                    "step": None if step is None else r["steps"].index(step) + 1,
                    "statistic": None if step is None else step["statistic"],
                    "p_value": None if step is None else step["p_value"],
                    "delta_chi2": None if step is None else step["delta_chi2"],
                    "overdispersion": None if step is None else step["overdispersion"],
                    "time_basis": None if step is None else step["time_basis"],
                    "parameters": None if step is None else step["parameters"],
                    "reduced_chi2_before": None
                    if step is None
                    else step["gap_before"]["reduced_chi2"],
                    "integration_jitter_before": None
                    if step is None
                    else step["gap_before"]["integration_jitter"],
                }
            )
    misses = Counter(m for r in rows for m in r["misses"])
    runtime = sum(
        r["timings_s"]["simulate"] + r["timings_s"]["strength"] + r["timings_s"]["diagnosis"]
        for r in rows
    )
    negligible = [
        {"case": r["case"]["name"], "hidden": r["hidden"], "negligible": r["negligible"]}
        for r in rows
        if r["negligible"]
    ]
    absorbed = [
        {"case": r["case"]["name"], "hidden": r["hidden"], "absorbed": r.get("absorbed", [])}
        for r in rows
        if r.get("absorbed")
    ]
    below_accuracy = [
        {"case": r["case"]["name"], "hidden": r["hidden"], "effects": r["below_model_accuracy"]}
        for r in rows
        if r.get("below_model_accuracy")
    ]
    indistinguishable = [
        {
            "case": r["case"]["name"],
            "hidden": r["hidden"],
            "candidates": list(r["indistinguishable"]["candidates"]),
        }
        for r in rows
        if r.get("indistinguishable")
    ]
    return {
        "cases": n,
        "exact": exact,
        "exact_fraction": exact / n if n else float("nan"),
        "exact_visible": sum(r["exact_visible"] for r in rows),
        "exact_or_negligible": sum(r["exact_or_negligible"] for r in rows),
        "exact_matters": sum(r.get("exact_matters", r["exact"]) for r in rows),
        "exact_matters_fraction": sum(r.get("exact_matters", r["exact"]) for r in rows) / n
        if n
        else float("nan"),
        "hidden_not_mattering": [
            {"case": r["case"]["name"], "effects": sorted(set(r["hidden"]) - set(r["matters"]))}
            for r in rows
            if "matters" in r and set(r["hidden"]) - set(r["matters"])
        ],
        "correct": sum(r["correct"] for r in rows),
        "correct_fraction": sum(r["correct"] for r in rows) / n if n else float("nan"),
        "cases_with_extras": sum(bool(r["extras"]) for r in rows),
        "unexplained": [r["case"]["name"] for r in rows if r.get("unexplained")],
        "negligible": negligible,
        "absorbed": absorbed,
        "below_model_accuracy": below_accuracy,
        "indistinguishable": indistinguishable,
        "per_effect": {k: dict(v) for k, v in sorted(per_effect.items())},
        "groups": {k: dict(v) for k, v in sorted(groups.items())},
        "clean_controls": len(clean),
        "clean_with_no_name": sum(not r["named"] for r in clean),
        "false_names": false_names,
        "false_name_counts": dict(Counter(f["name"] for f in false_names).most_common()),
        "misses": dict(misses.most_common()),
        "runtime_s": round(runtime, 1),
        "mean_diagnosis_s": round(sum(r["timings_s"]["diagnosis"] for r in rows) / max(n, 1), 2),
    }


def markdown(result: dict[str, Any]) -> str:
    """Render ``suite.md``: per-case table, then the summary tables."""
    rows, s = result["cases"], result["summary"]
    st = result["settings"]
    lines = [
        "# Diagnosis on data from the independent forward model",
        "",
        "Simulated by `tests/independent_sim.py` (GSM2008 via pygdsm at nside 32, AltAz per "
        "pixel with astropy, its own beams, hard horizon), hidden effects injected by "
        "`tests/independent_effects.py`, diagnosed by `autocal.diagnosis.run.run_diagnosis` "
        f"(model sky {st['sky']}, beam = the true beam's family, model ground "
        f"{st['model_tgnd_k']:g} K, template nside {st['nside']}, true `Trxr(nu)` as a "
        f"per-channel CSV prior of sigma {st['prior_sigma_k']:g} K for every case, "
        f"dnu dt = {st['dnu_dt']:g}). Exact = the named set equals the hidden set.",
        "",
        f"Generated {result['generated']} by `scripts/diagnose_independent_suite.py` "
        f"({s['cases']} cases, {s['runtime_s']:.0f} s, suite seed "
        f"{st.get('seed', ie.SUITE_SEED)}).",
        "",
        "## Summary",
        "",
        f"- **correct: {s['correct']} / {s['cases']} ({100 * s['correct_fraction']:.0f} %)**: "
        "no effect named that is not hidden, and every hidden effect that a perfect "
        "template could see (`effect_strength`) found, named or reported 'detected, "
        "negligible' (too small to move the products: the diagnosis's answer for it)",
        f"- exact names (named set = hidden set, strictly): {s['exact']} / {s['cases']} "
        f"({100 * s['exact_fraction']:.0f} %)",
        f"- exact against the visible hidden effects only: {s['exact_visible']} / {s['cases']}",
        f"- exact when 'detected, negligible' counts as naming (named or reported set = "
        f"hidden set): {s['exact_or_negligible']} / {s['cases']}",
        f"- **exact on the effects that move the products: {s['exact_matters']} / "
        f"{s['cases']} ({100 * s['exact_matters_fraction']:.0f} %)**: every hidden effect "
        "that matters named, and nothing named that is not hidden; an instrument effect always "
        "matters, a forward-model effect when autocal's negligibility rule, applied to the "
        "truth (the clean model fitted to the noiseless data against the true `G` and `Trxr`, "
        "radiometer sigma, the chi2-share clause included; `product_impact`), does not clear "
        "it. Hidden effects that do not matter: "
        + (
            ", ".join(f"{x['case']}: {x['effects']}" for x in s.get("hidden_not_mattering", []))
            or "none"
        ),
        f"- clean controls naming nothing: {s['clean_with_no_name']} / {s['clean_controls']}",
        f"- cases with extra names: {s['cases_with_extras']}; false names (extras): "
        f"{s['false_name_counts'] or 'none'}",
        f"- misses: {s['misses'] or 'none'}",
        f"- 'unexplained' reported: {', '.join(s['unexplained']) or 'none'}",
        "- 'detected, negligible': "
        + (", ".join(f"{x['case']}: {x['negligible']}" for x in s["negligible"]) or "none"),
        "- fitted but part of the unexplained remainder (negligible, < 10 % of its excess "
        "chi2; not counted as detected): "
        + (", ".join(f"{x['case']}: {x['absorbed']}" for x in s.get("absorbed", [])) or "none"),
        "- fitted but below the forward model's accuracy (a signal under the model beam's "
        f"floor of the data rms, {FORWARD_MODEL_ACCURACY:g} for the dipole and "
        f"{FORWARD_MODEL_ACCURACY_BY_BEAM['uvbeam_healpix']:g} for the HERA beam file; "
        "whatever it would change in the products; not counted as detected): "
        + (
            ", ".join(f"{x['case']}: {x['effects']}" for x in s.get("below_model_accuracy", []))
            or "none"
        ),
        "- indistinguishable (the search stopped: entries of the receiver and of the forward "
        "model explain a residual within the decisive margin; none named): "
        + (
            ", ".join(f"{x['case']}: {x['candidates']}" for x in s.get("indistinguishable", []))
            or "none"
        ),
        "",
        "| group | cases | correct | exact | exact (visible) | exact (move the products) |",
        "|---|---|---|---|---|---|",
    ]
    for key, g in s["groups"].items():
        lines.append(
            f"| {key} | {g['cases']} | {g['correct']} | {g['exact']} | {g['exact_visible']} "
            f"| {g.get('exact_matters', '-')} |"
        )
    lines += [
        "",
        "Per hidden effect (cases containing it; `named` = the effect itself was named; "
        "`visible` = strong enough to be seen by `effect_strength`; `alone` = single-effect "
        "cases):",
        "",
        "| effect | cases | exact | named | visible | named when visible | negligible | "
        "alone: exact / cases |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, g in s["per_effect"].items():
        lines.append(
            f"| {name} | {g['cases']} | {g['exact']} | {g['named']} | {g['visible']} | "
            f"{g['named_when_visible']} | {g['negligible']} | "
            f"{g['alone_exact']} / {g['alone_cases']} |"
        )
    lines += ["", "False names:", ""]
    if not s["false_names"]:
        lines.append("none")
    for f in s["false_names"]:
        pars = ", ".join(
            f"{k}={_fmt(v['value'], '.4g')}+-{_fmt(v['sigma'], '.2g')}"
            for k, v in (f["parameters"] or {}).items()
            if k not in ("order", "max_abs")
        )
        lines.append(
            f"- {f['case']} (hidden {f['hidden'] or 'none'}): **{f['name']}** at step "
            f"{f['step']}, dBIC {_fmt(f['statistic'], '.1f')}, p {_fmt(f['p_value'], '.2g')}, "
            f"dchi2 {_fmt(f['delta_chi2'], '.1f')}, overdispersion "
            f"{_fmt(f['overdispersion'], '.3f')}, chi2/dof before "
            f"{_fmt(f['reduced_chi2_before'], '.4f')}, integration jitter before "
            f"{_fmt(f['integration_jitter_before'], '.2f')} ({pars})"
        )
    lines += [
        "",
        "## Cases",
        "",
        "| case | span | beam | ants x pols | hidden (true parameters) | strength: dBIC of "
        "a perfect template | named | exact | chi2/dof initial -> final | steps (dBIC, p, "
        "overdispersion, parameters) | best rejected | time (s) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        c = r["case"]
        rej = r.get("last_rejected") or {}
        rej_text = (
            f"{rej.get('name')} dBIC={_fmt(rej.get('statistic'), '.1f')} "
            f"p={_fmt(rej.get('p_value'), '.2g')}"
            if rej
            else "-"
        )
        steps = "<br>".join(_step_text(st) for st in r["steps"]) or "-"
        if r.get("unexplained"):
            u = r["unexplained"]
            steps += f"<br>unexplained ({_fmt(u['excess_sigma'], '.1f')} sigma, {u['time']})"
        strength = (
            ", ".join(
                f"{k} {_fmt(v['dbic'], '.3g')}{'' if v['visible'] else ' (not visible)'}"
                + _impact_text(v)
                for k, v in r["strength"].items()
            )
            or "-"
        )
        named = ", ".join(r["named"]) or "-"
        if r["negligible"]:
            named += f" (negligible: {', '.join(r['negligible'])})"
        if r.get("absorbed"):
            named += f" (part of the remainder: {', '.join(r['absorbed'])})"
        if r.get("below_model_accuracy"):
            named += f" (below the model's accuracy: {', '.join(r['below_model_accuracy'])})"
        if r.get("indistinguishable"):
            named += f" (indistinguishable: {', '.join(r['indistinguishable']['candidates'])})"
        t = r["timings_s"]
        verdict = "yes" if r["exact"] else ("correct" if r["correct"] else "**no**")
        lines.append(
            f"| {c['name']} | {c['span']} ({c['ntime']} x {c['integration_s']:g} s, LST "
            f"{c['lst_start_h']:g} h) | {c['beam']} | {len(c['antennas'])} x "
            f"{'+'.join(c['pols'])} | {_hidden_text(r)} | {strength} | {named} | "
            f"{verdict} | {_fmt(r['initial_reduced_chi2'], '.4f')} "
            f"-> {_fmt(r['final_reduced_chi2'], '.4f')} | {steps} | {rej_text} | "
            f"{t['simulate']:.1f} + {t['diagnosis']:.1f} |"
        )
    return "\n".join(lines) + "\n"


def _impact_text(strength: dict[str, Any]) -> str:
    """`` (negligible for the products: ...)`` for a hidden effect that does not matter."""
    impact = strength.get("impact")
    if impact is None or strength.get("matters", True):
        return ""
    return (
        f" (negligible for the products: Trxr {impact['trxr_median_k']:.2g} K = "
        f"{impact['trxr_median_sigma']:.2g} sigma median, G "
        f"{impact['g_median_fraction']:.1e} = {impact['g_median_sigma']:.2g} sigma)"
    )


def select(cases: list[ie.Case], only: list[str] | None, count: int | None) -> list[ie.Case]:
    """Keep the cases whose name matches one of ``only`` (glob patterns), then the first N."""
    if only:
        cases = [c for c in cases if any(fnmatch.fnmatchcase(c.name, p) for p in only)]
    if count is not None:
        cases = cases[:count]
    return cases


def merge(paths: list[Path], out: Path) -> int:
    """Merge runs of disjoint selections into one ``suite.json`` / ``suite.md`` in ``out``.

    The cases are put in the suite's order; a case found in two runs is an error. The
    settings are the first run's (they must agree on the prior and the template nside).
    """
    runs = [json.loads(Path(p).read_text()) for p in paths]
    order = {c.name: i for i, c in enumerate(ie.suite_plan())}
    rows: dict[str, dict[str, Any]] = {}
    for run in runs:
        for key in ("prior_sigma_k", "nside", "dnu_dt", "seed"):
            if run["settings"].get(key) != runs[0]["settings"].get(key):
                print(f"runs differ in {key}: not merged", file=sys.stderr)
                return 2
        for row in run["cases"]:
            name = row["case"]["name"]
            if name in rows:
                print(f"case {name} is in two runs: not merged", file=sys.stderr)
                return 2
            rows[name] = row
    merged = sorted(rows.values(), key=lambda r: order.get(r["case"]["name"], len(order)))
    settings = dict(runs[0]["settings"])
    settings["selection"] = {"merged": [str(p) for p in paths]}
    settings["wall_time_s"] = round(max(r["settings"]["wall_time_s"] for r in runs), 1)
    result = {
        "generated": max(r["generated"] for r in runs),
        "settings": settings,
        "summary": summarise(merged),
        "cases": merged,
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "suite.json").write_text(json.dumps(result, indent=2, allow_nan=False) + "\n")
    (out / "suite.md").write_text(markdown(result))
    s = result["summary"]
    print(
        f"merged {len(merged)} cases: correct {s['correct']}/{s['cases']}, exact "
        f"{s['exact']}/{s['cases']}; wrote {out / 'suite.json'} and {out / 'suite.md'}"
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    """Run the suite (or a selection) and write ``suite.json`` and ``suite.md``."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--cases", type=int, default=None, help="run only the first N cases")
    parser.add_argument(
        "--only",
        action="append",
        default=None,
        help="case name or glob pattern (repeatable), e.g. 'clean_*'",
    )
    parser.add_argument(
        "--prior-sigma",
        type=float,
        default=ie.PRIOR_SIGMA_K,
        help="1-sigma of the per-channel Trxr prior, K",
    )
    parser.add_argument("--nside", type=int, default=64, help="template nside of the diagnosis")
    parser.add_argument(
        "--seed",
        type=int,
        default=ie.SUITE_SEED,
        help="suite seed: the cases' effect amplitudes and noise (default "
        f"{ie.SUITE_SEED}, the suite's; another seed is a held-out realisation of the same plan)",
    )
    parser.add_argument(
        "--keep", action="store_true", help="keep data and diagnosis products in OUT/cases"
    )
    parser.add_argument("--list", action="store_true", help="list the cases and exit")
    parser.add_argument(
        "--merge",
        nargs="+",
        type=Path,
        default=None,
        metavar="SUITE_JSON",
        help="instead of running: merge the suite.json of runs of disjoint selections "
        "(e.g. the suite run in shards, one process each) into OUT's suite.json and suite.md",
    )
    args = parser.parse_args(argv)
    if args.merge:
        return merge(args.merge, args.out)

    cases = select(ie.suite_plan(args.seed), args.only, args.cases)
    if args.list:
        for c in cases:
            print(f"{c.name}: {c.span.name} {c.beam} {list(c.hidden) or 'clean'}")
        return 0
    if not cases:
        print("no case selected", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    tmp = tempfile.TemporaryDirectory(prefix="diagnose_independent_")
    work = args.out / "cases" if args.keep else Path(tmp.name) / "cases"
    # the Tsky cache of the diagnosis's templates: private to this run
    os.environ.setdefault("AUTOCAL_CACHE_DIR", str(Path(tmp.name) / "tsky_cache"))
    rows = []
    t0 = time.perf_counter()
    try:
        for i, case in enumerate(cases, 1):
            row = ie.run_case(case, work, prior_sigma_k=args.prior_sigma, nside=args.nside)
            rows.append(row)
            mark = "ok " if row["exact"] else ("~ok" if row["correct"] else "BAD")
            print(
                f"[{i:2d}/{len(cases)}] {mark} {case.name}: hidden {row['hidden'] or '-'} "
                f"named {row['named'] or '-'} (chi2/dof {row['initial_reduced_chi2']:.4f} -> "
                f"{row['final_reduced_chi2']:.4f}, {row['timings_s']['simulate']:.1f} + "
                f"{row['timings_s']['diagnosis']:.1f} s)",
                flush=True,
            )
    finally:
        tmp.cleanup()
    summary = summarise(rows)
    result = {
        "generated": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "settings": {
            "sky": "gsm2008",
            "model_tgnd_k": ie.MODEL_TGND_K,
            "prior_sigma_k": args.prior_sigma,
            "prior": "true Trxr(nu) = 150 + 40 x + 20 x^2 K, x = (nu - 150 MHz) / 40 MHz, "
            "per-channel CSV, every case",
            "nside": args.nside,
            "seed": args.seed,
            "dnu_dt": ie.DNU_DT,
            "spans": {k: v.__dict__ for k, v in ie.SPANS.items()},
            "selection": {"only": args.only, "cases": args.cases},
            "wall_time_s": round(time.perf_counter() - t0, 1),
            "python": platform.python_version(),
        },
        "summary": summary,
        "cases": rows,
    }
    (args.out / "suite.json").write_text(json.dumps(result, indent=2, allow_nan=False) + "\n")
    (args.out / "suite.md").write_text(markdown(result))
    print(
        f"correct {summary['correct']}/{summary['cases']} "
        f"({100 * summary['correct_fraction']:.0f} %); "
        f"exact {summary['exact']}/{summary['cases']} ({100 * summary['exact_fraction']:.0f} %), "
        f"against visible effects {summary['exact_visible']}/{summary['cases']}, "
        f"on the effects that move the products {summary['exact_matters']}/{summary['cases']}; "
        f"clean naming nothing {summary['clean_with_no_name']}/{summary['clean_controls']}; "
        f"false names {summary['false_name_counts'] or 'none'}; misses "
        f"{summary['misses'] or 'none'}; {summary['runtime_s']:.0f} s"
    )
    print(f"wrote {args.out / 'suite.json'} and {args.out / 'suite.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
