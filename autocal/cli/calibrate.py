"""``autocal calibrate``: calibrate one observation and write its products."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from autocal.cli.args import CliError, check_output_folder, output_folder, validation_message
from autocal.cli.options import (
    add_calibration_arguments,
    calibration_settings,
    refuse_edges_options,
)


def add(sub: argparse._SubParsersAction) -> None:
    """Register the command."""
    p = sub.add_parser(
        "calibrate",
        help="fit G and Trxr to the autos of one observation and write calibration products",
        description="Calibrate the auto-correlations of one observation (UVH5 files, "
        "Miriad folders or EDGES ACQ / HDF5 spectra, consecutive in time) against "
        "sky x beam + CMB + ground: fit G (|g| = sqrt(G)) and Trxr per antenna, "
        "polarisation and channel, streaming the files, and write solution.calh5 / "
        "solution.calfits (pyuvdata UVCal), solution.h5 (every array, configuration and "
        "provenance), PNG plots and summary.json to --out. Options not given take the "
        "defaults shown (those of autocal.pipeline.config.CalibrationConfig and the REST API).",
    )
    p.add_argument(
        "inputs", nargs="+", type=Path, help="UVH5 files, Miriad folders or EDGES ACQ / HDF5 files"
    )
    add_calibration_arguments(p)
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
        "--readers",
        type=int,
        metavar="N",
        help="processes that read (decode) a night's UVH5 files, without Dask: 1 reads in "
        "this process; default: one per core for at least two files and 256 MiB on >= 4 "
        "cores (same solution)",
    )
    p.add_argument(
        "--block-size",
        type=int,
        metavar="N",
        help="integrations read per block (default: about 8 M values; bounds the memory)",
    )
    p.add_argument(
        "--out",
        required=True,
        type=output_folder,
        help="output folder, owned by autocal: a rerun replaces every product it wrote there "
        "(products this run does not write, e.g. an old comparison, are removed)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the command."""
    # Options checked here first: a usage error is reported before the science stack loads.
    check_output_folder(args.out)
    if args.dask_workers is not None and args.dask_workers < 1:
        raise CliError("--dask-workers must be at least 1")
    if args.dask_workers is not None and args.dask is None:
        raise CliError("--dask-workers needs --dask local")
    if args.readers is not None and args.readers < 1:
        raise CliError("--readers must be at least 1 (1: read in this process)")
    if args.readers is not None and args.dask is not None:
        raise CliError("--readers and --dask exclude each other: Dask workers read the files")
    if args.block_size is not None and args.block_size < 1:
        raise CliError("--block-size must be at least 1 integration")
    settings = calibration_settings(args)
    from pydantic import ValidationError
    from tqdm import tqdm

    from autocal.cli.quality import EXIT_FLAGGED, remove_stale
    from autocal.pipeline.calibrate import calibrate, read_summary
    from autocal.pipeline.config import CalibrationConfig

    refuse_edges_options(settings, args.inputs)
    try:
        config = CalibrationConfig(inputs=[str(p) for p in args.inputs], **settings)
    except ValidationError as err:
        raise CliError(validation_message(err)) from None
    with tqdm(total=100, desc="calibrate", unit="%", disable=None) as bar:

        def progress(fraction: float, message: str) -> None:
            bar.n = round(100 * min(fraction, 1.0))
            bar.set_postfix_str(message[-60:])
            bar.refresh()

        # autocal.calibrate: the notebook's, the service's and nightly's function
        calibrate(
            config,
            out=args.out,
            progress=progress,
            dask_scheduler=args.dask,
            dask_workers=args.dask_workers,
            block_size=args.block_size,
            readers=args.readers,
        )
    summary = read_summary(args.out)
    for path in remove_stale(args.out, summary["products"]):
        print(f"removed {path} (a product of an earlier run)")
    quality = summary["quality"]
    print(json.dumps(summary["solution"], indent=2))
    separation = summary.get("separation") or []
    shown = (
        separation
        if len(separation) <= 12
        else [e for e in separation if e["separation"] == "weak"][:12]
    )
    if len(separation) > 12:
        nweak = sum(e["separation"] == "weak" for e in separation)
        print(f"{nweak} of {len(separation)} antenna-pols separate G and n weakly; the first:")
    for entry in shown:
        print(entry["message"])
    for name, path in summary["products"].items():
        print(f"wrote {name}: {path}")
    if quality["status"] != "ok":
        what = "every channel" if quality["status"] == "fully_flagged" else "most channels"
        print(
            f"autocal calibrate: error: {what} flagged, no usable calibration: "
            f"{quality['message']} (products written; summary.json 'quality')",
            file=sys.stderr,
        )
        return EXIT_FLAGGED
    if quality["fully_flagged"]:
        print(f"autocal calibrate: warning: {quality['message']}", file=sys.stderr)
    return 0
