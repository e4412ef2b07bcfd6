"""What a live audit of the service found (2026-11-29), each answered before any work.

Every test here failed before its fix: an empty ``pols`` accepted and crashing the job,
options that do nothing accepted silently, unknown antennas, junk references and junk
uploads found out only by the worker, a form body answered "not a dict", the products link
dead, the documentation page blank offline, server paths shown to anonymous readers of a
night, a worker taking its own starved job for a dead one.
"""

from __future__ import annotations

import re
import time
import warnings
from collections.abc import Iterator
from pathlib import Path

import pytest

from autocal.service.app import create_app
from autocal.service.settings import Settings
from autocal.service.store import JobState, JobStore
from tests.service.tiny_uvh5 import ANTENNAS, write_tiny_uvh5

with warnings.catch_warnings():
    warnings.filterwarnings("ignore", message=".*httpx2")
    from fastapi.testclient import TestClient

TOKEN = "test-token-0123456789abcdef-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
NAME = "zen.2458116.30448.HH.uvh5"


@pytest.fixture
def data(tmp_path: Path) -> Path:
    folder = tmp_path / "data"
    write_tiny_uvh5(folder / NAME)
    (folder / "junk.calfits").write_bytes(b"SIMPLE  = not really a calibration")
    return folder


@pytest.fixture
def settings(tmp_path: Path, data: Path) -> Settings:
    return Settings(
        state_dir=tmp_path / "state",
        database_url=f"sqlite:///{tmp_path / 'jobs.sqlite'}",
        data_roots=[data],
        api_token=TOKEN,
        auth_failures=1_000_000,
    )


@pytest.fixture
def store(settings: Settings) -> Iterator[JobStore]:
    store = JobStore(settings.resolved_database_url())
    yield store
    store.engine.dispose()


@pytest.fixture
def client(settings: Settings, store: JobStore) -> Iterator[TestClient]:
    with TestClient(create_app(settings, store)) as test_client:
        yield test_client


def _submit(client: TestClient, **body: object):
    body.setdefault("inputs", [NAME])
    body.setdefault("beam", "dipole")
    return client.post("/jobs", json=body, headers=AUTH)


def _refused(response, field: str) -> str:
    assert response.status_code == 422, response.text
    assert [e["field"] for e in response.json()["errors"]] == [f"body.{field}"], response.text
    return response.json()["detail"]


def test_an_empty_pols_list_is_refused(client: TestClient, store: JobStore) -> None:
    for kind in ("calibrate", "diagnose"):
        response = _submit(client, kind=kind, pols=[])
        assert response.status_code == 422 and "pols" in response.text, response.text
    assert store.count("queued") == 0


@pytest.mark.parametrize(
    ("body", "field", "words"),
    [
        ({"order": 3}, "order", 'needs model="legendre"'),
        ({"trxr_prior_sigma_k": 5}, "trxr_prior_sigma_k", "give the prior too"),
        ({"weights": "identity", "passes": 2}, "passes", 'weights="identity"'),
        ({"weights": "identity", "inflate_errors": False}, "inflate_errors", "always scale"),
        ({"edges_bin": 8}, "edges_bin", "inputs are uvh5 files"),
        ({"products": []}, "products", "name at least one"),
        (
            {"kind": "diagnose", "trxr_prior_sigma_k": 5},
            "trxr_prior_sigma_k",
            "give the prior too",
        ),
        ({"kind": "diagnose", "max_steps": 0, "alpha": 0.01}, "alpha", "max_steps=0"),
    ],
)
def test_options_that_do_nothing_are_refused_as_the_command_line_refuses_them(
    client: TestClient, body: dict, field: str, words: str
) -> None:
    assert words in _refused(_submit(client, **body), field)


def test_selections_the_file_cannot_satisfy_are_refused_at_submission(
    client: TestClient,
) -> None:
    for kind in ("calibrate", "diagnose"):
        detail = _refused(_submit(client, kind=kind, antennas=[999]), "antennas")
        assert "999" in detail and str(list(ANTENNAS)) in detail
        detail = _refused(_submit(client, kind=kind, lst_range_h=[20.0, 21.0]), "lst_range_h")
        assert "holds no integration" in detail
    assert _submit(client, antennas=[23]).status_code == 202


