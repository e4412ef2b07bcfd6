"""Inputs re-checked when a worker starts a job (autocal.service.input_check; issue 24 D7)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from autocal.service.input_check import (
    InputChangedError,
    check_inputs,
    config_files,
    fingerprint,
    fingerprint_config,
)
from autocal.service.settings import Settings


@pytest.fixture
def roots(tmp_path: Path) -> tuple[Path, Path]:
    """An allowed data folder and a folder outside every root."""
    inside, outside = tmp_path / "data", tmp_path / "elsewhere"
    inside.mkdir()
    outside.mkdir()
    return inside, outside


def _settings(tmp_path: Path, data: Path, full_bytes: int = 64 * 1024**2) -> Settings:
    return Settings(
        state_dir=tmp_path / "state", data_roots=[data], fingerprint_full_bytes=full_bytes
    )


def test_config_files_names_inputs_references_and_path_options() -> None:
    config = {
        "inputs": ["/d/a.uvh5", "/d/b.uvh5"],
        "reference": ["/d/ref.calfits"],
        "beam": "hera",
        "trxr_prior": "/d/prior.csv",
    }
    assert config_files(config) == ["/d/a.uvh5", "/d/b.uvh5", "/d/ref.calfits", "/d/prior.csv"]
    assert config_files({"inputs": ["/d/a"], "beam": "/d/beam.fits", "trxr_prior": 150.0}) == [
        "/d/a",
        "/d/beam.fits",
    ]


def test_unchanged_inputs_pass(tmp_path: Path, roots) -> None:
    data, _ = roots
    (data / "obs.uvh5").write_bytes(os.urandom(5000))
    miriad = data / "obs.uv"
    miriad.mkdir()
    (miriad / "visdata").write_bytes(os.urandom(3000))
    config = {"inputs": [str(data / "obs.uvh5"), str(miriad)]}
    settings = _settings(tmp_path, data)
    recorded = fingerprint_config(config, settings)
    assert set(recorded) == set(config["inputs"])
    assert recorded[str(data / "obs.uvh5")]["size"] == 5000
    check_inputs(config, recorded, settings)  # no error
    check_inputs(config, None, settings)  # a job queued before fingerprints: paths only


def test_an_input_replaced_by_a_symlink_outside_the_roots_is_refused(tmp_path: Path, roots) -> None:
    data, outside = roots
    target = data / "obs.uvh5"
    target.write_bytes(b"observation")
    secret = outside / "secret"
    secret.write_bytes(b"observation")  # same bytes: only the path check can catch it
    config = {"inputs": [str(target)]}
    settings = _settings(tmp_path, data)
    recorded = fingerprint_config(config, settings)
    target.unlink()
    target.symlink_to(secret)
    with pytest.raises(InputChangedError, match="outside the allowed folders") as err:
        check_inputs(config, recorded, settings)
    assert str(secret) in str(err.value)
    # inside a Miriad folder too
    miriad = data / "obs.uv"
    miriad.mkdir()
    (miriad / "visdata").symlink_to(secret)
    with pytest.raises(InputChangedError, match="visdata"):
        check_inputs({"inputs": [str(miriad)]}, None, settings)


@pytest.mark.parametrize("full_bytes", [64 * 1024**2, 4096], ids=["whole", "sampled"])
def test_a_changed_input_is_refused_with_what_changed(tmp_path: Path, roots, full_bytes) -> None:
    data, _ = roots
    path = data / "obs.uvh5"
    content = bytearray(os.urandom(3 * 1024**2))
    path.write_bytes(content)
    config = {"inputs": [str(path)]}
    settings = _settings(tmp_path, data, full_bytes)
    recorded = fingerprint_config(config, settings)
    assert recorded[str(path)]["sampled"] == (full_bytes == 4096)
    stat = path.stat()
    content[0] ^= 0xFF  # the first byte is in every sample
    path.write_bytes(content)
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))  # even with the old time
    with pytest.raises(InputChangedError, match="changed since the job was submitted") as err:
        check_inputs(config, recorded, settings)
    assert "sha256" in str(err.value) and "size" not in str(err.value)
    path.unlink()
    with pytest.raises(InputChangedError, match="no longer exists"):
        check_inputs(config, recorded, settings)


def test_folder_fingerprints_name_the_changed_file(tmp_path: Path) -> None:
    folder = tmp_path / "obs.uv"
    folder.mkdir()
    (folder / "vartable").write_text("a")
    before = fingerprint(folder, 1024)
    (folder / "vartable").write_text("ab")
    (folder / "flags").write_text("x")
    settings = _settings(tmp_path, tmp_path)
    with pytest.raises(InputChangedError, match=r"vartable: size 1 -> 2.*flags added"):
        check_inputs({"inputs": [str(folder)]}, {str(folder): before}, settings)
