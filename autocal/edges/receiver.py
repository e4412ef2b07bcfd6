"""EDGES receiver calibration: three-position switch and noise waves.

Formulas (Monsalve et al. 2017, ApJ 835, 49, "M17", Eqs. 3-7; Rogers & Bowman 2012;
Bowman et al. 2018; implemented as in ``edges-cal``'s ``receiver_calibration_func``):

Switch powers ``p0`` (antenna), ``p1`` (ambient load), ``p2`` (load + noise source)::

    Q  = (p0 - p1) / (p2 - p1)
    T* = T_NS Q + T_L                        (nominal T_NS, T_L of the solution)

Reflection factors (``Gr`` LNA reflection coefficient, ``Ga`` antenna or load)::

    F  = sqrt(1 - |Gr|^2) / (1 - Ga Gr),    alpha = arg(Ga F)
    K1 = (1 - |Ga|^2) |F|^2 / (1 - |Gr|^2)  ( = (1 - |Ga|^2) / |1 - Ga Gr|^2 )
    K2 = |Ga|^2 |F|^2 / (1 - |Gr|^2)
    K3 = |Ga| |F| cos(alpha) / (1 - |Gr|^2),   K4 = |Ga| |F| sin(alpha) / (1 - |Gr|^2)

Calibration equation (M17 Eq. 7)::

    C1 (T* - T_L) + T_L - C2 = K1 T_ant + K2 T_unc + K3 T_cos + K4 T_sin
    T_ant = [C1 (T* - T_L) + T_L - C2 - T_nw] / K1,   T_nw = K2 T_unc + K3 T_cos + K4 T_sin

With the *effective* noise-source excess ``T_NS' = C1 T_NS`` and load temperature
``T_L' = T_L - C2`` this is ``Q = (K1 T_ant + T_nw - T_L') / T_NS'``. Raw powers need
two numbers a calibration solution does not fix (they cancel in ``Q``): the system gain
``g`` (arbitrary raw scale) and a noise offset ``T_0`` added to all three positions::

    p1 = g (T_L' + T_0),  p2 = g (T_L' + T_NS' + T_0),  p0 = g (K1 T_ant + T_nw + T_0)

(:func:`decalibrate`; ``T_0`` from ``p2 / p1`` of the EDGES-3 lab files is 450-570 K over
50-190 MHz, default 500 K.) The auto-correlation model ``R = G T_ant + n`` implied by a
solution (:func:`expected_auto_model`)::

    R = Q :  G = K1 / T_NS',   n = (T_nw - T_L') / T_NS',   Trxr = (T_nw - T_L') / K1
    R = p0:  G = g K1,         n = g (T_nw + T_0),          Trxr = (T_nw + T_0) / K1

Both are exactly linear in ``T_ant`` for any antenna reflection that is constant in time:
``Ga`` only sets the coefficients (matched, ``Ga = 0``: ``G = 1 / (C1 T_NS)`` and
``Trxr = C2 - T_L`` for ``Q``, about -302 K for EDGES-2, negative because ``Q`` subtracts
the load). What is approximate in comparing with a sky fit is ``T_ant = Tsky``: real data
carry antenna, balun and ground losses (``T_ant = eta Tsky + (1 - eta) T_phys``), which
scale ``G`` by ``eta`` and move ``Trxr``.

Conventions verified on the data folder:

- Bowman et al. 2018 ``specal_alan.txt`` (and EDGES-3 ``specal.txt``): ``T_L = 300 K``,
  ``T_NS = 1000 K``. Over 50-100 MHz ``C1 * 1000`` equals edges-cal's ``reference.h5``
  ``c1 * 350`` (its spectra record ``t_load_ns = 350``) to 0.33 %, constant in frequency;
  with these values the 2015 load spectra calibrate to their thermistor temperatures
  (:func:`check_edges2_loads`).
- A 400 K nominal noise source (the edges-cal default) would scale these ``C1`` wrongly by
  2.5: the nominal values travel with each solution (``ReceiverSolution.t_load_ns``).

The module also reads the lab spectra and thermistor logs of the data folder and checks
the calibration against them (``lab_check_*``), and simulates an EDGES-like day through
a real receiver solution into raw ACQ files (:func:`simulate_edges_day`), which
:func:`fit_edges_day` calibrates back with the auto-correlation fit.
"""

from __future__ import annotations

import contextlib
import logging
import re
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any, Literal

import numpy as np

from autocal.core.coords import night_epoch
from autocal.core.files import file_checksum
from autocal.errors import AutocalError

logger = logging.getLogger(__name__)

#: Nominal internal-load temperature of the EDGES solutions (K).
T_LOAD_NOMINAL = 300.0
#: Nominal noise-source excess temperature of the Bowman/Rogers (Alan's) solutions (K).
T_NS_ALAN = 1000.0
#: ``t_load_ns`` recorded with the edges-cal ``reference.h5`` test spectra (K).
T_NS_EDGES_CAL_REFERENCE = 350.0
#: Default noise offset ``T_0`` added to all switch positions by :func:`decalibrate` (K).
T_OFFSET_DEFAULT = 500.0
#: Default raw power per kelvin (keeps simulated powers near real ACQ levels, ~1e-7).
RAW_SCALE_DEFAULT = 1e-11

