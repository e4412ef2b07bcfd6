"""How smooth in time is each code's HERA-beam Tsky? (independent model vs autocal)

Usage (from the repository root, data in ``$AUTOCAL_DATA_DIR`` or ``../shared/data``)::

    python scripts/tsky_roughness.py [--sim-nside 32]

40 integrations of 10.7 s from LST 3.23 h, 17 channels 110-190 MHz, ee, hard horizon. For
the independent forward model (``tests/independent_sim.py``: the beam interpolated by pyuvdata
at every pixel's direction, per integration) and autocal's engine at nside 64 and 128, the
rms over time of the channel-averaged second difference of Tsky / its time mean (an
achromatic roughness from one integration to the next: what a per-integration gain fits),
and how the codes differ.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import autocal  # noqa: F401  (offline configuration)
from autocal.core.coords import night_epoch
from autocal.core.sites import get_site
from autocal.tsky.compute import compute_tsky
from tests.independent_sim import _apparent_lst_hours, independent_tsky, jd_at_lst


def roughness(tsky: np.ndarray) -> float:
    """Rms over time of the channel-averaged second difference of Tsky / its time mean."""
    rel = tsky / tsky.mean(axis=0)
    second = rel[2:] - 2 * rel[1:-1] + rel[:-2]
    return float(np.sqrt(np.mean(second.mean(axis=1) ** 2)))


def main() -> None:
    import argparse

    import tests.independent_sim as sim

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--sim-nside", type=int, default=sim.SIM_NSIDE, help="the independent model's sky nside"
    )
    args = parser.parse_args()
    sim.SIM_NSIDE = args.sim_nside  # before any (cached) evaluation
    site = get_site("hera")
    freqs = np.linspace(110e6, 190e6, 17)
    jds = jd_at_lst(3.23) + np.arange(40) * 10.7 / 86400
    lsts = _apparent_lst_hours(jds)
    epoch = night_epoch(jds, site.lon_deg)
    independent = independent_tsky(freqs, jds, pol="ee", beam="hera")
    kw = {"epoch": epoch, "pol": "ee", "horizon_width_deg": 0.0}
    a64 = compute_tsky("gsm2008", "hera", site, freqs, lsts, **kw).tsky
    a128 = compute_tsky("gsm2008", "hera", site, freqs, lsts, nside=128, **kw).tsky
    out = {
        "independent_sky_nside": args.sim_nside,
        "roughness": {
            "independent": roughness(independent),
            "autocal_nside64": roughness(a64),
            "autocal_nside128": roughness(a128),
        },
        "median_abs_relative_difference": {
            "independent_vs_autocal64": float(np.median(np.abs(independent / a64 - 1))),
            "autocal128_vs_autocal64": float(np.median(np.abs(a128 / a64 - 1))),
        },
    }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
