"""Argument parsing shared by the sub-commands: ranges, sky and beam help, :class:`CliError`."""

from __future__ import annotations

import argparse
import re
import sys
import tempfile
from pathlib import Path
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
    if value != value or value in (float("inf"), float("-inf")):
        raise CliError(f"--{what} {raw!r}: give a finite frequency in MHz")
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


#: Most points a ``START:STOP:N`` range may ask for (a million LSTs is 1 per 0.09 s).
MAX_RANGE_POINTS = 1_000_000


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
        if num > MAX_RANGE_POINTS:
            raise CliError(f"--{what}: N = {num} is more than {MAX_RANGE_POINTS} points")
        if not (np.isfinite(start) and np.isfinite(stop)):
            raise CliError(f"--{what} {text!r}: START and STOP must be finite numbers ({unit})")
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
    """One line listing every field a pydantic ``ValidationError`` rejected, and why.

    Each field is named as the command line spells it (``--tgnd``, not ``tgnd_k``:
    :data:`FIELD_FLAGS`, else ``--`` and the field with dashes; a setting of the service
    by its environment variable, ``AUTOCAL_DATA_ROOTS``), and the "Value error," that
    pydantic puts before a check's own message is dropped.
    """
    settings = getattr(err, "title", "") == "Settings"  # the service's, from AUTOCAL_*

    def where(loc: tuple[Any, ...]) -> str:
        if not loc:
            return what
        field = str(loc[0])
        if settings:
            flag = f"AUTOCAL_{field.upper()}"
        else:
            flag = FIELD_FLAGS.get(field, "--" + field.replace("_", "-"))
        return ".".join([flag, *(str(x) for x in loc[1:])])

    def why(message: str) -> str:  # a model-level check names fields in its text
        message = message.removeprefix("Value error, ")
        for field, flag in FIELD_FLAGS.items():
            message = re.sub(rf"\b{field}\b", flag, message)
        return message

    return "; ".join(f"{where(tuple(e['loc']))}: {why(str(e['msg']))}" for e in err.errors())


#: Configuration fields whose command-line option is not ``--`` and the field with dashes
#: (the one table: validation messages and :func:`autocal.cli.options.cli_spelling`).
FIELD_FLAGS = {
    "inflate_errors": "--(no-)inflate-errors",
    "rfi_flagging": "--(no-)rfi-flagging",
    "tgnd_k": "--tgnd",
    "trxr_k": "--trxr",
    "freq_range_mhz": "--freq-range",
    "lst_range_h": "--lst-range",
    "trxr_prior_sigma_k": "--trxr-prior-sigma",
    "input_format": "--format",
    "channel_width_khz": "--channel-width",
    "freq_start_mhz": "--freq-start",
    "freq_stop_mhz": "--freq-stop",
    "lst_start_h": "--lst-start",
    "duration_h": "--duration",
    "cadence_s": "--cadence",
    "jd_start": "--jd",
    "noise_dnu_hz": "--noise-dnu",
    "noise_dt_s": "--noise-dt",
}


def output_folder(text: str) -> Path:
    """Parse an ``--out`` folder (argparse ``type``): refuse an empty path.

    ``Path("")`` is the current folder, so ``--out ""`` (an unset shell variable) wrote
    every product there.
    """
    if not text.strip():
        raise argparse.ArgumentTypeError("the output folder is empty: give a folder path")
    return Path(text)


def output_file(text: str) -> Path:
    """Parse an ``--out`` file (argparse ``type``): refuse an empty path or a folder."""
    if not text.strip():
        raise argparse.ArgumentTypeError("the output file is empty: give a file path")
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a folder: give a file path")
    return path


def check_output_folder(out: Path) -> None:
    """Refuse, before any work, an output folder that is a file or cannot be written.

    Raises
    ------
    CliError
        Saying what is wrong with ``out`` (checked before a run computes for minutes and
        only then finds it cannot write its products).
    """
    if out.exists() and not out.is_dir():
        raise CliError(f"--out {out} is a file, not a folder: give a folder (new or autocal's)")
    probe = out
    while not probe.exists():  # the nearest existing parent decides whether it can be made
        probe = probe.parent
    if not probe.is_dir():
        raise CliError(f"--out {out}: {probe} is a file, so the folder cannot be made there")
    try:  # a write, not os.access: root passes that test on an immutable or read-only folder
        with tempfile.TemporaryFile(dir=probe):
            pass
    except OSError as err:
        raise CliError(
            f"--out {out}: {probe} cannot be written ({err.strerror or err}); choose a folder "
            "you can write"
        ) from None


def check_output_file(path: Path) -> None:
    """Refuse, before any work, an output file whose folder is missing or cannot be written.

    Raises
    ------
    CliError
        Saying what is wrong (a run that computed for minutes before failing to write, or
        that wrote one file of two, is what this prevents).
    """
    if path.is_dir():
        raise CliError(f"{path} is a folder: give a file path")
    folder = path.expanduser().absolute().parent
    if not folder.is_dir():
        raise CliError(f"{path}: the folder {folder} does not exist; create it first")
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as err:
        raise CliError(
            f"{path}: the folder {folder} cannot be written ({err.strerror or err})"
        ) from None
