"""UVH5 auto-correlation I/O: round trip, atomic writes, real HERA files, error model."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest
from astropy.time import Time

from autocal.core.observation import Observation, ObservationError
from autocal.core.sites import EDGES, HERA
from autocal.io.uvh5 import read_uvh5, write_uvh5
from autocal.io.uvh5_blocks import iter_uvh5_blocks
from autocal.io.uvh5_chunks import ReadStats
from autocal.io.uvh5_meta import UVH5FormatError
from autocal.io.uvh5_writer import UVH5AutosWriter

AUTOS = "hera/autos"
H1C_2458116 = [f"zen.2458116.{t}.HH.uvh5" for t in (30448, 31193, 31939)]

XRAA = [
    f"zen.{night}.{t}.xx.HH.XRAA.uvh5"
    for night, times in [
        (2458043, (40141, 40887, 41632)),
        (2458044, (40141, 40886, 41632)),
        (2458045, (40140, 40886, 41632)),
    ]
    for t in times
]

#: Every UVH5 file in the data folder and its (Nant, Npol, Ntime, Nfreq) by default.
REAL_FILES = {
    "zen.2458042.60288.HH.uvRXLS.uvh5_downselected": (8, 2, 60, 64),
    "zen.2458042.61034.HH.uvRXLS.uvh5_downselected": (8, 2, 60, 64),
    **{name: (7, 1, 60, 64) for name in XRAA},
    "zen.2458098.43124.downsample.uvh5": (10, 2, 3, 128),
    "zen.2458098.43124.subband.uvh5": (5, 2, 60, 175),
    "zen.2458098.45361.HH_downselected.uvh5": (8, 2, 10, 64),
    "zen.2458101.46106.xx.HH.OCR_53x_54x_only.uvh5": (2, 1, 60, 1024),
    **{name: (1, 2, 12, 1024) for name in H1C_2458116},
    "zen.2458116.61019.xx.HH.XRS_downselected.uvh5": (2, 1, 60, 1024),
    "zen.2458116.61765.xx.HH.XRS_downselected.uvh5": (2, 1, 60, 1024),
}


def _observation(
    jd0: float = 2458098.3,
    ntime: int = 4,
    freqs: np.ndarray | None = None,
    antennas: tuple[int, ...] = (0, 1, 11),
    site=HERA,
    telescope: str = "HERA",
) -> Observation:
    """A small synthetic observation with LSTs consistent with its JDs."""
    rng = np.random.default_rng(42)
    freqs = 120e6 + 97656.25 * np.arange(8) if freqs is None else freqs
    jds = jd0 + np.arange(ntime) * 10.737418 / 86400.0
    lsts = Time(jds, format="jd").sidereal_time("apparent", longitude=site.lon_deg).hour
    shape = (len(antennas), 2, ntime, freqs.size)
    return Observation(
        data=rng.uniform(1e3, 1e6, shape),
        freqs=freqs,
        lsts=lsts,
        jds=jds,
        antennas=np.array(antennas),
        pols=("ee", "nn"),
        site=site,
        flags=rng.random(shape) < 0.2,
        channel_width=97656.25,
        integration_time=10.737418,
        nsamples=rng.integers(0, 4, shape) / 2.0,
        telescope_name=telescope,
        meta={"history": "synthetic test data", "note": "hello", "gain": 2.5, "files": ["x"]},
    )


# ---------------------------------------------------------------------------------------
# writing and round trips
# ---------------------------------------------------------------------------------------
def test_round_trip_hera(tmp_path, capsys):
    obs = _observation()
    path = write_uvh5(
        obs, tmp_path / "synthetic.uvh5", history="round trip", extra_keywords={"k": 3}
    )
    back = read_uvh5(path)

    assert back.shape == obs.shape
    np.testing.assert_array_equal(back.data, obs.data)
    np.testing.assert_array_equal(back.flags, obs.flags)
    np.testing.assert_array_equal(back.nsamples, obs.nsamples)
    np.testing.assert_array_equal(back.freqs, obs.freqs)
    np.testing.assert_array_equal(back.channel_width, obs.channel_width)
    np.testing.assert_allclose(back.integration_time, obs.integration_time)
    np.testing.assert_allclose(back.jds, obs.jds, rtol=0, atol=1e-9)
    # pyuvdata's HERA location differs from autocal's rounded one by ~100 m: << 1 s of LST
    np.testing.assert_allclose(back.lsts, obs.lsts, rtol=0, atol=1.0 / 3600)
    assert back.antennas.tolist() == [0, 1, 11]
    assert back.antenna_names == ("HH0", "HH1", "HH11")
    assert back.pols == ("ee", "nn")
    assert back.telescope_name == "HERA"
    assert back.site.name == "hera"
    assert back.site.lat_deg == pytest.approx(HERA.lat_deg, abs=0.01)
    assert back.meta["extra_keywords"] == {"note": "hello", "gain": 2.5, "k": 3}
    assert back.meta["files"] == [str(path.resolve())]
    assert set(back.meta["sha256"]) == {str(path.resolve())}
    assert "synthetic test data" in back.meta["history"]
    assert "round trip" in back.meta["history"]
    assert capsys.readouterr().out == ""


def test_scanned_header_keeps_no_per_row_arrays(tmp_path):
    """A scanned file's metadata must not grow with its rows (a night scans every file)."""
    from autocal.io.uvh5_meta import read_file_meta

    path = write_uvh5(_observation(), tmp_path / "rows.uvh5", extra_keywords={"k": 3})
    meta = read_file_meta(path)
    assert meta.uv.extra_keywords["k"] == 3 and meta.uv.telescope.name
    for name in ("time_array", "lst_array", "uvw_array", "ant_1_array", "baseline_array"):
        assert not hasattr(meta.uv, name)
    assert meta.times.size == _observation().ntime


