"""Jy->K conversion and pol convention of written calfits files (autocal.compare.conversion)."""

from __future__ import annotations

import numpy as np
import pytest

import autocal  # noqa: F401
from autocal.compare.beam_area import jy_per_kelvin
from autocal.compare.comparison import compare
from autocal.io.calsol_read import ReferenceGains, read_reference_gains
from autocal.io.calsol_uvcal import solution_to_uvcal
from tests.compare.helpers import end_change
from tests.io.test_calsol import make_solution


def test_drift_through_a_written_calfits_file(tmp_path):
    sol = make_solution(ntime=12)
    omega = np.full(sol.freqs.size, 0.04)
    jpk = jy_per_kelvin(sol.freqs, omega)

    def written(rise: float, pol_convention: str | None) -> ReferenceGains:
        uvc = solution_to_uvcal(sol, per_time=True)
        power = 1.0 + rise * np.linspace(0.0, 1.0, sol.jds.size)
        # pyuvdata (A, F, T, J): a Jy-referenced |g| = |g_auto| sqrt(power) / sqrt(J)
        uvc.gain_array = (
            uvc.gain_array * np.sqrt(power)[None, None, :, None] / np.sqrt(jpk)[None, :, None, None]
        )
        uvc.gain_scale = "Jy"
        uvc.pol_convention = pol_convention
        path = tmp_path / f"ref_{rise}_{pol_convention}.calfits"
        uvc.write_calfits(str(path))
        return read_reference_gains(path)

    rising = compare(sol, written(0.5, None), omega=omega, auto_drift=0.0)
    flat = compare(sol, written(0.0, None), omega=omega, auto_drift=0.0)
    for row in rising.summary["per_antenna_pol"]:
        assert row["reference_drift"] == pytest.approx(end_change(0.5, 12, 1), rel=1e-6)
        assert row["reference_stable"] is False
    for row in flat.summary["per_antenna_pol"]:
        assert row["reference_stable"] is True
        assert row["ratio_mean"] == pytest.approx(1.0, rel=1e-6)
        pol = row["systematics"]["pol_convention"]
        assert pol["source"] == "assumed" and pol["used"] == "avg" and pol["stated"] is None
        assert pol["ratio_mean"] == pytest.approx(np.sqrt(2) * row["ratio_mean"])
    # a file stating the 'sum' convention: half the Jy per raw unit, ratio sqrt(2) larger
    summed = compare(sol, written(0.0, "sum"), omega=omega, auto_drift=0.0)
    np.testing.assert_allclose(summed.ratio[summed.valid], np.sqrt(2), rtol=1e-6)
    assert summed.summary["conversion"]["pol_convention"] == "sum"
    for row in summed.summary["per_antenna_pol"]:
        pol = row["systematics"]["pol_convention"]
        assert pol["source"] == "file" and pol["used"] == "sum"
        assert pol["alternative"] == "avg"
        assert pol["ratio_mean"] == pytest.approx(1.0, rel=1e-6)
    stated = compare(sol, written(0.0, "avg"), omega=omega)
    assert stated.summary["systematics"]["pol_convention"]["source"] == "file"
