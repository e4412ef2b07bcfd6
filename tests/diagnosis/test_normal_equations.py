"""The projected normal equations of the extended fit."""

from __future__ import annotations

import numpy as np
import pytest

from autocal.diagnosis.catalogue import catalogue
from autocal.diagnosis.extended_fit import radiometer_weights
from autocal.diagnosis.normal_equations import (
    FitProblem,
    identifiable_fractions,
    projected_normal_equations,
)


@pytest.mark.parametrize("with_prior", [False, True])
def test_projected_normal_equations_equal_the_dense_projected_jacobian(with_prior):
    """The factorised sums give what the projected (samples x K) Jacobian gives."""
    rng = np.random.default_rng(7)
    na, npol, nf, nt = 3, 2, 5, 7
    shape = (na, npol, nf, nt)
    w = rng.uniform(0.5, 2.0, shape) * (rng.uniform(size=shape) > 0.1)
    a1, a2 = rng.normal(size=shape) + 3.0, rng.normal(size=shape) + 1.0
    r = rng.normal(size=shape)
    wp = rng.uniform(0.1, 1.0, shape[:3]) if with_prior else np.zeros(shape[:3])
    t0 = rng.uniform(50.0, 150.0, nf) * with_prior
    rp = rng.normal(size=shape[:3]) * with_prior
    n11 = (w * a1 * a1).sum(-1) + wp * t0**2
    n12 = (w * a1 * a2).sum(-1) - wp * t0
    n22 = (w * a2 * a2).sum(-1) + wp
    det = n11 * n22 - n12**2
    inv = np.stack([n22 / det, -n12 / det, n11 / det])
    inv[:, 1, 0, 2] = 0.0  # a channel without a (G, n) solution is not projected
    # a Tsky-like block (shared by antennas, depends on pol and channel), a gain-like and a
    # noise-like block (time bases only)
    blocks = [
        (slice(0, 2), rng.normal(size=shape), rng.normal(size=(npol, nf, nt, 2))),
        (slice(2, 5), rng.normal(size=shape), rng.normal(size=(1, 1, nt, 3))),
        (slice(5, 6), rng.normal(size=shape), rng.normal(size=(1, 1, nt, 1))),
    ]
    nfree = 6
    jac = np.concatenate(
        [x[..., None] * np.broadcast_to(y, (*shape, y.shape[-1])) for _, x, y in blocks], -1
    )
    c1 = np.einsum("apft,apftk->apfk", w * a1, jac)
    c2 = np.einsum("apft,apftk->apfk", w * a2, jac)
    k1 = inv[0][..., None] * c1 + inv[1][..., None] * c2
    k2 = inv[1][..., None] * c1 + inv[2][..., None] * c2
    jp = jac - a1[..., None] * k1[..., None, :] - a2[..., None] * k2[..., None, :]
    jprior = t0[:, None] * k1 - k2
    h_dense = np.einsum("apft,apftk,apftl->kl", w, jp, jp) + np.einsum(
        "apf,apfk,apfl->kl", wp, jprior, jprior
    )
    grad_dense = np.einsum("apft,apftk,apft->k", w, jp, r) + np.einsum(
        "apf,apfk,apf->k", wp, jprior, rp
    )
    q1 = (w * a1 * r).sum(-1) - wp * t0 * rp
    q2 = (w * a2 * r).sum(-1) + wp * rp
    h, grad, raw = projected_normal_equations(blocks, w, w * a1, w * a2, inv, r, q1, q2, nfree)
    np.testing.assert_allclose(h, h_dense, rtol=1e-10, atol=1e-10 * np.abs(h_dense).max())
    np.testing.assert_allclose(grad, grad_dense, rtol=1e-10, atol=1e-10 * np.abs(grad_dense).max())
    np.testing.assert_allclose(raw, np.einsum("apft,apftk->k", w, jac**2), rtol=1e-12)


