"""Where the beam sees the sky: the soft horizon and the beam frame at LST 0.

The beam ``A`` is fixed in topocentric coordinates; a drift scan turns the sky under it.
Both Tsky implementations evaluate the beam at every equatorial HEALPix pixel's position
at LST 0 (:func:`topocentric_at_lst0`) and weigh it by :func:`horizon_weight`: the part of
the beam above the horizon sees the sky, the rest the ground.
"""

from __future__ import annotations

import numpy as np

from autocal.core.coords import hadec_to_altaz, healpix_ra_dec
from autocal.core.sites import Site

#: Default width of the soft horizon, degrees (see :func:`horizon_weight`).
HORIZON_WIDTH_DEG = 2.0


def horizon_weight(alt: np.ndarray, width_deg: float = HORIZON_WIDTH_DEG) -> np.ndarray:
    """Fraction of the beam weight at altitude ``alt`` (radians) that sees the sky.

    The horizon is a soft edge: the weight rises from 0 to 1 as a C1 smoothstep over
    ``width_deg`` centred on altitude 0 (real horizons are not a perfect plane, and a
    HEALPix pixel straddling the horizon sees partly sky and partly ground). Both Tsky
    implementations use it; a hard cut at pixel centres would add pixel-edge noise as
    the sky rotates. ``width_deg = 0`` gives the hard cut.
    """
    alt = np.asarray(alt, dtype=np.float64)
    if width_deg <= 0:
        return (alt > 0).astype(np.float64)
    x = np.clip(0.5 + alt / np.radians(width_deg), 0.0, 1.0)
    return x * x * (3 - 2 * x)


def topocentric_at_lst0(nside: int, site: Site) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth (east of north) and zenith angle of every equatorial pixel at LST 0.

    Returns
    -------
    az, za
        Radians, ``(Npix,)`` each.
    """
    ra, dec = healpix_ra_dec(nside)
    alt, az = hadec_to_altaz(-ra, dec, np.radians(site.lat_deg))
    return az, np.pi / 2 - alt
