"""Where the service may read inputs and write products.

Every path a client names (inputs, reference gains, a beam file, a nightly folder) must
resolve -- after ``..``, symlinks and relative parts -- to an existing file or folder under
one of the *allowed roots*: the configured data roots (``AUTOCAL_DATA_ROOTS``, by default
the reference data folder) and the uploads folder. Relative paths are taken relative to
each data root in turn. An uploaded file may also be named by its upload id
(``upload:<id>`` or the bare 32-character id returned by ``POST /uploads``).

A job's products live in ``<state dir>/jobs/<job id>/`` (:func:`job_products_dir`); the
API serves no product file outside that folder.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

from autocal.errors import AutocalError
from autocal.service.settings import Settings

logger = logging.getLogger(__name__)

#: An upload id: the hex form of a UUID4.
UPLOAD_ID = re.compile(r"^(?:upload:)?([0-9a-f]{32})$")
#: Suffix of an upload still being received (never an input).
PARTIAL_SUFFIX = ".part"


class InputPathError(AutocalError):
    """A client-named path is refused.

    Parameters
    ----------
    message
        What is wrong and what to do.
    status_code
        HTTP status for the API: 403 outside the allowed roots, 400 missing or malformed.
    """

    def __init__(self, message: str, status_code: int = 400) -> None:
        super().__init__(message)
        self.status_code = status_code


def allowed_roots(settings: Settings) -> list[Path]:
    """Return the resolved folders under which inputs may lie (data roots, then uploads).

    Parameters
    ----------
    settings
        The service settings.

    Returns
    -------
    list of pathlib.Path
        Resolved, without duplicates, in order of preference.
    """
    roots = [*settings.resolved_data_roots(), settings.uploads_dir.expanduser().resolve()]
    unique: list[Path] = []
    for root in roots:
        if root not in unique:
            unique.append(root)
    return unique


def job_products_dir(settings: Settings, job_id: str) -> Path:
    """Return the folder holding a job's products (``<state dir>/jobs/<job id>``).

    Parameters
    ----------
    settings
        The service settings.
    job_id
        The job id.

    Returns
    -------
    pathlib.Path
        The folder (not created).
    """
    if not re.fullmatch(r"[0-9A-Za-z_-]{1,64}", job_id):
        raise InputPathError(f"invalid job id {job_id!r}")
    return settings.products_dir.expanduser().resolve() / job_id


def _roots_text(roots: list[Path]) -> str:
    return ", ".join(str(r) for r in roots) or "(none configured: set AUTOCAL_DATA_ROOTS)"


def _under(path: Path, roots: list[Path]) -> bool:
    return any(path == root or path.is_relative_to(root) for root in roots)


def _resolve(path: Path, what: str, value: str) -> Path:
    try:
        return path.resolve(strict=False)
    except (OSError, RuntimeError, ValueError) as err:  # symlink loops, bad names
        raise InputPathError(f"{what} {value!r} cannot be resolved: {err}") from err


def _exists(path: Path) -> bool:
    try:
        return path.exists()
    except (OSError, ValueError):
        return False


def upload_path(settings: Settings, upload_id: str) -> Path:
    """Return the file of a completed upload.

    Parameters
    ----------
    settings
        The service settings.
    upload_id
        The id returned by ``POST /uploads`` (optionally prefixed ``upload:``).

    Returns
    -------
    pathlib.Path
        The uploaded file (resolved).

    Raises
    ------
    InputPathError
        If the id is malformed or names no completed upload.
    """
    match = UPLOAD_ID.fullmatch(upload_id.strip())
    if match is None:
        raise InputPathError(f"{upload_id!r} is not an upload id")
    folder = settings.uploads_dir.expanduser().resolve() / match.group(1)
    files = (
        [p for p in folder.iterdir() if p.is_file() and not p.name.endswith(PARTIAL_SUFFIX)]
        if folder.is_dir()
        else []
    )
    if len(files) != 1:
        raise InputPathError(
            f"no completed upload {match.group(1)}: upload the file first (POST /uploads)"
        )
    return files[0].resolve()


def resolve_input(value: str, settings: Settings, *, what: str = "input") -> Path:
    """Resolve a client-named path (or upload id) and check it is allowed and exists.

    Parameters
    ----------
    value
        An absolute path, a path relative to a data root, or an upload id.
    settings
        The service settings.
    what
        What the path is for (used in messages): ``input``, ``reference``, ``beam``...

    Returns
    -------
    pathlib.Path
        The resolved path (symlinks followed), under an allowed root, existing.

    Raises
    ------
    InputPathError
        403 if it resolves outside every allowed root, 400 if empty, malformed or missing.
    """
    text = value.strip()
    if not text:
        raise InputPathError(f"{what}: empty path")
    if "\x00" in text:
        raise InputPathError(f"{what} {value!r}: paths cannot contain NUL characters")
    if UPLOAD_ID.fullmatch(text):
        return upload_path(settings, text)
    if text.lower().startswith("upload:"):
        raise InputPathError(
            f"{what} {value!r}: {text[7:]!r} is not an upload id (the 32 hexadecimal "
            "characters POST /uploads returned, as upload:<id> or alone)"
        )
    roots = allowed_roots(settings)
    raw = Path(text)
    # a relative path is tried under each root in turn
    candidates = [raw] if raw.is_absolute() else [root / raw for root in roots]
    inside: list[Path] = []
    escaped = False
    for candidate in candidates:
        real = _resolve(candidate, what, value)
        if not _under(real, roots):
            escaped = True
        elif _exists(real):
            return real
        else:
            inside.append(real)
    if escaped:
        raise InputPathError(
            f"{what} {value!r} is outside the allowed folders ({_roots_text(roots)}); "
            "give a path under one of them or upload the file (POST /uploads)",
            status_code=403,
        )
    raise InputPathError(
        f"{what} {value!r} does not exist (looked for {', '.join(str(p) for p in inside)}); "
        f"allowed folders: {_roots_text(roots)}"
    )


def check_under_roots(path: Path, settings: Settings) -> Path | None:
    """Return the resolved ``path`` if it lies under an allowed root, else ``None``.

    Parameters
    ----------
    path
        A path found by the service itself (e.g. while scanning a folder).
    settings
        The service settings.

    Returns
    -------
    pathlib.Path or None
        The resolved path, or ``None`` when it escapes the roots (a symlink pointing out).
    """
    try:
        real = path.resolve(strict=False)
    except (OSError, RuntimeError, ValueError):
        return None
    return real if _under(real, allowed_roots(settings)) else None
