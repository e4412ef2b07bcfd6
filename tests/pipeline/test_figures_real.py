"""The figures of ``autocal calibrate`` on real HERA data, checked against pyuvdata's reading."""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib.image
import numpy as np
import pytest
from pyuvdata import UVData

import autocal.plots
import autocal.solution_plots
from autocal.pipeline.calibrate import run_calibration
from autocal.pipeline.config import CalibrationConfig
from autocal.pipeline.products import FIGURE_FILES, PRODUCT_FILES

pytestmark = [pytest.mark.slow, pytest.mark.data]


def test_hera_figures_name_the_run_and_count_the_antennas(data_root, tmp_path, monkeypatch):
    files = sorted((data_root / "hera/autos").glob("zen.2458043.*.XRAA.uvh5"))
    figures = {}
    save = autocal.plots.save_figure

    def keep(fig, path):
        figures[Path(path).name] = fig
        return save(fig, path)

    monkeypatch.setattr(autocal.plots, "save_figure", keep)
    monkeypatch.setattr(autocal.solution_plots, "save_figure", keep)
    # flagging off: the band edges (filter roll-off) stay in, and the figures must cope
    config = CalibrationConfig(
        inputs=[str(f) for f in files], products=["hdf5", "png"], rfi_flagging=False
    )
    result = run_calibration(config, tmp_path)

    uvd = UVData()
    uvd.read([str(f) for f in files], read_data=False)
    autos = sorted({a for a, b in uvd.get_antpairs() if a == b})
    jd = f"JD {uvd.time_array.min():.5f}-{uvd.time_array.max():.5f}"
    antpols = len(autos) * len(uvd.get_pols())
    assert antpols == 7  # the files' 7 antennas, one pol: more than the waterfalls' 4

    names = {PRODUCT_FILES["png"], *FIGURE_FILES.values()}
    assert set(figures) == names
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert {"png", *FIGURE_FILES} <= set(summary["products"])
    for name, fig in figures.items():
        title = fig._suptitle.get_text()
        assert title.startswith(f"{files[0].name.removesuffix('.uvh5')} (+2 files) | {jd}")
        assert "ants " + ", ".join(str(a) for a in autos) in title
        image = matplotlib.image.imread(tmp_path / name)
        width, height = fig.get_size_inches() * 110
        assert image.shape[:2] == (round(height), round(width))
        assert np.ptp(image[..., :3]) > 0.5  # drawn, not blank
    notes = {n: " ".join(t.get_text() for t in f.texts) for n, f in figures.items()}
    assert f"showing 4 of {antpols} antenna-pols" in notes["residuals.png"]
    assert f"showing 4 of {antpols} antenna-pols" in notes["data_model.png"]
    assert "showing" not in notes["solution.png"] + notes["delay_spectra.png"]
    # every antenna's G and Trxr delay spectrum
    delay = figures["delay_spectra.png"]
    assert [len(ax.lines) for ax in delay.axes] == [antpols, antpols]
    # the solution's band edges (the filter roll-off) are left out of the Trxr axis
    sol = result.solution
    core = autocal.plots.band_core(sol.G, sol.flags)
    assert 0 < np.count_nonzero(~core) < sol.freqs.size // 3
    lo, hi = figures["solution.png"].axes[2].get_ylim()
    edges = sol.Trxr[..., ~core]
    assert np.nanmax(edges) > hi or np.nanmin(edges) < lo
