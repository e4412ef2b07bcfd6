"""Solving in the sky-centred frame (autocal.fit.centring) on short spans.

Over ten minutes the sky changes by ~1 % of its mean: the extended model's column-scaled
normal matrix has a condition number ~1e11 and a plain solve of the float64 sums keeps ~5
digits. The solvers work in the frame where the gain columns are ``(Tsky - c) P_k``; their
solutions are checked against exact rational solves of the same float64 sums.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest

from autocal.fit.centring import centre, minus_product, quadratic_form, sky_mean
from autocal.fit.centring_kernel import quadratic_forms
from autocal.fit.model import FitModel
from autocal.fit.solve import solve_sums, solve_sums_numpy
from autocal.fit.sums import NormalSums, accumulate

SOLVERS = [solve_sums, solve_sums_numpy]


def _ten_minutes(curvature: np.ndarray, order: int = 1, sky: float = 0.01) -> NormalSums:
    """Sums of one antenna-pol over 10 minutes: the sky changes by ``sky`` of its mean.

    ``order`` 0 is the constant model, else the Legendre order.

    Each channel's sky also bends by ``curvature`` (relative): the less it bends, the
    closer the extended model's gain columns come to its offset columns.
    """
    nt, nf = 60, curvature.size
    lsts = 3.2 + np.linspace(0.0, 10.0 / 60.0, nt)
    x = np.linspace(-1.0, 1.0, nt)[:, None]
    freqs = np.linspace(110e6, 190e6, nf)
    tsky = 250.0 * (freqs / 150e6) ** -2.5 * (1.0 + sky * x + curvature * x**2)
    gain = 1e-3 * (1.0 + 0.1 * freqs / 150e6)
    rng = np.random.default_rng(1)
    noise = 1.0 + rng.standard_normal((1, 1, nt, nf)) / np.sqrt(1e5)
    data = (gain * (tsky + 120.0))[None, None] * noise
    model = FitModel() if order == 0 else FitModel.for_lsts(lsts, "legendre", order)
    return accumulate(model, data, tsky, lsts, bandwidth_time=1e5)


def _exact(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The exact solution and inverse of the float64 system ``a x = b`` (rationals)."""
    m = len(b)
    rows = [
        [Fraction(float(a[i, j])) for j in range(m)]
        + [Fraction(float(b[i]))]
        + [Fraction(int(i == j)) for j in range(m)]
        for i in range(m)
    ]
    for c in range(m):
        pivot = rows[c][c]
        rows[c] = [v / pivot for v in rows[c]]
        for r in range(m):
            if r != c:
                f = rows[r][c]
                rows[r] = [rows[r][j] - f * rows[c][j] for j in range(2 * m + 1)]
    x = np.array([float(rows[i][m]) for i in range(m)])
    inv = np.array([[float(v) for v in rows[i][m + 1 :]] for i in range(m)])
    return x, inv


def _scaled_condition(a: np.ndarray) -> np.ndarray:
    d = np.sqrt(np.diagonal(a, axis1=-2, axis2=-1))
    return np.linalg.cond(a / (d[..., :, None] * d[..., None, :]))


def test_minus_product_rounds_only_once() -> None:
    """``x - c y`` with ``x`` close to ``c y`` (the centring's cancellation) is the exact
    difference correctly rounded; an ordinary product would leave ``eps |x|``."""
    rng = np.random.default_rng(0)
    c = rng.uniform(100.0, 400.0, 2000)
    y = rng.uniform(1.0, 1e6, 2000)
    x = c * y * (1.0 + rng.uniform(-1e-4, 1e-4, 2000))
    got = minus_product(x, c, y)
    exact = [Fraction(xi) - Fraction(ci) * Fraction(yi) for xi, ci, yi in zip(x, c, y, strict=True)]
    np.testing.assert_array_equal(got, [float(e) for e in exact])
    assert np.any(x - c * y != got)  # the plain arithmetic does lose digits here


def test_the_compiled_array_forms_give_numpys_bits() -> None:
    """``minus_product_array`` and ``centre_many`` (numba) against the numpy functions, bit
    for bit: random and cancelling values, zeros, infinities and NaN, broadcasting."""
    from autocal.fit.centring_kernel import centre_many, minus_product_array

    rng = np.random.default_rng(7)
    n = 20000
    c = rng.uniform(-400.0, 400.0, n)
    y = rng.standard_normal((5, n)) * 10.0 ** rng.uniform(-6, 6, (5, n))
    x = c * y * (1.0 + rng.uniform(-1e-6, 1e-6, (5, n)))
    x[0, :50], y[1, :50], c[:3] = 0.0, -0.0, [0.0, np.inf, np.nan]
    x[2, 10:20] = np.inf
    with np.errstate(invalid="ignore"):
        want = minus_product(x, -c, y)  # the jackknife's form: (B, N) against (N,)
        got = minus_product_array(x, -c, y)
    np.testing.assert_array_equal(got.view(np.int64), want.view(np.int64))
    for m in (2, 4):
        a = rng.standard_normal((300, 7, m, m))
        a = a @ np.swapaxes(a, -1, -2) * 10.0 ** rng.uniform(-3, 3, (300, 7, 1, 1))
        cc = rng.uniform(100.0, 400.0, (300, 7))
        a[:5, :, 0, 0] = -0.0  # signed zeros: numpy's mirroring adds +0.0
        got, want = centre_many(a, cc), centre(a, cc)
        np.testing.assert_array_equal(got.view(np.int64), want.view(np.int64))


