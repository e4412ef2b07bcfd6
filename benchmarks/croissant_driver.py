"""Run croissant-sim on a problem written by ``benchmarks/tsky_vs_croissant.py`` and time it.

This script runs in croissant's own virtualenv (``make bench-croissant-env``), never in
autocal's: it imports only croissant, jax, numpy and astropy. Usage::

    .venv-croissant/bin/python benchmarks/croissant_driver.py PROBLEM.npz RESULT.npz

``PROBLEM.npz`` holds the beam on croissant's topocentric HEALPix grid (``theta`` the
zenith angle, ``phi`` from east towards north, RING order; the grid is checked against
croissant's own), the weight of every direction above the horizon (``horizon``: croissant
multiplies the beam by it before the transform, and its ground fraction is
``1 - integral(beam horizon) / integral(beam)``), the sky maps (RING, ``sky_coord``
frame), the channels, the start time (JD) and the LST offsets from it (hours), the
site and the ground temperature.

``RESULT.npz`` receives Tsky ``(Ntime, Nfreq)`` from ``Simulator.sim`` and, as JSON in
``report``, the timings: construction, the first call (jax compilation plus one run) and
the warm calls (all ``repeat`` of them) of the two stages of ``Simulator.sim()``: the
sky's transform and rotation (``Simulator.precompute_sky_alm``), then
``sim(sky_alm=...)`` (the beam's transform and rotation, the convolution). ``sim()``
itself is not called: it runs the same two stages in one jax program, whose compilation
took another 10 minutes on 2 busy cores.
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from functools import partial
from importlib.metadata import version
from typing import Any

os.environ.setdefault("JAX_ENABLE_X64", "1")  # croissant warns that float32 is inaccurate

import jax
import numpy as np
from astropy.utils import iers

iers.conf.auto_download = False  # offline: the bundled IERS tables cover the dates used

import croissant  # noqa: E402


def _say(message: str) -> None:
    """A progress line on stderr (the caller's terminal)."""
    sys.stderr.write(f"[croissant {time.strftime('%H:%M:%S')}] {message}\n")
    sys.stderr.flush()


def _timed(call: Any) -> tuple[float, Any]:
    """Wall time of ``call()`` with jax's asynchronous dispatch waited for."""
    t0 = time.perf_counter()
    value = jax.block_until_ready(call())
    return time.perf_counter() - t0, value


def _warm(call: Any, repeat: int) -> tuple[list[float], Any]:
    """Times of ``repeat`` calls after the first (compiling) one; the last value."""
    times, value = [], None
    for _ in range(repeat):
        elapsed, value = _timed(call)
        times.append(round(elapsed, 4))
    return times, value


def run(problem: dict[str, np.ndarray]) -> dict[str, Any]:
    """Build croissant's beam, sky and simulator for ``problem``, run and time them."""
    freqs = problem["freqs_mhz"]
    niter = int(problem["niter"])
    repeat = int(problem["repeat"])
    report: dict[str, Any] = {}

    # croissant turns the sky by 2 pi per croissant.constants.sidereal_day from the first
    # time on: times whose LST offsets are the problem's
    day_s = croissant.constants.sidereal_day["earth"]
    times_jd = float(problem["t0_jd"]) + problem["lst_offsets_h"] / 24.0 * day_s / 86400.0

    t0 = time.perf_counter()
    beam = croissant.Beam(
        problem["beam"], freqs, sampling="healpix", horizon=problem["horizon"], niter=niter
    )
    sky = croissant.Sky(
        problem["sky"], freqs, sampling="healpix", coord=str(problem["sky_coord"]), niter=niter
    )
    sim = croissant.Simulator(
        beam,
        sky,
        times_jd,
        freqs,
        lon=float(problem["lon_deg"]),
        lat=float(problem["lat_deg"]),
        alt=float(problem["alt_m"]),
        world="earth",
        Tgnd=float(problem["tgnd_K"]),
    )
    report["construct_s"] = round(time.perf_counter() - t0, 3)
    report["grid_max_diff_rad"] = float(
        max(
            np.abs(np.asarray(beam.theta) - problem["theta"]).max(),
            np.abs(np.asarray(beam.phi) - problem["phi"]).max(),
        )
    )
    report["lmax"] = int(sim.lmax)
    _say(f"constructed in {report['construct_s']} s; lmax {sim.lmax}; the sky's alm")

    # the sky's transform and rotation to FK5 (what sim() does first when not given them)
    report["sky_alm_first_s"], _ = _timed(sim.precompute_sky_alm)
    _say(f"sky alm first call {report['sky_alm_first_s']:.1f} s; warm calls")
    report["sky_alm_warm_s"], sky_alm = _warm(sim.precompute_sky_alm, repeat)
    # sim(sky_alm=...): the beam's transform and rotation to FK5, the convolution
    call = partial(sim.sim, sky_alm=sky_alm)
    report["sim_alm_first_call_s"], _ = _timed(call)
    _say(f"sim(sky_alm) first call {report['sim_alm_first_call_s']:.1f} s; warm calls")
    report["sim_alm_warm_s"], tsky = _warm(call, repeat)
    _say(f"sim(sky_alm) warm {report['sim_alm_warm_s']} s")

    report["versions"] = {
        pkg: version(pkg) for pkg in ("croissant-sim", "jax", "jaxlib", "s2fft", "numpy")
    }
    report["python"] = platform.python_version()
    report["jax_x64"] = bool(jax.config.read("jax_enable_x64"))
    report["jax_devices"] = [str(d) for d in jax.devices()]
    report["tsky"] = np.asarray(tsky)
    return report


def main() -> int:
    """Read the problem, run croissant, write Tsky and the report."""
    if len(sys.argv) != 3:
        sys.stderr.write(__doc__ or "")
        return 2
    with np.load(sys.argv[1]) as f:
        problem = {k: f[k] for k in f.files}
    report = run(problem)
    tsky = report.pop("tsky")
    np.savez(sys.argv[2], tsky=tsky, report=json.dumps(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
