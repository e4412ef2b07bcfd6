"""Inputs checked twice: fingerprinted at submission, re-resolved and compared at start.

A job waits in the queue between its submission (where :mod:`autocal.service.paths`
checks every path under the data roots) and the moment a worker reads its inputs.
:func:`fingerprint_config` records, at submission, a fingerprint of every file the job
names; :func:`check_inputs`, called by the worker before it reads anything, resolves each
path again (a file replaced by a symlink pointing outside the data roots is refused) and
compares the fingerprints (a file changed or replaced since submission is refused). The
job then fails with the reason instead of reading the wrong data.

A fingerprint is the size, the modification time and a SHA-256: of the whole file up to
``AUTOCAL_FINGERPRINT_FULL_BYTES`` (64 MiB), and of :data:`SAMPLE_BLOCKS` blocks of
:data:`BLOCK_BYTES` spread over a larger file (first and last included), so a
submission of many multi-GB files reads at most 16 MiB of each (deploy/README.md gives
the measured costs). A Miriad input (a folder) is fingerprinted file by file.
"""

from __future__ import annotations

import hashlib
import logging
import os
from pathlib import Path
from typing import Any

from autocal.errors import AutocalError
from autocal.service.paths import check_under_roots
from autocal.service.settings import Settings

logger = logging.getLogger(__name__)

#: Bytes of one sampled block of a large file.
BLOCK_BYTES = 1 << 20
#: Blocks sampled from a file larger than the full-hash limit.
SAMPLE_BLOCKS = 16


class InputChangedError(AutocalError):
    """An input moved outside the data roots or changed since the job was submitted."""


def config_files(config: dict[str, Any]) -> list[str]:
    """Return the file and folder paths a job configuration names.

    Parameters
    ----------
    config
        A calibration or diagnosis configuration (as stored with the job).

    Returns
    -------
    list of str
        Inputs, reference files, and a beam or receiver-prior file given as a path (a
        named beam or a number is not a path).
    """
    paths = [str(p) for p in config.get("inputs") or []]
    paths += [str(p) for p in config.get("reference") or []]
    for key in ("beam", "trxr_prior"):
        value = config.get(key)
        if isinstance(value, str) and os.path.isabs(value):
            paths.append(value)
    return list(dict.fromkeys(paths))


def _digest(path: Path, size: int, full_bytes: int) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        if size <= full_bytes:
            for block in iter(lambda: handle.read(BLOCK_BYTES), b""):
                digest.update(block)
        else:
            step = (size - BLOCK_BYTES) / (SAMPLE_BLOCKS - 1)
            for k in range(SAMPLE_BLOCKS):
                handle.seek(round(k * step))
                digest.update(handle.read(BLOCK_BYTES))
    return digest.hexdigest()


def file_fingerprint(path: Path, full_bytes: int) -> dict[str, Any]:
    """Return the fingerprint of one file.

    Parameters
    ----------
    path
        The file.
    full_bytes
        Files up to this size are hashed whole; larger ones by sampled blocks.

    Returns
    -------
    dict
        ``size``, ``mtime_ns``, ``sha256`` and ``sampled`` (whether blocks were sampled).
    """
    stat = path.stat()
    return {
        "size": stat.st_size,
        "mtime_ns": stat.st_mtime_ns,
        "sha256": _digest(path, stat.st_size, full_bytes),
        "sampled": stat.st_size > full_bytes,
    }


def fingerprint(path: Path, full_bytes: int) -> dict[str, Any]:
    """Return the fingerprint of a file, or of every file of a folder (by relative path).

    Parameters
    ----------
    path
        A file or a folder (Miriad).
    full_bytes
        See :func:`file_fingerprint`.

    Returns
    -------
    dict
        A file's fingerprint, or ``{"files": {relative path: fingerprint}}``.
    """
    if path.is_dir():
        files = sorted(p for p in path.rglob("*") if p.is_file())
        return {"files": {str(p.relative_to(path)): file_fingerprint(p, full_bytes) for p in files}}
    return file_fingerprint(path, full_bytes)


def fingerprint_config(config: dict[str, Any], settings: Settings) -> dict[str, Any]:
    """Return ``{path: fingerprint}`` of every existing file the configuration names.

    Parameters
    ----------
    config
        The job configuration, its paths already resolved under the data roots.
    settings
        Service settings (``fingerprint_full_bytes``).

    Returns
    -------
    dict
        The fingerprints, stored with the job (:meth:`JobStore.submit`).
    """
    found: dict[str, Any] = {}
    for text in config_files(config):
        path = Path(text)
        if path.exists():
            found[text] = fingerprint(path, settings.fingerprint_full_bytes)
    return found


def _changes(recorded: dict[str, Any], now: dict[str, Any]) -> list[str]:
    if "files" in recorded or "files" in now:
        old, new = recorded.get("files", {}), now.get("files", {})
        changed = [
            f"{name}: {', '.join(_changes(old[name], new[name]))}"
            for name in sorted(set(old) & set(new))
            if _changes(old[name], new[name])
        ]
        changed += [f"{name} removed" for name in sorted(set(old) - set(new))]
        changed += [f"{name} added" for name in sorted(set(new) - set(old))]
        return changed
    return [
        f"{key} {recorded.get(key)} -> {now.get(key)}"
        for key in ("size", "mtime_ns", "sha256")
        if recorded.get(key) != now.get(key)
    ]


def check_inputs(
    config: dict[str, Any], recorded: dict[str, Any] | None, settings: Settings
) -> None:
    """Check a job's inputs before the worker reads them.

    Every path the configuration names must still resolve under the allowed roots, and
    every fingerprint recorded at submission must still match.

    Parameters
    ----------
    config
        The job configuration.
    recorded
        The fingerprints recorded at submission (``None`` for a job queued before they
        were recorded: only the paths are checked).
    settings
        Service settings (data roots, ``fingerprint_full_bytes``).

    Raises
    ------
    InputChangedError
        With the path and what changed.
    """
    for text in config_files(config):
        path = Path(text)
        if check_under_roots(path, settings) is None:
            raise InputChangedError(
                f"{text} now resolves to {path.resolve()}, outside the allowed folders; "
                "it was replaced after the job was submitted: refusing to read it"
            )
        if path.is_dir():
            for inner in path.rglob("*"):
                if check_under_roots(inner, settings) is None:
                    raise InputChangedError(
                        f"{inner} (in {text}) now resolves outside the allowed folders"
                    )
    for text, before in (recorded or {}).items():
        path = Path(text)
        if not path.exists():
            raise InputChangedError(f"{text} no longer exists (it did at submission)")
        changes = _changes(before, fingerprint(path, settings.fingerprint_full_bytes))
        if changes:
            raise InputChangedError(
                f"{text} changed since the job was submitted ({'; '.join(changes)}); "
                "submit the job again to use the new file"
            )
