"""Normal sums and their accumulation by both engines (autocal.fit.sums, autocal.fit.kernels)."""

from __future__ import annotations

import numpy as np
import pytest

from autocal.fit.kernels import numba_available
from autocal.fit.model import FitError, FitModel, design
from autocal.fit.moments import num_array
from autocal.fit.solve import solve_sums
from autocal.fit.sums import NormalSums, accumulate, default_threads
from tests.fit.toy import LSTS, MODELS, NF, NT, noisy, random_chunk, toy_tsky


def test_streamed_sums_equal_one_pass_and_add_across_workers() -> None:
    rng = np.random.default_rng(3)
    tsky = toy_tsky()
    data = noisy((tsky + 150.0)[None, None] * np.ones((2, 1, 1, 1)), rng)
    model = FitModel.for_lsts(LSTS, "legendre", 1)
    whole = accumulate(model, data, tsky, LSTS, bandwidth_time=5e3)
    parts = [
        accumulate(model, data[:, :, sl], tsky[sl], LSTS[sl], bandwidth_time=5e3)
        for sl in (slice(0, 50), slice(50, 97), slice(97, NT))
    ]
    total = parts[0] + parts[1] + parts[2]
    for name in ("ata", "aty", "yty"):
        np.testing.assert_allclose(getattr(total, name), getattr(whole, name), rtol=1e-12)
    np.testing.assert_array_equal(total.count, whole.count)
    a, b = solve_sums(total), solve_sums(whole)
    np.testing.assert_allclose(a["coeffs"], b["coeffs"], rtol=1e-9, atol=1e-11)
    other = NormalSums.zeros(FitModel(), 2, 1, NF)
    with pytest.raises(FitError, match="different models"):
        _ = total + other


