"""Comparison of autos-derived gains with cross-correlation gains: units, shapes, CLI."""

from __future__ import annotations

import argparse
import json
from dataclasses import replace

import numpy as np
import pytest

import autocal  # noqa: F401
from autocal.cli import compare as compare_cmd
from autocal.cli.args import CliError
from autocal.compare.beam_area import (
    C_LIGHT,
    HERA_SIM_BEAM_INTEGRALS,
    K_B,
    beam_from_config,
    beam_solid_angle,
    jy_per_kelvin,
    uvbeam_solid_angle,
)
from autocal.compare.comparison import compare
from autocal.compare.drift import auto_trend, fractional_end_change
from autocal.compare.errors import CompareError
from autocal.compare.ratio_stats import block_bootstrap_error
from autocal.compare.reference import interpolate_frequency, smooth_frequency, time_average
from autocal.compare.report import write_comparison
from autocal.compare.stability import REFERENCE_DRIFT_ALLOWANCE, REFERENCE_DRIFT_FACTOR
from autocal.io.calsol import (
    ReferenceGains,
    read_reference_gains,
    solution_to_uvcal,
    write_calh5,
)
from autocal.io.products import write_solution
from autocal.sky.beams import FunctionBeam
from tests.io.test_calsol import H1C_ABS, REF, make_solution

BEAM_FILE = "hera/beams/HERA_NF_dipole_power.beamfits"


def exp_beam(s: float) -> FunctionBeam:
    """``A = exp(-(1 - cos za) / s)``: ``Omega = 2 pi s (1 - exp(-2 / s))`` in closed form."""
    return FunctionBeam(
        func=lambda f, az, za: np.exp(-(1 - np.cos(za)) / s)[None, :] * np.ones((f.size, 1)),
        key=f"exp{s}",
    )


def reference_for(
    sol,
    factor: np.ndarray | float,
    *,
    ntime: int = 5,
    jds: np.ndarray | None = None,
    freqs: np.ndarray | None = None,
    scatter: float = 0.0,
    absolute: bool = True,
    gain_scale: str | None = "Jy",
    flags: np.ndarray | None = None,
    seed: int = 0,
) -> ReferenceGains:
    """Reference gains with |g_ref|(nu) = factor(nu) |g_auto|(nu), interpolated to ``freqs``."""
    rng = np.random.default_rng(seed)
    freqs = sol.freqs if freqs is None else freqs
    jds = np.linspace(sol.jds.min(), sol.jds.max(), ntime) if jds is None else jds
    g = np.sqrt(np.nan_to_num(sol.G, nan=1.0))
    amp = np.array([[np.interp(freqs, sol.freqs, row) for row in ant] for ant in g])
    amp = amp * np.broadcast_to(factor, amp.shape)
    gains = amp[:, :, None, :] * (
        1 + scatter * rng.standard_normal((*amp.shape[:2], jds.size, freqs.size))
    )
    gains = gains * np.exp(1j * rng.uniform(0, 2 * np.pi, gains.shape))
    return ReferenceGains(
        gains=gains,
        flags=np.zeros(gains.shape, bool) if flags is None else flags,
        freqs=freqs,
        jds=jds,
        lsts=None,
        antennas=sol.antennas.copy(),
        pols=sol.pols,
        gain_convention="divide",
        absolute=absolute,
        gain_scale=gain_scale if absolute else None,
        meta={"files": ["synthetic"]},
    )


# ---------------------------------------------------------------------------------------
# units
# ---------------------------------------------------------------------------------------
def test_jy_per_kelvin_closed_form():
    # 2 k_B / lambda^2 * 1e26 at 150 MHz: 691.3 Jy per K per steradian
    lam = C_LIGHT / 150e6
    assert jy_per_kelvin(150e6, 1.0) == pytest.approx(2 * K_B / lam**2 * 1e26)
    assert jy_per_kelvin(150e6, 1.0) == pytest.approx(691.28, rel=1e-4)
    np.testing.assert_allclose(
        jy_per_kelvin(np.array([75e6, 150e6]), 1.0)[0] * 4, 691.28, rtol=1e-4
    )


