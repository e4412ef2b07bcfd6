"""The per-antenna history (autocal.service.history, .monitoring) on SQLite and PostgreSQL.

One real night (JD 2458043, 7 antennas) is calibrated once by an in-process worker: its
history rows are checked against the solution product read with h5py alone. The queries
and the nightly summaries run on synthetic rows with known departures.
"""

from __future__ import annotations

from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest

from autocal.pipeline.config import CalibrationConfig
from autocal.service.history import (
    AntennaNight,
    backfill,
    config_hash,
    ensure_table,
    record_job,
)
from autocal.service.monitoring import (
    UnknownAntennaError,
    UnknownNightError,
    antenna_history,
    latest_state,
    night_detail,
    nights_overview,
)
from autocal.service.settings import Settings
from autocal.service.store import JobState, JobStore
from autocal.service.worker import Worker
from tests.service.test_service_store import BACKENDS, database_url
from tests.service.tiny_uvh5 import write_tiny_uvh5

NIGHT = 2458043


@pytest.fixture(scope="module")
def real_night(tmp_path_factory: pytest.TempPathFactory, data_root: Path) -> dict[str, Any]:
    """Night 2458043 calibrated by an in-process worker (SQLite); its job record."""
    folder = tmp_path_factory.mktemp("state")
    settings = Settings(state_dir=folder, data_roots=[data_root], dask_scheduler="")
    store = JobStore(settings.resolved_database_url())
    inputs = sorted(str(p) for p in (data_root / "hera/autos").glob(f"zen.{NIGHT}.*.XRAA.uvh5"))
    config = CalibrationConfig(inputs=inputs, products=["hdf5"]).model_dump(mode="json")
    job, _ = store.submit(config, night=NIGHT)
    assert Worker(store, settings, worker_id="h").run_once()
    done = store.get(job["id"])
    assert done is not None and done["state"] == "succeeded", done
    with store.session() as s:
        rows = [r.to_dict() for r in s.query(AntennaNight).filter_by(job_id=job["id"])]
    store.engine.dispose()
    return {"job": done, "rows": rows}


