"""Which entries the data cannot tell from the step's best (:mod:`autocal.diagnosis.rivals`).

The rule on synthetic trials (the band-consistency check replaced by a stand-in); its effect
on data autocal did not make is in ``test_diagnose_independent.py`` (a clean half hour
through the HERA beam) and on autocal's own suite in ``test_hidden.py``.
"""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any

import pytest

from autocal.diagnosis import rivals
from autocal.diagnosis.catalogue import catalogue
from autocal.diagnosis.report import Diagnosis, summary_text
from autocal.diagnosis.trials import BandpassTrial, ModelTrial

ENTRIES = {e.name: e for e in catalogue(include_timing=True, ntime=100, nfeeds=2)}
NDATA = 10_000


def trial(name: str, statistic: float, k: int = 1) -> ModelTrial:
    """A trial whose Delta chi2 gives ``statistic`` as Delta BIC (c = 1)."""
    delta = statistic + k * math.log(NDATA)
    return ModelTrial(
        effect=ENTRIES[name],
        delta_chi2=delta,
        k=k,
        overdispersion=1.0,
        statistic=statistic,
        fit=SimpleNamespace(),
        free_fit=SimpleNamespace(),
        adopted=ENTRIES[name],
    )


#: The sigma of the best's lead over each entry that the ``search`` fixture's stand-in
#: for :func:`rivals.lead_sigma` gives (0 when not listed: the margin alone decides).
LEAD_SIGMA: dict[str, float] = {}


@pytest.fixture
def search(monkeypatch: pytest.MonkeyPatch) -> tuple[Any, Any, set[str]]:
    """A context and state; band_consistency says 'inconsistent' for names in the set."""
    inconsistent: set[str] = set()

    def check(ctx: Any, state: Any, trial: Any) -> Any:
        if trial.effect.name in inconsistent:
            return SimpleNamespace(consistent=False)
        return None  # no verdict

    monkeypatch.setattr(rivals, "check_trial", check)
    LEAD_SIGMA.clear()
    monkeypatch.setattr(
        rivals, "lead_sigma", lambda ctx, best, trial: LEAD_SIGMA.get(trial.effect.name, 0.0)
    )
    ctx = SimpleNamespace(
        settings=SimpleNamespace(bic_threshold=10.0, alpha=1e-4), tpl=None, prior_kw={}
    )
    state = SimpleNamespace(obs=None, active=[], weights=None)
    return ctx, state, inconsistent


def test_rivals_are_the_passing_entries_within_the_margin(search: Any) -> None:
    """Within DECISIVE_MARGIN and passing: rivals; further behind, or not significant: not."""
    ctx, state, _ = search
    m = rivals.DECISIVE_MARGIN
    best = trial("noise_drift", 142.0)
    trials = [
        best,
        trial("timing_offset", 142.0 - 0.5 * m),
        trial("sky_scale", 142.0 - 0.99 * m),
        trial("gain_drift", 142.0 - 1.01 * m),
        trial("ground_temperature", 20.0),
    ]
    got = rivals.find_rivals(ctx, state, best, trials)
    assert [t.effect.name for t in got] == ["timing_offset", "sky_scale"]
    # a best barely above the threshold: a rival below it does not pass the test
    weak = trial("noise_drift", 12.0)
    assert rivals.find_rivals(ctx, state, weak, [weak, trial("timing_offset", 9.0)]) == []


