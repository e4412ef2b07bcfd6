"""autocal.core.files: atomic, durable writes and publication of staged products."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from autocal.core import files
from autocal.core.files import atomic_path, publish_staged


@pytest.fixture
def synced(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Record what is flushed to disk (the path of each descriptor given to os.fsync)."""
    seen: list[str] = []
    real = os.fsync

    def fsync(fd: int) -> None:
        seen.append(os.readlink(f"/proc/self/fd/{fd}"))
        real(fd)

    monkeypatch.setattr(files.os, "fsync", fsync)
    return seen


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="needs /proc")
def test_atomic_path_flushes_the_file_then_its_folder(tmp_path: Path, synced) -> None:
    target = tmp_path / "out" / "summary.json"
    with atomic_path(target) as tmp:
        tmp.write_text("{}")
    assert target.read_text() == "{}"
    assert len(synced) == 2
    assert Path(synced[0]).name.startswith(".summary.json.")  # the file, before the rename
    assert synced[1] == str(target.parent)  # the folder, after it
    assert [p.name for p in target.parent.iterdir()] == ["summary.json"]


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="needs /proc")
def test_publish_staged_flushes_every_file_before_renaming(tmp_path: Path, synced) -> None:
    out = tmp_path / "attempt-1"
    staging = out / ".staging-1-2"
    staging.mkdir(parents=True)
    for name in ("solution.h5", "summary.json"):
        (staging / name).write_text(name)
    publish_staged(staging, out, ["solution.h5", "summary.json"])
    assert synced == [
        str(staging / "solution.h5"),
        str(staging / "summary.json"),
        str(staging),
        str(out),
    ]
    assert (out / "summary.json").read_text() == "summary.json"
    assert list(staging.iterdir()) == []


def test_atomic_path_leaves_nothing_on_error(tmp_path: Path) -> None:
    target = tmp_path / "product.h5"
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("disk full")
    assert list(tmp_path.iterdir()) == []
