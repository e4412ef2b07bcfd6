"""The batched gain / receiver-noise fit (autocal.fit.lsq)."""

from __future__ import annotations

import numpy as np
import pytest

from autocal.core.observation import Observation
from autocal.core.sites import HERA
from autocal.fit.lsq import (
    MAX_CONDITION,
    FitError,
    FitModel,
    NormalSums,
    Solution,
    _default_threads,
    _eigvalsh,
    _inv,
    _num_array,
    _numba_available,
    _offset_copy,
    _time_functions,
    accumulate,
    design,
    fit,
    solve_sums,
)

NT, NF = 144, 40
LSTS = np.arange(NT) * 24.0 / NT
FREQS = np.linspace(110e6, 190e6, NF)


def toy_tsky(nfreq: int = NF) -> np.ndarray:
    """A day of sky: bright peak near LST 17.5 h, falling with frequency."""
    f = np.linspace(110e6, 190e6, nfreq)
    shape = 1.0 + 3.0 * np.exp(-0.5 * ((LSTS - 17.5) / 3.0) ** 2)
    return 250.0 * shape[:, None] * (f / 150e6)[None, :] ** -2.5


def make_obs(data: np.ndarray, flags: np.ndarray | None = None, bt: float = 5e3) -> Observation:
    nant, npol, nt, nf = data.shape
    return Observation(
        data=data,
        freqs=np.linspace(110e6, 190e6, nf),
        lsts=LSTS[:nt],
        jds=2458098.0 + np.arange(nt) / 288.0,
        antennas=np.arange(nant),
        pols=("ee", "nn")[:npol],
        site=HERA,
        flags=flags,
        channel_width=bt,
        integration_time=1.0,
    )


def noisy(clean: np.ndarray, rng: np.random.Generator, bt: float = 5e3) -> np.ndarray:
    return clean * (1 + rng.standard_normal(clean.shape) / np.sqrt(bt))


def test_noiseless_constant_and_legendre_recover_truth() -> None:
    tsky = toy_tsky()
    s = FitModel.for_lsts(LSTS, "legendre", 2).s(LSTS)
    gain = (1.2 + 0.05 * s - 0.02 * (1.5 * s**2 - 0.5))[:, None] * np.ones(NF)
    trxr = 100.0 + 0.3 * (FREQS / 1e6 - 150.0)
    data = (gain * (tsky + trxr))[None, None]
    sol2 = fit(make_obs(data), tsky, model="legendre", order=2)
    ev = sol2.evaluate()
    np.testing.assert_allclose(ev["G"][0, 0], gain, rtol=1e-9)
    np.testing.assert_allclose(ev["Trxr"][0, 0], np.broadcast_to(trxr, (NT, NF)), rtol=1e-8)
    const = (1.3 * (tsky + trxr))[None, None]
    sol0 = fit(make_obs(const), tsky)
    np.testing.assert_allclose(sol0.G[0, 0], 1.3, rtol=1e-10)
    np.testing.assert_allclose(sol0.Trxr[0, 0], trxr, rtol=1e-9)
    np.testing.assert_allclose(sol0.abs_g, np.sqrt(1.3), rtol=1e-10)


def test_pulls_are_unit_normal_with_radiometer_weights() -> None:
    """Over many noise draws, (fit - truth) / sigma_stat has standard deviation 1 +- 0.1,
    and with the total errors (jackknife, drift model) 1 +- 0.35 on these clean data."""
    rng = np.random.default_rng(42)
    tsky = toy_tsky()
    clean = (tsky + 150.0)[None, None]
    stat: dict[str, list[np.ndarray]] = {"G": [], "n": [], "Trxr": []}
    total: dict[str, list[np.ndarray]] = {"G": [], "n": [], "Trxr": []}
    truth = {"G": 1.0, "n": 150.0, "Trxr": 150.0}
    for _ in range(60):
        sol = fit(make_obs(noisy(clean, rng)), tsky)
        assert sol.total is not None
        for name, value in truth.items():
            stat[name].append((getattr(sol, name) - value) / getattr(sol, f"sigma_{name}_stat"))
            total[name].append((getattr(sol, name) - value) / getattr(sol, f"sigma_{name}"))
    for name in truth:
        arr, tot = np.ravel(stat[name]), np.ravel(total[name])
        assert abs(np.std(arr) - 1.0) < 0.1, name
        assert abs(np.mean(arr)) < 0.1, name
        assert abs(np.std(tot) - 1.0) < 0.35, name
        assert np.all(np.abs(tot) <= np.abs(arr) + 1e-12), name  # the total never shrinks


