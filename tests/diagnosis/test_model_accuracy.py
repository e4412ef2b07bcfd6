"""The forward model's accuracy behind ``forward_model_accuracy``, measured on data autocal
did not simulate: a clean day from the independent simulator, through each beam it knows."""

from __future__ import annotations

import numpy as np
import pytest

from autocal.core.coords import night_epoch
from autocal.core.sites import get_site
from autocal.diagnosis.impact import FORWARD_MODEL_ACCURACY, forward_model_accuracy
from autocal.tsky.compute import compute_tsky
from tests import independent_sim as sim

pytestmark = pytest.mark.data


@pytest.mark.parametrize(
    ("beam", "pol"), [("dipole", "ee"), ("dipole", "nn"), ("hera", "ee"), ("hera", "nn")]
)
def test_independent_clean_day_differs_by_less_than_the_accuracy_floor(beam: str, pol: str) -> None:
    """After the per-channel (G, n) fit, the rms of what autocal's Tsky leaves of an
    independent Tsky (24 h, a 150 K receiver) is below the floor of autocal's beam, and of its
    order (6.4e-5 / 4.4e-5 through the dipole, 4.9e-4 / 5.0e-4 through the HERA beam file
    when the floors were set): a floor neither loose nor beaten by the model itself."""
    freqs = sim.default_freqs()
    jds = sim.jd_at_lst(0.0) + np.arange(96) * 900.0 / 86400.0
    lsts = np.asarray(sim._apparent_lst_hours(jds))
    trxr = 150.0
    data = sim.independent_tsky(freqs, jds, pol, beam) + trxr
    result = compute_tsky(
        "gsm2008",
        beam,
        get_site("hera"),
        freqs,
        lsts,
        epoch=night_epoch(jds, sim.HERA_LON_DEG),
        nside=64,
        pol=pol,
        cache=False,
        progress=False,
    )
    sizes = []
    for f in range(freqs.size):
        design = np.c_[result.tsky[:, f], np.ones(jds.size)] / data[:, f, None]
        coef, *_ = np.linalg.lstsq(design, np.ones(jds.size), rcond=None)
        sizes.append(1.0 - design @ coef)  # (data - model fit) / data
    rms = float(np.sqrt(np.mean(np.square(sizes))))
    floor = forward_model_accuracy(result.meta["beam"])
    assert floor / 10 < rms < floor
    if beam == "dipole":  # evaluated analytically: the default floor
        assert floor == FORWARD_MODEL_ACCURACY
    else:  # a beam file, interpolated: the default floor would be beaten by the model
        assert rms > FORWARD_MODEL_ACCURACY
