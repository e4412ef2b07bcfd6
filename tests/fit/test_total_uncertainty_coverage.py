"""Coverage of the total uncertainty on observations autocal did not simulate.

The data come from tests/independent_sim.py (its own sky handling, frame conversion pixel
by pixel with astropy, nside 32, hard horizon, its own beam evaluation and UVH5 writer);
autocal calibrates them through its ordinary pipeline (GSM2008 at nside 64, soft horizon,
its own Tsky engine). The truth is the simulated time-mean gain.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from autocal.pipeline.calibrate import run_calibration
from autocal.pipeline.config import CalibrationConfig
from tests import independent_sim
from tests.independent_sim import Truth, simulate_autos

pytestmark = [pytest.mark.data, pytest.mark.slow]

SEEDS = (0, 1, 2)


def calibrate(truth: Truth, out: Path, **options: object) -> object:
    config = CalibrationConfig(
        inputs=[str(truth.path)], beam="dipole", products=["hdf5"], **options
    )
    return run_calibration(config, out).solution


def pulls(tmp_path: Path, name: str, **sim: object) -> dict[str, np.ndarray]:
    """Calibrate three noise draws; return the channels' errors in total and stat sigmas."""
    total, stat, ratio = [], [], []
    for seed in SEEDS:
        truth = simulate_autos(tmp_path / f"{name}{seed}.uvh5", seed=seed, **sim)
        sol = calibrate(truth, tmp_path / f"{name}{seed}")
        err = sol.G[0, 0] - truth.G_mean
        total.append(err / sol.sigma_G[0, 0])  # NaN where a channel was not solved
        stat.append(err / sol.sigma_G_stat[0, 0])
        ratio.append(sol.sigma_G[0, 0] / sol.sigma_G_stat[0, 0])
    return {"total": np.ravel(total), "stat": np.ravel(stat), "ratio": np.ravel(ratio)}


def test_short_span_with_a_gain_drift_is_covered(data_root, tmp_path) -> None:
    """31 minutes at LST 3.2 h (the sky varies by ~0.5 % of Tsys), dipole, dnu dt = 1e6,
    the gain drifting linearly by 1 % over the span, fitted with the constant model: the
    statistical errors miss the truth by ~10 sigma; the total covers it in >= 90 % of the
    channels (unsolved channels count as misses)."""
    p = pulls(tmp_path, "drift", lst_start_h=3.2, duration_min=31.0, drift_total=0.01)
    assert np.mean(np.abs(p["stat"]) < 3) < 0.2
    assert np.mean(np.abs(p["total"]) < 3) >= 0.9


def test_short_clean_span_is_not_inflated_much(data_root, tmp_path) -> None:
    """The same 31 minutes with a constant gain: pull std <= 1.5 and the median total
    error at most 5x the statistical one."""
    p = pulls(tmp_path, "clean", lst_start_h=3.2, duration_min=31.0)
    assert np.nanstd(p["total"]) <= 1.5
    assert np.nanmedian(p["ratio"]) <= 5.0
    assert 0.8 < np.nanstd(p["stat"]) < 1.2  # the statistical part alone is right here


def _clear_simulator_caches() -> None:
    for obj in vars(independent_sim).values():
        if hasattr(obj, "cache_clear"):
            obj.cache_clear()


@pytest.fixture
def native_sky(monkeypatch: pytest.MonkeyPatch) -> object:
    """The independent simulator at GSM2008's own nside 64 instead of averaged to 32.

    A clean 24-h day's total errors (~2e-4 of G) are smaller than the difference between
    GSM2008 averaged down to nside 32 and GSM2008 as it is: with the nside-32 sky the pulls'
    mean was -0.52 against autocal's band-limited sky (which matches an independent
    converged quadrature to 0.04 K, benchmarks/tsky_accuracy.py); with the simulator's sky
    at the map's own resolution it is 0.16 (std 0.92). The simulator's caches hold maps of
    one nside, so they are emptied around the change.
    """
    _clear_simulator_caches()
    monkeypatch.setattr(independent_sim, "SIM_NSIDE", independent_sim.GSM_NSIDE)
    yield
    _clear_simulator_caches()


def test_a_clean_day_keeps_unit_pulls(data_root, tmp_path, native_sky) -> None:
    """24 h of 5-minute integrations with a constant gain: pulls 1 +- 0.35 in the total
    errors (the jackknife and drift terms do not inflate a long clean observation). The
    simulator's sky is GSM2008 at its own nside 64 (see :func:`native_sky`)."""
    p = pulls(tmp_path, "day", lst_start_h=0.0, duration_min=24 * 60 - 5.0, integration_s=300.0)
    assert abs(np.nanstd(p["total"]) - 1.0) < 0.35
    assert abs(np.nanmean(p["total"])) < 0.35
    assert np.nanmedian(p["ratio"]) < 1.5


def test_a_receiver_prior_decides_what_the_short_span_cannot(data_root, tmp_path) -> None:
    """With G and n weakly separated, a prior Trxr = 150 +- 5 K (the truth) gives G to a few
    per cent, covering the truth, where the free fit's total error is far larger."""
    errs, sig_free, sig_prior = [], [], []
    for seed in SEEDS:
        truth = simulate_autos(
            tmp_path / f"prior{seed}.uvh5", seed=seed, lst_start_h=3.2, duration_min=31.0
        )
        free = calibrate(truth, tmp_path / f"free{seed}")
        held = calibrate(truth, tmp_path / f"held{seed}", trxr_prior=150.0, trxr_prior_sigma_k=5.0)
        errs.append((held.G[0, 0] - truth.G_mean) / held.sigma_G[0, 0])
        sig_free.append(free.sigma_G[0, 0] / free.G[0, 0])
        sig_prior.append(held.sigma_G[0, 0] / held.G[0, 0])
        summary = held.total
        assert summary is not None
    assert np.mean(np.abs(np.ravel(errs)) < 3) >= 0.95
    assert np.nanmedian(sig_prior) < 0.5 * np.nanmedian(sig_free)
    # the prior's 5 K is in the error: G moves by dG/dTrxr * 5 K, about G * 5 / (Tsky + Trxr)
    assert np.nanmedian(sig_prior) > 0.5 * 5.0 / (250.0 + 150.0)
