"""The catalogue: every candidate effect the search tries, for given data.

:func:`catalogue` lists the :class:`~autocal.diagnosis.effects.Effect` entries a search
fits on top of the model: the per-integration gain (``gain_jitter``) and the per-antenna
gains, the Legendre and diurnal drifts of the gain and the noise, the changes of Tsky,
``cable_reflection``, and, when their templates exist, ``timing_offset`` and ``beam_width``.
"""

from __future__ import annotations

from autocal.diagnosis.effects import DIURNAL_MIN_SPAN_H, Effect


def catalogue(
    max_drift_order: int = 2,
    include_beam_width: bool = True,
    ntime: int | None = None,
    include_timing: bool = False,
    span_h: float | None = None,
    nfeeds: int | None = None,
    include_tilt: bool = False,
) -> list[Effect]:
    """Return the candidate effects (drifts in every order ``1..max_drift_order``).

    Parameters
    ----------
    max_drift_order
        Highest Legendre order of ``gain_drift`` and ``noise_drift``.
    include_beam_width
        Include ``beam_width`` (needs :attr:`.SkyTemplates.beam_dwidth`).
    include_timing
        Include ``timing_offset`` (needs :attr:`.SkyTemplates.lst_derivative`).
    span_h
        LST span of the data (hours): the diurnal drift variants only when it is at least
        :data:`.DIURNAL_MIN_SPAN_H` (over a shorter span a sidereal-day sine and cosine are
        nearly collinear with a constant and a linear drift).
    ntime
        Number of integrations: with 3 or more, include ``gain_jitter`` (one broadband
        gain factor per integration, the first one the reference).
    nfeeds
        Number of antenna-pols: with 2 or more, include ``antenna_gain_drift`` (every
        antenna-pol its own Legendre drift, orders ``1..max_drift_order``) and (with
        ``ntime`` >= 3) ``antenna_gain_jitter``, every antenna-pol its own ``gain_jitter``
        series (tested against a common series once ``gain_jitter`` is in the model).
    include_tilt
        With ``include_timing``, ``timing_offset`` also turns the sky about the equatorial
        x and y axes (``tilt_x_arcmin``, ``tilt_y_arcmin``; needs
        :attr:`.SkyTemplates.frame_tilt`): a sky in a wrong frame, e.g. J2000 instead of
        the date, is turned about the pole and tilted.
    """
    return [
        *_jitter_entries(ntime, nfeeds),
        *_drift_entries(max_drift_order, nfeeds),
        *_diurnal_entries(span_h),
        *_tsky_entries(include_timing, include_beam_width, include_tilt),
    ]


def _jitter_entries(ntime: int | None, nfeeds: int | None) -> list[Effect]:
    """Return ``gain_jitter`` and ``antenna_gain_jitter`` (:func:`catalogue`)."""
    out: list[Effect] = []
    if ntime is not None and ntime >= 3:
        out.append(
            Effect(
                "gain_jitter",
                "gain",
                tuple(f"eps_{t}" for t in range(1, ntime)),
                ("1",) * (ntime - 1),
                1,
                signature="G(t_i) = G (1 + eps_i), every integration its own achromatic "
                "gain factor (broadband gain fluctuations)",
                basis="integration",
            )
        )
        if nfeeds is not None and nfeeds >= 2:
            out.append(
                Effect(
                    "antenna_gain_jitter",
                    "feed_gain",
                    ("rms",),
                    ("1",),
                    1,
                    signature="G_a(t_i) = G_a (1 + eps_a,i), every antenna-pol its own "
                    "per-integration gain series (gain fluctuations in each signal chain, "
                    "not common to the array)",
                    basis="feed_integration",
                )
            )
    return out


