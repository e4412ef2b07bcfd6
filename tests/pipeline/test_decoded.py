"""Decoded blocks kept between a calibration's reads (:mod:`autocal.pipeline.decoded`).

The replayed blocks must be the blocks the reader yields, bit for bit: checked block by
block against :func:`autocal.io.uvh5_blocks.iter_uvh5_blocks` on real HERA files (data
autocal did not write), and end to end on the solution and flags of ``autocal calibrate``
with the cache on and off.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import h5py
import numpy as np
import pytest

from autocal.io.uvh5_blocks import iter_uvh5_blocks
from autocal.io.uvh5_chunks import ReadStats
from autocal.pipeline import decoded
from autocal.pipeline.calibrate import read_summary, run_calibration
from autocal.pipeline.config import CalibrationConfig, PipelineError

HERA_116 = [f"hera/autos/zen.2458116.{s}.HH.uvh5" for s in ("30448", "31193", "31939")]


def _equal(a: object, b: object) -> bool:
    if isinstance(a, np.ndarray):
        return (
            isinstance(b, np.ndarray)
            and a.dtype == b.dtype
            and np.array_equal(a, b, equal_nan=a.dtype.kind == "f")
        )
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_equal(a[k], b[k]) for k in a)
    return bool(a == b)


def _steady(doc: object) -> object:
    """``doc`` without what differs between two runs of the same data (read counters, time)."""
    if isinstance(doc, dict):
        return {k: _steady(v) for k, v in doc.items() if k not in ("io", "created_unix")}
    return doc


@pytest.mark.data
@pytest.mark.parametrize("file", [HERA_116[0], "hera/autos/zen.2458043.40141.xx.HH.XRAA.uvh5"])
def test_replayed_blocks_are_the_blocks_read(data_root: Path, file: str) -> None:
    """Every field of every block replayed equals the reader's (reused buffers and all);
    a file that flags nothing (JD 2458116) and one that flags 8 % of its autos."""
    path = data_root / file

    stats = ReadStats()

    def read() -> object:
        return iter_uvh5_blocks(path, block_size=5, reuse_buffers=True, prefetch=True, stats=stats)

    fresh = [
        {
            f.name: np.copy(v) if isinstance(v := getattr(b, f.name), np.ndarray) else v
            for f in dataclasses.fields(b)
        }
        for b in iter_uvh5_blocks(path, block_size=5)
    ]
    cache = decoded.DecodedBlocks(budget=2**30)
    first = sum(1 for _ in cache.blocks(("k",), read, stats))  # read, kept
    assert stats.blocks == len(fresh) and stats.blocks_from_memory == 0
    assert cache.used > 0 and len(cache.reads[("k",)]) == len(fresh)
    again = 0
    data_arrays: list[np.ndarray] = []  # kept: ids of arrays alive are distinct
    for want, got in zip(fresh, cache.blocks(("k",), read, stats), strict=True):
        for name, value in want.items():  # each block as it is yielded: its buffer is reused
            assert _equal(value, getattr(got, name)), name
        data_arrays.append(got.data)
        again += 1
    assert stats.blocks == len(fresh) and stats.blocks_from_memory == len(fresh)
    assert first == again == len(fresh)
    # one float64 buffer for every full-size block, one more for a shorter last block
    assert len({id(a) for a in data_arrays}) <= 2 < len(fresh)
    # the flagging's scans replay power and flags only: read-only views of the kept arrays,
    # widened to the same values
    scans = list(cache.blocks(("k",), read, stats, scan=True))
    assert [type(c) for c in scans] == [decoded.ScanChunk] * len(fresh)
    for want, got, block in zip(fresh, scans, cache.reads[("k",)], strict=True):
        assert got.data.base is block.data  # no copy
        if want["flags"].any():
            assert got.flags.base is block.flags
        else:  # a block that flags nothing keeps no flags
            assert block.flags is False and not got.flags.any()
        assert not got.data.flags.writeable and not got.flags.flags.writeable
        assert np.array_equal(got.data.astype(np.float64), want["data"], equal_nan=True)
        assert np.array_equal(got.flags, want["flags"]) and got.ntime == want["data"].shape[2]
    # float32 power (the stored complex64's real part), one number for uniform nsamples
    kept = cache.reads[("k",)][0]
    assert kept.data.dtype == np.float32 and isinstance(kept.nsamples, float)
    flagged = [isinstance(b.flags, np.ndarray) for b in cache.reads[("k",)]]
    assert flagged == [bool(b["flags"].any()) for b in fresh]
    assert any(flagged) == ("XRAA" in file)
    assert cache.used < 0.4 * sum(
        b["data"].nbytes + b["nsamples"].nbytes + b["flags"].nbytes for b in fresh
    )


@pytest.mark.data
def test_over_budget_or_stopped_reads_are_not_kept(data_root: Path) -> None:
    """A read larger than the budget, or left before its end, is not kept."""
    path = data_root / HERA_116[0]

    def read() -> object:
        return iter_uvh5_blocks(path, block_size=5)

    small = decoded.DecodedBlocks(budget=1000)
    assert len(list(small.blocks(("k",), read, ReadStats()))) > 1
    assert small.reads == {} and small.used == 0
    cache = decoded.DecodedBlocks(budget=2**30)
    blocks = cache.blocks(("k",), read, ReadStats())
    next(blocks)
    blocks.close()
    assert cache.reads == {}


def test_compact_forms_hold_the_values_exactly() -> None:
    """One number only for identical bits; float32 when exact; else float64."""
    ones = np.ones((2, 3))
    assert decoded._compact(ones) == 1.0
    signed = np.zeros(4)
    signed[1] = -0.0
    kept = decoded._compact(signed)
    assert isinstance(kept, np.ndarray) and np.signbit(kept[1]) and not np.signbit(kept[0])
    single = np.array([0.1, 0.2], np.float32).astype(np.float64)
    assert decoded._compact(single).dtype == np.float32
    double = np.array([0.1, 0.2])
    assert decoded._compact(double).dtype == np.float64
    for value in (ones, signed, single, double):
        back = decoded._full(decoded._compact(value), value.shape)
        assert back.dtype == np.float64
        np.testing.assert_array_equal(back.view(np.uint64), value.view(np.uint64))
    # a block of one power value is scanned as that value broadcast
    flags = np.zeros((1, 1, 2, 3), bool)
    block = decoded._Block(7.5, flags, 1.0, flags.shape, {})
    chunk = block.scan_chunk()
    assert chunk.data.shape == flags.shape and (chunk.data == 7.5).all() and chunk.ntime == 2


def _compact_numpy(values: np.ndarray) -> np.ndarray | float:
    """The numpy form of the compact test (independent of the compiled pass)."""
    bits = values.view(np.uint64)
    if np.all(bits == bits.flat[0]) and np.isfinite(values.flat[0]):
        return float(values.flat[0])
    with np.errstate(over="ignore"):
        small = values.astype(np.float32)
    return small if np.array_equal(small, values, equal_nan=True) else values.copy()


@pytest.mark.parametrize("threads", ["1", "2"])
def test_the_compiled_compact_pass_equals_numpys(monkeypatch, threads) -> None:
    """Across ranges of the threaded pass: a value that differs, or is not a float32, in
    the last range; NaNs, infinities, signed zeros, values beyond float32's range or
    precision."""
    monkeypatch.setenv("AUTOCAL_FIT_THREADS", threads)
    n = (1 << 20) * 2 + 5
    rng = np.random.default_rng(1)
    cases = {
        "constant": np.full(n, 3.0),
        "constant NaN": np.full(n, np.nan),
        "constant inf": np.full(n, np.inf),
        "float32 values": rng.normal(size=n).astype(np.float32).astype(np.float64),
    }
    last = n - 3
    for name, value in [("one other", 3.5), ("-0.0", -0.0), ("NaN", np.nan), ("inf", np.inf)]:
        x = np.full(n, 0.0 if name == "-0.0" else 3.0)
        x[last] = value
        cases[f"constant but {name}"] = x
    for name, value in [("double", 0.1), ("huge", 1e300), ("tiny", 1e-320)]:
        x = cases["float32 values"].copy()
        x[last] = value
        cases[f"float32 but {name}"] = x
    with_nan = cases["float32 values"].copy()
    with_nan[::7] = np.nan
    cases["float32 with NaNs"] = with_nan
    payload = np.full(n, np.nan)
    payload.view(np.uint64)[last] |= 0x55  # a NaN with another payload
    cases["NaNs of two payloads"] = payload
    cases["smaller than a range"] = cases["float32 values"][:1000].copy()
    cases["-0.0 first"] = np.where(np.arange(n) == 0, -0.0, 0.0)
    for name, values in cases.items():
        got, want = decoded._compact(values), _compact_numpy(values)
        if isinstance(want, float):
            assert isinstance(got, float) and got == want, name
        else:  # bit for bit (NaN payloads, signed zeros)
            assert isinstance(got, np.ndarray) and got.dtype == want.dtype, name
            uint = np.uint32 if want.dtype == np.float32 else np.uint64
            np.testing.assert_array_equal(got.view(uint), want.view(uint), err_msg=name)


def test_budget_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    """The budget is read in GB; 0 turns the cache off; nonsense is refused with advice."""
    monkeypatch.delenv(decoded.BUDGET_ENV, raising=False)
    assert decoded.budget_bytes() == int(decoded.DEFAULT_BUDGET_GB * 2**30)
    monkeypatch.setenv(decoded.BUDGET_ENV, "0")
    with decoded.keep_decoded(1) as cache:
        assert cache is None
    monkeypatch.setenv(decoded.BUDGET_ENV, "0.5")
    with decoded.keep_decoded(2**30) as cache:
        assert cache is None  # the observation does not fit
    with decoded.keep_decoded(2**20) as cache:
        assert cache is not None and cache.budget == 2**29
    for bad in ("lots", "-1", "nan", "inf", "1e400"):
        monkeypatch.setenv(decoded.BUDGET_ENV, bad)
        with pytest.raises(PipelineError, match="size in GB"):
            decoded.budget_bytes()


@pytest.mark.data
@pytest.mark.slow
def test_calibration_is_the_same_with_and_without_the_cache(
    data_root: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Three real HERA files, flagged and fitted: the same solution, flags and provenance
    whether the later reads replay the first one's blocks or decode the files again."""
    config = CalibrationConfig(inputs=[str(data_root / f) for f in HERA_116], products=["hdf5"])
    runs = {}
    for name, budget in (("off", "0"), ("on", "2")):
        monkeypatch.setenv(decoded.BUDGET_ENV, budget)
        out = tmp_path / name
        run_calibration(config, out=out)
        runs[name] = (out, read_summary(out))
    (off, s_off), (on, s_on) = runs["off"], runs["on"]
    io_off, io_on = s_off["execution"]["io"], s_on["execution"]["io"]
    assert io_off["blocks_from_memory"] == 0 and io_off["files"] == 3
    assert io_on["files"] == 0 and io_on["blocks_from_memory"] == s_on["execution"]["passes"] * (
        io_off["blocks"] // s_off["execution"]["passes"]
    )
    assert s_on["rfi_flagging"]["io"]["bytes_read"] * 2 == pytest.approx(
        s_off["rfi_flagging"]["io"]["bytes_read"], rel=0.01
    )
    for key in ("rfi_flagging", "quality", "provenance"):
        assert _steady(s_off[key]) == _steady(s_on[key]), key
    with h5py.File(off / "solution.h5") as ha, h5py.File(on / "solution.h5") as hb:
        names: list[str] = []
        ha.visit(names.append)
        compared = 0
        for name in names:
            if isinstance(ha[name], h5py.Dataset):
                x, y = ha[name][()], hb[name][()]
                assert _equal(np.asarray(x), np.asarray(y)), name
                compared += 1
        assert compared > 5


