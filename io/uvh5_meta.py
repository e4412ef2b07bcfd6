"""UVH5 file headers: the scan, the selections and the per-file record both readers use.

:func:`scan_uvh5` checks the files of one observation from their headers alone (no
data) and lists them in time order as :class:`UVH5File` records; :func:`scan_files` does
the same work and returns the fuller :class:`FileMeta` records the readers need. The
selections (:func:`select_antennas`, :func:`select_pols`, :func:`select_channels`,
:func:`lst_mask`) turn a reader's ``antennas``/``pols``/``freq_range``/``lst_range``
arguments into indices of a file's axes, with the messages a user sees when a selection
leaves nothing. The whole-file reader (:mod:`autocal.io.uvh5`) and the block reader
(:mod:`autocal.io.uvh5_blocks`) both start here.
"""

from __future__ import annotations

import itertools
import logging
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from autocal.core.observation import ObservationError
from autocal.core.sites import Site
from autocal.errors import AutocalError
from autocal.io.polarisations import codes_to_names, name_to_code
from autocal.io.pyuvdata_helpers import uvdata_class, warnings_to_log
from autocal.io.pyuvdata_helpers import x_orientation as feed_orientation
from autocal.io.uvh5_header import HeaderArrays, UVH5Header, header_from_uvdata, read_plain_header

logger = logging.getLogger(__name__)


#: pyuvdata polarisation codes of the feed-power (same-feed) polarisations, read by
#: default: xx/ee, yy/nn (linear), rr, ll (circular).
POWER_POL_CODES = (-5, -6, -1, -2)


class UVH5FormatError(AutocalError):
    """A file is missing, not UVH5, corrupt, lacks autos, or disagrees with its siblings."""


def _warnings_to_log(context: str) -> Any:
    return warnings_to_log(context, logger, logging.INFO)


def lst_hours(lst_rad: np.ndarray) -> np.ndarray:
    """Convert LSTs in radians (pyuvdata's) to hours in [0, 24)."""
    return np.mod(np.asarray(lst_rad, dtype=np.float64) * 12.0 / np.pi, 24.0)


def wrap_hours(diff: np.ndarray) -> np.ndarray:
    """Wrap LST differences (hours) into [-12, 12)."""
    return np.mod(np.asarray(diff) + 12.0, 24.0) - 12.0


def keyword_scalar(value: Any) -> Any:
    """Return ``value`` as a plain scalar/string for extra_keywords, or None if it is not one."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, bytes):
        return value.decode("utf-8", errors="replace")
    if isinstance(value, (bool, int, float, complex, str)):
        return value
    return None


def polarisation_names(codes: Sequence[int], x_orientation: str | None) -> list[str]:
    """Pyuvdata pol codes -> names: ee/nn when the orientation is known, else xx/yy."""
    orient = x_orientation if x_orientation in ("east", "north") else None
    return codes_to_names(codes, orient)


def describe_freqs(freqs: np.ndarray) -> str:
    """Describe a channel axis for messages: count and range in MHz."""
    if freqs.size == 0:
        return "no channels"
    return f"{freqs.size} channels {freqs.min() / 1e6:.6g}-{freqs.max() / 1e6:.6g} MHz"


@dataclass
class FileMeta:
    """What the readers need to know about one file before reading its data.

    Made by :func:`read_file_meta` (and :func:`scan_files` for every file of an
    observation). ``header`` keeps the header fields read later (telescope, site, units,
    history, extra keywords), nothing per baseline-time row.
    """

    path: Path
    header: UVH5Header
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
        """The file's name (for messages)."""
        return self.path.name


