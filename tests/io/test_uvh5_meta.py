"""UVH5 headers: what a scanned file keeps, pyuvdata's compiled helpers cached on disk."""

from __future__ import annotations

import numpy as np
import pytest

from autocal.io.uvh5 import write_uvh5
from tests.io.test_uvh5 import AUTOS, XRAA, synthetic_observation


def test_scanned_header_keeps_no_per_row_arrays(tmp_path):
    """A scanned file's metadata must not grow with its rows (a night scans every file)."""
    from autocal.io.uvh5_meta import read_file_meta

    obs = synthetic_observation(ntime=200)  # 600 rows, more than HERA's 350 antennas
    path = write_uvh5(obs, tmp_path / "rows.uvh5", extra_keywords={"k": 3})
    meta = read_file_meta(path)
    assert meta.header.extra_keywords["k"] == 3 and meta.header.telescope_name
    for value in vars(meta.header).values():  # per antenna at most, nothing per row
        assert np.size(value) < obs.ntime * obs.nant or isinstance(value, (str, dict))
    assert meta.times.size == obs.ntime


@pytest.mark.data
def test_pyuvdata_compiled_helpers_are_cached_on_disk(data_root, tmp_path) -> None:
    """A process reading a UVH5 header through pyuvdata leaves its machine code for the next.

    (The scan reads plain headers with h5py; pyuvdata reads the others.)
    """
    import os
    import subprocess
    import sys

    path = data_root / AUTOS / XRAA[0]
    code = (
        "import sys, pathlib; from autocal.io.uvh5_meta import _header_through_pyuvdata; "
        "_header_through_pyuvdata(pathlib.Path(sys.argv[1]))"
    )
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    subprocess.run([sys.executable, "-c", code, str(path)], env=env, check=True, timeout=300)
    assert list(tmp_path.rglob("bls_numba._antnums_to_baseline-*.nbi"))


@pytest.mark.parametrize(
    ("dataset", "value", "words"),
    [
        ("freq_array", np.nan, "channel frequencies not finite and positive"),
        ("freq_array", -1.0, "channel frequencies not finite and positive"),
        ("lst_array", np.inf, "Header/lst_array has"),
        ("ant_1_array", -7, "negative antenna numbers"),
    ],
)
def test_a_header_with_impossible_values_is_called_corrupt(tmp_path, dataset, value, words):
    """A live audit (2026-11-29): a NaN freq_array gave "the data cover nan-nan MHz ...
    choose a range inside that band" instead of saying the file is corrupt."""
    import h5py

    from autocal.io.uvh5_meta import UVH5FormatError, read_file_meta

    path = write_uvh5(synthetic_observation(), tmp_path / "zen.2458098.30000.HH.uvh5")
    with h5py.File(path, "r+") as h5:
        values = h5[f"Header/{dataset}"][()]
        values[...] = value
        h5[f"Header/{dataset}"][...] = values
    with pytest.raises(UVH5FormatError, match="is corrupt") as err:
        read_file_meta(path)
    assert words in str(err.value) and "copy or download it again" in str(err.value)


def test_pyuvdatas_errors_are_reported_on_one_line_without_asking_for_a_bug_report():
    from autocal.io.uvh5_meta import _first_line

    asked = ValueError("Frequencies are odd. Please file an issue in our GitHub issue log.")
    assert _first_line(asked) == "Frequencies are odd."
    compiled = ValueError('failed in nopython mode\nFile "bls_numba.py", line 1')
    assert _first_line(compiled) == "failed in nopython mode"
