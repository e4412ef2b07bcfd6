"""The REST API of the job service (autocal.service.app and its routers)."""

from __future__ import annotations

import hashlib
import socket
import threading
import time
import warnings
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path

import httpx
import jsonschema_rs
import pytest
import schemathesis
import uvicorn
from hypothesis import HealthCheck, given
from hypothesis import settings as hypothesis_settings
from schemathesis import GenerationMode
from schemathesis.checks import (
    content_type_conformance,
    not_a_server_error,
    response_headers_conformance,
    response_schema_conformance,
    status_code_conformance,
)

import autocal
from autocal.service.app import create_app
from autocal.service.nightly import (
    NightFile,
    find_observations,
    group_observations,
    submit_nightly,
)
from autocal.service.paths import job_products_dir
from autocal.service.schemas import CALIBRATE_ONLY, DIAGNOSE_ONLY, CalibrationOptions
from autocal.service.settings import Settings
from autocal.service.store import JobState, JobStore
from tests.service.tiny_uvh5 import write_tiny_uvh5

with warnings.catch_warnings():  # starlette's notice about httpx2, raised at import
    warnings.filterwarnings("ignore", message=".*httpx2")
    from fastapi.testclient import TestClient

TOKEN = "test-token-0123456789abcdef-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
HH = "zen.2458116.30448.HH.uvh5"


def _settings(tmp_path: Path, data: Path | None = None, **kwargs: object) -> Settings:
    values: dict[str, object] = {
        "state_dir": tmp_path / "state",
        "database_url": f"sqlite:///{tmp_path / 'jobs.sqlite'}",
        "data_roots": [data if data is not None else tmp_path / "data"],
        "api_token": TOKEN,
        # these tests send many wrong tokens on purpose (test_auth.py tests the limit)
        "auth_failures": 1_000_000,
    }
    values.update(kwargs)
    return Settings(**values)


@pytest.fixture
def data(tmp_path: Path) -> Path:
    """A data root with a few (fake) HERA files and a secret file beside it."""
    folder = tmp_path / "data"
    folder.mkdir()
    for name in (HH, "zen.2458116.31193.HH.uvh5", "zen.2458117.30000.HH.uvh5"):
        write_tiny_uvh5(folder / name)
    (tmp_path / "secret.txt").write_text("top secret")
    return folder


@pytest.fixture
def settings(tmp_path: Path, data: Path) -> Settings:
    return _settings(tmp_path, data)


@pytest.fixture
def store(settings: Settings) -> JobStore:
    return JobStore(settings.resolved_database_url())


@pytest.fixture
def client(settings: Settings, store: JobStore) -> Iterator[TestClient]:
    with TestClient(create_app(settings, store)) as test_client:
        yield test_client


def _submit(client: TestClient, **body: object) -> httpx.Response:
    body.setdefault("inputs", [HH])
    body.setdefault("beam", "dipole")
    return client.post("/jobs", json=body, headers=AUTH)


# the job lifecycle ----------------------------------------------------------------------


def test_nightly_needs_a_night_or_a_folder_as_its_schema_says(client: TestClient) -> None:
    """Issue 24 D11: ``POST /nightly {}`` answered 400 though the schema allowed it."""
    schema = client.get("/openapi.json").json()["components"]["schemas"]["NightlyCreate"]
    assert {"required": ["night"]} in schema["anyOf"]
    assert {"required": ["folder"]} in schema["anyOf"]
    response = client.post("/nightly", json={}, headers=AUTH)
    assert response.status_code == 422 and "night" in response.text, response.text


def test_results_document_the_422_of_a_filtered_diagnosis(client: TestClient) -> None:
    """Issue 24 D11: a diagnose job's results with an antenna filter answer a 422 the
    OpenAPI description did not mention."""
    spec = client.get("/openapi.json").json()
    text = spec["paths"]["/jobs/{job_id}/results"]["get"]["responses"]["422"]["description"]
    assert "diagnose" in text and "antenna" in text


def test_body_limit_before_reading_and_before_the_token(
    tmp_path: Path, data: Path, store: JobStore
) -> None:
    """Issue 24 D4: a 200 MB anonymous POST was read in full before the 401, and a 120 MB
    authenticated body was accepted."""
    settings = _settings(tmp_path, data, max_body_bytes=1000)
    big = b'{"inputs": ["' + b"x" * 2000 + b'"]}'

    def chunks():  # no Content-Length: counted as it arrives
        for start in range(0, len(big), 100):
            yield big[start : start + 100]

    with TestClient(create_app(settings, store)) as small:
        anonymous = small.post("/jobs", content=big, headers={"content-type": "application/json"})
        assert anonymous.status_code == 413, anonymous.text
        assert "AUTOCAL_MAX_BODY_BYTES" in anonymous.json()["detail"]
        authed = small.post(
            "/jobs", content=big, headers={**AUTH, "content-type": "application/json"}
        )
        assert authed.status_code == 413, authed.text
        streamed = small.post(
            "/jobs", content=chunks(), headers={**AUTH, "content-type": "application/json"}
        )
        assert streamed.status_code == 413, streamed.text
        assert "AUTOCAL_MAX_BODY_BYTES" in streamed.json()["detail"]
        fine = small.post("/jobs", json={"inputs": [HH], "beam": "dipole"}, headers=AUTH)
        assert fine.status_code == 202, fine.text
        assert small.get("/jobs").json()["count"] == 1


def test_a_repeated_query_parameter_is_refused(client: TestClient) -> None:
    """Issue 24 D11: ``?night=1&night=2`` was accepted (the last value used)."""
    response = client.get("/jobs?night=2458116&night=2458117")
    assert response.status_code == 422, response.text
    assert "'night' given 2 times" in response.json()["detail"]
    assert client.get("/jobs?night=2458116&limit=5").status_code == 200


