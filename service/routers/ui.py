"""The monitoring web page: nights, antenna histories, the array's latest state, outliers.

========================================  ==================================================
``GET /``                                 redirects to ``/ui``
``GET /ui``                               the latest state (antenna x band images of Trxr
                                          and ``|g|``), the latest night's outliers, every
                                          night, every antenna
``GET /ui/nights/{night}``                a night: values per antenna (outliers
                                          highlighted, with reasons), failed jobs with
                                          reasons, each job's products and figures (and
                                          its message when not ``done``: a fully or
                                          mostly flagged result)
``GET /ui/antennas/{antenna}``            ``|g|``, Trxr and G against night with 1-sigma
                                          error bars, per band
``GET /ui/static/{name}``                 the page's CSS and JS (shipped in the package)
========================================  ==================================================

Plain HTML rendered on the server with inline SVG figures (:mod:`autocal.service.ui_svg`);
nothing is fetched from elsewhere, so it works offline. The page only reads (no token
needed, no write action); it is left out of the OpenAPI schema.
"""

from __future__ import annotations

from collections.abc import Callable
from html import escape
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, Depends
from fastapi import Path as PathParam
from fastapi.responses import FileResponse, HTMLResponse, RedirectResponse

from autocal.service.auth import read_access
from autocal.service.monitoring import (
    MonitoringError,
    antenna_history,
    latest_state,
    night_detail,
    nights_overview,
    outliers_of_night,
)
from autocal.service.routers import app_store
from autocal.service.routers.job_common import ReaderDep, SettingsDep, redactor_for
from autocal.service.store import JobStore
from autocal.service.ui_svg import history_svg, state_svg

# the page follows AUTOCAL_READ_AUTH like the API reads: with it set, only clients that send
# the token (e.g. through a proxy that adds it) see the page
router = APIRouter(include_in_schema=False, dependencies=[Depends(read_access)])
StoreDep = Annotated[JobStore, Depends(app_store)]
STATIC = Path(__file__).resolve().parent.parent / "static"
STATIC_FILES = {"ui.css": "text/css", "ui.js": "text/javascript"}
#: Product names shown as images on a night's page.
FIGURES = ("png", "residuals_png", "delay_png", "data_model_png", "compare_png")
LABELS = {"abs_g": "|g| (sqrt(raw/K))", "Trxr": "Trxr (K)", "G": "G (raw/K)"}


def _page(title: str, body: str, status: int = 200) -> HTMLResponse:
    html = (
        '<!DOCTYPE html><html lang="en"><head><meta charset="utf-8">'
        f"<title>{escape(title)} - autocal</title>"
        '<link rel="icon" href="data:,">'
        '<link rel="stylesheet" href="/ui/static/ui.css">'
        '<script src="/ui/static/ui.js"></script></head><body>'
        '<header><a href="/ui">autocal monitoring</a><a href="/docs">API</a>'
        '<a href="/nights">nights (JSON)</a><a href="/antennas">antennas (JSON)</a></header>'
        f"<h1>{escape(title)}</h1>{body}</body></html>"
    )
    return HTMLResponse(html, status_code=status)


def _pm(value: Any, sigma: Any, digits: int = 4) -> str:
    if value is None:
        return "-"
    text = f"{value:.{digits}g}"
    return text if sigma is None else f"{text} &plusmn; {sigma:.2g}"


def _outlier_list(outliers: list[dict[str, Any]]) -> str:
    if not outliers:
        return '<p class="empty">no outlier antenna</p>'
    items = "".join(
        f'<li class="outlier"><a href="/ui/antennas/{o["antenna"]}">antenna {o["antenna"]} '
        f"{escape(o['pol'])}</a> ({escape(o['test'])}): {escape(o['reason'])}</li>"
        for o in outliers
    )
    return f"<ul>{items}</ul>"


