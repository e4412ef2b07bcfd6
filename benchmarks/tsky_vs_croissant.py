"""Speed guard (issue 25, item 4): the Tsky engine against croissant-sim on the same problem.

croissant-sim (https://github.com/christianhbye/croissant, a JAX spherical-harmonic
simulator) is not a dependency of autocal: it runs in its own virtualenv, made by
``make bench-croissant-env`` (``.venv-croissant/``, pinned in
``benchmarks/croissant-requirements.txt``), as a subprocess
(``benchmarks/croissant_driver.py``). One command:

1. builds one problem for both: GSM2008 (with the CMB), the HERA site, ``--nfreq``
   channels, ``--nlst`` LSTs over 24 h starting at apparent LST 0 on ``--date``, nside
   ``--nside`` (both band-limited to ``lmax = 2 nside``: croissant's HEALPix transforms
   stop there, and :func:`~autocal.tsky.compute.compute_tsky` band-limits its sky to it),
   a beam (``--beam``: the analytic dipole or the HERA beam file), the 2-degree soft
   horizon and a 300 K ground.

   * autocal: :func:`~autocal.tsky.bandlimit.band_limited_components` (the sky in the
     apparent equatorial frame of the start time) and
     :func:`~autocal.tsky.ringfft.tsky_fft`, as ``compute_tsky`` runs them (without its
     disk cache).
   * croissant: the same continuous sky (GSM2008's native maps interpolated bilinearly,
     band-limited the same way) but in *Galactic* coordinates, which croissant rotates to
     FK5 itself; the beam evaluated on croissant's topocentric HEALPix grid (``phi`` from
     east towards north); the soft horizon passed as croissant's ``horizon`` weight
     (croissant multiplies the beam by it and takes the ground fraction from it, so
     ``Tsky = [int A w T + Tgnd int A (1 - w)] / int A``, autocal's formula); times in
     JD whose LSTs are the same (croissant turns the sky at its own sidereal rate from
     the first time on).

2. compares the two tables (max and rms |difference|, per channel);
3. times both side by side on the same machine, best of ``--repeat`` warm runs each:
   the engine (``tsky_fft``, including its beam evaluation) against croissant's
   ``Simulator.sim(sky_alm=...)`` (beam transform and rotation, convolution; the sky's
   transform precomputed, as the engine's sky components are); and, for information,
   each from the sky maps (engine plus its sky preparation against croissant's sky
   transform and rotation, ``Simulator.precompute_sky_alm``, plus ``sim(sky_alm=...)``:
   the two stages of ``Simulator.sim()``). croissant's first calls (jax compilation plus
   one run) are reported separately;
4. exits 1 if the engine is less than ``--guard`` (100) times faster than croissant in
   the like-for-like comparison (3, first), 3 if croissant's environment is missing.

Usage::

    make bench-croissant-env                      # once (needs PyPI), then offline
    python benchmarks/tsky_vs_croissant.py        # dipole, 32 channels x 1440 LSTs
    python benchmarks/tsky_vs_croissant.py --quick

Writes ``benchmarks/results/tsky_vs_croissant.json`` and ``.md``
(``tsky_vs_croissant_quick.*`` with ``--quick``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import healpy as hp
import numpy as np
from astropy import units as u
from astropy.time import Time
from tsky import machine_info  # benchmarks/tsky.py: the same machine description

from autocal.core.coords import resample_healpix
from autocal.core.sites import HERA
from autocal.sky.beam_names import get_beam
from autocal.sky.models import T_CMB, get_sky
from autocal.tsky.bandlimit import band_limit_maps, band_limited_components, fine_nside
from autocal.tsky.horizon import HORIZON_WIDTH_DEG, horizon_weight
from autocal.tsky.result import T_GROUND
from autocal.tsky.ringfft import tsky_fft

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
DRIVER = ROOT / "benchmarks" / "croissant_driver.py"
DEFAULT_PYTHON = ROOT / ".venv-croissant" / "bin" / "python"
GUARD_SPEEDUP = 100.0
EXIT_GUARD_FAILED = 1
EXIT_NO_CROISSANT = 3


# the problem ----------------------------------------------------------------------------


def start_jd(date: str, lst0_hours: float) -> float:
    """The UTC Julian date on ``date`` when the apparent LST at HERA is ``lst0_hours``."""
    t0 = Time(f"{date}T00:00:00", scale="utc")
    lst = t0.sidereal_time("apparent", longitude=HERA.lon_deg * u.deg).hour
    solar_hours = ((lst0_hours - lst) % 24.0) / 1.00273790935
    t = t0 + solar_hours * u.hour
    for _ in range(3):  # refine: the sidereal rate above is the mean one
        lst = t.sidereal_time("apparent", longitude=HERA.lon_deg * u.deg).hour
        t = t + (((lst0_hours - lst + 12.0) % 24.0) - 12.0) / 1.00273790935 * u.hour
    return float(t.jd)


def croissant_grid(nside: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Croissant's topocentric HEALPix grid (RING) as ``theta, phi`` and autocal's ``az, za``.

    croissant's beam frame is east-north-up with ``phi`` from east towards north (its
    ``Beam`` docstring: ``beam_rot = 0`` keeps ``phi = 0`` on local east); autocal's
    azimuth runs from north through east, so ``az = pi/2 - phi``.
    """
    theta, phi = hp.pix2ang(nside, np.arange(hp.nside2npix(nside)))
    return theta, phi, np.mod(np.pi / 2 - phi, 2 * np.pi), theta


