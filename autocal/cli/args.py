"""Argument parsing shared by the sub-commands: ranges, sky and beam help, :class:`CliError`."""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING, Any

from autocal.errors import AutocalError

if TYPE_CHECKING:
    import numpy as np

#: What ``--sky`` accepts (every command that computes Tsky).
SKY_HELP = "gsm2008 | gsm2016 | lfsm | haslam | uniform:T0 | powerlaw:BASE@NU0MHZ:BETA"
#: What ``--beam`` accepts.
BEAM_HELP = (
    "dipole | airy | hera | edges-low | edges-low-45deg | edges-mid | edges-high | PATH "
    "(UVBeam file or EDGES FEKO .txt)"
)


class CliError(AutocalError):
    """A command-line argument is invalid."""


#: Unit suffixes a frequency option accepts, and their value in MHz.
FREQ_UNITS_MHZ = {"ghz": 1e3, "mhz": 1.0, "khz": 1e-3, "hz": 1e-6}


def parse_freq_mhz(
    text: str, what: str, bare_limit_mhz: float = 1e4, legacy_unit: str | None = None
) -> float:
    """Parse one frequency in MHz: a bare number (MHz) or a number with a unit suffix.

    ``150``, ``150MHz``, ``1.5e8Hz``, ``250kHz`` and ``0.15GHz`` are accepted (the suffix
    is case-insensitive). A bare number above ``bare_limit_mhz`` looks like Hz (or kHz) and
    is refused with its MHz equivalent, so an old Hz value cannot silently mean MHz; an
    option that used to take another unit (``legacy_unit``) reads it in that unit instead
    and says so on standard error.

    Parameters
    ----------
    text
        The value.
    what
        The option, for error messages (without the leading ``--``).
    bare_limit_mhz
        Largest plausible bare value in MHz.
    legacy_unit
        ``"Hz"`` or ``"kHz"``: the option's former unit, in which a bare value above
        ``bare_limit_mhz`` is read (with a note); ``None``: such a value is an error.

    Returns
    -------
    float
        The frequency in MHz.

    Raises
    ------
    CliError
        When the value is not a number with an optional unit, or a bare value looks like Hz.
    """
    raw = text.strip()
    lowered = raw.lower()
    scale, number = None, lowered
    for suffix in ("ghz", "mhz", "khz", "hz"):
        if lowered.endswith(suffix):
            scale, number = FREQ_UNITS_MHZ[suffix], lowered[: -len(suffix)].strip()
            break
    try:
        value = float(number)
    except ValueError:
        raise CliError(
            f"--{what} {raw!r}: give a frequency in MHz, or with a unit (150MHz, 1.5e8Hz, 250kHz)"
        ) from None
    if scale is not None:
        return value * scale
    if abs(value) > bare_limit_mhz and legacy_unit is not None:
        mhz = value * FREQ_UNITS_MHZ[legacy_unit.lower()]
        print(
            f"autocal: note: --{what} {raw} is read as {legacy_unit} ({mhz:g} MHz): "
            f"frequencies are in MHz now; give {mhz:g} or {raw}{legacy_unit}",
            file=sys.stderr,
        )
        return mhz
    if abs(value) > bare_limit_mhz:
        unit, factor = ("Hz", 1e-6) if abs(value) * 1e-6 >= 1e-3 else ("kHz", 1e-3)
        raise CliError(
            f"--{what} {raw}: frequencies are in MHz; {raw} looks like {unit} "
            f"({value * factor:g} MHz): give {value * factor:g} or {raw}{unit}"
        )
    return value


def parse_freq_range_mhz(text: str, what: str, legacy_unit: str | None = None) -> np.ndarray:
    """Parse frequencies in MHz: ``START:STOP:N`` (inclusive) or a comma-separated list.

    Each frequency takes an optional unit suffix (:func:`parse_freq_mhz`, which also
    describes ``legacy_unit``); ``N`` is a count.
    """
    parts = text.split(":")
    if ":" in text:
        if len(parts) != 3:
            raise CliError(f"--{what} {text!r}: give START:STOP:N (MHz) or a comma-separated list")
        start, stop = (parse_freq_mhz(v, what, legacy_unit=legacy_unit) for v in parts[:2])
        return parse_range(f"{start!r}:{stop!r}:{parts[2]}", what, "MHz")
    items = [v for v in text.split(",") if v.strip()]
    values = [parse_freq_mhz(v, what, legacy_unit=legacy_unit) for v in items]
    if not values:
        raise CliError(f"--{what} is empty")
    import numpy as np  # deferred: parsing the command line does not need numpy

    return np.array(values)


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
    import numpy as np  # deferred: parsing the command line does not need numpy

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


def parse_freq_pair(text: str | None, what: str) -> tuple[float, float] | None:
    """Parse ``LOW:HIGH`` frequencies in MHz, each with an optional unit suffix."""
    if text is None:
        return None
    parts = text.split(":")
    if len(parts) != 2:
        raise CliError(f"--{what} {text!r}: give LOW:HIGH in MHz (e.g. 110:190 or 110MHz:190MHz)")
    lo, hi = (parse_freq_mhz(v, what) for v in parts)
    return lo, hi


def validation_message(err: Any, what: str = "settings") -> str:
    """One line listing every field a pydantic ``ValidationError`` rejected, and why."""
    return "; ".join(
        f"{'.'.join(str(x) for x in e['loc']) or what}: {e['msg']}" for e in err.errors()
    )
