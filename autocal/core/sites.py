"""Observatory sites."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

from autocal.errors import AutocalError

if TYPE_CHECKING:  # astropy's coordinates take ~0.3 s to import: only when a location is used
    from astropy.coordinates import EarthLocation


class SiteError(AutocalError):
    """An unknown or impossible observing site."""


@dataclass(frozen=True)
class Site:
    """A geodetic observatory location.

    Parameters
    ----------
    name
        Short name, e.g. ``"hera"``.
    lat_deg, lon_deg
        Geodetic latitude and east longitude in degrees.
    alt_m
        Height above the WGS84 ellipsoid in metres.
    """

    name: str
    lat_deg: float
    lon_deg: float
    alt_m: float = 0.0

    def __post_init__(self) -> None:
        if not -90.0 <= self.lat_deg <= 90.0:
            raise SiteError(f"site latitude {self.lat_deg} deg is outside [-90, 90]")
        if not -360.0 <= self.lon_deg <= 360.0:
            raise SiteError(f"site longitude {self.lon_deg} deg is outside [-360, 360]")

    @cached_property
    def location(self) -> EarthLocation:
        """The site as an :class:`astropy.coordinates.EarthLocation`."""
        from astropy import units as u
        from astropy.coordinates import EarthLocation

        return EarthLocation.from_geodetic(
            lon=self.lon_deg * u.deg, lat=self.lat_deg * u.deg, height=self.alt_m * u.m
        )

    def describe(self) -> dict[str, float | str]:
        """Return a JSON-serialisable description (used in cache keys and provenance)."""
        return {
            "name": self.name,
            "lat_deg": self.lat_deg,
            "lon_deg": self.lon_deg,
            "alt_m": self.alt_m,
        }


HERA = Site("hera", -30.7224, 21.4278, 1100.0)
EDGES = Site("edges", -26.7148, 116.6054, 377.0)
SITES: dict[str, Site] = {"hera": HERA, "edges": EDGES, "mro": EDGES}


def get_site(spec: str | Site) -> Site:
    """Resolve a site by name (``hera``, ``edges``/``mro``) or ``LAT,LON[,ALT]`` in degrees/m.

    Parameters
    ----------
    spec
        A :class:`Site`, a known name, or a ``"lat,lon[,alt]"`` string.

    Returns
    -------
    Site
        The resolved site.

    Raises
    ------
    SiteError
        If the name is unknown and the string is not ``lat,lon[,alt]``.
    """
    if isinstance(spec, Site):
        return spec
    key = spec.strip().lower()
    if key in SITES:
        return SITES[key]
    parts = key.split(",")
    if len(parts) in (2, 3):
        try:
            values = [float(p) for p in parts]
        except ValueError:
            values = []
        if values:
            return Site("custom", values[0], values[1], values[2] if len(values) == 3 else 0.0)
    raise SiteError(
        f"unknown site {spec!r}: use one of {sorted(set(SITES))} or 'LAT,LON[,ALT]' "
        "(degrees, degrees, metres)"
    )
