"""Named tokens, the start-up check, read authentication, failed-auth limiting, and what
anonymous readers see (autocal.service.tokens, auth, job_views)."""

from __future__ import annotations

import subprocess
import sys
import warnings
from collections.abc import Iterator
from pathlib import Path

import pytest

from autocal.service.app import create_app
from autocal.service.settings import Settings
from autocal.service.store import JobStore
from autocal.service.tokens import FailedAuthLimiter, TokenConfigError, named_tokens
from tests.service.tiny_uvh5 import write_tiny_uvh5

with warnings.catch_warnings():
    warnings.filterwarnings("ignore", message=".*httpx2")
    from fastapi.testclient import TestClient

ALICE = "alice-token-0123456789abcdef0123456789"
NIGHTLY = "nightly-token-0123456789abcdef01234567"
HH = "zen.2458116.30448.HH.uvh5"


def _settings(tmp_path: Path, **kwargs: object) -> Settings:
    data = tmp_path / "data"
    data.mkdir(exist_ok=True)
    if not (data / HH).exists():
        write_tiny_uvh5(data / HH)
    values: dict[str, object] = {
        "state_dir": tmp_path / "state",
        "database_url": f"sqlite:///{tmp_path / 'jobs.sqlite'}",
        "data_roots": [data],
        "api_tokens": f"alice={ALICE}, nightly={NIGHTLY}",
    }
    values.update(kwargs)
    return Settings(**values)


@pytest.fixture
def settings(tmp_path: Path) -> Settings:
    return _settings(tmp_path)


@pytest.fixture
def client(settings: Settings) -> Iterator[TestClient]:
    store = JobStore(settings.resolved_database_url())
    with TestClient(create_app(settings, store)) as test_client:
        yield test_client
    store.engine.dispose()


def _bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


# the tokens ----------------------------------------------------------------------------


def test_named_tokens_from_the_list_the_file_and_the_single_token(tmp_path: Path) -> None:
    file = tmp_path / "tokens"
    file.write_text(f"# operators\nbob = {'b' * 40}  # bob's laptop\n\n")
    settings = _settings(tmp_path, api_tokens_file=file, api_token="d" * 32)
    assert named_tokens(settings) == {
        "alice": ALICE,
        "nightly": NIGHTLY,
        "bob": "b" * 40,
        "default": "d" * 32,
    }


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"api_tokens": "alice=x"}, "has 1 characters; tokens need at least 32"),
        ({"api_token": "secret"}, "'default' has 6 characters"),
        ({"api_tokens": f"{ALICE}"}, "not name=token"),
        ({"api_tokens": f"a b={ALICE}"}, "token name 'a b'"),
        ({"api_tokens": f"a={ALICE},a={NIGHTLY}"}, "given twice"),
        ({"api_tokens": f"a={ALICE},b={ALICE}"}, "also given another name"),
        ({"api_tokens": "", "read_auth": True}, "AUTOCAL_READ_AUTH=1 needs at least one"),
        ({"api_tokens_file": Path("/nonexistent/tokens")}, "cannot read it"),
    ],
)
def test_unusable_tokens_refuse_to_start(tmp_path: Path, values: dict, message: str) -> None:
    settings = _settings(tmp_path, **values)
    with pytest.raises(TokenConfigError, match=message.replace("(", r"\(")):
        create_app(settings, JobStore(settings.resolved_database_url()))


