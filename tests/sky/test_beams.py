"""Beams: conventions (azimuth, polarisation), file readers, error model, bad input."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from autocal.sky.analytic_beams import (
    AiryBeam,
    GaussianDipoleBeam,
    PerturbedBeam,
    s1_airy,
    s1_dipole,
)
from autocal.sky.beam_base import BeamError
from autocal.sky.beam_names import get_beam

NORTH, EAST = 0.0, np.pi / 2


def _ns_over_ew(beam, freq, za_deg=40.0):
    za = np.radians([za_deg, za_deg])
    north, east = beam.power(np.array([freq]), np.array([NORTH, EAST]), za)[0]
    return north / east


def test_dipole_matches_design_formula():
    beam = GaussianDipoleBeam(pol="ee")
    theta = np.radians(30.0)
    phi = np.radians(25.0)
    fwhm = np.radians(72.0) * (140e6 / 140e6) ** -1
    theta0 = fwhm / (2 * np.sqrt(np.log(2)))
    expected = (
        np.exp(-((theta / theta0) ** 2))
        / (np.sqrt(np.pi) * theta0)
        * (np.cos(phi) ** 2 + np.sin(phi) ** 2 * np.cos(theta)) ** 2
    )
    got = beam.power(np.array([140e6]), np.array([phi]), np.array([theta]))[0, 0]
    assert got == pytest.approx(expected, rel=1e-12)
    # the half-power point of the radial factor is at FWHM / 2
    radial = beam.power(np.array([140e6]), np.array([NORTH, NORTH]), np.array([0.0, fwhm / 2]))[0]
    assert radial[1] / radial[0] == pytest.approx(0.5, rel=1e-12)


def test_dipole_width_scales_inversely_with_frequency():
    beam = GaussianDipoleBeam()
    assert beam.fwhm(np.array([70e6]))[0] == pytest.approx(2 * np.radians(72.0))


def test_ew_dipole_is_wider_north_south():
    assert _ns_over_ew(GaussianDipoleBeam(pol="ee"), 150e6) > 1.2
    assert _ns_over_ew(GaussianDipoleBeam(pol="nn"), 150e6) < 1 / 1.2


@pytest.mark.data
def test_hera_file_beam_orientation(data_root):
    """Fagnoni dish beam: ee (x = east dipole feed) main lobe is wider east-west.

    The feed's narrower E-plane pattern under-illuminates the dish along the dipole,
    so the dish beam is wider in that plane; nn is the 90-degree rotation of ee.
    """
    ee, nn = get_beam("hera", "ee"), get_beam("hera", "nn")
    for freq in (110e6, 150e6, 190e6):
        assert _ns_over_ew(ee, freq, 8.0) < 0.9
        assert _ns_over_ew(nn, freq, 8.0) > 1 / 0.9
    za = np.radians(np.full(2, 8.0))
    a = ee.power(np.array([150e6]), np.array([NORTH, EAST]), za)[0]
    b = nn.power(np.array([150e6]), np.array([EAST, NORTH]), za)[0]
    np.testing.assert_allclose(a, b, rtol=0.05)


@pytest.mark.data
def test_hera_file_beam_uses_pyuvdata_azimuth_convention(data_root):
    """Our (az east of north) evaluation equals pyuvdata's own (az east to north) interp."""
    from pyuvdata import UVBeam

    with warnings.catch_warnings():  # the 2017 file predates pyuvdata's mount_type
        warnings.simplefilter("ignore", DeprecationWarning)
        uvb = UVBeam.from_file(data_root / "hera/beams/HERA_NF_dipole_power.beamfits")
    uvb.select(polarizations=[-5])  # xx = ee for x_orientation east
    az_ours = np.radians([0.0, 30.0, 90.0, 200.0])
    za = np.radians([6.0, 6.0, 6.0, 6.0])
    ref = uvb.interp(
        az_array=np.mod(np.pi / 2 - az_ours, 2 * np.pi),
        za_array=za,
        freq_array=np.array([152e6]),
        return_basis_vector=False,
    )[0][0, 0, 0]
    ours = get_beam("hera", "ee").power(np.array([152e6]), az_ours, za)[0]
    np.testing.assert_allclose(ours, np.real(ref), rtol=0.05)


