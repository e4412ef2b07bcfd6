"""Sky models: pygdsm offline, CMB convention, power-law extrapolation, rotation, errors."""

from __future__ import annotations

import healpy as hp
import numpy as np
import pytest

from autocal.core.coords import galactic_to_equatorial_matrix, hadec_to_altaz
from autocal.sky.models import T_CMB, PowerLawSky, PygdsmSky, SkyModelError, UniformSky, get_sky


@pytest.mark.data
def test_gsm2008_offline_matches_pygdsm_with_cmb_once(data_root):
    import pygdsm

    freqs = np.array([100e6, 150e6, 200e6])
    sky = get_sky("gsm2008")
    maps, spectra, labels = sky.galactic(freqs, 64)
    assert len(labels) == 3  # GSM2008: three principal components
    ours = spectra @ maps
    ref = np.asarray(pygdsm.GlobalSkyModel(include_cmb=False).generate(freqs / 1e6))
    np.testing.assert_allclose(ours, ref, rtol=1e-9, atol=1e-9)
    comps = sky.components(freqs, nside=64)
    assert comps.labels[-1] == "cmb"
    assert np.sum(np.array(comps.labels) == "cmb") == 1
    ref_cmb = np.asarray(pygdsm.GlobalSkyModel(include_cmb=True).generate(freqs / 1e6))
    # rotation preserves the mean (up to interpolation smoothing)
    np.testing.assert_allclose(comps.temperature().mean(axis=1), ref_cmb.mean(axis=1), rtol=2e-4)


@pytest.mark.data
def test_powerlaw_keeps_cmb_out_of_scaling(data_root):
    base = get_sky("gsm2008")
    sky = PowerLawSky(base, nu0=408e6, beta=-2.55)
    freqs = np.array([60e6, 408e6])
    comps = sky.components(freqs, nside=32)
    gsm408 = base.components(np.array([408e6]), nside=32).temperature()[0]
    total = comps.temperature()
    np.testing.assert_allclose(total[1], gsm408, rtol=1e-9)  # T(nu0) = T0
    expected = (gsm408 - T_CMB) * (60 / 408) ** -2.55 + T_CMB
    np.testing.assert_allclose(total[0], expected, rtol=1e-9)
    assert get_sky("powerlaw:gsm2008@200:-2.4") == PowerLawSky(base, 200e6, -2.4)


def test_uniform_sky_and_spec_strings():
    assert get_sky("uniform:1000") == UniformSky(1000.0)
    comps = get_sky("uniform").components(np.array([1e8]), nside=8)
    np.testing.assert_allclose(comps.temperature(), T_CMB)


def test_unavailable_pygdsm_model_names_the_file(monkeypatch):
    from astropy.utils import data as adata

    monkeypatch.setattr(adata, "is_url_in_cache", lambda url: False)
    monkeypatch.delenv("AUTOCAL_ALLOW_DOWNLOAD", raising=False)
    from autocal.io.datasets import DataFileMissingError

    with pytest.raises(DataFileMissingError, match=r"gsm2016_components\.h5"):
        PygdsmSky("gsm2016").galactic(np.array([1e8]), 32)


def test_bad_sky_inputs():
    with pytest.raises(SkyModelError, match="unknown sky model"):
        get_sky("gsm2099")
    with pytest.raises(SkyModelError, match="empty"):
        UniformSky(10.0).components(np.array([]), nside=8)
    with pytest.raises(SkyModelError, match="MHz"):
        UniformSky(10.0).components(np.array([150.0]), nside=8)
    with pytest.raises(SkyModelError, match="nside"):
        UniformSky(10.0).components(np.array([1e8]), nside=3)