def test_empty_antennas_and_repeated_inputs_are_refused_at_submission(client: TestClient) -> None:
    """Issue 24 D8: ``antennas: []`` failed in the worker (ZeroDivisionError) and one file
    listed 2000 times was accepted."""
    response = _submit(client, antennas=[])
    assert response.status_code == 422 and "antennas" in response.text, response.text
    response = _submit(client, inputs=[HH] * 2000)
    assert response.status_code == 422, response.text
    assert "listed 2000 times" in response.text and "inputs" in response.text, response.text
    assert client.get("/jobs").json()["count"] == 0


@pytest.mark.parametrize(
    "sky", ["uniform:.", "uniform:e", "uniform:-", "powerlaw:gsm2008@.:1", "uniform:-100"]
)
def test_malformed_sky_is_a_4xx_naming_the_sky(client: TestClient, sky: str) -> None:
    """Issue 24 D1: these skies answered 500 (a failed float() escaped); D8: -100 K ran."""
    for kind in ("calibrate", "diagnose"):
        response = _submit(client, sky=sky, kind=kind)
        assert 400 <= response.status_code < 500, (kind, response.status_code, response.text)
        assert sky in response.text, response.text
    response = client.post("/nightly", json={"night": 2458116, "sky": sky}, headers=AUTH)
    assert 400 <= response.status_code < 500, (response.status_code, response.text)
    assert sky in response.text, response.text


def test_submit_get_list_cancel(client: TestClient, data: Path) -> None:
    response = _submit(client, antennas=[23, 24], freq_range_mhz=[110, 190])
    assert response.status_code == 202, response.text
    accepted = response.json()
    assert accepted["created"] is True and accepted["state"] == "queued"
    job_id = accepted["id"]
    assert response.headers["location"] == f"/jobs/{job_id}"
    assert accepted["links"]["results"] == f"/jobs/{job_id}/results"

    job = client.get(f"/jobs/{job_id}", headers=AUTH).json()  # a token holder sees paths
    assert job["state"] == "queued" and job["night"] == 2458116
    assert job["antennas"] == [23, 24]
    assert job["config"]["inputs"] == [str((data / HH).resolve())]
    assert job["config"]["freq_range_mhz"] == [110.0, 190.0]
    assert "hdf5" in job["config"]["products"]  # always written: results read it
    assert job["timings"]["created"] is not None and job["timings"]["started"] is None
    assert job["attempts"] == 0 and job["log_tail"] == [] and job["error"] is None

    other = _submit(client, inputs=["zen.2458117.30000.HH.uvh5"]).json()["id"]
    listing = client.get("/jobs").json()
    assert {j["id"] for j in listing["items"]} == {job_id, other}
    assert [j["id"] for j in client.get("/jobs", params={"night": 2458116}).json()["items"]] == [
        job_id
    ]
    assert client.get("/jobs", params={"antenna": 24}).json()["count"] == 2  # other: all ants
    assert client.get("/jobs", params={"antenna": 99}).json()["count"] == 1
    assert client.get("/jobs", params={"kind": "calibrate", "limit": 1}).json()["count"] == 1
    assert client.get("/jobs", params={"offset": 1}).json()["count"] == 1
    assert client.get("/jobs", params={"state": "running"}).json()["items"] == []
    # pages: the cursor of one leads to the next, with the same filters
    page = client.get("/jobs", params={"limit": 1, "kind": "calibrate"}).json()
    assert page["items"][0]["id"] == other  # newest first
    assert page["next"] == f"/jobs?kind=calibrate&limit=1&cursor={page['next_cursor']}"
    last = client.get(page["next"]).json()
    assert [j["id"] for j in last["items"]] == [job_id] and last["next_cursor"] is None
    bad = client.get("/jobs", params={"cursor": "not-a-cursor"})
    assert bad.status_code == 422 and bad.json()["errors"][0]["field"] == "query.cursor"
    both = client.get("/jobs", params={"cursor": page["next_cursor"], "offset": 1})
    assert both.status_code == 422 and both.json()["errors"][0]["field"] == "query.offset"

    cancelled = client.post(f"/jobs/{job_id}/cancel", headers=AUTH)
    assert cancelled.status_code == 202 and cancelled.json()["state"] == "cancelled"
    assert client.get("/jobs", params={"state": "cancelled"}).json()["count"] == 1
    again = client.post(f"/jobs/{job_id}/cancel", headers=AUTH)
    assert again.status_code == 409 and "already cancelled" in again.json()["detail"]


def test_cancel_running_job_asks_the_worker(client: TestClient, store: JobStore) -> None:
    job_id = _submit(client).json()["id"]
    claimed = store.claim("w1")
    assert claimed is not None and claimed["id"] == job_id
    response = client.post(f"/jobs/{job_id}/cancel", headers=AUTH)
    assert response.status_code == 202
    assert response.json()["state"] == "running" and response.json()["cancel_requested"]
    assert store.heartbeat(job_id, "w1", 1) is False


def test_idempotent_resubmission_and_force(client: TestClient, data: Path) -> None:
    first = _submit(client, inputs=[HH, "zen.2458116.31193.HH.uvh5"]).json()
    # the same files (in another order, one by absolute path) and settings: no new job
    same = _submit(client, inputs=["zen.2458116.31193.HH.uvh5", str(data / HH)]).json()
    assert same["created"] is False and same["id"] == first["id"]
    # other settings: a new job
    other = _submit(client, inputs=[HH, "zen.2458116.31193.HH.uvh5"], tgnd_k=250).json()
    assert other["created"] is True and other["id"] != first["id"]
    forced = _submit(client, inputs=[HH, "zen.2458116.31193.HH.uvh5"], force=True).json()
    assert forced["created"] is True and forced["id"] not in {first["id"], other["id"]}
    # a cancelled job does not block a resubmission
    lone = _submit(client, inputs=["zen.2458117.30000.HH.uvh5"]).json()["id"]
    client.post(f"/jobs/{lone}/cancel", headers=AUTH)
    again = _submit(client, inputs=["zen.2458117.30000.HH.uvh5"]).json()
    assert again["created"] is True and again["id"] != lone


