"""Figures: what they show (panels, units, titles, colour scales), not only that they exist."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import autocal.plots as plots
import autocal.solution_plots as solution_plots
from autocal.compare.delay import delay_spectrum


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
    assert "showing" not in " ".join(t.get_text() for t in fig.texts)  # every one shown
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
    sol = _solution(nant)
    fig = solution_plots.solution_figure(sol, stems=("zen.2458116.30448.HH", "b"))
    title = fig._suptitle.get_text()
    assert "zen.2458116.30448.HH (+1 file)" in title
    assert f"JD {sol.jds.min():.5f}-{sol.jds.max():.5f}" in title
    ylabels = [ax.get_ylabel() for ax in fig.axes if ax.get_ylabel()]
    assert any("(data units / K)" in y and "|g|" in y for y in ylabels)
    assert any(y == "Trxr [K]" for y in ylabels)
    if nant * 2 <= solution_plots.MAX_SOLUTION_CURVES:
        assert f"ant{'s' if nant > 1 else ''} {sol.antennas[0]}" in title
        assert len(fig.axes) == 3
        assert [ax.get_ylabel() for ax in fig.axes] == [
            plots.ABS_G_LABEL,
            plots.G_LABEL,
            plots.TRXR_LABEL,
        ]
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


def _texts(fig) -> str:
    return " ".join(t.get_text() for t in fig.texts)


def _rolled_off(nant: int = 3):
    """A solution whose gain rolls off at both band edges, where Trxr runs away."""
    sol = _solution(nant)
    coeffs = sol.coeffs.copy()
    edge = np.r_[0:5, 43:48]
    coeffs[:, :, edge, 0] *= 1e-3  # the filter roll-off: G a thousandth of the band's
    coeffs[:, :, edge, 1] *= 1e-1  # n / G = Trxr a hundred times the band's
    return replace(sol, coeffs=coeffs), edge


def test_band_edges_and_flagged_channels_do_not_set_the_scales() -> None:
    sol, edge = _rolled_off()
    core = plots.band_core(sol.G, sol.flags)
    assert core.tolist() == [not (i < 5 or i >= 43) for i in range(48)]
    fig = solution_plots.solution_figure(sol)
    trxr_ax = fig.axes[2]
    inside = sol.Trxr[:, :, core & ~sol.flags.all(axis=(0, 1))]
    inside = inside[np.isfinite(inside)]
    lo, hi = trxr_ax.get_ylim()
    # the central percentiles of the in-band, unflagged values are shown ...
    assert lo <= np.percentile(inside, 1) and hi >= np.percentile(inside, 99)
    # ... and the band edges' hundred-times-larger Trxr is outside the axis
    assert hi < np.nanmin(sol.Trxr[:, :, edge][:, :, 5:])
    assert hi - lo < 3 * np.ptp(inside)
    # the edges are greyed out (two spans) on every panel
    assert all(len(ax.patches) >= 2 for ax in fig.axes)


def test_residual_colour_scale_is_a_percentile_of_the_band_and_counts_antennas() -> None:
    rng = np.random.default_rng(7)
    freqs = np.linspace(100e6, 200e6, 200, endpoint=False)
    res = 8.0 * rng.standard_normal((2, 30, 200))  # real data: far beyond +-5 sigma
    res[:, :, 50:53] = np.nan  # flagged channels
    res[:, :, :10] = 1e4  # band edges
    channels = np.ones(200, bool)
    channels[:10] = False
    fig = plots.residuals_figure(
        ["ant 23 ee", "ant 23 nn"], res, freqs, np.linspace(3.2, 3.7, 30),
        title="zen.x | JD 1-2", total=14, channels=channels,
    )  # fmt: skip
    inside = np.abs(res[:, :, channels])
    want = np.percentile(inside[np.isfinite(inside)], 99)
    waterfalls = [ax for ax in fig.axes if ax.images]
    assert len(waterfalls) == 2
    for ax, label in zip(waterfalls, ["ant 23 ee", "ant 23 nn"], strict=True):
        lo, hi = ax.images[0].get_clim()
        assert hi == pytest.approx(want) and lo == pytest.approx(-want)
        assert 8.0 * 2 < want < 8.0 * 3  # neither +-5 nor the edges' 1e4
        assert ax.get_title().startswith(label)
        assert ax.get_ylabel() == "LST [h]"
    assert waterfalls[-1].get_xlabel() == "frequency [MHz]"
    assert "showing 2 of 14 antenna-pols" in _texts(fig)
    assert fig._suptitle.get_text().startswith("zen.x | JD 1-2")
    colour_bars = [ax for ax in fig.axes if not ax.images]
    assert all(ax.get_ylabel() == plots.RESIDUAL_LABEL for ax in colour_bars)


def test_delay_figure_finds_a_cable_reflection() -> None:
    """A ripple of period 1/tau in G and Trxr peaks at tau in the delay spectra."""
    sol = _solution(3, nfreq=512)
    tau = 400e-9
    ripple = 1 + 0.05 * np.cos(2 * np.pi * sol.freqs * tau)
    coeffs = sol.coeffs.copy()
    coeffs[..., 0] *= ripple
    coeffs[..., 1] *= ripple**2
    sol = replace(sol, coeffs=coeffs)
    fig = solution_plots.delay_figure(sol)
    assert [ax.get_xlabel() for ax in fig.axes] == ["delay [ns]", "delay [ns]"]
    assert all("[dB]" in ax.get_ylabel() for ax in fig.axes)
    step = 1e9 / np.ptp(sol.freqs) * 511 / 512
    for ax in fig.axes:
        assert len(ax.lines) == 4  # antenna 4 (index 1) has no data: 2 of 3 antennas x 2
        for line in ax.lines:
            x, y = line.get_xdata(), line.get_ydata()
            far = x > 150
            assert abs(x[far][np.argmax(y[far])] - tau * 1e9) <= 1.5 * step
    assert "showing 4 of 6 antenna-pols" in _texts(fig)
    # the lines are the delay spectra of the unflagged channels, in dB
    want = delay_spectrum(sol.G[0, 0], sol.freqs, flags=sol.flags[0, 0])
    with np.errstate(divide="ignore"):
        np.testing.assert_allclose(fig.axes[0].lines[0].get_ydata(), 20 * np.log10(want.amplitude))


def test_delay_figure_on_an_irregular_grid_says_why_it_is_empty() -> None:
    sol = _solution(2)
    freqs = sol.freqs.copy()
    freqs[20:] += 5e6
    fig = solution_plots.delay_figure(replace(sol, freqs=freqs))
    assert all(not ax.lines for ax in fig.axes)
    assert "uniformly spaced" in " ".join(t.get_text() for ax in fig.axes for t in ax.texts)


def test_data_model_figure_panels() -> None:
    freqs = np.linspace(100e6, 200e6, 64, endpoint=False)
    lsts = np.linspace(3.2, 3.7, 12)
    rng = np.random.default_rng(2)
    model = 5 + rng.random((2, 64))
    model_t = 5 + 0.1 * lsts[None] + np.zeros((2, 1))
    curves = {
        "labels": ["ant 23 ee", "ant 23 nn"], "freqs": freqs, "lsts": lsts,
        "data": model * 1.01, "model": model, "data_t": model_t * 1.02, "model_t": model_t,
    }  # fmt: skip
    fig = solution_plots.data_model_figure(curves, title="t", total=6)
    spectrum, drift, frac = fig.axes
    assert spectrum.get_xlabel() == "frequency [MHz]"
    assert drift.get_xlabel() == frac.get_xlabel() == "LST [h]"
    assert spectrum.get_ylabel() == drift.get_ylabel() == "autocorrelation [data units]"
    assert frac.get_ylabel() == "(data - model) / model [%]"
    assert len(spectrum.lines) == len(drift.lines) == 4  # data and model per antenna-pol
    np.testing.assert_allclose(frac.lines[0].get_ydata(), 2.0)  # data 2 % above the model
    assert "showing 2 of 6 antenna-pols" in _texts(fig)


def test_run_title_names_files_jds_and_antennas() -> None:
    many = plots.run_title(np.array([2.5, 2.6]), np.arange(20), ("ee",), ())
    assert many == "JD 2.50000-2.60000 | 20 antennas (0-19) | ee"
    one = plots.run_title(np.array([1.0]), np.array([23]), ("ee", "nn"), ("a.HH",))
    assert one == "a.HH | JD 1.00000-1.00000 | ant 23 | ee, nn"
    assert plots.file_stems(["/x/zen.2458116.30448.HH.uvh5"]) == ("zen.2458116.30448.HH",)
