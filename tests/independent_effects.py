"""Hidden physical effects in the independent forward model, and their diagnosis.

A :class:`Case` is an observation simulated by ``tests/independent_sim.py`` (GSM2008 via
pygdsm, astropy AltAz per pixel at nside 32, its own dipole / HERA beam evaluation, a hard
horizon, its own UVH5 writer) with zero, one or two effects of autocal's catalogue
(:mod:`autocal.diagnosis.effects`) hidden in it. The injection is written here, from the
catalogue's definitions, without autocal's simulation or hidden-effect code:

======================  ================================================================
``gain_drift``          ``G(t) = G (1 + drift(t))``, achromatic. ``linear``: the gain
                        changes by ``amplitude`` from the first to the last integration
                        (centred: time-mean gain ``G``), 2-10 % over 24 h, 1-5 % over
                        ~30 min; ``diurnal``: ``amplitude sin(2 pi LST / 24 h + phase)``,
                        2-10 %, periodic in sidereal time like the catalogue's diurnal basis
``gain_jitter``         ``G(t_i) = G f_i``, ``f_i = (1 + eps_i) / mean(1 + eps)``,
                        ``eps_i ~ N(0, rms)`` from its own seed, rms 0.1-1 %
``antenna_gain_jitter`` every antenna-pol its own ``f_i`` series (seeds differ by
                        feed), rms 0.2-1 %
``antenna_gain_drift``  every antenna-pol its own linear gain drift, 1-5 % from first to
                        last integration, each of random sign
``timing_offset``       the sky simulated ``dt_s`` after the times in the file (a clock
                        behind), ``|dt_s|`` 30-90 s
``noise_drift``         ``Trxr(t) = Trxr (1 + e_1 s)``, ``s`` the time (linear in LST)
                        mapped onto ``[-1, 1]`` over the span, ``|e_1|`` 1-5 %
``cable_reflection``    ``G(nu) (1 + a cos(2 pi nu tau + phi))``: ``a`` 1e-3-1e-2,
                        ``tau`` 100-400 ns, ``phi`` uniform
``sky_spectral_index``  true sky ``S (nu / nu0)^dbeta + CMB``, ``|dbeta|`` 0.05-0.2,
                        ``nu0`` the band centre (150 MHz for 110-190 MHz): the
                        catalogue's reference for a sky without its own ``nu0``
                        (:func:`autocal.diagnosis.effects.sky_templates`)
``ground_temperature``  true ground 200-270 K or 320-350 K (at least 20 K from the 300 K
                        the model assumes, so that the effect exists at the prior's level)
``beam_width``          the true beam's width times ``1 + w``, ``|w|`` 5-15 %: the
                        dipole's FWHM (``fwhm``, default) or its whole pattern stretched
                        in zenith angle, ``A(za / (1 + w), phi)`` (``stretch``: the
                        catalogue's own definition); the HERA beam is always stretched
``missing_cmb``         the data's sky has no CMB
``sky_scale``           true sky ``(1 + s) S + CMB``, ``|s|`` 3-10 %
``sky_offset``          ``+ T_offset`` on every pixel above the horizon, ``|T_offset|``
                        5-15 K
======================  ================================================================

``S`` is the GSM2008 sky without the CMB. Every case's receiver temperature varies with
frequency, ``Trxr(nu) = 150 + 40 x + 20 x^2`` K with ``x = (nu - 150 MHz) / 40 MHz``
(:func:`receiver_temperature`), and the diagnosis of every case, with or without hidden
effects, is given the TRUE ``Trxr(nu)`` as a per-channel CSV prior (``freq_mhz,trxr_k,
sigma_k``, :data:`PRIOR_SIGMA_K`) written next to the data: the time-constant effects
and the sky scalings are identifiable only with it, and giving it to some cases only
would tell the diagnosis which cases hide them.

:func:`run_case` simulates a case, diagnoses it with autocal's ordinary stage function
:func:`autocal.diagnosis.run.run_diagnosis` and scores it by exact names: the effects the
diagnosis names must be the hidden set, no extras. :func:`suite_plan` is the fixed-seed
suite of ``scripts/diagnose_independent_suite.py``.

Not every hidden effect is visible at this sensitivity: :func:`effect_strength` measures,
in the independent model alone and without noise, the chi-square an effect costs the
clean model (per-channel ``G``, ``n`` and the same receiver prior) and its Delta BIC
with the catalogue's number of parameters; effects below the diagnosis's threshold are
reported as not detectable (a ground 20-50 K off 300 K is such a case for the dipole,
whose beam has 2 % below the horizon at 110 MHz and 0.2 % at 150 MHz, and so is every
time-constant effect over ~30 min, when ``G`` and ``n`` are nearly degenerate).
"""

from __future__ import annotations

import json
import math
import time
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tests import independent_sim as sim

#: Effects the independent model can hide (autocal's catalogue names).
HIDDEN_NAMES = (
    "gain_drift",
    "gain_jitter",
    "noise_drift",
    "cable_reflection",
    "sky_spectral_index",
    "ground_temperature",
    "beam_width",
    "missing_cmb",
    "sky_scale",
    "sky_offset",
    "antenna_gain_jitter",
    "antenna_gain_drift",
    "timing_offset",
)
#: Hidden effects of the forward model (the sky, beam, ground, CMB and clock), whose only
#: consequence for the calibration is a bias of the per-channel ``G`` and ``Trxr``; whether
#: one matters is judged from the truth (:func:`product_impact`). The instrument's effects
#: (drifts, jitter, a reflection) change the data's time or bandpass structure and always
#: matter.
FORWARD_MODEL_EFFECTS = frozenset(
    {
        "sky_spectral_index",
        "ground_temperature",
        "beam_width",
        "missing_cmb",
        "sky_scale",
        "sky_offset",
        "timing_offset",
    }
)
#: Ground temperature the diagnosis's model assumes, kelvin.
MODEL_TGND_K = 300.0
#: 1-sigma of the per-channel receiver prior, kelvin.
PRIOR_SIGMA_K = 1.0
#: Radiometer product of every sample (channel width x integration time x nsamples).
DNU_DT = 1e6
#: Seed of the suite (:func:`case_seed`).
SUITE_SEED = 20260
#: Delta BIC the diagnosis requires by default (:data:`autocal.diagnosis.trials.BIC_THRESHOLD`).
BIC_THRESHOLD = 10.0


class CaseError(ValueError):
    """Invalid case."""