def test_unknown_job_is_404_with_message(client: TestClient) -> None:
    for method, url in [
        ("GET", "/jobs/nope"),
        ("GET", "/jobs/nope/results"),
        ("GET", "/jobs/nope/products/hdf5"),
        ("POST", "/jobs/nope/cancel"),
    ]:
        response = client.request(method, url, headers=AUTH)
        assert response.status_code == 404, url
        assert "no job 'nope'" in response.json()["detail"]


def test_a_wrong_method_is_405_listing_every_method_of_the_resource(client: TestClient) -> None:
    for method, url, allowed in [
        ("OPTIONS", "/jobs", "GET, POST"),  # two routes share the path
        ("DELETE", "/jobs/nope", "GET"),
        ("GET", "/jobs/nope/cancel", "POST"),
        ("GET", "/uploads", "POST"),
        ("PUT", "/health", "GET"),
    ]:
        response = client.request(method, url, headers=AUTH)
        assert response.status_code == 405, (method, url)
        assert response.headers["allow"] == allowed, (method, url)
        assert response.json()["detail"] == f"method {method} not allowed here; use {allowed}"


def test_the_schema_states_which_options_each_kind_takes(client: TestClient) -> None:
    """The schema's if/then/else and the server refuse the same misplaced options."""
    from autocal.diagnosis.run import DiagnoseConfig

    calibrate_only = set(CalibrationOptions.model_fields) - set(DiagnoseConfig.model_fields)
    assert calibrate_only == CALIBRATE_ONLY
    assert set(DiagnoseConfig.model_fields) >= DIAGNOSE_ONLY
    spec = client.get("/openapi.json").json()
    validator = jsonschema_rs.Draft202012Validator(
        {"$ref": "#/components/schemas/JobCreate", "components": spec["components"]}
    )
    for extra, ok in [
        ({}, True),
        ({"alpha": 0.01}, False),  # a diagnose option in a calibration
        ({"alpha": None, "model": "constant"}, True),
        ({"kind": "diagnose", "alpha": 0.01, "max_steps": 2}, True),
        ({"kind": "diagnose", "model": "constant"}, False),  # a calibrate option
        ({"kind": "diagnose", "reference": None}, True),
        ({"kind": "calibrate", "max_steps": 3}, False),
        ({"kind": "diagnose", "passes": 2}, False),
        ({"kind": "diagnose", "edges_bin": 4}, False),
        ({"kind": "diagnose", "rfi_flagging": False}, True),  # an option of both kinds
    ]:
        body = {"inputs": [HH], **extra}
        assert validator.is_valid(body) is ok, extra
        response = _submit(client, **body)
        assert response.status_code == (202 if ok else 422), (extra, response.json())


def test_every_error_answer_is_documented_as_the_error_body(settings: Settings) -> None:
    """Generated clients parse errors by the schema: it must be the body the API sends."""
    spec = create_app(settings).openapi()
    for path, item in spec["paths"].items():
        for method, operation in item.items():
            for code, response in operation["responses"].items():
                if code[0] in "45" and path != "/health":  # /health answers 503 with Health
                    schema = response["content"]["application/json"]["schema"]
                    assert schema == {"$ref": "#/components/schemas/ErrorBody"}, (
                        method,
                        path,
                        code,
                    )
    assert "HTTPValidationError" not in spec["components"]["schemas"]


# authentication -------------------------------------------------------------------------


def test_write_endpoints_need_the_token(client: TestClient) -> None:
    job_id = _submit(client).json()["id"]
    writes = [
        ("POST", "/jobs", {"json": {"inputs": [HH]}}),
        ("POST", f"/jobs/{job_id}/cancel", {}),
        ("POST", "/nightly", {"json": {"night": 2458116}}),
        ("POST", "/uploads", {"files": {"file": ("a.uvh5", b"x")}}),
    ]
    for method, url, kwargs in writes:
        missing = client.request(method, url, **kwargs)
        assert missing.status_code == 401, url
        assert missing.headers["www-authenticate"].startswith("Bearer")
        assert "Authorization: Bearer" in missing.json()["detail"]
        wrong = client.request(method, url, headers={"Authorization": "Bearer nope"}, **kwargs)
        assert wrong.status_code == 401 and "invalid_token" in wrong.headers["www-authenticate"]
        basic = client.request(method, url, headers={"Authorization": "Basic c2VjcmV0"}, **kwargs)
        assert basic.status_code == 401
    # non-ASCII tokens are compared safely, not a 500
    odd = client.post(
        "/jobs", json={"inputs": [HH]}, headers={"Authorization": "Bearer é".encode()}
    )
    assert odd.status_code == 401
    assert client.get("/jobs").status_code == 200  # reads need no token
    assert client.get(f"/jobs/{job_id}").status_code == 200


def test_no_token_configured_refuses_writes(tmp_path: Path, data: Path) -> None:
    settings = _settings(tmp_path, data, api_token="")
    with TestClient(create_app(settings)) as client:
        response = client.post("/jobs", json={"inputs": [HH]}, headers=AUTH)
        assert response.status_code == 503
        assert "AUTOCAL_API_TOKEN" in response.json()["detail"]
        assert client.get("/health").json()["status"] == "ok"


# paths ----------------------------------------------------------------------------------


def test_paths_outside_the_roots_are_refused(client: TestClient, tmp_path: Path, data: Path):
    (data / "escape").symlink_to(tmp_path / "secret.txt")
    (data / "sub").mkdir()
    (data / "sub" / "inside").symlink_to(data / HH)
    for bad in ["../../etc/passwd", "../secret.txt", "/etc/passwd", "escape", str(data / "escape")]:
        response = _submit(client, inputs=[bad])
        assert response.status_code == 403, bad
        detail = response.json()["detail"]
        assert "outside the allowed folders" in detail and str(data) in detail
        assert "top secret" not in response.text
    for field, value in [("reference", ["/etc/passwd"]), ("beam", "/etc/passwd")]:
        response = _submit(client, **{field: value})
        assert response.status_code == 403, field
        assert field in response.json()["detail"]
    # a symlink staying inside a root is fine (stored resolved)
    ok = _submit(client, inputs=["sub/inside"])
    assert ok.status_code == 202
    config = client.get(f"/jobs/{ok.json()['id']}", headers=AUTH).json()["config"]
    assert config["inputs"] == [str((data / HH).resolve())]
    missing = _submit(client, inputs=["zen.2458116.99999.HH.uvh5"])
    assert missing.status_code == 400 and "does not exist" in missing.json()["detail"]
    nul = _submit(client, inputs=["a\x00b"])
    assert nul.status_code == 400
    unknown_upload = _submit(client, inputs=["0" * 32])
    assert unknown_upload.status_code == 400 and "POST /uploads" in unknown_upload.json()["detail"]


