"""An independent, converging reference for Tsky: direct quadrature in the topocentric frame.

The ring-FFT engine (:mod:`autocal.tsky.ringfft`) and the brute force
(:mod:`autocal.tsky.brute`) both sum over the pixels of one equatorial HEALPix grid: the
sky map, the beam and the horizon weight are each sampled once per pixel centre, so their
error is the pixelisation of that grid. :func:`tsky_quadrature` shares none of that: it
integrates

    Tsky(nu, L) = [ int A w T dOmega + Tgnd int A (1 - w) dOmega ] / int A dOmega

on a grid fixed to the *ground*, a product of Gauss-Legendre nodes in zenith angle and
equally spaced azimuths (their number shrinking as ``sin(za)`` so the samples stay
``step_deg`` apart), with the zenith-angle panels split exactly at the edges of the soft
horizon (:func:`~autocal.tsky.horizon.horizon_weight`), so the horizon is integrated as
a smooth function on each panel instead of being cut at pixel edges. The beam is
evaluated exactly at every sample (:meth:`Beam.power`), and the sky at every sample and
LST is the sky model's Galactic maps (at their native resolution) interpolated
bilinearly at the sample's Galactic direction, the same continuous sky that
:meth:`SkyModel.components <autocal.sky.models.SkyModel.components>` samples at the
centres of a finer grid. Refining ``step_deg`` converges to the integral; the
convergence is measured in ``benchmarks/tsky_accuracy.py``.

Cost: ~``2 pi / step^2`` samples above the horizon, each interpolated once per LST
(about 2 M samples and 1 s per LST at 0.1 degree), so it is a reference for tests and
benchmarks, not a method of :func:`~autocal.tsky.compute.compute_tsky`.
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass

import healpy as hp
import numpy as np
from tqdm.auto import tqdm

from autocal.core.coords import apparent_to_galactic, parse_epoch
from autocal.core.sites import Site
from autocal.sky.beam_base import Beam
from autocal.sky.models import T_CMB, SkyModel
from autocal.tsky.horizon import HORIZON_WIDTH_DEG, horizon_weight
from autocal.tsky.result import T_GROUND, TskyError, TskyResult, check_grid, tgnd_array
from autocal.tsky.ringfft import progress_disabled
from autocal.tsky.synthesis import lst_radians

logger = logging.getLogger(__name__)

#: Galactic map resolution asked of the sky model: models degrade finer native maps to it
#: and return coarser ones (GSM2008 here: nside 64) unchanged.
SKY_NSIDE_HINT = 512


@dataclass(frozen=True)
class TopocentricGrid:
    """Quadrature nodes on the sphere fixed to the ground.

    Attributes
    ----------
    az, za
        Azimuth (east of north) and zenith angle of every node, radians.
    solid_angle
        Quadrature weight of every node (steradians; they sum to ``4 pi``).
    """

    az: np.ndarray
    za: np.ndarray
    solid_angle: np.ndarray

    @property
    def size(self) -> int:
        """Number of nodes."""
        return self.az.size


def topocentric_grid(step_deg: float, za_edges_deg: list[float]) -> TopocentricGrid:
    """Gauss-Legendre panels in zenith angle times uniform azimuths, ~``step_deg`` apart.

    Parameters
    ----------
    step_deg
        Target spacing of the nodes in both directions, degrees.
    za_edges_deg
        Increasing panel edges in zenith angle, degrees (from 0 to at most 180): nodes of
        each panel never straddle an edge, so functions with kinks there (the horizon
        weight) are integrated piecewise-smoothly.
    """
    if not step_deg > 0:
        raise TskyError(f"quadrature step must be > 0 degrees, not {step_deg}")
    za_nodes, za_weights = [], []
    for lo, hi in itertools.pairwise(za_edges_deg):
        n = max(2, int(np.ceil((hi - lo) / step_deg)))
        x, wx = np.polynomial.legendre.leggauss(n)
        half = np.radians(hi - lo) / 2
        za = np.radians(lo) + half * (x + 1)
        za_nodes.append(za)
        za_weights.append(wx * half * np.sin(za))
    za = np.concatenate(za_nodes)
    wza = np.concatenate(za_weights)
    n_az = np.maximum(8, np.ceil(360.0 * np.sin(za) / step_deg)).astype(np.int64)
    ring = np.repeat(np.arange(za.size), n_az)
    first = np.concatenate([[0], np.cumsum(n_az)[:-1]])
    index_in_ring = np.arange(ring.size) - first[ring]
    az = 2 * np.pi * (index_in_ring + 0.5) / n_az[ring]
    return TopocentricGrid(az=az, za=za[ring], solid_angle=wza[ring] * 2 * np.pi / n_az[ring])


def _equatorial_at_lst0(grid: TopocentricGrid, lat: float) -> np.ndarray:
    """Return the unit vectors ``(3, N)`` of the nodes in the equatorial frame at LST 0.

    At LST 0 the right ascension is minus the hour angle; the hour-angle frame has ``x``
    towards (HA 0, Dec 0) on the meridian, ``y`` towards the east point, ``z`` the pole.
    """
    alt = np.pi / 2 - grid.za
    east = np.cos(alt) * np.sin(grid.az)
    north = np.cos(alt) * np.cos(grid.az)
    up = np.sin(alt)
    # zenith = (cos lat, 0, sin lat), north point = (-sin lat, 0, cos lat), east = (0, 1, 0)
    x = up * np.cos(lat) - north * np.sin(lat)
    z = up * np.sin(lat) + north * np.cos(lat)
    return np.array([x, east, z])


def _beam_sums(
    beam: Beam, freqs: np.ndarray, grid: TopocentricGrid, w_above: np.ndarray, chunk: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return ``A w dOmega`` ``(Nf, Nsky)``, ``int A dOmega`` and ``int A (1 - w) dOmega``.

    The first is kept only on the nodes where ``w > 0`` (the first ``Nsky`` nodes).
    """
    nsky = int(np.count_nonzero(w_above > 0))
    weighted = np.empty((freqs.size, nsky))
    total = np.zeros(freqs.size)
    below = np.zeros(freqs.size)
    for s0 in range(0, grid.size, chunk):
        s1 = min(s0 + chunk, grid.size)
        vals = beam.power(freqs, grid.az[s0:s1], grid.za[s0:s1]) * grid.solid_angle[s0:s1]
        if not np.all(np.isfinite(vals)) or vals.min() < 0:
            raise TskyError(f"beam {beam.name} gave negative or non-finite values")
        total += vals.sum(axis=1)
        below += vals @ (1.0 - w_above[s0:s1])
        if s0 < nsky:
            e1 = min(s1, nsky)
            weighted[:, s0:e1] = vals[:, : e1 - s0] * w_above[s0:e1]
    return weighted, total, below


