"""``POST /uploads``: receive one input file, streamed to disk with a size limit.

The multipart body is parsed as it arrives (python-multipart's streaming parser), so the
file goes straight to ``<state dir>/uploads/<upload id>/<safe name>.part`` and the limit
(``AUTOCAL_MAX_UPLOAD_BYTES``) is enforced while streaming: the first byte beyond it ends
the request with 413 and removes the partial file. A complete upload is renamed to its
final name; the id (or ``upload:<id>``) is then accepted as a job input.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import shutil
import uuid
from pathlib import Path
from typing import IO, Annotated, Any

from fastapi import APIRouter, Depends, Request
from python_multipart.exceptions import FormParserError
from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.concurrency import run_in_threadpool
from starlette.requests import ClientDisconnect

from autocal.service.auth import app_settings, require_token
from autocal.service.paths import PARTIAL_SUFFIX
from autocal.service.schemas import ApiError, ErrorBody, UploadCreated
from autocal.service.settings import Settings

logger = logging.getLogger(__name__)

router = APIRouter(tags=["uploads"])

#: Bytes of multipart framing and form fields tolerated beyond the file size limit.
OVERHEAD_BYTES = 1024 * 1024
#: Name of the form part holding the file.
FILE_FIELD = "file"

_BODY_SCHEMA = {
    "required": True,
    "content": {
        "multipart/form-data": {
            "schema": {
                "type": "object",
                "properties": {FILE_FIELD: {"type": "string", "format": "binary"}},
                "required": [FILE_FIELD],
            }
        }
    },
}


def safe_filename(name: str) -> str:
    """Return a harmless file name: the last path component, ``[A-Za-z0-9._-]`` only.

    Parameters
    ----------
    name
        The client's file name.

    Returns
    -------
    str
        At most 200 characters, no leading dot, never empty (``upload.bin``).
    """
    base = name.replace("\\", "/").rsplit("/", 1)[-1]
    base = re.sub(r"[^A-Za-z0-9._-]", "_", base).lstrip(".")[:200]
    if base.endswith(PARTIAL_SUFFIX):
        base += "_"
    return base or "upload.bin"


class _AbortError(Exception):
    """Stops the parser with an HTTP error."""

    def __init__(self, error: ApiError) -> None:
        super().__init__(error.detail)
        self.error = error


class _UploadSink:
    """Multipart callbacks writing the ``file`` part to disk while counting and hashing."""

    def __init__(self, folder: Path, limit: int) -> None:
        self.folder = folder
        self.limit = limit
        self.headers: dict[bytes, bytes] = {}
        self._field = bytearray()
        self._value = bytearray()
        self.handle: IO[bytes] | None = None
        self.partial: Path | None = None
        self.filename = ""
        self.nbytes = 0
        self.nfiles = 0
        self.finished = False
        self.sha256 = hashlib.sha256()

    def callbacks(self) -> dict[str, Any]:
        return {
            "on_part_begin": self._part_begin,
            "on_header_field": self._header_field,
            "on_header_value": self._header_value,
            "on_header_end": self._header_end,
            "on_headers_finished": self._headers_finished,
            "on_part_data": self._part_data,
            "on_part_end": self._part_end,
        }

    def _part_begin(self) -> None:
        self.headers = {}

    def _header_field(self, data: bytes, start: int, end: int) -> None:
        self._field += data[start:end]

    def _header_value(self, data: bytes, start: int, end: int) -> None:
        self._value += data[start:end]

    def _header_end(self) -> None:
        self.headers[bytes(self._field).lower()] = bytes(self._value)
        self._field.clear()
        self._value.clear()

    def _headers_finished(self) -> None:
        _, params = parse_options_header(self.headers.get(b"content-disposition", b""))
        name = params.get(b"name", b"").decode("utf-8", "replace")
        if name != FILE_FIELD or b"filename" not in params:
            return  # other form fields are ignored
        if self.nfiles:
            message = f"send one file per upload (one part named {FILE_FIELD!r})"
            raise _AbortError(ApiError(400, message))
        self.nfiles = 1
        self.filename = safe_filename(params[b"filename"].decode("utf-8", "replace"))
        self.partial = self.folder / (self.filename + PARTIAL_SUFFIX)
        self.handle = open(self.partial, "wb")  # noqa: SIM115 - closed in _part_end/close

    def _part_data(self, data: bytes, start: int, end: int) -> None:
        if self.handle is None:
            return
        self.nbytes += end - start
        if self.nbytes > self.limit:
            raise _AbortError(_too_large(self.limit))
        chunk = data[start:end]
        self.handle.write(chunk)
        self.sha256.update(chunk)

    def _part_end(self) -> None:
        if self.handle is not None:
            self.handle.close()
            self.handle = None
            self.finished = True

    def close(self) -> None:
        if self.handle is not None:
            self.handle.close()
            self.handle = None


#: The first bytes of every HDF5 file (UVH5, calh5, EDGES HDF5, solution.h5).
HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def check_uploaded_file(path: Path, name: str) -> None:
    """Refuse (422) an upload that cannot be any input: empty, or HDF5 that does not open.

    Other content (a text prior table, an ACQ file, calfits) is judged when a job names
    it: ``POST /jobs`` reads a UVH5 input's header as the worker would.
    """
    import h5py

    if path.stat().st_size == 0:
        raise ApiError(422, f"{name} is empty: upload the file's contents")
    with open(path, "rb") as handle:
        head = handle.read(len(HDF5_SIGNATURE))
    if head != HDF5_SIGNATURE:
        return
    try:
        with h5py.File(path, "r") as h5:
            list(h5.keys())
    except (OSError, RuntimeError) as err:  # h5py raises both for a damaged file
        raise ApiError(
            422,
            f"{name} starts as an HDF5 file but HDF5 cannot open it ({err}): it is truncated "
            "or corrupt; upload a complete copy",
        ) from None


def _too_large(limit: int) -> ApiError:
    return ApiError(
        413,
        f"the upload exceeds the limit of {limit} bytes (AUTOCAL_MAX_UPLOAD_BYTES); "
        "nothing was kept",
    )


@router.post(
    "/uploads",
    status_code=201,
    response_model=UploadCreated,
    dependencies=[Depends(require_token)],
    openapi_extra={"requestBody": _BODY_SCHEMA},
    responses={
        code: {"model": ErrorBody, "description": text}
        for code, text in {
            400: "malformed multipart body or no file part",
            401: "missing or wrong API token",
            429: "too many failed authentications; see Retry-After",
            413: "the file exceeds AUTOCAL_MAX_UPLOAD_BYTES",
            415: "not multipart/form-data",
            422: "an empty file, or an HDF5 file HDF5 cannot open (truncated)",
            503: "writes disabled: no API token configured",
        }.items()
    },
)
async def create_upload(
    request: Request, settings: Annotated[Settings, Depends(app_settings)]
) -> UploadCreated:
    """Upload one input file as multipart/form-data (part ``file``).

    Returns its ``upload_id`` (usable in ``POST /jobs`` inputs), server path, size and
    SHA-256. The original file name is kept (sanitised) so that ``zen.<JD>...`` names
    still tell the night.
    """
    limit = settings.max_upload_bytes
    ctype, params = parse_options_header(request.headers.get("content-type", ""))
    if ctype != b"multipart/form-data":
        raise ApiError(
            415, f"send the file as multipart/form-data with a part named {FILE_FIELD!r}"
        )
    boundary = params.get(b"boundary")
    if not boundary or len(boundary) > 200:
        raise ApiError(400, "the multipart Content-Type has no (valid) boundary")
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit + OVERHEAD_BYTES:
        raise _too_large(limit)

    upload_id = uuid.uuid4().hex
    folder = settings.uploads_dir.expanduser().resolve() / upload_id
    await run_in_threadpool(folder.mkdir, parents=True, exist_ok=False)
    sink = _UploadSink(folder, limit)
    parser = MultipartParser(boundary, sink.callbacks())
    received = 0
    try:
        async for chunk in request.stream():
            received += len(chunk)
            if received > limit + OVERHEAD_BYTES:
                raise _too_large(limit)
            if chunk:
                await run_in_threadpool(parser.write, chunk)
        await run_in_threadpool(parser.finalize)
        sink.close()
        if not sink.nfiles:
            raise ApiError(400, f"no file part named {FILE_FIELD!r} (with a filename) in the body")
        if not sink.finished or sink.partial is None:
            raise ApiError(400, "the multipart body ended before the file part was complete")
        await run_in_threadpool(check_uploaded_file, sink.partial, sink.filename)
        final = folder / sink.filename
        await run_in_threadpool(os.replace, sink.partial, final)
    except _AbortError as abort:
        sink.close()
        shutil.rmtree(folder, ignore_errors=True)
        raise abort.error from None
    except ClientDisconnect:
        sink.close()
        shutil.rmtree(folder, ignore_errors=True)
        logger.info("upload %s interrupted by the client; removed", upload_id)
        raise ApiError(400, "the upload was interrupted; nothing was kept") from None
    except ApiError:
        sink.close()
        shutil.rmtree(folder, ignore_errors=True)
        raise
    except FormParserError as err:
        sink.close()
        shutil.rmtree(folder, ignore_errors=True)
        raise ApiError(400, f"malformed multipart body: {err}") from None
    except BaseException:
        sink.close()
        shutil.rmtree(folder, ignore_errors=True)
        raise
    logger.info("upload %s: %s, %d bytes", upload_id, final.name, sink.nbytes)
    return UploadCreated(
        upload_id=upload_id,
        path=str(final),
        filename=final.name,
        bytes=sink.nbytes,
        sha256=sink.sha256.hexdigest(),
    )
