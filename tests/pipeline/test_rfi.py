"""Band-edge and RFI flags found from the autos (autocal.pipeline.rfi).

Synthetic checks of each step, then injected RFI on real HERA autos: a measured detection
and false-alarm rate, set beside hera_qm's own ``detrend_medfilt`` + watershed flagger.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from autocal.pipeline.calibrate import read
from autocal.pipeline.rfi import (
    LevelScan,
    RfiMask,
    RfiScan,
    band_edges,
    band_sky,
    robust_zscores,
    watershed,
)

HERA_116 = [f"hera/autos/zen.2458116.{s}.HH.uvh5" for s in ("30448", "31193", "31939")]


def _mask(data: np.ndarray, flags: np.ndarray, block: int | None = None) -> RfiMask:
    """Scan ``data`` as the pipeline does, in blocks of ``block`` integrations."""
    nt = data.shape[2]
    step = nt if block is None else block
    levels = LevelScan()
    for t0 in range(0, nt, step):
        levels.add(data[:, :, t0 : t0 + step], flags[:, :, t0 : t0 + step])
    scan = RfiScan(nt, levels.level())
    for t0 in range(0, nt, step):
        scan.add(data[:, :, t0 : t0 + step], flags[:, :, t0 : t0 + step], t0)
    return scan.finish()


def _bandpass(nt: int = 40, nf: int = 256, seed: int = 0) -> np.ndarray:
    """``(1, 1, nt, nf)`` a smooth bandpass with rolled-off edges, radiometer noise 1e-3."""
    rng = np.random.default_rng(seed)
    x = np.linspace(-1, 1, nf)
    shape = 1e3 * np.exp(-((x / 0.8) ** 12)) * (1 + 0.2 * x)
    drift = 1 + 0.01 * np.linspace(0, 1, nt)[:, None]
    wf = shape * drift * (1 + 1e-3 * rng.standard_normal((nt, nf)))
    return wf[None, None]


def test_robust_zscores_have_unit_width_on_white_noise() -> None:
    """Median-filter residuals over the robust width are about a unit normal (the 0.456
    factor of hera_qm's detrend_medfilt); floored at the series' width a little narrower
    (0.88: the larger of the neighbours' and the series'), and 5 sigma is then rare."""
    rng = np.random.default_rng(3)
    noise = rng.standard_normal((200, 512))
    z = robust_zscores(noise, 8)
    assert 0.9 < np.std(z[np.abs(z) < 10]) < 1.25
    floored = robust_zscores(noise, 8, series_floor=True)
    assert 0.8 < np.std(floored[np.abs(floored) < 10]) < 1.0
    assert np.mean(np.abs(floored) > 5) < 2e-5 < np.mean(np.abs(z) > 5)


def _local_zscores(values: np.ndarray, k: int) -> np.ndarray:
    """hera_qm's ``detrend_medfilt`` in one dimension, the width from the neighbours only."""
    from scipy.ndimage import median_filter

    footprint = np.ones((1, 2 * k + 1), bool)
    footprint[0, k] = False
    resid = values - median_filter(values, footprint=footprint, mode="reflect")
    return resid / np.sqrt(median_filter(resid**2, footprint=footprint, mode="reflect") / 0.456)


def test_the_width_floor_removes_false_alarms_of_white_noise_and_keeps_real_bursts() -> None:
    """White noise of 192 integrations (a HERA file's) with 8 neighbours each side: the
    width of 16 neighbours alone falls low by chance and flags ~5e-4 of the samples after
    the watershed (measured 5.4e-4; a clean HERA-size file had 71 spectra of 134 400
    flagged in time); floored at the series' width, as few as a unit normal gives at 5
    sigma. Bursts of 8 and 10 sigma are found as often as with the local width alone."""
    rng = np.random.default_rng(1)
    noise = rng.standard_normal((20000, 192))
    local = np.mean(watershed(_local_zscores(noise, 8), 5.0, 2.0))
    floored = np.mean(watershed(robust_zscores(noise, 8, series_floor=True), 5.0, 2.0))
    assert local > 3e-4  # the false alarms of the local width, which the floor removes
    assert floored < 1e-5
    np.testing.assert_array_equal(robust_zscores(noise, 8), _local_zscores(noise, 8))
    for amplitude in (8.0, 10.0):
        burst = noise.copy()
        burst[:, 100] += amplitude
        found = np.mean(robust_zscores(burst, 8, series_floor=True)[:, 100] > 5)
        found_local = np.mean(_local_zscores(burst, 8)[:, 100] > 5)
        assert found >= found_local - 0.01, (amplitude, found, found_local)


def test_a_clean_observation_has_no_integration_flagged() -> None:
    """100 antenna-pols x 192 integrations of radiometer noise on a sky that varies in
    time, with the model sky given as the pipeline gives it: no integration is flagged
    (the local width alone flagged 11 here)."""
    rng = np.random.default_rng(11)
    nant, nt, nf = 50, 192, 64
    t = np.linspace(0, 1, nt)[:, None]
    sky = 300 * (1 + 0.02 * t + 0.01 * t**2) * np.linspace(1, 0.5, nf) ** 2.5
    data = (sky + 150.0) * (1 + 1e-3 * rng.standard_normal((nant, 2, nt, nf)))
    flags = np.zeros(data.shape, bool)
    levels = LevelScan()
    levels.add(data, flags)
    scan = RfiScan(nt, levels.level(), band_sky(sky[None], 2))
    scan.add(data, flags, 0)
    assert scan.finish().integrations.sum() == 0


@pytest.mark.parametrize("threads", ["1", "3"])
def test_robust_zscores_on_threads_are_scipys_filter_of_the_whole(monkeypatch, threads) -> None:
    """Rows shared out over threads give what one median filter of the whole array gives."""
    from scipy.ndimage import median_filter

    monkeypatch.setenv("AUTOCAL_FIT_THREADS", threads)
    values = np.random.default_rng(3).random((5, 2, 40))
    footprint = np.ones((1, 1, 17), bool)
    footprint[..., 8] = False
    resid = values - median_filter(values, footprint=footprint, mode="reflect")
    local = median_filter(resid**2, footprint=footprint, mode="reflect")
    series = np.median(resid**2, axis=-1, keepdims=True)
    np.testing.assert_array_equal(robust_zscores(values, 8), resid / np.sqrt(local / 0.456))
    width = np.sqrt(np.maximum(local, series) / 0.456)
    np.testing.assert_array_equal(robust_zscores(values, 8, series_floor=True), resid / width)


def test_watershed_grows_only_runs_touching_a_strong_sample() -> None:
    z = np.array([[0, 3, 7, -3, 0, 3, 3, 0, 6, 0, -8]], float)
    got = watershed(z, 5.0, 2.0)
    expected = [False, True, True, True, False, False, False, False, True, False, False]
    assert got.tolist() == [expected]


def test_band_edges_keep_the_band_and_bridge_a_dead_channel() -> None:
    """Zeroed edge channels and a roll-off are edges; a dead channel inside the band and a
    spike on the last channel do not move the band."""
    level = np.full(100, 10.0)
    level[:12] = 0.0
    level[12:15] = 0.5  # below 10 % of the band: roll-off
    level[50] = 0.0  # dead channel inside the band
    level[90:99] = 0.2
    level[99] = 100.0  # a spike on the last channel
    edge = band_edges(level)
    assert np.flatnonzero(~edge)[[0, -1]].tolist() == [15, 89]
    assert not edge[50]


def test_channels_without_data_do_not_split_the_band() -> None:
    """A wide block of channels the data flag (NaN time-mean) inside the band is no edge:
    the band runs on across it (real HERA 2458099 Miriad autos: flagged blocks had made
    583 of 1024 channels 'band edge')."""
    level = np.full(200, 10.0)
    level[:10] = 0.1
    level[60:120] = np.nan  # 60 channels flagged by the data, far more than 2 KF
    level[190:] = 0.1
    edge = band_edges(level)
    assert np.flatnonzero(~edge)[[0, -1]].tolist() == [10, 189]
    assert not edge[120:190].any() and not edge[10:60].any()


def test_injected_spikes_and_a_burst_are_found_and_block_size_does_not_matter() -> None:
    data = _bandpass()
    flags = np.zeros(data.shape, bool)
    clean = _mask(data, flags)
    inband = ~clean.band_edge[0, 0]
    assert inband.sum() > 150 and clean.band_edge[0, 0, 0] and clean.band_edge[0, 0, -1]
    base = clean.apply(data, flags, 0)[0, 0][:, inband]
    assert base.mean() < 2e-3  # false alarms on Gaussian noise

    rng = np.random.default_rng(1)
    band_channels = np.flatnonzero(inband)
    spikes = [
        (t, band_channels[i]) for t, i in zip(range(0, 40, 2), rng.choice(150, 20), strict=True)
    ]
    hit = data.copy()
    for t, f in spikes:
        hit[0, 0, t, f] *= 1.02  # 20 sigma of the radiometer noise
    hit[0, 0, 25] *= 1.05  # a broadband burst
    whole = _mask(hit, flags)
    blocks = _mask(hit, flags, block=7)
    for name in ("band_edge", "channels", "integrations"):
        assert np.array_equal(getattr(whole, name), getattr(blocks, name)), name
    applied = np.concatenate(
        [blocks.apply(hit[:, :, t : t + 7], flags[:, :, t : t + 7], t) for t in range(0, 40, 7)],
        axis=2,
    )
    assert np.array_equal(applied, whole.apply(hit, flags, 0))
    assert all(applied[0, 0, t, f] for t, f in spikes)
    assert whole.integrations[0, 0].tolist() == [t == 25 for t in range(40)]
    assert whole.counts["rfi_integrations"] == 1
    assert whole.counts["samples"]["band_edge"] == int(whole.band_edge.sum()) * 40
    # flagged whole in time: the burst's samples not already flagged in frequency, counted
    # sample by sample from the mask
    later = whole.integrations[..., None] & ~(whole.band_edge | whole.channels)[:, :, None, :]
    assert whole.counts["samples"]["rfi_time"] == int(later.sum()) == int(inband.sum())


def test_the_scans_inverse_level_is_kept_between_blocks_not_pickled_nor_stale() -> None:
    """The inverse level is made once for a scan's blocks, made again for a new level, and
    not sent back with a file's scan from a reader process."""
    import pickle

    data = _bandpass()
    flags = np.zeros(data.shape, bool)
    levels = LevelScan()
    levels.add(data, flags)
    scan = RfiScan(40, levels.level())
    scan.add(data[:, :, :20], flags[:, :, :20], 0)
    kept = scan._inverse
    scan.add(data[:, :, 20:], flags[:, :, 20:], 20)
    assert kept is not None and scan._inverse is kept  # once for all the blocks
    back = pickle.loads(pickle.dumps(scan))
    assert back._inverse is None and np.array_equal(back.level, scan.level)
    assert len(pickle.dumps(scan)) == len(pickle.dumps(back))  # the same state, no inverse
    scan.level = 2 * scan.level
    scan.add(data[:, :, :1], flags[:, :, :1], 0)
    assert scan._inverse[0] is scan.level
    np.testing.assert_array_equal(scan._inverse[1], 0.5 * kept[1])


def test_the_scans_kept_hits_are_the_flags_the_kernel_gives_again(monkeypatch) -> None:
    """The fit's reads reuse the scan's frequency hits of each block; a block not kept (over
    the budget, another offset or shape, or a portable mask for Dask) is flagged again, with
    the same result."""
    from autocal.pipeline import rfi as rfi_module

    data = _bandpass()
    rng = np.random.default_rng(4)
    data = data * np.where(rng.random(data.shape) < 0.01, 1.02, 1.0)
    flags = np.zeros(data.shape, bool)
    mask = _mask(data, flags, block=8)
    assert len(mask.hits) == 5 and sum(h.size for h in mask.hits.values()) > 10
    portable = mask.portable()
    assert portable.hits == {} and mask.hits
    blocks = [(data[:, :, t : t + 8], flags[:, :, t : t + 8], t) for t in range(0, 40, 8)]
    again = [portable.apply(*b) for b in blocks]
    # the whole observation at once is not a kept block: flagged again, the same flags
    assert np.array_equal(mask.apply(data, flags, 0), portable.apply(data, flags, 0))

    def not_again(*args: object) -> None:
        raise AssertionError("a kept block was flagged again")

    monkeypatch.setattr(rfi_module, "frequency_flags", not_again)
    for b, flagged in zip(blocks, again, strict=True):
        assert np.array_equal(mask.apply(*b), flagged)
    monkeypatch.undo()
    monkeypatch.setattr(rfi_module, "MAX_KEPT_HITS", 0)
    assert _mask(data, flags, block=8).hits == {k: v for k, v in mask.hits.items() if not v.size}


def test_flags_in_time_follow_the_model_sky_not_its_transit() -> None:
    """A day at coarse cadence through a narrow beam: the galaxy's transit is sharper than
    the time median filter. Given the model sky's band level, the transit is not flagged
    (with a slow gain drift on top) and a +3 % broad-band burst still is; without it, the
    transit is flagged."""
    rng = np.random.default_rng(8)
    nt, nf = 96, 128
    t = np.arange(nt)
    freqs = np.linspace(1.0, 1.8, nf)
    sky = 200 * (1 + 3 * np.exp(-0.5 * ((t - 60) / 1.5) ** 2))[:, None] * freqs**-2.5
    gain = (1 + 0.03 * np.linspace(-1, 1, nt))[:, None]  # a 3 % drift over the day
    data = gain * (sky + 100.0) * (1 + 1e-3 * rng.standard_normal((nt, nf)))
    data[20] *= 1.03  # a broad-band burst
    data = data[None, None]
    flags = np.zeros(data.shape, bool)

    def time_flags(with_sky: bool) -> np.ndarray:
        levels = LevelScan()
        levels.add(data, flags)
        scan = RfiScan(nt, levels.level(), band_sky(sky[None], 1) if with_sky else None)
        scan.add(data, flags, 0)
        return scan.finish().integrations[0, 0]

    followed = time_flags(True)
    assert followed[20] and not followed[55:66].any()
    assert time_flags(False)[55:66].any()  # the transit, flagged without the model sky


def test_the_width_floor_is_taken_over_the_usable_integrations() -> None:
    """The first 60 of 192 integrations flagged in every channel (their band level is
    filled with the row's median, residuals near zero): with the floor taken over every
    integration it fell, and noise in the rest was flagged (12 integrations here, 78 with
    the local width alone); over the usable ones, none."""
    rng = np.random.default_rng(12)
    nant, nt, nf = 50, 192, 64
    t = np.linspace(0, 1, nt)[:, None]
    sky = 300 * (1 + 0.02 * t) * np.linspace(1, 0.5, nf) ** 2.5
    data = (sky + 150.0) * (1 + 1e-3 * rng.standard_normal((nant, 2, nt, nf)))
    flags = np.zeros(data.shape, bool)
    flags[:, :, :60] = True
    levels = LevelScan()
    levels.add(data, flags)
    scan = RfiScan(nt, levels.level(), band_sky(sky[None], 2))
    scan.add(data, flags, 0)
    assert not scan.finish().integrations[:, :, 60:].any()


def test_an_integration_without_a_model_sky_is_not_flagged_for_it() -> None:
    """A model sky that is not finite at one integration: the band level is not divided by
    a fit there (the fit's constant alone, a fraction of the level, flagged it in every
    antenna-pol), so nothing is flagged."""
    rng = np.random.default_rng(4)
    nt, nf = 60, 64
    t = np.linspace(0, 1, nt)[:, None]
    sky = 300 * (1 + 0.5 * t) * np.linspace(1, 0.6, nf) ** 2.5
    data = (sky + 150.0) * (1 + 1e-3 * rng.standard_normal((3, 2, nt, nf)))
    flags = np.zeros(data.shape, bool)
    model = band_sky(sky[None], 2).copy()
    model[:, 40] = np.nan
    levels = LevelScan()
    levels.add(data, flags)
    scan = RfiScan(nt, levels.level(), model)
    scan.add(data, flags, 0)
    assert not scan.finish().integrations.any()


def test_a_persistent_narrow_band_transmitter_flags_its_channel() -> None:
    data = _bandpass()
    data[0, 0, :, 128] *= 1.1
    mask = _mask(data, np.zeros(data.shape, bool))
    assert mask.channels[0, 0, 128] and mask.channels.sum() <= 3
    assert mask.counts["rfi_channels"] == int(mask.channels.sum())


def _hera_qm_flags(waterfall: np.ndarray) -> np.ndarray:
    """hera_qm's 2-D flagger on one waterfall: detrend_medfilt (Kt = Kf = 8), 5 sigma, grown
    to 2 sigma neighbours (simple_flag_waterfall's first step)."""
    xrfi = pytest.importorskip("hera_qm.xrfi")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        z = xrfi.detrend_medfilt(waterfall, Kt=8, Kf=8)
        flags = np.abs(z) > 5
        return flags | xrfi._ws_flag_waterfall(z, flags, nsig=2.0)


@pytest.mark.data
@pytest.mark.slow
def test_injected_rfi_on_real_hera_autos_is_found(data_root) -> None:
    """300 single-sample spikes of +1 % (about 20 radiometer sigma; real narrow-band RFI is
    far brighter) injected into in-band, unflagged samples of antenna 23's real autos: at
    least 85 % are found (92 % measured) while the new flags elsewhere stay below 0.2 % of
    the in-band samples; hera_qm's 2-D median filter on the same waterfalls finds far fewer
    of them, because the bandpass's fine structure, which autocal divides out first, widens
    its robust width. Broad-band bursts of +10 % at three integrations are all found."""
    obs = read([data_root / f for f in HERA_116], antennas=[23])
    data, flags = obs.data, obs.flags
    base = _mask(data, flags)
    base_flags = base.apply(data, flags, 0)
    inband = np.broadcast_to(~(base.band_edge | base.channels)[:, :, None, :], data.shape)
    candidates = np.argwhere(inband & ~base_flags)
    pick = candidates[np.random.default_rng(7).choice(len(candidates), 300, replace=False)]
    injected = np.zeros(data.shape, bool)
    injected[tuple(pick.T)] = True
    hit = np.where(injected, data * 1.01, data)
    found = _mask(hit, flags).apply(hit, flags, 0)
    detection = found[injected].mean()
    near = injected | np.roll(injected, 1, -1) | np.roll(injected, -1, -1)
    others = inband & ~base_flags & ~near
    false_alarm = (found & others).sum() / others.sum()
    assert detection >= 0.85, detection
    assert false_alarm < 2e-3, false_alarm

    qm_found = []
    for a, p in np.ndindex(*data.shape[:2]):
        band = ~base.band_edge[a, p]
        full = np.zeros(data.shape[2:], bool)
        full[:, band] = _hera_qm_flags(hit[a, p][:, band])
        qm_found.append(full[injected[a, p]])
    assert np.concatenate(qm_found).mean() < detection

    burst = data.copy()
    burst[:, :, [5, 17, 30]] *= 1.10
    times = _mask(burst, flags).integrations
    for a, p in np.ndindex(*times.shape[:2]):
        assert np.flatnonzero(times[a, p]).tolist() == [5, 17, 30]
