"""Temporary re-exports for the layout merge."""

from autocal.fit.blocks import BlockSums, base_sums, block_edges, extended_model, sums_nbytes  # noqa: F401
from autocal.fit.model import mean_vectors  # noqa: F401
from autocal.fit.separation import separation_summary  # noqa: F401
from autocal.fit.total_uncertainty import TotalUncertainty, total_uncertainty  # noqa: F401
