"""Auto-correlations in Miriad data sets (old HERA H1C files), through pyuvdata.

pyuvdata reads the autos of one or several consecutive Miriad directories into a UVData
object, which is converted to UVH5 in a private temporary folder and read with
:func:`autocal.io.uvh5.read_uvh5`, so both formats share one reader, one set of checks
and one :class:`~autocal.core.observation.Observation` layout. ``meta["files"]`` and
``meta["sha256"]`` name the original Miriad directories (digest of their ``visdata``).
"""

from __future__ import annotations

import logging
import tempfile
from collections.abc import Sequence
from pathlib import Path

from autocal.core.files import file_checksum
from autocal.core.observation import Observation
from autocal.errors import AutocalError
from autocal.io.pyuvdata_helpers import uvdata_class, warnings_to_log
from autocal.io.uvh5 import read_uvh5
from autocal.io.uvh5_meta import UVH5FormatError

logger = logging.getLogger(__name__)


class MiriadFormatError(AutocalError):
    """A path is not a readable Miriad data set with auto-correlations."""


def is_miriad(path: str | Path) -> bool:
    """Return whether ``path`` looks like a Miriad data set (a folder with ``visdata``)."""
    path = Path(path)
    return path.is_dir() and (path / "visdata").is_file() and (path / "vartable").is_file()


def read_miriad(
    paths: str | Path | Sequence[str | Path],
    *,
    antennas: Sequence[int] | None = None,
    pols: Sequence[str] | None = None,
    freq_range: tuple[float, float] | None = None,
    lst_range: tuple[float, float] | None = None,
) -> Observation:
    """Read the auto-correlations of Miriad data sets into an :class:`Observation`.

    Parameters are those of :func:`autocal.io.uvh5.read_uvh5`.

    Raises
    ------
    MiriadFormatError
        If a path is not a Miriad data set, or pyuvdata cannot read it.
    """
    UVData = uvdata_class()

    path_list = [Path(paths)] if isinstance(paths, (str, Path)) else [Path(p) for p in paths]
    if not path_list:
        raise MiriadFormatError("no Miriad data sets given")
    for path in path_list:
        if not is_miriad(path):
            raise MiriadFormatError(
                f"{path} is not a Miriad data set (a folder with 'visdata' and 'vartable'); "
                "check the path"
            )
    try:
        with warnings_to_log(f"reading {[p.name for p in path_list]}", logger):
            uv = UVData.from_file([str(p) for p in path_list], ant_str="auto")
    except Exception as err:
        raise MiriadFormatError(
            f"pyuvdata cannot read the autos of {[p.name for p in path_list]}: "
            f"{type(err).__name__}: {err}"
        ) from err
    with tempfile.TemporaryDirectory(prefix="autocal-miriad-") as tmp:
        converted = Path(tmp) / "autos.uvh5"
        uv.write_uvh5(str(converted))
        try:
            obs = read_uvh5(
                converted, antennas=antennas, pols=pols, freq_range=freq_range, lst_range=lst_range
            )
        except UVH5FormatError as err:
            raise MiriadFormatError(f"{[p.name for p in path_list]}: {err}") from err
    files = [str(p.expanduser().absolute()) for p in path_list]
    obs.meta.update(
        {
            "source": "miriad",
            "files": files,
            "sha256": {f: file_checksum(Path(f) / "visdata") for f in files},
        }
    )
    logger.info("read %d Miriad data set(s): %s", len(files), obs.describe())
    return obs
