"""``autocal compare``: autos-derived gains against cross-correlation calibration gains."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from autocal.cli.args import (
    CliError,
    check_output_folder,
    output_folder,
    parse_freq_mhz,
    parse_int_list,
    parse_str_list,
)


def add(sub: argparse._SubParsersAction) -> None:
    """Register the command."""
    p = sub.add_parser(
        "compare",
        help="compare |g| from the autos with reference gains (calfits/calh5)",
        description="Compare the gain amplitude |g| = sqrt(G) of an autocal solution "
        "product with gains from cross-correlation calibration. Absolute (abscal, "
        "Jy-referenced) gains are converted to kelvin units with the beam solid angle, "
        "|g_K| = |g_Jy| sqrt(2 k_B Omega_A / lambda^2 * 1e26); relative (redcal/omnical) "
        "gains are compared in shape after dividing each by its mean over frequency. "
        "Writes compare.json (summary), compare.png (ratio with 2-sigma band, delay "
        "spectrum) and compare.h5 (arrays) into --out.",
    )
    p.add_argument("solution", type=Path, help="autocal solution product (.h5)")
    p.add_argument(
        "reference",
        type=Path,
        nargs="+",
        help="reference gains: one calfits/calh5 file or consecutive files of one run",
    )
    p.add_argument("--out", required=True, type=output_folder, help="output folder")
    p.add_argument(
        "--smooth-mhz",
        default=None,
        help="smooth the reference along frequency with a Gaussian kernel of this FWHM (MHz)",
    )
    p.add_argument("--antennas", help="comma-separated antenna numbers (default: common ones)")
    p.add_argument("--pols", help="comma-separated polarisations (default: common ones)")
    p.add_argument(
        "--mode",
        choices=["auto", "absolute", "relative"],
        default="auto",
        help="absolute (unit conversion) or relative (shape) comparison; auto decides from "
        "the reference (gain_scale, |g| scale)",
    )
    p.add_argument(
        "--beam",
        default=None,
        help="beam for Omega_A: hera (Fagnoni beamfits), dipole, airy, or a beam file "
        "(default: the beam recorded in the solution, else hera)",
    )
    p.add_argument("--nside", type=int, default=None, help="HEALPix nside of the Omega_A integral")
    p.add_argument("--overwrite", action="store_true", help="replace existing output files")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the command."""
    check_output_folder(args.out)
    from autocal.compare.comparison import compare
    from autocal.compare.report import OUTPUT_NAMES, write_comparison
    from autocal.io.calsol_read import read_reference_gains
    from autocal.io.products import read_solution

    if args.smooth_mhz is not None:
        args.smooth_mhz = parse_freq_mhz(args.smooth_mhz, "smooth-mhz")
    if args.smooth_mhz is not None and not args.smooth_mhz > 0:
        raise CliError(f"--smooth-mhz must be positive (MHz), got {args.smooth_mhz}")
    if args.nside is not None and (not 2 <= args.nside <= 8192 or args.nside & (args.nside - 1)):
        raise CliError(f"--nside {args.nside}: a power of two from 2 to 8192")
    omega = [f"--{n}" for n in ("beam", "nside") if getattr(args, n) is not None]
    if args.mode == "relative" and omega:
        raise CliError(
            f"{', '.join(omega)}: the beam's solid angle converts units in an absolute "
            "comparison; a relative (shape) one does not use it: drop it or use --mode absolute"
        )
    if args.out.exists() and not args.out.is_dir():
        raise CliError(f"--out {args.out} exists and is not a folder")
    if not args.overwrite:
        existing = [args.out / n for n in OUTPUT_NAMES.values() if (args.out / n).exists()]
        if existing:
            raise CliError(
                f"{', '.join(str(e) for e in existing)} exist(s); pass --overwrite to replace"
            )
    antennas = parse_int_list(args.antennas, "antennas") if args.antennas else None
    pols = parse_str_list(args.pols, "pols") if args.pols else None
    solution = read_solution(args.solution)
    reference = read_reference_gains(
        args.reference,
        absolute={"auto": None, "absolute": True, "relative": False}[args.mode],
    )
    result = compare(
        solution,
        reference,
        antennas=antennas,
        pols=pols,
        smooth_mhz=args.smooth_mhz,
        mode=None if args.mode == "auto" else args.mode,
        beam=args.beam,
        nside=args.nside,
    )
    paths = write_comparison(result, args.out, overwrite=args.overwrite)
    if result.mode == "relative" and omega:  # --mode auto found a relative reference
        print(
            f"autocal compare: note: {', '.join(omega)} not used: the reference is relative "
            "(a shape comparison needs no beam solid angle)",
            file=sys.stderr,
        )
    print(
        f"{result.mode} comparison of {len(result.antennas)} antenna(s) x {len(result.pols)} pol(s)"
    )
    for row in result.summary["per_antenna_pol"]:
        mean = row.get("ratio_mean")
        rms = row.get("ratio_rms")
        text = (
            f"mean ratio {mean:.4f}, rms {rms:.4f}, {row['n_compared']} channels"
            if mean is not None
            else "no channels compared"
        )
        print(f"  ant {row['antenna']} {row['pol']}: {text}")
    for kind, path in paths.items():
        print(f"wrote {path} ({kind})")
    return 0
