"""autocal gains written as genuine UVCal files (calh5, calfits) and read back by pyuvdata."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

import autocal  # noqa: F401  (offline configuration first)
from autocal.core.sites import EDGES, HERA
from autocal.io.calsol_files import CalsolFormatError
from autocal.io.calsol_read import read_reference_gains
from autocal.io.calsol_write import write_calfits, write_calh5
from tests.io.test_calsol import fitted_solution, make_solution


@pytest.mark.parametrize("kind", ["calh5", "calfits"])
def test_round_trip_through_pyuvdata(tmp_path, kind, capsys):
    from pyuvdata import UVCal

    sol = make_solution()
    writer = write_calh5 if kind == "calh5" else write_calfits
    path = writer(sol, tmp_path / f"gains.{kind}", per_time=False)
    uvc = UVCal.from_file(str(path))  # a genuine, checked UVCal
    assert uvc.cal_type == "gain"
    assert uvc.gain_convention == "divide"
    assert uvc.gain_scale == "K str" and uvc.pol_convention == "avg"
    assert uvc.extra_keywords["ACVUNIT"].startswith("K antenna temperature")
    assert uvc.telescope.name == "HERA"
    assert uvc.telescope.get_x_orientation_from_feeds() == "east"
    assert list(uvc.jones_array) == [-5, -6]
    assert uvc.Ntimes == 1 and uvc.time_array is None
    start, stop = uvc.time_range[0]
    assert start < sol.jds.min() and stop > sol.jds.max()
    assert stop - start == pytest.approx(np.ptp(sol.jds) + 60 / 86400, rel=1e-6)
    assert "autocal" in uvc.history and "gain_scale 'K str'" in uvc.history
    gains = uvc.gain_array[:, :, 0, :].transpose(0, 2, 1)  # (A, J, F)
    flags = uvc.flag_array[:, :, 0, :].transpose(0, 2, 1)
    np.testing.assert_array_equal(flags, sol.flags)
    ok = ~sol.flags
    # single precision (complex64): |g| to 6e-8, far below any uncertainty
    np.testing.assert_allclose(gains.real[ok], np.sqrt(sol.G)[ok], rtol=1e-7)
    assert uvc.gain_array.dtype == np.complex64
    assert np.all(gains.imag == 0)
    assert np.all(np.isfinite(uvc.gain_array))
    assert np.all(gains[sol.flags] == 1.0)
    quality = uvc.quality_array[:, :, 0, :].transpose(0, 2, 1)
    ok_q = ok & np.isfinite(sol.sigma_abs_g)
    np.testing.assert_allclose(quality[ok_q], sol.sigma_abs_g[ok_q], rtol=1e-6)  # total |g| 1-sigma
    assert np.all(quality[sol.flags] == 0)
    np.testing.assert_allclose(uvc.total_quality_array[:, 0, :][~sol.flags[0].T], 1.1)

    ref = read_reference_gains(path)
    assert ref.absolute and ref.gain_scale == "K"
    assert ref.pols == ("ee", "nn") and ref.antennas.tolist() == [0, 23]
    np.testing.assert_allclose(ref.jds, [0.5 * (start + stop)])
    np.testing.assert_allclose(ref.abs_g[:, :, 0][ok], sol.abs_g[ok], rtol=1e-7)
    assert np.all(np.isnan(ref.abs_g[:, :, 0][sol.flags]))
    assert capsys.readouterr().out == ""


def test_per_time_and_explicit_time_range(tmp_path):
    from pyuvdata import UVCal

    sol = fitted_solution(order=1, residuals=False)
    path = write_calh5(sol, tmp_path / "per_time.calh5")  # the default
    uvc = UVCal.from_file(str(path))
    assert uvc.Ntimes == sol.jds.size > 1 and uvc.time_range is None
    np.testing.assert_allclose(uvc.time_array, sol.jds)
    big_g = sol.evaluate()["G"]  # (A, P, T, F)
    ok = ~uvc.flag_array.transpose(0, 3, 2, 1)
    np.testing.assert_allclose(
        uvc.gain_array.real.transpose(0, 3, 2, 1)[ok], np.sqrt(big_g)[ok], rtol=1e-7
    )
    rng = (sol.jds.min() - 0.01, sol.jds.max() + 0.01)
    uvc2 = UVCal.from_file(str(write_calh5(sol, tmp_path / "range.calh5", time_range=rng)))
    np.testing.assert_allclose(uvc2.time_range[0], rng)
    with pytest.raises(CalsolFormatError, match="increasing"):
        write_calh5(sol, tmp_path / "bad.calh5", time_range=(rng[1], rng[0]))
    assert not (tmp_path / "bad.calh5").exists()
    with pytest.raises(CalsolFormatError, match="per_time"):
        write_calh5(sol, tmp_path / "both.calh5", time_range=rng, per_time=True)
    assert not (tmp_path / "both.calh5").exists()


def test_a_constant_model_shares_one_integrations_arrays(tmp_path):
    """With ``shared_times`` (what the writers use) a gain constant in time is one
    integration's arrays seen at every integration (zero time stride, no copies); the file
    and the ordinary writable object hold the same values at every time."""
    from pyuvdata import UVCal

    from autocal.io.calsol_uvcal import solution_to_uvcal

    sol = fitted_solution(order=0, residuals=False)
    assert sol.model.nbasis == 1
    shared = solution_to_uvcal(sol, shared_times=True)
    plain = solution_to_uvcal(sol)
    for name in ("gain_array", "flag_array", "quality_array"):
        view, full = getattr(shared, name), getattr(plain, name)
        assert view.strides[2] == 0 and not view.flags.writeable
        assert full.strides[2] != 0 and full.flags.writeable
        np.testing.assert_array_equal(view, full)
    assert shared.Ntimes == plain.Ntimes == sol.jds.size > 1
    np.testing.assert_allclose(shared.lst_array, plain.lst_array)
    back = UVCal.from_file(str(write_calh5(sol, tmp_path / "constant.calh5")))
    np.testing.assert_array_equal(back.gain_array, plain.gain_array)
    np.testing.assert_allclose(back.time_array, sol.jds)
    assert np.ptp(np.abs(back.gain_array), axis=2).max() == 0  # the same at every time


@pytest.mark.parametrize(
    ("order", "per_time", "time_flags"),
    [(0, True, False), (0, True, True), (1, True, False), (0, False, False)],
)
def test_the_calh5_reads_back_as_pyuvdatas_own_writer_writes_it(
    tmp_path, order, per_time, time_flags
):
    """autocal writes the calh5 an antenna at a time; pyuvdata's ``UVCal.write_calh5`` of
    the same object (materialised) reads back equal, header and arrays, and each 4-D
    dataset has pyuvdata's type, one antenna per chunk, deflated."""
    from dataclasses import replace

    from pyuvdata import UVCal

    from autocal.io.calsol_uvcal import solution_to_uvcal
    from autocal.io.calsol_write import _write_calh5_file

    sol = fitted_solution(order=order, residuals=False)
    if time_flags:
        flags_t = np.zeros((sol.G.shape[0], sol.G.shape[1], sol.jds.size), bool)
        flags_t[0, 0, 2] = True
        sol = replace(sol, time_flags=flags_t)
    uvc = solution_to_uvcal(sol, per_time=per_time, shared_times=True)  # as write_calh5
    ours, theirs = tmp_path / "ours.calh5", tmp_path / "pyuvdata.calh5"
    _write_calh5_file(uvc, ours)
    uvc.write_calh5(str(theirs))
    a, b = UVCal.from_file(str(ours)), UVCal.from_file(str(theirs))
    assert a.__eq__(b, check_extra=True)
    assert a.Ntimes == (sol.jds.size if per_time else 1)
    if time_flags:
        assert a.flag_array[0, :, 2, 0].all() and not sol.flags[0, 0].all()
        np.testing.assert_array_equal(a.flag_array[0, :, 1, 0], sol.flags[0, 0])
    with h5py.File(ours) as f, h5py.File(theirs) as g:
        assert (
            set(f["Data"])
            == set(g["Data"])
            == {
                "gains",
                "flags",
                "qualities",
                "total_qualities",
            }
        )
        for name in f["Data"]:
            mine, ref = f["Data"][name], g["Data"][name]
            assert mine.dtype == ref.dtype, name
            if mine.ndim == 4:  # one antenna per chunk, deflated (readable without plugins)
                assert mine.chunks == (1, *mine.shape[1:]), name
                assert mine.compression == "gzip", name


