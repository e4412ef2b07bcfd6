"""Diffuse sky models in low-rank form.

Every sky model delivers its brightness temperature as a sum of a few fixed spatial
components times their spectra,

    T(nu, p) = sum_c S[nu, c] M[c, p],

in the apparent equatorial frame of the observation epoch (see :mod:`autocal.core.coords`),
at a chosen HEALPix resolution. The Tsky engine transforms each spatial component once,
whatever the number of frequencies.

CMB convention: each model states whether its *source maps* include the 2.725 K CMB
(:attr:`SkyModel.maps_include_cmb`). :meth:`SkyModel.components` always returns the
total sky brightness with the CMB counted exactly once: if the source maps exclude it, a
constant component labelled ``"cmb"`` with spectrum :data:`T_CMB` is appended.

pygdsm's models (GSM2008, GSM2016, LFSM, Haslam) are used with ``include_cmb=False``, so
their maps exclude the CMB (pygdsm 1.7 behaviour; see pygdsm issues #12, #17, #18).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import re
import threading
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from importlib.metadata import version
from typing import Any

import numpy as np

from autocal.core.coords import parse_epoch, resample_galactic_to_equatorial, tilt_rotation
from autocal.core.lazy import healpy as hp
from autocal.errors import AutocalError
from autocal.io.datasets import GSM2008_FILE, ensure_pygdsm_file

logger = logging.getLogger(__name__)

#: CMB temperature in kelvin (Fixsen 2009, rounded as in pygdsm).
T_CMB = 2.725
#: Skies in low-rank form kept for reuse (the same sky, channels, nside and epoch): a
#: diagnosis computes Tsky for the model beam and four widened beams per polarisation, a
#: calibration one per polarisation, all from the same components (~2 MB each at nside 64).
COMPONENTS_MEMO_SIZE = 4
_COMPONENTS: dict[tuple[Any, ...], SkyComponents] = {}
_COMPONENTS_LOCK = threading.Lock()


class SkyModelError(AutocalError):
    """A sky model was asked for something it cannot deliver."""


@dataclass(frozen=True)
class SkyComponents:
    """A sky in low-rank form on an equatorial HEALPix grid.

    Attributes
    ----------
    maps
        ``(Ncomp, Npix)`` spatial components, RING ordering, apparent equatorial frame.
    spectra
        ``(Nfreq, Ncomp)`` spectra; ``T = spectra @ maps`` in kelvin (includes the CMB once).
    labels
        Component names (``"cmb"`` for the CMB monopole).
    freqs
        ``(Nfreq,)`` frequencies in Hz.
    nside
        HEALPix resolution.
    epoch_jd
        Julian date of the equatorial frame.
    """

    maps: np.ndarray
    spectra: np.ndarray
    labels: tuple[str, ...]
    freqs: np.ndarray
    nside: int
    epoch_jd: float

    def __post_init__(self) -> None:
        if self.maps.ndim != 2 or self.maps.shape[1] != hp.nside2npix(self.nside):
            raise SkyModelError(f"maps must be (Ncomp, {hp.nside2npix(self.nside)})")
        if self.spectra.shape != (self.freqs.size, self.maps.shape[0]):
            raise SkyModelError("spectra must be (Nfreq, Ncomp)")
        if len(self.labels) != self.maps.shape[0]:
            raise SkyModelError("one label per component is required")

    @property
    def ncomp(self) -> int:
        """Number of spatial components."""
        return self.maps.shape[0]

    def temperature(self, index: int | slice | np.ndarray | None = None) -> np.ndarray:
        """Return full maps ``(Nfreq_sel, Npix)`` in kelvin for the selected frequencies."""
        spectra = self.spectra if index is None else np.atleast_2d(self.spectra[index])
        return spectra @ self.maps


def _check_freqs(freqs: np.ndarray | float) -> np.ndarray:
    freqs = np.atleast_1d(np.asarray(freqs, dtype=np.float64))
    if freqs.size == 0:
        raise SkyModelError("the frequency grid is empty: give at least one frequency")
    if not np.all(np.isfinite(freqs)) or np.any(freqs <= 0):
        raise SkyModelError("frequencies must be finite and positive (in Hz)")
    if freqs.max() < 1e5:
        raise SkyModelError(
            f"frequencies look like MHz ({freqs.min()}..{freqs.max()}): autocal takes Hz"
        )
    return freqs


class SkyModel(ABC):
    """A diffuse sky model.

    Subclasses implement :meth:`galactic`, which returns Galactic components *excluding*
    the CMB unless :attr:`maps_include_cmb` is true.
    """

    #: Short model name.
    name: str = "sky"
    #: Whether the source maps already contain the CMB monopole.
    maps_include_cmb: bool = False

    @abstractmethod
    def galactic(
        self, freqs: np.ndarray, nside: int
    ) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
        """Return ``(maps (Ncomp, Npix) Galactic RING, spectra (Nfreq, Ncomp), labels)``.

        ``nside`` is a hint: models with finer native maps may degrade to it.
        """

    @abstractmethod
    def describe(self) -> dict[str, Any]:
        """Return a JSON-serialisable description (provenance and cache keys)."""

    def frame_rotation(self) -> np.ndarray | None:
        """Return the rotation of the sky in the apparent frame (``None`` for the true sky)."""
        return None

    def components(
        self, freqs: np.ndarray | float, nside: int = 64, epoch: Any = None
    ) -> SkyComponents:
        """Return the sky (with the CMB counted once) in low-rank equatorial form.

        Parameters
        ----------
        freqs
            Frequencies in Hz.
        nside
            Output HEALPix resolution.
        epoch
            Epoch of the equatorial frame (see :func:`autocal.core.coords.parse_epoch`).

        Returns
        -------
        SkyComponents
            The low-rank sky, with read-only arrays: equal (frozen) sky models on the same
            channels, nside and epoch share one result, the last
            :data:`COMPONENTS_MEMO_SIZE` of which are kept.
        """
        freqs = _check_freqs(freqs)
        if nside < 1 or not hp.isnsideok(nside, nest=True):
            raise SkyModelError(f"nside {nside} is not a power of two >= 1")
        time = parse_epoch(epoch)
        # frozen dataclasses (the models here) are their repr; others are not memoised
        frozen = dataclasses.is_dataclass(self) and self.__dataclass_params__.frozen
        if not frozen:
            return self._components(freqs, nside, time)
        key = (repr(self), hashlib.sha256(freqs.tobytes()).hexdigest(), nside, float(time.jd))
        with _COMPONENTS_LOCK:
            cached = _COMPONENTS.get(key)
        if cached is not None:
            return cached
        comps = self._components(freqs, nside, time)
        with _COMPONENTS_LOCK:
            _COMPONENTS[key] = comps
            while len(_COMPONENTS) > COMPONENTS_MEMO_SIZE:
                _COMPONENTS.pop(next(iter(_COMPONENTS)))
        return comps

    def _components(self, freqs: np.ndarray, nside: int, time: Any) -> SkyComponents:
        """Compute :meth:`components` (arguments checked); the arrays are read-only."""
        maps, spectra, labels = self.galactic(freqs, nside)
        eq_maps = resample_galactic_to_equatorial(maps, nside, time, self.frame_rotation())
        if not self.maps_include_cmb:
            eq_maps = np.vstack([eq_maps, np.ones((1, eq_maps.shape[1]))])
            spectra = np.hstack([spectra, np.full((freqs.size, 1), T_CMB)])
            labels = (*labels, "cmb")
        arrays = [np.array(a, dtype=np.float64) for a in (eq_maps, spectra, freqs)]
        for a in arrays:
            a.flags.writeable = False  # shared by every caller of the memo
        return SkyComponents(
            maps=arrays[0],
            spectra=arrays[1],
            labels=tuple(labels),
            freqs=arrays[2],
            nside=nside,
            epoch_jd=float(time.jd),
        )


@dataclass(frozen=True)
class UniformSky(SkyModel):
    """A sky of uniform brightness ``t0`` kelvin.

    Parameters
    ----------
    t0
        Brightness in kelvin.
    includes_cmb
        Whether ``t0`` already includes the CMB (default true: ``t0`` is the total).
    """

    t0: float = T_CMB
    includes_cmb: bool = True
    name: str = "uniform"

    def __post_init__(self) -> None:
        if not (np.isfinite(self.t0) and self.t0 >= 0):
            raise SkyModelError(f"uniform sky temperature must be finite and >= 0 K, not {self.t0}")

    @property
    def maps_include_cmb(self) -> bool:  # type: ignore[override]
        """Whether ``t0`` includes the CMB."""
        return self.includes_cmb

    def galactic(self, freqs, nside):  # noqa: D102
        maps = np.ones((1, hp.nside2npix(nside)))
        return maps, np.full((freqs.size, 1), float(self.t0)), ("uniform",)

    def describe(self) -> dict[str, Any]:  # noqa: D102
        return {"model": "uniform", "t0_K": float(self.t0), "includes_cmb": self.includes_cmb}


@dataclass(frozen=True)
class TiltedSky(SkyModel):
    """Another sky model turned about the equatorial x and y axes (a sky in a wrong frame).

    Used for the diagnosis's frame-tilt templates (:mod:`autocal.diagnosis.effects`): a
    sky left in J2000 is, against the frame of the date, turned about the pole (a time
    offset) and tilted (precession in declination, 20 arcsec a year).

    Parameters
    ----------
    base
        The sky model.
    tilt_x_arcmin, tilt_y_arcmin
        Turns about the x (RA 0 h) and y (RA 6 h) axes, arcminutes
        (:func:`autocal.core.coords.tilt_rotation`).
    """

    base: SkyModel = field(default_factory=lambda: UniformSky())
    tilt_x_arcmin: float = 0.0
    tilt_y_arcmin: float = 0.0
    name: str = "tilted"

    @property
    def maps_include_cmb(self) -> bool:  # type: ignore[override]
        """Whether the base model's maps include the CMB."""
        return self.base.maps_include_cmb

    def galactic(self, freqs, nside):  # noqa: D102
        return self.base.galactic(freqs, nside)

    def frame_rotation(self) -> np.ndarray | None:  # noqa: D102
        return tilt_rotation(self.tilt_x_arcmin, self.tilt_y_arcmin)

    def describe(self) -> dict[str, Any]:  # noqa: D102
        return {
            **self.base.describe(),
            "tilt_arcmin": [float(self.tilt_x_arcmin), float(self.tilt_y_arcmin)],
        }


