"""``autocal apply``: calibrate UVH5 visibilities with a gain solution (pyuvdata)."""

from __future__ import annotations

import argparse
from pathlib import Path

from autocal.cli.args import output_file


def add(sub: argparse._SubParsersAction) -> None:
    """Register the command."""
    p = sub.add_parser(
        "apply",
        help="apply a calfits/calh5 solution to UVH5 data; write a calibrated UVH5 file",
        description="Calibrate UVH5 visibilities (the autos and any cross-correlations "
        "present) with a gain solution -- solution.calh5 or solution.calfits of autocal "
        "calibrate, or any per-channel gain calfits/calh5 -- through pyuvdata's uvcalibrate: "
        "V_cal = V / (g_i g_j^*), flags of the gains propagated, provenance in the history. "
        "With autocal's gains the calibrated autos are antenna temperatures in kelvin "
        "(vis_units 'K str'). A solution whose antennas, polarisations, channels or times "
        "do not cover the data is refused. The output is written atomically; an existing "
        "output is replaced only with --overwrite and only if autocal apply wrote it.",
    )
    p.add_argument("solution", type=Path, help="gain solution (calfits or calh5)")
    p.add_argument("data", type=Path, nargs="+", help="UVH5 file(s) of one observation")
    p.add_argument("--out", required=True, type=output_file, help="calibrated UVH5 file to write")
    p.add_argument(
        "--antennas",
        help="comma-separated antenna numbers: calibrate only the baselines between them "
        "(default: every antenna of the data, which the solution must cover)",
    )
    p.add_argument(
        "--freq-range",
        metavar="LOW:HIGH",
        help="MHz (a unit suffix, e.g. 1.1e8Hz, is accepted): calibrate only the data's "
        "channels in this range, e.g. the band of a solution that covers part of the data's; "
        "the output holds those channels only (default: every channel, which the solution "
        "must cover)",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace --out if it is a calibrated UVH5 file autocal apply wrote",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the command."""
    from autocal.cli.args import parse_freq_pair, parse_int_list
    from autocal.pipeline.apply import apply_solution

    antennas = None if args.antennas is None else parse_int_list(args.antennas, "antennas")
    result = apply_solution(
        args.solution,
        args.data,
        args.out,
        antennas=antennas,
        freq_range_mhz=parse_freq_pair(args.freq_range, "freq-range"),
        overwrite=args.overwrite,
    )
    print(
        f"calibrated {result.nbls} baseline(s) x {result.ntimes} integration(s) x "
        f"{result.nfreqs} channel(s), pols {','.join(result.pols)}; vis_units "
        f"{result.vis_units!r}; {100 * result.flagged_fraction:.1f}% flagged"
    )
    print(f"wrote {result.path}")
    return 0
