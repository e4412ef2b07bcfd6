"""Short representations of autocal's records: shapes, ranges and medians, never arrays.

A HERA night's :class:`~autocal.fit.solution.Solution` holds millions of values; printing it (or a
list holding it, or a notebook cell ending with it) shows one or two lines instead.
:func:`compact_repr` is the generic form for any dataclass record (arrays as their shape
and type); :class:`~autocal.core.observation.Observation`,
:class:`~autocal.fit.solution.Solution` and :class:`~autocal.tsky.result.TskyResult` build
theirs from the helpers here.

This module imports only numpy, so any module may use it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = ["array_summary", "compact_repr", "list_summary", "median", "span"]

#: Items of a list (antennas, pols) shown before it is abbreviated.
MAX_LISTED = 6


def array_summary(value: np.ndarray) -> str:
    """Return ``"float64(2, 60, 64)"``: an array's type and shape."""
    return f"{value.dtype}{tuple(value.shape)}"


def list_summary(values: Sequence[Any] | np.ndarray, max_items: int = MAX_LISTED) -> str:
    """Return ``"[23, 24, 25]"`` or, for a long list, ``"[23, 24, ..., 99] (350)"``."""
    items = [v.item() if isinstance(v, np.generic) else v for v in list(values)]
    if len(items) <= max_items:
        return "[" + ", ".join(str(v) for v in items) + "]"
    head = ", ".join(str(v) for v in items[: max_items - 1])
    return f"[{head}, ..., {items[-1]}] ({len(items)})"


def span(values: np.ndarray, scale: float = 1.0, unit: str = "", digits: int = 4) -> str:
    """Return ``"100-200 MHz"``: the first and last value of an axis (``"-"`` if empty)."""
    values = np.asarray(values, dtype=np.float64).ravel()
    if values.size == 0:
        return "-"
    lo, hi = values[0] / scale, values[-1] / scale
    text = f"{lo:.{digits}g}" if values.size == 1 else f"{lo:.{digits}g}-{hi:.{digits}g}"
    return f"{text} {unit}".rstrip()


def median(values: np.ndarray, where: np.ndarray | None = None) -> float:
    """Return the median of the finite values (selected by ``where``); NaN if none."""
    values = np.asarray(values, dtype=np.float64)
    ok = np.isfinite(values) if where is None else np.isfinite(values) & where
    return float(np.median(values[ok])) if np.any(ok) else float("nan")


def _value_summary(value: Any) -> str:
    if isinstance(value, np.ndarray):
        return array_summary(value)
    if isinstance(value, dict):
        return f"{{{len(value)} keys}}" if value else "{}"
    if isinstance(value, list | tuple) and len(value) > MAX_LISTED:
        return f"{type(value).__name__}({len(value)})"
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return f"{type(value).__name__}(...)"
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def compact_repr(obj: Any, head: str = "") -> str:
    """Return ``Name(head; field=summary, ...)`` for a dataclass record.

    Arrays appear as their type and shape, dictionaries as their number of keys, long
    sequences as their length, nested records as ``Name(...)``.

    Parameters
    ----------
    obj
        A dataclass instance.
    head
        A description put first (e.g. ranges and medians).

    Returns
    -------
    str
        One line.
    """
    parts = [
        f"{f.name}={_value_summary(getattr(obj, f.name))}"
        for f in dataclasses.fields(obj)
        if f.repr and getattr(obj, f.name, None) is not None
    ]
    body = "; ".join(p for p in (head, ", ".join(parts)) if p)
    return f"{type(obj).__name__}({body})"