# validation -----------------------------------------------------------------------------


def test_unknown_fields_and_bad_values_are_422_naming_the_field(client: TestClient) -> None:
    response = _submit(client, frequency_range=[100, 200])
    assert response.status_code == 422
    body = response.json()
    assert "frequency_range" in body["detail"] and "unknown field" in body["detail"]
    assert body["errors"][0]["field"] == "body.frequency_range"

    hz = _submit(client, freq_range_mhz=[100e6, 200e6])
    assert hz.status_code == 422
    assert "freq_range_mhz" in hz.json()["detail"] and "MHz, not Hz" in hz.json()["detail"]
    assert hz.json()["errors"][0]["field"] == "body.freq_range_mhz"

    several = _submit(client, model="quadratic", nside=3, order=-1, pols=["xy"])
    assert several.status_code == 422
    fields = {e["field"] for e in several.json()["errors"]}
    assert {"body.model", "body.nside", "body.order", "body.pols.0"} <= fields
    assert "power of two" in several.json()["detail"]
    # the schema lists the nsides it takes, so forms and generated clients offer only those
    nside = client.get("/openapi.json").json()["components"]["schemas"]["JobCreate"]
    nside = nside["properties"]["nside"]["anyOf"][0]
    assert nside["enum"] == [2**k for k in range(1, 11)]
    for good in nside["enum"]:
        assert "body.nside" not in str(_submit(client, nside=good).json())

    for body_extra, word in [
        ({"kind": "teleport"}, "kind"),
        ({"inputs": []}, "inputs"),
        ({"sky": "gsm2099"}, "gsm2099"),
        ({"lst_range_h": [0, 30]}, "lst_range_h"),
        ({"tgnd_k": -1}, "tgnd_k"),
        # types as the schema states them (pydantic's lax mode would coerce these)
        ({"force": 0}, "force"),
        ({"inflate_errors": "yes"}, "inflate_errors"),
        ({"tgnd_k": False}, "tgnd_k"),
        ({"freq_range_mhz": ["110", 190]}, "freq_range_mhz"),
        ({"antennas": [True]}, "antennas"),
        ({"order": "2", "model": "legendre"}, "order"),
        ({"passes": True}, "passes"),
        ({"kind": "diagnose", "max_steps": "3"}, "max_steps"),
    ]:
        bad = _submit(client, **body_extra)
        assert bad.status_code == 422, body_extra
        assert word in bad.json()["detail"], (body_extra, bad.json())
    integral = _submit(client, antennas=[23.0], tgnd_k=300, model="legendre", order=1.0)
    assert integral.status_code == 202, integral.json()  # 23.0 is a JSON integer
    not_json = client.post(
        "/jobs", content=b"{not json", headers={**AUTH, "content-type": "application/json"}
    )
    assert not_json.status_code == 422 and "invalid request" in not_json.json()["detail"]
    for params in [{"limit": 0}, {"limit": 1001}, {"state": "sleeping"}, {"offset": -1}]:
        assert client.get("/jobs", params=params).status_code == 422, params


@pytest.mark.parametrize("kind", ["calibrate", "diagnose"])
def test_receiver_priors_are_read_and_checked_at_submission(
    client: TestClient, data: Path, tmp_path: Path, kind: str
) -> None:
    """A prior table under the data roots is resolved and validated when the job is
    submitted: a malformed one is a 422 saying what is wrong, a file outside the roots a
    403, and a good one (or a number) is accepted with its absolute path recorded."""
    (data / "good.csv").write_text("freq_mhz,trxr_k,sigma_k\n100,150,5\n200,160,5\n")
    bad = {
        "header.csv": ("freq,trxr\n100,150\n200,150\n", "header 'freq,trxr' is not"),
        "nan.csv": ("freq_mhz,trxr_k\n100,150\n150,nan\n", "trxr_k is 'nan'"),
        "order.csv": ("freq_mhz,trxr_k\n100,150\n150,1\n140,1\n", "does not increase"),
    }
    for name, (text, _) in bad.items():
        (data / name).write_text(text)
    for name, (_, message) in bad.items():
        response = _submit(client, kind=kind, trxr_prior=name)
        assert response.status_code == 422, response.text
        assert message in response.json()["detail"]
    (tmp_path / "outside.csv").write_text("freq_mhz,trxr_k\n100,150\n200,150\n")
    assert _submit(client, kind=kind, trxr_prior=str(tmp_path / "outside.csv")).status_code == 403
    assert _submit(client, kind=kind, trxr_prior=True).status_code == 422
    good = _submit(client, kind=kind, trxr_prior="good.csv", trxr_prior_sigma_k=3)
    assert good.status_code == 202, good.text
    config = client.get(f"/jobs/{good.json()['id']}", headers=AUTH).json()["config"]
    assert config["trxr_prior"] == str((data / "good.csv").resolve())
    number = _submit(client, kind=kind, trxr_prior=150, force=True)
    assert number.status_code == 202, number.text


def test_unexpected_errors_are_a_generic_500(client: TestClient, store: JobStore, monkeypatch):
    def boom(_job_id: str) -> None:
        raise RuntimeError("secret internal detail")

    monkeypatch.setattr(store, "get", boom)
    response = client.get("/jobs/abc")
    assert response.status_code == 500
    assert "internal server error" in response.json()["detail"]
    assert "secret internal detail" not in response.text and "Traceback" not in response.text