def test_model_weights_remove_the_data_weight_bias() -> None:
    """Weights from the data bias G low by ~2/(dnu dt); the second pass removes it."""
    rng = np.random.default_rng(7)
    bt = 200.0  # strong noise makes the effect visible: expected bias -2/bt = -1 %
    tsky = toy_tsky(400)
    clean = (tsky + 150.0)[None, None]
    data = noisy(clean, rng, bt)
    one = fit(make_obs(data, bt=bt), tsky, passes=1)
    two = fit(make_obs(data, bt=bt), tsky, passes=2)
    sem = np.median(two.sigma_G) / np.sqrt(400)
    assert np.mean(one.G) - 1 < -5 * sem
    assert abs(np.mean(two.G) - 1) < 3 * sem


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


def test_flags_and_failures_are_reported_not_filled() -> None:
    tsky = toy_tsky()
    data = (1.0 * (tsky + 150.0))[None, None].copy()
    flags = np.zeros(data.shape, bool)
    flags[..., :10, 0] = True  # partly flagged channel
    flags[..., :, 1] = True  # fully flagged channel
    data[..., 5, 2] = np.nan  # one non-finite sample
    tsky_bad = tsky.copy()
    tsky_bad[:, 3] = 500.0  # constant sky: G and n are degenerate
    data[..., 3] = 1.0 * (500.0 + 150.0)
    data[..., 4] = -1.0 * (tsky[:, 4] + 150.0)  # negative gain
    sol = fit(make_obs(data, flags), tsky_bad, weights="identity")
    assert sol.flag_reason[0, 0, 1] == 1
    assert sol.flag_reason[0, 0, 3] == 2
    assert sol.flag_reason[0, 0, 4] == 3
    assert sol.flag_reason[0, 0, 0] == 0 and sol.flag_reason[0, 0, 2] == 0
    assert sol.count[0, 0, 0] == NT - 10 and sol.nflagged[0, 0, 0] == 10
    assert sol.nflagged[0, 0, 2] == 1
    for code in (1, 2, 3):
        j = int(np.flatnonzero(sol.flag_reason[0, 0] == code)[0])
        assert np.isnan(sol.G[0, 0, j]) and np.isnan(sol.Trxr[0, 0, j])
    assert np.all(np.isfinite(sol.G[0, 0, 5:]))


def test_identity_weights_scale_covariance_to_residual_variance() -> None:
    rng = np.random.default_rng(11)
    tsky = toy_tsky()
    clean = (tsky + 150.0)[None, None]
    pulls = []
    for _ in range(40):
        data = clean + rng.normal(0.0, 3.0, clean.shape)  # homoscedastic noise
        sol = fit(make_obs(data), tsky, weights="identity")
        pulls.append((sol.G - 1.0) / sol.sigma_G_stat)
        np.testing.assert_allclose(np.median(sol.reduced_chi2), 9.0, rtol=0.15)
    assert abs(np.std(pulls) - 1.0) < 0.1


def test_user_weights_match_radiometer_weights() -> None:
    rng = np.random.default_rng(5)
    tsky = toy_tsky()
    data = noisy((tsky + 150.0)[None, None], rng)
    obs = make_obs(data)
    radio = fit(obs, tsky, passes=1)
    user = fit(obs, tsky, weights=5e3 / data**2)
    np.testing.assert_allclose(user.coeffs, radio.coeffs, rtol=1e-12)
    np.testing.assert_allclose(user.cov, radio.cov, rtol=1e-12)


