"""Inline SVG figures of the monitoring page, drawn on the server (no chart library).

:func:`history_svg` draws one quantity of an antenna night by night with 1-sigma error
bars (one series per band, or the median over the band); :func:`state_svg` draws the
array's latest state as an antenna x band image, each cell coloured by its departure from
the band's array median in units of the combined sigma (robust z), outliers outlined.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from html import escape
from typing import Any

import numpy as np

from autocal.service.outliers import robust_centre

#: Colours of the band series (colour-blind safe, Okabe-Ito).
SERIES_COLOURS = ("#000000", "#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9")
WIDTH, HEIGHT = 520, 240
MARGIN = {"left": 64, "right": 110, "top": 16, "bottom": 40}


def _ticks(lo: float, hi: float, count: int = 5) -> list[float]:
    """Return round tick values covering ``[lo, hi]``."""
    if not math.isfinite(lo) or not math.isfinite(hi) or hi <= lo:
        return [lo]
    raw = (hi - lo) / count
    step = 10 ** math.floor(math.log10(raw))
    for mult in (1, 2, 5, 10):
        if raw <= mult * step:
            step *= mult
            break
    first = math.ceil(lo / step) * step
    return [first + i * step for i in range(int((hi - first) / step) + 1)]


def _series_points(
    items: Sequence[dict[str, Any]], quantity: str, band: str | None
) -> list[tuple[int, float, float]]:
    points = []
    for item in items:
        source = item if band is None else next(
            (b for b in item.get("bands") or [] if b["band"] == band), {}
        )  # fmt: skip
        value, sigma = source.get(quantity), source.get(f"sigma_{quantity}")
        if value is not None and math.isfinite(value):
            sig = sigma if sigma is not None and math.isfinite(sigma) else 0.0
            points.append((int(item["night"]), float(value), float(sig)))
    return points


def history_svg(
    items: Sequence[dict[str, Any]], quantity: str, label: str, *, bands: bool = True
) -> str:
    """Return an SVG plot of ``quantity`` against night with 1-sigma error bars.

    Parameters
    ----------
    items
        An antenna's night values (:func:`autocal.service.monitoring.antenna_history`).
    quantity
        ``abs_g``, ``G`` or ``Trxr``.
    label
        The y-axis label (with unit).
    bands
        Also draw one series per band.

    Returns
    -------
    str
        The ``<svg>`` element.
    """
    names = sorted({b["band"] for i in items for b in i.get("bands") or []}) if bands else []
    series = [("all channels", _series_points(items, quantity, None))]
    series += [(f"{name} MHz", _series_points(items, quantity, name)) for name in names]
    series = [(n, p) for n, p in series if p]
    points = [p for _, pts in series for p in pts]
    if not points:
        return f'<p class="empty">no {escape(label)} values</p>'
    nights = [p[0] for p in points]
    x_lo, x_hi = min(nights) - 0.5, max(nights) + 0.5
    lows = [v - s for _, v, s in points]
    highs = [v + s for _, v, s in points]
    values = [v for _, v, _ in points]
    # error bars can be far larger than the spread of the values: clip the axis to the
    # values' range widened by the median error bar, and mark clipped bars
    span = max(values) - min(values)
    pad = max(float(np.median([s for *_, s in points])), 0.1 * span, 1e-12)
    y_lo, y_hi = max(min(lows), min(values) - pad), min(max(highs), max(values) + pad)
    if y_hi <= y_lo:
        y_lo, y_hi = y_lo - 1, y_hi + 1
    plot_w = WIDTH - MARGIN["left"] - MARGIN["right"]
    plot_h = HEIGHT - MARGIN["top"] - MARGIN["bottom"]

    def sx(x: float) -> float:
        return MARGIN["left"] + (x - x_lo) / (x_hi - x_lo) * plot_w

    def sy(y: float) -> float:
        y = min(max(y, y_lo), y_hi)
        return MARGIN["top"] + (1 - (y - y_lo) / (y_hi - y_lo)) * plot_h

    parts = [
        f'<svg class="plot" role="img" width="{WIDTH}" height="{HEIGHT}" '
        f'viewBox="0 0 {WIDTH} {HEIGHT}" xmlns="http://www.w3.org/2000/svg">',
        f"<title>{escape(label)} against night</title>",
        f'<rect x="{MARGIN["left"]}" y="{MARGIN["top"]}" width="{plot_w}" height="{plot_h}" '
        'class="frame"/>',
    ]
    for tick in _ticks(y_lo, y_hi):
        parts.append(
            f'<text x="{MARGIN["left"] - 6}" y="{sy(tick) + 4:.1f}" class="tick" '
            f'text-anchor="end">{tick:.4g}</text>'
        )
    for night in sorted(set(nights)):
        parts.append(
            f'<text x="{sx(night):.1f}" y="{HEIGHT - MARGIN["bottom"] + 16}" class="tick" '
            f'text-anchor="middle">{night}</text>'
        )
    parts.append(
        f'<text x="14" y="{MARGIN["top"] + plot_h / 2:.0f}" class="axis" text-anchor="middle" '
        f'transform="rotate(-90 14 {MARGIN["top"] + plot_h / 2:.0f})">{escape(label)}</text>'
        f'<text x="{MARGIN["left"] + plot_w / 2:.0f}" y="{HEIGHT - 6}" class="axis" '
        'text-anchor="middle">night (JD)</text>'
    )
    for k, (name, pts) in enumerate(series):
        colour = SERIES_COLOURS[k % len(SERIES_COLOURS)]
        offset = (k - (len(series) - 1) / 2) * 0.06  # side by side, not on top
        path = " ".join(f"{sx(n + offset):.1f},{sy(v):.1f}" for n, v, _ in pts)
        parts.append(f'<g class="series" data-series="{escape(name)}" stroke="{colour}">')
        parts.append(f'<polyline points="{path}" fill="none" stroke-width="1" opacity="0.5"/>')
        for n, v, s in pts:
            x = sx(n + offset)
            parts.append(
                f'<line x1="{x:.1f}" x2="{x:.1f}" y1="{sy(v - s):.1f}" y2="{sy(v + s):.1f}"/>'
                f'<circle cx="{x:.1f}" cy="{sy(v):.1f}" r="3" fill="{colour}">'
                f"<title>{n}: {v:.4g} +/- {s:.2g}</title></circle>"
            )
        parts.append("</g>")
        y = MARGIN["top"] + 12 + 14 * k
        parts.append(
            f'<text x="{WIDTH - MARGIN["right"] + 8}" y="{y}" class="legend" '
            f'fill="{colour}">{escape(name)}</text>'
        )
    parts.append("</svg>")
    return "".join(parts)


def _diverging(z: float) -> str:
    """Colour of a robust z: white at 0, blue below, red above, saturated at |z| = 5."""
    t = max(-1.0, min(1.0, z / 5.0))
    if t >= 0:
        return f"rgb(255,{int(255 * (1 - t))},{int(255 * (1 - t))})"
    return f"rgb({int(255 * (1 + t))},{int(255 * (1 + t))},255)"


def state_svg(latest: Sequence[dict[str, Any]], quantity: str, label: str) -> str:
    """Return the antenna x band image of the latest state of ``quantity``.

    Each cell is the antenna-pol's band value; its colour is its departure from the
    band's array median in units of ``sqrt(spread^2 + sigma^2)`` (spread = 1.4826 MAD
    over the antennas), the same statistic as the array outlier test. Antenna-pols that
    are outliers on their latest night have a thick outline.
    """
    rows = [e for e in latest if e.get("bands")]
    names = sorted({b["band"] for e in rows for b in e["bands"]})
    if not rows or not names:
        return '<p class="empty">no antenna has band values yet</p>'
    centre = {}
    for name in names:
        vals = [b[quantity] for e in rows for b in e["bands"] if b["band"] == name and b[quantity]]
        centre[name] = robust_centre(vals) if vals else (math.nan, math.nan)
    cell_w, cell_h, left, top = 84, 22, 90, 36
    width, height = left + cell_w * len(names) + 10, top + cell_h * len(rows) + 10
    parts = [
        f'<svg class="state" role="img" width="{width}" height="{height}" '
        f'viewBox="0 0 {width} {height}" xmlns="http://www.w3.org/2000/svg">',
        f"<title>latest {escape(label)} per antenna and band</title>",
    ]
    for j, name in enumerate(names):
        parts.append(
            f'<text x="{left + cell_w * (j + 0.5):.0f}" y="{top - 8}" class="tick" '
            f'text-anchor="middle">{escape(name)} MHz</text>'
        )
    for i, entry in enumerate(rows):
        y = top + cell_h * i
        outlier = bool(entry.get("outliers"))
        parts.append(
            f'<text x="{left - 6}" y="{y + 15}" class="tick{" bad" if outlier else ""}" '
            f'text-anchor="end">{entry["antenna"]} {escape(entry["pol"])}</text>'
        )
        bands = {b["band"]: b for b in entry["bands"]}
        for j, name in enumerate(names):
            band = bands.get(name) or {}
            value, sigma = band.get(quantity), band.get(f"sigma_{quantity}") or 0.0
            mid, spread = centre[name]
            if value is None or not math.isfinite(mid):
                colour, text, z = "#dddddd", "-", math.nan
            else:
                scale = math.hypot(spread, sigma)
                z = (value - mid) / scale if scale > 0 else 0.0
                colour, text = _diverging(z), f"{value:.3g}"
            stroke = ' stroke="#000" stroke-width="2.5"' if outlier else ' stroke="#fff"'
            parts.append(
                f'<rect x="{left + cell_w * j}" y="{y}" width="{cell_w}" height="{cell_h}" '
                f'fill="{colour}"{stroke}><title>antenna {entry["antenna"]} {escape(entry["pol"])}'
                f" {escape(name)} MHz: {text} +/- {sigma:.2g} (z {z:+.1f})</title></rect>"
                f'<text x="{left + cell_w * (j + 0.5):.0f}" y="{y + 15}" class="cell" '
                f'text-anchor="middle">{text}</text>'
            )
    parts.append("</svg>")
    return "".join(parts)
