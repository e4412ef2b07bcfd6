"""EDGES raw spectra (ACQ, HDF5): reading, writing and refusing bad files (autocal.io.edges_*)."""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest
import read_acq

from autocal.core.files import file_checksum
from autocal.core.sites import EDGES
from autocal.io.edges_acq import ACQ_FLOOR, read_acq_spectra, write_acq
from autocal.io.edges_hdf5 import read_edges_hdf5, write_edges_hdf5
from autocal.io.edges_read import read_edges
from autocal.io.edges_spectra import (
    NATIVE_DF_HZ,
    NATIVE_NCHAN,
    EdgesFormatError,
    EdgesSpectra,
    channel_bins,
    native_freqs,
)
from autocal.io.edges_time import acq_time_to_jd, jd_to_acq_time

ACQ_DIR = "edges/acq"
RECEIVER01 = "edges/acq/Receiver01_25C_2019_11_26_040_to_200MHz"
EDGES3_ROOT = "edges/acq/edges3-mock-root/mro"


def _all_acq(root: Path) -> list[Path]:
    return sorted((root / ACQ_DIR).rglob("*.acq"))


def _synthetic(ntime: int = 3, lo: int = 8192, hi: int = 8192 + 512, seed: int = 1) -> EdgesSpectra:
    rng = np.random.default_rng(seed)
    f = native_freqs()[lo:hi]
    base = 1e-8 * (f / 75e6) ** -2.5
    jds = 2458000.5 + np.arange(ntime) * 40.0 / 86400
    p = [base * (k + 1.0) * (1 + 0.01 * rng.standard_normal((ntime, f.size))) for k in (1, 0, 2)]
    return EdgesSpectra(p[0], p[1], p[2], f, jds, NATIVE_DF_HZ, 6.71)


# ---------------------------------------------------------------------------------------
# reading every real file
# ---------------------------------------------------------------------------------------
@pytest.mark.data
def test_reads_every_acq_file(data_root: Path) -> None:
    files = _all_acq(data_root)
    assert len(files) == 26
    stamp = re.compile(r"(\d{4})_(\d{3})_(\d{2})_(\d{2})_(\d{2})")
    for path in files:
        for r in ("q", "p0"):
            obs = read_edges(path, r=r, freq_range=(40e6, 200e6), bin_factor=64)
            assert obs.telescope_name == "EDGES"
            assert obs.pols == ("ee",) and obs.antennas.tolist() == [0]
            assert obs.site == EDGES
            assert obs.nfreq == 409 and obs.freqs[0] >= 40e6 and obs.freqs[-1] <= 200e6
            assert np.allclose(obs.channel_width, 64 * NATIVE_DF_HZ)
            assert np.all((obs.lsts >= 0) & (obs.lsts < 24))
            assert obs.meta["r"] == r
            assert obs.meta["sha256"][str(path.resolve())] == file_checksum(path)
            assert not obs.flags.any()
            if r == "p0":
                assert np.all(obs.data > 0)
        # the cycle timestamps are those of the file name (UTC), except sample.acq
        match = stamp.search(path.name)
        if match:
            when = "{}:{}:{}:{}:{}".format(*match.groups())
            assert obs.jds[0] == pytest.approx(acq_time_to_jd([when])[0], abs=1e-9)
        # integration time from the header: nblk * 2 * num_channels / acquisition_rate
        expected_t = (
            2974 * 65536 / 400e6
            if "Receiver01" in str(path) or "sample" in path.name
            else 40956 * 65536 / 400e6
        )
        assert np.allclose(obs.integration_time, expected_t)
        assert "header" in obs.meta["integration_time_source"]


@pytest.mark.data
def test_edges3_files_join_in_time_and_noise_matches_integration_time(data_root: Path) -> None:
    files = sorted((data_root / EDGES3_ROOT).rglob("*.acq"))
    spec = read_acq_spectra(files[::-1], freq_range=(60e6, 120e6))
    assert spec.ntime == 12 and np.all(np.diff(spec.jds) > 0)
    assert spec.integration_time[0] == pytest.approx(6.7102, rel=1e-4)
    # channel-to-channel scatter of a ratio of two cycles of the ambient load
    amb = read_acq_spectra(files[0], freq_range=(60e6, 120e6))
    ratio = amb.p1[0] / amb.p1[1]
    ratio = ratio / np.convolve(ratio, np.ones(201) / 201, mode="same")
    measured = np.std(ratio[200:-200]) / np.sqrt(2)
    assert measured == pytest.approx(1 / np.sqrt(NATIVE_DF_HZ * 6.7102), rel=0.1)