def test_written_file_is_genuine_uvh5(tmp_path):
    from pyuvdata import UVData

    obs = _observation()
    path = write_uvh5(obs, tmp_path / "genuine.uvh5")
    uv = UVData.from_file(str(path))  # runs pyuvdata's full checks
    assert uv.telescope.name == "HERA"
    assert uv.telescope.Nants == 350
    assert uv.telescope.get_x_orientation_from_feeds() == "east"
    assert uv.get_pols() == ["ee", "nn"]
    assert list(uv.polarization_array) == [-5, -6]
    assert np.all(uv.ant_1_array == uv.ant_2_array)
    assert uv.vis_units == "uncalib"
    assert uv.phase_center_catalog[0]["cat_type"] == "unprojected"
    assert uv.phase_center_catalog[0]["cat_name"] == "zenith"
    assert np.all(uv.data_array.imag == 0)
    np.testing.assert_array_equal(uv.get_data(11, 11, "nn").real, obs.data[2, 1])
    np.testing.assert_array_equal(uv.get_flags(1, 1, "ee"), obs.flags[1, 0])


def test_round_trip_non_hera_site_and_selection(tmp_path):
    obs = _observation(antennas=(5, 6), site=EDGES, telescope="EDGES-test")
    path = write_uvh5(obs, tmp_path / "edges.uvh5")
    back = read_uvh5(path, antennas=[6], pols=["nn"], freq_range=(120.1e6, 120.4e6))
    assert back.telescope_name == "EDGES-test"
    assert back.site.name == "edges-test"
    assert back.site.lat_deg == pytest.approx(EDGES.lat_deg, abs=1e-9)
    assert back.site.lon_deg == pytest.approx(EDGES.lon_deg, abs=1e-9)
    assert back.antenna_names == ("ant6",)
    keep = (obs.freqs >= 120.1e6) & (obs.freqs <= 120.4e6)
    np.testing.assert_array_equal(back.data[0, 0], obs.data[1, 1][:, keep])
    np.testing.assert_allclose(back.lsts, obs.lsts, rtol=0, atol=1e-6)


