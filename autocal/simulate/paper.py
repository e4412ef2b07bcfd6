"""The simulation scenarios of Gehlot et al. (2021), run for several beams.

Each scenario simulates a day of mock autos (:mod:`autocal.simulate.mock`, the paper's
reference setup) and fits them (:mod:`autocal.fit`) with a model that may differ from the
truth: a gain drift fitted with a constant gain or with the order-1 time model, a sky
model extrapolated from GSM2008's 200 MHz map with ``beta = -2.4`` while the truth is
GSM2008 itself (GSM2016, the paper's truth, is not available offline), or a true beam
carrying the paper's error model while the fit assumes the nominal beam.

:func:`run_paper` writes ``paper_table.md``, ``paper_results.json`` and the figures.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from autocal.compare.delay import delay_spectrum
from autocal.core.coords import night_epoch
from autocal.core.files import atomic_path
from autocal.core.observation import Observation
from autocal.core.sites import get_site
from autocal.fit.passes import fit
from autocal.fit.solution import Solution
from autocal.simulate import paper_figures as plots
from autocal.simulate.mock import (
    SIDEREAL_DAY,
    SimulationConfig,
    gain_profile,
    lsts_to_jds,
    mock_autos,
    perturbed,
)
from autocal.sky.beam_names import get_beam
from autocal.tsky.compute import compute_tsky

logger = logging.getLogger(__name__)

#: The model sky of the sky-incompleteness scenario.
SKY_MODEL_INCOMPLETE = "powerlaw:gsm2008@200:-2.4"
#: Beams of the paper's table: HERA (Fagnoni CST file), Gaussian dipole, Airy (D = 14 m).
PAPER_BEAMS = ("hera", "dipole", "airy")


@dataclass(frozen=True)
class Scenario:
    """One row of the paper's summary table.

    Attributes
    ----------
    name
        Identifier.
    label
        Human-readable description.
    gain
        True gain profile (``constant``, ``a``, ``b``, ``c``).
    fit_model
        ``constant`` or ``legendre``.
    order
        Legendre order of the fit.
    model_sky
        Sky assumed by the fit (the truth is always GSM2008).
    beam_error
        Whether the true beam carries the beam error model (the fit assumes the nominal
        beam).
    """

    name: str
    label: str
    gain: str = "constant"
    fit_model: str = "constant"
    order: int = 0
    model_sky: str = "gsm2008"
    beam_error: bool = False


SCENARIOS: tuple[Scenario, ...] = (
    Scenario("reference", "Reference: truth = model"),
    Scenario("drift_a", "Gain drift (a), constant fit", gain="a"),
    Scenario("drift_b", "Gain drift (b), constant fit", gain="b"),
    Scenario("drift_c", "Gain drift (c), constant fit", gain="c"),
    Scenario("drift_a_t1", "Gain drift (a), order-1 time model", "a", "legendre", 1),
    Scenario("drift_b_t1", "Gain drift (b), order-1 time model", "b", "legendre", 1),
    Scenario("drift_c_t1", "Gain drift (c), order-1 time model", "c", "legendre", 1),
    Scenario(
        "sky_model",
        "Sky model: GSM2008 200 MHz map, beta = -2.4",
        model_sky=SKY_MODEL_INCOMPLETE,
    ),
    Scenario("beam_model", "Beam model: true beam has the error model", beam_error=True),
)

#: Reference values quoted from the paper (DESIGN.md section 1); ``None`` = not quoted.
PAPER_VALUES: dict[tuple[str, str], dict[str, float]] = {
    ("reference", "hera"): {"rms_G": 0.002, "rms_Trxr_K": 1.35},
    ("reference", "dipole"): {"rms_G": 0.002, "rms_Trxr_K": 1.64},
    ("drift_a_t1", "hera"): {"rms_G_t_pct": 0.7, "rms_Trxr_pct": 1.5},
    ("drift_a_t1", "dipole"): {"rms_G_t_pct": 0.9, "rms_Trxr_pct": 2.2},
}


_PAPER_LABELS = {
    "rms_G": "rms G",
    "rms_Trxr_K": "rms Trxr (K)",
    "rms_G_t_pct": "rms G(t) (%)",
    "rms_Trxr_pct": "rms Trxr (%)",
}


@dataclass(frozen=True)
class ScenarioResult:
    """Outcome of one scenario for one beam."""

    scenario: Scenario
    beam: str
    solution: Solution
    true_gain: np.ndarray  # (Ntime, Nfreq)
    true_trxr: np.ndarray  # (Nfreq,)

    @property
    def gain_error(self) -> np.ndarray:
        """``(Nfreq,)`` fitted minus true time-averaged gain."""
        return self.solution.G[0, 0] - self.true_gain.mean(axis=0)

    @property
    def trxr_error(self) -> np.ndarray:
        """``(Nfreq,)`` fitted minus true receiver temperature (K)."""
        return self.solution.Trxr[0, 0] - self.true_trxr

    def metrics(self) -> dict[str, float]:
        """Return rms and mean bias of G and Trxr over channels, and typical uncertainties."""
        dg, dt = self.gain_error, self.trxr_error
        g_true = self.true_gain.mean(axis=0)
        sol = self.solution
        out = {
            "rms_G": float(np.sqrt(np.nanmean(dg**2))),
            "bias_G": float(np.nanmean(dg)),
            "rms_G_pct": float(100 * np.sqrt(np.nanmean((dg / g_true) ** 2))),
            "rms_Trxr_K": float(np.sqrt(np.nanmean(dt**2))),
            "bias_Trxr_K": float(np.nanmean(dt)),
            "rms_Trxr_pct": float(100 * np.sqrt(np.nanmean((dt / self.true_trxr) ** 2))),
            "median_sigma_G": float(np.nanmedian(sol.sigma_G[0, 0])),
            "median_sigma_Trxr_K": float(np.nanmedian(sol.sigma_Trxr[0, 0])),
            "median_reduced_chi2": float(np.nanmedian(sol.reduced_chi2[0, 0])),
            "bias_G_sigmas": float(np.nanmedian(np.abs(dg) / sol.sigma_G[0, 0])),
            "bias_Trxr_sigmas": float(np.nanmedian(np.abs(dt) / sol.sigma_Trxr[0, 0])),
            "median_sigma_G_stat": float(np.nanmedian(sol.sigma_G_stat[0, 0])),
            "bias_G_stat_sigmas": float(np.nanmedian(np.abs(dg) / sol.sigma_G_stat[0, 0])),
            "bias_Trxr_stat_sigmas": float(np.nanmedian(np.abs(dt) / sol.sigma_Trxr_stat[0, 0])),
            "G_within_3_sigma": float(np.mean(np.abs(dg) < 3 * sol.sigma_G[0, 0])),
            "G_within_3_stat": float(np.mean(np.abs(dg) < 3 * sol.sigma_G_stat[0, 0])),
            "Trxr_within_3_sigma": float(np.mean(np.abs(dt) < 3 * sol.sigma_Trxr[0, 0])),
        }
        if sol.model.kind == "legendre":
            ev = sol.evaluate()
            err = ev["G"][0, 0] - self.true_gain
            out["rms_G_t_pct"] = float(100 * np.sqrt(np.nanmean((err / self.true_gain) ** 2)))
            err_t = ev["Trxr"][0, 0] - self.true_trxr[None, :]
            out["rms_Trxr_t_pct"] = float(
                100 * np.sqrt(np.nanmean((err_t / self.true_trxr[None, :]) ** 2))
            )
        return out


class PaperRun:
    """Runs scenarios for one beam, computing each Tsky table once.

    Parameters
    ----------
    beam
        Beam name (``hera``, ``dipole``, ``airy`` or any :func:`autocal.sky.beam_names.get_beam`
        spec).
    config
        Sampling and noise settings (its ``sky``, ``beam``, ``gain`` fields are
        overridden per scenario).
    cache
        Use the on-disk Tsky cache.
    """

    def __init__(
        self, beam: str, config: SimulationConfig | None = None, cache: bool = True
    ) -> None:
        self.beam = beam
        self.config = config or SimulationConfig()
        self.cache = cache
        self.freqs = self.config.freqs()
        self.lsts = self.config.lsts()
        self.jds = lsts_to_jds(self.lsts, self.config.site, self.config.jd_start)
        self._tsky: dict[tuple[str, bool], np.ndarray] = {}

    def tsky(self, sky: str, beam_error: bool) -> np.ndarray:
        """``(Ntime, Nfreq)`` Tsky of a sky and the (possibly perturbed) beam, pol ee."""
        key = (sky, beam_error)
        if key not in self._tsky:
            beam = get_beam(self.beam, "ee")
            if beam_error:
                beam = perturbed(beam)
            self._tsky[key] = compute_tsky(
                sky,
                beam,
                self.config.site,
                self.freqs,
                self.lsts,
                tgnd=self.config.tgnd_k,
                nside=self.config.nside,
                epoch=night_epoch(self.jds, get_site(self.config.site).lon_deg),
                cache=self.cache,
            ).tsky
        return self._tsky[key]

    def observation(
        self, scenario: Scenario, seed: int | None, noise: bool = True
    ) -> tuple[Observation, np.ndarray]:
        """Mock observation of a scenario and its true ``G(t, nu)``."""
        cfg = self.config
        gain = np.broadcast_to(
            gain_profile(scenario.gain, self.lsts, cfg.g0, cfg.gain_amplitude)[:, None],
            (self.lsts.size, self.freqs.size),
        )
        rng = np.random.default_rng(seed)
        truth = self.tsky("gsm2008", scenario.beam_error)
        bt = cfg.noise_dnu_hz * cfg.noise_dt_s if (cfg.noise and noise) else None
        data = mock_autos(truth[None], gain, cfg.trxr_k, bandwidth_time=bt, rng=rng)
        width = cfg.channel_width_khz * 1e3
        tint = cfg.cadence_s * SIDEREAL_DAY
        obs = Observation(
            data=data,
            freqs=self.freqs,
            lsts=self.lsts,
            jds=self.jds,
            antennas=np.array([0]),
            pols=("ee",),
            site=get_site(cfg.site),
            channel_width=width,
            integration_time=tint,
            nsamples=cfg.noise_dnu_hz * cfg.noise_dt_s / (width * tint),
            telescope_name=cfg.telescope,
        )
        return obs, np.asarray(gain)

    def run(self, scenario: Scenario, seed: int | None = 1, noise: bool = True) -> ScenarioResult:
        """Simulate and fit one scenario (``noise=False``: its systematic part only)."""
        obs, gain = self.observation(scenario, seed, noise)
        model_tsky = self.tsky(scenario.model_sky, False)
        sol = fit(  # the paper's statistical errors: radiometer covariance, not inflated
            obs,
            model_tsky,
            model=scenario.fit_model,
            order=scenario.order,
            inflate_errors=False,
            config={
                "scenario": scenario.name,
                "beam": self.beam,
                "model_sky": scenario.model_sky,
            },
        )
        return ScenarioResult(scenario, self.beam, sol, gain, np.full(self.freqs.size, 150.0))


# outputs --------------------------------------------------------------------------------


def _fmt(value: float | None, digits: int = 4) -> str:
    if value is None or not np.isfinite(value):
        return "-"
    return f"{value:.{digits}g}"


def markdown_table(results: list[ScenarioResult]) -> str:
    """Markdown summary table with the paper's values beside ours where it quotes them."""
    lines = [
        "| scenario | beam | rms G | bias G | rms Trxr (K) | bias Trxr (K) | rms Trxr (%) "
        "| rms G(t) (%) | rms Trxr(t) (%) | median chi2/dof "
        "| G within 3 sigma: stat / total (%) | paper |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for res in results:
        m = res.metrics()
        paper = PAPER_VALUES.get((res.scenario.name, res.beam))
        paper_text = (
            ", ".join(f"{_PAPER_LABELS[k]} {v:g}" for k, v in paper.items()) if paper else ""
        )
        lines.append(
            f"| {res.scenario.label} | {res.beam} | {_fmt(m['rms_G'], 3)} | "
            f"{_fmt(m['bias_G'], 3)} | {_fmt(m['rms_Trxr_K'], 3)} | "
            f"{_fmt(m['bias_Trxr_K'], 3)} | {_fmt(m['rms_Trxr_pct'], 3)} | "
            f"{_fmt(m.get('rms_G_t_pct'), 3)} | {_fmt(m.get('rms_Trxr_t_pct'), 3)} | "
            f"{_fmt(m['median_reduced_chi2'], 3)} | "
            f"{100 * m['G_within_3_stat']:.0f} / {100 * m['G_within_3_sigma']:.0f} | "
            f"{paper_text} |"
        )
    return "\n".join(lines) + "\n"


def run_paper(
    out: str | Path,
    beams: tuple[str, ...] = PAPER_BEAMS,
    scenarios: tuple[Scenario, ...] = SCENARIOS,
    config: SimulationConfig | None = None,
    seed: int = 1,
    figures: bool = True,
    cache: bool = True,
) -> dict[str, Any]:
    """Run every scenario for every beam and write the table, JSON results and figures.

    Parameters
    ----------
    out
        Output folder (created).
    beams
        Beams to run.
    scenarios
        Scenarios to run.
    config
        Sampling and noise settings (default: the paper's).
    seed
        Noise seed (the same noise realisation for every scenario of a beam, so
        differences between rows come from the scenario).
    figures
        Write the PNG figures.
    cache
        Use the Tsky cache.

    Returns
    -------
    dict
        Paths of the written files and the metrics.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    results: list[ScenarioResult] = []
    noiseless: list[ScenarioResult] = []
    for beam in beams:
        runner = PaperRun(beam, config, cache=cache)
        for scenario in scenarios:
            logger.info("scenario %s, beam %s", scenario.name, beam)
            results.append(runner.run(scenario, seed))
            if figures:
                noiseless.append(runner.run(scenario, seed, noise=False))
    table = markdown_table(results)
    written: dict[str, Any] = {}
    table_path = out / "paper_table.md"
    with atomic_path(table_path) as tmp:
        tmp.write_text(table)
    written["table"] = str(table_path)
    metrics = [{"scenario": asdict(r.scenario), "beam": r.beam, **r.metrics()} for r in results]
    json_path = out / "paper_results.json"
    cfg = (config or SimulationConfig()).model_dump()
    with atomic_path(json_path) as tmp:
        tmp.write_text(
            json.dumps(
                {"config": cfg, "seed": seed, "results": metrics, "paper_values": _paper_json()},
                indent=2,
            )
        )
    written["results"] = str(json_path)
    if figures:
        written["figures"] = []
        for beam in beams:
            mine = [r for r in results if r.beam == beam]
            written["figures"].append(
                str(plots.plot_scenarios(mine, out / f"gain_trxr_{beam}.png"))
            )
            timed = [r for r in mine if r.solution.model.kind == "legendre"]
            if timed:
                written["figures"].append(
                    str(plots.plot_time_model(timed, out / f"time_model_{beam}.png"))
                )
            clean = [r for r in noiseless if r.beam == beam]
            written["figures"].append(
                str(plots.plot_delay_spectra(clean, mine[0], out / f"delay_spectra_{beam}.png"))
            )
    written["seconds"] = round(time.perf_counter() - t0, 1)
    written["metrics"] = metrics
    written["table_text"] = table
    return written


def _paper_json() -> list[dict[str, Any]]:
    return [{"scenario": s, "beam": b, **v} for (s, b), v in PAPER_VALUES.items()]


def scenario_delay(result: ScenarioResult) -> dict[str, np.ndarray]:
    """Delay spectra (normalised to tau = 0) of the fitted G and Trxr of a scenario."""
    sol = result.solution
    g = delay_spectrum(sol.G[0, 0], sol.freqs)
    t = delay_spectrum(sol.Trxr[0, 0], sol.freqs)
    return {"delays_ns": g.delays_ns, "G": g.amplitude, "Trxr": t.amplitude}
