"""Every antenna-pol its own gain series."""

from __future__ import annotations

import dataclasses

import numpy as np

from autocal.diagnosis.catalogue import catalogue
from autocal.diagnosis.extended_fit import fit_extended, radiometer_weights
from autocal.diagnosis.feeds import fit_feed_gains
from tests.diagnosis.simulated import hidden, s_of


def test_feed_gains_with_a_dead_antenna(setup):
    """Every antenna-pol its own drift: an antenna-pol without data follows the shared
    series and adds no parameter; an integration flagged for one antenna-pol only leaves
    its own jitter factor without data, which takes no part in the fit (it was an error
    that hid the effect)."""
    obs, tpl = setup
    drift = next(e for e in catalogue(nfeeds=2) if e.name == "antenna_gain_drift" and e.order == 1)
    jitter = next(e for e in catalogue(ntime=obs.ntime) if e.basis == "integration")
    two = hidden(obs, tpl.total)
    two = dataclasses.replace(
        two,
        antennas=np.array([0, 1]),
        antenna_names=("ant0", "ant1"),
        data=np.concatenate([two.data, two.data * (1 + 0.01 * s_of(obs.lsts))[:, None]]),
        flags=np.concatenate([two.flags, two.flags]),
        nsamples=np.concatenate([two.nsamples, two.nsamples]),
    )
    w = radiometer_weights(two, two.data)
    current = fit_extended(two, tpl, [], weights=w)
    feed = fit_feed_gains(two, tpl, [], current, w, {}, drift)
    assert feed is not None and feed.k == 2
    assert abs(feed.values[1, 0, 0] - 0.01) < 1e-3 and abs(feed.values[0, 0, 0]) < 1e-3
    dead = dataclasses.replace(two, flags=two.flags.copy())
    dead.flags[1] = True
    feed = fit_feed_gains(dead, tpl, [], current, w, {}, drift)
    assert feed is not None and feed.k == 1
    np.testing.assert_array_equal(feed.factors[1], 1.0)
    # an integration flagged for one antenna-pol only: its own jitter factor has no data
    gap = dataclasses.replace(two, flags=two.flags.copy())
    gap.flags[1, 0, 5] = True
    wg = radiometer_weights(gap, gap.data)
    with_jitter = fit_extended(gap, tpl, [jitter], weights=wg)
    own = next(e for e in catalogue(ntime=obs.ntime, nfeeds=2) if e.name == "antenna_gain_jitter")
    # its factor there takes no part (not "degenerate"): the other integrations are fitted
    gapped = fit_feed_gains(gap, tpl, [jitter], with_jitter, wg, {}, own)
    assert gapped is not None
    assert np.isfinite(np.delete(gapped.factors[1, 0], 5)).all()
    assert np.isfinite(gapped.factors[0]).all()


def test_feed_departures_judged_against_the_bulk_of_the_residuals(setup):
    """A few strong outliers (RFI not yet flagged) inflate the antenna-pols' chi2/dof
    several-fold; the overdispersion their departures are judged against is the bulk's
    (a median), which stays near 1."""
    obs, tpl = setup
    jitter = next(e for e in catalogue(ntime=obs.ntime) if e.basis == "integration")
    own = next(e for e in catalogue(ntime=obs.ntime, nfeeds=2) if e.name == "antenna_gain_jitter")
    one = hidden(obs, tpl.total)
    two = dataclasses.replace(
        one,
        antennas=np.array([0, 1]),
        antenna_names=("ant0", "ant1"),
        data=np.concatenate([one.data, one.data]),
        flags=np.concatenate([one.flags, one.flags]),
        nsamples=np.concatenate([one.nsamples, one.nsamples]),
    )
    spikes = np.random.default_rng(3).random(two.data.shape) < 0.01
    two.data[spikes] *= 1.03  # 1 % of the samples, ~30 radiometer sigma each
    w = radiometer_weights(two, two.data)
    current = fit_extended(two, tpl, [jitter], weights=w)
    feed = fit_feed_gains(two, tpl, [jitter], current, w, {}, own)
    assert feed is not None
    assert feed.reduced_chi2 > 5.0
    assert 0.8 < feed.bulk_overdispersion < 1.5
