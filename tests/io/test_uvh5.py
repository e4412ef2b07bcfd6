"""UVH5 files read and written whole: round trip, atomic writes, real HERA files, error model.

The module's synthetic observation and file lists are shared by the other UVH5 tests.
"""

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
from autocal.io.uvh5_meta import UVH5FormatError

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


def synthetic_observation(
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
    obs = synthetic_observation()
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


def test_written_file_is_genuine_uvh5(tmp_path):
    from pyuvdata import UVData

    obs = synthetic_observation()
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
    obs = synthetic_observation(antennas=(5, 6), site=EDGES, telescope="EDGES-test")
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
    obs = synthetic_observation()
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

    obs = synthetic_observation()
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
    obs = synthetic_observation()
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
    first = synthetic_observation(ntime=3)
    second = synthetic_observation(jd0=first.jds[-1] + 10.737418 / 86400.0, ntime=3)
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
    first = synthetic_observation(ntime=2)
    jd_next = first.jds[-1] + 10.737418 / 86400.0
    p1 = write_uvh5(first, tmp_path / "a.uvh5")
    shifted = write_uvh5(
        synthetic_observation(jd0=jd_next, ntime=2, freqs=first.freqs + 1e6), tmp_path / "freq.uvh5"
    )
    with pytest.raises(UVH5FormatError, match=r"freq\.uvh5.*frequencies differ"):
        read_uvh5([p1, shifted])
    fewer = write_uvh5(
        synthetic_observation(jd0=jd_next, ntime=2, freqs=first.freqs[:4]), tmp_path / "nfreq.uvh5"
    )
    with pytest.raises(UVH5FormatError, match=r"nfreq\.uvh5.* 4 channels"):
        read_uvh5([p1, fewer])
    ants = write_uvh5(
        synthetic_observation(jd0=jd_next, ntime=2, antennas=(0, 1)), tmp_path / "ants.uvh5"
    )
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
    with pytest.raises(UVH5FormatError, match="is a Miriad data set, not a UVH5 file"):
        read_uvh5(miriad)
    with pytest.raises(UVH5FormatError, match="not a whole Miriad data set either"):
        read_uvh5(tmp_path)  # a folder without visdata and vartable
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
