"""Outlier antennas of a night: robust departures from their own history or from the array.

For each antenna and polarisation calibrated on a night (values: medians over the solved
channels with their total 1-sigma, :mod:`autocal.service.history`), three tests run:

``array``
    ``G`` and ``Trxr`` against the same polarisation's antennas that night: centre ``m`` =
    median over the antennas, spread ``s`` = 1.4826 x MAD (the normal-equivalent standard
    deviation, robust to the outliers themselves). Flagged when
    ``|x - m| / sqrt(s^2 + sigma^2) > threshold``. Needs :data:`MIN_ARRAY` antennas.
``history``
    ``G`` and ``Trxr`` against the antenna's own earlier nights with the same
    configuration: reference ``r`` = median of the earlier values, spread ``s`` = 1.4826 x
    MAD of them (0 with fewer than three nights), ``sigma_r`` = median of their sigmas.
    Flagged when ``|x - r| / sqrt(s^2 + sigma^2 + sigma_r^2) > threshold``.
``chi2_jump``
    The reduced chi^2 more than ``chi2_jump`` times the median of the antenna's earlier
    nights (a fit that got much worse: RFI, a changed receiver, a broken cable).

Because each test includes the values' own uncertainties, a poorly constrained antenna is
not flagged for a departure its error bars allow. The default threshold (5) keeps false
alarms rare for a few hundred antenna-pols per night at Gaussian tails.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np
from scipy.stats import median_abs_deviation

#: Robust z above which a value is an outlier.
THRESHOLD = 5.0
#: A reduced chi^2 this many times the antenna's earlier median is a jump.
CHI2_JUMP = 2.0
#: Fewest antennas of a polarisation for the array test.
MIN_ARRAY = 4
#: The quantities tested against the array and the history.
TESTED = ("G", "Trxr")
UNITS = {"G": "raw/K", "Trxr": "K"}


def robust_centre(values: Sequence[float]) -> tuple[float, float]:
    """Return the median and the normal-equivalent spread (scipy's MAD, ``scale="normal"``)."""
    arr = np.asarray(values, dtype=np.float64)
    return float(np.median(arr)), float(median_abs_deviation(arr, scale="normal"))


def _ok(value: Any) -> bool:
    return value is not None and bool(np.isfinite(value))


def _entry(row: dict[str, Any], quantity: str, test: str, **stats: Any) -> dict[str, Any]:
    return {
        "antenna": row["antenna"],
        "pol": row["pol"],
        "night": row["night"],
        "job_id": row.get("job_id"),
        "quantity": quantity,
        "test": test,
        **stats,
    }


def array_outliers(rows: Sequence[dict[str, Any]], threshold: float) -> list[dict[str, Any]]:
    """Antenna-pols of one night whose ``G`` or ``Trxr`` departs from the array's median."""
    out = []
    by_pol: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for row in rows:
        by_pol[row["pol"]].append(row)
    for pol_rows in by_pol.values():
        for quantity in TESTED:
            usable = [r for r in pol_rows if _ok(r[quantity]) and _ok(r[f"sigma_{quantity}"])]
            if len(usable) < MIN_ARRAY:
                continue
            centre, spread = robust_centre([r[quantity] for r in usable])
            for row in usable:
                value, sigma = row[quantity], row[f"sigma_{quantity}"]
                scale = float(np.hypot(spread, sigma))
                z = (value - centre) / scale if scale > 0 else 0.0
                if abs(z) > threshold:
                    reason = (
                        f"{quantity} = {value:.4g} +/- {sigma:.2g} {UNITS[quantity]} departs from "
                        f"the array's median {centre:.4g} (spread {spread:.2g}) by {z:+.1f} sigma"
                    )
                    out.append(
                        _entry(
                            row, quantity, "array", value=value, sigma=sigma, reference=centre,
                            spread=spread, z=z, reason=reason,
                        )
                    )  # fmt: skip
    return out


def history_outliers(
    row: dict[str, Any], earlier: Sequence[dict[str, Any]], threshold: float, chi2_jump: float
) -> list[dict[str, Any]]:
    """Departures of one antenna-pol from its own earlier nights (same configuration)."""
    out = []
    for quantity in TESTED:
        past = [r for r in earlier if _ok(r[quantity]) and _ok(r[f"sigma_{quantity}"])]
        value, sigma = row[quantity], row[f"sigma_{quantity}"]
        if not past or not _ok(value) or not _ok(sigma):
            continue
        reference, spread = robust_centre([r[quantity] for r in past])
        if len(past) < 3:
            spread = 0.0
        sigma_ref = float(np.median([r[f"sigma_{quantity}"] for r in past]))
        scale = float(np.sqrt(spread**2 + sigma**2 + sigma_ref**2))
        z = (value - reference) / scale if scale > 0 else 0.0
        if abs(z) > threshold:
            reason = (
                f"{quantity} = {value:.4g} +/- {sigma:.2g} {UNITS[quantity]} departs from its "
                f"median {reference:.4g} +/- {sigma_ref:.2g} over {len(past)} earlier night(s) "
                f"by {z:+.1f} sigma"
            )
            out.append(
                _entry(
                    row, quantity, "history", value=value, sigma=sigma, reference=reference,
                    spread=spread, z=z, reason=reason,
                )
            )  # fmt: skip
    chi2 = row.get("reduced_chi2")
    past_chi2 = [r["reduced_chi2"] for r in earlier if _ok(r.get("reduced_chi2"))]
    if _ok(chi2) and past_chi2:
        reference = float(np.median(past_chi2))
        if reference > 0 and chi2 > chi2_jump * reference:
            reason = (
                f"chi2/dof jumped to {chi2:.3g} from a median {reference:.3g} over "
                f"{len(past_chi2)} earlier night(s) (x{chi2 / reference:.1f})"
            )
            out.append(
                _entry(
                    row, "reduced_chi2", "chi2_jump", value=chi2, sigma=None, reference=reference,
                    spread=None, z=None, reason=reason,
                )
            )  # fmt: skip
    return out


def night_outliers(
    tonight: Iterable[dict[str, Any]],
    earlier: Iterable[dict[str, Any]],
    *,
    threshold: float = THRESHOLD,
    chi2_jump: float = CHI2_JUMP,
) -> list[dict[str, Any]]:
    """Return the outliers of a night, each with its test, numbers and a reason.

    Parameters
    ----------
    tonight
        One value per antenna, pol and configuration of the night (see
        :func:`autocal.service.monitoring.night_values`): ``antenna``, ``pol``, ``night``,
        ``config_hash``, ``G``, ``sigma_G``, ``Trxr``, ``sigma_Trxr``, ``reduced_chi2``.
    earlier
        The same for earlier nights (any configuration; only the same one is compared).
    threshold
        Robust z above which a value is an outlier.
    chi2_jump
        Factor over the earlier median reduced chi^2 that is a jump.

    Returns
    -------
    list of dict
        ``antenna``, ``pol``, ``night``, ``job_id``, ``quantity``, ``test`` (``array``,
        ``history``, ``chi2_jump``), ``value``, ``sigma``, ``reference``, ``spread``, ``z``
        and ``reason``; sorted by antenna, pol and test.
    """
    tonight = list(tonight)
    past: dict[tuple[int, str, str], list[dict[str, Any]]] = defaultdict(list)
    for row in earlier:
        past[(row["antenna"], row["pol"], row["config_hash"])].append(row)
    out: list[dict[str, Any]] = []
    by_config: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for row in tonight:
        by_config[row["config_hash"]].append(row)
    for rows in by_config.values():
        out.extend(array_outliers(rows, threshold))
    for row in tonight:
        key = (row["antenna"], row["pol"], row["config_hash"])
        out.extend(history_outliers(row, past.get(key, []), threshold, chi2_jump))
    return sorted(out, key=lambda o: (o["antenna"], o["pol"], o["test"], o["quantity"]))
