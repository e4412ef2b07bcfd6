"""The auto-correlation fit of a simulated EDGES-like day against its receiver solution.

:func:`fit_edges_day` reads the raw files of an :class:`~autocal.edges.simulated_day.EdgesDay`,
fits ``R = G Tsky + n`` and compares ``G`` and ``Trxr`` with what the receiver solution
implies (:class:`~autocal.edges.noise_waves.AutoModelExpectation`), as pulls.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from autocal.core.coords import night_epoch
from autocal.edges.noise_waves import AutoModelExpectation
from autocal.edges.simulated_day import EdgesDay
from autocal.edges.solutions import ReceiverCalError
from autocal.fit.passes import fit
from autocal.io.edges_read import read_edges_spectra
from autocal.io.edges_spectra import MIN_OBS_FREQ_HZ
from autocal.tsky.compute import compute_tsky


@dataclass(frozen=True, eq=False)
class EdgesDayFit:
    """The auto-correlation fit of an EDGES-like day against the receiver's expectation.

    Attributes
    ----------
    solution
        The fit (:class:`autocal.fit.solution.Solution`).
    expected
        What the receiver solution implies.
    pull_gain, pull_trxr
        ``(fit - expected) / sigma`` per channel.
    rel_err_gain
        ``fit / expected - 1`` per channel.
    err_trxr
        ``fit - expected`` per channel (K).
    """

    solution: Any
    expected: AutoModelExpectation
    pull_gain: np.ndarray
    pull_trxr: np.ndarray
    rel_err_gain: np.ndarray
    err_trxr: np.ndarray

    def summary(self) -> dict[str, float]:
        """Medians and spreads of the comparison."""
        return {
            "median_rel_err_gain": float(np.median(self.rel_err_gain)),
            "rms_rel_err_gain": float(np.sqrt(np.mean(self.rel_err_gain**2))),
            "median_err_trxr_K": float(np.median(self.err_trxr)),
            "rms_err_trxr_K": float(np.sqrt(np.mean(self.err_trxr**2))),
            "median_sigma_trxr_K": float(np.median(self.solution.sigma_Trxr[0, 0])),
            "mean_pull_gain": float(np.mean(self.pull_gain)),
            "std_pull_gain": float(np.std(self.pull_gain)),
            "mean_pull_trxr": float(np.mean(self.pull_trxr)),
            "std_pull_trxr": float(np.std(self.pull_trxr)),
            "max_abs_pull": float(
                max(np.max(np.abs(self.pull_gain)), np.max(np.abs(self.pull_trxr)))
            ),
            "median_reduced_chi2": float(np.median(self.solution.reduced_chi2)),
        }


def fit_edges_day(
    day: EdgesDay,
    r: Literal["q", "p0"] = "q",
    weights: Literal["variance", "identity"] = "variance",
) -> EdgesDayFit:
    """Calibrate a simulated day from its raw files with the auto-correlation fit.

    Reads the files (:func:`autocal.io.edges_read.read_edges_spectra` with the day's band and
    binning), builds the ``R`` observation, computes ``Tsky`` with the same sky, beam and
    ground, fits ``R = G Tsky + n`` (constant model; inverse-variance weights from the
    propagated radiometer noise, or identity) and compares with the expectation.
    """
    cfg = day.config
    spec = read_edges_spectra(
        day.paths, freq_range=tuple(cfg["freq_range_Hz"]), bin_factor=cfg["bin_factor"]
    )
    obs = spec.to_observation(r)
    if obs.freqs.shape != day.freqs.shape or not np.allclose(obs.freqs, day.freqs, atol=1e-3):
        raise ReceiverCalError("the files' channels differ from the simulated ones")
    tsky = compute_tsky(
        cfg["sky"],
        cfg["beam"],
        obs.site,
        obs.freqs,
        obs.lsts,
        tgnd=cfg["tgnd_K"],
        nside=cfg["nside"],
        epoch=night_epoch(obs.jds, obs.site.lon_deg),
    ).tsky
    w: Any = "identity"
    if weights == "variance":
        keep = spec.freqs >= MIN_OBS_FREQ_HZ
        w = (1.0 / spec.variance(r)[:, keep])[None, None]
    sol = fit(  # pulls of the propagated noise: the covariance as it is, not inflated
        obs,
        tsky,
        model="constant",
        weights=w,
        inflate_errors=False,
        config={"edges_day": cfg, "r": r},
    )
    exp = day.expected[r]
    g, sg = sol.G[0, 0], sol.sigma_G[0, 0]
    t, st = sol.Trxr[0, 0], sol.sigma_Trxr[0, 0]
    return EdgesDayFit(
        solution=sol,
        expected=exp,
        pull_gain=(g - exp.G) / sg,
        pull_trxr=(t - exp.trxr) / st,
        rel_err_gain=g / exp.G - 1.0,
        err_trxr=t - exp.trxr,
    )
