"""What a live audit of the command line found (2026-11-29): each now a clear error, early.

Every test failed before its fix: tracebacks (a damaged HDF5 file, Ctrl-C, SIGTERM, a
database URL, huge ranges), output written where it should not be (``--out ""``, a Tsky
table over an existing file, the truth side-car over the data), work done before an error
that was known at the start (an unwritable ``--out``, a missing reference), data
calibrated twice, field names instead of options in messages.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from autocal.cli.main import EXIT_INTERRUPTED, EXIT_USER_ERROR, main

HH = "zen.2458116.31939.HH.uvh5"


@pytest.fixture
def hera(data_root: Path) -> Path:
    return data_root / "hera" / "autos" / HH


def _error(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    assert main(argv) == EXIT_USER_ERROR
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err


def test_a_damaged_hdf5_file_is_called_corrupt(hera, tmp_path, capsys) -> None:
    path = tmp_path / HH
    raw = bytearray(hera.read_bytes())
    raw[4000:8000] = np.random.default_rng(0).bytes(4000)  # the header's B-tree nodes
    path.write_bytes(bytes(raw))
    for command in ("calibrate", "diagnose"):
        err = _error(capsys, [command, str(path), "--out", str(tmp_path / command)])
        assert "corrupt" in err and HH in err


def test_an_empty_or_unwritable_out_is_refused_before_any_work(hera, tmp_path, capsys) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["calibrate", str(hera), "--out", ""])
    assert exit_.value.code == 2 and "output folder is empty" in capsys.readouterr().err
    afile = tmp_path / "afile"
    afile.write_text("x")
    err = _error(capsys, ["calibrate", str(hera), "--out", str(afile)])
    assert "is a file, not a folder" in err
    err = _error(capsys, ["diagnose", str(hera), "--out", str(afile / "sub")])
    assert "cannot be made there" in err


def test_a_missing_reference_is_refused_before_the_fit(hera, tmp_path, capsys) -> None:
    out = tmp_path / "out"
    err = _error(capsys, ["calibrate", str(hera), "--reference", "nope.calfits", "--out", str(out)])
    assert "nope.calfits does not exist" in err
    assert not out.exists()  # not even an empty folder


def test_messages_name_the_options_not_the_fields(hera, tmp_path, capsys) -> None:
    out = str(tmp_path / "o")
    assert "--freq-range must be" in _error(
        capsys, ["calibrate", str(hera), "--freq-range", "180:120", "--out", out]
    )
    err = _error(capsys, ["calibrate", str(hera), "--tgnd", "nan", "--out", out])
    assert err.count("--tgnd") and "tgnd_k" not in err
    assert "finite frequency" in _error(
        capsys, ["calibrate", str(hera), "--freq-range", "120:inf", "--out", out]
    )
    assert "--nside" in _error(capsys, ["calibrate", str(hera), "--nside", "65536", "--out", out])


def test_tsky_refuses_to_overwrite_huge_tables_and_bad_plot_names(tmp_path, capsys) -> None:
    table = tmp_path / "t.h5"
    table.write_text("precious")
    base = ["tsky", "--freqs", "100:200:3", "--lsts", "0:24:3", "--nside", "8"]
    assert "exists; pass --overwrite" in _error(capsys, [*base, "--out", str(table)])
    assert table.read_text() == "precious"
    new = str(tmp_path / "new.h5")
    assert "PNG" in _error(capsys, [*base, "--out", new, "--plot", str(tmp_path / "x.csv")])
    assert not Path(new).exists()  # refused before the table was written
    huge = ["tsky", "--lsts", "0:24:1000000000", "--out", new]
    assert "more than 1000000 points" in _error(capsys, huge)
    big = ["tsky", "--freqs", "100:200:5000", "--lsts", "0:24:100000", "--out", new]
    assert "held in memory" in _error(capsys, big)
    assert "0 (a hard cut) to 30" in _error(capsys, [*base, "--horizon-width=-3", "--out", new])


def test_simulate_checks_its_grid_seed_and_truth_before_simulating(tmp_path, capsys) -> None:
    out = str(tmp_path / "s.uvh5")
    assert "--channel-width" in _error(capsys, ["simulate", "--channel-width", "0", "--out", out])
    assert "--seed" in _error(capsys, ["simulate", "--seed=-1", "--out", out])
    err = _error(
        capsys,
        ["simulate", "--duration", "24", "--cadence", "0.01", "--channel-width", "0.001",
         "--out", out],
    )  # fmt: skip
    assert "a simulation holds in memory" in err
    assert "is --out itself" in _error(capsys, ["simulate", "--out", out, "--truth", out])
    missing = str(tmp_path / "no" / "t.h5")
    assert "does not exist" in _error(capsys, ["simulate", "--out", out, "--truth", missing])
    assert not Path(out).exists()


def test_apply_refuses_data_already_calibrated_and_flags_nan_samples(
    hera, tmp_path, capsys
) -> None:
    solution = tmp_path / "cal"
    argv = ["calibrate", str(hera), "--out", str(solution), "--products", "calh5", "--nside", "32"]
    assert main(argv) == 0
    data = tmp_path / HH
    data.write_bytes(hera.read_bytes())
    with h5py.File(data, "r+") as h5:
        vis = h5["Data/visdata"][()]
        vis[:, 100:110] = np.nan
        h5["Data/visdata"][...] = vis
    once = tmp_path / "once.uvh5"
    cal = str(solution / "solution.calh5")
    assert main(["apply", cal, str(data), "--antennas", "23", "--out", str(once)]) == 0
    with h5py.File(once, "r") as h5:
        auto = h5["Header/ant_1_array"][()] == h5["Header/ant_2_array"][()]
        assert h5["Data/flags"][()][auto][:, 100:110].all()
        assert np.isfinite(h5["Data/visdata"][()]).all()
    twice = ["apply", cal, str(once), "--antennas", "23", "--out", str(tmp_path / "twice.uvh5")]
    assert "already calibrated" in _error(capsys, twice)


def test_a_bad_database_url_or_data_roots_setting_is_a_message(monkeypatch, capsys) -> None:
    from autocal.service.settings import get_settings

    monkeypatch.setenv("AUTOCAL_DATABASE_URL", "garbage://x")
    get_settings.cache_clear()
    try:
        assert "database URL is not usable" in _error(capsys, ["nightly", "--night", "2458043"])
        monkeypatch.delenv("AUTOCAL_DATABASE_URL")
        monkeypatch.setenv("AUTOCAL_DATA_ROOTS", "[/x")
        get_settings.cache_clear()
        assert "AUTOCAL_DATA_ROOTS" in _error(capsys, ["nightly", "--night", "2458043"])
    finally:
        get_settings.cache_clear()


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_run_interrupted_while_writing_says_so_and_leaves_no_staging_folder(
    hera, tmp_path, monkeypatch, capsys, signum: int
) -> None:
    """Ctrl-C printed a traceback; SIGTERM while writing left ``.staging-*`` behind.

    The signal is sent from inside the product writer, when the staging folder exists,
    to this process running the command as ``autocal`` does (``main()`` with the command
    line in ``sys.argv``).
    """
    import autocal.pipeline.products as products

    real = products.write_solution_products

    def write_then_signal(solution, staging, *args, **kwargs):
        assert Path(staging).is_dir()
        os.kill(os.getpid(), signum)
        time.sleep(5)  # the handler raises here
        return real(solution, staging, *args, **kwargs)

    monkeypatch.setattr(products, "write_solution_products", write_then_signal)
    out = tmp_path / "out"
    argv = ["autocal", "calibrate", str(hera), "--out", str(out), "--nside", "32"]
    monkeypatch.setattr(sys, "argv", argv)
    before = signal.getsignal(signal.SIGTERM)
    # a pytest-xdist worker ignores SIGINT: the command's process has Python's default
    interrupt = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        assert main() == EXIT_INTERRUPTED
    finally:
        signal.signal(signal.SIGINT, interrupt)
    err = capsys.readouterr().err
    assert "interrupted" in err and "Traceback" not in err
    assert out.is_dir() and not list(out.iterdir())  # no staging folder, no product
    assert signal.getsignal(signal.SIGTERM) is before  # put back


def test_main_called_by_a_program_keeps_its_sigterm(hera, tmp_path) -> None:
    """A program calling ``main([...])`` must still be ended by SIGTERM (a batch system's
    time limit), not get 130 back and go on."""
    code = (
        "import os, signal, sys, time\n"
        "import autocal.pipeline.products as p\n"
        "def w(*a, **k):\n"
        "    os.kill(os.getpid(), signal.SIGTERM); time.sleep(5)\n"
        "p.write_solution_products = w\n"
        "from autocal.cli.main import main\n"
        f"main(['calibrate', {str(hera)!r}, '--out', {str(tmp_path / 'o')!r}, '--nside', '32'])\n"
        "print('went on')\n"
    )
    env = {**os.environ, "AUTOCAL_CACHE_DIR": "off", "MPLBACKEND": "Agg"}
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, timeout=300)
    assert done.returncode == -signal.SIGTERM and b"went on" not in done.stdout


def test_a_killed_runs_staging_folder_is_removed_by_the_next_run(tmp_path) -> None:
    from autocal.core.files import _host, make_staging

    out = tmp_path / "out"
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)  # fmt: skip
    orphan = out / f".staging-{int(dead.stdout)}-1@{_host()}"
    orphan.mkdir(parents=True)
    (orphan / "solution.h5").write_bytes(b"half")
    elsewhere = out / f".staging-{int(dead.stdout)}-1@another-machine"  # not checkable here
    elsewhere.mkdir()
    alive = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        running = out / f".staging-{alive.pid}-1@{_host()}"  # a live run's, kept
        running.mkdir()
        mine = make_staging(out)
        assert not orphan.exists() and mine.is_dir()
        assert elsewhere.is_dir() and running.is_dir()
        second = make_staging(out)  # this process's own stays
        assert mine.is_dir() and second.is_dir()
    finally:
        alive.kill()
        alive.wait()


def test_paper_seed_and_diagnose_lst_range_messages(hera, tmp_path, capsys) -> None:
    out = tmp_path / "paper"
    assert "integer >= 0" in _error(capsys, ["paper", "--seed=-1", "--quick", "--out", str(out)])
    assert not out.exists()  # refused before the folder was made
    err = _error(capsys, ["diagnose", str(hera), "--lst-range", "10:11", "--out", str(out)])
    assert "the data cover LST" in err and "PosixPath" not in err


def test_a_beam_folder_and_the_figures_of_an_all_flagged_solution(hera, tmp_path, capsys) -> None:
    import warnings

    table = str(tmp_path / "t.h5")
    err = _error(capsys, ["tsky", "--beam", str(tmp_path), "--nside", "8", "--out", table])
    assert "is a folder" in err and "named beam" in err
    zero = tmp_path / HH
    zero.write_bytes(hera.read_bytes())
    with h5py.File(zero, "r+") as h5:
        h5["Data/visdata"][...] = 0
    with warnings.catch_warnings():  # matplotlib's "No artists with labels" for the legend
        warnings.simplefilter("error", UserWarning)
        status = main(["calibrate", str(zero), "--out", str(tmp_path / "o"), "--nside", "32"])
    assert status == 3 and "no usable data" in capsys.readouterr().err


def test_compare_refuses_a_beam_a_relative_comparison_does_not_use(tmp_path, capsys) -> None:
    """The audit: ``compare --mode relative --beam nope.fits`` ignored the beam silently."""
    out = str(tmp_path / "cmp")
    argv = ["compare", "solution.h5", "ref.calfits", "--mode", "relative", "--out", out]
    err = _error(capsys, [*argv, "--beam", "nope.fits"])
    assert "--beam" in err and "--mode absolute" in err
    err = _error(capsys, [*argv, "--nside", "64"])
    assert "--nside" in err and "--mode absolute" in err


def test_nightly_exits_2_when_an_observation_is_refused(tmp_path, monkeypatch, capsys) -> None:
    """A timer must notice an observation the submission refused (a truncated file)."""
    from autocal.service.settings import get_settings
    from tests.service.tiny_uvh5 import write_tiny_uvh5

    data = tmp_path / "data"
    write_tiny_uvh5(data / "zen.2458117.30000.HH.uvh5")  # one observation of two files,
    write_tiny_uvh5(data / "zen.2458117.30745.HH.uvh5")  # then one much later
    bad = write_tiny_uvh5(data / "zen.2458117.60000.HH.uvh5")
    bad.write_bytes(bad.read_bytes()[:5000])
    monkeypatch.setenv("AUTOCAL_STATE_DIR", str(tmp_path / "state"))
    monkeypatch.setenv("AUTOCAL_DATA_ROOTS", str(data))
    monkeypatch.delenv("AUTOCAL_DATABASE_URL", raising=False)
    get_settings.cache_clear()
    try:
        argv = ["nightly", "--night", "2458117", "--folder", str(data), "--beam", "dipole"]
        assert main(argv) == EXIT_USER_ERROR
    finally:
        get_settings.cache_clear()
    out = capsys.readouterr().out
    assert "1 submitted" in out and "1 refused" in out and "zen.2458117.60000" in out
