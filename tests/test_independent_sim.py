"""The independent forward model (tests/independent_sim.py): files, Tsky, noise, gains.

The model shares no code with autocal's Tsky engine; the only place autocal's engine is
imported is the comparison of the two Tsky computations. Measured agreement (GSM2008,
Gaussian dipole, hard horizon, 110-190 MHz, 161 channels, both at the night's epoch):

* 31 min from LST 3.23 h (174 x 10.7 s): ``ee`` max 2.9e-4, median 9.5e-5;
  ``nn`` max 1.1e-4, median 6.3e-5 (largest at 110 MHz).
* 24 h (288 x 300 s): ``ee`` max 9.7e-4, median 8.4e-5; ``nn`` max 3.8e-4,
  median 6.4e-5.
* HERA Fagnoni beam, 31 min, 6 times: ``ee`` max 3.7e-3, median 1.8e-3; ``nn`` max
  4.1e-3, median 2.1e-3 (the two interpolate the nside-32 beam differently).

The tolerances below are about twice these.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from tests import independent_sim as sim

HERA_LON_DEG = 21.4278
ANTENNAS = (0, 1)
POLS = ("ee", "nn")
DNU_DT = 1e6
LST_START_H = 3.23
DURATION_MIN = 31.0


@pytest.fixture(scope="module")
def sim31(tmp_path_factory: pytest.TempPathFactory, data_root: Path) -> sim.Truth:
    """A 31-minute, 161-channel, 2-antenna, ee/nn simulation without drift."""
    path = tmp_path_factory.mktemp("independent") / "sim31.uvh5"
    return sim.simulate_autos(
        path,
        lst_start_h=LST_START_H,
        duration_min=DURATION_MIN,
        antennas=ANTENNAS,
        pols=POLS,
        trxr_k=150.0,
        dnu_dt=DNU_DT,
        seed=7,
    )


def _autocal_tsky(
    truth: sim.Truth, pol: str, beam: str = "dipole", idx: np.ndarray | None = None
) -> np.ndarray:
    """autocal's Tsky (hard horizon) at the truth's LSTs (or those at ``idx``)."""
    from autocal.core.coords import night_epoch
    from autocal.core.sites import get_site
    from autocal.tsky.compute import compute_tsky

    take = slice(None) if idx is None else idx
    return compute_tsky(
        "gsm2008",
        beam,
        get_site("hera"),
        truth.freqs,
        truth.lsts[take],
        epoch=night_epoch(truth.jds, HERA_LON_DEG),
        pol=pol,
        horizon_width_deg=0.0,
        cache=False,
        progress=False,
    ).tsky


def _relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``|a / b - 1|``."""
    return np.abs(np.asarray(a) / np.asarray(b) - 1.0)


# ---------------------------------------------------------------------------------------
# model pieces that need no data
# ---------------------------------------------------------------------------------------
def test_dipole_beam_orientation_and_width() -> None:
    """Ee is wider north-south, nn east-west; the FWHM is 72 deg at 140 MHz."""
    freqs = np.array([140e6, 180e6])
    za = np.full(4, np.radians(45.0))
    az = np.radians([0.0, 90.0, 180.0, 270.0])
    ee = sim.dipole_beam(freqs, za, az, "ee")
    nn = sim.dipole_beam(freqs, za, az, "nn")
    assert np.all(ee[:, 0] > ee[:, 1]) and np.allclose(ee[:, 0], ee[:, 2])
    assert np.all(nn[:, 1] > nn[:, 0]) and np.allclose(nn[:, 1], nn[:, 3])
    np.testing.assert_allclose(ee[:, [0, 1]], nn[:, [1, 0]], rtol=1e-12)
    zenith = sim.dipole_beam(freqs, np.zeros(1), np.zeros(1), "ee")[:, 0]
    half = sim.dipole_beam(freqs, np.radians([36.0]), np.zeros(1), "ee")[:, 0]
    np.testing.assert_allclose(half[0] / zenith[0], 0.5, rtol=1e-12)
    fwhm_180 = 72.0 * 140.0 / 180.0
    half = sim.dipole_beam(freqs, np.radians([fwhm_180 / 2]), np.zeros(1), "ee")[:, 0]
    np.testing.assert_allclose(half[1] / zenith[1], 0.5, rtol=1e-12)
    with pytest.raises(ValueError, match="polarisation"):
        sim.dipole_beam(freqs, za, az, "xy")


