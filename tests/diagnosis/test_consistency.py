"""A candidate's consistency across the two halves of the band."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from autocal.diagnosis.catalogue import catalogue
from autocal.diagnosis.consistency import band_consistency, wald_statistic
from autocal.diagnosis.extended_fit import fit_extended, radiometer_weights
from tests.diagnosis.simulated import PRIOR_SIGMA, hidden, s_of


def test_band_consistency_tells_a_real_effect_from_an_absorbing_template(setup):
    """A sky spectral index error is the same in both halves of the band; the same
    template made to absorb a beam-shape error (a narrower beam at low frequencies only)
    is not."""
    obs, tpl = setup
    index = next(e for e in catalogue() if e.name == "sky_spectral_index")
    kw = {"trxr_prior": 150.0, "trxr_prior_sigma": PRIOR_SIGMA}
    real = tpl.total + index.delta(np.array([0.1]), tpl)
    data = hidden(obs, real)
    w = radiometer_weights(data, data.data)
    fit = fit_extended(data, tpl, [index], weights=w, **kw)
    check = band_consistency(data, tpl, [], index, fit, w, kw)
    assert check is not None and check.consistent, check
    lower, upper = check.values["lower"][0], check.values["upper"][0]
    assert abs(lower - 0.1) < 0.02 and abs(upper - 0.1) < 0.02
    # a chromatic error the index template can only partly follow: the beam-width
    # template's change in the lower half of the band only
    low = (obs.freqs < np.median(obs.freqs)).astype(float)
    other = tpl.total + 0.08 * tpl.beam_dwidth * low[None, None, :]
    data = hidden(obs, other)
    w = radiometer_weights(data, data.data)
    fit = fit_extended(data, tpl, [index], weights=w, **kw)
    check = band_consistency(data, tpl, [], index, fit, w, kw)
    assert check is not None and not check.consistent, check
    assert check.p_value < 1e-3 and check.relative_difference > 0.3
    # no verdict for a per-integration series or a fixed hypothesis
    jitter = next(e for e in catalogue(ntime=obs.ntime) if e.basis == "integration")
    assert band_consistency(data, tpl, [], jitter, fit, w, kw) is None


def test_band_consistency_with_a_partner(setup):
    """A noise drift next to a spectral-index error: fitted alone its half-band values are
    pulled apart by the other chromatic error; fitted with it alongside, both agree."""
    obs, tpl = setup
    cat = catalogue()
    index = next(e for e in cat if e.name == "sky_spectral_index")
    drift = next(e for e in cat if e.name == "noise_drift" and e.order == 1)
    truth = tpl.total + index.delta(np.array([-0.1]), tpl)
    trxr = (150 * (1 + 0.02 * s_of(obs.lsts)))[:, None] * np.ones(obs.nfreq)
    data = hidden(obs, truth, trxr=trxr)
    w = radiometer_weights(data, data.data)
    kw = {"trxr_prior": 150.0, "trxr_prior_sigma": PRIOR_SIGMA}
    alone = fit_extended(data, tpl, [drift], weights=w, **kw)
    check = band_consistency(data, tpl, [], drift, alone, w, kw)
    joint = fit_extended(data, tpl, [drift, index], weights=w, **kw)
    both = band_consistency(data, tpl, [], drift, joint, w, kw, partner=index)
    assert both is not None and both.consistent and both.partner == "sky_spectral_index"
    assert abs(joint.params["noise_drift"][0] - 0.02) < 5 * joint.sigmas["noise_drift"][0]
    # alone: both halves biased (0.046 and 0.034 against 0.02), and significantly apart
    assert check is not None and check.p_value < 1e-3 and both.p_value > 1e-3
    assert check.relative_difference > 5 * both.relative_difference


def test_wald_statistic_uses_the_full_covariance_block(setup):
    """A drift of two correlated parameters (a sidereal-day sine and cosine over a third of
    the day, where they are far from orthogonal): the Wald statistic with the full
    covariance block equals the fit's Delta chi2 (the model is linear in them); the
    diagonal one does not."""
    obs, tpl = setup
    keep = np.arange(obs.ntime // 3)  # the first third of the day
    part = dataclasses.replace(
        obs,
        data=obs.data[:, :, keep],
        flags=obs.flags[:, :, keep],
        nsamples=obs.nsamples[:, :, keep],
        lsts=obs.lsts[keep],
        jds=obs.jds[keep],
        integration_time=obs.integration_time[keep],
    )
    ptpl = dataclasses.replace(
        tpl,
        **{
            name: getattr(tpl, name)[:, keep]
            for name in ("total", "galactic", "cmb", "ground", "beam_dwidth", "lst_derivative")
            if getattr(tpl, name) is not None
        },
        lsts=tpl.lsts[keep],
        **{  # (K or 2, Npol, Ntime, Nfreq)
            name: getattr(tpl, name)[:, :, keep]
            for name in ("beam_width_poly", "frame_tilt")
            if getattr(tpl, name) is not None
        },
    )
    drift = next(
        e
        for e in catalogue(ntime=part.ntime, span_h=8.0)
        if e.name == "noise_drift" and e.basis == "diurnal"
    )
    phase = 2 * np.pi * part.lsts / 24.0
    trxr = 150.0 * (1 + 0.004 * np.sin(phase) + 0.003 * np.cos(phase))[:, None]
    data = hidden(part, ptpl.total, trxr=trxr)
    w = radiometer_weights(data, data.data)
    kw = {"trxr_prior": 150.0, "trxr_prior_sigma": PRIOR_SIGMA}
    base = fit_extended(data, ptpl, [], weights=w, **kw)
    fit = fit_extended(data, ptpl, [drift], weights=w, **kw)
    cov = fit.covariances[drift.name]
    corr = cov[0, 1] / np.sqrt(cov[0, 0] * cov[1, 1])
    assert abs(corr) > 0.2, corr
    dchi2 = base.chi2 - fit.chi2
    full = wald_statistic(fit, drift)
    values, sigmas = fit.params[drift.name], fit.sigmas[drift.name]
    diagonal = float(np.sum((values / sigmas) ** 2))
    assert full == pytest.approx(dchi2, rel=0.02)
    assert abs(diagonal - dchi2) > 0.05 * dchi2


def test_the_relative_escape_compares_parameters_of_one_unit_only() -> None:
    """A tilt the halves disagree on is not hidden behind a large clock offset."""
    from autocal.diagnosis.consistency import _relative_difference
    from autocal.diagnosis.effects import Effect

    timing = Effect(
        "timing_offset",
        "tsky",
        ("dt_s", "tilt_x_arcmin", "tilt_y_arcmin"),
        ("s", "arcmin", "arcmin"),
    )
    whole = np.array([50.0, 0.5, 6.0])
    diff = np.array([1.0, 2.0, 2.0])  # 2 % of the offset, 47 % of the tilt
    ok = np.ones(3, bool)
    mixed = np.linalg.norm(diff) / np.linalg.norm(whole)  # the old, unit-mixing figure
    assert mixed < 0.1
    assert _relative_difference(timing, diff, whole, ok) == pytest.approx(
        np.linalg.norm(diff[1:]) / np.linalg.norm(whole[1:])
    )
    # one unit: the norm over all parameters, as before
    drift = Effect("gain_drift", "gain", ("d_1", "d_2"), ("", ""))
    d2, w2 = np.array([0.1, -0.2]), np.array([1.0, 0.5])
    assert _relative_difference(drift, d2, w2, np.ones(2, bool)) == pytest.approx(
        np.linalg.norm(d2) / np.linalg.norm(w2)
    )
    # parameters left out (not finite in a half) are left out of their unit's norm
    assert _relative_difference(timing, diff, whole, np.array([True, False, True])) == (
        pytest.approx(2.0 / 6.0)
    )


def test_the_relative_escape_is_closed_without_a_whole_band_value() -> None:
    """A unit whose whole-band value is not finite gives no escape (inf), and units that do
    not match the parameters are an error, not a silent mix."""
    from autocal.diagnosis.consistency import _relative_difference
    from autocal.diagnosis.effects import Effect

    timing = Effect(
        "timing_offset",
        "tsky",
        ("dt_s", "tilt_x_arcmin", "tilt_y_arcmin"),
        ("s", "arcmin", "arcmin"),
    )
    ok = np.ones(3, bool)
    whole = np.array([50.0, np.nan, 6.0])
    assert _relative_difference(timing, np.array([1.0, 0.1, 0.1]), whole, ok) == np.inf
    short = Effect("timing_offset", "tsky", ("dt_s",), ("s",))
    with pytest.raises(ValueError, match="units"):
        _relative_difference(short, np.zeros(3), np.ones(3), ok)


def _half(name: str, values: list[float], cov: np.ndarray) -> SimpleNamespace:
    """A half-band fit's parameters and covariance block (what the comparison reads)."""
    return SimpleNamespace(
        params={name: np.array(values)},
        sigmas={name: np.sqrt(np.diag(cov))},
        covariances={name: cov},
    )


