"""The autocal solution product: one HDF5 file with every array of a fit and its provenance.

Layout (format tag ``autocal-solution-1`` in the root attribute ``format``)
---------------------------------------------------------------------------
Root attributes
    ``format``, ``autocal_version``, ``created_utc``, ``config`` (JSON: the solution's
    resolved configuration), ``provenance`` (JSON: autocal and library versions, input
    files with SHA-256 checksums, the sky/beam/CMB/ground/site conventions found in the
    configuration, and anything the caller adds), ``model`` (JSON description of the
    time model), ``flag_reasons`` (JSON legend of ``flag_reason``), ``axes``.
Group ``model`` (attributes)
    ``kind``, ``order``, ``lst_start_h``, ``lst_span_h``, ``parameters`` (names of the
    coefficients), ``description`` (text).
Datasets (exactly what :class:`autocal.fit.solution.Solution` holds; read back bit for bit)
    ``antennas`` (Nant,), ``antenna_names`` (Nant,), ``pols`` (Npol,), ``freqs`` (Nfreq,;
    Hz), ``lsts`` (Ntime,; hours), ``jds`` (Ntime,), ``coeffs`` (Nant, Npol, Nfreq,
    nparam), ``cov`` (Nant, Npol, Nfreq, nparam, nparam), ``chi2``, ``dof``, ``count``,
    ``nflagged``, ``flag_reason`` (Nant, Npol, Nfreq), optional ``residuals`` (Nant, Npol,
    Ntime, Nfreq) and ``time_flags`` (Nant, Npol, Ntime; integrations flagged whole
    before the fit).
Group ``derived`` (for readers that do not use autocal; recomputed on reading)
    ``G``, ``abs_g`` (``|g| = sqrt(G)``), ``n``, ``Trxr`` (K), ``sigma_G``, ``sigma_abs_g``,
    ``sigma_n``, ``sigma_Trxr`` (K) -- the TOTAL 1-sigma when the solution has one (see
    ``uncertainty``), ``sigma_G_stat``, ``sigma_abs_g_stat``, ``sigma_n_stat``,
    ``sigma_Trxr_stat`` (the statistical part alone), ``reduced_chi2``, ``flags`` -- all
    (Nant, Npol, Nfreq); ``G`` and ``n`` are time averages over the fitted integrations.
Group ``uncertainty`` (with a total uncertainty; :mod:`autocal.fit.total_uncertainty`)
    ``cov`` (Nant, Npol, Nfreq, 2, 2) total covariance of the time-averaged ``(G, n)``;
    ``jackknife_factor``, ``drift_weight``, ``G_drift``, ``n_drift``, ``sigma_G_drift``,
    ``sky_contrast``, ``corr_G_n``, ``drift_sensitivity`` (Nant, Npol, Nfreq), ``G_halves``
    (2, Nant, Npol, Nfreq), the profile ``profile_trxr`` (Ngrid,; K) and ``profile_G``
    (Nant, Npol, Ngrid, Nfreq): ``G`` if ``Trxr`` were known to be each grid value;
    attributes ``method``, ``nblocks``, ``notes`` (JSON).

Units: ``G`` is raw correlator units per kelvin, ``n`` raw units, ``Trxr`` kelvin.

The configuration is stored as JSON: a configuration made of JSON types (dicts with
string keys, lists, strings, numbers, booleans, None) reads back identical; numpy values
are stored as their list/number equivalents and tuples as lists. Files are written
atomically (temporary file, then rename) and never overwritten unless asked.
"""

from __future__ import annotations

import importlib.metadata
import json
import logging
import platform
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from autocal import __version__
from autocal.core.files import atomic_path, file_checksum
from autocal.errors import AutocalError
from autocal.fit.model import FitModel
from autocal.fit.solution import Solution
from autocal.fit.solve import FLAG_REASONS
from autocal.fit.total_uncertainty import TotalUncertainty

logger = logging.getLogger(__name__)

#: Format tag of the product.
FORMAT = "autocal-solution-1"

