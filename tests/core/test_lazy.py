"""healpy imported on first use: the stand-in, and the checks that replaced healpy calls."""

from __future__ import annotations

import json
import subprocess
import sys

import healpy
import numpy as np
import pytest

from autocal.core.lazy import LazyModule
from autocal.tsky.compute import _nside_ok


def test_the_stand_in_gives_the_modules_attributes() -> None:
    lazy = LazyModule("healpy")
    assert lazy.nside2npix(64) == healpy.nside2npix(64)
    assert lazy.pix2ang is healpy.pix2ang
    with pytest.raises(AttributeError):
        _ = lazy.no_such_function
    assert "healpy" in repr(lazy)


def test_the_tsky_stage_imports_without_healpy() -> None:
    """Importing the Tsky stage (for a cached Tsky) does not import healpy (0.7-1 s)."""
    code = (
        "import json, sys\n"
        "import autocal.tsky.compute, autocal.sky.models, autocal.core.coords\n"
        "print(json.dumps('healpy' in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert json.loads(out.stdout) is False


@pytest.mark.parametrize(
    "nside", [1, 2, 3, 4, 64, 100, 128, 2**29, 2**30, np.int64(64), 64.0, 64.5, -4, 0]
)
def test_nside_check_agrees_with_healpy(nside) -> None:
    """``compute_tsky``'s nside check is healpy's ``isnsideok(nest=True)`` and >= 2."""
    assert _nside_ok(nside) == (bool(healpy.isnsideok(nside, nest=True)) and nside >= 2)


def test_nside_check_refuses_what_is_not_a_number() -> None:
    assert not any(_nside_ok(v) for v in (True, "64", None, [64]))
