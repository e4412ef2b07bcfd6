"""The ``autocal`` command line.

Commands (one module each in :mod:`autocal.cli`)
------------------------------------------------
``autocal calibrate``
    Fit G and Trxr to the autos of one observation; write calh5/calfits, HDF5, plots.
``autocal apply``
    Apply a calfits/calh5 gain solution to UVH5 data; write calibrated UVH5.
``autocal diagnose``
    Name the physical effects missing from the model, add them, show the gap shrink.
``autocal compare``
    ``|g|`` from autos against cross-correlation (abscal or redcal/omnical) gains.
``autocal tsky``
    Beam-weighted sky temperature table Tsky(nu, LST) to HDF5 (and a plot).
``autocal simulate``
    Mock auto-correlations written as a UVH5 file, with a truth side-car.
``autocal paper``
    The paper's simulation scenarios: summary table, JSON results and figures.
``autocal info``
    Version, data folder, cache folder, and which sky models and beams are available.
``autocal serve``
    The REST job service (uvicorn running the FastAPI app factory).
``autocal worker``
    One job-worker process: claims queued jobs from the store and runs them.
``autocal nightly``
    Queue one calibration job per observation of a night (JD) or a watched folder.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from collections.abc import Sequence
from typing import Any

from autocal.cli.args import CliError, parse_range
from autocal.errors import AutocalError

__all__ = [
    "EXIT_INTERRUPTED",
    "EXIT_OK",
    "EXIT_USER_ERROR",
    "CliError",
    "build_parser",
    "main",
    "parse_range",
    "user_error_message",
]

logger = logging.getLogger("autocal.cli.main")


class VersionAction(argparse.Action):
    """``--version``: print ``autocal VERSION`` and exit.

    argparse's own ``version`` action needs the text when the parser is built; looking the
    version up in the package metadata costs ~0.1 s, so it is done only when asked for.
    """

    def __init__(self, option_strings: Sequence[str], dest: str, **kwargs: Any) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        from autocal import __version__

        sys.stdout.write(f"autocal {__version__}\n")  # on standard output, as argparse's
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    """Build the argument parser."""
    from autocal.cli import (
        apply,
        calibrate,
        compare,
        diagnose,
        info,
        nightly,
        paper,
        serve,
        simulate,
        tsky,
        worker,
    )

    parser = argparse.ArgumentParser(
        prog="autocal",
        description="Calibrate radio-telescope auto-correlations against sky models.",
    )
    parser.add_argument(
        "--version", action=VersionAction, help="show the version of autocal and exit"
    )
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="more log output (-v info, -vv debug)"
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for module in (
        calibrate,
        apply,
        compare,
        diagnose,
        tsky,
        simulate,
        paper,
        info,
        serve,
        worker,
        nightly,
    ):
        module.add(sub)
    return parser


#: Exit status of a command that succeeded.
EXIT_OK = 0
#: Exit status of bad input: an :class:`~autocal.errors.AutocalError`, a file that is
#: missing or cannot be written (:class:`OSError`), or options pydantic rejects.
EXIT_USER_ERROR = 2


#: Exit status of a command stopped by Ctrl-C or SIGTERM (128 + SIGINT, as shells report).
EXIT_INTERRUPTED = 130


def _terminate_unwinds() -> Any:
    """Make SIGTERM stop a command as Ctrl-C does, running its clean-ups.

    Python's default SIGTERM ends the process at once: a run stopped while writing left its
    staging folder behind. Installed only when :func:`main` runs as the command (``autocal``,
    ``python -m autocal``); commands that handle SIGTERM themselves (``serve``, ``worker``)
    install their own handler later, which replaces this one.

    Returns
    -------
    object
        The handler replaced (:func:`main` puts it back), or ``None`` when nothing was
        changed (not the main thread, or SIGTERM already handled).
    """
    if threading.current_thread() is not threading.main_thread():
        return None
    previous = signal.getsignal(signal.SIGTERM)
    if previous is not signal.SIG_DFL:
        return None

    def interrupt(signum: int, frame: object) -> None:
        raise KeyboardInterrupt(f"signal {signum}")

    signal.signal(signal.SIGTERM, interrupt)
    return previous


def user_error_message(err: BaseException) -> str | None:
    """Return the one-line message of an error the user caused, ``None`` for anything else.

    User errors are :class:`~autocal.errors.AutocalError` (every autocal input error),
    :class:`OSError` (a missing input, an existing output) and pydantic's
    ``ValidationError`` (options out of range). Any other exception, a plain
    ``ValueError`` from numpy included, is a bug and is not reported as bad input.

    Parameters
    ----------
    err
        The exception a command raised.

    Returns
    -------
    str or None
        The message to print, or ``None`` when ``err`` is not a user error.
    """
    # A ValidationError comes from pydantic, so it is loaded when there is one (and it is
    # not imported for a usage error: reporting one loads no library).
    pydantic = sys.modules.get("pydantic")
    if pydantic is not None and isinstance(err, pydantic.ValidationError):
        from autocal.cli.args import validation_message

        return validation_message(err)
    if isinstance(err, AutocalError | OSError):
        return " ".join(str(err).split()) or type(err).__name__
    return None


def parse_arguments(
    parser: argparse.ArgumentParser, argv: Sequence[str] | None
) -> argparse.Namespace:
    """Parse the command line; an unknown option is reported with its sub-command's usage.

    argparse leaves options a sub-command does not know to the top-level parser, which
    would print the usage of ``autocal`` itself; the sub-command's parser reports them here
    (and exits with status 2), so ``autocal calibrate --site x`` shows ``calibrate``'s usage.
    """
    args, extras = parser.parse_known_args(argv)
    if extras:
        commands = next(
            a for a in parser._actions if isinstance(a, argparse._SubParsersAction)
        ).choices
        commands[args.command].error(f"unrecognized arguments: {' '.join(extras)}")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; return the exit status.

    Returns
    -------
    int
        :data:`EXIT_OK`, or :data:`EXIT_USER_ERROR` after printing a user error's message
        to standard error. Other exceptions (bugs) propagate with their traceback (the
        interpreter exits with status 1).
    """
    parser = build_parser()
    args = parse_arguments(parser, argv)
    level = [logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    # only as the command (argv from the command line): a program calling main([...]) in
    # a loop keeps Python's SIGTERM, which ends it (a batch system's time limit must)
    previous = _terminate_unwinds() if argv is None else None
    try:
        return int(args.func(args))
    except KeyboardInterrupt:
        print(
            f"autocal {args.command}: interrupted; products are published only when a run "
            "finishes, so none was left half-written (earlier ones are kept)",
            file=sys.stderr,
        )
        return EXIT_INTERRUPTED
    except Exception as err:
        message = user_error_message(err)
        if message is None:
            raise
        print(f"autocal {args.command}: error: {message}", file=sys.stderr)
        return EXIT_USER_ERROR
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
