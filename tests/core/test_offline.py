"""The parsed IERS table kept in the user's cache (autocal.core.offline.install_iers_table)."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from astropy.time import Time
from astropy.utils import iers

from autocal.core import offline
from autocal.core.offline import iers_cache_file, install_iers_table
from autocal.core.user_cache import user_cache_dir

# Times spanning the table: IERS-B (final) values, the HERA nights of the data folder,
# IERS-A rapid values and predictions, and both ends of the bundled range.
MJDS = np.concatenate(
    [np.linspace(41684.0, 60000.0, 37), np.linspace(58042.1, 58098.9, 50), [61000.0, 61300.5]]
)


@pytest.fixture
def iers_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A private IERS cache folder; restores the session's table afterwards."""
    folder = tmp_path / "iers"
    monkeypatch.setenv("AUTOCAL_IERS_CACHE", str(folder))
    previous = iers.earth_orientation_table.get()
    yield folder
    iers.earth_orientation_table.set(previous)


def _no_parse(monkeypatch: pytest.MonkeyPatch) -> None:
    """Make any parse of the IERS text files fail."""

    def boom(*args: object, **kwargs: object) -> None:
        raise AssertionError("the IERS text files were parsed")

    monkeypatch.setattr(iers.IERS_Auto, "open", classmethod(boom))
    monkeypatch.setattr(iers.IERS_A, "read", classmethod(boom))
    monkeypatch.setattr(iers.IERS_B, "read", classmethod(boom))


def _assert_same_earth_orientation(table: iers.IERS, parsed: iers.IERS) -> None:
    times = Time(MJDS, format="mjd", scale="utc")
    np.testing.assert_array_equal(
        table.ut1_utc(times, return_status=True)[0].value,
        parsed.ut1_utc(times, return_status=True)[0].value,
    )
    for mine, theirs in zip(table.pm_xy(times), parsed.pm_xy(times), strict=True):
        np.testing.assert_array_equal(mine.value, theirs.value)
    for mine, theirs in zip(table.dcip_xy(times), parsed.dcip_xy(times), strict=True):
        np.testing.assert_array_equal(mine.value, theirs.value)


