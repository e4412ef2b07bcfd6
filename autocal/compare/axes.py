"""The axes a comparison runs on: shared antennas, polarisations and channels.

:func:`match_axes` picks the antennas and polarisations both sides hold (or checks the
caller's choice), :func:`index_axes` checks the frequency overlap and returns a
:class:`MatchedAxes` with the indices into the solution's and the reference's arrays.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from autocal.compare.errors import CompareError

if TYPE_CHECKING:
    from autocal.fit.solution import Solution
    from autocal.io.calsol_read import ReferenceGains

logger = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class MatchedAxes:
    """Antennas, polarisations and channels compared, with their indices on both sides.

    Attributes
    ----------
    antennas, pols
        Antenna numbers and polarisation names compared.
    sol_antennas, sol_pols
        Their indices into the solution's antenna and polarisation axes.
    ref_antennas, ref_pols
        Their indices into the reference's axes.
    freqs
        ``(Nfreq,)`` the solution's channels (Hz).
    ref_freqs
        ``(Nref,)`` the reference's channels (Hz).
    in_range
        ``(Nfreq,)`` the solution's channels inside the reference's range.
    """

    antennas: list[int]
    pols: list[str]
    sol_antennas: list[int]
    sol_pols: list[int]
    ref_antennas: list[int]
    ref_pols: list[int]
    freqs: np.ndarray
    ref_freqs: np.ndarray
    in_range: np.ndarray


def match_axes(
    solution: Solution,
    reference: ReferenceGains,
    antennas: list[int] | None,
    pols: list[str] | None,
) -> tuple[list[int], list[str]]:
    """Return the antennas and polarisations to compare.

    Parameters
    ----------
    solution, reference
        The two sides.
    antennas, pols
        What the caller asked for, or ``None`` for everything the two have in common.

    Returns
    -------
    antennas, pols
        Antenna numbers and lower-case polarisation names.

    Raises
    ------
    CompareError
        When nothing is shared or an asked-for antenna/polarisation is missing on either
        side (the message lists what is available).
    """
    sol_ants = [int(a) for a in solution.antennas]
    ref_ants = [int(a) for a in reference.antennas]
    if antennas is None:
        ants = [a for a in sol_ants if a in ref_ants]
        if not ants:
            raise CompareError(
                f"the solution's antennas {sol_ants} are not in the reference; it has "
                f"antennas {ref_ants}"
            )
    else:
        ants = [int(a) for a in antennas]
        missing = [a for a in ants if a not in sol_ants]
        if missing:
            raise CompareError(f"antenna(s) {missing} are not in the solution; it has {sol_ants}")
        missing = [a for a in ants if a not in ref_ants]
        if missing:
            raise CompareError(
                f"antenna(s) {missing} are not in the reference gains; available in the "
                f"reference: {ref_ants} (solution: {sol_ants})"
            )
    sol_pols = [str(p).lower() for p in solution.pols]
    ref_pols = [str(p).lower() for p in reference.pols]
    if pols is None:
        use = [p for p in sol_pols if p in ref_pols]
        if not use:
            raise CompareError(
                f"the solution's polarisations {sol_pols} are not in the reference; it has "
                f"{ref_pols}"
            )
    else:
        use = [str(p).lower() for p in pols]
        missing_p = [p for p in use if p not in sol_pols]
        if missing_p:
            raise CompareError(
                f"polarisation(s) {missing_p} are not in the solution; it has {sol_pols}"
            )
        missing_p = [p for p in use if p not in ref_pols]
        if missing_p:
            raise CompareError(
                f"polarisation(s) {missing_p} are not in the reference gains; available in "
                f"the reference: {ref_pols} (solution: {sol_pols})"
            )
    return ants, use


def index_axes(
    solution: Solution, reference: ReferenceGains, antennas: list[int], pols: list[str]
) -> MatchedAxes:
    """Check the frequency overlap and index the matched antennas and polarisations.

    Parameters
    ----------
    solution, reference
        The two sides.
    antennas, pols
        From :func:`match_axes`.

    Returns
    -------
    MatchedAxes
        The axes and indices; solution channels outside the reference's range are logged.

    Raises
    ------
    CompareError
        When no solution channel lies inside the reference's frequency range.
    """
    freqs = np.asarray(solution.freqs, dtype=np.float64)
    ref_freqs = np.asarray(reference.freqs, dtype=np.float64)
    lo, hi = float(ref_freqs.min()), float(ref_freqs.max())
    in_range = (freqs >= lo - 1.0) & (freqs <= hi + 1.0)
    if not in_range.any():
        raise CompareError(
            f"no frequency overlap: the solution covers {freqs.min() / 1e6:.4f}-"
            f"{freqs.max() / 1e6:.4f} MHz, the reference {lo / 1e6:.4f}-{hi / 1e6:.4f} MHz"
        )
    if not in_range.all():
        logger.warning(
            "%d of %d solution channels lie outside the reference's %.3f-%.3f MHz and are "
            "not compared",
            int((~in_range).sum()),
            freqs.size,
            lo / 1e6,
            hi / 1e6,
        )
    return MatchedAxes(
        antennas=antennas,
        pols=pols,
        sol_antennas=[int(np.flatnonzero(solution.antennas == a)[0]) for a in antennas],
        sol_pols=[list(solution.pols).index(p) for p in pols],
        ref_antennas=[int(np.flatnonzero(reference.antennas == a)[0]) for a in antennas],
        ref_pols=[list(reference.pols).index(p) for p in pols],
        freqs=freqs,
        ref_freqs=ref_freqs,
        in_range=in_range,
    )
