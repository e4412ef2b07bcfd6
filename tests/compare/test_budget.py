"""The systematics budget (autocal.compare.budget)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import autocal  # noqa: F401
from autocal.compare.beam_area import (
    HERA_SIM_BEAM_INTEGRALS,
    beam_solid_angle,
    jy_per_kelvin,
)
from autocal.compare.comparison import compare
from autocal.io.calsol_read import read_reference_gains
from tests.compare.helpers import reference_for
from tests.io.test_calsol import H1C_ABS, REF, make_solution


def test_sky_model_alternatives_spread():
    sol = make_solution(flagged=())
    omega = np.full(sol.freqs.size, 0.04)
    ref = reference_for(sol, 1.0 / np.sqrt(jy_per_kelvin(sol.freqs, omega)))
    alts = {
        "beta -2.5": replace(sol, coeffs=sol.coeffs * 1.1**2, cov=sol.cov * 1.1**4),
        "beta -2.55": replace(sol, coeffs=sol.coeffs * 0.95**2, cov=sol.cov * 0.95**4),
    }
    result = compare(sol, ref, omega=omega, alternatives=alts)
    for row in result.summary["per_antenna_pol"]:
        sky = row["systematics"]["sky_model"]
        assert sky["alternatives"]["beta -2.5"]["shift"] == pytest.approx(0.1, rel=1e-6)
        assert sky["alternatives"]["beta -2.55"]["ratio_mean"] == pytest.approx(0.95, rel=1e-3)
        assert sky["spread_fraction"] == pytest.approx(0.15, rel=1e-6)
    plain = compare(sol, ref, omega=omega)
    assert plain.summary["per_antenna_pol"][0]["systematics"]["sky_model"] is None
    assert compare(sol, reference_for(sol, 1.0, absolute=False)).summary["systematics"] is None


@pytest.mark.data
def test_budget_and_drift_from_the_real_files(data_root):
    """omega_source from hera_sim's table, pol_convention from the calfits, drift of ant 23."""
    from pyuvdata import UVCal

    files = [data_root / REF / n for n in H1C_ABS]
    ref = read_reference_gains(files, antennas=[23], freq_range=(140e6, 160e6))
    amp = ref.abs_g
    finite = np.isfinite(amp)
    with np.errstate(invalid="ignore"):
        mean_sq = np.where(finite, amp**2, 0).sum(axis=2) / finite.sum(axis=2)
    omega = beam_solid_angle("hera", ref.freqs)
    gain = mean_sq * jy_per_kelvin(ref.freqs, omega)
    flagged = tuple(int(i) for i in np.flatnonzero(np.all(~np.isfinite(gain), axis=(0, 1))))
    sol = make_solution(
        antennas=(23,),
        freqs=ref.freqs,
        ntime=36,
        gain=np.nan_to_num(gain, nan=1.0),
        flagged=flagged,
    )
    sol = replace(sol, jds=ref.jds.copy())
    result = compare(sol, ref, auto_drift=-0.036)
    # omega_source: hera_sim's omega_p, read here independently of autocal
    table = np.load(data_root / HERA_SIM_BEAM_INTEGRALS)
    om_hs = np.interp(ref.freqs, table["freqs"] * 1e9, table["omega_p"])
    # pol_convention: what pyuvdata reads from the files
    stated = {UVCal.from_file(str(f), read_data=False).pol_convention for f in files}
    for ip, row in enumerate(result.summary["per_antenna_pol"]):
        ok = result.valid[0, ip]
        scale = np.sqrt(result.omega[ip] / om_hs)
        r = result.ratio[0, ip]
        om_entry = row["systematics"]["omega_source"]
        assert om_entry["shift"] == pytest.approx(
            np.mean(r[ok] * scale[ok]) / np.mean(r[ok]) - 1, rel=1e-9
        )
        assert 0.015 < om_entry["shift"] < 0.035  # hera_sim's Omega is ~5 % smaller
        pol = row["systematics"]["pol_convention"]
        if stated == {None}:
            assert pol["source"] == "assumed" and pol["used"] == "avg"
            assert pol["shift"] == pytest.approx(np.sqrt(2) - 1)
        else:
            assert pol["source"] == "file" and pol["used"] in stated
        # abscal's |g|^2 of antenna 23 rises by ~50 % over the 31 minutes
        assert 0.4 < row["reference_drift"] < 0.6
        assert row["reference_stable"] is False
    at150 = result.summary["systematics"]["per_pol"]["ee"]
    assert at150["omega_ratio_hera_sim_over_autocal"] == pytest.approx(0.95, abs=0.01)