def test_jd_at_lst_lands_on_the_night() -> None:
    """The start JD has the requested apparent LST and follows ``jd_night``."""
    from astropy.time import Time

    for lst in (0.01, 3.23, 17.5):
        jd = sim.jd_at_lst(lst, 2458116)
        assert 2458116 <= jd < 2458117
        got = Time(jd, format="jd", scale="utc").sidereal_time("apparent", longitude=HERA_LON_DEG)
        assert abs((got.hour - lst + 12.0) % 24.0 - 12.0) < 1e-7


def test_default_bandpass_is_smooth_and_positive() -> None:
    """The documented default G0 stays positive and peaks inside the band."""
    freqs = sim.default_freqs()
    assert freqs.size == 161 and freqs[0] == 110e6 and freqs[-1] == 190e6
    gain = sim.default_bandpass(freqs)
    assert np.all(gain > 0.008) and np.all(gain < 0.019)
    assert np.max(np.abs(np.diff(gain, 2))) < 1e-5


# ---------------------------------------------------------------------------------------
# the file
# ---------------------------------------------------------------------------------------
@pytest.mark.data
def test_file_is_a_genuine_uvh5(sim31: sim.Truth) -> None:
    """Pyuvdata reads the file back with the metadata it was built with."""
    from pyuvdata import UVData
    from pyuvdata import utils as uvutils

    uvd = UVData.from_file(str(sim31.path), file_type="uvh5")
    uvd.check()
    assert uvd.telescope.name == "HERA"
    lat, lon, alt = uvd.telescope.location_lat_lon_alt_degrees
    assert lat == pytest.approx(-30.7224, abs=1e-9)
    assert lon == pytest.approx(HERA_LON_DEG, abs=1e-9)
    assert alt == pytest.approx(1100.0, abs=1e-3)
    assert uvd.telescope.get_x_orientation_from_feeds() == "east"
    assert list(uvd.polarization_array) == [-5, -6]
    assert uvutils.polnum2str(list(uvd.polarization_array), x_orientation="east") == list(POLS)
    assert np.array_equal(uvd.ant_1_array, uvd.ant_2_array)
    assert sorted(set(uvd.ant_1_array.tolist())) == list(ANTENNAS)
    assert uvd.Ntimes == sim31.jds.size == 174
    np.testing.assert_allclose(np.unique(uvd.time_array), sim31.jds, rtol=0, atol=1e-9)
    np.testing.assert_allclose(uvd.freq_array.ravel(), sim31.freqs)
    np.testing.assert_allclose(uvd.channel_width, 0.5e6)
    np.testing.assert_allclose(uvd.integration_time, 10.7)
    product = uvd.channel_width[None, :, None] * uvd.integration_time[:, None, None]
    np.testing.assert_allclose(product * uvd.nsample_array, DNU_DT, rtol=1e-6)
    assert not np.any(uvd.flag_array)
    assert np.all(uvd.data_array.imag == 0)
    for ant in ANTENNAS:
        for ip, pol in enumerate(POLS):
            blts = np.arange(uvd.Nblts)[uvd.antpair2ind(ant, ant)]
            blts = blts[np.argsort(uvd.time_array[blts])]
            np.testing.assert_allclose(uvd.lst_array[blts] * 12 / np.pi, sim31.lsts, atol=1e-12)
            data = uvd.data_array[blts, :, ip].real
            assert np.all(data > 0)
            # the file holds the model plus noise at the radiometer level
            ratio = data / sim31.expected()[ip]
            assert np.abs(ratio - 1).max() < 6.0 / math.sqrt(DNU_DT), (ant, pol)
    assert sim31.lsts[0] == pytest.approx(LST_START_H, abs=1e-6)


@pytest.mark.data
def test_autocal_reader_reads_the_file(sim31: sim.Truth) -> None:
    """autocal's reader gives the same data, LSTs and radiometer product."""
    from pyuvdata import UVData

    from autocal.io.uvh5 import read_uvh5

    obs = read_uvh5(sim31.path)
    assert obs.shape == (len(ANTENNAS), len(POLS), sim31.jds.size, sim31.freqs.size)
    assert tuple(obs.pols) == POLS
    assert tuple(obs.antennas.tolist()) == ANTENNAS
    np.testing.assert_allclose(obs.freqs, sim31.freqs)
    np.testing.assert_allclose(obs.jds, sim31.jds, rtol=0, atol=1e-9)
    assert np.max(np.abs(obs.lsts - sim31.lsts)) < 1e-6
    np.testing.assert_allclose(obs.bandwidth_time(), DNU_DT, rtol=1e-6)
    assert not np.any(obs.flags)
    uvd = UVData.from_file(str(sim31.path), file_type="uvh5")
    for ia, ant in enumerate(ANTENNAS):
        blts = np.arange(uvd.Nblts)[uvd.antpair2ind(ant, ant)]
        blts = blts[np.argsort(uvd.time_array[blts])]
        for ip in range(len(POLS)):
            np.testing.assert_array_equal(obs.data[ia, ip], uvd.data_array[blts, :, ip].real)


