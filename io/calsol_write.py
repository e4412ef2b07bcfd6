"""Writing an autocal solution's gains as calh5 or calfits files through pyuvdata.

:func:`write_calh5` and :func:`write_calfits` write the ``UVCal`` that
:func:`autocal.io.calsol_uvcal.solution_to_uvcal` builds (gains ``|g| = sqrt(G)``,
``gain_convention="divide"``, ``gain_scale="K str"``, ``pol_convention="avg"``, the time model
at every fitted integration; see that module for what the file
holds). Files are written atomically (temporary file in the same folder, then rename)
and existing files are replaced only with ``overwrite=True``.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

from autocal.core.files import atomic_path
from autocal.io.calsol_files import CalsolFormatError
from autocal.io.calsol_uvcal import solution_to_uvcal
from autocal.io.pyuvdata_helpers import warnings_to_log

if TYPE_CHECKING:
    from autocal.fit.solution import Solution

logger = logging.getLogger(__name__)


def _warnings_to_log(context: str) -> Any:
    return warnings_to_log(context, logger, logging.DEBUG)


def _write(
    solution: Solution, path: str | Path, file_type: str, overwrite: bool, **kwargs: Any
) -> Path:
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
    uvc = solution_to_uvcal(solution, shared_times=True, **kwargs)
    with atomic_path(path) as tmp, _warnings_to_log(f"writing {path.name}"):
        tmp.unlink()  # pyuvdata writes a new file
        try:
            if file_type == "calh5":
                uvc.write_calh5(str(tmp))
            else:
                uvc.write_calfits(str(tmp))
        except ValueError as err:
            raise CalsolFormatError(f"cannot write {path} as {file_type}: {err}") from err
    logger.info(
        "wrote %s (%s): %d antennas, pols %s, %d channels, %d time(s)",
        path,
        file_type,
        uvc.Nants_data,
        ",".join(solution.pols),
        uvc.Nfreqs,
        uvc.Ntimes,
    )
    return path


def write_calh5(
    solution: Solution,
    path: str | Path,
    *,
    overwrite: bool = False,
    time_range: tuple[float, float] | None = None,
    per_time: bool | None = None,
    telescope: str | None = None,
    site: Any = None,
    history: str = "",
) -> Path:
    """Write a solution's gains ``|g| = sqrt(G)`` as a calh5 file (atomically).

    Parameters
    ----------
    solution
        An :class:`autocal.fit.solution.Solution`.
    path
        Output file.
    overwrite
        Replace an existing file.
    time_range, per_time, telescope, site, history
        See :func:`~autocal.io.calsol_uvcal.solution_to_uvcal`.

    Returns
    -------
    pathlib.Path
        The written file.

    Raises
    ------
    FileExistsError
        If ``path`` exists and ``overwrite`` is false.
    CalsolFormatError
        If the solution cannot be written.
    """
    return _write(
        solution,
        path,
        "calh5",
        overwrite,
        time_range=time_range,
        per_time=per_time,
        telescope=telescope,
        site=site,
        history=history,
    )


def write_calfits(
    solution: Solution,
    path: str | Path,
    *,
    overwrite: bool = False,
    time_range: tuple[float, float] | None = None,
    per_time: bool | None = None,
    telescope: str | None = None,
    site: Any = None,
    history: str = "",
) -> Path:
    """Write a solution's gains ``|g| = sqrt(G)`` as a calfits file (atomically).

    calfits needs uniformly spaced channels. Parameters, return value and errors as
    :func:`write_calh5`.
    """
    return _write(
        solution,
        path,
        "calfits",
        overwrite,
        time_range=time_range,
        per_time=per_time,
        telescope=telescope,
        site=site,
        history=history,
    )
