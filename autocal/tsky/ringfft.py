"""The ring-FFT engine: Tsky at every LST at once.

    Tsky(nu, t) = [ sum_above A Tmap + Tgnd sum_below A ] / sum_all A

The beam ``A`` is fixed in topocentric coordinates; ``Tmap`` includes the CMB exactly
once (see :mod:`autocal.sky.models`); the ground below the horizon radiates ``Tgnd`` (300 K by
default, scalar or per frequency).

For a drift scan the sky seen at LST ``L`` is the sky rotated about the celestial pole by
``L``. On HEALPix iso-latitude rings both the above-horizon beam (in equatorial
coordinates at LST 0) and each sky component are Fourier-transformed along the ring once;
the overlap at every LST is then ``Re sum_m D_m exp(-i m L)`` with ``D_m = sum_rings w_m
B_m conj(T_m) / n_ring``: a ring-wise circular cross-correlation, exact up to
pixelisation (band-limited interpolation in LST). The cost is independent of the number
of LSTs; sky components are transformed once whatever the number of frequencies.
Frequency chunks run in parallel threads; the beam integrals and the ``m = 0`` term are
float64, the ring FFTs of the beam and the ``m >= 1`` terms float32 (relative error
~1e-7, i.e. < 1 mK).

:func:`tsky_harmonics` returns the LST-free output (:class:`~autocal.tsky.result.TskyHarmonics`,
what the Tsky cache stores), :func:`tsky_fft` a table at given LSTs. The references it is
tested and benchmarked against are in :mod:`autocal.tsky.brute`; the public entry point,
with names, checks and the cache, is :func:`autocal.tsky.compute.compute_tsky`.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass, field

import numpy as np
import scipy.fft as sp_fft
from tqdm.auto import tqdm

from autocal.core.lazy import healpy as hp
from autocal.core.sites import Site
from autocal.core.stopping import checkpoint
from autocal.sky.beam_base import Beam, BeamEvaluator
from autocal.sky.models import SkyComponents
from autocal.tsky.horizon import HORIZON_WIDTH_DEG, horizon_weight, topocentric_at_lst0
from autocal.tsky.result import (
    T_GROUND,
    TskyError,
    TskyHarmonics,
    TskyResult,
    check_grid,
    tgnd_array,
)
from autocal.tsky.rings import FFT_DTYPE, RingPlan, ring_plan
from autocal.tsky.synthesis import lst_radians, synthesise

logger = logging.getLogger(__name__)

#: Bump when the numerical method changes, so cached tables are recomputed.
ENGINE_VERSION = "ringfft-4"  # 3: band-limited sky (tsky.bandlimit); 4: aberration in the sky frame


def progress_disabled(progress: bool | None) -> bool | None:
    """Tqdm's ``disable`` argument: ``None`` disables on non-terminals."""
    if progress is None:
        return None
    return not progress


class _Clock:
    """CPU time of the calling thread per stage (reported at DEBUG level).

    Thread CPU time rather than wall time: stage costs stay meaningful on a busy machine.
    """

    def __init__(self) -> None:
        self.times: dict[str, float] = {}
        self._last = time.thread_time()

    def lap(self, stage: str | None = None) -> None:
        """Charge the time since the previous lap to ``stage`` (``None``: discard)."""
        now = time.thread_time()
        if stage is not None:
            self.times[stage] = self.times.get(stage, 0.0) + now - self._last
        self._last = now

    def merge(self, times: dict[str, float]) -> None:
        """Add another clock's stage times (e.g. a worker thread's)."""
        for key, value in times.items():
            self.times[key] = self.times.get(key, 0.0) + value

    def report(self) -> str:
        """``stage=seconds`` pairs and their total."""
        parts = [f"{k}={v:.3f}s" for k, v in self.times.items()]
        return " ".join([*parts, f"sum={sum(self.times.values()):.3f}s"])


def _default_chunk(npix: int) -> int:
    """Frequencies per chunk: a power of two in [4, 64], the float32 beam within ~12 MB."""
    nf = 4
    while nf < 64 and 2 * nf * npix * 4 <= 12 << 20:
        nf *= 2
    return nf


