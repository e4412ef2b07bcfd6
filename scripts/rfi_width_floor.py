"""Measure the RFI test in time with and without the robust width's floor at the series' own.

Usage (from the repository root)::

    python scripts/rfi_width_floor.py

``autocal.pipeline.rfi.robust_zscores`` divides a sample's residual from the median of its
8 neighbours each side by a robust width from the same neighbours (hera_qm's
``detrend_medfilt``); with ``series_floor`` (the band level in time) that width is never
less than the whole series'. On series of 192 samples (a HERA file's integrations), 20 000
rows of white noise per figure, fixed seeds, this prints as JSON:

* ``false_alarm``: the share of samples flagged by the 5-sigma test grown to 2-sigma
  neighbours (:func:`autocal.pipeline.rfi.watershed`), local width and floored;
* ``z_spread``: the standard deviation of the z-scores within +-10;
* ``found``: the share of single-sample bursts of 6, 8 and 10 sigma above 5 sigma;
* ``found_beside_noisier_part``: the same for 8-sigma bursts (in the quiet part's sigma)
  in a series whose last 40 % (60 %) has twice (three times) the noise;
* ``false_alarm_beside_filled``: the false-alarm share when the first 30, 60 or 90
  samples are unusable and filled with the row's median (as the pipeline fills them),
  the floor taken over every sample or over the usable ones only (``usable``, as
  :meth:`autocal.pipeline.rfi.RfiScan._time_outliers` does).

Takes about 20 s.
"""

from __future__ import annotations

import json

import numpy as np

from autocal.pipeline.rfi import KT, NSIG, NSIG_ADJACENT, robust_zscores, watershed

ROWS, NTIME, BURST_AT = 20000, 192, 60


def _z(values: np.ndarray, floor: bool) -> np.ndarray:
    return robust_zscores(values, KT, series_floor=floor)


def main() -> None:
    """Print the measured rates as JSON."""
    rng = np.random.default_rng(1)
    noise = rng.standard_normal((ROWS, NTIME))
    out: dict[str, object] = {}
    for name, floor in (("local", False), ("floored", True)):
        z = _z(noise, floor)
        found = {}
        for amp in (6.0, 8.0, 10.0):
            burst = noise.copy()
            burst[:, BURST_AT] += amp
            found[f"{amp:g}"] = round(float(np.mean(_z(burst, floor)[:, BURST_AT] > NSIG)), 3)
        beside = {}
        for share, scale in ((0.4, 2.0), (0.6, 3.0)):
            uneven = noise.copy()
            uneven[:, int(NTIME * (1 - share)) :] *= scale
            uneven[:, BURST_AT // 2] += 8.0
            key = f"{share:g} at {scale:g}x"
            beside[key] = round(float(np.mean(_z(uneven, floor)[:, BURST_AT // 2] > NSIG)), 3)
        out[name] = {
            "false_alarm": float(np.mean(watershed(z, NSIG, NSIG_ADJACENT))),
            "z_spread": round(float(np.std(z[np.abs(z) < 10])), 3),
            "found": found,
            "found_beside_noisier_part": beside,
        }
    filled_out = {}
    for nfill in (30, 60, 90):
        usable = np.ones(noise.shape, bool)
        usable[:, :nfill] = False
        filled = noise.copy()
        filled[:, :nfill] = np.median(noise[:, nfill:], axis=-1, keepdims=True)
        rates = {}
        for name, mask in (
            ("local", None),
            ("floor over all", None),
            ("floor over usable", usable),
        ):
            z = robust_zscores(filled, KT, series_floor=name != "local", usable=mask)
            rates[name] = float(np.mean(watershed(z, NSIG, NSIG_ADJACENT) & usable))
        filled_out[str(nfill)] = rates
    out["false_alarm_beside_filled"] = filled_out
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