@pytest.mark.data
@pytest.mark.filterwarnings("ignore::UserWarning")  # read_acq: header items without value
def test_sample_acq_drops_its_incomplete_last_cycle(data_root: Path) -> None:
    spec = read_acq_spectra(data_root / ACQ_DIR / "sample.acq")
    assert spec.ntime == 1 and spec.nfreq == NATIVE_NCHAN
    assert spec.freqs[1] == NATIVE_DF_HZ
    assert np.all(spec.p0[0, :10] == pytest.approx(ACQ_FLOOR))  # FASTSPEC blanks them
    q, _, _ = read_acq.decode_file(data_root / ACQ_DIR / "sample.acq", progress=False)
    step = spec.p2[0] > spec.p1[0]  # Q is NaN where the noise source adds nothing
    assert np.all(step[(spec.freqs > 40e6) & (spec.freqs < 195e6)])  # the lab band
    np.testing.assert_allclose(spec.q[0, step], q[step, 0])
    assert np.all(np.isnan(spec.q[0, ~step]))


# ---------------------------------------------------------------------------------------
# round trips
# ---------------------------------------------------------------------------------------
@pytest.mark.data
def test_hdf5_round_trip(data_root: Path, tmp_path: Path) -> None:
    path = data_root / EDGES3_ROOT / "amb/2023/2023_070_12_43_06_amb.acq"
    spec = read_acq_spectra(path)
    out = write_edges_hdf5(tmp_path / "amb.h5", spec)
    back = read_edges_hdf5(out)
    for name in ("p0", "p1", "p2", "freqs", "jds", "channel_width", "integration_time"):
        np.testing.assert_array_equal(getattr(back, name), getattr(spec, name))
    for key in spec.aux:
        np.testing.assert_array_equal(back.aux[key], spec.aux[key])
    assert back.meta["parents"] == spec.meta["files"]
    assert back.meta["header"]["nblk"] == 40956
    # the observation from the HDF5 file equals the one from the ACQ file
    a = read_edges(path, freq_range=(50e6, 150e6), bin_factor=32)
    b = read_edges(out, freq_range=(50e6, 150e6), bin_factor=32)
    np.testing.assert_array_equal(a.data, b.data)
    np.testing.assert_array_equal(a.lsts, b.lsts)
    # binned spectra round trip too, and keep their bin factor
    binned = spec.select((50e6, 100e6), 16)
    back2 = read_edges_hdf5(write_edges_hdf5(tmp_path / "binned.h5", binned))
    np.testing.assert_array_equal(back2.p2, binned.p2)
    assert back2.meta["bin_factor"] == 16
    with h5py.File(out) as h5:
        assert h5.attrs["format"] == "autocal-edges-spectra-1"
        assert set(h5) >= {"p0", "p1", "p2", "freqs", "jds", "channel_width", "integration_time"}
    assert not list(tmp_path.glob(".*.part"))  # atomic writes leave no temporaries


@pytest.mark.data
def test_acq_round_trip_of_a_real_file(data_root: Path, tmp_path: Path) -> None:
    spec = read_acq_spectra(data_root / RECEIVER01 / "Spectra/HotLoad_01_2019_330_23_38_05_lab.acq")
    out = write_acq(tmp_path / "hot.acq", spec, header={"site": "asulab", "instrument": "lab"})
    back = read_acq_spectra(out)
    for name in ("p0", "p1", "p2"):
        a, b = getattr(spec, name), getattr(back, name)
        assert np.max(np.abs(b / a - 1)) < 2.31e-6  # 1e-5 dB steps
    np.testing.assert_array_equal(back.jds, spec.jds)
    np.testing.assert_array_equal(back.freqs, spec.freqs)
    assert back.integration_time[0] == pytest.approx(spec.integration_time[0], rel=1e-12)
    assert back.meta["header"]["site"] == "asulab"
    np.testing.assert_allclose(back.aux["adcmax"], spec.aux["adcmax"], atol=1e-5)
    # the raw text: header lines, then comment + data line per switch position
    lines = out.read_text().splitlines()
    body = [line for line in lines if not line.startswith(";")]
    assert len(body) == 6
    assert body[0].startswith("# swpos 0 data_drops")
    assert body[1].startswith("2019:330:23:38:05 0 ")
    assert len(body[1].split(" spectrum ")[1]) == 4 * NATIVE_NCHAN


def test_acq_round_trip_of_a_sub_band(tmp_path: Path) -> None:
    spec = _synthetic()
    out = write_acq(tmp_path / "sub.acq", spec)
    back = read_acq_spectra(out, freq_range=(spec.freqs[0], spec.freqs[-1]))
    assert back.nfreq == spec.nfreq
    for name in ("p0", "p1", "p2"):
        assert np.max(np.abs(getattr(back, name) / getattr(spec, name) - 1)) < 2.31e-6
    np.testing.assert_allclose(back.q, spec.q, rtol=2e-5)
    assert back.integration_time[0] == pytest.approx(6.71, abs=2e-4)  # kept as nblk
    full = read_acq_spectra(out)  # the rest of the band holds the edge values
    assert full.nfreq == NATIVE_NCHAN and np.all(np.isfinite(full.p0))
    # read_acq itself reads it
    q, _p, _ = read_acq.decode_file(out, progress=False)
    assert q.shape == (NATIVE_NCHAN, 3)


