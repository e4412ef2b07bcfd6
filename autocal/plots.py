"""Figures of autocal products (matplotlib, Agg backend, written atomically)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from autocal.core.files import atomic_path

logger = logging.getLogger(__name__)


def _pyplot() -> Any:
    """Return ``matplotlib.pyplot`` on the Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def figure(nrows: int, ncols: int, size: tuple[float, float]) -> tuple[Any, Any]:
    """Return ``(fig, axes)``: a grid of panels (inches) with constrained layout."""
    return _pyplot().subplots(nrows, ncols, figsize=size, constrained_layout=True)


def save_figure(fig: Any, path: str | Path) -> Path:
    """Save a figure atomically (PNG unless the suffix says otherwise) and close it."""
    import matplotlib.pyplot as plt

    path = Path(path)
    with atomic_path(path) as tmp:
        fmt = path.suffix.lstrip(".") or "png"
        # zlib level 3: a fifth of the PNG encoding time of the default 6, files ~10 % larger
        extra = {"pil_kwargs": {"compress_level": 3}} if fmt == "png" else {}
        fig.savefig(tmp, dpi=110, format=fmt, **extra)
    plt.close(fig)
    logger.info("wrote %s", path)
    return path


def plot_tsky(result: Any, path: str | Path, title: str | None = None) -> Path:
    """Plot a Tsky table: waterfall, Tsky vs LST at three frequencies, spectrum.

    Parameters
    ----------
    result
        A :class:`autocal.tsky.result.TskyResult`.
    path
        Output image.
    title
        Figure title (default: sky, beam and site from ``result.meta``).

    Returns
    -------
    pathlib.Path
        The written file.
    """
    fmhz = result.freqs / 1e6
    lsts = result.lsts
    fig, axes = figure(1, 3, (15, 4.2))
    order = np.argsort(lsts)
    if lsts.size > 1 and fmhz.size > 1:
        mesh = axes[0].pcolormesh(
            fmhz, lsts[order], result.tsky[order], shading="auto", norm=_lognorm(result.tsky)
        )
        fig.colorbar(mesh, ax=axes[0], label="Tsky [K]")
    else:
        axes[0].imshow(result.tsky, aspect="auto", norm=_lognorm(result.tsky))
    axes[0].set(xlabel="frequency [MHz]", ylabel="LST [h]", title="Tsky(nu, LST)")
    for idx in np.unique(np.linspace(0, fmhz.size - 1, 3).astype(int)):
        axes[1].plot(lsts[order], result.tsky[order, idx], label=f"{fmhz[idx]:.1f} MHz")
    axes[1].set(xlabel="LST [h]", ylabel="Tsky [K]", yscale="log", title="Tsky vs LST")
    axes[1].legend(fontsize=8)
    axes[2].loglog(fmhz, result.tsky.mean(axis=0), label="mean over LST")
    axes[2].fill_between(
        fmhz, result.tsky.min(axis=0), result.tsky.max(axis=0), alpha=0.3, label="range over LST"
    )
    axes[2].set(xlabel="frequency [MHz]", ylabel="Tsky [K]", title="spectrum")
    axes[2].legend(fontsize=8)
    if title is None:
        meta = result.meta
        sky = meta.get("sky", {}).get("model", "?") if isinstance(meta.get("sky"), dict) else "?"
        beam = meta.get("beam", {}) if isinstance(meta.get("beam"), dict) else {}
        site = meta.get("site", {}).get("name", "?") if isinstance(meta.get("site"), dict) else "?"
        beam_name = beam.get("file", beam.get("beam", "?"))
        title = (
            f"sky {sky}, beam {Path(str(beam_name)).name} {beam.get('pol', '')}, "
            f"site {site}, Tgnd {meta.get('tgnd_K', '?')} K, nside {meta.get('nside', '?')}"
        )
    fig.suptitle(title, fontsize=10)
    return save_figure(fig, path)


def _lognorm(values: np.ndarray) -> Any:
    from matplotlib.colors import LogNorm

    positive = values[values > 0]
    if positive.size == 0:
        return None
    return LogNorm(vmin=positive.min(), vmax=positive.max())


def band(
    ax: Any,
    x: np.ndarray,
    y: np.ndarray,
    sigma: np.ndarray,
    label: str,
    inner: np.ndarray | None = None,
    alpha: tuple[float, float] = (0.18, 0.35),
    **kw: Any,
) -> None:
    """Plot ``y`` with a shaded 2-sigma band (and a darker ``inner`` 2-sigma band).

    ``inner``: e.g. the statistical part of a total error drawn inside it; ``alpha``: the
    opacities of the band and of the inner band.
    """
    (line,) = ax.plot(x, y, label=label, lw=1, **kw)
    color = line.get_color()
    ax.fill_between(x, y - 2 * sigma, y + 2 * sigma, color=color, alpha=alpha[0], lw=0)
    if inner is not None:
        ax.fill_between(x, y - 2 * inner, y + 2 * inner, color=color, alpha=alpha[1], lw=0)


