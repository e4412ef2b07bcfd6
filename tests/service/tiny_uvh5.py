"""Small real UVH5 files for the service's tests (the submission reads their headers).

``POST /jobs`` reads each UVH5 input's header as the worker's reader would
(:func:`autocal.service.submission_checks.check_uvh5_inputs`), so the data roots of the
API tests hold real, tiny files: 4 integrations at the JD of the file's ``zen.<JD>`` name,
antennas 0, 1, 11, 23 and 24, ``ee`` and ``nn``, 8 channels spread over 100-200 MHz.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from tests.io.test_uvh5 import synthetic_observation
from tests.io.test_uvh5_writer import part_writer

#: The antennas of every tiny file.
ANTENNAS = (0, 1, 11, 23, 24)


def write_tiny_uvh5(path: Path) -> Path:
    """Write a tiny UVH5 file at ``path``, at the JD its ``zen.<JD>`` name gives."""
    match = re.match(r"zen\.(\d{7}\.\d+)", path.name)
    jd0 = float(match.group(1)) if match else 2458116.3
    obs = synthetic_observation(jd0=jd0, antennas=ANTENNAS, freqs=np.linspace(100e6, 200e6, 8))
    path.parent.mkdir(parents=True, exist_ok=True)
    with part_writer(obs, path) as writer:
        writer.write(0, obs.data, np.zeros(obs.shape, bool), np.ones(obs.shape))
    return path