def _values_table(
    rows: list[dict[str, Any]], reasons_of: Callable[[dict[str, Any]], list[str]]
) -> str:
    head = (
        '<table><tr><th class="text">antenna</th><th class="text">pol</th><th>night</th>'
        "<th>|g|</th><th>Trxr (K)</th><th>G (raw/K)</th><th>chi2/dof</th><th>flagged</th>"
        '<th>ratio</th><th class="text">effects</th><th class="text">outlier</th>'
        '<th class="text">job</th></tr>'
    )
    lines = []
    for r in rows:
        reasons = reasons_of(r)
        lines.append(
            f'<tr class="{"outlier" if reasons else ""}">'
            f'<td class="text"><a href="/ui/antennas/{r["antenna"]}">{r["antenna"]}</a></td>'
            f'<td class="text">{escape(r["pol"])}</td>'
            f'<td><a href="/ui/nights/{r["night"]}">{r["night"]}</a></td>'
            f"<td>{_pm(r['abs_g'], r['sigma_abs_g'])}</td>"
            f"<td>{_pm(r['Trxr'], r['sigma_Trxr'])}</td>"
            f"<td>{_pm(r['G'], r['sigma_G'])}</td><td>{_pm(r['reduced_chi2'], None, 3)}</td>"
            f"<td>{100 * (r['flagged_fraction'] or 0):.0f} %</td>"
            f"<td>{_pm(r['ratio'], r['sigma_ratio'])}</td>"
            f'<td class="text">{escape(", ".join(r["effects"] or []))}</td>'
            f'<td class="text">{escape("; ".join(reasons))}</td>'
            f'<td class="text"><a href="/jobs/{r["job_id"]}">{r["job_id"][:8]}</a></td></tr>'
        )
    return head + "".join(lines) + "</table>"


def _reasons_by_antenna(outliers: list[dict[str, Any]]) -> Callable[[dict[str, Any]], list[str]]:
    found: dict[tuple[int, str], list[str]] = {}
    for o in outliers:
        found.setdefault((o["antenna"], o["pol"]), []).append(o["reason"])
    return lambda row: found.get((row["antenna"], row["pol"]), [])


@router.get("/")
def root() -> RedirectResponse:
    """Send a browser to the monitoring page."""
    return RedirectResponse("/ui", status_code=307)


@router.get("/ui/static/{name}")
def static_file(name: str) -> FileResponse:
    """Serve the page's CSS and JS."""
    if name not in STATIC_FILES:
        return _page("not found", f"<p>no static file {escape(name)}</p>", 404)  # type: ignore[return-value]
    return FileResponse(STATIC / name, media_type=STATIC_FILES[name])


@router.get("/ui", response_class=HTMLResponse)
def overview(store: StoreDep) -> HTMLResponse:
    """Render the overview: latest state, latest outliers, nights, antennas."""
    latest = latest_state(store)
    nights = nights_overview(store)
    body = [
        '<p class="note">Values are medians over the solved channels with their total '
        "1-sigma; outliers depart from the array or from the antenna's own earlier nights "
        "by more than 5 combined sigma, or their chi2/dof more than doubled.</p>",
        "<h2>Latest state: Trxr per antenna and band</h2>",
        '<p class="note">colour: departure from the band\'s array median in combined sigma '
        "(blue below, red above, saturated at 5); outlined: an outlier that night</p>",
        state_svg(latest, "Trxr", "Trxr (K)"),
        "<h2>Latest state: |g| per antenna and band</h2>",
        state_svg(latest, "abs_g", "|g|"),
    ]
    recorded = [n for n in nights if n["antennas"]]
    if recorded:
        night = recorded[0]["night"]
        body.append(
            f'<h2>Outliers of the latest night, <a href="/ui/nights/{night}">{night}</a></h2>'
        )
        body.append(_outlier_list(outliers_of_night(store, night)))
    body.append("<h2>Nights</h2>")
    if nights:
        lines = "".join(
            f'<tr><td class="text"><a href="/ui/nights/{n["night"]}">{n["night"]}</a></td>'
            f"<td>{n['antennas']}</td><td>{n['observations']}</td>"
            f'<td class="text{" bad" if n["jobs"].get("failed") else ""}">'
            f"{escape(', '.join(f'{v} {k}' for k, v in sorted(n['jobs'].items())))}</td></tr>"
            for n in nights
        )
        body.append(
            '<table><tr><th class="text">night (JD)</th><th>antennas</th><th>observations</th>'
            f'<th class="text">jobs</th></tr>{lines}</table>'
        )
    else:
        body.append('<p class="empty">no night yet: submit one with POST /nightly</p>')
    body.append("<h2>Antennas (latest night of each)</h2>")
    body.append(
        _values_table(latest, lambda row: row["outliers"])
        if latest
        else '<p class="empty">no antenna calibrated yet</p>'
    )
    return _page("Nightly monitoring", "".join(body))


