"""Tsky harmonics (the engine's LST-free output), their cache, and the night's sky frame."""

from __future__ import annotations

import time
from dataclasses import dataclass

import h5py
import healpy as hp
import numpy as np
import pytest

import autocal.tsky.compute as tsky_module
from autocal.core.coords import night_epoch
from autocal.core.sites import EDGES, HERA
from autocal.io.tskyfile import read_harmonics, write_harmonics
from autocal.sky.beam_names import get_beam
from autocal.sky.models import SkyModel
from autocal.tsky.compute import compute_tsky
from autocal.tsky.result import TskyError, TskyHarmonics
from autocal.tsky.ringfft import tsky_fft, tsky_harmonics

FREQS = np.array([100e6, 150e6, 200e6])


@dataclass(frozen=True)
class DipoleSky(SkyModel):
    """A sky brighter towards the Galactic centre (no data files needed)."""

    name: str = "dipole-test"

    def galactic(self, freqs, nside):
        x = hp.pix2vec(nside, np.arange(hp.nside2npix(nside)))[0]
        spectra = np.column_stack([np.full(freqs.size, 100.0), 80.0 * (freqs / 1.5e8) ** -2.5])
        return np.vstack([np.ones_like(x), (1 + x) ** 3]), spectra, ("floor", "dipole")

    def describe(self):
        return {"model": "dipole-test"}


@pytest.fixture(scope="module")
def sky_and_beam():
    return DipoleSky().components(FREQS, nside=16), get_beam("airy", "ee")


def test_table_from_harmonics_is_the_engine_table(sky_and_beam):
    sky, beam = sky_and_beam
    lsts = np.array([0.3, 2.0, 7.77, 13.1, 23.9])  # irregular: the cos/sin synthesis
    tgnd = np.array([280.0, 300.0, 320.0])
    direct = tsky_fft(sky, beam, HERA, lsts, tgnd=tgnd)
    harmonics = tsky_harmonics(sky, beam, HERA)
    table = harmonics.table(lsts, tgnd)
    np.testing.assert_array_equal(table.tsky, direct.tsky)
    np.testing.assert_array_equal(table.f_below, direct.f_below)
    regular = harmonics.table(np.arange(0, 24, 0.25))  # regular grid: the inverse FFT
    again = tsky_fft(sky, beam, HERA, np.arange(0, 24, 0.25))
    np.testing.assert_allclose(regular.tsky, again.tsky, rtol=1e-14)
    with pytest.raises(TskyError, match="LST"):
        harmonics.table([])
    with pytest.raises(TskyError, match="ground temperature"):
        harmonics.table([0.0], tgnd=[300.0, 300.0])


def test_harmonics_file_round_trip_and_bad_files(sky_and_beam, tmp_path):
    sky, beam = sky_and_beam
    harmonics = tsky_harmonics(sky, beam, HERA)
    harmonics = TskyHarmonics(**{**harmonics.__dict__, "meta": {"nside": 16, "sky": {"a": 1}}})
    path = write_harmonics(tmp_path / "h.h5", harmonics)
    back = read_harmonics(path)
    np.testing.assert_array_equal(back.coef, harmonics.coef)
    np.testing.assert_array_equal(back.sum_all, harmonics.sum_all)
    assert back.meta == {"nside": 16, "sky": {"a": 1}}
    with h5py.File(path, "a") as h5:
        del h5["coef"]
        h5["coef"] = np.zeros((3, 2))  # real and the wrong number of channels
    with pytest.raises(ValueError, match="not complex"):
        read_harmonics(path)
    with pytest.raises(ValueError, match="not an autocal Tsky harmonics"):
        read_harmonics(write_harmonics_table(tmp_path))


def write_harmonics_table(tmp_path):
    from autocal.io.tskyfile import write_tsky

    table = compute_tsky("uniform:10", "dipole", "hera", [1e8], [0.0], nside=8, cache=False)
    return write_tsky(tmp_path / "table.h5", table)


def test_every_observation_of_a_night_reuses_one_cache_entry(tmp_cache, monkeypatch):
    # two 10-minute observations of one HERA night: different LSTs and times, one epoch
    jds = {"a": 2458098.30241 + np.arange(4) / 8640, "b": 2458098.61 + np.arange(4) / 8640}
    epochs = {k: night_epoch(v, HERA.lon_deg) for k, v in jds.items()}
    assert epochs["a"] == epochs["b"]
    kwargs = dict(nside=16, epoch=epochs["a"], pol="ee")
    first = compute_tsky(DipoleSky(), "airy", "hera", FREQS, [1.0, 1.1, 1.2], **kwargs)

    def engine(*args, **kw):
        raise AssertionError("the second observation recomputed the harmonics")

    monkeypatch.setattr(tsky_module, "tsky_harmonics", engine)
    second = compute_tsky(DipoleSky(), "airy", "hera", FREQS, [8.4, 8.5], **kwargs)
    monkeypatch.undo()
    fresh = compute_tsky(DipoleSky(), "airy", "hera", FREQS, [8.4, 8.5], cache=False, **kwargs)
    np.testing.assert_allclose(second.tsky, fresh.tsky, rtol=1e-13)
    assert not np.allclose(first.tsky[:2], second.tsky)
    assert second.meta["epoch_jd"] == pytest.approx(epochs["a"], abs=1e-9)