def check_uvh5_file(path: Path) -> None:
    """Raise UVH5FormatError unless ``path`` is a readable HDF5 file with UVH5 groups."""
    if not path.exists():
        raise UVH5FormatError(f"{path} does not exist: check the path")
    if path.is_dir():
        missing = [n for n in ("visdata", "vartable") if not (path / n).is_file()]
        raise UVH5FormatError(
            f"{path} is a folder, not a UVH5 file, and not a whole Miriad data set either "
            f"(it has no {' and no '.join(missing)}): give UVH5 files or complete Miriad "
            "folders"
            if missing
            else f"{path} is a Miriad data set, not a UVH5 file: this reader takes UVH5 "
            "(autocal calibrate reads Miriad folders; elsewhere convert them with pyuvdata)"
        )
    if not h5py.is_hdf5(path):
        raise UVH5FormatError(
            f"{path} is not an HDF5 file, so not UVH5: pass a UVH5 file (convert other "
            "formats with pyuvdata)"
        )
    try:
        with h5py.File(path, "r") as h5:
            groups = set(h5.keys())
    except (OSError, RuntimeError) as err:  # h5py raises both for a damaged file
        raise UVH5FormatError(
            f"{path} is truncated or corrupt (HDF5 error: {err}); copy or download it again"
        ) from err
    missing = {"Header", "Data"} - groups
    if missing:
        raise UVH5FormatError(
            f"{path} is an HDF5 file but not UVH5 (no {'/'.join(sorted(missing))} group)"
        )


def read_file_meta(path: Path) -> FileMeta:
    """Read one file's header (no data) into a :class:`FileMeta`.

    The header is read with h5py (:func:`autocal.io.uvh5_header.read_plain_header`) when it
    has the usual plain form, else through pyuvdata. Raises :class:`UVH5FormatError` for a
    missing, non-UVH5 or corrupt file, or one without auto-correlations.
    """
    check_uvh5_file(path)
    plain = read_plain_header(path)
    header, arrays = plain if plain is not None else _header_through_pyuvdata(path)
    _check_header_values(path, arrays)
    is_auto = arrays.ant_1 == arrays.ant_2
    if not np.any(is_auto):
        nbls = np.unique(np.stack([arrays.ant_1, arrays.ant_2]), axis=1).shape[1]
        raise UVH5FormatError(
            f"{path} has no auto-correlations (baselines (a, a)); it holds only "
            f"{nbls} cross-correlation baseline(s). Use a file with autos."
        )
    auto_ants = sorted(int(a) for a in np.unique(arrays.ant_1[is_auto]))
    times, first = np.unique(arrays.times[is_auto], return_index=True)
    lsts = lst_hours(arrays.lsts_rad[is_auto][first])
    return FileMeta(
        path=path,
        header=header,
        freqs=arrays.freqs,
        channel_width=arrays.channel_width,
        pol_codes=arrays.pol_codes,
        pol_names=polarisation_names(arrays.pol_codes, header.x_orientation),
        x_orientation=header.x_orientation,
        auto_ants=auto_ants,
        times=times,
        lsts=lsts,
    )


def _header_through_pyuvdata(path: Path) -> tuple[UVH5Header, HeaderArrays]:
    """Read the header with pyuvdata (headers not in the plain form, broken ones)."""
    UVData = uvdata_class()
    try:
        with _warnings_to_log(f"reading metadata of {path.name}"):
            uv = UVData.from_file(str(path), file_type="uvh5", read_data=False)
    except Exception as err:  # pyuvdata raises many types for broken headers
        raise UVH5FormatError(
            f"pyuvdata cannot read the UVH5 header of {path}: {type(err).__name__}: "
            f"{_first_line(err)}; the file may be corrupt (copy or download it again) or "
            "not a UVData UVH5 file"
        ) from err
    return header_from_uvdata(uv, feed_orientation(uv.telescope), file_history(path))


def _first_line(err: Exception) -> str:
    """Return an error's first line, without a request to report it upstream.

    Errors raised inside compiled code (numba) carry a traceback after the first line, and
    some of pyuvdata's ask the user to file an issue with pyuvdata: a corrupt file is not
    pyuvdata's bug.
    """
    lines = str(err).strip().splitlines()
    text = lines[0] if lines else ""
    return re.sub(r"\s*[^.;]*\bfile an issue\b[^.;]*[.;]?", "", text, flags=re.I).strip() or (
        "(no message)"
    )


