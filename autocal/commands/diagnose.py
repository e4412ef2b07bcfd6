"""``autocal diagnose``: find the effect the forward model is missing, add it, repeat."""

from __future__ import annotations

import argparse
from pathlib import Path

from autocal.commands import parse_int_list, parse_pair, parse_str_list


def add(sub: argparse._SubParsersAction) -> None:
    """Register the command."""
    p = sub.add_parser(
        "diagnose",
        help="name the physical effects missing from the model (gain drift, reflections, ...)",
        description="Fit the current model (sky x beam + CMB + ground, constant gain per "
        "channel) to the autos of one observation, measure the gap, fit each candidate "
        "effect of the catalogue (gain_drift, noise_drift, sky_scale, sky_offset, "
        "sky_spectral_index, ground_temperature, beam_width, missing_cmb, "
        "cable_reflection), accept the best by BIC while significant, and repeat. Writes "
        "diagnosis.json, summary.txt and residual plots to --out.",
    )
    p.add_argument("inputs", nargs="+", type=Path, help="UVH5 files of one observation")
    p.add_argument("--sky", default="gsm2008", help="model sky (default gsm2008)")
    p.add_argument("--beam", default="hera", help="model beam (default hera)")
    p.add_argument("--tgnd", type=float, default=300.0, help="model ground temperature K")
    p.add_argument("--nside", type=int, default=64, help="HEALPix resolution (64)")
    p.add_argument("--antennas", help="comma-separated antenna numbers (default all)")
    p.add_argument("--pols", help="comma-separated polarisations (default all)")
    p.add_argument("--freq-range", help="LOW:HIGH in MHz")
    p.add_argument(
        "--trxr-prior",
        type=float,
        help="known receiver temperature K: makes effects that are constant in time "
        "(sky_offset, ground_temperature, missing_cmb) and sky scalings identifiable",
    )
    p.add_argument("--trxr-prior-sigma", type=float, default=1.0, help="its 1-sigma, K (1)")
    p.add_argument("--out", required=True, type=Path, help="output folder")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the command."""
    from autocal.diagnose import diagnose, summary_text, write_diagnosis
    from autocal.effects import sky_templates
    from autocal.io.uvh5 import read_uvh5

    mhz = parse_pair(args.freq_range, "freq-range", "MHz")
    freq_range = None if mhz is None else (mhz[0] * 1e6, mhz[1] * 1e6)
    obs = read_uvh5(
        args.inputs,
        antennas=parse_int_list(args.antennas, "antennas") if args.antennas else None,
        pols=parse_str_list(args.pols, "pols") if args.pols else None,
        freq_range=freq_range,
    )
    templates = sky_templates(
        args.sky,
        args.beam,
        obs.site,
        obs.freqs,
        obs.lsts,
        pols=tuple("ee" if p == "xx" else "nn" if p == "yy" else p for p in obs.pols),
        tgnd=args.tgnd,
        nside=args.nside,
        epoch=float(obs.jds.mean()),
    )
    result = diagnose(
        obs, templates, trxr_prior=args.trxr_prior, trxr_prior_sigma=args.trxr_prior_sigma
    )
    path = write_diagnosis(result, args.out, obs)
    print(summary_text(result))
    print(f"wrote {path}")
    return 0
