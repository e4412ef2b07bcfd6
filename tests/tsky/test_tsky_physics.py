"""Physical sanity of Tsky on real beams and sky maps, including the published EDGES spectrum."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from autocal.io.datasets import EDGES_2018_SPECTRUM
from autocal.sky.models import T_CMB
from autocal.tsky.compute import compute_tsky

pytestmark = pytest.mark.data


@pytest.fixture(scope="module")
def hera_day(data_root):
    freqs = np.linspace(100e6, 200e6, 11)
    lsts = np.arange(0.0, 24.0, 0.05)
    return compute_tsky(
        "gsm2008", "hera", "hera", freqs, lsts, nside=64, epoch="2018-01-01", cache=False
    )


def test_hera_tsky_peaks_at_galactic_centre_transit(hera_day):
    """The Galactic centre (RA 17.76 h) transits near zenith at HERA: Tsky peaks there."""
    peak = hera_day.lsts[np.argmax(hera_day.tsky, axis=0)]
    assert np.all(np.abs(peak - 17.8) < 0.5), f"peak LSTs {peak}"


def test_hera_tsky_falls_like_power_law(hera_day):
    mean = hera_day.tsky.mean(axis=0)
    slope = np.polyfit(np.log(hera_day.freqs), np.log(mean), 1)[0]
    assert -2.7 < slope < -2.3, f"spectral slope {slope:.3f}"
    assert np.all(np.diff(mean) < 0)


def test_hera_ee_and_nn_differ_but_little(data_root):
    freqs = np.array([150e6])
    lsts = np.arange(0.0, 24.0, 1.0)
    ee = compute_tsky("gsm2008", "hera", "hera", freqs, lsts, pol="ee", cache=False)
    nn = compute_tsky("gsm2008", "hera", "hera", freqs, lsts, pol="nn", cache=False)
    rel = np.abs(ee.tsky / nn.tsky - 1)
    assert 1e-4 < rel.max() < 0.1


def edges_shape_fit(data_root):
    """Fit scale and spectral index of the 408 MHz power-law sky to the EDGES 2018 spectrum."""
    table = np.genfromtxt(data_root / EDGES_2018_SPECTRUM, delimiter=",", skip_header=1)
    freqs, weight, tsky_pub = table[:, 0] * 1e6, table[:, 1], table[:, 2]
    sel = (weight > 0) & (freqs >= 55e6) & (freqs <= 95e6)
    freqs, tsky_pub = freqs[sel], tsky_pub[sel]
    lsts = np.linspace(0, 24, 73)[:-1]
    result = compute_tsky(
        "powerlaw:gsm2008@408:-2.55",
        "edges-low",
        "edges",
        freqs,
        lsts,
        nside=64,
        epoch="2016-10-01",
        keep_components=True,
        cache=False,
    )
    assert result.meta["component_labels"] == ["powerlaw", "cmb"]
    comp = result.components.mean(axis=0)  # (Nfreq, 2): power-law map and CMB responses
    ground = 300.0 * result.f_below

    def model(beta: float) -> np.ndarray:
        return (freqs / 408e6) ** beta * comp[:, 0] + T_CMB * comp[:, 1] + ground

    def rms_for(beta: float) -> tuple[float, float]:
        m = model(beta)
        scale = np.sum(m / tsky_pub) / np.sum((m / tsky_pub) ** 2)
        return float(np.sqrt(np.mean((scale * m / tsky_pub - 1) ** 2))), float(scale)

    best = minimize_scalar(lambda b: rms_for(b)[0], bounds=(-3.0, -2.0), method="bounded")
    rms, scale = rms_for(best.x)
    return float(best.x), scale, rms, rms_for(-2.55)[0]


def test_edges_lowband_matches_published_spectrum_shape(data_root):
    beta, scale, rms, rms_255 = edges_shape_fit(data_root)
    print(
        f"EDGES 2018 shape fit: beta={beta:.3f} scale={scale:.3f} rms={rms:.2e} "
        f"(rms at beta=-2.55: {rms_255:.2e})"
    )
    assert rms <= 0.03
    assert rms_255 <= 0.03
    assert -2.7 < beta < -2.4
    assert 0.3 < scale < 3
