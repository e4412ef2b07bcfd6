"""The in-memory auto-correlation observation that loaders produce and the fit consumes.

An :class:`Observation` holds the real auto-correlation spectra of several antennas and
polarisations over a set of integrations, with everything the fit needs to weight them
(channel widths, integration times, sample counts) and everything a product needs to
describe them (antenna names, JDs, site, source files). It checks itself on creation,
like pyuvdata's containers.

Axis order of the data arrays: ``(Nant, Npol, Ntime, Nfreq)``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from autocal.core.reprs import list_summary, span
from autocal.core.sites import Site
from autocal.errors import AutocalError

logger = logging.getLogger(__name__)

#: Polarisation names understood by the fit (linear feeds; ``ee`` = east-west dipole).
KNOWN_POLS = ("ee", "nn", "en", "ne", "xx", "yy", "xy", "yx")


def _all_finite(data: np.ndarray) -> bool:
    """Whether every value of ``data`` is finite, in one summing pass when it is.

    A NaN or an infinity makes the sum non-finite; a finite sum proves them absent. Only
    a sum that overflows or meets one falls back to the element-wise test.
    """
    with np.errstate(over="ignore", invalid="ignore"):
        if np.isfinite(np.sum(data)):
            return True
    return bool(np.isfinite(data).all())


class ObservationError(AutocalError):
    """An observation is inconsistent or a selection is invalid."""


def _as_1d(values: Any, what: str, size: int | None = None) -> np.ndarray:
    arr = np.atleast_1d(np.asarray(values, dtype=np.float64))
    if arr.ndim != 1:
        raise ObservationError(f"{what} must be one-dimensional, got shape {arr.shape}")
    if size is not None and arr.size == 1 and size != 1:
        arr = np.full(size, arr[0])
    if size is not None and arr.size != size:
        raise ObservationError(f"{what} has {arr.size} values, expected {size}")
    if not np.all(np.isfinite(arr)):
        raise ObservationError(f"{what} has non-finite values")
    return arr


@dataclass(frozen=True, eq=False)
class Observation:
    """Auto-correlation spectra of one observation.

    Parameters
    ----------
    data
        ``(Nant, Npol, Ntime, Nfreq)`` real auto-correlation power (raw correlator units).
        Non-finite samples are allowed only where flagged; :meth:`__post_init__` flags them.
    freqs
        ``(Nfreq,)`` channel centres in Hz, increasing.
    lsts
        ``(Ntime,)`` local apparent sidereal times in hours, in time order.
    jds
        ``(Ntime,)`` Julian dates (UTC) of the integration centres.
    antennas
        ``(Nant,)`` antenna numbers.
    pols
        Polarisation names, e.g. ``("ee", "nn")``.
    site
        Where the telescope is.
    flags
        Boolean flags like ``data`` (``True`` = bad); default none.
    channel_width
        ``(Nfreq,)`` or scalar channel width in Hz.
    integration_time
        ``(Ntime,)`` or scalar integration time in seconds.
    nsamples
        Like ``data``: effective number of samples relative to ``channel_width *
        integration_time`` (pyuvdata's ``nsample_array``); default ones.
    antenna_names
        Names of the antennas (default ``"ant<N>"``).
    telescope_name
        Telescope name.
    meta
        Provenance: source files and checksums, history, extra keywords.
    """

    data: np.ndarray
    freqs: np.ndarray
    lsts: np.ndarray
    jds: np.ndarray
    antennas: np.ndarray
    pols: tuple[str, ...]
    site: Site
    flags: np.ndarray | None = None
    channel_width: np.ndarray | float = 0.0
    integration_time: np.ndarray | float = 0.0
    nsamples: np.ndarray | None = None
    antenna_names: tuple[str, ...] = ()
    telescope_name: str = "unknown"
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        data = np.asarray(self.data)
        if np.iscomplexobj(data):
            if np.any(np.abs(data.imag) > 1e-6 * np.abs(data.real) + 1e-12):
                logger.warning("auto-correlations have imaginary parts; using the real part")
            data = data.real
        data = np.asarray(data, dtype=np.float64)
        if data.ndim != 4:
            raise ObservationError(
                f"data must have shape (Nant, Npol, Ntime, Nfreq), got {data.shape}"
            )
        nant, npol, ntime, nfreq = data.shape
        if min(data.shape) == 0:
            raise ObservationError(
                f"the observation is empty (shape {data.shape}): check the antenna, "
                "polarisation, frequency and LST selections"
            )
        freqs = _as_1d(self.freqs, "freqs", nfreq)
        if nfreq > 1 and np.any(np.diff(freqs) <= 0):
            raise ObservationError("frequencies must be strictly increasing")
        if np.any(freqs < 1e5):
            raise ObservationError("frequencies must be in Hz (got values below 100 kHz)")
        lsts = _as_1d(self.lsts, "lsts", ntime)
        if np.any((lsts < 0) | (lsts >= 24.0 + 1e-9)):
            raise ObservationError("LSTs must be in hours within [0, 24)")
        jds = _as_1d(self.jds, "jds", ntime)
        antennas = np.atleast_1d(np.asarray(self.antennas)).astype(np.int64)
        if antennas.shape != (nant,):
            raise ObservationError(f"{antennas.size} antenna numbers for {nant} antennas")
        if np.unique(antennas).size != nant:
            raise ObservationError("antenna numbers are not unique")
        pols = tuple(str(p).lower() for p in self.pols)
        if len(pols) != npol or len(set(pols)) != npol:
            raise ObservationError(f"need {npol} distinct polarisation names, got {pols}")
        flags = (
            np.zeros(data.shape, bool)
            if self.flags is None
            else np.broadcast_to(np.asarray(self.flags, dtype=bool), data.shape).copy()
        )
        if not _all_finite(data):
            bad = ~np.isfinite(data)
            if np.any(bad & ~flags):
                logger.info("flagging %d non-finite samples", int(np.sum(bad & ~flags)))
            flags |= bad
        width = _as_1d(self.channel_width, "channel_width", nfreq)
        tint = _as_1d(self.integration_time, "integration_time", ntime)
        nsamples = (
            np.ones(data.shape)
            if self.nsamples is None
            else np.broadcast_to(np.asarray(self.nsamples, np.float64), data.shape)
        )
        # min and max propagate NaN: one pass each, no temporaries (a block is 8 M samples);
        # one value broadcast (a reader's uniform nsamples) is checked once
        lone = nsamples.flat[:1] if nsamples.size and not any(nsamples.strides) else nsamples
        if lone.size and not (lone.min() >= 0 and lone.max() < np.inf):
            raise ObservationError("nsamples must be finite and >= 0")
        names = tuple(self.antenna_names) or tuple(f"ant{a}" for a in antennas)
        if len(names) != nant:
            raise ObservationError(f"{len(names)} antenna names for {nant} antennas")
        for key, value in (
            ("data", data),
            ("freqs", freqs),
            ("lsts", lsts),
            ("jds", jds),
            ("antennas", antennas),
            ("pols", pols),
            ("flags", flags),
            ("channel_width", width),
            ("integration_time", tint),
            ("nsamples", nsamples),
            ("antenna_names", names),
        ):
            object.__setattr__(self, key, value)

    def __repr__(self) -> str:
        """Return one line: telescope, antennas, pols, shape, ranges (never the arrays)."""
        nant = self.nant
        return (
            f"Observation({self.telescope_name} at {self.site.name}: "
            f"{nant} antenna{'s' * (nant != 1)} {list_summary(self.antennas)}, "
            f"pols {list_summary(self.pols)}, {self.ntime} times x {self.nfreq} channels; "
            f"{span(self.freqs, 1e6, 'MHz')}, LST {span(self.lsts, 1, 'h')}, "
            f"JD {span(self.jds, 1, '', 13)}; {100 * float(np.mean(self.flags)):.3g} % flagged)"
        )

    # shape helpers ---------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int, int, int]:
        """``(Nant, Npol, Ntime, Nfreq)``."""
        return self.data.shape  # type: ignore[return-value]

    @property
    def nant(self) -> int:
        """Number of antennas."""
        return self.data.shape[0]

    @property
    def ntime(self) -> int:
        """Number of integrations."""
        return self.data.shape[2]

    @property
    def nfreq(self) -> int:
        """Number of channels."""
        return self.data.shape[3]

    def bandwidth_time(self) -> np.ndarray:
        """Return ``dnu * dt * nsamples`` per sample (the radiometer equation's product)."""
        return self.channel_width[None, None, None, :] * (
            self.integration_time[None, None, :, None] * self.nsamples
        )

    # selection -------------------------------------------------------------------------
    def select(
        self,
        antennas: list[int] | None = None,
        pols: list[str] | None = None,
        freq_range: tuple[float, float] | None = None,
        lst_range: tuple[float, float] | None = None,
    ) -> Observation:
        """Return a sub-observation.

        Parameters
        ----------
        antennas
            Antenna numbers to keep.
        pols
            Polarisations to keep.
        freq_range
            ``(low, high)`` in Hz, inclusive.
        lst_range
            ``(start, stop)`` in hours, inclusive; ``start > stop`` wraps through 24 h.

        Raises
        ------
        ObservationError
            For unknown antennas or polarisations, or an empty selection.
        """
        ia = np.arange(self.nant)
        if antennas is not None:
            missing = sorted(set(int(a) for a in antennas) - set(self.antennas.tolist()))
            if missing:
                raise ObservationError(
                    f"antenna(s) {missing} not in this observation; it has {self.antennas.tolist()}"
                )
            ia = np.array([int(np.flatnonzero(self.antennas == int(a))[0]) for a in antennas])
        ip = np.arange(len(self.pols))
        if pols is not None:
            wanted = [p.lower() for p in pols]
            missing_p = [p for p in wanted if p not in self.pols]
            if missing_p:
                raise ObservationError(
                    f"polarisation(s) {missing_p} not in this observation; it has {self.pols}"
                )
            ip = np.array([self.pols.index(p) for p in wanted])
        jf = np.arange(self.nfreq)
        if freq_range is not None:
            lo, hi = sorted(freq_range)
            jf = np.flatnonzero((self.freqs >= lo) & (self.freqs <= hi))
        it = np.arange(self.ntime)
        if lst_range is not None:
            start, stop = lst_range
            if start <= stop:
                keep = (self.lsts >= start) & (self.lsts <= stop)
            else:
                keep = (self.lsts >= start) | (self.lsts <= stop)
            it = np.flatnonzero(keep)
        if jf.size == 0:
            raise ObservationError(
                f"no channels in {freq_range} Hz; the data cover "
                f"{self.freqs[0]:.6g}-{self.freqs[-1]:.6g} Hz"
            )
        if it.size == 0:
            raise ObservationError(
                f"no integrations in LST range {lst_range} h; the data cover "
                f"{self.lsts.min():.3f}-{self.lsts.max():.3f} h"
            )
        index = np.ix_(ia, ip, it, jf)
        return replace(
            self,
            data=self.data[index],
            flags=self.flags[index],
            nsamples=self.nsamples[index],
            freqs=self.freqs[jf],
            channel_width=self.channel_width[jf],
            lsts=self.lsts[it],
            jds=self.jds[it],
            integration_time=self.integration_time[it],
            antennas=self.antennas[ia],
            antenna_names=tuple(self.antenna_names[i] for i in ia),
            pols=tuple(self.pols[i] for i in ip),
        )

    def describe(self) -> dict[str, Any]:
        """Return a JSON-serialisable summary."""
        return {
            "telescope": self.telescope_name,
            "site": self.site.describe(),
            "antennas": self.antennas.tolist(),
            "pols": list(self.pols),
            "nfreq": self.nfreq,
            "freq_range_Hz": [float(self.freqs[0]), float(self.freqs[-1])],
            "ntime": self.ntime,
            "lst_range_h": [float(self.lsts[0]), float(self.lsts[-1])],
            "jd_range": [float(self.jds[0]), float(self.jds[-1])],
            "flagged_fraction": float(np.mean(self.flags)),
            **{k: v for k, v in self.meta.items() if k in {"files", "source"}},
        }