def test_overwrite_refused_unless_asked(tmp_path, capsys):
    obs = _observation()
    path = write_uvh5(obs, tmp_path / "a.uvh5")
    with pytest.raises(FileExistsError, match="overwrite=True"):
        write_uvh5(obs, path)
    doubled = replace(obs, data=obs.data * 2)
    write_uvh5(doubled, path, overwrite=True)
    np.testing.assert_array_equal(read_uvh5(path).data, doubled.data)
    assert capsys.readouterr().out == ""  # pyuvdata's "clobbering" print is avoided


def test_failed_write_leaves_no_file(tmp_path, monkeypatch):
    from pyuvdata import UVData

    def broken_write(self, filename, **kwargs):
        Path(filename).write_bytes(b"partial")
        raise OSError("disk full")

    obs = _observation()
    good = write_uvh5(obs, tmp_path / "keep.uvh5")
    before = good.read_bytes()
    monkeypatch.setattr(UVData, "write_uvh5", broken_write)
    with pytest.raises(OSError, match="disk full"):
        write_uvh5(obs, tmp_path / "new.uvh5")
    with pytest.raises(OSError, match="disk full"):
        write_uvh5(obs, good, overwrite=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.uvh5"]
    assert good.read_bytes() == before


def test_write_rejects_inconsistent_observations(tmp_path):
    obs = _observation()
    with pytest.raises(ObservationError, match="LSTs disagree"):
        write_uvh5(replace(obs, jds=obs.jds + 0.01), tmp_path / "wrong_jd.uvh5")
    with pytest.raises(ObservationError, match="do not exist in HERA"):
        write_uvh5(replace(obs, antennas=np.array([0, 1, 999])), tmp_path / "bad_ant.uvh5")
    with pytest.raises(ObservationError, match="integration_time"):
        write_uvh5(replace(obs, integration_time=0.0), tmp_path / "no_tint.uvh5")
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------------------------
# joining files
# ---------------------------------------------------------------------------------------
def test_join_synthetic_files_in_time_order_with_lst_wrap(tmp_path):
    first = _observation(ntime=3)
    second = _observation(jd0=first.jds[-1] + 10.737418 / 86400.0, ntime=3)
    p2 = write_uvh5(second, tmp_path / "b.uvh5")
    p1 = write_uvh5(first, tmp_path / "a.uvh5")
    joined = read_uvh5([p2, p1])
    assert joined.ntime == 6
    np.testing.assert_array_equal(joined.data[..., :3, :], first.data)
    np.testing.assert_array_equal(joined.data[..., 3:, :], second.data)
    assert joined.meta["files"] == [str(p1.resolve()), str(p2.resolve())]
    # an LST window that wraps through 24 h keeps everything after its start
    start = float(joined.lsts[2])
    wrapped = read_uvh5([p1, p2], lst_range=(start, start - 12.0))
    np.testing.assert_array_equal(wrapped.jds, joined.jds[2:])


def test_inconsistent_files_are_rejected(tmp_path):
    first = _observation(ntime=2)
    jd_next = first.jds[-1] + 10.737418 / 86400.0
    p1 = write_uvh5(first, tmp_path / "a.uvh5")
    shifted = write_uvh5(
        _observation(jd0=jd_next, ntime=2, freqs=first.freqs + 1e6), tmp_path / "freq.uvh5"
    )
    with pytest.raises(UVH5FormatError, match=r"freq\.uvh5.*frequencies differ"):
        read_uvh5([p1, shifted])
    fewer = write_uvh5(
        _observation(jd0=jd_next, ntime=2, freqs=first.freqs[:4]), tmp_path / "nfreq.uvh5"
    )
    with pytest.raises(UVH5FormatError, match=r"nfreq\.uvh5.* 4 channels"):
        read_uvh5([p1, fewer])
    ants = write_uvh5(_observation(jd0=jd_next, ntime=2, antennas=(0, 1)), tmp_path / "ants.uvh5")
    with pytest.raises(UVH5FormatError, match=r"antennas \[0, 1\]"):
        read_uvh5([p1, ants])
    with pytest.raises(UVH5FormatError, match="overlaps in time"):
        read_uvh5([p1, write_uvh5(first, tmp_path / "copy.uvh5")])


# ---------------------------------------------------------------------------------------
# real HERA files
# ---------------------------------------------------------------------------------------
@pytest.mark.data
def test_read_h1c_2458116_joined(data_root):
    from pyuvdata import UVData

    paths = [data_root / AUTOS / name for name in H1C_2458116]
    obs = read_uvh5(paths[::-1])
    assert obs.shape == (1, 2, 36, 1024)
    assert obs.antennas.tolist() == [23]
    assert obs.antenna_names == ("HH23",)
    assert obs.pols == ("ee", "nn")
    assert obs.freqs[0] == pytest.approx(100e6)
    assert obs.channel_width[0] == pytest.approx(97656.25)
    assert np.all(np.diff(obs.jds) > 0)
    assert obs.lsts[0] == pytest.approx(3.23, abs=0.01)
    assert obs.lsts[-1] == pytest.approx(3.76, abs=0.01)
    assert obs.integration_time[0] == pytest.approx(10.737, abs=1e-3)
    assert obs.site.name == "hera"
    assert obs.site.lat_deg == pytest.approx(-30.7215, abs=1e-3)
    assert obs.meta["files"] == [str(p) for p in paths]
    assert len(obs.meta["sha256"]) == 3
    assert obs.meta["vis_units"] == "uncalib"
    assert len(obs.meta["extra_keywords"]["obsid"]) == 3  # differs per file
    # the values are pyuvdata's own
    uv = UVData.from_file(str(paths[1]))
    np.testing.assert_array_equal(obs.data[0, 1, 12:24], uv.get_data(23, 23, "nn").real)


@pytest.mark.data
def test_read_2458043_with_antenna_selection(data_root):
    paths = [data_root / AUTOS / name for name in XRAA[:3]]
    obs = read_uvh5(paths, antennas=[53, 24], pols=["xx"])  # xx is an alias of ee here
    assert obs.shape == (2, 1, 180, 64)
    assert obs.antennas.tolist() == [53, 24]
    assert obs.antenna_names == ("HH53", "HH24")
    assert obs.pols == ("ee",)
    assert obs.lsts[0] == pytest.approx(0.77, abs=0.01)
    assert obs.lsts[-1] == pytest.approx(1.31, abs=0.01)
    alone = read_uvh5(paths[1], antennas=[24])
    np.testing.assert_array_equal(obs.data[1, 0, 60:120], alone.data[0, 0])
    np.testing.assert_array_equal(obs.flags[1, 0, 60:120], alone.flags[0, 0])
    part = read_uvh5(paths, antennas=[24], freq_range=(150e6, 120e6), lst_range=(1.0, 1.2))
    assert part.freqs.min() >= 120e6 and part.freqs.max() <= 150e6
    assert part.lsts.min() >= 1.0 and part.lsts.max() <= 1.2
    assert part.meta["files"] == [str(p) for p in paths[1:]]


@pytest.mark.data
def test_every_real_uvh5_file_reads(data_root):
    found = sorted(p for p in (data_root / AUTOS).iterdir() if p.is_file() and ".uvh5" in p.name)
    assert set(REAL_FILES) <= {p.name for p in found}
    for path in found:
        obs = read_uvh5(path)
        if path.name in REAL_FILES:
            assert obs.shape == REAL_FILES[path.name], path.name
        assert obs.telescope_name == "HERA"
        assert set(obs.pols) <= {"ee", "nn"}
        assert np.all(np.isfinite(obs.data[~obs.flags])), path.name


# ---------------------------------------------------------------------------------------
# errors
# ---------------------------------------------------------------------------------------
@pytest.mark.data
def test_broken_and_wrong_files(data_root, tmp_path):
    real = data_root / AUTOS / H1C_2458116[0]
    truncated = tmp_path / "truncated.uvh5"
    truncated.write_bytes(real.read_bytes()[:1000])
    with pytest.raises(UVH5FormatError, match=r"truncated\.uvh5 is truncated or corrupt"):
        read_uvh5(truncated)
    text = tmp_path / "notes.uvh5"
    text.write_text("not a UVH5 file\n")
    with pytest.raises(UVH5FormatError, match=r"notes\.uvh5 is not an HDF5 file"):
        read_uvh5(text)
    other_hdf5 = tmp_path / "table.h5"
    with h5py.File(other_hdf5, "w") as h5:
        h5["x"] = np.arange(3)
    with pytest.raises(UVH5FormatError, match="not UVH5"):
        read_uvh5(other_hdf5)
    with pytest.raises(UVH5FormatError, match="does not exist"):
        read_uvh5(tmp_path / "missing.uvh5")
    miriad = next((data_root / AUTOS).glob("*.uvOR_36x_auto_only"))
    with pytest.raises(UVH5FormatError, match="is a directory"):
        read_uvh5(miriad)
    with pytest.raises(ValueError):  # the error class is a ValueError for callers
        read_uvh5(text)


@pytest.mark.data
def test_file_without_autos(data_root, tmp_path):
    from pyuvdata import UVData

    uv = UVData.from_file(str(data_root / AUTOS / H1C_2458116[0]), bls=[(23, 24)])
    cross_only = tmp_path / "cross.uvh5"
    uv.write_uvh5(str(cross_only))
    with pytest.raises(UVH5FormatError, match="no auto-correlations"):
        read_uvh5(cross_only)


@pytest.mark.data
def test_bad_selections(data_root):
    path = data_root / AUTOS / XRAA[0]
    with pytest.raises(ObservationError, match=r"\[99\].*available antennas: \[24, 25, 37"):
        read_uvh5(path, antennas=[24, 99])
    with pytest.raises(ObservationError, match=r"no channels in the frequency range"):
        read_uvh5(path, freq_range=(50e6, 60e6))
    with pytest.raises(ObservationError, match=r"polarisation 'nn' is not in"):
        read_uvh5(path, pols=["nn"])
    with pytest.raises(ObservationError, match="no integrations in LST range"):
        read_uvh5(path, lst_range=(12.0, 13.0))


# ---------------------------------------------------------------------------------------
# writing in parts, reading in blocks
# ---------------------------------------------------------------------------------------
def _writer(obs: Observation, path: Path, **kwargs) -> UVH5AutosWriter:
    return UVH5AutosWriter(
        path,
        freqs=obs.freqs,
        channel_width=obs.channel_width,
        jds=obs.jds,
        lsts=obs.lsts,
        integration_time=obs.integration_time,
        antennas=obs.antennas,
        pols=obs.pols,
        site=obs.site,
        telescope_name=obs.telescope_name,
        **kwargs,
    )


@pytest.mark.parametrize(
    ("dtype", "compression", "scale"),
    [("c8", "lzf", 1.0), ("c16", "gzip", 1.0), ("c8", None, 1.0), ("int32", "gzip", 1.0)],
)
def test_part_writer_round_trip(tmp_path, dtype, compression, scale):
    obs = _observation(ntime=7)
    data = np.rint(obs.data) if dtype == "int32" else obs.data
    flags = np.zeros(obs.shape, bool)
    flags[1, 0, 2, 3] = True
    path = tmp_path / "parts.uvh5"
    with _writer(obs, path, dtype=dtype, compression=compression) as writer:
        for start in (0, 3, 6):  # any order of parts, each written once
            part = slice(start, min(start + 3, 7))
            writer.write(start, data[:, :, part], flags[:, :, part], obs.nsamples[:, :, part])
    back = read_uvh5(path)
    rtol = 1e-7 if dtype == "c8" else 0
    np.testing.assert_allclose(back.data, data, rtol=rtol)
    np.testing.assert_array_equal(back.flags, flags)
    np.testing.assert_allclose(back.lsts, obs.lsts, atol=1 / 3600)
    assert back.pols == obs.pols and back.telescope_name == "HERA"
    with h5py.File(path, "r") as h5:
        vis = h5["Data/visdata"]
        assert vis.shape == (7 * obs.nant, obs.nfreq, 2)
        assert vis.chunks == (obs.nant, obs.nfreq, 1)
        assert vis.compression == compression and vis.shuffle == (compression is not None)
        if dtype == "int32":
            assert vis.dtype.names == ("r", "i")
    blocks = list(iter_uvh5_blocks(path, block_size=2))
    np.testing.assert_array_equal(np.concatenate([b.data for b in blocks], axis=2), back.data)


def test_part_writer_refuses_incomplete_or_bad_parts(tmp_path):
    obs = _observation(ntime=4)
    path = tmp_path / "incomplete.uvh5"
    with pytest.raises(ObservationError, match="never written"), _writer(obs, path) as writer:
        writer.write(0, obs.data[:, :, :2])
    assert not path.exists() and not list(tmp_path.iterdir())
    with pytest.raises(ObservationError, match="outside"), _writer(obs, path) as writer:
        writer.write(3, obs.data[:, :, :2])
    with pytest.raises(ObservationError, match="expected"), _writer(obs, path) as writer:
        writer.write(0, obs.data[:1])
    assert not list(tmp_path.iterdir())
    with pytest.raises(ObservationError, match="data type"):
        _writer(obs, path, dtype="f4")
    with pytest.raises(ObservationError, match="compression"):
        _writer(obs, path, compression="szip")
    path.touch()
    with pytest.raises(FileExistsError):
        _writer(obs, path)


def test_block_reader_matches_pyuvdata_on_real_files(data_root):
    """Every real file (complex64/128, old and new shapes, with crosses, imaginary autos)."""
    for name in REAL_FILES:
        path = data_root / AUTOS / name
        whole = read_uvh5(path)
        stats = ReadStats()
        blocks = list(iter_uvh5_blocks(path, block_size=7, stats=stats))
        for key in ("data", "flags", "nsamples"):
            np.testing.assert_array_equal(
                np.concatenate([getattr(b, key) for b in blocks], axis=2), getattr(whole, key)
            )
        np.testing.assert_array_equal(
            np.concatenate([b.integration_time for b in blocks]), whole.integration_time
        )
        assert stats.largest_array <= 7 * whole.nant * 4 * whole.nfreq * 16
    # selections: antennas in any order, one pol, a channel range, an LST range
    path = data_root / AUTOS / "zen.2458098.43124.subband.uvh5"
    whole = read_uvh5(path)
    sel = {
        "antennas": whole.antennas[::-1][:3].tolist(),
        "pols": ["nn"],
        "freq_range": (120e6, 130e6),
        "lst_range": (whole.lsts[5], whole.lsts[40]),
    }
    expected = read_uvh5(path, **sel)
    blocks = list(iter_uvh5_blocks(path, block_size=4, **sel))
    np.testing.assert_array_equal(np.concatenate([b.data for b in blocks], axis=2), expected.data)
    assert blocks[0].antennas.tolist() == sel["antennas"]


def _block_copies(path: Path, **kwargs) -> tuple[list[dict], dict]:
    """Copies of every block's arrays and meta (taken before the next block is asked for)."""
    stats = ReadStats()
    out = []
    for b in iter_uvh5_blocks(path, stats=stats, **kwargs):
        out.append(
            {
                "data": b.data.copy(),
                "flags": b.flags.copy(),
                "nsamples": np.array(b.nsamples),
                "integration_time": b.integration_time.copy(),
                "meta": dict(b.meta),
            }
        )
    return out, stats.as_dict()


def _reader_threads() -> list:
    import threading

    return [t for t in threading.enumerate() if t.name.startswith("autocal-uvh5")]


@pytest.mark.parametrize(
    "name, selection",
    [
        ("zen.2458098.43124.subband.uvh5", {}),
        ("zen.2458098.43124.subband.uvh5", {"pols": ["nn"], "freq_range": (120e6, 130e6)}),
        ("zen.2458042.60288.HH.uvRXLS.uvh5_downselected", {}),  # crosses: point selection
        ("zen.2458116.30448.HH.uvh5", {}),  # imaginary autos
    ],
)
def test_prefetch_and_reused_buffers_give_the_same_blocks(data_root, name, selection):
    path = data_root / AUTOS / name
    kw = {"block_size": 3, **selection}
    expected, expected_stats = _block_copies(path, prefetch=False, **kw)
    assert len(expected) > 2 and "sha256" in expected[0]["meta"]
    for prefetch, reuse in ((True, False), (False, True), (True, True)):
        got, stats = _block_copies(path, prefetch=prefetch, reuse_buffers=reuse, **kw)
        assert stats == expected_stats
        assert len(got) == len(expected)
        for g, e in zip(got, expected, strict=True):
            assert g["meta"] == e["meta"]
            for key in ("data", "flags", "nsamples", "integration_time"):
                np.testing.assert_array_equal(g[key], e[key])
    assert not _reader_threads()


def test_reused_buffers_alternate_between_two_sets(tmp_path):
    obs = _observation(ntime=7)
    path = tmp_path / "obs.uvh5"
    write_uvh5(obs, path)
    fresh = list(iter_uvh5_blocks(path, block_size=2))
    assert not np.shares_memory(fresh[0].data, fresh[2].data)
    seen = []
    for block in iter_uvh5_blocks(path, block_size=2, reuse_buffers=True):
        seen.append(block.data)
    assert np.shares_memory(seen[0], seen[2]) and np.shares_memory(seen[1], seen[3])
    assert not np.shares_memory(seen[0], seen[1])


def test_block_reader_early_close_and_errors_leave_no_thread_or_open_file(tmp_path, monkeypatch):
    import autocal.io.uvh5_blocks as uvh5_blocks

    obs = _observation(ntime=9)
    path = tmp_path / "obs.uvh5"
    write_uvh5(obs, path)
    opened: list = []

    class Tracked(uvh5_blocks.CountingFile):
        def __init__(self, p):
            super().__init__(p)
            opened.append(self)

    monkeypatch.setattr(uvh5_blocks, "CountingFile", Tracked)
    blocks = iter_uvh5_blocks(path, block_size=2)
    first = next(blocks)  # the second block is being read meanwhile
    blocks.close()
    assert first.ntime == 2 and opened[-1].closed and not _reader_threads()

    real_read = uvh5_blocks.read_rows
    calls = []

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) > 6:  # 3 data sets per block: the third block fails
            raise OSError("simulated read error")
        return real_read(*args, **kwargs)

    monkeypatch.setattr(uvh5_blocks, "read_rows", failing)
    got = []
    with pytest.raises(UVH5FormatError, match="simulated read error"):
        for block in iter_uvh5_blocks(path, block_size=2):
            got.append(block.meta["block"])
    assert got == [0, 1]  # the error surfaces at the block it belongs to
    assert opened[-1].closed and not _reader_threads()


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
            for lo, hi, chans, pols in [
                (0, 50, slice(0, 37), slice(0, 2)),
                (3, 19, slice(5, 30), slice(1, 2)),
                (44, 50, slice(36, 37), slice(0, 1)),
            ]:
                out = np.full((hi - lo, chans.stop - chans.start, pols.stop - pols.start), -1.0)
                out = out.astype(dset.dtype)
                index = (slice(lo, hi), 0, chans, pols) if legacy else (slice(lo, hi), chans, pols)
                if rep.fill(out, lo, hi, chans, pols, stats):
                    np.testing.assert_array_equal(out, dset[index])
                else:
                    assert name in ("noisy", "gaps") and not rep.active
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
            out = np.empty((hi - lo, 37, 2))
            if not rep.fill(out, lo, hi, slice(0, 37), slice(0, 2), ReadStats()):
                break
        assert not rep.active and not rep.decoded and rep.seen >= RepeatedChunks.TRIAL_CHUNKS


