"""The numba engine of the moment sums: generated kernels and their on-disk cache.

One fused kernel per model order and weight kind computes every moment of
:mod:`autocal.fit.moments` in one pass over a chunk. Its Python source is generated
(:func:`kernel_source`), compiled by numba on first use and cached twice: in this process
(a dict keyed by order, weight kind and block layout) and on disk
(:func:`kernel_cache_dir`), where numba keeps the machine code next to the generated module.
numba is imported only when a kernel is built, so the numpy engine never loads it.
"""

from __future__ import annotations

import hashlib
import importlib.util
import logging
import os
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np

from autocal.core.user_cache import user_cache_dir
from autocal.fit.moments import Chunk

logger = logging.getLogger(__name__)

#: Integrations handled per pass of the compiled kernel's channel loop, by the number of
#: chunk-sized arrays it reads per sample (data, dnu dt N or user weights, reference power):
#: with Nfreq a multiple of 512 (HERA: 1536) every row of these starts at the same offset
#: modulo 4 kB (large arrays are page-aligned alike), so the rows read together compete for
#: one 8-way L1 set; at most 8 of them may be in flight. Tsky is copied to another offset
#: (:func:`autocal.fit.moments.offset_copy`) and the kernel places its accumulators off that
#: set too.
_TUNROLL = {1: 4, 2: 4, 3: 2}
#: Bytes of accumulators per channel block: a block has as many channels (a multiple of 256,
#: 256 to 1536) as keep its ``3 (2p + 1) + 2 (p + 1) + 2`` accumulator rows within this, so
#: they stay in the L2 cache; a longer block reads a longer stretch of each data row per pass,
#: which the hardware prefetcher streams faster (constant model: 1536 channels, Legendre 1:
#: 768, Legendre 2: 512; ``benchmarks/fit.py``).
_BLOCK_BYTES = 96 * 1024
_KERNELS: dict[tuple[Any, ...], Any] = {}
_KERNEL_LOCK = threading.Lock()


def numba_available() -> bool:
    """Return whether numba can be imported (the compiled engine needs it)."""
    try:
        # numba is heavy (~0.5 s, LLVM): imported only when the numba engine is considered
        import numba  # noqa: F401
    except ImportError:  # pragma: no cover - numba is optional
        return False
    return True


