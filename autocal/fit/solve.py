"""Solving the normal equations of every channel at once.

All channels, antennas and polarisations are solved at once (:func:`solve_sums`, a
compiled loop over channels; :func:`solve_sums_numpy`, batched numpy linear algebra in
blocks that bound the temporaries, is its reference). A channel with too few
samples, a singular normal matrix or a non-positive gain is flagged with its reason
(:data:`FLAG_REASONS`) and its values set to NaN, never filled.

Both solve in the sky-centred frame (:mod:`autocal.fit.centring`): the congruence that
replaces each gain column ``Tsky P_k`` by ``(Tsky - c) P_k``, ``c`` the weighted time mean
of ``Tsky`` taken from the sums, and maps the solution and covariance back. Over a short
span the sky changes by ~1 % of its mean and the column-scaled normal matrix is nearly
singular in the original frame (condition ~5e10 for a 10-minute HERA file's extended
model): solved there, coefficients kept ~6 digits (1e-6 median relative error, 6e-4 at
worst, against exact rational solves of the same sums) and the total uncertainty built on
them moved by up to x300. In the centred frame the condition is ~5e5 and the same
comparison gives 1e-10 (median; 1e-6 at worst).

Singular: the column-scaled centred matrix's condition number, or the digits the
centring cancelled (:func:`autocal.fit.centring.cancellation_bound`, which for the
constant model is, as it nears singularity, the original matrix's condition number: the
same channels as before), reaches :data:`MAX_CONDITION`. So a sky that does not change
stays singular, while a 10-minute span whose sky changes by ~1 % solves even where the
original frame's condition passes 1e12 (~2 % of the extended fits of those files, now
solved to 7e-9, median).

``chi^2`` is the residual sum of squares at the solution (``y^T y - 2 x^T b + x^T A x``),
which an error of the solve changes only to second order.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from autocal.fit.centring import (
    cancellation_bound,
    centre,
    centre_rhs,
    sky_mean,
    uncentre,
    uncentre_cov,
)
from autocal.fit.finite import finite_trailing
from autocal.fit.model import FitError
from autocal.fit.sums import NormalSums

#: Reasons a channel is flagged by the fit (``Solution.flag_reason`` codes).
FLAG_REASONS: dict[int, str] = {
    0: "ok",
    1: "too few unflagged samples",
    2: "singular normal matrix",
    3: "non-positive gain",
    4: "band edge",
    5: "RFI",
    6: "no usable data",
}
#: ``flag_reason`` of a channel with too few unflagged samples.
FLAG_TOO_FEW = 1
#: ``flag_reason`` of a channel flagged whole as a band edge before the fit
#: (:mod:`autocal.pipeline.rfi`).
FLAG_BAND_EDGE = 4
#: ``flag_reason`` of a channel flagged whole (or at every integration) for RFI before the fit.
FLAG_RFI = 5
#: ``flag_reason`` of a channel with no usable sample at all ("no usable data": every one
#: flagged by the file, or NaN, infinite, zero or negative), found by the flagging's
#: time-mean spectra.
FLAG_NO_DATA = 6
#: Largest condition number of the (column-scaled, sky-centred) normal matrix accepted as
#: solvable (see the module notes).
MAX_CONDITION = 1e12


#: Channel systems solved per block by :func:`solve_sums_numpy`: its temporaries (scaled normal
#: matrices, inverses) are then a few MB per block instead of several copies of ``ata``
#: (for a Legendre-2 fit of 350 antennas x 2 pols x 1536 channels, 310 MB each).
SOLVE_BLOCK = 1 << 14


def solve_sums(
    sums: NormalSums,
    *,
    min_samples: int | None = None,
    scale_covariance: bool | Literal["inflate"] = False,
    max_condition: float = MAX_CONDITION,
    positive_gain: bool = True,
) -> dict[str, np.ndarray]:
    """Solve the normal equations of every channel.

    Computed channel by channel by the compiled
    :func:`autocal.fit.solve_kernel.solve_channels`; :func:`solve_sums_numpy` is the same
    as batched numpy linear algebra (its reference).

    Parameters
    ----------
    sums
        Accumulated sums.
    min_samples
        Fewest used samples for a channel to be solved (default ``nparam + 1``).
    scale_covariance
        ``True``: multiply the covariance by ``chi^2 / dof`` (for weights that are not
        inverse variances, e.g. identity). ``"inflate"``: multiply by ``max(1, chi^2 /
        dof)``, so errors from inverse-variance weights also cover unmodelled structure
        in real data without being shrunk below the noise.
    max_condition
        Largest condition number of the column-scaled normal matrix in the sky-centred
        frame (or of the centring's cancellation), see the module notes.
    positive_gain
        Flag (reason 3) channels whose first gain coefficient is not positive. ``False``
        keeps such solutions (refits that only serve an error estimate).

    Returns
    -------
    dict
        ``coeffs`` (..., M), ``cov`` (..., M, M), ``chi2``, ``dof``, ``flag_reason``.
    """
    from autocal.fit.solve_kernel import solve_channels  # numba: only when solving

    m, min_samples, flat = _flattened(sums, min_samples)
    ata, aty, yty, count = flat
    mode = 0 if not scale_covariance else (2 if scale_covariance == "inflate" else 1)
    out = solve_channels(ata, aty, yty, count, min_samples, mode, max_condition, positive_gain)
    out["dof"] = (count - m).astype(np.float64)
    lead = sums.count.shape
    return {name: value.reshape(*lead, *value.shape[1:]) for name, value in out.items()}


def _flattened(
    sums: NormalSums, min_samples: int | None
) -> tuple[int, int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Return ``M``, the checked ``min_samples`` and the sums as ``(N, ...)`` arrays."""
    m = sums.model.nparam
    min_samples = m + 1 if min_samples is None else int(min_samples)
    if min_samples < m:
        raise FitError(f"min_samples must be at least the number of parameters ({m})")
    flat = (
        sums.ata.reshape(-1, m, m),
        sums.aty.reshape(-1, m),
        sums.yty.reshape(-1),
        sums.count.reshape(-1),
    )
    return m, min_samples, flat


def solve_sums_numpy(
    sums: NormalSums,
    *,
    min_samples: int | None = None,
    scale_covariance: bool | Literal["inflate"] = False,
    max_condition: float = MAX_CONDITION,
    block: int = SOLVE_BLOCK,
    positive_gain: bool = True,
) -> dict[str, np.ndarray]:
    """:func:`solve_sums` as batched numpy linear algebra, ``block`` channels at a time.

    The compiled solver's reference (several times slower on a HERA file). ``block``
    bounds the temporaries; the result does not depend on it.
    """
    if block < 1:
        raise FitError(f"block must be at least 1 channel system, got {block}")
    m, min_samples, (ata, aty, yty, count) = _flattened(sums, min_samples)
    lead = sums.count.shape
    n = count.size
    out = {
        "coeffs": np.empty((n, m)),
        "cov": np.empty((n, m, m)),
        "chi2": np.empty(n),
        "dof": (count - m).astype(np.float64),
        "flag_reason": np.zeros(n, np.int8),
    }
    for i0 in range(0, n, block):
        sl = slice(i0, min(i0 + block, n))
        part = _solve_block(
            ata[sl],
            aty[sl],
            yty[sl],
            count[sl],
            min_samples,
            scale_covariance,
            max_condition,
            positive_gain,
        )
        for name, value in part.items():
            out[name][sl] = value
    return {name: value.reshape(*lead, *value.shape[1:]) for name, value in out.items()}


def sym_eigvalsh(a: np.ndarray) -> np.ndarray:
    """Eigenvalues of ``(..., M, M)`` symmetric matrices; closed form for ``M = 2``.

    The constant model's 2 x 2 systems (a million per HERA file) take ~20 ms this way
    against ~0.3 s through LAPACK.
    """
    if a.shape[-1] != 2:
        return np.linalg.eigvalsh(a)
    mean = (a[..., 0, 0] + a[..., 1, 1]) / 2
    radius = np.hypot((a[..., 0, 0] - a[..., 1, 1]) / 2, a[..., 1, 0])
    return np.stack([mean - radius, mean + radius], axis=-1)


def sym_inv(a: np.ndarray) -> np.ndarray:
    """Inverses of ``(..., M, M)`` symmetric matrices; closed form (adjugate) for ``M = 2``."""
    if a.shape[-1] != 2:
        return np.linalg.inv(a)
    det = a[..., 0, 0] * a[..., 1, 1] - a[..., 1, 0] * a[..., 1, 0]
    out = np.empty_like(a)
    out[..., 0, 0] = a[..., 1, 1] / det
    out[..., 1, 1] = a[..., 0, 0] / det
    out[..., 0, 1] = out[..., 1, 0] = -a[..., 1, 0] / det
    return out


def _solve_block(
    ata: np.ndarray,
    aty: np.ndarray,
    yty: np.ndarray,
    count: np.ndarray,
    min_samples: int,
    scale_covariance: bool | Literal["inflate"],
    max_condition: float,
    positive_gain: bool = True,
) -> dict[str, np.ndarray]:
    """Solve ``(n, M, M)`` normal systems (see :func:`solve_sums`), in the sky-centred frame."""
    m = ata.shape[-1]
    reason = np.zeros(count.shape, np.int8)
    reason[count < min_samples] = 1
    c = sky_mean(ata)
    centred, rhs = centre(ata, c), centre_rhs(aty, c)
    diag = np.diagonal(centred, axis1=-2, axis2=-1)
    d = np.where(diag > 0, np.sqrt(np.where(diag > 0, diag, 1.0)), 1.0)
    scaled = centred / (d[..., :, None] * d[..., None, :])
    ok = (reason == 0) & np.all(diag > 0, axis=-1) & finite_trailing(scaled, 2)
    reason[(reason == 0) & ~ok] = 2
    eye = np.eye(m)
    scaled = np.where(ok[..., None, None], scaled, eye)
    # 2-norm condition number of the symmetric matrix from its eigenvalues (as
    # np.linalg.cond, but eigvalsh is several times faster than an SVD per channel), and
    # the digits the centring cancelled (centring.cancellation_bound)
    ev = np.abs(sym_eigvalsh(scaled))
    with np.errstate(divide="ignore", invalid="ignore"):
        cond = np.maximum(ev.max(axis=-1) / ev.min(axis=-1), cancellation_bound(ata, centred))
    singular = ok & ~(np.isfinite(cond) & (cond < max_condition))
    reason[singular] = 2
    ok &= ~singular
    scaled = np.where(ok[..., None, None], scaled, eye)
    inv = sym_inv(scaled)
    cov = inv / (d[..., :, None] * d[..., None, :])
    coeffs = (cov @ rhs[..., None])[..., 0]
    chi2 = _chi2(yty, centred, rhs, coeffs)
    coeffs, cov = uncentre(coeffs, c), uncentre_cov(cov, c)
    dof = (count - m).astype(np.float64)
    if scale_covariance:
        with np.errstate(divide="ignore", invalid="ignore"):
            factor = np.where(dof > 0, chi2 / dof, np.nan)
        if scale_covariance == "inflate":
            factor = np.maximum(np.nan_to_num(factor, nan=1.0), 1.0)
        cov = cov * factor[..., None, None]
    if positive_gain:
        reason[ok & ~(coeffs[..., 0] > 0)] = 3
    bad = reason != 0
    coeffs = np.where(bad[..., None], np.nan, coeffs)
    cov = np.where(bad[..., None, None], np.nan, cov)
    chi2 = np.where(bad, np.nan, chi2)
    return {"coeffs": coeffs, "cov": cov, "chi2": chi2, "flag_reason": reason}


def _chi2(yty: np.ndarray, ata: np.ndarray, aty: np.ndarray, coeffs: np.ndarray) -> np.ndarray:
    """``chi^2 = y^T y - 2 x^T b + x^T A x`` at the solution ``x``, at least 0.

    The residual sum of squares is stationary at the solution, so an error ``dx`` of the
    solve changes it by ``dx^T A dx`` only: ``y^T y - x^T b`` (equal for the exact ``x``)
    changes by ``dx^T b``, which on an ill-conditioned system (a 10-minute span's extended
    model, a few samples) is as large as ``chi^2`` itself. Evaluated as ``y^T y - x^T (b +
    r)`` with the residual ``r = b - A x``. Still a difference of large sums: rounding can
    make a (near-)perfect fit's ``chi^2`` negative, hence the floor.
    """
    resid = aty - np.einsum("...kj,...j->...k", ata, coeffs)
    return np.maximum(yty - np.einsum("...m,...m->...", coeffs, aty + resid), 0.0)
