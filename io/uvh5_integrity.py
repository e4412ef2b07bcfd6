"""Whether the data of a UVH5 file can be checked for corruption, and the check's failure.

HDF5 can store a Fletcher-32 checksum with every chunk of a data set (the ``fletcher32``
filter, ``h5py``'s ``create_dataset(..., fletcher32=True)``); the library then verifies each
chunk as it is read and fails the read of a corrupt one. A UVH5 file whose ``visdata``,
``flags`` and ``nsamples`` all carry the filter is *checksummed*: the block reader refuses
it with :class:`DataIntegrityError` if a chunk it reads fails. Files written without the
filter (pyuvdata's default, the HERA correlator's files) cannot be checked at all: bytes
flipped inside a data chunk decode to other numbers that nothing distinguishes from data.
Their status is ``unchecked``, logged once per file and recorded in the run's provenance
(``integrity``); the SHA-256 in the provenance only identifies the bytes that were read.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import h5py

from autocal.io.uvh5_meta import UVH5FormatError

logger = logging.getLogger(__name__)

#: The data sets whose chunks must carry checksums for a file to count as checksummed.
DATA_SETS = ("visdata", "flags", "nsamples")


class DataIntegrityError(UVH5FormatError):
    """A checksummed chunk of a UVH5 data set failed its check: the file is corrupt."""


def data_set_integrity(h5: h5py.File) -> dict[str, bool]:
    """Return, per data set of ``Data``, whether its chunks carry Fletcher-32 checksums.

    Parameters
    ----------
    h5
        An open UVH5 file.

    Returns
    -------
    dict
        ``visdata``, ``flags``, ``nsamples`` -> ``True`` if checksummed (absent data sets
        are left out).
    """
    data = h5.get("Data")
    if data is None:
        return {}
    return {name: bool(data[name].fletcher32) for name in DATA_SETS if name in data}


def integrity_status(checked: dict[str, bool]) -> str:
    """Return ``checksummed`` (every data set), ``partial`` or ``unchecked`` (none)."""
    if checked and all(checked.values()):
        return "checksummed"
    return "partial" if any(checked.values()) else "unchecked"


def file_integrity(path: str | Path) -> dict[str, Any]:
    """Describe what of a UVH5 file's data can be verified (for provenance).

    Parameters
    ----------
    path
        The file.

    Returns
    -------
    dict
        ``status`` (``checksummed``, ``partial``, ``unchecked`` or ``unknown`` for a file
        that is not readable HDF5), ``checksummed`` (data set -> bool) and ``note``.
    """
    try:
        with h5py.File(path, "r") as h5:
            checked = data_set_integrity(h5)
    except (OSError, KeyError) as err:
        return {"status": "unknown", "checksummed": {}, "note": f"not readable HDF5: {err}"}
    status = integrity_status(checked)
    notes = {
        "checksummed": "every data chunk read was verified (HDF5 Fletcher-32)",
        "partial": "only some data sets carry HDF5 checksums; the others cannot be verified",
        "unchecked": "the data sets carry no HDF5 checksums: corruption of the data "
        "cannot be detected",
    }
    return {"status": status, "checksummed": checked, "note": notes[status]}


def log_unchecked(path: Path, checked: dict[str, bool]) -> None:
    """Log, once per read of a file, that (some of) its data cannot be verified."""
    status = integrity_status(checked)
    if status != "checksummed":
        missing = ", ".join(name for name, ok in checked.items() if not ok)
        logger.info(
            "%s: %s without HDF5 checksums (%s): data corruption cannot be detected",
            path.name,
            status,
            missing,
        )


def read_error(path: Path, dset: h5py.Dataset, what: str, err: OSError) -> UVH5FormatError:
    """Return the error for a failed read of ``dset``: a checksum failure or corruption.

    Parameters
    ----------
    path
        The file.
    dset
        The data set whose read failed.
    what
        What was being read (e.g. ``"integrations 0-9"``).
    err
        The HDF5 error.

    Returns
    -------
    UVH5FormatError
        :class:`DataIntegrityError` when the data set is checksummed (HDF5 verifies every
        chunk it decodes, so a failed read of such a data set is a failed check or worse).
    """
    if dset.fletcher32:
        return DataIntegrityError(
            f"{path}: a chunk of {dset.name} ({what}) failed its HDF5 Fletcher-32 checksum "
            f"({err}); the file is corrupt: copy it again from the archive, or leave it out"
        )
    return UVH5FormatError(
        f"{path}: cannot read {dset.name} for {what} ({err}); the file is corrupt or "
        "truncated: copy it again from the archive, or leave it out"
    )


def input_integrity(input_format: str, files: Any) -> dict[str, dict[str, Any]] | None:
    """Return :func:`file_integrity` of every input file of a UVH5 run (``None`` otherwise).

    Parameters
    ----------
    input_format
        The run's input format (``uvh5``, ``miriad``, ``edges``...).
    files
        The input files (an iterable of paths, e.g. the provenance's checksum keys).

    Returns
    -------
    dict or None
        Path -> integrity, for the provenance of a UVH5 run.
    """
    if input_format != "uvh5":
        return None
    return {str(path): file_integrity(path) for path in files}