# ---------------------------------------------------------------------------------------
# Tsky
# ---------------------------------------------------------------------------------------
@pytest.mark.data
def test_tsky_agrees_with_autocal_engine(sim31: sim.Truth) -> None:
    """Independent Tsky vs autocal's (hard horizon): measured max 2.9e-4, median 9.5e-5."""
    for ip, pol in enumerate(POLS):
        rel = _relative(sim31.tsky[ip], _autocal_tsky(sim31, pol))
        assert rel.max() < 6e-4, pol
        assert np.median(rel) < 2e-4, pol


@pytest.mark.data
def test_tsky_is_exact_at_every_integration(sim31: sim.Truth) -> None:
    """The default evaluates every integration exactly; the spline option is close."""
    idx = np.array([0, 29, 87, 140, sim31.jds.size - 1])
    for ip, pol in enumerate(POLS):
        exact = sim.independent_tsky(sim31.freqs, sim31.jds[idx], pol)
        np.testing.assert_allclose(sim31.tsky[ip, idx], exact, rtol=1e-12)
        spline = sim.independent_tsky(sim31.freqs, sim31.jds, pol, node_spacing_s=120.0)
        rel = _relative(spline, sim31.tsky[ip])
        # measured: max 0.8e-4 (ee) / 0.7e-4 (nn), median 1.2e-6 / 1.7e-6; the maximum is
        # the hard horizon's pixel steps, which a spline in time cannot follow
        assert rel.max() < 2e-4 and np.median(rel) < 5e-6, pol
    assert len(sim.node_times(sim31.jds, 120.0)) == 17
    assert len(sim.node_times(sim31.jds[:12], 120.0)) == 12


@pytest.mark.data
def test_tsky_ground_and_sky_physics(sim31: sim.Truth) -> None:
    """Tsky rises by the beam's below-horizon fraction x dTgnd; it falls steeply with nu.

    The fraction from the pixelised sums matches a fine quadrature of the dipole beam to
    0.14 % (2.03 % at 110 MHz, 0.0088 % at 190 MHz).
    """
    jds = sim31.jds[::58]
    base = sim.independent_tsky(sim31.freqs, jds, "ee")
    warm = sim.independent_tsky(sim31.freqs, jds, "ee", tgnd_k=400.0)
    fraction = (warm - base) / 100.0
    za = np.linspace(0.0, np.pi, 2001)
    za = 0.5 * (za[1:] + za[:-1])
    phi = np.linspace(0.0, 2 * np.pi, 361)[:-1]
    grid_za, grid_phi = np.meshgrid(za, phi, indexing="ij")
    chans = np.array([0, 40, 80, 120, 160])
    weight = sim.dipole_beam(sim31.freqs[chans], grid_za, grid_phi, "ee") * np.sin(grid_za)
    below = weight[:, za > np.pi / 2].sum(axis=(1, 2)) / weight.sum(axis=(1, 2))
    np.testing.assert_allclose(
        fraction[:, chans], np.broadcast_to(below, (jds.size, chans.size)), rtol=5e-3
    )
    index = np.log(base[:, -1] / base[:, 0]) / np.log(sim31.freqs[-1] / sim31.freqs[0])
    # GSM2008 off the plane (~ -2.5) steepened by the chromatic dipole: measured -2.81..-2.83
    assert np.all((index > -3.0) & (index < -2.5))


