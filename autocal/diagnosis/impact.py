"""How much an effect matters for the calibration products: impact and negligibility.

:func:`product_impact` measures how ``G`` and ``Trxr`` move between two models, against the
total 1-sigma of the ordinary calibration (:func:`product_sigmas`); :func:`is_negligible`
says when that is too small to matter: the effect is then reported "detected, negligible".
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from typing import Any

import numpy as np

from autocal.core.observation import Observation
from autocal.diagnosis.chunks import antenna_chunks
from autocal.diagnosis.effects import SkyTemplates
from autocal.diagnosis.extended_fit import ExtendedFit
from autocal.fit.passes import fit

logger = logging.getLogger(__name__)

#: An effect is negligible when it moves ``G`` and ``Trxr`` by less than this many total
#: sigma in the median channel ...
NEGLIGIBLE_MEDIAN_SIGMA = 0.1
#: ... and by less than this many in every channel.
NEGLIGIBLE_MAX_SIGMA = 1.0


#: ... or, whatever the errors, when the median channel's ``G`` moves by less than this
#: fraction and its ``Trxr`` by less than :data:`NEGLIGIBLE_TRXR_K`: below what the sky model
#: supports (autocal's Tsky and an independent forward model agree to 1e-4 to 1e-3,
#: ``tests/test_independent_sim.py``; a long clean observation has statistical errors
#: smaller than that).
NEGLIGIBLE_G_FRACTION = 1e-3
#: See :data:`NEGLIGIBLE_G_FRACTION` (kelvin).
NEGLIGIBLE_TRXR_K = 1.0


#: An effect whose Delta chi^2 exceeds this share of the data count (it removes more than
#: a tenth of the noise variance per sample) is a substantial feature of the data and never
#: "negligible", however little it moves the products (a clock 87 s off over a day takes
#: chi^2/dof from 8.5 to 1.0 and moves G by 6e-4 total sigma).
NEGLIGIBLE_MAX_CHI2_SHARE = 0.1


#: Relative rms of the data below which a fitted effect's signal cannot be told from the
#: forward model's own error, for a beam evaluated analytically (and any beam not measured,
#: the lower floor putting less down to the model): autocal's Tsky and an independent
#: forward model (``tests/independent_sim.py``: GSM2008 at nside 32 per pixel, astropy
#: AltAz, its own beams, a hard horizon) differ by 6.4e-5 (ee) and 4.4e-5 (nn) of the data
#: rms over a clean dipole day (a 150 K receiver) once the per-channel ``G`` and ``n`` are
#: fitted, smooth in time and much of it common to all channels, i.e. gain-like
#: (``tests/diagnosis/test_model_accuracy.py`` measures it). An effect whose Delta chi^2
#: corresponds to less than the floor of its beam (:func:`forward_model_accuracy`,
#: :func:`signal_rms`) is reported "below the forward model's accuracy" rather than
#: "detected".
FORWARD_MODEL_ACCURACY = 1e-4
#: The floor for beams whose forward model was measured to be coarser, by their kind
#: (``Beam.describe()["beam"]``). A HEALPix beam file (``uvbeam_healpix``: HERA's Fagnoni
#: beamfits, nside 32 maps at 26 frequencies 4 MHz apart) is interpolated in angle and
#: frequency, and two reasonable evaluations of the same file (autocal's, and the
#: independent simulator's band-limited resampling with a cubic spline in frequency) give
#: Tsky that differ by 4.9e-4 (ee) and 5.0e-4 (nn) of the data rms over a clean day after
#: the same fit (the same test), eight times the dipole's: the two comparisons differ only
#: in the beam. The floor is 1.4x the measured difference, as 1e-4 is 1.6x the dipole's.
FORWARD_MODEL_ACCURACY_BY_BEAM: dict[str, float] = {"uvbeam_healpix": 7e-4}


def forward_model_accuracy(beam: Mapping[str, Any] | None) -> float:
    """Return the forward model's accuracy (relative data rms) for a model beam.

    Parameters
    ----------
    beam
        The beam's description (``Beam.describe()``, as in the Tsky's ``meta["beam"]``),
        or ``None``. A beam made from another (perturbed, widened) is judged by its
        ``base``.

    Returns
    -------
    float
        :data:`FORWARD_MODEL_ACCURACY_BY_BEAM` of its kind, else
        :data:`FORWARD_MODEL_ACCURACY`.
    """
    while isinstance(beam, Mapping):
        kind = str(beam.get("beam"))
        if kind in FORWARD_MODEL_ACCURACY_BY_BEAM:
            return FORWARD_MODEL_ACCURACY_BY_BEAM[kind]
        beam = beam.get("base")
    return FORWARD_MODEL_ACCURACY


#: The entries seen through the data's structure in time and frequency, to which
#: :func:`forward_model_accuracy` applies. The time-constant Tsky entries (``sky_offset``,
#: ``sky_scale``, ``sky_spectral_index``, ``ground_temperature``, ``missing_cmb``) are seen
#: through the receiver prior, and ``cable_reflection`` in the bandpass: not these; nor the
#: per-antenna entries, whose signal :func:`signal_rms` would dilute over every antenna-pol
#: while the forward model's error, common to all of them, cannot explain one antenna's
#: departure.
DATA_STRUCTURE_EFFECTS = frozenset(
    {"gain_drift", "gain_jitter", "noise_drift", "beam_width", "timing_offset"}
)


def signal_rms(delta_chi2: float, radiometer_total: float) -> float:
    """Return the rms, relative to the data, of the signal behind a radiometer Delta chi^2.

    With weights ``dnu dt N / D^2``, a model change ``s`` costs ``sum dnu dt N (s / D)^2``;
    over usable samples whose ``dnu dt N`` add up to ``radiometer_total`` the rms of ``s /
    D`` is ``sqrt(Delta chi^2 / radiometer_total)``.
    """
    if not radiometer_total > 0:
        return float("nan")
    return math.sqrt(max(float(delta_chi2), 0.0) / radiometer_total)


def is_negligible(impact: dict[str, Any], chi2_share: float = 0.0) -> bool:
    """Return whether a :func:`product_impact` is too small to matter for the products.

    Negligible: below :data:`NEGLIGIBLE_MEDIAN_SIGMA` total sigma in the median channel and
    :data:`NEGLIGIBLE_MAX_SIGMA` in every channel, for both ``G`` and ``Trxr``; or a median
    absolute change below :data:`NEGLIGIBLE_G_FRACTION` of ``G`` and
    :data:`NEGLIGIBLE_TRXR_K` in ``Trxr`` (below what the sky model itself supports) and
    no channel moving by ten times that. In both cases the products' variation in time
    must also stay put (``G_time``, ``Trxr_time``: a drift or jitter changing ``G(t)`` by
    more than :data:`NEGLIGIBLE_G_FRACTION` rms or ten times that at any integration, or
    ``Trxr(t)`` by :data:`NEGLIGIBLE_TRXR_K` in the median channel, matters to whoever
    applies the gains per integration, however well the time-mean products agree). Never
    negligible when fewer than half of the channels could be compared (the ordinary
    calibration failed in the rest). Never negligible either when the effect's
    ``chi2_share`` (its Delta chi^2 over the number of data) exceeds
    :data:`NEGLIGIBLE_MAX_CHI2_SHARE`.
    """
    if chi2_share > NEGLIGIBLE_MAX_CHI2_SHARE:
        return False
    g, t = impact.get("G", {}), impact.get("Trxr", {})
    if "median_change_over_sigma" not in g or "median_change_over_sigma" not in t:
        return False
    if any(e["channels"] < 0.5 * e.get("of", e["channels"]) for e in (g, t)):
        return False  # the yardstick calibration failed in most channels: no verdict
    small = (
        g.get("median_abs_relative_change", np.inf) < NEGLIGIBLE_G_FRACTION
        and t.get("median_abs_change_K", np.inf) < NEGLIGIBLE_TRXR_K
        and g.get("max_abs_relative_change", np.inf) < 10 * NEGLIGIBLE_G_FRACTION
        and t.get("max_abs_change_K", np.inf) < 10 * NEGLIGIBLE_TRXR_K
    )
    within = all(
        e["median_change_over_sigma"] < NEGLIGIBLE_MEDIAN_SIGMA
        and e["max_change_over_sigma"] < NEGLIGIBLE_MAX_SIGMA
        for e in (g, t)
    )
    gt, tt = impact.get("G_time", {}), impact.get("Trxr_time", {})
    steady = (
        gt.get("rms_relative_change", 0.0) < NEGLIGIBLE_G_FRACTION
        and gt.get("max_abs_relative_change", 0.0) < 10 * NEGLIGIBLE_G_FRACTION
        and tt.get("median_max_abs_change_K", 0.0) < NEGLIGIBLE_TRXR_K
        and tt.get("max_abs_change_K", 0.0) < 10 * NEGLIGIBLE_TRXR_K
    )
    return bool((small or within) and steady)


#: Samples of one ordinary calibration in :func:`product_sigmas` (~0.5 GB of working arrays).
PRODUCT_SIGMA_SAMPLES = 1 << 23


def product_sigmas(
    obs: Observation, tpl: SkyTemplates, prior: tuple[Any, Any] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Return the total 1-sigma of ``G`` and ``Trxr`` of the ordinary calibration.

    The constant-model fit of :func:`autocal.fit.passes.fit` against the model Tsky, with
    radiometer weights, errors inflated by ``max(1, chi^2/dof)``, the total uncertainty
    (:mod:`autocal.fit.total_uncertainty`) and the diagnosis's receiver prior ``(trxr, sigma)`` if
    any: the yardstick of :func:`product_impact`. Every channel is fitted on its own, so a
    large observation is fitted :data:`PRODUCT_SIGMA_SAMPLES` at a time (the fit holds a
    few float64 copies of what it is given).
    """
    per_antenna = math.prod(obs.shape[1:])
    chunks = antenna_chunks(obs.shape, max(1, PRODUCT_SIGMA_SAMPLES // per_antenna))
    if len(chunks) == 1:
        sol = fit(obs, tpl.total, scale_covariance="inflate", trxr_prior=prior)
        return sol.sigma_G, sol.sigma_Trxr
    shape3 = (obs.nant, len(obs.pols), obs.nfreq)
    sigma_g, sigma_t = np.empty(shape3), np.empty(shape3)
    unsolved = 0
    with _one_warning_for_unsolved_channels():  # not one per chunk (25 per whole HERA file)
        for sl in chunks:
            part = obs.select(antennas=[int(a) for a in obs.antennas[sl]])
            part_prior = (
                None
                if prior is None
                else tuple(np.broadcast_to(np.asarray(v, float), shape3)[sl] for v in prior)
            )
            sol = fit(part, tpl.total, scale_covariance="inflate", trxr_prior=part_prior)
            sigma_g[sl], sigma_t[sl] = sol.sigma_G, sol.sigma_Trxr
            unsolved += int(np.sum(sol.flag_reason != 0))
    if unsolved:
        logger.info(
            "the yardstick calibration left %d of %d channels unsolved (flagged or too few "
            "samples): no product impact is measured there",
            unsolved,
            math.prod(shape3),
        )
    return sigma_g, sigma_t


@contextmanager
def _one_warning_for_unsolved_channels() -> Iterator[None]:
    """Drop :mod:`autocal.fit.passes`' per-fit warning of unsolved channels for a while."""
    passes_logger = logging.getLogger("autocal.fit.passes")

    def keep(record: logging.LogRecord) -> bool:
        return "could not be solved" not in record.getMessage()

    passes_logger.addFilter(keep)
    try:
        yield
    finally:
        passes_logger.removeFilter(keep)


def product_impact(
    before: ExtendedFit,
    after: ExtendedFit,
    sigma_g: np.ndarray,
    sigma_t: np.ndarray,
    *,
    after_feed_factors: np.ndarray | None = None,
) -> dict[str, Any]:
    """Return how ``G`` and ``Trxr`` move between two models, against the total errors.

    Parameters
    ----------
    before, after
        Fits without and with the effect(s).
    sigma_g, sigma_t
        ``(Nant, Npol, Nfreq)`` total 1-sigma of ``G`` and ``Trxr`` (:func:`product_sigmas`).
    after_feed_factors
        ``(Nant, Npol, Ntime)`` each antenna-pol's own gain factors on top of ``after``'s
        shared one (accepted per-antenna gains, divided out of the data ``after`` was
        fitted to), or ``None``.

    Returns
    -------
    dict
        For ``G`` and ``Trxr``: the median and largest ``|change| / sigma`` over channels,
        the median change (relative for ``G``, kelvin for ``Trxr``) and the channels
        compared (time means: a jitter's ``G`` is its reference integration's);
        ``significant`` when the median change exceeds one total sigma. ``G_time``: the rms
        and largest change of ``G(t) / <G>`` (achromatic; with ``after_feed_factors``
        over every antenna-pol's ``G(t)``); ``Trxr_time``: the largest change over time of
        ``Trxr(t) - <Trxr>`` in kelvin, median channel and worst.
    """
    out: dict[str, Any] = {}
    gs_b, ns_b = _time_shapes(before)
    gs_a, ns_a = _time_shapes(after)
    gain_a = _mean_factor(after.gain_factor)
    if after_feed_factors is not None:
        # every antenna-pol's G(t): the shared factor times its own
        shared = np.ones(1) if after.gain_factor is None else np.asarray(after.gain_factor)
        per_feed = np.asarray(after_feed_factors, float) * shared
        gain_a = np.mean(per_feed, axis=-1)[..., None]  # (A, P, 1) against G's (A, P, F)
        gs_a = per_feed / np.mean(per_feed, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        # the time-mean products (a jitter's G is that of its reference integration)
        g_b, g_a = (
            before.G * _mean_factor(before.gain_factor),
            after.G * gain_a,
        )
        t_b, t_a = (
            before.Trxr * _mean_factor(before.noise_factor),
            after.Trxr * _mean_factor(after.noise_factor),
        )
        pairs = {
            "G": (g_a - g_b, sigma_g, (g_a - g_b) / np.abs(g_b)),
            "Trxr": (t_a - t_b, sigma_t, t_a - t_b),
        }
        for name, (diff, sig, change) in pairs.items():
            z = np.abs(diff) / sig
            ok = np.isfinite(z) & np.isfinite(change)
            entry: dict[str, Any] = {"channels": int(ok.sum()), "of": int(z.size)}
            if ok.any():
                entry["median_change_over_sigma"] = float(np.median(z[ok]))
                entry["max_change_over_sigma"] = float(np.max(z[ok]))
                key = "median_relative_change" if name == "G" else "median_change_K"
                entry[key] = float(np.median(change[ok]))
                entry[key.replace("median_", "median_abs_")] = float(np.median(np.abs(change[ok])))
                entry[key.replace("median_", "max_abs_")] = float(np.max(np.abs(change[ok])))
            out[name] = entry
        # how the products' variation in time changes (drifts, jitter): G's relative
        # shape is achromatic; Trxr's in kelvin per channel
        dshape = gs_a - gs_b
        out["G_time"] = {
            "rms_relative_change": float(np.sqrt(np.mean(dshape**2))),
            "max_abs_relative_change": float(np.max(np.abs(dshape))),
        }
        # the largest change over time, one integration at a time (a whole HERA file's
        # (A, P, F, T) temporaries would be 1.6 GB each)
        ua, vb = np.broadcast_arrays(ns_a - 1.0, ns_b - 1.0)
        dtrx = np.zeros(np.shape(t_a))
        for u, v in zip(np.atleast_1d(ua), np.atleast_1d(vb), strict=True):
            np.fmax(dtrx, np.abs(t_a * u - t_b * v), out=dtrx)
        dtrx = np.where(np.isfinite(t_a) & np.isfinite(t_b), dtrx, np.nan)
        ok = np.isfinite(dtrx)
        out["Trxr_time"] = (
            {
                "median_max_abs_change_K": float(np.median(dtrx[ok])),
                "max_abs_change_K": float(np.max(dtrx[ok])),
            }
            if ok.any()
            else {}
        )
    medians = [e.get("median_change_over_sigma", 0.0) for e in (out["G"], out["Trxr"])]
    out["significant"] = bool(max(medians) > 1.0)
    return out


def _mean_factor(factor: np.ndarray | None) -> float:
    """Time mean of a fit's gain or noise factor (1 without one)."""
    return 1.0 if factor is None else float(np.mean(factor))


def _time_shapes(model: ExtendedFit) -> tuple[np.ndarray, np.ndarray]:
    """``(Ntime,)`` gain and noise factors relative to their time means."""
    shapes = []
    for factor in (model.gain_factor, model.noise_factor):
        f = np.ones(1) if factor is None else np.asarray(factor, float)
        shapes.append(f / np.mean(f))
    return shapes[0], shapes[1]
