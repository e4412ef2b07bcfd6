"""Measure how often autocal's errors cover the truth on data it did not simulate.

Usage (from the repository root, data in ``$AUTOCAL_DATA_DIR`` or ``../shared/data``)::

    python scripts/uncertainty_coverage.py --out docs/results/uncertainty --seeds 5

Each case writes ``--seeds`` observations with the independent forward model of
``tests/independent_sim.py`` (its own sky, frame conversion, beam evaluation, hard horizon
and UVH5 writer), calibrates them with ``autocal calibrate``'s pipeline (dipole beam,
constant model, default settings) and compares the fitted ``G`` with the simulated
time-mean gain. ``OUT/coverage.json`` holds every number the README quotes.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import autocal  # noqa: F401  (offline configuration)
from autocal.pipeline.calibrate import run_calibration
from autocal.pipeline.config import CalibrationConfig
from tests.independent_sim import simulate_autos

CASES = {
    "31 min, 1 % linear gain drift": {
        "lst_start_h": 3.2,
        "duration_min": 31.0,
        "drift_total": 0.01,
    },
    "31 min, constant gain": {"lst_start_h": 3.2, "duration_min": 31.0},
    "31 min, constant gain, prior Trxr = 150 +- 5 K": {
        "lst_start_h": 3.2,
        "duration_min": 31.0,
        "prior": (150.0, 5.0),
    },
    "24 h, constant gain (300 s integrations)": {
        "lst_start_h": 0.0,
        "duration_min": 24 * 60 - 5.0,
        "integration_s": 300.0,
    },
    "24 h, 1 % linear gain drift (300 s integrations)": {
        "lst_start_h": 0.0,
        "duration_min": 24 * 60 - 5.0,
        "integration_s": 300.0,
        "drift_total": 0.01,
    },
}


def run_case(name: str, spec: dict, seeds: int, work: Path) -> dict:
    """Simulate, calibrate and score one case over ``seeds`` noise draws."""
    spec = dict(spec)
    prior = spec.pop("prior", None)
    total, stat, ratio, solved = [], [], [], []
    for seed in range(seeds):
        truth = simulate_autos(work / f"{abs(hash(name))}_{seed}.uvh5", seed=seed, **spec)
        options = {}
        if prior is not None:
            options = {"trxr_prior": prior[0], "trxr_prior_sigma_k": prior[1]}
        config = CalibrationConfig(
            inputs=[str(truth.path)], beam="dipole", products=["hdf5"], **options
        )
        sol = run_calibration(config, work / f"out_{abs(hash(name))}_{seed}").solution
        err = sol.G[0, 0] - truth.G_mean
        total.append(err / sol.sigma_G[0, 0])
        stat.append(err / sol.sigma_G_stat[0, 0])
        ratio.append(sol.sigma_G[0, 0] / sol.sigma_G_stat[0, 0])
        solved.append(np.isfinite(sol.G[0, 0]))
    total, stat = np.ravel(total), np.ravel(stat)
    ratio, solved = np.ravel(ratio), np.ravel(solved)
    return {
        "case": name,
        "channels": int(total.size),
        "solved_fraction": float(solved.mean()),
        "within_3_total": float(np.mean(np.abs(total) < 3)),  # unsolved count as misses
        "within_3_stat": float(np.mean(np.abs(stat) < 3)),
        "pull_std_total": float(np.nanstd(total)),
        "pull_std_stat": float(np.nanstd(stat)),
        "median_total_over_stat": float(np.nanmedian(ratio)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/results/uncertainty"))
    parser.add_argument("--seeds", type=int, default=5)
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    args.out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        rows = [run_case(name, spec, args.seeds, Path(tmp)) for name, spec in CASES.items()]
    result = {
        "command": f"python scripts/uncertainty_coverage.py --out {args.out} --seeds {args.seeds}",
        "seconds": round(time.perf_counter() - start, 1),
        "cases": rows,
    }
    (args.out / "coverage.json").write_text(json.dumps(result, indent=2) + "\n")
    for row in rows:
        print(json.dumps(row))


if __name__ == "__main__":
    main()