def galactic_band_limited(freqs: np.ndarray, nside: int) -> np.ndarray:
    """GSM2008 plus the CMB in Galactic coordinates, band-limited as the engine's sky.

    The same continuous sky as :func:`band_limited_components` (the native maps
    interpolated bilinearly at the pixel centres of nside :func:`fine_nside`, transformed
    to ``lmax = 2 nside`` and synthesised at ``nside``), in the Galactic frame.
    """
    fine = fine_nside(nside)
    maps, spectra, _ = get_sky("gsm2008").galactic(freqs, fine)
    pixels = np.array(hp.pix2vec(fine, np.arange(hp.nside2npix(fine))))
    sampled = resample_healpix(maps, fine, pixels)  # no change of frame
    return spectra @ band_limit_maps(sampled, nside) + T_CMB


def build_problem(args: argparse.Namespace) -> dict[str, Any]:
    """Channels, LSTs, start time, beam grid and both skies of the comparison."""
    beam = get_beam(args.beam)
    lo, hi = beam.freq_range or (args.fmin_mhz * 1e6, args.fmax_mhz * 1e6)
    freqs = np.linspace(max(lo, args.fmin_mhz * 1e6), min(hi, args.fmax_mhz * 1e6), args.nfreq)
    lsts = np.arange(args.nlst) * (24.0 / args.nlst)
    t0 = start_jd(args.date, float(lsts[0]))
    theta, phi, az, za = croissant_grid(args.nside)
    return {
        "beam": beam,
        "freqs": freqs,
        "lsts": lsts,
        "t0_jd": t0,
        "croissant": {
            "freqs_mhz": freqs / 1e6,
            "beam": beam.power(freqs, az, za),
            "horizon": horizon_weight(np.pi / 2 - theta, HORIZON_WIDTH_DEG),
            "theta": theta,
            "phi": phi,
            "sky": galactic_band_limited(freqs, args.nside),
            "sky_coord": np.array("galactic"),
            "t0_jd": t0,
            "lst_offsets_h": lsts - lsts[0],
            "lon_deg": HERA.lon_deg,
            "lat_deg": HERA.lat_deg,
            "alt_m": HERA.alt_m,
            "tgnd_K": T_GROUND,
            "niter": args.niter,
            "repeat": args.repeat,
        },
    }


# the two sides --------------------------------------------------------------------------