def test_trxr_uncertainty_matches_jacobian_propagation() -> None:
    """sigma_Trxr equals sqrt(J C J^T) with J = d(n/G)/d(G, n) = (-n/G^2, 1/G)."""
    rng = np.random.default_rng(9)
    tsky = toy_tsky()
    sol = fit(make_obs(noisy((0.8 * (tsky + 150.0))[None, None], rng)), tsky)
    g, n = sol.coeffs[..., 0], sol.coeffs[..., 1]
    jac = np.stack([-n / g**2, 1 / g], axis=-1)
    var = np.einsum("...i,...ij,...j->...", jac, sol.cov, jac)
    np.testing.assert_allclose(sol.sigma_Trxr_stat, np.sqrt(var), rtol=1e-10)
    # the total error propagates the total (G, n) covariance the same way
    assert sol.total is not None
    var_total = np.einsum("...i,...ij,...j->...", jac, sol.total.cov, jac)
    np.testing.assert_allclose(sol.sigma_Trxr, np.sqrt(var_total), rtol=1e-10)
    # slope and intercept anticorrelate (Tsky > 0), so the cross term raises the error:
    # dropping it (or adding it with the wrong sign) would understate sigma_Trxr
    assert np.all(sol.cov[..., 0, 1] < 0)
    naive = sol.Trxr * np.sqrt(sol.sigma_G**2 / g**2 + sol.sigma_n**2 / n**2)
    assert np.all(sol.sigma_Trxr > naive)


def test_time_axis_maps_across_midnight() -> None:
    lsts = (22.0 + np.arange(49) / 12.0) % 24.0  # 22 h to 2 h
    model = FitModel.for_lsts(lsts, "legendre", 1)
    s = model.s(lsts)
    assert s[0] == pytest.approx(-1.0) and s[-1] == pytest.approx(1.0)
    assert np.all(np.diff(s) > 0)
    assert design(model, np.ones((49, 3)), lsts).shape == (1, 3, 49, 4)


def test_residuals_are_normalised() -> None:
    rng = np.random.default_rng(2)
    tsky = toy_tsky()
    obs = make_obs(noisy((tsky + 150.0)[None, None], rng))
    sol = fit(obs, tsky, return_residuals=True)
    assert sol.residuals is not None and sol.residuals.shape == obs.shape
    assert abs(np.nanstd(sol.residuals) - 1.0) < 0.05
    pred = sol.predict(tsky)
    assert pred.shape == obs.shape


def test_bad_inputs_are_refused_with_a_reason() -> None:
    tsky = toy_tsky()
    obs = make_obs((tsky + 150.0)[None, None])
    with pytest.raises(FitError, match="Tsky has shape"):
        fit(obs, tsky[:, :5])
    with pytest.raises(FitError, match="non-finite"):
        fit(obs, np.full_like(tsky, np.nan))
    with pytest.raises(FitError, match="unknown weights"):
        fit(obs, tsky, weights="bogus")
    with pytest.raises(FitError, match="unknown model"):
        FitModel("quadratic")
    with pytest.raises(FitError, match="more than one LST"):
        FitModel.for_lsts(np.array([3.0]), "legendre", 1)
    no_width = Observation(
        data=obs.data,
        freqs=obs.freqs,
        lsts=obs.lsts,
        jds=obs.jds,
        antennas=obs.antennas,
        pols=obs.pols,
        site=HERA,
    )
    with pytest.raises(FitError, match="identity"):
        fit(no_width, tsky)
    for empty in ((1, 1, 0, NF), (0, 1, 4, NF), (1, 1, 4, 0)):
        with pytest.raises(FitError, match="nothing to fit"):
            accumulate(
                FitModel(),
                np.ones(empty),
                np.ones(empty[1:]),
                np.zeros(empty[2]),
                bandwidth_time=np.ones(empty[3]),
            )
    with pytest.raises(FitError, match="shape"):
        Solution(
            model=FitModel(),
            antennas=np.array([0]),
            pols=("ee",),
            freqs=FREQS,
            lsts=LSTS,
            jds=LSTS,
            coeffs=np.zeros((1, 1, NF, 3)),
            cov=np.zeros((1, 1, NF, 2, 2)),
            chi2=np.zeros((1, 1, NF)),
            dof=np.zeros((1, 1, NF)),
            count=np.zeros((1, 1, NF)),
            nflagged=np.zeros((1, 1, NF)),
            flag_reason=np.zeros((1, 1, NF), np.int8),
        )


def test_inflate_scales_errors_only_upwards() -> None:
    rng = np.random.default_rng(4)
    tsky = toy_tsky()
    clean = (tsky + 150.0)[None, None]
    model = FitModel()
    quiet = accumulate(model, noisy(clean, rng), tsky, LSTS, bandwidth_time=5e3)
    loud = accumulate(model, noisy(clean, rng, 5e3 / 9), tsky, LSTS, bandwidth_time=5e3)
    for sums, expected in ((quiet, 1.0), (loud, 9.0)):
        plain = solve_sums(sums)
        inflated = solve_sums(sums, scale_covariance="inflate")
        ratio = inflated["cov"][..., 0, 0] / plain["cov"][..., 0, 0]
        assert np.all(ratio >= 1.0)
        assert np.median(ratio) == pytest.approx(expected, rel=0.2)