@dataclass(frozen=True)
class Span:
    """Time sampling of a case.

    Attributes
    ----------
    name
        Label (``day``, ``short``).
    lst_start_h
        Apparent LST of the first integration, hours.
    duration_min
        Span, minutes.
    integration_s
        Integration time, seconds.
    """

    name: str
    lst_start_h: float
    duration_min: float
    integration_s: float

    @property
    def ntime(self) -> int:
        """Number of integrations."""
        return max(1, round(self.duration_min * 60.0 / self.integration_s))

    @property
    def is_day(self) -> bool:
        """True for spans of 12 h or more."""
        return self.duration_min >= 720.0


#: A sidereal-ish day of 96 x 15 min from LST 0 h, and 174 x 10.7 s from LST 3.23 h.
SPANS = {
    "day": Span("day", 0.0, 1440.0, 900.0),
    "short": Span("short", 3.23, 31.0, 10.7),
}


@dataclass(frozen=True)
class Hidden:
    """One hidden effect: its catalogue name and true parameters."""

    name: str
    params: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON form."""
        return {"name": self.name, "params": dict(self.params)}


@dataclass(frozen=True)
class Case:
    """A simulated observation with hidden effects.

    Attributes
    ----------
    name
        Unique label.
    span
        Time sampling.
    effects
        The hidden effects (none: a clean control).
    seed
        Seed of the radiometer noise (and of the drawn parameters).
    beam
        ``"dipole"`` or ``"hera"`` (true beam and the diagnosis's model beam).
    antennas, pols
        Antennas and polarisations of the file.
    node_spacing_s
        Tsky time sampling of the independent model (``None``: exact at every time).
    """

    name: str
    span: Span
    effects: tuple[Hidden, ...] = ()
    seed: int = 0
    beam: str = "dipole"
    antennas: tuple[int, ...] = (0,)
    pols: tuple[str, ...] = ("ee",)
    node_spacing_s: float | None = None

    @property
    def hidden(self) -> tuple[str, ...]:
        """Names of the hidden effects."""
        return tuple(e.name for e in self.effects)

    def to_dict(self) -> dict[str, Any]:
        """JSON form."""
        return {
            "name": self.name,
            "span": self.span.name,
            "lst_start_h": self.span.lst_start_h,
            "duration_min": self.span.duration_min,
            "integration_s": self.span.integration_s,
            "ntime": self.span.ntime,
            "beam": self.beam,
            "antennas": list(self.antennas),
            "pols": list(self.pols),
            "seed": self.seed,
            "node_spacing_s": self.node_spacing_s,
            "hidden": [e.to_dict() for e in self.effects],
        }


# ---------------------------------------------------------------------------------------
# truth
# ---------------------------------------------------------------------------------------
def receiver_temperature(freqs_hz: np.ndarray) -> np.ndarray:
    """Return the true receiver temperature ``150 + 40 x + 20 x^2`` K, ``x = (nu - 150) / 40``.

    Parameters
    ----------
    freqs_hz
        Frequencies in Hz.

    Returns
    -------
    numpy.ndarray
        Kelvin, like ``freqs_hz`` (146-190 K over 110-190 MHz).
    """
    x = (np.asarray(freqs_hz, np.float64) - 150e6) / 40e6
    return 150.0 + 40.0 * x + 20.0 * x * x


def write_trxr_prior(
    path: str | Path, freqs_hz: np.ndarray, trxr_k: np.ndarray, sigma_k: float
) -> Path:
    """Write a ``freq_mhz,trxr_k,sigma_k`` table, one row per channel.

    Parameters
    ----------
    path
        The CSV file (overwritten).
    freqs_hz
        ``(Nfreq,)`` channel frequencies, Hz.
    trxr_k
        ``(Nfreq,)`` receiver temperature, kelvin.
    sigma_k
        1-sigma of every row, kelvin.

    Returns
    -------
    pathlib.Path
        The file.
    """
    path = Path(path)
    rows = [
        f"{f / 1e6:.6f},{t:.6f},{sigma_k:g}\n"
        for f, t in zip(np.asarray(freqs_hz), np.asarray(trxr_k), strict=True)
    ]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("freq_mhz,trxr_k,sigma_k\n" + "".join(rows))
    return path


def jitter_factors(rms: float, seed: int, ntime: int) -> np.ndarray:
    """Per-integration gain factors ``(1 + eps) / mean(1 + eps)``, ``eps ~ N(0, rms)``."""
    eps = np.random.default_rng(int(seed)).normal(0.0, float(rms), ntime)
    return (1.0 + eps) / np.mean(1.0 + eps)


def feed_jitter_factors(rms: float, seed: int, nant: int, npol: int, ntime: int) -> np.ndarray:
    """``(Nant, Npol, Ntime)``: every antenna-pol its own :func:`jitter_factors` series."""
    return np.array(
        [
            [jitter_factors(rms, seed + 7919 * (ia * npol + ip + 1), ntime) for ip in range(npol)]
            for ia in range(nant)
        ]
    )


def feed_drift_factors(seed: int, nant: int, npol: int, ntime: int) -> np.ndarray:
    """``(Nant, Npol, Ntime)``: every antenna-pol its own linear drift (mean 1).

    Each changes by ``+-U(1 %, 5 %)`` from the first to the last integration.
    """
    rng = np.random.default_rng(int(seed))
    size = (nant, npol)
    amplitude = rng.choice([-1.0, 1.0], size) * rng.uniform(0.01, 0.05, size)
    t_frac = np.linspace(-0.5, 0.5, ntime) if ntime > 1 else np.zeros(1)
    return 1.0 + amplitude[..., None] * t_frac


def draw_effect(name: str, span: Span, rng: np.random.Generator) -> Hidden:
    """Draw one hidden effect's parameters in its range (see the module table).

    Parameters
    ----------
    name
        A name of :data:`HIDDEN_NAMES`, optionally ``gain_drift:linear`` or
        ``gain_drift:diurnal`` (default: diurnal for a day, linear otherwise),
        ``beam_width:fwhm`` (default) or ``beam_width:stretch``.
    span
        The case's time sampling (a short span gets a 1-5 % linear gain drift).
    rng
        Random generator.

    Returns
    -------
    Hidden
        The effect.
    """
    base, _, variant = name.partition(":")
    sign = float(rng.choice([-1.0, 1.0]))
    if base == "gain_drift":
        profile = variant or ("diurnal" if span.is_day else "linear")
        if profile == "linear":
            lo, hi = (0.02, 0.10) if span.is_day else (0.01, 0.05)
            return Hidden(base, {"profile": "linear", "amplitude": sign * rng.uniform(lo, hi)})
        if profile == "diurnal":
            return Hidden(
                base,
                {
                    "profile": "diurnal",
                    "amplitude": rng.uniform(0.02, 0.10),
                    "phase": rng.uniform(-math.pi, math.pi),
                },
            )
        raise CaseError(f"unknown gain_drift profile {profile!r}: linear or diurnal")
    if base == "beam_width":
        mode = variant or "fwhm"
        if mode not in ("fwhm", "stretch"):
            raise CaseError(f"unknown beam_width variant {mode!r}: fwhm or stretch")
        return Hidden(base, {"w": sign * rng.uniform(0.05, 0.15), "mode": mode})
    if base == "timing_offset" and variant == "j2000":
        # the sky in J2000 instead of the apparent frame of the date (the mistake of issue
        # 21): precession since J2000 is mostly a turn in right ascension, which this
        # catalogue entry names ("a sky in a frame rotated in right ascension")
        return Hidden(base, {"sky_frame": "J2000"})
    if variant:
        raise CaseError(f"{base} has no variants")
    if base == "timing_offset":
        return Hidden(base, {"dt_s": sign * rng.uniform(30.0, 90.0)})
    if base == "gain_jitter":
        return Hidden(
            base, {"rms": rng.uniform(1e-3, 1e-2), "seed": int(rng.integers(0, 2**31 - 1))}
        )
    if base == "antenna_gain_drift":
        return Hidden(base, {"seed": int(rng.integers(0, 2**31 - 1))})
    if base == "antenna_gain_jitter":
        return Hidden(
            base, {"rms": rng.uniform(2e-3, 1e-2), "seed": int(rng.integers(0, 2**31 - 1))}
        )
    if base == "noise_drift":
        return Hidden(base, {"e_1": sign * rng.uniform(0.01, 0.05)})
    if base == "cable_reflection":
        return Hidden(
            base,
            {
                "a": rng.uniform(1e-3, 1e-2),
                "tau_ns": rng.uniform(100.0, 400.0),
                "phi": rng.uniform(-math.pi, math.pi),
            },
        )
    if base == "sky_spectral_index":
        return Hidden(base, {"dbeta": sign * rng.uniform(0.05, 0.2)})
    if base == "ground_temperature":
        tgnd = rng.uniform(200.0, 270.0) if sign < 0 else rng.uniform(320.0, 350.0)
        return Hidden(base, {"tgnd_K": tgnd, "dT_gnd": tgnd - MODEL_TGND_K})
    if base == "missing_cmb":
        return Hidden(base, {"cmb_factor": -1.0})
    if base == "sky_scale":
        return Hidden(base, {"s": sign * rng.uniform(0.03, 0.10)})
    if base == "sky_offset":
        return Hidden(base, {"T_offset": sign * rng.uniform(5.0, 15.0)})
    raise CaseError(f"unknown hidden effect {base!r}: use one of {HIDDEN_NAMES}")


def make_case(
    name: str,
    effects: Sequence[str],
    span: str | Span,
    seed: int,
    *,
    beam: str = "dipole",
    antennas: Sequence[int] = (0,),
    pols: Sequence[str] = ("ee",),
    node_spacing_s: float | None = None,
) -> Case:
    """Return a case hiding ``effects`` with parameters drawn from ``seed``.

    Parameters
    ----------
    name
        Label.
    effects
        Effect names (:func:`draw_effect`), empty for a clean control.
    span
        ``"day"``, ``"short"`` or a :class:`Span`.
    seed
        Seed of the parameters and the noise.
    beam, antennas, pols, node_spacing_s
        See :class:`Case`.

    Returns
    -------
    Case
        The case.
    """
    sp = SPANS[span] if isinstance(span, str) else span
    rng = np.random.default_rng(seed)
    drawn = tuple(draw_effect(e, sp, rng) for e in effects)
    if len({e.name for e in drawn}) != len(drawn):
        raise CaseError(f"case {name}: an effect is hidden twice")
    return Case(name, sp, drawn, seed, beam, tuple(antennas), tuple(pols), node_spacing_s)


def simulation_kwargs(case: Case) -> dict[str, Any]:
    """Translate a case's effects into :func:`tests.independent_sim.simulate_autos` arguments.

    Parameters
    ----------
    case
        The case.

    Returns
    -------
    dict
        Keyword arguments (without the path).
    """
    sp = case.span
    freqs = sim.default_freqs()
    nu0 = 0.5 * (freqs[0] + freqs[-1])
    ntime = sp.ntime
    span_h = (ntime - 1) * sp.integration_s / 3600.0
    gain0 = sim.default_bandpass(freqs)
    factors = np.ones(ntime)
    sky: dict[str, float] = {}
    kwargs: dict[str, Any] = {}
    for eff in case.effects:
        p = eff.params
        if eff.name == "gain_drift":
            t_frac = np.linspace(0.0, 1.0, ntime) if ntime > 1 else np.zeros(1)
            if p["profile"] == "linear":
                drift = p["amplitude"] * (t_frac - np.mean(t_frac))
            else:
                lst = sp.lst_start_h + t_frac * span_h * sim.SIDEREAL_RATE
                drift = p["amplitude"] * np.sin(2 * np.pi * lst / 24.0 + p["phase"])
            factors = factors * (1.0 + drift)
        elif eff.name == "gain_jitter":
            factors = factors * jitter_factors(p["rms"], p["seed"], ntime)
        elif eff.name == "timing_offset" and "sky_frame" in p:
            kwargs["sky_frame"] = p["sky_frame"]
        elif eff.name == "timing_offset":
            kwargs["clock_offset_s"] = p["dt_s"]
        elif eff.name == "antenna_gain_drift":
            kwargs["feed_gain"] = feed_drift_factors(
                p["seed"], len(case.antennas), len(case.pols), ntime
            )
        elif eff.name == "antenna_gain_jitter":
            kwargs["feed_gain"] = feed_jitter_factors(
                p["rms"], p["seed"], len(case.antennas), len(case.pols), ntime
            )
        elif eff.name == "noise_drift":
            kwargs["noise_drift"] = p["e_1"]
        elif eff.name == "cable_reflection":
            phase = 2 * np.pi * freqs * p["tau_ns"] * 1e-9 + p["phi"]
            gain0 = gain0 * (1.0 + p["a"] * np.cos(phase))
        elif eff.name == "sky_spectral_index":
            sky["dbeta"] = p["dbeta"]
        elif eff.name == "ground_temperature":
            kwargs["tgnd_k"] = p["tgnd_K"]
        elif eff.name == "beam_width":
            kwargs["beam_width"] = p["w"]
            kwargs["beam_width_mode"] = p.get("mode", "fwhm")
        elif eff.name == "missing_cmb":
            sky["cmb_k"] = 0.0
        elif eff.name == "sky_scale":
            sky["scale"] = p["s"]
        elif eff.name == "sky_offset":
            sky["offset_k"] = p["T_offset"]
        else:
            raise CaseError(f"unknown hidden effect {eff.name!r}")
    if np.any(factors != 1.0):
        fixed = factors - 1.0
        kwargs["drift"] = lambda t: fixed  # one value per integration, whatever t
    if sky:
        kwargs["sky"] = sim.SkyChange(nu0_hz=nu0, **sky)
    return {
        "lst_start_h": sp.lst_start_h,
        "duration_min": sp.duration_min,
        "integration_s": sp.integration_s,
        "freqs_hz": freqs,
        "antennas": case.antennas,
        "pols": case.pols,
        "G0": gain0,
        "trxr_k": receiver_temperature(freqs),
        "dnu_dt": DNU_DT,
        "beam": case.beam,
        "seed": case.seed,
        "node_spacing_s": case.node_spacing_s,
        **kwargs,
    }


def simulate_case(case: Case, folder: str | Path, prior_sigma_k: float = PRIOR_SIGMA_K) -> dict:
    """Write a case's UVH5 file and its receiver prior (true ``Trxr``) into ``folder``.

    Returns
    -------
    dict
        ``truth`` (:class:`tests.independent_sim.Truth`), ``data`` and ``prior`` paths.
    """
    folder = Path(folder)
    truth = sim.simulate_autos(folder / f"{case.name}.uvh5", **simulation_kwargs(case))
    prior = write_trxr_prior(
        folder / f"{case.name}.trxr_prior.csv", truth.freqs, truth.Trxr, prior_sigma_k
    )
    return {"truth": truth, "data": truth.path, "prior": prior}


def _integration_jds(span: Span) -> np.ndarray:
    """The integration centres :func:`tests.independent_sim.simulate_autos` uses."""
    jd0 = sim.jd_at_lst(span.lst_start_h)
    return jd0 + np.arange(span.ntime) * (span.integration_s / 86400.0)


def effect_parameters(effect: Hidden, ntime: int, nfeeds: int = 1, span_h: float = 0.0) -> int:
    """Free parameters of the catalogue entry that describes ``effect``.

    ``gain_drift`` linear / ``noise_drift``: 1 (Legendre order 1); ``gain_drift``
    diurnal: 2 (sine and cosine); ``gain_jitter``: one per integration but the first;
    ``antenna_gain_jitter``: that for each of the ``nfeeds`` antenna-pols;
    ``missing_cmb``: 0 (a discrete hypothesis); ``cable_reflection``: an amplitude and a
    phase per antenna-pol and the shared delay, ``2 nfeeds + 1`` (as the diagnosis counts);
    ``timing_offset``: 3 over spans of ``span_h`` >= 6 h (the time offset and two frame
    tilts, as the diagnosis fits it), else 1; others 1.
    """
    if effect.name == "timing_offset":
        return 3 if span_h >= 6.0 else 1
    if effect.name == "gain_drift":
        return 2 if effect.params.get("profile") == "diurnal" else 1
    if effect.name == "gain_jitter":
        return ntime - 1
    if effect.name == "antenna_gain_jitter":
        return nfeeds * (ntime - 1)
    if effect.name == "antenna_gain_drift":
        return nfeeds
    if effect.name == "missing_cmb":
        return 0
    if effect.name == "cable_reflection":
        return 2 * nfeeds + 1
    return 1


#: Shortest delay a reflection is told from a smooth bandpass by: the catalogue's smooth
#: bandpass is a Legendre series of order ``round(1.5 B tau)`` over the band ``B`` (the
#: order that keeps >= 90 % of a ripple of this delay; autocal's ``auto_smooth_order``
#: at its shortest searched delay), clipped to 4..24.
SMOOTH_DELAY_S = 90e-9


def ripple_template_chi2(
    freqs: np.ndarray, gain: np.ndarray, sigma: np.ndarray, tau_s: float
) -> float:
    """Delta chi^2 a perfect ripple template gains on one antenna-pol's ``G(nu)``.

    ``gain`` (with its 1-sigma) is fitted by the smooth bandpass (a Legendre series of
    the order :data:`SMOOTH_DELAY_S` sets), then by the smooth bandpass plus the ripple's
    two quadratures at the true delay ``tau_s``, ``s(nu) cos(2 pi nu tau)`` and
    ``s(nu) sin(2 pi nu tau)`` with ``s`` the smooth fit (free amplitude and phase); the
    drop in chi-square is what the ripple explains beyond a smooth bandpass. Weighted
    least squares with numpy's ``lstsq`` on its own basis (not autocal's bandpass code),
    but the catalogue's model of a reflection (its smooth order and linearised ripple):
    it measures what that model can see at the truth, not whether the model is adequate.
    """
    span = float(freqs[-1] - freqs[0])
    order = int(np.clip(round(1.5 * span * SMOOTH_DELAY_S), 4, 24))
    x = 2.0 * (freqs - freqs[0]) / span - 1.0
    basis = np.polynomial.legendre.legvander(x, order)
    w = 1.0 / np.asarray(sigma, dtype=float)
    y = np.asarray(gain, dtype=float) * w

    def chi2(cols: np.ndarray) -> tuple[float, np.ndarray]:
        coef = np.linalg.lstsq(cols * w[:, None], y, rcond=None)[0]
        return float(np.sum((cols @ coef * w - y) ** 2)), coef

    smooth_chi2, coef = chi2(basis)
    smooth = basis @ coef
    phase = 2.0 * np.pi * freqs * tau_s
    ripple = np.column_stack([smooth * np.cos(phase), smooth * np.sin(phase)])
    return smooth_chi2 - chi2(np.hstack([basis, ripple]))[0]


def _clean_model_fit(
    data: np.ndarray, clean: np.ndarray, gain0: np.ndarray, trxr: np.ndarray, sigma_k: float
) -> dict[str, Any]:
    """Fit the clean model ``G Tsky + n`` per channel to noiseless data.

    Radiometer weights ``dnu dt / D^2``, with the receiver prior row ``n - Trxr G = 0`` of
    1-sigma ``G sigma_k``; ``data`` and ``clean`` are ``(Ntime, Nfreq)``. Returns the
    chi-square and, per channel, ``g``, ``trxr`` (``n / g``) and their 1-sigma of the
    same weights (the radiometer noise the data would have).
    """
    w = DNU_DT / data**2
    wp = 1.0 / (gain0 * sigma_k) ** 2
    n11 = (w * clean**2).sum(0) + wp * trxr**2
    n12 = (w * clean).sum(0) - wp * trxr
    n22 = w.sum(0) + wp
    b1 = (w * clean * data).sum(0)
    b2 = (w * data).sum(0)
    det = n11 * n22 - n12**2
    g = (n22 * b1 - n12 * b2) / det
    n = (n11 * b2 - n12 * b1) / det
    resid = data - g[None] * clean - n[None]
    var_g, var_n, cov = n22 / det, n11 / det, -n12 / det
    t_fit = n / g
    var_t = (var_n - 2 * t_fit * cov + t_fit**2 * var_g) / g**2
    return {
        "chi2": float((w * resid**2).sum() + (wp * (n - trxr * g) ** 2).sum()),
        "g": g,
        "sigma_g": np.sqrt(var_g),
        "trxr": t_fit,
        "sigma_trxr": np.sqrt(var_t),
    }


def product_impact(
    fit: dict[str, Any], gain: np.ndarray, trxr: np.ndarray, chi2_share: float = 0.0
) -> dict[str, Any]:
    """How far the clean model's ``G`` and ``Trxr`` land from the truth, by autocal's rule.

    ``fit`` is :func:`_clean_model_fit` of noiseless data with one hidden effect,
    ``gain`` and ``trxr`` the true per-channel values, ``chi2_share`` the chi-square the
    effect costs the clean model over the number of data. The effect does not matter to
    the products when it is negligible by the rule the diagnosis applies to its own
    findings (:func:`autocal.diagnosis.impact.is_negligible`: under 0.1 sigma in the
    median channel and 1 sigma in every one for both ``G`` and ``Trxr``, or a median
    change under 1e-3 of ``G`` and 1 K of ``Trxr`` with none ten times that; never with a
    chi-square share over 0.1), here judged from the truth with the radiometer sigma alone
    (smaller than the calibration's total sigma, so stricter).
    """
    from autocal.diagnosis import impact as rule

    dg = np.abs(fit["g"] - gain) / gain
    dt = np.abs(fit["trxr"] - trxr)
    g_sig, t_sig = dg * gain / fit["sigma_g"], dt / fit["sigma_trxr"]
    out = {
        "g_median_sigma": float(np.median(g_sig)),
        "g_max_sigma": float(np.max(g_sig)),
        "trxr_median_sigma": float(np.median(t_sig)),
        "trxr_max_sigma": float(np.max(t_sig)),
        "g_median_fraction": float(np.median(dg)),
        "g_max_fraction": float(np.max(dg)),
        "trxr_median_k": float(np.median(dt)),
        "trxr_max_k": float(np.max(dt)),
        "chi2_share": float(chi2_share),
    }
    within = (
        max(out["g_median_sigma"], out["trxr_median_sigma"]) < rule.NEGLIGIBLE_MEDIAN_SIGMA
        and max(out["g_max_sigma"], out["trxr_max_sigma"]) < rule.NEGLIGIBLE_MAX_SIGMA
    )
    small = (
        out["g_median_fraction"] < rule.NEGLIGIBLE_G_FRACTION
        and out["trxr_median_k"] < rule.NEGLIGIBLE_TRXR_K
        and out["g_max_fraction"] < 10 * rule.NEGLIGIBLE_G_FRACTION
        and out["trxr_max_k"] < 10 * rule.NEGLIGIBLE_TRXR_K
    )
    substantial = chi2_share > rule.NEGLIGIBLE_MAX_CHI2_SHARE
    return out | {"matters": substantial or not (within or small)}


def _worst_impact(impacts: list[dict[str, Any]]) -> dict[str, Any]:
    """The largest of each statistic over feeds; the effect matters if it does in one."""
    out: dict[str, Any] = {k: max(i[k] for i in impacts) for k in impacts[0] if k != "matters"}
    return out | {"matters": any(i["matters"] for i in impacts)}


def effect_strength(
    case: Case, effect: Hidden, prior_sigma_k: float = PRIOR_SIGMA_K
) -> dict[str, Any]:
    """How visible one hidden effect is, alone, in the independent model without noise.

    The noise-free autos with only ``effect`` hidden, ``D = G(t) (Tsky' + Trxr (1 + e_1 s))``,
    are fitted channel by channel by the clean model ``G Tsky + n`` (the independent
    model's own Tsky, so no model error enters) with radiometer weights ``dnu dt / D^2``
    and the receiver prior ``n = Trxr G +- G sigma``. The minimum chi-square is the
    Delta chi^2 a perfect template of the effect could gain; ``dbic`` subtracts
    ``k ln N`` (:func:`effect_parameters`; ``N`` data plus prior rows). A cable
    reflection is absorbed by the per-channel gain, so it is judged where it can be seen,
    in the bandpass domain: the clean fit's ``G(nu)``, with its sigma, against a smooth
    bandpass without and with the ripple of the true delay (:func:`ripple_template_chi2`),
    ``N`` the antenna-pols' gains.

    Parameters
    ----------
    case
        The case (sampling, beam, antennas, pols).
    effect
        One of its hidden effects.
    prior_sigma_k
        1-sigma of the receiver prior, kelvin.

    Returns
    -------
    dict
        ``chi2``, ``k``, ``ndata``, ``dbic`` and ``visible`` (``dbic`` above
        :data:`BIC_THRESHOLD`; a cable reflection's in the bandpass domain); ``impact``, how
        far the clean model's ``G`` and ``Trxr`` land from the truth
        (:func:`product_impact`, worst feed), and ``matters``: an effect of the instrument,
        or one of the forward model (:data:`FORWARD_MODEL_EFFECTS`) whose impact is not
        negligible.
    """
    single = Case(
        case.name,
        case.span,
        (effect,),
        case.seed,
        case.beam,
        case.antennas,
        case.pols,
        case.node_spacing_s,
    )
    kw = simulation_kwargs(single)
    freqs = kw["freqs_hz"]
    jds = _integration_jds(case.span)
    ntime = jds.size
    gain0 = np.asarray(kw["G0"])
    drift = np.asarray(kw["drift"](None)) if "drift" in kw else np.zeros(ntime)
    gain = gain0[None, :] * (1.0 + drift[:, None])
    trxr = np.asarray(kw["trxr_k"])
    s_time = np.linspace(-1.0, 1.0, ntime) if ntime > 1 else np.zeros(1)
    trxr_t = trxr[None, :] * (1.0 + kw.get("noise_drift", 0.0) * s_time[:, None])
    chi2 = bandpass_chi2 = 0.0
    impacts: list[dict[str, Any]] = []
    for pol in case.pols:
        common = {"node_spacing_s": case.node_spacing_s}
        clean = sim.independent_tsky(freqs, jds, pol, case.beam, MODEL_TGND_K, **common)
        true = sim.independent_tsky(
            freqs,
            jds + kw.get("clock_offset_s", 0.0) / 86400.0,
            pol,
            case.beam,
            kw.get("tgnd_k", MODEL_TGND_K),
            sky=kw.get("sky"),
            beam_width=kw.get("beam_width", 0.0),
            beam_width_mode=kw.get("beam_width_mode", "fwhm"),
            sky_frame=kw.get("sky_frame", "apparent"),
            **common,
        )
        feed_gain = kw.get("feed_gain")
        for ia in range(len(case.antennas)):
            own = 1.0 if feed_gain is None else feed_gain[ia, case.pols.index(pol)][:, None]
            fed = gain * own
            fit = _clean_model_fit(fed * (true + trxr_t), clean, gain0, trxr, prior_sigma_k)
            chi2 += fit["chi2"]
            if effect.name == "cable_reflection":
                bandpass_chi2 += ripple_template_chi2(
                    freqs, fit["g"], fit["sigma_g"], effect.params["tau_ns"] * 1e-9
                )
            share = fit["chi2"] / (ntime * freqs.size)
            impacts.append(product_impact(fit, fed.mean(axis=0), trxr, share))
    nfeeds = len(case.antennas) * len(case.pols)
    ndata = nfeeds * freqs.size * (ntime + 1)
    span_h = (ntime - 1) * case.span.integration_s / 3600.0
    k = effect_parameters(effect, ntime, nfeeds, span_h)
    if effect.name == "cable_reflection":  # seen in the bandpass domain: N = the gains
        chi2, ndata = bandpass_chi2, nfeeds * freqs.size
    dbic = chi2 - k * math.log(ndata)
    visible = dbic > BIC_THRESHOLD
    impact = _worst_impact(impacts)
    matters = effect.name not in FORWARD_MODEL_EFFECTS or bool(impact["matters"])
    return {
        "chi2": chi2,
        "k": k,
        "ndata": ndata,
        "dbic": dbic,
        "visible": bool(visible),
        "impact": impact,
        "matters": matters,
    }


# ---------------------------------------------------------------------------------------
# diagnosis and score
# ---------------------------------------------------------------------------------------
def score_names(
    hidden: Sequence[str],
    named: Sequence[str],
    negligible: Sequence[str] = (),
    visible: Sequence[str] | None = None,
    matters: Sequence[str] | None = None,
) -> dict[str, Any]:
    """Score names exactly: the named set must equal the hidden set.

    Parameters
    ----------
    hidden
        The hidden effects.
    named
        The effects the diagnosis names (``diagnosis.json`` ``effects``).
    negligible
        Effects it reports as "detected, negligible" (not named).
    visible
        The hidden effects strong enough to be seen (:func:`effect_strength`; default all).
    matters
        The hidden effects that move the products by the truth (:func:`effect_strength`'s
        ``matters``; default all).

    Returns
    -------
    dict
        ``exact`` (named == hidden), ``extras`` (named, not hidden), ``misses`` (hidden,
        not named), ``exact_or_negligible`` (named plus reported "detected, negligible" ==
        hidden: a negligible report of an effect that is not hidden counts against it),
        ``exact_visible`` (named == the visible
        hidden effects), ``exact_matters`` (every hidden effect that matters named, and
        nothing named that is not hidden: the issue's rule that an effect too small to
        matter is not added to the model, judged from the truth) and ``correct``: nothing
        named that is not hidden, and every visible hidden effect found, named or reported
        "detected, negligible" (a hidden effect no perfect template could see may be found
        or not).
    """
    h, n = set(hidden), set(named)
    vis = h if visible is None else set(visible)
    must = h if matters is None else set(matters)
    found = n | (set(negligible) & h)
    return {
        "exact": h == n,
        "extras": sorted(n - h),
        "misses": sorted(h - n),
        "exact_or_negligible": n | set(negligible) == h,
        "exact_visible": n == vis,
        "exact_matters": must <= n <= h,
        "correct": n <= h and vis <= found,
    }


def _gap(gap: dict[str, Any] | None) -> dict[str, Any]:
    gap = gap or {}
    keys = ("reduced_chi2", "integration_jitter", "time_mode_power", "bandpass_reduced_chi2")
    return {k: gap.get(k) for k in keys}


def _step_row(step: dict[str, Any]) -> dict[str, Any]:
    params = {
        k: {"value": v.get("value"), "sigma": v.get("sigma")}
        | ({"adopted": v["adopted"]} if "adopted" in v else {})
        for k, v in step.get("parameters", {}).items()
    }
    return {
        "name": step.get("name"),
        "statistic": step.get("statistic"),
        "delta_chi2": step.get("delta"),
        "k": step.get("k"),
        "p_value": step.get("p_value"),
        "overdispersion": step.get("overdispersion"),
        "time_basis": step.get("time_basis"),
        "parameters": params,
        "candidates": step.get("candidates"),
        "gap_before": _gap(step.get("gap_before")),
        "gap_after": _gap(step.get("gap_after")),
        "negligible": step.get("negligible"),
        "absorbed_by_unexplained": step.get("absorbed_by_unexplained"),
        "signal_rms": step.get("signal_rms"),
        "below_model_accuracy": bool(step.get("below_model_accuracy")),
        "product_impact": _impact(step.get("product_impact")),
        "final_negligible": step.get("final_negligible"),
        "final_product_impact": _impact(step.get("final_product_impact")),
        "dropped_in_backward_pass": step.get("dropped_in_backward_pass"),
        "superseded_by": step.get("superseded_by"),
        "per_feed": step.get("per_feed"),
        "band_consistency": step.get("band_consistency"),
    }


def _impact(impact: dict[str, Any] | None) -> dict[str, Any] | None:
    """The median and largest change of ``G`` and ``Trxr`` in total sigma, and the median
    absolute change (relative for ``G``, kelvin for ``Trxr``)."""
    if not impact:
        return None
    keys = (
        "median_change_over_sigma",
        "max_change_over_sigma",
        "median_abs_relative_change",
        "median_abs_change_K",
    )
    return {
        name: {k: impact[name].get(k) for k in keys}
        for name in ("G", "Trxr")
        if isinstance(impact.get(name), dict)
    }


def run_case(
    case: Case,
    folder: str | Path,
    *,
    prior_sigma_k: float = PRIOR_SIGMA_K,
    nside: int = 64,
    max_steps: int = 5,
) -> dict[str, Any]:
    """Simulate a case, diagnose it with :func:`autocal.diagnosis.run.run_diagnosis`, score it.

    Parameters
    ----------
    case
        The case.
    folder
        Working folder: the data, the prior and the diagnosis (``<name>.diagnosis/``).
    prior_sigma_k
        1-sigma of the per-channel receiver prior (the true ``Trxr``), kelvin.
    nside
        HEALPix resolution of the diagnosis's templates.
    max_steps
        Most effects the diagnosis adds.

    Returns
    -------
    dict
        The case, the names (``named``, ``exact``, ``extras``, ``misses``), the initial and
        final gaps, every step with its statistics, ``last_rejected``, the final
        parameters, and ``timings_s``.
    """
    from autocal.diagnosis.run import DiagnoseConfig, run_diagnosis

    folder = Path(folder)
    t0 = time.perf_counter()
    files = simulate_case(case, folder, prior_sigma_k)
    t_sim = time.perf_counter() - t0
    strength = {e.name: effect_strength(case, e, prior_sigma_k) for e in case.effects}
    t_strength = time.perf_counter() - t0 - t_sim
    config = DiagnoseConfig(
        inputs=[str(files["data"])],
        sky="gsm2008",
        beam=case.beam,
        tgnd_k=MODEL_TGND_K,
        nside=nside,
        trxr_prior=str(files["prior"]),
        max_steps=max_steps,
    )
    out = folder / f"{case.name}.diagnosis"
    t1 = time.perf_counter()
    run_diagnosis(config, out)
    t_diag = time.perf_counter() - t1
    doc = json.loads((out / "diagnosis.json").read_text())
    summary = json.loads((out / "summary.json").read_text())
    named = list(doc.get("effects", []))
    negligible = list(doc.get("negligible", []))
    visible = [name for name, st in strength.items() if st["visible"]]
    matters = [name for name, st in strength.items() if st["matters"]]
    cfg = doc.get("config", {})
    unexplained = doc.get("unexplained")
    return {
        "case": case.to_dict(),
        "hidden": list(case.hidden),
        "visible": visible,
        "matters": matters,
        "strength": strength,
        "named": named,
        "negligible": negligible,
        "absorbed": list(doc.get("absorbed", [])),
        "below_model_accuracy": list(doc.get("below_model_accuracy", [])),
        "indistinguishable": None
        if not doc.get("indistinguishable")
        else {
            k: doc["indistinguishable"][k]
            for k in ("step", "candidates", "lead_sigma", "message")
            if k in doc["indistinguishable"]
        },
        **score_names(case.hidden, named, negligible, visible, matters),
        "unexplained": None
        if not unexplained
        else {
            k: unexplained.get(k)
            for k in ("reduced_chi2", "excess_sigma", "time", "frequency", "message")
        },
        "initial_reduced_chi2": (doc.get("initial_gap") or {}).get("reduced_chi2"),
        "final_reduced_chi2": (doc.get("final_gap") or {}).get("reduced_chi2"),
        "initial_gap": _gap(doc.get("initial_gap")),
        "final_gap": _gap(doc.get("final_gap")),
        "steps": [_step_row(st) for st in doc.get("steps", [])],
        "last_rejected": cfg.get("last_rejected"),
        "failed_candidates": cfg.get("failed_candidates"),
        "jitter_tests": cfg.get("jitter_tests"),
        "restarts": cfg.get("restarts"),
        "outlier_flagging": cfg.get("outlier_flagging"),
        "final_parameters": doc.get("final_parameters"),
        "diagnose_config": {
            "beam": case.beam,
            "nside": nside,
            "tgnd_k": MODEL_TGND_K,
            "trxr_prior": "true Trxr(nu), per-channel CSV",
            "trxr_prior_sigma_k": prior_sigma_k,
            "bic_threshold": cfg.get("bic_threshold"),
            "alpha": cfg.get("alpha"),
            "max_steps": max_steps,
        },
        "timings_s": {
            "simulate": round(t_sim, 3),
            "strength": round(t_strength, 3),
            "diagnosis": round(t_diag, 3),
            **{f"diagnosis_{k}": v for k, v in summary.get("timings_s", {}).items()},
        },
    }


# ---------------------------------------------------------------------------------------
# the suite
# ---------------------------------------------------------------------------------------
#: Tsky node spacing of the HERA-beam cases (the independent HERA beam costs ~0.3 s per
#: evaluation time): exact at every 15-min integration of a day, a spline through nodes
#: 120 s apart for the 10.7-s integrations of a short span.
HERA_NODE_SPACING_S = {"day": None, "short": 120.0}

_PAIRS = (
    ("gain_drift:linear", "cable_reflection"),
    ("noise_drift", "sky_spectral_index"),
    ("beam_width:stretch", "cable_reflection"),
    ("gain_drift:diurnal", "ground_temperature"),
    ("missing_cmb", "cable_reflection"),
    ("gain_jitter", "noise_drift"),
)


def case_seed(name: str, seed: int = SUITE_SEED) -> int:
    """Return the fixed seed of the case called ``name`` (CRC-32 of the suite seed and name).

    A case's seed depends on its name only, so adding or removing cases leaves the others'
    data and parameters unchanged.
    """
    return zlib.crc32(f"{seed}:{name}".encode())


def suite_plan(seed: int = SUITE_SEED) -> list[Case]:
    """Return the fixed-seed suite (54 cases).

    * 8 clean controls: the dipole over a day (1 antenna ee, twice with different noise;
      2 antennas ee + nn), over a short span at LST 3.23 h (1 antenna ee; 2 antennas
      ee + nn) and at LST 17.5 h (Galactic centre up), the HERA beam over a day and a
      short span;
    * every effect alone over a day (dipole, ee): ``gain_drift`` linear and diurnal,
      ``gain_jitter`` twice, ``ground_temperature`` twice, ``beam_width`` as an FWHM
      change and twice as a stretch, the others once (15 cases);
    * the effects alone over a short span (dipole, ee; 9 cases): the time-structured ones,
      ``beam_width`` both ways, and three time-constant ones that a short span cannot
      show (expected misses, see :func:`effect_strength`);
    * nn, two antennas or the HERA beam (7 cases);
    * every antenna-pol its own gain jitter: 2 antennas x ee + nn over a short span, 3
      antennas (ee) over a day; its own gain drift, 2 antennas x ee + nn over a short span
      (3 cases); a clock 30-90 s behind over a day (1 case); the sky in J2000 instead of
      the frame of the date, over a day and a short span (2 cases, hidden as
      ``timing_offset``, the catalogue entry for a sky in a frame turned in right
      ascension);
    * pairs: the 6 of autocal's own suite over a day, 2 over a short span, 1 with the
      HERA beam over a day (9 cases).

    Parameters
    ----------
    seed
        Suite seed (:func:`case_seed`).

    Returns
    -------
    list of Case
        The cases, in order.
    """
    plan: list[dict[str, Any]] = []

    def add(name: str, effects: Sequence[str], span: str, **kw: Any) -> None:
        plan.append({"name": name, "effects": tuple(effects), "span": span, **kw})

    two = {"antennas": (0, 1), "pols": ("ee", "nn")}
    hera_day = {"beam": "hera", "node_spacing_s": HERA_NODE_SPACING_S["day"]}
    hera_short = {"beam": "hera", "node_spacing_s": HERA_NODE_SPACING_S["short"]}
    # clean controls
    add("clean_day", (), "day")
    add("clean_day_b", (), "day")
    add("clean_day_2ant_eenn", (), "day", **two)
    add("clean_short", (), "short")
    add("clean_short_2ant_eenn", (), "short", **two)
    add("clean_short_lst17", (), "short17")
    add("clean_day_hera", (), "day", **hera_day)
    add("clean_short_hera", (), "short", **hera_short)
    # every effect alone over a day
    for name, eff in (
        ("gain_drift_linear_day", "gain_drift:linear"),
        ("gain_drift_diurnal_day", "gain_drift:diurnal"),
        ("gain_jitter_day", "gain_jitter"),
        ("gain_jitter_day_b", "gain_jitter"),
        ("noise_drift_day", "noise_drift"),
        ("cable_reflection_day", "cable_reflection"),
        ("sky_spectral_index_day", "sky_spectral_index"),
        ("ground_temperature_day", "ground_temperature"),
        ("ground_temperature_day_b", "ground_temperature"),
        ("beam_width_fwhm_day", "beam_width:fwhm"),
        ("beam_width_stretch_day", "beam_width:stretch"),
        ("beam_width_stretch_day_b", "beam_width:stretch"),
        ("missing_cmb_day", "missing_cmb"),
        ("sky_scale_day", "sky_scale"),
        ("sky_offset_day", "sky_offset"),
    ):
        add(name, (eff,), "day")
    # alone over a short span
    for name, eff in (
        ("gain_drift_short", "gain_drift:linear"),
        ("gain_jitter_short", "gain_jitter"),
        ("noise_drift_short", "noise_drift"),
        ("cable_reflection_short", "cable_reflection"),
        ("beam_width_fwhm_short", "beam_width:fwhm"),
        ("beam_width_stretch_short", "beam_width:stretch"),
        ("ground_temperature_short", "ground_temperature"),
        ("missing_cmb_short", "missing_cmb"),
        ("sky_spectral_index_short", "sky_spectral_index"),
    ):
        add(name, (eff,), "short")
    # nn, two antennas, the HERA beam
    add("noise_drift_day_2ant_eenn", ("noise_drift",), "day", **two)
    add("gain_jitter_short_2ant_eenn", ("gain_jitter",), "short", **two)
    add("ground_temperature_day_nn", ("ground_temperature",), "day", pols=("nn",))
    add("gain_drift_day_hera", ("gain_drift:diurnal",), "day", **hera_day)
    add("cable_reflection_day_hera", ("cable_reflection",), "day", **hera_day)
    add("missing_cmb_day_hera", ("missing_cmb",), "day", **hera_day)
    add("noise_drift_short_hera", ("noise_drift",), "short", **hera_short)
    # every antenna-pol its own gain jitter (the common series is not the answer)
    add("antenna_gain_jitter_short_2ant_eenn", ("antenna_gain_jitter",), "short", **two)
    add("antenna_gain_jitter_day_3ant", ("antenna_gain_jitter",), "day", antennas=(0, 1, 2))
    add("antenna_gain_drift_short_2ant_eenn", ("antenna_gain_drift",), "short", **two)
    add("timing_offset_day", ("timing_offset",), "day")
    # the sky in J2000 instead of the frame of the date (issue 21's implementation mistake)
    add("sky_frame_j2000_day", ("timing_offset:j2000",), "day")
    add("sky_frame_j2000_short", ("timing_offset:j2000",), "short")
    # pairs
    for a, b in _PAIRS:
        add(f"{a.split(':')[0]}+{b}_day", (a, b), "day")
    add("gain_drift+cable_reflection_short", ("gain_drift:linear", "cable_reflection"), "short")
    add("gain_jitter+noise_drift_short", ("gain_jitter", "noise_drift"), "short")
    add(
        "gain_drift+cable_reflection_day_hera",
        ("gain_drift:linear", "cable_reflection"),
        "day",
        **hera_day,
    )
    spans = {**SPANS, "short17": Span("short17", 17.5, 31.0, 10.7)}
    return [
        make_case(
            p["name"],
            p["effects"],
            spans[p["span"]],
            case_seed(p["name"], seed),
            beam=p.get("beam", "dipole"),
            antennas=p.get("antennas", (0,)),
            pols=p.get("pols", ("ee",)),
            node_spacing_s=p.get("node_spacing_s"),
        )
        for p in plan
    ]
