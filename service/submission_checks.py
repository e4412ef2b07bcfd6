"""Checks at submission of what a job would only find out later, in the worker.

Run after the options are validated and the paths resolved, before the job is queued:

- the same file named twice in a list (``inputs``, ``reference``), after resolution: a
  relative and an absolute path, or an upload id and its file, are the same input;
- a frequency range outside the band of the data: a range holding no channel of some UVH5
  input is refused with that file's band (from the header :func:`check_uvh5_inputs` reads);
- a sky that would flag every channel: a sky constant in time (``uniform:T``, or a power
  law of a uniform sky) leaves the receiver temperature and the gain inseparable, so every
  channel's normal matrix is singular, unless a receiver-temperature prior ties them;
- options that do not apply to the kind of inputs (:func:`check_input_kind`: EDGES options
  on UVH5 files, ``rfi_flagging`` on EDGES spectra);
- UVH5 inputs whose header the reader refuses (not HDF5, empty, truncated, not UVH5,
  without auto-correlations) and selections they cannot satisfy (an antenna without an
  auto-correlation, a polarisation they do not hold, an LST range holding none of their
  integrations): :func:`check_uvh5_inputs` runs the reader's own header checks
  (:func:`autocal.io.uvh5_meta.read_file_meta`, no data read), so the job is refused with
  the message the worker would have failed with.

Miriad folders and EDGES files are left to the worker, which reports them.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from autocal.errors import AutocalError

logger = logging.getLogger(__name__)


class SubmissionError(AutocalError):
    """An option that the job would fail (or flag everything) on; names the field.

    Parameters
    ----------
    field
        The request field at fault (``freq_range_mhz``, ``inputs``, ``sky``...).
    message
        What is wrong and what to do.
    """

    def __init__(self, field: str, message: str) -> None:
        super().__init__(message)
        self.field = field


def check_distinct(paths: Sequence[str | Path], field: str) -> None:
    """Refuse a list of resolved paths that names one file more than once.

    Parameters
    ----------
    paths
        Resolved paths, in the order given.
    field
        The request field they came from.

    Raises
    ------
    SubmissionError
        Naming the repeated file and the positions it was given at.
    """
    positions: dict[str, list[int]] = {}
    for index, path in enumerate(paths):
        positions.setdefault(str(path), []).append(index)
    repeated = {path: where for path, where in positions.items() if len(where) > 1}
    if repeated:
        path, where = next(iter(repeated.items()))
        raise SubmissionError(
            field,
            f"{field}: items {', '.join(str(i) for i in where)} are the same file "
            f"({Path(path).name}); list each file once",
        )


def check_sky_varies(sky: str | None, trxr_prior: object) -> None:
    """Refuse a sky constant in time when nothing else separates gain and receiver.

    Parameters
    ----------
    sky
        The sky specification (``None``: the default, a Galactic model).
    trxr_prior
        The receiver-temperature prior, if any (it makes the fit solvable).

    Raises
    ------
    SubmissionError
        For ``sky``.
    """
    from autocal.sky.models import PowerLawSky, UniformSky, get_sky

    if sky is None or trxr_prior is not None:
        return
    model = get_sky(str(sky))
    base = model.base if isinstance(model, PowerLawSky) else model
    if isinstance(base, UniformSky):
        raise SubmissionError(
            "sky",
            f"sky {sky!r} is the same in every direction, so the sky temperature seen by "
            "the beam does not change with LST: the gain and the receiver temperature "
            "cannot be told apart and every channel would be flagged (singular). Use a "
            "sky map (gsm2008, gsm2016, lfsm, haslam) or give trxr_prior",
        )


def check_input_kind(paths: Sequence[Path], opts: Mapping[str, Any]) -> str:
    """Refuse options that do not apply to the inputs' kind; return the kind.

    Parameters
    ----------
    paths
        Resolved inputs.
    opts
        The options given.

    Returns
    -------
    str
        ``uvh5``, ``miriad`` or ``edges`` (:func:`autocal.pipeline.sources.detect_format`).

    Raises
    ------
    SubmissionError
        For the first option that does not apply
        (:func:`autocal.pipeline.option_rules.input_kind_refusals`), or for ``inputs`` that
        mix formats.
    """
    from autocal.pipeline.config import PipelineError
    from autocal.pipeline.option_rules import input_kind_refusals
    from autocal.pipeline.sources import detect_format

    try:
        kind = detect_format(list(paths), str(opts.get("input_format", "auto")))
    except PipelineError as err:
        raise SubmissionError("inputs", str(err)) from None
    for field, why in input_kind_refusals(opts, kind):
        raise SubmissionError(field, why)
    return kind


def check_uvh5_inputs(paths: Sequence[Path], opts: Mapping[str, Any]) -> None:
    """Refuse UVH5 inputs the reader would refuse, and selections they cannot satisfy.

    Each file's header is read as the worker's reader reads it
    (:func:`autocal.io.uvh5_meta.read_file_meta`; no data), and the antenna and
    polarisation selections are made as it makes them; an LST range is refused when no
    input has an integration in it.

    Parameters
    ----------
    paths
        Resolved UVH5 inputs.
    opts
        The options given (``freq_range_mhz``, ``antennas``, ``pols``, ``lst_range_h``).

    Raises
    ------
    SubmissionError
        For ``inputs`` (the reader's message: not HDF5, truncated, not UVH5, no
        auto-correlations), ``freq_range_mhz``, ``antennas``, ``pols`` or ``lst_range_h``.
    """
    from autocal.core.observation import ObservationError
    from autocal.io.uvh5_meta import (
        UVH5FormatError,
        lst_mask,
        read_file_meta,
        select_antennas,
        select_pols,
    )

    lst_range = opts.get("lst_range_h")
    in_range = 0
    lsts: list[np.ndarray] = []
    for path in paths:
        try:
            meta = read_file_meta(Path(path))
        except (UVH5FormatError, ObservationError) as err:
            raise SubmissionError("inputs", str(err)) from None
        except (
            OSError,
            RuntimeError,
            KeyError,
            ValueError,
            TypeError,
        ) as err:  # a header h5py cannot read
            raise SubmissionError(
                "inputs",
                f"{Path(path).name}: its header cannot be read ({type(err).__name__}: {err}); "
                "the file is corrupt: copy or download it again",
            ) from None
        _check_band(meta.path, meta.freqs, opts.get("freq_range_mhz"))
        for field, select in (("antennas", select_antennas), ("pols", select_pols)):
            if opts.get(field) is not None:
                try:
                    select(meta, opts[field])
                except ObservationError as err:
                    raise SubmissionError(field, str(err)) from None
        if lst_range is not None:
            in_range += int(lst_mask(meta.lsts, tuple(lst_range)).sum())
            lsts.append(meta.lsts)
    if lst_range is not None and lsts and not in_range:
        every = np.concatenate(lsts)
        raise SubmissionError(
            "lst_range_h",
            f"lst_range_h {lst_range[0]:g}-{lst_range[1]:g} h holds no integration of the "
            f"input(s), whose LSTs are {every.min():.4g}-{every.max():.4g} h: give a range "
            "inside them (start > stop wraps through 24 h)",
        )


def check_references(paths: Sequence[str | Path]) -> None:
    """Refuse reference files that are not calibration files (calfits or calh5).

    Each file's first bytes and header are checked as the comparison's reader checks them
    (:func:`autocal.io.calsol_files.sniff_cal_file`), so a job is not run through its
    whole calibration only to fail when it reads its reference.

    Raises
    ------
    SubmissionError
        For ``reference``, with the reader's message.
    """
    from autocal.io.calsol_files import CalsolFormatError, sniff_cal_file

    for path in paths:
        try:
            sniff_cal_file(Path(path))
        except CalsolFormatError as err:
            raise SubmissionError("reference", f"reference: {err}") from None


def _check_band(path: Path, freqs: np.ndarray, freq_range_mhz: Sequence[float] | None) -> None:
    """Refuse a frequency range that holds no channel of the file (its header's ``freqs``).

    Raises
    ------
    SubmissionError
        For ``freq_range_mhz``, naming the file and its band.
    """
    if freq_range_mhz is None:
        return
    lo, hi = sorted(float(f) * 1e6 for f in freq_range_mhz)
    if not np.any((freqs >= lo) & (freqs <= hi)):
        raise SubmissionError(
            "freq_range_mhz",
            f"freq_range_mhz {lo / 1e6:g}-{hi / 1e6:g} MHz holds no channel of "
            f"{Path(path).name}, whose band is {freqs.min() / 1e6:.6g}-"
            f"{freqs.max() / 1e6:.6g} MHz ({freqs.size} channels): give a range inside it",
        )
