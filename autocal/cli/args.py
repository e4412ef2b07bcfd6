"""Argument parsing shared by the sub-commands: ranges, sky and beam help, :class:`CliError`."""

from __future__ import annotations

from typing import Any

import numpy as np

from autocal.errors import AutocalError

#: What ``--sky`` accepts (every command that computes Tsky).
SKY_HELP = "gsm2008 | gsm2016 | lfsm | haslam | uniform:T0 | powerlaw:BASE@NU0MHZ:BETA"
#: What ``--beam`` accepts.
BEAM_HELP = (
    "dipole | airy | hera | edges-low | edges-low-45deg | edges-mid | edges-high | PATH "
    "(UVBeam file or EDGES FEKO .txt)"
)


class CliError(AutocalError):
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


def parse_str_list(text: str, what: str) -> list[str]:
    """Parse a comma-separated list of names (lower-cased, non-empty)."""
    items = [t.strip().lower() for t in text.split(",") if t.strip()]
    if not items:
        raise CliError(f"--{what} is empty")
    return items


def parse_int_list(text: str, what: str) -> list[int]:
    """Parse a comma-separated list of integers."""
    try:
        return [int(t) for t in parse_str_list(text, what)]
    except ValueError as err:
        raise CliError(f"--{what} {text!r}: give comma-separated integers") from err


def parse_pair(text: str | None, what: str, unit: str) -> tuple[float, float] | None:
    """Parse ``LOW:HIGH`` (``None`` stays ``None``)."""
    if text is None:
        return None
    try:
        lo, hi = (float(v) for v in text.split(":"))
    except ValueError as err:
        raise CliError(f"--{what} {text!r}: give LOW:HIGH in {unit}") from err
    return lo, hi


def validation_message(err: Any, what: str = "settings") -> str:
    """One line listing every field a pydantic ``ValidationError`` rejected, and why."""
    return "; ".join(
        f"{'.'.join(str(x) for x in e['loc']) or what}: {e['msg']}" for e in err.errors()
    )