@pytest.mark.parametrize("s", [0.05, 0.3])
def test_solid_angle_of_analytic_beams(s):
    omega = beam_solid_angle(exp_beam(s), np.array([100e6, 150e6]), nside=128)
    exact = 2 * np.pi * s * (1 - np.exp(-2 / s))
    np.testing.assert_allclose(omega, exact, rtol=2e-3)
    # cos^2 above the horizon: 2 pi / 3
    cos2 = FunctionBeam(
        func=lambda f, az, za: (np.clip(np.cos(za), 0, None) ** 2)[None, :] * np.ones((f.size, 1))
    )
    assert beam_solid_angle(cos2, [150e6], nside=64)[0] == pytest.approx(2 * np.pi / 3, rel=2e-3)


def test_gaussian_dipole_solid_angle_is_close_to_small_angle_formula():
    from autocal.sky.beams import GaussianDipoleBeam

    # Narrow FWHM 10 deg: the azimuth factor is ~1 and Omega ~ pi theta0^2 (Gaussian in za).
    beam = GaussianDipoleBeam(fwhm_ref_deg=10.0, nu_ref=150e6)
    theta0 = np.radians(10.0) / (2 * np.sqrt(np.log(2)))
    assert beam_solid_angle(beam, [150e6], nside=256)[0] == pytest.approx(
        np.pi * theta0**2, rel=0.01
    )


@pytest.mark.data
def test_hera_beam_solid_angle_matches_uvbeam(data_root):
    freqs = np.array([100e6, 148e6, 152e6, 200e6])
    for pol in ("ee", "nn"):
        ours = beam_solid_angle("hera", freqs, pol=pol)
        theirs = uvbeam_solid_angle(data_root / BEAM_FILE, freqs, pol)
        np.testing.assert_allclose(ours, theirs, rtol=1e-6)
    at150 = beam_solid_angle("hera", [150e6])[0]
    assert at150 == pytest.approx(0.0411, abs=5e-4)
    # hera_sim's H1C beam integral (a different, polynomial beam model) agrees to ~5 %
    table = np.load(data_root / "hera/instrument/HERA_H1C_BEAM_INTEGRALS.npz")
    assert at150 == pytest.approx(np.interp(0.15, table["freqs"], table["omega_p"]), rel=0.08)


@pytest.mark.data
@pytest.mark.slow
def test_readme_sanity_number_for_antenna_23(data_root):
    """raw / |g_abscal|^2 ~ 6900 Jy ~ 255 K at 150 MHz (README of the data folder)."""
    from autocal.io.uvh5 import read_uvh5

    autos = [data_root / "hera/autos" / f"zen.2458116.{t}.HH.uvh5" for t in (30448, 31193, 31939)]
    obs = read_uvh5(autos, antennas=[23], pols=["ee"])
    ref = read_reference_gains([data_root / REF / n for n in H1C_ABS], antennas=[23], pols=["ee"])
    np.testing.assert_allclose(ref.jds, obs.jds, atol=1e-6)
    np.testing.assert_array_equal(ref.freqs, obs.freqs)
    k = int(np.argmin(np.abs(obs.freqs - 150e6)))
    window = slice(k - 5, k + 6)
    raw = np.where(obs.flags[0, 0], np.nan, obs.data[0, 0])[:, window]  # (T, F)
    jy = raw / ref.abs_g[0, 0][:, window] ** 2
    jy_value = float(np.nanmedian(jy))
    kelvin = jy_value / jy_per_kelvin(150e6, beam_solid_angle("hera", [150e6])[0])
    assert jy_value == pytest.approx(6900, rel=0.05)
    assert kelvin == pytest.approx(255, rel=0.06)  # ~245 K with the Fagnoni beam


# ---------------------------------------------------------------------------------------
# the comparison on synthetic data
# ---------------------------------------------------------------------------------------
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


