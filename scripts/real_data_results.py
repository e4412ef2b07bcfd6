"""Reproduce the README's real-data results (HERA nights, EDGES lab loads, EDGES-like day).

Usage (from the repository root, data in ``$AUTOCAL_DATA_DIR`` or ``../shared/data``)::

    python scripts/real_data_results.py --out docs/results

Writes the products of each calibration under ``OUT/<case>/`` and ``OUT/results.json``
with every number the README quotes, plus ``OUT/repeatability.png``.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np

import autocal  # noqa: F401  (offline configuration)
from autocal.io.datasets import data_dir
from autocal.pipeline.calibrate import run_calibration
from autocal.pipeline.config import CalibrationConfig
from autocal.plots import band, figure, robust_ylim, save_figure

NIGHTS = (2458043, 2458044, 2458045)
#: LSTs shared by the three nights (hours).
COMMON_LST = (0.905, 1.305)


def per_pol(compare_json: Path) -> list[dict]:
    """Comparison statistics per antenna and polarisation.

    Besides compare.json's entries, ``ratio_single_reference`` is the range of the mean
    ratio against each single reference integration (compare.h5 ``reference_series``:
    ``|g_ref(t)|^2`` over its time mean, median over channels).
    """
    import h5py

    keys = (
        "antenna",
        "pol",
        "n_compared",
        "ratio_mean",
        "ratio_rms",
        "sigma_ratio_median",
        "offset",
        "offset_error",
        "offset_sigma",
        "offset_error_without_auto_systematic",
        "offset_sigma_without_auto_systematic",
        "sigma_auto_rel_median",
        "sigma_auto_stat_rel_median",
        "sigma_reference_rel_median",
        "reference_drift",
        "reference_drift_rms",
        "auto_drift",
        "reference_stable",
        "reference_stability",
        "systematics",
        "shape_pull_rms",
        "fraction_within_2sigma",
    )
    summary = json.loads(compare_json.read_text())
    rows = [{k: p.get(k) for k in keys} for p in summary["per_antenna_pol"]]
    h5path = compare_json.with_name("compare.h5")
    if h5path.is_file():
        with h5py.File(h5path, "r") as h5:
            if "reference_series" in h5:
                series = h5["reference_series"][()]  # (A, P, T)
                ants = [int(a) for a in h5["antennas"][()]]
                pols = [p.decode() if isinstance(p, bytes) else str(p) for p in h5["pols"][()]]
                for row in rows:
                    s = series[ants.index(row["antenna"]), pols.index(row["pol"])]
                    s = s[np.isfinite(s) & (s > 0)]
                    if s.size and row["ratio_mean"] is not None:
                        single = row["ratio_mean"] / np.sqrt(s)
                        row["ratio_single_reference"] = [float(single.min()), float(single.max())]
    return rows


def hera_2458116(root: Path, out: Path) -> dict:
    """Antenna 23, 31 minutes, 1024 channels, vs the abscal gains of the same night."""
    autos = sorted(str(p) for p in (root / "hera/autos").glob("zen.2458116.*.HH.uvh5"))
    refs = sorted(
        str(p) for p in (root / "hera/reference_gains").glob("zen.2458116.*.flagged_abs.calfits")
    )
    result = run_calibration(
        CalibrationConfig(
            inputs=autos,
            antennas=[23],
            freq_range_mhz=(110.0, 190.0),
            reference=refs,
            products=["calh5", "hdf5", "png"],
        ),
        out / "hera_2458116",
    )
    # the same with an assumed receiver (150 +- 10 K): what knowing Trxr would change
    held = run_calibration(
        CalibrationConfig(
            inputs=autos,
            antennas=[23],
            freq_range_mhz=(110.0, 190.0),
            reference=refs,
            products=["hdf5"],
            trxr_prior=150.0,
            trxr_prior_sigma_k=10.0,
        ),
        out / "hera_2458116_prior150",
    )
    return {
        "solution": result.summary["solution"],
        "separation": result.summary["separation"],
        "comparison": per_pol(Path(result.products["compare_json"])),
        "with_prior_150_10": {
            "separation": held.summary["separation"],
            "comparison": per_pol(Path(held.products["compare_json"])),
        },
    }


def hera_repeatability(root: Path, out: Path) -> dict:
    """Seven antennas on three consecutive nights over the LSTs they share."""
    sols = []
    for night in NIGHTS:
        files = sorted(str(p) for p in (root / "hera/autos").glob(f"zen.{night}.*.XRAA.uvh5"))
        cfg = CalibrationConfig(inputs=files, lst_range_h=COMMON_LST, products=["hdf5"])
        sols.append(run_calibration(cfg, out / f"hera_{night}").solution)
    g = np.array([s.G[:, 0] for s in sols])  # (night, ant, freq)
    sg = np.array([s.sigma_G[:, 0] for s in sols])
    sg_stat = np.array([s.sigma_G_stat[:, 0] for s in sols])
    t = np.array([s.Trxr[:, 0] for s in sols])
    st = np.array([s.sigma_Trxr[:, 0] for s in sols])
    st_stat = np.array([s.sigma_Trxr_stat[:, 0] for s in sols])
    from autocal.fit.separation import separation_summary

    seps = [{e["antenna"]: e for e in separation_summary(s)} for s in sols]
    ok = np.all(np.array([~s.flags[:, 0] for s in sols]), axis=0)
    rows = []
    for ia, ant in enumerate(sols[0].antennas):
        m = ok[ia]
        spread = np.std(g[:, ia, m], axis=0) / np.mean(g[:, ia, m], axis=0)
        diff = np.abs(g[1:, ia, m] - g[0, ia, m])
        diff_sig = diff / np.hypot(sg[1:, ia, m], sg[0, ia, m])
        diff_sig_stat = diff / np.hypot(sg_stat[1:, ia, m], sg_stat[0, ia, m])
        nights = range(len(NIGHTS))
        rows.append(
            {
                "antenna": int(ant),
                "channels": int(m.sum()),
                "G_night_spread_pct": float(100 * np.median(spread)),
                "G_sigma_pct": float(100 * np.median(sg[:, ia, m] / g[:, ia, m])),
                "G_sigma_stat_pct": float(100 * np.median(sg_stat[:, ia, m] / g[:, ia, m])),
                "G_diff_in_sigma": float(np.median(diff_sig)),
                "G_diff_in_stat_sigma": float(np.median(diff_sig_stat)),
                "Trxr_median_K": [float(np.median(t[n, ia, m])) for n in nights],
                "Trxr_sigma_K": [float(np.median(st[n, ia, m])) for n in nights],
                "Trxr_sigma_stat_K": [float(np.median(st_stat[n, ia, m])) for n in nights],
                "reduced_chi2": [float(np.nanmedian(s.reduced_chi2[ia, 0])) for s in sols],
                "sky_contrast": [seps[n][int(ant)]["sky_contrast"] for n in nights],
                "drift_sensitivity": [seps[n][int(ant)]["drift_sensitivity"] for n in nights],
                "separation": [seps[n][int(ant)]["separation"] for n in nights],
            }
        )
    fig, axes = figure(2, 1, (10, 7))
    fmhz = sols[0].freqs / 1e6
    for night, sol in zip(NIGHTS, sols, strict=True):
        band(axes[0], fmhz, sol.G[0, 0], sol.sigma_G[0, 0], f"JD {night}")
        band(axes[1], fmhz, sol.Trxr[0, 0], sol.sigma_Trxr[0, 0], f"JD {night}")
    robust_ylim(axes[0], g[:, 0])
    robust_ylim(axes[1], t[:, 0])
    axes[0].set(ylabel="G", title=f"antenna {sols[0].antennas[0]} ee, LST {COMMON_LST} h")
    axes[1].set(ylabel="Trxr [K]", xlabel="frequency [MHz]")
    axes[0].legend(fontsize=8)
    save_figure(fig, out / "repeatability.png")
    return {"lst_range_h": COMMON_LST, "antennas": rows}


def hera_2458098(root: Path, out: Path) -> dict:
    """The paper's night: 8 antennas, 10 integrations, vs relative omnical gains."""
    result = run_calibration(
        CalibrationConfig(
            inputs=[str(root / "hera/autos/zen.2458098.45361.HH_downselected.uvh5")],
            reference=[
                str(root / "hera/reference_gains/zen.2458098.45361.HH.omni_downselected.calfits")
            ],
            products=["hdf5", "png"],
        ),
        out / "hera_2458098",
    )
    return {"comparison": per_pol(Path(result.products["compare_json"]))}


