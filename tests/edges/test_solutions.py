"""Receiver solutions: the files of the data folder and their conventions."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from autocal.edges.lab_files import read_s11_modelled
from autocal.edges.solutions import ReceiverCalError, load_receiver_solution


@pytest.mark.data
def test_receiver_solution_files_and_their_conventions(data_root: Path) -> None:
    alan = load_receiver_solution("edges2-lowband-2015")
    e3 = load_receiver_solution("edges3-2022-316")
    ref = load_receiver_solution("edges2-2015-09")
    assert alan.freqs.size == 1434 and alan.freqs[0] == pytest.approx(40.002441e6)
    assert alan.freqs[-1] == pytest.approx(109.973145e6)
    assert e3.freqs.size == 2868 and 50e6 <= e3.freqs[0] < e3.freqs[-1] <= 190e6
    assert ref.freqs.size == 100
    # the LNA S11 column is the modelled LNA S11 of the same folder
    fs, s11 = read_s11_modelled(
        data_root / "edges/receiver_cal/edges2_lowband_2015/s11_modelled_alan.txt"
    )
    np.testing.assert_allclose(fs, alan.freqs)
    assert np.max(np.abs(s11["lna"] - alan.gamma_rec)) < 1e-6
    # Alan's C1 goes with T_NS = 1000 K, edges-cal's reference with 350 K: same product
    ratio = ref.c1 * ref.t_load_ns / alan.at(ref.freqs).c1 / alan.t_load_ns
    assert np.ptp(ratio) < 2e-3 and abs(np.mean(ratio) - 1) < 0.005
    with pytest.raises(ReceiverCalError, match="covers"):
        alan.at(np.array([120e6]))
    with pytest.raises(ReceiverCalError, match="unknown receiver solution"):
        load_receiver_solution("nope")
