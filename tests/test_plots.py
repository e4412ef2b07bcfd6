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


def _solution(nant: int, npol: int = 2, nfreq: int = 48):
    from autocal.fit.model import FitModel
    from autocal.fit.solution import Solution

    rng = np.random.default_rng(3)
    shape = (nant, npol, nfreq)
    gain = 0.01 * (1 + 0.1 * rng.standard_normal(shape))
    coeffs = np.stack([gain, gain * (150 + 10 * rng.standard_normal(shape))], -1)
    cov = np.zeros((*shape, 2, 2))
    cov[..., 0, 0], cov[..., 1, 1] = (1e-3 * gain) ** 2, (0.1 * gain) ** 2
    reason = np.zeros(shape, np.int8)
    reason[:, :, 10:13] = 2  # channels flagged for every antenna
    reason[1] = 1  # an antenna without data
    coeffs[reason != 0], cov[reason != 0] = np.nan, np.nan
    return Solution(
        model=FitModel(),
        antennas=np.arange(nant) * 3 + 1,
        pols=("ee", "nn")[:npol],
        freqs=np.linspace(100e6, 200e6, nfreq, endpoint=False),
        lsts=np.linspace(1.0, 1.2, 20),
        jds=np.linspace(0.0, 0.01, 20),
        coeffs=coeffs,
        cov=cov,
        chi2=18 * (1 + 0.1 * rng.standard_normal(shape)),
        dof=np.full(shape, 18.0),
        count=np.full(shape, 20),
        nflagged=np.zeros(shape, int),
        flag_reason=reason,
    )


@pytest.mark.parametrize("nant", [3, 7, 40])
def test_solution_figure_shows_every_antenna(nant, tmp_path, monkeypatch) -> None:
    """Up to 12 antenna-pols: one line per antenna-pol with its band; more: every antenna
    as an image row of |g|, Trxr and chi2/dof per pol (flagged channels blank), beside the
    median and 16-84 % spread over antennas."""
    figures = []
    monkeypatch.setattr(plots, "save_figure", lambda fig, path: figures.append(fig) or path)
    sol = _solution(nant)
    plots.plot_solution(sol, tmp_path / "s.png")
    (fig,) = figures
    if nant * 2 <= plots.MAX_SOLUTION_CURVES:
        assert len(fig.axes) == 3
        assert all(len(ax.lines) == nant * 2 for ax in fig.axes)
        assert len(fig.axes[0].get_legend().texts) == nant * 2
    else:
        images = [ax for ax in fig.axes if ax.images]
        assert len(images) == 6  # 3 quantities x 2 pols
        expected = (sol.abs_g, sol.Trxr, sol.reduced_chi2)
        for k, ax in enumerate(images):
            (image,) = ax.images
            shown = np.ma.filled(image.get_array().astype(float), np.nan)
            assert shown.shape == (nant, 48)  # every antenna, every channel
            want = expected[k // 2][:, k % 2]
            np.testing.assert_array_equal(np.isnan(shown), sol.flags[:, k % 2])
            np.testing.assert_allclose(shown[~sol.flags[:, k % 2]], want[~sol.flags[:, k % 2]])
        spread = [ax for ax in fig.axes if ax.lines and not ax.images]
        assert len(spread) == 3
        median = spread[0].lines[0].get_ydata()
        with np.errstate(all="ignore"), pytest.warns(RuntimeWarning):
            np.testing.assert_allclose(median, np.nanmedian(sol.abs_g[:, 0], axis=0))
    import matplotlib.pyplot as plt

    plt.close(fig)


def test_nan_quantiles_match_numpy() -> None:
    rng = np.random.default_rng(5)
    values = rng.standard_normal((37, 3, 50))
    values[rng.random(values.shape) < 0.3] = np.nan
    values[:, 1, 7] = np.nan  # a column without values
    values[:36, 2, 3] = np.nan  # a column with one value
    with pytest.warns(RuntimeWarning):
        want = np.nanquantile(values, [0.5, 0.16, 0.84], axis=0)
    got = plots.nan_quantiles(values, (0.5, 0.16, 0.84))
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-14, atol=1e-15)
