"""HDF5 chunk reading: repeated stored chunks decoded once give exactly a plain read."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from autocal.io.uvh5_chunks import ReadStats


@pytest.mark.parametrize("legacy", [False, True])
def test_repeated_chunks_give_exactly_a_plain_read(tmp_path, legacy):
    from autocal.io.uvh5_chunks import RepeatedChunks

    shape, chunks = (50, 37, 2), (7, 8, 1)  # chunks straddle every edge
    if legacy:  # the old (Nblts, 1, Nfreq, Npol) layout
        shape, chunks = (50, 1, 37, 2), (7, 1, 8, 1)
    rng = np.random.default_rng(3)
    uniform = np.ones(shape, np.float32)
    with h5py.File(tmp_path / "c.h5", "w") as h5:
        h5.create_dataset("same", data=uniform, chunks=chunks, compression="gzip")
        mixed = uniform.copy()
        mixed[10:12, ..., 3:5, :] = 7  # two chunks differ
        h5.create_dataset("mixed", data=mixed, chunks=chunks, compression="lzf", shuffle=True)
        h5.create_dataset("noisy", data=rng.random(shape), chunks=chunks, compression="gzip")
        gaps = h5.create_dataset("gaps", shape=shape, dtype="f4", chunks=chunks, compression="gzip")
        gaps[:7] = 1.0  # later chunks never written: fill value
    with h5py.File(tmp_path / "c.h5", "r") as h5:
        for name in ("same", "mixed", "noisy", "gaps"):
            dset = h5[name]
            rep = RepeatedChunks(dset)
            stats = ReadStats()
            one_value = []
            for lo, hi, chans, pols in [
                (0, 50, slice(0, 37), slice(0, 2)),
                (3, 19, slice(5, 30), slice(1, 2)),
                (44, 50, slice(36, 37), slice(0, 1)),
            ]:
                out = np.full((hi - lo, chans.stop - chans.start, pols.stop - pols.start), -1.0)
                out = out.astype(dset.dtype)
                index = (slice(lo, hi), 0, chans, pols) if legacy else (slice(lo, hi), chans, pols)
                got = rep.fill(lambda out=out: out, lo, hi, chans, pols, stats)
                if got is not None:
                    np.testing.assert_array_equal(got, dset[index])
                    assert got.shape == out.shape and got.dtype == dset.dtype
                    one_value.append(not any(got.strides))  # else: it is ``out``
                    assert one_value[-1] or got is out
                else:
                    assert name in ("noisy", "gaps") and not rep.active
            # all ones: broadcast; 'mixed' has its changed chunk in the first two slabs
            want = {"same": [True] * 3, "mixed": [False, False, True]}
            if name in want:
                assert one_value == want[name]
            if name in ("same", "mixed"):
                assert rep.active and rep.reused > rep.seen // 2 and stats.bytes_reused > 0
                # full chunks, the short last row and channel chunks and their corner;
                # 'mixed' adds the changed chunk (stored alike in both pols)
                assert len(rep.decoded) == (4 if name == "same" else 5)
    # a data set whose chunks never repeat is read normally after the trial
    with h5py.File(tmp_path / "c.h5", "r") as h5:
        rep = RepeatedChunks(h5["noisy"])
        lo_hi = [(i, i + 7) for i in range(0, 49, 7)] * 3
        for lo, hi in lo_hi:
            make = lambda: np.empty((hi - lo, 37, 2))  # noqa: E731, B023 - used at once
            if rep.fill(make, lo, hi, slice(0, 37), slice(0, 2), ReadStats()) is None:
                break
        assert not rep.active and not rep.decoded and rep.seen >= RepeatedChunks.TRIAL_CHUNKS


def test_one_value_is_told_by_bits() -> None:
    """A chunk's one value: same bits everywhere (a ``-0.0`` among zeros or another NaN
    payload is not the same value), for 1-, 4-, 8- and 16-byte types."""
    from autocal.io.uvh5_chunks import one_value

    assert one_value(np.zeros((3, 4), bool)) == np.array(False)
    assert one_value(np.full((2, 5), 3.5, np.float32)).dtype == np.float32
    signed = np.zeros(6)
    signed[4] = -0.0
    assert one_value(signed) is None
    payloads = np.full(4, np.nan).view(np.uint64)
    payloads[1] += 1
    assert one_value(payloads.view(np.float64)) is None
    same = np.full((2, 3), 1 + 2j, np.complex128)
    assert one_value(same) == 1 + 2j
    same[1, 2] = 1 + 3j
    assert one_value(same) is None
    assert one_value(np.empty((0, 3))) is None
