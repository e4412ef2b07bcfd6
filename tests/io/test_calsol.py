"""Reference gains (calfits/calh5) in, autocal gains out as genuine UVCal files."""

from __future__ import annotations

import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from astropy.time import Time

import autocal  # noqa: F401  (offline configuration first)
from autocal.core.observation import Observation
from autocal.core.sites import EDGES, HERA
from autocal.fit.lsq import FitModel, Solution, fit
from autocal.io.calsol import (
    CalsolFormatError,
    ReferenceGains,
    read_reference_gains,
    write_calfits,
    write_calh5,
)

REF = "hera/reference_gains"
H1C_ABS = [f"zen.2458116.{t}.HH.flagged_abs.calfits" for t in (30448, 31193, 31939)]
OMNI_36 = [f"zen.2458099.{t}.HH.uv.omni.calfits_36x_only" for t in (22245, 22991, 23737)]
ABS_54 = [f"zen.2458101.{t}.xx.HH.uv.abs.calfits_54x_only" for t in (44615, 45361, 46106)]

#: Every reference-gain file: (Nant, Npol, Ntime, Nfreq), pols, absolute?
SINGLE_FILES = {
    "zen.2458043.40141.xx.HH.XRAA.abs.calfits": ((7, 1, 60, 64), ("ee",), False),
    "zen.2458098.43124.downsample.omni.calfits": ((10, 2, 3, 128), ("ee", "nn"), False),
    "zen.2458098.45361.HH.omni_downselected.calfits": ((8, 2, 10, 64), ("ee", "nn"), False),
    **{name: ((1, 1, 60, 1024), ("ee",), False) for name in OMNI_36},
    **{name: ((1, 1, 60, 1024), ("ee",), True) for name in ABS_54},
    **{name: ((3, 2, 12, 1024), ("ee", "nn"), True) for name in H1C_ABS},
}


# ---------------------------------------------------------------------------------------
# a synthetic solution (shared with test_products and test_compare)
# ---------------------------------------------------------------------------------------
def hera_lsts(jds: np.ndarray, site=HERA) -> np.ndarray:
    return Time(jds, format="jd").sidereal_time("apparent", longitude=site.lon_deg).hour


def make_solution(
    *,
    antennas: tuple[int, ...] = (0, 23),
    pols: tuple[str, ...] = ("ee", "nn"),
    freqs: np.ndarray | None = None,
    ntime: int = 6,
    jd0: float = 2458116.30,
    gain: np.ndarray | None = None,
    rel_sigma: float = 0.01,
    flagged: tuple[int, ...] = (3,),
    config: dict | None = None,
) -> Solution:
    """A constant-model solution with known G (raw/K), Trxr = 150 K and flagged channels."""
    freqs = np.linspace(100e6, 200e6, 41) if freqs is None else np.asarray(freqs, float)
    nant, npol, nfreq = len(antennas), len(pols), freqs.size
    jds = jd0 + np.arange(ntime) * 60.0 / 86400.0
    if gain is None:
        f = freqs / 150e6
        gain = np.empty((nant, npol, nfreq))
        for ia in range(nant):
            for ip in range(npol):
                gain[ia, ip] = (1.0 + 0.1 * ia + 0.05 * ip) * (1 + 0.3 * (f - 1)) * 2e-2
    gain = np.broadcast_to(gain, (nant, npol, nfreq)).astype(float)
    noise = 150.0 * gain
    coeffs = np.stack([gain, noise], axis=-1)
    sig_g, sig_n = rel_sigma * gain, rel_sigma * noise
    cov = np.zeros((nant, npol, nfreq, 2, 2))
    cov[..., 0, 0] = sig_g**2
    cov[..., 1, 1] = sig_n**2
    cov[..., 0, 1] = cov[..., 1, 0] = -0.5 * sig_g * sig_n
    reason = np.zeros((nant, npol, nfreq), np.int64)
    for ch in flagged:
        reason[..., ch] = 2
    bad = reason != 0
    coeffs[bad] = np.nan
    cov[bad] = np.nan
    dof = np.full((nant, npol, nfreq), float(ntime - 2))
    chi2 = np.where(bad, np.nan, dof * 1.1)
    return Solution(
        model=FitModel.for_lsts(hera_lsts(jds)),
        antennas=np.array(antennas, dtype=np.int64),
        pols=tuple(pols),
        freqs=freqs,
        lsts=hera_lsts(jds),
        jds=jds,
        coeffs=coeffs,
        cov=cov,
        chi2=chi2,
        dof=dof,
        count=np.full((nant, npol, nfreq), ntime, np.int64),
        nflagged=np.zeros((nant, npol, nfreq), np.int64),
        flag_reason=reason,
        config={"sky": "gsm2008", "beam": "hera", "telescope": "HERA", **(config or {})},
        antenna_names=tuple(f"HH{a}" for a in antennas),
    )