def edges(out: Path) -> dict:
    """EDGES-2 lab loads calibrated against thermistors; an EDGES-like day through autocal."""
    from autocal.edges.lab_checks import check_edges2_loads
    from autocal.edges.noise_waves import expected_auto_model
    from autocal.edges.simulated_day import simulate_edges_day
    from autocal.edges.solutions import load_receiver_solution
    from autocal.io.products import read_solution

    loads = check_edges2_loads()
    receiver = load_receiver_solution("edges2-lowband-2015")
    day = simulate_edges_day(out / "edges_day_raw", solution=receiver, n_times=72, seed=11)
    run_calibration(
        CalibrationConfig(
            inputs=[str(p) for p in day.paths],
            beam="edges-low",
            sky="powerlaw:gsm2008@408:-2.55",
            freq_range_mhz=(50.0, 100.0),
            products=["hdf5", "png"],
        ),
        out / "edges_day",
    )
    sol = read_solution(out / "edges_day" / "solution.h5")
    expected = expected_auto_model(receiver, 0.0, "q")
    exp_g = np.interp(sol.freqs, expected.freqs, expected.G)
    exp_t = np.interp(sol.freqs, expected.freqs, expected.trxr)
    pull_g = (sol.G[0, 0] - exp_g) / sol.sigma_G[0, 0]  # total errors
    pull_t = (sol.Trxr[0, 0] - exp_t) / sol.sigma_Trxr[0, 0]
    stat_g = (sol.G[0, 0] - exp_g) / sol.sigma_G_stat[0, 0]
    stat_t = (sol.Trxr[0, 0] - exp_t) / sol.sigma_Trxr_stat[0, 0]
    return {
        "lab_loads": loads,
        "edges_day": {
            "channels": int(sol.freqs.size),
            "integrations": int(sol.lsts.size),
            "G_pull_mean": float(np.mean(pull_g)),
            "G_pull_std": float(np.std(pull_g)),
            "Trxr_pull_mean": float(np.mean(pull_t)),
            "Trxr_pull_std": float(np.std(pull_t)),
            "G_stat_pull_std": float(np.std(stat_g)),
            "Trxr_stat_pull_std": float(np.std(stat_t)),
            "Trxr_expected_median_K": float(np.median(exp_t)),
            "median_reduced_chi2": float(np.nanmedian(sol.reduced_chi2)),
        },
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, default=Path("docs/results"))
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    root = data_dir()
    if root is None:
        raise SystemExit("data folder not found: set AUTOCAL_DATA_DIR")
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    results = {
        "hera_2458116_ant23": hera_2458116(root, args.out),
        "hera_repeatability": hera_repeatability(root, args.out),
        "hera_2458098": hera_2458098(root, args.out),
        "edges": edges(args.out),
    }
    results["seconds"] = round(time.perf_counter() - t0, 1)
    (args.out / "results.json").write_text(json.dumps(results, indent=2, default=str))
    print(json.dumps(results, indent=2, default=str))


if __name__ == "__main__":
    main()