def test_chunks_cut_in_time_and_the_padded_edge_read_back(tmp_path, monkeypatch):
    """Chunks smaller than an antenna's integrations (the last one padded), compressed on
    one thread and on two: the arrays read back as pyuvdata's writer writes them."""
    from pyuvdata import UVCal

    import autocal.io.calsol_write as calsol_write
    from autocal.io.calsol_uvcal import solution_to_uvcal

    sol = fitted_solution(order=1, residuals=False)
    uvc = solution_to_uvcal(sol, shared_times=True)
    per_time = uvc.Nfreqs * uvc.Njones * 8
    monkeypatch.setattr(calsol_write, "MAX_CHUNK_BYTES", 5 * per_time)  # 5 integrations
    assert uvc.Ntimes % 5 != 0
    theirs = tmp_path / "pyuvdata.calh5"
    uvc.write_calh5(str(theirs))
    ref = UVCal.from_file(str(theirs))
    for threads in ("1", "2"):
        monkeypatch.setenv("AUTOCAL_FIT_THREADS", threads)
        ours = tmp_path / f"ours{threads}.calh5"
        calsol_write._write_calh5_file(uvc, ours)
        with h5py.File(ours) as f:
            assert f["Data/gains"].chunks[2] == 5
        back = UVCal.from_file(str(ours))
        for name in ("gain_array", "flag_array", "quality_array", "total_quality_array"):
            np.testing.assert_array_equal(getattr(back, name), getattr(ref, name), err_msg=name)


