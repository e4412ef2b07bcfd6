"""The effects' templates."""

from __future__ import annotations

import numpy as np

import autocal.tsky.compute
from autocal.core.sites import HERA
from autocal.diagnosis.effects import sky_templates


def test_beam_width_templates_come_from_the_tsky_cache(tmp_cache, monkeypatch) -> None:
    """The four widened beams of the beam_width template are cached Tsky harmonics: a
    second diagnosis of the night computes none of them again (same templates)."""
    freqs = np.linspace(120e6, 180e6, 4)
    lsts = np.linspace(0.0, 23.0, 24)
    kw = {"pols": ("ee",), "nside": 16, "epoch": 2458116.0}
    first = sky_templates("uniform:300", "dipole", HERA, freqs, lsts, **kw)
    assert len(list(tmp_cache.rglob("*.h5"))) >= 4
    real = autocal.tsky.ringfft.tsky_harmonics

    def no_widened_beams(sky, beam, *args, **kwargs):
        assert "scaled" not in str(beam.describe()), "a widened beam was computed again"
        return real(sky, beam, *args, **kwargs)

    monkeypatch.setattr(autocal.tsky.compute, "tsky_harmonics", no_widened_beams)
    second = sky_templates("uniform:300", "dipole", HERA, freqs, lsts, **kw)
    np.testing.assert_allclose(second.beam_width_poly, first.beam_width_poly, rtol=1e-12)


def test_frame_tilt_templates_follow_the_span_unless_asked(tmp_cache) -> None:
    """By default the frame-tilt templates of ``timing_offset`` are made over spans of
    DIURNAL_MIN_SPAN_H or more (as ``autocal diagnose`` has them) and not over shorter ones,
    also for LSTs that wrap through 24 h; ``tilt`` decides when given."""
    from autocal.diagnosis.effects import DIURNAL_MIN_SPAN_H

    freqs = np.linspace(120e6, 180e6, 3)
    kw = {"pols": ("ee",), "nside": 16, "epoch": 2458116.0, "beam_width_step": None}
    day = np.linspace(0.0, 23.0, 24)
    wrapped = np.mod(np.linspace(20.0, 21.0 + DIURNAL_MIN_SPAN_H, 8), 24.0)
    exactly = np.linspace(1.0, 1.0 + DIURNAL_MIN_SPAN_H, 8)  # its ptp rounds below 6 h
    short = np.linspace(2.0, 2.0 + 0.9 * DIURNAL_MIN_SPAN_H, 8)
    sky = "gsm2008"
    assert sky_templates(sky, "dipole", HERA, freqs, day, **kw).frame_tilt.shape == (2, 1, 24, 3)
    assert sky_templates(sky, "dipole", HERA, freqs, wrapped, **kw).frame_tilt is not None
    assert sky_templates(sky, "dipole", HERA, freqs, exactly, **kw).frame_tilt is not None
    assert sky_templates(sky, "dipole", HERA, freqs, short, **kw).frame_tilt is None
    assert sky_templates(sky, "dipole", HERA, freqs, day, tilt=False, **kw).frame_tilt is None
    forced = sky_templates(sky, "dipole", HERA, freqs, short, tilt=True, **kw)
    assert forced.frame_tilt is not None