def robust_limits(
    values: np.ndarray, low: float = 2.0, high: float = 98.0
) -> tuple[float, float] | None:
    """Return limits spanning the central percentiles of the finite values, padded by 15 %.

    ``None`` when fewer than 10 values are finite.
    """
    finite = values[np.isfinite(values)]
    if finite.size < 10:
        return None
    lo, hi = np.percentile(finite, [low, high])
    pad = 0.15 * (hi - lo) if hi > lo else max(abs(hi), 1e-12) * 0.1
    return float(lo - pad), float(hi + pad)


def robust_ylim(ax: Any, values: np.ndarray, low: float = 2.0, high: float = 98.0) -> None:
    """Limit the y axis to the central percentiles of the finite values (RFI-proof)."""
    limits = robust_limits(values, low, high)
    if limits is not None:
        ax.set_ylim(*limits)


#: Axis labels of the solution's quantities, with their units: ``G`` converts kelvin into
#: the correlator's raw units (HERA: uncalibrated correlator units), ``|g| = sqrt(G)``.
G_LABEL = "G [data units / K]"
ABS_G_LABEL = "|g| [(data units / K)$^{1/2}$]"
TRXR_LABEL = "Trxr [K]"
RESIDUAL_LABEL = "(R - model) / sigma"

#: A channel is inside the band when the median gain over antenna-pols is at least this
#: fraction of its 90th percentile (the filter roll-off at the band edges is outside).
BAND_EDGE_FRACTION = 0.25


def run_title(
    jds: np.ndarray, antennas: np.ndarray, pols: tuple[str, ...], stems: tuple[str, ...] = ()
) -> str:
    """Return a figure title naming the files, the JD range and the antennas and pols.

    E.g. ``zen.2458116.30448.HH (+2 files) | JD 2458116.30448-2458116.32613 | ant 23 | ee, nn``.
    """
    parts = []
    if stems:
        more = len(stems) - 1
        parts.append(stems[0] + (f" (+{more} file{'s' if more > 1 else ''})" if more else ""))
    jds = np.asarray(jds, float)
    if jds.size:
        parts.append(f"JD {np.min(jds):.5f}-{np.max(jds):.5f}")
    ants = [str(a) for a in np.asarray(antennas).tolist()]
    if len(ants) <= 8:
        parts.append(("ant " if len(ants) == 1 else "ants ") + ", ".join(ants))
    else:
        parts.append(f"{len(ants)} antennas ({ants[0]}-{ants[-1]})")
    parts.append(", ".join(pols))
    return " | ".join(parts)


def file_stems(paths: Any) -> tuple[str, ...]:
    """Return the stems of input files (``zen.2458116.30448.HH`` of ``...HH.uvh5``)."""
    return tuple(Path(str(p)).name.removesuffix(".uvh5") for p in paths)


def band_core(gain: np.ndarray, flags: np.ndarray) -> np.ndarray:
    """Return a ``(Nfreq,)`` mask of the channels inside the band.

    The contiguous channels from the first to the last whose median ``gain`` over the
    unflagged antenna-pols is at least :data:`BAND_EDGE_FRACTION` of its 90th percentile;
    every channel when that leaves fewer than 4 (or no gain is finite).
    """
    values = np.where(flags, np.nan, gain).reshape(-1, gain.shape[-1])
    median = nan_quantiles(values, (0.5,))[0]
    finite = np.isfinite(median)
    core = np.ones(gain.shape[-1], bool)
    if np.count_nonzero(finite) < 4:
        return core
    inside = np.flatnonzero(
        finite & (median >= BAND_EDGE_FRACTION * np.percentile(median[finite], 90))
    )
    if inside.size < 4:
        return core
    core[:] = False
    core[inside[0] : inside[-1] + 1] = True
    return core


def shade_band_edges(ax: Any, fmhz: np.ndarray, core: np.ndarray) -> None:
    """Grey out the channels outside ``core`` (band edges, left out of the scales)."""
    if core.all() or not core.any():
        return
    step = abs(fmhz[1] - fmhz[0]) / 2 if fmhz.size > 1 else 0.0
    inside = np.flatnonzero(core)
    lo, hi = fmhz[inside[0]] - step, fmhz[inside[-1]] + step
    ax.axvspan(fmhz.min() - step, lo, color="0.85", zorder=0, lw=0)
    ax.axvspan(hi, fmhz.max() + step, color="0.85", zorder=0, lw=0)


#: Antenna-polarisations shown in a residual waterfall figure (``autocal calibrate``'s
#: ``residuals.png`` and ``data_model.png``, ``autocal diagnose``'s residual figures).
MAX_PLOTTED = 4


