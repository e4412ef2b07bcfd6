"""Shared helpers of the calibration-file tests: reference-gain file lists and solutions.

The tests are in test_calsol_read.py, test_calsol_files.py and test_calsol_write.py;
these helpers are also used by test_products.py and tests/compare.
"""

from __future__ import annotations

import numpy as np
from astropy.time import Time

import autocal  # noqa: F401  (offline configuration first)
from autocal.core.observation import Observation
from autocal.core.sites import HERA
from autocal.fit.model import FitModel
from autocal.fit.passes import fit
from autocal.fit.solution import Solution

REF = "hera/reference_gains"
H1C_ABS = [f"zen.2458116.{t}.HH.flagged_abs.calfits" for t in (30448, 31193, 31939)]
OMNI_36 = [f"zen.2458099.{t}.HH.uv.omni.calfits_36x_only" for t in (22245, 22991, 23737)]
ABS_54 = [f"zen.2458101.{t}.xx.HH.uv.abs.calfits_54x_only" for t in (44615, 45361, 46106)]

#: Every reference-gain file: (Nant, Npol, Ntime, Nfreq), pols, absolute?
SINGLE_FILES = {
    "zen.2458043.40141.xx.HH.XRAA.abs.calfits": ((7, 1, 60, 64), ("ee",), False),
    "zen.2458098.43124.downsample.omni.calfits": ((10, 2, 3, 128), ("ee", "nn"), False),
    "zen.2458098.45361.HH.omni_downselected.calfits": ((8, 2, 10, 64), ("ee", "nn"), False),
    **{name: ((1, 1, 60, 1024), ("ee",), False) for name in OMNI_36},
    **{name: ((1, 1, 60, 1024), ("ee",), True) for name in ABS_54},
    **{name: ((3, 2, 12, 1024), ("ee", "nn"), True) for name in H1C_ABS},
}


# ---------------------------------------------------------------------------------------
# a synthetic solution (shared with test_products and test_compare)
# ---------------------------------------------------------------------------------------
def hera_lsts(jds: np.ndarray, site=HERA) -> np.ndarray:
    return Time(jds, format="jd").sidereal_time("apparent", longitude=site.lon_deg).hour


def make_solution(
    *,
    antennas: tuple[int, ...] = (0, 23),
    pols: tuple[str, ...] = ("ee", "nn"),
    freqs: np.ndarray | None = None,
    ntime: int = 6,
    jd0: float = 2458116.30,
    gain: np.ndarray | None = None,
    rel_sigma: float = 0.01,
    flagged: tuple[int, ...] = (3,),
    config: dict | None = None,
) -> Solution:
    """A constant-model solution with known G (raw/K), Trxr = 150 K and flagged channels."""
    freqs = np.linspace(100e6, 200e6, 41) if freqs is None else np.asarray(freqs, float)
    nant, npol, nfreq = len(antennas), len(pols), freqs.size
    jds = jd0 + np.arange(ntime) * 60.0 / 86400.0
    if gain is None:
        f = freqs / 150e6
        gain = np.empty((nant, npol, nfreq))
        for ia in range(nant):
            for ip in range(npol):
                gain[ia, ip] = (1.0 + 0.1 * ia + 0.05 * ip) * (1 + 0.3 * (f - 1)) * 2e-2
    gain = np.broadcast_to(gain, (nant, npol, nfreq)).astype(float)
    noise = 150.0 * gain
    coeffs = np.stack([gain, noise], axis=-1)
    sig_g, sig_n = rel_sigma * gain, rel_sigma * noise
    cov = np.zeros((nant, npol, nfreq, 2, 2))
    cov[..., 0, 0] = sig_g**2
    cov[..., 1, 1] = sig_n**2
    cov[..., 0, 1] = cov[..., 1, 0] = -0.5 * sig_g * sig_n
    reason = np.zeros((nant, npol, nfreq), np.int64)
    for ch in flagged:
        reason[..., ch] = 2
    bad = reason != 0
    coeffs[bad] = np.nan
    cov[bad] = np.nan
    dof = np.full((nant, npol, nfreq), float(ntime - 2))
    chi2 = np.where(bad, np.nan, dof * 1.1)
    return Solution(
        model=FitModel.for_lsts(hera_lsts(jds)),
        antennas=np.array(antennas, dtype=np.int64),
        pols=tuple(pols),
        freqs=freqs,
        lsts=hera_lsts(jds),
        jds=jds,
        coeffs=coeffs,
        cov=cov,
        chi2=chi2,
        dof=dof,
        count=np.full((nant, npol, nfreq), ntime, np.int64),
        nflagged=np.zeros((nant, npol, nfreq), np.int64),
        flag_reason=reason,
        config={"sky": "gsm2008", "beam": "hera", "telescope": "HERA", **(config or {})},
        antenna_names=tuple(f"HH{a}" for a in antennas),
    )


def fitted_solution(order: int = 1, residuals: bool = True) -> Solution:
    """A solution from autocal.fit on a small noisy synthetic observation."""
    rng = np.random.default_rng(3)
    ntime, nfreq = 24, 16
    jds = 2458098.30 + np.arange(ntime) * 300.0 / 86400.0
    lsts = hera_lsts(jds)
    freqs = np.linspace(120e6, 180e6, nfreq)
    tsky = 300.0 * (freqs / 150e6) ** -2.5 * (1 + 0.3 * np.sin(lsts / 24 * 2 * np.pi))[:, None]
    gain = np.array([1.0, 1.2])[:, None, None, None] * np.ones((2, 1, 1, nfreq))
    data = gain * (tsky[None, None] + 150.0)
    data = data * (1 + rng.standard_normal(data.shape) * 1e-3)
    flags = np.zeros(data.shape, bool)
    flags[:, :, :, 5] = True  # one channel fails: too few samples
    obs = Observation(
        data=data,
        freqs=freqs,
        lsts=lsts,
        jds=jds,
        antennas=np.array([0, 1]),
        pols=("ee",),
        site=HERA,
        flags=flags,
        channel_width=1e5,
        integration_time=10.0,
    )
    return fit(
        obs,
        tsky,
        model="legendre" if order else "constant",
        order=order,
        weights="identity",
        return_residuals=residuals,
        config={"sky": {"model": "uniform", "cmb": "included"}, "beam": "hera", "tgnd_K": 300.0},
    )
