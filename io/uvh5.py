"""Auto-correlations in UVH5 files, read and written through pyuvdata.

:func:`read_uvh5` loads only the auto-correlations ``(a, a)`` of one UVH5 file, or of
several consecutive files forming one observation, into an
:class:`autocal.core.observation.Observation`. :func:`write_uvh5` writes an observation's
autos as a genuine UVH5 file (HERA telescope metadata when the telescope is HERA) that
pyuvdata, hera_cal and friends can read.

Conventions
-----------
* Polarisations are named ``ee``/``nn`` (``ee`` = east-west dipole) when the file's
  ``x_orientation`` is known: pyuvdata codes -5/-6 with ``x_orientation="east"``.
  Files with no orientation keep ``xx``/``yy``.
* LSTs are local apparent sidereal times in hours; JDs are UTC Julian dates.
* The data are written as complex128 with zero imaginary part, phase centre "zenith"
  (unprojected, i.e. drift scan), ``vis_units="uncalib"``.

Files named ``*.uvh5_downselected`` (hera_cal test data) are read too: the file type
is always given to pyuvdata explicitly. Reading a file block by block in bounded memory
(what the calibration pipeline does) is :mod:`autocal.io.uvh5_blocks`.
"""

from __future__ import annotations

import itertools
import logging
import os
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any

import numpy as np

from autocal.core.files import atomic_path, file_checksum
from autocal.core.observation import Observation, ObservationError
from autocal.core.sites import Site
from autocal.errors import AutocalError
from autocal.io.pyuvdata_helpers import uvdata_class, warnings_to_log
from autocal.io.pyuvdata_helpers import x_orientation as feed_orientation

if TYPE_CHECKING:
    from autocal.io.uvh5_blocks import ReadStats

logger = logging.getLogger(__name__)

#: pyuvdata polarisation codes of the feed-power (same-feed) polarisations, read by
#: default: xx/ee, yy/nn (linear), rr, ll (circular).
POWER_POL_CODES = (-5, -6, -1, -2)

#: LST agreement required between an observation and pyuvdata's LSTs, in hours (1 s).
LST_TOLERANCE_HOURS = 1.0 / 3600.0

#: Phase centre written to files: zenith drift scan (pyuvdata 3 "unprojected").
ZENITH: dict[str, Any] = {
    "cat_name": "zenith",
    "cat_type": "unprojected",
    "cat_lon": 0.0,
    "cat_lat": np.pi / 2,
    "cat_frame": "altaz",
    "info_source": "user",
}

#: Keys of ``Observation.meta`` that are not copied one-to-one into ``extra_keywords``.
_RESERVED_META = ("files", "sha256", "history", "extra_keywords")


class UVH5FormatError(AutocalError):
    """A file is missing, not UVH5, corrupt, lacks autos, or disagrees with its siblings."""


# ---------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------
def _warnings_to_log(context: str) -> Any:
    return warnings_to_log(context, logger, logging.INFO)


def _lst_hours(lst_rad: np.ndarray) -> np.ndarray:
    return np.mod(np.asarray(lst_rad, dtype=np.float64) * 12.0 / np.pi, 24.0)


def _wrap_hours(diff: np.ndarray) -> np.ndarray:
    """Wrap LST differences (hours) into [-12, 12)."""
    return np.mod(np.asarray(diff) + 12.0, 24.0) - 12.0


