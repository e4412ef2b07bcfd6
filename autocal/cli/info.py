"""``autocal info``: version, data and cache folders, available data files."""

from __future__ import annotations

import argparse


def add(sub: argparse._SubParsersAction) -> None:
    """Register the command."""
    p = sub.add_parser(
        "info",
        help="show version, data and cache folders",
        description="Show the autocal version, the data folder, the cache folders "
        "(Tsky harmonics, compiled fit kernels, parsed IERS table) and which data-backed "
        "sky models and beams are present.",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the command."""
    from autocal import __version__
    from autocal.core.offline import iers_cache_file
    from autocal.fit.kernels import kernel_cache_dir
    from autocal.io import datasets
    from autocal.tsky.cache import cache_dir

    root = datasets.data_dir()
    print(f"autocal {__version__}")
    print(f"data folder:  {root or 'not found (set AUTOCAL_DATA_DIR)'}")
    print(f"Tsky cache:   {cache_dir() or 'disabled'}")
    print(f"fit kernels:  {kernel_cache_dir() or 'not cached'}")
    iers_file = iers_cache_file()
    print(f"IERS table:   {iers_file.parent if iers_file else 'not cached'}")
    files = {
        "gsm2008 sky": datasets.GSM2008_FILE,
        "hera beam": datasets.HERA_BEAM_FILE,
        **{f"{k} beam": v for k, v in datasets.EDGES_BEAM_FILES.items()},
    }
    for name, rel in files.items():
        ok = root is not None and (root / rel).is_file()
        print(f"  {name:<22} {'present' if ok else 'MISSING'}  {rel}")
    return 0
