"""Calibration options shared by ``autocal calibrate`` and ``autocal nightly``.

Every field of :class:`autocal.pipeline.config.CalibrationConfig` except ``inputs`` has
exactly one option here, and the defaults shown in ``--help`` are read from the configuration
itself, so the command line, the REST API (``service.schemas.CalibrationOptions``) and the Python
configuration cannot drift apart (``tests/cli/test_cli_options.py`` checks the coverage).
Options left out on the command line are not passed on: the configuration's defaults apply.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from autocal.cli.args import (
    BEAM_HELP,
    FIELD_FLAGS,
    SKY_HELP,
    CliError,
    parse_freq_pair,
    parse_int_list,
    parse_pair,
    parse_str_list,
)

#: The defaults of :class:`~autocal.pipeline.config.CalibrationConfig` that ``--help`` shows
#: (``autocal diagnose --help`` shows ``rfi_flagging``'s too, the default of
#: :class:`~autocal.diagnosis.run.DiagnoseConfig`). A copy, so that building the parser does
#: not import the configurations (which import the fit and, through it, scipy and pyuvdata:
#: ~1 s of a fresh process); the options test checks that it equals the configurations' own
#: defaults (``tests/cli/test_cli_startup.py``).
HELP_DEFAULTS: dict[str, Any] = {
    "sky": "gsm2008",
    "beam": "hera",
    "tgnd_k": 300.0,
    "nside": 64,
    "model": "constant",
    "order": 1,
    "weights": "radiometer",
    "passes": "auto",
    "inflate_errors": True,
    "rfi_flagging": True,
    "trxr_prior_sigma_k": 10.0,
    "antennas": None,
    "products": ["calh5", "hdf5", "png"],
    "input_format": "auto",
    "edges_r": "q",
    "edges_bin": 64,
}


def default_text(value: Any) -> str:
    """Return how ``--help`` shows a configuration default (``default: ...``)."""
    if value is None:
        return "default: all"
    if isinstance(value, list):
        value = ",".join(str(v) for v in value)
    if isinstance(value, bool):
        value = "on" if value else "off"
    return f"default: {value}"


def _default(name: str) -> str:
    """Return the configuration's default of a field, as ``--help`` shows it."""
    return default_text(HELP_DEFAULTS[name])


def add_calibration_arguments(group: argparse._ActionsContainer) -> None:
    """Add one option per calibration setting to a parser or an argument group.

    Parameters
    ----------
    group
        The parser (``autocal calibrate``) or argument group (``autocal nightly``).
    """
    _add_model_arguments(group)
    _add_fit_arguments(group)
    _add_selection_arguments(group)


def _add_model_arguments(group: argparse._ActionsContainer) -> None:
    """Add the sky, beam, ground and gain-model options."""
    d = _default
    group.add_argument(
        "--sky",
        help=f"sky model: {SKY_HELP} ({d('sky')})",
    )
    group.add_argument(
        "--beam",
        help=f"beam: {BEAM_HELP} ({d('beam')})",
    )
    group.add_argument(
        "--tgnd",
        dest="tgnd_k",
        type=float,
        metavar="K",
        help=f"ground temperature K ({d('tgnd_k')})",
    )
    group.add_argument(
        "--nside", type=int, help=f"HEALPix resolution of Tsky, a power of two ({d('nside')})"
    )
    group.add_argument("--model", choices=["constant", "legendre"], help=f"({d('model')})")
    group.add_argument(
        "--order",
        type=int,
        help=f"Legendre order of G(t) and n(t), --model legendre ({d('order')})",
    )


def _add_fit_arguments(group: argparse._ActionsContainer) -> None:
    """Add the weights, passes, error-inflation and receiver-prior options."""
    d = _default
    group.add_argument("--weights", choices=["radiometer", "identity"], help=f"({d('weights')})")
    group.add_argument(
        "--passes",
        choices=["auto", "1", "2"],
        help="radiometer weighting passes over the data: 2 re-weights with the fitted model, "
        "auto makes the second only when data-derived weights would bias G by more than "
        f"1e-5 ({d('passes')})",
    )
    group.add_argument(
        "--inflate-errors",
        action=argparse.BooleanOptionalAction,
        help="radiometer weights: scale each channel's covariance by chi2/dof when it exceeds "
        f"1 (identity weights always scale) ({d('inflate_errors')})",
    )
    group.add_argument(
        "--rfi-flagging",
        action=argparse.BooleanOptionalAction,
        help="flag band edges and RFI from the autos before the fit (robust median filters in "
        "frequency and time, as hera_qm's xrfi; counts per reason in summary.json); "
        f"--no-rfi-flagging fits every sample the data do not flag ({d('rfi_flagging')})",
    )
    group.add_argument(
        "--trxr-prior",
        metavar="K|CSV|H5",
        help="receiver-temperature prior: a number in K, a CSV table with the header "
        "freq_mhz,trxr_k[,sigma_k] (MHz, K; interpolated in frequency, must cover the data "
        "band) or a previous solution.h5 of the same antennas and pols; the errors of G "
        "then include the prior's (default: none)",
    )
    group.add_argument(
        "--trxr-prior-sigma",
        dest="trxr_prior_sigma_k",
        type=float,
        metavar="K",
        help=f"1-sigma of a number prior or a table without sigma_k ({d('trxr_prior_sigma_k')})",
    )