# moment-based accumulation against the normal equations written out --------------------


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


def random_chunk(
    seed: int, nant: int = 3, ntime: int = 37, nfreq: int = 11
) -> dict[str, np.ndarray]:
    """Random data with flags, NaN, inf, zeros, and weights that are sometimes unusable."""
    rng = np.random.default_rng(seed)
    shape = (nant, 2, ntime, nfreq)
    data = rng.uniform(50.0, 6000.0, shape)
    data[rng.random(shape) < 0.03] = np.nan
    data[rng.random(shape) < 0.01] = np.inf
    data[rng.random(shape) < 0.01] = 0.0
    flags = rng.random(shape) < 0.1
    flags[0, 0, :, 1] = True  # a fully flagged channel
    bt = rng.uniform(1e3, 1e4, shape)
    bt[rng.random(shape) < 0.05] = 0.0
    reference = data * rng.uniform(0.9, 1.1, shape)
    reference[rng.random(shape) < 0.05] = -1.0
    user = rng.uniform(0.0, 3.0, shape)
    user[rng.random(shape) < 0.05] = 0.0
    user[~(np.isfinite(data) & ~flags) & (rng.random(shape) < 0.5)] = np.nan  # unusable anyway
    return {
        "data": data,
        "flags": flags,
        "tsky": rng.uniform(100.0, 5000.0, (2, ntime, nfreq)),
        "lsts": np.sort(rng.uniform(0.0, 24.0, ntime)),
        "bt": bt,
        "reference": reference,
        "user": user,
    }


WEIGHT_CASES = {
    "identity": lambda c: {"weights": "identity"},
    "radiometer": lambda c: {"bandwidth_time": c["bt"]},
    "radiometer-scalar": lambda c: {"bandwidth_time": 5e3},
    "radiometer-per-channel": lambda c: {"bandwidth_time": c["bt"][0, 0, 0]},
    "radiometer-reference": lambda c: {"bandwidth_time": c["bt"], "reference": c["reference"]},
    "user": lambda c: {"weights": c["user"]},
    "user-scalar": lambda c: {"weights": 2.5},
}
MODELS = [("constant", 0), ("legendre", 0), ("legendre", 1), ("legendre", 2), ("legendre", 4)]
NO_NUMBA = pytest.mark.skipif(not _numba_available(), reason="numba is not installed")
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
    assert _num_array(per_time, c["data"]).shape == per_time.shape
    assert _num_array(per_channel, c["data"]).shape == per_time.shape[1:]
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
    assert _default_threads() == 3
    monkeypatch.setenv("AUTOCAL_FIT_THREADS", "")
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert _default_threads() == 1


def test_time_functions_linearise_the_basis_products() -> None:
    lsts = np.linspace(1.0, 5.0, 50)
    for kind, order in MODELS:
        model = FitModel.for_lsts(lsts, kind, order)
        coef, lin = _time_functions(model, lsts)
        basis = model.basis(lsts)
        np.testing.assert_array_equal(coef[0], 1.0)  # the kernel relies on P_0 = 1
        np.testing.assert_allclose(coef[: model.nbasis], basis, atol=1e-15)
        products = basis[:, None, :] * basis[None, :, :]
        np.testing.assert_allclose(np.einsum("jkr,rt->jkt", lin, coef), products, atol=1e-14)


def test_solve_flags_non_finite_normal_matrices() -> None:
    sums = NormalSums.zeros(FitModel(), 1, 1, 2)
    sums.ata[...] = np.array([[4.0, 1.0], [1.0, 2.0]])
    sums.aty[...] = 1.0
    sums.count[...] = 10
    sums.ata[0, 0, 1, 0, 1] = sums.ata[0, 0, 1, 1, 0] = np.inf
    out = solve_sums(sums)
    assert out["flag_reason"][0, 0, 1] == 2 and np.isnan(out["coeffs"][0, 0, 1]).all()
    assert out["flag_reason"][0, 0, 0] == 0
    np.testing.assert_allclose(
        out["coeffs"][0, 0, 0], np.linalg.solve(sums.ata[0, 0, 0], sums.aty[0, 0, 0])
    )