def run_engine(problem: dict[str, Any], nside: int, repeat: int) -> dict[str, Any]:
    """Sky preparation and ``tsky_fft``, each best of ``repeat`` (warm), and the table."""
    sky, beam, freqs, lsts = get_sky("gsm2008"), problem["beam"], problem["freqs"], problem["lsts"]
    prep, first_call, times = [], None, []
    comps = None
    for i in range(repeat):
        # a new epoch (1 s later) each round: nothing memoised; the first is the problem's
        epoch = problem["t0_jd"] + i / 86400.0
        t0 = time.perf_counter()
        prepared = band_limited_components(sky, freqs, nside, epoch=epoch)
        prep.append(time.perf_counter() - t0)
        comps = comps or prepared
    assert comps is not None
    table = None
    for i in range(repeat + 1):
        t0 = time.perf_counter()
        result = tsky_fft(comps, beam, HERA, lsts, progress=False)
        elapsed = time.perf_counter() - t0
        if i == 0:
            first_call, table = elapsed, result.tsky
        else:
            times.append(elapsed)
    return {
        "sky_prep_s": [round(t, 3) for t in prep],
        "sky_prep_best_s": round(min(prep), 3),
        "first_call_s": round(float(first_call or 0.0), 3),
        "times_s": [round(t, 4) for t in times],
        "best_s": round(min(times), 4),
        "median_s": round(float(np.median(times)), 4),
        "tsky": table,
    }


def croissant_missing(python: Path) -> str | None:
    """Why croissant cannot be run with ``python`` (``None``: it can)."""
    if not python.exists():
        return f"{python} does not exist"
    check = subprocess.run(
        [str(python), "-c", "import croissant, jax, s2fft"],
        capture_output=True,
        text=True,
        check=False,
    )
    if check.returncode != 0:
        last = (check.stderr.strip().splitlines() or ["no message"])[-1]
        return f"{python} cannot import croissant ({last})"
    return None


def run_croissant(problem: dict[str, Any], python: Path) -> dict[str, Any]:
    """Write the problem, run the driver in croissant's environment, read its result."""
    with tempfile.TemporaryDirectory(prefix="autocal-croissant-") as tmp:
        src, dst = Path(tmp) / "problem.npz", Path(tmp) / "result.npz"
        np.savez(src, **problem["croissant"])
        t0 = time.perf_counter()
        subprocess.run([str(python), str(DRIVER), str(src), str(dst)], check=True)
        wall = time.perf_counter() - t0
        with np.load(dst) as f:
            tsky = f["tsky"]
            report = json.loads(str(f["report"]))
    report["process_wall_s"] = round(wall, 1)
    for key in ("sim_alm_warm_s", "sky_alm_warm_s"):
        report[key.replace("warm_s", "best_s")] = min(report[key])
    report["tsky"] = tsky
    return report


# comparison and report ------------------------------------------------------------------


def agreement(engine: np.ndarray, croissant: np.ndarray, freqs: np.ndarray) -> dict[str, Any]:
    """Max, rms and per-channel max of ``|engine - croissant|`` (K), and relative to Tsky."""
    diff = engine - croissant
    per_channel = np.abs(diff).max(axis=0)
    show = np.unique(np.linspace(0, freqs.size - 1, min(5, freqs.size)).astype(int))
    return {
        "max_K": round(float(np.abs(diff).max()), 4),
        "rms_K": round(float(np.sqrt(np.mean(diff**2))), 4),
        "max_relative": float(np.abs(diff / engine).max()),
        "mean_K": round(float(diff.mean()), 4),
        "tsky_range_K": [round(float(engine.min()), 1), round(float(engine.max()), 1)],
        "max_per_channel_K": {
            f"{freqs[i] / 1e6:.1f} MHz": round(float(per_channel[i]), 4) for i in show
        },
    }


