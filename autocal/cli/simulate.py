"""``autocal simulate``: a mock observation written as a genuine UVH5 file."""

from __future__ import annotations

import argparse
from pathlib import Path

from autocal.cli.args import (
    CliError,
    check_output_file,
    output_file,
    parse_freq_mhz,
    parse_int_list,
    parse_str_list,
    validation_message,
)

#: Largest bare value (MHz) of each frequency option, and the option's former unit in which
#: a larger bare value is read (with a note); ``None``: a larger value is an error.
BARE_LIMIT_MHZ: dict[str, tuple[float, str | None]] = {
    "freq-start": (1e4, None),
    "freq-stop": (1e4, None),
    "channel-width": (10.0, "kHz"),
    "noise-dnu": (100.0, "Hz"),
}


def add(sub: argparse._SubParsersAction) -> None:
    """Register the command."""
    p = sub.add_parser(
        "simulate",
        help="write mock auto-correlations R = G(t) (Tsky + Trxr) + noise as UVH5",
        description="Simulate auto-correlations for a beam, sky and site and write them as "
        "a UVH5 file (HERA antenna positions and metadata, autos only, LSTs consistent "
        "with the JDs) plus a truth side-car HDF5 file. Defaults: the paper's reference "
        "setup (110-190 MHz in 250 kHz channels, 5-minute sampling over 24 h of LST, "
        "G = 1, Trxr = 150 K, noise with dnu = 5 kHz and dt = 1 s).",
    )
    p.add_argument("--sky", default="gsm2008", help="true sky model (default gsm2008)")
    p.add_argument("--beam", default="hera", help="true beam: hera | dipole | airy | PATH")
    p.add_argument("--beam-error", action="store_true", help="apply the paper's beam error model")
    p.add_argument("--site", default="hera", help="hera | edges | LAT,LON[,ALT]")
    p.add_argument("--telescope", default="HERA", help="telescope name written to the file")
    p.add_argument("--antennas", default="0", help="comma-separated antenna numbers (0)")
    p.add_argument("--pols", default="ee", help="comma-separated polarisations (ee)")
    p.add_argument("--freq-start", default="110", help="first channel, MHz (110)")
    p.add_argument("--freq-stop", default="190", help="last channel, MHz (190)")
    p.add_argument(
        "--channel-width",
        default="0.25",
        help="channel width, MHz (0.25; a unit suffix such as 250kHz is accepted; a bare "
        "value above 10 is read as kHz, the former unit, with a note)",
    )
    p.add_argument("--lst-start", type=float, default=0.0, help="first LST, hours")
    p.add_argument("--duration", type=float, default=24.0, help="LST hours covered (24)")
    p.add_argument("--cadence", type=float, default=300.0, help="sidereal seconds per sample")
    p.add_argument("--jd", type=float, default=2458098.0, help="start at or after this JD")
    p.add_argument("--gain", default="constant", choices=["constant", "a", "b", "c"])
    p.add_argument("--gain-amplitude", type=float, default=0.1, help="drift amplitude (0.1)")
    p.add_argument("--g0", type=float, default=1.0, help="mean gain G0 (1)")
    p.add_argument("--bandpass", default="flat", choices=["flat", "hera-h1c"])
    p.add_argument("--trxr", type=float, default=150.0, help="receiver temperature, K")
    p.add_argument("--tgnd", type=float, default=300.0, help="ground temperature, K")
    p.add_argument(
        "--noise-dnu",
        default="0.005",
        help="noise bandwidth, MHz (0.005; a unit suffix such as 5kHz is accepted; a bare "
        "value above 100 is read as Hz, the former unit, with a note)",
    )
    p.add_argument("--noise-dt", type=float, default=1.0, help="noise integration, s (1)")
    p.add_argument("--no-noise", action="store_true", help="noiseless data")
    p.add_argument("--seed", type=int, default=0, help="noise seed (0)")
    p.add_argument("--nside", type=int, default=64, help="HEALPix resolution of Tsky (64)")
    p.add_argument("--out", required=True, type=output_file, help="output .uvh5 file")
    p.add_argument("--truth", type=Path, help="truth side-car (default OUT.truth.h5)")
    p.add_argument("--overwrite", action="store_true", help="replace existing files")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the command."""
    from pydantic import ValidationError

    from autocal.io.simtruth import write_truth
    from autocal.io.uvh5 import write_uvh5
    from autocal.simulate.mock import SimulationConfig, simulate

    if args.out.suffix.lower() != ".uvh5":
        raise CliError(f"--out {args.out}: give a file name ending in .uvh5")
    truth_path = args.truth or args.out.with_suffix(".truth.h5")
    if truth_path.expanduser().absolute() == args.out.expanduser().absolute():
        raise CliError(f"--truth {truth_path} is --out itself: give the truth its own file")
    for path in (args.out, truth_path):
        if path.exists() and not args.overwrite:
            raise CliError(f"{path} exists; pass --overwrite to replace it")
        check_output_file(path)  # before simulating, not after writing the data
    freq = {
        name: parse_freq_mhz(getattr(args, name.replace("-", "_")), name, limit, legacy)
        for name, (limit, legacy) in BARE_LIMIT_MHZ.items()
    }
    try:
        config = SimulationConfig(
            sky=args.sky,
            beam=args.beam,
            beam_error=args.beam_error,
            site=args.site,
            telescope=args.telescope,
            antennas=parse_int_list(args.antennas, "antennas"),
            pols=parse_str_list(args.pols, "pols"),
            freq_start_mhz=freq["freq-start"],
            freq_stop_mhz=freq["freq-stop"],
            channel_width_khz=freq["channel-width"] * 1e3,
            lst_start_h=args.lst_start,
            duration_h=args.duration,
            cadence_s=args.cadence,
            jd_start=args.jd,
            gain=args.gain,
            gain_amplitude=args.gain_amplitude,
            g0=args.g0,
            bandpass=args.bandpass,
            trxr_k=args.trxr,
            tgnd_k=args.tgnd,
            noise=not args.no_noise,
            noise_dnu_hz=freq["noise-dnu"] * 1e6,
            noise_dt_s=args.noise_dt,
            seed=args.seed,
            nside=args.nside,
        )
    except ValidationError as err:
        raise CliError(validation_message(err)) from None
    obs, truth = simulate(config, progress=None)
    write_uvh5(
        obs,
        args.out,
        history=f"autocal simulate: {config.model_dump_json()}",
        overwrite=args.overwrite,
    )
    write_truth(truth_path, truth, obs)
    nant, npol, ntime, nfreq = obs.shape
    print(
        f"wrote {args.out} ({nant} antennas x {npol} pols x {ntime} times x {nfreq} channels, "
        f"LST {obs.lsts[0]:.3f}-{obs.lsts[-1]:.3f} h, JD {obs.jds[0]:.5f}-{obs.jds[-1]:.5f})"
    )
    print(f"wrote {truth_path} (true gain, Trxr and Tsky)")
    return 0