def _add_selection_arguments(group: argparse._ActionsContainer) -> None:
    """Add the data-selection, product, reference and input-format options."""
    d = _default
    group.add_argument("--antennas", help=f"comma-separated antenna numbers ({d('antennas')})")
    group.add_argument("--pols", help="comma-separated polarisations (default: all in the data)")
    group.add_argument(
        "--freq-range",
        dest="freq_range_mhz",
        metavar="LOW:HIGH",
        help="frequencies in MHz (a unit suffix, e.g. 110MHz or 1.1e8Hz, is accepted)",
    )
    group.add_argument(
        "--lst-range",
        dest="lst_range_h",
        metavar="START:STOP",
        help="LSTs in hours (START > STOP wraps)",
    )
    group.add_argument(
        "--products",
        help=f"comma-separated of calh5, calfits, hdf5, png ({d('products')})",
    )
    group.add_argument(
        "--reference",
        action="append",
        type=Path,
        metavar="FILE",
        help="reference gains (calfits/calh5, abscal or redcal) to compare |g| with; one file "
        "per flag, repeat it for consecutive files (before or after the inputs)",
    )
    group.add_argument(
        "--format",
        dest="input_format",
        choices=["auto", "uvh5", "miriad", "edges"],
        help=f"input format; edges: ACQ or autocal's EDGES HDF5 ({d('input_format')})",
    )
    group.add_argument(
        "--edges-r",
        choices=["q", "p0"],
        help=f"EDGES: fit Q = (p0 - p1)/(p2 - p1) or the raw antenna power p0 ({d('edges_r')})",
    )
    group.add_argument(
        "--edges-bin",
        type=int,
        metavar="N",
        help=f"EDGES: native channels averaged per bin ({d('edges_bin')})",
    )


def calibration_settings(args: argparse.Namespace) -> dict[str, Any]:
    """Return the calibration settings given on the command line, parsed and validated.

    Parameters
    ----------
    args
        Parsed arguments of a parser set up by :func:`add_calibration_arguments`.

    Returns
    -------
    dict
        :class:`~autocal.pipeline.config.CalibrationConfig` fields (without ``inputs``); options
        not given are left out, so the configuration's defaults apply.

    Raises
    ------
    CliError
        When an option is invalid.
    """
    parsers = {
        "antennas": lambda v: parse_int_list(v, "antennas"),
        "pols": lambda v: parse_str_list(v, "pols"),
        "products": lambda v: parse_str_list(v, "products"),
        "freq_range_mhz": lambda v: parse_freq_pair(v, "freq-range"),
        "lst_range_h": lambda v: parse_pair(v, "lst-range", "hours"),
        "passes": lambda v: v if v == "auto" else int(v),
        "reference": lambda v: [str(p) for p in v],
        "trxr_prior": _prior_value,
    }
    settings: dict[str, Any] = {}
    for name in calibration_dests():
        value = getattr(args, name)
        if value is not None:
            settings[name] = parsers.get(name, lambda v: v)(value)
    refuse_inapplicable(settings)
    # Only the configuration's own checks need it (and the fit and scipy with it): options
    # the checks above refuse are reported without loading the science stack.
    from pydantic import ValidationError

    from autocal.cli.args import validation_message
    from autocal.pipeline.config import CalibrationConfig

    try:
        CalibrationConfig(inputs=["-"], **settings)
    except ValidationError as err:
        raise CliError(validation_message(err, "options")) from None
    return settings


def _prior_value(text: str) -> Any:
    """Parse ``--trxr-prior`` (:func:`autocal.fit.priors.prior_value`, imported when given)."""
    from autocal.fit.priors import prior_value  # deferred: imports the fit and scipy

    return prior_value(text)


def cli_spelling(field: str, value: Any = None) -> str:
    """Return a configuration field as its command-line option (and a value of it).

    The option is :data:`autocal.cli.args.FIELD_FLAGS`'s (the table the CLI's validation
    messages use too), else ``--`` and the field with dashes.
    """
    flag = FIELD_FLAGS.get(field, "--" + field.replace("_", "-"))
    return flag if value is None else f"{flag} {value}"


def refuse_inapplicable(settings: dict[str, Any]) -> None:
    """Refuse options that do nothing with the other options given, saying why.

    The rules are :func:`autocal.pipeline.option_rules.calibration_refusals` (the API's too).

    Parameters
    ----------
    settings
        The options given (:func:`calibration_settings`).

    Raises
    ------
    CliError
        ``--order`` without ``--model legendre``, ``--trxr-prior-sigma`` without
        ``--trxr-prior``, ``--passes`` or ``--no-inflate-errors`` with identity weights, or an
        EDGES option with a ``--format`` other than ``edges`` or ``auto``.
    """
    from autocal.pipeline.option_rules import calibration_refusals

    for _, why in calibration_refusals(settings, cli_spelling):
        raise CliError(why)


def refuse_edges_options(settings: dict[str, Any], inputs: list[Path]) -> None:
    """Refuse options that do not apply to the kind of inputs.

    ``--edges-r`` / ``--edges-bin`` unless the inputs are EDGES spectra, and
    ``--(no-)rfi-flagging`` when they are
    (:func:`autocal.pipeline.option_rules.input_kind_refusals`).
    """
    from autocal.pipeline.option_rules import input_kind_refusals
    from autocal.pipeline.sources import detect_format

    if not {"edges_r", "edges_bin", "rfi_flagging"} & set(settings):
        return
    kind = detect_format(
        [Path(p).expanduser().absolute() for p in inputs], settings.get("input_format", "auto")
    )
    for _, why in input_kind_refusals(settings, kind, cli_spelling):
        raise CliError(why)


def calibration_dests() -> list[str]:
    """Return the ``dest`` of every option :func:`add_calibration_arguments` adds, in order.

    Each is the name of the :class:`~autocal.pipeline.config.CalibrationConfig` field it sets.
    """
    parser = argparse.ArgumentParser(add_help=False)
    add_calibration_arguments(parser)
    return [action.dest for action in parser._actions]
