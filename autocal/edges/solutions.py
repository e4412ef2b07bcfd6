"""Noise-wave receiver solutions: :class:`ReceiverSolution`, its file formats, named ones.

A solution tabulates, per frequency, the LNA reflection coefficient, the scale ``C1`` and
offset ``C2`` and the noise-wave temperatures ``T_unc, T_cos, T_sin`` (the equations
that use them are in :mod:`autocal.edges.noise_waves`). Readers: Alan Rogers' ``specal``
text files (:func:`read_specal`), edges-cal's ``reference.h5`` (:func:`read_reference_h5`);
named solutions of the data folder: :func:`load_receiver_solution`.

Conventions verified on the data folder:

- Bowman et al. 2018 ``specal_alan.txt`` (and EDGES-3 ``specal.txt``): ``T_L = 300 K``,
  ``T_NS = 1000 K``. Over 50-100 MHz ``C1 * 1000`` equals edges-cal's ``reference.h5``
  ``c1 * 350`` (its spectra record ``t_load_ns = 350``) to 0.33 %, constant in frequency;
  with these values the 2015 load spectra calibrate to their thermistor temperatures
  (:func:`autocal.edges.lab_checks.check_edges2_loads`).
- A 400 K nominal noise source (the edges-cal default) would scale these ``C1`` wrongly by
  2.5: the nominal values travel with each solution (``ReceiverSolution.t_load_ns``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from autocal.core.files import file_checksum
from autocal.errors import AutocalError
from autocal.io.datasets import data_file

#: Nominal internal-load temperature of the EDGES solutions (K).
T_LOAD_NOMINAL = 300.0
#: Nominal noise-source excess temperature of the Bowman/Rogers (Alan's) solutions (K).
T_NS_ALAN = 1000.0
#: ``t_load_ns`` recorded with the edges-cal ``reference.h5`` test spectra (K).
T_NS_EDGES_CAL_REFERENCE = 350.0

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


def resolve_solution(solution: ReceiverSolution | str) -> ReceiverSolution:
    """Return ``solution``, loading it first if it is a name (:func:`load_receiver_solution`)."""
    return load_receiver_solution(solution) if isinstance(solution, str) else solution