def _kernel_key(c: Chunk) -> tuple[Any, ...]:
    nb, _, nr = c.lin.shape
    num_dims = np.ndim(c.num)  # 0 scalar, 1 (Nfreq,) / 2 (Ntime, Nfreq) shared, 4 per sample
    nbig = 1 + (num_dims == 4) + (c.power is not None)
    nacc = 3 * nr + 2 * nb + 2 + (c.mode == "user")
    fb = int(np.clip(_BLOCK_BYTES // (8 * nacc) // 256 * 256, 256, 1536))
    return (nr, nb, c.mode, num_dims, c.power is None, c.lin.tobytes(), _TUNROLL[nbig], fb)


def kernel_compiled(c: Chunk) -> bool:
    """Return whether the kernel for this chunk's order and weight kind is already built."""
    return _kernel_key(c) in _KERNELS


def kernel_source(key: tuple[Any, ...], lin: np.ndarray) -> str:
    """Python source of the fused moment kernel for one model order and weight kind.

    The channel loop is straight-line code over scalar accumulators (one per moment, kept in
    a flat block with a constant row stride so LLVM vectorises it over channels without
    aliasing checks between rows), unrolled over ``_TUNROLL`` integrations. Built in steps:
    the loops (:func:`_kernel_loops`), each integration's rows (:func:`_row_loads`), each
    sample's moments (:func:`_sample_update`) and the normal equations of a channel block
    (:func:`_normal_writes`).
    """
    nr, nb, mode, num_dims, own_power, _, tu, fb = key
    fbp = fb + 8  # pad rows so they do not share cache sets
    names = [f"m{e}_{r}" for e in range(3) for r in range(nr)]
    names += [f"q{e}_{k}" for e in range(2) for k in range(nb)]
    names += ["yy", "cn"] + (["bd"] if mode == "user" else [])
    src = _kernel_loops(len(names) * fbp, fb, tu)
    for u in range(tu):
        src += _row_loads(u, nr, mode, num_dims, own_power)
    src.append(f"{' ' * 20}for j in range(nf):")
    ind = " " * 24
    src += [f"{ind}{n} = acc[{i * fbp} + j]" for i, n in enumerate(names)]
    for u in range(tu):
        src += _sample_update(u, nr, nb, mode, num_dims, own_power)
    src += [f"{ind}acc[{i * fbp} + j] = {n}" for i, n in enumerate(names)]
    src += _normal_writes(names, fbp, nr, nb, mode, lin)
    src.append("        bad[ia] = nbad")
    return "\n".join(src) + "\n"


def _kernel_loops(nacc: int, fb: int, tu: int) -> list[str]:
    """Return the kernel's signature, accumulator block and loops down to the time block."""
    return [
        "def kernel(data, flags, num, power, tsky, coef, a_start, a_stop, ata, aty, yty, "
        "count, nflagged, bad):",
        "    npol, ntime, nfreq = data.shape[1], data.shape[2], data.shape[3]",
        # the accumulator rows start one cache line after the data rows modulo 4 kB, so
        # they never share an L1 set with the data (see _TUNROLL)
        f"    buf = np.empty({nacc + 512})",
        "    off = ((np.int64(data.ctypes.data) + 64 - np.int64(buf.ctypes.data)) % 4096) // 8",
        f"    acc = buf[off : off + {nacc}]",
        "    for ia in range(a_start, a_stop):",
        "        nbad = 0.0",
        "        for p in range(npol):",
        f"            for f0 in range(0, nfreq, {fb}):",
        f"                nf = min({fb}, nfreq - f0)",
        "                acc[:] = 0.0",
        f"                for tb in range(0, ntime, {tu}):",
    ]


def _row_loads(u: int, nr: int, mode: str, num_dims: int, own_power: bool) -> list[str]:
    """Return the loads of integration ``u``: its rows (data, flags, Tsky, weights) and P_r."""
    ind = " " * 20
    src = [
        f"{ind}t{u} = min(tb + {u}, ntime - 1)",
        f"{ind}v{u} = tb + {u} < ntime",
        f"{ind}d{u} = data[ia, p, t{u}, f0:f0 + nf]",
        f"{ind}g{u} = flags[ia, p, t{u}, f0:f0 + nf]",
        f"{ind}s{u} = tsky[p, t{u}, f0:f0 + nf]",
    ]
    if mode != "identity" and num_dims:
        lead = {1: "", 2: f"t{u}, ", 4: f"ia, p, t{u}, "}[num_dims]
        src.append(f"{ind}n{u} = num[{lead}f0:f0 + nf]")
    if mode == "radiometer" and not own_power:
        src.append(f"{ind}w{u} = power[ia, p, t{u}, f0:f0 + nf]")
    src += [f"{ind}c{u}_{r} = coef[{r}, t{u}]" for r in range(1, nr)]
    return src


def _sample_update(
    u: int, nr: int, nb: int, mode: str, num_dims: int, own_power: bool
) -> list[str]:
    """One sample of integration ``u``: its weight and its additions to every moment."""
    ind = " " * 24
    src = [f"{ind}x = d{u}[j]", f"{ind}ok = (x - x == 0.0) & (g{u}[j] == 0) & v{u}"]
    numer = f"n{u}[j]" if num_dims else "num"
    if mode == "identity":
        src.append(f"{ind}w = 1.0")
    elif mode == "radiometer":
        pw = "x" if own_power else f"w{u}[j]"
        src += [
            f"{ind}pw = {pw}",
            f"{ind}w = {numer} / (pw * pw)",
            f"{ind}ok = ok & (w > 0.0) & (w < np.inf)",
        ]
    else:
        src += [
            f"{ind}w = {numer}",
            f"{ind}bd += 0.0 if (w >= 0.0) & (w < np.inf) else (1.0 if ok else 0.0)",
            f"{ind}ok = ok & (w > 0.0)",
        ]
    src += [
        f"{ind}w = w if ok else 0.0",
        f"{ind}y = x if ok else 0.0",
        f"{ind}cn += 1.0 if ok else 0.0",
        f"{ind}ts = s{u}[j]",
        f"{ind}x1 = w * ts",
        f"{ind}x2 = x1 * ts",
        f"{ind}x3 = w * y",
        f"{ind}x4 = x3 * ts",
        f"{ind}yy += x3 * y",
    ]
    # P_0 = 1: the r = 0 moments are plain sums (adds, off the FMA pipes)
    feats = ("w", "x1", "x2")
    src += [f"{ind}m{e}_0 += {feats[e]}" for e in range(3)]
    src += [f"{ind}m{e}_{r} += c{u}_{r} * {feats[e]}" for e in range(3) for r in range(1, nr)]
    yfeats = ("x3", "x4")
    src += [f"{ind}q{e}_0 += {yfeats[e]}" for e in range(2)]
    src += [f"{ind}q{e}_{k} += c{u}_{k} * {yfeats[e]}" for e in range(2) for k in range(1, nb)]
    return src


def _normal_writes(
    names: list[str], fbp: int, nr: int, nb: int, mode: str, lin: np.ndarray
) -> list[str]:
    """Add the normal matrix, right-hand side and counts of each channel of the block."""
    ind = " " * 16
    src = [f"{ind}for j in range(nf):"]
    ind = " " * 20
    src.append(f"{ind}f = f0 + j")
    src += [f"{ind}{n} = acc[{i * fbp} + j]" for i, n in enumerate(names)]

    def comb(e: int, j: int, k: int) -> str:
        terms = [
            f"m{e}_{r}" if lin[j, k, r] == 1.0 else f"{lin[j, k, r]!r} * m{e}_{r}"
            for r in range(nr)
            if lin[j, k, r] != 0.0
        ]
        return " + ".join(terms) if terms else "0.0"

    for j in range(nb):
        for k in range(nb):
            src += [
                f"{ind}ata[ia, p, f, {j}, {k}] += {comb(2, j, k)}",
                f"{ind}ata[ia, p, f, {j}, {nb + k}] += {comb(1, j, k)}",
                f"{ind}ata[ia, p, f, {nb + j}, {k}] += {comb(1, j, k)}",
                f"{ind}ata[ia, p, f, {nb + j}, {nb + k}] += {comb(0, j, k)}",
            ]
    for k in range(nb):
        src += [f"{ind}aty[ia, p, f, {k}] += q1_{k}", f"{ind}aty[ia, p, f, {nb + k}] += q0_{k}"]
    src += [
        f"{ind}yty[ia, p, f] += yy",
        f"{ind}count[ia, p, f] += np.int64(cn)",
        f"{ind}nflagged[ia, p, f] += ntime - np.int64(cn)",
    ]
    if mode == "user":
        src.append(f"{ind}nbad += bd")
    return src


_KERNEL_HEADER = (
    '"""Generated by autocal.fit.kernels.kernel_source; safe to delete."""\n\n'
    "import numba\nimport numpy as np\n\n\n"
    "@numba.njit(cache=True, nogil=True, fastmath={'contract'}, boundscheck=False, "
    "error_model='numpy')\n"
)


def kernel_cache_dir() -> Path | None:
    """Return the folder of the compiled fit kernels, or ``None`` when caching is off.

    ``AUTOCAL_KERNEL_CACHE`` (``off`` disables), else ``$XDG_CACHE_HOME/autocal/fit_kernels``
    (default ``~/.cache/autocal/fit_kernels``). Each kernel is a generated module there
    whose machine code numba caches next to it, so a process does not recompile it.
    """
    return user_cache_dir("AUTOCAL_KERNEL_CACHE", "fit_kernels")


def _load_kernel(source: str) -> Any:
    """Compile a kernel's source, through the on-disk cache when it is usable."""
    # numba is heavy (~0.5 s, LLVM) and needed only here: imported when a kernel is built
    import numba

    text = _KERNEL_HEADER + source
    name = "autocal_fit_kernel_" + hashlib.sha256(text.encode()).hexdigest()[:20]
    folder = kernel_cache_dir()
    if folder is not None:
        path = folder / f"{name}.py"
        try:
            if not path.is_file() or path.read_text() != text:
                folder.mkdir(parents=True, exist_ok=True)
                tmp = path.with_suffix(f".{os.getpid()}.tmp")
                tmp.write_text(text)
                os.replace(tmp, path)
            spec = importlib.util.spec_from_file_location(name, path)
            if spec is not None and spec.loader is not None:
                module = importlib.util.module_from_spec(spec)
                sys.modules[name] = module  # numba's cache re-imports it by name
                spec.loader.exec_module(module)
                return module.kernel
        except OSError as err:
            logger.info("not caching the fit kernel in %s: %s", folder, err)
    namespace: dict[str, Any] = {"np": np}
    exec(compile(source, f"<{name}>", "exec"), namespace)
    return numba.njit(nogil=True, fastmath={"contract"}, boundscheck=False, error_model="numpy")(
        namespace["kernel"]
    )


def _kernel(c: Chunk) -> Any:
    """Return the compiled kernel for this chunk's order and weight kind (built on first use)."""
    key = _kernel_key(c)
    with _KERNEL_LOCK:
        if key not in _KERNELS:
            logger.debug("loading the fit kernel for %s", key[:5])
            _KERNELS[key] = _load_kernel(kernel_source(key, c.lin))
        return _KERNELS[key]


def moments_numba(c: Chunk, a0: int, a1: int, out: dict[str, np.ndarray]) -> int:
    """Fill ``out[...][a0:a1]`` with the compiled kernel; return the invalid user weights."""
    power = c.data if c.power is None else c.power
    _kernel(c)(
        c.data,
        c.flags,
        c.num,
        power,
        c.tsky,
        c.coef,
        a0,
        a1,
        out["ata"],
        out["aty"],
        out["yty"],
        out["count"],
        out["nflagged"],
        out["bad"],
    )
    return int(out["bad"][a0:a1].sum())
