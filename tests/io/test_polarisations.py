"""Polarisation names and codes against pyuvdata's, code by code and orientation by orientation."""

from __future__ import annotations

import pytest
from pyuvdata import utils as uvutils

from autocal.io.polarisations import CODE_TO_NAME, NAME_TO_CODE, code_to_name, name_to_code

ORIENTATIONS = [None, "east", "north", "e", "EW", "n", "ns", "North"]


@pytest.mark.parametrize("orientation", ORIENTATIONS)
def test_names_of_every_code_are_pyuvdatas(orientation) -> None:
    for code in CODE_TO_NAME:
        assert code_to_name(code, orientation) == uvutils.polnum2str(
            code, x_orientation=orientation
        )


@pytest.mark.parametrize("orientation", ORIENTATIONS)
def test_codes_of_every_name_and_alias_are_pyuvdatas(orientation) -> None:
    names = set(NAME_TO_CODE) | {code_to_name(c, orientation) for c in CODE_TO_NAME}
    names |= {n.upper() for n in names} | {n.lower() for n in names}
    for name in sorted(names):
        assert name_to_code(name, orientation) == uvutils.polstr2num(
            name, x_orientation=orientation
        ), name


def test_unknown_codes_names_and_orientations_raise_keyerror() -> None:
    with pytest.raises(KeyError):
        code_to_name(-9)
    with pytest.raises(KeyError):
        name_to_code("ee")  # e/n names need the feeds' orientation
    with pytest.raises(KeyError):
        name_to_code("zz", "east")
    with pytest.raises(KeyError):
        code_to_name(-5, "up")  # pyuvdata only warns and keeps xx
