"""The flagging stage of a calibration (autocal.pipeline.flagging): before the fit, in the
summary and in the products; ``rfi_flagging=False`` turns it off."""

from __future__ import annotations

import dataclasses

import h5py
import numpy as np
import pytest
from pyuvdata import UVCal

from autocal.cli.main import main
from autocal.fit.solve import FLAG_BAND_EDGE, FLAG_RFI
from autocal.pipeline.calibrate import read, read_summary, run_calibration
from autocal.pipeline.config import CalibrationConfig
from autocal.simulate.mock import SimulationConfig, simulate

SIM = SimulationConfig(
    beam="dipole",
    antennas=[0],
    pols=["ee"],
    channel_width_khz=1000.0,
    duration_h=12.0,
    cadence_s=900.0,
    gain="a",
    seed=4,
)
HERA_116 = [f"hera/autos/zen.2458116.{s}.HH.uvh5" for s in ("30448", "31193", "31939")]


def test_rfi_spikes_do_not_reach_the_fit_and_the_switch_turns_it_off(tmp_path) -> None:
    """Strong spikes in one channel of a simulated night: flagged before the fit, that
    channel's G stays at the clean fit's (within its error) and the flags are counted;
    with rfi_flagging off the same spikes pull G far off."""
    obs, _ = simulate(SIM)
    channel = obs.nfreq // 2
    data = obs.data.copy()
    data[0, 0, ::4, channel] *= 1.5  # intermittent narrow-band RFI, a quarter of the time
    hit = dataclasses.replace(obs, data=data)
    config = CalibrationConfig(inputs=["sim"], beam="dipole", products=["hdf5"])
    clean = run_calibration(config, None, observation=obs).solution
    flagged = run_calibration(config, tmp_path / "on", observation=hit)
    off = run_calibration(
        config.model_copy(update={"rfi_flagging": False}), tmp_path / "off", observation=hit
    )
    g_clean, g_on = clean.G[0, 0, channel], flagged.solution.G[0, 0, channel]
    g_off = off.solution.G[0, 0, channel]
    sigma = flagged.solution.sigma_G[0, 0, channel]
    assert abs(g_on - g_clean) < 3 * sigma
    assert abs(g_off - g_clean) > 5 * abs(g_on - g_clean)
    assert np.array_equal(obs.data, simulate(SIM)[0].data)  # the caller's data untouched

    counts = read_summary(tmp_path / "on")["rfi_flagging"]
    assert counts["applied"] and counts["samples"]["rfi_frequency"] >= hit.ntime // 4
    assert read_summary(tmp_path / "off")["rfi_flagging"]["applied"] is False
    provenance = flagged.solution.config["provenance"]["rfi_flagging"]
    assert provenance == counts


def test_integrations_flagged_whole_are_flagged_at_their_times_in_the_products(tmp_path):
    """A broad-band burst flags its integration before the fit; the solution records it
    (time_flags, also in solution.h5) and the per-time calh5 flags that time in every
    channel, the other times only where the channel is flagged."""
    from autocal.io.products import read_solution

    obs, _ = simulate(SIM)
    burst = obs.ntime // 3
    data = obs.data.copy()
    data[:, :, burst] *= 1.2
    hit = dataclasses.replace(obs, data=data)
    config = CalibrationConfig(inputs=["sim"], beam="dipole", products=["hdf5", "calh5"])
    result = run_calibration(config, tmp_path, observation=hit)
    tflags = result.solution.time_flags
    assert tflags is not None and tflags[0, 0].tolist() == [t == burst for t in range(obs.ntime)]
    assert np.array_equal(read_solution(tmp_path / "solution.h5").time_flags, tflags)
    uvc = UVCal.from_file(str(tmp_path / "solution.calh5"))
    flags = uvc.flag_array[0, :, :, 0]  # (F, T) of antenna 0, ee
    assert flags[:, burst].all()
    others = np.delete(flags, burst, axis=1)
    channels = np.broadcast_to(result.solution.flags[0, 0][:, None], others.shape)
    np.testing.assert_array_equal(others, channels)
    assert not others.all()