def waterfall_antennas(npol: int) -> int:
    """Return how many antennas (the first ones, with every pol) the waterfalls show.

    Whole antennas, at least one: ``MAX_PLOTTED // npol`` (2 antennas of 2 pols).
    """
    return max(1, MAX_PLOTTED // max(npol, 1))


def showing_note(fig: Any, shown: int, total: int, what: str = "antenna-pols") -> None:
    """Write 'showing N of M antenna-pols' in the figure's lower right when N < M."""
    if shown < total:
        fig.text(0.99, 0.005, f"showing {shown} of {total} {what}", ha="right", va="bottom",
                 fontsize=9, color="firebrick")  # fmt: skip


def symmetric_limit(values: np.ndarray, percentile: float = 99.0) -> float:
    """Return the ``percentile`` of ``|values|`` over the finite ones (1 without any)."""
    finite = np.abs(values[np.isfinite(values)])
    return float(np.percentile(finite, percentile)) if finite.size else 1.0


def channel_image(ax: Any, fmhz: np.ndarray, values: np.ndarray, **style: Any) -> Any:
    """Draw ``(Nrow, Nfreq)`` values against frequency (MHz), one row per unit of y.

    On a regular increasing channel grid this is an image of the same cells as
    ``pcolormesh`` (much faster to render for thousands of channels); otherwise a mesh.
    Rows are centred on ``0 .. Nrow - 1``.
    """
    nrow = values.shape[0]
    step = np.diff(fmhz)
    if fmhz.size > 1 and step[0] > 0 and np.allclose(step, step[0], rtol=1e-6, atol=0):
        half = step[0] / 2
        extent = (fmhz[0] - half, fmhz[-1] + half, -0.5, nrow - 0.5)
        kw = {"aspect": "auto", "origin": "lower", "interpolation": "nearest"}
        return ax.imshow(values, extent=extent, **kw, **style)
    return ax.pcolormesh(fmhz, np.arange(nrow), values, shading="auto", **style)


def nan_quantiles(values: np.ndarray, qs: tuple[float, ...]) -> list[np.ndarray]:
    """Quantiles over the first axis ignoring NaN, as ``np.nanquantile`` (linear).

    Vectorised through one sort (numpy's NaN-aware median and percentiles take 0.17 s
    against 0.02 s for 350 antennas x 2 pols x 1536 channels with flagged channels). NaN
    where a column has no value.
    """
    ordered = np.sort(values, axis=0)  # NaN last
    last = np.count_nonzero(~np.isnan(values), axis=0) - 1
    top = np.maximum(last, 0)[None]
    out = []
    for q in qs:
        pos = q * top
        low = np.floor(pos).astype(np.intp)
        below = np.take_along_axis(ordered, low, axis=0)[0]
        above = np.take_along_axis(ordered, np.minimum(low + 1, top), axis=0)[0]
        frac = (pos - low)[0]
        out.append(np.where(last >= 0, below + (above - below) * frac, np.nan))
    return out


def plot_residuals(
    labels: list[str],
    residuals: np.ndarray,
    freqs: np.ndarray,
    lsts: np.ndarray,
    path: str | Path,
    *,
    title: str | None = None,
    total: int | None = None,
    shown: int | None = None,
    channels: np.ndarray | None = None,
    ncols: int = 1,
) -> Path:
    """Write :func:`residuals_figure` to ``path``; return it."""
    fig = residuals_figure(
        labels,
        residuals,
        freqs,
        lsts,
        title=title,
        total=total,
        shown=shown,
        channels=channels,
        ncols=ncols,
    )
    return save_figure(fig, path)


def residuals_figure(
    labels: list[str],
    residuals: np.ndarray,
    freqs: np.ndarray,
    lsts: np.ndarray,
    *,
    title: str | None = None,
    total: int | None = None,
    shown: int | None = None,
    channels: np.ndarray | None = None,
    ncols: int = 1,
) -> Any:
    """Waterfalls of normalised residuals ``(R - model) / sigma``.

    The colour range is symmetric, ``+-`` the 99th percentile of ``|residual|`` over the
    finite values in ``channels`` (flagged channels are NaN, drawn grey).

    Parameters
    ----------
    labels
        One label per waterfall (which antenna and pol).
    residuals
        ``(K, Ntime, Nfreq)``.
    freqs, lsts
        Axes (Hz, hours).
    title
        Figure title (the run: files, JDs, antennas).
    total
        Antenna-pols there are; more than ``shown`` writes 'showing <shown> of <total>'.
    shown
        Antenna-pols the waterfalls show (default ``K``; ``K / 2`` for each antenna-pol
        before and after a change).
    channels
        ``(Nfreq,)`` mask of the channels setting the colour range (default: all).
    ncols
        Waterfalls per row, filled row by row (2: each antenna-pol before and after a
        change side by side); one colour bar per row.

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib

    k = len(labels)
    nrows = -(-k // ncols)
    height = 2.6 * nrows + 1.2
    width = 9.0 + 6.0 * (ncols - 1)
    fig = _pyplot().figure(figsize=(width, height))
    # a fixed grid (constrained layout took 0.5 s of a HERA file's 1.1 s figure); margins
    # in inches: 0.81 left (LST ticks and label), 0.9 right (the colour bars' label)
    grid = fig.add_gridspec(
        nrows, 2, width_ratios=[1.0, 0.025 / ncols], left=0.81 / width, right=1 - 0.9 / width,
        wspace=0.04, hspace=0.5, bottom=0.55 / height, top=1 - 0.95 / height,
    )  # fmt: skip
    cells = [grid[r, 0].subgridspec(1, ncols, wspace=0.2) for r in range(nrows)]
    axes = [fig.add_subplot(cells[i // ncols][0, i % ncols]) for i in range(k)]
    fmhz = freqs / 1e6
    scaled = residuals if channels is None else residuals[..., channels]
    vmax = max(symmetric_limit(scaled), 1.0)
    cmap = matplotlib.colormaps["RdBu_r"].with_extremes(bad="0.8")
    for i, (ax, label, res) in enumerate(zip(axes, labels, residuals, strict=True)):
        mesh = channel_image(ax, fmhz, res, cmap=cmap, vmin=-vmax, vmax=vmax)
        ticks = np.unique(np.linspace(0, lsts.size - 1, 6).astype(int))
        ax.set_yticks(ticks, [f"{lsts[t]:.2f}" for t in ticks])
        rms = float(np.sqrt(np.nanmean(res**2))) if np.any(np.isfinite(res)) else float("nan")
        ax.set(ylabel="LST [h]", title=f"{label}: normalised residuals (rms {rms:.3g})")
        if i % ncols == ncols - 1 or i == k - 1:  # the row's colour bar (one scale)
            fig.colorbar(mesh, cax=fig.add_subplot(grid[i // ncols, 1]), label=RESIDUAL_LABEL)
    for ax in axes[(nrows - 1) * ncols :]:
        ax.set_xlabel("frequency [MHz]")
    note = f"colour range +-{vmax:.3g} sigma (99th percentile of |residual|)"
    fig.suptitle((title + "\n" if title else "") + note, fontsize=9)
    shown = k if shown is None else shown
    showing_note(fig, shown, total or shown)
    return fig


def plot_gain_series(
    steps: list[dict[str, Any]], path: str | Path, title: str | None = None
) -> Path | None:
    """Plot a diagnosis's per-integration gain series against LST.

    One panel per ``gain_jitter`` / ``antenna_gain_jitter`` step, one line per
    antenna-pol (and the common series).

    Parameters
    ----------
    steps
        ``diagnosis.json`` steps; those with a ``series`` are drawn, one panel each.
    path
        Output image.
    title
        Figure title (the run: files, JDs, antennas).

    Returns
    -------
    Path or None
        The image, or ``None`` when no step has a series.
    """
    found = [st for st in steps if st.get("series") and "dropped_in_backward_pass" not in st]
    if not found:
        return None
    fig, axes = figure(len(found), 1, (9, 2.8 * len(found) + 0.4))
    axes = np.atleast_1d(axes)
    for ax, st in zip(axes, found, strict=True):
        series = st["series"]
        lst = np.asarray(series["lst_h"], float)
        factors = np.asarray(series["gain_factor"], float)
        if factors.ndim == 1:
            ax.plot(lst, 100 * (factors - 1), lw=1, label="all antennas")
        else:
            feeds = st.get("per_feed") or []
            labels = [f"{f['antenna']} {f['pol']}" for f in feeds]
            flat = factors.reshape(-1, factors.shape[-1])
            for i, row in enumerate(flat):
                label = labels[i] if i < len(labels) and flat.shape[0] <= 12 else None
                ax.plot(lst, 100 * (row - 1), lw=0.8, alpha=0.8, label=label)
            shared = series.get("shared_gain_factor")
            if shared is not None:
                ax.plot(lst, 100 * (np.asarray(shared) - 1), "k--", lw=1, label="common")
        rms = st["parameters"].get("rms", {}).get("value", float("nan"))
        ax.set(
            ylabel="gain factor - 1 [%]",
            title=f"{st['name']}: per-integration gain (rms {100 * rms:.2g} %)",
        )
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7, ncol=4, loc="upper right")
    axes[-1].set_xlabel("LST [h]")
    if title:
        fig.suptitle(title, fontsize=9)
    return save_figure(fig, path)
