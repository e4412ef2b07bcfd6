"""An autocal solution as a pyuvdata ``UVCal``: the gains, flags and qualities it holds.

:func:`solution_to_uvcal` builds a genuine ``UVCal`` (``cal_type="gain"``,
``cal_style="sky"``) from an autocal :class:`~autocal.fit.solution.Solution`; the calh5 and
calfits writers (:mod:`autocal.io.calsol_write`) write it:

* autocal fits ``R = G (Tsky + Trxr)`` with ``G = |g|^2`` in raw units per kelvin. The
  gain written is ``g = |g| = sqrt(G)``: real and positive (the phase of an
  auto-correlation is zero, so no phase is determined);
* ``gain_convention = "divide"``: as hera_cal applies gains to visibilities,
  ``V_cal = V_raw / (g_i g_j^*)``, so an auto becomes ``R / |g|^2 = Tsky + Trxr`` in
  kelvin. This is the same convention as the H1C abscal files (whose ``R / |g|^2`` is
  in Jy);
* ``gain_scale = "K str"`` (:data:`GAIN_SCALE`): pyuvdata's ``uvcalibrate`` copies the gain
  scale into ``UVData.vis_units``, whose only allowed values are ``"uncalib"``, ``"Jy"`` and
  ``"K str"``; ``"K str"`` is the one temperature unit among them. The calibrated autos
  ``R / |g|^2 = Tsky + Trxr`` are the beam-averaged antenna temperature in kelvin (NOT
  multiplied by the beam solid angle): multiply by the beam solid angle ``Omega_p(nu)`` (sr)
  for kelvin steradians proper. ``extra_keywords["ACVUNIT"]`` says so in the file;
* ``pol_convention = "avg"`` (:data:`POL_CONVENTION`): each calibrated instrumental
  polarisation carries the full temperature of an unpolarised sky (``ee ~ I``), as the Tsky
  model autocal fits is the beam-weighted (Stokes I) temperature;
* polarisations ``ee``/``nn`` are Jones codes -5/-6 with the x feed pointing east
  (pyuvdata's HERA telescope has exactly these feeds); ``xx``/``yy`` names are written
  with the same codes and, for a non-HERA telescope, the same east-pointing x feed;
* by default (``per_time=True``) the time model ``G(t)`` (Legendre or constant) evaluated at
  every fitted integration: ``time_array`` holds their Julian dates (``Ntimes > 1``, as
  hera_cal's ``HERACal`` and ``smooth_cal`` need) and ``integration_time`` the median
  spacing; with ``per_time=False`` (or a ``time_range``) one time-averaged solution,
  ``Ntimes = 1``, over a ``time_range`` spanning the fitted integrations;
* ``flag_array`` is the solution's channel flags (failed fits, non-positive ``G``);
  flagged gains are written as 1 (never NaN); per time, the integrations flagged whole
  before the fit (RFI in time, ``Solution.time_flags``) are flagged too (their gains are
  the time model's);
* ``quality_array`` holds the total 1-sigma uncertainty of the written gain amplitude
  ``|g|`` (:attr:`autocal.fit.solution.Solution.sigma_abs_g`: statistical, jackknife and drift
  terms, :mod:`autocal.fit.total_uncertainty`; with ``per_time=True`` the statistical error of
  ``|g(t)|`` scaled by the channel's total-to-statistical ratio of the time-averaged
  ``|g|``), 0 where undefined; ``total_quality_array`` the pooled ``sum chi^2 / sum dof``
  over antennas (``chi^2 / dof`` per antenna is in the HDF5 product);
* the telescope is pyuvdata's known HERA telescope (all antennas and positions) when the
  solution's telescope is HERA (or unknown and every antenna number exists in HERA);
  otherwise a minimal telescope at the solution's site with its antennas at zero
  positions;
* ``sky_catalog`` / ``diffuse_model`` describe the Tsky model, ``ref_antenna_name`` is
  ``"none"`` (amplitude-only calibration), the history records autocal's version, the
  model and the inputs. Uncertainties do not fit in a UVCal: they are in the HDF5
  product (:mod:`autocal.io.products`).

"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from pyuvdata import Telescope, UVCal
from pyuvdata import utils as uvutils
from pyuvdata.uvdata.initializers import get_time_params

from autocal import __version__
from autocal.core.sites import HERA, Site, get_site
from autocal.io.calsol_files import CalsolFormatError
from autocal.io.pyuvdata_helpers import warnings_to_log

if TYPE_CHECKING:
    from autocal.fit.solution import Solution

logger = logging.getLogger(__name__)

#: Gain scale written by autocal: pyuvdata's temperature unit (the calibrated autos are
#: beam-averaged antenna temperatures in kelvin; see the module notes).
GAIN_SCALE = "K str"

#: What the calibrated data carry (``extra_keywords["ACVUNIT"]``).
CALIBRATED_UNIT = "K antenna temperature, not times beam solid angle"

#: Polarisation convention written by autocal (``ee ~ I``).
POL_CONVENTION = "avg"

#: Gain convention written by autocal (``V_cal = V_raw / (g_i g_j^*)``).
GAIN_CONVENTION = "divide"


def _warnings_to_log(context: str) -> Any:
    return warnings_to_log(context, logger, logging.DEBUG)


#: Sub-dictionaries of ``Solution.config`` searched after its top level (the pipeline
#: stores ``{"calibration": <settings>, "provenance": <resolved conventions>}``).
CONFIG_SECTIONS = ("provenance", "calibration")


def config_sources(config: dict[str, Any] | None) -> list[dict[str, Any]]:
    """Return ``config`` and its ``provenance``/``calibration`` sections, in lookup order."""
    config = config or {}
    sources = [config]
    sources += [config[k] for k in CONFIG_SECTIONS if isinstance(config.get(k), dict)]
    return sources


def _config_value(config: dict[str, Any], *keys: str) -> Any:
    for source in config_sources(config):
        for key in keys:
            if key in source and source[key] not in (None, ""):
                return source[key]
    return None


def _resolve_site(site: Any, config: dict[str, Any]) -> Any:
    spec = site if site is not None else _config_value(config, "site")
    if spec is None:
        return None
    if isinstance(spec, Site):
        return spec
    if isinstance(spec, dict) and {"lat_deg", "lon_deg"} <= set(spec):
        return Site(
            str(spec.get("name", "site")),
            float(spec["lat_deg"]),
            float(spec["lon_deg"]),
            float(spec.get("alt_m", 0.0)),
        )
    if isinstance(spec, dict) and "name" in spec:
        spec = spec["name"]
    try:
        return get_site(str(spec))
    except ValueError:
        logger.warning("site %r not understood; using HERA's location", spec)
        return HERA


def _telescope_for(solution: Solution, telescope: str | None, site: Any) -> tuple[Any, bool]:
    """Return ``(pyuvdata Telescope, is_known_hera)`` for a solution."""
    config = solution.config or {}
    name = telescope or _config_value(config, "telescope", "telescope_name")
    resolved_site = _resolve_site(site, config)
    ants = [int(a) for a in solution.antennas]
    hera = Telescope.from_known_telescopes("HERA")
    known = set(int(a) for a in hera.antenna_numbers)
    fits_hera = set(ants) <= known
    site_is_hera = resolved_site is None or resolved_site.name.lower() == "hera"
    want_hera = (
        str(name).strip().upper() == "HERA" if name is not None else (site_is_hera and fits_hera)
    )
    if want_hera and fits_hera:
        if not hera.instrument:
            hera.instrument = hera.name
        return hera, True
    if want_hera:
        logger.warning(
            "antenna number(s) %s do not exist in HERA; writing a minimal telescope",
            sorted(set(ants) - known),
        )
    location_site = resolved_site or HERA
    if resolved_site is None:
        logger.warning("the solution records no site; using HERA's location")
    names = list(solution.antenna_names) or [f"ant{a}" for a in ants]
    if name is not None:
        tel_name = str(name)
    else:
        tel_name = resolved_site.name if resolved_site is not None else "unknown"
    with _warnings_to_log("building the telescope"):
        tel = Telescope.new(
            name=tel_name,
            location=location_site.location,
            antenna_positions=np.zeros((len(ants), 3)),
            antenna_names=names,
            antenna_numbers=ants,
            instrument=tel_name,
            mount_type="fixed",
            update_from_known=False,
        )
    return tel, False


def _jones_codes(pols: Sequence[str]) -> tuple[list[int], str | None]:
    names = [str(p).lower() for p in pols]
    compass = [p for p in names if set(p) <= {"e", "n"}]
    if compass and len(compass) != len(names):
        raise CalsolFormatError(f"cannot mix e/n and x/y polarisation names: {names}")
    orient = "east" if compass else None
    try:
        codes = [int(c) for c in np.atleast_1d(uvutils.jstr2num(names, x_orientation=orient))]
    except (KeyError, ValueError) as err:
        raise CalsolFormatError(f"polarisations {names} have no Jones code: {err}") from err
    return codes, orient


def _describe_sky(config: dict[str, Any]) -> str:
    value = _config_value(config, "sky", "model_sky", "sky_model")
    if value is None:
        return "autocal Tsky model (unspecified)"
    if isinstance(value, dict):
        return json.dumps(value, sort_keys=True, default=str)
    return str(value)


def _history(solution: Solution, extra: str) -> str:
    config = solution.config or {}
    lines = [
        f"autocal {__version__}: gains |g| = sqrt(G) fitted to auto-correlations "
        "R = G (Tsky + Trxr) + noise; gain_convention divide, gain_scale 'K str' "
        "(R / |g|^2 is the beam-averaged antenna temperature in kelvin, not multiplied by "
        "the beam solid angle), pol_convention avg; phases are zero.",
        f"autocal model: {json.dumps(solution.model.describe(), sort_keys=True)}",
        f"autocal fitted {len(solution.jds)} integrations, JD "
        f"{float(np.min(solution.jds)):.6f}-{float(np.max(solution.jds)):.6f}"
        if len(solution.jds)
        else "autocal fitted no integrations",
    ]
    for key in ("sky", "model_sky", "beam", "site", "tgnd", "tgnd_K", "cmb", "inputs", "files"):
        value = _config_value(config, key)
        if value is not None:
            lines.append(f"autocal {key}: {json.dumps(value, sort_keys=True, default=str)}")
    lines.append(
        "autocal: uncertainties, covariances and the time model are in the autocal HDF5 "
        "product (autocal.io.products)."
    )
    if extra:
        lines.append(extra.rstrip())
    return "\n".join(lines) + "\n"


def solution_to_uvcal(
    solution: Solution,
    *,
    time_range: tuple[float, float] | None = None,
    per_time: bool | None = None,
    telescope: str | None = None,
    site: Any = None,
    history: str = "",
    shared_times: bool = False,
) -> Any:
    """Build a pyuvdata ``UVCal`` from an autocal solution (see the module notes).

    Parameters
    ----------
    solution
        An :class:`autocal.fit.solution.Solution`.
    time_range
        ``(start, stop)`` JD of a single time-averaged solution (with ``per_time=False``;
        default: the fitted integrations, padded by half the median integration spacing at
        each end).
    per_time
        Write ``G(t)`` of the time model at every fitted integration (``time_array``;
        the default unless a ``time_range`` is given) rather than one time-averaged
        solution over a ``time_range``.
    telescope
        Telescope name (default: ``"telescope"`` in ``solution.config`` or its
        ``provenance``/``calibration`` sections; else HERA when the site is HERA or unknown
        and every antenna exists in HERA; else the site's name).
    site
        Site of a non-HERA telescope: a :class:`~autocal.core.sites.Site`, a name or a
        ``describe()`` dict (default: ``"site"`` in ``solution.config`` or its sections).
    history
        Text appended to the history.
    shared_times
        For a time model constant in time (``constant``), let every integration's gains,
        flags and qualities be read-only views of one integration's (no copies: a
        350-antenna HERA file's 192 integrations would otherwise take 2.7 GB); the
        writers use this. Default: writable arrays.

    Returns
    -------
    pyuvdata.UVCal
        The calibration object (checked).

    Raises
    ------
    CalsolFormatError
        If the solution cannot be represented (no integrations, bad time range,
        polarisations without Jones codes).
    """
    jds = np.asarray(solution.jds, dtype=np.float64)
    if jds.size == 0:
        raise CalsolFormatError("the solution has no fitted integrations (no JDs)")
    freqs = np.asarray(solution.freqs, dtype=np.float64)
    codes, orient = _jones_codes(solution.pols)
    tel, _ = _telescope_for(solution, telescope, site)
    if orient is not None:
        tel.set_feeds_from_x_orientation(orient, feeds=["x", "y"], polarization_array=codes)
    elif tel.feed_array is None:
        tel.set_feeds_from_x_orientation("east", feeds=["x", "y"], polarization_array=codes)

    flags = np.asarray(solution.flags, dtype=bool)  # (A, P, F)
    sigma_amp = np.asarray(solution.sigma_abs_g, dtype=np.float64)  # (A, P, F), total
    total = _pooled_chi2(solution, flags)
    if per_time is None:
        per_time = time_range is None
    if per_time and time_range is not None:
        raise CalsolFormatError("time_range describes one averaged solution: not with per_time")
    if per_time:
        gains = _per_time_gains(solution, jds, flags, sigma_amp, shared_times)
    else:
        gains = _averaged_gains(solution, jds, flags, sigma_amp, time_range)
    ntime_out = gains.gain_array.shape[2]
    data = {
        "gain_array": gains.gain_array,
        "flag_array": gains.flag_array,
        "quality_array": gains.quality_array,
        "total_quality_array": np.ascontiguousarray(
            np.broadcast_to(total.T[:, None, :], (freqs.size, ntime_out, total.shape[0]))
        ).astype(np.float32),
    }
    steps = np.diff(freqs)
    width = np.full(freqs.size, float(np.median(steps)) if steps.size else 1.0)
    config = solution.config or {}
    sky = _describe_sky(config)
    # pyuvdata's UVCal.new evaluates its default arrays eagerly (np.ones of the full shape:
    # 3.3 GB for a 350-antenna HERA file), so it is built for the first integration and
    # then given all of them
    first = {k: v[:, :1] if k == "total_quality_array" else v[:, :, :1] for k, v in data.items()}
    first_times = {k: v[:1] for k, v in gains.times.items()}
    with _warnings_to_log("building UVCal"):
        uvc = UVCal.new(
            cal_style="sky",
            gain_convention=GAIN_CONVENTION,
            jones_array=np.asarray(codes),
            telescope=tel,
            freq_array=freqs,
            channel_width=width,
            ant_array=np.asarray(solution.antennas, dtype=np.int64),
            ref_antenna_name="none",
            sky_catalog=sky,
            data=first,
            history=_history(solution, history),
            gain_scale=GAIN_SCALE,
            **first_times,
        )
        if ntime_out > 1:
            lsts, tint = get_time_params(
                telescope_location=tel.location,
                time_array=gains.times["time_array"],
                integration_time=gains.times["integration_time"],
            )
            uvc.time_array, uvc.lst_array, uvc.integration_time = (
                gains.times["time_array"],
                lsts,
                tint,
            )
            uvc.Ntimes = ntime_out
        for key, value in data.items():
            setattr(uvc, key, value)
        uvc.pol_convention = POL_CONVENTION
        uvc.diffuse_model = sky
        uvc.extra_keywords = {
            "AUTOCAL": True,
            "ACMODEL": str(solution.model.kind),
            "ACORDER": int(solution.model.order),
            "ACGAIN": "|g|=sqrt(G); R/|g|^2 in K",
            "ACVUNIT": CALIBRATED_UNIT,
        }
        uvc.check()
    return uvc


def _pooled_chi2(solution: Solution, flags: np.ndarray) -> np.ndarray:
    """Return ``sum chi^2 / sum dof`` over unflagged antennas, ``(Npol, Nfreq)`` (0: none)."""
    chi2 = np.where(np.isfinite(solution.chi2) & ~flags, solution.chi2, 0.0)
    dof = np.where(~flags, np.asarray(solution.dof, dtype=np.float64), 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(dof.sum(0) > 0, chi2.sum(0) / dof.sum(0), 0.0)  # (P, F)


@dataclass(frozen=True, eq=False)
class _Gains:
    """The arrays of ``UVCal.new`` on pyuvdata's ``(A, F, T, J)`` axes, and its times.

    ``gain_array`` (complex64: |g| to 6e-8, far below any uncertainty, half the memory
    and file of complex128) is ``|g| = sqrt(G)``, 1 where flagged or ``G <= 0``;
    ``quality_array`` (float32) the ``|g|`` error, 0 where undefined; ``times`` the time
    keywords of ``UVCal.new`` (``time_array`` or ``time_range``, and
    ``integration_time``).
    """

    gain_array: np.ndarray
    flag_array: np.ndarray
    quality_array: np.ndarray
    times: dict[str, np.ndarray]


def _one_antenna(
    big_g: np.ndarray, flags: np.ndarray, sigma: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return one antenna's gain, flag and quality arrays ``(F, T, J)``.

    ``big_g`` and ``sigma`` (the ``|g|`` error) are ``(P, T, F)``, ``flags`` ``(P, F)``.
    """
    with np.errstate(invalid="ignore"):
        amp = np.sqrt(big_g)
    bad = flags[:, None, :] | ~np.isfinite(amp) | ~(big_g > 0)
    quality = np.where(bad | ~np.isfinite(sigma), 0.0, sigma)
    to_uvc = (2, 1, 0)  # (P, T, F) -> (F, T, J)
    return (
        np.where(bad, 1.0, amp).transpose(to_uvc).astype(np.complex64),
        bad.transpose(to_uvc),
        quality.transpose(to_uvc).astype(np.float32),
    )


def _per_time_gains(
    solution: Solution,
    jds: np.ndarray,
    flags: np.ndarray,
    sigma_amp: np.ndarray,
    shared_times: bool,
) -> _Gains:
    """Return ``G(t)`` of the time model at every fitted integration (``per_time=True``).

    Evaluated antenna by antenna into the output arrays, so no ``(A, P, T, F)`` float64
    intermediate is made (a 350-antenna HERA file's took 21 GB); the ``|g|`` error is the
    statistical error of ``G(t)`` scaled by the channel's total-to-statistical ratio.
    """
    ntime = jds.size
    if ntime > 1 and np.any(np.diff(jds) <= 0):
        raise CalsolFormatError("per_time needs strictly increasing JDs")
    steps = np.diff(jds)
    tint = np.full(ntime, np.median(steps) * 86400.0 if steps.size else 1.0)
    times = {"time_array": jds, "integration_time": tint}
    nb = solution.model.nbasis
    basis = solution.model.basis(solution.lsts)  # (K, T)
    constant = nb == 1 and bool(np.all(basis == basis[:, :1]))
    if constant and shared_times:
        basis = basis[:, :1]
    coeffs, cov = solution.coeffs, solution.cov
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = sigma_amp / np.asarray(solution.sigma_abs_g_stat, dtype=np.float64)
    nant, npol, nfreq = flags.shape
    shape = (nant, nfreq, basis.shape[1], npol)
    gain = np.empty(shape, np.complex64)
    flag = np.empty(shape, bool)
    quality = np.empty(shape, np.float32)
    for a in range(nant):
        big_g = np.einsum("kt,pfk->ptf", basis, coeffs[a, ..., :nb])
        var_g = np.einsum("kt,pfkl,lt->ptf", basis, cov[a, ..., :nb, :nb], basis)
        with np.errstate(invalid="ignore", divide="ignore"):
            sigma = np.sqrt(var_g) / (2 * np.sqrt(big_g)) * ratio[a, :, None, :]
        gain[a], flag[a], quality[a] = _one_antenna(big_g, flags[a], sigma)
    if basis.shape[1] != ntime:  # one integration's arrays, shared by all (read-only)
        full = (nant, nfreq, ntime, npol)
        gain, flag, quality = (np.broadcast_to(x, full) for x in (gain, flag, quality))
    if solution.time_flags is not None and solution.time_flags.any():
        # integrations flagged whole before the fit: flagged at their times (the gain
        # there is the time model's, still valid)
        flag = flag | np.asarray(solution.time_flags).transpose(0, 2, 1)[:, None, :, :]
    return _Gains(gain, flag, quality, times)


def _averaged_gains(
    solution: Solution,
    jds: np.ndarray,
    flags: np.ndarray,
    sigma_amp: np.ndarray,
    time_range: tuple[float, float] | None,
) -> _Gains:
    """Return the time-averaged ``G`` as one solution over ``time_range`` (default: the data's)."""
    if time_range is None:
        pad = 0.5 * float(np.median(np.diff(np.sort(jds)))) if jds.size > 1 else 0.5 / 86400
        start, stop = float(jds.min()) - pad, float(jds.max()) + pad
    else:
        start, stop = (float(t) for t in time_range)
    if not (np.isfinite(start) and np.isfinite(stop) and stop > start):
        raise CalsolFormatError(
            f"time_range ({start}, {stop}) must be finite and increasing (Julian dates)"
        )
    if jds.min() < start - 1e-9 or jds.max() > stop + 1e-9:
        logger.warning(
            "time_range %.6f-%.6f does not cover the fitted JDs %.6f-%.6f",
            start,
            stop,
            jds.min(),
            jds.max(),
        )
    times = {
        "time_range": np.array([[start, stop]]),
        "integration_time": np.array([(stop - start) * 86400.0]),
    }
    big_g = np.asarray(solution.G, dtype=np.float64)
    parts = [
        _one_antenna(big_g[a][:, None, :], flags[a], sigma_amp[a][:, None, :])
        for a in range(big_g.shape[0])
    ]
    gain, flag, quality = (np.stack(x) for x in zip(*parts, strict=True))
    return _Gains(gain, flag, quality, times)
