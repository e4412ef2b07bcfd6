"""Figures of the paper's simulation scenarios (:mod:`autocal.simulate.paper`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from autocal.compare.delay import delay_spectrum
from autocal.plots import band, figure, save_figure


def plot_scenarios(results: list[Any], path: str | Path) -> Path:
    """G and Trxr vs frequency with 2-sigma bands, one row per scenario, truth dashed."""
    fig, axes = figure(len(results), 2, (11, 2.0 * len(results) + 1))
    axes = np.atleast_2d(axes)
    for row, res in zip(axes, results, strict=True):
        sol = res.solution
        fmhz = sol.freqs / 1e6
        band(row[0], fmhz, sol.G[0, 0], sol.sigma_G[0, 0], "fit")
        row[0].plot(fmhz, res.true_gain.mean(axis=0), "k--", lw=1, label="truth (time mean)")
        band(row[1], fmhz, sol.Trxr[0, 0], sol.sigma_Trxr[0, 0], "fit")
        row[1].plot(fmhz, res.true_trxr, "k--", lw=1, label="truth")
        row[0].set_ylabel("G")
        row[1].set_ylabel("Trxr [K]")
        row[0].set_title(res.scenario.label, fontsize=9, loc="left")
    axes[0, 0].legend(fontsize=7)
    for ax in axes[-1]:
        ax.set_xlabel("frequency [MHz]")
    fig.suptitle(f"beam {results[0].beam}: fitted G and Trxr, 2-sigma bands", fontsize=10)
    return save_figure(fig, path)


def plot_time_model(results: list[Any], path: str | Path) -> Path:
    """Time-model fits: G and Trxr averaged over time (vs freq) and over frequency (vs LST)."""
    fig, axes = figure(len(results), 4, (17, 2.4 * len(results) + 1))
    axes = np.atleast_2d(axes)
    for row, res in zip(axes, results, strict=True):
        sol = res.solution
        ev = sol.evaluate()
        fmhz = sol.freqs / 1e6
        order = np.argsort(sol.lsts)
        lst = sol.lsts[order]
        band(row[0], fmhz, sol.G[0, 0], sol.sigma_G[0, 0], "fit, time mean")
        row[0].plot(fmhz, res.true_gain.mean(axis=0), "k--", lw=1, label="truth")
        band(row[1], fmhz, sol.Trxr[0, 0], sol.sigma_Trxr[0, 0], "fit, time mean")
        row[1].plot(fmhz, res.true_trxr, "k--", lw=1)
        g_t = np.nanmean(ev["G"][0, 0], axis=1)[order]
        sg_t = np.sqrt(np.nanmean(ev["sigma_G"][0, 0] ** 2, axis=1))[order]
        band(row[2], lst, g_t, sg_t, "fit, mean over frequency (band: per-channel 2 sigma)")
        row[2].plot(lst, res.true_gain.mean(axis=1)[order], "k--", lw=1, label="truth")
        t_t = np.nanmean(ev["Trxr"][0, 0], axis=1)[order]
        st_t = np.sqrt(np.nanmean(ev["sigma_Trxr"][0, 0] ** 2, axis=1))[order]
        band(row[3], lst, t_t, st_t, "fit, mean over frequency (band: per-channel 2 sigma)")
        row[3].plot(lst, np.full(lst.size, np.mean(res.true_trxr)), "k--", lw=1)
        for ax, name in zip(row, ("G", "Trxr [K]", "G(t)", "Trxr(t) [K]"), strict=True):
            ax.set_ylabel(name)
        row[0].set_title(res.scenario.label, fontsize=9, loc="left")
    axes[0, 0].legend(fontsize=7)
    axes[0, 2].legend(fontsize=7)
    for ax, name in zip(axes[-1], ("frequency [MHz]",) * 2 + ("LST [h]",) * 2, strict=True):
        ax.set_xlabel(name)
    fig.suptitle(f"beam {results[0].beam}: order-1 time model, 2-sigma bands", fontsize=10)
    return save_figure(fig, path)


def plot_delay_spectra(results: list[Any], noisy: Any, path: str | Path) -> Path:
    """Delay spectra (normalised to tau = 0) of the fitted G and Trxr of every scenario.

    ``results`` are noiseless runs (the systematic structure each scenario imprints);
    ``noisy`` is a run with noise, drawn in grey to show the noise floor.
    """
    fig, axes = figure(1, 2, (13, 4.5))
    sol = noisy.solution
    for ax, values in zip(axes, (sol.G[0, 0], sol.Trxr[0, 0]), strict=True):
        ds = delay_spectrum(values, sol.freqs)
        ax.semilogy(ds.delays_ns, ds.amplitude, color="0.7", lw=1, label="noise floor (reference)")
    for res in results:
        sol = res.solution
        for ax, values in zip(axes, (sol.G[0, 0], sol.Trxr[0, 0]), strict=True):
            ds = delay_spectrum(values, sol.freqs)
            ax.semilogy(ds.delays_ns, ds.amplitude, lw=1, label=res.scenario.name)
    for ax, name in zip(axes, ("G", "Trxr"), strict=True):
        ax.set(
            xlabel="delay [ns]", ylabel=f"|FT({name})| / tau=0", title=f"delay spectrum of {name}"
        )
        ax.set_ylim(1e-7, 1.5)
    axes[0].legend(fontsize=7, ncol=2)
    fig.suptitle(
        f"beam {results[0].beam}: noiseless scenarios (Blackman-Harris window)", fontsize=10
    )
    return save_figure(fig, path)
