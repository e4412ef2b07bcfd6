"""Figures of autocal products (matplotlib, Agg backend, written atomically)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

logger = logging.getLogger(__name__)


def _figure(nrows: int, ncols: int, size: tuple[float, float]) -> tuple[Any, Any]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(nrows, ncols, figsize=size, constrained_layout=True)


def save_figure(fig: Any, path: str | Path) -> Path:
    """Save a figure atomically (PNG unless the suffix says otherwise) and close it."""
    import matplotlib.pyplot as plt

    from autocal.io.tskyfile import atomic_path

    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format=path.suffix.lstrip(".") or "png")
    plt.close(fig)
    logger.info("wrote %s", path)
    return path


def plot_tsky(result: Any, path: str | Path, title: str | None = None) -> Path:
    """Plot a Tsky table: waterfall, Tsky vs LST at three frequencies, spectrum.

    Parameters
    ----------
    result
        A :class:`autocal.tsky.TskyResult`.
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
    fig, axes = _figure(1, 3, (15, 4.2))
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


def band(ax: Any, x: np.ndarray, y: np.ndarray, sigma: np.ndarray, label: str, **kw: Any) -> None:
    """Plot ``y`` with a shaded 2-sigma band."""
    (line,) = ax.plot(x, y, label=label, lw=1, **kw)
    ax.fill_between(x, y - 2 * sigma, y + 2 * sigma, color=line.get_color(), alpha=0.25, lw=0)


def robust_ylim(ax: Any, values: np.ndarray, low: float = 2.0, high: float = 98.0) -> None:
    """Limit the y axis to the central percentiles of the finite values (RFI-proof)."""
    finite = values[np.isfinite(values)]
    if finite.size < 10:
        return
    lo, hi = np.percentile(finite, [low, high])
    pad = 0.15 * (hi - lo) if hi > lo else max(abs(hi), 1e-12) * 0.1
    ax.set_ylim(lo - pad, hi + pad)


def plot_solution(solution: Any, path: str | Path, title: str | None = None) -> Path:
    """Plot ``|g|``, ``G`` and ``Trxr`` vs frequency with 2-sigma bands for every antenna/pol.

    Parameters
    ----------
    solution
        A :class:`autocal.fit.Solution`.
    path
        Output image.
    title
        Figure title.

    Returns
    -------
    pathlib.Path
        The written file.
    """
    fmhz = solution.freqs / 1e6
    fig, axes = _figure(3, 1, (9, 9))
    values = (
        (solution.abs_g, solution.sigma_abs_g, "|g|"),
        (solution.G, solution.sigma_G, "G"),
        (solution.Trxr, solution.sigma_Trxr, "Trxr [K]"),
    )
    for ax, (val, sig, name) in zip(axes, values, strict=True):
        for ia, ant in enumerate(solution.antennas):
            for ip, pol in enumerate(solution.pols):
                band(ax, fmhz, val[ia, ip], sig[ia, ip], f"ant {ant} {pol}")
        ax.set(ylabel=name)
        robust_ylim(ax, val[~solution.flags])
    axes[-1].set(xlabel="frequency [MHz]")
    if solution.antennas.size * len(solution.pols) <= 12:
        axes[0].legend(fontsize=7, ncol=2)
    fig.suptitle(title or f"{solution.model.kind} fit, 2-sigma bands", fontsize=10)
    return save_figure(fig, path)


def plot_residuals(
    labels: list[str],
    residuals: np.ndarray,
    freqs: np.ndarray,
    lsts: np.ndarray,
    path: str | Path,
) -> Path:
    """Waterfalls of normalised residuals ``(R - model) / sigma`` (colour range +-5).

    Parameters
    ----------
    labels
        One label per waterfall.
    residuals
        ``(K, Ntime, Nfreq)``.
    freqs, lsts
        Axes (Hz, hours).
    path
        Output image.
    """
    k = len(labels)
    fig, axes = _figure(k, 1, (9, 2.6 * k + 0.6))
    axes = np.atleast_1d(axes)
    rows = np.arange(lsts.size)
    fmhz = freqs / 1e6
    step = np.diff(fmhz)
    regular = fmhz.size > 1 and step[0] > 0 and np.allclose(step, step[0], rtol=1e-6, atol=0)
    for ax, label, res in zip(axes, labels, residuals, strict=True):
        style = {"cmap": "RdBu_r", "vmin": -5, "vmax": 5}
        if regular:  # an image of the same cells as pcolormesh: 0.4 s less for a HERA file
            half = step[0] / 2
            extent = (fmhz[0] - half, fmhz[-1] + half, -0.5, lsts.size - 0.5)
            kw = {"aspect": "auto", "origin": "lower", "interpolation": "nearest"}
            mesh = ax.imshow(res, extent=extent, **kw, **style)
        else:
            mesh = ax.pcolormesh(fmhz, rows, res, shading="auto", **style)
        ticks = np.unique(np.linspace(0, lsts.size - 1, 6).astype(int))
        ax.set_yticks(ticks, [f"{lsts[i]:.2f}" for i in ticks])
        rms = float(np.sqrt(np.nanmean(res**2))) if np.any(np.isfinite(res)) else float("nan")
        ax.set(ylabel="LST [h]", title=f"{label}: normalised residuals (rms {rms:.2f})")
        fig.colorbar(mesh, ax=ax, label="(R - model) / sigma")
    axes[-1].set_xlabel("frequency [MHz]")
    return save_figure(fig, path)