def fitted_solution(order: int = 1, residuals: bool = True) -> Solution:
    """A solution from autocal.fit.lsq on a small noisy synthetic observation."""
    rng = np.random.default_rng(3)
    ntime, nfreq = 24, 16
    jds = 2458098.30 + np.arange(ntime) * 300.0 / 86400.0
    lsts = hera_lsts(jds)
    freqs = np.linspace(120e6, 180e6, nfreq)
    tsky = 300.0 * (freqs / 150e6) ** -2.5 * (1 + 0.3 * np.sin(lsts / 24 * 2 * np.pi))[:, None]
    gain = np.array([1.0, 1.2])[:, None, None, None] * np.ones((2, 1, 1, nfreq))
    data = gain * (tsky[None, None] + 150.0)
    data = data * (1 + rng.standard_normal(data.shape) * 1e-3)
    flags = np.zeros(data.shape, bool)
    flags[:, :, :, 5] = True  # one channel fails: too few samples
    obs = Observation(
        data=data,
        freqs=freqs,
        lsts=lsts,
        jds=jds,
        antennas=np.array([0, 1]),
        pols=("ee",),
        site=HERA,
        flags=flags,
        channel_width=1e5,
        integration_time=10.0,
    )
    return fit(
        obs,
        tsky,
        model="legendre" if order else "constant",
        order=order,
        weights="identity",
        return_residuals=residuals,
        config={"sky": {"model": "uniform", "cmb": "included"}, "beam": "hera", "tgnd_K": 300.0},
    )


# ---------------------------------------------------------------------------------------
# reading every reference file
# ---------------------------------------------------------------------------------------
@pytest.mark.data
def test_reads_every_reference_gain_file(data_root):
    folder = data_root / REF
    names = sorted(p.name for p in folder.iterdir())
    assert set(names) == set(SINGLE_FILES), "a reference-gain file is not covered"
    for name, (shape, pols, absolute) in SINGLE_FILES.items():
        ref = read_reference_gains(folder / name)
        assert isinstance(ref, ReferenceGains)
        assert ref.gains.shape == shape, name
        assert ref.pols == pols, name
        assert ref.absolute is absolute, (name, ref.meta["kind_reason"])
        assert ref.gain_convention == "divide"
        assert ref.gain_scale == ("Jy" if absolute else None)
        assert np.all(np.diff(ref.freqs) > 0) and np.all(np.diff(ref.jds) > 0)
        assert ref.lsts is not None and np.all((ref.lsts >= 0) & (ref.lsts < 24))
        assert ref.meta["sha256"][0] and len(ref.meta["sha256"][0]) == 64
        assert np.iscomplexobj(ref.gains)
        med = np.nanmedian(ref.abs_g)
        assert (med < 0.1) if absolute else (0.5 < med < 2.0), name


