"""The comparison figure: gains, ratio with its 2-sigma band, its delay spectrum and drift.

matplotlib is imported lazily by :mod:`autocal.plots`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from autocal.compare.comparison import Comparison
from autocal.plots import band, figure, save_figure


def plot_comparison(comparison: Comparison, path: str | Path, title: str | None = None) -> Path:
    """Plot the compared gains, the ratio with its 2-sigma band, its delay spectrum and drift.

    The last panel shows the reference's ``|g_ref|^2(t) / mean`` (median over the band)
    and, when given, the raw auto's ``power / mean`` against time, with the offset, the
    stability verdict and the systematics budget as text.

    Parameters
    ----------
    comparison
        The comparison.
    path
        Output image (PNG).
    title
        Figure title.

    Returns
    -------
    pathlib.Path
        The written file.
    """
    c = comparison
    fmhz = c.freqs / 1e6
    fig, axes = figure(4, 1, (9, 13))
    for ia, ant in enumerate(c.antennas):
        for ip, pol in enumerate(c.pols):
            label = f"ant {ant} {pol}"
            mask = c.valid[ia, ip]
            auto = np.where(mask, c.auto[ia, ip], np.nan)
            ref = np.where(mask, c.reference[ia, ip], np.nan)
            (line,) = axes[0].plot(fmhz, auto, lw=1, label=f"{label} autos")
            axes[0].plot(fmhz, ref, lw=1, ls="--", color=line.get_color(), label=f"{label} ref")
            sig = np.where(mask, c.sigma_ratio[ia, ip], np.nan)
            band(axes[1], fmhz, c.ratio[ia, ip], sig, label)
            if c.delay_amplitude is not None and c.delays is not None:
                # tau = 0 of the mean-subtracted ratio is ~0 by construction: not shown
                axes[2].semilogy(
                    c.delays[1:] * 1e9, c.delay_amplitude[ia, ip, 1:], lw=1, label=label
                )
    axes[0].set(
        xlabel="frequency [MHz]",
        ylabel="|g| [sqrt(raw/K)]" if c.mode == "absolute" else "|g| / mean",
        title="autos (solid) vs reference converted (dashed)"
        if c.mode == "absolute"
        else "normalised shapes: autos (solid), reference (dashed)",
    )
    axes[1].axhline(1.0, color="k", lw=0.8)
    good = c.ratio[c.valid & np.isfinite(c.ratio)]
    if good.size:
        # robust limits (single RFI channels with huge error bars must not squash the plot)
        lo, hi = np.percentile(good, [1, 99])
        lo, hi = min(lo, 1.0), max(hi, 1.0)
        pad = 0.15 * (hi - lo) + 0.02
        axes[1].set_ylim(lo - pad, hi + pad)
    axes[1].set(
        xlabel="frequency [MHz]", ylabel="|g_auto| / |g_ref|", title="ratio with 2-sigma band"
    )
    axes[2].set(
        xlabel="delay [ns]",
        ylabel="|FT(ratio - mean)| / |FT(mean)|",
        title="delay spectrum of the ratio",
    )
    _plot_drift(axes[3], c)
    if c.antennas.size * len(c.pols) <= 12:
        for i, ax in enumerate(axes):
            if ax.get_legend_handles_labels()[0]:
                ax.legend(fontsize=7, ncol=2, loc="lower right" if i == 3 else "best")
    ref_files = c.summary.get("reference", {}).get("files", [])
    name = Path(ref_files[0]).name if ref_files else "reference"
    fig.suptitle(title or f"{c.mode} comparison with {name}", fontsize=10)
    return save_figure(fig, path)


def _plot_drift(ax: Any, c: Comparison) -> None:
    """Plot the reference's |g|^2(t)/mean and the raw auto's power/mean against time."""
    t0 = None
    if c.reference_jds is not None and c.reference_series is not None:
        t0 = float(c.reference_jds[0])
        minutes = (c.reference_jds - t0) * 1440.0
        for ia, ant in enumerate(c.antennas):
            for ip, pol in enumerate(c.pols):
                (line,) = ax.plot(
                    minutes,
                    c.reference_series[ia, ip],
                    lw=1,
                    marker=".",
                    label=f"ant {ant} {pol} ref",
                )
                if c.auto_series and (int(ant), pol) in c.auto_series:
                    jds, values = c.auto_series[(int(ant), pol)]
                    ax.plot(
                        (np.asarray(jds) - t0) * 1440.0,
                        values,
                        lw=1,
                        ls=":",
                        color=line.get_color(),
                        label=f"ant {ant} {pol} raw auto",
                    )
    ax.axhline(1.0, color="k", lw=0.8)
    ax.set(
        xlabel="minutes since the first reference time",
        ylabel="value / time mean (median over band)",
        title="drift: reference |g_ref|^2 (solid) and raw auto power (dotted)",
    )
    lines = [_budget_text(row) for row in c.summary.get("per_antenna_pol", [])][:6]
    if lines:
        lo, hi = ax.get_ylim()  # headroom for the text above the curves
        ax.set_ylim(lo, hi + (hi - lo) * 0.1 * (len(lines) + 1))
        ax.text(
            0.01,
            0.98,
            "\n".join(lines),
            transform=ax.transAxes,
            fontsize=6.5,
            va="top",
            ha="left",
            bbox={"facecolor": "white", "alpha": 0.8, "lw": 0},
        )


def _fmt(value: Any, spec: str = ".3f") -> str:
    """Format a number, ``"n/a"`` for ``None`` or non-finite values."""
    return "n/a" if value is None or not np.isfinite(value) else format(value, spec)


def _budget_text(row: dict[str, Any]) -> str:
    """One line per antenna/pol: offset, drift verdict and systematics."""
    parts = [
        f"ant {row['antenna']} {row['pol']}: offset {_fmt(row.get('offset'), '+.3f')} "
        f"+- {_fmt(row.get('offset_error'))} ({_fmt(row.get('offset_sigma'), '+.1f')} sigma)",
        f"ref drift {_fmt(row.get('reference_drift'), '+.1%')} vs auto "
        f"{_fmt(row.get('auto_drift'), '+.1%')}: "
        + {True: "stable", False: "UNSTABLE", None: "untested"}[row.get("reference_stable")],
    ]
    sysm = row.get("systematics") or {}
    om = (sysm.get("omega_source") or {}).get("shift")
    pc = sysm.get("pol_convention") or {}
    sky = sysm.get("sky_model") or {}
    if om is not None:
        parts.append(f"Omega(hera_sim) {om:+.1%}")
    if pc.get("shift") is not None:
        parts.append(f"pol '{pc['alternative']}' {pc['shift']:+.1%} ({pc['source']} {pc['used']})")
    if sky.get("spread_fraction") is not None:
        parts.append(f"sky spread {sky['spread_fraction']:.1%}")
    return "; ".join(parts)