_CORE = ("coeffs", "cov", "chi2", "dof", "count", "nflagged", "flag_reason")
#: Arrays of :class:`autocal.fit.total_uncertainty.TotalUncertainty` in the ``uncertainty`` group.
_UNCERTAINTY = {
    "cov": "total covariance of the time-averaged (G, n)",
    "jackknife_factor": "delete-a-block jackknife variance over the statistical variance",
    "drift_weight": "BIC weight of the model with one more time order (a drift)",
    "G_drift": "time-averaged G of that model",
    "n_drift": "time-averaged n of that model",
    "sigma_G_drift": "its statistical 1-sigma of G",
    "G_halves": "G from the first and the second half of the time blocks",
    "sky_contrast": "weighted rms of Tsky over the span / (mean Tsky + Trxr)",
    "corr_G_n": "statistical correlation coefficient of G and n",
    "drift_sensitivity": "(dG/G) per unit fractional gain drift over the span",
    "profile_trxr": "assumed receiver temperatures of the profile (K)",
    "profile_G": "time-averaged G with n(t) = G(t) Trxr held at each profile_trxr",
}
_DERIVED = {
    "G": ("raw/K", "gain G = |g|^2, time average over the fitted integrations"),
    "abs_g": ("sqrt(raw/K)", "gain amplitude |g| = sqrt(G)"),
    "n": ("raw", "noise offset n = G Trxr, time average"),
    "Trxr": ("K", "receiver temperature n / G"),
    "sigma_G": ("raw/K", "total 1-sigma uncertainty of G (statistical if no total)"),
    "sigma_abs_g": ("sqrt(raw/K)", "total 1-sigma uncertainty of |g|"),
    "sigma_n": ("raw", "total 1-sigma uncertainty of n"),
    "sigma_Trxr": ("K", "total 1-sigma of Trxr (linear propagation incl. Cov(G, n))"),
    "sigma_G_stat": ("raw/K", "statistical part of sigma_G"),
    "sigma_abs_g_stat": ("sqrt(raw/K)", "statistical part of sigma_abs_g"),
    "sigma_n_stat": ("raw", "statistical part of sigma_n"),
    "sigma_Trxr_stat": ("K", "statistical part of sigma_Trxr"),
    "reduced_chi2": ("", "chi^2 / dof"),
    "flags": ("", "True where the channel could not be solved"),
}
#: Configuration keys (substrings) collected as conventions in the provenance.
_CONVENTION_WORDS = (
    "sky",
    "beam",
    "cmb",
    "tgnd",
    "ground",
    "site",
    "frame",
    "azimuth",
    "epoch",
    "tsky",
    "horizon",
    "nside",
)


class ProductFormatError(AutocalError):
    """A file is missing, not HDF5, truncated, or not an autocal solution product."""


def _json_default(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (set, frozenset)):
        return sorted(value, key=str)
    if isinstance(value, Path):
        return str(value)
    if hasattr(value, "model_dump"):  # pydantic models
        return value.model_dump()
    return str(value)


def to_json(value: Any) -> str:
    """Serialise configuration/provenance to JSON (numpy and paths converted)."""
    return json.dumps(value, sort_keys=True, default=_json_default, allow_nan=True)


def _utc_now() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


def _input_entries(value: Any) -> list[Any]:
    """Normalise an ``inputs`` value: paths, dicts, or a ``{path: sha256}`` mapping."""
    if isinstance(value, (str, Path)):
        return [value]
    if isinstance(value, (list, tuple)):
        return list(value)
    if isinstance(value, dict):
        if isinstance(value.get("files"), (list, tuple)):
            return list(value["files"])
        return [{"path": str(k), "sha256": v} for k, v in value.items()]
    return []


def _input_files(config: dict[str, Any]) -> list[dict[str, Any]]:
    """Input files named in the configuration, with checksums (computed if missing).

    The configuration's top level and its ``provenance`` and ``calibration`` sections
    are searched (in the order provenance, top level, calibration) for ``inputs``,
    ``files``, ``input_files`` or ``observation_files``; the first non-empty one wins.
    """
    config = config or {}
    sections = [config.get("provenance"), config, config.get("calibration")]
    found: list[Any] = []
    given: Any = None
    for section in sections:
        if not isinstance(section, dict):
            continue
        for key in ("inputs", "files", "input_files", "observation_files"):
            found = _input_entries(section.get(key))
            if found:
                given = section.get("sha256") or section.get("checksums")
                break
        if found:
            break
    out: list[dict[str, Any]] = []
    for i, item in enumerate(found):
        if isinstance(item, dict):
            out.append(dict(item))
            continue
        entry: dict[str, Any] = {"path": str(item)}
        if isinstance(given, (list, tuple)) and i < len(given):
            entry["sha256"] = given[i]
        elif isinstance(given, dict) and str(item) in given:
            entry["sha256"] = given[str(item)]
        else:
            path = Path(str(item))
            if path.is_file():
                entry["sha256"] = file_checksum(path)
        out.append(entry)
    return out