def test_the_cached_table_is_the_one_astropy_parses_and_is_read_without_parsing(
    iers_cache: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    install_iers_table()
    path = iers_cache_file()
    assert path is not None and path.parent == iers_cache and path.is_file()
    parsed = iers.IERS_Auto.read()
    _assert_same_earth_orientation(iers.earth_orientation_table.get(), parsed)

    _no_parse(monkeypatch)
    before = iers.earth_orientation_table.get()
    install_iers_table()
    table = iers.earth_orientation_table.get()
    assert table is not before  # a new copy, read from the file
    _assert_same_earth_orientation(table, parsed)
    # what the pipeline computes from it: the LST of a HERA time, as astropy gives it
    hera = Time(2458043.40141, format="jd", location=("21.4283d", "-30.7215d"))
    lst = hera.sidereal_time("apparent").hour
    with iers.earth_orientation_table.set(parsed):
        assert (
            lst == Time(hera.jd, format="jd", location=hera.location).sidereal_time("apparent").hour
        )


def test_a_damaged_entry_is_replaced(iers_cache: Path, caplog: pytest.LogCaptureFixture) -> None:
    install_iers_table()
    path = iers_cache_file()
    assert path is not None
    size = path.stat().st_size
    path.write_bytes(path.read_bytes()[: size // 2])  # truncated
    with caplog.at_level(logging.WARNING, logger="autocal.core.offline"):
        install_iers_table()
    assert "replacing the unreadable IERS table cache" in caplog.text
    assert path.stat().st_size == size
    _assert_same_earth_orientation(iers.earth_orientation_table.get(), iers.IERS_Auto.read())

    path.write_bytes(b"not a pickle")
    install_iers_table()
    assert path.stat().st_size == size


def test_no_entry_when_switched_off_or_astropy_would_read_a_local_file(
    iers_cache: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("AUTOCAL_IERS_CACHE", "off")
    assert user_cache_dir("AUTOCAL_IERS_CACHE", "iers") is None
    assert iers_cache_file() is None
    before = iers.earth_orientation_table.get()
    install_iers_table()
    assert iers.earth_orientation_table.get() is before

    monkeypatch.setenv("AUTOCAL_IERS_CACHE", str(iers_cache))
    assert iers_cache_file() is not None
    monkeypatch.chdir(tmp_path)
    (tmp_path / "finals2000A.all").write_text("")
    assert iers_cache_file() is None


def test_a_new_iers_data_release_gets_its_own_entry(
    iers_cache: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import astropy_iers_data

    first = iers_cache_file()
    monkeypatch.setattr(astropy_iers_data, "__version__", "0.9999.1.1.0.0.0")
    second = iers_cache_file()
    assert first is not None and second is not None and first != second
    assert first.parent == second.parent == iers_cache


def test_an_unusable_cache_folder_only_costs_the_parse(
    tmp_path: Path, iers_cache: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    sentinel = iers.IERS_Auto.read()
    monkeypatch.setattr(iers.IERS_Auto, "open", classmethod(lambda cls: sentinel))
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    monkeypatch.setenv("AUTOCAL_IERS_CACHE", str(blocker / "iers"))  # cannot be a folder
    install_iers_table()
    assert iers.earth_orientation_table.get() is sentinel

    monkeypatch.setenv("AUTOCAL_IERS_CACHE", str(iers_cache))

    def refuse(*args: object) -> None:
        raise PermissionError("read-only file system")

    monkeypatch.setattr(offline.os, "replace", refuse)  # the entry cannot be written
    iers.earth_orientation_table.set(iers.IERS_B.open())
    install_iers_table()
    assert iers.earth_orientation_table.get() is sentinel
    assert list(iers_cache.iterdir()) == []  # no entry, no temporary file left


def test_an_entry_others_could_have_written_is_not_loaded(
    iers_cache: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    install_iers_table()
    path = iers_cache_file()
    assert path is not None and path.is_file()
    sentinel = iers.IERS_Auto.read()
    monkeypatch.setattr(iers.IERS_Auto, "open", classmethod(lambda cls: sentinel))
    for item in (iers_cache, path):
        mode = item.stat().st_mode
        item.chmod(mode | 0o002)  # writable by everyone
        with caplog.at_level(logging.WARNING, logger="autocal.core.offline"):
            install_iers_table()
        assert "writable by everyone; not loading it" in caplog.text
        assert iers.earth_orientation_table.get() is sentinel  # parsed, not unpickled
        item.chmod(mode)
        caplog.clear()
    install_iers_table()
    assert iers.earth_orientation_table.get() is not sentinel  # trusted again: loaded


def test_importing_autocal_installs_the_cached_table(tmp_path: Path) -> None:
    """A new process with a warm cache converts times without parsing the text files."""
    script = (
        "from astropy.utils import iers\n"
        "def boom(*a, **k):\n"
        "    raise SystemExit('parsed the IERS text files')\n"
        "if {warm}:\n"
        "    iers.IERS_Auto.open = classmethod(boom)\n"
        "import autocal\n"
        "from astropy.time import Time\n"
        "print(Time(2458043.4, format='jd').ut1.jd)\n"
    )
    env = {**os.environ, "AUTOCAL_IERS_CACHE": str(tmp_path / "iers")}
    env.pop("AUTOCAL_ALLOW_DOWNLOAD", None)
    cold = subprocess.run(
        [sys.executable, "-c", script.format(warm=False)], env=env, capture_output=True, text=True
    )
    assert cold.returncode == 0, cold.stderr
    assert list((tmp_path / "iers").glob("IERS_Auto-*.pickle"))
    warm = subprocess.run(
        [sys.executable, "-c", script.format(warm=True)], env=env, capture_output=True, text=True
    )
    assert warm.returncode == 0, warm.stderr
    assert warm.stdout == cold.stdout


def test_cache_folders_follow_the_variables_and_xdg(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("AUTOCAL_IERS_CACHE", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert user_cache_dir("AUTOCAL_IERS_CACHE", "iers") == tmp_path / "xdg" / "autocal" / "iers"
    monkeypatch.setenv("AUTOCAL_IERS_CACHE", " OFF ")
    assert user_cache_dir("AUTOCAL_IERS_CACHE", "iers") is None
    monkeypatch.setenv("AUTOCAL_IERS_CACHE", str(tmp_path / "mine"))
    assert user_cache_dir("AUTOCAL_IERS_CACHE", "iers") == tmp_path / "mine"
    # no home folder: no default cache, rather than a "~" folder in the working directory
    monkeypatch.delenv("AUTOCAL_IERS_CACHE")
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setattr(Path, "home", classmethod(lambda cls: Path("~")))
    assert user_cache_dir("AUTOCAL_IERS_CACHE", "iers") is None
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/cache")
    assert user_cache_dir("AUTOCAL_IERS_CACHE", "iers") is None
