"""Checks at submission (autocal.service.submission_checks) through ``POST /jobs``: a
frequency range outside the data's band, the same file twice, a sky that flags every
channel are 422s naming the field, before anything is queued."""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from autocal.service.app import create_app
from autocal.service.settings import Settings
from autocal.service.store import JobStore
from tests.io.test_uvh5 import synthetic_observation
from tests.io.test_uvh5_writer import part_writer

with warnings.catch_warnings():
    warnings.filterwarnings("ignore", message=".*httpx2")
    from fastapi.testclient import TestClient

TOKEN = "test-token-0123456789abcdef-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
NAME = "zen.2458098.30000.HH.uvh5"


@pytest.fixture
def data(tmp_path: Path) -> Path:
    """A data root with one real UVH5 file (8 channels, 120.0-120.7 MHz) and a fake one."""
    folder = tmp_path / "data"
    folder.mkdir()
    obs = synthetic_observation(ntime=4)
    with part_writer(obs, folder / NAME) as writer:
        writer.write(0, obs.data, np.zeros(obs.shape, bool), np.ones(obs.shape))
    (folder / "zen.2458098.40000.HH.uvh5").write_bytes(b"not really uvh5")
    return folder


@pytest.fixture
def client(tmp_path: Path, data: Path) -> Iterator[TestClient]:
    settings = Settings(
        state_dir=tmp_path / "state",
        database_url=f"sqlite:///{tmp_path / 'jobs.sqlite'}",
        data_roots=[data],
        api_token=TOKEN,
    )
    store = JobStore(settings.resolved_database_url())
    with TestClient(create_app(settings, store)) as test_client:
        yield test_client
    store.engine.dispose()


def _submit(client: TestClient, **body: object):
    body.setdefault("inputs", [NAME])
    body.setdefault("beam", "dipole")
    return client.post("/jobs", json=body, headers=AUTH)


def _refused(response, field: str) -> str:
    assert response.status_code == 422, response.text
    assert [e["field"] for e in response.json()["errors"]] == [f"body.{field}"]
    return response.json()["detail"]


@pytest.mark.parametrize("kind", ["calibrate", "diagnose"])
def test_a_frequency_range_outside_the_band_is_refused_with_the_band(
    client: TestClient, kind: str
) -> None:
    detail = _refused(_submit(client, kind=kind, freq_range_mhz=[150, 160]), "freq_range_mhz")
    assert "120-120.684 MHz (8 channels)" in detail and NAME in detail
    assert client.get("/jobs").json()["count"] == 0
    inside = _submit(client, kind=kind, freq_range_mhz=[120.1, 120.5])
    assert inside.status_code == 202, inside.text


def test_an_unreadable_file_is_refused_with_the_readers_message(client: TestClient) -> None:
    """A live audit (2026-11-29): a text file, an empty or a truncated UVH5 file were
    accepted (202) and failed later in the worker."""
    for kind in ("calibrate", "diagnose"):
        response = _submit(client, kind=kind, inputs=["zen.2458098.40000.HH.uvh5"])
        detail = _refused(response, "inputs")
        assert "is not an HDF5 file, so not UVH5" in detail


def test_the_same_file_named_twice_is_refused(client: TestClient, data: Path) -> None:
    for kind in ("calibrate", "diagnose"):
        detail = _refused(_submit(client, kind=kind, inputs=[NAME, str(data / NAME)]), "inputs")
        assert "items 0, 1 are the same file" in detail


@pytest.mark.parametrize("kind", ["calibrate", "diagnose"])
@pytest.mark.parametrize("sky", ["uniform:300", "uniform", "powerlaw:uniform@150:-2.5"])
def test_a_sky_constant_in_time_is_refused_unless_a_prior_separates_trxr(
    client: TestClient, sky: str, kind: str
) -> None:
    detail = _refused(_submit(client, sky=sky, kind=kind), "sky")
    assert "every channel would be flagged" in detail
    accepted = _submit(client, sky=sky, trxr_prior=100.0, kind=kind)
    assert accepted.status_code == 202, accepted.text
