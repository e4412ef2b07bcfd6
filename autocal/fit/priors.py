"""Receiver-temperature priors from a number, a CSV table or a previous solution.

The ``--trxr-prior`` option accepts one of

* a number: ``Trxr`` in kelvin at every frequency, its 1-sigma given separately;
* a ``.csv`` table with the header ``freq_mhz,trxr_k`` or ``freq_mhz,trxr_k,sigma_k``
  (blank lines and ``#`` comment lines are skipped, whitespace around values is ignored),
  one row per frequency in MHz, frequencies strictly increasing, at least two rows;
* a previous autocal ``solution.h5`` (:func:`autocal.io.products.write_solution`): its
  ``derived/Trxr`` and ``derived/sigma_Trxr`` per antenna and polarisation; flagged or
  non-finite channels are dropped per antenna-pol.

:func:`parse_trxr_prior` reads any of them into a :class:`TrxrPrior`, whose
:meth:`TrxrPrior.at` gives the prior mean and 1-sigma on the data's channels (linear
interpolation in frequency). Every problem raises :class:`PriorError` saying what is wrong
and what to do.
"""

from __future__ import annotations

import hashlib
import logging
import math
import numbers
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from autocal.core.reprs import compact_repr
from autocal.errors import AutocalError
from autocal.fit.solve import solve_sums
from autocal.fit.sums import NormalSums
from autocal.io.products import FORMAT

logger = logging.getLogger(__name__)

#: Largest CSV table read (bytes).
MAX_TABLE_BYTES = 10_000_000
#: How far (Hz) data channels may lie outside a table prior's band (rounding of MHz values).
BAND_SLACK_HZ = 1e3
_HEADERS = (("freq_mhz", "trxr_k"), ("freq_mhz", "trxr_k", "sigma_k"))
_EXPECTED = "'freq_mhz,trxr_k' or 'freq_mhz,trxr_k,sigma_k'"


class PriorError(AutocalError):
    """A receiver-temperature prior is malformed, unreadable or does not fit the data."""


