r"""Beam solid angles and the jansky-to-kelvin conversion of absolute reference gains.

An auto-correlation in Jy is ``V_Jy = 2 k_B Tsky Omega_A / lambda^2 * 1e26`` for a
peak-normalised power beam whose solid angle ``Omega_A = \oint A / A_peak d\Omega`` is
integrated over the whole sphere (see :mod:`autocal.compare.comparison` for the
derivation). This module computes ``Omega_A`` from autocal's beams on a HEALPix grid
(:func:`beam_solid_angle`), cross-checks it with pyuvdata's ``UVBeam.get_beam_area``
(:func:`uvbeam_solid_angle`), reads hera_sim's H1C beam integrals for the systematics
budget (:func:`hera_sim_omega`) and turns ``Omega_A`` into Jy per K
(:func:`jy_per_kelvin`).
"""

from __future__ import annotations

import logging
import warnings
from pathlib import Path
from typing import Any

import healpy as hp
import numpy as np
from scipy.interpolate import CubicSpline

from autocal.compare.errors import CompareError
from autocal.io.calsol_uvcal import config_sources
from autocal.io.datasets import HERA_BEAM_FILE, data_file
from autocal.sky.beam_base import Beam
from autocal.sky.beam_names import get_beam
from autocal.sky.file_beams import HealpixFileBeam

logger = logging.getLogger(__name__)

#: Boltzmann constant, J/K.
K_B = 1.380649e-23
#: Speed of light, m/s.
C_LIGHT = 299792458.0
#: One jansky in W m^-2 Hz^-1.
JANSKY = 1e-26
#: Default HEALPix resolution for beams that are not HEALPix files.
DEFAULT_NSIDE = 128
#: hera_sim's H1C beam integrals (``freqs`` in GHz, ``omega_p`` in sr), data-folder path.
HERA_SIM_BEAM_INTEGRALS = "hera/instrument/HERA_H1C_BEAM_INTEGRALS.npz"
#: Frequency (Hz) at which single values of ``Omega_A`` and ``J`` are reported.
REPORT_FREQ_HZ = 150e6


