"""The bandpass domain: a cable reflection as a ripple on the fitted ``G(nu)``.

``cable_reflection`` is absorbed by the per-channel gain, so it is ranked in the bandpass
domain: ``chi^2`` of the fitted ``G(nu)`` (with its errors) against a smooth Legendre
bandpass (:func:`auto_smooth_order`), with and without the ripple, ``N = Nfreq``
(:func:`fit_cable_reflection`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.polynomial import legendre
from scipy import stats
from scipy.ndimage import median_filter

#: Delays (ns) a reflection is claimed at: from the shortest a smooth bandpass of the
#: default order leaves alone (:func:`auto_smooth_order`) to a few cable lengths.
REFLECTION_DELAYS_NS = (90.0, 500.0)
#: Resolution elements (``1 / bandwidth``) within which a best delay in the range is a
#: side lobe of shorter structure that fits better (:attr:`BandpassFit.shorter_tau_ns`):
#: a localised bump rings at ~64 ns with side minima at 90-106 ns, 2-3.5 elements on.
SIDE_LOBE_ELEMENTS = 4.0


@dataclass(frozen=True)
class BandpassFit:
    """Fit of the fitted ``G(nu)`` by a smooth bandpass, optionally times a ripple.

    Attributes
    ----------
    chi2, nfreq, nparam
        Chi-square over channels (all antennas and pols), channels, parameters.
    a, sigma_a, tau_ns, sigma_tau_ns, phi, sigma_phi
        Ripple parameters (``NaN`` for the smooth fit); the delay is shared by all
        antennas and pols, ``a`` and ``phi`` are those of the first (see ``per_feed``).
    per_feed
        ``a``, ``phi`` and their sigmas for every antenna/pol row, in order.
    at_edge
        The best delay in the range searched is none: refined, it lies below the range
        (the chi^2 falls on towards shorter delays, scanned from half the range's lower
        end), or within one resolution element of its upper end: bandpass structure
        shorter or longer than the delays searched rather than a reflection.
    smooth_order
        Legendre order of the smooth bandpass.
    masked_channels
        Channels left out as narrow-band outliers of the smooth bandpass.
    delay_range_ns
        The delays a reflection is claimed at (the upper end capped below Nyquist).
    shorter_tau_ns
        The scan's best delay below the range when it fits better than the best in the
        range (shorter bandpass structure), else NaN.
    """

    chi2: float
    nfreq: int
    nparam: int
    a: float = float("nan")
    sigma_a: float = float("nan")
    tau_ns: float = float("nan")
    sigma_tau_ns: float = float("nan")
    phi: float = float("nan")
    sigma_phi: float = float("nan")
    per_feed: tuple[dict[str, float], ...] = ()
    at_edge: bool = False
    smooth_order: int = 0
    masked_channels: int = 0
    delay_range_ns: tuple[float, float] = (float("nan"), float("nan"))
    shorter_tau_ns: float = float("nan")

    @property
    def reduced_chi2(self) -> float:
        """``chi^2 / dof``."""
        return self.chi2 / max(self.nfreq - self.nparam, 1)


def _bandpass_chi2(
    freqs: np.ndarray, g: np.ndarray, sg: np.ndarray, order: int, tau: float | None
) -> tuple[float, np.ndarray, np.ndarray]:
    x = 2 * (freqs - freqs[0]) / (freqs[-1] - freqs[0]) - 1
    basis = legendre.legvander(x, order)  # (F, O+1)
    ok = np.isfinite(g) & np.isfinite(sg) & (sg > 0)
    wsq = np.where(ok, 1 / np.where(ok, sg, 1.0), 0.0)
    smooth_coef = np.linalg.lstsq(basis * wsq[:, None], np.where(ok, g, 0) * wsq, rcond=None)[0]
    if tau is None:
        cols = basis
    else:
        smooth = basis @ smooth_coef
        ph = 2 * np.pi * freqs * tau
        cols = np.hstack([basis, (smooth * np.cos(ph))[:, None], (smooth * np.sin(ph))[:, None]])
    a = cols * wsq[:, None]
    coef, *_ = np.linalg.lstsq(a, np.where(ok, g, 0) * wsq, rcond=None)
    chi2 = float(np.sum((a @ coef - np.where(ok, g, 0) * wsq) ** 2))
    cov = np.linalg.pinv(a.T @ a)
    return chi2, coef, cov


class _RippleScan:
    """Total chi^2 of :func:`_bandpass_chi2` with a ripple, summed over rows, for many delays.

    The same least-squares fits, all rows at once: each row's weighted smooth basis is
    factorised once (QR), and for every delay only the two ripple columns are projected
    off it, so a scan costs a few batched matrix products per delay instead of a
    least-squares solve per row and delay (a whole HERA file has 700 rows and ~370
    delays). Rows whose smooth basis is (nearly) rank-deficient over their usable channels
    are fitted one by one as before.
    """

    def __init__(self, freqs: np.ndarray, g2: np.ndarray, s2: np.ndarray, order: int) -> None:
        x = 2 * (freqs - freqs[0]) / (freqs[-1] - freqs[0]) - 1
        basis = legendre.legvander(x, order)  # (F, O+1)
        ok = np.isfinite(g2) & np.isfinite(s2) & (s2 > 0)
        wsq = np.where(ok, 1 / np.where(ok, s2, 1.0), 0.0)  # (R, F)
        b = np.where(ok, g2, 0.0) * wsq
        a = basis[None] * wsq[..., None]  # (R, F, O+1)
        q, r = np.linalg.qr(a)
        diag = np.abs(np.diagonal(r, axis1=1, axis2=2))
        full = (ok.sum(axis=1) > order + 3) & (diag.min(axis=1) > 1e-10 * diag.max(axis=1))
        self.freqs, self.order = freqs, order
        self.rows = [(g2[i], s2[i]) for i in np.flatnonzero(~full)]
        q, r, b, wsq = q[full], r[full], b[full], wsq[full]
        qtb = np.einsum("rfk,rf->rk", q, b)
        self.resid = b - np.einsum("rfk,rk->rf", q, qtb)  # off the smooth basis
        self.null = (self.resid**2).sum(axis=1)
        coef = np.linalg.solve(r, qtb[..., None])[..., 0]  # smooth fit of each row
        smooth_w = (coef @ basis.T) * wsq  # weighted smooth bandpass (R, F)
        # the ripple columns are smooth_w cos / sin: with c = s cos(2 pi nu tau) etc.,
        # Q^T c = (Q s)^T cos and |c - Q Q^T c|^2 = |c|^2 - |Q^T c|^2 (Q orthonormal), and
        # the residual is orthogonal to Q: every delay needs three small matrix products
        self.qs = np.ascontiguousarray(np.swapaxes(q * smooth_w[..., None], 1, 2))  # (R, K, F)
        self.s2 = smooth_w**2
        self.sr = smooth_w * self.resid

    def __call__(self, tau_s: float) -> float:
        """Return the total chi^2 with a ripple of delay ``tau_s`` (seconds)."""
        ph = 2 * np.pi * self.freqs * tau_s
        cs = np.stack([np.cos(ph), np.sin(ph)], axis=-1)  # (F, 2)
        qtc = (self.qs.reshape(-1, cs.shape[0]) @ cs).reshape(*self.qs.shape[:2], 2)
        trig = np.stack([cs[:, 0] ** 2, cs[:, 0] * cs[:, 1], cs[:, 1] ** 2], axis=-1)
        cc = self.s2 @ trig  # (R, 3): c^T c
        m = np.stack([cc[:, 0], cc[:, 1], cc[:, 1], cc[:, 2]], axis=-1).reshape(-1, 2, 2)
        m = m - np.swapaxes(qtc, 1, 2) @ qtc
        v = self.sr @ cs  # (R, 2)
        gain = np.einsum("rk,rkl,rl->r", v, np.linalg.pinv(m, hermitian=True), v)
        total = float(np.sum(self.null - gain))
        for g, s in self.rows:
            total += _bandpass_chi2(self.freqs, g, s, self.order, tau_s)[0]
        return total


def auto_smooth_order(freqs: np.ndarray, min_delay_ns: float = 100.0) -> int:
    """Legendre order of a smooth bandpass that leaves delays >= ``min_delay_ns`` alone.

    A Legendre series of order ``N`` over a band ``B`` absorbs ripples of delay up to
    about ``N / (3.3 B)`` (>= 90 % of the variance of a cosine at ``N / (1.5 B)`` is
    left), so ``N = round(1.5 B min_delay)``, clipped to 4..24.
    """
    bandwidth = float(abs(freqs[-1] - freqs[0]))
    return int(np.clip(round(1.5 * bandwidth * min_delay_ns * 1e-9), 4, 24))


def _narrowband_outliers(
    freqs: np.ndarray, g: np.ndarray, sg: np.ndarray, order: int, threshold: float = 6.0
) -> np.ndarray:
    """Channels whose gain departs from the smooth bandpass by a narrow feature (RFI)."""
    x = 2 * (freqs - freqs[0]) / (freqs[-1] - freqs[0]) - 1
    ok = np.isfinite(g) & np.isfinite(sg) & (sg > 0)
    if ok.sum() <= order + 2:
        return ~ok
    coef = legendre.legfit(x[ok], g[ok], order, w=1 / sg[ok])
    r = np.where(ok, (g - legendre.legval(x, coef)) / np.where(ok, sg, 1.0), 0.0)
    dev = r - median_filter(r, size=9, mode="mirror")
    sigma = 1.4826 * np.median(np.abs(dev[ok] - np.median(dev[ok])))
    if not np.isfinite(sigma) or sigma <= 0:
        return ~ok
    return ~ok | (np.abs(dev - np.median(dev[ok])) > threshold * sigma)


def fit_cable_reflection(
    freqs: np.ndarray,
    gain: np.ndarray,
    sigma_gain: np.ndarray,
    *,
    smooth_order: int | None = None,
    tau_range_ns: tuple[float, float] = REFLECTION_DELAYS_NS,
) -> tuple[BandpassFit, BandpassFit]:
    """Fit ``G(nu)`` by a smooth Legendre bandpass, and by the same times ``1 + a cos``.

    The ripple is linearised, ``P(nu) + Pbar(nu) (c cos 2 pi nu tau + s sin 2 pi nu tau)``
    with ``Pbar`` the smooth fit; ``tau`` is scanned on a grid oversampled 8x relative to
    the delay resolution ``1 / bandwidth`` from half the range's lower end, the best minimum
    inside the range refined on a grid 20x finer around it (``BandpassFit.shorter_tau_ns``
    when one below the range fits better); its error is where ``chi^2`` rises by 1. The
    delay is common to all antennas and polarisations, the amplitude and phase are fitted
    for each (``per_feed``). Channels with narrow-band outliers from the smooth bandpass
    (RFI absorbed by the per-channel gain) are left out of both fits.

    Parameters
    ----------
    freqs
        ``(Nfreq,)`` Hz.
    gain, sigma_gain
        ``(..., Nfreq)`` fitted gain and its 1-sigma.
    smooth_order
        Legendre order of the smooth bandpass (default :func:`auto_smooth_order` for the
        shortest searched delay).
    tau_range_ns
        Delays a reflection is claimed at (capped at 0.95 of the Nyquist delay
        ``1 / (2 dnu)``); the scan starts at half the lower end.

    Returns
    -------
    (BandpassFit, BandpassFit)
        Smooth fit and smooth-with-ripple fit.
    """
    order = auto_smooth_order(freqs, tau_range_ns[0]) if smooth_order is None else smooth_order
    g2, s2, masked = _mask_narrowband(freqs, gain, sigma_gain, order)
    nyq = 0.5 / abs(freqs[1] - freqs[0]) * 1e9
    hi = min(tau_range_ns[1], 0.95 * nyq)
    resolution = 1e9 / (freqs[-1] - freqs[0])
    # scanned from half the shortest claimed delay, the best minimum taken inside the
    # range: a reflection at the range's lower end is a minimum inside the scan, shorter
    # structure (a localised bump or step rings down to ~0.7 of the claimed delay) is a
    # minimum below the range that reaches into it as a slope (refused: the refined best
    # lies below the range) or side lobes (refused in candidate_fits), and shorter
    # structure stronger than a reflection further up does not hide it
    lo = max(0.5 * tau_range_ns[0], resolution / 8)
    grid = np.arange(lo, hi, resolution / 8)
    rows = list(zip(g2, s2, strict=True))
    nused = int((np.isfinite(g2) & np.isfinite(s2)).sum())
    null = BandpassFit(
        sum(_bandpass_chi2(freqs, g, s, order, None)[0] for g, s in rows),
        nused,
        g2.shape[0] * (order + 1),
        smooth_order=order,
        masked_channels=masked,
    )
    if grid.size < 3:
        return null, null
    scan = _RippleScan(freqs, g2, s2, order)
    chis = np.array([scan(t * 1e-9) for t in grid])
    chis = np.where(np.isfinite(chis), chis, np.inf)
    # the best minimum inside the range: a point on the slope of a minimum below it is none
    claimed = np.flatnonzero(grid >= tau_range_ns[0])
    interior = [
        k
        for k in claimed
        if 0 < k < grid.size - 1 and chis[k] < chis[k - 1] and chis[k] <= chis[k + 1]
    ]
    pool = np.asarray(interior if interior else claimed, dtype=int)
    i = int(pool[np.argmin(chis[pool])]) if pool.size else int(np.argmin(chis))
    deepest = int(np.argmin(chis))
    shorter = float(grid[deepest]) if chis[deepest] < chis[i] else float("nan")
    fine = np.linspace(grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)], 41)
    fchis = np.array([scan(t * 1e-9) for t in fine])
    j = int(np.argmin(fchis))
    tau = float(fine[j])
    inside = fine[fchis <= fchis[j] + 1.0]
    sig_tau = max(float(inside.max() - inside.min()) / 2, float(fine[1] - fine[0]))
    feeds = _ripple_per_feed(freqs, rows, order, tau, sig_tau)
    rip = BandpassFit(
        float(fchis[j]),
        null.nfreq,
        null.nparam + 2 * g2.shape[0] + 1,
        feeds[0]["a"],
        feeds[0]["sigma_a"],
        tau,
        sig_tau,
        feeds[0]["phi"],
        feeds[0]["sigma_phi"],
        per_feed=tuple(feeds),
        at_edge=bool(tau < tau_range_ns[0] or hi - tau < resolution),
        smooth_order=order,
        masked_channels=masked,
        delay_range_ns=(float(tau_range_ns[0]), float(hi)),
        shorter_tau_ns=shorter,
    )
    return null, rip


@dataclass(frozen=True)
class RippleHalves:
    """The ripple of one delay fitted on the band's two halves separately.

    Attributes
    ----------
    lower, upper
        Every antenna-pol's ``(c, s)``, the ripple's quadratures relative to the smooth
        bandpass (``a = hypot(c, s)``), in each half, ``(Nrow, 2)``.
    chi2, dof, p_value
        The halves' difference against its covariance, summed over antenna-pols (two
        degrees of freedom each), and its survival probability.
    p_lower, p_upper
        Each half's ripple against zero (the same units and degrees of freedom): the
        survival probability of its Wald statistic.
    relative_difference
        ``|lower - upper|`` over the whole band's amplitude (root sums of squares over the
        antenna-pols, each less what noise adds to it).
    """

    lower: np.ndarray
    upper: np.ndarray
    chi2: float
    dof: int
    p_value: float
    relative_difference: float
    p_lower: float = 1.0
    p_upper: float = 1.0


def ripple_halves(
    freqs: np.ndarray, gain: np.ndarray, sigma_gain: np.ndarray, rip: BandpassFit
) -> RippleHalves:
    """Fit ``rip``'s delay on each half of the band, to see the ripple run through both.

    A reflection is a ripple across the whole band, with one amplitude and phase; what the
    smooth bandpass leaves of structure in one part of the band (a step or a bump near an
    edge) can pass for a ripple of some delay, carried by that part alone. Each half gets
    its own smooth bandpass (half the whole band's order, at least 4: the same shortest
    delay unless clipped) and the
    two ripple columns at ``rip.tau_ns`` (the same narrow-band channels left out as for the
    whole); the statistics are in units of the ripple fit's overdispersion. The verdict is
    :func:`autocal.diagnosis.candidate_fits.reflection_refusal`'s (measured in
    ``tests/diagnosis/test_bandpass.py``).
    """
    g2, s2, _ = _mask_narrowband(freqs, gain, sigma_gain, rip.smooth_order)
    mid = freqs.size // 2
    halves = (slice(0, mid), slice(mid, None))
    order = max(4, -(-rip.smooth_order // 2))  # half the band, the same shortest delay
    quads = np.full((2, g2.shape[0], 2), np.nan)
    covs = np.full((2, g2.shape[0], 2, 2), np.nan)
    for i, (g, s) in enumerate(zip(g2, s2, strict=True)):
        for h, part in enumerate(halves):
            if int((np.isfinite(g[part]) & np.isfinite(s[part])).sum()) > order + 3:
                _, coef, cov = _bandpass_chi2(
                    freqs[part], g[part], s[part], order, rip.tau_ns * 1e-9
                )
                quads[h, i], covs[h, i] = coef[-2:], cov[-2:, -2:]
    diff = quads[0] - quads[1]
    cdiff = covs.sum(axis=0)
    amp_all = np.array([f["a"] for f in rip.per_feed])
    sig_all = np.array([f["sigma_a"] for f in rip.per_feed])
    ok = (
        np.all(np.isfinite(diff), axis=1)
        & np.all(np.isfinite(cdiff), axis=(1, 2))
        & np.isfinite(amp_all)
        & np.isfinite(sig_all)
    )
    chi2 = float(
        sum(
            d @ np.linalg.pinv(c, hermitian=True) @ d
            for d, c in zip(diff[ok], cdiff[ok], strict=True)
        )
    )
    # in units of the ripple fit's own overdispersion, as the search's statistic is
    chat = max(1.0, rip.reduced_chi2)
    chi2 /= chat
    dof = 2 * int(ok.sum())

    against_none = [
        sum(
            q @ np.linalg.pinv(c, hermitian=True) @ q
            for q, c in zip(quads[h][ok], covs[h][ok], strict=True)
        )
        / chat
        for h in (0, 1)
    ]
    # |lower - upper| over the whole band's amplitude, both less what noise alone adds to
    # them (the trace of the difference's covariance; twice the amplitude's variance), so
    # that many antenna-pols of modest signal do not add up to a difference
    amp, sig_amp = amp_all[ok], sig_all[ok]
    signal = float(np.sum(diff[ok] ** 2) - np.trace(cdiff[ok], axis1=1, axis2=2).sum())
    whole = float(np.sum(amp**2 - 2 * sig_amp**2))
    return RippleHalves(
        lower=quads[0],
        upper=quads[1],
        chi2=chi2,
        dof=dof,
        p_value=float(stats.chi2.sf(chi2, dof)) if dof else 1.0,
        relative_difference=float(np.sqrt(max(signal, 0.0) / whole)) if whole > 0 else 0.0,
        p_lower=float(stats.chi2.sf(against_none[0], dof)) if dof else 1.0,
        p_upper=float(stats.chi2.sf(against_none[1], dof)) if dof else 1.0,
    )


def _mask_narrowband(
    freqs: np.ndarray, gain: np.ndarray, sigma_gain: np.ndarray, order: int
) -> tuple[np.ndarray, np.ndarray, int]:
    """Return the gains and sigmas as rows, narrow-band outliers' sigmas NaN, and their count."""
    g2 = np.asarray(gain, float).reshape(-1, freqs.size)
    s2 = np.asarray(sigma_gain, float).reshape(-1, freqs.size).copy()
    masked = 0
    for i in range(g2.shape[0]):
        bad = _narrowband_outliers(freqs, g2[i], s2[i], order)
        masked += int((bad & np.isfinite(g2[i])).sum())
        s2[i, bad] = np.nan
    return g2, s2, masked


