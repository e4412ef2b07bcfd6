"""The jitter test's overdispersion."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from autocal.diagnosis.dispersion import robust_overdispersion


def test_robust_overdispersion_ignores_a_few_outliers() -> None:
    """The bulk's scatter: 1 for unit normal residuals with 1 % huge outliers, which
    multiply chi2/dof by ~100."""
    rng = np.random.default_rng(5)
    res = rng.standard_normal((1, 2, 200, 100))
    res.flat[::100] = 100.0
    res[0, 0, 0, 0] = np.nan
    fit = SimpleNamespace(residuals=res, reduced_chi2=float(np.nanmean(res**2)))
    assert fit.reduced_chi2 > 50
    assert robust_overdispersion(fit) == pytest.approx(1.0, abs=0.05)