@pytest.mark.data
def test_joins_consecutive_files_and_records_quirks(data_root):
    folder = data_root / REF
    h1c = read_reference_gains([folder / n for n in H1C_ABS])
    assert h1c.gains.shape == (3, 2, 36, 1024)
    assert h1c.antennas.tolist() == [23, 24, 25]
    assert h1c.absolute and h1c.gain_scale == "Jy"
    assert 0.02 < np.nanmedian(h1c.abs_g) < 0.035
    assert h1c.meta["x_orientation"] == "east"
    assert h1c.meta["jones"] == [-5, -6]
    assert np.all(np.diff(h1c.jds) > 0)
    # The old 2018 omnical files lack antenna positions: read without pyuvdata's checks.
    omni = read_reference_gains([folder / n for n in reversed(OMNI_36)])
    assert omni.gains.shape == (1, 1, 180, 1024)
    assert len(omni.meta["unchecked_files"]) == 3
    assert not omni.absolute and "near unity" in omni.meta["kind_reason"]
    assert np.all(np.diff(omni.jds) > 0)  # sorted although given in reverse
    # Named 'abs' but redcal-derived (|g| ~ 0.93): relative, with the reason recorded.
    xraa = read_reference_gains(folder / "zen.2458043.40141.xx.HH.XRAA.abs.calfits")
    assert not xraa.absolute and "abs" in xraa.meta["kind_reason"]
    forced = read_reference_gains(
        folder / "zen.2458043.40141.xx.HH.XRAA.abs.calfits", absolute=True
    )
    assert forced.absolute and forced.gain_scale == "Jy"


@pytest.mark.data
def test_selection_and_clear_errors(data_root):
    files = [data_root / REF / n for n in H1C_ABS[:1]]
    ref = read_reference_gains(files, antennas=[25, 23], pols=["nn"], freq_range=(150e6, 120e6))
    assert ref.antennas.tolist() == [25, 23]
    assert ref.pols == ("nn",)
    assert ref.freqs.min() >= 120e6 and ref.freqs.max() <= 150e6
    full = read_reference_gains(files)
    j = np.searchsorted(full.freqs, ref.freqs[0])
    np.testing.assert_array_equal(ref.gains[1, 0], full.gains[0, 1, :, j : j + ref.nfreq])
    alias = read_reference_gains(files, pols=["xx"])  # x feed points east: xx is ee
    assert alias.pols == ("ee",)
    with pytest.raises(
        CalsolFormatError, match=r"antenna\(s\) \[99\].*available antennas: \[23, 24, 25\]"
    ):
        read_reference_gains(files, antennas=[99])
    with pytest.raises(CalsolFormatError, match="available"):
        read_reference_gains(data_root / REF / OMNI_36[0], pols=["nn"])
    with pytest.raises(CalsolFormatError, match="no channels"):
        read_reference_gains(files, freq_range=(100.0, 200.0))  # MHz given for Hz
    with pytest.raises(CalsolFormatError, match="cannot be joined"):
        read_reference_gains([files[0], data_root / REF / ABS_54[0]])