@pytest.fixture(params=BACKENDS)
def store(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[JobStore]:
    with database_url(request.param, tmp_path / "db") as url:
        s = JobStore(url)
        yield s
        s.engine.dispose()


def _succeed(store: JobStore, config: dict[str, Any], **fields: Any) -> str:
    """Queue a job and close it as succeeded with ``fields`` (result, products)."""
    kind = fields.pop("kind", "calibrate")
    job, _ = store.submit(config, kind=kind, night=fields.pop("night", None))
    claimed = store.claim("test", kinds=[kind])
    assert claimed is not None and claimed["id"] == job["id"]
    assert store.finish(job["id"], "test", claimed["attempts"], JobState.succeeded, **fields)
    return str(job["id"])


def test_the_worker_records_each_antenna_as_the_product_holds_it(real_night) -> None:
    rows, job = real_night["rows"], real_night["job"]
    with h5py.File(job["products"]["hdf5"], "r") as h5:
        antennas = h5["antennas"][:].tolist()
        freqs_mhz = h5["freqs"][:] / 1e6
        derived = {k: h5["derived"][k][:] for k in ("G", "sigma_G", "Trxr", "sigma_Trxr")}
        flags = h5["derived"]["flags"][:].astype(bool)
        chi2 = h5["derived"]["reduced_chi2"][:]
    assert sorted(r["antenna"] for r in rows) == sorted(antennas) == [24, 25, 37, 38, 39, 52, 53]
    for row in rows:
        ia = antennas.index(row["antenna"])
        ok = ~flags[ia, 0]
        assert row["night"] == NIGHT and row["pol"] == "ee"
        assert (
            row["observation"].startswith(f"zen.{NIGHT}.40141") and "+2 files" in row["observation"]
        )
        assert row["config_hash"] == config_hash(job["config"])
        assert row["flagged_fraction"] == pytest.approx(1 - ok.mean())
        assert row["reduced_chi2"] == pytest.approx(np.median(chi2[ia, 0][ok]))
        for name, values in derived.items():
            assert row[name] == pytest.approx(np.median(values[ia, 0][ok]), rel=1e-12)
        band = next(b for b in row["bands"] if b["band"] == "150-175")
        keep = ok & (freqs_mhz >= 150) & (freqs_mhz < 175)
        assert band["n_channels"] == keep.sum() > 0
        assert band["Trxr"] == pytest.approx(np.median(derived["Trxr"][ia, 0][keep]))
        assert band["sigma_Trxr"] == pytest.approx(np.median(derived["sigma_Trxr"][ia, 0][keep]))
        assert row["ratio"] is None and row["effects"] is None  # no reference, no diagnosis


def test_recording_is_idempotent_and_takes_the_diagnosis_effects(store, real_night) -> None:
    job = real_night["job"]
    config, products = job["config"], {"hdf5": job["products"]["hdf5"]}
    comparison = {"per_antenna_pol": [{"antenna": 24, "pol": "ee", "ratio_median": 1.02,
                                       "sigma_ratio_median": 0.05}]}  # fmt: skip
    first = _succeed(store, config, night=NIGHT, products=products,
                     result={"comparison": comparison})  # fmt: skip
    assert record_job(store, first) == 7
    assert record_job(store, first) == 7  # replaced, not duplicated
    assert backfill(store) == {"recorded": 0, "rows": 0, "skipped": 1, "failed": 0}
    rows = antenna_history(store, 24)
    assert len(rows) == 1 and rows[0]["ratio"] == 1.02 and rows[0]["sigma_ratio"] == 0.05
    diagnosis = {"inputs": config["inputs"]}
    diag = _succeed(store, diagnosis, kind="diagnose", night=NIGHT,
                    result={"effects": ["gain_drift", "sky_offset"]})  # fmt: skip
    assert record_job(store, diag) == 7
    assert {tuple(r["effects"]) for r in latest_state(store)} == {("gain_drift", "sky_offset")}
    other = _succeed(store, {"inputs": ["elsewhere.uvh5"]}, kind="diagnose", night=NIGHT,
                     result={"effects": ["beam_width"]})  # fmt: skip
    assert record_job(store, other) == 0  # another observation: nothing attached


# synthetic nights -----------------------------------------------------------------------

ANTENNAS = list(range(10))
NIGHTS = [2460001, 2460002, 2460003, 2460004]


def _row(night: int, ant: int, **change: float) -> AntennaNight:
    rng = np.random.default_rng(night * 100 + ant)
    values = {
        "G": 20.0 + rng.normal(0, 0.2),
        "sigma_G": 0.2,
        "abs_g": 4.47,
        "sigma_abs_g": 0.02,
        "Trxr": 150.0 + rng.normal(0, 3.0),
        "sigma_Trxr": 3.0,
        "reduced_chi2": 1.0 + rng.normal(0, 0.05),
        **change,
    }
    return AntennaNight(
        job_id=f"job{night}", night=night, observation=f"zen.{night}.1", jd=night + 0.4,
        antenna=ant, pol="ee", config_hash="cfg", recorded_at=datetime.now(UTC),
        flagged_fraction=0.05, bands=[], **values,
    )  # fmt: skip


def _fill(store: JobStore, changes: dict[tuple[int, int], dict[str, float]]) -> None:
    ensure_table(store)
    with store.session() as s:
        for night in NIGHTS:
            for ant in ANTENNAS:
                s.add(_row(night, ant, **changes.get((night, ant), {})))


def test_outliers_name_the_antenna_the_test_and_the_reason(store) -> None:
    last = NIGHTS[-1]
    _fill(
        store,
        {
            (last, 3): {"Trxr": 250.0},  # a receiver that changed: history and array
            (last, 7): {"reduced_chi2": 3.5},  # the fit got worse
            (last, 5): {"Trxr": 175.0, "sigma_Trxr": 40.0},  # far off, but within its errors
        },
    )
    outliers = night_detail(store, last)["outliers"]
    found = {(o["antenna"], o["test"], o["quantity"]) for o in outliers}
    assert found == {(3, "array", "Trxr"), (3, "history", "Trxr"), (7, "chi2_jump", "reduced_chi2")}
    history = next(o for o in outliers if o["test"] == "history")
    assert history["z"] > 5 and "3 earlier night(s)" in history["reason"]
    assert history["reference"] == pytest.approx(150.0, abs=5)
    # the earlier nights, calm, have none; the latest state carries the reasons
    assert night_detail(store, NIGHTS[1])["outliers"] == []
    state = {s["antenna"]: s for s in latest_state(store)}
    assert len(state[3]["outliers"]) == 2 and state[0]["outliers"] == []


def test_history_series_ranges_and_what_exists(store) -> None:
    _fill(store, {})
    series = antenna_history(store, 4, pol="ee", nights=(NIGHTS[1], NIGHTS[2]))
    assert [r["night"] for r in series] == NIGHTS[1:3]
    assert all(r["sigma_Trxr"] == 3.0 for r in series)
    with pytest.raises(UnknownAntennaError, match="antennas with history: 0, 1, 2"):
        antenna_history(store, 99)
    with pytest.raises(UnknownAntennaError, match=r"pols: \['ee'\]"):
        antenna_history(store, 4, pol="nn")
    with pytest.raises(UnknownNightError, match="nights: 2460001, 2460002"):
        night_detail(store, 2459000)
    overview = nights_overview(store)
    assert [n["night"] for n in overview] == NIGHTS[::-1]
    assert overview[0]["antennas"] == 10 and overview[0]["observations"] == 1


def test_a_night_with_only_failed_jobs_says_why(store) -> None:
    job, _ = store.submit({"inputs": ["zen.2460010.1.HH.uvh5"]}, night=2460010)
    claimed = store.claim("test")
    assert claimed is not None
    store.finish(job["id"], "test", 1, JobState.failed, error="PipelineError: no autos")
    detail = night_detail(store, 2460010)
    assert detail["antennas"] == [] and detail["outliers"] == []
    assert detail["failed_jobs"][0]["error"] == "PipelineError: no autos"
    assert detail["jobs"] == {"failed": 1}
    assert nights_overview(store)[0]["jobs"] == {"failed": 1}


# the HTTP API ---------------------------------------------------------------------------


def test_the_endpoints_answer_with_values_and_404s_that_list_what_exists(
    store, tmp_path: Path
) -> None:
    from fastapi.testclient import TestClient

    from autocal.service.app import create_app

    _fill(store, {(NIGHTS[-1], 3): {"Trxr": 250.0}})
    client = TestClient(create_app(Settings(state_dir=tmp_path, api_token="t" * 32), store))
    antennas = client.get("/antennas").json()
    assert antennas["count"] == 10 and len(antennas["items"][3]["outliers"]) == 2
    series = client.get("/antennas/3/history", params={"pol": "EE", "from": NIGHTS[2]}).json()
    assert [r["night"] for r in series["items"]] == NIGHTS[2:]
    assert series["items"][-1]["Trxr"] == 250.0 and series["items"][-1]["sigma_Trxr"] == 3.0
    answer = client.get("/antennas/42/history")
    assert answer.status_code == 404 and "antennas with history: 0, 1" in answer.json()["detail"]
    answer = client.get("/antennas/3/history", params={"from": NIGHTS[2], "to": NIGHTS[1]})
    assert answer.status_code == 422 and answer.json()["errors"][0]["field"] == "query.from"
    assert client.get("/nights").json()["items"][0]["night"] == NIGHTS[-1]
    night = client.get(f"/nights/{NIGHTS[-1]}").json()
    assert {o["antenna"] for o in night["outliers"]} == {3} and len(night["antennas"]) == 10
    answer = client.get("/nights/2459999")
    assert answer.status_code == 404 and str(NIGHTS[0]) in answer.json()["detail"]


def test_autocal_nightly_prints_the_nights_outliers(tmp_path: Path, monkeypatch, capsys) -> None:
    from autocal.cli.main import main
    from autocal.service.settings import get_settings

    data = tmp_path / "data"
    data.mkdir()
    write_tiny_uvh5(data / f"zen.{NIGHTS[-1]}.40000.HH.uvh5")  # a real header: it is read
    monkeypatch.setenv("AUTOCAL_STATE_DIR", str(tmp_path / "state"))
    monkeypatch.setenv("AUTOCAL_DATA_ROOTS", str(data))
    monkeypatch.delenv("AUTOCAL_DATABASE_URL", raising=False)
    get_settings.cache_clear()
    try:
        store = JobStore(get_settings().resolved_database_url())
        _fill(store, {(NIGHTS[-1], 6): {"G": 30.0}})
        store.engine.dispose()
        argv = ["nightly", "--night", str(NIGHTS[-1]), "--beam", "dipole", "--wait", "0"]
        assert main(argv) == 0
    finally:
        get_settings.cache_clear()
    out = capsys.readouterr().out
    assert "1 job(s) not finished yet" in out
    assert "outlier antenna 6 ee (array): G = 30" in out
    assert "outlier antenna 6 ee (history): G = 30" in out


def test_the_page_is_read_only_and_out_of_the_schema(store, tmp_path: Path) -> None:
    from fastapi.testclient import TestClient

    from autocal.service.app import create_app

    client = TestClient(create_app(Settings(state_dir=tmp_path, api_token="t" * 32), store))
    answer = client.post("/ui")
    assert answer.status_code == 405 and answer.headers["allow"] == "GET"
    assert not [p for p in client.get("/openapi.json").json()["paths"] if p.startswith("/ui")]
    assert "no night yet" in client.get("/ui").text  # an empty store: a page, not an error
