"""The gap between a fit and the data, and the unexplained remainder."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from autocal.diagnosis.gap import describe_unexplained


def test_unexplained_remainder_is_described_not_named(setup):
    """A gap left after the search is reported with its structure; a fit within the noise
    is not."""
    obs, _ = setup
    rng = np.random.default_rng(3)
    shape = (1, 1, obs.ntime, obs.nfreq)
    white = rng.standard_normal(shape)
    dof = white.size - 2 * obs.nfreq
    base = {
        "chi2": float((white**2).sum()),
        "dof": dof,
        "reduced_chi2": float((white**2).sum() / dof),
        "time_mode_power": [1.0, 1.1, 0.9, 1.0],
        "integration_jitter": 1.0,
        "residual_delay_power": {"max": 1.5, "delay_ns": 300.0},
    }
    assert describe_unexplained(SimpleNamespace(residuals=white), obs, base) is None
    smooth = white + 0.5 * np.linspace(-1, 1, obs.ntime)[None, None, :, None]
    gap = {
        **base,
        "chi2": float((smooth**2).sum()),
        "reduced_chi2": float((smooth**2).sum() / dof),
        "time_mode_power": [1.0, 40.0, 2.0, 1.0],
    }
    out = describe_unexplained(SimpleNamespace(residuals=smooth), obs, gap)
    assert out is not None and out["time"] == "smooth in time"
    assert out["excess_sigma"] > 5 and "unexplained" in out["message"]
    assert out["antennas"][0]["antenna"] == int(obs.antennas[0])
    jumpy = {**gap, "time_mode_power": [1.0, 1.2, 1.1, 1.0], "integration_jitter": 6.0}
    out = describe_unexplained(SimpleNamespace(residuals=smooth), obs, jumpy)
    assert out is not None and out["time"].startswith("integration to integration")
