"""EDGES lab files: S11 tables, averaged load spectra, thermistor and temperature logs.

The lab data in the data folder the receiver calibration is checked against
(:mod:`autocal.edges.lab_checks`): modelled and measured reflection coefficients, the
averaged load spectra of Bowman et al. 2018, the ASU lab's thermistor logs and the
EDGES-3 temperature logger, read into :class:`TemperatureSeries`.
"""

from __future__ import annotations

import contextlib
import csv
import logging
import re
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np
from astropy.time import Time

from autocal.edges.solutions import ReceiverCalError

logger = logging.getLogger(__name__)


def read_s11_modelled(path: str | Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Read an ``s11_modelled*.txt`` table: ``# freq, amb_real amb_imag hot_real ...``.

    Returns
    -------
    freqs : numpy.ndarray
        Hz.
    s11 : dict
        Complex reflection coefficient per name (``amb``, ``hot``, ``open``, ``short``,
        ``lna``, ...).
    """
    path = Path(path)
    with path.open() as handle:
        head = handle.readline().lstrip("#").replace(",", " ").split()
    a = np.loadtxt(path, comments="#")
    names = head[1:]
    if len(names) != a.shape[1] - 1 or len(names) % 2:
        raise ReceiverCalError(f"{path}: header {head} does not match {a.shape[1]} columns")
    out = {}
    for i in range(0, len(names), 2):
        key = names[i].rsplit("_", 1)[0]
        out[key] = a[:, 1 + i] + 1j * a[:, 2 + i]
    return a[:, 0] * 1e6, out


def read_s11_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read an EDGES-3 ``s11*.csv`` (``BEGIN``, rows ``MHz,re,im``, ``END``): Hz, complex."""
    rows = []
    with Path(path).open() as handle:
        for line in handle:
            parts = line.strip().split(",")
            if len(parts) == 3:
                rows.append([float(v) for v in parts])
    a = np.array(rows)
    return a[:, 0] * 1e6, a[:, 1] + 1j * a[:, 2]


def read_load_spectrum_txt(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read an averaged load spectrum ``sp*.txt``: Hz, ``T*`` (K, ``T_L = 300``), weight."""
    rows = []
    with Path(path).open() as handle:
        for line in handle:
            tokens = line.split()
            if len(tokens) >= 3:
                rows.append([float(t) for t in tokens[:3]])
    a = np.array(rows)
    return a[:, 0] * 1e6, a[:, 1], a[:, 2]


@dataclass(frozen=True)
class TemperatureSeries:
    """Temperatures in time: ``jds`` (UTC) and named series in kelvin."""

    jds: np.ndarray
    temperatures: dict[str, np.ndarray]
    source: str = ""

    def at(
        self, jds: np.ndarray | float, key: str, max_extrapolation_s: float = 120.0
    ) -> np.ndarray:
        """Interpolate a series to ``jds``; extrapolate linearly up to ``max_extrapolation_s``.

        Outside the logged span the line through the nearest 4 samples is used; farther
        than ``max_extrapolation_s`` the result is NaN.
        """
        x = np.atleast_1d(np.asarray(jds, np.float64))
        t, y = self.jds, self.temperatures[key]
        ok = np.isfinite(y)
        t, y = t[ok], y[ok]
        out = np.interp(x, t, y)
        lim = max_extrapolation_s / 86400.0
        for side, sel in (("lo", x < t[0]), ("hi", x > t[-1])):
            if not np.any(sel):
                continue
            idx = slice(0, 4) if side == "lo" else slice(-4, None)
            if t[idx].size >= 2:
                slope, icpt = np.polyfit(t[idx] - t[0], y[idx], 1)
                out[sel] = slope * (x[sel] - t[0]) + icpt
            edge = t[0] if side == "lo" else t[-1]
            out[sel & (np.abs(x - edge) > lim)] = np.nan
        return out


def _to_jd(times: Sequence[datetime]) -> np.ndarray:
    return np.asarray(Time(list(times), scale="utc").jd, dtype=np.float64)


def read_lab_thermistor(path: str | Path, utc_offset_hours: float = -7.0) -> TemperatureSeries:
    """Read a lab ``Resistance/*.csv`` thermistor log (EDGES lab at ASU).

    Columns: ``Date, Time, LNA Voltage, LNA Thermistor (Ohm), LNA (C), SP4T Voltage, SP4T
    Thermistor (Ohm), SP4T (C), Load Voltage, Load-thermistor (Ohm), Load (C),
    Room_Temp(C)``. Times are local (the file names and the ACQ UTC timestamps differ by
    7 h: Arizona, UTC-7, no daylight saving). The ``LNA (C)`` column reads ~205 C
    (a disconnected thermistor) and is not returned.

    Returns
    -------
    TemperatureSeries
        ``load``, ``sp4t`` (the switch) and ``room`` in kelvin.
    """
    jd, load, sp4t, room = [], [], [], []
    with Path(path).open(newline="") as handle:
        reader = csv.DictReader(handle)
        for row in reader:
            stamp = datetime.strptime(f"{row['Date']} {row['Time']}", "%m/%d/%Y %H:%M:%S")
            jd.append(stamp - timedelta(hours=utc_offset_hours))
            load.append(float(row["Load (C)"]) + 273.15)
            sp4t.append(float(row["SP4T (C)"]) + 273.15)
            room.append(float(row["Room_Temp(C)"]) + 273.15)
    if not jd:
        raise ReceiverCalError(f"{path} holds no thermistor rows")
    return TemperatureSeries(
        _to_jd(jd),
        {"load": np.array(load), "sp4t": np.array(sp4t), "room": np.array(room)},
        source=str(path),
    )


#: Channel codes of the EDGES-3 temperature logger (edges-io): degrees C.
EDGES3_LOG_CODES = {
    100: "front_end",
    101: "amb_load",
    102: "hot_load",
    103: "inner_box",
}


def read_edges3_temperature_log(path: str | Path) -> TemperatureSeries:
    """Read an EDGES-3 ``temperature.log``.

    Entries: ``YYYY_DDD_HH``, a UTC date line, ``code value`` lines; codes 100 front end,
    101 ambient load, 102 hot load, 103 inner box, in C (edges-io's mapping). Damaged
    entries are skipped.
    """
    jds, series = [], {name: [] for name in EDGES3_LOG_CODES.values()}
    header = re.compile(r"^\d{4}_\d{3}_\d{2}$")
    lines = Path(path).read_text(errors="replace").splitlines()
    i, skipped = 0, 0
    while i < len(lines):
        if not header.match(lines[i].strip()):
            i += 1
            continue
        j = i + 2
        values: dict[int, float] = {}
        while j < len(lines) and not header.match(lines[j].strip()):
            parts = lines[j].split()
            if len(parts) == 2:
                with contextlib.suppress(ValueError):
                    values[int(parts[0])] = float(parts[1])
            j += 1
        try:
            stamp = datetime.strptime(lines[i + 1].strip(), "%a %b %d %H:%M:%S UTC %Y")
        except (ValueError, IndexError):
            skipped += 1
            i = j
            continue
        jds.append(stamp)
        for code, name in EDGES3_LOG_CODES.items():
            series[name].append(values.get(code, np.nan) + 273.15)
        i = j
    if skipped:
        logger.info("%s: skipped %d damaged entries", path, skipped)
    return TemperatureSeries(
        _to_jd(jds), {k: np.array(v) for k, v in series.items()}, source=str(path)
    )