def _drift_entries(max_drift_order: int, nfeeds: int | None) -> list[Effect]:
    """Return the Legendre drifts of every order: per antenna-pol, gain, noise."""
    out: list[Effect] = []
    for order in range(1, max_drift_order + 1):
        names = tuple(f"d_{k}" for k in range(1, order + 1))
        if nfeeds is not None and nfeeds >= 2:
            out.append(
                Effect(
                    "antenna_gain_drift",
                    "feed_gain",
                    names,
                    ("1",) * order,
                    order,
                    signature="G_a(t) = G_a (1 + sum_k d_a,k P_k(s)), every antenna-pol its "
                    "own achromatic drift (one signal chain's gain changing against the "
                    "others')",
                    basis="feed_legendre",
                )
            )
        out.append(
            Effect(
                "gain_drift",
                "gain",
                names,
                ("1",) * order,
                order,
                signature="G(t) = G (1 + sum_k d_k P_k(s)), achromatic",
            )
        )
        names = tuple(f"e_{k}" for k in range(1, order + 1))
        out.append(
            Effect(
                "noise_drift",
                "noise",
                names,
                ("1",) * order,
                order,
                signature="n(t) = n (1 + sum_k e_k P_k(s)), achromatic",
            )
        )
    return out


def _diurnal_entries(span_h: float | None) -> list[Effect]:
    """Return the diurnal (sidereal-day harmonic) drifts of the gain and the noise."""
    out: list[Effect] = []
    diurnal = ("gain", "gain_drift", "d"), ("noise", "noise_drift", "e")
    if span_h is not None and span_h < DIURNAL_MIN_SPAN_H:
        diurnal = ()
    for kind, name, letter in diurnal:
        out.append(
            Effect(
                name,
                kind,  # type: ignore[arg-type]
                (f"{letter}_sin", f"{letter}_cos"),
                ("1", "1"),
                1,
                signature=f"{'G' if kind == 'gain' else 'n'}(t) x (1 + {letter}_sin sin(2 pi "
                f"L / 24 h) + {letter}_cos cos(2 pi L / 24 h)), diurnal, achromatic",
                basis="diurnal",
            )
        )
    return out


def _tsky_entries(
    include_timing: bool, include_beam_width: bool, include_tilt: bool = False
) -> list[Effect]:
    """Return the Tsky entries and ``cable_reflection``."""
    out = [
        Effect("sky_scale", "tsky", ("s",), ("1",), signature="S -> (1 + s) S"),
        Effect("sky_offset", "tsky", ("T_offset",), ("K",), signature="+ T_offset f_above"),
        Effect(
            "sky_spectral_index",
            "tsky",
            ("dbeta",),
            ("1",),
            signature="S -> S (nu / nu0)^dbeta",
        ),
        Effect("ground_temperature", "tsky", ("dT_gnd",), ("K",), signature="+ dT f_below"),
        Effect(
            "missing_cmb",
            "tsky",
            ("cmb_factor",),
            ("1",),
            signature="+ m 2.725 K f_above, m = -1 (no CMB in data) or +1 (CMB missed)",
        ),
        Effect(
            "cable_reflection",
            "bandpass",
            ("a", "tau_ns", "phi"),
            ("1", "ns", "rad"),
            signature="G(nu) smooth x (1 + a cos(2 pi nu tau + phi))",
        ),
    ]
    if include_timing and include_tilt:
        out.append(
            Effect(
                "timing_offset",
                "tsky",
                ("dt_s", "tilt_x_arcmin", "tilt_y_arcmin"),
                ("s", "arcmin", "arcmin"),
                signature="Tsky(t + dt) of a sky also tilted about the equatorial x and y "
                "axes: a clock or LST error, or a sky in a wrong frame (e.g. J2000 instead "
                "of the frame of date: turned in right ascension and tilted)",
            )
        )
    elif include_timing:
        out.append(
            Effect(
                "timing_offset",
                "tsky",
                ("dt_s",),
                ("s",),
                signature="Tsky(t + dt): a clock or LST error, or a sky in a frame rotated in "
                "right ascension (e.g. J2000 instead of the frame of date)",
            )
        )
    if include_beam_width:
        out.append(
            Effect(
                "beam_width",
                "tsky",
                ("w",),
                ("1",),
                signature="beam width x (1 + w): + sum_k c_k w^k (quartic via Tsky at 4 widths)",
            )
        )
    return out
