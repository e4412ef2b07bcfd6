"""Observations with hidden effects: the test generator of the diagnosis workflow.

A :class:`HiddenCase` names up to two physical effects of the catalogue
(:mod:`autocal.diagnosis.effects`) with their true parameters; :class:`HiddenGenerator` simulates
the autos of an observation that contains them (through the *true* sky, beam and
receiver, with radiometer noise) while the model the diagnosis starts from does not,
writes them as UVH5 with a ``.truth.json`` beside, and scores a diagnosis against the
truth (:func:`score`). :func:`draw_case` draws random parameters in the ranges the
workflow is specified for:

======================  =============================================================
``gain_drift``          profile a (linear), b or c (diurnal sines), amplitude 2-10 %
``gain_jitter``         white broadband gain fluctuations, 0.1-1 % rms per integration
``noise_drift``         linear in LST, 1-5 % of Trxr
``cable_reflection``    ``1 + a cos(2 pi nu tau + phi)``: a 1e-3-1e-2, tau 100-400 ns
``sky_spectral_index``  index off by +-(0.05-0.2)
``ground_temperature``  ground at 200-350 K while the model assumes 300 K
``beam_width``          true beam wider or narrower by 5-15 %
``missing_cmb``         no CMB in the data
======================  =============================================================
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from autocal.core.coords import night_epoch
from autocal.core.observation import Observation
from autocal.diagnosis.catalogue import catalogue
from autocal.diagnosis.effects import Effect, ScaledBeam, SkyTemplates, sky_templates
from autocal.diagnosis.stepwise import diagnose
from autocal.errors import AutocalError
from autocal.io.uvh5 import read_uvh5, write_uvh5
from autocal.simulate.mock import (
    SimulationConfig,
    gain_profile,
    hera_h1c_bandpass,
    mock_autos,
    simulate,
)
from autocal.sky.beam_names import get_beam
from autocal.tsky.compute import compute_tsky

logger = logging.getLogger(__name__)

#: The effects the generator can hide (``clean``: none).
HIDDEN_KINDS = (
    "clean",
    "gain_drift",
    "gain_jitter",
    "noise_drift",
    "cable_reflection",
    "sky_spectral_index",
    "ground_temperature",
    "beam_width",
    "missing_cmb",
)
#: Effects only a receiver prior makes identifiable (:mod:`autocal.diagnosis.effects`).
NEEDS_PRIOR = ("sky_spectral_index", "ground_temperature", "missing_cmb")


class HiddenError(AutocalError):
    """Invalid hidden-effect case."""


@dataclass(frozen=True)
class HiddenEffect:
    """One hidden effect: its catalogue name and true parameters."""

    name: str
    params: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class HiddenCase:
    """A simulated observation's hidden effects and noise seed."""

    seed: int
    effects: tuple[HiddenEffect, ...] = ()
    bandpass: str = "flat"

    @property
    def names(self) -> tuple[str, ...]:
        """Names of the hidden effects."""
        return tuple(e.name for e in self.effects)

    def to_dict(self) -> dict[str, Any]:
        """JSON form."""
        return {
            "seed": self.seed,
            "bandpass": self.bandpass,
            "effects": [{"name": e.name, "params": e.params} for e in self.effects],
        }


def draw_effect(name: str, rng: np.random.Generator) -> HiddenEffect:
    """Draw one hidden effect with random parameters in the specified ranges."""
    sign = float(rng.choice([-1.0, 1.0]))
    if name == "gain_drift":
        profile = str(rng.choice(["a", "b", "c"]))
        return HiddenEffect(name, {"profile": profile, "amplitude": rng.uniform(0.02, 0.1)})
    if name == "noise_drift":
        return HiddenEffect(name, {"e_1": sign * rng.uniform(0.01, 0.05)})
    if name == "gain_jitter":
        return HiddenEffect(
            name, {"rms": rng.uniform(1e-3, 1e-2), "seed": int(rng.integers(0, 2**31 - 1))}
        )
    if name == "cable_reflection":
        return HiddenEffect(
            name,
            {
                "a": rng.uniform(1e-3, 1e-2),
                "tau_ns": rng.uniform(100.0, 400.0),
                "phi": rng.uniform(-math.pi, math.pi),
            },
        )
    if name == "sky_spectral_index":
        return HiddenEffect(name, {"dbeta": sign * rng.uniform(0.05, 0.2)})
    if name == "ground_temperature":
        return HiddenEffect(name, {"tgnd_K": rng.uniform(200.0, 350.0)})
    if name == "beam_width":
        return HiddenEffect(name, {"w": sign * rng.uniform(0.05, 0.15)})
    if name == "missing_cmb":
        return HiddenEffect(name, {"cmb_factor": -1.0})
    raise HiddenError(f"unknown hidden effect {name!r}: use one of {HIDDEN_KINDS[1:]}")