# ---------------------------------------------------------------------------------------
# writing: calh5 and calfits round trips
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["calh5", "calfits"])
def test_round_trip_through_pyuvdata(tmp_path, kind, capsys):
    from pyuvdata import UVCal

    sol = make_solution()
    writer = write_calh5 if kind == "calh5" else write_calfits
    path = writer(sol, tmp_path / f"gains.{kind}")
    uvc = UVCal.from_file(str(path))  # a genuine, checked UVCal
    assert uvc.cal_type == "gain"
    assert uvc.gain_convention == "divide"
    assert uvc.gain_scale == "K"
    assert uvc.telescope.name == "HERA"
    assert uvc.telescope.get_x_orientation_from_feeds() == "east"
    assert list(uvc.jones_array) == [-5, -6]
    assert uvc.Ntimes == 1 and uvc.time_array is None
    start, stop = uvc.time_range[0]
    assert start < sol.jds.min() and stop > sol.jds.max()
    assert stop - start == pytest.approx(np.ptp(sol.jds) + 60 / 86400, rel=1e-6)
    assert "autocal" in uvc.history and "gain_scale K" in uvc.history
    gains = uvc.gain_array[:, :, 0, :].transpose(0, 2, 1)  # (A, J, F)
    flags = uvc.flag_array[:, :, 0, :].transpose(0, 2, 1)
    np.testing.assert_array_equal(flags, sol.flags)
    ok = ~sol.flags
    np.testing.assert_allclose(gains.real[ok], np.sqrt(sol.G)[ok], rtol=1e-12)
    assert np.all(gains.imag == 0)
    assert np.all(np.isfinite(uvc.gain_array))
    assert np.all(gains[sol.flags] == 1.0)
    quality = uvc.quality_array[:, :, 0, :].transpose(0, 2, 1)
    ok_q = ok & np.isfinite(sol.sigma_abs_g)
    np.testing.assert_allclose(quality[ok_q], sol.sigma_abs_g[ok_q])  # total 1-sigma of |g|
    assert np.all(quality[sol.flags] == 0)
    np.testing.assert_allclose(uvc.total_quality_array[:, 0, :][~sol.flags[0].T], 1.1)

    ref = read_reference_gains(path)
    assert ref.absolute and ref.gain_scale == "K"
    assert ref.pols == ("ee", "nn") and ref.antennas.tolist() == [0, 23]
    np.testing.assert_allclose(ref.jds, [0.5 * (start + stop)])
    np.testing.assert_allclose(ref.abs_g[:, :, 0][ok], sol.abs_g[ok], rtol=1e-12)
    assert np.all(np.isnan(ref.abs_g[:, :, 0][sol.flags]))
    assert capsys.readouterr().out == ""


def test_per_time_and_explicit_time_range(tmp_path):
    from pyuvdata import UVCal

    sol = fitted_solution(order=1, residuals=False)
    path = write_calh5(sol, tmp_path / "per_time.calh5", per_time=True)
    uvc = UVCal.from_file(str(path))
    assert uvc.Ntimes == sol.jds.size
    np.testing.assert_allclose(uvc.time_array, sol.jds)
    big_g = sol.evaluate()["G"]  # (A, P, T, F)
    ok = ~uvc.flag_array.transpose(0, 3, 2, 1)
    np.testing.assert_allclose(
        uvc.gain_array.real.transpose(0, 3, 2, 1)[ok], np.sqrt(big_g)[ok], rtol=1e-12
    )
    rng = (sol.jds.min() - 0.01, sol.jds.max() + 0.01)
    uvc2 = UVCal.from_file(str(write_calh5(sol, tmp_path / "range.calh5", time_range=rng)))
    np.testing.assert_allclose(uvc2.time_range[0], rng)
    with pytest.raises(CalsolFormatError, match="increasing"):
        write_calh5(sol, tmp_path / "bad.calh5", time_range=(rng[1], rng[0]))
    assert not (tmp_path / "bad.calh5").exists()


def test_non_hera_antennas_get_a_minimal_telescope(tmp_path):
    from pyuvdata import UVCal

    sol = make_solution(
        antennas=(0, 400), pols=("ee",), config={"telescope": "EDGES-like", "site": "edges"}
    )
    uvc = UVCal.from_file(str(write_calh5(sol, tmp_path / "edges.calh5")))
    assert uvc.telescope.name == "EDGES-like"
    assert sorted(uvc.telescope.antenna_numbers.tolist()) == [0, 400]
    lat, lon, _ = uvc.telescope.location_lat_lon_alt_degrees
    assert lat == pytest.approx(EDGES.lat_deg, abs=1e-3) and lon == pytest.approx(
        EDGES.lon_deg, abs=1e-3
    )
    assert read_reference_gains(tmp_path / "edges.calh5").antennas.tolist() == [0, 400]


