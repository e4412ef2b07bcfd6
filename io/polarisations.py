"""Polarisation codes and names (AIPS Memo 117), as pyuvdata names them, without pyuvdata.

The header scan of every UVH5 file turns the file's polarisation codes into names; importing
pyuvdata for its two lookup functions cost a fresh process over a second. These are the
same tables and the same renaming of x/y to e/n by the feeds' orientation as
``pyuvdata.utils.polnum2str`` and ``polstr2num`` (checked against them code by code,
orientation by orientation, in ``tests/io/test_polarisations.py``).
"""

from __future__ import annotations

from collections.abc import Sequence

#: Code -> name, AIPS Memo 117 (pseudo-Stokes as ``pI`` ... so they are not read as Stokes).
CODE_TO_NAME: dict[int, str] = {
    1: "pI",
    2: "pQ",
    3: "pU",
    4: "pV",
    -1: "rr",
    -2: "ll",
    -3: "rl",
    -4: "lr",
    -5: "xx",
    -6: "yy",
    -7: "xy",
    -8: "yx",
}

#: Name -> code, the names above plus the aliases pyuvdata accepts.
NAME_TO_CODE: dict[str, int] = {
    **{name: code for code, name in CODE_TO_NAME.items()},
    "I": 1,
    "Q": 2,
    "U": 3,
    "V": 4,
    "hh": -5,
    "vv": -6,
    "hv": -7,
    "vh": -8,
}

#: The x and y feeds' compass letters for each orientation of the x feed.
_FEED_LETTERS = {"east": {"x": "e", "y": "n"}, "north": {"x": "n", "y": "e"}}

#: The spellings of the orientation pyuvdata accepts (its ``XORIENTMAP``).
_ORIENTATIONS = {"east": "east", "e": "east", "ew": "east", "north": "north", "n": "north"}
_ORIENTATIONS["ns"] = "north"


def _letters(x_orientation: str | None) -> dict[str, str] | None:
    """Return the compass letters of an orientation; None without one (x and y stay x, y).

    Raises
    ------
    KeyError
        For an orientation pyuvdata does not know (it warns and keeps x and y).
    """
    if x_orientation is None:
        return None
    return _FEED_LETTERS[_ORIENTATIONS[str(x_orientation).lower()]]


def code_to_name(code: int, x_orientation: str | None = None) -> str:
    """Return the name of polarisation ``code`` (``ee``/``nn`` when the orientation is known).

    Parameters
    ----------
    code
        A polarisation code (AIPS Memo 117), e.g. -5.
    x_orientation
        ``"east"`` or ``"north"``: the x feed's direction; x and y become e and n.

    Returns
    -------
    str
        The name, e.g. ``"xx"``, or ``"ee"`` with ``x_orientation="east"``.

    Raises
    ------
    KeyError
        For a code that is not a polarisation, or an orientation pyuvdata does not know.
    """
    name = CODE_TO_NAME[int(code)]
    letters = _letters(x_orientation)
    if letters is not None:
        name = name.replace("x", letters["x"]).replace("y", letters["y"])
    return name


def codes_to_names(codes: Sequence[int], x_orientation: str | None = None) -> list[str]:
    """Names of several codes, lower case (``pI`` -> ``pi``), as the readers list them."""
    return [code_to_name(c, x_orientation).lower() for c in codes]


def name_to_code(name: str, x_orientation: str | None = None) -> int:
    """Return the code of polarisation ``name`` (case-insensitive; e/n names by orientation).

    Raises
    ------
    KeyError
        For a name that is not a polarisation (or an e/n name without an orientation).
    """
    table = dict(NAME_TO_CODE)
    letters = _letters(x_orientation)
    if letters is not None:
        for key, value in NAME_TO_CODE.items():
            table[key.replace("x", letters["x"]).replace("y", letters["y"])] = value
    lowered = {k.lower(): v for k, v in table.items()}
    return lowered[str(name).lower()]
