"""A file's partial sums with time blocks: blocks reduced as soon as they are read."""

from __future__ import annotations

import numpy as np
import pytest

from autocal.fit.model import FitModel
from autocal.io.uvh5 import write_uvh5
from autocal.io.uvh5_meta import scan_uvh5
from autocal.pipeline import partials
from autocal.pipeline.partials import FileTask, PartialSpec, compute_partial
from tests.io.test_uvh5 import synthetic_observation

FIELDS = ("ata", "aty", "yty", "count", "nflagged")


def _partial(path, block_size: int):
    file = scan_uvh5([path])[0]
    ntime = file.lsts.size
    tsky = np.full((len(file.pols), ntime, file.freqs.size), 300.0)
    tsky += np.linspace(0.0, 40.0, ntime)[None, :, None]
    sel = {"antennas": None, "pols": None, "freq_range": None, "lst_range": None}
    spec = PartialSpec(
        FitModel.for_lsts(file.lsts),
        "identity",
        sel,
        2,
        1,
        block_size=block_size,
        edges=(0, 5, 9, 14, ntime),
    )
    return compute_partial(spec, FileTask(0, file, 0, file.lsts, tsky))


@pytest.mark.parametrize("block_size", [1, 3, 20])
def test_early_reduction_gives_the_values_of_reducing_at_the_end(
    tmp_path, monkeypatch, block_size
) -> None:
    """Read blocks of 1, 3 or all 20 integrations over four time blocks: the fitted sums
    of every block and the extended total are those of reducing every block when the file
    ends (as before), bit for bit."""
    path = write_uvh5(synthetic_observation(ntime=20), tmp_path / "a.uvh5")
    early = _partial(path, block_size)
    retire = partials._FileSums._retire

    def at_the_end(self, before=None):
        if before is None:
            retire(self)

    monkeypatch.setattr(partials._FileSums, "_retire", at_the_end)
    late = _partial(path, block_size)
    assert sorted(early.blocks) == sorted(late.blocks) == [0, 1, 2, 3]
    for b in early.blocks:
        for name in FIELDS:
            np.testing.assert_array_equal(
                getattr(early.blocks[b], name), getattr(late.blocks[b], name)
            )
    for name in FIELDS:
        got, want = getattr(early.extended, name), getattr(late.extended, name)
        np.testing.assert_array_equal(got.view(np.int64), want.view(np.int64))
