"""The moment formulation of the normal sums (autocal.fit.moments)."""

from __future__ import annotations

import numpy as np

from autocal.fit.model import FitModel
from autocal.fit.moments import offset_copy, time_functions
from tests.fit.toy import MODELS


def test_time_functions_linearise_the_basis_products() -> None:
    lsts = np.linspace(1.0, 5.0, 50)
    for kind, order in MODELS:
        model = FitModel.for_lsts(lsts, kind, order)
        coef, lin = time_functions(model, lsts)
        basis = model.basis(lsts)
        np.testing.assert_array_equal(coef[0], 1.0)  # the kernel relies on P_0 = 1
        np.testing.assert_allclose(coef[: model.nbasis], basis, atol=1e-15)
        products = basis[:, None, :] * basis[None, :, :]
        np.testing.assert_allclose(np.einsum("jkr,rt->jkt", lin, coef), products, atol=1e-14)


def test_offset_copy_moves_rows_to_other_cache_sets() -> None:
    other = np.zeros((3, 512))
    arr = np.arange(6 * 512, dtype=float).reshape(2, 3, 512)
    for src in (arr, np.broadcast_to(arr[0], (2, 3, 512))):
        out = offset_copy(src, other)
        np.testing.assert_array_equal(out, src)
        assert out.flags.c_contiguous
        assert (out.ctypes.data - other.ctypes.data) % 4096 == 2048
