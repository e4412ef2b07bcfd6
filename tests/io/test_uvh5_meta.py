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
