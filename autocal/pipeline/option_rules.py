"""Options that do nothing with the other options given: one table for every front end.

``autocal calibrate`` / ``autocal diagnose`` refuse them with a usage error, ``POST /jobs``
and ``POST /nightly`` with a 422 naming the field, before anything is read. Each rule is a
field of :class:`~autocal.pipeline.config.CalibrationConfig` (or of
:class:`~autocal.diagnosis.run.DiagnoseConfig`) and why it does nothing; the messages name
the other options through ``spell``, so the command line says ``--model legendre`` and the
API ``model="legendre"``.

Deliberately light (no numpy, no pydantic): the command line checks these before it loads
the science stack.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from typing import Any

#: ``spell(field, value=None)``: how a front end writes an option (and a value of it).
Spell = Callable[..., str]

#: Input kinds that :func:`autocal.pipeline.sources.detect_format` returns for EDGES spectra.
EDGES_KIND = "edges"


def api_spelling(field: str, value: Any = None) -> str:
    """Return an option as the REST API's bodies write it: ``field`` or ``field=<JSON value>``."""
    return field if value is None else f"{field}={json.dumps(value)}"


def calibration_refusals(
    given: Mapping[str, Any], spell: Spell = api_spelling
) -> list[tuple[str, str]]:
    """Return ``(field, why)`` for every calibration option given that does nothing.

    Parameters
    ----------
    given
        The options given (fields of ``CalibrationConfig``; left-out ones take defaults).
    spell
        Writes an option's name (and a value) as the front end's users type it.

    Returns
    -------
    list of tuple
        ``order`` without the Legendre model, ``trxr_prior_sigma_k`` without
        ``trxr_prior``, ``passes`` or ``inflate_errors`` with identity weights, an EDGES
        option with an ``input_format`` other than ``edges`` or ``auto``; in that order.
    """
    identity = given.get("weights") == "identity"
    fmt = given.get("input_format", "auto")
    rules = {
        "order": (
            given.get("model", "constant") != "legendre",
            f"{spell('order')} sets the Legendre order: it needs {spell('model', 'legendre')} "
            "(the constant model has none)",
        ),
        "trxr_prior_sigma_k": (
            "trxr_prior" not in given,
            f"{spell('trxr_prior_sigma_k')} is the 1-sigma of {spell('trxr_prior')}: "
            "give the prior too",
        ),
        "passes": (
            identity,
            f"{spell('passes')} re-weights radiometer weights: it does nothing with "
            f"{spell('weights', 'identity')}",
        ),
        "inflate_errors": (
            identity,
            f"identity weights always scale the errors by chi2/dof: drop {spell('inflate_errors')}",
        ),
    }
    for field in ("edges_r", "edges_bin"):
        rules[field] = (
            fmt not in ("auto", EDGES_KIND),
            f"{spell(field)} is an option of EDGES spectra: it does nothing with "
            f"{spell('input_format', fmt)}",
        )
    return [(field, why) for field, (refused, why) in rules.items() if field in given and refused]


def input_kind_refusals(
    given: Mapping[str, Any], kind: str, spell: Spell = api_spelling
) -> list[tuple[str, str]]:
    """Return ``(field, why)`` for options that do not apply to the kind of inputs.

    Parameters
    ----------
    given
        The options given.
    kind
        The inputs' kind (:func:`autocal.pipeline.sources.detect_format`: ``uvh5``,
        ``miriad``, ``edges``).
    spell
        As :func:`calibration_refusals`.

    Returns
    -------
    list of tuple
        The EDGES options with inputs that are not EDGES spectra, ``rfi_flagging`` with
        inputs that are.
    """
    out = []
    if kind == EDGES_KIND and "rfi_flagging" in given:
        out.append(
            (
                "rfi_flagging",
                f"{spell('rfi_flagging')}: EDGES spectra are not flagged from the autos (the "
                "option applies to HERA UVH5 and Miriad inputs): drop it",
            )
        )
    if kind != EDGES_KIND:
        edges = [field for field in ("edges_r", "edges_bin") if field in given]
        if edges:
            names = ", ".join(spell(field) for field in edges)
            why = f"{names}: option(s) of EDGES spectra, and the inputs are {kind} files: drop them"
            out.append((edges[0], why))
    return out


def diagnosis_refusals(
    given: Mapping[str, Any], spell: Spell = api_spelling
) -> list[tuple[str, str]]:
    """Return ``(field, why)`` for every diagnosis option given that does nothing.

    Parameters
    ----------
    given
        The options given (fields of ``DiagnoseConfig``).
    spell
        As :func:`calibration_refusals`.

    Returns
    -------
    list of tuple
        ``trxr_prior_sigma_k`` without ``trxr_prior``; ``bic_threshold`` or ``alpha`` with
        ``max_steps`` 0 (no effect is tried, so none is accepted or refused).
    """
    out = []
    if given.get("trxr_prior_sigma_k") is not None and given.get("trxr_prior") is None:
        out.append(
            (
                "trxr_prior_sigma_k",
                f"{spell('trxr_prior_sigma_k')} is the 1-sigma of {spell('trxr_prior')}: "
                "give the prior too",
            )
        )
    if given.get("max_steps") == 0:
        tests = [field for field in ("bic_threshold", "alpha") if given.get(field) is not None]
        if tests:
            names = ", ".join(spell(field) for field in tests)
            out.append(
                (
                    tests[0],
                    f"{names}: the acceptance test of an effect, and {spell('max_steps', 0)} "
                    "tries none: drop it or allow steps",
                )
            )
    return out