def _jobs_section(store: JobStore, job_ids: list[str]) -> str:
    parts = []
    for job_id in job_ids:
        job = store.get(job_id)
        if job is None:
            continue
        products = sorted(job.get("products") or {})
        links = " ".join(
            f'<a href="/jobs/{job_id}/products/{escape(p)}">{escape(p)}</a>' for p in products
        )
        figures = "".join(
            f'<img class="figure" alt="{escape(p)} of job {job_id}" '
            f'src="/jobs/{job_id}/products/{escape(p)}">'
            for p in FIGURES
            if p in products
        )
        # a succeeded job's message other than "done": its result is fully or mostly flagged
        message = job.get("message") or ""
        note = f'<p class="bad">{escape(message)}</p>' if message not in ("", "done") else ""
        parts.append(
            f'<h3>job <a href="/jobs/{job_id}">{job_id}</a> '
            f'(<a href="/jobs/{job_id}/results">results</a>)</h3>{note}'
            f"<p>products: {links}</p>{figures}"
        )
    return "".join(parts)


@router.get("/ui/nights/{night}", response_class=HTMLResponse)
def night_page(
    store: StoreDep,
    settings: SettingsDep,
    reader: ReaderDep,
    night: Annotated[int, PathParam(ge=0, le=10**8)],
) -> HTMLResponse:
    """Render a night: values, outliers, failed jobs, products and figures.

    The failed jobs' errors are shown without server paths unless the reader sent a token
    (as ``GET /nights/{night}`` answers).
    """
    try:
        detail = night_detail(store, night)
    except MonitoringError as err:
        return _page("Unknown night", f'<p class="bad">{escape(str(err))}</p>', 404)
    redactor = redactor_for(reader, settings)
    if redactor is not None:
        detail["failed_jobs"] = redactor.value(detail["failed_jobs"])
    body = [
        f"<p>jobs: {escape(', '.join(f'{v} {k}' for k, v in sorted(detail['jobs'].items())))}</p>",
        "<h2>Outliers</h2>",
        _outlier_list(detail["outliers"]),
        "<h2>Antennas</h2>",
        _values_table(detail["antennas"], _reasons_by_antenna(detail["outliers"]))
        if detail["antennas"]
        else '<p class="empty">no antenna calibrated on this night</p>',
    ]
    if detail["failed_jobs"]:
        items = "".join(
            f'<li><a href="/jobs/{f["job_id"]}">{f["job_id"][:8]}</a> ({escape(f["kind"])}): '
            f'<span class="bad">{escape(f["error"])}</span></li>'
            for f in detail["failed_jobs"]
        )
        body.append(f"<h2>Failed jobs</h2><ul>{items}</ul>")
    job_ids = sorted({j for a in detail["antennas"] for j in a["jobs"]})
    if job_ids:
        body.append("<h2>Products and figures</h2>" + _jobs_section(store, job_ids))
    return _page(f"Night {night}", "".join(body))


@router.get("/ui/antennas/{antenna}", response_class=HTMLResponse)
def antenna_page(
    store: StoreDep, antenna: Annotated[int, PathParam(ge=0, le=10**6)]
) -> HTMLResponse:
    """Render an antenna's history: ``|g|``, Trxr and G against night, per band, with errors."""
    try:
        items = antenna_history(store, antenna)
    except MonitoringError as err:
        return _page("Unknown antenna", f'<p class="bad">{escape(str(err))}</p>', 404)
    body = [
        '<p><label><input type="checkbox" id="show-bands" checked> show the 25 MHz bands'
        "</label></p>"
    ]
    for pol in sorted({i["pol"] for i in items}):
        series = [i for i in items if i["pol"] == pol]
        plots = "".join(
            f"<figure>{history_svg(series, q, LABELS[q])}</figure>" for q in ("abs_g", "Trxr", "G")
        )
        body.append(f'<h2>pol {escape(pol)}</h2><div class="plots">{plots}</div>')
        body.append(_history_table(store, series, antenna, pol))
    return _page(f"Antenna {antenna}", "".join(body))


def _history_table(store: JobStore, series: list[dict[str, Any]], antenna: int, pol: str) -> str:
    """Return the antenna's nights as a table, outlier nights highlighted with reasons."""
    reasons = {
        item["night"]: [
            o["reason"]
            for o in outliers_of_night(store, item["night"])
            if o["antenna"] == antenna and o["pol"] == pol
        ]
        for item in series
    }
    return _values_table(series, lambda row: reasons.get(row["night"], []))