def test_refuses_overwrite_and_writes_atomically(tmp_path, monkeypatch):
    from pyuvdata import UVCal

    sol = make_solution()
    path = write_calh5(sol, tmp_path / "g.calh5")
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match="overwrite"):
        write_calh5(sol, path)
    with pytest.raises(FileExistsError):
        write_calfits(sol, path)
    assert path.read_bytes() == before

    def broken(self, filename, **kwargs):
        Path(filename).write_bytes(b"partial")
        raise OSError("disk full")

    monkeypatch.setattr(UVCal, "write_calh5", broken)
    with pytest.raises(OSError, match="disk full"):
        write_calh5(make_solution(flagged=(1,)), path, overwrite=True)
    assert path.read_bytes() == before  # untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g.calh5"]  # no temporary left
    monkeypatch.undo()
    write_calh5(make_solution(flagged=(1,)), path, overwrite=True)
    assert read_reference_gains(path).flags[:, :, 0, 1].all()


# ---------------------------------------------------------------------------------------
# corrupt and foreign files
# ---------------------------------------------------------------------------------------
def test_corrupt_and_foreign_files_raise_clear_errors(tmp_path):
    empty = tmp_path / "empty.calfits"
    empty.write_bytes(b"")
    junk = tmp_path / "junk.calh5"
    junk.write_bytes(b"this is not a calibration file\n" * 10)
    other_h5 = tmp_path / "other.h5"
    with h5py.File(other_h5, "w") as h5:
        h5["x"] = np.arange(3)
    good = write_calh5(make_solution(), tmp_path / "good.calh5")
    truncated = tmp_path / "truncated.calh5"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    good_fits = write_calfits(make_solution(), tmp_path / "good.calfits")
    truncated_fits = tmp_path / "truncated.calfits"
    truncated_fits.write_bytes(good_fits.read_bytes()[: good_fits.stat().st_size // 2])
    cases = {
        tmp_path / "missing.calfits": "does not exist",
        tmp_path: "directory",
        empty: "empty",
        junk: "neither FITS nor HDF5",
        other_h5: "not calh5",
        truncated: "truncated or corrupt",
        truncated_fits: "corrupt|truncated",
    }
    for path, message in cases.items():
        with pytest.raises(CalsolFormatError, match=message):
            read_reference_gains(path)
    assert issubclass(CalsolFormatError, ValueError)


@pytest.mark.data
def test_visibility_beam_and_product_files_are_not_calibration(data_root, tmp_path):
    from autocal.io.products import write_solution

    with pytest.raises(CalsolFormatError, match="UVH5"):
        read_reference_gains(data_root / "hera/autos/zen.2458116.30448.HH.uvh5")
    with pytest.raises(CalsolFormatError, match="not calfits"):
        read_reference_gains(data_root / "hera/beams/HERA_NF_dipole_power.beamfits")
    product = write_solution(make_solution(), tmp_path / "sol.h5")
    with pytest.raises(CalsolFormatError, match="autocal product"):
        read_reference_gains(product)
    # a truncated real calfits
    src = data_root / REF / H1C_ABS[0]
    cut = tmp_path / "cut.calfits"
    shutil.copyfile(src, cut)
    with open(cut, "r+b") as handle:
        handle.truncate(src.stat().st_size // 3)
    with pytest.raises(CalsolFormatError, match=r"corrupt|truncated"):
        read_reference_gains(cut)


def test_pipeline_style_configuration_sets_telescope_and_history(tmp_path):
    from dataclasses import replace

    from pyuvdata import UVCal

    edges = make_solution(antennas=(0, 1), pols=("ee",))
    edges = replace(
        edges,
        config={
            "calibration": {"sky": "gsm2008", "beam": "edges-low"},
            "provenance": {"site": EDGES.describe(), "sky": {"model": "gsm2008"}},
        },
    )
    uvc = UVCal.from_file(str(write_calh5(edges, tmp_path / "edges.calh5")))
    assert uvc.telescope.name == "edges"
    assert uvc.telescope.location_lat_lon_alt_degrees[0] == pytest.approx(EDGES.lat_deg, abs=1e-3)
    assert '"model": "gsm2008"' in uvc.history and "edges-low" in uvc.history
    hera = replace(edges, config={"provenance": {"site": HERA.describe()}})
    uvc = UVCal.from_file(str(write_calh5(hera, tmp_path / "hera.calh5")))
    assert uvc.telescope.name == "HERA" and uvc.telescope.Nants == 350