def draw_case(names: tuple[str, ...] | list[str], seed: int, bandpass: str = "flat") -> HiddenCase:
    """Draw a case hiding ``names`` (empty or ``("clean",)``: a clean control)."""
    rng = np.random.default_rng(seed)
    chosen = [n for n in names if n != "clean"]
    return HiddenCase(seed, tuple(draw_effect(n, rng) for n in chosen), bandpass)


def jitter_series(params: dict[str, Any], ntime: int) -> np.ndarray:
    """Return the true per-integration gain factors of a ``gain_jitter`` effect (mean 1)."""
    eps = np.random.default_rng(int(params["seed"])).normal(0.0, params["rms"], ntime)
    return (1 + eps) / np.mean(1 + eps)


def _angle(x: float) -> float:
    return float((x + math.pi) % (2 * math.pi) - math.pi)


class HiddenGenerator:
    """Simulate observations with hidden effects on one grid, and score diagnoses.

    Parameters
    ----------
    config
        Sampling, sky, beam, receiver and noise (:class:`autocal.simulate.mock.SimulationConfig`;
        its ``gain`` and ``bandpass`` are ignored: the case sets them).
    tgnd_k
        Ground temperature of the *model* (kelvin).
    """

    def __init__(self, config: SimulationConfig, tgnd_k: float = 300.0) -> None:
        self.config = config
        self.tgnd_k = tgnd_k
        base = config.model_copy(update={"noise": False, "gain": "constant", "bandpass": "flat"})
        self.base, _ = simulate(base)
        self.templates: SkyTemplates = sky_templates(
            config.sky,
            config.beam,
            config.site,
            self.base.freqs,
            self.base.lsts,
            pols=tuple(config.pols),
            tgnd=tgnd_k,
            nside=config.nside,
            epoch=night_epoch(self.base.jds, self.base.site.lon_deg),
        )
        self.bandwidth_time = config.noise_dnu_hz * config.noise_dt_s

    # truth ------------------------------------------------------------------------------

    def _scaled_beam_tsky(self, w: float) -> np.ndarray:
        cfg, obs = self.config, self.base
        out = []
        for pol in cfg.pols:
            beam = ScaledBeam(base=get_beam(cfg.beam, pol), factor=1.0 + w)
            res = compute_tsky(
                cfg.sky,
                beam,
                cfg.site,
                obs.freqs,
                obs.lsts,
                tgnd=self.tgnd_k,
                nside=cfg.nside,
                epoch=night_epoch(obs.jds, obs.site.lon_deg),
                pol=pol,
                cache=False,
                progress=False,
            )
            out.append(res.tsky)
        return np.stack(out)

    def observation(self, case: HiddenCase) -> Observation:
        """Simulate the observation of ``case`` (radiometer noise from its seed)."""
        tpl, obs = self.templates, self.base
        f, lsts = obs.freqs, obs.lsts
        tsky = tpl.total.copy()
        gain = np.ones((obs.ntime, obs.nfreq))
        trxr: np.ndarray | float = self.config.trxr_k
        for eff in case.effects:
            p = eff.params
            if eff.name == "gain_drift":
                gain = gain * gain_profile(p["profile"], lsts, amplitude=p["amplitude"])[:, None]
            elif eff.name == "gain_jitter":
                gain = gain * jitter_series(p, obs.ntime)[:, None]
            elif eff.name == "noise_drift":
                s = 2 * (lsts - lsts.min()) / (lsts.max() - lsts.min()) - 1
                trxr = (self.config.trxr_k * (1 + p["e_1"] * s))[:, None] * np.ones(f.size)
            elif eff.name == "cable_reflection":
                ripple = 1 + p["a"] * np.cos(2 * np.pi * f * p["tau_ns"] * 1e-9 + p["phi"])
                gain = gain * ripple[None, :]
            elif eff.name == "sky_spectral_index":
                tsky = tsky + tpl.galactic * ((f / tpl.nu0) ** p["dbeta"] - 1)
            elif eff.name == "ground_temperature":
                tsky = tsky + (p["tgnd_K"] - self.tgnd_k) * tpl.f_below[:, None, :]
            elif eff.name == "beam_width":
                tsky = tsky + (self._scaled_beam_tsky(p["w"]) - tpl.total)
            elif eff.name == "missing_cmb":
                tsky = tsky - tpl.cmb
            else:
                raise HiddenError(f"unknown hidden effect {eff.name!r}")
        if case.bandpass == "hera-h1c":
            gain = gain * hera_h1c_bandpass(f)[None, :]
        elif case.bandpass != "flat":
            raise HiddenError(f"unknown bandpass {case.bandpass!r}: flat or hera-h1c")
        data = mock_autos(
            tsky,
            gain,
            trxr,
            nant=obs.nant,
            bandwidth_time=self.bandwidth_time if self.config.noise else None,
            rng=np.random.default_rng(case.seed),
        )
        return dataclasses.replace(obs, data=data)

    def write(self, case: HiddenCase, path: str | Path) -> Path:
        """Write the case as UVH5 at ``path`` and its truth as ``<path>.truth.json``."""
        path = Path(path)
        write_uvh5(
            self.observation(case),
            path,
            history="autocal hidden-effect test case",
            overwrite=True,
        )
        truth = {
            **case.to_dict(),
            "simulation": self.config.model_dump(),
            "model_tgnd_K": self.tgnd_k,
        }
        path.with_name(path.name + ".truth.json").write_text(json.dumps(truth, indent=2))
        return path

    # expectations -----------------------------------------------------------------------

    def expected(self, case: HiddenCase, step: dict[str, Any]) -> dict[str, float]:
        """Return the true values of an accepted step's parameters (diagnosis convention).

        Drifts are compared through the least-squares projection of the true profile on
        the accepted variant's time basis (``1`` plus its ``k`` functions, relative to
        the constant term).
        """
        lsts = self.base.lsts
        eff = next((e for e in case.effects if e.name == step["name"]), None)
        if eff is None:
            return {}
        p = eff.params
        if step["name"] in ("gain_drift", "noise_drift"):
            if step["name"] == "gain_drift":
                true = gain_profile(p["profile"], lsts, amplitude=p["amplitude"])
            else:
                s = 2 * (lsts - lsts.min()) / (lsts.max() - lsts.min()) - 1
                true = 1 + p["e_1"] * s
            names = [k for k in step["parameters"] if k != "order"]
            variant = _variant(step["name"], step.get("time_basis", "legendre"), len(names))
            basis = np.vstack([np.ones(lsts.size), variant.time_basis(lsts)])
            coef = np.linalg.lstsq(basis.T, true, rcond=None)[0]
            return dict(zip(variant.params, coef[1:] / coef[0], strict=True))
        if step["name"] == "gain_jitter":
            series = jitter_series(p, lsts.size)
            return {"rms": float(np.std(series))}
        if step["name"] == "ground_temperature":
            return {"dT_gnd": p["tgnd_K"] - self.tgnd_k}
        if step["name"] == "cable_reflection":
            return {"a": p["a"], "tau_ns": p["tau_ns"], "phi": p["phi"]}
        return {k: float(v) for k, v in p.items()}


