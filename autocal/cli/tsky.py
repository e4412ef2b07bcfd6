"""``autocal tsky``: a beam-weighted sky temperature table Tsky(nu, LST)."""

from __future__ import annotations

import argparse

from autocal.cli.args import (
    BEAM_HELP,
    SKY_HELP,
    CliError,
    check_output_file,
    output_file,
    parse_freq_range_mhz,
    parse_range,
)


def add(sub: argparse._SubParsersAction) -> None:
    """Register the command."""
    p = sub.add_parser(
        "tsky",
        help="compute a Tsky(nu, LST) table",
        description="Compute the beam-weighted sky temperature Tsky(nu, LST) of a drift-scan "
        "antenna (CMB and ground pickup included) with the ring-FFT engine, write it "
        "to HDF5 and optionally plot it. Results are cached on disk.",
    )
    p.add_argument(
        "--sky",
        default="gsm2008",
        help=f"{SKY_HELP} (default gsm2008)",
    )
    p.add_argument(
        "--beam",
        default="dipole",
        help=f"{BEAM_HELP}; default dipole",
    )
    p.add_argument("--pol", default="ee", choices=["ee", "nn"], help="polarisation")
    p.add_argument("--site", default="hera", help="hera | edges | LAT,LON[,ALT]")
    p.add_argument(
        "--freqs",
        default="100:200:101",
        help="frequencies START:STOP:N in MHz, or a list; a unit suffix (150MHz, 1.5e8Hz) "
        "is accepted; a bare value above 1e4 is read as Hz, the former unit, with a note "
        "(default 100:200:101)",
    )
    p.add_argument(
        "--lsts", default="0:24:97", help="LSTs START:STOP:N in hours, or a list (default 0:24:97)"
    )
    p.add_argument("--nside", type=int, default=64, help="HEALPix resolution (default 64)")
    p.add_argument("--tgnd", type=float, default=300.0, help="ground temperature K (300)")
    p.add_argument(
        "--epoch",
        default="J2000",
        help="epoch of the equatorial frame: J2000, ISO date or JD (default J2000)",
    )
    p.add_argument(
        "--horizon-width",
        type=float,
        default=2.0,
        help="width of the soft horizon in degrees (default 2; 0 = hard cut)",
    )
    p.add_argument(
        "--method",
        default="fft",
        choices=["fft", "brute"],
        help="fft (fast engine, default) or brute (per-LST reference)",
    )
    p.add_argument("--no-cache", action="store_true", help="neither read nor write the cache")
    p.add_argument("--out", required=True, type=output_file, help="output HDF5 file")
    p.add_argument("--plot", type=output_file, help="also write a PNG plot here")
    p.add_argument("--overwrite", action="store_true", help="replace existing files")
    p.set_defaults(func=run)


#: Largest HEALPix resolution (as ``autocal diagnose``): 8192 is 805 M pixels per map.
MAX_NSIDE = 8192
#: Largest Tsky table (channels x LSTs; float64, and the engine's work arrays): ~1.6 GB.
MAX_TABLE_VALUES = 200_000_000


def run(args: argparse.Namespace) -> int:
    """Run the command."""
    from autocal.io.tskyfile import write_tsky
    from autocal.plots import plot_tsky
    from autocal.tsky.compute import compute_tsky

    if args.out.suffix.lower() not in {".h5", ".hdf5"}:
        raise CliError(f"--out {args.out}: the Tsky table is HDF5; use a .h5 file name")
    if args.plot is not None and args.plot.suffix.lower() != ".png":
        raise CliError(f"--plot {args.plot}: the plot is a PNG image; use a .png file name")
    for path in (args.out, args.plot):
        if path is None:
            continue
        if path.exists() and not args.overwrite:
            raise CliError(f"{path} exists; pass --overwrite to replace it")
        check_output_file(path)
    if not 0.0 <= args.horizon_width <= 30.0:
        raise CliError(
            f"--horizon-width {args.horizon_width:g}: the soft horizon's width is 0 (a hard "
            "cut) to 30 degrees"
        )
    if not 1 <= args.nside <= MAX_NSIDE or args.nside & (args.nside - 1):
        raise CliError(f"--nside {args.nside}: a power of two from 1 to {MAX_NSIDE}")
    # MHz on the command line; the engine works in Hz
    freqs = parse_freq_range_mhz(args.freqs, "freqs", legacy_unit="Hz") * 1e6
    lsts = parse_range(args.lsts, "lsts", "hours")
    if freqs.size * lsts.size > MAX_TABLE_VALUES:
        raise CliError(
            f"{freqs.size} channels x {lsts.size} LSTs = {freqs.size * lsts.size:.3g} values, "
            f"more than the {MAX_TABLE_VALUES:.0e} of a table held in memory: ask for fewer"
        )
    result = compute_tsky(
        args.sky,
        args.beam,
        args.site,
        freqs,
        lsts,
        tgnd=args.tgnd,
        nside=args.nside,
        epoch=args.epoch,
        pol=args.pol,
        horizon_width_deg=args.horizon_width,
        method=args.method,
        cache=not args.no_cache,
        progress=None,
    )
    write_tsky(args.out, result)
    print(
        f"wrote {args.out} ({result.lsts.size} LSTs x {result.freqs.size} channels, "
        f"Tsky {result.tsky.min():.1f}-{result.tsky.max():.1f} K)"
    )
    if args.plot:
        plot_tsky(result, args.plot)
        print(f"wrote {args.plot}")
    return 0