@pytest.mark.data
def test_hera_beam_is_upsampled_only_when_evaluated(data_root, tmp_cache, monkeypatch):
    """A Tsky cache hit names and checks the beam but never upsamples its maps."""
    from autocal.sky import file_beams as beams
    from autocal.tsky.compute import compute_tsky

    monkeypatch.setattr(beams, "_UPSAMPLED", {})
    beam = get_beam("hera", "nn")
    beam.describe()  # what the Tsky cache key needs
    beam.check_freqs(np.array([150e6]))
    assert beams._UPSAMPLED == {} and "_maps_t" not in vars(beam)
    beam.power(np.array([150e6]), np.array([0.0]), np.array([0.1]))
    assert beam._maps_t.shape == (12 * 512**2, beam.native_freqs.size)  # upsampled to 512
    args = ("uniform:100", "hera", "hera", np.array([150e6, 160e6]), np.array([1.0, 2.0]))
    first = compute_tsky(*args, nside=16, pol="nn")  # computed (and cached)
    beams._UPSAMPLED.clear()
    hit = compute_tsky(*args, nside=16, pol="nn")
    assert beams._UPSAMPLED == {}
    np.testing.assert_array_equal(hit.tsky, first.tsky)


@pytest.mark.data
def test_a_cache_hit_does_not_read_the_beam_file(data_root, tmp_cache):
    """Naming the HERA beam needs its checksum and the header's nside, not the file's maps.

    In a fresh process: the key is the one the read beam gives, a Tsky cache hit neither
    reads the file nor imports pyuvdata or healpy, and a miss still checks the range.
    """
    import json
    import subprocess
    import sys

    from autocal.sky.file_beams import HealpixFileBeam
    from autocal.tsky.compute import compute_tsky

    beam = get_beam("hera", "nn")
    assert "data" not in vars(beam)
    named = beam.describe()
    assert beam.upsample_nside == max(512, beam.data.nside)  # the file read now
    assert named == beam.describe()
    args = ("uniform:100", "hera", "hera", np.array([150e6, 160e6]), np.array([1.0, 2.0]))
    compute_tsky(*args, nside=16, pol="nn")  # computed and cached
    code = (
        "import json, sys\n"
        "import numpy as np\n"
        "from autocal.tsky.compute import compute_tsky\n"
        "t = compute_tsky('uniform:100', 'hera', 'hera', np.array([150e6, 160e6]),\n"
        "    np.array([1.0, 2.0]), nside=16, pol='nn')\n"
        "heavy = ('pyuvdata', 'healpy', 'matplotlib', 'astropy.coordinates')\n"
        "mods = [m for m in heavy if m in sys.modules]\n"
        "print(json.dumps([t.meta['beam'], mods]))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    meta_beam, imported = json.loads(out.stdout)
    assert meta_beam == named and imported == []
    with pytest.raises(BeamError, match="outside"):
        compute_tsky("uniform:100", "hera", "hera", np.array([250e6]), np.array([1.0]), nside=16)
    assert isinstance(beam, HealpixFileBeam)


@pytest.mark.data
def test_hera_file_beam_interpolates_frequency_smoothly(data_root):
    beam = get_beam("hera", "ee")
    assert beam.freq_range == (100e6, 200e6)
    freqs = np.linspace(100e6, 200e6, 201)
    zen = beam.power(freqs, np.array([0.0]), np.array([0.0]))[:, 0]
    off = beam.power(freqs, np.array([0.0]), np.array([np.radians(5.0)]))[:, 0]
    assert np.all(zen > 0.9) and np.all(zen < 1.1)  # peak-normalised file
    assert np.all(np.diff(off / zen) < 0.01)  # beam narrows with frequency (mostly)


@pytest.mark.data
def test_edges_feko_beam(data_root):
    beam = get_beam("edges-low", "ee")
    assert beam.freq_range == (40e6, 100e6)
    data = beam.data
    assert data.gain.shape == (31, 360, 91)
    # a file grid point is reproduced exactly: true az = file az + 90 deg
    f_idx, file_az, el = 10, 33, 47
    value = beam.power(
        np.array([data.freqs[f_idx]]), np.radians([file_az + 90.0]), np.radians([90.0 - el])
    )[0, 0]
    assert value == pytest.approx(data.gain[f_idx, file_az, el], rel=1e-9)
    assert _ns_over_ew(beam, 70e6, 50.0) > 1.2  # excitation axis east-west
    below = beam.power(np.array([70e6]), np.array([0.0]), np.radians([100.0]))
    assert below[0, 0] == 0.0


def test_airy_formula_and_horizon():
    beam = AiryBeam(diameter=14.0)
    freq = 150e6
    lam = 299792458.0 / freq
    # first null at 1.2197 lambda / D... x = 3.8317
    za_null = np.arcsin(3.8317 * lam / (np.pi * 14.0))
    vals = beam.power(np.array([freq]), np.zeros(3), np.array([0.0, za_null, 1.8]))[0]
    assert vals[0] == pytest.approx(1.0)
    assert vals[1] < 1e-8
    assert vals[2] == 0.0  # below the horizon


def test_perturbed_beam_follows_error_model():
    base = AiryBeam()
    pert = PerturbedBeam(base=base, s1=s1_airy, s1_kind="airy")
    freq = np.array([150e6])
    s1 = s1_airy(freq)[0]
    sig = 1.5 * s1
    zas = np.array([0.0, np.arcsin(0.5 * s1), np.arcsin(0.99 * s1), np.arcsin(min(2 * s1, 1))])
    ratio = pert.power(freq, np.zeros(4), zas)[0] / base.power(freq, np.zeros(4), zas)[0]
    s = np.minimum(np.sin(zas), s1)
    f = 1 - (1 - 0.06) * np.exp(-(s**2) / (2 * sig**2))
    np.testing.assert_allclose(ratio, (1 + f) ** 2, rtol=1e-10)
    assert ratio[0] == pytest.approx(1.06**2)
    assert ratio[3] == pytest.approx(ratio[2], rel=0.02)  # constant beyond s1
    assert s1_dipole(np.array([140e6]))[0] == pytest.approx(np.sin(np.radians(36.0)))


def test_perturbed_beam_evaluator_matches_power():
    pert = PerturbedBeam()
    az = np.linspace(0, 2 * np.pi, 7)
    za = np.linspace(0, np.pi, 7)
    freqs = np.array([120e6, 180e6])
    np.testing.assert_allclose(pert.on(az, za)(freqs), pert.power(freqs, az, za))


def test_bad_beam_inputs(tmp_path, data_root):
    with pytest.raises(BeamError, match="unknown beam"):
        get_beam("no-such-beam")
    with pytest.raises(BeamError, match="does not exist"):
        get_beam(str(tmp_path / "missing.beamfits"))
    with pytest.raises(BeamError, match="polarisation"):
        get_beam("dipole", "xy")
    junk = tmp_path / "junk.beamfits"
    junk.write_bytes(b"not a beam" * 100)
    with pytest.raises(BeamError, match="not a readable UVBeam"):
        get_beam(str(junk))
    truncated = tmp_path / "trunc.txt"
    lines = (data_root / "edges/beams/low/default.txt").read_text().splitlines()[:500]
    truncated.write_text("\n".join(lines))
    with pytest.raises(BeamError, match="truncated"):
        get_beam(str(truncated))
    with pytest.raises(BeamError, match="outside"):
        get_beam("hera").power(np.array([90e6]), np.zeros(1), np.zeros(1))
    with pytest.raises(BeamError, match="empty"):
        GaussianDipoleBeam().power(np.array([]), np.zeros(1), np.zeros(1))