def _variant(name: str, basis: str, nparams: int) -> Effect:
    for eff in catalogue(max_drift_order=max(nparams, 2)):
        if eff.name == name and eff.basis == basis and len(eff.params) == nparams:
            return eff
    raise HiddenError(f"no {basis} variant of {name} with {nparams} parameters")


@dataclass(frozen=True)
class Score:
    """How a diagnosis did on a hidden case."""

    hidden: tuple[str, ...]
    found: tuple[str, ...]
    named: bool
    parameters_ok: bool
    gap_shrinks: bool
    pulls: dict[str, float]

    @property
    def ok(self) -> bool:
        """Named exactly the hidden effects, recovered them, and shrank the gap."""
        return self.named and self.parameters_ok and self.gap_shrinks

    def to_dict(self) -> dict[str, Any]:
        """JSON form."""
        return {**dataclasses.asdict(self), "ok": self.ok}


def score(
    generator: HiddenGenerator, case: HiddenCase, diagnosis: Any, max_pull: float = 3.0
) -> Score:
    """Score a diagnosis: names, parameters (``|value - truth| < max_pull sigma``), gaps.

    Names: every named effect must be hidden, and every hidden effect named or reported
    as detected but negligible (``Diagnosis.negligible``). Parameters are those of the
    final joint fit (``Diagnosis.final_parameters``).

    A parameter's pull is ``(value - truth) / sigma``; for ``missing_cmb`` the adopted
    hypothesis must equal the truth; phases are compared modulo ``2 pi``.
    """
    found = tuple(diagnosis.effects)
    negligible = set(getattr(diagnosis, "negligible", []))
    # every effect named is hidden, and every hidden effect is named or reported as
    # detected but negligible for the products (not added to the model)
    named = set(found) <= set(case.names) and set(case.names) <= set(found) | negligible
    named = named and len(found) == len(set(found))
    pulls: dict[str, float] = {}
    for st in diagnosis.steps:
        if "dropped_in_backward_pass" in st:
            continue
        final = diagnosis.final_parameters.get(st["name"], st["parameters"])
        truth = generator.expected(case, {**st, "parameters": final})
        for par, value in truth.items():
            got = final.get(par)
            if got is None:
                continue
            if par == "cmb_factor":
                pulls[f"{st['name']}.{par}"] = 0.0 if got.get("adopted") == value else math.inf
                continue
            diff = got["value"] - value
            if par == "phi":
                diff = _angle(diff)
            sigma = got["sigma"] if got["sigma"] > 0 else math.inf
            pulls[f"{st['name']}.{par}"] = float(diff / sigma)
    params_ok = named and all(abs(v) < max_pull for v in pulls.values())
    gap_ok = True
    for st in diagnosis.steps:
        key = "bandpass_reduced_chi2" if st["name"] == "cable_reflection" else "reduced_chi2"
        before, after = st["gap_before"].get(key), st["gap_after"].get(key)
        gap_ok &= before is not None and after is not None and after < before
    return Score(case.names, found, named, params_ok, bool(gap_ok), pulls)