def test_a_reference_that_is_not_a_calibration_is_refused_before_the_fit(
    client: TestClient,
) -> None:
    detail = _refused(_submit(client, reference=["junk.calfits"]), "reference")
    assert "junk.calfits" in detail and "corrupt or truncated" in detail


def test_empty_and_truncated_uploads_are_refused_and_nothing_is_kept(
    client: TestClient, settings: Settings, data: Path
) -> None:
    whole = (data / NAME).read_bytes()
    for payload, words in ((b"", "is empty"), (whole[: len(whole) // 3], "truncated")):
        response = client.post("/uploads", files={"file": (NAME, payload)}, headers=AUTH)
        assert response.status_code == 422 and words in response.json()["detail"], response.text
    assert not any(settings.uploads_dir.iterdir())
    assert client.post("/uploads", files={"file": (NAME, whole)}, headers=AUTH).status_code == 201


def test_a_body_that_is_not_json_gets_415_or_a_hint(client: TestClient) -> None:
    form = client.post("/jobs", data={"inputs": NAME}, headers=AUTH)  # a form
    text = client.post("/jobs", content="inputs", headers={**AUTH, "content-type": "text/plain"})
    for response in (form, text):
        assert response.status_code == 415, response.text
        assert "application/json" in response.json()["detail"]
    json_type = {**AUTH, "content-type": "application/json"}
    bad_utf8 = client.post("/jobs", content=b'{"inputs": ["\xff"]}', headers=json_type)
    assert bad_utf8.status_code in (400, 422), bad_utf8.text
    assert "parsing the body" not in bad_utf8.text and "JSON" in bad_utf8.json()["detail"]


def test_the_job_list_refuses_an_unknown_kind(client: TestClient) -> None:
    response = client.get("/jobs", params={"kind": "x"})
    assert response.status_code == 422 and "kind" in response.text


def test_misnamed_upload_ids_and_beams_get_messages_that_say_what_is_expected(
    client: TestClient,
) -> None:
    response = _submit(client, inputs=["upload:nonexistent"])
    assert response.status_code == 400 and "not an upload id" in response.json()["detail"]
    response = _submit(client, beam="nope")
    assert response.status_code == 400
    assert "edges-low" in response.json()["detail"] and "hera" in response.json()["detail"]


def test_products_of_a_job_that_has_not_succeeded_answer_409(client: TestClient) -> None:
    job_id = _submit(client).json()["id"]
    for path in (f"/jobs/{job_id}/products", f"/jobs/{job_id}/products/hdf5"):
        response = client.get(path)
        assert response.status_code == 409 and "queued" in response.json()["detail"]


def test_the_documentation_pages_need_no_internet_and_render_the_schema(
    client: TestClient, settings: Settings, store: JobStore
) -> None:
    version = client.get("/openapi.json").json()["openapi"]
    for page_path in ("/docs", "/redoc"):
        page = client.get(page_path)
        assert page.status_code == 200
        assert not re.search(r"""(src|href)=["']https?://""", page.text), page.text
    bundle = client.get("/docs/static/swagger-ui-bundle.js")
    assert bundle.status_code == 200
    # a Swagger UI that renders the schema's version (Swagger UI 4 refused 3.1: a review)
    assert version.startswith("3.1") and b"isOAS31" in bundle.content
    for name in ("swagger-ui.css", "redoc.standalone.js", "favicon.png"):
        assert client.get(f"/docs/static/{name}").status_code == 200
    for name in ("..%2F..%2Fsettings.py", "index.html"):
        assert client.get(f"/docs/static/{name}").status_code == 404
    with TestClient(create_app(settings, store), root_path="/autocal") as behind_a_proxy:
        page = behind_a_proxy.get("/docs").text
        assert "'/autocal/openapi.json'" in page or '"/autocal/openapi.json"' in page
        assert "/autocal/docs/static/swagger-ui-bundle.js" in page


def test_a_nights_failed_jobs_show_no_server_paths_to_anonymous_readers(
    client: TestClient, store: JobStore, data: Path
) -> None:
    path = str((data / NAME).resolve())
    job, _ = store.submit({"inputs": [path], "beam": "dipole"}, night=2458116, max_attempts=1)
    claimed = store.claim("w")
    assert claimed is not None and claimed["id"] == job["id"]
    store.finish(job["id"], "w", claimed["attempts"], JobState.failed, error=f"{path}: broken")
    anonymous = client.get("/nights/2458116")
    assert anonymous.status_code == 200, anonymous.text
    assert str(data.resolve()) not in anonymous.text and NAME in anonymous.text
    assert str(data.resolve()) not in client.get("/ui/nights/2458116").text
    assert path in client.get("/nights/2458116", headers=AUTH).text


def test_a_worker_never_takes_its_own_running_job_for_a_dead_one(store: JobStore) -> None:
    """A CI run under load (2026-11-29): a worker starved of CPU for 5.5 s re-queued its own
    job as stale (stale_after 3 s), cancelled itself and ran the job a third time."""
    job, _ = store.submit({"inputs": ["x"]}, max_attempts=1)
    claimed = store.claim("w")
    assert claimed is not None
    time.sleep(0.05)  # its last heartbeat is now older than a stale threshold of 0 s
    assert store.recover_stale(0.0, alive=(job["id"], claimed["attempts"])) == []
    assert store.get(job["id"])["state"] == "running"
    assert store.recover_stale(0.0, alive=("another job", 1))[0]["id"] == job["id"]
    assert store.get(job["id"])["state"] == "failed"  # max_attempts=1: a dead worker's job


def test_a_nightly_submission_reports_a_refused_observation_and_submits_the_rest(
    client: TestClient, data: Path
) -> None:
    """A review (2026-11-29): a truncated file in one observation stopped the whole night
    after the first job (the submission checks raised out of the loop)."""
    write_tiny_uvh5(data / "night" / "zen.2458117.30000.HH.uvh5")
    later = data / "night" / "zen.2458118.30000.HH.uvh5"  # another night: its own job
    whole = write_tiny_uvh5(later).read_bytes()
    later.write_bytes(whole[: len(whole) // 3])  # still being copied
    answer = client.post("/nightly", json={"folder": "night", "beam": "dipole"}, headers=AUTH)
    assert answer.status_code == 202, answer.text
    body = answer.json()
    states = {Path(o["files"][0]).name: o for o in body["observations"]}
    assert states["zen.2458117.30000.HH.uvh5"]["job_id"] and body["created"] == 1
    refused = states["zen.2458118.30000.HH.uvh5"]
    assert refused["job_id"] is None and refused["state"] == "refused"
    assert "truncated" in refused["error"] or "corrupt" in refused["error"]
    assert body["refused"] == 1
    # what is not about one observation's files is the whole request's error (a review)
    for extra, words in (
        ({"order": 2}, "legendre"),
        ({"sky": "uniform:100"}, "same in every direction"),
        ({"reference": ["junk.calfits"]}, "corrupt or truncated"),
    ):
        body = {"folder": "night", "beam": "dipole", "force": True, **extra}
        answer = client.post("/nightly", json=body, headers=AUTH)
        assert answer.status_code == 422 and words in answer.text, (extra, answer.text)
    # and so is a night whose every observation is refused
    only_bad = data / "bad"
    only_bad.mkdir()
    (only_bad / later.name).write_bytes(later.read_bytes())
    answer = client.post("/nightly", json={"folder": "bad", "beam": "dipole"}, headers=AUTH)
    assert answer.status_code == 422 and "every observation (1) was refused" in answer.text


def test_a_negative_receiver_prior_is_accepted(client: TestClient) -> None:
    """EDGES' Q has Trxr ~ -302 K (a review of a refusal tried and reverted)."""
    from autocal.pipeline.config import CalibrationConfig

    assert CalibrationConfig(inputs=["x"], trxr_prior=-302.0).trxr_prior == -302.0
    assert _submit(client, trxr_prior=-302.0).status_code == 202