#: Named receiver solutions in the data folder.
SOLUTIONS: dict[str, dict[str, Any]] = {
    "edges2-lowband-2015": {
        "path": "edges/receiver_cal/edges2_lowband_2015/specal_alan.txt",
        "kind": "specal",
        "t_load": T_LOAD_NOMINAL,
        "t_load_ns": T_NS_ALAN,
        "description": "EDGES-2 low-band receiver, Bowman et al. 2018 (40-110 MHz)",
    },
    "edges3-2022-316": {
        "path": "edges/receiver_cal/edges3_2022_316/specal.txt",
        "kind": "specal",
        "t_load": T_LOAD_NOMINAL,
        "t_load_ns": T_NS_ALAN,
        "description": "EDGES-3 receiver, lab calibration 2022 day 316 (50-190 MHz)",
    },
    "edges2-2015-09": {
        "path": "edges/receiver_cal/edges2_2015_09/reference.h5",
        "kind": "reference-h5",
        "t_load": T_LOAD_NOMINAL,
        "t_load_ns": T_NS_EDGES_CAL_REFERENCE,
        "description": "EDGES-2 receiver Sept 2015, edges-cal test reference (50-100 MHz)",
    },
}
_ALIASES = {"bowman2018": "edges2-lowband-2015", "edges2": "edges2-lowband-2015"}


class ReceiverCalError(AutocalError):
    """A receiver solution or calibration input is invalid."""


# ---------------------------------------------------------------------------------------
# receiver solutions
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class ReceiverSolution:
    """A noise-wave receiver calibration solution tabulated in frequency.

    Parameters
    ----------
    freqs
        ``(Nfreq,)`` Hz, increasing.
    gamma_rec
        ``(Nfreq,)`` complex LNA (receiver) reflection coefficient.
    c1, c2
        Scale and offset (``C1`` dimensionless, ``C2`` in K).
    t_unc, t_cos, t_sin
        Noise-wave parameters in K.
    t_load, t_load_ns
        Nominal load and noise-source temperatures the solution was derived with (K);
        ``T* = t_load_ns Q + t_load``.
    weights
        Optional per-channel weights of the solution file (``wtcal``).
    name
        Short name.
    meta
        Provenance (file, sha256, description).
    """

    freqs: np.ndarray
    gamma_rec: np.ndarray
    c1: np.ndarray
    c2: np.ndarray
    t_unc: np.ndarray
    t_cos: np.ndarray
    t_sin: np.ndarray
    t_load: float = T_LOAD_NOMINAL
    t_load_ns: float = T_NS_ALAN
    weights: np.ndarray | None = None
    name: str = "receiver"
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        freqs = np.atleast_1d(np.asarray(self.freqs, dtype=np.float64))
        n = freqs.size
        if n > 1 and np.any(np.diff(freqs) <= 0):
            raise ReceiverCalError("solution frequencies must be strictly increasing")
        object.__setattr__(self, "freqs", freqs)
        gamma = np.broadcast_to(np.asarray(self.gamma_rec, np.complex128), (n,)).copy()
        object.__setattr__(self, "gamma_rec", gamma)
        for name in ("c1", "c2", "t_unc", "t_cos", "t_sin"):
            arr = np.broadcast_to(np.asarray(getattr(self, name), np.float64), (n,)).copy()
            if not np.all(np.isfinite(arr)):
                raise ReceiverCalError(f"solution {name} has non-finite values")
            object.__setattr__(self, name, arr)
        if np.any(np.abs(gamma) >= 1):
            raise ReceiverCalError("|Gamma_rec| must be below 1")
        if self.weights is not None:
            object.__setattr__(
                self, "weights", np.broadcast_to(np.asarray(self.weights, np.float64), (n,)).copy()
            )
        if not (self.t_load_ns > 0 and np.isfinite(self.t_load)):
            raise ReceiverCalError("nominal t_load_ns must be positive and t_load finite")

    @property
    def t_ns_eff(self) -> np.ndarray:
        """Effective noise-source excess temperature ``T_NS' = C1 T_NS`` (K)."""
        return self.c1 * self.t_load_ns

    @property
    def t_load_eff(self) -> np.ndarray:
        """Effective internal-load temperature ``T_L' = T_L - C2`` (K)."""
        return self.t_load - self.c2

    def at(self, freqs: np.ndarray) -> ReceiverSolution:
        """Return the solution linearly interpolated to ``freqs`` (Hz).

        Raises
        ------
        ReceiverCalError
            If ``freqs`` reach outside the solution's range (by more than half a step).
        """
        freqs = np.atleast_1d(np.asarray(freqs, dtype=np.float64))
        step = np.median(np.diff(self.freqs)) if self.freqs.size > 1 else 0.0
        lo, hi = self.freqs[0] - step / 2, self.freqs[-1] + step / 2
        if freqs.min() < lo or freqs.max() > hi:
            raise ReceiverCalError(
                f"the {self.name} solution covers {self.freqs[0] / 1e6:.3f}-"
                f"{self.freqs[-1] / 1e6:.3f} MHz; {freqs.min() / 1e6:.3f}-"
                f"{freqs.max() / 1e6:.3f} MHz was asked for: choose frequencies inside it"
            )

        def lin(y: np.ndarray) -> np.ndarray:
            return np.interp(freqs, self.freqs, y)

        return replace(
            self,
            freqs=freqs,
            gamma_rec=lin(self.gamma_rec.real) + 1j * lin(self.gamma_rec.imag),
            c1=lin(self.c1),
            c2=lin(self.c2),
            t_unc=lin(self.t_unc),
            t_cos=lin(self.t_cos),
            t_sin=lin(self.t_sin),
            weights=None if self.weights is None else lin(self.weights),
        )

    def describe(self) -> dict[str, Any]:
        """JSON-serialisable summary."""
        return {
            "name": self.name,
            "freq_range_Hz": [float(self.freqs[0]), float(self.freqs[-1])],
            "nfreq": int(self.freqs.size),
            "t_load_K": float(self.t_load),
            "t_load_ns_K": float(self.t_load_ns),
            **{k: v for k, v in self.meta.items() if k in {"path", "sha256", "description"}},
        }