@dataclass(frozen=True, eq=False)
class TrxrPrior:
    """A receiver-temperature prior (kelvin) with its 1-sigma.

    Parameters
    ----------
    source
        Description for provenance, e.g. ``"constant 150 K +- 20 K"`` or
        ``"table prior.csv (sha256 ...)"``.
    freqs_hz
        ``None`` for a constant prior (it applies at every frequency); else ``(N,)``
        strictly increasing frequencies in Hz, ``N >= 2``.
    trxr_k, sigma_k
        Prior mean and 1-sigma: 0-d arrays for a constant prior, ``(N,)`` for a table,
        ``(Nant, Npol, N)`` for a solution prior (NaN where the channel is unusable).
    antennas, pols
        The antennas and polarisations of a solution prior's rows; ``None`` otherwise.
    sha256
        Checksum of the file read, ``None`` for a constant prior.
    """

    source: str
    freqs_hz: np.ndarray | None
    trxr_k: np.ndarray
    sigma_k: np.ndarray
    antennas: tuple[int, ...] | None = None
    pols: tuple[str, ...] | None = None
    sha256: str | None = None

    def __repr__(self) -> str:
        """Return one line; arrays as type and shape (:func:`~autocal.core.reprs.compact_repr`)."""
        return compact_repr(self)

    def __post_init__(self) -> None:
        trxr = np.array(self.trxr_k, dtype=float)
        sigma = np.array(self.sigma_k, dtype=float)
        freqs = None if self.freqs_hz is None else np.array(self.freqs_hz, dtype=float)
        if freqs is None:
            shape: tuple[int, ...] = ()
        elif self.antennas is None:
            shape = freqs.shape
        else:
            shape = (len(self.antennas), len(self.pols or ()), freqs.size)
        if trxr.shape != shape or sigma.shape != shape:
            raise PriorError(
                f"trxr prior {self.source}: trxr_k {trxr.shape} and sigma_k {sigma.shape} "
                f"must have shape {shape}"
            )
        if freqs is not None and (freqs.ndim != 1 or freqs.size < 2 or np.any(np.diff(freqs) <= 0)):
            raise PriorError(
                f"trxr prior {self.source}: freqs_hz must be at least two increasing values"
            )
        finite = np.isfinite(trxr) & np.isfinite(sigma)
        if (self.antennas is None and not finite.all()) or np.any(sigma[finite] <= 0):
            raise PriorError(
                f"trxr prior {self.source}: trxr_k and sigma_k must be finite, sigma_k > 0"
            )
        for arr in (trxr, sigma) if freqs is None else (trxr, sigma, freqs):
            arr.flags.writeable = False
        object.__setattr__(self, "trxr_k", trxr)
        object.__setattr__(self, "sigma_k", sigma)
        object.__setattr__(self, "freqs_hz", freqs)

    @property
    def kind(self) -> str:
        """``"constant"``, ``"table"`` or ``"solution"``."""
        if self.freqs_hz is None:
            return "constant"
        return "table" if self.antennas is None else "solution"

    @property
    def _label(self) -> str:
        """The source without its checksum, for messages."""
        return self.source.partition(" (sha256")[0]

    def _check_band(self, freqs: np.ndarray) -> None:
        fp = self.freqs_hz
        assert fp is not None
        if self.kind == "solution":  # the same channel grid: half a channel of slack
            lo, hi = fp[0] - (fp[1] - fp[0]) / 2, fp[-1] + (fp[-1] - fp[-2]) / 2
        else:  # a table must cover the data (1 kHz for rounding of MHz values)
            lo, hi = fp[0] - BAND_SLACK_HZ, fp[-1] + BAND_SLACK_HZ
        if freqs.min() < lo or freqs.max() > hi:
            what = "table" if self.kind == "table" else "solution"
            raise PriorError(
                f"trxr prior {self._label}: covers {fp[0] / 1e6:.3f}-{fp[-1] / 1e6:.3f} MHz but "
                f"the data span {freqs.min() / 1e6:.3f}-{freqs.max() / 1e6:.3f} MHz: give a "
                f"{what} that covers the data band, or select channels inside it"
            )

    def _rows(self, antennas: Any, pols: Any) -> tuple[list[int], list[int]]:
        assert self.antennas is not None and self.pols is not None
        ia = list(range(len(self.antennas)))
        ip = list(range(len(self.pols)))
        if antennas is not None:
            index = {a: i for i, a in enumerate(self.antennas)}
            missing = [int(a) for a in antennas if int(a) not in index]
            if missing:
                raise PriorError(
                    f"trxr prior {self._label}: antenna(s) {_join(missing)} not in the file, "
                    f"which has antennas {_join(self.antennas)}: give a solution of these "
                    "antennas or a constant/table prior"
                )
            ia = [index[int(a)] for a in antennas]
        if pols is not None:
            pindex = {p.lower(): i for i, p in enumerate(self.pols)}
            pindex.update(
                {str(p).lower(): pindex[alias] for p in pols if (alias := _alias(p, pindex))}
            )
            missing_p = [str(p) for p in pols if str(p).lower() not in pindex]
            if missing_p:
                raise PriorError(
                    f"trxr prior {self._label}: polarisation(s) {_join(missing_p)} not in the "
                    f"file, which has {_join(self.pols)}: give a solution of these polarisations "
                    "or a constant/table prior"
                )
            ip = [pindex[str(p).lower()] for p in pols]
        return ia, ip

    def at(
        self,
        freqs_hz: np.ndarray,
        antennas: Any = None,
        pols: Any = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Return the prior mean and 1-sigma on the data's channels.

        Parameters
        ----------
        freqs_hz
            ``(Nfreq,)`` data frequencies in Hz.
        antennas
            Antenna numbers of the data. A solution prior selects these rows (all of its
            antennas if ``None``); other priors repeat for each (one row if ``None``).
        pols
            Polarisation names of the data (case-insensitive), used like ``antennas``.

        Returns
        -------
        trxr, sigma : numpy.ndarray
            ``(Nant, Npol, Nfreq)`` in kelvin. Tables and solution rows are interpolated
            linearly in frequency (``numpy.interp``); a solution row skips its unusable
            channels and holds its outermost usable value beyond them.

        Raises
        ------
        PriorError
            If the data reach beyond a table's band (more than :data:`BAND_SLACK_HZ`) or
            more than half a channel beyond a solution prior's band, an
            antenna or polarisation is not in a solution prior, or a selected solution row
            has no usable channel.
        """
        freqs = np.asarray(freqs_hz, dtype=float)
        if freqs.ndim != 1 or freqs.size == 0 or not np.all(np.isfinite(freqs)):
            raise PriorError(
                f"trxr prior {self._label}: the data frequencies must be a non-empty 1-d "
                "array of finite values in Hz"
            )
        if self.kind != "solution":
            nant = 1 if antennas is None else len(antennas)
            npol = 1 if pols is None else len(pols)
            if self.kind == "constant":
                mean = np.full(freqs.size, float(self.trxr_k))
                sig = np.full(freqs.size, float(self.sigma_k))
            else:
                self._check_band(freqs)
                mean = np.interp(freqs, self.freqs_hz, self.trxr_k)
                sig = np.interp(freqs, self.freqs_hz, self.sigma_k)
            shape = (nant, npol, freqs.size)
            return np.broadcast_to(mean, shape).copy(), np.broadcast_to(sig, shape).copy()
        self._check_band(freqs)
        ia, ip = self._rows(antennas, pols)
        assert self.antennas is not None and self.pols is not None
        mean = np.empty((len(ia), len(ip), freqs.size))
        sig = np.empty_like(mean)
        for i, a in enumerate(ia):
            for j, p in enumerate(ip):
                t, s = self.trxr_k[a, p], self.sigma_k[a, p]
                ok = np.isfinite(t) & np.isfinite(s)
                if not ok.any():
                    raise PriorError(
                        f"trxr prior {self._label}: antenna {self.antennas[a]} pol "
                        f"{self.pols[p]} has no solved channel in the file: leave the antenna "
                        "out or use a constant/table prior"
                    )
                mean[i, j] = np.interp(freqs, self.freqs_hz[ok], t[ok])
                sig[i, j] = np.interp(freqs, self.freqs_hz[ok], s[ok])
        return mean, sig

    def describe(self) -> dict[str, Any]:
        """Return a JSON-serialisable summary for provenance.

        Returns
        -------
        dict
            ``kind``, ``source``, ``sha256``, ``band_mhz`` (``[lo, hi]`` or ``None`` for
            a constant), ``nfreq``, ``trxr_median_k``, ``sigma_median_k`` (over usable
            channels), and for a solution prior ``antennas`` and ``pols``.
        """
        fp = self.freqs_hz
        ok = np.isfinite(self.trxr_k) & np.isfinite(self.sigma_k)
        out: dict[str, Any] = {
            "kind": self.kind,
            "source": self.source,
            "sha256": self.sha256,
            "band_mhz": None if fp is None else [float(fp[0] / 1e6), float(fp[-1] / 1e6)],
            "nfreq": None if fp is None else int(fp.size),
            "trxr_median_k": float(np.median(self.trxr_k[ok])),
            "sigma_median_k": float(np.median(self.sigma_k[ok])),
        }
        if self.kind == "solution":
            out["antennas"] = list(self.antennas or ())
            out["pols"] = list(self.pols or ())
        return out


def _join(values: Any) -> str:
    return ", ".join(str(v) for v in values)


def _as_number(spec: Any) -> float | None:
    """Return ``spec`` as a float if it is a number or a string holding one."""
    if isinstance(spec, bool):
        return None
    if isinstance(spec, numbers.Real):
        return float(spec)
    if isinstance(spec, str):
        try:
            return float(spec.strip())
        except ValueError:
            return None
    return None


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def parse_trxr_prior(
    spec: str | float | int | Path, *, sigma_k: float, base_dir: Path | None = None
) -> TrxrPrior:
    """Read a receiver-temperature prior from a number, a CSV table or a solution file.

    Parameters
    ----------
    spec
        A number (or a string that parses as one): constant ``Trxr`` in K. Otherwise a
        path: ``.csv`` is a table, ``.h5``/``.hdf5`` a previous autocal solution.
    sigma_k
        1-sigma in K of a constant prior and of a table without ``sigma_k``; must be > 0.
    base_dir
        Directory that relative paths are taken from (default: the working directory).

    Returns
    -------
    TrxrPrior
        The prior.

    Raises
    ------
    PriorError
        If the number or file is invalid, missing, unreadable or of an unknown kind.
    """
    if not (isinstance(sigma_k, numbers.Real) and math.isfinite(sigma_k) and sigma_k > 0):
        raise PriorError(f"trxr prior sigma {sigma_k!r} K: give a finite 1-sigma > 0 K")
    value = None if isinstance(spec, Path) else _as_number(spec)
    if value is not None:
        if not math.isfinite(value):
            raise PriorError(f"trxr prior {spec!r}: give a finite temperature in K")
        prior = TrxrPrior(f"constant {value:g} K +- {float(sigma_k):g} K", None, value, sigma_k)
    else:
        label = str(spec).strip()
        if not label:
            raise PriorError("trxr prior is empty: give a number in K or a .csv/.h5 path")
        path = Path(label).expanduser()
        if not path.is_absolute() and base_dir is not None:
            path = Path(base_dir) / path
        suffix = path.suffix.lower()
        if suffix not in (".csv", ".h5", ".hdf5"):
            raise PriorError(
                f"trxr prior {label}: neither a number nor a .csv, .h5 or .hdf5 file: give "
                "Trxr in K, a table freq_mhz,trxr_k[,sigma_k] (.csv) or a solution.h5"
            )
        if not path.is_file():
            state = "is a directory" if path.is_dir() else "does not exist"
            raise PriorError(f"trxr prior {label}: {path} {state}: check the path")
        try:
            sha = _sha256(path)
        except OSError as err:
            raise PriorError(f"trxr prior {label}: cannot read {path} ({err})") from err
        if suffix == ".csv":
            if path.stat().st_size > MAX_TABLE_BYTES:
                raise PriorError(
                    f"trxr prior {label}: {path.stat().st_size} bytes; a table is at most "
                    f"{MAX_TABLE_BYTES // 1_000_000} MB: give one row per frequency channel"
                )
            prior = _read_table(path, label, sha, float(sigma_k))
        else:
            prior = _read_solution(path, label, sha)
    logger.info("trxr prior: %s", prior.source)
    return prior


def _read_table(path: Path, label: str, sha: str, sigma_default: float) -> TrxrPrior:
    """Read a ``freq_mhz,trxr_k[,sigma_k]`` table."""

    def fail(lineno: int, text: str) -> PriorError:
        return PriorError(f"trxr prior {label}: line {lineno}: {text}")

    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as err:
        raise PriorError(f"trxr prior {label}: cannot read it as UTF-8 text ({err})") from err
    header: tuple[str, ...] | None = None
    rows: list[tuple[float, float, float]] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        fields = [f.strip() for f in stripped.split(",")]
        if header is None:
            if tuple(fields) not in _HEADERS:
                raise fail(lineno, f"header {stripped!r} is not {_EXPECTED}: write one of these")
            header = tuple(fields)
            continue
        if len(fields) != len(header):
            raise fail(lineno, f"{len(fields)} values, expected {len(header)} ({','.join(header)})")
        values = []
        for name, field in zip(header, fields, strict=True):
            try:
                number = float(field)
            except ValueError:
                raise fail(lineno, f"{name} {field!r} is not a number") from None
            if not math.isfinite(number):
                raise fail(lineno, f"{name} is {field!r}: give finite numbers")
            values.append(number)
        freq, trxr = values[0], values[1]
        sigma = values[2] if len(values) == 3 else sigma_default
        if freq > 1e5:
            raise fail(lineno, f"frequency {freq:g} looks like Hz: give freq_mhz in MHz")
        if freq <= 0:
            raise fail(lineno, f"frequency {freq:g} MHz is not positive")
        if rows and freq <= rows[-1][0]:
            raise fail(
                lineno,
                f"frequency {freq} MHz does not increase (previous {rows[-1][0]}): sort the "
                "rows and give each frequency once",
            )
        if sigma <= 0:
            raise fail(lineno, f"sigma_k {sigma:g} is not positive: give a 1-sigma > 0 K")
        rows.append((freq, trxr, sigma))
    if header is None:
        raise PriorError(
            f"trxr prior {label}: the file is empty: give a header {_EXPECTED} and one row "
            "per frequency"
        )
    if len(rows) < 2:
        raise PriorError(
            f"trxr prior {label}: {len(rows)} data row(s), need at least two: give the prior "
            "at two or more frequencies, or one number for a constant prior"
        )
    table = np.array(rows)
    with_sigma = "" if len(header) == 3 else f", sigma {sigma_default:g} K"
    return TrxrPrior(
        f"table {label} (sha256 {sha}{with_sigma})",
        table[:, 0] * 1e6,
        table[:, 1],
        table[:, 2],
        sha256=sha,
    )


def _read_solution(path: Path, label: str, sha: str) -> TrxrPrior:
    """Read ``derived/Trxr`` and ``derived/sigma_Trxr`` of an autocal solution product."""
    if not h5py.is_hdf5(path):
        raise PriorError(
            f"trxr prior {label}: not an HDF5 file (truncated or corrupt?): give a "
            "solution.h5 written by autocal calibrate"
        )
    try:
        with h5py.File(path, "r") as h5:
            fmt = h5.attrs.get("format")
            if fmt != FORMAT:
                raise PriorError(
                    f"trxr prior {label}: format {fmt!r}, not an autocal solution "
                    f"({FORMAT!r}): give a solution.h5 written by autocal calibrate"
                )
            freqs = np.asarray(h5["freqs"][()], dtype=float)
            antennas = tuple(int(a) for a in h5["antennas"][()])
            pols = tuple(p.decode() if isinstance(p, bytes) else str(p) for p in h5["pols"][()])
            trxr = np.asarray(h5["derived/Trxr"][()], dtype=float)
            sigma = np.asarray(h5["derived/sigma_Trxr"][()], dtype=float)
            flags = h5["derived/flags"][()] if "derived/flags" in h5 else None
    except PriorError:
        raise
    except (OSError, KeyError, ValueError, TypeError) as err:
        raise PriorError(
            f"trxr prior {label}: truncated, corrupt or incomplete solution file "
            f"({type(err).__name__}: {err}): give an intact solution.h5"
        ) from err
    shape = (len(antennas), len(pols), freqs.size)
    if trxr.shape != shape or sigma.shape != shape or (flags is not None and flags.shape != shape):
        raise PriorError(
            f"trxr prior {label}: derived/Trxr {trxr.shape} does not match (antennas, pols, "
            f"freqs) {shape}: give an intact solution.h5"
        )
    if freqs.size < 2:
        raise PriorError(f"trxr prior {label}: {freqs.size} channel(s), need at least two")
    order = np.argsort(freqs)
    freqs, trxr, sigma = freqs[order], trxr[..., order], sigma[..., order]
    if not np.all(np.isfinite(freqs)) or np.any(np.diff(freqs) <= 0):
        raise PriorError(f"trxr prior {label}: its frequencies are not finite and distinct")
    bad = ~(np.isfinite(trxr) & np.isfinite(sigma) & (sigma > 0))
    if flags is not None:
        bad |= np.asarray(flags, dtype=bool)[..., order]
    if bad.all():
        raise PriorError(
            f"trxr prior {label}: no solved channel in the file: give a solution that solved "
            "some channels, or a constant/table prior"
        )
    trxr, sigma = np.where(bad, np.nan, trxr), np.where(bad, np.nan, sigma)
    logger.debug("trxr prior %s: %d of %d channels unusable", label, bad.sum(), bad.size)
    return TrxrPrior(
        f"solution {label} (sha256 {sha})", freqs, trxr, sigma, antennas, pols, sha256=sha
    )


def add_trxr_prior(
    sums: NormalSums,
    vg: np.ndarray,
    vn: np.ndarray,
    trxr: np.ndarray,
    sigma: np.ndarray,
    scale_covariance: bool | str = False,
) -> NormalSums:
    """Add a receiver prior to normal sums as one pseudo-observation per channel.

    The prior says ``n = G Trxr_p +- G sigma_p`` for the time-averaged ``G = vg . x`` and
    ``n = vn . x``: a row ``a = vn - Trxr_p vg`` with datum 0 and weight
    ``1 / (G_ref sigma_p)^2``. ``G_ref`` is the gain fitted with ``n(t) = G(t) Trxr_p``
    held (well determined even when ``G`` and ``n`` separate weakly, where the free fit's
    ``G`` may be far off or negative). The solution's covariance then includes the
    prior's uncertainty.

    Parameters
    ----------
    sums
        :class:`autocal.fit.sums.NormalSums` (gain coefficients first, then as many offset
        coefficients).
    vg, vn
        ``(nparam,)`` vectors giving the time-averaged ``G`` and ``n`` from the parameters.
    trxr, sigma
        Prior mean and 1-sigma in K, broadcastable to ``(Nant, Npol, Nfreq)``; channels
        where either is not finite get no prior.
    scale_covariance
        The scaling :func:`autocal.fit.solve.solve_sums` will apply to the covariance
        (``True``: ``chi^2/dof``, ``"inflate"``: ``max(1, chi^2/dof)``). The prior's weight
        is multiplied by the same factor of the prior-free fit, so that the scaling
        widens the data's information only and the prior keeps its stated sigma:
        ``phi (A^T W A + phi w_p a a^T)^-1 = (A^T W A / phi + w_p a a^T)^-1``.

    Returns
    -------
    autocal.fit.sums.NormalSums
        New sums with the prior added (``sums`` is not changed).
    """
    lead = sums.count.shape
    t = np.broadcast_to(np.asarray(trxr, dtype=float), lead)
    s = np.broadcast_to(np.asarray(sigma, dtype=float), lead)
    use = np.isfinite(t) & np.isfinite(s) & (s > 0)
    t = np.where(use, t, 0.0)
    nb = len(vg) // 2
    g, n = slice(0, nb), slice(nb, 2 * nb)
    # the gain with n(t) = G(t) Trxr_p held (reduced normal equations of the gain block)
    red = (
        sums.ata[..., g, g]
        + t[..., None, None] * (sums.ata[..., g, n] + sums.ata[..., n, g])
        + (t * t)[..., None, None] * sums.ata[..., n, n]
    )
    rhs = sums.aty[..., g] + t[..., None] * sums.aty[..., n]
    with np.errstate(all="ignore"):
        ok = use & (np.linalg.det(red) > 0)
        coef = np.linalg.solve(np.where(ok[..., None, None], red, np.eye(nb)), rhs[..., None])
        g_ref = np.abs(coef[..., 0] @ vg[g])
        wp = np.where(ok & (g_ref > 0), 1.0 / (g_ref * np.where(use, s, 1.0)) ** 2, 0.0)
    if scale_covariance:
        free = solve_sums(sums, positive_gain=False)
        with np.errstate(all="ignore"):
            phi = np.where(free["dof"] > 0, free["chi2"] / free["dof"], np.nan)
        if scale_covariance == "inflate":
            phi = np.maximum(phi, 1.0)
        wp = wp * np.where(np.isfinite(phi) & (phi > 0), phi, 1.0)
    row = vn[None, None, None, :] - t[..., None] * vg[None, None, None, :]  # (A, P, F, M)
    return NormalSums(
        sums.model,
        sums.ata + wp[..., None, None] * row[..., :, None] * row[..., None, :],
        sums.aty.copy(),
        sums.yty.copy(),
        sums.count.copy(),
        sums.nflagged.copy(),
        sums.lst_min,
        sums.lst_max,
        {**sums.info, "trxr_prior": True},
    )


@dataclass(frozen=True, eq=False)
class PriorTerm:
    """A receiver prior ready to add to normal sums: ``term(sums, vg, vn) -> sums``.

    The function :func:`~autocal.fit.total_uncertainty.total_uncertainty` and the solve
    apply to every set of sums (:func:`add_trxr_prior` with these values).

    Attributes
    ----------
    trxr, sigma
        Prior mean and 1-sigma in K, broadcastable to ``(Nant, Npol, Nfreq)``.
    scale_covariance
        The covariance scaling of the solve (see :func:`add_trxr_prior`).
    """

    trxr: np.ndarray
    sigma: np.ndarray
    scale_covariance: bool | str = False

    def __repr__(self) -> str:
        """Return one line; arrays as type and shape (:func:`~autocal.core.reprs.compact_repr`)."""
        return compact_repr(self)

    def __call__(self, sums: NormalSums, vg: np.ndarray, vn: np.ndarray) -> NormalSums:
        """Return ``sums`` with the prior added (:func:`add_trxr_prior`)."""
        return add_trxr_prior(
            sums, vg, vn, self.trxr, self.sigma, scale_covariance=self.scale_covariance
        )

    def antennas(self, lo: int, hi: int) -> PriorTerm:
        """Return the prior of antennas ``lo`` to ``hi - 1`` (a value shared by all is kept)."""

        def part(value: np.ndarray) -> np.ndarray:
            value = np.asarray(value, dtype=float)
            return value[lo:hi] if value.ndim == 3 and value.shape[0] != 1 else value

        return PriorTerm(part(self.trxr), part(self.sigma), self.scale_covariance)


def prior_value(text: str) -> float | str:
    """Return a ``--trxr-prior`` value: a number in K as a float, else the path as given."""
    try:
        return float(text)
    except ValueError:
        return text


def _alias(pol: Any, names: Mapping[str, int]) -> str | None:
    """Return the name among ``names`` of the same feeds as ``pol``, when ``pol`` is not one.

    A solution calibrated with ``pols=["xx"]`` of an ``ee``/``nn`` file names its pol
    ``xx`` (earlier versions did; the data name it ``ee``). The feeds are matched as
    HERA's files orient them, x east (``xx`` is ``ee``, ``yy`` is ``nn``), and only so: a
    north-oriented file's old solution is refused ("not in the file") rather than matched
    to the other feed. ``None`` when no name matches or ``pol`` is there already.
    """
    from autocal.io.polarisations import name_to_code

    name = str(pol).lower()
    if name in names:
        return None
    try:
        code = name_to_code(name, "east")
    except KeyError:
        return None
    for other in names:
        try:
            if name_to_code(other, "east") == code:
                return other
        except KeyError:
            continue
    return None
