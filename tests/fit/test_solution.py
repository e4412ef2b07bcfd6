"""The fitted solution's derived quantities (autocal.fit.solution)."""

from __future__ import annotations

import numpy as np

from autocal.fit.passes import fit
from tests.fit.toy import make_obs, noisy, toy_tsky


def test_trxr_uncertainty_matches_jacobian_propagation() -> None:
    """sigma_Trxr equals sqrt(J C J^T) with J = d(n/G)/d(G, n) = (-n/G^2, 1/G)."""
    rng = np.random.default_rng(9)
    tsky = toy_tsky()
    sol = fit(make_obs(noisy((0.8 * (tsky + 150.0))[None, None], rng)), tsky)
    g, n = sol.coeffs[..., 0], sol.coeffs[..., 1]
    jac = np.stack([-n / g**2, 1 / g], axis=-1)
    var = np.einsum("...i,...ij,...j->...", jac, sol.cov, jac)
    np.testing.assert_allclose(sol.sigma_Trxr_stat, np.sqrt(var), rtol=1e-10)
    # the total error propagates the total (G, n) covariance the same way
    assert sol.total is not None
    var_total = np.einsum("...i,...ij,...j->...", jac, sol.total.cov, jac)
    np.testing.assert_allclose(sol.sigma_Trxr, np.sqrt(var_total), rtol=1e-10)
    # slope and intercept anticorrelate (Tsky > 0), so the cross term raises the error:
    # dropping it (or adding it with the wrong sign) would understate sigma_Trxr
    assert np.all(sol.cov[..., 0, 1] < 0)
    naive = sol.Trxr * np.sqrt(sol.sigma_G**2 / g**2 + sol.sigma_n**2 / n**2)
    assert np.all(sol.sigma_Trxr > naive)


def test_derived_arrays_are_computed_once_and_read_only() -> None:
    from dataclasses import replace

    rng = np.random.default_rng(3)
    tsky = toy_tsky()
    sol = fit(make_obs(noisy((0.8 * (tsky + 150.0))[None, None], rng)), tsky)
    assert sol.G is sol.G and sol.sigma_G is sol.sigma_G
    for arr in (sol.G, sol.n, sol.sigma_G, sol.sigma_G_stat, sol.sigma_Trxr):
        assert not arr.flags.writeable
    # a copy without the total recomputes: its sigma_G is the statistical one
    stat = replace(sol, total=None)
    np.testing.assert_array_equal(stat.sigma_G, sol.sigma_G_stat)
    assert not np.array_equal(stat.sigma_G, sol.sigma_G)
    vg = np.zeros(sol.model.nparam)
    vg[: sol.model.nbasis] = sol.time_average
    np.testing.assert_array_equal(sol.G, sol.coeffs @ vg)
