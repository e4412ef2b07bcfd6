"""EDGES raw spectra (ACQ, HDF5), the receiver calibration and an EDGES-like day."""

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
from autocal.edges import receiver as er
from autocal.io.edges import (
    ACQ_FLOOR,
    NATIVE_DF_HZ,
    NATIVE_NCHAN,
    EdgesFormatError,
    EdgesSpectra,
    acq_time_to_jd,
    channel_bins,
    jd_to_acq_time,
    native_freqs,
    read_acq_spectra,
    read_edges,
    read_edges_hdf5,
    write_acq,
    write_edges_hdf5,
)

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


# ---------------------------------------------------------------------------------------
# receiver solutions and the calibration equations
# ---------------------------------------------------------------------------------------
@pytest.mark.data
def test_receiver_solution_files_and_their_conventions(data_root: Path) -> None:
    alan = er.load_receiver_solution("edges2-lowband-2015")
    e3 = er.load_receiver_solution("edges3-2022-316")
    ref = er.load_receiver_solution("edges2-2015-09")
    assert alan.freqs.size == 1434 and alan.freqs[0] == pytest.approx(40.002441e6)
    assert alan.freqs[-1] == pytest.approx(109.973145e6)
    assert e3.freqs.size == 2868 and 50e6 <= e3.freqs[0] < e3.freqs[-1] <= 190e6
    assert ref.freqs.size == 100
    # the LNA S11 column is the modelled LNA S11 of the same folder
    fs, s11 = er.read_s11_modelled(
        data_root / "edges/receiver_cal/edges2_lowband_2015/s11_modelled_alan.txt"
    )
    np.testing.assert_allclose(fs, alan.freqs)
    assert np.max(np.abs(s11["lna"] - alan.gamma_rec)) < 1e-6
    # Alan's C1 goes with T_NS = 1000 K, edges-cal's reference with 350 K: same product
    ratio = ref.c1 * ref.t_load_ns / alan.at(ref.freqs).c1 / alan.t_load_ns
    assert np.ptp(ratio) < 2e-3 and abs(np.mean(ratio) - 1) < 0.005
    with pytest.raises(er.ReceiverCalError, match="covers"):
        alan.at(np.array([120e6]))
    with pytest.raises(er.ReceiverCalError, match="unknown receiver solution"):
        er.load_receiver_solution("nope")


@pytest.mark.data
def test_calibrate_and_decalibrate_invert_each_other(data_root: Path) -> None:
    sol = er.load_receiver_solution("edges2-lowband-2015").at(np.linspace(50e6, 100e6, 40))
    rng = np.random.default_rng(5)
    t_ant = rng.uniform(500.0, 8000.0, (7, 40))
    gammas = [0.0, 0.3 * np.exp(0.7j), 0.2 * np.exp(2j * np.pi * sol.freqs * 40e-9)]
    for gamma in gammas:
        p0, p1, p2 = er.decalibrate(t_ant, sol, gamma, raw_scale=3e-11, t_offset=450.0)
        np.testing.assert_allclose(er.calibrate_powers(p0, p1, p2, sol, gamma), t_ant, rtol=1e-10)
        q = (p0 - p1) / (p2 - p1)
        np.testing.assert_allclose(er.decalibrate_q(t_ant, sol, gamma), q, rtol=1e-10)
        tstar = er.tstar_from_q(q, sol.t_load_ns, sol.t_load)
        np.testing.assert_allclose(er.calibrate_tstar(tstar, sol, gamma), t_ant, rtol=1e-10)
        # the auto-correlation models are exactly linear in T_ant
        for r, data in (("q", q), ("p0", p0)):
            exp = er.expected_auto_model(sol, gamma, r, raw_scale=3e-11, t_offset=450.0)
            np.testing.assert_allclose(exp.G * t_ant + exp.n, data, rtol=1e-10)
            np.testing.assert_allclose(exp.trxr, exp.n / exp.G)
    # K factors: closed forms
    k1, k2, k3, k4 = er.k_factors(sol.gamma_rec, gammas[1])
    ga, gr = gammas[1], sol.gamma_rec
    np.testing.assert_allclose(k1, (1 - abs(ga) ** 2) / np.abs(1 - ga * gr) ** 2)
    np.testing.assert_allclose(k2, abs(ga) ** 2 / np.abs(1 - ga * gr) ** 2)
    np.testing.assert_allclose(
        np.hypot(k3, k4), abs(ga) / (np.sqrt(1 - abs(gr) ** 2) * np.abs(1 - ga * gr))
    )
    # matched antenna: G = 1 / (C1 T_NS), Trxr = C2 - T_L for Q
    exp = er.expected_auto_model(sol, 0.0, "q")
    np.testing.assert_allclose(exp.G, 1 / (sol.c1 * 1000.0))
    np.testing.assert_allclose(exp.trxr, sol.c2 - 300.0)


