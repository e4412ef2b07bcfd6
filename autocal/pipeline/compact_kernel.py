"""One compiled pass that finds the compact form of a decoded block's float64 array.

:func:`autocal.pipeline.decoded` keeps a block's power and sample counts as one number when
every value has the same bits, else as float32 when that holds every value exactly (UVH5
autos are complex64), else as they are. numpy's tests (bits against the first value, a
float32 copy, ``array_equal`` with NaNs equal) took ~6 s of CPU for a HERA file's 2 x 206 M
values in the flagging's first read, on the calibration's critical path; this loop does
them in one pass over the values, on threads (:func:`autocal.fit.threads.in_threads`).
"""

from __future__ import annotations

import numba
import numpy as np

from autocal.fit.threads import in_threads

#: Values per range of the threaded pass.
_RANGE = 1 << 20


def compact_pass(values: np.ndarray, small: np.ndarray) -> tuple[bool, bool]:
    """Fill ``small`` with ``values`` as float32; say whether all are one and exact.

    Parameters
    ----------
    values
        C-contiguous float64 values.
    small
        A float32 array of the same size (filled).

    Returns
    -------
    tuple of bool
        ``(same, exact)``: every value has the bits of the first; every value equals its
        float32 (NaNs count as equal, as ``numpy.array_equal(..., equal_nan=True)``).
    """
    flat, out = values.reshape(-1), small.reshape(-1)
    bits = flat.view(np.uint64)
    n = flat.size
    nranges = max(1, -(-n // _RANGE))
    same = np.ones(nranges, np.bool_)
    exact = np.ones(nranges, np.bool_)
    in_threads(lambda r0, r1: _kernel(flat, bits, out, same, exact, r0, r1), nranges)
    return bool(same.all()), bool(exact.all())


@numba.njit(cache=True, nogil=True)
def _kernel(flat, bits, out, same, exact, r0, r1):  # type: ignore[no-untyped-def]
    first = bits[0]
    n = flat.size
    for r in range(r0, r1):
        all_same = True
        all_exact = True
        for i in range(r * _RANGE, min((r + 1) * _RANGE, n)):
            v = flat[i]
            s = np.float32(v)
            out[i] = s
            all_same &= bits[i] == first  # without branches: the loop vectorises
            all_exact &= (np.float64(s) == v) | (v != v)  # a NaN's float32 is a NaN
        same[r] = all_same
        exact[r] = all_exact