def test_the_antenna_fill_copies_any_layout():
    """The wide-item fill of a zero-time-stride view equals numpy's copy, and arrays it
    cannot widen (three feeds, another type) are copied as numpy copies them."""
    from autocal.io.calsol_write import _fill

    rng = np.random.default_rng(3)
    for dtype, njones in [(np.complex64, 2), (np.float32, 2), (bool, 2), (np.float32, 3)]:
        one = (rng.normal(size=(5, 1, njones)) > 0).astype(dtype)
        for src in (np.broadcast_to(one, (5, 4, njones)), np.repeat(one, 4, axis=1)):
            out = np.empty(src.shape, dtype)
            np.testing.assert_array_equal(_fill(out, src), src)
    src = rng.normal(size=(5, 4, 2))
    np.testing.assert_array_equal(
        _fill(np.empty(src.shape, np.float32), src), src.astype(np.float32)
    )


def test_non_hera_antennas_get_a_minimal_telescope(tmp_path):
    from pyuvdata import UVCal

    sol = make_solution(
        antennas=(0, 400), pols=("ee",), config={"telescope": "EDGES-like", "site": "edges"}
    )
    uvc = UVCal.from_file(str(write_calh5(sol, tmp_path / "edges.calh5")))
    assert uvc.telescope.name == "EDGES-like"
    assert sorted(uvc.telescope.antenna_numbers.tolist()) == [0, 400]
    lat, lon, _ = uvc.telescope.location_lat_lon_alt_degrees
    assert lat == pytest.approx(EDGES.lat_deg, abs=1e-3) and lon == pytest.approx(
        EDGES.lon_deg, abs=1e-3
    )
    assert read_reference_gains(tmp_path / "edges.calh5").antennas.tolist() == [0, 400]


def test_refuses_overwrite_and_writes_atomically(tmp_path, monkeypatch):
    sol = make_solution()
    path = write_calh5(sol, tmp_path / "g.calh5")
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match="overwrite"):
        write_calh5(sol, path)
    with pytest.raises(FileExistsError):
        write_calfits(sol, path)
    assert path.read_bytes() == before

    import autocal.io.calsol_write as calsol_write

    real_chunks = calsol_write._deflated_chunks

    def broken(*args, **kwargs):
        yield next(real_chunks(*args, **kwargs))  # the header and a chunk are in the file
        raise OSError("disk full")

    monkeypatch.setattr(calsol_write, "_deflated_chunks", broken)
    with pytest.raises(OSError, match="disk full"):
        write_calh5(make_solution(flagged=(1,)), path, overwrite=True)
    assert path.read_bytes() == before  # untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g.calh5"]  # no temporary left
    monkeypatch.undo()
    write_calh5(make_solution(flagged=(1,)), path, overwrite=True)
    assert read_reference_gains(path).flags[:, :, 0, 1].all()


def test_pipeline_style_configuration_sets_telescope_and_history(tmp_path):
    from dataclasses import replace

    from pyuvdata import UVCal

    edges = make_solution(antennas=(0, 1), pols=("ee",))
    edges = replace(
        edges,
        config={
            "calibration": {"sky": "gsm2008", "beam": "edges-low"},
            "provenance": {"site": EDGES.describe(), "sky": {"model": "gsm2008"}},
        },
    )
    uvc = UVCal.from_file(str(write_calh5(edges, tmp_path / "edges.calh5")))
    assert uvc.telescope.name == "edges"
    assert uvc.telescope.location_lat_lon_alt_degrees[0] == pytest.approx(EDGES.lat_deg, abs=1e-3)
    assert '"model": "gsm2008"' in uvc.history and "edges-low" in uvc.history
    hera = replace(edges, config={"provenance": {"site": HERA.describe()}})
    uvc = UVCal.from_file(str(write_calh5(hera, tmp_path / "hera.calh5")))
    assert uvc.telescope.name == "HERA" and uvc.telescope.Nants == 350
