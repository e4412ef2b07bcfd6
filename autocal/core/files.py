"""File helpers every writer and reader shares: atomic writes and content checksums.

Renames are made durable: a file is flushed to disk (``fsync``) before it is renamed into
place and its folder afterwards, so a power cut leaves either the old or the new product,
never a renamed but empty file.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import shutil
import socket
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path

logger = logging.getLogger(__name__)

#: A staging folder of the product writers: ``.staging-<pid>-<ns>@<host>``.
_STAGING = re.compile(r"^\.staging-(\d+)-\d+@(.+)$")


def _current_umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


#: The process umask, read once at import (``os.umask`` can only be read by setting it).
_UMASK = _current_umask()


def fsync_file(path: str | Path) -> None:
    """Flush a file's content to disk.

    Parameters
    ----------
    path
        The file.
    """
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_dir(path: str | Path) -> None:
    """Flush a folder's entries (renames, new files) to disk (a no-op where unsupported).

    Parameters
    ----------
    path
        The folder.
    """
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:  # e.g. Windows cannot open folders
        return
    try:
        os.fsync(fd)
    except OSError:  # some file systems refuse fsync on folders
        pass
    finally:
        os.close(fd)


def make_staging(out: Path) -> Path:
    """Create ``out`` and a new staging folder in it, removing orphaned ones first.

    A run's products are written into ``out/.staging-<pid>-<ns>@<host>`` and renamed into
    ``out`` once all are written; a run killed outright (SIGKILL, a crash) leaves its
    staging folder behind. Those of this machine (same host name) whose process no longer
    exists are removed here, so the next run into ``out`` cleans up; another machine's
    (a folder shared over the network), and the host-less names of earlier versions, are
    left alone: their processes cannot be checked from here (the service's janitor removes
    old ones by age).
    """
    out.mkdir(parents=True, exist_ok=True)
    host = _host()
    for entry in out.iterdir():
        match = _STAGING.match(entry.name)
        if match is None or match.group(2) != host or not entry.is_dir():
            continue
        if _alive(int(match.group(1))):
            continue
        shutil.rmtree(entry, ignore_errors=True)
        logger.info("removed %s, left by a run that no longer exists", entry)
    staging = out / f".staging-{os.getpid()}-{time.time_ns()}@{host}"
    staging.mkdir()
    return staging


def _host() -> str:
    """Return this machine's name as a file name may hold it."""
    return re.sub(r"[^A-Za-z0-9._-]", "_", socket.gethostname()) or "host"


def _alive(pid: int) -> bool:
    """Whether a process ``pid`` exists on this machine (ours included)."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # exists, another user's
        return True
    return True


def publish_staged(staging: Path, out: Path, names: list[str]) -> None:
    """Move the files ``names`` from ``staging`` into ``out``, durably and in order.

    Every staged file (and the staging folder) is flushed to disk before the first
    rename, and ``out`` after the last, so that what is visible after a crash was fully
    written. Put the file whose presence marks a complete set (``summary.json``) last.

    Parameters
    ----------
    staging
        The folder the products were written into (inside ``out``: same file system).
    out
        Where they are published.
    names
        File names in ``staging``, in publication order.
    """
    for name in names:
        fsync_file(staging / name)
    fsync_dir(staging)
    for name in names:
        os.replace(staging / name, out / name)
    fsync_dir(out)


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success.

    On any exception the temporary file is removed and ``path`` is left untouched. The
    file is flushed to disk before the rename and its folder after it.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        # mkstemp makes the file private (0600); give the product the usual permissions
        # so that a service reading it as another user (API vs worker) can serve it
        if tmp_path.exists():
            os.chmod(tmp_path, 0o666 & ~_UMASK)
            fsync_file(tmp_path)
        os.replace(tmp_path, path)
        fsync_dir(path.parent)
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise


@lru_cache(maxsize=32)
def file_sha256(path: str, mtime_ns: int) -> str:
    """Return the SHA-256 of ``path`` (memoised on path and modification time)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def file_checksum(path: str | Path) -> str:
    """Return the SHA-256 of a file (memoised on path and modification time)."""
    path = Path(path).resolve()
    return file_sha256(str(path), path.stat().st_mtime_ns)