def test_health_reports_database_errors(client: TestClient, store: JobStore, monkeypatch):
    _submit(client)
    health = client.get("/health").json()
    assert health == {
        "status": "ok",
        "version": autocal.__version__,
        "database": "ok",
        "queued": 1,
        "running": 0,
    }

    def down() -> bool:
        raise OSError("database is gone")

    monkeypatch.setattr(store, "ping", down)
    response = client.get("/health")
    assert response.status_code == 503
    assert response.json()["database"] == "error" and response.json()["status"] == "degraded"


# uploads --------------------------------------------------------------------------------


def test_upload_then_submit_by_id(client: TestClient, settings: Settings, tmp_path: Path) -> None:
    payload = write_tiny_uvh5(tmp_path / "upload" / "zen.2458118.40000.HH.uvh5").read_bytes()
    response = client.post(
        "/uploads",
        files={"file": ("../../zen.2458118.40000.HH.uvh5", payload)},
        data={"comment": "ignored"},
        headers=AUTH,
    )
    assert response.status_code == 201, response.text
    upload = response.json()
    assert upload["bytes"] == len(payload)
    assert upload["sha256"] == hashlib.sha256(payload).hexdigest()
    assert upload["filename"] == "zen.2458118.40000.HH.uvh5"  # no path parts kept
    path = Path(upload["path"])
    assert path.read_bytes() == payload
    assert path.parent.parent == settings.uploads_dir.resolve()

    job = _submit(client, inputs=[upload["upload_id"]])
    assert job.status_code == 202
    record = client.get(f"/jobs/{job.json()['id']}", headers=AUTH).json()
    assert record["config"]["inputs"] == [upload["path"]] and record["night"] == 2458118
    same = _submit(client, inputs=[f"upload:{upload['upload_id']}"]).json()
    assert same["created"] is False
    by_path = _submit(client, inputs=[upload["path"]]).json()  # the uploads folder is a root
    assert by_path["created"] is False


def test_oversized_upload_is_refused_and_leaves_nothing(tmp_path: Path, data: Path) -> None:
    settings = _settings(tmp_path, data, max_upload_bytes=1000)
    with TestClient(create_app(settings)) as client:
        ok = client.post("/uploads", files={"file": ("a.bin", b"x" * 1000)}, headers=AUTH)
        assert ok.status_code == 201
        kept = set(settings.uploads_dir.rglob("*"))
        # refused while streaming (the body is within the framing allowance)
        big = client.post("/uploads", files={"file": ("b.bin", b"x" * 5000)}, headers=AUTH)
        assert big.status_code == 413
        assert "1000 bytes" in big.json()["detail"]
        assert "AUTOCAL_MAX_UPLOAD_BYTES" in big.json()["detail"]
        # refused from the declared Content-Length before reading
        huge = client.post(
            "/uploads", files={"file": ("c.bin", b"x" * (2 * 1024 * 1024))}, headers=AUTH
        )
        assert huge.status_code == 413
        assert set(settings.uploads_dir.rglob("*")) == kept  # no partial file, no folder


def test_malformed_uploads_are_4xx(client: TestClient, settings: Settings) -> None:
    not_multipart = client.post("/uploads", content=b"abc", headers=AUTH)
    assert not_multipart.status_code == 415
    no_file = client.post("/uploads", data={"x": "1"}, files={"other": ("a", b"1")}, headers=AUTH)
    assert no_file.status_code == 400 and "'file'" in no_file.json()["detail"]
    two = client.post(
        "/uploads",
        files=[("file", ("a.bin", b"1")), ("file", ("b.bin", b"2"))],
        headers=AUTH,
    )
    assert two.status_code == 400 and "one file" in two.json()["detail"]
    truncated = client.post(
        "/uploads",
        content=b'--xyz\r\nContent-Disposition: form-data; name="file"; filename="a"\r\n\r\nabc',
        headers={**AUTH, "content-type": "multipart/form-data; boundary=xyz"},
    )
    assert truncated.status_code == 400
    no_boundary = client.post(
        "/uploads", content=b"x", headers={**AUTH, "content-type": "multipart/form-data"}
    )
    assert no_boundary.status_code == 400
    leftovers = list(settings.uploads_dir.rglob("*")) if settings.uploads_dir.exists() else []
    assert leftovers == []


# results and products -------------------------------------------------------------------