def jy_per_kelvin(freqs: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """Return ``J = 2 k_B Omega_A / lambda^2 * 1e26``: Jy of an auto per K of antenna temperature.

    Parameters
    ----------
    freqs
        Hz.
    omega
        Beam solid angle ``Omega_A`` (sr) of the peak-normalised power beam, same shape.

    Returns
    -------
    numpy.ndarray
        Jy per K.
    """
    lam = C_LIGHT / np.asarray(freqs, dtype=np.float64)
    return 2.0 * K_B * np.asarray(omega, dtype=np.float64) / lam**2 / JANSKY


def beam_pol(pol: str) -> str:
    """Return the beam polarisation (``"ee"``/``"nn"``) for a polarisation name (x feed east)."""
    pol = pol.lower()
    alias = {"xx": "ee", "yy": "nn"}
    if pol in alias:
        logger.info("using the %s beam for polarisation %s (x feed east)", alias[pol], pol)
    return alias.get(pol, pol)


def resolve_beam(beam: Any, pol: str = "ee") -> Any:
    """Resolve a beam for solid-angle integrals.

    ``"hera"`` and UVBeam file paths give a
    :class:`~autocal.sky.file_beams.HealpixFileBeam` at the file's own resolution (no harmonic
    upsampling, whose ringing would bias the peak); other specifications go through
    :func:`autocal.sky.beam_names.get_beam`.
    """
    pol = beam_pol(pol)
    if isinstance(beam, Beam):
        return beam
    spec = str(beam).strip()
    if spec.lower() == "hera":
        return HealpixFileBeam(data_file(HERA_BEAM_FILE, "HERA Fagnoni beam"), pol, 0)
    path = Path(spec).expanduser()
    if path.suffix.lower() in {".beamfits", ".fits", ".h5", ".uvbeam"}:
        return HealpixFileBeam(path, pol, 0)
    return get_beam(spec, pol)


def beam_from_config(config: dict[str, Any] | None) -> str:
    """Return the beam specification a solution's configuration records, else ``"hera"``.

    Looks for ``beam`` at the top level and in the ``provenance``/``calibration``
    sections: a name or path string, or a beam description (``{"file": ...}``,
    ``{"beam": "gaussian_dipole" | "airy"}``).
    """
    for source in config_sources(config):
        value = source.get("beam")
        if isinstance(value, str) and value.strip():
            return value.strip()
        if isinstance(value, dict):
            if value.get("file"):
                return str(value["file"])
            kind = {"gaussian_dipole": "dipole", "airy": "airy"}.get(str(value.get("beam")))
            if kind:
                return kind
    logger.warning("the solution records no usable beam; using the HERA beam for Omega_A")
    return "hera"


def beam_solid_angle(
    beam: Any, freqs: np.ndarray, *, pol: str = "ee", nside: int | None = None
) -> np.ndarray:
    """Return ``Omega_A(nu)``, the peak-normalised beam integrated over the whole sphere.

    The beam is evaluated at the centres of a RING HEALPix grid (plus the zenith, for the
    peak) and summed times the pixel area.

    Parameters
    ----------
    beam
        A :class:`~autocal.sky.beam_base.Beam` or a specification for :func:`resolve_beam`.
    freqs
        Hz.
    pol
        ``"ee"`` or ``"nn"``.
    nside
        HEALPix resolution (default: a HEALPix file beam's own, else 128).

    Returns
    -------
    numpy.ndarray
        ``(Nfreq,)`` steradians.
    """
    b = resolve_beam(beam, pol)
    freqs = np.atleast_1d(np.asarray(freqs, dtype=np.float64))
    if nside is None:
        nside = b.data.nside if isinstance(b, HealpixFileBeam) else DEFAULT_NSIDE
    npix = hp.nside2npix(nside)
    theta, phi = hp.pix2ang(nside, np.arange(npix))
    az = np.mod(np.pi / 2 - phi, 2 * np.pi)  # pixel phi: azimuth east through north
    za = np.append(theta, 0.0)
    az = np.append(az, 0.0)
    evaluate = b.on(az, za)
    out = np.empty(freqs.size)
    chunk = max(1, int(4e6 // npix))
    for start in range(0, freqs.size, chunk):
        power = np.asarray(evaluate(freqs[start : start + chunk]), dtype=np.float64)
        peak = power.max(axis=1)
        if np.any(~(peak > 0)):
            raise CompareError(f"the beam {b.name} is not positive anywhere at some frequency")
        out[start : start + chunk] = power[:, :-1].sum(axis=1) * hp.nside2pixarea(nside) / peak
    return out


def uvbeam_solid_angle(path: str | Path, freqs: np.ndarray, pol: str = "ee") -> np.ndarray:
    """``Omega_A`` from pyuvdata's ``UVBeam.get_beam_area`` (peak-normalised), cubic in frequency.

    Parameters
    ----------
    path
        A power-beam file pyuvdata reads (e.g. the HERA beamfits).
    freqs
        Hz, inside the file's frequency range.
    pol
        ``"ee"`` or ``"nn"``.

    Returns
    -------
    numpy.ndarray
        ``(Nfreq,)`` steradians.
    """
    from pyuvdata import UVBeam  # heavy, only for this cross-check of a beam file

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        uvb = UVBeam.from_file(str(path))
        if uvb.data_normalization != "peak":
            uvb.peak_normalize()
        area = np.real(uvb.get_beam_area(beam_pol(pol)))
    native = np.asarray(uvb.freq_array, dtype=np.float64).ravel()
    freqs = np.asarray(freqs, dtype=np.float64)
    if freqs.min() < native.min() - 1 or freqs.max() > native.max() + 1:
        raise CompareError(
            f"frequencies {freqs.min() / 1e6:.3f}-{freqs.max() / 1e6:.3f} MHz are outside "
            f"the beam file's {native.min() / 1e6:.3f}-{native.max() / 1e6:.3f} MHz"
        )
    return CubicSpline(native, area)(freqs)


def hera_sim_omega(freqs: np.ndarray, path: str | Path | None = None) -> np.ndarray:
    """hera_sim's H1C beam solid angle ``omega_p`` interpolated onto ``freqs``.

    Parameters
    ----------
    freqs
        Hz.
    path
        The ``HERA_H1C_BEAM_INTEGRALS.npz`` file (default: :data:`HERA_SIM_BEAM_INTEGRALS`
        in the data folder). Its ``freqs`` are in GHz (MHz or Hz are recognised by size),
        ``omega_p`` in sr, one curve for both feeds.

    Returns
    -------
    numpy.ndarray
        sr, NaN outside the table's frequency range.
    """
    if path is None:
        path = data_file(HERA_SIM_BEAM_INTEGRALS, "hera_sim H1C beam integrals")
    with np.load(path) as table:
        if "freqs" not in table or "omega_p" not in table:
            raise CompareError(f"{path} has keys {table.files}; 'freqs' and 'omega_p' needed")
        nu = np.asarray(table["freqs"], dtype=np.float64)
        om = np.asarray(table["omega_p"], dtype=np.float64)
    scale = 1e9 if nu.max() < 10 else (1e6 if nu.max() < 1e4 else 1.0)
    nu = nu * scale
    freqs = np.asarray(freqs, dtype=np.float64)
    inside = (freqs >= nu.min()) & (freqs <= nu.max())
    return np.where(inside, np.interp(freqs, nu, om), np.nan)


def pol_solid_angles(
    beam: Any, pols: list[str], freqs: np.ndarray, nside: int | None, omega: np.ndarray | None
) -> tuple[np.ndarray, dict[str, Any]]:
    """Return ``Omega_A`` per polarisation and a description of the Jy->K conversion.

    Parameters
    ----------
    beam
        Beam specification for :func:`resolve_beam` (ignored when ``omega`` is given).
    pols
        Polarisation names.
    freqs
        ``(Nfreq,)`` Hz.
    nside
        HEALPix resolution (see :func:`beam_solid_angle`).
    omega
        Precomputed ``Omega_A`` in sr, ``(Npol, Nfreq)`` or ``(Nfreq,)``, or ``None``.

    Returns
    -------
    omega, info
        ``(Npol, Nfreq)`` sr and a JSON-ready description: source, beam, the UVBeam
        cross-check for beam files, ``Omega_A`` and Jy/K at :func:`report_channel`.
    """
    info: dict[str, Any] = {
        "applied": True,
        "formula": "|g_ref,K| = |g_ref,Jy| sqrt(2 k_B Omega_A / lambda^2 * 1e26)",
    }
    if omega is not None:
        om = np.broadcast_to(np.asarray(omega, dtype=np.float64), (len(pols), freqs.size)).copy()
        info["omega_source"] = "given"
    else:
        rows = []
        checks = []
        for pol in pols:
            b = resolve_beam(beam, pol)
            row = beam_solid_angle(b, freqs, pol=pol, nside=nside)
            rows.append(row)
            info.setdefault("beam", b.describe())
            if isinstance(b, HealpixFileBeam):
                try:
                    alt = uvbeam_solid_angle(b.path, freqs, pol)
                    checks.append(float(np.max(np.abs(row / alt - 1.0))))
                except Exception as err:  # the cross-check must never block the comparison
                    logger.warning("UVBeam cross-check of Omega_A failed: %s", err)
        om = np.array(rows)
        info["omega_source"] = "autocal beam on a HEALPix grid (whole sphere, peak-normalised)"
        if checks:
            info["uvbeam_get_beam_area_max_rel_diff"] = max(checks)
    k = report_channel(freqs)
    info["at_freq_Hz"] = float(freqs[k])
    info["omega_sr"] = {p: float(om[i, k]) for i, p in enumerate(pols)}
    info["jy_per_K"] = {p: float(jy_per_kelvin(freqs[k], om[i, k])) for i, p in enumerate(pols)}
    return om, info


def report_channel(freqs: np.ndarray) -> int:
    """Return the channel nearest :data:`REPORT_FREQ_HZ`, else nearest the median frequency."""
    ref_f = (
        REPORT_FREQ_HZ if freqs.min() <= REPORT_FREQ_HZ <= freqs.max() else float(np.median(freqs))
    )
    return int(np.argmin(np.abs(freqs - ref_f)))