def test_smoothing_kernel():
    freqs = np.linspace(100e6, 200e6, 201)
    linear = 1 + 0.01 * (freqs / 1e6 - 150)
    out, sig = smooth_frequency(freqs, linear[None], np.full((1, 201), 0.1), 2.0)
    np.testing.assert_allclose(out[0, 20:-20], linear[20:-20], rtol=1e-9)
    # noise is averaged down by ~sqrt(number of channels in the kernel)
    assert np.all(sig[0, 20:-20] < 0.1 / np.sqrt(3))
    rng = np.random.default_rng(1)
    noisy = linear + 0.01 * rng.standard_normal(201)
    noisy[50] = np.nan  # flagged channels stay flagged and do not contaminate
    sm, _ = smooth_frequency(freqs, noisy[None], np.full((1, 201), 0.01), 3.0)
    assert np.isnan(sm[0, 50]) and np.isfinite(sm[0, 49])
    assert np.nanstd(sm[0] - linear) < 0.5 * np.nanstd(noisy - linear)
    with pytest.raises(CompareError, match="positive"):
        smooth_frequency(freqs, linear[None], linear[None], 0.0)


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


def test_non_overlapping_times_use_the_nearest_reference_time():
    sol = make_solution()
    ref = reference_for(sol, 0.5, gain_scale="K", jds=sol.jds.max() + np.array([1.0, 2.0]))
    result = compare(sol, ref)
    info = result.summary["time_match"]
    assert info["match"] == "nearest" and info["ntimes"] == 1
    assert info["offset_days"] == pytest.approx(1.0 + 0.5 * np.ptp(sol.jds) * 1, rel=1e-6)
    assert not result.summary["per_antenna_pol"][0]["reference_sigma_available"]
    np.testing.assert_allclose(result.ratio[result.valid], 2.0)


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


# ---------------------------------------------------------------------------------------
# outputs and the command line
# ---------------------------------------------------------------------------------------
def _run_cli(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="autocal")
    sub = parser.add_subparsers(dest="command", required=True)
    compare_cmd.add(sub)
    args = parser.parse_args(argv)
    return args.func(args)


