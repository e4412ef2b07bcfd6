"""Solving the normal equations of every channel (autocal.fit.solve)."""

from __future__ import annotations

import numpy as np
import pytest

from autocal.fit.model import FitError, FitModel
from autocal.fit.solve import MAX_CONDITION, solve_sums, solve_sums_numpy, sym_eigvalsh, sym_inv
from autocal.fit.sums import NormalSums, accumulate
from tests.fit.toy import LSTS, noisy, random_chunk, toy_tsky


def test_inflate_scales_errors_only_upwards() -> None:
    rng = np.random.default_rng(4)
    tsky = toy_tsky()
    clean = (tsky + 150.0)[None, None]
    model = FitModel()
    quiet = accumulate(model, noisy(clean, rng), tsky, LSTS, bandwidth_time=5e3)
    loud = accumulate(model, noisy(clean, rng, 5e3 / 9), tsky, LSTS, bandwidth_time=5e3)
    for sums, expected in ((quiet, 1.0), (loud, 9.0)):
        plain = solve_sums(sums)
        inflated = solve_sums(sums, scale_covariance="inflate")
        ratio = inflated["cov"][..., 0, 0] / plain["cov"][..., 0, 0]
        assert np.all(ratio >= 1.0)
        assert np.median(ratio) == pytest.approx(expected, rel=0.2)


def test_solve_flags_non_finite_normal_matrices() -> None:
    sums = NormalSums.zeros(FitModel(), 1, 1, 2)
    sums.ata[...] = np.array([[4.0, 1.0], [1.0, 2.0]])
    sums.aty[...] = 1.0
    sums.count[...] = 10
    sums.ata[0, 0, 1, 0, 1] = sums.ata[0, 0, 1, 1, 0] = np.inf
    out = solve_sums(sums)
    assert out["flag_reason"][0, 0, 1] == 2 and np.isnan(out["coeffs"][0, 0, 1]).all()
    assert out["flag_reason"][0, 0, 0] == 0
    np.testing.assert_allclose(
        out["coeffs"][0, 0, 0], np.linalg.solve(sums.ata[0, 0, 0], sums.aty[0, 0, 0])
    )


def test_two_parameter_systems_are_solved_in_closed_form_as_lapack_would() -> None:
    """The constant model's 2 x 2 systems skip LAPACK: eigenvalues and inverses agree
    with numpy's to rounding, conditioning included, and solve_sums flags the same
    channels as singular (condition numbers around MAX_CONDITION, on both sides)."""
    rng = np.random.default_rng(7)
    n = 4000
    a = rng.standard_normal((n, 2, 2))
    a = a @ np.swapaxes(a, -1, -2) + np.eye(2) * rng.uniform(0, 1, (n, 1, 1))
    # near-singular: columns almost parallel, condition numbers from 1e6 to 1e14
    c = np.logspace(6, 14, 200)
    eps = 2.0 / c
    a[:200] = np.stack([np.ones(200), 1 - eps, 1 - eps, np.ones(200)], -1).reshape(200, 2, 2)
    ev = np.linalg.eigvalsh(a)
    np.testing.assert_allclose(sym_eigvalsh(a), ev, rtol=1e-12, atol=1e-15 * np.abs(ev).max())
    well = np.abs(ev).max(-1) / np.abs(ev).min(-1) < 1e8
    np.testing.assert_allclose(sym_inv(a)[well], np.linalg.inv(a[well]), rtol=1e-7)
    # the general path is LAPACK's own
    b = rng.standard_normal((5, 3, 3))
    np.testing.assert_array_equal(sym_eigvalsh(b @ b.mT), np.linalg.eigvalsh(b @ b.mT))
    np.testing.assert_array_equal(sym_inv(b), np.linalg.inv(b))

    sums = NormalSums.zeros(FitModel(), 1, 1, n)
    sums.ata[0, 0] = a * 1e6  # column scaling is undone by solve_sums
    sums.aty[0, 0] = np.abs(rng.standard_normal((n, 2))) * 1e3
    sums.yty[...] = 1e9
    sums.count[...] = 100
    out = solve_sums(sums)
    cond = np.linalg.cond(a)
    singular = out["flag_reason"][0, 0] == 2
    clear = np.abs(np.log10(cond / MAX_CONDITION)) > 0.01
    np.testing.assert_array_equal(singular[clear], (cond >= MAX_CONDITION)[clear])
    assert singular.any() and not singular.all()
    solved = out["flag_reason"][0, 0] != 2
    ref = np.linalg.solve(sums.ata[0, 0][solved & well], sums.aty[0, 0][solved & well][..., None])
    got = out["coeffs"][0, 0][solved & well]
    keep = np.isfinite(got[:, 0])  # reason 3 (non-positive gain) is NaN in both
    np.testing.assert_allclose(got[keep], ref[keep, :, 0], rtol=1e-7)


