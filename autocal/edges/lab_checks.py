"""Checks of the receiver calibration against the lab data in the data folder.

:func:`check_edges2_loads` calibrates the EDGES-2 2015 calibration loads with their own
solutions, :func:`lab_check_edges3` the EDGES-3 mock-archive loads, and
:func:`lab_check_receiver01` derives a two-load calibration of the Receiver01 lab spectra;
each compares with the loads' logged temperatures.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import h5py
import numpy as np

from autocal.edges.lab_files import (
    TemperatureSeries,
    read_edges3_temperature_log,
    read_lab_thermistor,
    read_load_spectrum_txt,
    read_s11_modelled,
)
from autocal.edges.noise_waves import calibrate_q, calibrate_tstar, tstar_from_q, two_load_solution
from autocal.edges.solutions import (
    ReceiverCalError,
    ReceiverSolution,
    load_receiver_solution,
    resolve_solution,
)
from autocal.io.datasets import data_dir, data_file
from autocal.io.edges_acq import read_acq_spectra


def _band_stats(values: np.ndarray) -> dict[str, float]:
    """Return the mean, rms about it, min and max of the finite ``values``."""
    v = np.asarray(values, np.float64)
    v = v[np.isfinite(v)]
    return {
        "mean": float(v.mean()),
        "rms_about_mean": float(v.std()),
        "min": float(v.min()),
        "max": float(v.max()),
    }


def check_edges2_loads(
    freq_range: tuple[float, float] = (50e6, 100e6),
) -> dict[str, dict[str, Any]]:
    """Calibrate the EDGES-2 2015 calibration loads with their own solutions.

    Two independent routes, both from the data folder: (1) Bowman et al. 2018
    ``specal_alan.txt`` (T_NS 1000 K) on the averaged ``sp*.txt`` load spectra (``T*``)
    with the modelled S11s of ``s11_modelled_alan.txt``; (2) edges-cal's
    ``reference.h5`` (T_NS 350 K) on the ``Q`` spectra of ``edges2_2015_09/spectra``,
    which also record the loads' thermistor temperatures (``temp_ave``).

    Returns
    -------
    dict
        Per route and load: band statistics of the calibrated temperature (K) and, for
        route 2, the thermistor temperature.
    """
    lo, hi = freq_range
    out: dict[str, dict[str, Any]] = {"specal_alan": {}, "edges_cal_reference": {}}
    sol = load_receiver_solution("edges2-lowband-2015")
    base = "edges/receiver_cal/edges2_lowband_2015/"
    fs, s11 = read_s11_modelled(data_file(base + "s11_modelled_alan.txt"))
    # the modelled S11s are fitted over 50-100 MHz and diverge outside (|S11| > 1 at 40 MHz)
    band = (sol.freqs >= lo) & (sol.freqs <= hi)
    sub = sol.at(sol.freqs[band])
    for load in ("amb", "hot", "open", "short"):
        f, tstar, w = read_load_spectrum_txt(data_file(base + f"sp{load}.txt"))
        if not (np.allclose(f, sol.freqs) and np.allclose(fs, sol.freqs)):
            raise ReceiverCalError("Alan's load spectra, S11 and solution channels differ")
        temp = calibrate_tstar(tstar[band], sub, s11[load][band])
        out["specal_alan"][load] = _band_stats(temp[w[band] > 0])
    ref = load_receiver_solution("edges2-2015-09")
    keys = {
        "ambient": "ambient_s11",
        "hot_load": "hot_load_s11",
        "open": "open_s11",
        "short": "short_s11",
    }
    with h5py.File(data_file("edges/receiver_cal/edges2_2015_09/reference.h5"), "r") as h5:
        gammas = {k: h5[v][()] for k, v in keys.items()}
    band = (ref.freqs >= lo) & (ref.freqs <= hi)
    for load in keys:
        with h5py.File(
            data_file(f"edges/receiver_cal/edges2_2015_09/spectra/{load}.h5"), "r"
        ) as h5:
            q = h5["data/q"][()]
            fq = h5["data/freq/freq"][()] * 1e6
            t_load, t_ns = float(h5["data/t_load"][()]), float(h5["data/t_load_ns"][()])
            thermistor = float(h5["data/temp_ave"][()])
        if (t_load, t_ns) != (ref.t_load, ref.t_load_ns):
            raise ReceiverCalError(f"{load}.h5 uses T_L {t_load}, T_NS {t_ns}, not the solution's")
        temp = calibrate_q(np.interp(ref.freqs, fq, q), ref, gammas[load])
        out["edges_cal_reference"][load] = {**_band_stats(temp[band]), "thermistor_K": thermistor}
    return out


def lab_check_edges3(
    solution: ReceiverSolution | str = "edges3-2022-316",
    *,
    freq_range: tuple[float, float] = (50e6, 190e6),
    bin_factor: int = 64,
) -> dict[str, dict[str, Any]]:
    """Calibrate the EDGES-3 mock-archive lab loads (2023 day 070) with a receiver solution.

    Reads ``acq/edges3-mock-root/mro/{amb,hot,open,short}``, averages each file's cycles,
    calibrates ``Q`` with the solution (nominal ``T_NS = 1000 K``) and the modelled load
    S11s of ``edges3_2022_316/s11_modelled.txt``, and compares with the EDGES-3
    temperature log (ambient load code 101, hot load code 102) at the file's time. The
    solution is from 2022 (four months earlier); the open/short cable S11s have changed
    since, so their noise-wave ripple is not expected to cancel.

    Returns
    -------
    dict
        Per load: band statistics (K), the logged load temperature (K) and ``T*`` stats.
    """
    sol = resolve_solution(solution)
    root = data_dir(required=True) / "edges/acq/edges3-mock-root"
    log = read_edges3_temperature_log(root / "temperature_logger/temperature.log")
    fs, s11 = read_s11_modelled(data_file("edges/receiver_cal/edges3_2022_316/s11_modelled.txt"))
    out: dict[str, dict[str, Any]] = {}
    for load in ("amb", "hot", "open", "short"):
        files = sorted((root / "mro" / load).rglob("*.acq"))
        spec = read_acq_spectra(files, freq_range=freq_range, bin_factor=bin_factor)
        s = sol.at(spec.freqs)
        q = np.nanmean(spec.q, axis=0)
        temp = calibrate_q(q, s, (fs, s11[load]))
        jd = float(spec.jds.mean())
        entry: dict[str, Any] = {
            **_band_stats(temp),
            "tstar": _band_stats(tstar_from_q(q, s.t_load_ns, s.t_load)),
            "jd": jd,
            "files": [str(f) for f in files],
        }
        for name in ("amb_load", "hot_load", "front_end"):
            entry[f"log_{name}_K"] = float(log.at(jd, name, max_extrapolation_s=900.0)[0])
        out[load] = entry
    return out


def lab_check_receiver01(
    *,
    freq_range: tuple[float, float] = (50e6, 190e6),
    bin_factor: int = 256,
    utc_offset_hours: float = -7.0,
) -> dict[str, Any]:
    """Two-load calibration of the Receiver01 (2019, 25 C) lab spectra.

    No noise-wave solution of this lab receiver is available, so: (1) ``T*`` with the
    nominal 400 K / 300 K is reported for every file; (2) ``T_NS'`` and ``T_L'`` are
    derived from the *first* ambient and hot-load files and the load thermistor
    (``Resistance/*.csv``, interpolated or extrapolated to the spectrum time) assuming
    matched loads (their raw S11 is ~0.02); (3) every file is calibrated with that
    two-load solution and compared with its own load thermistor where one was logged
    within 2 minutes. Noise: one 0.49 s cycle per file.

    Returns
    -------
    dict
        ``t_ns_eff``, ``t_load_eff`` and ``t_offset`` band statistics (K), the thermistor
        temperatures used, and per-file results.
    """
    root = data_dir(required=True) / "edges/acq/Receiver01_25C_2019_11_26_040_to_200MHz"
    spectra_dir, res_dir = root / "Spectra", root / "Resistance"

    def thermistor(stem: str) -> TemperatureSeries | None:
        hits = sorted(res_dir.glob(f"{stem}_*.csv"))
        return read_lab_thermistor(hits[0], utc_offset_hours) if hits else None

    def read(path: Path) -> Any:
        return read_acq_spectra(path, freq_range=freq_range, bin_factor=bin_factor)

    amb_file = sorted(spectra_dir.glob("Ambient_*.acq"))[0]
    hot_file = sorted(spectra_dir.glob("HotLoad_*.acq"))[0]
    amb, hot = read(amb_file), read(hot_file)
    t_amb = float(thermistor("Ambient").at(amb.jds[0], "load")[0])
    t_hot = float(thermistor("HotLoad").at(hot.jds[0], "load")[0])
    t_ns, t_l = two_load_solution(amb.q[0], hot.q[0], t_amb, t_hot)
    ratio = amb.p2[0] / amb.p1[0]
    out: dict[str, Any] = {
        "freq_range_Hz": list(freq_range),
        "bin_factor": bin_factor,
        "t_amb_K": t_amb,
        "t_hot_K": t_hot,
        "t_ns_eff": _band_stats(t_ns),
        "t_load_eff": _band_stats(t_l),
        "t_offset": _band_stats(t_ns / (ratio - 1) - t_l),
        "files": {},
    }
    for path in sorted(spectra_dir.glob("*.acq")):
        spec = read(path)
        q = spec.q[0]
        stem = path.name.split("_")[0]
        series = thermistor(stem)
        t_phys = float(series.at(spec.jds[0], "load")[0]) if series is not None else np.nan
        out["files"][path.name] = {
            "tstar_400_300": _band_stats(tstar_from_q(q, 400.0, 300.0)),
            "two_load": _band_stats(t_ns * q + t_l),
            "thermistor_K": t_phys,
        }
    return out
