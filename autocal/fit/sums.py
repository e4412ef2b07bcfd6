"""Normal-equation sums of the fit and their accumulation chunk by chunk.

The generalised least-squares solution ``x = (A^T W A)^-1 A^T W y`` with ``C_x = (A^T W
A)^-1`` is computed from *normal-equation sums* (:class:`NormalSums`) accumulated chunk by
chunk (:func:`accumulate`), so a night never sits in memory and sums from several workers
simply add. Only weighted time moments of the data are computed
(:mod:`autocal.fit.moments`), by the numba kernel (:mod:`autocal.fit.kernels`) or numpy,
over antenna blocks in threads.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from autocal.core.reprs import compact_repr
from autocal.fit.kernels import kernel_compiled, moments_numba, numba_available
from autocal.fit.model import FitError, FitModel, check_tsky
from autocal.fit.moments import Chunk, moments_numpy, num_array, offset_copy, time_functions

#: Antenna-block engines: ``"numba"`` (fused compiled kernel), ``"numpy"`` or ``"auto"``.
Engine = Literal["auto", "numba", "numpy"]
#: Smallest chunk (samples) for which ``engine="auto"`` compiles a numba kernel; smaller
#: chunks use numpy unless a matching kernel is already compiled.
NUMBA_MIN_SAMPLES = 1 << 22


@dataclass
class NormalSums:
    """Sufficient statistics of the weighted least-squares problem per channel.

    Arrays have leading axes ``(Nant, Npol, Nfreq)``; sums over time of ``w a a^T``
    (``ata``), ``w a y`` (``aty``), ``w y^2`` (``yty``), the number of used samples
    (``count``) and of excluded (flagged or non-finite) samples (``nflagged``). Two sums
    over disjoint sets of integrations add with ``+``.
    """

    model: FitModel
    ata: np.ndarray
    aty: np.ndarray
    yty: np.ndarray
    count: np.ndarray
    nflagged: np.ndarray
    lst_min: float = np.inf
    lst_max: float = -np.inf
    info: dict[str, Any] = field(default_factory=dict)

    def __repr__(self) -> str:
        """Return one line; arrays as type and shape (:func:`~autocal.core.reprs.compact_repr`)."""
        return compact_repr(self)

    @classmethod
    def zeros(cls, model: FitModel, nant: int, npol: int, nfreq: int) -> NormalSums:
        """Empty sums."""
        m = model.nparam
        lead = (nant, npol, nfreq)
        return cls(
            model,
            np.zeros((*lead, m, m)),
            np.zeros((*lead, m)),
            np.zeros(lead),
            np.zeros(lead, np.int64),
            np.zeros(lead, np.int64),
        )

    def antennas(self, lo: int, hi: int) -> NormalSums:
        """Return the sums of antennas ``lo`` to ``hi - 1`` (views of these arrays)."""
        sl = slice(lo, hi)
        return NormalSums(
            self.model,
            self.ata[sl],
            self.aty[sl],
            self.yty[sl],
            self.count[sl],
            self.nflagged[sl],
            self.lst_min,
            self.lst_max,
            dict(self.info),
        )

    def __iadd__(self, other: NormalSums) -> NormalSums:
        """Add ``other`` into these sums in place (the same values as ``self + other``)."""
        if self.model != other.model or self.ata.shape != other.ata.shape:
            return self + other  # raises the FitError that explains the mismatch
        self.ata += other.ata
        self.aty += other.aty
        self.yty += other.yty
        self.count += other.count
        self.nflagged += other.nflagged
        self.lst_min = min(self.lst_min, other.lst_min)
        self.lst_max = max(self.lst_max, other.lst_max)
        self.info.update(other.info)
        return self

    def __add__(self, other: NormalSums) -> NormalSums:
        if self.model != other.model:
            raise FitError("cannot add normal sums of different models")
        if self.ata.shape != other.ata.shape:
            raise FitError(f"cannot add normal sums of shapes {self.ata.shape}, {other.ata.shape}")
        return NormalSums(
            self.model,
            self.ata + other.ata,
            self.aty + other.aty,
            self.yty + other.yty,
            self.count + other.count,
            self.nflagged + other.nflagged,
            min(self.lst_min, other.lst_min),
            max(self.lst_max, other.lst_max),
            {**self.info, **other.info},
        )


def default_threads() -> int:
    """Return the default thread count of :func:`accumulate`.

    ``AUTOCAL_FIT_THREADS``, else ``OMP_NUM_THREADS`` (Dask workers set it to 1), else the
    usable CPUs (at most 8).
    """
    for var in ("AUTOCAL_FIT_THREADS", "OMP_NUM_THREADS"):
        value = os.environ.get(var, "").strip()
        if value.isdigit() and int(value) > 0:
            return int(value)
    try:
        ncpu = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        ncpu = os.cpu_count() or 1
    return max(1, min(ncpu, 8))


def _choose_engine(engine: str | None, c: Chunk) -> str:
    engine = engine or os.environ.get("AUTOCAL_FIT_ENGINE", "auto")
    if engine not in ("auto", "numba", "numpy"):
        raise FitError(f"unknown fit engine {engine!r}: use 'auto', 'numba' or 'numpy'")
    if engine == "numpy":
        return "numpy"
    if not numba_available():
        if engine == "numba":
            raise FitError("the numba fit engine needs the numba package")
        return "numpy"
    if engine == "numba" or c.data.size >= NUMBA_MIN_SAMPLES or kernel_compiled(c):
        return "numba"
    return "numpy"


def antenna_blocks(nant: int, size: int) -> list[tuple[int, int]]:
    """Split ``nant`` antennas into ``[a0, a1)`` blocks of ``size`` (at least 1)."""
    size = max(1, size)
    return [(a, min(a + size, nant)) for a in range(0, nant, size)]


def accumulate(
    model: FitModel,
    data: np.ndarray,
    tsky: np.ndarray,
    lsts: np.ndarray,
    *,
    flags: np.ndarray | None = None,
    weights: str | np.ndarray = "radiometer",
    bandwidth_time: np.ndarray | float | None = None,
    reference: np.ndarray | None = None,
    engine: Engine | None = None,
    threads: int | None = None,
    into: NormalSums | None = None,
) -> NormalSums:
    """Accumulate the normal-equation sums of one chunk of integrations.

    Only weighted time moments of the data are computed (:mod:`autocal.fit.moments`), in
    one pass over the chunk; the design matrix is never built.

    Parameters
    ----------
    model
        The fit model (its LST range must cover the whole fit, not just this chunk).
    data
        ``(Nant, Npol, Ntime, Nfreq)`` auto-correlations.
    tsky
        ``(Npol, Ntime, Nfreq)`` or ``(Ntime, Nfreq)`` model Tsky in kelvin.
    lsts
        ``(Ntime,)`` hours.
    flags
        Boolean flags like ``data`` (``True`` excludes the sample).
    weights
        See :func:`autocal.fit.model.weights_for`.
    bandwidth_time
        ``dnu dt N`` for radiometer weights.
    reference
        Model power for the radiometer weights (second and later passes).
    engine
        ``"numba"`` (fused compiled kernel), ``"numpy"``, or ``"auto"`` (default, or the
        ``AUTOCAL_FIT_ENGINE`` environment variable): numba when it is installed and the
        chunk has at least :data:`NUMBA_MIN_SAMPLES` samples or a matching kernel is
        already compiled. Both give the same sums to rounding.
    threads
        Threads over antenna blocks (default: ``AUTOCAL_FIT_THREADS``, else
        ``OMP_NUM_THREADS``, else the usable CPUs, at most 8).
    into
        Running sums of the same model and shape to add this chunk's sums to, in place
        (the same values as ``into + accumulate(...)``, without a new set of arrays per
        chunk and a separate addition: for a Legendre-2 model the sums of a 7-integration
        block are 5x its data). On an error ``into`` may be partly updated.

    Returns
    -------
    NormalSums
        The chunk's sums, or ``into`` with them added.
    """
    data, lsts = _checked_chunk(data, lsts)
    nant, npol, ntime, nfreq = data.shape
    tsky = offset_copy(check_tsky(tsky, npol, ntime, nfreq), data)
    if flags is None:
        flag_bytes = np.zeros(data.shape, np.uint8)
    else:
        flag_bytes = np.ascontiguousarray(
            np.broadcast_to(np.asarray(flags, dtype=bool), data.shape)
        ).view(np.uint8)
    mode, num, power = _weight_inputs(weights, data, bandwidth_time, reference)
    coef, lin = time_functions(model, lsts)
    chunk = Chunk(data, flag_bytes, mode, num, power, tsky, coef, lin)
    lead = (nant, npol, nfreq)
    out = NormalSums.zeros(model, *lead) if into is None else into  # the engines add to it
    _check_into(out, model, lead)
    if _run_engine(chunk, out, engine, threads):
        raise FitError("user weights (1/sigma^2) must be finite and >= 0")
    out.lst_min = min(out.lst_min, float(lsts.min()))
    out.lst_max = max(out.lst_max, float(lsts.max()))
    return out


def _checked_chunk(data: np.ndarray, lsts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the data (C-ordered float64) and LSTs of a chunk, or raise :class:`FitError`."""
    data = np.ascontiguousarray(data, dtype=np.float64)
    if data.ndim != 4:
        raise FitError(f"data must be (Nant, Npol, Ntime, Nfreq), got shape {data.shape}")
    ntime = data.shape[2]
    if data.size == 0:
        raise FitError(
            f"nothing to fit: the chunk has shape {data.shape} (antennas, pols, integrations, "
            "channels); select at least one of each"
        )
    lsts = np.asarray(lsts, dtype=np.float64)
    if lsts.shape != (ntime,):
        raise FitError(f"{lsts.size} LSTs for {ntime} integrations")
    return data, lsts


