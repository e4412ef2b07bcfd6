"""Locating reference data files and keeping third-party downloads offline.

The data folder is given by the environment variable ``AUTOCAL_DATA_DIR``. When it is
unset, the ``shared/data`` folder beside the source checkout is used if it exists
(the layout of this project's CI). Files are addressed by their path relative to that
folder, e.g. ``sky/gsm2008_components_nside64.h5``.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

from astropy.utils.data import import_file_to_cache, is_url_in_cache

from autocal.core.offline import downloads_allowed
from autocal.errors import AutocalError

logger = logging.getLogger(__name__)

#: Relative path of the pygdsm-format GSM2008 component file in the data folder.
GSM2008_FILE = "sky/gsm2008_components_nside64.h5"
#: Relative path of the HERA Fagnoni power beam.
HERA_BEAM_FILE = "hera/beams/HERA_NF_dipole_power.beamfits"
#: Relative paths of the EDGES FEKO beams.
EDGES_BEAM_FILES = {
    "edges-low": "edges/beams/low/default.txt",
    "edges-low-45deg": "edges/beams/low/45deg.txt",
    "edges-mid": "edges/beams/mid/default.txt",
    "edges-high": "edges/beams/high/default.txt",
}
#: The published EDGES 2018 low-band spectrum (Bowman et al. 2018, Figure 1).
EDGES_2018_SPECTRUM = "edges/published/edges2018_figure1_plotdata.csv"


class DataFileMissingError(FileNotFoundError, AutocalError):
    """A reference data file is not available locally (a missing file and a user error)."""


def data_dir(required: bool = False) -> Path | None:
    """Return the reference data folder.

    Parameters
    ----------
    required
        Raise instead of returning ``None`` when no folder is found.

    Returns
    -------
    pathlib.Path or None
        ``$AUTOCAL_DATA_DIR`` if set, else ``<checkout>/../shared/data`` if it exists.

    Raises
    ------
    DataFileMissingError
        If ``required`` and no data folder exists.
    """
    env = os.environ.get("AUTOCAL_DATA_DIR")
    if env:
        path = Path(env).expanduser().resolve()
        if path.is_dir():
            return path
        if required:
            raise DataFileMissingError(
                f"AUTOCAL_DATA_DIR={env!r} is not a folder; point it at the autocal data "
                "folder (the one holding sky/, hera/ and edges/)"
            )
        return None
    checkout = Path(__file__).resolve().parent.parent
    candidate = checkout.parent / "shared" / "data"
    if candidate.is_dir():
        return candidate
    if required:
        raise DataFileMissingError(
            "no data folder found: set AUTOCAL_DATA_DIR to the folder holding sky/, hera/ "
            "and edges/ (in this project's CI it is ../shared/data)"
        )
    return None


def data_file(relpath: str, purpose: str = "") -> Path:
    """Return the absolute path of a file in the data folder, checking that it exists.

    Parameters
    ----------
    relpath
        Path relative to the data folder.
    purpose
        What the file is for; used in the error message.

    Returns
    -------
    pathlib.Path
        The existing file.

    Raises
    ------
    DataFileMissingError
        If the data folder or the file is missing; the message names the file and how
        to provide it.
    """
    root = data_dir(required=False)
    what = f" ({purpose})" if purpose else ""
    if root is None:
        raise DataFileMissingError(
            f"data file {relpath}{what} is needed but no data folder is configured: set "
            "AUTOCAL_DATA_DIR to the folder that holds it"
        )
    path = root / relpath
    if not path.is_file():
        raise DataFileMissingError(
            f"data file {path}{what} does not exist: copy it there or set AUTOCAL_DATA_DIR "
            "to a data folder that has it"
        )
    return path


def ensure_pygdsm_file(urls: list[str], relpath: str | None, model: str) -> None:
    """Make a pygdsm data file available offline through astropy's download cache.

    pygdsm fetches its component files with ``astropy.utils.data.download_file(url,
    cache=True)``. If none of ``urls`` is cached yet and a local copy exists in the data
    folder, the copy is registered in the cache under every URL, so pygdsm finds it
    without the internet.

    Parameters
    ----------
    urls
        The URLs pygdsm tries, in order.
    relpath
        The local copy relative to the data folder, or ``None`` if there is none.
    model
        Sky model name for messages.

    Raises
    ------
    DataFileMissingError
        If the file is neither cached, nor available locally, nor downloadable.
    """
    if any(is_url_in_cache(url) for url in urls):
        return
    local: Path | None = None
    if relpath is not None:
        root = data_dir()
        if root is not None and (root / relpath).is_file():
            local = root / relpath
    if local is not None:
        for url in urls:
            import_file_to_cache(url, str(local), remove_original=False)
        logger.info("registered %s in astropy's cache for pygdsm (%s)", local, model)
        return
    if downloads_allowed():
        logger.warning("%s data will be downloaded by pygdsm from %s", model, urls[0])
        return
    hint = f" or place it at $AUTOCAL_DATA_DIR/{relpath}" if relpath else ""
    raise DataFileMissingError(
        f"sky model {model!r} needs the pygdsm data file {urls[0]}, which is not in astropy's "
        f"cache: import a local copy with astropy.utils.data.import_file_to_cache(url, path)"
        f"{hint}, or set AUTOCAL_ALLOW_DOWNLOAD=1 on a machine with internet access"
    )