def test_acq_writer_refuses_what_acq_cannot_hold(tmp_path: Path) -> None:
    spec = _synthetic()
    with pytest.raises(ValueError, match="native"):
        write_acq(tmp_path / "x.acq", spec.select(None, 4))
    with pytest.raises(ValueError, match="rescale"):
        write_acq(tmp_path / "x.acq", replace(spec, p0=spec.p0 * 1e9))
    assert not (tmp_path / "x.acq").exists()


def test_times_round_trip_to_whole_seconds() -> None:
    jds = np.array([2458000.5, 2458000.5 + 12.4 / 86400, 2458001.123456])
    back = acq_time_to_jd(jd_to_acq_time(jds))
    assert np.all(np.abs(back - jds) * 86400 <= 0.5 + 1e-6)
    assert jd_to_acq_time(back) == jd_to_acq_time(jds)
    assert jd_to_acq_time([2458000.5])[0] == "2017:247:00:00:00"


def test_select_bins_and_q_variance() -> None:
    spec = _synthetic()
    index, centres = channel_bins(spec.freqs, None, 8)
    assert index.shape == (64, 8)
    binned = spec.select(None, 8)
    np.testing.assert_allclose(binned.p0, spec.p0.reshape(3, 64, 8).mean(axis=2))
    np.testing.assert_allclose(binned.freqs, centres)
    np.testing.assert_allclose(binned.channel_width, 8 * NATIVE_DF_HZ)
    # propagated Q variance against a Monte Carlo of the radiometer noise
    rng = np.random.default_rng(3)
    p0, p1, p2 = 3.0, 1.0, 2.5
    bt = NATIVE_DF_HZ * 6.71
    draws = [p * (1 + rng.standard_normal(200000) / np.sqrt(bt)) for p in (p0, p1, p2)]
    one = EdgesSpectra([[p0]], [[p1]], [[p2]], [60e6], [2458000.5], NATIVE_DF_HZ, 6.71)
    q = (draws[0] - draws[1]) / (draws[2] - draws[1])
    assert one.variance("q")[0, 0] == pytest.approx(np.var(q), rel=0.02)
    assert one.variance("p0")[0, 0] == pytest.approx(p0**2 / bt)
    with pytest.raises(ValueError, match="bin_factor"):
        channel_bins(spec.freqs, None, 0)
    with pytest.raises(ValueError, match="no complete bin"):
        channel_bins(spec.freqs, (1e6, 2e6), 1)
    with pytest.raises(ValueError, match="unknown auto-correlation"):
        spec.to_observation("p1")  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------------
# refusing bad files
# ---------------------------------------------------------------------------------------
@pytest.fixture
def good_acq(tmp_path: Path) -> Path:
    return write_acq(tmp_path / "good.acq", _synthetic(ntime=4))


def test_truncated_and_corrupt_acq_files_are_refused(good_acq: Path, tmp_path: Path) -> None:
    raw = good_acq.read_bytes()
    cases = {
        "text.acq": b"this is not an ACQ file\nat all\n",
        "binary.acq": bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8)),
        "empty.acq": b"",
        "header_only.acq": raw[: raw.index(b"\n#") + 1],
        "truncated.acq": raw[: int(len(raw) * 0.7)],
        "nul_padded.acq": raw[: int(len(raw) * 0.6)] + b"\x00" * 4096,
    }
    lines = raw.split(b"\n")
    first = next(i for i, line in enumerate(lines) if line.startswith(b"#"))
    lines[first + 8] = b"# swpos garbage"
    cases["bad_comment.acq"] = b"\n".join(lines)
    for name, content in cases.items():
        path = tmp_path / name
        path.write_bytes(content)
        with pytest.raises(EdgesFormatError, match=re.escape(str(path))) as info:
            read_edges(path)
        message = str(info.value)
        assert "re-copy" in message.lower() or "archive" in message, (name, message)
    # partial files can be kept on request
    spec = read_acq_spectra(tmp_path / "truncated.acq", allow_partial=True)
    assert 1 <= spec.ntime < 4
    spec = read_acq_spectra(tmp_path / "bad_comment.acq", allow_partial=True)
    assert spec.ntime == 3
    with pytest.raises(FileNotFoundError, match="does not exist"):
        read_edges(tmp_path / "missing.acq")
    with pytest.raises(EdgesFormatError, match="folder"):
        read_edges(tmp_path)


def test_bad_hdf5_files_are_refused(tmp_path: Path) -> None:
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as h5:
        h5["x"] = np.arange(3)
    with pytest.raises(EdgesFormatError, match="not an autocal EDGES"):
        read_edges(other)
    good = write_edges_hdf5(tmp_path / "good.h5", _synthetic())
    broken = tmp_path / "broken.h5"
    broken.write_bytes(good.read_bytes()[:3000])
    with pytest.raises(EdgesFormatError, match=re.escape(str(broken))):
        read_edges(broken)