@pytest.mark.data
@pytest.mark.slow
def test_real_band_edges_and_rfi_are_in_the_summary_and_the_products(data_root, tmp_path):
    """HERA 2458116, antenna 23: the zeroed and rolled-off ends of the band and the RFI
    channels (ORBCOMM near 137 MHz among them) are flagged before the fit; the quality
    block, calfits flag_array and solution.h5 flag_reason all carry them."""
    out = tmp_path / "cal"
    code = main(
        [
            "calibrate",
            *[str(data_root / f) for f in HERA_116],
            "--antennas",
            "23",
            "--products",
            "calfits,hdf5",
            "--out",
            str(out),
        ]
    )
    assert code == 0
    summary = read_summary(out)
    flagging = summary["rfi_flagging"]
    reasons = summary["quality"]["reasons"]
    assert flagging["band_edge_channels"] > 50 and flagging["rfi_channels"] >= 1
    # the flagging's reads are counted beside the fit's own: its first read decodes the
    # files, its second and the fit's passes replay the decoded blocks (small observation)
    fit_io, flag_io = summary["execution"]["io"], flagging["io"]
    assert flag_io["bytes_decoded"] > 0 and flag_io["blocks_from_memory"] == flag_io["blocks"]
    assert fit_io["bytes_read"] == 0 and fit_io["files"] == 0
    assert fit_io["blocks_from_memory"] == summary["execution"]["passes"] * flag_io["blocks"]
    assert reasons["band edge"] >= flagging["band_edge_channels"]
    with h5py.File(out / "solution.h5") as h5:
        flag_reason = h5["flag_reason"][()]
        freqs = h5["freqs"][()]
        pols = [p.decode() if isinstance(p, bytes) else str(p) for p in h5["pols"][()]]
    assert np.count_nonzero(flag_reason == FLAG_BAND_EDGE) == reasons["band edge"]
    assert np.count_nonzero(flag_reason == FLAG_RFI) == reasons.get("RFI", 0)
    assert flag_reason[..., 0].all() and flag_reason[..., -1].all()  # the zeroed ends
    orbcomm = (freqs > 137.0e6) & (freqs < 138.0e6)
    assert np.any(flag_reason[..., orbcomm] == FLAG_RFI)

    cal = UVCal.from_file(str(out / "solution.calfits"))
    for j, code in enumerate(cal.jones_array):  # flagged at every integration
        pol = {-5: "ee", -6: "nn"}[int(code)]
        assert np.array_equal(
            cal.flag_array[0, :, :, j].all(axis=1), flag_reason[0, pols.index(pol)] != 0
        )

    off_args = ["--antennas", "23", "--no-rfi-flagging", "--products", "hdf5"]
    assert (
        main(["calibrate", str(data_root / HERA_116[0]), *off_args, "--out", str(tmp_path / "off")])
        == 0
    )
    off = read_summary(tmp_path / "off")
    assert off["rfi_flagging"]["applied"] is False
    assert "band edge" not in off["quality"]["reasons"]


@pytest.mark.data
def test_read_keeps_the_data_flags_only(data_root) -> None:
    """autocal.read is a reader: it adds no RFI flags (the calibration does)."""
    obs = read(data_root / HERA_116[0], antennas=[23])
    assert not obs.flags.any()


@pytest.mark.data
def test_channels_without_usable_data_are_not_called_band_edges(data_root, tmp_path) -> None:
    """A live audit (2026-11-29): all-zero (or NaN, or negative) autos were reported as
    "2048 band edge"; such channels now have their own reason, in the solution and the
    flagging's counts."""
    import h5py

    from autocal.fit.solve import FLAG_NO_DATA

    path = tmp_path / "zen.2458116.31939.HH.uvh5"
    path.write_bytes((data_root / "hera" / "autos" / path.name).read_bytes())
    with h5py.File(path, "r+") as h5:
        vis = h5["Data/visdata"]
        values = vis[()]
        values[:, 400:500] = 0.0  # channels without any usable sample
        values[:, 600:610] = np.nan
        vis[...] = values
    config = CalibrationConfig(inputs=[str(path)], beam="hera", products=["hdf5"], nside=32)
    result = run_calibration(config, tmp_path / "out")
    reason = result.solution.flag_reason
    assert np.all(reason[..., 400:500] == FLAG_NO_DATA)
    assert np.all(reason[..., 600:610] == FLAG_NO_DATA)
    assert not np.any(reason[..., 400:500] == FLAG_BAND_EDGE)
    counts = result.summary["rfi_flagging"]
    with h5py.File(path, "r") as h5:  # the file's own dead channels (zeros, flags) count too
        auto = h5["Header/ant_1_array"][()] == h5["Header/ant_2_array"][()]
        power = h5["Data/visdata"][()][auto].real
        unusable = ~(np.isfinite(power) & (power > 0)) | h5["Data/flags"][()][auto]
    dead = unusable.all(axis=0).T  # (pol, channel): no usable sample at any integration
    assert dead[:, 400:500].all() and dead[:, 600:610].all()
    assert counts["no_data_channels"] == int(dead.any(axis=0).sum())
    assert np.all(reason[0][dead] == FLAG_NO_DATA)
    assert counts["samples"]["no_data"] == int(dead.sum()) * unusable.shape[0]
    assert "no usable data" in result.summary["quality"]["message"]


@pytest.mark.data
def test_a_polarisation_asked_for_by_its_alias_is_named_as_the_file_names_it(
    data_root, tmp_path
) -> None:
    """A live audit (2026-11-29): ``pols=["xx"]`` of an ee/nn file (x pointing east) gave a
    solution, and a service history, of pol ``xx`` beside ``ee``: one feed, two names."""
    path = data_root / "hera" / "autos" / "zen.2458116.31939.HH.uvh5"
    config = CalibrationConfig(inputs=[str(path)], pols=["xx"], products=[], nside=32)
    result = run_calibration(config, None)
    assert tuple(result.solution.pols) == ("ee",)
