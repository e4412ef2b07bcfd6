"""Normal sums per time block, of the fitted model and of the model with one more order.

The total uncertainty (:mod:`autocal.fit.total_uncertainty`) needs no second pass over the
data: the integrations are split into ``B`` contiguous time blocks (:func:`block_edges`) and
the normal sums of the fitted model are kept per block (:class:`BlockSums`), those of the
model with one more order (:func:`extended_model`) once. The ordinary fit is the lower
orders of the latter (:func:`base_sums`; equal to a direct fit to rounding, ~1e-11
relative).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from autocal.core.reprs import compact_repr
from autocal.fit.model import FitError, FitModel
from autocal.fit.sums import NormalSums, accumulate

#: Fewest blocks for a jackknife (``B - 1`` degrees of freedom in ``V_jk``).
MIN_BLOCKS = 4
#: Blocks used when the observation has enough integrations.
DEFAULT_BLOCKS = 10
#: Bytes the per-block sums may take; larger problems use fewer blocks (at least
#: :data:`MIN_BLOCKS`, else no jackknife and no drift model).
BLOCK_MEMORY = 1 << 30
#: Above this median drift sensitivity ``(dG/G)/delta`` an antenna-pol's ``G`` and ``n``


def block_edges(ntime: int, nblocks: int | None = None, *, bytes_per_block: int = 0) -> np.ndarray:
    """Return the integration indices that split ``ntime`` integrations into blocks.

    Parameters
    ----------
    ntime
        Number of integrations of the observation.
    nblocks
        Blocks wanted (default :data:`DEFAULT_BLOCKS`), reduced to ``ntime // 2`` (at least
        two integrations a block) and to what :data:`BLOCK_MEMORY` allows.
    bytes_per_block
        Size of one block's normal sums.

    Returns
    -------
    numpy.ndarray
        ``(B + 1,)`` increasing indices from 0 to ``ntime``; ``B = 1`` (``[0, ntime]``) when
        fewer than :data:`MIN_BLOCKS` blocks are possible.
    """
    want = DEFAULT_BLOCKS if nblocks is None else int(nblocks)
    if want < 1:
        raise FitError(f"the number of blocks must be at least 1, got {want}")
    nb = min(want, ntime // 2)
    if bytes_per_block > 0:
        nb = min(nb, BLOCK_MEMORY // bytes_per_block)
    if nb < MIN_BLOCKS:
        nb = 1
    return np.linspace(0, ntime, nb + 1).round().astype(np.int64)


def sums_nbytes(model: FitModel, nant: int, npol: int, nfreq: int) -> int:
    """Bytes of one set of :class:`~autocal.fit.sums.NormalSums` of this shape."""
    m = model.nparam
    return 8 * nant * npol * nfreq * (m * m + m + 3)


@dataclass
class BlockSums:
    """Normal sums of contiguous time blocks of one observation.

    Attributes
    ----------
    blocks
        One :class:`~autocal.fit.sums.NormalSums` per block, in time order, of the fitted
        ``model`` (the jackknife's and the halves' refits).
    model
        The fitted model.
    edges
        ``(B + 1,)`` integration indices of the block boundaries.
    lsts
        ``(Ntime,)`` LSTs (hours) of all integrations of the fit.
    extended
        The sums over all blocks of the *extended* model (:func:`extended_model`): the
        drift term's fit, and (its lower orders) the ordinary fit. One set, not one per
        block: a HERA file's extended sums are ~200 MB.
    """

    blocks: list[NormalSums]
    model: FitModel
    edges: np.ndarray
    lsts: np.ndarray
    extended: NormalSums

    def __repr__(self) -> str:
        """Return one line; arrays as type and shape (:func:`~autocal.core.reprs.compact_repr`)."""
        return compact_repr(self)

    def __post_init__(self) -> None:
        if len(self.blocks) != len(self.edges) - 1:
            raise FitError(f"{len(self.blocks)} block sums for {len(self.edges) - 1} blocks")
        if self.edges[0] != 0 or self.edges[-1] != len(self.lsts):
            raise FitError("block edges must run from 0 to the number of integrations")
        if any(b.model != self.model for b in self.blocks):
            raise FitError("block sums must be of the fitted model")
        if self.extended.model != extended_model(self.model):
            raise FitError("the extended sums must be of the fitted model's extended model")

    @classmethod
    def from_extended(
        cls,
        blocks: list[NormalSums],
        model: FitModel,
        edges: np.ndarray,
        lsts: np.ndarray,
    ) -> BlockSums:
        """Build from per-block sums of the extended model (their sum is kept once)."""
        total = NormalSums.zeros(blocks[0].model, *blocks[0].count.shape)
        for part in blocks:
            total += part
        return cls([base_sums(b, model) for b in blocks], model, edges, lsts, total)

    def antennas(self, lo: int, hi: int) -> BlockSums:
        """Return the block sums of antennas ``lo`` to ``hi - 1`` (views of these arrays)."""
        return BlockSums(
            [b.antennas(lo, hi) for b in self.blocks],
            self.model,
            self.edges,
            self.lsts,
            self.extended.antennas(lo, hi),
        )

    def fitted_total(self) -> NormalSums:
        """Return the fitted model's sums over all blocks (the ordinary fit)."""
        return base_sums(self.extended, self.model)

    @property
    def nblocks(self) -> int:
        """Number of blocks ``B``."""
        return len(self.blocks)

    def total(self) -> NormalSums:
        """Return the extended model's sums over all blocks."""
        return self.extended