# ---------------------------------------------------------------------------------------
# lab loads
# ---------------------------------------------------------------------------------------
@pytest.mark.data
def test_edges2_loads_calibrate_to_their_thermistors(data_root: Path) -> None:
    res = er.check_edges2_loads()
    ref = res["edges_cal_reference"]
    for load, entry in ref.items():
        assert abs(entry["mean"] - entry["thermistor_K"]) < 0.6, load
        assert entry["rms_about_mean"] < 1.5, load
    alan = res["specal_alan"]
    # ambient, open and short cables are all at room temperature; the hot load is hot
    for load in ("open", "short"):
        assert abs(alan[load]["mean"] - alan["amb"]["mean"]) < 0.5
        assert alan[load]["rms_about_mean"] < 1.0
    assert alan["amb"]["mean"] == pytest.approx(ref["ambient"]["thermistor_K"], abs=0.5)
    assert alan["hot"]["mean"] == pytest.approx(ref["hot_load"]["thermistor_K"], abs=1.0)


@pytest.mark.data
def test_edges3_lab_loads_against_the_temperature_log(data_root: Path) -> None:
    res = er.lab_check_edges3()
    amb, hot = res["amb"], res["hot"]
    assert abs(amb["mean"] - amb["log_amb_load_K"]) < 4.0
    assert abs(hot["mean"] - hot["log_hot_load_K"]) < 6.0
    assert amb["rms_about_mean"] < 1.0 and hot["rms_about_mean"] < 1.0  # flat over 50-190 MHz
    assert hot["tstar"]["rms_about_mean"] > 3.0  # T* is not flat; the calibration makes it so
    # the solution's nominal noise source is 1000 K: with 400 K the hot load is far off
    wrong = er.lab_check_edges3(
        replace(er.load_receiver_solution("edges3-2022-316"), t_load_ns=400.0)
    )
    assert abs(wrong["hot"]["mean"] - hot["log_hot_load_K"]) > 30.0


@pytest.mark.data
def test_receiver01_lab_loads_two_load_calibration(data_root: Path) -> None:
    res = er.lab_check_receiver01()
    files = res["files"]
    amb0, hot0 = "Ambient_01_2019_329_23_01_16_lab.acq", "HotLoad_01_2019_330_23_38_05_lab.acq"
    # the load thermistors at the spectrum times (ambient ~22 C, hot load warming through 70 C)
    assert 293.0 < res["t_amb_K"] < 297.0 and 335.0 < res["t_hot_K"] < 350.0
    # uncalibrated T* (400 K / 300 K nominal): ambient reads near T_L, the hot load more
    assert abs(files[amb0]["tstar_400_300"]["mean"] - 300.0) < 3.0
    assert files[hot0]["tstar_400_300"]["mean"] > files[amb0]["tstar_400_300"]["mean"] + 10.0
    # the derived internal load sits at the receiver's 25 C
    assert res["t_load_eff"]["mean"] == pytest.approx(298.15, abs=3.0)
    assert res["t_ns_eff"]["min"] > 900.0 and res["t_ns_eff"]["max"] < 2200.0
    # the second ambient file (1 h later) reads the ambient temperature again
    assert files["Ambient_01_2019_330_00_00_00_lab.acq"]["two_load"]["mean"] == pytest.approx(
        res["t_amb_K"], abs=4.0
    )
    # the hot load, settled on later days, reads hot and flat within the noise
    for name in ("HotLoad_01_2019_331_00_00_23_lab.acq", "HotLoad_01_2019_333_00_00_01_lab.acq"):
        assert 380.0 < files[name]["two_load"]["mean"] < 415.0
        assert files[name]["two_load"]["rms_about_mean"] < 8.0


# ---------------------------------------------------------------------------------------
# an EDGES-like day
# ---------------------------------------------------------------------------------------
@pytest.mark.data
@pytest.mark.slow
def test_edges_like_day_recovers_the_receiver(data_root: Path, tmp_path: Path) -> None:
    day = er.simulate_edges_day(tmp_path, noise=True, seed=11)
    assert len(day.paths) == 4 and all(p.suffix == ".acq" for p in day.paths)
    assert np.ptp(day.lsts) > 23.5
    for r in ("q", "p0"):
        res = er.fit_edges_day(day, r=r)
        s = res.summary()
        assert abs(s["mean_pull_gain"]) < 0.3 and abs(s["mean_pull_trxr"]) < 0.3, (r, s)
        assert 0.8 < s["std_pull_gain"] < 1.25 and 0.8 < s["std_pull_trxr"] < 1.25, (r, s)
        assert s["max_abs_pull"] < 4.5, (r, s)
        assert 0.9 < s["median_reduced_chi2"] < 1.1, (r, s)
        assert s["rms_err_trxr_K"] < 2.0
    np.testing.assert_allclose(day.expected["q"].trxr, day.solution.c2 - 300.0)


@pytest.mark.data
def test_edges_like_day_with_a_real_antenna_reflection(data_root: Path, tmp_path: Path) -> None:
    s11 = er.read_s11_csv(data_root / "edges/receiver_cal/edges3_2022_316/s11ant.csv")
    day = er.simulate_edges_day(
        tmp_path, noise=False, gamma_ant=s11, freq_range=(60e6, 100e6), n_times=24, n_files=2
    )
    matched = er.expected_auto_model(day.solution, 0.0, "q")
    assert np.min(np.abs(day.expected["q"].G / matched.G - 1)) > 0.02  # the reflection matters
    for r in ("q", "p0"):
        res = er.fit_edges_day(day, r=r)
        assert np.max(np.abs(res.rel_err_gain)) < 1e-5  # ACQ keeps 1e-5 dB
        assert np.max(np.abs(res.err_trxr)) < 0.02