def test_fast_normal_equations_equal_the_reference_sums(several) -> None:
    """The template-by-template contractions give :func:`projected_normal_equations`'s sums
    (itself checked against the dense projected Jacobian above)."""
    obs, tpl = several
    effects = {(e.name, e.basis, e.order): e for e in catalogue(ntime=obs.ntime)}
    chosen = (
        effects["gain_jitter", "integration", 1],
        effects["noise_drift", "legendre", 2],
        effects["beam_width", "legendre", 0],
        effects["sky_scale", "legendre", 0],
    )
    w = radiometer_weights(obs, obs.data)
    prob = FitProblem(obs, tpl, chosen, w, 150.0, 0.1, None, 1)
    rng = np.random.default_rng(2)
    p = rng.normal(scale=1e-3, size=prob.nfree)
    st = prob.evaluate(p)
    h, grad, raw = prob.normal_equations(p, st)
    # the reference: the factorised Jacobian J = X Y in the (A, P, F, T) layout
    tt = np.swapaxes(st.tt, 1, 2)[None]
    g, nn = st.g[..., None], st.nn[..., None]
    factors = []
    for eff, sl in prob.blocks:
        if eff.kind == "tsky":
            factors.append((sl, g * st.gfac, np.swapaxes(eff.jacobian(p[sl], tpl), 1, 2)))
        else:
            x = g * tt + nn * st.nfac if eff.kind == "gain" else nn * st.gfac
            factors.append((sl, x, prob.bases[eff.basis, eff.order].T[None, None]))
    wt = np.swapaxes(np.stack([prob.chunk_arrays(slice(a, a + 1))[0][0] for a in range(4)]), 2, 3)
    yt = np.swapaxes(np.where(np.isfinite(obs.data), obs.data, 0.0), 2, 3)
    a1 = np.broadcast_to(np.swapaxes(st.a1, 1, 2)[None], wt.shape)
    a2 = np.broadcast_to(st.a2, wt.shape)
    r = np.where(wt > 0, yt - (st.g[..., None] * a1 + st.nn[..., None] * a2), 0.0)
    q1 = (wt * a1 * r).sum(-1) - prob.wp * prob.t0 * st.rp
    q2 = (wt * a2 * r).sum(-1) + prob.wp * st.rp
    h_ref, grad_ref, raw_ref = projected_normal_equations(
        factors, wt, wt * a1, wt * a2, st.inv, r, q1, q2, prob.nfree
    )
    np.testing.assert_allclose(h, h_ref, rtol=1e-9, atol=1e-9 * np.abs(h_ref).max())
    np.testing.assert_allclose(grad, grad_ref, rtol=1e-7, atol=1e-7 * np.abs(grad_ref).max())
    np.testing.assert_allclose(raw, raw_ref, rtol=1e-12)


def test_a_parameter_without_data_does_not_make_its_block_degenerate() -> None:
    """The jitter factor of an integration flagged whole has no data (unprojected Fisher
    information 0): the block's fraction is that of its other parameters, as without it;
    it was 0 ("degenerate") and a real gain jitter went unnamed."""
    from types import SimpleNamespace

    jitter = SimpleNamespace(name="gain_jitter")
    h = np.diag([0.5, 0.0, 0.25])  # projected: parameter 1 has no data
    raw = np.array([1.0, 0.0, 1.0])
    got = identifiable_fractions([(jitter, slice(0, 3))], h, raw)
    assert got == {"gain_jitter": 0.25}
    none = identifiable_fractions([(jitter, slice(1, 2))], h, raw)
    assert none == {"gain_jitter": 0.0}  # nothing constrained at all


def test_prior_gain_reference_is_the_datas_own_gain() -> None:
    """``<D> / (<Tsky> + Trxr0)`` over the usable samples: within 1e-3 of the true gain for
    a half hour with a 5 % gain drift; NaN for a channel without usable samples and where
    ``Trxr0`` nearly cancels ``<Tsky>``."""
    from types import SimpleNamespace

    from autocal.diagnosis.normal_equations import prior_gain_reference

    rng = np.random.default_rng(3)
    nt, nf = 20, 6
    s = np.linspace(-1.0, 1.0, nt)
    tsky = (300.0 + rng.uniform(0, 50, nf))[None, :] * (1 + 0.01 * s)[:, None]  # (T, F)
    gain, trxr = rng.uniform(0.5, 2.0, nf), rng.uniform(100.0, 200.0, nf)
    data = gain * (1 + 0.05 * s)[:, None] * (tsky + trxr)
    obs = SimpleNamespace(
        nant=1, pols=("ee",), nfreq=nf, shape=(1, 1, nt, nf), data=data[None, None]
    )
    tpl = SimpleNamespace(total=tsky[None])
    weights = np.ones(obs.shape)
    weights[..., 5] = 0.0  # a channel flagged whole
    ref = prior_gain_reference(obs, tpl, weights, trxr)
    np.testing.assert_allclose(ref[0, 0, :5], gain[:5], rtol=1e-3)
    assert np.isnan(ref[0, 0, 5])
    # a receiver temperature cancelling the sky's gives no reference
    cancel = trxr.copy()
    cancel[0] = -tsky[:, 0].mean() * 0.98  # <Tsky> + Trxr0 > 0 but 2 % of <Tsky>
    assert np.isnan(prior_gain_reference(obs, tpl, weights, cancel)[0, 0, 0])


def test_the_prior_weights_default_to_the_datas_own_gain(several) -> None:
    """``fit_extended`` without ``gain_ref`` weights the prior with
    :func:`prior_gain_reference`: the same fit, bit for bit, as when it is given."""
    from autocal.diagnosis.extended_fit import fit_extended
    from autocal.diagnosis.normal_equations import prior_gain_reference

    obs, tpl = several
    w = radiometer_weights(obs, obs.data)
    ref = prior_gain_reference(obs, tpl, w, 150.0)
    assert np.isfinite(ref[obs.flags.all(axis=2) == 0]).all()
    a = fit_extended(obs, tpl, [], weights=w, trxr_prior=150.0, trxr_prior_sigma=5.0)
    b = fit_extended(obs, tpl, [], weights=w, trxr_prior=150.0, trxr_prior_sigma=5.0, gain_ref=ref)
    assert a.chi2 == b.chi2
    np.testing.assert_array_equal(a.G, b.G)
