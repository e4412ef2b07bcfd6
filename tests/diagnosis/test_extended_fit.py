"""The extended fit: warm starts, antennas streamed in chunks."""

from __future__ import annotations

import numpy as np
import pytest

from autocal.diagnosis.catalogue import catalogue
from autocal.diagnosis.chunks import antenna_chunks
from autocal.diagnosis.errors import DiagnoseError
from autocal.diagnosis.extended_fit import fit_extended, radiometer_weights
from tests.diagnosis.simulated import PRIOR_SIGMA, hidden, s_of


def test_fits_from_another_start_compare(setup):
    """A fit started elsewhere reaches the same minimum with the same chi2: its receiver
    prior's weights come from the data's own gain, not from the start."""
    obs, tpl = setup
    g = 1 + 0.02 * s_of(obs.lsts)
    data = hidden(obs, tpl.total, gain=g)
    drift = next(e for e in catalogue() if e.name == "gain_drift" and e.order == 1)
    w = radiometer_weights(data, data.data)
    kw = {"weights": w, "trxr_prior": 150.0, "trxr_prior_sigma": PRIOR_SIGMA}
    zero = fit_extended(data, tpl, [drift], **kw)
    far = fit_extended(data, tpl, [drift], start={"gain_drift": np.array([-0.05])}, **kw)
    assert far.chi2 == pytest.approx(zero.chi2, rel=1e-9)
    np.testing.assert_allclose(far.params["gain_drift"], zero.params["gain_drift"], rtol=1e-5)
    # a start of the wrong length is ignored
    odd = fit_extended(data, tpl, [drift], start={"gain_drift": np.zeros(3)}, **kw)
    assert odd.chi2 == pytest.approx(zero.chi2, rel=1e-12)
    # the gain factor over time is the fitted drift, the noise factor is one
    np.testing.assert_allclose(zero.gain_factor, 1 + zero.params["gain_drift"][0] * s_of(obs.lsts))
    np.testing.assert_array_equal(zero.noise_factor, np.ones(obs.ntime))


@pytest.mark.parametrize("prior", [None, 150.0])
def test_chunked_fit_equals_the_unchunked_fit(several, prior) -> None:
    """One antenna per chunk gives the fit of all antennas at once."""
    obs, tpl = several
    effects = {(e.name, e.basis, e.order): e for e in catalogue(ntime=obs.ntime)}
    chosen = [
        effects["gain_drift", "legendre", 1],
        effects["noise_drift", "legendre", 2],
        effects["beam_width", "legendre", 0],
    ]
    if prior is not None:  # identifiable only with a receiver prior
        chosen.append(effects["sky_spectral_index", "legendre", 0])
    w = radiometer_weights(obs, obs.data)
    kw = {"weights": w, "trxr_prior": prior, "trxr_prior_sigma": 0.1}
    whole = fit_extended(obs, tpl, chosen, chunk_antennas=obs.nant, **kw)
    single = fit_extended(obs, tpl, chosen, chunk_antennas=1, **kw)
    assert len(antenna_chunks(obs.shape, 1)) == obs.nant
    assert single.chi2 == pytest.approx(whole.chi2, rel=1e-12)
    assert single.ndata == whole.ndata and single.nparam == whole.nparam
    np.testing.assert_allclose(single.G, whole.G, rtol=1e-11)
    np.testing.assert_allclose(single.n, whole.n, rtol=1e-11)
    np.testing.assert_allclose(single.sigma_G, whole.sigma_G, rtol=1e-11)
    for name, value in whole.params.items():
        np.testing.assert_allclose(
            single.params[name], value, rtol=0, atol=1e-9 * whole.sigmas[name].max()
        )
        np.testing.assert_allclose(single.sigmas[name], whole.sigmas[name], rtol=1e-9)
    assert single.identifiable == pytest.approx(whole.identifiable, rel=1e-9)
    assert all(np.isfinite(s).all() for s in whole.sigmas.values()), whole.identifiable
    np.testing.assert_allclose(single.residuals, whole.residuals, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(single.model, whole.model, rtol=1e-12)
    assert np.isnan(whole.residuals[2, 0, 6, 7]) and np.all(np.isnan(whole.residuals[1, 0, :, 3]))
    # the residuals are computed from the fit's inputs, on demand, until it is detached
    assert whole.residuals_of(3, 0).shape == (obs.ntime, obs.nfreq)
    with pytest.raises(DiagnoseError, match="detached"):
        _ = whole.detached().residuals