@pytest.mark.data
def test_the_last_read_releases_the_blocks_as_it_replays_them(data_root: Path) -> None:
    """After final_read the kept read is replayed once (the same blocks), its memory given
    back block by block; a read not kept is decoded and not kept."""
    path = data_root / HERA_116[0]
    stats = ReadStats()

    def read() -> object:
        return iter_uvh5_blocks(path, block_size=5, stats=stats)

    cache = decoded.DecodedBlocks(budget=2**30)
    first = [b.data.copy() for b in cache.blocks(("k",), read, stats)]
    full = cache.used
    cache.final_read()
    used = []
    for want, block in zip(first, cache.blocks(("k",), read, stats), strict=True):
        np.testing.assert_array_equal(block.data, want)
        used.append(cache.used)
    assert used == sorted(used, reverse=True) and used[0] < full and cache.used == 0
    assert cache.reads == {} and stats.blocks_from_memory == len(first)
    decoded_before = stats.blocks
    assert len(list(cache.blocks(("k",), read, stats))) == len(first)  # decoded again
    assert stats.blocks == decoded_before + len(first) and cache.reads == {}


def test_blocks_that_flag_nothing_beside_blocks_that_flag(tmp_path: Path) -> None:
    """One read mixing a flagged block and unflagged ones: only the flagged block keeps an
    array; the others replay no flags, the scans one zero array shared by same-shape blocks."""
    from autocal.io.uvh5 import write_uvh5
    from tests.io.test_uvh5 import synthetic_observation

    obs = synthetic_observation(ntime=6)
    flags = np.zeros(obs.shape, bool)
    flags[1, 0, 0, 3] = True  # one sample of the first two-integration block
    path = tmp_path / "mixed.uvh5"
    write_uvh5(dataclasses.replace(obs, flags=flags), path)
    stats = ReadStats()

    def read() -> object:
        return iter_uvh5_blocks(path, block_size=2, stats=stats)

    want = [b.flags.copy() for b in iter_uvh5_blocks(path, block_size=2)]
    cache = decoded.DecodedBlocks(budget=2**30)
    assert sum(1 for _ in cache.blocks(("k",), read, stats)) == 3
    kept = cache.reads[("k",)]
    assert [isinstance(b.flags, np.ndarray) for b in kept] == [True, False, False]
    scans = list(cache.blocks(("k",), read, stats, scan=True))
    assert [np.array_equal(s.flags, w) for s, w in zip(scans, want, strict=True)] == [True] * 3
    assert scans[1].flags.base is scans[2].flags.base is not None  # one zero array
    replayed = [b.flags.copy() for b in cache.blocks(("k",), read, stats)]
    assert all(np.array_equal(r, w) for r, w in zip(replayed, want, strict=True))
    assert want[0].any() and not want[1].any() and not want[2].any()