def subtract_sums(total: NormalSums, part: NormalSums) -> NormalSums:
    """Return the sums of ``total`` without those of ``part`` (a jackknife's refit data)."""
    return NormalSums(
        total.model,
        total.ata - part.ata,
        total.aty - part.aty,
        total.yty - part.yty,
        total.count - part.count,
        total.nflagged - part.nflagged,
    )


def extended_model(model: FitModel) -> FitModel:
    """Return the fitted model with one more Legendre order in ``G(t)`` and ``n(t)``.

    Its time axis is the fitted model's (for the constant model: the LST span of the data,
    which :meth:`FitModel.for_lsts` records), so the fitted model's sums are a sub-block of
    its sums (:func:`base_sums`).
    """
    return FitModel("legendre", model.order + 1, model.lst_start, model.lst_span)


def base_index(model: FitModel) -> np.ndarray:
    """Return the indices of the fitted model's parameters among the extended model's."""
    nb = model.nbasis
    return np.r_[np.arange(nb), nb + 1 + np.arange(nb)]


def base_sums(sums: NormalSums, model: FitModel) -> NormalSums:
    """Return the fitted model's sums: a sub-block of the extended model's sums.

    Legendre polynomials of a lower order are the first basis functions of a higher one,
    so ``P_0 .. P_p`` columns of the extended design are exactly the fitted design.
    """
    idx = base_index(model)
    return NormalSums(
        model,
        np.ascontiguousarray(sums.ata[..., idx[:, None], idx[None, :]]),
        np.ascontiguousarray(sums.aty[..., idx]),
        sums.yty.copy(),
        sums.count.copy(),
        sums.nflagged.copy(),
        sums.lst_min,
        sums.lst_max,
        dict(sums.info),
    )


def accumulate_blocks(
    model: FitModel,
    data: np.ndarray,
    tsky: np.ndarray,
    lsts: np.ndarray,
    edges: np.ndarray,
    **kwargs: Any,
) -> BlockSums:
    """Accumulate the normal sums of an in-memory chunk block by block.

    Parameters
    ----------
    model
        The fitted model (the blocks hold the sums of its :func:`extended_model`).
    data, tsky, lsts
        As for :func:`autocal.fit.sums.accumulate` (the whole observation).
    edges
        Block boundaries from :func:`block_edges`.
    **kwargs
        Passed to :func:`autocal.fit.sums.accumulate` (``flags``, ``weights``,
        ``bandwidth_time``, ``reference``); arrays ``(..., Ntime, Nfreq)`` are sliced per
        block.
    """
    tsky = np.asarray(tsky)
    ntime = data.shape[2]

    def part(value: Any, sl: slice) -> Any:
        if isinstance(value, np.ndarray) and value.ndim >= 2 and value.shape[-2] == ntime:
            return value[..., sl, :]  # (..., Ntime, Nfreq)
        return value

    ext = extended_model(model)
    blocks = []
    for b in range(len(edges) - 1):
        sl = slice(int(edges[b]), int(edges[b + 1]))
        tpart = tsky[..., sl, :]
        blocks.append(
            accumulate(
                ext,
                data[:, :, sl],
                tpart,
                lsts[sl],
                **{k: part(v, sl) for k, v in kwargs.items()},
            )
        )
    return BlockSums.from_extended(blocks, model, np.asarray(edges), np.asarray(lsts, np.float64))
