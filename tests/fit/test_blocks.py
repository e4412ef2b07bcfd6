"""Normal sums per time block and of the extended model (autocal.fit.blocks)."""

from __future__ import annotations

import numpy as np
import pytest

from autocal.fit.blocks import MIN_BLOCKS, accumulate_blocks, base_sums, block_edges, extended_model
from autocal.fit.model import FitModel
from autocal.fit.passes import fit
from autocal.fit.sums import accumulate
from tests.fit.toy import SHORT_NF as NF
from tests.fit.toy import short_obs as make_obs
from tests.fit.toy import short_sky


def test_block_edges_cover_the_integrations_and_degrade_gracefully() -> None:
    edges = block_edges(174)
    assert edges[0] == 0 and edges[-1] == 174 and len(edges) == 11
    assert np.all(np.diff(edges) >= 17)
    assert len(block_edges(9)) == MIN_BLOCKS + 1  # 4 blocks of two or more
    np.testing.assert_array_equal(block_edges(7), [0, 7])  # too few: one block
    # memory: blocks shrink to what fits, and below MIN_BLOCKS there is one
    assert len(block_edges(1000, bytes_per_block=1 << 28)) == 5
    np.testing.assert_array_equal(block_edges(1000, bytes_per_block=1 << 29), [0, 1000])


@pytest.mark.parametrize("order", [0, 1])
def test_block_sums_add_up_to_the_ordinary_fit(order: int) -> None:
    rng = np.random.default_rng(3)
    lsts, tsky = short_sky(60)
    data = (tsky + 150.0)[None, None] * (1 + rng.standard_normal((1, 1, 60, NF)) * 1e-3)
    kind = "constant" if order == 0 else "legendre"
    model = FitModel.for_lsts(lsts, kind, order)
    blocks = accumulate_blocks(
        model, data, tsky, lsts, block_edges(60), weights="radiometer", bandwidth_time=1e6
    )
    whole = accumulate(model, data, tsky, lsts, weights="radiometer", bandwidth_time=1e6)
    base = blocks.fitted_total()
    np.testing.assert_allclose(base.ata, whole.ata, rtol=1e-12)
    np.testing.assert_allclose(base.aty, whole.aty, rtol=1e-12)
    np.testing.assert_allclose(base.yty, whole.yty, rtol=1e-12)
    np.testing.assert_array_equal(base.count, whole.count)
    # and the extended model's sums are those of the model with one more order
    ext = accumulate(
        extended_model(model), data, tsky, lsts, weights="radiometer", bandwidth_time=1e6
    )
    np.testing.assert_allclose(blocks.total().ata, ext.ata, rtol=1e-12)
    np.testing.assert_allclose(base_sums(ext, model).ata, whole.ata, rtol=1e-12)


def test_per_pol_weights_are_sliced_per_block() -> None:
    """Inverse variances given per pol (Npol, Ntime, Nfreq) work with the total as without."""
    rng = np.random.default_rng(4)
    lsts, tsky = short_sky(40)
    data = (0.02 * (tsky + 150.0))[None, None] * (1 + 1e-3 * rng.standard_normal((1, 2, 40, NF)))
    w = np.broadcast_to(1.0 / (1e-3 * data[0]) ** 2, (2, 40, NF)).copy()
    obs = make_obs(data, lsts)
    total = fit(obs, np.stack([tsky, tsky]), weights=w)
    stat = fit(obs, np.stack([tsky, tsky]), weights=w, uncertainty="statistical")
    np.testing.assert_allclose(total.G, stat.G, rtol=1e-9)
    assert total.total is not None and total.total.nblocks == 10