@pytest.mark.parametrize(
    ("spec", "says"),
    [
        ("uniform:.", "T0 (kelvin) is '.', not a number"),
        ("uniform:e", "T0 (kelvin) is 'e', not a number"),
        ("uniform:-", "T0 (kelvin) is '-', not a number"),
        ("uniform:1e400", "must be finite"),
        ("uniform:-100", "must be > 0 K"),
        ("uniform:0", "must be > 0 K"),
        ("powerlaw:gsm2008@.:1", "NU0MHZ (the reference frequency, MHz) is '.'"),
        ("powerlaw:gsm2008@150:-", "BETA (the spectral index) is '-'"),
    ],
)
def test_malformed_sky_numbers_are_user_errors(spec: str, says: str) -> None:
    """A number in a sky specification that is not one (issue 24 D1) or unphysical (D8)."""
    with pytest.raises(SkyModelError) as err:
        get_sky(spec)
    assert says in str(err.value) and spec in str(err.value)
    with pytest.raises(SkyModelError, match=">= 0 K"):
        UniformSky(-1.0)


def test_galactic_centre_lands_at_its_equatorial_position():
    rot = galactic_to_equatorial_matrix("J2000")
    vec = rot @ np.array(hp.ang2vec(np.pi / 2, 0.0))
    theta, phi = hp.vec2ang(vec)
    ra_h, dec = np.degrees(phi[0]) / 15, 90 - np.degrees(theta[0])
    assert ra_h == pytest.approx(17.761, abs=0.01)  # apparent place at J2000
    assert dec == pytest.approx(-28.94, abs=0.02)


def test_hadec_to_altaz_conventions():
    lat = np.radians(-30.0)
    alt, az = hadec_to_altaz(np.array([0.0]), np.array([lat]), lat)
    assert alt[0] == pytest.approx(np.pi / 2)
    # a source on the meridian north of zenith has azimuth 0, east of it azimuth ~90 deg
    alt, az = hadec_to_altaz(np.array([0.0, -0.3]), np.array([0.0, lat]), lat)
    assert az[0] == pytest.approx(0.0, abs=1e-12)
    assert 0 < az[1] < np.pi  # negative hour angle = rising in the east


def test_import_configures_astropy_offline():
    from astropy.coordinates import EarthLocation
    from astropy.utils import iers
    from astropy.utils.data import conf

    assert conf.allow_internet is False
    assert iers.conf.auto_download is False
    registry = EarthLocation._site_registry
    assert registry is not None and len(registry.names) > 0


def test_sky_components_are_computed_once_per_sky_grid_and_epoch(monkeypatch):
    from autocal.sky import models as sky_module
    from autocal.sky.models import UniformSky

    monkeypatch.setattr(sky_module, "_COMPONENTS", {})
    calls = []
    real = UniformSky.galactic

    def counted(self, freqs, nside):
        calls.append((freqs.size, nside))
        return real(self, freqs, nside)

    monkeypatch.setattr(UniformSky, "galactic", counted)
    freqs = np.linspace(100e6, 200e6, 11)
    first = UniformSky(40.0).components(freqs, nside=8, epoch="2020-01-01")
    again = UniformSky(40.0).components(freqs.copy(), nside=8, epoch="2020-01-01")
    assert again is first and len(calls) == 1  # an equal sky, the same grid and epoch
    with pytest.raises(ValueError, match="read-only"):
        first.maps[0, 0] = 1.0  # shared: nobody may change it
    UniformSky(41.0).components(freqs, nside=8, epoch="2020-01-01")
    UniformSky(40.0).components(freqs[:5], nside=8, epoch="2020-01-01")
    UniformSky(40.0).components(freqs, nside=16, epoch="2020-01-01")
    UniformSky(40.0).components(freqs, nside=8, epoch="2021-01-01")
    assert len(calls) == 5
    assert len(sky_module._COMPONENTS) == sky_module.COMPONENTS_MEMO_SIZE  # bounded
    UniformSky(40.0).components(freqs, nside=8, epoch="2020-01-01")  # evicted: recomputed
    assert len(calls) == 6