@pytest.mark.data
def test_results_and_products_of_a_completed_job(
    client: TestClient, store: JobStore, settings: Settings, data: Path, data_root: Path
) -> None:
    from autocal.io.uvh5 import write_uvh5
    from autocal.pipeline.calibrate import run_calibration
    from autocal.pipeline.config import CalibrationConfig
    from autocal.simulate.mock import SimulationConfig, simulate

    obs, _ = simulate(
        SimulationConfig(beam="dipole", channel_width_khz=4000, duration_h=4, cadence_s=900)
    )
    write_uvh5(obs, data / "zen.2458098.50000.sim.uvh5")
    accepted = _submit(client, inputs=["zen.2458098.50000.sim.uvh5"], products=["png"]).json()
    job_id = accepted["id"]
    early = client.get(f"/jobs/{job_id}/results")
    assert early.status_code == 409 and "queued" in early.json()["detail"]

    job = store.claim("test-worker")
    assert job is not None and job["id"] == job_id
    assert client.get(f"/jobs/{job_id}/results").status_code == 409  # running
    config = CalibrationConfig(**job["config"])
    result = run_calibration(config, job_products_dir(settings, job_id))
    summary = {**result.summary, "comparison": {"ratio_mean": float("nan"), "n": 3}}
    assert store.finish(
        job_id,
        "test-worker",
        job["attempts"],
        JobState.succeeded,
        result=summary,
        products=result.products,
        provenance=result.summary["provenance"],
    )

    response = client.get(f"/jobs/{job_id}/results")
    assert response.status_code == 200, response.text
    body = response.json()
    nfreq = obs.freqs.size
    assert body["antennas"] == [0] and body["pols"] == ["ee"]
    assert len(body["freqs_mhz"]) == nfreq and 109 < body["freqs_mhz"][0] < 191
    (sol,) = body["solutions"]
    for name in ("G", "sigma_G", "abs_g", "sigma_abs_g", "Trxr", "sigma_Trxr", "reduced_chi2"):
        assert len(sol[name]) == nfreq, name
    assert len(sol["flags"]) == nfreq and not any(sol["flags"])
    # simulated G = 1 and Trxr = 150 K, recovered within the quoted errors
    assert all(abs(g - 1.0) < 5 * s for g, s in zip(sol["G"], sol["sigma_G"], strict=True))
    pulls = [(t - 150.0) / s for t, s in zip(sol["Trxr"], sol["sigma_Trxr"], strict=True)]
    assert all(abs(p) < 5 for p in pulls)
    # total errors, their statistical parts and the separation of G and n over the span
    for name in ("sigma_G", "sigma_abs_g", "sigma_Trxr"):
        assert all(t >= s * (1 - 1e-9) for t, s in zip(sol[name], sol[f"{name}_stat"], strict=True))
    separation = sol["separation"]
    assert separation["antenna"] == 0 and separation["pol"] == "ee"
    assert separation["separation"] in ("weak", "adequate") and separation["message"]
    assert 0 < separation["sky_contrast"] < 1 and "150" in separation["G_if_trxr_K"]
    assert body["units"]["sigma_G_stat"] == "raw/K"
    assert body["comparison"] == {"ratio_mean": None, "n": 3}  # NaN -> null
    assert isinstance(body["summary"], dict) and body["summary"]
    # how much is flagged, and what was flagged before the fit, shown with the results
    assert body["quality"] == result.summary["quality"] and body["quality"]["status"] == "ok"
    assert body["rfi_flagging"]["applied"] is True
    assert client.get(f"/jobs/{job_id}/results", params={"antenna": 0, "pol": "ee"}).json()[
        "solutions"
    ] == [sol]
    assert client.get(f"/jobs/{job_id}/results", params={"antenna": 7}).status_code == 404
    assert client.get(f"/jobs/{job_id}/results", params={"pol": "nn"}).status_code == 404

    detail = client.get(f"/jobs/{job_id}").json()
    assert detail["state"] == "succeeded" and detail["progress"] == 1.0
    assert detail["timings"]["duration_s"] >= 0 and detail["provenance"]["inputs"]
    assert set(detail["products"]) >= {"hdf5", "png", "residuals_png", "summary"}
    hdf5 = client.get(detail["products"]["hdf5"])
    assert hdf5.status_code == 200
    assert hdf5.content == Path(result.products["hdf5"]).read_bytes()
    png = client.get(f"/jobs/{job_id}/products/png")
    assert png.headers["content-type"] == "image/png" and png.content[:4] == b"\x89PNG"
    summary_file = client.get(f"/jobs/{job_id}/products/summary")
    assert summary_file.json()["config"]["beam"] == "dipole"
    missing = client.get(f"/jobs/{job_id}/products/calfits")
    assert missing.status_code == 404 and "available" in missing.json()["detail"]
    # the job's products link lists them (it answered 404 before the 2026-11-29 audit)
    listing = client.get(detail["links"]["products"])
    assert listing.status_code == 200, listing.text
    entries = {e["name"]: e for e in listing.json()["products"]}
    assert set(entries) == set(detail["products"])
    assert entries["hdf5"]["size_bytes"] == len(hdf5.content)
    assert entries["png"]["media_type"] == "image/png"
    assert client.get(entries["png"]["url"]).content == png.content

    # a record pointing outside the job's folder is never served
    _submit(client, inputs=["zen.2458098.50000.sim.uvh5"], force=True)
    rogue = store.claim("test-worker")
    assert rogue is not None
    store.finish(
        rogue["id"],
        "test-worker",
        rogue["attempts"],
        JobState.succeeded,
        products={"hdf5": str(data.parent / "secret.txt"), "png": result.products["png"]},
    )
    for name in ("hdf5", "png"):
        refused = client.get(f"/jobs/{rogue['id']}/products/{name}")
        assert refused.status_code == 404 and "top secret" not in refused.text
    assert client.get(f"/jobs/{rogue['id']}/results").status_code == 404


# concurrency and a real server ----------------------------------------------------------


