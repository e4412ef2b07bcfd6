"""Times of EDGES spectra: ACQ timestamps, Julian dates and sidereal times at the site.

ACQ files stamp each switch cycle ``YYYY:DDD:HH:MM:SS`` (UTC, 1 s resolution):
:func:`acq_time_to_jd` and :func:`jd_to_acq_time` convert between those and UTC Julian
dates; :func:`lsts_for_jds` gives the local apparent sidereal times (hours) at a site, as
pyuvdata computes them for UVH5 files.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from astropy.time import Time

from autocal.core.sites import EDGES, Site


def acq_time_to_jd(times: Sequence[str] | np.ndarray) -> np.ndarray:
    """Convert ACQ timestamps ``YYYY:DDD:HH:MM:SS`` (UTC) to Julian dates."""
    strs = [t.decode() if isinstance(t, bytes | np.bytes_) else str(t) for t in times]
    return np.asarray(Time(strs, format="yday", scale="utc").jd, dtype=np.float64)


def jd_to_acq_time(jds: np.ndarray) -> list[str]:
    """Convert UTC Julian dates to ACQ timestamps, rounded to the nearest second."""
    t = Time(np.atleast_1d(np.asarray(jds, dtype=np.float64)), format="jd", scale="utc")
    whole = Time(np.round(t.unix), format="unix", scale="utc")
    return [s[:17] for s in whole.yday]


def lsts_for_jds(jds: np.ndarray, site: Site = EDGES) -> np.ndarray:
    """Local apparent sidereal times in hours (pyuvdata's computation) at ``site``."""
    # pyuvdata takes a second to import; the ACQ and HDF5 readers and writers need it only
    # here, for the LSTs of an Observation
    from pyuvdata.utils import get_lst_for_time

    rad = get_lst_for_time(
        np.atleast_1d(np.asarray(jds, dtype=np.float64)),
        latitude=site.lat_deg,
        longitude=site.lon_deg,
        altitude=site.alt_m,
    )
    return np.mod(np.asarray(rad) * 12.0 / np.pi, 24.0)