def test_two_parameter_systems_are_solved_in_closed_form_as_lapack_would() -> None:
    """The constant model's 2 x 2 systems skip LAPACK: eigenvalues and inverses agree
    with numpy's to rounding, conditioning included, and solve_sums flags the same
    channels as singular (condition numbers around MAX_CONDITION, on both sides)."""
    rng = np.random.default_rng(7)
    n = 4000
    a = rng.standard_normal((n, 2, 2))
    a = a @ np.swapaxes(a, -1, -2) + np.eye(2) * rng.uniform(0, 1, (n, 1, 1))
    # near-singular: columns almost parallel, condition numbers from 1e6 to 1e14
    c = np.logspace(6, 14, 200)
    eps = 2.0 / c
    a[:200] = np.stack([np.ones(200), 1 - eps, 1 - eps, np.ones(200)], -1).reshape(200, 2, 2)
    ev = np.linalg.eigvalsh(a)
    np.testing.assert_allclose(_eigvalsh(a), ev, rtol=1e-12, atol=1e-15 * np.abs(ev).max())
    well = np.abs(ev).max(-1) / np.abs(ev).min(-1) < 1e8
    np.testing.assert_allclose(_inv(a)[well], np.linalg.inv(a[well]), rtol=1e-7)
    # the general path is LAPACK's own
    b = rng.standard_normal((5, 3, 3))
    np.testing.assert_array_equal(_eigvalsh(b @ b.mT), np.linalg.eigvalsh(b @ b.mT))
    np.testing.assert_array_equal(_inv(b), np.linalg.inv(b))

    sums = NormalSums.zeros(FitModel(), 1, 1, n)
    sums.ata[0, 0] = a * 1e6  # column scaling is undone by solve_sums
    sums.aty[0, 0] = np.abs(rng.standard_normal((n, 2))) * 1e3
    sums.yty[...] = 1e9
    sums.count[...] = 100
    out = solve_sums(sums)
    cond = np.linalg.cond(a)
    singular = out["flag_reason"][0, 0] == 2
    clear = np.abs(np.log10(cond / MAX_CONDITION)) > 0.01
    np.testing.assert_array_equal(singular[clear], (cond >= MAX_CONDITION)[clear])
    assert singular.any() and not singular.all()
    solved = out["flag_reason"][0, 0] != 2
    ref = np.linalg.solve(sums.ata[0, 0][solved & well], sums.aty[0, 0][solved & well][..., None])
    got = out["coeffs"][0, 0][solved & well]
    keep = np.isfinite(got[:, 0])  # reason 3 (non-positive gain) is NaN in both
    np.testing.assert_allclose(got[keep], ref[keep, :, 0], rtol=1e-7)


def test_solve_in_blocks_gives_the_whole_solve() -> None:
    """Channel blocks bound solve_sums' memory; every block size gives the same arrays,
    including flagged channels of each reason at block edges."""
    c = random_chunk(31, nant=3, ntime=20, nfreq=7)
    model = FitModel.for_lsts(c["lsts"], "legendre", 2)
    sums = accumulate(model, c["data"], c["tsky"], c["lsts"], flags=c["flags"], weights="identity")
    sums.count[0, 0, 0] = 2  # too few samples
    sums.ata[0, 1, 3] = 0.0  # singular
    sums.aty[1, 0, 6, 0] = -1e9  # non-positive gain
    whole = solve_sums(sums, scale_covariance=True, block=sums.count.size)
    assert {1, 2, 3} <= set(np.unique(whole["flag_reason"]))
    for block in (1, 5, 16):
        part = solve_sums(sums, scale_covariance=True, block=block)
        for name, value in whole.items():
            np.testing.assert_array_equal(part[name], value)
            assert part[name].shape == value.shape
    with pytest.raises(FitError, match="block must be at least 1"):
        solve_sums(sums, block=0)


def test_offset_copy_moves_rows_to_other_cache_sets() -> None:
    other = np.zeros((3, 512))
    arr = np.arange(6 * 512, dtype=float).reshape(2, 3, 512)
    for src in (arr, np.broadcast_to(arr[0], (2, 3, 512))):
        out = _offset_copy(src, other)
        np.testing.assert_array_equal(out, src)
        assert out.flags.c_contiguous
        assert (out.ctypes.data - other.ctypes.data) % 4096 == 2048
