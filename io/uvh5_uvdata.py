"""The pyuvdata ``UVData`` of an autos-only UVH5 file, as both UVH5 writers build it.

:func:`build_uvdata` makes the UVData (metadata only, or with data arrays) that
:func:`autocal.io.uvh5.write_uvh5` writes whole and that
:class:`~autocal.io.uvh5_writer.UVH5AutosWriter` uses as the header of a file written in
parts: HERA telescope metadata from pyuvdata's known-telescope table when the telescope
is HERA, otherwise a minimal telescope at the observation's site; polarisation codes
from the names (``ee``/``nn`` with the x feed pointing east, or ``xx``/``yy``); a zenith
(unprojected, drift-scan) phase centre; a time-major baseline-time axis, checked against
pyuvdata's LSTs. :func:`header_keywords` and :func:`file_history` derive the header's
extra keywords and history from an observation's ``meta``.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import numpy as np

from autocal import __version__
from autocal.core.observation import ObservationError
from autocal.core.sites import Site
from autocal.io.polarisations import name_to_code
from autocal.io.pyuvdata_helpers import uvdata_class, warnings_to_log
from autocal.io.uvh5_meta import keyword_scalar, lst_hours, wrap_hours

logger = logging.getLogger(__name__)


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


def _warnings_to_log(context: str) -> Any:
    return warnings_to_log(context, logger, logging.INFO)


def _hera_telescope(antennas: np.ndarray, site: Site) -> Any:
    from pyuvdata import Telescope  # ~1.5 s to import: only when a file is written

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
    compass = [p for p in pols if set(p) <= {"e", "n"}]
    if compass and len(compass) != len(pols):
        raise ObservationError(
            f"cannot mix e/n and x/y polarisation names in one file: {list(pols)}"
        )
    x_orientation = "east" if compass else None
    try:
        codes = [name_to_code(p, x_orientation) for p in pols]
    except KeyError as err:
        raise ObservationError(f"polarisations {list(pols)} have no UVH5 code: {err}") from err
    return codes, x_orientation


def header_keywords(meta: dict[str, Any], extra: dict | None) -> dict[str, Any]:
    """Return a file's extra keywords: ``meta``'s (inherited, then its own) and ``extra``.

    Only scalars and strings are kept (others are skipped with a debug message); the
    keys ``files``, ``sha256``, ``history`` and ``extra_keywords`` of ``meta`` are not
    copied one-to-one.
    """
    keywords: dict[str, Any] = {}
    inherited = meta.get("extra_keywords")
    candidates: list[tuple[str, Any]] = []
    if isinstance(inherited, dict):
        candidates += list(inherited.items())
    candidates += [(k, v) for k, v in meta.items() if k not in _RESERVED_META]
    candidates += list((extra or {}).items())
    for key, value in candidates:
        scalar = keyword_scalar(value)
        if scalar is None:
            logger.debug("extra keyword %r skipped: %s is not a scalar or string", key, type(value))
            continue
        keywords[str(key)] = scalar
    return keywords


def file_history(meta: dict[str, Any], history: str, writer: str = "write_uvh5") -> str:
    """Return a file's history: ``meta``'s history and source files, ``history``, autocal's line."""
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


def build_uvdata(
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

    file_lsts = lst_hours(uv.lst_array[::nant])
    worst = float(np.max(np.abs(wrap_hours(file_lsts - np.asarray(lsts)))))
    if worst > LST_TOLERANCE_HOURS:
        raise ObservationError(
            f"the observation's LSTs disagree with those pyuvdata computes from its JDs at "
            f"{telescope.name} by up to {worst * 3600:.1f} s (allowed 1 s): check the JDs "
            "(UTC Julian dates of the integration centres), the LSTs (apparent, hours) and "
            "the site"
        )
    uv.extra_keywords = extra_keywords
    return uv
