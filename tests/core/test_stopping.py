"""Cooperative stopping (autocal.core.stopping): checkpoints inside the long stages.

A worker asked to stop (a cancellation, SIGTERM) must not wait for a whole Tsky
computation (tens of seconds on a loaded machine when its cache is cold): the sky's
rotation and band limit and the Tsky engine's chunks check the run's ``should_stop``.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest

from autocal.core.stopping import checkpoint, stop_when
from autocal.errors import RunCancelledError
from autocal.simulate.mock import SimulationConfig, simulate
from autocal.tsky.compute import compute_tsky


def test_checkpoint_raises_only_inside_a_stopped_run() -> None:
    checkpoint()  # no run: nothing to stop
    with stop_when(lambda: False):
        checkpoint()
        with stop_when(None):  # an inner run without its own check keeps the outer one
            checkpoint()
    with (
        stop_when(lambda: True),
        pytest.raises(RunCancelledError, match="cancelled"),
        stop_when(None),
    ):
        checkpoint("the next step")
    checkpoint()  # the check ends with its block


def _tsky(freqs_mhz: tuple[float, ...]) -> None:
    # channels no other test uses: the sky's memo cannot skip the rotation and band limit
    compute_tsky(
        "gsm2008",
        "dipole",
        "hera",
        np.array(freqs_mhz) * 1e6,
        np.linspace(0, 24, 6, endpoint=False),
        nside=32,
        cache=False,
    )


def test_the_tsky_computation_stops_at_each_of_its_checkpoints() -> None:
    calls: list[int] = []

    def count() -> bool:
        calls.append(1)
        return False

    with stop_when(count):
        _tsky((101.25, 133.75))
    # two channels give a rank-2 sky: the rotation of its two maps, the band limit of
    # those and of the CMB, and at least one chunk of the engine
    total = len(calls)
    assert total >= 6, total
    for stop_at in (1, total // 2, total):  # the first, a middle and the last (a chunk)
        seen: list[int] = []

        def stop(stop_at: int = stop_at, seen: list[int] = seen) -> bool:
            seen.append(1)
            return len(seen) >= stop_at

        with stop_when(stop), pytest.raises(RunCancelledError):
            _tsky((101.25, 133.75 + stop_at / 1000))
        assert len(seen) == stop_at


def test_a_calibration_stops_inside_its_tsky_stage(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    import autocal

    monkeypatch.setenv("AUTOCAL_CACHE_DIR", "off")
    obs, _ = simulate(
        SimulationConfig(beam="dipole", channel_width_khz=4000, duration_h=2, cadence_s=900)
    )
    messages: list[str] = []
    caplog.set_level(logging.INFO, logger="autocal")
    with pytest.raises(RunCancelledError, match="cancelled"):
        autocal.calibrate(
            obs,
            beam="dipole",
            nside=32,
            progress=lambda f, m: messages.append(m),
            should_stop=lambda: any(m.startswith("Tsky for") for m in messages),
        )
    # stopped inside the Tsky stage (before this, at its end, after a whole computation)
    assert not any("Tsky harmonics for" in r.getMessage() for r in caplog.records)
    assert messages[-1].startswith("Tsky for")


def test_a_stop_asked_after_the_products_are_published_does_not_fail_the_run(
    monkeypatch: pytest.MonkeyPatch, tmp_path
) -> None:
    import autocal

    monkeypatch.setenv("AUTOCAL_CACHE_DIR", "off")
    obs, _ = simulate(
        SimulationConfig(beam="dipole", channel_width_khz=4000, duration_h=2, cadence_s=900)
    )
    out = tmp_path / "cal"
    # True once summary.json is published (the last product): nothing is left to stop
    sol = autocal.calibrate(
        obs,
        beam="dipole",
        nside=32,
        out=out,
        products=["hdf5"],
        should_stop=lambda: (out / "summary.json").exists(),
    )
    assert sol.G.shape[-1] == obs.freqs.size
    assert (out / "summary.json").is_file() and (out / "solution.h5").is_file()