def render(res: dict[str, Any]) -> str:
    """Markdown report."""
    cfg, eng, cro, agr, sp = (
        res[k] for k in ("config", "engine", "croissant", "agreement", "speedup")
    )
    mach = res["machine"]
    lines = [
        f"# Tsky: autocal's engine vs croissant-sim {cro['versions']['croissant-sim']} "
        f"(`{cfg['command']}`)",
        "",
        f"GSM2008 + CMB, HERA site, {cfg['beam']} beam, {cfg['nfreq']} channels "
        f"{cfg['fmin_MHz']:g}-{cfg['fmax_MHz']:g} MHz, {cfg['nlst']} LSTs over 24 h from "
        f"apparent LST 0 on {cfg['date']} (JD {cfg['t0_jd']:.5f}), nside {cfg['nside']} "
        f"(lmax {cro['lmax']}), soft horizon {HORIZON_WIDTH_DEG:g} deg, Tgnd {T_GROUND:g} K; "
        f"croissant's transforms with niter {cfg['niter']}, jax {cro['versions']['jax']} on "
        f"{', '.join(cro['jax_devices'])}, x64 {cro['jax_x64']}.",
        "",
        f"Machine: {mach['cpu']}, {mach['cores']} cores, shared with other work: load "
        f"average {mach['load_average_start']} at the start, {mach['load_average_end']} at "
        "the end (timings are noisy).",
        "",
        f"**Agreement**: max |engine - croissant| = {agr['max_K']} K, rms {agr['rms_K']} K, "
        f"mean {agr['mean_K']} K, max relative {agr['max_relative']:.2g} (Tsky "
        f"{agr['tsky_range_K'][0]}-{agr['tsky_range_K'][1]} K); per channel: "
        + ", ".join(f"{k} {v} K" for k, v in agr["max_per_channel_K"].items())
        + ".",
        "",
        f"| best of {cfg['repeat']} warm runs, side by side | autocal | croissant | "
        "engine speed-up |",
        "|---|---|---|---|",
        f"| Tsky from the prepared sky: `tsky_fft` vs `Simulator.sim(sky_alm=...)` | "
        f"{eng['best_s']:.3f} s | {cro['sim_alm_best_s']:.2f} s | "
        f"**{sp['prepared_sky']:.0f}x** |",
        "| Tsky from the sky maps: sky preparation + `tsky_fft` vs "
        "`precompute_sky_alm()` + `sim(sky_alm=...)` (the two stages of `sim()`) | "
        f"{eng['sky_prep_best_s']:.2f} + {eng['best_s']:.3f} s | "
        f"{cro['sky_alm_best_s']:.2f} + {cro['sim_alm_best_s']:.2f} s | "
        f"{sp['from_maps']:.0f}x |",
        "| first call (croissant: jax compilation + one run) of the first row | "
        f"{eng['first_call_s']:.3f} s | {cro['sim_alm_first_call_s']:.1f} s | "
        f"{sp['first_call']:.0f}x |",
        "",
        f"croissant, not in the times above: construction {cro['construct_s']} s (jax "
        f"compiles its rotation tables), first call of the sky's transform "
        f"{cro['sky_alm_first_s']:.1f} s; the whole subprocess {cro['process_wall_s']} s. "
        "The engine's sky preparation is the band-limited GSM2008 components (model "
        f"evaluation at nside {fine_nside(cfg['nside'])}, transform, synthesis), once per "
        "sky, channel set and epoch; croissant's the sky's transform and rotation, from "
        "maps made beforehand (the same band-limited sky, in Galactic coordinates).",
        "",
        f"**Guard** (engine >= {cfg['guard']:g}x faster than croissant, Tsky from the "
        f"prepared sky): {'PASS' if res['guard_passed'] else 'FAIL'} ({sp['prepared_sky']:.0f}x).",
        "",
    ]
    return "\n".join(lines)


