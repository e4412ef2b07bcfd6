"""A real HERA observation and autocal's solution of it, for tests of the products.

One file of night 2458116 (12 integrations), the auto of antenna 23 selected (the file's
crosses involve antennas without autos), calibrated over 150-160 MHz; the data handed to
consumers are that auto restricted to the solution's channels.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from pyuvdata import UVCal, UVData

from autocal.pipeline.calibrate import run_calibration
from autocal.pipeline.config import CalibrationConfig

#: The real file (relative to the data folder).
HERA_FILE = "hera/autos/zen.2458116.30448.HH.uvh5"


@dataclass(frozen=True)
class RealProducts:
    """Paths of the real-data products: raw file, auto, band-matched auto, solutions."""

    raw: Path
    auto: Path
    band: Path
    calh5: Path
    calfits: Path


def real_products(data_root: Path, folder: Path) -> RealProducts:
    """Calibrate antenna 23 of :data:`HERA_FILE` into ``folder`` and return the paths."""
    raw = data_root / HERA_FILE
    uvd = UVData.from_file(str(raw))
    uvd.select(bls=[(23, 23)])
    auto = folder / "auto23.uvh5"
    uvd.write_uvh5(str(auto))
    out = folder / "cal"
    config = CalibrationConfig(
        inputs=[str(auto)],
        antennas=[23],
        freq_range_mhz=(150.0, 160.0),
        products=["calh5", "calfits"],
    )
    run_calibration(config, out)
    uvc = UVCal.from_file(str(out / "solution.calfits"))
    uvd.select(frequencies=uvc.freq_array)
    band = folder / "auto23_band.uvh5"
    uvd.write_uvh5(str(band))
    return RealProducts(raw, auto, band, out / "solution.calh5", out / "solution.calfits")