def tsky_quadrature(
    sky: SkyModel,
    beam: Beam,
    site: Site,
    freqs: np.ndarray,
    lsts: np.ndarray,
    tgnd: float | np.ndarray = T_GROUND,
    horizon_width_deg: float = HORIZON_WIDTH_DEG,
    epoch: object = None,
    step_deg: float = 0.1,
    progress: bool | None = None,
    chunk: int = 1 << 18,
) -> TskyResult:
    """Tsky by direct quadrature on a topocentric grid (see the module docstring).

    Parameters
    ----------
    sky
        Sky model (its Galactic maps are interpolated at every node and LST).
    beam
        Power beam, evaluated exactly at every node.
    site
        Observatory.
    freqs
        Frequencies in Hz.
    lsts
        LSTs in hours.
    tgnd
        Ground temperature in kelvin (scalar or per frequency).
    horizon_width_deg
        Width of the soft horizon (:func:`~autocal.tsky.horizon.horizon_weight`).
    epoch
        Epoch of the equatorial frame (default J2000), as for
        :func:`~autocal.tsky.compute.compute_tsky`.
    step_deg
        Spacing of the quadrature nodes, degrees (the accuracy knob).
    progress
        Progress bar over LSTs (``None``: only on a terminal).
    chunk
        Nodes per beam evaluation (memory bound).

    Returns
    -------
    TskyResult
        The table (``f_below`` from the beam integrals, LST-independent).
    """
    freqs = beam.check_freqs(check_grid(freqs, "frequency"))
    lsts = check_grid(lsts, "LST")
    tg = tgnd_array(tgnd, freqs.size)
    half = max(horizon_width_deg, 0.0) / 2
    edges = [0.0, 90.0 - half, 90.0 + half, 180.0] if half > 0 else [0.0, 90.0, 180.0]
    grid = topocentric_grid(step_deg, edges)
    w_above = horizon_weight(np.pi / 2 - grid.za, horizon_width_deg)
    weighted, total, below = _beam_sums(beam, freqs, grid, w_above, chunk)
    nsky = weighted.shape[1]
    maps, spectra, _ = sky.galactic(freqs, SKY_NSIDE_HINT)
    maps = np.atleast_2d(maps)
    cmb = 0.0 if sky.maps_include_cmb else T_CMB
    nside_map = hp.npix2nside(maps.shape[1])
    eq0 = _equatorial_at_lst0(grid, np.radians(site.lat_deg))[:, :nsky]
    time = parse_epoch(epoch)
    turned = sky.frame_rotation()  # a sky in a wrong frame (TiltedSky): M(R^T n)
    logger.info(
        "Tsky quadrature: %d nodes (%d above the horizon), step %.3g deg, sky nside %d",
        grid.size,
        nsky,
        step_deg,
        nside_map,
    )
    out = np.empty((lsts.size, freqs.size))
    sky_weight = weighted.sum(axis=1)
    for i, lst in enumerate(
        tqdm(lst_radians(lsts), desc="Tsky (quadrature)", disable=progress_disabled(progress))
    ):
        c, s = np.cos(lst), np.sin(lst)
        turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        vec = turn @ eq0
        gal = apparent_to_galactic(vec if turned is None else turned.T @ vec, time)
        theta, phi = hp.vec2ang(gal.T)
        pix, wgt = hp.get_interp_weights(nside_map, theta, phi)
        comp = np.zeros((maps.shape[0], nsky))
        for k in range(4):
            comp += maps[:, pix[k]] * wgt[k]
        overlap = weighted @ comp.T  # (Nf, Ncomp)
        numerator = np.einsum("fc,fc->f", spectra, overlap) + cmb * sky_weight
        out[i] = (numerator + tg * below) / total
    f_below = below / total
    return TskyResult(tsky=out, freqs=freqs, lsts=lsts, f_above=1 - f_below, f_below=f_below)