def _specal_value(tokens: list[str], key: str, count: int = 1) -> list[float]:
    i = tokens.index(key)
    return [float(v) for v in tokens[i + 1 : i + 1 + count]]


def read_specal(
    path: str | Path,
    *,
    t_load: float = T_LOAD_NOMINAL,
    t_load_ns: float = T_NS_ALAN,
    name: str | None = None,
) -> ReceiverSolution:
    """Read a ``specal`` receiver solution (Alan Rogers' text format).

    One line per channel: ``freq <MHz> s11lna <re> <im> sca <C1> ofs <C2> tlnau <Tunc>
    tlnac <Tcos> tlnas <Tsin> wtcal <w> cal_data``; values are found by keyword.

    Parameters
    ----------
    path
        The file.
    t_load, t_load_ns
        Nominal temperatures the solution was derived with (300 K and 1000 K for the
        Bowman et al. 2018 and EDGES-3 files, see the module doc).
    name
        Solution name (default the file stem).

    Returns
    -------
    ReceiverSolution
        The solution.

    Raises
    ------
    ReceiverCalError
        If a line lacks a keyword or a value, naming the line.
    """
    path = Path(path)
    rows = []
    with path.open() as handle:
        for number, line in enumerate(handle, 1):
            tokens = line.split()
            if not tokens or tokens[0].startswith("#"):
                continue
            try:
                row = (
                    _specal_value(tokens, "freq")
                    + _specal_value(tokens, "s11lna", 2)
                    + _specal_value(tokens, "sca")
                    + _specal_value(tokens, "ofs")
                    + _specal_value(tokens, "tlnau")
                    + _specal_value(tokens, "tlnac")
                    + _specal_value(tokens, "tlnas")
                    + (_specal_value(tokens, "wtcal") if "wtcal" in tokens else [1.0])
                )
            except (ValueError, IndexError) as exc:
                raise ReceiverCalError(
                    f"{path}, line {number}: not a specal line (need freq, s11lna re im, sca, "
                    f"ofs, tlnau, tlnac, tlnas): {line.strip()[:80]!r}"
                ) from exc
            if len(row) != 9:
                raise ReceiverCalError(f"{path}, line {number}: missing values")
            rows.append(row)
    if not rows:
        raise ReceiverCalError(f"{path} holds no specal lines")
    a = np.array(rows)
    return ReceiverSolution(
        freqs=a[:, 0] * 1e6,
        gamma_rec=a[:, 1] + 1j * a[:, 2],
        c1=a[:, 3],
        c2=a[:, 4],
        t_unc=a[:, 5],
        t_cos=a[:, 6],
        t_sin=a[:, 7],
        weights=a[:, 8],
        t_load=t_load,
        t_load_ns=t_load_ns,
        name=name or path.stem,
        meta={"path": str(path.resolve()), "sha256": file_checksum(path), "format": "specal"},
    )


