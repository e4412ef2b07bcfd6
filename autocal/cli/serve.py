"""``autocal serve``: run the REST job service (uvicorn with the app factory)."""

from __future__ import annotations

import argparse

#: Import string of the FastAPI application factory.
APP_FACTORY = "autocal.service.app:create_app"


def add(sub: argparse._SubParsersAction) -> None:
    """Register the command."""
    p = sub.add_parser(
        "serve",
        help="run the REST job service (jobs are run by `autocal worker` processes)",
        description="Run the autocal REST API with uvicorn. Settings come from AUTOCAL_* "
        "environment variables (AUTOCAL_DATABASE_URL, AUTOCAL_STATE_DIR, AUTOCAL_DATA_ROOTS, "
        "AUTOCAL_API_TOKENS, ...), checked before it starts (a token shorter than "
        "AUTOCAL_MIN_TOKEN_LENGTH is refused). The API only queues jobs: start one or more "
        "`autocal worker` processes against the same database to run them.",
    )
    p.add_argument("--host", default="127.0.0.1", help="bind address (127.0.0.1)")
    p.add_argument("--port", type=int, default=8000, help="port (8000)")
    p.add_argument(
        "--workers", type=int, default=1, help="uvicorn HTTP worker processes (1); not job workers"
    )
    p.add_argument(
        "--log-level",
        default="info",
        choices=["critical", "error", "warning", "info", "debug"],
        help="uvicorn log level (info)",
    )
    p.add_argument("--root-path", default="", help="URL prefix when behind a reverse proxy")
    p.set_defaults(func=run)


def check_settings() -> None:
    """Read the service settings and check the tokens, before uvicorn starts.

    Raises
    ------
    pydantic.ValidationError
        A malformed ``AUTOCAL_*`` value (the CLI prints one line naming it).
    autocal.service.tokens.TokenConfigError
        Unusable tokens: too short, malformed, repeated, or read auth without a token.
    """
    from autocal.service.settings import Settings
    from autocal.service.tokens import checked_tokens

    checked_tokens(Settings())


def run(args: argparse.Namespace) -> int:
    """Run the command."""
    import uvicorn

    from autocal.cli.args import CliError

    if not 0 < args.port < 65536:
        raise CliError(f"--port {args.port}: give a TCP port between 1 and 65535")
    if args.workers < 1:
        raise CliError(f"--workers {args.workers}: give at least 1")
    check_settings()
    uvicorn.run(
        APP_FACTORY,
        factory=True,
        host=args.host,
        port=args.port,
        workers=args.workers,
        log_level=args.log_level,
        root_path=args.root_path,
        proxy_headers=True,
    )
    return 0