def test_cli_writes_plot_and_json(tmp_path, capsys):
    sol = make_solution()
    sol_path = write_solution(sol, tmp_path / "sol.h5")
    # the reference: an autocal calh5 (gain_scale K) of a solution with G / 1.21
    other = replace(sol, coeffs=sol.coeffs / 1.21, cov=sol.cov / 1.21**2)
    ref_path = write_calh5(other, tmp_path / "ref.calh5")
    out = tmp_path / "out"
    assert (
        _run_cli(["compare", str(sol_path), str(ref_path), "--out", str(out), "--smooth-mhz", "5"])
        == 0
    )
    printed = capsys.readouterr().out
    assert "absolute comparison of 2 antenna(s) x 2 pol(s)" in printed
    summary = json.loads((out / "compare.json").read_text())
    assert summary["mode"] == "absolute"
    assert summary["conversion"]["applied"] is False
    for row in summary["per_antenna_pol"]:
        assert row["ratio_mean"] == pytest.approx(1.1, rel=0.01)
    assert summary["smoothing"]["fwhm_MHz"] == 5.0
    assert (out / "compare.png").stat().st_size > 10_000
    assert (out / "compare.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "compare.h5").exists()
    # outputs are not overwritten unless asked; relative mode and selections work
    with pytest.raises(CliError, match="overwrite"):
        _run_cli(["compare", str(sol_path), str(ref_path), "--out", str(out)])
    assert (
        _run_cli(
            [
                "compare",
                str(sol_path),
                str(ref_path),
                "--out",
                str(out),
                "--overwrite",
                "--mode",
                "relative",
                "--antennas",
                "23",
                "--pols",
                "nn",
            ]
        )
        == 0
    )
    summary = json.loads((out / "compare.json").read_text())
    assert summary["mode"] == "relative" and summary["antennas"] == [23]
    assert summary["pols"] == ["nn"]
    with pytest.raises(CliError, match="smooth"):
        _run_cli(["compare", str(sol_path), str(ref_path), "--out", str(out), "--smooth-mhz", "-1"])
    with pytest.raises(CompareError, match=r"not in the solution; it has \[0, 23\]"):
        _run_cli(
            [
                "compare",
                str(sol_path),
                str(ref_path),
                "--out",
                str(out),
                "--overwrite",
                "--antennas",
                "5",
            ]
        )


def test_write_comparison_refuses_overwrite(tmp_path):
    sol = make_solution()
    result = compare(sol, reference_for(sol, 0.5, gain_scale="K"))
    paths = write_comparison(result, tmp_path / "cmp")
    assert set(paths) == {"json", "png", "h5"}
    with pytest.raises(FileExistsError):
        write_comparison(result, tmp_path / "cmp")
    text = (tmp_path / "cmp/compare.json").read_text()
    assert "NaN" not in text  # strict JSON


def test_beam_defaults_to_the_one_recorded_in_the_solution():
    assert beam_from_config({"beam": "dipole"}) == "dipole"
    assert beam_from_config({"provenance": {"beam": {"beam": "airy", "diameter_m": 14}}}) == "airy"
    assert beam_from_config({"provenance": {"beam": {"file": "/x/b.beamfits"}}}) == "/x/b.beamfits"
    assert beam_from_config({}) == "hera"
    # a dipole-beam solution converts with the dipole's Omega_A
    sol = replace(make_solution(pols=("ee",), antennas=(0,), flagged=()), config={"beam": "dipole"})
    result = compare(sol, reference_for(sol, 0.1), nside=32)
    assert result.summary["conversion"]["beam"]["beam"] == "gaussian_dipole"


# ---------------------------------------------------------------------------------------
# reference drift and stability
# ---------------------------------------------------------------------------------------
def drifting(ref: ReferenceGains, rise: float) -> ReferenceGains:
    """Scale the reference so that |g|^2 rises linearly by ``rise`` over its times."""
    power = 1.0 + rise * np.linspace(0.0, 1.0, ref.ntime)
    return replace(ref, gains=ref.gains * np.sqrt(power)[None, None, :, None])


def end_change(rise: float, ntime: int, k: int) -> float:
    """The drift statistic of a linear |g|^2 ramp with ``k`` integrations per end."""
    power = 1.0 + rise * np.linspace(0.0, 1.0, ntime)
    return power[-k:].mean() / power[:k].mean() - 1.0


def test_fractional_end_change_of_a_ramp_with_flags():
    values = np.outer(1.0 + 0.5 * np.linspace(0, 1, 30), np.ones(8))
    values[0] = np.nan  # a fully flagged integration is not an end
    values[5, 2] = np.nan
    stats = fractional_end_change(values)
    ramp = 1.0 + 0.5 * np.linspace(0, 1, 30)[1:]
    assert stats["n_valid"] == 29 and stats["n_end"] == 3
    assert stats["change"] == pytest.approx(ramp[-3:].mean() / ramp[:3].mean() - 1.0)
    assert stats["rms"] == pytest.approx(np.std(ramp / ramp.mean()), rel=1e-9)
    assert np.isnan(stats["series"][0])
    np.testing.assert_allclose(stats["series"][1:], ramp / ramp.mean())
    single = fractional_end_change(values[:2])
    assert np.isnan(single["change"]) and single["n_valid"] == 1


def test_drifting_reference_is_unstable_and_a_flat_one_stable():
    sol = make_solution(ntime=20)
    flat = reference_for(sol, 0.5, gain_scale="K", ntime=20)
    rising = drifting(flat, 0.5)  # |g_ref|^2 +50 % while the autos are flat
    result = compare(sol, rising, auto_drift=0.0)
    expected = end_change(0.5, 20, 2)
    for row in result.summary["per_antenna_pol"]:
        assert row["reference_drift"] == pytest.approx(expected, rel=1e-9)
        assert row["reference_drift_rms"] > 0.1
        assert row["auto_drift"] == 0.0
        assert row["reference_stable"] is False
        assert row["reference_stability"]["failed"] == ["drift"]
        assert row["reference_stability"]["drift_limit"] == pytest.approx(REFERENCE_DRIFT_ALLOWANCE)
    np.testing.assert_allclose(
        result.reference_series[0, 0], (1 + 0.5 * np.linspace(0, 1, 20)) / 1.25, rtol=1e-9
    )
    stable = compare(sol, flat, auto_drift=0.0)
    for row in stable.summary["per_antenna_pol"]:
        assert row["reference_drift"] == pytest.approx(0.0, abs=1e-12)
        assert row["reference_stable"] is True
    # a reference drift the autos share is allowed (3x the auto's change + 5 %)
    auto = {(0, "ee"): 0.2, (0, "nn"): 0.2, (23, "ee"): 0.1, (23, "nn"): 0.1}
    shared = compare(sol, rising, auto_drift=auto)
    verdict = {
        (r["antenna"], r["pol"]): r["reference_stable"] for r in shared.summary["per_antenna_pol"]
    }
    assert verdict[(0, "ee")] is True and verdict[(23, "nn")] is False  # 0.47 > 0.35
    assert expected > REFERENCE_DRIFT_FACTOR * 0.1 + REFERENCE_DRIFT_ALLOWANCE
    # without the auto's change the drift clause is skipped, the verdict unknown
    unknown = compare(sol, rising)
    row = unknown.summary["per_antenna_pol"][0]
    assert row["auto_drift"] is None and row["reference_stable"] is None
    assert set(row["reference_stability"]["skipped"]) == {"drift", "negative_trxr"}
    assert row["reference_drift"] == pytest.approx(expected)
    # one reference time: no drift, no verdict
    one = compare(sol, reference_for(sol, 0.5, gain_scale="K", ntime=1), auto_drift=0.0)
    assert one.summary["per_antenna_pol"][0]["reference_drift"] is None
    assert one.summary["per_antenna_pol"][0]["reference_stable"] is None


def test_negative_receiver_temperature_implied_by_the_reference():
    sol = make_solution(antennas=(0,), pols=("ee",), ntime=20, flagged=())
    ref = drifting(reference_for(sol, 1.0, gain_scale="K", ntime=20), 0.5)
    g2 = sol.G[0, 0]
    first, last = (
        (1 + 0.5 * np.linspace(0, 1, 20)[:2]).mean(),
        (1 + 0.5 * np.linspace(0, 1, 20)[-2:]).mean(),
    )
    power = np.stack([g2 * 150.0, g2 * 150.0])  # the raw autos do not move
    for tsky, verdict in ((20.0, True), (120.0, False)):
        result = compare(
            sol,
            ref,
            auto_power_ends={(0, "ee"): power},
            tsky_ends={"ee": np.full((2, sol.freqs.size), tsky)},
        )
        row = result.summary["per_antenna_pol"][0]
        implied = row["reference_stability"]["implied_trxr_K"]
        assert implied["first"] == pytest.approx(150.0 / first - tsky, rel=1e-6)
        assert implied["last"] == pytest.approx(150.0 / last - tsky, rel=1e-6)
        assert row["reference_stability"]["tested"] == ["negative_trxr"]
        assert row["reference_stable"] is verdict


def test_auto_trend_feeds_compare():
    sol = make_solution(antennas=(0,), pols=("ee", "nn"), ntime=20, flagged=())
    power = np.ones((1, 2, 20, sol.freqs.size)) * sol.G[:, :, None, :] * 150.0
    power = power * (1 - 0.036 * np.linspace(0, 1, 20))[None, None, :, None]
    flags = np.zeros(power.shape, bool)
    flags[0, 0, 7, :] = True
    tsky = np.full((2, 20, sol.freqs.size), 100.0)
    trend = auto_trend(power, sol.jds, [0], ["ee", "nn"], flags=flags, tsky=tsky)
    assert trend["auto_drift"][(0, "nn")] == pytest.approx(end_change(-0.036, 20, 2))
    assert trend["tsky_ends"][(0, "ee")].shape == (2, sol.freqs.size)
    ref = drifting(reference_for(sol, 1.0, gain_scale="K", ntime=20), 0.5)
    result = compare(sol, ref, **trend)
    for row in result.summary["per_antenna_pol"]:
        assert row["auto_drift"] == pytest.approx(-0.035, abs=2e-3)
        assert row["reference_stable"] is False
        assert row["reference_stability"]["tested"] == ["drift", "negative_trxr"]
    assert result.auto_series is not None and (0, "ee") in result.auto_series


def test_drift_through_a_written_calfits_file(tmp_path):
    sol = make_solution(ntime=12)
    omega = np.full(sol.freqs.size, 0.04)
    jpk = jy_per_kelvin(sol.freqs, omega)

    def written(rise: float, pol_convention: str | None) -> ReferenceGains:
        uvc = solution_to_uvcal(sol, per_time=True)
        power = 1.0 + rise * np.linspace(0.0, 1.0, sol.jds.size)
        # pyuvdata (A, F, T, J): a Jy-referenced |g| = |g_auto| sqrt(power) / sqrt(J)
        uvc.gain_array = (
            uvc.gain_array * np.sqrt(power)[None, None, :, None] / np.sqrt(jpk)[None, :, None, None]
        )
        uvc.gain_scale = "Jy"
        uvc.pol_convention = pol_convention
        path = tmp_path / f"ref_{rise}_{pol_convention}.calfits"
        uvc.write_calfits(str(path))
        return read_reference_gains(path)

    rising = compare(sol, written(0.5, None), omega=omega, auto_drift=0.0)
    flat = compare(sol, written(0.0, None), omega=omega, auto_drift=0.0)
    for row in rising.summary["per_antenna_pol"]:
        assert row["reference_drift"] == pytest.approx(end_change(0.5, 12, 1), rel=1e-6)
        assert row["reference_stable"] is False
    for row in flat.summary["per_antenna_pol"]:
        assert row["reference_stable"] is True
        assert row["ratio_mean"] == pytest.approx(1.0, rel=1e-6)
        pol = row["systematics"]["pol_convention"]
        assert pol["source"] == "assumed" and pol["used"] == "avg" and pol["stated"] is None
        assert pol["ratio_mean"] == pytest.approx(np.sqrt(2) * row["ratio_mean"])
    # a file stating the 'sum' convention: half the Jy per raw unit, ratio sqrt(2) larger
    summed = compare(sol, written(0.0, "sum"), omega=omega, auto_drift=0.0)
    np.testing.assert_allclose(summed.ratio[summed.valid], np.sqrt(2), rtol=1e-6)
    assert summed.summary["conversion"]["pol_convention"] == "sum"
    for row in summed.summary["per_antenna_pol"]:
        pol = row["systematics"]["pol_convention"]
        assert pol["source"] == "file" and pol["used"] == "sum"
        assert pol["alternative"] == "avg"
        assert pol["ratio_mean"] == pytest.approx(1.0, rel=1e-6)
    stated = compare(sol, written(0.0, "avg"), omega=omega)
    assert stated.summary["systematics"]["pol_convention"]["source"] == "file"


# ---------------------------------------------------------------------------------------
# reference uncertainty and the offset's error
# ---------------------------------------------------------------------------------------
def test_sigma_reference_is_the_scatter_over_time():
    sol = make_solution(rel_sigma=1e-4, flagged=())
    ref = reference_for(sol, 0.5, gain_scale="K", ntime=40, scatter=0.05, seed=3)
    result = compare(sol, ref)
    amp = ref.abs_g  # (A, P, T, F), the same channels: no interpolation
    expected = np.std(amp, axis=2, ddof=1)
    ok = result.valid
    np.testing.assert_allclose(result.sigma_reference[ok], expected[ok], rtol=1e-9)
    rel = result.sigma_reference[ok] / result.reference[ok]
    assert np.median(rel) == pytest.approx(0.05, rel=0.15)  # not 0.05 / sqrt(40)
    assert result.summary["per_antenna_pol"][0]["sigma_reference_rel_median"] == pytest.approx(
        np.median(rel[: ok[0, 0].sum()]), rel=1e-9
    )
    _, sem, count = time_average(amp, error="sem")
    np.testing.assert_allclose(sem, expected / np.sqrt(count))
    with pytest.raises(CompareError, match="scatter"):
        time_average(amp, error="bogus")


def test_block_bootstrap_of_white_noise_matches_the_standard_error():
    rng = np.random.default_rng(0)
    x = rng.standard_normal(2000)
    freqs = 100e6 + 0.1e6 * np.arange(2000)
    err, info = block_bootstrap_error(x, freqs)
    assert info["block_channels"] == 50 and info["resamples"] == 1000
    assert err == pytest.approx(1 / np.sqrt(2000), rel=0.15)
    again, _ = block_bootstrap_error(x, freqs)
    assert again == err  # seeded
    assert np.isnan(block_bootstrap_error(x[:1], freqs[:1])[0])


def test_offset_error_respects_correlations_across_channels():
    from scipy.ndimage import gaussian_filter1d

    freqs = np.linspace(110e6, 190e6, 401)  # 0.2 MHz channels
    eps = 0.004  # per-channel noise of |g|
    base = make_solution(antennas=(0,), pols=("ee",), freqs=freqs, flagged=(), rel_sigma=2 * eps)
    ref = reference_for(base, 1.0, gain_scale="K", ntime=3)
    g_ref = np.sqrt(base.G[0, 0])
    true = 0.05
    s = 2.0 / 0.2 / 2.355  # a smooth perturbation with a 2 MHz FWHM correlation
    covered, ratio_boot = [], []
    for seed in range(200):
        rng = np.random.default_rng(seed)
        smooth = gaussian_filter1d(rng.standard_normal(freqs.size), s)
        smooth *= 0.02 * np.sqrt(2 * np.sqrt(np.pi) * s)  # 2 % rms
        r = (1 + true) * (1 + smooth) + eps * rng.standard_normal(freqs.size)
        sol = make_solution(
            antennas=(0,),
            pols=("ee",),
            freqs=freqs,
            flagged=(),
            rel_sigma=2 * eps,
            gain=(r * g_ref) ** 2,
        )
        row = compare(sol, ref).summary["per_antenna_pol"][0]
        assert row["offset"] == pytest.approx(row["ratio_mean"] - 1)
        assert row["offset_error_reference_common"] == 0.0
        covered.append(abs(row["offset"] - true) < 2 * row["offset_error"])
        ratio_boot.append(row["offset_error"] / row["offset_error_independent"])
    assert np.median(ratio_boot) > 3  # correlated channels: far above sqrt(sum s^2) / N
    assert 0.9 <= np.mean(covered) <= 0.99


def test_reference_scatter_common_to_all_channels_enters_the_offset_error():
    sol = make_solution(rel_sigma=1e-4, flagged=(), ntime=20)
    ref = drifting(reference_for(sol, 1.0, gain_scale="K", ntime=20), 0.5)
    row = compare(sol, ref).summary["per_antenna_pol"][0]
    amp = np.sqrt(1 + 0.5 * np.linspace(0, 1, 20))
    level = amp / np.sqrt(np.mean(amp**2))
    assert row["offset_error_reference_common"] == pytest.approx(
        row["ratio_mean"] * np.std(level, ddof=1), rel=1e-6
    )
    assert row["offset_error"] >= row["offset_error_reference_common"]


# ---------------------------------------------------------------------------------------
# systematics budget
# ---------------------------------------------------------------------------------------
def test_sky_model_alternatives_spread():
    sol = make_solution(flagged=())
    omega = np.full(sol.freqs.size, 0.04)
    ref = reference_for(sol, 1.0 / np.sqrt(jy_per_kelvin(sol.freqs, omega)))
    alts = {
        "beta -2.5": replace(sol, coeffs=sol.coeffs * 1.1**2, cov=sol.cov * 1.1**4),
        "beta -2.55": replace(sol, coeffs=sol.coeffs * 0.95**2, cov=sol.cov * 0.95**4),
    }
    result = compare(sol, ref, omega=omega, alternatives=alts)
    for row in result.summary["per_antenna_pol"]:
        sky = row["systematics"]["sky_model"]
        assert sky["alternatives"]["beta -2.5"]["shift"] == pytest.approx(0.1, rel=1e-6)
        assert sky["alternatives"]["beta -2.55"]["ratio_mean"] == pytest.approx(0.95, rel=1e-3)
        assert sky["spread_fraction"] == pytest.approx(0.15, rel=1e-6)
    plain = compare(sol, ref, omega=omega)
    assert plain.summary["per_antenna_pol"][0]["systematics"]["sky_model"] is None
    assert compare(sol, reference_for(sol, 1.0, absolute=False)).summary["systematics"] is None


def test_figure_and_outputs_carry_the_drift(tmp_path):
    sol = make_solution(ntime=20)
    ref = drifting(reference_for(sol, 0.5, gain_scale="K", ntime=20), 0.5)
    power = np.ones((2, 2, 20, sol.freqs.size))
    result = compare(sol, ref, **auto_trend(power, sol.jds, sol.antennas, sol.pols))
    paths = write_comparison(result, tmp_path / "cmp")
    summary = json.loads(paths["json"].read_text())
    row = summary["per_antenna_pol"][0]
    for key in ("offset", "offset_error", "offset_sigma", "reference_drift", "reference_stable"):
        assert key in row
    assert "bootstrap" in summary["offset_method"]
    assert (
        str(REFERENCE_DRIFT_FACTOR).rstrip("0").rstrip(".") in summary["reference_stability_rule"]
    )
    import h5py

    with h5py.File(paths["h5"]) as h5:
        assert h5["reference_series"].shape == (2, 2, 20)
        assert "auto_series/0_ee/power_over_mean" in h5
    assert paths["png"].stat().st_size > 10_000


@pytest.mark.data
def test_budget_and_drift_from_the_real_files(data_root):
    """omega_source from hera_sim's table, pol_convention from the calfits, drift of ant 23."""
    from pyuvdata import UVCal

    files = [data_root / REF / n for n in H1C_ABS]
    ref = read_reference_gains(files, antennas=[23], freq_range=(140e6, 160e6))
    amp = ref.abs_g
    finite = np.isfinite(amp)
    with np.errstate(invalid="ignore"):
        mean_sq = np.where(finite, amp**2, 0).sum(axis=2) / finite.sum(axis=2)
    omega = beam_solid_angle("hera", ref.freqs)
    gain = mean_sq * jy_per_kelvin(ref.freqs, omega)
    flagged = tuple(int(i) for i in np.flatnonzero(np.all(~np.isfinite(gain), axis=(0, 1))))
    sol = make_solution(
        antennas=(23,),
        freqs=ref.freqs,
        ntime=36,
        gain=np.nan_to_num(gain, nan=1.0),
        flagged=flagged,
    )
    sol = replace(sol, jds=ref.jds.copy())
    result = compare(sol, ref, auto_drift=-0.036)
    # omega_source: hera_sim's omega_p, read here independently of autocal
    table = np.load(data_root / HERA_SIM_BEAM_INTEGRALS)
    om_hs = np.interp(ref.freqs, table["freqs"] * 1e9, table["omega_p"])
    # pol_convention: what pyuvdata reads from the files
    stated = {UVCal.from_file(str(f), read_data=False).pol_convention for f in files}
    for ip, row in enumerate(result.summary["per_antenna_pol"]):
        ok = result.valid[0, ip]
        scale = np.sqrt(result.omega[ip] / om_hs)
        r = result.ratio[0, ip]
        om_entry = row["systematics"]["omega_source"]
        assert om_entry["shift"] == pytest.approx(
            np.mean(r[ok] * scale[ok]) / np.mean(r[ok]) - 1, rel=1e-9
        )
        assert 0.015 < om_entry["shift"] < 0.035  # hera_sim's Omega is ~5 % smaller
        pol = row["systematics"]["pol_convention"]
        if stated == {None}:
            assert pol["source"] == "assumed" and pol["used"] == "avg"
            assert pol["shift"] == pytest.approx(np.sqrt(2) - 1)
        else:
            assert pol["source"] == "file" and pol["used"] in stated
        # abscal's |g|^2 of antenna 23 rises by ~50 % over the 31 minutes
        assert 0.4 < row["reference_drift"] < 0.6
        assert row["reference_stable"] is False
    at150 = result.summary["systematics"]["per_pol"]["ee"]
    assert at150["omega_ratio_hera_sim_over_autocal"] == pytest.approx(0.95, abs=0.01)
