"""The paper's scenarios (autocal.simulate.paper): scatter, drift biases, calibrated errors.

Reference values from Gehlot et al. (2021) as quoted in DESIGN.md section 1.
"""

from __future__ import annotations

import numpy as np
import pytest

from autocal.simulate.paper import PAPER_VALUES, SCENARIOS, PaperRun, run_paper

BY_NAME = {s.name: s for s in SCENARIOS}


@pytest.fixture(scope="module")
def runs(data_root) -> dict[str, PaperRun]:
    return {beam: PaperRun(beam, cache=False) for beam in ("hera", "dipole")}


@pytest.mark.parametrize("beam", ["hera", "dipole"])
def test_reference_scatter_matches_the_paper(runs, beam: str) -> None:
    res = runs[beam].run(BY_NAME["reference"])
    m = res.metrics()
    paper = PAPER_VALUES[("reference", beam)]
    assert m["rms_Trxr_K"] == pytest.approx(paper["rms_Trxr_K"], rel=0.3)
    # The scatter of G is what the fit's own covariance predicts ...
    predicted = float(np.sqrt(np.mean(res.solution.sigma_G_stat**2)))
    assert m["rms_G"] == pytest.approx(predicted, rel=0.3)
    # ... and within 50 % of the paper's "~0.002" (we measure 0.0027-0.0028: see README).
    assert m["rms_G"] == pytest.approx(paper["rms_G"], rel=0.5)
    assert abs(m["bias_G"]) < 3 * predicted / np.sqrt(res.solution.freqs.size)


@pytest.mark.parametrize("beam", ["hera", "dipole"])
def test_gain_drifts_bias_a_constant_fit_and_order_one_fixes_drift_a(runs, beam: str) -> None:
    run = runs[beam]
    reference = run.run(BY_NAME["reference"]).metrics()
    for profile in "abc":
        m = run.run(BY_NAME[f"drift_{profile}"]).metrics()
        # far outside the statistical errors, covered by the total (its drift term)
        assert m["bias_G_stat_sigmas"] > 3, profile
        assert m["bias_Trxr_stat_sigmas"] > 3, profile
        assert m["G_within_3_sigma"] > 0.9, profile
        assert m["Trxr_within_3_sigma"] > 0.9, profile
    res = run.run(BY_NAME["drift_a_t1"])
    m = res.metrics()
    sol = res.solution
    nf = sol.freqs.size
    assert abs(m["bias_G"]) < 2 * np.sqrt(np.mean(sol.sigma_G_stat**2)) / np.sqrt(nf)
    assert abs(m["bias_Trxr_K"]) < 2 * np.sqrt(np.mean(sol.sigma_Trxr_stat**2)) / np.sqrt(nf)
    assert np.mean(np.abs(res.gain_error) < 2 * sol.sigma_G_stat[0, 0]) > 0.9
    assert m["rms_G"] > 1.3 * reference["rms_G"]
    assert m["rms_Trxr_K"] > 1.3 * reference["rms_Trxr_K"]
    paper = PAPER_VALUES[("drift_a_t1", beam)]
    assert m["rms_G_t_pct"] == pytest.approx(paper["rms_G_t_pct"], rel=0.3)
    assert m["rms_Trxr_pct"] == pytest.approx(paper["rms_Trxr_pct"], rel=0.3)


@pytest.mark.slow
@pytest.mark.parametrize("scenario", ["reference", "drift_a_t1"])
def test_fitted_uncertainties_are_calibrated(scenario: str) -> None:
    """Pulls over 60 noise draws x 321 channels have standard deviation 1 +- 0.1 with the
    statistical errors, 1 +- 0.35 with the total errors (24 h of clean data: the jackknife
    and drift terms must not inflate them)."""
    run = PaperRun("dipole", cache=False)
    pulls: dict[str, list[np.ndarray]] = {"G": [], "n": [], "Trxr": []}
    total: dict[str, list[np.ndarray]] = {"G": [], "n": [], "Trxr": []}
    for seed in range(60):
        res = run.run(BY_NAME[scenario], seed=seed)
        sol = res.solution
        dn = sol.n[0, 0] - 150.0 * res.true_gain.mean(0)
        for name, err in (("G", res.gain_error), ("n", dn), ("Trxr", res.trxr_error)):
            pulls[name].append(err / getattr(sol, f"sigma_{name}_stat")[0, 0])
            total[name].append(err / getattr(sol, f"sigma_{name}")[0, 0])
    for name, values in pulls.items():
        arr = np.ravel(values)
        assert abs(np.std(arr) - 1) < 0.1, name
        assert abs(np.mean(arr)) < 0.1, name
        assert abs(np.std(np.ravel(total[name])) - 1) < 0.35, name


@pytest.mark.parametrize("beam", ["hera", "dipole"])
def test_sky_model_incompleteness_biases_g_up_at_low_frequency(runs, beam: str) -> None:
    """The beta = -2.4 extrapolation from 200 MHz under-predicts the sky's variation
    below 200 MHz, so the gain comes out high, most at the bottom of the band; the size
    follows the regression slope of the true on the model Tsky.
    """
    run = runs[beam]
    res = run.run(BY_NAME["sky_model"], noise=False)
    bias = res.gain_error
    freqs = res.solution.freqs
    low, high = freqs < 130e6, freqs > 170e6
    assert np.mean(bias[low]) > np.mean(bias[high]) > 0
    assert np.mean(bias[low]) > 0.02
    true, model = run.tsky("gsm2008", False), run.tsky(BY_NAME["sky_model"].model_sky, False)
    tc, mc = true - true.mean(0), model - model.mean(0)
    slope = (tc * mc).sum(0) / (mc * mc).sum(0)
    np.testing.assert_allclose(1 + bias, slope, rtol=0.03)


@pytest.mark.parametrize("beam", ["hera", "dipole"])
def test_beam_model_incompleteness_biases_g_low_and_trxr_high(runs, beam: str) -> None:
    """A true beam broader than modelled (the error model widens it and raises the
    ground and sidelobe share) dilutes the sky's diurnal contrast: G low, Trxr high,
    with frequency structure from the beam's chromaticity.
    """
    res = runs[beam].run(BY_NAME["beam_model"], noise=False)
    noisy = runs[beam].run(BY_NAME["beam_model"]).solution
    bias_g, bias_t = res.gain_error, res.trxr_error
    assert np.all(bias_g < 0) and np.all(bias_t > 0)
    assert np.ptp(bias_g) > 2 * np.median(noisy.sigma_G_stat)
    assert np.mean(bias_t) > 5 * np.median(noisy.sigma_Trxr_stat)


def test_run_paper_writes_table_results_and_figures(tmp_path, data_root) -> None:
    from autocal.simulate.mock import SimulationConfig

    cfg = SimulationConfig(channel_width_khz=2000.0, cadence_s=900.0)
    out = run_paper(tmp_path / "paper", beams=("dipole",), config=cfg, cache=False)
    table = (tmp_path / "paper" / "paper_table.md").read_text()
    assert table.count("| dipole |") == len(SCENARIOS)
    assert "rms Trxr (K) 1.64" in table
    names = {p.split("/")[-1] for p in out["figures"]}
    assert names == {"gain_trxr_dipole.png", "time_model_dipole.png", "delay_spectra_dipole.png"}
    assert (tmp_path / "paper" / "paper_results.json").stat().st_size > 0