def read_reference_h5(
    path: str | Path,
    *,
    t_load: float = T_LOAD_NOMINAL,
    t_load_ns: float = T_NS_EDGES_CAL_REFERENCE,
    name: str | None = None,
) -> ReceiverSolution:
    """Read an edges-cal ``reference.h5`` receiver solution.

    Datasets ``freq`` (MHz), ``c1``, ``c2``, ``tunc``, ``tcos``, ``tsin`` and
    ``receiver_modeled`` (LNA S11); its test spectra record ``t_load_ns = 350``.
    """
    import h5py

    path = Path(path)
    try:
        with h5py.File(path, "r") as h5:
            d = {k: h5[k][()] for k in ("freq", "c1", "c2", "tunc", "tcos", "tsin")}
            d["gamma"] = h5["receiver_modeled"][()]
    except (OSError, KeyError) as exc:
        raise ReceiverCalError(f"{path} is not an edges-cal reference.h5 solution: {exc}") from exc
    return ReceiverSolution(
        freqs=np.asarray(d["freq"]) * 1e6,
        gamma_rec=d["gamma"],
        c1=d["c1"],
        c2=d["c2"],
        t_unc=d["tunc"],
        t_cos=d["tcos"],
        t_sin=d["tsin"],
        t_load=t_load,
        t_load_ns=t_load_ns,
        name=name or path.parent.name,
        meta={"path": str(path.resolve()), "sha256": file_checksum(path), "format": "reference-h5"},
    )


def load_receiver_solution(name: str = "edges2-lowband-2015") -> ReceiverSolution:
    """Load a named solution from the data folder (see :data:`SOLUTIONS`).

    Names: ``edges2-lowband-2015`` (alias ``bowman2018``), ``edges3-2022-316``,
    ``edges2-2015-09``.
    """
    from autocal.io.datasets import data_file

    key = _ALIASES.get(name.lower(), name.lower())
    if key not in SOLUTIONS:
        raise ReceiverCalError(
            f"unknown receiver solution {name!r}: use one of {sorted(SOLUTIONS)}"
        )
    info = SOLUTIONS[key]
    path = data_file(info["path"], purpose=f"receiver solution {key}")
    reader = read_specal if info["kind"] == "specal" else read_reference_h5
    sol = reader(path, t_load=info["t_load"], t_load_ns=info["t_load_ns"], name=key)
    return replace(sol, meta={**sol.meta, "description": info["description"]})


def _solution(solution: ReceiverSolution | str) -> ReceiverSolution:
    return load_receiver_solution(solution) if isinstance(solution, str) else solution


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