def test_block_reader_decodes_repeated_flag_and_nsample_chunks_once(tmp_path):
    obs = _observation(ntime=9)
    path = tmp_path / "parts.uvh5"
    flags = np.zeros(obs.shape, bool)
    flags[2, 1, 4, 1:3] = True  # a few flagged samples: their chunk is decoded, not reused
    nsamples = np.ones(obs.shape)  # uniform, as in raw HERA files
    with _writer(obs, path, compression="gzip") as writer:
        writer.write(0, obs.data, flags, nsamples)
    whole = read_uvh5(path)  # pyuvdata
    stats = ReadStats()
    blocks = list(iter_uvh5_blocks(path, block_size=2, stats=stats))
    for key in ("data", "flags", "nsamples"):
        np.testing.assert_array_equal(
            np.concatenate([getattr(b, key) for b in blocks], axis=2), getattr(whole, key)
        )
    assert whole.flags.sum() == 2
    plain_stats = ReadStats()
    plain = list(iter_uvh5_blocks(path, block_size=2, stats=plain_stats, decode_repeats_once=False))
    for b, c in zip(blocks, plain, strict=True):
        np.testing.assert_array_equal(b.flags, c.flags)
        np.testing.assert_array_equal(b.nsamples, c.nsamples)
    assert plain_stats.bytes_reused == 0
    # one chunk per integration and pol (all antennas and channels): every chunk is a copy
    # except the first of each data set and the one with the flags
    with h5py.File(path, "r") as h5:
        assert h5["Data/flags"].chunks == (obs.nant, obs.nfreq, 1)
        per_chunk = {
            k: obs.nant * obs.nfreq * h5[f"Data/{k}"].dtype.itemsize for k in ("flags", "nsamples")
        }
    nchunks = obs.ntime * len(obs.pols)
    assert (
        stats.bytes_reused
        == (nchunks - 2) * per_chunk["flags"] + (nchunks - 1) * per_chunk["nsamples"]
    )


