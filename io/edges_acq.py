"""EDGES ACQ files (FASTSPEC's format), read and written through the ``read_acq`` package.

:func:`read_acq_spectra` decodes ACQ files (``read_acq.decode_file``) into
:class:`~autocal.io.edges_spectra.EdgesSpectra`; :func:`write_acq` writes spectra on the
native grid as an ACQ file (``read_acq.encode``).

ACQ format (what ``read_acq`` decodes; verified on every file of the data folder)
---------------------------------------------------------------------------------
* A text file. Header lines start with ``;`` (``; FASTSPEC v1.1.0``, then
  ``;--key: value`` with the acquisition settings, e.g. ``num_channels``,
  ``acquisition_rate`` (MS/s), ``samples_per_accumulation``, ``switch_delay``).
* Then, per switch position, a comment line ``# swpos 0 data_drops 0 adcmax 0.29
  adcmin -0.33 temp 0 C nblk 2974 nspec 32768`` and a data line
  ``2019:335:00:00:06 0 0.000 0.006104 200.000 0.3 spectrum <4 chars per channel>``.
  Positions come in cycles 0, 1, 2; incomplete cycles are dropped by ``read_acq``.
* Each channel is 4 base64 characters (A-Z a-z 0-9 + /) holding a 24-bit integer
  ``k = -10 log10(p) * 1e5``: powers are stored in dB with 1e-5 dB steps (relative
  precision 2.3e-6, truncated towards higher power), clipped to ``1e-16.7 <= p <= 1``.
  FASTSPEC blanks the first 10 channels (they hold the floor ``10**-16.7``).
* 32768 channels over 0-200 MHz: channel ``k`` is at ``k * 200 MHz / 32768`` (the
  convention of ``read_acq`` and ``edges-cal``); ``freq_min`` must be 0 for that to hold,
  so the writer always writes the whole native band.
* Timestamps are ``YYYY:DDD:HH:MM:SS`` UTC with 1 s resolution. FASTSPEC writes the
  *same* timestamp on the three lines of a cycle (the cycle's time): that is the time
  used for the whole cycle here (and for its LST).
* Integration time per switch position: ``nblk`` spectra of ``2 num_channels`` samples at
  ``acquisition_rate``: ``t = nblk * 2 * num_channels / acquisition_rate`` (0.487 s for
  the 2019 Receiver01 lab files, 6.71 s for the EDGES-3 files). Checked against the data:
  the EDGES-3 channel scatter matches ``1 / sqrt(dnu t)`` to 1 %; the 2019 files scatter
  1.45x more (their window's noise bandwidth is about 2 channels).
  ``samples_per_accumulation`` is not used: it disagrees with the cycle timing of the
  2019 files (it would give 10.7 s per position, while their cycles last 44 s with a
  13 s switch delay per position). When the header lacks ``num_channels`` or
  ``acquisition_rate``, ``nspec`` and 400 MS/s are assumed and ``meta`` says so.
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from autocal.core.files import atomic_path, file_checksum
from autocal.io.edges_spectra import (
    NATIVE_DF_HZ,
    NATIVE_FMAX_HZ,
    NATIVE_NCHAN,
    EdgesFormatError,
    EdgesSpectra,
    jsonable,
)
from autocal.io.edges_time import acq_time_to_jd, jd_to_acq_time

logger = logging.getLogger(__name__)

#: ADC sample rate assumed when an ACQ header does not give ``acquisition_rate``.
DEFAULT_ADC_RATE_HZ = 400e6
#: Smallest power an ACQ file can hold (-167 dB); FASTSPEC writes it in blank channels.
ACQ_FLOOR = 10.0 ** (-16.7)
#: Largest power an ACQ file can hold (0 dB); larger values are clipped by the encoder.
ACQ_MAX = 1.0

#: read_acq warnings that only describe header lines without a value (every real file).
_HARMLESS = ("has no value",)


def acq_integration_time(header: dict[str, Any]) -> tuple[float, str]:
    """Integration time per switch position (s) from an ACQ header, and how it was found.

    ``t = nblk * 2 * num_channels / acquisition_rate`` (``acquisition_rate`` in MS/s).
    Without ``num_channels`` or ``acquisition_rate`` in the header, ``nspec`` and
    400 MS/s are used and the source says ``"estimate"``.
    """
    nblk = float(header["nblk"])
    nchan = header.get("num_channels")
    rate = header.get("acquisition_rate")
    source = "nblk * 2 * num_channels / acquisition_rate (ACQ header)"
    if not isinstance(nchan, int | float) or nchan <= 0:
        nchan = float(header.get("nfreq", NATIVE_NCHAN))
        source = "estimate: nblk * 2 * nspec / 400 MS/s (header lacks num_channels)"
    if not isinstance(rate, int | float) or rate <= 0:
        rate_hz = DEFAULT_ADC_RATE_HZ
        source = "estimate: nblk * 2 * nspec / 400 MS/s (header lacks acquisition_rate)"
    else:
        rate_hz = float(rate) * 1e6
    return nblk * 2.0 * float(nchan) / rate_hz, source


def _not_acq(path: Path, why: str) -> EdgesFormatError:
    return EdgesFormatError(
        f"{path} is not a readable EDGES ACQ file ({why}). Check that it is an ACQ "
        "spectrum file written by FASTSPEC (or autocal) and that it was copied completely; "
        "re-copy it from the archive if it is damaged."
    )


def _decode_acq(path: Path, allow_partial: bool) -> tuple[np.ndarray, np.ndarray, Any]:
    """Decode one ACQ file with read_acq, turning its failures into EdgesFormatError."""
    if not path.exists():
        raise FileNotFoundError(f"ACQ file {path} does not exist")
    if path.is_dir():
        raise EdgesFormatError(f"{path} is a folder, not an ACQ file: pass the .acq files in it")
    if path.stat().st_size == 0:
        raise _not_acq(path, "the file is empty")
    import read_acq  # imports astropy's coordinates (~0.3 s): only when an ACQ file is read
    from read_acq.read_acq import ACQError

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            _, powers, anc = read_acq.decode_file(path, progress=False)
        except (ACQError, UnicodeDecodeError, ValueError, TypeError, IndexError, KeyError) as exc:
            raise _not_acq(path, f"{type(exc).__name__}: {str(exc)[:200]}") from exc
        except SystemError as exc:
            raise _not_acq(path, f"the spectrum decoder failed: {exc}") from exc
    problems = [str(w.message) for w in caught if not any(h in str(w.message) for h in _HARMLESS)]
    p = [np.atleast_2d(np.asarray(x, dtype=np.float64)) for x in powers]
    ncycle = p[0].shape[1] if p[0].size else 0
    if problems:
        detail = problems[0].strip().splitlines()[0][:160]
        msg = (
            f"{path}: {len(problems)} damaged entr{'y' if len(problems) == 1 else 'ies'} "
            f"(first: {detail!r}); the file is truncated or corrupt"
        )
        if not allow_partial or ncycle == 0:
            raise EdgesFormatError(
                msg + ". Re-copy it from the archive, or pass allow_partial=True to keep the "
                f"{ncycle} complete switch cycle(s) that could be read."
            )
        logger.warning("%s; keeping the %d complete switch cycle(s) read", msg, ncycle)
    if ncycle == 0:
        raise _not_acq(path, "it holds no complete three-position switch cycle (0, 1, 2)")
    nspec = int(anc.meta.get("nfreq", p[0].shape[0]))
    if p[0].shape[0] != nspec:
        raise _not_acq(path, f"{p[0].shape[0]} channels decoded but nspec is {nspec}")
    times = np.asarray(anc.data["times"])
    return np.stack([x.T for x in p]), times, anc


def _acq_one(path: Path, allow_partial: bool) -> EdgesSpectra:
    powers, times, anc = _decode_acq(path, allow_partial)
    header = dict(anc.meta)
    fmin = float(header.get("freq_min", 0.0))
    fmax = float(header.get("freq_max", NATIVE_FMAX_HZ / 1e6))
    nspec = powers.shape[2]
    if fmax <= fmin:
        raise _not_acq(path, f"its band {fmin}-{fmax} MHz is empty")
    if fmin != 0.0:
        logger.warning(
            "%s: freq_min is %s MHz, not 0; channels are placed at freq_min + k (freq_max - "
            "freq_min) / nspec (read_acq would misplace them)",
            path,
            fmin,
        )
    df = (fmax - fmin) * 1e6 / nspec
    freqs = fmin * 1e6 + np.arange(nspec) * df
    # the three timestamps of a cycle are the cycle's time (FASTSPEC writes one per cycle)
    cycle_times = times[:, 0] if times.ndim == 2 else times
    jds = acq_time_to_jd(cycle_times)
    tint, source = acq_integration_time(header)
    aux = {k: np.asarray(v) for k, v in anc.data.items() if k != "times"}
    if "data_drops" in aux and np.any(aux["data_drops"] > 0):
        logger.warning(
            "%s: %d switch spectra report data drops; their integration is shorter than %.3g s",
            path,
            int(np.sum(aux["data_drops"] > 0)),
            tint,
        )
    resolved = str(path.resolve())
    return EdgesSpectra(
        p0=powers[0],
        p1=powers[1],
        p2=powers[2],
        freqs=freqs,
        jds=jds,
        channel_width=df,
        integration_time=tint,
        aux=aux,
        meta={
            "source": "acq",
            "files": [resolved],
            "sha256": {resolved: file_checksum(path)},
            "header": jsonable(header),
            "bin_factor": 1,
            "native_channel_width_hz": df,
            "integration_time_source": source,
            "time_reference": "cycle timestamp (UTC, 1 s resolution), shared by p0, p1, p2",
        },
    )


def read_acq_spectra(
    paths: str | Path | Sequence[str | Path],
    *,
    freq_range: tuple[float, float] | None = None,
    bin_factor: int = 1,
    allow_partial: bool = False,
) -> EdgesSpectra:
    """Read ACQ files into :class:`EdgesSpectra` (joined in time order).

    Parameters
    ----------
    paths
        One ACQ file or several (same channels).
    freq_range
        ``(low, high)`` native channel centres to keep, Hz, inclusive.
    bin_factor
        Average this many consecutive selected channels.
    allow_partial
        Keep the complete switch cycles of a truncated or corrupt file (with a logged
        warning) instead of refusing it.

    Returns
    -------
    EdgesSpectra
        Powers, frequencies (Hz), JDs, channel width, integration time, ancillary data
        (``adcmax``, ``adcmin``, ``data_drops``) and provenance.

    Raises
    ------
    FileNotFoundError
        If a file does not exist.
    EdgesFormatError
        If a file is not ACQ, holds no complete switch cycle, is truncated or corrupt
        (unless ``allow_partial``), or has different channels from the others.
    """
    plist = [Path(paths)] if isinstance(paths, str | Path) else [Path(p) for p in paths]
    if not plist:
        raise EdgesFormatError("no ACQ files given")
    pieces = []
    for path in plist:
        spec = _acq_one(path, allow_partial)
        if freq_range is not None or bin_factor != 1:
            spec = spec.select(freq_range, bin_factor)
        pieces.append(spec)
        logger.info("%s: %d switch cycle(s), %d channel(s)", path, spec.ntime, spec.nfreq)
    return EdgesSpectra.concatenate(pieces)


def write_acq(
    path: str | Path,
    spectra: EdgesSpectra,
    *,
    header: dict[str, Any] | None = None,
    temperature: int = 0,
) -> Path:
    """Write spectra as an ACQ file (``read_acq.encode``), atomically.

    ACQ holds the native grid only (32768 channels, 0-200 MHz): ``spectra`` must be on it
    (any contiguous run of native channels); the other channels are filled with the
    nearest in-band value (the first 10 with the FASTSPEC floor). The integration time
    is stored as ``nblk`` (``nblk * 2 * 32768 / 400 MS/s``, so it is kept to 164 us).
    Times are rounded to whole seconds. Powers must lie within ``[1e-16.7, 1]``.

    Parameters
    ----------
    path
        Output file.
    spectra
        Native-grid spectra.
    header
        Extra ``;--key: value`` header entries (values must not contain ``": "``).
    temperature
        The ``temp`` field of the comment lines (C, integer).

    Returns
    -------
    pathlib.Path
        The written file.

    Raises
    ------
    ValueError
        If the spectra are not on the native grid (binned or resampled: write HDF5
        instead), powers are out of the encodable range, or the integration time varies.
    """
    powers = _checked_powers(spectra)
    tint = spectra.integration_time
    if np.ptp(tint) > 1e-9 * tint.max():
        raise EdgesFormatError("ACQ stores one integration time per file; write one file per value")
    nblk = max(1, round(float(tint[0]) * DEFAULT_ADC_RATE_HZ / (2 * NATIVE_NCHAN)))
    full = _native_band(spectra, powers)
    meta = _acq_header(header, temperature, nblk)
    ntime = spectra.ntime
    ancillary = {
        "times": np.array(jd_to_acq_time(spectra.jds)),
        "adcmax": np.asarray(spectra.aux.get("adcmax", np.full((ntime, 3), 0.25)), np.float64),
        "adcmin": np.asarray(spectra.aux.get("adcmin", np.full((ntime, 3), -0.25)), np.float64),
        "data_drops": np.asarray(
            spectra.aux.get("data_drops", np.zeros((ntime, 3), int)), dtype=np.int64
        ),
    }
    import read_acq

    path = Path(path)
    with atomic_path(path) as tmp:
        read_acq.encode(tmp, p=list(full), meta=meta, ancillary=ancillary)
    logger.info("wrote %s: %d switch cycle(s)", path, ntime)
    return path


def _checked_powers(spectra: EdgesSpectra) -> np.ndarray:
    """Return ``(3, Ntime, Nfreq)`` powers, or raise unless ACQ can hold them."""
    if not spectra.is_native:
        raise EdgesFormatError(
            "ACQ files hold the native 32768-channel 0-200 MHz grid; these spectra are "
            "binned or resampled: write them with write_edges_hdf5 instead"
        )
    powers = np.stack([spectra.p0, spectra.p1, spectra.p2])
    if (
        not np.all(np.isfinite(powers))
        or powers.min() < ACQ_FLOOR * (1 - 1e-9)
        or powers.max() > ACQ_MAX
    ):
        raise EdgesFormatError(
            f"ACQ stores powers between {ACQ_FLOOR:.3g} and {ACQ_MAX} (-167 to 0 dB); these "
            f"span {np.nanmin(powers):.3g}-{np.nanmax(powers):.3g}: rescale them"
        )
    return powers


def _native_band(spectra: EdgesSpectra, powers: np.ndarray) -> np.ndarray:
    """Return ``powers`` on the whole native band: nearest in-band value outside, floor below 10."""
    chan = np.round(spectra.freqs / NATIVE_DF_HZ).astype(int)
    full = np.empty((3, spectra.ntime, NATIVE_NCHAN))
    full[:, :, chan[0] : chan[-1] + 1] = powers
    full[:, :, : chan[0]] = powers[:, :, :1]
    full[:, :, chan[-1] + 1 :] = powers[:, :, -1:]
    full[:, :, : min(10, int(chan[0]))] = ACQ_FLOOR
    return full


def _acq_header(header: dict[str, Any] | None, temperature: int, nblk: int) -> dict[str, Any]:
    """Return the ``;--key: value`` header of a written file (``header`` entries checked)."""
    meta: dict[str, Any] = {
        "fastspec_version": "autocal",
        "site": "edges",
        "instrument": "autocal",
        "acquisition_rate": int(DEFAULT_ADC_RATE_HZ / 1e6),
        "num_channels": NATIVE_NCHAN,
        **(header or {}),
    }
    for key, value in meta.items():
        if ": " in str(value) or "\n" in str(value):
            raise EdgesFormatError(f"header value of {key!r} must not contain ': ' or a newline")
    meta.update(
        {
            "temperature": int(temperature),
            "nblk": int(nblk),
            "nfreq": NATIVE_NCHAN,
            "freq_min": 0.0,
            "freq_max": NATIVE_FMAX_HZ / 1e6,
            "freq_res": round(NATIVE_DF_HZ / 1e6, 6),
        }
    )
    return meta