# pygdsm models ---------------------------------------------------------------------------

_PYGDSM = {
    # name: (class name, constructor kwargs, URL attribute in pygdsm.component_data,
    #        local file relative to the data folder)
    "gsm2008": ("GlobalSkyModel", {"basemap": "haslam"}, "GSM_DATA_URL", "gsm2008"),
    "gsm2016": ("GlobalSkyModel16", {"data_unit": "TRJ"}, "GSM2016_DATA_URL", None),
    "lfsm": ("LowFrequencySkyModel", {}, "LFSM_DATA_URL", None),
    "haslam": ("HaslamSkyModel", {"spectral_index": -2.55}, "HASLAM_DATA_URL", None),
}
_PYGDSM_CACHE: dict[str, Any] = {}


def _pygdsm_model(name: str) -> Any:
    """Instantiate (once) a pygdsm model, making its data file available offline."""
    if name in _PYGDSM_CACHE:
        return _PYGDSM_CACHE[name]
    import pygdsm  # optional heavy dependency, used only by the pygdsm models
    from pygdsm import component_data

    cls_name, kwargs, url_attr, local = _PYGDSM[name]
    urls = getattr(component_data, url_attr)
    ensure_pygdsm_file(list(urls), GSM2008_FILE if local == "gsm2008" else None, name)
    model = getattr(pygdsm, cls_name)(freq_unit="MHz", include_cmb=False, **kwargs)
    _PYGDSM_CACHE[name] = model
    return model


