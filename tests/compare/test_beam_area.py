"""Beam solid angles and the Jy-per-K conversion (autocal.compare.beam_area)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import autocal  # noqa: F401
from autocal.compare.beam_area import (
    C_LIGHT,
    K_B,
    beam_from_config,
    beam_solid_angle,
    jy_per_kelvin,
    uvbeam_solid_angle,
)
from autocal.compare.comparison import compare
from autocal.io.calsol_read import read_reference_gains
from autocal.sky.analytic_beams import FunctionBeam
from tests.compare.helpers import BEAM_FILE, exp_beam, reference_for
from tests.io.test_calsol import H1C_ABS, REF, make_solution


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
    from autocal.sky.analytic_beams import GaussianDipoleBeam

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


def test_beam_defaults_to_the_one_recorded_in_the_solution():
    assert beam_from_config({"beam": "dipole"}) == "dipole"
    assert beam_from_config({"provenance": {"beam": {"beam": "airy", "diameter_m": 14}}}) == "airy"
    assert beam_from_config({"provenance": {"beam": {"file": "/x/b.beamfits"}}}) == "/x/b.beamfits"
    assert beam_from_config({}) == "hera"
    # a dipole-beam solution converts with the dipole's Omega_A
    sol = replace(make_solution(pols=("ee",), antennas=(0,), flagged=()), config={"beam": "dipole"})
    result = compare(sol, reference_for(sol, 0.1), nside=32)
    assert result.summary["conversion"]["beam"]["beam"] == "gaussian_dipole"