def test_autocal_serve_exits_with_one_line_on_a_short_token(tmp_path: Path) -> None:
    env = {
        "PATH": "/usr/bin:/bin",
        "AUTOCAL_STATE_DIR": str(tmp_path),
        "AUTOCAL_API_TOKEN": "short",
        "AUTOCAL_DATA_ROOTS": str(tmp_path),
        "PYTHONPATH": str(Path(__file__).resolve().parents[2]),
    }
    result = subprocess.run(
        [sys.executable, "-m", "autocal", "serve", "--port", "1"],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode != 0
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    assert "AUTOCAL_MIN_TOKEN_LENGTH" in lines[0]
    assert "Traceback" not in result.stderr


# authentication ------------------------------------------------------------------------


def test_each_named_token_writes_and_the_job_records_its_name(client: TestClient) -> None:
    body = {"inputs": [HH], "beam": "dipole"}
    first = client.post("/jobs", json=body, headers=_bearer(NIGHTLY))
    assert first.status_code == 202, first.text
    detail = client.get(first.json()["links"]["self"], headers=_bearer(ALICE)).json()
    assert detail["submitted_by"] == "nightly"
    second = client.post("/jobs", json={**body, "force": True}, headers=_bearer(ALICE))
    assert (
        client.get(f"/jobs/{second.json()['id']}", headers=_bearer(ALICE)).json()["submitted_by"]
        == "alice"
    )


def test_failed_authentications_are_limited_per_client(tmp_path: Path) -> None:
    settings = _settings(tmp_path, auth_failures=5, auth_window_s=600)
    with TestClient(create_app(settings, JobStore(settings.resolved_database_url()))) as client:
        codes = [
            client.post("/jobs", json={}, headers=_bearer(f"guess-{i}")).status_code
            for i in range(8)
        ]
        assert codes == [401] * 5 + [429] * 3
        refused = client.post("/jobs", json={"inputs": [HH]}, headers=_bearer(ALICE))
        assert refused.status_code == 429  # even the right token waits: no more guesses
        assert 1 <= int(refused.headers["Retry-After"]) <= 600
        assert "retry in" in refused.json()["detail"]
        # reads with a wrong token count too; anonymous reads do not
        assert client.get("/jobs").status_code == 200


def test_the_limiter_forgets_failures_after_the_window() -> None:
    now = [0.0]
    limiter = FailedAuthLimiter(3, 60.0, clock=lambda: now[0])
    for _ in range(3):
        assert limiter.retry_after("10.0.0.1") is None
        limiter.failed("10.0.0.1")
    assert limiter.retry_after("10.0.0.1") == 60
    assert limiter.retry_after("10.0.0.2") is None  # per client
    now[0] = 59.5
    assert limiter.retry_after("10.0.0.1") == 1
    now[0] = 60.5
    assert limiter.retry_after("10.0.0.1") is None


def test_read_auth_makes_reads_need_a_token(tmp_path: Path) -> None:
    settings = _settings(tmp_path, read_auth=True)
    with TestClient(create_app(settings, JobStore(settings.resolved_database_url()))) as client:
        assert client.get("/jobs").status_code == 401
        assert client.get("/jobs/abc").status_code == 401
        assert client.get("/jobs", headers=_bearer(ALICE)).status_code == 200
        assert client.get("/health").status_code == 200  # probes stay open


def test_a_wrong_token_on_a_read_is_refused_not_anonymous(client: TestClient) -> None:
    response = client.get("/jobs", headers=_bearer("wrong-" * 8))
    assert response.status_code == 401


# what an anonymous reader sees ---------------------------------------------------------


def test_anonymous_reads_hide_server_paths_worker_and_log(
    client: TestClient, settings: Settings
) -> None:
    accepted = client.post("/jobs", json={"inputs": [HH], "beam": "dipole"}, headers=_bearer(ALICE))
    job_id = accepted.json()["id"]
    store: JobStore = client.app.state.store  # type: ignore[attr-defined]
    worker = "node7.example:4242:a1b2c3"
    claimed = store.claim(worker)
    data = settings.resolved_data_roots()[0]
    store.append_log(job_id, f"reading {data / HH}")
    store.append_log(job_id, "loaded /opt/autocal/lib/beam.fits")
    store.finish(
        job_id,
        worker,
        claimed["attempts"],
        __import__("autocal.service.store", fromlist=["JobState"]).JobState.failed,
        error=f"worker {worker} failed on {data / HH} with /usr/lib/x.so and "
        f"{settings.state_dir.resolve() / 'jobs' / job_id}/summary.json",
        provenance={"inputs": {str(data / HH): "ab12"}, "service": {"worker": worker}},
    )
    full = client.get(f"/jobs/{job_id}", headers=_bearer(ALICE)).json()
    assert full["worker"] == worker
    assert any(str(data) in line for line in full["log_tail"])
    anonymous = client.get(f"/jobs/{job_id}").json()
    text = str(anonymous)
    assert str(data) not in text and "/opt/autocal" not in text and "/usr/lib" not in text
    assert str(settings.state_dir.resolve()) not in text
    assert "node7" not in text and "4242" not in text
    assert anonymous["worker"] is None and anonymous["submitted_by"] is None
    assert anonymous["log_tail"] == [] and anonymous["log_hidden"] is True
    assert anonymous["config"]["inputs"] == [HH]  # relative to the data root, resubmittable
    assert HH in anonymous["error"] and f"<state>/jobs/{job_id}/summary.json" in anonymous["error"]
    assert ".../x.so" in anonymous["error"]
    assert anonymous["provenance"] == {"inputs": {HH: "ab12"}, "service": {"worker": "a worker"}}
    listed = client.get("/jobs").json()["items"][0]
    assert "node7" not in str(listed) and str(data) not in str(listed)
