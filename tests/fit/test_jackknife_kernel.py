"""The compiled expected jackknife (autocal.fit.jackknife_kernel) against its numpy reference.

Random positive-definite block normal matrices, 2 x 2 (the constant model) and 4 x 4
(Legendre order 1), with and without a prior, and channels whose refits are singular.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from autocal.fit.total_uncertainty import expected_jackknife, expected_jackknife_numpy


def _blocks(m: int, nchan: int, nblk: int, seed: int) -> tuple[SimpleNamespace, SimpleNamespace]:
    rng = np.random.default_rng(seed)
    parts = []
    for _ in range(nblk):
        x = rng.standard_normal((nchan, 3 * m, m))
        parts.append(SimpleNamespace(ata=np.einsum("nki,nkj->nij", x, x)))
    parts[0].ata[:3] = 0.0  # channels 0-2: all data in the other blocks
    for part in parts[1:]:
        part.ata[3] = 0.0  # channel 3: all its data in block 0, so its refit is singular
    total = sum(part.ata for part in parts)
    return SimpleNamespace(blocks=parts, nblocks=nblk), SimpleNamespace(ata=total)


@pytest.mark.parametrize("m", [2, 4])
@pytest.mark.parametrize("with_prior", [False, True])
def test_the_kernel_gives_the_numpy_expectation(m: int, with_prior: bool) -> None:
    blocks, fitted = _blocks(m, 500, 5, seed=m)
    vg = np.zeros(m)
    vn = np.zeros(m)
    vg[0], vn[m // 2] = 1.0, 1.0
    prior = None
    if with_prior:

        def prior(sums, vg_, vn_):  # a noiseless prior on n: adds rows to A
            return SimpleNamespace(ata=sums.ata + 0.5 * np.outer(vn_, vn_))

    got = expected_jackknife(blocks, fitted, prior, vg, vn)
    ref = expected_jackknife_numpy(blocks, fitted, prior, vg, vn)
    assert got.shape == (500, 2, 2)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(ref))
    assert np.isnan(got[3]).all() and np.isfinite(got[:3]).all()  # singular refit, or not
    np.testing.assert_allclose(got, ref, rtol=1e-9, atol=0)
    np.testing.assert_allclose(got, np.swapaxes(got, -1, -2), rtol=1e-9)  # a covariance
