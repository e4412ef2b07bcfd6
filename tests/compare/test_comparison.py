"""The comparison on synthetic and real data (autocal.compare.comparison)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import autocal  # noqa: F401
from autocal.compare.beam_area import (
    beam_solid_angle,
    jy_per_kelvin,
)
from autocal.compare.comparison import compare
from autocal.compare.errors import CompareError
from autocal.compare.reference import interpolate_frequency
from autocal.io.calsol_read import read_reference_gains
from tests.compare.helpers import exp_beam, reference_for
from tests.io.test_calsol import H1C_ABS, REF, make_solution


def test_absolute_comparison_recovers_a_known_ratio():
    sol = make_solution(rel_sigma=0.002)
    freqs = sol.freqs
    omega = 0.04 * (freqs / 150e6) ** -1.5
    jpk = jy_per_kelvin(freqs, omega)
    # A Jy-referenced |g_ref| whose kelvin equivalent is |g_auto| / 1.07
    ref = reference_for(sol, 1.0 / (1.07 * np.sqrt(jpk)), scatter=0.003, ntime=8)
    result = compare(sol, ref, omega=omega)
    assert result.mode == "absolute"
    ok = result.valid
    assert not ok[..., 3].any()  # the solution's flagged channel
    assert ok.sum() == ok.size - ok.shape[0] * ok.shape[1]
    np.testing.assert_allclose(result.ratio[ok], 1.07, rtol=0.01)
    np.testing.assert_allclose(result.jy_per_k[0], jpk)
    for row in result.summary["per_antenna_pol"]:
        assert row["ratio_mean"] == pytest.approx(1.07, rel=2e-3)
        assert row["ratio_rms"] < 0.01
        assert row["offset_sigma"] > 10  # 7 % is many sigma
        assert row["reference_sigma_available"]
        assert row["shape_pull_rms"] < 3
    assert result.summary["time_match"]["match"] == "overlap"
    assert result.summary["time_match"]["ntimes"] == 8
    # the combined uncertainty includes the reference scatter over time
    assert np.all(result.sigma_ratio[ok] > result.ratio[ok] * 0.001)
    assert result.delays is not None and result.delay_amplitude.shape[:2] == (2, 2)


def test_absolute_conversion_through_a_beam_and_kelvin_references():
    sol = make_solution(pols=("ee",), antennas=(0,), rel_sigma=0.001, flagged=())
    beam = exp_beam(0.05)
    omega = 2 * np.pi * 0.05 * (1 - np.exp(-40))
    ref = reference_for(sol, 1.0 / np.sqrt(jy_per_kelvin(sol.freqs, omega)))
    result = compare(sol, ref, beam=beam, nside=128)
    np.testing.assert_allclose(result.ratio, 1.0, rtol=3e-3)
    assert result.summary["conversion"]["omega_sr"]["ee"] == pytest.approx(omega, rel=3e-3)
    # a K-referenced reference (an autocal calh5) is compared without conversion
    kref = reference_for(sol, 0.5, gain_scale="K")
    k_result = compare(sol, kref)
    np.testing.assert_allclose(k_result.ratio, 2.0, rtol=1e-9)
    assert k_result.jy_per_k is None
    with pytest.raises(CompareError, match="gain_scale"):
        compare(sol, reference_for(sol, 1.0, gain_scale="furlongs"))


def test_relative_comparison_normalises_shapes():
    sol = make_solution(rel_sigma=0.001)
    f = sol.freqs / 150e6
    # redcal-like: arbitrary overall scale and time variation; antenna 23 has a 2 % slope
    slope = np.ones((2, 2, sol.freqs.size))
    slope[1] = 1 + 0.02 * (f - 1)
    ref = reference_for(sol, 37.0 * slope, absolute=False, ntime=4)
    ref = replace(ref, gains=ref.gains * np.linspace(0.9, 1.1, 4)[None, None, :, None])
    result = compare(sol, ref)
    assert result.mode == "relative"
    ok = result.valid
    # antenna 0: ratio 1 everywhere; antenna 23: 1 / (1 + 0.02 (f - 1)) up to normalisation
    np.testing.assert_allclose(result.ratio[0][ok[0]], 1.0, atol=1e-6)
    expected = 1 / slope[1, 0]  # up to a constant near 1
    r23 = result.ratio[1, 0][ok[1, 0]]
    assert np.ptp(r23) == pytest.approx(np.ptp(expected[ok[1, 0]]), rel=0.05)
    for name in ("auto", "reference"):
        arr = getattr(result, name)
        np.testing.assert_allclose(np.nanmean(np.where(ok, arr, np.nan), axis=-1), 1.0)
    # forcing absolute on a relative reference is allowed and unconverted when scale is K
    assert compare(sol, ref, mode="relative").mode == "relative"


def test_smoothing_in_compare_reduces_reference_noise():
    sol = make_solution(rel_sigma=1e-4, flagged=())
    ref = reference_for(sol, 0.5, gain_scale="K", scatter=0.0)
    rng = np.random.default_rng(5)
    noisy = replace(ref, gains=ref.gains * (1 + 0.02 * rng.standard_normal(ref.gains.shape[-1])))
    raw = compare(sol, noisy)
    smooth = compare(sol, noisy, smooth_mhz=10.0)
    inner = slice(5, -5)
    assert np.std(smooth.ratio[..., inner]) < 0.5 * np.std(raw.ratio[..., inner])
    assert smooth.summary["smoothing"]["kernel"] == "gaussian"
    assert smooth.summary["smoothing"]["fwhm_MHz"] == 10.0


def test_frequency_mismatch_interpolates_or_fails_clearly():
    sol = make_solution(freqs=np.linspace(120e6, 180e6, 31), flagged=())
    # reference on a finer, offset grid covering only 100-160 MHz: linear interpolation
    ref_freqs = np.linspace(100e6, 160e6, 97)
    ref = reference_for(sol, 0.5, freqs=ref_freqs, gain_scale="K")
    result = compare(sol, ref)
    inside = sol.freqs <= 160e6
    assert np.all(result.valid[..., inside]) and not result.valid[..., ~inside].any()
    np.testing.assert_allclose(result.ratio[..., inside], 2.0, rtol=2e-4)
    assert result.summary["per_antenna_pol"][0]["n_outside_reference_range"] == (~inside).sum()
    # flagged reference channels are not bridged
    flags = np.zeros(ref.gains.shape, bool)
    flags[..., [39, 48]] = True  # 124.375 MHz (brackets 124 MHz) and 130 MHz (exact)
    gap = compare(sol, replace(ref, flags=flags))
    lost = result.valid & ~gap.valid
    np.testing.assert_array_equal(
        np.flatnonzero(lost[0, 0]), np.searchsorted(sol.freqs, [124e6, 130e6])
    )
    far = reference_for(sol, 0.5, freqs=np.linspace(300e6, 400e6, 11), gain_scale="K")
    with pytest.raises(CompareError, match=r"no frequency overlap.*120.0000-180.0000 MHz"):
        compare(sol, far)
    vals = interpolate_frequency(
        np.array([1e8, 2e8]), np.array([[1.0, 3.0]]), np.array([1.5e8, 2.5e8])
    )
    np.testing.assert_allclose(vals[0, 0], 2.0)
    assert np.isnan(vals[0, 1])


def test_missing_antennas_and_pols_list_what_is_available():
    sol = make_solution()
    ref = reference_for(sol, 0.5, gain_scale="K")
    only_ee = replace(ref, gains=ref.gains[:, :1], flags=ref.flags[:, :1], pols=("ee",))
    with pytest.raises(CompareError, match=r"\['nn'\] are not in the reference.*\['ee'\]"):
        compare(sol, only_ee, pols=["nn"])
    assert compare(sol, only_ee).pols == ("ee",)  # default: what both have
    with pytest.raises(CompareError, match=r"\[5\] are not in the solution; it has \[0, 23\]"):
        compare(sol, ref, antennas=[5])
    other = replace(ref, antennas=np.array([7, 8]))
    with pytest.raises(
        CompareError, match=r"antennas \[0, 23\] are not in the reference.*\[7, 8\]"
    ):
        compare(sol, other)
    with pytest.raises(CompareError, match=r"\[23\] are not in the reference gains; available"):
        compare(sol, replace(ref, antennas=np.array([0, 24])), antennas=[0, 23])


@pytest.mark.data
def test_real_abscal_file_against_a_consistent_solution(data_root):
    """A solution with G = |g_abscal|^2 J(nu) on the real file's grid compares to 1."""
    ref = read_reference_gains([data_root / REF / n for n in H1C_ABS], antennas=[23, 24])
    omega = beam_solid_angle("hera", ref.freqs)
    amp = ref.abs_g
    finite = np.isfinite(amp)
    with np.errstate(invalid="ignore"):
        mean_sq = np.where(finite, amp**2, 0).sum(axis=2) / finite.sum(axis=2)  # (A, P, F)
    gain = mean_sq * jy_per_kelvin(ref.freqs, omega)
    flagged = tuple(int(i) for i in np.flatnonzero(np.all(~np.isfinite(gain), axis=(0, 1))))
    sol = make_solution(
        antennas=(23, 24),
        freqs=ref.freqs,
        ntime=36,
        jd0=float(ref.jds[0]),
        gain=np.nan_to_num(gain, nan=1.0),
        flagged=flagged,
    )
    sol = replace(sol, jds=ref.jds.copy())
    result = compare(sol, ref)
    assert result.mode == "absolute"
    ok = result.valid
    assert ok.sum() > 0.5 * ok.size
    np.testing.assert_allclose(result.ratio[ok], 1.0, rtol=1e-6)
    conv = result.summary["conversion"]
    assert conv["omega_sr"]["ee"] == pytest.approx(0.0411, abs=5e-4)
    assert conv["uvbeam_get_beam_area_max_rel_diff"] < 1e-3