def _scalar(value: Any) -> Any:
    """Return ``value`` as a plain scalar/string for extra_keywords, or None if it is not one."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, bytes):
        return value.decode("utf-8", errors="replace")
    if isinstance(value, (bool, int, float, complex, str)):
        return value
    return None


def _pol_names(codes: Sequence[int], x_orientation: str | None) -> list[str]:
    """Pyuvdata pol codes -> names: ee/nn when the orientation is known, else xx/yy."""
    from pyuvdata import utils as uvutils

    orient = x_orientation if x_orientation in ("east", "north") else None
    names = uvutils.polnum2str(list(int(c) for c in codes), x_orientation=orient)
    return [str(n).lower() for n in np.atleast_1d(names)]


def _describe_freqs(freqs: np.ndarray) -> str:
    if freqs.size == 0:
        return "no channels"
    return f"{freqs.size} channels {freqs.min() / 1e6:.6g}-{freqs.max() / 1e6:.6g} MHz"


# ---------------------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------------------
def _hera_telescope(antennas: np.ndarray, site: Site) -> Any:
    from pyuvdata import Telescope

    telescope = Telescope.from_known_telescopes("HERA")
    if not telescope.instrument:
        telescope.instrument = telescope.name
    known = set(int(a) for a in telescope.antenna_numbers)
    missing = sorted(set(np.asarray(antennas).tolist()) - known)
    if missing:
        raise ObservationError(
            f"antenna number(s) {missing} do not exist in HERA (known antennas are "
            f"{min(known)}-{max(known)})"
        )
    # The file takes pyuvdata's HERA location; warn if the observation says otherwise.
    known_xyz = np.array([q.to_value("m") for q in telescope.location.geocentric], float)
    site_xyz = np.array([q.to_value("m") for q in site.location.geocentric], float)
    offset = float(np.linalg.norm(known_xyz - site_xyz))
    if offset > 1000.0:
        logger.warning(
            "observation site %s is %.0f m from pyuvdata's HERA location; the file uses "
            "HERA's location",
            site.describe(),
            offset,
        )
    return telescope


def _generic_telescope(
    name: str, site: Site, antennas: np.ndarray, antenna_names: Sequence[str]
) -> Any:
    from pyuvdata import Telescope

    with _warnings_to_log("building the telescope"):
        return Telescope.new(
            name=name,
            location=site.location,
            antenna_positions=np.zeros((len(antennas), 3)),
            antenna_names=list(antenna_names),
            antenna_numbers=np.asarray(antennas).tolist(),
            instrument=name,
            mount_type="fixed",
            update_from_known=False,
        )


def _pol_codes_for_write(pols: Sequence[str]) -> tuple[list[int], str | None]:
    from pyuvdata import utils as uvutils

    compass = [p for p in pols if set(p) <= {"e", "n"}]
    if compass and len(compass) != len(pols):
        raise ObservationError(
            f"cannot mix e/n and x/y polarisation names in one file: {list(pols)}"
        )
    x_orientation = "east" if compass else None
    try:
        codes = uvutils.polstr2num(list(pols), x_orientation=x_orientation)
    except (KeyError, ValueError) as err:
        raise ObservationError(f"polarisations {list(pols)} have no UVH5 code: {err}") from err
    return [int(c) for c in np.atleast_1d(codes)], x_orientation


def _extra_keywords(meta: dict[str, Any], extra: dict | None) -> dict[str, Any]:
    keywords: dict[str, Any] = {}
    inherited = meta.get("extra_keywords")
    candidates: list[tuple[str, Any]] = []
    if isinstance(inherited, dict):
        candidates += list(inherited.items())
    candidates += [(k, v) for k, v in meta.items() if k not in _RESERVED_META]
    candidates += list((extra or {}).items())
    for key, value in candidates:
        scalar = _scalar(value)
        if scalar is None:
            logger.debug("extra keyword %r skipped: %s is not a scalar or string", key, type(value))
            continue
        keywords[str(key)] = scalar
    return keywords


def _history(meta: dict[str, Any], history: str, writer: str = "write_uvh5") -> str:
    from autocal import __version__

    parts = []
    upstream = meta.get("history")
    if isinstance(upstream, str) and upstream.strip():
        parts.append(upstream.rstrip())
    files = meta.get("files")
    if files:
        parts.append("autocal: derived from " + ", ".join(str(f) for f in np.atleast_1d(files)))
    if history:
        parts.append(history.rstrip())
    parts.append(f"autocal {__version__}: auto-correlations written by autocal.io.uvh5.{writer}")
    return "\n".join(parts) + "\n"


def _build_uvdata(
    name: str,
    *,
    freqs: np.ndarray,
    pols: Sequence[str],
    jds: np.ndarray,
    lsts: np.ndarray,
    antennas: np.ndarray,
    antenna_names: Sequence[str],
    site: Site,
    telescope_name: str,
    integration_time: np.ndarray,
    channel_width: np.ndarray,
    history: str,
    extra_keywords: dict[str, Any],
    arrays: dict[str, np.ndarray] | None = None,
) -> Any:
    """Build the UVData of an autos-only file (metadata only when ``arrays`` is None).

    The baseline-time axis is time-major (antennas fastest). Checks that pyuvdata kept
    that order and that its LSTs agree with ``lsts`` to 1 s.
    """
    UVData = uvdata_class()

    antennas = np.asarray(antennas)
    codes, x_orientation = _pol_codes_for_write(pols)
    is_hera = telescope_name.strip().upper() == "HERA"
    telescope = (
        _hera_telescope(antennas, site)
        if is_hera
        else _generic_telescope(telescope_name, site, antennas, antenna_names)
    )
    if x_orientation is not None:
        telescope.set_feeds_from_x_orientation(
            x_orientation, feeds=["x", "y"], polarization_array=codes
        )
    nant = antennas.size
    with _warnings_to_log(f"building UVData for {name}"):
        uv = UVData.new(
            freq_array=np.asarray(freqs, dtype=np.float64),
            polarization_array=codes,
            times=np.asarray(jds, dtype=np.float64),
            telescope=telescope,
            antpairs=[(int(a), int(a)) for a in antennas],
            do_blt_outer=True,
            time_axis_faster_than_bls=False,
            integration_time=np.asarray(integration_time, dtype=np.float64),
            channel_width=np.asarray(channel_width, dtype=np.float64),
            history=history,
            vis_units="uncalib",
            phase_center_catalog={0: dict(ZENITH)},
            update_telescope_from_known=is_hera,
            **(arrays or {}),
        )
    # Guard against a silent reordering of the blt axis by pyuvdata.
    expected_ants = np.tile(antennas, np.size(jds))
    if not (
        np.array_equal(uv.ant_1_array, expected_ants)
        and np.allclose(uv.time_array, np.repeat(jds, nant), rtol=0, atol=1e-9)
    ):  # pragma: no cover - depends on pyuvdata internals
        raise RuntimeError("pyuvdata reordered the baseline-time axis; cannot write safely")

    file_lsts = _lst_hours(uv.lst_array[::nant])
    worst = float(np.max(np.abs(_wrap_hours(file_lsts - np.asarray(lsts)))))
    if worst > LST_TOLERANCE_HOURS:
        raise ObservationError(
            f"the observation's LSTs disagree with those pyuvdata computes from its JDs at "
            f"{telescope.name} by up to {worst * 3600:.1f} s (allowed 1 s): check the JDs "
            "(UTC Julian dates of the integration centres), the LSTs (apparent, hours) and "
            "the site"
        )
    uv.extra_keywords = extra_keywords
    return uv


def write_uvh5(
    obs: Observation,
    path: str | Path,
    *,
    history: str = "",
    extra_keywords: dict | None = None,
    overwrite: bool = False,
) -> Path:
    """Write an observation's auto-correlations as a UVH5 file through pyuvdata.

    The file holds the baselines ``(a, a)`` for every antenna, the observation's
    polarisations, times (``obs.jds``), channels, channel widths, integration times,
    flags and sample counts; the data are complex with zero imaginary part. When
    ``obs.telescope_name`` is ``"HERA"`` the telescope metadata (all 350 antennas,
    positions, location) come from pyuvdata's known-telescope table; otherwise the
    telescope is built from ``obs.site`` with the observation's antennas at zero
    positions. pyuvdata computes the LSTs from the times and location; they must agree
    with ``obs.lsts`` to within 1 s.

    Parameters
    ----------
    obs
        The observation. Its ``integration_time`` and ``channel_width`` must be positive.
    path
        Output file.
    history
        Text appended to the file's history (after ``obs.meta["history"]``).
    extra_keywords
        Extra UVH5 header keywords (scalars or strings), added to those derived from
        ``obs.meta`` (its scalar/string entries and its ``extra_keywords``
        entries); non-scalar values are skipped.
    overwrite
        Replace an existing file.

    Returns
    -------
    pathlib.Path
        The written file.

    Raises
    ------
    FileExistsError
        If ``path`` exists and ``overwrite`` is false.
    ObservationError
        If the observation cannot be written faithfully: unknown HERA antenna
        numbers, non-positive integration times or channel widths, polarisation names
        without a UVH5 code, or LSTs inconsistent with the JDs and site.

    Notes
    -----
    The file is written to a temporary file in the same folder and renamed onto
    ``path``, so a failed write leaves no partial file. Non-finite data (which
    :class:`~autocal.core.observation.Observation` always flags) are stored as 0.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
    if np.any(obs.integration_time <= 0):
        raise ObservationError("integration_time must be positive to write UVH5")
    if np.any(obs.channel_width <= 0):
        raise ObservationError("channel_width must be positive to write UVH5")
    if obs.ntime > 1 and np.any(np.diff(obs.jds) <= 0):
        raise ObservationError("JDs must be strictly increasing to write UVH5")

    nant, npol, ntime, nfreq = obs.shape

    # Baseline-time axis: time slowest, antennas fastest -> index it * nant + ia.
    def to_blt(arr: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(arr.transpose(2, 0, 3, 1)).reshape(ntime * nant, nfreq, npol)

    real = np.where(np.isfinite(obs.data), obs.data, 0.0)
    uv = _build_uvdata(
        path.name,
        freqs=obs.freqs,
        pols=obs.pols,
        jds=obs.jds,
        lsts=obs.lsts,
        antennas=obs.antennas,
        antenna_names=obs.antenna_names,
        site=obs.site,
        telescope_name=obs.telescope_name,
        integration_time=obs.integration_time,
        channel_width=obs.channel_width,
        history=_history(obs.meta, history),
        extra_keywords=_extra_keywords(obs.meta, extra_keywords),
        arrays={
            "data_array": to_blt(real).astype(np.complex128),
            "flag_array": to_blt(obs.flags),
            "nsample_array": to_blt(obs.nsamples).astype(np.float64),
        },
    )

    with atomic_path(path) as tmp, _warnings_to_log(f"writing {path.name}"):
        # atomic_path creates the temporary file; remove it so that pyuvdata need not
        # clobber it (pyuvdata prints when it clobbers).
        tmp.unlink()
        uv.write_uvh5(str(tmp))
    logger.info(
        "wrote %s: %d antennas, pols %s, %d times, %d channels",
        path,
        nant,
        ",".join(obs.pols),
        ntime,
        nfreq,
    )
    return path


#: Data types :class:`UVH5AutosWriter` can store: complex64, complex128, and the HERA
#: correlator's int32 compound type (fields ``r``, ``i``; values rounded to integers).
WRITE_DTYPES: dict[str, Any] = {
    "c8": np.dtype("c8"),
    "c16": np.dtype("c16"),
    "int32": np.dtype([("r", "<i4"), ("i", "<i4")]),
}


class UVH5AutosWriter:
    """Write a UVH5 file of auto-correlations in parts (memory bounded by a part).

    The header comes from pyuvdata (:meth:`pyuvdata.UVData.initialize_uvh5_file` on a
    metadata-only UVData, so it is what :func:`write_uvh5` writes); the three data sets
    ``Data/visdata``, ``Data/flags`` and ``Data/nsamples`` of shape ``(Nblts, Nfreqs,
    Npols)`` are created with chunks of one integration (all antennas) by
    ``chunk_channels`` channels by one polarisation, HDF5 byte shuffle and LZF or gzip
    compression (flags and nsamples with the same filter; LZF when the data are not
    compressed), which pyuvdata and h5py read without plugins. The baseline-time axis
    is time-major (antennas fastest), as HERA's correlator writes it.

    Use as a context manager: the file is written under a temporary name and renamed
    onto ``path`` only when every integration was written and the block exits cleanly.

    Parameters
    ----------
    path
        Output file.
    freqs, channel_width
        ``(Nfreq,)`` Hz.
    jds, lsts, integration_time
        ``(Ntime,)`` Julian dates, LSTs (hours) and integration times (s).
    antennas
        Antenna numbers.
    pols
        Polarisation names (``ee``/``nn`` or ``xx``/``yy``).
    site
        Telescope site.
    telescope_name
        ``"HERA"`` takes pyuvdata's HERA telescope metadata (all 350 antennas).
    antenna_names
        Names when the telescope is not HERA (default ``ant<N>``).
    history, extra_keywords
        Header history and extra keywords.
    dtype
        ``"c8"`` (default), ``"c16"`` or ``"int32"`` (HERA correlator compound type).
    compression
        ``"lzf"`` (default), ``"gzip"`` or ``None``.
    compression_level
        gzip level (1-9; 1 decodes fastest and compresses noise-like data nearly as
        well as higher levels).
    shuffle
        Apply HDF5's byte-shuffle filter before compressing (default True: the zero
        imaginary parts and the slowly varying high bytes then compress to little).
    chunk_channels
        Channels per chunk.
    overwrite
        Replace an existing file.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        freqs: np.ndarray,
        channel_width: np.ndarray | float,
        jds: np.ndarray,
        lsts: np.ndarray,
        integration_time: np.ndarray | float,
        antennas: Sequence[int],
        pols: Sequence[str],
        site: Site,
        telescope_name: str = "HERA",
        antenna_names: Sequence[str] | None = None,
        history: str = "",
        extra_keywords: dict[str, Any] | None = None,
        dtype: str = "c8",
        compression: str | None = "lzf",
        compression_level: int = 1,
        shuffle: bool = True,
        chunk_channels: int = 256,
        overwrite: bool = False,
    ) -> None:
        self.path = Path(path)
        if self.path.exists() and not overwrite:
            raise FileExistsError(f"{self.path} exists; pass overwrite=True to replace it")
        if dtype not in WRITE_DTYPES:
            raise ObservationError(f"unknown UVH5 data type {dtype!r}: use {list(WRITE_DTYPES)}")
        if compression not in ("lzf", "gzip", None):
            raise ObservationError(f"unknown compression {compression!r}: use lzf, gzip or None")
        self.freqs = np.atleast_1d(np.asarray(freqs, np.float64))
        self.jds = np.atleast_1d(np.asarray(jds, np.float64))
        self.antennas = np.atleast_1d(np.asarray(antennas, np.int64))
        self.pols = tuple(str(p).lower() for p in pols)
        nfreq, ntime, nant = self.freqs.size, self.jds.size, self.antennas.size
        width = np.broadcast_to(np.asarray(channel_width, np.float64), (nfreq,))
        tint = np.broadcast_to(np.asarray(integration_time, np.float64), (ntime,))
        if np.any(width <= 0) or np.any(tint <= 0):
            raise ObservationError("channel widths and integration times must be positive")
        if ntime > 1 and np.any(np.diff(self.jds) <= 0):
            raise ObservationError("JDs must be strictly increasing to write UVH5")
        if np.unique(self.antennas).size != nant:
            raise ObservationError("antenna numbers are not unique")
        names = tuple(antenna_names or (f"ant{a}" for a in self.antennas))
        self.uv = _build_uvdata(
            self.path.name,
            freqs=self.freqs,
            pols=self.pols,
            jds=self.jds,
            lsts=np.asarray(lsts, np.float64),
            antennas=self.antennas,
            antenna_names=names,
            site=site,
            telescope_name=telescope_name,
            integration_time=np.asarray(tint),
            channel_width=np.asarray(width),
            history=_history({}, history, writer="UVH5AutosWriter"),
            extra_keywords=_extra_keywords({}, extra_keywords),
        )
        self.dtype = dtype
        self._options = {
            "compression": compression,
            "compression_opts": int(compression_level) if compression == "gzip" else None,
            "shuffle": bool(shuffle and compression is not None),
        }
        self._chunks = (nant, max(1, min(int(chunk_channels), nfreq)), 1)
        self._written = np.zeros(ntime, bool)
        self._tmp: Path | None = None
        self._h5: Any = None

    @property
    def shape(self) -> tuple[int, int, int, int]:
        """``(Nant, Npol, Ntime, Nfreq)`` of the file."""
        return (self.antennas.size, len(self.pols), self.jds.size, self.freqs.size)

    def __enter__(self) -> UVH5AutosWriter:
        import h5py

        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.{time.time_ns()}.tmp")
        self._tmp = tmp
        with _warnings_to_log(f"initialising {self.path.name}"):
            self.uv.initialize_uvh5_file(str(tmp), clobber=False)
        nblt, nfreq, npol = self.uv.Nblts, self.freqs.size, len(self.pols)
        h5 = h5py.File(tmp, "r+")
        try:
            del h5["Data"]  # re-create the data sets with our chunks and filters
            group = h5.create_group("Data")
            shape = (nblt, nfreq, npol)
            group.create_dataset(
                "visdata",
                shape,
                dtype=WRITE_DTYPES[self.dtype],
                chunks=self._chunks,
                **self._options,
            )
            aux = {**self._options, "compression": self._options["compression"] or "lzf"}
            group.create_dataset("flags", shape, dtype="b1", chunks=self._chunks, **aux)
            group.create_dataset("nsamples", shape, dtype="f4", chunks=self._chunks, **aux)
        except Exception:
            h5.close()
            tmp.unlink(missing_ok=True)
            raise
        self._h5 = h5
        return self

    def write(
        self,
        start: int,
        data: np.ndarray,
        flags: np.ndarray | None = None,
        nsamples: np.ndarray | float = 1.0,
    ) -> None:
        """Write integrations ``start .. start + Ntime_part - 1``.

        Parameters
        ----------
        start
            Index of the first integration of the part.
        data
            ``(Nant, Npol, Ntime_part, Nfreq)`` real auto-correlation power. Non-finite
            values are stored as 0 and flagged.
        flags
            Boolean flags like ``data`` (default none).
        nsamples
            Sample counts, broadcastable to ``data``.
        """
        if self._h5 is None:
            raise RuntimeError("use UVH5AutosWriter as a context manager (with ... as w:)")
        data = np.asarray(data)
        nant, npol, ntime, nfreq = self.shape
        if data.ndim != 4 or data.shape[:2] != (nant, npol) or data.shape[3] != nfreq:
            raise ObservationError(
                f"part has shape {data.shape}; expected (Nant, Npol, Ntime, Nfreq) with "
                f"Nant={nant}, Npol={npol}, Nfreq={nfreq}"
            )
        nt = data.shape[2]
        if not 0 <= start <= ntime - nt:
            raise ObservationError(
                f"integrations {start}..{start + nt - 1} are outside 0..{ntime - 1}"
            )
        bad = ~np.isfinite(data)
        flag = bad if flags is None else (np.broadcast_to(flags, data.shape) | bad)
        real = np.where(bad, 0.0, data) if np.any(bad) else data

        def to_blt(arr: np.ndarray) -> np.ndarray:
            return arr.transpose(2, 0, 3, 1).reshape(nt * nant, nfreq, npol)

        rows = slice(start * nant, (start + nt) * nant)
        out = np.zeros((nt * nant, nfreq, npol), WRITE_DTYPES[self.dtype])
        if self.dtype == "int32":
            values = np.rint(to_blt(real))
            if np.any(np.abs(values) > np.iinfo(np.int32).max):
                raise ObservationError("data exceed the int32 range of the correlator type")
            out["r"] = values
        else:
            out.real = to_blt(real)
        group = self._h5["Data"]
        group["visdata"][rows] = out
        del out
        group["flags"][rows] = to_blt(np.asarray(flag, bool))
        group["nsamples"][rows] = to_blt(
            np.broadcast_to(np.asarray(nsamples, np.float32), data.shape)
        )
        self._written[start : start + nt] = True

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        h5, tmp = self._h5, self._tmp
        self._h5 = None
        if h5 is not None:
            h5.close()
        if tmp is None:
            return
        if exc_type is not None:
            tmp.unlink(missing_ok=True)
            return
        if not np.all(self._written):
            tmp.unlink(missing_ok=True)
            missing = np.flatnonzero(~self._written)
            raise ObservationError(
                f"{self.path.name}: {missing.size} integration(s) were never written "
                f"(first {missing[0]}); the file was not created"
            )
        os.replace(tmp, self.path)
        logger.info("wrote %s: %s (ant, pol, time, chan) in parts", self.path, self.shape)


# ---------------------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------------------
@dataclass
class _FileMeta:
    """What read_uvh5 needs to know about one file before reading its data."""

    path: Path
    uv: Any  # the header fields read later: telescope, vis_units, history, extra_keywords
    freqs: np.ndarray  # (Nfreq,) file order
    channel_width: np.ndarray
    pol_codes: list[int]
    pol_names: list[str]
    x_orientation: str | None
    auto_ants: list[int]
    times: np.ndarray  # unique, sorted
    lsts: np.ndarray  # hours, per unique time

    @property
    def name(self) -> str:
        return self.path.name


def _open_check(path: Path) -> None:
    """Raise UVH5FormatError unless ``path`` is a readable HDF5 file with UVH5 groups."""
    import h5py

    if not path.exists():
        raise UVH5FormatError(f"{path} does not exist: check the path")
    if path.is_dir():
        raise UVH5FormatError(
            f"{path} is a directory, not a UVH5 file (Miriad data sets are not read by "
            "read_uvh5; convert them to UVH5 with pyuvdata)"
        )
    if not h5py.is_hdf5(path):
        raise UVH5FormatError(
            f"{path} is not an HDF5 file, so not UVH5: pass a UVH5 file (convert other "
            "formats with pyuvdata)"
        )
    try:
        with h5py.File(path, "r") as h5:
            groups = set(h5.keys())
    except OSError as err:
        raise UVH5FormatError(
            f"{path} is truncated or corrupt (HDF5 error: {err}); copy or download it again"
        ) from err
    missing = {"Header", "Data"} - groups
    if missing:
        raise UVH5FormatError(
            f"{path} is an HDF5 file but not UVH5 (no {'/'.join(sorted(missing))} group)"
        )


def _read_meta(path: Path) -> _FileMeta:
    UVData = uvdata_class()

    _open_check(path)
    try:
        with _warnings_to_log(f"reading metadata of {path.name}"):
            uv = UVData.from_file(str(path), file_type="uvh5", read_data=False)
    except Exception as err:  # pyuvdata raises many types for broken headers
        raise UVH5FormatError(
            f"pyuvdata cannot read the UVH5 header of {path}: {type(err).__name__}: {err}; "
            "the file may be corrupt or not a UVData UVH5 file"
        ) from err
    is_auto = uv.ant_1_array == uv.ant_2_array
    if not np.any(is_auto):
        raise UVH5FormatError(
            f"{path} has no auto-correlations (baselines (a, a)); it holds only "
            f"{uv.Nbls} cross-correlation baseline(s). Use a file with autos."
        )
    auto_ants = sorted(int(a) for a in np.unique(uv.ant_1_array[is_auto]))
    freqs = np.asarray(uv.freq_array, dtype=np.float64).ravel()
    width = np.broadcast_to(np.asarray(uv.channel_width, dtype=np.float64).ravel(), freqs.shape)
    codes = [int(c) for c in np.asarray(uv.polarization_array).ravel()]
    x_orientation = feed_orientation(uv.telescope)
    times, first = np.unique(uv.time_array[is_auto], return_index=True)
    lsts = _lst_hours(uv.lst_array[is_auto][first])
    # keep the header, not the UVData: its per baseline-time arrays (uvw, times, LSTs,
    # antenna pairs, ~100 bytes per row) would grow with the night when every file of a
    # long observation is scanned before its data are read
    header = SimpleNamespace(
        telescope=uv.telescope,
        vis_units=uv.vis_units,
        history=uv.history,
        extra_keywords=dict(uv.extra_keywords),
    )
    return _FileMeta(
        path=path,
        uv=header,
        freqs=freqs,
        channel_width=np.array(width),
        pol_codes=codes,
        pol_names=_pol_names(codes, x_orientation),
        x_orientation=x_orientation,
        auto_ants=auto_ants,
        times=times,
        lsts=lsts,
    )


def _check_consistent(first: _FileMeta, other: _FileMeta) -> None:
    """Raise UVH5FormatError if ``other`` cannot be joined to ``first``."""

    def fail(what: str) -> None:
        raise UVH5FormatError(
            f"{other.path} cannot be joined to {first.path}: {what}. Pass only files of "
            "one observation (same correlator setup)."
        )

    if other.freqs.shape != first.freqs.shape:
        fail(
            f"it has {_describe_freqs(other.freqs)}, the first file has "
            f"{_describe_freqs(first.freqs)}"
        )
    if not np.allclose(other.freqs, first.freqs, rtol=0, atol=1.0):
        worst = float(np.max(np.abs(other.freqs - first.freqs)))
        fail(
            f"its channel frequencies differ by up to {worst:.6g} Hz "
            f"({_describe_freqs(other.freqs)} vs {_describe_freqs(first.freqs)})"
        )
    if not np.allclose(other.channel_width, first.channel_width, rtol=1e-9, atol=0):
        fail("its channel widths differ")
    if other.auto_ants != first.auto_ants:
        fail(f"it has autos of antennas {other.auto_ants}, the first file {first.auto_ants}")
    if other.pol_names != first.pol_names:
        fail(f"it has polarisations {other.pol_names}, the first file {first.pol_names}")
    if other.uv.telescope.name != first.uv.telescope.name:
        fail(f"its telescope is {other.uv.telescope.name!r}, not {first.uv.telescope.name!r}")


def _select_pols(meta: _FileMeta, pols: Sequence[str] | None) -> list[int]:
    """Return indices into the file's polarisation axis, in the requested order."""
    from pyuvdata import utils as uvutils

    if pols is None:
        chosen = [i for i, c in enumerate(meta.pol_codes) if c in POWER_POL_CODES]
        return chosen or list(range(len(meta.pol_codes)))
    if isinstance(pols, str):
        pols = [pols]
    orient = meta.x_orientation if meta.x_orientation in ("east", "north") else None
    chosen = []
    for pol in pols:
        name = str(pol).lower()
        if name in meta.pol_names:
            chosen.append(meta.pol_names.index(name))
            continue
        try:  # aliases: "xx" for "ee" when x points east, etc.
            code = int(uvutils.polstr2num(name, x_orientation=orient))
        except (KeyError, ValueError):
            code = None
        if code is None or code not in meta.pol_codes:
            raise ObservationError(
                f"polarisation {pol!r} is not in {meta.path.name}; it has {meta.pol_names}"
            )
        chosen.append(meta.pol_codes.index(code))
    if len(set(chosen)) != len(chosen):
        raise ObservationError(f"polarisations {list(pols)} repeat a polarisation")
    return chosen


def _select_antennas(meta: _FileMeta, antennas: Sequence[int] | None) -> list[int]:
    if antennas is None:
        return list(meta.auto_ants)
    wanted = [int(a) for a in np.atleast_1d(antennas)]
    missing = [a for a in wanted if a not in meta.auto_ants]
    if missing:
        raise ObservationError(
            f"antenna(s) {missing} have no auto-correlations in {meta.path.name}; "
            f"available antennas: {meta.auto_ants}"
        )
    if len(set(wanted)) != len(wanted):
        raise ObservationError(f"antennas {wanted} repeat an antenna")
    return wanted


def _select_channels(meta: _FileMeta, freq_range: tuple[float, float] | None) -> np.ndarray:
    """Channel indices (file order) sorted by frequency."""
    order = np.argsort(meta.freqs, kind="stable")
    if freq_range is None:
        return order
    lo, hi = sorted(float(f) for f in freq_range)
    keep = order[(meta.freqs[order] >= lo) & (meta.freqs[order] <= hi)]
    if keep.size == 0:
        raise ObservationError(
            f"no channels in the frequency range {lo:.6g}-{hi:.6g} Hz; the data have "
            f"{_describe_freqs(meta.freqs)} (give the range in Hz)"
        )
    return keep


def _lst_mask(lsts: np.ndarray, lst_range: tuple[float, float] | None) -> np.ndarray:
    if lst_range is None:
        return np.ones(lsts.shape, bool)
    start, stop = (float(v) % 24.0 if float(v) != 24.0 else 24.0 for v in lst_range)
    if start <= stop:
        return (lsts >= start) & (lsts <= stop)
    return (lsts >= start) | (lsts <= stop)


def _read_data(
    meta: _FileMeta,
    ants: list[int],
    pol_idx: list[int],
    chans: np.ndarray,
    keep_times: np.ndarray,
) -> dict[str, np.ndarray]:
    """Read the selected autos of one file into (Nant, Npol, Ntime, Nfreq) arrays."""
    UVData = uvdata_class()

    codes = [meta.pol_codes[i] for i in pol_idx]
    try:
        with _warnings_to_log(f"reading {meta.name}"):
            uv = UVData.from_file(
                str(meta.path),
                file_type="uvh5",
                bls=[(a, a) for a in ants],
                polarizations=codes,
                freq_chans=None if chans.size == meta.freqs.size else np.sort(chans),
            )
    except Exception as err:
        raise UVH5FormatError(
            f"pyuvdata failed to read the auto-correlations of {meta.path}: "
            f"{type(err).__name__}: {err}; the file may be corrupt"
        ) from err

    # Map the read object's axes onto the requested order.
    read_freqs = np.asarray(uv.freq_array, dtype=np.float64).ravel()
    fidx = (
        np.searchsorted(read_freqs, meta.freqs[chans])
        if read_freqs.size > 1
        else np.zeros(chans.size, int)
    )
    if not np.allclose(read_freqs[fidx], meta.freqs[chans], rtol=0, atol=1e-3):
        fidx = np.array([int(np.argmin(np.abs(read_freqs - f))) for f in meta.freqs[chans]])
    read_codes = [int(c) for c in np.asarray(uv.polarization_array).ravel()]
    pidx = [read_codes.index(c) for c in codes]

    times = meta.times[keep_times]
    nant, npol, ntime, nfreq = len(ants), len(codes), times.size, chans.size
    data = np.full((nant, npol, ntime, nfreq), np.nan)
    flags = np.ones((nant, npol, ntime, nfreq), bool)
    nsamples = np.zeros((nant, npol, ntime, nfreq))
    tint = np.full(ntime, np.nan)
    filled = np.zeros((nant, ntime), bool)

    ant_pos = {a: i for i, a in enumerate(ants)}
    tpos = np.searchsorted(times, uv.time_array)
    tpos_clipped = np.clip(tpos, 0, max(ntime - 1, 0))
    in_time = (tpos < ntime) & np.isclose(times[tpos_clipped], uv.time_array, rtol=0, atol=1e-9)
    ia = np.array([ant_pos.get(int(a), -1) for a in uv.ant_1_array])
    blts = np.flatnonzero(in_time & (uv.ant_1_array == uv.ant_2_array) & (ia >= 0))
    ia, it = ia[blts], tpos[blts]
    # (Nblt, Nfreq, Npol) -> (Nblt, Npol, Nfreq) in the requested channel/pol order.
    block = np.ix_(blts, fidx, pidx)
    data[ia, :, it, :] = uv.data_array[block].real.transpose(0, 2, 1)
    flags[ia, :, it, :] = uv.flag_array[block].transpose(0, 2, 1)
    nsamples[ia, :, it, :] = uv.nsample_array[block].transpose(0, 2, 1)
    tint[it] = uv.integration_time[blts]
    filled[ia, it] = True
    if not np.all(filled):
        logger.warning(
            "%s: %d antenna-time samples are missing; they are flagged",
            meta.name,
            int(np.sum(~filled)),
        )
    if np.any(np.isnan(tint)):
        fallback = float(np.nanmedian(tint)) if np.any(np.isfinite(tint)) else 0.0
        tint = np.where(np.isnan(tint), fallback, tint)
    imag = float(np.max(np.abs(uv.data_array.imag))) if uv.data_array.size else 0.0
    if imag > 0:
        logger.debug("%s: dropped imaginary parts up to %.3g", meta.name, imag)
    return {
        "data": data,
        "flags": flags,
        "nsamples": nsamples,
        "integration_time": tint,
        "jds": times,
        "lsts": meta.lsts[keep_times],
    }


def _merge_keywords(metas: list[_FileMeta]) -> dict[str, Any]:
    """Extra keywords of all files: one value where they agree, a per-file list otherwise."""
    per_file = [
        {
            str(k): (_scalar(v) if _scalar(v) is not None else v)
            for k, v in m.uv.extra_keywords.items()
        }
        for m in metas
    ]
    merged: dict[str, Any] = {}
    for key in dict.fromkeys(k for kw in per_file for k in kw):
        values = [kw.get(key) for kw in per_file]
        if all(_same(values[0], v) for v in values[1:]):
            merged[key] = values[0]
        else:
            merged[key] = values
    return merged


def _same(a: Any, b: Any) -> bool:
    try:
        return bool(np.all(np.asarray(a) == np.asarray(b)))
    except (TypeError, ValueError):
        return False


def _site(uv: Any) -> Site:
    loc = uv.telescope.location
    try:
        lat = float(loc.lat.deg)
        lon = float(loc.lon.deg)
        alt = float(loc.height.to_value("m"))
    except AttributeError as err:  # pragma: no cover - non-Earth telescopes
        raise UVH5FormatError(f"telescope location {loc!r} is not a geodetic location") from err
    name = str(uv.telescope.name or "unknown").strip().lower() or "unknown"
    return Site(name, lat, lon, alt)


def _scan(paths: str | Path | Sequence[str | Path]) -> list[_FileMeta]:
    """Read and cross-check the headers of the files of one observation, in time order."""
    path_list = [Path(paths)] if isinstance(paths, (str, Path)) else [Path(p) for p in paths]
    if not path_list:
        raise UVH5FormatError("no files given")
    path_list = [p.expanduser().absolute() for p in path_list]
    if len(set(path_list)) != len(path_list):
        raise UVH5FormatError("the same file is given more than once")

    metas = sorted((_read_meta(p) for p in path_list), key=lambda m: float(m.times[0]))
    first = metas[0]
    for other in metas[1:]:
        _check_consistent(first, other)
    for prev, nxt in itertools.pairwise(metas):
        if nxt.times[0] <= prev.times[-1]:
            raise UVH5FormatError(
                f"{nxt.path} overlaps in time with {prev.path} (JD {nxt.times[0]:.6f} <= "
                f"{prev.times[-1]:.6f}); pass consecutive files of one observation"
            )
        cadence = float(np.median(np.diff(prev.times))) if prev.times.size > 1 else 0.0
        gap = float(nxt.times[0] - prev.times[-1])
        if cadence > 0 and gap > 2.5 * cadence:
            logger.warning("gap of %.1f min between %s and %s", gap * 1440.0, prev.name, nxt.name)

    return metas


@dataclass(frozen=True)
class UVH5File:
    """Header summary of one UVH5 file of an observation (see :func:`scan_uvh5`)."""

    path: Path
    jds: np.ndarray
    lsts: np.ndarray
    freqs: np.ndarray
    antennas: tuple[int, ...]
    pols: tuple[str, ...]
    site: Site
    header: Any = field(default=None, repr=False, compare=False)
    """The file's metadata as scanned (lets :func:`iter_uvh5_blocks` skip a re-scan)."""


def scan_uvh5(paths: str | Path | Sequence[str | Path]) -> list[UVH5File]:
    """Check the files of one observation and list them in time order (headers only).

    Raises the same :class:`UVH5FormatError` as :func:`read_uvh5` for missing, corrupt,
    autos-free, inconsistent or overlapping files, without reading any data.
    """
    return [
        UVH5File(
            m.path,
            m.times.copy(),
            m.lsts.copy(),
            np.sort(m.freqs),
            tuple(m.auto_ants),
            tuple(m.pol_names),
            _site(m.uv),
            m,
        )
        for m in _scan(paths)
    ]


def iter_uvh5(
    paths: str | Path | Sequence[str | Path],
    *,
    antennas: Sequence[int] | None = None,
    pols: Sequence[str] | None = None,
    freq_range: tuple[float, float] | None = None,
    lst_range: tuple[float, float] | None = None,
    block_size: int | None = None,
    stats: ReadStats | None = None,
) -> Iterator[Observation]:
    """Yield the observation file by file (same selections as :func:`read_uvh5`).

    Files with no integration in ``lst_range`` are skipped. Only one file's autos are in
    memory at a time, so a whole night can be streamed into the fit's normal sums.
    With ``block_size`` (integrations; ``0`` = automatic, see :func:`iter_uvh5_blocks`)
    each file is yielded in blocks of integrations, so memory is bounded by the block,
    not the file.
    """
    from autocal.io.uvh5_blocks import iter_uvh5_blocks

    for meta in _scan(paths):
        if not np.any(_lst_mask(meta.lsts, lst_range)):
            continue
        if block_size is not None:
            yield from iter_uvh5_blocks(
                meta,
                antennas=antennas,
                pols=pols,
                freq_range=freq_range,
                lst_range=lst_range,
                block_size=block_size or None,
                stats=stats,
            )
            continue
        yield read_uvh5(
            [meta.path], antennas=antennas, pols=pols, freq_range=freq_range, lst_range=lst_range
        )


def read_uvh5(
    paths: str | Path | Sequence[str | Path],
    *,
    antennas: Sequence[int] | None = None,
    pols: Sequence[str] | None = None,
    freq_range: tuple[float, float] | None = None,
    lst_range: tuple[float, float] | None = None,
) -> Observation:
    """Read the auto-correlations of UVH5 files into an :class:`Observation`.

    Only the baselines ``(a, a)`` are read from disk (pyuvdata partial read);
    cross-correlations are never loaded. Several files are joined in time order after
    checking that they share frequencies, antennas (with autos), polarisations and
    telescope.

    Parameters
    ----------
    paths
        One file or a list of consecutive files of one observation (any order; they
        are sorted by time). ``*.uvh5_downselected`` names are fine.
    antennas
        Antenna numbers to keep, in this order (default: every antenna with autos).
    pols
        Polarisations to keep, e.g. ``["ee", "nn"]`` (case-insensitive; ``xx``/``yy``
        are accepted as aliases of ``ee``/``nn`` in files whose x dipole points east).
        Default: the feed-power polarisations (ee/nn, or xx/yy when the orientation is
        unknown); cross-feed autos (en/ne) only when asked for, as their real part.
    freq_range
        ``(low, high)`` channel-centre frequencies to keep, in Hz, inclusive.
    lst_range
        ``(start, stop)`` LSTs to keep, in hours, inclusive; ``start > stop`` wraps
        through 24 h.

    Returns
    -------
    Observation
        Data ``(Nant, Npol, Ntime, Nfreq)`` (real part of the autos), flags, nsamples,
        channel widths, integration times, LSTs (hours) and JDs, antenna numbers and
        names, polarisation names, the telescope site (named after the telescope,
        lowercased) and ``meta`` with ``source`` ("uvh5"), ``files`` (absolute paths
        in time order), ``sha256`` (path -> digest), ``history``, ``extra_keywords``
        (one value per keyword, or a per-file list where the files differ),
        ``vis_units`` and ``x_orientation``.

    Raises
    ------
    UVH5FormatError
        If a file is missing, a directory, not HDF5/UVH5, truncated or corrupt, has no
        auto-correlations, or differs from the first file in frequencies, antennas,
        polarisations or telescope; or if files overlap in time.
    ObservationError
        For an unknown antenna or polarisation, or a frequency or LST selection that
        leaves nothing.
    """
    metas = _scan(paths)
    first = metas[0]
    ants = _select_antennas(first, antennas)
    pol_idx = _select_pols(first, pols)
    chans = _select_channels(first, freq_range)

    pieces = []
    used = []
    for meta in metas:
        keep = _lst_mask(meta.lsts, lst_range)
        if not np.any(keep):
            logger.info("%s: no integrations in LST range %s h; skipped", meta.name, lst_range)
            continue
        pieces.append(_read_data(meta, ants, pol_idx, chans, keep))
        used.append(meta)
    if not pieces:
        covered = ", ".join(f"{m.lsts.min():.3f}-{m.lsts.max():.3f}" for m in metas)
        raise ObservationError(
            f"no integrations in LST range {lst_range} h; the files cover LSTs {covered} h"
        )

    def join(key: str, axis: int) -> np.ndarray:
        return np.concatenate([p[key] for p in pieces], axis=axis)

    telescope = first.uv.telescope
    names_by_number = {
        int(n): str(name)
        for n, name in zip(telescope.antenna_numbers, telescope.antenna_names, strict=True)
    }
    histories = [m.uv.history or "" for m in used]
    if all(h == histories[0] for h in histories):
        history = histories[0]
    else:
        history = "\n".join(
            f"[{m.name}]\n{h.rstrip()}" for m, h in zip(used, histories, strict=True)
        )
    files = [str(m.path) for m in used]
    meta_out: dict[str, Any] = {
        "source": "uvh5",
        "files": files,
        "sha256": {f: file_checksum(f) for f in files},
        "history": history,
        "extra_keywords": _merge_keywords(used),
        "vis_units": str(first.uv.vis_units),
        "x_orientation": first.x_orientation,
    }
    obs = Observation(
        data=join("data", 2),
        freqs=first.freqs[chans],
        lsts=join("lsts", 0),
        jds=join("jds", 0),
        antennas=np.array(ants),
        pols=tuple(first.pol_names[i] for i in pol_idx),
        site=_site(first.uv),
        flags=join("flags", 2),
        channel_width=first.channel_width[chans],
        integration_time=join("integration_time", 0),
        nsamples=join("nsamples", 2),
        antenna_names=tuple(names_by_number.get(a, f"ant{a}") for a in ants),
        telescope_name=str(first.uv.telescope.name),
        meta=meta_out,
    )
    logger.info(
        "read %d file(s): antennas %s, pols %s, %d times, %d channels",
        len(files),
        ants,
        ",".join(obs.pols),
        obs.ntime,
        obs.nfreq,
    )
    return obs