def main() -> int:
    """Run the comparison; the exit code is the guard's."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="8 channels x 96 LSTs, 2 runs")
    parser.add_argument("--beam", default="dipole", help="dipole (default) or hera")
    parser.add_argument("--nside", type=int, default=64)
    parser.add_argument("--nfreq", type=int, default=None, help="default 32 (quick 8)")
    parser.add_argument("--nlst", type=int, default=None, help="default 1440 (quick 96)")
    parser.add_argument("--fmin-mhz", type=float, default=100.0)
    parser.add_argument("--fmax-mhz", type=float, default=200.0)
    parser.add_argument("--date", default="2000-01-01", help="UTC date of the first LST")
    parser.add_argument(
        "--niter", type=int, default=0, help="croissant's SHT iterations (its default 0)"
    )
    parser.add_argument("--repeat", type=int, default=None, help="warm runs (3; quick 2)")
    parser.add_argument("--guard", type=float, default=GUARD_SPEEDUP)
    parser.add_argument("--croissant-python", type=Path, default=DEFAULT_PYTHON)
    parser.add_argument("--out", type=Path, default=None, help="output prefix (no suffix)")
    parser.add_argument("--tables", type=Path, default=None, help="also save both tables (.npz)")
    args = parser.parse_args()
    args.nfreq = args.nfreq or (8 if args.quick else 32)
    args.repeat = args.repeat or (2 if args.quick else 3)
    args.nlst = args.nlst or (96 if args.quick else 1440)

    why = croissant_missing(args.croissant_python)
    if why:
        print(
            f"croissant-sim is not available: {why}.\nIt is optional and lives in its own "
            "virtualenv: run `make bench-croissant-env` (needs PyPI once), or pass "
            "--croissant-python PATH to a Python with croissant-sim installed.",
            file=sys.stderr,
        )
        return EXIT_NO_CROISSANT

    machine = machine_info()
    problem = build_problem(args)
    freqs = problem["freqs"]
    print(f"problem: {freqs.size} channels x {args.nlst} LSTs, nside {args.nside}", flush=True)
    engine = run_engine(problem, args.nside, args.repeat)
    print(f"engine: {engine['times_s']} s (sky preparation {engine['sky_prep_s']} s)", flush=True)
    croissant = run_croissant(problem, args.croissant_python)
    print(f"croissant: sim(sky_alm) {croissant['sim_alm_warm_s']} s", flush=True)
    machine["load_average_end"] = [round(x, 2) for x in os.getloadavg()]

    speedup = {
        "prepared_sky": croissant["sim_alm_best_s"] / engine["best_s"],
        "from_maps": (croissant["sky_alm_best_s"] + croissant["sim_alm_best_s"])
        / (engine["sky_prep_best_s"] + engine["best_s"]),
        "first_call": croissant["sim_alm_first_call_s"] / engine["first_call_s"],
    }
    command = "python benchmarks/tsky_vs_croissant.py" + " ".join(
        [""] + [a for a in sys.argv[1:] if not a.startswith("--croissant-python")]
    )
    res: dict[str, Any] = {
        "config": {
            "command": command,
            "beam": args.beam,
            "nside": args.nside,
            "nfreq": int(freqs.size),
            "fmin_MHz": float(freqs[0] / 1e6),
            "fmax_MHz": float(freqs[-1] / 1e6),
            "nlst": args.nlst,
            "date": args.date,
            "t0_jd": problem["t0_jd"],
            "niter": args.niter,
            "repeat": args.repeat,
            "guard": args.guard,
        },
        "machine": machine,
        "agreement": agreement(engine["tsky"], croissant["tsky"], freqs),
        "engine": {k: v for k, v in engine.items() if k != "tsky"},
        "croissant": {k: v for k, v in croissant.items() if k != "tsky"},
        "speedup": {k: round(v, 1) for k, v in speedup.items()},
        "guard_passed": bool(speedup["prepared_sky"] >= args.guard),
    }
    if args.tables:
        np.savez(
            args.tables,
            engine=engine["tsky"],
            croissant=croissant["tsky"],
            freqs=freqs,
            lsts=problem["lsts"],
        )
    markdown = render(res)
    print(markdown)
    out = args.out or RESULTS / ("tsky_vs_croissant_quick" if args.quick else "tsky_vs_croissant")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(res, indent=2) + "\n")
    out.with_suffix(".md").write_text(markdown)
    print(f"wrote {out.with_suffix('.json')} and {out.with_suffix('.md')}")
    return 0 if res["guard_passed"] else EXIT_GUARD_FAILED


if __name__ == "__main__":
    sys.exit(main())