def build_provenance(solution: Solution, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """Collect the provenance of a solution.

    Parameters
    ----------
    solution
        The :class:`autocal.fit.solution.Solution`.
    extra
        Entries added on top (they win over derived ones).

    Returns
    -------
    dict
        ``autocal_version``, ``created_utc``, ``software`` (python, numpy, pyuvdata,
        h5py versions), ``inputs`` (paths and SHA-256), ``conventions`` (every
        configuration entry about sky, beam, CMB, ground, site, frame, epoch ..., from
        the top level and the ``provenance`` and ``calibration`` sections),
        ``model`` and ``extra`` entries.
    """
    try:  # pyuvdata takes a second to import: its installed version, without importing it
        uvd_version = importlib.metadata.version("pyuvdata")
    except importlib.metadata.PackageNotFoundError:  # pragma: no cover
        uvd_version = None
    config = solution.config or {}
    conventions: dict[str, Any] = {}
    for section in (config, config.get("provenance"), config.get("calibration")):
        if not isinstance(section, dict):
            continue
        for key, value in section.items():
            if key not in conventions and any(w in str(key).lower() for w in _CONVENTION_WORDS):
                conventions[key] = value
    prov: dict[str, Any] = {
        "autocal_version": __version__,
        "created_utc": _utc_now(),
        "software": {
            "python": platform.python_version(),
            "numpy": np.__version__,
            "h5py": h5py.__version__,
            "pyuvdata": uvd_version,
        },
        "inputs": _input_files(config),
        "conventions": conventions,
        "model": solution.model.describe(),
    }
    prov.update(extra or {})
    return prov


def _write_strings(h5: h5py.File, name: str, values: Any) -> None:
    data = np.array([str(v) for v in values], dtype=object)
    h5.create_dataset(name, data=data, dtype=h5py.string_dtype("utf-8"))


def write_solution(
    solution: Solution,
    path: str | Path,
    *,
    provenance: dict[str, Any] | None = None,
    overwrite: bool = False,
) -> Path:
    """Write a solution to the HDF5 product (atomically).

    Parameters
    ----------
    solution
        An :class:`autocal.fit.solution.Solution`.
    path
        Output file (``.h5``).
    provenance
        Extra provenance (e.g. job id, command line); merged over the derived one.
    overwrite
        Replace an existing file.

    Returns
    -------
    pathlib.Path
        The written file.

    Raises
    ------
    FileExistsError
        If ``path`` exists and ``overwrite`` is false.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
    prov = build_provenance(solution, provenance)
    model = solution.model
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as h5:
        h5.attrs["format"] = FORMAT
        h5.attrs["autocal_version"] = __version__
        h5.attrs["created_utc"] = prov["created_utc"]
        h5.attrs["config"] = to_json(solution.config or {})
        h5.attrs["provenance"] = to_json(prov)
        h5.attrs["model"] = to_json(model.describe())
        h5.attrs["flag_reasons"] = to_json({str(k): v for k, v in FLAG_REASONS.items()})
        h5.attrs["axes"] = "antenna, pol, freq[, parameter[, parameter]]; residuals: time"
        grp = h5.create_group("model")
        grp.attrs["kind"] = model.kind
        grp.attrs["order"] = int(model.order)
        grp.attrs["lst_start_h"] = float(model.lst_start)
        grp.attrs["lst_span_h"] = float(model.lst_span)
        grp.attrs["parameters"] = to_json(list(model.param_names))
        grp.attrs["description"] = (
            "constant: G, n per channel"
            if model.kind == "constant"
            else f"Legendre order {model.order}: G(t) = sum_k g_k P_k(s), n(t) = sum_k n_k "
            "P_k(s), s = 2 ((LST - lst_start_h) mod 24) / lst_span_h - 1"
        )
        h5.create_dataset("antennas", data=np.asarray(solution.antennas, dtype=np.int64))
        _write_strings(h5, "antenna_names", solution.antenna_names)
        _write_strings(h5, "pols", solution.pols)
        for name, unit in (("freqs", "Hz"), ("lsts", "hour"), ("jds", "JD (UTC)")):
            ds = h5.create_dataset(name, data=np.asarray(getattr(solution, name), np.float64))
            ds.attrs["units"] = unit
        for name in _CORE:
            h5.create_dataset(name, data=np.asarray(getattr(solution, name)))
        h5["coeffs"].attrs["parameters"] = to_json(list(model.param_names))
        h5["flag_reason"].attrs["legend"] = to_json({str(k): v for k, v in FLAG_REASONS.items()})
        if solution.residuals is not None:
            h5.create_dataset("residuals", data=np.asarray(solution.residuals))
        if solution.time_flags is not None:
            h5.create_dataset("time_flags", data=np.asarray(solution.time_flags, dtype=bool))
        der = h5.create_group("derived")
        with np.errstate(invalid="ignore", divide="ignore"):
            for name, (unit, text) in _DERIVED.items():
                ds = der.create_dataset(name, data=np.asarray(getattr(solution, name)))
                ds.attrs["units"] = unit
                ds.attrs["description"] = text
        if solution.total is not None:
            unc = h5.create_group("uncertainty")
            unc.attrs["method"] = solution.total.describe()["method"]
            unc.attrs["nblocks"] = int(solution.total.nblocks)
            unc.attrs["notes"] = to_json(list(solution.total.notes))
            for name, text in _UNCERTAINTY.items():
                ds = unc.create_dataset(name, data=np.asarray(getattr(solution.total, name)))
                ds.attrs["description"] = text
    logger.info("wrote solution product %s", path)
    return path


def _open_check(path: Path) -> None:
    if not path.exists():
        raise ProductFormatError(f"{path} does not exist: check the path")
    if path.is_dir():
        raise ProductFormatError(f"{path} is a directory, not an autocal solution file")
    if not h5py.is_hdf5(path):
        raise ProductFormatError(
            f"{path} is not an HDF5 file, so not an autocal solution product ({FORMAT})"
        )


def _strings(ds: h5py.Dataset) -> tuple[str, ...]:
    return tuple(v.decode() if isinstance(v, bytes) else str(v) for v in ds[()])


def read_solution(path: str | Path) -> Solution:
    """Read a solution written by :func:`write_solution`.

    Parameters
    ----------
    path
        The product file.

    Returns
    -------
    autocal.fit.solution.Solution
        The solution, identical to the written one (configuration via JSON).

    Raises
    ------
    ProductFormatError
        If the file is missing, not HDF5, truncated, or not an ``autocal-solution-1``
        product.
    """
    path = Path(path)
    _open_check(path)
    try:
        with h5py.File(path, "r") as h5:
            fmt = h5.attrs.get("format")
            if fmt != FORMAT:
                hint = (
                    " (a calh5 file? read it with autocal.io.calsol_read)" if "Header" in h5 else ""
                )
                raise ProductFormatError(
                    f"{path} is not an autocal solution product: format {fmt!r}, "
                    f"expected {FORMAT!r}{hint}"
                )
            grp = h5["model"]
            model = FitModel(
                kind=str(grp.attrs["kind"]),  # type: ignore[arg-type]
                order=int(grp.attrs["order"]),
                lst_start=float(grp.attrs["lst_start_h"]),
                lst_span=float(grp.attrs["lst_span_h"]),
            )
            arrays = {name: h5[name][()] for name in _CORE}
            residuals = h5["residuals"][()] if "residuals" in h5 else None
            time_flags = h5["time_flags"][()] if "time_flags" in h5 else None
            total = None
            if "uncertainty" in h5:
                unc = h5["uncertainty"]
                total = TotalUncertainty(
                    **{name: unc[name][()] for name in _UNCERTAINTY},
                    nblocks=int(unc.attrs["nblocks"]),
                    notes=tuple(json.loads(unc.attrs["notes"])),
                )
            solution = Solution(
                model=model,
                antennas=h5["antennas"][()],
                pols=_strings(h5["pols"]),
                freqs=h5["freqs"][()],
                lsts=h5["lsts"][()],
                jds=h5["jds"][()],
                config=json.loads(h5.attrs["config"]),
                residuals=residuals,
                antenna_names=_strings(h5["antenna_names"]),
                total=total,
                time_flags=time_flags,
                **arrays,
            )
    except ProductFormatError:
        raise
    except (OSError, KeyError, ValueError) as err:
        raise ProductFormatError(
            f"{path} is truncated or corrupt, or misses parts of the {FORMAT} layout "
            f"({type(err).__name__}: {err})"
        ) from err
    return solution


def read_provenance(path: str | Path) -> dict[str, Any]:
    """Return the provenance stored in a product file."""
    path = Path(path)
    _open_check(path)
    try:
        with h5py.File(path, "r") as h5:
            if h5.attrs.get("format") != FORMAT:
                raise ProductFormatError(f"{path} is not an autocal solution product")
            return json.loads(h5.attrs["provenance"])
    except OSError as err:
        raise ProductFormatError(f"{path} is truncated or corrupt: {err}") from err
