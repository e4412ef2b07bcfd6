"""An effect's impact on the calibration products, and negligibility."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from autocal.diagnosis.impact import is_negligible, product_impact


def test_negligible_needs_a_verdict_on_most_channels() -> None:

    tiny = {
        "channels": 161,
        "of": 161,
        "median_change_over_sigma": 0.01,
        "max_change_over_sigma": 0.05,
    }
    impact = {
        "G": {**tiny, "median_relative_change": 1e-5, "median_abs_relative_change": 1e-5},
        "Trxr": {**tiny, "median_change_K": 0.01, "median_abs_change_K": 0.01},
    }
    impact["G"]["max_abs_relative_change"] = 2e-5
    impact["Trxr"]["max_abs_change_K"] = 0.02
    assert is_negligible(impact)
    # the yardstick calibration failed in 158 of 161 channels: no verdict, not negligible
    few = {name: {**entry, "channels": 3} for name, entry in impact.items()}
    assert not is_negligible(few)
    # tiny in absolute terms (below the sky model's accuracy) though many sigma
    precise = {
        "G": {**impact["G"], "median_change_over_sigma": 0.6, "median_abs_relative_change": 2e-4},
        "Trxr": {**impact["Trxr"], "median_change_over_sigma": 0.5, "median_abs_change_K": 0.2},
    }
    assert is_negligible(precise)
    big = {**precise, "G": {**precise["G"], "median_abs_relative_change": 0.02}}
    assert not is_negligible(big)
    # a change alternating in sign: its signed median is ~0, its absolute one is not
    alternating = {**precise, "G": {**precise["G"], "median_relative_change": 0.0}}
    alternating["G"]["median_abs_relative_change"] = 0.05
    assert not is_negligible(alternating)
    # below the sky model's accuracy it does not matter how many sigma the change is ...
    sharp = {**precise, "Trxr": {**precise["Trxr"], "max_change_over_sigma": 1.5}}
    assert is_negligible(sharp)
    # ... unless a channel moves by ten times that accuracy
    spike = {**sharp, "Trxr": {**sharp["Trxr"], "max_abs_change_K": 12.0}}
    assert not is_negligible(spike)
    # the products' variation in time must stay put as well: a 1 % rms jitter is not
    # negligible to whoever applies the gains per integration, however well the time
    # means agree
    jitter = {**impact, "G_time": {"rms_relative_change": 1e-2, "max_abs_relative_change": 3e-2}}
    assert not is_negligible(jitter)
    steady = {**impact, "G_time": {"rms_relative_change": 1e-4, "max_abs_relative_change": 3e-4}}
    assert is_negligible(steady)
    drifting = {**impact, "Trxr_time": {"median_max_abs_change_K": 3.0, "max_abs_change_K": 5.0}}
    assert not is_negligible(drifting)
    # an effect that removes a fifth of the noise variance per sample is never negligible
    assert not is_negligible(steady, chi2_share=0.2) and is_negligible(steady, chi2_share=0.01)


def test_product_impact_counts_each_antenna_pols_own_gain_series() -> None:
    """The whole diagnosis's product change includes the accepted per-antenna gain series
    (divided out of the data the final model was fitted to): without them it would show
    no change of G(t) at all."""
    ntime, shape = 40, (2, 1, 8)
    flat = SimpleNamespace(
        G=np.ones(shape), Trxr=np.full(shape, 150.0), gain_factor=None, noise_factor=None
    )
    sigma_g, sigma_t = np.full(shape, 1e-3), np.full(shape, 1.0)
    own = np.ones((2, 1, ntime))
    own[1, 0] = 1 + 0.01 * np.sin(np.linspace(0, 6, ntime))  # antenna 1 jitters
    without = product_impact(flat, flat, sigma_g, sigma_t)
    assert without["G_time"]["max_abs_relative_change"] == 0.0
    with_feeds = product_impact(flat, flat, sigma_g, sigma_t, after_feed_factors=own)
    assert with_feeds["G_time"]["max_abs_relative_change"] > 9e-3
    assert not is_negligible(with_feeds)


def test_product_sigmas_in_chunks_warn_once_not_per_chunk(several, monkeypatch, caplog) -> None:
    """The yardstick calibration of a large observation is fitted antenna chunk by chunk: a
    channel flagged whole is reported once (info), not as one warning per chunk, and the
    chunked sigmas equal the one-piece ones."""
    import logging

    from autocal.diagnosis import impact

    obs, tpl = several
    whole_g, whole_t = impact.product_sigmas(obs, tpl)
    monkeypatch.setattr(impact, "PRODUCT_SIGMA_SAMPLES", obs.data[0].size)  # one antenna each
    caplog.clear()
    with caplog.at_level(logging.INFO):
        sigma_g, sigma_t = impact.product_sigmas(obs, tpl)
    np.testing.assert_allclose(sigma_g, whole_g, rtol=1e-10, equal_nan=True)
    np.testing.assert_allclose(sigma_t, whole_t, rtol=1e-10, equal_nan=True)
    unsolved = [r for r in caplog.records if "could not be solved" in r.getMessage()]
    once = [r for r in caplog.records if "left 1 of" in r.getMessage()]
    assert not unsolved and len(once) == 1 and once[0].levelno == logging.INFO
    # the per-fit warning is back once the chunks are done
    caplog.clear()
    monkeypatch.undo()
    with caplog.at_level(logging.WARNING):
        impact.product_sigmas(obs, tpl)
    assert any("could not be solved" in r.getMessage() for r in caplog.records)