@dataclass(frozen=True)
class PygdsmSky(SkyModel):
    """A pygdsm sky model (``gsm2008``, ``gsm2016``, ``lfsm`` or ``haslam``) without the CMB.

    The low-rank form is found exactly: maps generated at up to ``nprobe`` frequencies
    spanning the band are decomposed (SVD) into spatial components; the spectra are the
    projections of the maps at every requested frequency onto them (the reconstruction
    error is checked and logged).
    """

    model: str = "gsm2008"
    nprobe: int = 16
    name: str = "gsm2008"
    maps_include_cmb: bool = False

    def __post_init__(self) -> None:
        if self.model not in _PYGDSM:
            raise SkyModelError(f"unknown pygdsm model {self.model!r}: use {sorted(_PYGDSM)}")
        object.__setattr__(self, "name", self.model)

    def _generate(self, gsm: Any, freqs_hz: np.ndarray, nside: int) -> np.ndarray:
        maps = np.atleast_2d(np.asarray(gsm.generate(freqs_hz / 1e6), dtype=np.float64))
        native = hp.npix2nside(maps.shape[1])
        if native > nside:
            maps = np.atleast_2d(hp.ud_grade(maps, nside))
        return maps

    def galactic(self, freqs, nside):  # noqa: D102
        gsm = _pygdsm_model(self.model)
        if freqs.size <= self.nprobe:
            probe = freqs
        else:
            probe = np.geomspace(freqs.min(), freqs.max(), self.nprobe)
        probe_maps = self._generate(gsm, probe, nside)
        _, s, vt = np.linalg.svd(probe_maps, full_matrices=False)
        rank = int(np.sum(s > s[0] * 1e-9))
        basis = vt[:rank]  # orthonormal rows (Ncomp, Npix)
        spectra = np.empty((freqs.size, rank))
        worst = 0.0
        for start in range(0, freqs.size, 64):
            chunk = self._generate(gsm, freqs[start : start + 64], nside)
            coef = chunk @ basis.T
            spectra[start : start + 64] = coef
            resid = np.linalg.norm(chunk - coef @ basis, axis=1) / np.linalg.norm(chunk, axis=1)
            worst = max(worst, float(resid.max()))
        if worst > 1e-6:
            logger.warning("%s low-rank form reproduces maps to %.1e only", self.model, worst)
        logger.debug("%s: rank %d, max relative reconstruction error %.1e", self.model, rank, worst)
        labels = tuple(f"{self.model}_pc{i}" for i in range(rank))
        return basis, spectra, labels

    def describe(self) -> dict[str, Any]:  # noqa: D102
        return {
            "model": self.model,
            "source": "pygdsm",
            "pygdsm_version": version("pygdsm"),
            "includes_cmb": False,
        }