def run_case(
    generator: HiddenGenerator,
    case: HiddenCase,
    workdir: str | Path,
    *,
    trxr_prior_sigma: float = 0.1,
) -> dict[str, Any]:
    """Write ``case`` as UVH5, read it back, diagnose it and score the diagnosis.

    The diagnosis gets the true receiver temperature as a prior (``trxr_prior_sigma``
    kelvin), which the time-constant effects need (:data:`NEEDS_PRIOR`).
    """
    path = generator.write(case, Path(workdir) / f"hidden_{case.seed}.uvh5")
    obs = read_uvh5(path)
    diag = diagnose(
        obs,
        generator.templates,
        trxr_prior=generator.config.trxr_k,
        trxr_prior_sigma=trxr_prior_sigma,
    )
    sc = score(generator, case, diag)
    return {
        "case": case.to_dict(),
        "score": sc.to_dict(),
        "initial_reduced_chi2": diag.initial_gap["reduced_chi2"],
        "final_reduced_chi2": diag.final_gap["reduced_chi2"],
        "steps": [
            {k: st[k] for k in ("name", "parameters", "statistic", "p_value")} for st in diag.steps
        ],
        "indistinguishable": None
        if diag.indistinguishable is None
        else {k: diag.indistinguishable[k] for k in ("step", "candidates", "message")},
    }


def suite_cases(n: int = 42, seed: int = 2026) -> list[HiddenCase]:
    """Return the fixed-seed suite: clean controls, single effects, pairs, bandpasses.

    Cases cycle through clean, each single effect of :data:`HIDDEN_KINDS`, pairs of
    effects, and a clean control with the HERA H1C bandpass (a reflection-free but
    structured bandpass that must not be taken for a reflection).
    """
    singles = list(HIDDEN_KINDS)
    pairs = [
        ("gain_drift", "cable_reflection"),
        ("noise_drift", "sky_spectral_index"),
        ("beam_width", "cable_reflection"),
        ("gain_drift", "ground_temperature"),
        ("missing_cmb", "cable_reflection"),
        ("gain_jitter", "noise_drift"),
    ]
    plan: list[tuple[tuple[str, ...], str]] = [((s,), "flat") for s in singles]
    plan += [(p, "flat") for p in pairs]
    plan += [(("clean",), "hera-h1c"), (("cable_reflection",), "hera-h1c")]
    rng = np.random.default_rng(seed)
    seeds = rng.integers(0, 2**31 - 1, size=n)
    return [
        draw_case(plan[i % len(plan)][0], int(seeds[i]), plan[i % len(plan)][1]) for i in range(n)
    ]
