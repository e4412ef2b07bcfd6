"""The ``autocal`` command line, the HDF5 Tsky table and the on-disk cache."""

from __future__ import annotations

from typing import ClassVar

import h5py
import numpy as np
import pytest

from autocal.cli.args import parse_range
from autocal.cli.main import main
from autocal.io.tskyfile import read_tsky, write_tsky
from autocal.tsky import cache as tsky_cache
from autocal.tsky.compute import compute_tsky
from autocal.tsky.result import TskyError


def test_parse_range():
    np.testing.assert_allclose(parse_range("100e6:200e6:3", "freqs", "Hz"), [100e6, 150e6, 200e6])
    np.testing.assert_allclose(parse_range("1,2.5", "lsts", "h"), [1, 2.5])
    with pytest.raises(ValueError, match="START:STOP:N"):
        parse_range("1:2", "lsts", "hours")
    with pytest.raises(ValueError, match="N must be"):
        parse_range("1:2:0", "lsts", "hours")


@pytest.mark.data
def test_cli_tsky_writes_table_and_plot(tmp_path, capsys, data_root):
    out, png = tmp_path / "t.h5", tmp_path / "t.png"
    code = main(
        [
            "tsky",
            "--sky",
            "gsm2008",
            "--beam",
            "dipole",
            "--pol",
            "nn",
            "--site",
            "edges",
            "--freqs",
            "60e6:90e6:4",
            "--lsts",
            "0:23:24",
            "--nside",
            "32",
            "--tgnd",
            "280",
            "--no-cache",
            "--out",
            str(out),
            "--plot",
            str(png),
        ]
    )
    assert code == 0
    assert "wrote" in capsys.readouterr().out
    with h5py.File(out) as h5:
        assert h5["tsky"].shape == (24, 4)
        assert h5["tsky"].attrs["units"] == "K"
        np.testing.assert_allclose(h5["freqs"][()], np.linspace(60e6, 90e6, 4))
        np.testing.assert_allclose(h5["lsts"][()], np.arange(24.0))
        assert h5.attrs["tgnd_K"] == 280.0
        assert '"pol": "nn"' in h5.attrs["beam"]
    assert png.stat().st_size > 10_000
    table = read_tsky(out)
    assert table.meta["site"]["name"] == "edges"
    assert np.all(table.tsky > 500)  # the 60-90 MHz sky is ~1000-4000 K


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--sky", "nosuchsky"], "unknown sky model"),
        (["--beam", "nosuchbeam"], "unknown beam"),
        (["--beam", "/no/such/file.beamfits"], "does not exist"),
        (["--beam", "edges-low"], "outside"),
        (["--freqs", "100e6:200e6:0"], "N must be"),
        (["--lsts", "abc"], "START:STOP:N"),
        (["--site", "mars"], "unknown site"),
        (["--nside", "48"], "nside"),
        (["--tgnd", "nan"], "ground temperature"),
        (["--beam", "edges-low", "--freqs", "0.1:0.2GHz:3"], "outside"),
        (["--freqs", "100:2ooMHz:3"], "give a frequency in MHz"),
    ],
)
def test_cli_bad_input_gives_clear_error(tmp_path, capsys, args, message, data_root):
    out = tmp_path / "bad.h5"
    code = main(["tsky", "--sky", "uniform:100", "--no-cache", "--out", str(out), *args])
    assert code == 2
    err = capsys.readouterr().err
    assert "error" in err
    import re

    assert re.search(message, err), err
    assert not out.exists()  # no half-written product


def test_empty_grids_are_refused():
    with pytest.raises(TskyError, match="empty"):
        compute_tsky("uniform:10", "dipole", "hera", [], [0.0], nside=8, cache=False)
    with pytest.raises(TskyError, match="empty"):
        compute_tsky("uniform:10", "dipole", "hera", [1e8], [], nside=8, cache=False)
    with pytest.raises(TskyError, match="non-finite"):
        compute_tsky("uniform:10", "dipole", "hera", [1e8], [np.inf], nside=8, cache=False)


def test_cache_hit_and_key(tmp_cache, monkeypatch):
    import autocal.tsky.compute as tsky_module

    freqs = [1e8, 1.5e8]
    first = compute_tsky("uniform:100", "dipole", "hera", freqs, [0.0, 12.0], nside=8)
    files = list(tmp_cache.glob("*.h5"))
    assert len(files) == 1

    def no_compute(*args, **kw):
        raise AssertionError("cache miss: the harmonics were recomputed")

    monkeypatch.setattr(tsky_module, "tsky_harmonics", no_compute)
    second = compute_tsky("uniform:100", "dipole", "hera", freqs, [0.0, 12.0], nside=8)
    np.testing.assert_array_equal(first.tsky, second.tsky)
    # other LSTs and another ground temperature come from the same entry
    other = compute_tsky("uniform:100", "dipole", "hera", freqs, [3.0, 5.5], tgnd=250.0, nside=8)
    monkeypatch.undo()  # (also the fixture's cache folder)
    monkeypatch.setenv("AUTOCAL_CACHE_DIR", str(tmp_cache))
    fresh = compute_tsky(
        "uniform:100", "dipole", "hera", freqs, [3.0, 5.5], tgnd=250.0, nside=8, cache=False
    )
    np.testing.assert_allclose(other.tsky, fresh.tsky, rtol=1e-13, atol=0)
    assert other.meta["tgnd_K"] == 250.0 and other.meta["compute_seconds"] >= 0
    assert len(list(tmp_cache.glob("*.h5"))) == 1
    compute_tsky("uniform:100", "airy", "hera", freqs, [0.0], nside=8)
    compute_tsky("uniform:100", "dipole", "edges", freqs, [0.0], nside=8)
    compute_tsky("uniform:100", "dipole", "hera", freqs, [0.0], nside=8, epoch=2458098.5)
    compute_tsky("uniform:100", "dipole", "hera", [1e8, 1.6e8], [0.0], nside=8)
    assert len(list(tmp_cache.glob("*.h5"))) == 5  # distinct keys


def test_corrupt_cache_entry_is_recomputed(tmp_cache):
    kwargs = dict(freqs=[1e8], lsts=[0.0], nside=8)
    compute_tsky("uniform:100", "dipole", "hera", **kwargs)
    (entry,) = tmp_cache.glob("*.h5")
    entry.write_bytes(b"garbage")
    again = compute_tsky("uniform:100", "dipole", "hera", **kwargs)
    assert np.isfinite(again.tsky).all()
    assert tsky_cache.load(entry.stem) is not None


def test_write_is_atomic(tmp_path):
    class Broken:
        """A table whose description cannot be stored: fails after the arrays are written."""

        tsky = np.zeros((1, 1))
        freqs = lsts = f_above = f_below = np.zeros(1)
        meta: ClassVar[dict] = {"sky": "ok", "engine": object()}

    target = tmp_path / "out.h5"
    with pytest.raises(TypeError):
        write_tsky(target, Broken())
    assert not target.exists()
    assert list(tmp_path.iterdir()) == []
