"""Candidate physical effects for the discrepancy workflow (DESIGN.md section 5).

Each effect is a parameterised extension of the forward model

    R(t, nu) = G(nu) [1 + sum_k d_k P_k(s)] {Tsky(t, nu) + sum_j D_j(t, nu; p_j)
               + Trxr(nu) [1 + sum_k e_k P_k(s)]}   (n = G Trxr)

with per-channel ``(G, n)`` (profiled out) and a few *global* parameters shared by all
channels, antennas and polarisations. The entries a search tries are listed by
:func:`autocal.diagnosis.catalogue.catalogue`. ``P_k`` are Legendre polynomials of ``s``,
the LST mapped onto ``[-1, 1]`` (:class:`autocal.fit.model.FitModel`).

Identifiability (constant per-channel ``G`` and ``n``):

- A Tsky change constant in time (``sky_offset``, ``ground_temperature``, ``missing_cmb``)
  is absorbed exactly by ``n`` (``Trxr``): the data chi-square cannot see it. It is seen
  only through a *receiver prior* (a known ``Trxr(nu)`` with an uncertainty), which turns
  the shift of the implied ``Trxr`` into chi-square.
- A per-channel scale of the sky part ``S`` (``sky_scale``, ``sky_spectral_index``) is
  absorbed by ``G`` plus an offset ``-s C`` (``C`` the time-constant CMB + ground part),
  absorbed by ``n``: ``(1+s) S + C = (1+s)(S + C) - s C``. Also only seen with a receiver
  prior (then through ``Trxr -> (Trxr - s C) / (1 + s)``).
- ``gain_drift``, ``noise_drift`` (achromatic, relative Legendre drifts) and
  ``beam_width`` have time x frequency structure that ``(G, n)`` cannot absorb and are
  identifiable from the data alone.
- ``cable_reflection`` (a bandpass ripple) is absorbed exactly by the per-channel ``G``;
  it is detected in the bandpass domain, on the fitted ``G(nu)``, against a smooth
  bandpass (see :func:`autocal.diagnosis.bandpass.fit_cable_reflection`).

The diagnosis measures identifiability numerically (the fraction of each template's
Fisher information left after projecting out ``(G, n)``) and skips effects below a
threshold, so none is ever "found" through round-off.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np
from numpy.polynomial import legendre

from autocal.errors import AutocalError
from autocal.fit.model import FitModel, unwrap_lsts
from autocal.sky.beam_base import Beam, BeamEvaluator
from autocal.sky.beam_names import get_beam
from autocal.sky.models import T_CMB, TiltedSky, get_sky
from autocal.tsky.compute import compute_tsky

logger = logging.getLogger(__name__)

#: Sidereal seconds per solar second (LST advances this much faster than UTC).
SIDEREAL_RATE = 1.002737909

#: The catalogue's identifiers.
EFFECT_NAMES = (
    "gain_drift",
    "gain_jitter",
    "noise_drift",
    "sky_scale",
    "sky_offset",
    "sky_spectral_index",
    "ground_temperature",
    "beam_width",
    "missing_cmb",
    "cable_reflection",
    "timing_offset",
    "antenna_gain_jitter",
    "antenna_gain_drift",
)
#: Shortest LST span (hours) for which the diurnal drift variants are candidates.
DIURNAL_MIN_SPAN_H = 6.0
#: Step (hours) of the central difference of Tsky in LST behind ``timing_offset``.
LST_STEP_H = 2.0 / 60.0
#: Step (arcmin) of the central differences of Tsky in the sky's tilt about the equatorial
#: x and y axes behind ``timing_offset``'s frame-tilt parameters (linear well beyond the
#: 6 arcmin a J2000 sky is tilted by in 2018).
TILT_STEP_ARCMIN = 30.0


class EffectError(AutocalError):
    """Invalid effect or template input."""


# templates ------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ScaledBeam(Beam):
    """A beam whose width is scaled by ``factor``: ``A'(az, za) = A(az, za / factor)``.

    Used to build the first-order ``beam_width`` template; the normalisation of the beam
    does not matter because Tsky divides by the beam integral.
    """

    base: Beam | None = None
    factor: float = 1.0
    name: str = "scaled"

    @property
    def freq_range(self) -> tuple[float, float] | None:  # noqa: D102
        return None if self.base is None else self.base.freq_range

    def power(self, freqs: np.ndarray, az: np.ndarray, za: np.ndarray) -> np.ndarray:  # noqa: D102
        if self.base is None:
            raise EffectError("ScaledBeam needs a base beam")
        za = np.clip(np.asarray(za) / self.factor, 0.0, np.pi)
        return self.base.power(freqs, az, za)

    def on(self, az: np.ndarray, za: np.ndarray) -> BeamEvaluator:
        """Bind the base beam to the scaled directions (keeps its fast evaluator)."""
        if self.base is None:
            raise EffectError("ScaledBeam needs a base beam")
        return self.base.on(az, np.clip(np.asarray(za) / self.factor, 0.0, np.pi))

    def describe(self) -> dict[str, Any]:  # noqa: D102
        base = {} if self.base is None else self.base.describe()
        return {"beam": "scaled", "factor": self.factor, "base": base}


@dataclass(frozen=True, eq=False)
class SkyTemplates:
    """The model Tsky split into the parts the effects act on.

    Attributes
    ----------
    freqs, lsts
        ``(Nfreq,)`` Hz and ``(Ntime,)`` hours.
    total
        ``(Npol, Ntime, Nfreq)`` model Tsky (galactic + CMB + ground), kelvin.
    galactic
        ``(Npol, Ntime, Nfreq)`` the sky part without CMB ("S").
    cmb
        ``(Npol, Ntime, Nfreq)`` the CMB part (``2.725 K f_above``).
    ground
        ``(Npol, Ntime, Nfreq)`` ``Tgnd f_below``.
    f_above, f_below
        ``(Npol, Nfreq)`` beam fractions above / below the horizon.
    beam_dwidth
        ``(Npol, Ntime, Nfreq)`` ``dTsky / dw`` for a fractional beam-width change ``w``
        (central difference), or ``None``.
    beam_width_poly
        ``(K, Npol, Ntime, Nfreq)`` coefficients ``c_k`` of ``Tsky(w) - Tsky(0) =
        sum_k c_k w^k`` (k = 1..K), the polynomial through Tsky computed with the beam
        width scaled by ``1 + w`` at ``K`` nodes ``w != 0`` (+-h/2, +-h), or ``None``.
        It makes ``beam_width`` exact at the nodes and accurate between them for the
        5-15 % width errors of real beam models.
    nu0
        Reference frequency (Hz) of the spectral-index error ``(nu / nu0)^dbeta``.
    lst_derivative
        ``(Npol, Ntime, Nfreq)`` ``dTsky / dt`` in kelvin per second of time (central
        difference over :data:`LST_STEP_H`), the template of ``timing_offset``, or ``None``.
    frame_tilt
        ``(2, Npol, Ntime, Nfreq)`` ``dTsky / d tilt`` in kelvin per arcminute for the sky
        turned about the equatorial x and y axes (central differences over
        :data:`TILT_STEP_ARCMIN`), the frame-tilt part of ``timing_offset`` over long spans,
        or ``None``.
    meta
        Provenance.
    """

    freqs: np.ndarray
    lsts: np.ndarray
    total: np.ndarray
    galactic: np.ndarray
    cmb: np.ndarray
    ground: np.ndarray
    f_above: np.ndarray
    f_below: np.ndarray
    beam_dwidth: np.ndarray | None = None
    beam_width_poly: np.ndarray | None = None
    nu0: float = 150e6
    meta: dict[str, Any] = field(default_factory=dict)
    lst_derivative: np.ndarray | None = None
    frame_tilt: np.ndarray | None = None

    def __post_init__(self) -> None:
        shape = self.total.shape
        if len(shape) != 3 or shape[1:] != (self.lsts.size, self.freqs.size):
            raise EffectError(f"Tsky templates have shape {shape}; expected (Npol, Ntime, Nfreq)")
        for name in ("galactic", "cmb", "ground"):
            if getattr(self, name).shape != shape:
                raise EffectError(f"template {name} has the wrong shape")
        if self.beam_dwidth is not None and self.beam_dwidth.shape != shape:
            raise EffectError("template beam_dwidth has the wrong shape")
        if self.beam_width_poly is not None and self.beam_width_poly.shape[1:] != shape:
            raise EffectError("template beam_width_poly has the wrong shape")
        if self.lst_derivative is not None and self.lst_derivative.shape != shape:
            raise EffectError("template lst_derivative has the wrong shape")
        if self.frame_tilt is not None and self.frame_tilt.shape != (2, *shape):
            raise EffectError("template frame_tilt has the wrong shape")

    def subset(self, pols: slice = slice(None), channels: slice = slice(None)) -> SkyTemplates:
        """Return the templates of some polarisations and channels."""
        fields: dict[str, Any] = {"freqs": self.freqs[channels]}
        for name in ("total", "galactic", "cmb", "ground", "beam_dwidth", "lst_derivative"):
            arr = getattr(self, name)
            fields[name] = None if arr is None else arr[pols, :, channels]
        for name in ("f_above", "f_below"):
            fields[name] = getattr(self, name)[pols, channels]
        if self.beam_width_poly is not None:
            fields["beam_width_poly"] = self.beam_width_poly[:, pols, :, channels]
        if self.frame_tilt is not None:
            fields["frame_tilt"] = self.frame_tilt[:, pols, :, channels]
        return replace(self, **fields)


def sky_templates(
    sky: Any,
    beam: Beam | str,
    site: Any,
    freqs: np.ndarray,
    lsts: np.ndarray,
    *,
    pols: tuple[str, ...] | list[str] = ("ee",),
    tgnd: float = 300.0,
    nside: int = 64,
    epoch: Any = None,
    beam_width_step: float | None = 0.2,
    nu0: float | None = None,
    timing: bool = True,
    tilt: bool | None = None,
) -> SkyTemplates:
    """Compute the model Tsky and its effect templates (one FFT Tsky pass per beam).

    Parameters
    ----------
    sky
        Sky model or spec (:func:`autocal.sky.models.get_sky`).
    beam
        Beam or spec (:func:`autocal.sky.beam_names.get_beam`).
    site
        Site or name.
    freqs
        Hz.
    lsts
        Hours.
    pols
        Polarisations.
    tgnd
        Model ground temperature in kelvin.
    nside
        HEALPix resolution.
    epoch
        Epoch of the equatorial frame (use the observation date).
    beam_width_step
        Largest fractional width change ``h`` of the ``beam_width`` template: Tsky is
        computed with the width scaled by ``1 +- h/2`` and ``1 +- h`` and a quartic in
        ``w`` passed through them (``None``: no template).
    nu0
        Reference of the spectral-index error; default the sky's ``nu0`` for a power-law
        sky, else the band centre.
    timing
        Compute the ``timing_offset`` template (Tsky's derivative in time).
    tilt
        With ``timing``, also the frame-tilt templates (Tsky's derivatives in the sky's
        tilt about the equatorial x and y axes: 4 more Tsky computations per beam, each
        preparing a turned sky); worth it over spans long enough to tell a tilt from a
        time offset. ``None`` (default): when the LSTs span at least
        :data:`DIURNAL_MIN_SPAN_H`, as ``autocal diagnose`` and the service have them.

    Returns
    -------
    SkyTemplates
        The templates.
    """
    freqs = np.asarray(freqs, np.float64)
    lsts = np.asarray(lsts, np.float64)
    if tilt is None:  # by the span (to within rounding: 6 h of LSTs may come out 5.99...)
        span = float(np.ptp(unwrap_lsts(lsts))) if lsts.size else 0.0
        tilt = span >= DIURNAL_MIN_SPAN_H - 1e-9
    parts: dict[str, list[np.ndarray]] = {
        k: [] for k in ("tot", "gal", "cmb", "gnd", "bw", "dt", "tilt")
    }
    fa, fb = [], []
    meta: dict[str, Any] = {}
    for pol in pols:
        b = get_beam(beam, pol)
        kw = {"tgnd": tgnd, "nside": nside, "epoch": epoch, "pol": pol, "progress": False}
        res = compute_tsky(sky, b, site, freqs, lsts, keep_components=True, cache=False, **kw)
        assert res.components is not None and res.spectra is not None
        labels = list(res.meta.get("component_labels", []))
        contrib = res.components * res.spectra[None]  # (T, F, C)
        is_cmb = np.array([lab == "cmb" for lab in labels])
        gal = contrib[..., ~is_cmb].sum(axis=-1)
        cmb = contrib[..., is_cmb].sum(axis=-1)
        gnd = np.broadcast_to(tgnd * res.f_below, gal.shape)
        parts["tot"].append(res.tsky)
        parts["gal"].append(gal)
        parts["cmb"].append(cmb)
        parts["gnd"].append(np.array(gnd))
        fa.append(res.f_above)
        fb.append(res.f_below)
        meta = res.meta
        if timing:
            parts["dt"].append(_lst_derivative(sky, b, site, freqs, lsts, kw))
            if tilt:
                parts["tilt"].append(_frame_tilt(sky, b, site, freqs, lsts, kw))
        if beam_width_step:
            parts["bw"].append(
                _beam_width_poly(sky, b, site, freqs, lsts, kw, beam_width_step, res.tsky)
            )
    if nu0 is None:
        nu0 = float(meta.get("sky", {}).get("nu0_Hz") or 0.5 * (freqs[0] + freqs[-1]))
    return SkyTemplates(
        freqs=freqs,
        lsts=lsts,
        total=np.stack(parts["tot"]),
        galactic=np.stack(parts["gal"]),
        cmb=np.stack(parts["cmb"]),
        ground=np.stack(parts["gnd"]),
        f_above=np.stack(fa),
        f_below=np.stack(fb),
        beam_dwidth=np.stack([c[0] for c in parts["bw"]]) if parts["bw"] else None,
        beam_width_poly=np.stack(parts["bw"], axis=1) if parts["bw"] else None,
        lst_derivative=np.stack(parts["dt"]) if parts["dt"] else None,
        frame_tilt=np.stack(parts["tilt"], axis=1) if parts["tilt"] else None,
        nu0=nu0,
        meta={"tsky": meta, "tgnd_K": tgnd, "beam_width_step": beam_width_step},
    )


def _lst_derivative(
    sky: Any,
    beam: Beam,
    site: Any,
    freqs: np.ndarray,
    lsts: np.ndarray,
    kw: dict[str, Any],
) -> np.ndarray:
    """Return ``dTsky / dt`` in kelvin per second of time (the ``timing_offset`` template).

    Tsky one LST step either side (cached harmonics, any LST grid): per second of time, a
    sidereal second being 1/1.0027379 of a solar one.
    """
    ahead, behind = (
        compute_tsky(sky, beam, site, freqs, (lsts + d) % 24.0, **kw).tsky
        for d in (LST_STEP_H, -LST_STEP_H)
    )
    per_hour = (ahead - behind) / (2 * LST_STEP_H)
    return per_hour * SIDEREAL_RATE / 3600.0


def _frame_tilt(
    sky: Any,
    beam: Beam,
    site: Any,
    freqs: np.ndarray,
    lsts: np.ndarray,
    kw: dict[str, Any],
) -> np.ndarray:
    """Return ``dTsky / d tilt`` (K per arcmin) about the equatorial x and y axes: ``(2, T, F)``.

    Central differences over :data:`TILT_STEP_ARCMIN` of Tsky with the sky turned
    (:class:`autocal.sky.models.TiltedSky`), cached like any other sky.
    """
    base = get_sky(sky) if isinstance(sky, str) else sky
    h = TILT_STEP_ARCMIN
    out = []
    for axis in (0, 1):
        turned = []
        for sign in (1.0, -1.0):
            angles = [0.0, 0.0]
            angles[axis] = sign * h
            tilted = TiltedSky(base=base, tilt_x_arcmin=angles[0], tilt_y_arcmin=angles[1])
            turned.append(compute_tsky(tilted, beam, site, freqs, lsts, **kw).tsky)
        out.append((turned[0] - turned[1]) / (2 * h))
    return np.stack(out)


def _beam_width_poly(
    sky: Any,
    beam: Beam,
    site: Any,
    freqs: np.ndarray,
    lsts: np.ndarray,
    kw: dict[str, Any],
    step: float,
    tsky: np.ndarray,
) -> np.ndarray:
    """Return the coefficients ``c_1..c_4`` of ``Tsky(w) - Tsky(0) = sum_k c_k w^k``.

    Tsky with the beam width scaled by ``1 + w`` at the nodes ``w = +-step/2, +-step``; the
    quartic passes exactly through them and ``w = 0`` (``tsky``).
    """
    nodes = step * np.array([-1.0, -0.5, 0.5, 1.0])
    deltas = np.stack(
        [
            # the widened beams' harmonics come from the Tsky cache (every
            # diagnosis of the night and the calibration share them)
            compute_tsky(sky, ScaledBeam(base=beam, factor=1 + w), site, freqs, lsts, **kw).tsky
            - tsky
            for w in nodes
        ]
    )
    # solve sum_k c_k w_j^k = delta_j for c_1..c_4 (exact through the 5 nodes)
    vander = nodes[:, None] ** np.arange(1, nodes.size + 1)[None, :]
    return np.tensordot(np.linalg.inv(vander), deltas, axes=([1], [0]))


# effects --------------------------------------------------------------------------------


def time_basis(lsts: np.ndarray, order: int) -> np.ndarray:
    """``(order, Ntime)`` Legendre polynomials ``P_1..P_order`` of the LST on ``[-1, 1]``."""
    model = FitModel.for_lsts(np.asarray(lsts), "legendre", max(order, 1))
    return legendre.legvander(model.s(lsts), order)[:, 1:].T


def diurnal_basis(lsts: np.ndarray, harmonics: int) -> np.ndarray:
    """``(2 harmonics, Ntime)``: ``sin(2 pi k L / 24 h)``, ``cos(2 pi k L / 24 h)``, k = 1.."""
    phase = 2 * np.pi * np.asarray(lsts, np.float64) / 24.0
    rows = []
    for k in range(1, harmonics + 1):
        rows += [np.sin(k * phase), np.cos(k * phase)]
    return np.array(rows)


@dataclass(frozen=True)
class Effect:
    """A candidate effect: a parameterised extension of the forward model.

    Attributes
    ----------
    name
        Catalogue identifier (:data:`EFFECT_NAMES`).
    kind
        ``"tsky"`` (additive change of Tsky), ``"gain"`` (relative achromatic gain
        drift), ``"noise"`` (relative achromatic noise drift), ``"bandpass"`` or
        ``"feed_gain"`` (one gain series per antenna-pol, fitted feed by feed:
        :func:`autocal.diagnosis.feeds.fit_feed_gains`).
    params
        Parameter names.
    units
        Parameter units.
    order
        Legendre order (``basis="legendre"``) or number of harmonics of the sidereal day
        (``basis="diurnal"``) of drift effects.
    fixed
        For discrete hypotheses (``missing_cmb``): parameter values held fixed.
    signature
        One-line description of the effect's signature.
    """

    name: str
    kind: Literal["tsky", "gain", "noise", "bandpass", "feed_gain"]
    params: tuple[str, ...]
    units: tuple[str, ...]
    order: int = 0
    fixed: tuple[float, ...] | None = None
    signature: str = ""
    basis: Literal["legendre", "diurnal", "integration", "feed_integration", "feed_legendre"] = (
        "legendre"
    )

    def time_basis(self, lsts: np.ndarray) -> np.ndarray:
        """``(k, Ntime)`` time basis of a drift effect (:func:`time_basis`)."""
        if self.basis == "diurnal":
            return diurnal_basis(lsts, self.order)
        if self.basis == "integration":
            if len(self.params) != len(lsts) - 1:
                raise EffectError(
                    f"gain_jitter was built for {len(self.params) + 1} integrations, "
                    f"the data have {len(lsts)}"
                )
            return np.eye(len(lsts))[1:]
        return time_basis(lsts, self.order)

    @property
    def label(self) -> str:
        """``name/basis order``: the candidate's key among a diagnosis's failed candidates."""
        return f"{self.name}/{self.basis}{self.order}"

    @property
    def nfree(self) -> int:
        """Number of free (penalised) parameters (``feed_gain``: counted by its fit)."""
        if self.kind == "bandpass":
            return 3
        return 0 if self.fixed is not None else len(self.params)

    def delta(self, p: np.ndarray, tpl: SkyTemplates) -> np.ndarray:
        """Additive Tsky change ``(Npol, Ntime, Nfreq)`` for ``kind == "tsky"``."""
        p = np.asarray(p, np.float64)
        if self.name == "sky_spectral_index":
            ratio = tpl.freqs / tpl.nu0
            return tpl.galactic * (ratio ** p[0] - 1.0)[None, None, :]
        if self.name == "beam_width" and tpl.beam_width_poly is not None:
            powers = float(p[0]) ** np.arange(1, tpl.beam_width_poly.shape[0] + 1)
            return np.tensordot(powers, tpl.beam_width_poly, axes=([0], [0]))
        return np.tensordot(self.jacobian(p, tpl), p, axes=([-1], [0]))

    def jacobian(self, p: np.ndarray, tpl: SkyTemplates) -> np.ndarray:
        """``d delta / d p`` as ``(Npol, Ntime, Nfreq, k)`` for ``kind == "tsky"``."""
        shape = tpl.total.shape
        if self.name == "sky_scale":
            t = tpl.galactic
        elif self.name == "sky_offset":
            t = np.broadcast_to(tpl.f_above[:, None, :], shape)
        elif self.name == "ground_temperature":
            t = np.broadcast_to(tpl.f_below[:, None, :], shape)
        elif self.name == "missing_cmb":
            t = np.broadcast_to(T_CMB * tpl.f_above[:, None, :], shape)
        elif self.name == "beam_width":
            if tpl.beam_dwidth is None:
                raise EffectError("beam_width needs templates built with beam_width_step")
            t = tpl.beam_dwidth
            if tpl.beam_width_poly is not None:
                k = np.arange(1, tpl.beam_width_poly.shape[0] + 1)
                dpow = k * float(p[0]) ** (k - 1)
                t = np.tensordot(dpow, tpl.beam_width_poly, axes=([0], [0]))
        elif self.name == "sky_spectral_index":
            ratio = tpl.freqs / tpl.nu0
            t = tpl.galactic * (np.log(ratio) * ratio ** float(p[0]))[None, None, :]
        elif self.name == "timing_offset":
            if tpl.lst_derivative is None:
                raise EffectError("timing_offset needs templates built with timing=True")
            if len(self.params) == 3:
                if tpl.frame_tilt is None:
                    raise EffectError("the frame tilt needs templates built with tilt=True")
                return np.stack([tpl.lst_derivative, *tpl.frame_tilt], axis=-1)
            t = tpl.lst_derivative
        else:
            raise EffectError(f"{self.name} is not a Tsky effect")
        return np.asarray(t)[..., None]

    def describe(self) -> dict[str, Any]:
        """JSON-serialisable description."""
        return {
            "name": self.name,
            "kind": self.kind,
            "params": list(self.params),
            "units": list(self.units),
            "order": self.order,
            "fixed": None if self.fixed is None else list(self.fixed),
            "signature": self.signature,
            "basis": self.basis,
        }