def _check_header_values(path: Path, arrays: HeaderArrays) -> None:
    """Refuse a header whose channels, times or antennas are not numbers a file can hold.

    Raises
    ------
    UVH5FormatError
        Naming the data set and what is wrong with it.
    """
    problems = []
    with np.errstate(invalid="ignore"):
        bad_freqs = ~(np.isfinite(arrays.freqs) & (arrays.freqs > 0))
        if bad_freqs.any():
            problems.append(
                f"Header/freq_array has {int(bad_freqs.sum())} of {arrays.freqs.size} "
                "channel frequencies not finite and positive"
            )
        for name, values in (("time_array", arrays.times), ("lst_array", arrays.lsts_rad)):
            bad = ~np.isfinite(np.asarray(values, dtype=np.float64))
            if bad.any():
                problems.append(f"Header/{name} has {int(bad.sum())} non-finite value(s)")
    for name, values in (("ant_1_array", arrays.ant_1), ("ant_2_array", arrays.ant_2)):
        numbers = np.asarray(values)
        if numbers.dtype.kind not in "iu" and not (
            numbers.dtype.kind == "f"
            and np.all(np.isfinite(numbers))
            and np.all(numbers == np.round(numbers))
        ):
            problems.append(f"Header/{name} holds values that are not antenna numbers")
        elif numbers.size and numbers.min() < 0:
            problems.append(f"Header/{name} holds negative antenna numbers")
    if problems:
        raise UVH5FormatError(
            f"{path.name} is corrupt: {'; '.join(problems)}; copy or download it again"
        )


def file_history(path: Path) -> str | None:
    """Return the ``history`` a UVH5 file holds (without what a reader appends), or None."""
    try:
        with h5py.File(path, "r") as h5:
            value = h5["Header"].get("history")
            return None if value is None else bytes(value[()]).decode("utf8")
    except (OSError, UnicodeDecodeError, TypeError):
        return None


def check_joinable(first: FileMeta, other: FileMeta) -> None:
    """Raise UVH5FormatError if ``other`` cannot be joined to ``first``."""

    def fail(what: str) -> None:
        raise UVH5FormatError(
            f"{other.path} cannot be joined to {first.path}: {what}. Pass only files of "
            "one observation (same correlator setup)."
        )

    if other.freqs.shape != first.freqs.shape:
        fail(
            f"it has {describe_freqs(other.freqs)}, the first file has "
            f"{describe_freqs(first.freqs)}"
        )
    if not np.allclose(other.freqs, first.freqs, rtol=0, atol=1.0):
        worst = float(np.max(np.abs(other.freqs - first.freqs)))
        fail(
            f"its channel frequencies differ by up to {worst:.6g} Hz "
            f"({describe_freqs(other.freqs)} vs {describe_freqs(first.freqs)})"
        )
    if not np.allclose(other.channel_width, first.channel_width, rtol=1e-9, atol=0):
        fail("its channel widths differ")
    if other.auto_ants != first.auto_ants:
        fail(f"it has autos of antennas {other.auto_ants}, the first file {first.auto_ants}")
    if other.pol_names != first.pol_names:
        fail(f"it has polarisations {other.pol_names}, the first file {first.pol_names}")
    if other.header.telescope_name != first.header.telescope_name:
        fail(
            f"its telescope is {other.header.telescope_name!r}, not {first.header.telescope_name!r}"
        )


def select_pols(meta: FileMeta, pols: Sequence[str] | None) -> list[int]:
    """Return indices into the file's polarisation axis, in the requested order."""
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
            code = name_to_code(name, orient)
        except KeyError:
            code = None
        if code is None or code not in meta.pol_codes:
            raise ObservationError(
                f"polarisation {pol!r} is not in {meta.path.name}; it has {meta.pol_names}"
            )
        chosen.append(meta.pol_codes.index(code))
    if len(set(chosen)) != len(chosen):
        raise ObservationError(f"polarisations {list(pols)} repeat a polarisation")
    return chosen