@pytest.mark.parametrize("dataset", ["Data/visdata", "Data/flags"])
def test_a_chunk_that_does_not_decode_is_a_clear_error(tmp_path, dataset, capsys):
    from autocal.cli.main import main

    obs = _observation(ntime=9)
    path = tmp_path / "corrupt.uvh5"
    with _writer(obs, path, compression="gzip") as writer:
        writer.write(0, obs.data, np.zeros(obs.shape, bool), np.ones(obs.shape))
    with h5py.File(path, "r+") as h5:  # the chunk of integration 5, pol 0: garbage bytes
        dset = h5[dataset]
        mask, _ = dset.id.read_direct_chunk((obs.nant * 5, 0, 0))
        dset.id.write_direct_chunk((obs.nant * 5, 0, 0), b"\x00garbage" * 4, mask)
    with pytest.raises(UVH5FormatError, match=r"integrations 4-5 .*corrupt or truncated"):
        for _ in iter_uvh5_blocks(path, block_size=2):
            pass
    assert not _reader_threads()
    out = tmp_path / "cal"
    argv = ["calibrate", str(path), "--beam", "dipole", "--nside", "16", "--out", str(out)]
    assert main(argv) == 2
    assert "corrupt or truncated" in capsys.readouterr().err and not out.exists()


@pytest.mark.data
def test_pyuvdata_compiled_helpers_are_cached_on_disk(data_root, tmp_path) -> None:
    """A process reading a UVH5 header leaves pyuvdata's machine code for the next one."""
    import os
    import subprocess
    import sys

    path = data_root / AUTOS / XRAA[0]
    code = "import sys; from autocal.io.uvh5 import scan_uvh5; scan_uvh5([sys.argv[1]])"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    subprocess.run([sys.executable, "-c", code, str(path)], env=env, check=True, timeout=300)
    assert list(tmp_path.rglob("bls_numba._antnums_to_baseline-*.nbi"))