def _ripple_per_feed(
    freqs: np.ndarray,
    rows: list[tuple[np.ndarray, np.ndarray]],
    order: int,
    tau: float,
    sig_tau: float,
) -> list[dict[str, float]]:
    """Return every row's ripple amplitude and phase, with their 1-sigma, at delay ``tau`` ns."""
    # the phase is referred to nu = 0: its marginal error includes the delay's
    nu_mean = float(np.mean(freqs))
    feeds = []
    for g, s in rows:
        _, coef, cov = _bandpass_chi2(freqs, g, s, order, tau * 1e-9)
        c, sn = coef[-2], coef[-1]
        a = float(np.hypot(c, sn))
        ccs = cov[-2:, -2:]
        grad_a = np.array([c, sn]) / max(a, 1e-300)
        grad_p = np.array([sn, -c]) / max(a, 1e-300) ** 2
        feeds.append(
            {
                "a": a,
                "sigma_a": float(np.sqrt(abs(grad_a @ ccs @ grad_a))),
                "phi": float(np.arctan2(-sn, c)),
                "sigma_phi": float(
                    np.hypot(
                        np.sqrt(abs(grad_p @ ccs @ grad_p)), 2 * np.pi * nu_mean * sig_tau * 1e-9
                    )
                ),
            }
        )
    return feeds
