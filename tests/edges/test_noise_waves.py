"""The receiver calibration equations: calibration and decalibration, K factors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from autocal.edges.noise_waves import (
    calibrate_powers,
    calibrate_tstar,
    decalibrate,
    decalibrate_q,
    expected_auto_model,
    k_factors,
    tstar_from_q,
)
from autocal.edges.solutions import load_receiver_solution


@pytest.mark.data
def test_calibrate_and_decalibrate_invert_each_other(data_root: Path) -> None:
    sol = load_receiver_solution("edges2-lowband-2015").at(np.linspace(50e6, 100e6, 40))
    rng = np.random.default_rng(5)
    t_ant = rng.uniform(500.0, 8000.0, (7, 40))
    gammas = [0.0, 0.3 * np.exp(0.7j), 0.2 * np.exp(2j * np.pi * sol.freqs * 40e-9)]
    for gamma in gammas:
        p0, p1, p2 = decalibrate(t_ant, sol, gamma, raw_scale=3e-11, t_offset=450.0)
        np.testing.assert_allclose(calibrate_powers(p0, p1, p2, sol, gamma), t_ant, rtol=1e-10)
        q = (p0 - p1) / (p2 - p1)
        np.testing.assert_allclose(decalibrate_q(t_ant, sol, gamma), q, rtol=1e-10)
        tstar = tstar_from_q(q, sol.t_load_ns, sol.t_load)
        np.testing.assert_allclose(calibrate_tstar(tstar, sol, gamma), t_ant, rtol=1e-10)
        # the auto-correlation models are exactly linear in T_ant
        for r, data in (("q", q), ("p0", p0)):
            exp = expected_auto_model(sol, gamma, r, raw_scale=3e-11, t_offset=450.0)
            np.testing.assert_allclose(exp.G * t_ant + exp.n, data, rtol=1e-10)
            np.testing.assert_allclose(exp.trxr, exp.n / exp.G)
    # K factors: closed forms
    k1, k2, k3, k4 = k_factors(sol.gamma_rec, gammas[1])
    ga, gr = gammas[1], sol.gamma_rec
    np.testing.assert_allclose(k1, (1 - abs(ga) ** 2) / np.abs(1 - ga * gr) ** 2)
    np.testing.assert_allclose(k2, abs(ga) ** 2 / np.abs(1 - ga * gr) ** 2)
    np.testing.assert_allclose(
        np.hypot(k3, k4), abs(ga) / (np.sqrt(1 - abs(gr) ** 2) * np.abs(1 - ga * gr))
    )
    # matched antenna: G = 1 / (C1 T_NS), Trxr = C2 - T_L for Q
    exp = expected_auto_model(sol, 0.0, "q")
    np.testing.assert_allclose(exp.G, 1 / (sol.c1 * 1000.0))
    np.testing.assert_allclose(exp.trxr, sol.c2 - 300.0)