def test_the_whole_band_lies_where_the_halves_combine() -> None:
    """Disjoint halves combine by their information: one parameter, a weighted mean; two
    correlated ones, the matrix-weighted combination ((0.0095, 0.0005) here, where the
    component-wise means would say (0.005, 0.005)). A whole band far from it is refused."""
    from autocal.diagnosis.consistency import _whole_against_halves
    from autocal.diagnosis.effects import Effect

    offset = Effect("sky_offset", "tsky", ("T_offset",), ("K",))
    ok = np.ones(1, bool)
    halves = [
        _half("sky_offset", [-4.1], np.eye(1) * 1.9**2),
        _half("sky_offset", [-4.2], np.eye(1) * 0.9**2),
    ]
    w = np.array([1 / 1.9**2, 1 / 0.9**2])
    mean = (w[0] * -4.1 + w[1] * -4.2) / w.sum()
    combined, departure, outside = _whole_against_halves(offset, halves, np.array([mean]), ok, 1.0)
    assert combined[0] == pytest.approx(mean) and departure < 1e-12 and not outside
    # the beam-width case of the held-out suite: +23.5 K from halves of -4.1 and -4.2 K
    combined, departure, outside = _whole_against_halves(offset, halves, np.array([23.5]), ok, 1.0)
    assert outside and departure == pytest.approx((23.5 - mean) / 23.5)
    # a small departure (under CONSISTENCY_RELATIVE of the whole) is not refused, however
    # significant: a real effect next to a slightly wrong model
    near = mean * 1.2
    assert not _whole_against_halves(offset, halves, np.array([near]), ok, 1.0)[2]

    drift = Effect("gain_drift", "gain", ("d_sin", "d_cos"), ("", ""))
    lo_cov = np.array([[1.0, 0.9], [0.9, 1.0]]) * 1e-6
    hi_cov = np.array([[1.0, -0.9], [-0.9, 1.0]]) * 1e-6
    lo, hi = np.array([0.010, 0.000]), np.array([0.000, 0.010])
    info = [np.linalg.inv(lo_cov), np.linalg.inv(hi_cov)]
    joint = np.linalg.solve(info[0] + info[1], info[0] @ lo + info[1] @ hi)
    halves = [_half("gain_drift", lo.tolist(), lo_cov), _half("gain_drift", hi.tolist(), hi_cov)]
    both = np.ones(2, bool)
    combined, departure, outside = _whole_against_halves(drift, halves, joint, both, 1.0)
    np.testing.assert_allclose(combined, joint)
    assert not outside and departure < 1e-9
    assert _whole_against_halves(drift, halves, -joint, both, 1.0)[2]