def test_a_lead_within_twice_its_own_noise_is_no_decision(
    search: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Beyond the margin a lead decides only when it is more than LEAD_SIGMAS sigma of its
    own noise (the two fits' difference, Vuong's test); the sigmas computed are handed
    back; an entry far behind is not even asked for its sigma (the bound from the two
    Delta chi2 already rules it out), but a fixed hypothesis, which has no such bound, is;
    a sigma that cannot be computed (NaN) decides nothing."""
    ctx, state, _ = search
    best = trial("noise_drift", 268.0, k=2)
    LEAD_SIGMA.update({"timing_offset": 13.0, "gain_drift": 13.0, "sky_offset": 1.0})
    trials = [
        best,
        trial("timing_offset", 260.0),  # 8 behind: 0.6 sigma
        trial("gain_drift", 230.0, k=2),  # 38 behind: 2.9 sigma
        trial("sky_offset", 255.0),  # 13 behind: 13 sigma
    ]
    sigmas: dict[str, float] = {}
    got = rivals.find_rivals(ctx, state, best, trials, sigmas)
    assert [t.effect.name for t in got] == ["timing_offset"]
    assert sigmas == {"timing_offset": 13.0, "gain_drift": 13.0, "sky_offset": 1.0}
    asked: list[str] = []

    def sigma(c: Any, b: Any, t: Any) -> float:
        asked.append(t.effect.name)
        return 1e9

    monkeypatch.setattr(rivals, "lead_sigma", sigma)
    big = trial("noise_drift", 1000.0, k=2)
    far = trial("sky_scale", 500.0)  # passes the test; bound 2 (32 + 23) = 109: 6 + 2 x 109 < 500
    assert rivals.find_rivals(ctx, state, big, [big, far]) == []
    assert asked == []
    fixed = trial("missing_cmb", 500.0, k=0)  # a fixed hypothesis: no bound, asked
    assert [t.effect.name for t in rivals.find_rivals(ctx, state, big, [big, fixed])] == [
        "missing_cmb"
    ]
    assert asked == ["missing_cmb"]
    monkeypatch.setattr(rivals, "lead_sigma", lambda c, b, t: math.nan)
    assert rivals.find_rivals(ctx, state, big, [big, trial("timing_offset", 980.0)]) != []


def test_nested_inconsistent_and_earlier_trials_are_not_rivals(search: Any) -> None:
    """missing_cmb is sky_offset at T_offset = -2.725 K: not a rival; nor one whose band
    halves disagree, nor a trial ranked above the best (it failed the band check)."""
    ctx, state, inconsistent = search
    inconsistent.add("sky_scale")
    failed = trial("beam_width", 300.0)
    best = trial("missing_cmb", 100.0, k=0)
    trials = [failed, best, trial("sky_offset", 99.0), trial("sky_scale", 98.0)]
    assert rivals.find_rivals(ctx, state, best, trials) == []
    inconsistent.clear()
    got = rivals.find_rivals(ctx, state, best, trials)
    assert [t.effect.name for t in got] == ["sky_scale"]


def test_a_bandpass_winner_has_no_rivals(search: Any) -> None:
    """A reflection is ranked on the bandpass (N = Nfreq): not compared with time entries."""
    ctx, state, _ = search
    best = BandpassTrial(
        effect=ENTRIES["cable_reflection"],
        delta_chi2=100.0,
        k=3,
        overdispersion=1.0,
        statistic=80.0,
        ripple=SimpleNamespace(),
    )
    assert rivals.find_rivals(ctx, state, best, [best, trial("gain_drift", 79.0)]) == []


def test_domains_split_receiver_from_forward_model() -> None:
    """Gains, noise and the bandpass are the receiver's; sky, ground, beam, timing not."""
    receiver = {n for n, e in ENTRIES.items() if rivals.domain(e) == "receiver"}
    assert receiver == {
        "gain_jitter",
        "gain_drift",
        "noise_drift",
        "antenna_gain_jitter",
        "antenna_gain_drift",
        "cable_reflection",
    }
    assert rivals.domain(ENTRIES["timing_offset"]) == "forward model"
    assert rivals.domain(ENTRIES["beam_width"]) == "forward model"


def test_summary_states_indistinguishable_steps_and_close_alternatives() -> None:
    """The summary says which entries tie and that none is named; a named step lists its
    close alternatives of the same domain."""
    gap = {"reduced_chi2": 1.0, "rms_normalised_residual": 1.0}
    diag = Diagnosis(
        initial_gap=gap,
        final_gap=gap,
        config={"decisive_margin": rivals.DECISIVE_MARGIN, "lead_sigmas": rivals.LEAD_SIGMAS},
        indistinguishable={"message": "step 1: indistinguishable: ... none is named"},
    )
    text = summary_text(diag)
    assert "none is named" in text and "consistent with the data" not in text
    assert diag.to_dict()["indistinguishable"]["message"].startswith("step 1")
    diag = Diagnosis(
        initial_gap=gap,
        final_gap=gap,
        config={"decisive_margin": rivals.DECISIVE_MARGIN, "lead_sigmas": rivals.LEAD_SIGMAS},
        effects=["missing_cmb"],
        steps=[
            {
                "name": "missing_cmb",
                "parameters": {},
                "statistic": 20026.9,
                "delta": 20026.9,
                "gap_before": gap,
                "gap_after": gap,
                "close_alternatives": {"sky_scale": 20023.6},
            }
        ],
    )
    expected = (
        "nearly as good (Delta BIC within 6.0 of it, or within 2.0 sigma of the noise of its "
        "lead; the same domain): sky_scale"
    )
    assert expected in summary_text(diag)


def test_the_search_stops_on_a_rival_of_the_other_domain_only(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A receiver winner with a forward-model rival: the step is indistinguishable, nothing
    accepted; with a rival of its own domain: accepted, the rival a close alternative."""
    from autocal.diagnosis import stepwise
    from autocal.diagnosis.acceptance import AcceptedStep

    gap = {"reduced_chi2": 1.0}
    accepted: list[str] = []

    def accept(ctx: Any, state: Any, trial: Any, step: int) -> AcceptedStep:
        accepted.append(trial.effect.name)
        return AcceptedStep(parameters={}, gap_before=gap, gap_after=gap, extra={})

    def run(best: ModelTrial, rival: ModelTrial) -> Diagnosis:
        diag = Diagnosis(config={"failed_candidates": {}})
        state = SimpleNamespace(diag=diag, feed_accepted=set())
        monkeypatch.setattr(stepwise, "_fit_candidates", lambda c, s, k: [best, rival])
        monkeypatch.setattr(stepwise, "_best_consistent", lambda c, s, t, k: (best, None))
        monkeypatch.setattr(stepwise, "find_rivals", lambda c, s, b, t, sig=None: [rival])
        monkeypatch.setattr(
            stepwise, "indistinguishable_record", lambda c, s, k, b, r, sig=None: {"step": k + 1}
        )
        monkeypatch.setattr(stepwise, "accept", accept)
        ctx = SimpleNamespace(settings=SimpleNamespace(bic_threshold=10.0, alpha=1e-4))
        stepwise._search_step(ctx, state, 0)
        return diag

    diag = run(trial("noise_drift", 142.0), trial("timing_offset", 139.0))
    assert diag.indistinguishable == {"step": 1} and accepted == [] and diag.effects == []
    diag = run(trial("missing_cmb", 100.0, k=0), trial("sky_scale", 97.0))
    assert accepted == ["missing_cmb"] and diag.effects == ["missing_cmb"]
    assert diag.indistinguishable is None
    assert diag.steps[0]["close_alternatives"] == {"sky_scale": 97.0}


def _fits(obs: Any, tpl: Any, truth: Any, seed: int, kw: dict[str, Any]) -> tuple[Any, Any]:
    """A noise drift and a diurnal gain drift fitted to one noise realisation of ``truth``."""
    import numpy as np

    from autocal.diagnosis.extended_fit import fit_extended, radiometer_weights
    from tests.diagnosis.simulated import hidden, s_of

    trxr = (150 * (1 + 0.002 * s_of(obs.lsts)))[:, None] * np.ones(obs.nfreq)
    data = hidden(obs, truth, trxr=trxr, seed=seed)
    w = radiometer_weights(data, data.data)
    cat = catalogue(ntime=obs.ntime)
    noise = next(e for e in cat if e.name == "noise_drift" and e.order == 1)
    gain = next(e for e in cat if e.name == "gain_drift" and e.basis == "diurnal")
    return (
        fit_extended(data, tpl, [noise], weights=w, **kw),
        fit_extended(data, tpl, [gain], weights=w, **kw),
    )


@pytest.mark.slow
def test_lead_sigma_is_the_noise_of_the_lead(setup: Any) -> None:
    """The sigma of a lead is what the lead scatters by over noise realisations.

    A small noise drift (0.2 % of Trxr over the day) fitted as a noise drift and as a
    diurnal gain drift in 24 realisations of the radiometer noise: the standard deviation
    of their chi2 difference matches ``lead_sigma`` (Vuong's 2 |m_a - m_b|) within the
    sampling error of 24 draws, and ``lead_sigma`` equals the sum computed here from the
    two fits' models, weights and prior rows.
    """
    import numpy as np

    from autocal.diagnosis.extended_fit import radiometer_weights

    obs, tpl = setup
    kw = {"trxr_prior": 150.0, "trxr_prior_sigma": 1.0, "gain_ref": None}
    base = _fits(obs, tpl, tpl.total, 0, {**kw, "gain_ref": None})[0]
    kw["gain_ref"] = np.abs(base.G)
    leads, sigmas = [], []
    for seed in range(24):
        a, b = _fits(obs, tpl, tpl.total, 100 + seed, kw)
        ctx = SimpleNamespace(prior_kw=kw)
        best = SimpleNamespace(fit=a, overdispersion=1.0)
        other = SimpleNamespace(fit=b, overdispersion=1.0)
        sigma = rivals.lead_sigma(ctx, best, other)
        leads.append(b.chi2 - a.chi2)
        sigmas.append(sigma)
        if seed == 0:  # the same sum, written out
            w = radiometer_weights(a.source.obs, a.source.obs.data)
            w = np.where(a.source.chan_ok[:, :, None, :] & b.source.chan_ok[:, :, None, :], w, 0)
            data_rows = float(np.sum(w * (a.model - b.model) ** 2))
            t0, ref = 150.0, kw["gain_ref"]
            prior_rows = float(np.sum((((a.n - b.n) - t0 * (a.G - b.G)) / ref) ** 2))
            assert sigma == pytest.approx(2 * math.sqrt(data_rows + prior_rows), rel=1e-6)
    spread = float(np.std(leads, ddof=1))
    predicted = float(np.median(sigmas))
    # the sample sd of 24 draws is within ~30 % of the truth at 2 sigma (chi distribution)
    assert 0.6 * predicted < spread < 1.45 * predicted, (spread, predicted, np.mean(leads))