# ---------------------------------------------------------------------------------------
# the calibration equations
# ---------------------------------------------------------------------------------------
def k_factors(
    gamma_rec: np.ndarray, gamma_ant: np.ndarray | complex
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Return ``K1, K2, K3, K4`` of M17 Eq. 7 (factors of ``T_ant, T_unc, T_cos, T_sin``)."""
    gr = np.asarray(gamma_rec, np.complex128)
    ga = np.asarray(gamma_ant, np.complex128)
    gain = 1.0 - np.abs(gr) ** 2
    f = np.sqrt(gain) / (1.0 - ga * gr)
    alpha = np.angle(ga * f)
    fg = np.abs(ga) * np.abs(f) / gain
    k2 = fg**2 * gain
    k1 = np.abs(f) ** 2 / gain - k2
    return k1, k2, fg * np.cos(alpha), fg * np.sin(alpha)


def noise_wave_temperature(solution: ReceiverSolution, gamma_ant: Any = 0.0) -> np.ndarray:
    """``T_nw = K2 T_unc + K3 T_cos + K4 T_sin`` (K) for an antenna reflection."""
    _, k2, k3, k4 = k_factors(solution.gamma_rec, _gamma_at(gamma_ant, solution.freqs))
    return k2 * solution.t_unc + k3 * solution.t_cos + k4 * solution.t_sin


def tstar_from_q(q: np.ndarray, t_load_ns: float, t_load: float) -> np.ndarray:
    """Uncalibrated temperature ``T* = T_NS Q + T_L``."""
    return t_load_ns * np.asarray(q) + t_load


def calibrate_tstar(
    tstar: np.ndarray, solution: ReceiverSolution | str, gamma_ant: Any = 0.0
) -> np.ndarray:
    """Calibrated antenna temperature from ``T*`` (M17 Eq. 7), K.

    Parameters
    ----------
    tstar
        ``(..., Nfreq)`` uncalibrated temperature at the solution's frequencies.
    solution
        Receiver solution (tabulated at the same frequencies; use ``solution.at``).
    gamma_ant
        Antenna (or load) reflection coefficient: scalar, ``(Nfreq,)`` or ``(freqs_hz,
        gamma)`` to interpolate.
    """
    sol = _solution(solution)
    k1, _, _, _ = k_factors(sol.gamma_rec, _gamma_at(gamma_ant, sol.freqs))
    t_nw = noise_wave_temperature(sol, gamma_ant)
    lhs = sol.c1 * (np.asarray(tstar) - sol.t_load) + sol.t_load - sol.c2
    return (lhs - t_nw) / k1


def calibrate_q(
    q: np.ndarray, solution: ReceiverSolution | str, gamma_ant: Any = 0.0
) -> np.ndarray:
    """Calibrated antenna temperature (K) from ``Q`` with the solution's nominal ``T_NS, T_L``."""
    sol = _solution(solution)
    return calibrate_tstar(tstar_from_q(q, sol.t_load_ns, sol.t_load), sol, gamma_ant)


def calibrate_powers(
    p0: np.ndarray,
    p1: np.ndarray,
    p2: np.ndarray,
    solution: ReceiverSolution | str,
    gamma_ant: Any = 0.0,
) -> np.ndarray:
    """Calibrated antenna temperature (K) from the three switch powers."""
    p0, p1, p2 = (np.asarray(x, np.float64) for x in (p0, p1, p2))
    with np.errstate(divide="ignore", invalid="ignore"):
        q = (p0 - p1) / (p2 - p1)
    return calibrate_q(q, solution, gamma_ant)


def decalibrate_q(
    t_ant: np.ndarray, solution: ReceiverSolution | str, gamma_ant: Any = 0.0
) -> np.ndarray:
    """``Q`` a receiver with this solution measures for antenna temperature ``t_ant`` (K)."""
    sol = _solution(solution)
    k1, _, _, _ = k_factors(sol.gamma_rec, _gamma_at(gamma_ant, sol.freqs))
    t_nw = noise_wave_temperature(sol, gamma_ant)
    return (k1 * np.asarray(t_ant) + t_nw - sol.t_load_eff) / sol.t_ns_eff


def decalibrate(
    t_ant: np.ndarray,
    solution: ReceiverSolution | str,
    gamma_ant: Any = 0.0,
    *,
    raw_scale: float | np.ndarray = RAW_SCALE_DEFAULT,
    t_offset: float | np.ndarray = T_OFFSET_DEFAULT,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw switch powers for antenna temperature ``t_ant`` (inverse of :func:`calibrate_powers`).

    ``p1 = g (T_L' + T_0)``, ``p2 = g (T_L' + T_NS' + T_0)``, ``p0 = g (K1 T_ant + T_nw +
    T_0)`` with ``T_NS' = C1 T_NS``, ``T_L' = T_L - C2`` of the solution's nominal
    ``T_NS, T_L``.

    Parameters
    ----------
    t_ant
        ``(..., Nfreq)`` antenna temperature in K at the solution's frequencies.
    solution
        Receiver solution (tabulated at the same frequencies).
    gamma_ant
        Antenna reflection coefficient (see :func:`calibrate_tstar`).
    raw_scale
        System gain ``g``: raw power per kelvin (scalar or ``(Nfreq,)`` bandpass).
    t_offset
        Noise offset ``T_0`` (K) common to the three positions; it cancels in ``Q``.

    Returns
    -------
    p0, p1, p2 : numpy.ndarray
        Broadcast to the shape of ``t_ant``.
    """
    sol = _solution(solution)
    t_ant = np.asarray(t_ant, np.float64)
    k1, _, _, _ = k_factors(sol.gamma_rec, _gamma_at(gamma_ant, sol.freqs))
    t_nw = noise_wave_temperature(sol, gamma_ant)
    g = np.asarray(raw_scale, np.float64)
    t0 = np.asarray(t_offset, np.float64)
    p0 = g * (k1 * t_ant + t_nw + t0)
    p1 = np.broadcast_to(g * (sol.t_load_eff + t0), t_ant.shape).copy()
    p2 = np.broadcast_to(g * (sol.t_load_eff + sol.t_ns_eff + t0), t_ant.shape).copy()
    if np.any(p1 <= 0) or np.any(p2 <= p1):
        raise ReceiverCalError("raw_scale and t_offset must make p1 > 0 and p2 > p1")
    return p0, p1, p2


@dataclass(frozen=True)
class AutoModelExpectation:
    """The ``R = G T_ant + n`` coefficients implied by a receiver solution.

    Attributes
    ----------
    r
        ``"q"`` or ``"p0"``.
    freqs
        Hz.
    G, n, trxr
        Gain (R per K), offset (R units) and ``Trxr = n / G`` (K).
    k1, t_nw
        The reflection factor of ``T_ant`` and the noise-wave temperature (K).
    note
        The approximations behind a comparison with a sky fit.
    """

    r: str
    freqs: np.ndarray
    G: np.ndarray
    n: np.ndarray
    trxr: np.ndarray
    k1: np.ndarray
    t_nw: np.ndarray
    note: str = ""


def expected_auto_model(
    solution: ReceiverSolution | str,
    gamma_ant: Any = 0.0,
    r: Literal["q", "p0"] = "q",
    *,
    raw_scale: float | np.ndarray = RAW_SCALE_DEFAULT,
    t_offset: float | np.ndarray = T_OFFSET_DEFAULT,
) -> AutoModelExpectation:
    """Return the ``G`` and ``Trxr`` of ``R = G T_ant + n`` a receiver solution implies.

    ``Q``: ``G = K1 / (C1 T_NS)``, ``Trxr = (T_nw - T_L + C2) / K1``. ``p0``: ``G = g K1``,
    ``Trxr = (T_nw + T_0) / K1`` (needs the raw scale ``g`` and offset ``T_0`` the powers
    were generated with; they are not part of a calibration solution). Exact for any
    time-constant antenna reflection; the sky fit sees ``T_ant = Tsky`` only when the
    antenna is lossless.
    """
    sol = _solution(solution)
    if r not in ("q", "p0"):
        raise ReceiverCalError(f"unknown auto-correlation kind {r!r}: use 'q' or 'p0'")
    k1, _, _, _ = k_factors(sol.gamma_rec, _gamma_at(gamma_ant, sol.freqs))
    t_nw = noise_wave_temperature(sol, gamma_ant)
    if r == "q":
        gain = k1 / sol.t_ns_eff
        offset = (t_nw - sol.t_load_eff) / sol.t_ns_eff
    else:
        g = np.asarray(raw_scale, np.float64)
        gain = np.broadcast_to(g * k1, sol.freqs.shape).copy()
        offset = np.broadcast_to(g * (t_nw + np.asarray(t_offset, np.float64)), sol.freqs.shape)
    note = (
        "exactly linear in T_ant for a time-constant antenna reflection; compared with a sky "
        "fit, T_ant = Tsky assumes a lossless antenna (losses eta scale G by eta and add "
        "(1 - eta) T_phys / eta to Trxr)"
    )
    return AutoModelExpectation(
        r, sol.freqs, gain, np.asarray(offset), offset / gain, k1, t_nw, note
    )


def _gamma_at(gamma_ant: Any, freqs: np.ndarray) -> np.ndarray:
    """Resolve an antenna reflection (scalar, per-channel array, or ``(freqs, gamma)``)."""
    if isinstance(gamma_ant, tuple) and len(gamma_ant) == 2:
        fg, gg = (np.asarray(x) for x in gamma_ant)
        if freqs.min() < fg.min() - 1.0 or freqs.max() > fg.max() + 1.0:
            raise ReceiverCalError(
                f"the antenna S11 covers {fg.min() / 1e6:.3f}-{fg.max() / 1e6:.3f} MHz, not "
                f"{freqs.min() / 1e6:.3f}-{freqs.max() / 1e6:.3f} MHz"
            )
        gg = np.asarray(gg, np.complex128)
        return np.interp(freqs, fg, gg.real) + 1j * np.interp(freqs, fg, gg.imag)
    arr = np.asarray(gamma_ant, np.complex128)
    if arr.ndim == 0:
        return np.full(freqs.shape, complex(arr))
    if arr.shape[-1] != freqs.size:
        raise ReceiverCalError(f"gamma_ant has {arr.shape[-1]} channels for {freqs.size}")
    if np.any(np.abs(arr) > 1):
        raise ReceiverCalError("|gamma_ant| must not exceed 1")
    return arr


# ---------------------------------------------------------------------------------------
# lab housekeeping: thermistors and temperature logs
# ---------------------------------------------------------------------------------------
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
    from astropy.time import Time

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
    import csv

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


def two_load_solution(
    q_amb: np.ndarray, q_hot: np.ndarray, t_amb: float, t_hot: float
) -> tuple[np.ndarray, np.ndarray]:
    """Effective ``T_NS'`` and ``T_L'`` from an ambient and a hot load (matched loads).

    With ``|Ga| ~ 0`` the calibration is ``T = T_NS' Q + T_L'``, so two loads of known
    temperature fix it: ``T_NS' = (t_hot - t_amb) / (q_hot - q_amb)``, ``T_L' = t_amb -
    T_NS' q_amb``. Neglects ``|Ga|^2`` and the noise waves (``|Ga| T_cos``-sized terms).
    """
    q_amb, q_hot = np.asarray(q_amb, np.float64), np.asarray(q_hot, np.float64)
    t_ns = (t_hot - t_amb) / (q_hot - q_amb)
    return t_ns, t_amb - t_ns * q_amb


# ---------------------------------------------------------------------------------------
# checks against the lab data in the data folder
# ---------------------------------------------------------------------------------------
def _band_stats(values: np.ndarray) -> dict[str, float]:
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
    import h5py

    from autocal.io.datasets import data_file

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
    from autocal.io.datasets import data_dir, data_file
    from autocal.io.edges import read_acq_spectra

    sol = _solution(solution)
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
    from autocal.io.datasets import data_dir
    from autocal.io.edges import read_acq_spectra

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


# ---------------------------------------------------------------------------------------
# an EDGES-like day
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class EdgesDay:
    """A simulated EDGES-like day written as raw files.

    Attributes
    ----------
    paths
        The written files (time order).
    freqs
        ``(Nfreq,)`` Hz: the binned channels :func:`autocal.io.edges.read_edges` returns
        for ``freq_range`` and ``bin_factor``.
    jds, lsts
        ``(Ntime,)`` UTC Julian dates (whole seconds) and LSTs (hours) of the cycles.
    t_ant
        ``(Ntime, Nfreq)`` true antenna temperature (= the beam-weighted sky, K).
    solution
        The receiver solution at ``freqs``.
    gamma_ant
        ``(Nfreq,)`` antenna reflection coefficient used.
    expected
        ``{"q": ..., "p0": ...}`` :class:`AutoModelExpectation`.
    config
        Everything needed to recompute the sky model and to read the files.
    """

    paths: list[Path]
    freqs: np.ndarray
    jds: np.ndarray
    lsts: np.ndarray
    t_ant: np.ndarray
    solution: ReceiverSolution
    gamma_ant: np.ndarray
    expected: dict[str, AutoModelExpectation]
    config: dict[str, Any]


def simulate_edges_day(
    out_dir: str | Path,
    *,
    solution: ReceiverSolution | str = "edges2-lowband-2015",
    freq_range: tuple[float, float] = (50e6, 100e6),
    bin_factor: int = 64,
    n_times: int = 72,
    jd_start: float = 2458000.5,
    sky: str = "powerlaw:gsm2008@408:-2.55",
    beam: str = "edges-low",
    tgnd: float = 300.0,
    nside: int = 64,
    gamma_ant: Any = 0.0,
    raw_scale: float | np.ndarray = RAW_SCALE_DEFAULT,
    t_offset: float | np.ndarray = T_OFFSET_DEFAULT,
    integration_time: float = 6.71,
    noise: bool = True,
    seed: int | None = 0,
    n_files: int = 4,
    file_format: Literal["acq", "hdf5"] = "acq",
) -> EdgesDay:
    """Simulate one sidereal day of raw EDGES spectra through a receiver solution.

    The antenna temperature is the beam-weighted sky (:func:`autocal.tsky.engine.compute_tsky`
    with ``sky``, ``beam``, the EDGES site, ``tgnd``; CMB included once) at the binned
    channel centres, sampled ``n_times`` times over one sidereal day. It passes through
    the receiver (:func:`decalibrate`) into ``p0, p1, p2``, constant within each bin of
    ``bin_factor`` native channels (so that binning on reading is exact), with radiometer
    noise ``p / sqrt(dnu dt)`` per native channel (``dnu`` = 6.1 kHz, ``dt`` =
    ``integration_time``), and is written as ``n_files`` native-grid files (ACQ by
    default, else autocal HDF5).

    Returns
    -------
    EdgesDay
        Files, truth and the expected ``G``, ``Trxr`` for ``R = Q`` and ``R = p0``.
    """
    from autocal.core.sites import EDGES
    from autocal.io.edges import (
        MIN_OBS_FREQ_HZ,
        NATIVE_DF_HZ,
        EdgesSpectra,
        acq_time_to_jd,
        channel_bins,
        jd_to_acq_time,
        lsts_for_jds,
        native_freqs,
        write_acq,
        write_edges_hdf5,
    )
    from autocal.simulate.mock import SIDEREAL_DAY
    from autocal.tsky.engine import compute_tsky

    if n_times < 3:
        raise ReceiverCalError("simulate at least 3 cycles")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    native = native_freqs()
    index, freqs = channel_bins(native, freq_range, bin_factor, min_freq=MIN_OBS_FREQ_HZ)
    sol = _solution(solution).at(freqs)
    gamma = _gamma_at(gamma_ant, freqs)
    jds = jd_start + np.arange(n_times) * SIDEREAL_DAY / n_times
    jds = acq_time_to_jd(jd_to_acq_time(jds))  # whole seconds, as an ACQ file stores them
    lsts = lsts_for_jds(jds, EDGES)
    t_ant = compute_tsky(
        sky,
        beam,
        EDGES,
        freqs,
        lsts,
        tgnd=tgnd,
        nside=nside,
        epoch=night_epoch(jds, EDGES.lon_deg),
    ).tsky
    powers = decalibrate(t_ant, sol, gamma, raw_scale=raw_scale, t_offset=t_offset)
    rng = np.random.default_rng(seed)
    sigma_rel = 1.0 / np.sqrt(NATIVE_DF_HZ * integration_time)
    fine = []
    for p in powers:
        full = np.repeat(p, bin_factor, axis=1)
        if noise:
            full = full * (1.0 + sigma_rel * rng.standard_normal(full.shape))
        fine.append(full)
    chans = index.ravel()
    paths = []
    for k, part in enumerate(np.array_split(np.arange(n_times), max(1, min(n_files, n_times)))):
        spec = EdgesSpectra(
            p0=fine[0][part],
            p1=fine[1][part],
            p2=fine[2][part],
            freqs=native[chans],
            jds=jds[part],
            channel_width=NATIVE_DF_HZ,
            integration_time=integration_time,
            meta={"history": "simulated by autocal.edges.receiver.simulate_edges_day"},
        )
        stamp = jd_to_acq_time(jds[part][:1])[0].replace(":", "_")
        if file_format == "acq":
            paths.append(
                write_acq(
                    out / f"edges_sim_{k:02d}_{stamp}.acq",
                    spec,
                    header={"site": "edges-sim", "instrument": "autocal-sim"},
                )
            )
        elif file_format == "hdf5":
            paths.append(write_edges_hdf5(out / f"edges_sim_{k:02d}_{stamp}.h5", spec))
        else:
            raise ReceiverCalError(f"unknown file_format {file_format!r}: use 'acq' or 'hdf5'")
    expected = {
        r: expected_auto_model(sol, gamma, r, raw_scale=raw_scale, t_offset=t_offset)
        for r in ("q", "p0")
    }
    config = {
        "solution": sol.describe(),
        "freq_range_Hz": list(freq_range),
        "bin_factor": int(bin_factor),
        "n_times": int(n_times),
        "sky": sky,
        "beam": beam,
        "tgnd_K": float(tgnd),
        "nside": int(nside),
        "raw_scale": raw_scale,
        "t_offset_K": t_offset,
        "integration_time_s": float(integration_time),
        "noise": bool(noise),
        "seed": seed,
        "file_format": file_format,
    }
    logger.info("simulated an EDGES-like day: %d cycles in %d file(s)", n_times, len(paths))
    return EdgesDay(paths, freqs, jds, lsts, t_ant, sol, gamma, expected, config)


@dataclass(frozen=True, eq=False)
class EdgesDayFit:
    """The auto-correlation fit of an EDGES-like day against the receiver's expectation.

    Attributes
    ----------
    solution
        The fit (:class:`autocal.fit.lsq.Solution`).
    expected
        What the receiver solution implies.
    pull_gain, pull_trxr
        ``(fit - expected) / sigma`` per channel.
    rel_err_gain
        ``fit / expected - 1`` per channel.
    err_trxr
        ``fit - expected`` per channel (K).
    """

    solution: Any
    expected: AutoModelExpectation
    pull_gain: np.ndarray
    pull_trxr: np.ndarray
    rel_err_gain: np.ndarray
    err_trxr: np.ndarray

    def summary(self) -> dict[str, float]:
        """Medians and spreads of the comparison."""
        return {
            "median_rel_err_gain": float(np.median(self.rel_err_gain)),
            "rms_rel_err_gain": float(np.sqrt(np.mean(self.rel_err_gain**2))),
            "median_err_trxr_K": float(np.median(self.err_trxr)),
            "rms_err_trxr_K": float(np.sqrt(np.mean(self.err_trxr**2))),
            "median_sigma_trxr_K": float(np.median(self.solution.sigma_Trxr[0, 0])),
            "mean_pull_gain": float(np.mean(self.pull_gain)),
            "std_pull_gain": float(np.std(self.pull_gain)),
            "mean_pull_trxr": float(np.mean(self.pull_trxr)),
            "std_pull_trxr": float(np.std(self.pull_trxr)),
            "max_abs_pull": float(
                max(np.max(np.abs(self.pull_gain)), np.max(np.abs(self.pull_trxr)))
            ),
            "median_reduced_chi2": float(np.median(self.solution.reduced_chi2)),
        }


def fit_edges_day(
    day: EdgesDay,
    r: Literal["q", "p0"] = "q",
    weights: Literal["variance", "identity"] = "variance",
) -> EdgesDayFit:
    """Calibrate a simulated day from its raw files with the auto-correlation fit.

    Reads the files (:func:`autocal.io.edges.read_edges_spectra` with the day's band and
    binning), builds the ``R`` observation, computes ``Tsky`` with the same sky, beam and
    ground, fits ``R = G Tsky + n`` (constant model; inverse-variance weights from the
    propagated radiometer noise, or identity) and compares with the expectation.
    """
    from autocal.fit.lsq import fit
    from autocal.io.edges import MIN_OBS_FREQ_HZ, read_edges_spectra
    from autocal.tsky.engine import compute_tsky

    cfg = day.config
    spec = read_edges_spectra(
        day.paths, freq_range=tuple(cfg["freq_range_Hz"]), bin_factor=cfg["bin_factor"]
    )
    obs = spec.to_observation(r)
    if obs.freqs.shape != day.freqs.shape or not np.allclose(obs.freqs, day.freqs, atol=1e-3):
        raise ReceiverCalError("the files' channels differ from the simulated ones")
    tsky = compute_tsky(
        cfg["sky"],
        cfg["beam"],
        obs.site,
        obs.freqs,
        obs.lsts,
        tgnd=cfg["tgnd_K"],
        nside=cfg["nside"],
        epoch=night_epoch(obs.jds, obs.site.lon_deg),
    ).tsky
    w: Any = "identity"
    if weights == "variance":
        keep = spec.freqs >= MIN_OBS_FREQ_HZ
        w = (1.0 / spec.variance(r)[:, keep])[None, None]
    sol = fit(  # pulls of the propagated noise: the covariance as it is, not inflated
        obs,
        tsky,
        model="constant",
        weights=w,
        inflate_errors=False,
        config={"edges_day": cfg, "r": r},
    )
    exp = day.expected[r]
    g, sg = sol.G[0, 0], sol.sigma_G[0, 0]
    t, st = sol.Trxr[0, 0], sol.sigma_Trxr[0, 0]
    return EdgesDayFit(
        solution=sol,
        expected=exp,
        pull_gain=(g - exp.G) / sg,
        pull_trxr=(t - exp.trxr) / st,
        rel_err_gain=g / exp.G - 1.0,
        err_trxr=t - exp.trxr,
    )
