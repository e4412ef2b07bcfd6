"""The compared quantities: autocal's ``|g|`` and the ratio to the reference with its error.

:func:`auto_gains` takes the solution's ``|g|`` and errors on the compared axes;
:func:`gain_ratio` forms ``r = |g_auto| / |g_ref|`` (absolute) or the ratio of the shapes
normalised over the valid channels (relative), and the ratio's 1-sigma error (step 7 of
the procedure in :mod:`autocal.compare.comparison`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from autocal.compare.axes import MatchedAxes
from autocal.compare.errors import CompareError

if TYPE_CHECKING:
    from autocal.fit.solution import Solution


@dataclass(frozen=True, eq=False)
class AutoGains:
    """autocal's ``|g|`` on the compared axes, ``(Nant, Npol, Nfreq)``.

    Attributes
    ----------
    abs_g, sigma
        ``|g|`` and its 1-sigma error (the total error when the solution carries one).
    sigma_stat
        The statistical error alone, or ``None`` when the solution has no split.
    sys_rel
        The error beyond the statistical one, relative to ``|g|``, or ``None``.
    ok
        Channels valid in the solution (unflagged, finite, positive).
    """

    abs_g: np.ndarray
    sigma: np.ndarray
    sigma_stat: np.ndarray | None
    sys_rel: np.ndarray | None
    ok: np.ndarray


@dataclass(frozen=True, eq=False)
class GainRatio:
    """The compared quantities and their ratio, ``(Nant, Npol, Nfreq)``.

    Attributes
    ----------
    quantity
        What ``auto`` and ``reference`` hold.
    valid
        Channels valid on both sides.
    auto, sigma_auto
        autocal's ``|g|`` (normalised in relative mode) and its error.
    reference, sigma_reference
        The reference likewise (kelvin units in absolute mode).
    ratio, sigma
        ``auto / reference`` and its 1-sigma error (NaN where not valid).
    sigma_stat
        The ratio's error with the auto's statistical error only, or ``None``.
    rel_reference
        ``sigma_reference / reference`` (0 where unknown).
    auto_sys_rel
        The auto's relative systematic error (``None`` in relative mode, where a
        channel-common fractional error cancels in the shapes).
    """

    quantity: str
    valid: np.ndarray
    auto: np.ndarray
    sigma_auto: np.ndarray
    reference: np.ndarray
    sigma_reference: np.ndarray
    ratio: np.ndarray
    sigma: np.ndarray
    sigma_stat: np.ndarray | None
    rel_reference: np.ndarray
    auto_sys_rel: np.ndarray | None


def auto_gains(solution: Solution, axes: MatchedAxes) -> AutoGains:
    """Return the solution's ``|g|``, errors and valid channels on the compared axes.

    Parameters
    ----------
    solution
        An :class:`autocal.fit.solution.Solution`.
    axes
        The matched axes.

    Returns
    -------
    AutoGains
        ``(Nant, Npol, Nfreq)`` arrays.
    """
    idx_sol = np.ix_(axes.sol_antennas, axes.sol_pols)
    stat_all = getattr(solution, "sigma_abs_g_stat", None)
    with np.errstate(invalid="ignore", divide="ignore"):
        auto = np.asarray(solution.abs_g)[idx_sol]
        sigma_auto = np.asarray(solution.sigma_abs_g)[idx_sol]
        sigma_stat = None if stat_all is None else np.asarray(stat_all)[idx_sol]
        # the part of the auto's (total) error beyond the statistical one, relative
        auto_sys_rel = (
            None
            if sigma_stat is None
            else np.sqrt(np.clip(sigma_auto**2 - sigma_stat**2, 0.0, None)) / auto
        )
    auto_ok = (
        ~np.asarray(solution.flags)[idx_sol]
        & np.isfinite(auto)
        & (auto > 0)
        & np.isfinite(sigma_auto)
    )
    return AutoGains(
        abs_g=auto, sigma=sigma_auto, sigma_stat=sigma_stat, sys_rel=auto_sys_rel, ok=auto_ok
    )


def gain_ratio(mode: str, auto: AutoGains, ref_i: np.ndarray, sig_i: np.ndarray) -> GainRatio:
    """Return the ratio of autocal's ``|g|`` to the reference's and its error.

    Parameters
    ----------
    mode
        ``"absolute"`` (``ref_i`` in kelvin units) or ``"relative"`` (both sides are
        divided by their mean over the channels valid in both).
    auto
        From :func:`auto_gains`.
    ref_i, sig_i
        ``(Nant, Npol, Nfreq)`` the reference on the solution's channels and its error.

    Returns
    -------
    GainRatio
        The compared quantities, the ratio and its errors.

    Raises
    ------
    CompareError
        When no channel is valid on both sides.
    """
    valid = auto.ok & np.isfinite(ref_i) & (ref_i > 0)
    if not valid.any():
        raise CompareError(
            "no channel is valid in both the solution and the reference (check flags and "
            "the frequency overlap)"
        )
    sigma_auto, sigma_stat = auto.sigma, auto.sigma_stat
    auto_sys_rel = auto.sys_rel
    if mode == "relative":
        quantity = "|g| / mean over valid channels"
        nvalid = valid.sum(axis=-1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            a_mean = np.where(valid, auto.abs_g, 0.0).sum(axis=-1, keepdims=True) / nvalid
            r_mean = np.where(valid, ref_i, 0.0).sum(axis=-1, keepdims=True) / nvalid
            auto_c, sig_auto_c = auto.abs_g / a_mean, sigma_auto / a_mean
            ref_c, sig_ref_c = ref_i / r_mean, sig_i / r_mean
        auto_sys_rel = None  # a channel-common fractional error cancels in the shapes
    else:
        quantity = "|g| = sqrt(G) in sqrt(raw/K)"
        auto_c, sig_auto_c, ref_c, sig_ref_c = auto.abs_g, sigma_auto, ref_i, sig_i
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(valid, auto_c / ref_c, np.nan)
        rel_ref = np.where(np.isfinite(sig_ref_c), sig_ref_c / ref_c, 0.0)
        sigma_ratio = np.where(
            valid, np.abs(ratio) * np.sqrt((sig_auto_c / auto_c) ** 2 + rel_ref**2), np.nan
        )
        sigma_ratio_stat = (
            None
            if sigma_stat is None
            else np.where(
                valid,
                np.abs(ratio) * np.sqrt((sigma_stat / auto.abs_g) ** 2 + rel_ref**2),
                np.nan,
            )
        )
    return GainRatio(
        quantity=quantity,
        valid=valid,
        auto=auto_c,
        sigma_auto=sig_auto_c,
        reference=ref_c,
        sigma_reference=sig_ref_c,
        ratio=ratio,
        sigma=sigma_ratio,
        sigma_stat=sigma_ratio_stat,
        rel_reference=rel_ref,
        auto_sys_rel=auto_sys_rel,
    )
