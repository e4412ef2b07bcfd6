"""Measure the RFI flagging on real HERA autos with injected RFI, beside hera_qm's flagger.

Usage (from the repository root, data in ``$AUTOCAL_DATA_DIR`` or ``../shared/data``)::

    python scripts/rfi_injection.py

Antenna 23 of JD 2458116 (three files, 36 integrations x 1024 channels, ee and nn): 300
single-sample spikes of each relative amplitude are injected into clean in-band samples,
and broad-band bursts into integrations 5, 17 and 30. Prints the detection rate, the rate
of new flags elsewhere (the injected samples and their neighbouring channels excluded) and
the detection rate of hera_qm's ``detrend_medfilt`` (Kt = Kf = 8, 5 sigma, watershed to
2 sigma) on the same in-band waterfalls, and what is flagged on the data as they are.
"""

from __future__ import annotations

import json
import warnings

import numpy as np

import autocal  # noqa: F401  (offline configuration)
from autocal.io.datasets import data_dir
from autocal.pipeline.calibrate import read
from autocal.pipeline.rfi import LevelScan, RfiMask, RfiScan

FILES = [f"hera/autos/zen.2458116.{s}.HH.uvh5" for s in ("30448", "31193", "31939")]
AMPLITUDES = (0.002, 0.005, 0.01, 0.03)
BURSTS = (0.003, 0.01, 0.03, 0.1)


def scan(data: np.ndarray, flags: np.ndarray) -> RfiMask:
    """The pipeline's two reads on an in-memory waterfall."""
    levels = LevelScan()
    levels.add(data, flags)
    rfi = RfiScan(data.shape[2], levels.level())
    rfi.add(data, flags, 0)
    return rfi.finish()


def hera_qm_flags(data: np.ndarray, band_edge: np.ndarray) -> np.ndarray:
    """hera_qm's 2-D median-filter flags of every antenna-pol's in-band waterfall."""
    from hera_qm import xrfi

    out = np.zeros(data.shape, bool)
    for a, p in np.ndindex(*data.shape[:2]):
        band = ~band_edge[a, p]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            z = xrfi.detrend_medfilt(data[a, p][:, band], Kt=8, Kf=8)
            flags = np.abs(z) > 5
            flags |= xrfi._ws_flag_waterfall(z, flags, nsig=2.0)
        out[a, p][:, band] = flags
    return out


def _runs_mhz(freqs: np.ndarray, flagged: np.ndarray) -> list[str]:
    """Return the runs of flagged channels as ``"a-b"`` (or ``"a"``) in MHz, 2 decimals."""
    idx = np.flatnonzero(flagged)
    runs = np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1) if idx.size else []
    out = []
    for run in runs:
        lo, hi = freqs[run[0]] / 1e6, freqs[run[-1]] / 1e6
        out.append(f"{lo:.2f}" if run.size == 1 else f"{lo:.2f}-{hi:.2f}")
    return out


def main() -> None:
    """Print the measured rates as JSON."""
    root = data_dir()
    obs = read([root / f for f in FILES], antennas=[23])
    data, flags = obs.data, obs.flags
    base = scan(data, flags)
    base_flags = base.apply(data, flags, 0)
    inband = np.broadcast_to(~(base.band_edge | base.channels)[:, :, None, :], data.shape)
    candidates = np.argwhere(inband & ~base_flags)
    rng = np.random.default_rng(1)
    results: dict[str, object] = {
        "as_is": base.counts,
        "channels_flagged_whole_mhz": {
            pol: _runs_mhz(obs.freqs, base.channels[0, p]) for p, pol in enumerate(obs.pols)
        },
    }
    spikes = {}
    for amp in AMPLITUDES:
        pick = candidates[rng.choice(len(candidates), 300, replace=False)]
        injected = np.zeros(data.shape, bool)
        injected[tuple(pick.T)] = True
        hit = np.where(injected, data * (1 + amp), data)
        found = scan(hit, flags).apply(hit, flags, 0)
        near = injected | np.roll(injected, 1, -1) | np.roll(injected, -1, -1)
        others = inband & ~base_flags & ~near
        spikes[str(amp)] = {
            "detection": round(float(found[injected].mean()), 3),
            "false_alarm": float(f"{(found & others).sum() / others.sum():.2e}"),
            "hera_qm_detection": round(
                float(hera_qm_flags(hit, base.band_edge)[injected].mean()), 3
            ),
        }
    results["spikes"] = spikes
    bursts = {}
    for amp in BURSTS:
        hit = data.copy()
        hit[:, :, [5, 17, 30]] *= 1 + amp
        times = scan(hit, flags).integrations
        pairs = np.ndindex(*times.shape[:2])
        bursts[str(amp)] = [np.flatnonzero(times[a, p]).tolist() for a, p in pairs]
    results["bursts_at_5_17_30"] = bursts
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
