"""EDGES receiver calibration equations: three-position switch and noise waves.

Formulas (Monsalve et al. 2017, ApJ 835, 49, "M17", Eqs. 3-7; Rogers & Bowman 2012;
Bowman et al. 2018; implemented as in ``edges-cal``'s ``receiver_calibration_func``):

Switch powers ``p0`` (antenna), ``p1`` (ambient load), ``p2`` (load + noise source)::

    Q  = (p0 - p1) / (p2 - p1)
    T* = T_NS Q + T_L                        (nominal T_NS, T_L of the solution)

Reflection factors (``Gr`` LNA reflection coefficient, ``Ga`` antenna or load)::

    F  = sqrt(1 - |Gr|^2) / (1 - Ga Gr),    alpha = arg(Ga F)
    K1 = (1 - |Ga|^2) |F|^2 / (1 - |Gr|^2)  ( = (1 - |Ga|^2) / |1 - Ga Gr|^2 )
    K2 = |Ga|^2 |F|^2 / (1 - |Gr|^2)
    K3 = |Ga| |F| cos(alpha) / (1 - |Gr|^2),   K4 = |Ga| |F| sin(alpha) / (1 - |Gr|^2)

Calibration equation (M17 Eq. 7)::

    C1 (T* - T_L) + T_L - C2 = K1 T_ant + K2 T_unc + K3 T_cos + K4 T_sin
    T_ant = [C1 (T* - T_L) + T_L - C2 - T_nw] / K1,   T_nw = K2 T_unc + K3 T_cos + K4 T_sin

With the *effective* noise-source excess ``T_NS' = C1 T_NS`` and load temperature
``T_L' = T_L - C2`` this is ``Q = (K1 T_ant + T_nw - T_L') / T_NS'``. Raw powers need
two numbers a calibration solution does not fix (they cancel in ``Q``): the system gain
``g`` (arbitrary raw scale) and a noise offset ``T_0`` added to all three positions::

    p1 = g (T_L' + T_0),  p2 = g (T_L' + T_NS' + T_0),  p0 = g (K1 T_ant + T_nw + T_0)

(:func:`decalibrate`; ``T_0`` from ``p2 / p1`` of the EDGES-3 lab files is 450-570 K over
50-190 MHz, default 500 K.) The auto-correlation model ``R = G T_ant + n`` implied by a
solution (:func:`expected_auto_model`)::

    R = Q :  G = K1 / T_NS',   n = (T_nw - T_L') / T_NS',   Trxr = (T_nw - T_L') / K1
    R = p0:  G = g K1,         n = g (T_nw + T_0),          Trxr = (T_nw + T_0) / K1

Both are exactly linear in ``T_ant`` for any antenna reflection that is constant in time:
``Ga`` only sets the coefficients (matched, ``Ga = 0``: ``G = 1 / (C1 T_NS)`` and
``Trxr = C2 - T_L`` for ``Q``, about -302 K for EDGES-2, negative because ``Q`` subtracts
the load). What is approximate in comparing with a sky fit is ``T_ant = Tsky``: real data
carry antenna, balun and ground losses (``T_ant = eta Tsky + (1 - eta) T_phys``), which
scale ``G`` by ``eta`` and move ``Trxr``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from autocal.edges.solutions import ReceiverCalError, ReceiverSolution, resolve_solution

#: Default noise offset ``T_0`` added to all switch positions by :func:`decalibrate` (K).
T_OFFSET_DEFAULT = 500.0
#: Default raw power per kelvin (keeps simulated powers near real ACQ levels, ~1e-7).
RAW_SCALE_DEFAULT = 1e-11


def k_factors(
    gamma_rec: np.ndarray, gamma_ant: np.ndarray | complex
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Return ``K1, K2, K3, K4`` of M17 Eq. 7 (factors of ``T_ant, T_unc, T_cos, T_sin``)."""
    gr = np.asarray(gamma_rec, np.complex128)
    ga = np.asarray(gamma_ant, np.complex128)
    gain = 1.0 - np.abs(gr) ** 2
    f = np.sqrt(gain) / (1.0 - ga * gr)
    alpha = np.angle(ga * f)
    fg = np.abs(ga) * np.abs(f) / gain
    k2 = fg**2 * gain
    k1 = np.abs(f) ** 2 / gain - k2
    return k1, k2, fg * np.cos(alpha), fg * np.sin(alpha)


def noise_wave_temperature(solution: ReceiverSolution, gamma_ant: Any = 0.0) -> np.ndarray:
    """``T_nw = K2 T_unc + K3 T_cos + K4 T_sin`` (K) for an antenna reflection."""
    _, k2, k3, k4 = k_factors(solution.gamma_rec, gamma_at(gamma_ant, solution.freqs))
    return k2 * solution.t_unc + k3 * solution.t_cos + k4 * solution.t_sin


def tstar_from_q(q: np.ndarray, t_load_ns: float, t_load: float) -> np.ndarray:
    """Uncalibrated temperature ``T* = T_NS Q + T_L``."""
    return t_load_ns * np.asarray(q) + t_load


