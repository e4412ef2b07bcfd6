"""How far a fit is from the data: the gap metrics and the unexplained remainder.

:func:`gap_metrics` measures a model's disagreement with the data in one pass over its
residuals (chi^2, time modes, delay spectra, correlation with the sky's templates);
:func:`describe_unexplained` describes what the final model leaves when no catalogue entry
explains it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from autocal.compare.delay import delay_spectrum
from autocal.core.observation import Observation
from autocal.diagnosis.bandpass import BandpassFit
from autocal.diagnosis.effects import SkyTemplates, time_basis
from autocal.diagnosis.extended_fit import ExtendedFit, residual_pieces


def gap_metrics(
    fit: ExtendedFit,
    obs: Observation,
    tpl: SkyTemplates,
    bandpass: BandpassFit | None = None,
    n_time_modes: int = 4,
) -> dict[str, Any]:
    """Measure the disagreement between a fit and the data.

    One pass over the residuals, a chunk of antennas at a time
    (:meth:`~autocal.diagnosis.extended_fit.ExtendedFit.residual_chunks`): every metric is a
    sum over antennas.

    Returns
    -------
    dict
        ``chi2``, ``dof``, ``reduced_chi2``, ``rms_normalised_residual``,
        ``integration_jitter`` (rms over integrations of the channel-summed normalised
        residual / sqrt(channels): ~1 for white noise, >> 1 when whole integrations
        move together, e.g. broadband gain fluctuations), ``time_mode_power`` (mean
        over channels of the squared projection of the normalised residuals on
        ``P_0..P_{m-1}`` of LST, ~1 each when white),
        ``residual_delay_power`` (max and its delay of the time-averaged residual power
        spectrum along frequency, ~1 when white), ``delay_peak_G`` / ``delay_peak_Trxr``
        (largest delay-spectrum amplitude beyond 100 ns, mean removed),
        ``template_correlation`` (Pearson r of the residuals with Tsky, its Galactic part
        and the ground fraction), ``bandpass_reduced_chi2``.
    """
    basis = time_basis(obs.lsts, n_time_modes - 1)
    basis = np.vstack([np.ones(obs.ntime), basis]) if basis.size else np.ones((1, obs.ntime))
    norm = basis / np.sqrt((basis**2).sum(axis=1, keepdims=True))
    fb = np.broadcast_to(tpl.f_below[:, None, :], tpl.total.shape)
    templates = {"tsky": tpl.total, "galactic": tpl.galactic, "ground_fraction": fb}
    sums = _ResidualSums(
        mode_power=np.zeros(norm.shape[0]),
        ps_sum=np.zeros(obs.nfreq // 2 + 1),
        count=np.zeros(tpl.total.shape),  # antennas with a usable sample, (P, T, F)
        sum_tr=dict.fromkeys(templates, 0.0),
    )
    for _, res in residual_pieces(fit):
        sums.add(res, norm, templates, obs.nfreq)
    ps_mean = sums.ps_sum / max(sums.nspectra, 1)
    delays = np.fft.rfftfreq(obs.nfreq, d=obs.freqs[1] - obs.freqs[0]) * 1e9
    k = int(np.argmax(ps_mean[1:]) + 1)
    n = max(sums.nused, 1)
    return {
        "chi2": fit.chi2,
        "dof": fit.dof,
        "reduced_chi2": fit.reduced_chi2,
        "rms_normalised_residual": float(np.sqrt(sums.sum_r2 / n)),
        "integration_jitter": float(np.sqrt(sums.jitter_sum / sums.nint)) if sums.nint else 0.0,
        "time_mode_power": [float(v) for v in sums.mode_power / max(sums.nchan, 1)],
        "residual_delay_power": {"max": float(ps_mean[k]), "delay_ns": float(delays[k])},
        "delay_peak_G": _delay_peak(fit.G, obs),
        "delay_peak_Trxr": _delay_peak(fit.Trxr, obs),
        "template_correlation": {
            name: sums.correlation(templates[name], name) for name in templates
        },
        "bandpass_reduced_chi2": None if bandpass is None else bandpass.reduced_chi2,
    }


@dataclass(eq=False)
class _ResidualSums:
    """The sums over a fit's normalised residuals the gap metrics are made of.

    Every one is a sum over antennas, added up a chunk of antennas at a time (:meth:`add`).
    """

    mode_power: np.ndarray
    ps_sum: np.ndarray
    count: np.ndarray
    sum_tr: dict[str, float]
    nchan: int = 0
    nspectra: int = 0
    nused: int = 0
    sum_r: float = 0.0
    sum_r2: float = 0.0
    jitter_sum: float = 0.0
    nint: int = 0

    def add(
        self,
        res: np.ndarray,
        norm: np.ndarray,
        templates: dict[str, np.ndarray],
        nfreq: int,
    ) -> None:
        """Add a chunk's residuals ``(a, P, T, F)`` (NaN unused)."""
        ok = np.isfinite(res)
        r0 = np.where(ok, res, 0.0)
        proj = np.einsum("kt,aptf->apfk", norm, r0)
        self.mode_power += (proj**2).reshape(-1, proj.shape[-1]).sum(axis=0)
        self.nchan += proj.size // proj.shape[-1]
        ps = np.abs(np.fft.rfft(r0, axis=-1)) ** 2 / nfreq
        self.ps_sum += ps.reshape(-1, ps.shape[-1]).sum(axis=0)
        self.nspectra += ps.size // ps.shape[-1]
        self.nused += int(ok.sum())
        self.sum_r += float(r0.sum())
        self.sum_r2 += float((r0**2).sum())
        nused = ok.sum(axis=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            per_int = r0.sum(axis=-1) / np.sqrt(nused)
        self.jitter_sum += float((per_int[nused > 0] ** 2).sum())
        self.nint += int((nused > 0).sum())
        self.count += ok.sum(axis=0)
        for name, t in templates.items():
            self.sum_tr[name] += float(np.einsum("aptf,ptf->", r0, t))

    def correlation(self, template: np.ndarray, name: str) -> float:
        """Return the Pearson r of the residuals with a template over the usable samples.

        The template is shared by all antennas, so its moments are weighted by the number
        of antennas with a usable sample.
        """
        n = max(self.nused, 1)
        t = np.asarray(template, float)
        count = self.count
        seen = count > 0
        if not seen.any() or np.ptp(t[seen]) == 0:
            return 0.0
        t_mean = float((count * t).sum()) / n
        var_t = float((count * (t - t_mean) ** 2).sum())
        r_mean = self.sum_r / n
        var_r = self.sum_r2 - n * r_mean**2
        cov = self.sum_tr[name] - t_mean * self.sum_r
        return float(cov / math.sqrt(var_t * var_r)) if var_t > 0 and var_r > 0 else 0.0


def _delay_peak(values: np.ndarray, obs: Observation) -> dict[str, float]:
    """Return the largest delay-spectrum amplitude beyond 100 ns (mean removed), its delay."""
    try:
        ds = delay_spectrum(values.reshape(-1, obs.nfreq), obs.freqs, subtract_mean=True)
    except ValueError:
        return {"amplitude": float("nan"), "delay_ns": float("nan")}
    sel = ds.delays_ns > 100
    amp = np.nanmax(ds.amplitude[:, sel], axis=0)
    i = int(np.nanargmax(amp))
    return {"amplitude": float(amp[i]), "delay_ns": float(ds.delays_ns[sel][i])}


#: The final model's chi-square may exceed its degrees of freedom by this many standard
#: deviations (``sqrt(2 dof)``) before the remainder is reported as unexplained.
UNEXPLAINED_SIGMAS = 5.0
#: An effect negligible for the products that explains less than this share of the
#: unexplained remainder's excess chi^2 (``chi2 - dof`` of the final model) is reported as
#: part of that remainder, not as detected (:attr:`autocal.diagnosis.report.Diagnosis.absorbed`).
ABSORBED_SHARE = 0.1


def describe_unexplained(
    fit: ExtendedFit, obs: Observation, gap: dict[str, Any]
) -> dict[str, Any] | None:
    """Describe the residual no catalogue entry explained, or ``None`` if there is none.

    Parameters
    ----------
    fit
        The final model's fit.
    obs
        The observation.
    gap
        The final model's :func:`gap_metrics`.

    Returns
    -------
    dict or None
        ``reduced_chi2``, ``excess_sigma`` (``(chi2 - dof) / sqrt(2 dof)``), the
        structure: ``time`` (``smooth`` when the low Legendre modes of LST carry most of
        it, ``integration to integration`` when whole integrations move together, else
        ``unstructured``), ``frequency`` (the delay of the residual's largest delay power
        and that power over white), ``antennas`` (reduced chi2 per antenna-pol, worst
        first) and ``message``.
    """
    dof = max(int(gap["dof"]), 1)
    excess = (gap["chi2"] - dof) / math.sqrt(2.0 * dof)
    if excess <= UNEXPLAINED_SIGMAS:
        return None
    modes = gap["time_mode_power"]
    jitter = gap["integration_jitter"]
    smooth = max(modes[1:], default=1.0)
    if smooth > max(4.0, jitter**2):
        time_kind = "smooth in time"
    elif jitter > 2.0:
        time_kind = "integration to integration (whole integrations move together)"
    else:
        time_kind = "unstructured in time"
    delay = gap["residual_delay_power"]
    freq_kind = (
        f"structured in frequency (delay power {delay['max']:.3g} x white at "
        f"{delay['delay_ns']:.0f} ns)"
        if delay["max"] > 4.0
        else "white in frequency"
    )
    per_feed = np.zeros((len(obs.antennas), len(obs.pols)))
    for sl, res in residual_pieces(fit):
        ok = np.isfinite(res)
        per_feed[sl] = (np.where(ok, res, 0.0) ** 2).sum(axis=(2, 3)) / np.maximum(
            ok.sum(axis=(2, 3)), 1
        )
    feeds = sorted(
        (
            (float(per_feed[ia, ip]), int(a), str(p))
            for ia, a in enumerate(obs.antennas)
            for ip, p in enumerate(obs.pols)
        ),
        reverse=True,
    )
    antennas = [{"antenna": a, "pol": p, "reduced_chi2": v} for v, a, p in feeds]
    worst = ", ".join(f"{e['antenna']} {e['pol']} ({e['reduced_chi2']:.3g})" for e in antennas[:3])
    return {
        "reduced_chi2": float(gap["reduced_chi2"]),
        "excess_sigma": float(excess),
        "time": time_kind,
        "time_mode_power": modes,
        "integration_jitter": jitter,
        "frequency": freq_kind,
        "antennas": antennas,
        "message": (
            f"unexplained: chi2/dof {gap['reduced_chi2']:.4g} remains ({excess:.3g} sigma above "
            f"the noise) with no catalogue entry significant; the residual is {time_kind}, "
            f"{freq_kind}; largest in {worst}"
        ),
    }
