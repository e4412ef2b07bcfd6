"""Finiteness of small trailing vectors and matrices, per leading element.

``np.all(np.isfinite(x), axis=-1)`` over a trailing axis of two values (the fit's
``(G, n)`` pairs, its 2 x 2 covariances) runs numpy's reduction with an inner loop of two
elements per step: ~0.1 s for a HERA-size file's 5.4 M refits of the jackknife, five times
the cost of testing the columns one by one, which is what :func:`finite_trailing` does.
"""

from __future__ import annotations

import numpy as np


def finite_trailing(values: np.ndarray, ndim: int = 1) -> np.ndarray:
    """Return whether every value of each trailing ``ndim``-dimensional element is finite.

    The same as ``np.all(np.isfinite(values), axis=tuple(range(-ndim, 0)))``.

    Parameters
    ----------
    values
        Array of at least ``ndim`` dimensions.
    ndim
        Trailing dimensions tested together (1: vectors, 2: matrices).

    Returns
    -------
    numpy.ndarray
        Boolean array of ``values.shape[:-ndim]``.

    Raises
    ------
    ValueError
        When ``ndim`` is not between 1 and ``values.ndim``.
    """
    if not 1 <= ndim <= values.ndim:
        raise ValueError(f"{ndim} trailing dimensions of a {values.ndim}-d array")
    lead = values.shape[: values.ndim - ndim]
    flat = values.reshape(*lead, int(np.prod(values.shape[values.ndim - ndim :])))
    if flat.shape[-1] == 0:
        return np.ones(lead, bool)
    ok = np.isfinite(flat[..., 0])
    for i in range(1, flat.shape[-1]):
        ok &= np.isfinite(flat[..., i])
    return ok