# ---------------------------------------------------------------------------------------
# data model
# ---------------------------------------------------------------------------------------
@pytest.mark.data
def test_noise_is_radiometric(sim31: sim.Truth) -> None:
    """(R / (G0 (Tsky + Trxr)) - 1) sqrt(dnu_dt) has unit std (within 5 sigma)."""
    from autocal.io.uvh5 import read_uvh5

    obs = read_uvh5(sim31.path)
    assert np.all(sim31.drift == 0)
    model = sim31.G0[None, None, None, :] * (sim31.tsky[None] + sim31.Trxr[None, None, None, :])
    z = (obs.data / model - 1.0) * math.sqrt(sim31.dnu_dt)
    size = z.size
    assert abs(np.std(z) - 1.0) < 5.0 / math.sqrt(2.0 * size)
    assert abs(np.mean(z)) < 5.0 / math.sqrt(size)
    # independent antennas and polarisations
    corr = np.corrcoef(z.reshape(-1, z.shape[2] * z.shape[3]))
    off = corr[~np.eye(corr.shape[0], dtype=bool)]
    assert np.all(np.abs(off) < 5.0 / math.sqrt(z.shape[2] * z.shape[3]))


@pytest.mark.data
def test_gain_drift(tmp_path: Path, sim31: sim.Truth) -> None:
    """A linear drift changes G by drift_total end to end with mean G0; callables too."""
    truth = sim.simulate_autos(
        tmp_path / "drift.uvh5",
        lst_start_h=LST_START_H,
        duration_min=DURATION_MIN,
        drift_total=0.02,
        seed=3,
    )
    np.testing.assert_allclose((truth.G[-1] - truth.G[0]) / truth.G0, 0.02, rtol=1e-10)
    np.testing.assert_allclose(truth.G_mean, truth.G0, rtol=1e-12)
    np.testing.assert_allclose(truth.tsky[0], sim31.tsky[0], rtol=1e-12)
    assert truth.G.shape == (truth.jds.size, truth.freqs.size)

    def wobble(t: np.ndarray) -> np.ndarray:
        return 0.01 * np.sin(2 * np.pi * t)

    truth = sim.simulate_autos(
        tmp_path / "wobble.uvh5",
        lst_start_h=LST_START_H,
        duration_min=DURATION_MIN,
        drift=wobble,
        G0=np.full(161, 0.01),
        trxr_k=np.linspace(120.0, 180.0, 161),
        dnu_dt=1e12,
    )
    t_frac = (truth.jds - truth.jds[0]) / (truth.jds[-1] - truth.jds[0])
    np.testing.assert_allclose(truth.drift, wobble(t_frac), atol=1e-15)
    expected = np.broadcast_to(0.01 * (1 + wobble(t_frac))[:, None], truth.G.shape)
    np.testing.assert_allclose(truth.G, expected, rtol=1e-12)
    from autocal.io.uvh5 import read_uvh5

    obs = read_uvh5(truth.path)
    np.testing.assert_allclose(obs.data[0, 0], truth.expected()[0], rtol=1e-5)
    with pytest.raises(ValueError, match="either"):
        sim.simulate_autos(
            tmp_path / "both.uvh5",
            lst_start_h=LST_START_H,
            duration_min=DURATION_MIN,
            drift_total=0.01,
            drift=wobble,
        )


# ---------------------------------------------------------------------------------------
# slow: a whole day, the HERA beam
# ---------------------------------------------------------------------------------------
@pytest.mark.data
@pytest.mark.slow
def test_full_day_agrees_with_autocal(tmp_path: Path, data_root: Path) -> None:
    """24 h of 300 s integrations: measured max 9.7e-4 (ee) / 3.8e-4 (nn), median 8e-5."""
    truth = sim.simulate_autos(
        tmp_path / "day.uvh5",
        lst_start_h=0.01,
        duration_min=1440.0,
        integration_s=300.0,
        pols=POLS,
    )
    assert truth.jds.size == 288
    assert np.all(np.diff(truth.lsts) > 0)
    for ip, pol in enumerate(POLS):
        rel = _relative(truth.tsky[ip], _autocal_tsky(truth, pol))
        assert rel.max() < 2e-3, pol
        assert np.median(rel) < 2e-4, pol


@pytest.mark.data
@pytest.mark.slow
def test_hera_beam_agrees_with_autocal(sim31: sim.Truth) -> None:
    """HERA beam at 6 times: measured max 3.7e-3 (ee) / 4.1e-3 (nn), median ~2e-3."""
    idx = np.arange(0, sim31.jds.size, 29)
    for pol in POLS:
        mine = sim.independent_tsky(sim31.freqs, sim31.jds[idx], pol, beam="hera")
        rel = _relative(mine, _autocal_tsky(sim31, pol, beam="hera", idx=idx))
        assert rel.max() < 8e-3, pol
        assert np.median(rel) < 4e-3, pol