def select_antennas(meta: FileMeta, antennas: Sequence[int] | None) -> list[int]:
    """Return the antenna numbers to read, in the requested order (default: all autos)."""
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


def select_channels(meta: FileMeta, freq_range: tuple[float, float] | None) -> np.ndarray:
    """Channel indices (file order) sorted by frequency."""
    order = np.argsort(meta.freqs, kind="stable")
    if freq_range is None:
        return order
    lo, hi = sorted(float(f) for f in freq_range)
    keep = order[(meta.freqs[order] >= lo) & (meta.freqs[order] <= hi)]
    if keep.size == 0:
        raise ObservationError(
            f"no channels in the frequency range {lo:.6g}-{hi:.6g} Hz; the data have "
            f"{describe_freqs(meta.freqs)} (give the range in Hz)"
        )
    return keep


def antenna_names(meta: FileMeta, ants: Sequence[int]) -> tuple[str, ...]:
    """Return the names of antennas ``ants`` in the file's telescope (``ant<N>`` if unnamed)."""
    header = meta.header
    names_by_number = dict(zip(header.antenna_numbers, header.antenna_names, strict=True))
    return tuple(names_by_number.get(a, f"ant{a}") for a in ants)


def lst_mask(lsts: np.ndarray, lst_range: tuple[float, float] | None) -> np.ndarray:
    """Return which ``lsts`` (hours) lie in ``lst_range`` (inclusive; ``start > stop`` wraps)."""
    if lst_range is None:
        return np.ones(lsts.shape, bool)
    start, stop = (float(v) % 24.0 if float(v) != 24.0 else 24.0 for v in lst_range)
    if start <= stop:
        return (lsts >= start) & (lsts <= stop)
    return (lsts >= start) | (lsts <= stop)


def scan_files(paths: str | Path | Sequence[str | Path]) -> list[FileMeta]:
    """Read and cross-check the headers of the files of one observation, in time order."""
    path_list = [Path(paths)] if isinstance(paths, (str, Path)) else [Path(p) for p in paths]
    if not path_list:
        raise UVH5FormatError("no files given")
    path_list = [p.expanduser().absolute() for p in path_list]
    if len(set(path_list)) != len(path_list):
        raise UVH5FormatError("the same file is given more than once")

    metas = sorted((read_file_meta(p) for p in path_list), key=lambda m: float(m.times[0]))
    first = metas[0]
    for other in metas[1:]:
        check_joinable(first, other)
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
    """The file's :class:`FileMeta` as scanned (lets the block reader skip a re-scan)."""


def scan_uvh5(paths: str | Path | Sequence[str | Path]) -> list[UVH5File]:
    """Check the files of one observation and list them in time order (headers only).

    Raises the same :class:`UVH5FormatError` as :func:`autocal.io.uvh5.read_uvh5` for
    missing, corrupt, autos-free, inconsistent or overlapping files, without reading any
    data.
    """
    return [
        UVH5File(
            m.path,
            m.times.copy(),
            m.lsts.copy(),
            np.sort(m.freqs),
            tuple(m.auto_ants),
            tuple(m.pol_names),
            m.header.site,
            m,
        )
        for m in scan_files(paths)
    ]


def file_meta_of(file: UVH5File | FileMeta | str | Path) -> FileMeta:
    """Return the :class:`FileMeta` of a file: the scanned one when given, else a new scan.

    Parameters
    ----------
    file
        A :class:`FileMeta`, a :class:`UVH5File` from :func:`scan_uvh5` (its header is
        reused) or a path (scanned now).

    Returns
    -------
    FileMeta
        The file's header record.
    """
    if isinstance(file, FileMeta):
        return file
    if isinstance(file, UVH5File) and isinstance(file.header, FileMeta):
        return file.header
    path = file.path if isinstance(file, UVH5File) else Path(file)
    return scan_files([path])[0]