def calibrate_tstar(
    tstar: np.ndarray, solution: ReceiverSolution | str, gamma_ant: Any = 0.0
) -> np.ndarray:
    """Calibrated antenna temperature from ``T*`` (M17 Eq. 7), K.

    Parameters
    ----------
    tstar
        ``(..., Nfreq)`` uncalibrated temperature at the solution's frequencies.
    solution
        Receiver solution (tabulated at the same frequencies; use ``solution.at``).
    gamma_ant
        Antenna (or load) reflection coefficient: scalar, ``(Nfreq,)`` or ``(freqs_hz,
        gamma)`` to interpolate.
    """
    sol = resolve_solution(solution)
    k1, _, _, _ = k_factors(sol.gamma_rec, gamma_at(gamma_ant, sol.freqs))
    t_nw = noise_wave_temperature(sol, gamma_ant)
    lhs = sol.c1 * (np.asarray(tstar) - sol.t_load) + sol.t_load - sol.c2
    return (lhs - t_nw) / k1


def calibrate_q(
    q: np.ndarray, solution: ReceiverSolution | str, gamma_ant: Any = 0.0
) -> np.ndarray:
    """Calibrated antenna temperature (K) from ``Q`` with the solution's nominal ``T_NS, T_L``."""
    sol = resolve_solution(solution)
    return calibrate_tstar(tstar_from_q(q, sol.t_load_ns, sol.t_load), sol, gamma_ant)


def calibrate_powers(
    p0: np.ndarray,
    p1: np.ndarray,
    p2: np.ndarray,
    solution: ReceiverSolution | str,
    gamma_ant: Any = 0.0,
) -> np.ndarray:
    """Calibrated antenna temperature (K) from the three switch powers."""
    p0, p1, p2 = (np.asarray(x, np.float64) for x in (p0, p1, p2))
    with np.errstate(divide="ignore", invalid="ignore"):
        q = (p0 - p1) / (p2 - p1)
    return calibrate_q(q, solution, gamma_ant)


def decalibrate_q(
    t_ant: np.ndarray, solution: ReceiverSolution | str, gamma_ant: Any = 0.0
) -> np.ndarray:
    """``Q`` a receiver with this solution measures for antenna temperature ``t_ant`` (K)."""
    sol = resolve_solution(solution)
    k1, _, _, _ = k_factors(sol.gamma_rec, gamma_at(gamma_ant, sol.freqs))
    t_nw = noise_wave_temperature(sol, gamma_ant)
    return (k1 * np.asarray(t_ant) + t_nw - sol.t_load_eff) / sol.t_ns_eff


