"""Absolute references in kelvin units: the Jy->K conversion and the pseudo-Stokes convention.

An abscal (Jy-referenced) ``|g_ref|`` becomes ``|g_ref,K| = |g_ref| sqrt(J)`` with
``J = 2 k_B Omega_A / lambda^2 * 1e26`` Jy per K (:mod:`autocal.compare.beam_area`), halved
under pyuvdata's ``'sum'`` pseudo-Stokes convention (:func:`reference_pol_convention`);
a K-referenced reference (an autocal calh5) is not converted. See
:mod:`autocal.compare.comparison` for the derivation.
"""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from autocal.compare.beam_area import beam_from_config, jy_per_kelvin, pol_solid_angles
from autocal.compare.errors import CompareError

if TYPE_CHECKING:
    from autocal.io.calsol_read import ReferenceGains

logger = logging.getLogger(__name__)

#: Pseudo-Stokes convention assumed when the reference file states none (HERA's).
DEFAULT_POL_CONVENTION = "avg"


@dataclass(frozen=True, eq=False)
class KelvinConversion:
    """How the reference's ``|g|`` is put into the solution's kelvin units.

    Attributes
    ----------
    info
        JSON-ready description (``applied``, formula, beam, ``Omega_A`` and Jy/K at one
        frequency, the pol convention used).
    jy_per_k, omega
        ``(Npol, Nfreq)`` Jy per K and ``Omega_A`` (sr), or ``None`` without a Jy->K
        conversion.
    kfac
        ``(Npol, Nfreq)`` the factor ``|g_ref|^2`` is multiplied by (``J``, ``J / 2``
        under 'sum', 1 for a K reference), or ``None`` in relative mode.
    pol_convention
        The stated and used pseudo-Stokes convention and its source, or ``None``.
    """

    info: dict[str, Any]
    jy_per_k: np.ndarray | None = None
    omega: np.ndarray | None = None
    kfac: np.ndarray | None = None
    pol_convention: dict[str, Any] | None = None

    def apply(self, values: np.ndarray) -> np.ndarray:
        """Return ``(Nant, Npol, Nfreq)`` reference amplitudes (or errors) in kelvin units."""
        if self.jy_per_k is None or self.kfac is None:
            return values
        return values * np.sqrt(self.kfac)[None, :, :]


def reference_pol_convention(reference: ReferenceGains) -> tuple[str | None, str]:
    """Return the pseudo-Stokes convention (pyuvdata ``pol_convention``) a reference states.

    ``reference.meta["pol_convention"]`` when the reader recorded it, else each file in
    ``reference.meta["files"]`` is opened with pyuvdata (metadata only).

    Parameters
    ----------
    reference
        The reference gains.

    Returns
    -------
    convention, note
        ``"sum"``, ``"avg"`` or ``None`` (not stated or not readable), and how it was
        found.
    """
    if "pol_convention" in reference.meta:
        value = reference.meta["pol_convention"]
        return (str(value) if value else None), "recorded by the reference reader"
    files = [Path(f) for f in reference.meta.get("files", [])]
    readable = [f for f in files if f.is_file()]
    if not readable:
        return None, "no reference file to read"
    from pyuvdata import UVCal  # heavy, only to read a reference file's metadata

    found: list[str | None] = []
    for path in readable:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                uvc = UVCal.from_file(str(path), read_data=False, run_check=False)
        except Exception as err:  # a metadata read must never block the comparison
            logger.warning("cannot read pol_convention from %s: %s", path.name, err)
            return None, f"pyuvdata could not read {path.name}"
        found.append(getattr(uvc, "pol_convention", None))
    stated = {v for v in found if v}
    if len(stated) > 1:
        logger.warning("the reference files state different pol_conventions %s", stated)
    if not stated:
        return None, f"not stated in {len(found)} file(s) (pyuvdata UVCal.pol_convention)"
    return str(found[0] or sorted(stated)[0]), "stated in the file (pyuvdata UVCal.pol_convention)"


def convert_reference(
    mode: str,
    reference: ReferenceGains,
    solution_config: dict[str, Any] | None,
    beam: Any,
    pols: list[str],
    freqs: np.ndarray,
    nside: int | None,
    omega: np.ndarray | None,
) -> KelvinConversion:
    """Return the conversion of the reference into kelvin units (procedure step 7).

    Parameters
    ----------
    mode
        ``"absolute"`` or ``"relative"`` (relative: nothing is converted).
    reference
        The reference gains (``gain_scale``: ``"Jy"``, ``"K"`` or unstated = Jy).
    solution_config
        The solution's configuration, for the beam it used when ``beam`` and ``omega``
        are ``None``.
    beam, nside, omega
        See :func:`~autocal.compare.comparison.compare`.
    pols
        Compared polarisations.
    freqs
        ``(Nfreq,)`` the solution's channels (Hz).

    Returns
    -------
    KelvinConversion
        The factors and their description.

    Raises
    ------
    CompareError
        For a gain scale other than Jy or K.
    """
    if mode != "absolute":
        return KelvinConversion(info={"applied": False})
    if not reference.gain_scale:
        logger.warning(
            "the reference states no gain scale; absolute gains are taken to be "
            "Jy-referenced (HERA abscal)"
        )
    scale = (reference.gain_scale or "Jy").strip()
    if scale.lower() in ("k", "kelvin"):
        return KelvinConversion(
            info={"applied": False, "reason": "reference gain_scale is K"},
            kfac=np.ones((len(pols), freqs.size)),
        )
    if scale.lower() != "jy":
        raise CompareError(
            f"reference gain_scale {scale!r} is not understood: absolute gains must be "
            "Jy- or K-referenced (use mode='relative' to compare shapes)"
        )
    if beam is None and omega is None:
        beam = beam_from_config(solution_config)
    om, conversion = pol_solid_angles(beam, pols, freqs, nside, omega)
    jpk = jy_per_kelvin(freqs[None, :], om)
    pol_conv = _pol_convention_used(reference)
    used = pol_conv["used"]
    conversion["pol_convention"] = used
    conversion["pol_convention_source"] = pol_conv["source"]
    if used == "sum":
        conversion["formula"] = (
            "|g_ref,K| = |g_ref,Jy| sqrt(2 k_B Omega_A / lambda^2 * 1e26 / 2) ('sum')"
        )
    kfac = jpk * (0.5 if used == "sum" else 1.0)
    return KelvinConversion(
        info=conversion, jy_per_k=jpk, omega=om, kfac=kfac, pol_convention=pol_conv
    )


def _pol_convention_used(reference: ReferenceGains) -> dict[str, Any]:
    """Return the stated and used pol convention (unstated or unknown: the default)."""
    stated, note = reference_pol_convention(reference)
    if stated not in (None, "sum", "avg"):
        logger.warning("unknown pol_convention %r; assuming 'avg'", stated)
        note = f"unknown value {stated!r}; {DEFAULT_POL_CONVENTION!r} assumed"
        stated = None
    used = stated or DEFAULT_POL_CONVENTION
    return {
        "stated": stated,
        "used": used,
        "source": "file" if stated else "assumed",
        "note": note,
    }