@dataclass(frozen=True)
class PowerLawSky(SkyModel):
    """A sky extrapolated from one map of another model with a power law, CMB kept out.

    ``T(nu) = (T0 - Tcmb) (nu / nu0)^beta + Tcmb``, where ``T0`` is ``base`` at ``nu0``.

    Parameters
    ----------
    base
        The model providing the reference map.
    nu0
        Reference frequency in Hz.
    beta
        Spectral index (e.g. -2.55 from 408 MHz).
    """

    base: SkyModel = field(default_factory=lambda: PygdsmSky("gsm2008"))
    nu0: float = 408e6
    beta: float = -2.55
    name: str = "powerlaw"
    maps_include_cmb: bool = False

    def __post_init__(self) -> None:
        if not (np.isfinite(self.nu0) and self.nu0 > 1e5):
            raise SkyModelError(f"reference frequency {self.nu0} must be in Hz (> 1e5)")
        if not np.isfinite(self.beta):
            raise SkyModelError("spectral index must be finite")

    def reference_map(self, nside: int) -> np.ndarray:
        """Return ``T0 - Tcmb`` (Galactic RING, kelvin) at ``nu0``."""
        maps, spectra, _ = self.base.galactic(np.array([self.nu0]), nside)
        t0 = spectra[0] @ maps
        if self.base.maps_include_cmb:
            t0 = t0 - T_CMB
        return t0

    def frame_rotation(self) -> np.ndarray | None:  # noqa: D102
        return self.base.frame_rotation()

    def galactic(self, freqs, nside):  # noqa: D102
        ref = self.reference_map(nside)[None, :]
        return ref, ((freqs / self.nu0) ** self.beta)[:, None], ("powerlaw",)

    def describe(self) -> dict[str, Any]:  # noqa: D102
        return {
            "model": "powerlaw",
            "base": self.base.describe(),
            "nu0_Hz": self.nu0,
            "beta": self.beta,
            "includes_cmb": False,
            "formula": "(T0 - Tcmb) (nu/nu0)^beta + Tcmb",
        }


