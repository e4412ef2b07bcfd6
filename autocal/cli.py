"""The ``autocal`` command line.

Commands (one module each in :mod:`autocal.commands`)
-----------------------------------------------------
``autocal calibrate``
    Fit G and Trxr to the autos of one observation; write calh5/calfits, HDF5, plots.
``autocal diagnose``
    Name the physical effects missing from the model, add them, show the gap shrink.
``autocal compare``
    |g| from autos against cross-correlation (abscal or redcal/omnical) gains.
``autocal tsky``
    Beam-weighted sky temperature table Tsky(nu, LST) to HDF5 (and a plot).
``autocal simulate``
    Mock auto-correlations written as a UVH5 file, with a truth side-car.
``autocal paper``
    The paper's simulation scenarios: summary table, JSON results and figures.
``autocal info``
    Version, data folder, cache folder, and which sky models and beams are available.
``autocal serve``
    The REST job service (uvicorn running the FastAPI app factory).
``autocal worker``
    One job-worker process: claims queued jobs from the store and runs them.
``autocal nightly``
    Queue one calibration job per observation of a night (JD) or a watched folder.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence

from autocal.commands import CliError, parse_range

__all__ = ["CliError", "build_parser", "main", "parse_range"]

logger = logging.getLogger("autocal.cli")


def build_parser() -> argparse.ArgumentParser:
    """Build the argument parser."""
    from autocal import __version__
    from autocal.commands import (
        calibrate,
        compare,
        diagnose,
        info,
        nightly,
        paper,
        serve,
        simulate,
        tsky,
        worker,
    )

    parser = argparse.ArgumentParser(
        prog="autocal",
        description="Calibrate radio-telescope auto-correlations against sky models.",
    )
    parser.add_argument("--version", action="version", version=f"autocal {__version__}")
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="more log output (-v info, -vv debug)"
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for module in (
        calibrate,
        compare,
        diagnose,
        tsky,
        simulate,
        paper,
        info,
        serve,
        worker,
        nightly,
    ):
        module.add(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; return the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    level = [logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args))
    except (ValueError, FileExistsError, FileNotFoundError) as err:
        # Every autocal input error is a ValueError subclass with a message that says
        # what to do (sky, beam, Tsky, fit, observation, file-format and CLI errors).
        print(f"autocal {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
