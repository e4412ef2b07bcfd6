"""The ``autocal`` command line.

Commands
--------
``autocal tsky``
    Beam-weighted sky temperature table Tsky(nu, LST) to HDF5 (and a plot).
``autocal info``
    Version, data folder, cache folder, and which sky models and beams are available.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

logger = logging.getLogger("autocal.cli")


class CliError(ValueError):
    """A command-line argument is invalid."""


def parse_range(text: str, what: str, unit: str) -> np.ndarray:
    """Parse ``START:STOP:N`` (inclusive, N points) or a comma-separated list.

    Parameters
    ----------
    text
        The argument.
    what, unit
        For error messages.

    Returns
    -------
    numpy.ndarray
        The values.
    """
    try:
        if ":" in text:
            parts = text.split(":")
            if len(parts) != 3:
                raise ValueError
            start, stop, num = float(parts[0]), float(parts[1]), int(parts[2])
        else:
            values = np.array([float(v) for v in text.split(",") if v.strip()])
    except ValueError as err:
        raise CliError(
            f"--{what} {text!r}: give START:STOP:N ({unit}) or a comma-separated list"
        ) from err
    if ":" in text:
        if num < 1:
            raise CliError(f"--{what}: N must be >= 1 (got {num})")
        return np.linspace(start, stop, num)
    if values.size == 0:
        raise CliError(f"--{what} is empty")
    return values


def _add_tsky(sub: argparse._SubParsersAction) -> None:
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
        help="gsm2008 | gsm2016 | lfsm | haslam | uniform:T0 | "
        "powerlaw:BASE@NU0MHZ:BETA (default gsm2008)",
    )
    p.add_argument(
        "--beam",
        default="dipole",
        help="dipole | airy | hera | edges-low | edges-low-45deg | edges-mid | "
        "edges-high | PATH (UVBeam file or EDGES FEKO .txt); default dipole",
    )
    p.add_argument("--pol", default="ee", choices=["ee", "nn"], help="polarisation")
    p.add_argument("--site", default="hera", help="hera | edges | LAT,LON[,ALT]")
    p.add_argument(
        "--freqs",
        default="100e6:200e6:101",
        help="frequencies START:STOP:N in Hz, or a list (default 100e6:200e6:101)",
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
    p.add_argument("--out", required=True, type=Path, help="output HDF5 file")
    p.add_argument("--plot", type=Path, help="also write a PNG plot here")
    p.set_defaults(func=_run_tsky)


def _run_tsky(args: argparse.Namespace) -> int:
    from autocal.io.tskyfile import write_tsky
    from autocal.plots import plot_tsky
    from autocal.tsky import compute_tsky

    if args.out.suffix.lower() not in {".h5", ".hdf5"}:
        raise CliError(f"--out {args.out}: the Tsky table is HDF5; use a .h5 file name")
    freqs = parse_range(args.freqs, "freqs", "Hz")
    lsts = parse_range(args.lsts, "lsts", "hours")
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


def _add_info(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "info",
        help="show version, data and cache folders",
        description="Show the autocal version, the data folder, the Tsky "
        "cache folder and which data-backed sky models and beams are present.",
    )
    p.set_defaults(func=_run_info)


def _run_info(args: argparse.Namespace) -> int:
    from autocal import __version__
    from autocal.io import datasets
    from autocal.tsky_cache import cache_dir

    root = datasets.data_dir()
    print(f"autocal {__version__}")
    print(f"data folder:  {root or 'not found (set AUTOCAL_DATA_DIR)'}")
    print(f"Tsky cache:   {cache_dir() or 'disabled'}")
    files = {
        "gsm2008 sky": datasets.GSM2008_FILE,
        "hera beam": datasets.HERA_BEAM_FILE,
        **{f"{k} beam": v for k, v in datasets.EDGES_BEAM_FILES.items()},
    }
    for name, rel in files.items():
        ok = root is not None and (root / rel).is_file()
        print(f"  {name:<22} {'present' if ok else 'MISSING'}  {rel}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """Build the argument parser."""
    from autocal import __version__

    parser = argparse.ArgumentParser(
        prog="autocal",
        description="Calibrate radio-telescope auto-correlations against sky models.",
    )
    parser.add_argument("--version", action="version", version=f"autocal {__version__}")
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="more log output (-v info, -vv debug)"
    )
    sub = parser.add_subparsers(dest="command", required=True)
    _add_tsky(sub)
    _add_info(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; return the exit status."""
    from autocal.beams import BeamError
    from autocal.io.datasets import DataFileMissingError
    from autocal.sky import SkyModelError
    from autocal.tsky import TskyError

    parser = build_parser()
    args = parser.parse_args(argv)
    level = [logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args))
    except (CliError, SkyModelError, BeamError, TskyError, DataFileMissingError, ValueError) as err:
        print(f"autocal {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