def test_solve_in_blocks_gives_the_whole_solve() -> None:
    """Channel blocks bound solve_sums' memory; every block size gives the same arrays,
    including flagged channels of each reason at block edges."""
    c = random_chunk(31, nant=3, ntime=20, nfreq=7)
    model = FitModel.for_lsts(c["lsts"], "legendre", 2)
    sums = accumulate(model, c["data"], c["tsky"], c["lsts"], flags=c["flags"], weights="identity")
    sums.count[0, 0, 0] = 2  # too few samples
    sums.ata[0, 1, 3] = 0.0  # singular
    sums.aty[1, 0, 6, 0] = -1e9  # non-positive gain
    whole = solve_sums_numpy(sums, scale_covariance=True, block=sums.count.size)
    assert {1, 2, 3} <= set(np.unique(whole["flag_reason"]))
    for block in (1, 5, 16):
        part = solve_sums_numpy(sums, scale_covariance=True, block=block)
        for name, value in whole.items():
            np.testing.assert_array_equal(part[name], value)
            assert part[name].shape == value.shape
    with pytest.raises(FitError, match="block must be at least 1"):
        solve_sums_numpy(sums, block=0)


@pytest.mark.parametrize(("kind", "order"), [("constant", 0), ("legendre", 1), ("legendre", 2)])
@pytest.mark.parametrize("scale", [False, True, "inflate"])
def test_the_compiled_solver_gives_the_numpy_solve(kind: str, order: int, scale) -> None:
    """Every output of the compiled solver equals the numpy reference's (to rounding), and
    every flag reason, on systems with too few samples, singular and ill-conditioned
    matrices, non-finite sums and a non-positive gain."""
    c = random_chunk(32, nant=3, ntime=30, nfreq=9)
    model = FitModel.for_lsts(c["lsts"], kind, order)
    sums = accumulate(model, c["data"], c["tsky"], c["lsts"], flags=c["flags"], weights="identity")
    sums.count[0, 0, 0] = 2  # too few samples
    sums.ata[0, 1, 3] = 0.0  # singular
    sums.ata[0, 1, 4, 0, 0] = np.nan  # not finite
    sums.ata[1, 0, 2, -1, -1] *= 1e-14  # ill-conditioned
    sums.aty[1, 0, 6, 0] = -1e9  # non-positive gain
    sums.count[2, 0, 1] = model.nparam  # dof 0: a NaN covariance scale, not a flag
    got = solve_sums(sums, scale_covariance=scale)
    ref = solve_sums_numpy(sums, scale_covariance=scale)
    assert {1, 2, 3} <= set(np.unique(ref["flag_reason"]))
    np.testing.assert_array_equal(got["flag_reason"], ref["flag_reason"])
    for name in ("coeffs", "cov", "chi2", "dof"):
        np.testing.assert_array_equal(np.isnan(got[name]), np.isnan(ref[name]), err_msg=name)
        scale = np.nanmax(np.abs(ref[name]))  # cancellations: near-zero cross terms
        np.testing.assert_allclose(got[name], ref[name], rtol=1e-8, atol=1e-12 * scale)


