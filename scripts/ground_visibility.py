"""Where a hidden ground-temperature error's chi-square goes between the suite and the search.

The independent suite (``scripts/diagnose_independent_suite.py``) calls a hidden effect
visible when a *perfect* template fitted to noise-free data, with the independent model's own
Tsky as the clean model, gains Delta BIC > 10 (``tests.independent_effects.effect_strength``).
The search fits autocal's template on top of autocal's Tsky to noisy, flagged data. For one
suite case (default ``ground_temperature_day``) this script splits the difference:

1. the templates: autocal's ``f_below(nu)`` (constant in time) against the independent model's
   exact ground part, ``(Tsky(Tgnd) - Tsky(300 K)) / (Tgnd - 300 K)`` at every integration
   (its hard horizon at moving pixel centres makes it flicker in time);
2. the search's candidate fit (per-channel ``G``, ``n``, the per-channel receiver prior, the
   flagging stage, radiometer weights from the starting model: as
   :func:`autocal.diagnosis.stepwise.diagnose` starts) with autocal's template, the exact
   time-varying one and its time mean, on the file's data, on the noise-free data, and on
   the noise-free data without the effect (the clean model's own bias);
3. the same fit on ``--realisations`` new noise draws of the same case;
4. with ``--sim-nside``, the independent model recomputed at other sky resolutions as the
   data, to tell whose discretisation the clean bias is.

Usage (from the repository root)::

    python scripts/ground_visibility.py [--case ground_temperature_day] [--realisations 60]
        [--sim-nside 64 128] [--out DIR]

prints a table and writes ``ground_visibility.json`` into ``--out`` (default: nothing written).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import autocal  # noqa: F401  (offline configuration)
from autocal.core.coords import night_epoch
from autocal.core.observation import Observation
from autocal.diagnosis import effects
from autocal.diagnosis.catalogue import catalogue
from autocal.diagnosis.effects import Effect, SkyTemplates
from autocal.diagnosis.extended_fit import fit_extended, radiometer_weights
from autocal.diagnosis.reading import read_observation
from autocal.diagnosis.trials import BIC_THRESHOLD
from autocal.fit.priors import parse_trxr_prior
from autocal.pipeline.flagging import flag_observation
from tests import independent_effects as ie
from tests import independent_sim as sim


@dataclasses.dataclass(frozen=True)
class ExactGround(Effect):
    """``ground_temperature`` with a given ``(Ntime, Nfreq)`` template instead of ``f_below``."""

    template: np.ndarray | None = None

    def jacobian(self, p: np.ndarray, tpl: SkyTemplates) -> np.ndarray:
        """The template, ``(Npol, Ntime, Nfreq, 1)``."""
        if self.template is None:
            return super().jacobian(p, tpl)
        return np.broadcast_to(self.template[None], tpl.total.shape)[..., None]


def candidate_fit(
    obs: Observation, tpl: SkyTemplates, effect: Effect, prior: tuple[np.ndarray, np.ndarray]
) -> dict[str, float]:
    """Fit ``effect`` on top of the model without effects, as the search's first step does.

    The starting model is fitted twice (weights from the data, then from the model), the
    prior's weights scaled by its gain; Delta BIC uses the candidate's own ``max(1,
    chi2/dof)`` (the search takes the smallest over a step's candidates).
    """
    prior_kw: dict[str, Any] = {"trxr_prior": prior[0], "trxr_prior_sigma": prior[1]}
    w = radiometer_weights(obs, obs.data)
    current = fit_extended(obs, tpl, [], weights=w, **prior_kw)
    w = radiometer_weights(obs, current)
    current = fit_extended(obs, tpl, [], weights=w, **prior_kw)
    prior_kw["gain_ref"] = current.G
    trial = fit_extended(obs, tpl, [effect], weights=w, start=current.params, **prior_kw)
    dchi2 = current.chi2 - trial.chi2
    chat = max(1.0, trial.reduced_chi2)
    return {
        "delta_chi2": float(dchi2),
        "overdispersion": float(chat),
        "ndata": int(current.ndata),
        "delta_bic": float(dchi2 / chat - math.log(current.ndata)),
        "dT_gnd": float(trial.params[effect.name][0]),
        "sigma": float(trial.sigmas[effect.name][0]),
    }


def _with_data(obs: Observation, data: np.ndarray, flags: np.ndarray | None = None) -> Observation:
    """The observation with other data (and flags)."""
    out = dataclasses.replace(obs, data=np.asarray(data, obs.data.dtype))
    return out if flags is None else dataclasses.replace(out, flags=flags)


def _autos(truth: sim.Truth, tsky: np.ndarray) -> np.ndarray:
    """Noise-free autos ``G (Tsky + Trxr)`` of the case's one feed: ``(1, 1, Ntime, Nfreq)``."""
    return (truth.G * (tsky + truth.Trxr[None]))[None, None]


def _row(label: str, template: str, fit: dict[str, float]) -> str:
    return (
        f"{label:34s} {template:16s} dchi2 {fit['delta_chi2']:7.2f}  c {fit['overdispersion']:.4f}"
        f"  N {fit['ndata']}  dBIC {fit['delta_bic']:6.2f}  dT {fit['dT_gnd']:7.2f} +- "
        f"{fit['sigma']:.2f}"
    )


def main(argv: list[str] | None = None) -> int:
    """Run the decomposition for one case and print (and optionally write) it."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", default="ground_temperature_day", help="a suite case")
    parser.add_argument("--realisations", type=int, default=60, help="new noise draws")
    parser.add_argument("--seed", type=int, default=12345, help="seed of the noise draws")
    parser.add_argument(
        "--sim-nside", type=int, nargs="*", default=[], help="recompute the data at these nsides"
    )
    parser.add_argument("--out", type=Path, default=None, help="write ground_visibility.json")
    args = parser.parse_args(argv)
    case = next((c for c in ie.suite_plan() if c.name == args.case), None)
    if case is None or len(case.pols) != 1 or len(case.antennas) != 1:
        parser.error(f"{args.case!r} is not a one-feed case of the suite")
    effect = next((e for e in case.effects if e.name == "ground_temperature"), None)
    if effect is None or len(case.effects) != 1:
        parser.error(f"{args.case!r} does not hide ground_temperature alone")
    pol = case.pols[0]
    kw = ie.simulation_kwargs(case)
    freqs, tgnd = kw["freqs_hz"], kw["tgnd_k"]
    dtg = tgnd - ie.MODEL_TGND_K
    result: dict[str, Any] = {"case": case.name, "dT_gnd_true": dtg}

    with tempfile.TemporaryDirectory() as tmp:
        files = ie.simulate_case(case, tmp)
        truth = files["truth"]
        prior = parse_trxr_prior(str(files["prior"]), sigma_k=ie.PRIOR_SIGMA_K)
        obs = read_observation([files["data"]])
    prior_mean, prior_sigma = prior.at(obs.freqs, antennas=obs.antennas, pols=obs.pols)
    priors = (prior_mean, prior_sigma)
    tpl = effects.sky_templates(
        "gsm2008",
        case.beam,
        obs.site,
        obs.freqs,
        obs.lsts,
        pols=(pol,),
        tgnd=ie.MODEL_TGND_K,
        nside=64,
        epoch=night_epoch(obs.jds, obs.site.lon_deg),
        beam_width_step=None,
        timing=False,
    )
    flagged, _ = flag_observation(obs, tsky=tpl.total)
    result["flagged_integrations"] = [int(t) for t in np.nonzero(flagged.flags.all(axis=3))[2]]

    # 1. the templates
    clean_tsky = sim.independent_tsky(freqs, truth.jds, pol, case.beam, ie.MODEL_TGND_K)
    true_tsky = sim.independent_tsky(freqs, truth.jds, pol, case.beam, tgnd)
    exact = (true_tsky - clean_tsky) / dtg
    ours = tpl.f_below[0]
    mean = exact.mean(axis=0)
    result["templates"] = {
        "freq_mhz": (obs.freqs / 1e6).tolist(),
        "f_below_autocal": ours.tolist(),
        "f_below_exact_time_mean": mean.tolist(),
        "f_below_exact_time_rms": exact.std(axis=0).tolist(),
    }
    print(
        f"case {case.name}: dT_gnd {dtg:.2f} K; "
        f"flagged integrations {result['flagged_integrations']}"
    )
    for i in np.linspace(0, freqs.size - 1, 5).astype(int):
        print(
            f"  {freqs[i] / 1e6:5.1f} MHz: f_below autocal {ours[i]:.5f}, exact time mean "
            f"{mean[i]:.5f} (ratio {mean[i] / ours[i]:.4f}), "
            f"its rms in time {exact[:, i].std():.1e}"
        )
    ground = next(e for e in catalogue() if e.name == "ground_temperature")
    variants = {
        "autocal": ground,
        "exact(t)": ExactGround(**ground.__dict__, template=exact),
        "exact time mean": ExactGround(
            **ground.__dict__, template=np.broadcast_to(mean, exact.shape)
        ),
    }

    # 2. the candidate fit: file data, noise-free, noise-free without the effect
    noisefree = _autos(truth, true_tsky)
    datasets = {
        "file data, flagged (the search)": flagged,
        "file data, not flagged": obs,
        "noise-free, flagged as the file": _with_data(obs, noisefree, flagged.flags),
        "noise-free, not flagged": _with_data(obs, noisefree),
        "noise-free, no effect (bias)": _with_data(obs, _autos(truth, clean_tsky)),
    }
    result["fits"] = {}
    for label, data in datasets.items():
        result["fits"][label] = {}
        for name, eff in variants.items():
            fit = candidate_fit(data, tpl, eff, priors)
            result["fits"][label][name] = fit
            print(_row(label, name, fit))
    strength = ie.effect_strength(case, effect)
    result["strength"] = strength
    print(f"strength (suite): chi2 {strength['chi2']:.2f}, dBIC {strength['dbic']:.2f}")

    # 3. new noise draws (the prior's mean is exact: only the data's noise varies)
    if args.realisations:
        rng = np.random.default_rng(args.seed)
        rows = []
        for _ in range(args.realisations):
            noise = rng.standard_normal(noisefree.shape) / math.sqrt(ie.DNU_DT)
            draw, _ = flag_observation(_with_data(obs, noisefree * (1.0 + noise)), tsky=tpl.total)
            rows.append(
                [candidate_fit(draw, tpl, variants[k], priors) for k in ("autocal", "exact(t)")]
            )
        summary = {}
        for j, name in enumerate(("autocal", "exact(t)")):
            d = np.array([[r[j]["delta_chi2"], r[j]["delta_bic"], r[j]["dT_gnd"]] for r in rows])
            summary[name] = {
                "delta_chi2_mean": float(d[:, 0].mean()),
                "delta_chi2_std": float(d[:, 0].std()),
                "dT_gnd_mean": float(d[:, 2].mean()),
                "dT_gnd_std": float(d[:, 2].std()),
                "fraction_above_threshold": float((d[:, 1] > BIC_THRESHOLD).mean()),
            }
            s = summary[name]
            print(
                f"{args.realisations} noise draws, {name:9s}: dchi2 {s['delta_chi2_mean']:.2f} +- "
                f"{s['delta_chi2_std']:.2f}, dT {s['dT_gnd_mean']:.2f} +- {s['dT_gnd_std']:.2f}, "
                f"dBIC > {BIC_THRESHOLD:g} in {100 * s['fraction_above_threshold']:.0f} %"
            )
        result["realisations"] = {"count": args.realisations, "seed": args.seed, **summary}

    # 4. the independent model at other resolutions as the data
    result["sim_nside"] = {}
    models = {
        "autocal nside 64": tpl,
        "sim nside 32": dataclasses.replace(tpl, total=clean_tsky[None]),
    }
    for nside in args.sim_nside:
        for fn in (sim._sky_maps, sim._galactic_maps, sim._galactic_pixels, sim._altaz):
            fn.cache_clear()
        sim._tsky_cached.cache_clear()
        sim.SIM_NSIDE = nside
        clean_n = sim.independent_tsky(freqs, truth.jds, pol, case.beam, ie.MODEL_TGND_K)
        true_n = sim.independent_tsky(freqs, truth.jds, pol, case.beam, tgnd)
        for model, model_tpl in models.items():
            bias = candidate_fit(_with_data(obs, _autos(truth, clean_n)), model_tpl, ground, priors)
            fit = candidate_fit(_with_data(obs, _autos(truth, true_n)), model_tpl, ground, priors)
            result["sim_nside"][f"{model} vs data at sim nside {nside}"] = {
                "bias": bias,
                "effect": fit,
            }
            print(
                f"model {model:16s} data sim nside {nside:3d}: "
                f"clean bias dT {bias['dT_gnd']:6.2f}; "
                f"effect dchi2 {fit['delta_chi2']:6.2f} (dT {fit['dT_gnd']:.2f})"
            )
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "ground_visibility.json").write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