@contextmanager
def _serve(app: object) -> Iterator[str]:
    """Run ``app`` on a real uvicorn server on a free port of 127.0.0.1."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="on"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 10
    while not server.started:
        assert time.monotonic() < deadline, "uvicorn did not start"
        time.sleep(0.01)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(10)
        sock.close()


def test_real_server_health_docs_and_100_concurrent_submissions(
    settings: Settings, store: JobStore
) -> None:
    with _serve(create_app(settings, store)) as base, httpx.Client(base_url=base) as http:
        health = http.get("/health")
        assert health.status_code == 200 and health.json()["database"] == "ok"
        docs = http.get("/docs")
        assert docs.status_code == 200 and "swagger" in docs.text.lower()
        schema = http.get("/openapi.json").json()
        assert {"/jobs", "/jobs/{job_id}", "/uploads", "/nightly", "/health"} <= set(
            schema["paths"]
        )

        def submit(i: int) -> httpx.Response:
            with httpx.Client(base_url=base, timeout=60) as one:
                return one.post(
                    "/jobs", json={"inputs": [HH], "beam": "dipole", "tgnd_k": i}, headers=AUTH
                )

        with ThreadPoolExecutor(max_workers=100) as pool:
            responses = list(pool.map(submit, range(100)))
        assert [r.status_code for r in responses] == [202] * 100
        ids = {r.json()["id"] for r in responses}
        assert len(ids) == 100 and all(r.json()["created"] for r in responses)
        assert store.count() == 100

        # the same job submitted concurrently is created once
        def same(_: int) -> httpx.Response:
            with httpx.Client(base_url=base, timeout=60) as one:
                return one.post("/jobs", json={"inputs": [HH], "sky": "haslam"}, headers=AUTH)

        with ThreadPoolExecutor(max_workers=20) as pool:
            dupes = list(pool.map(same, range(20)))
        assert [r.status_code for r in dupes] == [202] * 20
        assert len({r.json()["id"] for r in dupes}) == 1
        assert sum(r.json()["created"] for r in dupes) == 1
        assert store.count() == 101


# schemathesis ----------------------------------------------------------------------------
# (schemathesis.pytest.from_fixture needs a pytest attribute that pytest 9 no longer has, so
# each operation's schemathesis strategy is driven by hypothesis directly)

OPERATIONS = [
    ("POST", "/jobs"),
    ("GET", "/jobs"),
    ("GET", "/jobs/{job_id}"),
    ("POST", "/jobs/{job_id}/cancel"),
    ("GET", "/jobs/{job_id}/results"),
    ("GET", "/jobs/{job_id}/products"),
    ("GET", "/jobs/{job_id}/products/{name}"),
    ("POST", "/uploads"),
    ("POST", "/nightly"),
    ("GET", "/health"),
    ("GET", "/antennas"),
    ("GET", "/antennas/{antenna}/history"),
    ("GET", "/nights"),
    ("GET", "/nights/{night}"),
]


#: Every answer: no server error, a documented status code, and a body, media type and
#: headers as documented for that status (what generated clients rely on).
CHECKS = [
    not_a_server_error,
    status_code_conformance,
    content_type_conformance,
    response_schema_conformance,
    response_headers_conformance,
]


def _schema(tmp_path: Path, data: Path) -> object:
    app = create_app(_settings(tmp_path, data, max_upload_bytes=10_000))
    return schemathesis.openapi.from_asgi("/openapi.json", app)


def _steer(case: schemathesis.Case) -> schemathesis.Case:
    """Point valid bodies at existing files, so that fuzzing reaches the job store."""
    if isinstance(case.body, dict):
        if "inputs" in case.body:
            case.body["inputs"] = [HH]
        if case.path == "/nightly":
            case.body["folder"] = "."
            case.body.pop("night", None)
        for key in ("beam", "reference"):
            case.body.pop(key, None)
    return case


def test_fuzzed_operations_cover_the_schema(tmp_path: Path, data: Path) -> None:
    schema = _schema(tmp_path, data)
    found = {(op.ok().method.upper(), op.ok().path) for op in schema.get_all_operations()}
    assert found == set(OPERATIONS)


@pytest.mark.parametrize(
    ("method", "path", "mode"),
    [
        (method, path, mode)
        for method, path in OPERATIONS
        for mode in (GenerationMode.POSITIVE, GenerationMode.NEGATIVE)
        # nothing to get wrong in these (no parameters)
        if path not in {"/health", "/antennas", "/nights"} or mode == GenerationMode.POSITIVE
    ],
)
def test_api_answers_as_documented_and_never_with_a_server_error(
    tmp_path: Path, data: Path, method: str, path: str, mode: GenerationMode
) -> None:
    operation = _schema(tmp_path, data)[path][method]
    strategy = operation.as_strategy(mode)
    if mode == GenerationMode.POSITIVE:
        strategy = strategy.map(_steer)

    @given(case=strategy)
    @hypothesis_settings(
        max_examples=25, deadline=None, suppress_health_check=list(HealthCheck), database=None
    )
    def check(case: schemathesis.Case) -> None:
        case.call_and_validate(headers=AUTH, checks=CHECKS)

    check()


def test_job_links_lead_to_the_operations_on_the_new_job(settings: Settings) -> None:
    spec = create_app(settings).openapi()
    links = spec["paths"]["/jobs"]["post"]["responses"]["202"]["links"]
    targets = set()
    for link in links.values():
        assert link["parameters"] == {"job_id": "$response.body#/id"}
        _, _, pointer = link["operationRef"].partition("#/paths/")
        path, method = pointer.replace("~1", "/").rsplit("/", 1)
        assert "job_id" in {p["name"] for p in spec["paths"][path][method]["parameters"]}
        targets.add((method.upper(), path))
    assert targets == {
        ("GET", "/jobs/{job_id}"),
        ("POST", "/jobs/{job_id}/cancel"),
        ("GET", "/jobs/{job_id}/results"),
    }


def test_sequences_of_calls_on_a_job_answer_as_documented(tmp_path: Path, data: Path) -> None:
    """Stateful: submit, then follow the links (get, cancel, results) in random orders."""
    machine = _schema(tmp_path, data).as_state_machine()
    seen: set[tuple[str, str, int]] = set()

    class Steered(machine):  # type: ignore[misc, valid-type]
        def before_call(self, case: schemathesis.Case) -> None:
            _steer(case)

        def get_call_kwargs(self, case: schemathesis.Case) -> dict[str, object]:
            return {"headers": AUTH}

        def validate_response(self, response, case, **kwargs):  # type: ignore[no-untyped-def]
            seen.add((case.method.upper(), case.path, response.status_code))
            case.validate_response(response, checks=CHECKS)

    Steered.run(
        settings=hypothesis_settings(
            max_examples=30,
            stateful_step_count=6,
            derandomize=True,  # the same sequences every run: the coverage asserted below
            deadline=None,
            suppress_health_check=list(HealthCheck),
            database=None,
        )
    )
    # the links were followed to an existing job (a 200 of GET /jobs/{id}), not only to
    # 404s of made-up ids; whether the random sequences also ask for its results before it
    # runs depends on the schema (the 409 of a queued or running job's results is checked
    # deterministically in test_results_and_products_of_a_completed_job)
    assert ("GET", "/jobs/{job_id}", 200) in seen


# nightly --------------------------------------------------------------------------------


def _nf(start: float, kind: str = "HH.uvh5", folder: str = "/d") -> NightFile:
    night = int(start)
    return NightFile(Path(folder) / f"zen.{start:.5f}.{kind}", night, start, kind)


def test_grouping_rules() -> None:
    step = 0.00745
    files = [_nf(2458116.3 + i * step) for i in range(4)]  # consecutive
    files += [_nf(2458116.3 + (10 + i) * step) for i in range(3)]  # after a gap of 7 steps
    files += [_nf(2458116.3 + i * step, "xx.HH.XRAA.uvh5") for i in range(2)]  # other kind
    files += [_nf(2458116.3, folder="/elsewhere")]  # other folder
    files += [_nf(2458117.3 + i * step) for i in range(2)]  # next night
    groups = group_observations(files)
    sizes = sorted((g.night, g.kind, str(g.folder), len(g.files)) for g in groups)
    assert sizes == [
        (2458116, "HH.uvh5", "/d", 3),
        (2458116, "HH.uvh5", "/d", 4),
        (2458116, "HH.uvh5", "/elsewhere", 1),
        (2458116, "xx.HH.XRAA.uvh5", "/d", 2),
        (2458117, "HH.uvh5", "/d", 2),
    ]
    # a slightly uneven spacing is not a gap
    uneven = [_nf(2458116.3 + s) for s in (0.0, 0.0074, 0.0150, 0.0350)]
    assert [len(g.files) for g in group_observations(uneven)] == [3, 1]
    assert [len(g.files) for g in group_observations(uneven[:3])] == [3]
    # three files, the last after a long gap: the gap is seen (lower median spacing)
    three = [_nf(2458116.3 + s) for s in (0.0, 0.0075, 0.0600)]
    assert [len(g.files) for g in group_observations(three)] == [2, 1]
    assert [len(g.files) for g in group_observations(three[:1])] == [1]


@pytest.mark.data
def test_nightly_on_the_real_data_is_idempotent(tmp_path: Path, data_root: Path) -> None:
    settings = _settings(tmp_path, data_root)
    store = JobStore(settings.resolved_database_url())
    autos = (data_root / "hera" / "autos").resolve()
    with TestClient(create_app(settings, store)) as client:
        first = client.post("/nightly", json={"night": 2458116, "beam": "dipole"}, headers=AUTH)
        assert first.status_code == 202, first.text
        report = first.json()
        assert report["night"] == 2458116 and report["created"] == 2 and report["existing"] == 0
        hh, xrs = report["observations"]
        assert [Path(f).name for f in hh["files"]] == [
            "zen.2458116.30448.HH.uvh5",
            "zen.2458116.31193.HH.uvh5",
            "zen.2458116.31939.HH.uvh5",
        ]
        assert hh["kind"] == "HH.uvh5" and all(Path(f).parent == autos for f in hh["files"])
        assert xrs["kind"] == "xx.HH.XRS_downselected.uvh5" and len(xrs["files"]) == 2
        job = client.get(f"/jobs/{hh['job_id']}", headers=AUTH).json()
        assert job["night"] == 2458116 and job["config"]["inputs"] == hh["files"]
        assert job["config"]["beam"] == "dipole"

        second = client.post(
            "/nightly", json={"night": 2458116, "beam": "dipole"}, headers=AUTH
        ).json()
        assert second["created"] == 0 and second["existing"] == 2
        assert [o["job_id"] for o in second["observations"]] == [hh["job_id"], xrs["job_id"]]
        # POST /jobs with the same files and settings finds the nightly job
        same = client.post("/jobs", json={"inputs": hh["files"], "beam": "dipole"}, headers=AUTH)
        assert same.json() == {**same.json(), "id": hh["job_id"], "created": False}

        forced = client.post(
            "/nightly", json={"night": 2458116, "beam": "dipole", "force": True}, headers=AUTH
        ).json()
        assert forced["created"] == 2
        assert {o["job_id"] for o in forced["observations"]}.isdisjoint(
            {hh["job_id"], xrs["job_id"]}
        )
        assert store.count() == 4

        other = client.post("/nightly", json={"night": 2458043}, headers=AUTH).json()
        assert len(other["observations"]) == 1 and len(other["observations"][0]["files"]) == 3

    # the function the CLI calls: a folder, every night in it
    report = submit_nightly(store, settings, folder="hera/autos", options={"beam": "dipole"})
    assert report["night"] is None
    by_night: dict[int, list[int]] = {}
    for obs in report["observations"]:
        by_night.setdefault(obs["night"], []).append(len(obs["files"]))
    assert by_night[2458116] == [3, 2] and by_night[2458043] == [3]
    assert sorted(by_night[2458098]) == [1, 1, 1]  # downsample, subband, HH_downselected
    assert by_night[2458042] == [2]  # uvh5_downselected names count too
    assert 2458099 not in by_night  # Miriad folders are not UVH5 files
    assert report["existing"] == 2  # the 2458116 dipole jobs already exist
    groups = find_observations(settings, night=2458116)
    assert [len(g.files) for g in groups] == [3, 2]


def test_nightly_errors(client: TestClient, tmp_path: Path) -> None:
    nothing = client.post("/nightly", json={}, headers=AUTH)
    assert nothing.status_code == 422 and "night" in nothing.json()["detail"]
    absent = client.post("/nightly", json={"night": 2450000}, headers=AUTH)
    assert absent.status_code == 404 and "zen.2450000" in absent.json()["detail"]
    outside = client.post("/nightly", json={"folder": str(tmp_path)}, headers=AUTH)
    assert outside.status_code == 403
    bad = client.post(
        "/nightly", json={"night": 2458116, "freq_range_mhz": [1e8, 2e8]}, headers=AUTH
    )
    assert bad.status_code == 422 and "freq_range_mhz" in bad.json()["detail"]
    unknown = client.post("/nightly", json={"night": 2458116, "nigth": 1}, headers=AUTH)
    assert unknown.status_code == 422 and "nigth" in unknown.json()["detail"]
    ok = client.post("/nightly", json={"folder": ".", "beam": "dipole"}, headers=AUTH).json()
    assert [o["night"] for o in ok["observations"]] == [2458116, 2458117]
    assert [len(o["files"]) for o in ok["observations"]] == [2, 1]
