"""Temporary re-exports for the layout merge."""

from autocal.io.edges_acq import ACQ_FLOOR, read_acq_spectra, write_acq  # noqa: F401
from autocal.io.edges_hdf5 import read_edges_hdf5, write_edges_hdf5  # noqa: F401
from autocal.io.edges_read import read_edges, read_edges_spectra  # noqa: F401
from autocal.io.edges_spectra import (  # noqa: F401
    MIN_OBS_FREQ_HZ,
    NATIVE_DF_HZ,
    NATIVE_NCHAN,
    EdgesFormatError,
    EdgesSpectra,
    channel_bins,
    native_freqs,
)
from autocal.io.edges_time import acq_time_to_jd, jd_to_acq_time, lsts_for_jds  # noqa: F401