def reference_sums(
    model: FitModel,
    data: np.ndarray,
    tsky: np.ndarray,
    lsts: np.ndarray,
    flags: np.ndarray,
    weights: str | np.ndarray = "radiometer",
    bandwidth_time: np.ndarray | float | None = None,
    reference: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``A^T W A``, ``A^T W y``, ``y^T W y`` and the count, straight from the design."""
    usable = np.isfinite(data) & ~flags
    if isinstance(weights, str) and weights == "identity":
        w = usable.astype(float)
    elif isinstance(weights, str):
        power = data if reference is None else reference
        with np.errstate(divide="ignore", invalid="ignore"):
            w = np.broadcast_to(bandwidth_time, data.shape) / power**2
        w = np.where(usable & np.isfinite(w) & (w > 0), w, 0.0)
    else:
        w = np.where(usable, np.broadcast_to(weights, data.shape), 0.0)
    used = w > 0
    y = np.where(used, data, 0.0)
    a = design(model, tsky, lsts)  # (P, F, T, M)
    ata = np.einsum("aptf,pftm,pftn->apfmn", w, a, a)
    aty = np.einsum("aptf,aptf,pftm->apfm", w, y, a)
    yty = np.einsum("aptf,aptf,aptf->apf", w, y, y)
    return ata, aty, yty, used.sum(axis=2)


WEIGHT_CASES = {
    "identity": lambda c: {"weights": "identity"},
    "radiometer": lambda c: {"bandwidth_time": c["bt"]},
    "radiometer-scalar": lambda c: {"bandwidth_time": 5e3},
    "radiometer-per-channel": lambda c: {"bandwidth_time": c["bt"][0, 0, 0]},
    "radiometer-reference": lambda c: {"bandwidth_time": c["bt"], "reference": c["reference"]},
    "user": lambda c: {"weights": c["user"]},
    "user-scalar": lambda c: {"weights": 2.5},
}


NO_NUMBA = pytest.mark.skipif(not numba_available(), reason="numba is not installed")


ENGINES = ["numpy", pytest.param("numba", marks=NO_NUMBA)]


def assert_sums_match(sums: NormalSums, ref: tuple[np.ndarray, ...], ntime: int) -> None:
    ata, aty, yty, count = ref
    np.testing.assert_array_equal(sums.count, count)
    np.testing.assert_array_equal(sums.nflagged, ntime - count)
    for got, want in ((sums.ata, ata), (sums.aty, aty)):
        # relative to each channel's largest entry (off-diagonal Legendre moments cancel)
        scale = np.abs(want).max(axis=tuple(range(3, want.ndim)), keepdims=True)
        rel = np.abs(got - want) / np.where(scale > 0, scale, 1.0)
        assert rel.max() < 1e-13, f"max relative difference {rel.max():.2e}"
    np.testing.assert_allclose(sums.yty, yty, rtol=1e-13, atol=0)


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("kind,order", MODELS)
@pytest.mark.parametrize("case", sorted(WEIGHT_CASES))
def test_moment_sums_equal_the_normal_equations(
    engine: str, kind: str, order: int, case: str
) -> None:
    if engine == "numba" and (
        ((kind, order) == ("legendre", 4) and case != "radiometer")
        or ((kind, order) == ("legendre", 1) and case not in ("identity", "radiometer"))
    ):
        pytest.skip("every weight kind is compiled for orders 0 and 2 (compile time)")
    c = random_chunk(13)
    model = FitModel.for_lsts(c["lsts"], kind, order)
    kw = WEIGHT_CASES[case](c)
    ref = reference_sums(model, c["data"], c["tsky"], c["lsts"], c["flags"], **kw)
    for threads in (1, 2):
        sums = accumulate(
            model,
            c["data"],
            c["tsky"],
            c["lsts"],
            flags=c["flags"],
            engine=engine,
            threads=threads,
            **kw,
        )
        assert_sums_match(sums, ref, c["data"].shape[2])
        assert sums.model == model and sums.lst_min == c["lsts"].min()


@pytest.mark.parametrize("engine", ENGINES)
def test_engines_accept_broadcast_and_float32_inputs(engine: str) -> None:
    c = random_chunk(5, nant=2, ntime=16, nfreq=9)
    data = np.abs(np.nan_to_num(c["data"], posinf=1.0)).astype(np.float32)
    flags = c["flags"][:1, :1]  # broadcast over antennas and pols
    tsky2d = c["tsky"][0]  # one Tsky for both pols
    model = FitModel.for_lsts(c["lsts"], "legendre", 1)
    bt = c["bt"][0, 0, :, :1]  # per integration
    full_flags = np.broadcast_to(flags, data.shape)
    tsky = np.broadcast_to(tsky2d, (2, *tsky2d.shape))
    ref = reference_sums(model, data.astype(float), tsky, c["lsts"], full_flags, "radiometer", bt)
    sums = accumulate(model, data, tsky2d, c["lsts"], flags=flags, bandwidth_time=bt, engine=engine)
    assert_sums_match(sums, ref, 16)


@pytest.mark.parametrize("engine", ENGINES)
def test_shared_weights_give_the_per_sample_sums(engine: str) -> None:
    """dnu dt N or user weights varying only in (time, frequency) are read as one array,
    and those varying only in frequency as one row."""
    c = random_chunk(21, nant=3, ntime=13, nfreq=16)
    model = FitModel.for_lsts(c["lsts"], "legendre", 2)
    per_time = c["bt"][0, 0]
    per_channel = np.broadcast_to(per_time[0], per_time.shape).copy()  # uniform in time
    assert num_array(per_time, c["data"]).shape == per_time.shape
    assert num_array(per_channel, c["data"]).shape == per_time.shape[1:]
    args = (model, c["data"], c["tsky"], c["lsts"])
    for shared in (per_time, per_channel):
        for weights, key in (("radiometer", "bandwidth_time"), (None, "weights")):
            kw = {"weights": weights} if weights else {}
            full = accumulate(
                *args,
                flags=c["flags"],
                engine=engine,
                **kw,
                **{key: np.broadcast_to(shared, c["data"].shape).copy()},
            )
            row = (shared[0],) if shared is per_channel else ()
            for form in (shared, shared[None, None], shared[None], *row):
                sums = accumulate(*args, flags=c["flags"], engine=engine, **kw, **{key: form})
                for name in ("ata", "aty", "yty", "count", "nflagged"):
                    np.testing.assert_array_equal(getattr(sums, name), getattr(full, name))
    with pytest.raises(FitError, match="do not broadcast"):
        accumulate(*args, bandwidth_time=np.ones((2, 5)), engine=engine)


@pytest.mark.parametrize("engine", ENGINES)
def test_into_adds_a_chunk_to_running_sums(engine: str) -> None:
    c = random_chunk(22, nant=2, ntime=9, nfreq=8)
    model = FitModel.for_lsts(c["lsts"], "legendre", 1)

    def chunk(t: slice, **kw: object) -> NormalSums:
        return accumulate(
            model,
            c["data"][:, :, t],
            c["tsky"][:, t],
            c["lsts"][t],
            flags=c["flags"][:, :, t],
            bandwidth_time=c["bt"][:, :, t],
            engine=engine,
            **kw,  # type: ignore[arg-type]
        )

    first, second = chunk(slice(0, 5)), chunk(slice(5, 9))
    want = first + second
    running = chunk(slice(0, 5))
    assert chunk(slice(5, 9), into=running) is running
    for name in ("ata", "aty", "yty", "count", "nflagged"):
        np.testing.assert_array_equal(getattr(running, name), getattr(want, name))
    assert (running.lst_min, running.lst_max) == (want.lst_min, want.lst_max)
    with pytest.raises(FitError, match="another model"):
        accumulate(FitModel(), c["data"], c["tsky"], c["lsts"], weights="identity", into=running)
    with pytest.raises(FitError, match=r"into\.ata must be"):
        accumulate(model, c["data"][:1], c["tsky"], c["lsts"], weights="identity", into=running)


@pytest.mark.parametrize("engine", ENGINES)
def test_invalid_user_weights_are_refused(engine: str) -> None:
    c = random_chunk(8, nant=1, ntime=8, nfreq=5)
    model = FitModel()
    usable = np.isfinite(c["data"]) & ~c["flags"]
    first = tuple(np.argwhere(usable)[0])
    for bad in (-1.0, np.nan, np.inf):
        w = np.ones(c["data"].shape)
        w[first] = bad
        with pytest.raises(FitError, match="finite and >= 0"):
            accumulate(
                model, c["data"], c["tsky"], c["lsts"], flags=c["flags"], weights=w, engine=engine
            )
    # bad values where the sample is flagged or non-finite are ignored
    w = np.where(usable, 1.0, -1.0)
    accumulate(model, c["data"], c["tsky"], c["lsts"], flags=c["flags"], weights=w, engine=engine)


def test_engine_choice(monkeypatch: pytest.MonkeyPatch) -> None:
    c = random_chunk(2, nant=1, ntime=6, nfreq=4)
    args = (FitModel(), c["data"], c["tsky"], c["lsts"])
    with pytest.raises(FitError, match="unknown fit engine"):
        accumulate(*args, weights="identity", engine="fortran")  # type: ignore[arg-type]
    monkeypatch.setenv("AUTOCAL_FIT_ENGINE", "bogus")
    with pytest.raises(FitError, match="unknown fit engine"):
        accumulate(*args, weights="identity")
    monkeypatch.setenv("AUTOCAL_FIT_ENGINE", "numpy")
    numpy_sums = accumulate(*args, weights="identity")
    monkeypatch.delenv("AUTOCAL_FIT_ENGINE")
    auto = accumulate(*args, weights="identity")  # small chunk: numpy unless compiled
    np.testing.assert_allclose(auto.ata, numpy_sums.ata, rtol=1e-14)
    monkeypatch.setenv("AUTOCAL_FIT_THREADS", "3")
    assert default_threads() == 3
    monkeypatch.setenv("AUTOCAL_FIT_THREADS", "")
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert default_threads() == 1