_SPEC_HELP = (
    "sky models: gsm2008, gsm2016, lfsm, haslam (pygdsm; GSM2016, LFSM and the Haslam FITS "
    "need their pygdsm files), 'uniform:T0' (kelvin, CMB included), "
    "'powerlaw:BASE@NU0MHZ:BETA' e.g. 'powerlaw:gsm2008@408:-2.55'"
)


def get_sky(spec: str | SkyModel) -> SkyModel:
    """Resolve a sky-model specification string.

    Parameters
    ----------
    spec
        ``gsm2008``, ``gsm2016``, ``lfsm``, ``haslam``, ``uniform:T0`` or
        ``powerlaw:BASE@NU0MHZ:BETA``; or a :class:`SkyModel` (returned unchanged).

    Returns
    -------
    SkyModel
        The model.

    Raises
    ------
    SkyModelError
        For an unknown or malformed specification.
    """
    if isinstance(spec, SkyModel):
        return spec
    text = spec.strip().lower()
    if text in _PYGDSM:
        return PygdsmSky(text)
    if text.startswith("uniform"):
        match = re.fullmatch(r"uniform(?::([-+0-9.eE]+))?", text)
        if match:
            if match.group(1) is None:
                return UniformSky(T_CMB)
            t0 = _spec_number(match.group(1), spec, "T0 (kelvin)")
            if t0 <= 0:
                raise SkyModelError(
                    f"sky {spec!r}: the uniform sky's total brightness T0 must be > 0 K "
                    f"(it includes the CMB, {T_CMB} K)"
                )
            return UniformSky(t0)
    if text.startswith("powerlaw"):
        match = re.fullmatch(r"powerlaw:([a-z0-9]+)@([0-9.eE+]+):([-+0-9.eE]+)", text)
        if match:
            nu0 = _spec_number(match.group(2), spec, "NU0MHZ (the reference frequency, MHz)")
            beta = _spec_number(match.group(3), spec, "BETA (the spectral index)")
            return PowerLawSky(get_sky(match.group(1)), nu0 * 1e6, beta)
    raise SkyModelError(f"unknown sky model {spec!r}; {_SPEC_HELP}")


def _spec_number(text: str, spec: str, what: str) -> float:
    """Return a number of a sky specification, or raise :class:`SkyModelError` naming it."""
    try:
        value = float(text)
    except ValueError:
        raise SkyModelError(
            f"sky {spec!r}: {what} is {text!r}, not a number; {_SPEC_HELP}"
        ) from None
    if not np.isfinite(value):
        raise SkyModelError(f"sky {spec!r}: {what} must be finite; {_SPEC_HELP}")
    return value


def describe_hash(description: dict[str, Any]) -> str:
    """Return a short stable hash of a description dictionary."""
    text = json.dumps(description, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]