def _default_workers() -> int:
    """Return the number of CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


@dataclass
class _FftJob:
    """Everything one frequency chunk of :func:`tsky_fft` needs (shared by the workers).

    ``weights`` rows: 1 (beam integral), ``1 - w`` (below-horizon part) and ``w`` times
    each component's ring average (the exact ``m = 0`` overlaps); ``sums`` and
    ``overlap`` receive the results, each chunk writing its own frequency columns.
    """

    plan: RingPlan
    evaluator: BeamEvaluator
    beam_name: str
    freqs: np.ndarray
    chunk: int
    weights: np.ndarray
    w_above: np.ndarray
    sums: np.ndarray
    overlap: np.ndarray
    local: threading.local = field(default_factory=threading.local)

    def buffers(self) -> tuple[np.ndarray, np.ndarray]:
        """Return the calling thread's work arrays (allocated once; ``cap_buf`` kept zero)."""
        if not hasattr(self.local, "b_sky"):
            plan, nf = self.plan, min(self.chunk, self.freqs.size)
            self.local.b_sky = np.empty((plan.hi - plan.lo, nf), dtype=FFT_DTYPE)
            shape = (plan.y_cap.shape[0], len(plan.caps), nf)
            self.local.cap_buf = np.zeros(shape, dtype=plan.y_cap.dtype)
        return self.local.b_sky, self.local.cap_buf

    def run(self, start: int) -> dict[str, float]:
        """Process the frequencies ``start : start + chunk``; return the stage times."""
        clock = _Clock()
        sel = slice(start, min(start + self.chunk, self.freqs.size))
        freqs = self.freqs[sel]
        nf = freqs.size
        plan = self.plan
        b_sky, cap_buf = self.buffers()
        b_sky, cap_buf = b_sky[:, :nf], cap_buf[:, :, :nf]
        npix = self.w_above.size
        acc = np.zeros((self.weights.shape[0], nf))
        # Blocks of directions small enough to stay in cache, and for the products
        # below to run single-threaded in BLAS (parallelism comes from the chunks).
        step = max(256, 32768 // nf)
        for b0 in range(0, npix, step):
            b1 = min(b0 + step, npix)
            vals = self.evaluator.by_direction(freqs, slice(b0, b1))  # (rows, Nf) float64
            clock.lap("beam")
            if not (self.evaluator.nonnegative or vals.min() >= 0):  # also catches NaN
                raise TskyError(f"beam {self.beam_name} gave negative or non-finite values")
            acc += self.weights[:, b0:b1] @ vals
            o0, o1 = max(b0, plan.lo), min(b1, plan.hi)
            if o0 < o1:
                np.multiply(
                    vals[o0 - b0 : o1 - b0],
                    self.w_above[o0:o1, None],
                    out=b_sky[o0 - plan.lo : o1 - plan.lo],
                    casting="same_kind",
                )
            clock.lap("sums+horizon")
        self.sums[:, sel] = acc
        if plan.hi > plan.lo:
            _overlap_chunk(plan, b_sky, self.overlap[:, :, sel], cap_buf, clock)
        return clock.times


def _overlap_chunk(
    plan: RingPlan, b_sky: np.ndarray, out: np.ndarray, cap_buf: np.ndarray, clock: _Clock
) -> None:
    """Set the ``m >= 1`` ring overlaps of one frequency chunk in ``out`` (``(M, Ncomp, Nf)``).

    ``b_sky`` is the ``(hi - lo, Nf)`` horizon-weighted beam over the transformed rings,
    ``cap_buf`` a zeroed ``(M, Ncap, Nf)`` complex work array (only the entries
    ``m <= n/2`` of each cap ring are ever written, so it stays zero elsewhere).
    """
    nf = b_sky.shape[1]
    total = np.zeros((out.shape[0], plan.y_eq.shape[1], nf), dtype=np.complex128)
    if plan.eq_rings:
        first = plan.eq_start - plan.lo
        block = b_sky[first : first + plan.eq_rings * plan.eq_len]
        x_eq = sp_fft.rfft(block.reshape(plan.eq_rings, plan.eq_len, nf), axis=1)
        clock.lap("fft")
        total += np.matmul(plan.y_eq, x_eq.transpose(1, 0, 2))
        clock.lap("ring_sum")
    if plan.caps:
        for j, (first, n) in enumerate(plan.caps):
            ring = b_sky[first - plan.lo : first - plan.lo + n]
            cap_buf[: n // 2 + 1, j] = sp_fft.rfft(ring, axis=0)
        clock.lap("fft")
        total += np.matmul(plan.y_cap, cap_buf)
        clock.lap("ring_sum")
    out[:, plan.moving] = total  # constant maps have no m >= 1 terms (out stays zero)


def _run_chunks(
    job: _FftJob, starts: list[int], nworkers: int, clock: _Clock, progress: bool | None
) -> None:
    """Run ``job`` on the chunks starting at ``starts`` in ``nworkers`` threads.

    Each chunk's stage times are added to ``clock``; an error in any chunk cancels the
    chunks not yet started and is raised.
    """
    bar = tqdm(
        total=len(starts), desc="Tsky (ring FFT)", unit="chunk", disable=progress_disabled(progress)
    )
    with bar:
        if nworkers == 1:
            for start in starts:
                checkpoint("a Tsky chunk")
                clock.merge(job.run(start))
                bar.update()
        else:
            with ThreadPoolExecutor(max_workers=nworkers) as pool:
                futures = [pool.submit(job.run, start) for start in starts]
                try:
                    for future in as_completed(futures):
                        clock.merge(future.result())
                        bar.update()
                        checkpoint("the next Tsky chunks")
                except BaseException:
                    for future in futures:
                        future.cancel()
                    raise


def _fft_overlaps(
    sky: SkyComponents,
    beam: Beam,
    site: Site,
    horizon_width_deg: float,
    freq_chunk: int | None,
    progress: bool | None,
    workers: int | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run the ring-FFT engine: ``(freqs, sums, overlap)``, nothing depending on the LSTs.

    ``sums`` is ``(2 + Ncomp, Nfreq)``: the beam integral, its below-horizon part and
    each component's ``m = 0`` overlap; ``overlap`` is ``(M, Ncomp, Nfreq)`` complex, the
    harmonics of every component's above-horizon overlap (its ``m = 0`` row set from
    ``sums``). See :func:`tsky_fft` for the method and the parameters.
    """
    freqs = beam.check_freqs(sky.freqs)
    nside = sky.nside
    npix = hp.nside2npix(nside)
    wall0 = time.perf_counter()
    clock = _Clock()
    az, za = topocentric_at_lst0(nside, site)
    w_above = horizon_weight(np.pi / 2 - za, horizon_width_deg)
    evaluator = beam.on(az, za)
    clock.lap("beam_bind")
    plan = ring_plan(sky.maps, w_above, nside)
    ncomp, nfreq, mmax = sky.ncomp, freqs.size, 2 * nside
    chunk = int(freq_chunk) if freq_chunk is not None else _default_chunk(npix)
    if chunk < 1:
        raise TskyError("freq_chunk must be >= 1")
    job = _FftJob(
        plan=plan,
        evaluator=evaluator,
        beam_name=beam.name,
        freqs=freqs,
        chunk=chunk,
        weights=np.vstack([np.ones(npix), 1.0 - w_above, w_above * plan.mean_ring]),
        w_above=w_above,
        sums=np.empty((2 + ncomp, nfreq)),
        overlap=np.zeros((mmax + 1, ncomp, nfreq), dtype=np.complex128),
    )
    starts = list(range(0, nfreq, chunk))
    nworkers = max(1, min(int(workers) if workers is not None else _default_workers(), len(starts)))
    clock.lap("setup")
    _run_chunks(job, starts, nworkers, clock, progress)
    clock.lap()
    sums, overlap = job.sums, job.overlap
    if not np.all(np.isfinite(sums)):
        raise TskyError(f"beam {beam.name} gave negative or non-finite values")
    if np.any(sums[0] <= 0):
        bad = freqs[sums[0] <= 0] / 1e6
        raise TskyError(f"beam {beam.name} integrates to zero at {bad[:5]} MHz")
    overlap[0] = sums[2:]
    logger.debug(
        "ring-FFT engine: %d freqs at nside %d in %.3f s wall; thread CPU per stage: %s",
        nfreq,
        nside,
        time.perf_counter() - wall0,
        clock.report(),
    )
    return freqs, sums, overlap


def tsky_harmonics(
    sky: SkyComponents,
    beam: Beam,
    site: Site,
    horizon_width_deg: float = HORIZON_WIDTH_DEG,
    freq_chunk: int | None = None,
    progress: bool | None = None,
    workers: int | None = None,
) -> TskyHarmonics:
    """Tsky's Fourier series in LST by the ring-FFT engine (see :func:`tsky_fft`).

    Parameters are as for :func:`tsky_fft`; the LSTs and the ground temperature come
    later, in :meth:`TskyHarmonics.table`.

    Returns
    -------
    TskyHarmonics
        Harmonics and beam integrals (``meta`` empty:
        :func:`~autocal.tsky.compute.compute_tsky` fills it).
    """
    freqs, sums, overlap = _fft_overlaps(
        sky, beam, site, horizon_width_deg, freq_chunk, progress, workers
    )
    return _harmonics(sky.spectra, freqs, sums, overlap)


def _harmonics(
    spectra: np.ndarray, freqs: np.ndarray, sums: np.ndarray, overlap: np.ndarray
) -> TskyHarmonics:
    """Combine the engine's per-component output with the component ``spectra``."""
    return TskyHarmonics(
        freqs=freqs,
        coef=np.einsum("fc,mcf->mf", spectra, overlap),
        sum_all=sums[0],
        sum_below=sums[1],
    )


def tsky_fft(
    sky: SkyComponents,
    beam: Beam,
    site: Site,
    lsts: np.ndarray,
    tgnd: float | np.ndarray = T_GROUND,
    horizon_width_deg: float = HORIZON_WIDTH_DEG,
    freq_chunk: int | None = None,
    keep_components: bool = False,
    progress: bool | None = None,
    workers: int | None = None,
) -> TskyResult:
    """Tsky at all LSTs by ring-wise FFT cross-correlation (see module docstring).

    Implementation: the beam is evaluated once per frequency chunk at the LST-0
    position of every pixel (direction-major, :meth:`BeamEvaluator.by_direction`); one
    float64 matrix product gives its integral, its below-horizon part and the exact
    ``m = 0`` overlap with every sky component (ring averages); the horizon-weighted beam
    is cast to float32 and Fourier-transformed along the rings that ever rise (one
    batched FFT for the equatorial block, one per polar-cap ring); the ``m >= 1``
    overlaps are summed over rings by batched complex matrix products with the
    precomputed sky transforms and accumulated in float64. Finally one inverse transform
    over ``m`` (an FFT for a regular LST grid, else a matrix product) gives every LST.

    Parameters
    ----------
    sky
        Low-rank equatorial sky (:meth:`autocal.sky.models.SkyModel.components`).
    beam
        Power beam.
    site
        Observatory.
    lsts
        LSTs in hours.
    tgnd
        Ground temperature in kelvin (scalar or per frequency).
    horizon_width_deg
        Width of the soft horizon (:func:`horizon_weight`).
    freq_chunk
        Frequencies processed together (bounds memory to a few ``freq_chunk * Npix``
        floats); ``None`` chooses it from the map size (cache-sized chunks).
    keep_components
        Also return the per-component contributions (``TskyResult.components``).
    progress
        Show a progress bar (``None``: only on a terminal).
    workers
        Threads processing frequency chunks in parallel (``None``: one per available
        CPU). The beam evaluator is called from these threads.

    Returns
    -------
    TskyResult
        The table.
    """
    lsts = check_grid(lsts, "LST")
    tg = tgnd_array(tgnd, sky.freqs.size)
    freqs, sums, overlap = _fft_overlaps(
        sky, beam, site, horizon_width_deg, freq_chunk, progress, workers
    )
    result = _harmonics(sky.spectra, freqs, sums, overlap).table(lsts, tg)
    if not keep_components:
        return result
    ncomp, nfreq, nm = sky.ncomp, freqs.size, overlap.shape[0]
    per_comp = synthesise(overlap.reshape(nm, ncomp * nfreq), lst_radians(lsts))
    comps = per_comp.reshape(lsts.size, ncomp, nfreq).transpose(0, 2, 1) / sums[0][:, None]
    return TskyResult(
        tsky=result.tsky,
        freqs=freqs,
        lsts=lsts,
        f_above=result.f_above,
        f_below=result.f_below,
        components=comps,
    )