def _weight_inputs(
    weights: str | np.ndarray,
    data: np.ndarray,
    bandwidth_time: np.ndarray | float | None,
    reference: np.ndarray | None,
) -> tuple[str, np.ndarray | float, np.ndarray | None]:
    """Return the :class:`~autocal.fit.moments.Chunk`'s weight ``mode``, ``num`` and ``power``."""
    power = None
    num: np.ndarray | float = 0.0
    if isinstance(weights, str):
        if weights == "radiometer":
            if bandwidth_time is None:
                raise FitError("radiometer weights need the channel width and integration time")
            num = num_array(bandwidth_time, data)
            if reference is not None:
                power = np.ascontiguousarray(
                    np.broadcast_to(np.asarray(reference, dtype=np.float64), data.shape)
                )
        elif weights != "identity":
            raise FitError(
                f"unknown weights {weights!r}: use 'radiometer', 'identity' or an array of "
                "1/sigma^2"
            )
        mode = weights
    else:
        mode = "user"
        num = num_array(weights, data)
    return mode, num, power


def _run_engine(chunk: Chunk, out: NormalSums, engine: str | None, threads: int | None) -> int:
    """Add the chunk's moments to ``out`` over antenna blocks; return the invalid user weights."""
    nant = chunk.data.shape[0]
    bufs = {
        "ata": out.ata,
        "aty": out.aty,
        "yty": out.yty,
        "count": out.count,
        "nflagged": out.nflagged,
        "bad": np.zeros(nant),
    }
    nthreads = default_threads() if threads is None else max(1, int(threads))
    moments = moments_numba if _choose_engine(engine, chunk) == "numba" else moments_numpy
    blocks = antenna_blocks(nant, nant if nthreads == 1 else -(-nant // (4 * nthreads)))
    if nthreads == 1 or len(blocks) == 1:
        nbad = sum(moments(chunk, a0, a1, bufs) for a0, a1 in blocks)
    else:
        with ThreadPoolExecutor(min(nthreads, len(blocks))) as pool:
            nbad = sum(pool.map(lambda ab: moments(chunk, *ab, bufs), blocks))
    return nbad


def _check_into(out: NormalSums, model: FitModel, lead: tuple[int, int, int]) -> None:
    """Raise :class:`FitError` unless ``out`` can hold the sums of ``model`` over ``lead``."""
    m = model.nparam
    want = {
        "ata": ((*lead, m, m), np.float64),
        "aty": ((*lead, m), np.float64),
        "yty": (lead, np.float64),
        "count": (lead, np.int64),
        "nflagged": (lead, np.int64),
    }
    if out.model != model:
        raise FitError("into= holds the sums of another model")
    for name, (shape, dtype) in want.items():
        arr = getattr(out, name)
        if arr.shape != shape or arr.dtype != dtype or not arr.flags.c_contiguous:
            raise FitError(
                f"into.{name} must be a C-contiguous {np.dtype(dtype).name} array of shape "
                f"{shape}, got {arr.dtype.name} {arr.shape}"
            )
