"""EDGES spectrum files of either format, recognised by content, as spectra or an observation.

:func:`read_edges_spectra` reads ACQ files (:mod:`autocal.io.edges_acq`) and autocal
HDF5 files (:mod:`autocal.io.edges_hdf5`), told apart by the HDF5 signature, into one
time series of :class:`~autocal.io.edges_spectra.EdgesSpectra`; :func:`read_edges` turns
it into an :class:`autocal.core.observation.Observation` of ``R = Q`` or ``R = p0``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from autocal.core.observation import Observation
from autocal.core.sites import EDGES, Site
from autocal.io.edges_acq import read_acq_spectra
from autocal.io.edges_hdf5 import read_edges_hdf5
from autocal.io.edges_spectra import EdgesFormatError, EdgesSpectra, RKind


def _is_hdf5(path: Path) -> bool:
    try:
        with path.open("rb") as handle:
            return handle.read(8) == b"\x89HDF\r\n\x1a\n"
    except OSError:
        return False


def read_edges_spectra(
    paths: str | Path | Sequence[str | Path],
    *,
    freq_range: tuple[float, float] | None = None,
    bin_factor: int = 1,
    allow_partial: bool = False,
) -> EdgesSpectra:
    """Read ACQ or autocal-HDF5 EDGES files (recognised by content) into one time series.

    Parameters are as for :func:`~autocal.io.edges_acq.read_acq_spectra`.
    """
    plist = [Path(paths)] if isinstance(paths, str | Path) else [Path(p) for p in paths]
    if not plist:
        raise EdgesFormatError("no EDGES files given")
    pieces = []
    for path in plist:
        if path.is_file() and _is_hdf5(path):
            pieces.append(read_edges_hdf5(path, freq_range=freq_range, bin_factor=bin_factor))
        else:
            pieces.append(
                read_acq_spectra(
                    path, freq_range=freq_range, bin_factor=bin_factor, allow_partial=allow_partial
                )
            )
    return EdgesSpectra.concatenate(pieces)


def read_edges(
    paths: str | Path | Sequence[str | Path],
    *,
    r: RKind = "q",
    freq_range: tuple[float, float] | None = None,
    bin_factor: int = 1,
    site: Site = EDGES,
    allow_partial: bool = False,
) -> Observation:
    """Read EDGES spectra (ACQ or HDF5) into an :class:`Observation`.

    Parameters
    ----------
    paths
        One file or several of one observation (joined in time order).
    r
        ``"q"``: ``Q = (p0 - p1) / (p2 - p1)``; ``"p0"``: raw antenna power.
    freq_range
        ``(low, high)`` in Hz, inclusive (native channels); channels below 1 MHz are
        always left out.
    bin_factor
        Average this many consecutive channels (e.g. 64: 390.6 kHz channels).
    site
        Telescope site (default the EDGES site at the MRO).
    allow_partial
        Keep the complete cycles of truncated or corrupt ACQ files.

    Returns
    -------
    Observation
        ``data`` ``(1, 1, Ntime, Nfreq)`` (antenna 0, pol ``ee``), LSTs at ``site``,
        ``channel_width``, ``integration_time`` per switch position, ``telescope_name``
        "EDGES", ``meta`` with ``files``, ``sha256``, ``header``, ``r``,
        ``r_definition``, ``bin_factor``, ``integration_time_source``.

    Raises
    ------
    EdgesFormatError
        For unreadable, corrupt or inconsistent files.
    """
    spec = read_edges_spectra(
        paths, freq_range=freq_range, bin_factor=bin_factor, allow_partial=allow_partial
    )
    return spec.to_observation(r=r, site=site)
