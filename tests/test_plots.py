"""Figures: residual waterfalls drawn as images on regular channel grids."""

from __future__ import annotations

import numpy as np
import pytest

import autocal.plots as plots


@pytest.mark.parametrize(
    ("freqs", "kind"),
    [
        (np.linspace(100e6, 200e6, 64, endpoint=False), "AxesImage"),
        (
            np.r_[np.linspace(100e6, 150e6, 32, endpoint=False), np.linspace(160e6, 200e6, 32)],
            "QuadMesh",
        ),
        (np.linspace(200e6, 100e6, 64), "QuadMesh"),  # decreasing: keep the axis increasing
    ],
)
def test_residual_waterfalls_cover_the_channels(freqs, kind, tmp_path, monkeypatch) -> None:
    figures = []
    monkeypatch.setattr(plots, "save_figure", lambda fig, path: figures.append(fig) or path)
    res = np.random.default_rng(1).standard_normal((2, 10, freqs.size))
    plots.plot_residuals(["a", "b"], res, freqs, np.linspace(3.0, 3.5, 10), tmp_path / "r.png")
    (fig,) = figures
    for ax in fig.axes[:2]:  # the waterfalls (the colour bars come after them)
        (artist,) = ax.images or ax.collections
        assert type(artist).__name__ == kind
        lo, hi = sorted(ax.get_xlim())
        step = abs(freqs[1] - freqs[0]) / 1e6
        assert lo <= freqs.min() / 1e6 and hi >= freqs.max() / 1e6
        assert hi - lo <= np.ptp(freqs) / 1e6 + 2 * step
        assert ax.get_xlim()[0] < ax.get_xlim()[1]
        assert sorted(ax.get_ylim()) == [-0.5, 9.5]
    import matplotlib.pyplot as plt

    plt.close(fig)
