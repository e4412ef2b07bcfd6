"""``autocal calibrate``: calibrate one observation and write its products."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from autocal.commands import (
    CliError,
    parse_int_list,
    parse_pair,
    parse_str_list,
    validation_message,
)


def add(sub: argparse._SubParsersAction) -> None:
    """Register the command."""
    p = sub.add_parser(
        "calibrate",
        help="fit G and Trxr to the autos of one observation and write calibration products",
        description="Calibrate the auto-correlations of one observation (UVH5 files or "
        "Miriad folders, consecutive in time) against sky x beam + CMB + ground: fit "
        "G (|g| = sqrt(G)) and Trxr per antenna, polarisation and channel, streaming the "
        "files, and write solution.calh5 / solution.calfits (pyuvdata UVCal), solution.h5 "
        "(every array, configuration and provenance), PNG plots and summary.json to --out.",
    )
    p.add_argument("inputs", nargs="+", type=Path, help="UVH5 files or Miriad folders")
    p.add_argument("--sky", default="gsm2008", help="sky model (default gsm2008)")
    p.add_argument("--beam", default="hera", help="beam: hera | dipole | airy | PATH (hera)")
    p.add_argument("--tgnd", type=float, default=300.0, help="ground temperature K (300)")
    p.add_argument("--nside", type=int, default=64, help="HEALPix resolution of Tsky (64)")
    p.add_argument("--model", default="constant", choices=["constant", "legendre"])
    p.add_argument("--order", type=int, default=1, help="Legendre order (1)")
    p.add_argument("--weights", default="radiometer", choices=["radiometer", "identity"])
    p.add_argument("--antennas", help="comma-separated antenna numbers (default all)")
    p.add_argument("--pols", help="comma-separated polarisations (default ee,nn)")
    p.add_argument("--freq-range", help="LOW:HIGH in MHz")
    p.add_argument("--lst-range", help="START:STOP in hours (START > STOP wraps)")
    p.add_argument(
        "--products",
        default="calh5,hdf5,png",
        help="comma-separated of calh5, calfits, hdf5, png (default calh5,hdf5,png)",
    )
    p.add_argument(
        "--reference",
        nargs="+",
        type=Path,
        help="reference gains (calfits/calh5, abscal or redcal) to compare |g| with",
    )
    p.add_argument("--format", default="auto", choices=["auto", "uvh5", "miriad"])
    p.add_argument(
        "--dask",
        metavar="SCHEDULER",
        help="map the files over a Dask cluster: a scheduler address (tcp://HOST:8786) or "
        "'local' for a local cluster (same solution as the default in-process run)",
    )
    p.add_argument(
        "--dask-workers",
        type=int,
        metavar="N",
        help="worker processes of --dask local (default: the number of CPUs)",
    )
    p.add_argument(
        "--block-size",
        type=int,
        metavar="N",
        help="integrations read per block (default: about 8 M values; bounds the memory)",
    )
    p.add_argument("--out", required=True, type=Path, help="output folder")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the command."""
    from pydantic import ValidationError
    from tqdm import tqdm

    from autocal.pipeline import CalibrationConfig, run_calibration

    try:
        config = CalibrationConfig(
            inputs=[str(p) for p in args.inputs],
            input_format=args.format,
            sky=args.sky,
            beam=args.beam,
            tgnd_k=args.tgnd,
            nside=args.nside,
            model=args.model,
            order=args.order,
            weights=args.weights,
            antennas=parse_int_list(args.antennas, "antennas") if args.antennas else None,
            pols=parse_str_list(args.pols, "pols") if args.pols else None,
            freq_range_mhz=parse_pair(args.freq_range, "freq-range", "MHz"),
            lst_range_h=parse_pair(args.lst_range, "lst-range", "hours"),
            products=parse_str_list(args.products, "products"),
            reference=[str(p) for p in args.reference] if args.reference else None,
        )
    except ValidationError as err:
        raise CliError(validation_message(err)) from None
    if args.dask_workers is not None and args.dask_workers < 1:
        raise CliError("--dask-workers must be at least 1")
    if args.dask_workers is not None and args.dask is None:
        raise CliError("--dask-workers needs --dask local")
    if args.block_size is not None and args.block_size < 1:
        raise CliError("--block-size must be at least 1 integration")
    with tqdm(total=100, desc="calibrate", unit="%", disable=None) as bar:

        def progress(fraction: float, message: str) -> None:
            bar.n = round(100 * min(fraction, 1.0))
            bar.set_postfix_str(message[-60:])
            bar.refresh()

        result = run_calibration(
            config,
            args.out,
            progress=progress,
            dask_scheduler=args.dask,
            dask_workers=args.dask_workers,
            block_size=args.block_size,
        )
    print(json.dumps(result.summary["solution"], indent=2))
    for name, path in result.products.items():
        print(f"wrote {name}: {path}")
    return 0
