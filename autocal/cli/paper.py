"""``autocal paper``: the simulation table and figures of Gehlot et al. (2021)."""

from __future__ import annotations

import argparse

from autocal.cli.args import CliError, check_output_folder, output_folder, parse_str_list


def add(sub: argparse._SubParsersAction) -> None:
    """Register the command."""
    p = sub.add_parser(
        "paper",
        help="run the paper's simulation scenarios and write the table and figures",
        description="Simulate and fit every scenario of the paper's summary table (reference, "
        "gain drifts a/b/c with constant and order-1 time models, sky-model and "
        "beam-model incompleteness) for each beam, and write paper_table.md, "
        "paper_results.json and PNG figures to --out.",
    )
    p.add_argument("--out", required=True, type=output_folder, help="output folder")
    p.add_argument("--beams", default="hera,dipole,airy", help="comma-separated beams")
    p.add_argument("--seed", type=int, default=1, help="noise seed (1)")
    p.add_argument(
        "--quick",
        action="store_true",
        help="coarse sampling (2 MHz channels, 15-minute cadence) for a fast look",
    )
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    p.add_argument("--no-cache", action="store_true", help="do not use the Tsky cache")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the command."""
    check_output_folder(args.out)
    from autocal.simulate.mock import SimulationConfig
    from autocal.simulate.paper import PAPER_BEAMS, run_paper

    beams = tuple(parse_str_list(args.beams, "beams"))
    if args.seed < 0:
        raise CliError(f"--seed {args.seed}: a noise seed is an integer >= 0")
    unknown = [b for b in beams if b not in PAPER_BEAMS]
    if unknown:
        raise CliError(f"--beams: unknown {unknown}; choose from {list(PAPER_BEAMS)}")
    config = (
        SimulationConfig(channel_width_khz=2000.0, cadence_s=900.0)
        if args.quick
        else SimulationConfig()
    )
    written = run_paper(
        args.out,
        beams=beams,
        config=config,
        seed=args.seed,
        figures=not args.no_figures,
        cache=not args.no_cache,
    )
    print(written["table_text"])
    print(f"wrote {written['table']} and {written['results']}")
    for fig in written.get("figures", []):
        print(f"wrote {fig}")
    print(f"({written['seconds']} s)")
    return 0
