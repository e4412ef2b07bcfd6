"""Diagnose jobs: ``POST /jobs`` with ``kind: "diagnose"``, the worker, results and products.

A small simulated observation (dipole beam, power-law sky, 1 MHz channels, 10-minute
cadence over 24 h, low noise ``dnu dt = 1e6``) hides a linear gain drift; it is submitted
through the API, run by an in-process worker and must come back named ``gain_drift``.
Also: validation (422 naming the field, 403 outside the data roots), a failing input
(failed with a one-line reason, no products), cancellation, and the all-or-nothing
staging of :func:`autocal.diagnosis.run.run_diagnosis`.
"""

from __future__ import annotations

import json
import os
import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pydantic import ValidationError

from autocal.diagnosis.run import DiagnoseConfig, product_name, read_summary, run_diagnosis
from autocal.service.app import create_app
from autocal.service.settings import Settings
from autocal.service.store import JobStore
from autocal.service.worker import Worker

with warnings.catch_warnings():  # starlette's notice about httpx2, raised at import
    warnings.filterwarnings("ignore", message=".*httpx2")
    from fastapi.testclient import TestClient

TOKEN = "test-token-0123456789abcdef-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
SKY = "powerlaw:gsm2008@408:-2.55"
SIM = "zen.2458098.50000.sim.uvh5"
JUNK = "zen.2458099.10000.HH.uvh5"
#: Options of a fast diagnosis of the simulated observation.
FAST = {"sky": SKY, "beam": "dipole", "nside": 32}


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A data root: the simulated observation with a gain drift, a junk file, a folder."""
    from autocal.io.uvh5 import write_uvh5
    from autocal.simulate.mock import SimulationConfig, simulate

    root = tmp_path_factory.mktemp("data")
    obs, _ = simulate(
        SimulationConfig(
            sky=SKY,
            beam="dipole",
            channel_width_khz=1000,
            cadence_s=600,
            nside=32,
            noise_dnu_hz=1e6,
            gain="a",
        )
    )
    write_uvh5(obs, root / SIM)
    (root / JUNK).write_bytes(np.random.default_rng(0).bytes(4096))
    (root / "miriad.uv").mkdir()
    (root.parent / "secret.uvh5").write_bytes(b"outside the data roots")
    return root


@pytest.fixture
def settings(tmp_path: Path, data: Path) -> Settings:
    return Settings(
        state_dir=tmp_path / "state",
        database_url=f"sqlite:///{tmp_path / 'jobs.sqlite'}",
        data_roots=[data],
        api_token=TOKEN,
        heartbeat_s=0.1,
        stale_after_s=30,
        dask_scheduler="",
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


@pytest.fixture
def worker(settings: Settings, store: JobStore) -> Worker:
    return Worker(store, settings, worker_id="inproc")


def _submit(client: TestClient, **body: Any) -> Any:
    body.setdefault("kind", "diagnose")
    body.setdefault("inputs", [SIM])
    for key, value in FAST.items():
        body.setdefault(key, value)
    return client.post("/jobs", json=body, headers=AUTH)


def _strict(text: str) -> Any:
    """Parse JSON refusing NaN and infinities."""

    def refuse(constant: str) -> None:
        raise AssertionError(f"non-standard JSON constant {constant}")

    return json.loads(text, parse_constant=refuse)


def _files(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if p.is_file()] if folder.exists() else []


# the job through the API and the worker --------------------------------------------------


def test_diagnose_job_end_to_end(
    client: TestClient, store: JobStore, worker: Worker, settings: Settings, data: Path
) -> None:
    from autocal.diagnosis.effects import time_basis
    from autocal.io.uvh5 import read_uvh5
    from autocal.simulate.mock import gain_profile

    response = _submit(client)
    assert response.status_code == 202, response.text
    job_id = response.json()["id"]
    assert response.json()["created"] is True
    job = client.get(f"/jobs/{job_id}", headers=AUTH).json()
    assert job["kind"] == "diagnose" and job["state"] == "queued"
    assert job["config"]["inputs"] == [str((data / SIM).resolve())]
    DiagnoseConfig(**job["config"])  # the stored configuration is a valid DiagnoseConfig

    # dedupe on kind + inputs + options
    same = _submit(client, inputs=[str(data / SIM)]).json()
    assert same["created"] is False and same["id"] == job_id
    other = _submit(client, bic_threshold=25).json()
    assert other["created"] is True and other["id"] != job_id
    calibration = client.post("/jobs", json={"inputs": [SIM], "beam": "dipole"}, headers=AUTH)
    assert calibration.status_code == 202 and calibration.json()["id"] != job_id
    listed = client.get("/jobs", params={"kind": "diagnose"}).json()
    assert {j["id"] for j in listed["items"]} == {job_id, other["id"]}
    assert {j["kind"] for j in listed["items"]} == {"diagnose"}
    assert client.get("/jobs", params={"kind": "calibrate"}).json()["count"] == 1
    for extra in (other["id"], calibration.json()["id"]):  # run only the first one
        assert client.post(f"/jobs/{extra}/cancel", headers=AUTH).status_code == 202
    early = client.get(f"/jobs/{job_id}/results")
    assert early.status_code == 409 and "queued" in early.json()["detail"]

    assert worker.run_once() is True
    job = client.get(f"/jobs/{job_id}", headers=AUTH).json()
    assert job["state"] == "succeeded", job
    assert job["progress"] == 1.0 and job["error"] is None
    # the hidden effect is a linear gain drift: it must be named as such
    assert job["result"]["effects"][:1] == ["gain_drift"], job["result"]["steps"]
    assert any("100% done: gain_drift" in line for line in job["log_tail"])
    assert job["result"]["final_gap"]["reduced_chi2"] is not None
    prov = job["provenance"]
    path = str((data / SIM).resolve())
    assert prov["inputs"][path] and prov["input_bytes"][path] == (data / SIM).stat().st_size
    assert prov["autocal_version"] and prov["service"]["worker"] == "inproc"
    assert prov["integrity"][path]["status"] == "unchecked"  # written without HDF5 checksums
    assert set(job["result"]["timings_s"]) >= {"read_s", "templates_s", "diagnose_s", "total_s"}

    response = client.get(f"/jobs/{job_id}/results")
    assert response.status_code == 200, response.text
    body = _strict(response.text)  # NaN -> null
    assert body["kind"] == "diagnose" and body["job_id"] == job_id
    assert body["effects"][0] == "gain_drift"
    assert body["absorbed"] == [] and "gain_drift" not in body["negligible"]
    assert body["below_model_accuracy"] == []  # the field is served (a named effect: empty)
    assert body["indistinguishable"] is None and body["config"]["decisive_margin"] > 0
    step = body["steps"][0]
    assert step["step"] == 1 and step["name"] == "gain_drift"
    assert step["statistic"] > body["config"]["bic_threshold"]
    assert step["delta"] > 0
    assert step["gap_after"]["reduced_chi2"] < step["gap_before"]["reduced_chi2"]
    assert body["final_gap"]["reduced_chi2"] < body["initial_gap"]["reduced_chi2"]
    # band edges and RFI were flagged before the fits, as a calibration flags them
    assert body["rfi_flagging"]["applied"] is True
    assert body["rfi_flagging"] == job["result"]["rfi_flagging"]
    # what the accepted effect does to the calibration products, against the total errors
    impact = step["details"]["product_impact"]
    assert impact["G"]["median_change_over_sigma"] > 0 and "Trxr" in impact
    assert body["product_change"]["G"]["channels"] == impact["G"]["channels"]
    # what the search left untested (nothing on this small file) is read from diagnosis.json
    doc = json.loads((settings.products_dir / job_id / "attempt-1" / "diagnosis.json").read_text())
    assert body["not_tested"] == doc["not_tested"]
    # the drift coefficients are the projection of the true gain on the effect's basis
    obs = read_uvh5(data / SIM)
    order = int(step["parameters"]["order"]["value"])
    basis = np.vstack([np.ones(obs.ntime), time_basis(obs.lsts, order)])
    coeffs = np.linalg.lstsq(basis.T, gain_profile("a", obs.lsts), rcond=None)[0]
    for k in range(1, order + 1):
        got = step["parameters"][f"d_{k}"]
        assert got["sigma"] > 0
        assert abs(got["value"] - coeffs[k] / coeffs[0]) < 5 * got["sigma"], (k, got)
    assert client.get(f"/jobs/{job_id}/results", params={"antenna": 0}).status_code == 422

    # products: every file of the attempt folder, downloadable, nothing left in staging
    out = settings.products_dir / job_id / "attempt-1"
    assert sorted(p.name for p in out.iterdir()) == sorted(
        Path(p).name for p in job["result"]["products"].values()
    )
    names = set(job["products"])
    assert {"diagnosis", "summary", "summary_txt"} <= names
    assert any(n.startswith("residuals") and n.endswith("_png") for n in names)
    diagnosis = client.get(f"/jobs/{job_id}/products/diagnosis")
    assert diagnosis.headers["content-type"] == "application/json"
    assert diagnosis.json()["effects"] == body["effects"]
    text = client.get(f"/jobs/{job_id}/products/summary_txt")
    assert text.headers["content-type"].startswith("text/plain") and "gain_drift" in text.text
    png_name = next(n for n in names if n.endswith("_png"))
    png = client.get(f"/jobs/{job_id}/products/{png_name}")
    assert png.headers["content-type"] == "image/png" and png.content[:4] == b"\x89PNG"
    summary = client.get(f"/jobs/{job_id}/products/summary").json()
    assert summary["kind"] == "diagnose" and summary["config"]["sky"] == SKY


# validation ------------------------------------------------------------------------------


def test_bad_options_are_422_naming_the_field(client: TestClient) -> None:
    for body, field, word in [
        ({"alpha": 2}, "body.alpha", "alpha"),
        ({"max_steps": -1}, "body.max_steps", "max_steps"),
        ({"colour": "blue"}, "body.colour", "unknown field"),
        ({"model": "legendre"}, "body.model", "option of kind 'calibrate'"),
        ({"products": ["png"]}, "body.products", "option of kind 'calibrate'"),
        ({"kind": "calibrate", "bic_threshold": 5}, "body.bic_threshold", "kind 'diagnose'"),
        ({"freq_range_mhz": [100e6, 200e6]}, "body.freq_range_mhz", "MHz, not Hz"),
        ({"lst_range_h": [0, 30]}, "body.lst_range_h", "lst_range_h"),
        ({"nside": 48}, "body.nside", "power of two"),
        ({"pols": ["xy"]}, "body.pols.0", "pols"),
    ]:
        response = _submit(client, **body)
        assert response.status_code == 422, (body, response.text)
        answer = response.json()
        assert field in {e["field"] for e in answer["errors"]}, (body, answer)
        assert word in answer["detail"], (body, answer)
        assert "Traceback" not in response.text
    sky = _submit(client, sky="gsm2099")
    assert sky.status_code == 422 and "gsm2099" in sky.json()["detail"]
    folder = _submit(client, inputs=["miriad.uv"])
    assert folder.status_code == 422 and "UVH5" in folder.json()["detail"]
    assert client.get("/jobs").json()["count"] == 0


def test_paths_outside_the_data_roots_are_403(client: TestClient, data: Path) -> None:
    for inputs in ([str(data.parent / "secret.uvh5")], ["../secret.uvh5"], ["/etc/passwd"]):
        response = _submit(client, inputs=inputs)
        assert response.status_code == 403, (inputs, response.text)
        assert "outside the allowed folders" in response.json()["detail"]
    beam = _submit(client, beam="../secret.uvh5")
    assert beam.status_code == 403 and "beam" in beam.json()["detail"]
    missing = _submit(client, inputs=["zen.2458098.99999.sim.uvh5"])
    assert missing.status_code == 400 and "does not exist" in missing.json()["detail"]
    assert client.get("/jobs").json()["count"] == 0


# failure and cancellation ----------------------------------------------------------------


def test_failing_input_fails_the_job_with_a_reason_and_no_products(
    client: TestClient, worker: Worker, settings: Settings, data: Path, store: JobStore
) -> None:
    # the API refuses the junk file at submission, with the reader's message
    refused = _submit(client, inputs=[JUNK])
    assert refused.status_code == 422, refused.text
    assert refused.json()["errors"][0]["field"] == "body.inputs"
    assert "not an HDF5 file" in refused.json()["detail"]
    # a job queued without that check (another client of the store) fails in the worker
    from autocal.diagnosis.run import DiagnoseConfig

    config = DiagnoseConfig(inputs=[str((data / JUNK).resolve())], **FAST)
    job_id = store.submit(config.model_dump(mode="json"), kind="diagnose")[0]["id"]
    assert worker.run_once() is True
    job = client.get(f"/jobs/{job_id}", headers=AUTH).json()
    assert job["state"] == "failed", job
    error = job["error"]
    assert str((data / JUNK).resolve()) in error
    assert "\n" not in error and "Traceback" not in error and ": " in error
    assert job["products"] == {} and job["result"] is None
    assert _files(settings.products_dir / job_id) == []
    results = client.get(f"/jobs/{job_id}/results")
    assert results.status_code == 409 and "failed" in results.json()["detail"]


def test_cancelling_a_running_diagnosis(
    client: TestClient, worker: Worker, settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    import autocal.diagnosis.effects

    real = autocal.diagnosis.effects.sky_templates

    def templates_then_cancel(*args: Any, **kwargs: Any) -> Any:
        # the job is running: cancel it through the API and wait for the heartbeat
        answer = client.post(f"/jobs/{job_id}/cancel", headers=AUTH)
        assert answer.status_code == 202 and answer.json()["cancel_requested"]
        deadline = time.monotonic() + 10
        while worker.current is not None and not worker.current.stop_flag.is_set():
            assert time.monotonic() < deadline, "the heartbeat never saw the cancellation"
            time.sleep(0.02)
        return real(*args, **kwargs)

    monkeypatch.setattr(autocal.diagnosis.effects, "sky_templates", templates_then_cancel)
    job_id = _submit(client).json()["id"]
    assert worker.run_once() is True
    job = client.get(f"/jobs/{job_id}").json()
    assert job["state"] == "cancelled", job
    assert job["error"] == "cancelled on request" and job["products"] == {}
    assert _files(settings.products_dir / job_id) == []


# run_diagnosis ---------------------------------------------------------------------------


def test_run_diagnosis_publishes_all_or_nothing(
    data: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import autocal.diagnosis.report

    config = DiagnoseConfig(inputs=[str(data / SIM)], max_steps=0, **FAST)  # gap only: fast
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    real = autocal.diagnosis.report.write_diagnosis

    def half_then_fail(diag: Any, out_dir: Path, obs: Any = None, **kw: Any) -> Path:
        (Path(out_dir) / "diagnosis.json").write_text('{"effects": [')
        raise OSError("disk full")

    monkeypatch.setattr(autocal.diagnosis.report, "write_diagnosis", half_then_fail)
    with pytest.raises(OSError, match="disk full"):
        run_diagnosis(config, out)
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]  # no products, no staging

    # cancelled after the products were staged: still nothing published
    calls: list[str] = []

    def write_then_cancel(diag: Any, out_dir: Path, obs: Any = None, **kw: Any) -> Path:
        calls.append("write")
        return real(diag, out_dir, obs, **kw)

    monkeypatch.setattr(autocal.diagnosis.report, "write_diagnosis", write_then_cancel)
    from autocal.errors import RunCancelledError

    with pytest.raises(RunCancelledError, match="cancelled"):
        run_diagnosis(config, out, should_stop=lambda: bool(calls))
    assert calls and sorted(p.name for p in out.iterdir()) == ["notes.txt"]

    # cancelled in the middle of the search (between two candidate fits)
    monkeypatch.setattr(autocal.diagnosis.report, "write_diagnosis", real)
    messages: list[str] = []
    with pytest.raises(RunCancelledError, match="cancelled"):
        run_diagnosis(
            config.model_copy(update={"max_steps": 2}),
            out,
            progress=lambda f, m: messages.append(m),
            should_stop=lambda: any("step 1: trying" in m for m in messages),
        )
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    assert not any("writing" in m for m in messages)

    seen: list[tuple[float, str]] = []
    config = config.model_copy(update={"max_steps": 1})
    assert run_diagnosis(config, out, progress=lambda f, m: seen.append((f, m))) == out
    summary = read_summary(out)
    diagnosis = json.loads((out / "diagnosis.json").read_text())
    assert summary["effects"] == diagnosis["effects"] and len(summary["effects"]) == 1
    assert summary["config"]["max_steps"] == 1
    published = [p for p in out.iterdir() if p.name != "notes.txt"]
    assert {product_name(p.name): str(p) for p in published} == summary["products"]
    fractions = [f for f, _ in seen]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    assert any("step 1: trying gain_drift" in m for _, m in seen)  # progress inside the search


def test_diagnose_config_and_command(data: Path, tmp_path: Path, capsys) -> None:
    from autocal.cli.main import main

    config = DiagnoseConfig(inputs=["a.uvh5"], pols=["EE", "yy"])
    assert config.pols == ["ee", "yy"] and config.max_steps >= 1
    for bad, field in [
        ({"inputs": []}, "inputs"),
        ({"alpha": 0}, "alpha"),
        ({"nside": 100}, "nside"),
        ({"trxr_prior": float("nan")}, "trxr_prior"),
        ({"model": "legendre"}, "model"),
    ]:
        with pytest.raises(ValidationError, match=field):
            DiagnoseConfig(**{"inputs": ["a.uvh5"], **bad})
    with pytest.raises(ValidationError, match="MHz, not Hz"):
        DiagnoseConfig(inputs=["a.uvh5"], freq_range_mhz=(1e8, 2e8))
    assert product_name("residuals_step2.png") == "residuals_step2_png"
    assert product_name("diagnosis.json") == "diagnosis"

    out = tmp_path / "cli"
    args = ["diagnose", str(data / SIM), "--sky", SKY, "--beam", "dipole", "--nside", "32"]
    assert main([*args, "--max-steps", "0", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "autocal diagnose" in printed and f"wrote {out}" in printed
    summary = read_summary(out)
    assert summary["effects"] == [] and summary["config"]["max_steps"] == 0
    assert os.path.isfile(out / "diagnosis.json") and os.path.isfile(out / "summary.txt")
    assert main([*args, "--alpha", "2", "--out", str(out)]) != 0
    assert "alpha" in capsys.readouterr().err
