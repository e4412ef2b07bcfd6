"""Power beams from UVBeam-readable files (beamfits, etc.) through pyuvdata."""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from autocal.io.feko import BeamFileError

logger = logging.getLogger(__name__)

#: Linear-pol names autocal uses and the pyuvdata codes for an east-oriented x dipole.
POL_NAMES = ("ee", "nn")


@dataclass(frozen=True)
class HealpixBeamData:
    """A HEALPix power beam (zenith at the pole, azimuth from east through north).

    Attributes
    ----------
    freqs
        ``(Nfreq,)`` Hz.
    nside
        HEALPix resolution.
    nest
        Whether the pixel ordering is NESTED.
    pixels
        ``(Npix_stored,)`` pixel indices present in ``data``.
    data
        ``(Nfreq, Npix_stored)`` power beam (real).
    pol
        ``"ee"`` or ``"nn"``.
    """

    freqs: np.ndarray
    nside: int
    nest: bool
    pixels: np.ndarray
    data: np.ndarray
    pol: str


def read_healpix_power_beam(path: str | Path, pol: str = "ee") -> HealpixBeamData:
    """Read one linear polarisation of a HEALPix power beam with pyuvdata.

    Parameters
    ----------
    path
        A file :meth:`pyuvdata.UVBeam.from_file` can read (e.g. beamfits).
    pol
        ``"ee"`` (east-west dipole) or ``"nn"`` (north-south dipole).

    Returns
    -------
    HealpixBeamData
        The beam.

    Raises
    ------
    BeamFileError
        If the file is unreadable, not a HEALPix power beam, or lacks ``pol``.
    """
    path = Path(path)
    if not path.is_file():
        raise BeamFileError(f"beam file {path} does not exist")
    stat = path.stat()
    return _read_cached(str(path.resolve()), pol, stat.st_mtime_ns)


@lru_cache(maxsize=8)
def _read_cached(path: str, pol: str, _mtime: int) -> HealpixBeamData:
    if pol not in POL_NAMES:
        raise BeamFileError(f"polarisation {pol!r} not supported: use one of {POL_NAMES}")
    from pyuvdata import UVBeam  # ~1 s to import: only when a beam file is read
    from pyuvdata import utils as uvutils

    try:
        with warnings.catch_warnings():
            # Old files lack mount_type / feed metadata: pyuvdata's deprecation notices
            # about them are not actionable by an autocal user.
            warnings.simplefilter("ignore", DeprecationWarning)
            beam = UVBeam.from_file(path)
    except Exception as err:  # pyuvdata raises many kinds for unreadable files
        raise BeamFileError(f"{path} is not a readable UVBeam file: {err}") from err
    if beam.beam_type != "power":
        beam.efield_to_power(calc_cross_pols=False)
    if beam.pixel_coordinate_system != "healpix":
        raise BeamFileError(
            f"{path}: pixel coordinate system {beam.pixel_coordinate_system!r}; autocal "
            "reads HEALPix beams (convert with UVBeam.to_healpix)"
        )
    try:
        x_orient = beam.get_x_orientation_from_feeds() or "east"
    except AttributeError:  # pyuvdata < 3.2
        x_orient = getattr(beam, "x_orientation", None) or "east"
    pol_nums = uvutils.polstr2num(pol, x_orientation=x_orient)
    if pol_nums not in list(beam.polarization_array):
        names = uvutils.polnum2str(beam.polarization_array, x_orientation=x_orient)
        raise BeamFileError(f"{path} has no {pol!r} beam (has {names})")
    ipol = list(beam.polarization_array).index(pol_nums)
    data = np.real(beam.data_array[0, ipol]).astype(np.float64)  # (Nfreq, Npix)
    if not np.all(np.isfinite(data)):
        raise BeamFileError(f"{path}: beam has non-finite values")
    freqs = np.asarray(beam.freq_array, dtype=np.float64).ravel()
    logger.info(
        "read UVBeam %s (%s): nside %d, %d frequencies %.0f-%.0f MHz",
        path,
        pol,
        beam.nside,
        freqs.size,
        freqs[0] / 1e6,
        freqs[-1] / 1e6,
    )
    return HealpixBeamData(
        freqs=freqs,
        nside=int(beam.nside),
        nest=str(beam.ordering).lower() == "nested",
        pixels=np.asarray(beam.pixel_array),
        data=data,
        pol=pol,
    )
