"""Reference gains read from every calfits/calh5 file in the data folder, joined and selected."""

from __future__ import annotations

import numpy as np
import pytest

import autocal  # noqa: F401  (offline configuration first)
from autocal.io.calsol_files import CalsolFormatError
from autocal.io.calsol_read import ReferenceGains, read_reference_gains
from tests.io.test_calsol import ABS_54, H1C_ABS, OMNI_36, REF, SINGLE_FILES


@pytest.mark.data
def test_reads_every_reference_gain_file(data_root):
    folder = data_root / REF
    names = sorted(p.name for p in folder.iterdir())
    assert set(names) == set(SINGLE_FILES), "a reference-gain file is not covered"
    for name, (shape, pols, absolute) in SINGLE_FILES.items():
        ref = read_reference_gains(folder / name)
        assert isinstance(ref, ReferenceGains)
        assert ref.gains.shape == shape, name
        assert ref.pols == pols, name
        assert ref.absolute is absolute, (name, ref.meta["kind_reason"])
        assert ref.gain_convention == "divide"
        assert ref.gain_scale == ("Jy" if absolute else None)
        assert np.all(np.diff(ref.freqs) > 0) and np.all(np.diff(ref.jds) > 0)
        assert ref.lsts is not None and np.all((ref.lsts >= 0) & (ref.lsts < 24))
        assert ref.meta["sha256"][0] and len(ref.meta["sha256"][0]) == 64
        assert np.iscomplexobj(ref.gains)
        med = np.nanmedian(ref.abs_g)
        assert (med < 0.1) if absolute else (0.5 < med < 2.0), name


@pytest.mark.data
def test_joins_consecutive_files_and_records_quirks(data_root):
    folder = data_root / REF
    h1c = read_reference_gains([folder / n for n in H1C_ABS])
    assert h1c.gains.shape == (3, 2, 36, 1024)
    assert h1c.antennas.tolist() == [23, 24, 25]
    assert h1c.absolute and h1c.gain_scale == "Jy"
    assert 0.02 < np.nanmedian(h1c.abs_g) < 0.035
    assert h1c.meta["x_orientation"] == "east"
    assert h1c.meta["jones"] == [-5, -6]
    assert np.all(np.diff(h1c.jds) > 0)
    # The old 2018 omnical files lack antenna positions: read without pyuvdata's checks.
    omni = read_reference_gains([folder / n for n in reversed(OMNI_36)])
    assert omni.gains.shape == (1, 1, 180, 1024)
    assert len(omni.meta["unchecked_files"]) == 3
    assert not omni.absolute and "near unity" in omni.meta["kind_reason"]
    assert np.all(np.diff(omni.jds) > 0)  # sorted although given in reverse
    # Named 'abs' but redcal-derived (|g| ~ 0.93): relative, with the reason recorded.
    xraa = read_reference_gains(folder / "zen.2458043.40141.xx.HH.XRAA.abs.calfits")
    assert not xraa.absolute and "abs" in xraa.meta["kind_reason"]
    forced = read_reference_gains(
        folder / "zen.2458043.40141.xx.HH.XRAA.abs.calfits", absolute=True
    )
    assert forced.absolute and forced.gain_scale == "Jy"


@pytest.mark.data
def test_selection_and_clear_errors(data_root):
    files = [data_root / REF / n for n in H1C_ABS[:1]]
    ref = read_reference_gains(files, antennas=[25, 23], pols=["nn"], freq_range=(150e6, 120e6))
    assert ref.antennas.tolist() == [25, 23]
    assert ref.pols == ("nn",)
    assert ref.freqs.min() >= 120e6 and ref.freqs.max() <= 150e6
    full = read_reference_gains(files)
    j = np.searchsorted(full.freqs, ref.freqs[0])
    np.testing.assert_array_equal(ref.gains[1, 0], full.gains[0, 1, :, j : j + ref.nfreq])
    alias = read_reference_gains(files, pols=["xx"])  # x feed points east: xx is ee
    assert alias.pols == ("ee",)
    with pytest.raises(
        CalsolFormatError, match=r"antenna\(s\) \[99\].*available antennas: \[23, 24, 25\]"
    ):
        read_reference_gains(files, antennas=[99])
    with pytest.raises(CalsolFormatError, match="available"):
        read_reference_gains(data_root / REF / OMNI_36[0], pols=["nn"])
    with pytest.raises(CalsolFormatError, match="no channels"):
        read_reference_gains(files, freq_range=(100.0, 200.0))  # MHz given for Hz
    with pytest.raises(CalsolFormatError, match="cannot be joined"):
        read_reference_gains([files[0], data_root / REF / ABS_54[0]])
