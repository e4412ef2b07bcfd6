"""``autocal diagnose``: find the effect the forward model is missing, add it, repeat."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from autocal.cli.args import (
    CliError,
    check_output_folder,
    output_folder,
    parse_freq_pair,
    parse_int_list,
    parse_pair,
    parse_str_list,
    validation_message,
)
from autocal.cli.options import HELP_DEFAULTS, default_text


def add(sub: argparse._SubParsersAction) -> None:
    """Register the command."""
    p = sub.add_parser(
        "diagnose",
        help="name the physical effects missing from the model (gain drift, reflections, ...)",
        description="Fit the current model (sky x beam + CMB + ground, constant gain per "
        "channel) to the autos of one observation (band edges and RFI flagged first, as "
        "calibrate does), measure the gap, fit each candidate "
        "effect of the catalogue (gain_drift, gain_jitter, antenna_gain_jitter, "
        "antenna_gain_drift, noise_drift, sky_scale, sky_offset, sky_spectral_index, "
        "ground_temperature, beam_width, missing_cmb, timing_offset, cable_reflection), "
        "accept the best by BIC while significant and consistent across the band, and "
        "repeat; report what barely moves the products as negligible and what nothing "
        "explains as unexplained. Writes diagnosis.json, summary.txt, summary.json, "
        "residual plots and gain_series.png to --out (all or nothing). The service runs "
        "the same as a job of kind 'diagnose'.",
    )
    p.add_argument("inputs", nargs="+", type=Path, help="UVH5 files of one observation")
    p.add_argument("--sky", default="gsm2008", help="model sky (default gsm2008)")
    p.add_argument("--beam", default="hera", help="model beam (default hera)")
    p.add_argument("--tgnd", type=float, default=300.0, help="model ground temperature K")
    p.add_argument("--nside", type=int, default=64, help="HEALPix resolution (64)")
    p.add_argument("--antennas", help="comma-separated antenna numbers (default all)")
    p.add_argument("--pols", help="comma-separated polarisations (default all)")
    p.add_argument(
        "--freq-range", help="LOW:HIGH in MHz (a unit suffix, e.g. 1.1e8Hz, is accepted)"
    )
    p.add_argument("--lst-range", help="START:STOP in hours (START > STOP wraps)")
    p.add_argument(
        "--trxr-prior",
        metavar="K|CSV|H5",
        help="known receiver temperature: a number in K, a CSV table freq_mhz,trxr_k[,sigma_k] "
        "or a previous solution.h5; makes effects that are constant in time (sky_offset, "
        "ground_temperature, missing_cmb) and sky scalings identifiable",
    )
    p.add_argument(
        "--trxr-prior-sigma",
        type=float,
        help="1-sigma K of a number prior or a table without sigma_k (1); needs --trxr-prior",
    )
    p.add_argument(
        "--bic-threshold",
        type=float,
        help="Delta BIC an effect must exceed to be accepted (default 10)",
    )
    p.add_argument(
        "--alpha",
        type=float,
        help="largest chi^2 probability of an accepted effect's Delta chi^2 (default 1e-4)",
    )
    p.add_argument("--max-steps", type=int, help="most effects added (default 5)")
    p.add_argument(
        "--rfi-flagging",
        action=argparse.BooleanOptionalAction,
        help="flag band edges and RFI from the autos before the fits, as calibrate does "
        "(counts per reason in diagnosis.json and summary.txt); --no-rfi-flagging fits every "
        "sample the data do not flag (outliers of the residuals are flagged either way) "
        f"({default_text(HELP_DEFAULTS['rfi_flagging'])})",
    )
    p.add_argument("--out", required=True, type=output_folder, help="output folder")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the command."""
    check_output_folder(args.out)
    from pydantic import ValidationError
    from tqdm import tqdm

    from autocal.diagnosis.run import DiagnoseConfig, run_diagnosis
    from autocal.fit.priors import prior_value

    refuse_inapplicable(args)
    optional: dict[str, Any] = {
        "bic_threshold": args.bic_threshold,
        "alpha": args.alpha,
        "max_steps": args.max_steps,
        "trxr_prior_sigma_k": args.trxr_prior_sigma,
        "rfi_flagging": args.rfi_flagging,
    }
    try:
        config = DiagnoseConfig(
            inputs=[str(p) for p in args.inputs],
            sky=args.sky,
            beam=args.beam,
            tgnd_k=args.tgnd,
            nside=args.nside,
            antennas=parse_int_list(args.antennas, "antennas") if args.antennas else None,
            pols=parse_str_list(args.pols, "pols") if args.pols else None,
            freq_range_mhz=parse_freq_pair(args.freq_range, "freq-range"),
            lst_range_h=parse_pair(args.lst_range, "lst-range", "hours"),
            trxr_prior=None if args.trxr_prior is None else prior_value(args.trxr_prior),
            **{k: v for k, v in optional.items() if v is not None},
        )
    except ValidationError as err:
        raise CliError(validation_message(err)) from None
    with tqdm(total=100, desc="diagnose", unit="%", disable=None) as bar:

        def progress(fraction: float, message: str) -> None:
            bar.n = round(100 * min(fraction, 1.0))
            bar.set_postfix_str(message[-60:])
            bar.refresh()

        out = run_diagnosis(config, args.out, progress=progress)
    print((out / "summary.txt").read_text())
    print(f"wrote {out}")
    return 0


def refuse_inapplicable(args: argparse.Namespace) -> None:
    """Refuse options that do nothing with the other options given, saying why.

    The rules are :func:`autocal.pipeline.option_rules.diagnosis_refusals` (the API's too).

    Raises
    ------
    CliError
        ``--trxr-prior-sigma`` without ``--trxr-prior``; ``--bic-threshold`` or ``--alpha``
        with ``--max-steps 0`` (no effect is tried, so nothing is accepted or refused).
    """
    from autocal.cli.options import cli_spelling
    from autocal.pipeline.option_rules import diagnosis_refusals

    given = {
        "trxr_prior": args.trxr_prior,
        "trxr_prior_sigma_k": args.trxr_prior_sigma,
        "bic_threshold": args.bic_threshold,
        "alpha": args.alpha,
        "max_steps": args.max_steps,
    }
    for _, why in diagnosis_refusals(given, cli_spelling):
        raise CliError(why)