def test_night_epoch_is_local_midnight_of_the_night():
    # HERA (21.4 deg E) nights run over JD fractions ~0.2-0.7: one epoch per night,
    # the local mean midnight (21:34 UTC, i.e. JD fraction ~0.44)
    hera = [night_epoch([jd], HERA.lon_deg) for jd in (2458098.20, 2458098.45, 2458098.75)]
    assert hera[0] == hera[1] == hera[2]
    assert hera[0] == pytest.approx(2458098.5 - HERA.lon_deg / 360, abs=1e-9)
    assert night_epoch([2458099.3], HERA.lon_deg) == pytest.approx(hera[0] + 1, abs=1e-9)
    # EDGES (116.6 deg E): a night crosses noon UTC (the JD's integer boundary)
    edges = [night_epoch([jd], EDGES.lon_deg) for jd in (2458200.90, 2458201.35)]
    assert edges[0] == edges[1]
    # the frame is within 12 h of the data, and the mean time decides
    for jd in np.linspace(2458000.0, 2458003.0, 61):
        assert abs(night_epoch(jd, HERA.lon_deg) - jd) <= 0.5
    assert night_epoch([2458098.2, 2458098.4], HERA.lon_deg) == hera[0]
    # a whole day (an EDGES day file) keeps its mean time: nothing to share
    day = 2458200.1 + np.arange(97) / 96
    assert night_epoch(day, EDGES.lon_deg) == pytest.approx(day.mean(), abs=1e-9)
    assert night_epoch(day[:48], EDGES.lon_deg) != pytest.approx(day[:48].mean(), abs=1e-9)
    with pytest.raises(ValueError, match="finite"):
        night_epoch([], HERA.lon_deg)
    with pytest.raises(ValueError, match="finite"):
        night_epoch([np.nan], HERA.lon_deg)
    with pytest.raises(ValueError, match="Julian date"):
        night_epoch([58098.3], HERA.lon_deg)  # an MJD


@pytest.mark.data
@pytest.mark.slow
def test_the_night_frame_changes_tsky_by_millikelvin(data_root):
    """The frame of the night's midnight instead of the data's own time: < 0.01 K.

    HERA beam, GSM2008, a file 6.7 h after the night's midnight (the end of a HERA
    night). Over a day of LSTs at nside 128 the same comparison gives at most 2.6 mK at 6 h
    and 4.9 mK at 12 h (2e-6 of Tsky; ``benchmarks/observations.py --parts frame``); the
    check here is at nside 64 on a few LSTs to stay quick.
    """
    jds = 2458098.72 + np.arange(96) * 3.32 / 86400
    lsts = np.linspace(4.0, 4.09, 96)
    freqs = np.linspace(100e6, 200e6, 8)
    kwargs = dict(nside=64, pol="ee", cache=False, progress=False)
    own = compute_tsky("gsm2008", "hera", "hera", freqs, lsts, epoch=float(jds.mean()), **kwargs)
    night = night_epoch(jds, HERA.lon_deg)
    assert float(jds.mean()) - night == pytest.approx(0.28, abs=0.01)
    shared = compute_tsky("gsm2008", "hera", "hera", freqs, lsts, epoch=night, **kwargs)
    diff = np.abs(shared.tsky - own.tsky)
    assert 0 < diff.max() < 0.01


def test_concurrent_jobs_of_a_night_compute_its_harmonics_once(tmp_cache, monkeypatch, caplog):
    """A night's first jobs start together: one computes the entry, the others wait for it
    under the entry's lock and read it (flock also excludes threads with their own file)."""
    import threading

    from autocal.tsky import cache as tsky_cache

    calls = []
    engine = tsky_module.tsky_harmonics

    def slow_engine(*args, **kw):
        calls.append(threading.get_ident())
        time.sleep(0.5)  # the others arrive while this one computes
        return engine(*args, **kw)

    monkeypatch.setattr(tsky_module, "tsky_harmonics", slow_engine)
    kwargs = dict(nside=16, epoch=2458098.5, pol="ee")
    results, errors = {}, []

    def job(i):
        try:
            lsts = [1.0 + i, 1.1 + i]
            results[i] = compute_tsky(DipoleSky(), "airy", "hera", FREQS, lsts, **kwargs)
        except Exception as err:  # pragma: no cover - reported below
            errors.append(err)

    caplog.set_level("INFO", logger="autocal.tsky.cache")
    threads = [threading.Thread(target=job, args=(i,)) for i in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    assert len(calls) == 1
    assert "waiting for another process computing Tsky entry" in caplog.text
    monkeypatch.undo()
    for i, result in results.items():
        fresh = compute_tsky(
            DipoleSky(), "airy", "hera", FREQS, [1.0 + i, 1.1 + i], cache=False, **kwargs
        )
        np.testing.assert_allclose(result.tsky, fresh.tsky, rtol=1e-13)
    assert len(list(tmp_cache.glob("*.h5"))) == 1

    # no lock where the cache folder cannot hold one: the job computes all the same
    monkeypatch.setenv("AUTOCAL_CACHE_DIR", str(tmp_cache / "entry.h5" / "x"))
    (tmp_cache / "entry.h5").write_text("a file where a folder should be")
    with tsky_cache.computing("k"):
        pass
    # a holder that never finishes: the waiter computes after the timeout
    monkeypatch.setenv("AUTOCAL_CACHE_DIR", str(tmp_cache))
    with tsky_cache.computing("k2"):
        t0 = time.monotonic()
        with tsky_cache.computing("k2", timeout=0.3):
            assert time.monotonic() - t0 >= 0.3
    assert "computing it" in caplog.text