@pytest.mark.parametrize("solver", SOLVERS)
def test_a_ten_minute_extended_fit_is_its_exact_solution(solver) -> None:
    """The constant model's extension (Legendre order 1) over 10 minutes: condition
    numbers 2e10 to 6e11, yet coefficients to 1e-8 and covariances to 1e-7 of the exact
    rational solve of the same sums (a plain solve is off by ~1e-6)."""
    sums = _ten_minutes(np.geomspace(4e-4, 9e-4, 6))
    a, b = sums.ata[0, 0], sums.aty[0, 0]
    cond = _scaled_condition(a)
    assert cond.min() > 1e10 and cond.max() > 1e11
    out = solver(sums, positive_gain=False)
    assert (out["flag_reason"] == 0).all()
    for ch in range(a.shape[0]):
        x, inv = _exact(a[ch], b[ch])
        np.testing.assert_allclose(out["coeffs"][0, 0, ch], x, rtol=1e-8, atol=0)
        np.testing.assert_allclose(out["cov"][0, 0, ch], inv, rtol=1e-7, atol=0)
        chi2 = sums.yty[0, 0, ch] - float(
            sum(Fraction(float(v)) * Fraction(float(w)) for v, w in zip(x, b[ch], strict=True))
        )
        assert out["chi2"][0, 0, ch] == pytest.approx(chi2, rel=1e-6)


@pytest.mark.parametrize("solver", SOLVERS)
@pytest.mark.parametrize("order", [0, 1])
def test_a_sky_that_does_not_change_stays_singular(solver, order: int) -> None:
    """A sky constant in time, or changing by 1e-7 of its mean, leaves the gain columns
    (nearly) the offset columns times ``c``: singular in the centred frame too, where the
    centring's cancellation is counted (the centred matrix itself is well conditioned),
    for the constant model and a Legendre one alike. 1 % of change solves."""
    flags = {}
    for change, bend in ((0.0, 0.0), (1e-7, 1e-8), (1e-2, 1e-3)):
        sums = _ten_minutes(np.full(3, bend), order=order, sky=change)
        flags[change] = solver(sums, positive_gain=False)["flag_reason"][0, 0]
    assert (flags[0.0] == 2).all() and (flags[1e-7] == 2).all()
    assert (flags[1e-2] == 0).all()


def test_the_quadratic_form_of_a_near_null_vector_keeps_its_digits() -> None:
    """``v^T A v`` for ``v`` along the extended model's poorly determined direction (the
    drift term's chi2 drop): to 1e-9 of the exact value of the same float64 numbers (the
    plain sum of its terms is off by up to ~5e-7 here)."""
    sums = _ten_minutes(np.geomspace(4e-4, 9e-4, 6))
    a = sums.ata[0, 0]
    rng = np.random.default_rng(3)
    for ch in range(a.shape[0]):
        vecs = np.linalg.eigh(centre(a[ch], sky_mean(a[ch])))[1]
        vc = vecs[:, 0] + 1e-3 * rng.standard_normal(4)  # near the smallest eigenvector
        v = vc.copy()
        v[2:] -= sky_mean(a[ch]) * vc[:2]  # back to the original frame: large, cancelling
        exact = sum(
            Fraction(float(v[i])) * Fraction(float(a[ch, i, j])) * Fraction(float(v[j]))
            for i in range(4)
            for j in range(4)
        )
        assert quadratic_form(v, a[ch]) == pytest.approx(float(exact), rel=1e-9)
        assert quadratic_forms(v[None], a[ch][None])[0] == pytest.approx(float(exact), rel=1e-9)


def test_the_compiled_quadratic_forms_equal_numpys() -> None:
    """One system at a time (compiled) or all at once (numpy): the same to rounding, for
    random vectors, any leading shape, and systems without a sky mean (c = 0)."""
    sums = _ten_minutes(np.geomspace(4e-4, 9e-4, 6))
    a = sums.ata
    rng = np.random.default_rng(5)
    v = rng.standard_normal(a.shape[:-1])
    a = a.copy()
    a[0, 0, 0, 2, 2] = 0.0  # A[nb, nb] = 0: no change of frame, as numpy's sky_mean gives
    a[0, 0, 1, 2, 2] = np.nan  # a non-finite sky mean: no change of frame either
    a[0, 0, 1, 0, 2] = np.inf
    got = quadratic_forms(v, a)
    assert got.shape == a.shape[:-2]
    want = quadratic_form(v, a)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=0, equal_nan=True)
    assert np.isnan(got[0, 0, 1]) == np.isnan(want[0, 0, 1])
    np.testing.assert_allclose(quadratic_forms(v[0, 0], a[0, 0]), want[0, 0], rtol=1e-12)
    with pytest.raises(ValueError, match="do not match"):
        quadratic_forms(v[:, :, :2], a)
