"""The time model and its design (autocal.fit.model)."""

from __future__ import annotations

import numpy as np
import pytest

from autocal.fit.model import FitModel, design


def test_time_axis_maps_across_midnight() -> None:
    lsts = (22.0 + np.arange(49) / 12.0) % 24.0  # 22 h to 2 h
    model = FitModel.for_lsts(lsts, "legendre", 1)
    s = model.s(lsts)
    assert s[0] == pytest.approx(-1.0) and s[-1] == pytest.approx(1.0)
    assert np.all(np.diff(s) > 0)
    assert design(model, np.ones((49, 3)), lsts).shape == (1, 3, 49, 4)