def decalibrate(
    t_ant: np.ndarray,
    solution: ReceiverSolution | str,
    gamma_ant: Any = 0.0,
    *,
    raw_scale: float | np.ndarray = RAW_SCALE_DEFAULT,
    t_offset: float | np.ndarray = T_OFFSET_DEFAULT,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw switch powers for antenna temperature ``t_ant`` (inverse of :func:`calibrate_powers`).

    ``p1 = g (T_L' + T_0)``, ``p2 = g (T_L' + T_NS' + T_0)``, ``p0 = g (K1 T_ant + T_nw +
    T_0)`` with ``T_NS' = C1 T_NS``, ``T_L' = T_L - C2`` of the solution's nominal
    ``T_NS, T_L``.

    Parameters
    ----------
    t_ant
        ``(..., Nfreq)`` antenna temperature in K at the solution's frequencies.
    solution
        Receiver solution (tabulated at the same frequencies).
    gamma_ant
        Antenna reflection coefficient (see :func:`calibrate_tstar`).
    raw_scale
        System gain ``g``: raw power per kelvin (scalar or ``(Nfreq,)`` bandpass).
    t_offset
        Noise offset ``T_0`` (K) common to the three positions; it cancels in ``Q``.

    Returns
    -------
    p0, p1, p2 : numpy.ndarray
        Broadcast to the shape of ``t_ant``.
    """
    sol = resolve_solution(solution)
    t_ant = np.asarray(t_ant, np.float64)
    k1, _, _, _ = k_factors(sol.gamma_rec, gamma_at(gamma_ant, sol.freqs))
    t_nw = noise_wave_temperature(sol, gamma_ant)
    g = np.asarray(raw_scale, np.float64)
    t0 = np.asarray(t_offset, np.float64)
    p0 = g * (k1 * t_ant + t_nw + t0)
    p1 = np.broadcast_to(g * (sol.t_load_eff + t0), t_ant.shape).copy()
    p2 = np.broadcast_to(g * (sol.t_load_eff + sol.t_ns_eff + t0), t_ant.shape).copy()
    if np.any(p1 <= 0) or np.any(p2 <= p1):
        raise ReceiverCalError("raw_scale and t_offset must make p1 > 0 and p2 > p1")
    return p0, p1, p2


@dataclass(frozen=True)
class AutoModelExpectation:
    """The ``R = G T_ant + n`` coefficients implied by a receiver solution.

    Attributes
    ----------
    r
        ``"q"`` or ``"p0"``.
    freqs
        Hz.
    G, n, trxr
        Gain (R per K), offset (R units) and ``Trxr = n / G`` (K).
    k1, t_nw
        The reflection factor of ``T_ant`` and the noise-wave temperature (K).
    note
        The approximations behind a comparison with a sky fit.
    """

    r: str
    freqs: np.ndarray
    G: np.ndarray
    n: np.ndarray
    trxr: np.ndarray
    k1: np.ndarray
    t_nw: np.ndarray
    note: str = ""


def expected_auto_model(
    solution: ReceiverSolution | str,
    gamma_ant: Any = 0.0,
    r: Literal["q", "p0"] = "q",
    *,
    raw_scale: float | np.ndarray = RAW_SCALE_DEFAULT,
    t_offset: float | np.ndarray = T_OFFSET_DEFAULT,
) -> AutoModelExpectation:
    """Return the ``G`` and ``Trxr`` of ``R = G T_ant + n`` a receiver solution implies.

    ``Q``: ``G = K1 / (C1 T_NS)``, ``Trxr = (T_nw - T_L + C2) / K1``. ``p0``: ``G = g K1``,
    ``Trxr = (T_nw + T_0) / K1`` (needs the raw scale ``g`` and offset ``T_0`` the powers
    were generated with; they are not part of a calibration solution). Exact for any
    time-constant antenna reflection; the sky fit sees ``T_ant = Tsky`` only when the
    antenna is lossless.
    """
    sol = resolve_solution(solution)
    if r not in ("q", "p0"):
        raise ReceiverCalError(f"unknown auto-correlation kind {r!r}: use 'q' or 'p0'")
    k1, _, _, _ = k_factors(sol.gamma_rec, gamma_at(gamma_ant, sol.freqs))
    t_nw = noise_wave_temperature(sol, gamma_ant)
    if r == "q":
        gain = k1 / sol.t_ns_eff
        offset = (t_nw - sol.t_load_eff) / sol.t_ns_eff
    else:
        g = np.asarray(raw_scale, np.float64)
        gain = np.broadcast_to(g * k1, sol.freqs.shape).copy()
        offset = np.broadcast_to(g * (t_nw + np.asarray(t_offset, np.float64)), sol.freqs.shape)
    note = (
        "exactly linear in T_ant for a time-constant antenna reflection; compared with a sky "
        "fit, T_ant = Tsky assumes a lossless antenna (losses eta scale G by eta and add "
        "(1 - eta) T_phys / eta to Trxr)"
    )
    return AutoModelExpectation(
        r, sol.freqs, gain, np.asarray(offset), offset / gain, k1, t_nw, note
    )


def gamma_at(gamma_ant: Any, freqs: np.ndarray) -> np.ndarray:
    """Resolve an antenna reflection (scalar, per-channel array, or ``(freqs, gamma)``)."""
    if isinstance(gamma_ant, tuple) and len(gamma_ant) == 2:
        fg, gg = (np.asarray(x) for x in gamma_ant)
        if freqs.min() < fg.min() - 1.0 or freqs.max() > fg.max() + 1.0:
            raise ReceiverCalError(
                f"the antenna S11 covers {fg.min() / 1e6:.3f}-{fg.max() / 1e6:.3f} MHz, not "
                f"{freqs.min() / 1e6:.3f}-{freqs.max() / 1e6:.3f} MHz"
            )
        gg = np.asarray(gg, np.complex128)
        return np.interp(freqs, fg, gg.real) + 1j * np.interp(freqs, fg, gg.imag)
    arr = np.asarray(gamma_ant, np.complex128)
    if arr.ndim == 0:
        return np.full(freqs.shape, complex(arr))
    if arr.shape[-1] != freqs.size:
        raise ReceiverCalError(f"gamma_ant has {arr.shape[-1]} channels for {freqs.size}")
    if np.any(np.abs(arr) > 1):
        raise ReceiverCalError("|gamma_ant| must not exceed 1")
    return arr


def two_load_solution(
    q_amb: np.ndarray, q_hot: np.ndarray, t_amb: float, t_hot: float
) -> tuple[np.ndarray, np.ndarray]:
    """Effective ``T_NS'`` and ``T_L'`` from an ambient and a hot load (matched loads).

    With ``|Ga| ~ 0`` the calibration is ``T = T_NS' Q + T_L'``, so two loads of known
    temperature fix it: ``T_NS' = (t_hot - t_amb) / (q_hot - q_amb)``, ``T_L' = t_amb -
    T_NS' q_amb``. Neglects ``|Ga|^2`` and the noise waves (``|Ga| T_cos``-sized terms).
    """
    q_amb, q_hot = np.asarray(q_amb, np.float64), np.asarray(q_hot, np.float64)
    t_ns = (t_hot - t_amb) / (q_hot - q_amb)
    return t_ns, t_amb - t_ns * q_amb
