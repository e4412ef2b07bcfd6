"""Tsky against an independent reference: direct quadrature on a topocentric grid.

The tolerance comes from ``benchmarks/tsky_accuracy.py`` (results in
``benchmarks/results/tsky_accuracy.md``): the quadrature at 0.2 degrees is within
0.017 K (dipole) and 0.040 K (HERA) of the 0.1-degree one on 24 LSTs (and that within
0.001 / 0.006 K of 0.05 degrees), and the target for the engine at nside 64 is 0.05 K, so
the engine must be within 0.05 K plus that of the 0.2-degree quadrature. The engine with
the sky sampled at the pixel centres (before :mod:`autocal.tsky.bandlimit`) is 0.09 K
(dipole) and 1.07 K (HERA) off on these LSTs.
"""

from __future__ import annotations

import numpy as np
import pytest

from autocal.core.sites import HERA
from autocal.sky.beam_names import get_beam
from autocal.sky.models import UniformSky, get_sky
from autocal.tsky.compute import compute_tsky
from autocal.tsky.horizon import horizon_weight
from autocal.tsky.quadrature import topocentric_grid, tsky_quadrature
from autocal.tsky.result import TskyError

#: max |quadrature(0.2 deg) - quadrature(0.1 deg)| measured (0.017 K dipole, 0.040 K HERA
#: on 24 LSTs, rounded up) plus the engine's 0.05 K target.
TOL_DIPOLE_K = 0.05 + 0.02
TOL_HERA_K = 0.05 + 0.04
LSTS = np.array([0.0, 6.0, 12.0, 18.0])


def test_grid_integrates_the_sphere_and_the_horizon_weight():
    grid = topocentric_grid(1.0, [0.0, 89.0, 91.0, 180.0])
    assert grid.solid_angle.sum() == pytest.approx(4 * np.pi, rel=1e-9)
    # the smoothstep is symmetric about the horizon: it covers exactly half the sphere
    w = horizon_weight(np.pi / 2 - grid.za, 2.0)
    assert (w * grid.solid_angle).sum() == pytest.approx(2 * np.pi, rel=1e-9)
    with pytest.raises(TskyError, match="step"):
        topocentric_grid(0.0, [0.0, 180.0])


def test_uniform_sky_and_ground_are_exact():
    beam = get_beam("dipole")
    freqs = np.array([100e6, 180e6])
    out = tsky_quadrature(UniformSky(20.0), beam, HERA, freqs, LSTS, tgnd=300.0, step_deg=1.0)
    expected = 20.0 * out.f_above + 300.0 * out.f_below
    np.testing.assert_allclose(out.tsky, np.broadcast_to(expected, out.tsky.shape), rtol=1e-12)
    assert 0.01 < out.f_below[0] < 0.2  # the wide dipole at 100 MHz sees some ground


def _max_error(beam_name: str, freqs: np.ndarray) -> float:
    sky = get_sky("gsm2008")
    ref = tsky_quadrature(sky, get_beam(beam_name), HERA, freqs, LSTS, step_deg=0.2)
    engine = compute_tsky(sky, beam_name, HERA, freqs, LSTS, nside=64, cache=False)
    return float(np.abs(engine.tsky - ref.tsky).max())


@pytest.mark.data
@pytest.mark.slow
def test_engine_at_nside_64_matches_quadrature_dipole(data_root):
    err = _max_error("dipole", np.array([100e6, 200e6]))
    assert err <= TOL_DIPOLE_K, f"max |engine - quadrature| = {err:.4f} K"


@pytest.mark.data
@pytest.mark.slow
def test_engine_at_nside_64_matches_quadrature_hera(data_root):
    err = _max_error("hera", np.array([150e6]))
    assert err <= TOL_HERA_K, f"max |engine - quadrature| = {err:.4f} K"


@pytest.mark.data
def test_a_tilted_sky_is_tilted_in_the_quadrature_too(data_root):
    """The independent quadrature turns a :class:`~autocal.sky.models.TiltedSky` as the
    engine does (the diagnosis's frame-tilt templates), not silently the untilted sky."""
    from autocal.sky.models import TiltedSky

    freqs = np.array([150e6])
    tilted = TiltedSky(base=get_sky("gsm2008"), tilt_x_arcmin=40.0, tilt_y_arcmin=-60.0)
    beam = get_beam("dipole")
    ref = tsky_quadrature(tilted, beam, HERA, freqs, LSTS, step_deg=0.5).tsky
    plain = tsky_quadrature(get_sky("gsm2008"), beam, HERA, freqs, LSTS, step_deg=0.5).tsky
    engine = compute_tsky(tilted, "dipole", HERA, freqs, LSTS, nside=64, cache=False).tsky
    moved = float(np.abs(ref - plain).max())
    assert moved > 10 * TOL_DIPOLE_K
    assert float(np.abs(engine - ref).max()) < 0.2 * moved
