"""The ``quality`` block every calibration summary carries (autocal.pipeline.quality)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from autocal.pipeline.calibrate import calibrate, read_summary
from autocal.pipeline.quality import flag_quality, flagged_verdict

HERA_FILE = "hera/autos/zen.2458043.40141.xx.HH.XRAA.uvh5"


@pytest.mark.data
def test_every_summary_has_the_quality_the_solution_flags_say(data_root, tmp_path) -> None:
    """Written by the pipeline itself, so service and nightly jobs get it, not only the CLI;
    then the flags of one antenna-pol are all set: that feed is named as unsolved, and with
    most channels set the status is mostly_flagged."""
    sol = calibrate(
        data_root / HERA_FILE, antennas=[24, 25], freq_range_mhz=(120, 180), out=tmp_path
    )
    quality = read_summary(tmp_path)["quality"]
    reason = np.asarray(sol.flag_reason)
    assert quality["flagged"] == int(np.count_nonzero(reason)) and quality["total"] == reason.size
    assert quality["status"] == ("ok" if quality["flagged_fraction"] <= 0.5 else "mostly_flagged")
    assert quality == flag_quality(sol)

    dead = reason.copy()
    dead[0, 0] = 3  # every channel of the first antenna-pol: "non-positive gain"
    one_dead = flag_quality(dataclasses.replace(sol, flag_reason=dead))
    assert one_dead["fully_flagged"] == [f"{sol.antennas[0]} {sol.pols[0]}"]
    assert "no solved channel for" in one_dead["message"]
    dead[:] = 3
    assert flag_quality(dataclasses.replace(sol, flag_reason=dead))["status"] == "fully_flagged"


def test_the_verdict_of_a_flagged_solution_follows_its_status() -> None:
    """The few words a service job's message carries: only a fully or mostly flagged status
    (flag_quality's decision) gets them, with the counts."""
    block = {"flagged": 1405, "total": 2048}
    assert flagged_verdict({**block, "status": "mostly_flagged"}) == (
        "1405 of 2048 channels flagged (mostly flagged)"
    )
    assert flagged_verdict({"flagged": 8, "total": 8, "status": "fully_flagged"}) == (
        "8 of 8 channels flagged (fully flagged)"
    )
    assert flagged_verdict({**block, "status": "ok"}) is None
    assert flagged_verdict(None) is None and flagged_verdict({}) is None
