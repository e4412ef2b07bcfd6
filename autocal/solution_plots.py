"""Figures of a calibration solution: the solution, its delay spectra, data vs model.

Each ``*_figure`` function builds and returns a matplotlib figure (tests read its axes);
each ``plot_*`` writes one with :func:`autocal.plots.save_figure`. Axis scales come from
percentiles of the unflagged channels inside the band (:func:`autocal.plots.band_core`);
the band edges are greyed out.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from autocal.compare.delay import DelayError, delay_spectrum
from autocal.plots import (
    ABS_G_LABEL,
    G_LABEL,
    TRXR_LABEL,
    band,
    band_core,
    channel_image,
    nan_quantiles,
    robust_limits,
    robust_ylim,
    run_title,
    save_figure,
    shade_band_edges,
    showing_note,
)

#: Curves (antennas x polarisations) up to which ``solution.png`` and ``delay_spectra.png``
#: draw every antenna's line; above it they show the whole array as images / spreads.
MAX_SOLUTION_CURVES = 12


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_solution(
    solution: Any, path: str | Path, title: str | None = None, stems: tuple[str, ...] = ()
) -> Path:
    """Write :func:`solution_figure` to ``path``; return it."""
    return save_figure(solution_figure(solution, title, stems), path)


def solution_figure(solution: Any, title: str | None = None, stems: tuple[str, ...] = ()) -> Any:
    """Plot a solution against frequency.

    Up to :data:`MAX_SOLUTION_CURVES` antenna-polarisations: ``|g|``, ``G`` and ``Trxr``
    of each with its 2-sigma band. More: every antenna as a row of an image of ``|g|``,
    ``Trxr`` and ``chi^2 / dof`` (log scale) per polarisation, beside the median over
    antennas and the 16-84 % spread between them.

    Parameters
    ----------
    solution
        A :class:`autocal.fit.solution.Solution`.
    title
        Figure title (default: :func:`autocal.plots.run_title` and the fit).
    stems
        Input file stems for the default title.

    Returns
    -------
    matplotlib.figure.Figure
    """
    kind = solution.model.kind
    core = band_core(solution.G, solution.flags)
    if solution.antennas.size * len(solution.pols) <= MAX_SOLUTION_CURVES:
        bands = (
            "2-sigma bands: total (light), statistical (dark)"
            if solution.total is not None
            else "2-sigma bands (statistical)"
        )
        fig, default = _solution_lines(solution, core), f"{kind} fit, {bands}"
    else:
        fig, default = _solution_array(solution, core), f"{kind} fit"
    head = run_title(solution.jds, solution.antennas, solution.pols, stems)
    fig.suptitle(title or f"{head}\n{default}; grey: band edges (outside the scales)", fontsize=9)
    return fig


def _solution_lines(solution: Any, core: np.ndarray) -> Any:
    fmhz = solution.freqs / 1e6
    fig = _pyplot().figure(figsize=(11, 9.6))
    # the legend right of the panels: over them it hides the curves of many antennas
    grid = fig.add_gridspec(3, 1, left=0.08, right=0.76, bottom=0.06, top=0.93, hspace=0.12)
    axes = [fig.add_subplot(grid[i, 0]) for i in range(3)]
    stat = solution.total is not None
    ncurve = solution.antennas.size * len(solution.pols)
    alpha = (0.18, 0.35) if ncurve <= 2 else (0.07, 0.2)  # overlapping bands stay readable
    values = (
        (solution.abs_g, solution.sigma_abs_g, solution.sigma_abs_g_stat, ABS_G_LABEL),
        (solution.G, solution.sigma_G, solution.sigma_G_stat, G_LABEL),
        (solution.Trxr, solution.sigma_Trxr, solution.sigma_Trxr_stat, TRXR_LABEL),
    )
    weak = solution.total.separation() if stat else np.zeros((0, 0), bool)
    scaled = ~solution.flags & core
    for ax, (val, sig, sig_stat, name) in zip(axes, values, strict=True):
        for ia, ant in enumerate(solution.antennas):
            for ip, pol in enumerate(solution.pols):
                label = f"ant {ant} {pol}" + (
                    " (weak G-n separation)" if stat and weak[ia, ip] else ""
                )
                inner = sig_stat[ia, ip] if stat else None
                band(ax, fmhz, val[ia, ip], sig[ia, ip], label, inner=inner, alpha=alpha)
        ax.set(ylabel=name, xlim=(fmhz.min(), fmhz.max()))
        robust_ylim(ax, val[scaled], 1.0, 99.0)
        shade_band_edges(ax, fmhz, core)
        if ax is not axes[-1]:
            ax.tick_params(labelbottom=False)
    axes[-1].set(xlabel="frequency [MHz]")
    axes[0].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return fig


def _solution_array(solution: Any, core: np.ndarray) -> Any:
    import matplotlib

    fmhz = solution.freqs / 1e6
    npol, nant = len(solution.pols), solution.antennas.size
    # a fixed grid (images, colour bar, gap, spread over antennas) instead of constrained
    # layout, which took 0.8 s of this figure's 2 s
    fig = _pyplot().figure(figsize=(3.4 * npol + 5.0, 9.5))
    widths = [1.0] * npol + [0.05, 0.32, 1.3]
    grid = fig.add_gridspec(
        3, npol + 3, width_ratios=widths, left=0.06, right=0.99, bottom=0.06, top=0.9,
        wspace=0.12, hspace=0.38,
    )  # fmt: skip
    rows = (
        (ABS_G_LABEL, solution.abs_g, "viridis"),
        (TRXR_LABEL, solution.Trxr, "viridis"),
        ("chi2 / dof", solution.reduced_chi2, "magma"),
    )
    ticks = np.unique(np.linspace(0, nant - 1, min(nant, 8)).astype(int))
    for r, (name, values, cmap) in enumerate(rows):
        values = np.where(solution.flags, np.nan, values)
        style: dict[str, Any] = {"cmap": matplotlib.colormaps[cmap].with_extremes(bad="0.85")}
        if r == 2:  # chi2/dof spans decades where the model fails: a log scale around 1
            limits = _chi2_limits(values[..., core])
            style["norm"] = matplotlib.colors.LogNorm(*limits)
        else:
            limits = robust_limits(values[..., core]) or (None, None)
            style.update(vmin=limits[0], vmax=limits[1])
        for ip, pol in enumerate(solution.pols):
            ax = fig.add_subplot(grid[r, ip])
            image = channel_image(ax, fmhz, values[:, ip], **style)
            ax.set_yticks(ticks, [str(a) for a in solution.antennas[ticks]] if ip == 0 else [])
            ax.set(ylabel="antenna" if ip == 0 else None, title=f"{name}, {pol}")
            if r == 2:
                ax.set_xlabel("frequency [MHz]")
        fig.colorbar(image, cax=fig.add_subplot(grid[r, npol]))
        ax = fig.add_subplot(grid[r, npol + 2])
        median, lo, hi = nan_quantiles(values, (0.5, 0.16, 0.84))
        for ip, pol in enumerate(solution.pols):
            (line,) = ax.plot(fmhz, median[ip], lw=1, label=f"{pol} median")
            ax.fill_between(fmhz, lo[ip], hi[ip], color=line.get_color(), alpha=0.25, lw=0)
        if r == 2:
            ax.axhline(1.0, color="k", lw=0.6, ls="--")
            ax.set(yscale="log", xlabel="frequency [MHz]")
        if limits[0] is not None:
            ax.set_ylim(*limits)
        shade_band_edges(ax, fmhz, core)
        ax.set(ylabel=name, title="spread over antennas (16-84 %)")
        ax.legend(fontsize=7, loc="upper right")
    return fig


def _chi2_limits(values: np.ndarray) -> tuple[float, float]:
    """Return log-scale limits of ``chi^2 / dof``.

    The central 2-98 % of the positive values, widened to at least 0.5 to 2.
    """
    positive = values[np.isfinite(values) & (values > 0)]
    lo, hi = np.percentile(np.log10(positive), [2, 98]) if positive.size else (0.0, 0.0)
    return min(10.0**lo, 0.5), max(10.0**hi, 2.0)


def plot_delay_spectra(
    solution: Any, path: str | Path, title: str | None = None, stems: tuple[str, ...] = ()
) -> Path:
    """Write :func:`delay_figure` to ``path``; return it."""
    return save_figure(delay_figure(solution, title, stems), path)


def delay_figure(solution: Any, title: str | None = None, stems: tuple[str, ...] = ()) -> Any:
    """Delay spectra of ``G`` and ``Trxr`` (:func:`autocal.compare.delay.delay_spectrum`).

    Blackman-Harris windowed, normalised to zero delay, in dB; flagged channels and the
    band edges (:func:`autocal.plots.band_core`) get zero weight. One line per
    antenna-pol up to :data:`MAX_SOLUTION_CURVES`, else the median over antennas and its
    16-84 % spread per pol. A spectrum without 4 usable channels is left out (and counted
    in 'showing N of M').

    Returns
    -------
    matplotlib.figure.Figure
    """
    fig = _pyplot().figure(figsize=(9, 7))
    grid = fig.add_gridspec(2, 1, left=0.1, right=0.98, bottom=0.08, top=0.9, hspace=0.3)
    axes = [fig.add_subplot(grid[i, 0]) for i in range(2)]
    core = band_core(solution.G, solution.flags)
    flags = solution.flags | ~core
    usable = np.count_nonzero(~flags, axis=-1) >= 4  # (A, P)
    labels = [f"ant {a} {p}" for a in solution.antennas for p in solution.pols]
    total = len(labels)
    for ax, (name, values) in zip(axes, (("G", solution.G), ("Trxr", solution.Trxr)), strict=True):
        ax.set(xlabel="delay [ns]", ylabel=f"|FT({name})| / |FT({name})(0)| [dB]")
        ax.set_title(f"delay spectrum of {name} (band edges and flagged channels excluded)")
        try:
            spec = delay_spectrum(values[usable], solution.freqs, flags=flags[usable])
        except DelayError as exc:  # a non-uniform grid or nothing usable
            ax.text(0.5, 0.5, f"no delay spectrum: {exc}", ha="center", transform=ax.transAxes)
            continue
        with np.errstate(divide="ignore"):
            db = 20 * np.log10(spec.amplitude)
        shown = [lab for lab, ok in zip(labels, usable.ravel(), strict=True) if ok]
        if total <= MAX_SOLUTION_CURVES:
            for lab, row in zip(shown, db, strict=True):
                ax.plot(spec.delays_ns, row, lw=0.9, label=lab)
        else:
            pol_of = np.broadcast_to(np.arange(len(solution.pols)), usable.shape)[usable]
            for ip, pol in enumerate(solution.pols):
                rows = db[pol_of == ip]
                if rows.size == 0:
                    continue
                median, lo, hi = nan_quantiles(np.where(np.isfinite(rows), rows, np.nan),
                                               (0.5, 0.16, 0.84))  # fmt: skip
                (line,) = ax.plot(spec.delays_ns, median, lw=1, label=f"{pol} median")
                ax.fill_between(spec.delays_ns, lo, hi, color=line.get_color(), alpha=0.25, lw=0)
        finite = db[np.isfinite(db)]
        if finite.size:
            ax.set_ylim(max(np.percentile(finite, 1) - 5, -120), 5)
        ax.set_xlim(0, spec.delays_ns.max())
        if ax.get_legend_handles_labels()[1]:  # nothing drawn when every spectrum is flagged
            ax.legend(fontsize=7, ncol=2, loc="upper right")
    showing_note(fig, int(np.count_nonzero(usable)), total)
    head = run_title(solution.jds, solution.antennas, solution.pols, stems)
    fig.suptitle(title or f"{head}\ndelay spectra, Blackman-Harris window", fontsize=9)
    return fig


def plot_data_model(curves: dict[str, np.ndarray], path: str | Path, **kw: Any) -> Path:
    """Write :func:`data_model_figure` to ``path``; return it."""
    return save_figure(data_model_figure(curves, **kw), path)


def data_model_figure(
    curves: dict[str, Any],
    *,
    title: str | None = None,
    total: int | None = None,
    core: np.ndarray | None = None,
) -> Any:
    """Plot the data against the fitted model for the shown antenna-pols.

    Top: the spectra averaged over time (data solid, model dashed); middle: both averaged
    over the band's channels against LST; bottom: that average's fractional residual
    ``(data - model) / model`` in %.

    Parameters
    ----------
    curves
        ``labels`` (K,), ``freqs`` (Hz), ``lsts`` (hours, Nbins), ``data`` and ``model``
        ``(K, Nfreq)`` averaged over time, ``data_t`` and ``model_t`` ``(K, Nbins)``
        averaged over the band's channels (data units).
    title
        Figure title.
    total
        Antenna-pols there are ('showing K of total' when more than K).
    core
        ``(Nfreq,)`` channels inside the band (setting the scales; the rest greyed out).

    Returns
    -------
    matplotlib.figure.Figure
    """
    fmhz = np.asarray(curves["freqs"]) / 1e6
    data, model = curves["data"], curves["model"]
    core = np.ones(fmhz.size, bool) if core is None else core
    fig = _pyplot().figure(figsize=(9, 9.6))
    grid = fig.add_gridspec(3, 1, left=0.11, right=0.98, bottom=0.06, top=0.92, hspace=0.36)
    axes = [fig.add_subplot(grid[i, 0]) for i in range(3)]
    lsts = curves["lsts"]
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = 100 * (curves["data_t"] - curves["model_t"]) / curves["model_t"]
    for k, label in enumerate(curves["labels"]):
        (line,) = axes[0].plot(fmhz, data[k], lw=1, label=f"{label} data")
        color = line.get_color()
        axes[0].plot(fmhz, model[k], "--", color=color, lw=1, label=f"{label} model")
        axes[1].plot(
            lsts, curves["data_t"][k], ".-", ms=3, lw=1, color=color, label=f"{label} data"
        )
        axes[1].plot(lsts, curves["model_t"][k], "--", lw=1, color=color, label=f"{label} model")
        axes[2].plot(lsts, frac[k], ".-", ms=3, lw=0.8, color=color, label=label)
    axes[0].set(ylabel="autocorrelation [data units]", xlabel="frequency [MHz]",
                title="time-averaged spectrum (data solid, model dashed)",
                xlim=(fmhz.min(), fmhz.max()))  # fmt: skip
    robust_ylim(axes[0], np.concatenate([data, model])[..., core], 1.0, 99.0)
    shade_band_edges(axes[0], fmhz, core)
    axes[1].set(
        xlabel="LST [h]",
        ylabel="autocorrelation [data units]",
        title="mean over the band's channels with data at every LST (edges excluded) vs LST",
    )
    axes[2].set(xlabel="LST [h]", ylabel="(data - model) / model [%]",
                title="fractional residual of the band average")  # fmt: skip
    axes[2].axhline(0, color="k", lw=0.6)
    axes[0].legend(fontsize=7, ncol=2, loc="upper right")  # the colours of every panel
    showing_note(fig, len(curves["labels"]), total or len(curves["labels"]))
    fig.suptitle(title or "data vs model", fontsize=9)
    return fig