@pytest.mark.parametrize("scale_mode", [0, 1, 2])
@pytest.mark.parametrize("positive", [False, True])
def test_the_unrolled_two_parameter_kernel_is_the_general_one_bit_for_bit(
    scale_mode: int, positive: bool
) -> None:
    """The constant model's unrolled kernel: every output equal to the general kernel's,
    signs of zero and NaNs included, on fits of both signs and on too few samples, zero,
    NaN, tiny, exactly degenerate and negative-diagonal systems and infinite sums."""
    from autocal.fit import solve_kernel

    rng = np.random.default_rng(11)
    n = 6000
    sky = rng.uniform(100, 1000, (n, 20))
    ata = np.empty((n, 2, 2))
    ata[:, 0, 0] = (sky * sky).sum(1)
    ata[:, 0, 1] = ata[:, 1, 0] = sky.sum(1)
    ata[:, 1, 1] = 20
    y = (
        rng.choice([0.02, -0.02], n)[:, None]
        * (sky + 150)
        * (1 + 1e-3 * rng.normal(size=sky.shape))
    )
    aty = np.stack([(sky * y).sum(1), y.sum(1)], -1)
    yty = (y * y).sum(1)
    count = rng.integers(0, 30, n)
    ata[:50] = 0.0
    ata[50:100, 0, 0] = np.nan
    ata[100:150] *= 1e-300
    ata[150:200, 0, 1] = ata[150:200, 1, 0] = np.sqrt(ata[150:200, 0, 0] * ata[150:200, 1, 1])
    aty[200:250] = np.inf
    yty[250:300] = np.nan
    ata[300:350, 1, 1] = -5.0

    def run(kernel) -> dict[str, np.ndarray]:
        out = {
            "coeffs": np.empty((n, 2)),
            "cov": np.empty((n, 2, 2)),
            "chi2": np.empty(n),
            "flag_reason": np.zeros(n, np.int8),
        }
        args = (ata, aty, yty, count, 3, scale_mode, 1e12, positive, *out.values())
        kernel(*args, 0, -(-n // solve_kernel._CHUNK))
        return out

    general, unrolled = run(solve_kernel._kernel), run(solve_kernel._kernel2)
    assert {0, 1, 2} <= set(np.unique(general["flag_reason"]))
    for name, value in general.items():
        np.testing.assert_array_equal(unrolled[name], value, err_msg=name)
        np.testing.assert_array_equal(np.signbit(unrolled[name]), np.signbit(value))


def test_the_condition_bound_flags_as_the_eigenvalues_do() -> None:
    """Legendre-1 systems (4 x 4) conditioned from 1e4 to 1e15 around the 1e12 limit: the
    compiled solver, which takes ``||A||_inf ||A^-1||_inf`` for the condition when it is far
    below the limit, flags exactly the channels the numpy reference's eigenvalues flag, and
    solves the others alike."""
    rng = np.random.default_rng(4)
    n = 3000
    q, _ = np.linalg.qr(rng.normal(size=(n, 4, 4)))
    cond = 10.0 ** rng.uniform(4, 15, n)
    lam = np.stack([np.ones(n), cond ** (1 / 3), cond ** (2 / 3), cond], -1) * 1e3
    ata = np.einsum("nij,nj,nkj->nik", q, lam, q)
    ata = (ata + np.swapaxes(ata, -1, -2)) / 2
    truth = np.stack([rng.uniform(0.5, 2.0, n), rng.normal(size=n), 150 + rng.normal(size=n)], -1)
    truth = np.concatenate([truth, rng.normal(size=(n, 1))], -1)
    aty = np.einsum("nij,nj->ni", ata, truth)
    yty = np.einsum("ni,ni->n", aty, truth) + 10.0
    sums = NormalSums(
        model=FitModel.for_lsts(LSTS, "legendre", 1),
        nflagged=np.zeros((1, 1, n), np.int64),
        ata=ata.reshape(1, 1, n, 4, 4),
        aty=aty.reshape(1, 1, n, 4),
        yty=yty.reshape(1, 1, n),
        count=np.full((1, 1, n), 100),
    )
    got = solve_sums(sums, scale_covariance=False, positive_gain=False)
    ref = solve_sums_numpy(sums, scale_covariance=False, positive_gain=False)
    reasons = set(np.unique(ref["flag_reason"]))
    assert {0, 2} <= reasons  # both sides of the limit
    np.testing.assert_array_equal(got["flag_reason"], ref["flag_reason"])
    # where the solution is well determined (cond x eps < 1e-10), both give it
    solved = ((ref["flag_reason"] == 0) & (cond < 1e6)).reshape(1, 1, n)
    assert solved.sum() > 100
    np.testing.assert_allclose(got["coeffs"][solved], ref["coeffs"][solved], rtol=1e-6, atol=1e-8)


def test_the_bounded_condition_path_is_the_eigenvalue_path_bit_for_bit() -> None:
    """The general kernel with and without the condition bound: every output identical
    (NaNs and signs of zero included) on 4 x 4 systems conditioned 1e4-1e15, zero, NaN and
    exactly singular ones, with and without the positive-gain check."""
    from autocal.fit import solve_kernel

    rng = np.random.default_rng(9)
    n = 5000
    q, _ = np.linalg.qr(rng.normal(size=(n, 4, 4)))
    cond = 10.0 ** rng.uniform(4, 15, n)
    lam = np.stack([np.ones(n), cond ** (1 / 3), cond ** (2 / 3), cond], -1)
    ata = np.einsum("nij,nj,nkj->nik", q, lam, q)
    ata = (ata + np.swapaxes(ata, -1, -2)) / 2
    aty = rng.normal(size=(n, 4)) * 10
    yty = np.full(n, 1e4)
    count = np.full(n, 40)
    ata[:40] = 0.0
    ata[40:80, 2, 2] = np.nan
    ata[80:120, :, 3] = ata[80:120, :, 2]  # two equal columns: exactly singular
    ata[80:120, 3, :] = ata[80:120, 2, :]
    for positive in (False, True):
        outs = []
        for bounded in (False, True):
            out = {
                "coeffs": np.empty((n, 4)),
                "cov": np.empty((n, 4, 4)),
                "chi2": np.empty(n),
                "flag_reason": np.zeros(n, np.int8),
            }
            args = (ata, aty, yty, count, 5, 2, 1e12, positive, *out.values())
            solve_kernel._kernel(*args, 0, -(-n // solve_kernel._CHUNK), bounded)
            outs.append(out)
        assert {0, 2} <= set(np.unique(outs[0]["flag_reason"]))
        for name, value in outs[0].items():
            np.testing.assert_array_equal(outs[1][name], value, err_msg=name)
            np.testing.assert_array_equal(np.signbit(outs[1][name]), np.signbit(value))
