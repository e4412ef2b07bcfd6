"""Service settings, read from the environment (``AUTOCAL_*``) through pydantic-settings.

==================================  ==========================================================
variable                            meaning (default)
==================================  ==========================================================
``AUTOCAL_DATABASE_URL``            SQLAlchemy URL of the job store
                                    (``sqlite:///<state dir>/jobs.sqlite``); PostgreSQL for
                                    many workers: ``postgresql+psycopg://user:pw@host/db``
``AUTOCAL_STATE_DIR``               where the SQLite store, uploads and products live
                                    (``~/.local/share/autocal``)
``AUTOCAL_DATA_ROOTS``              input paths must lie under one of these folders
                                    (JSON list or ``:``-separated; default: the data folder)
``AUTOCAL_API_TOKEN``               token required by write endpoints (``Authorization:
                                    Bearer <token>``), named ``default``; unset and no
                                    other token = writes refused
``AUTOCAL_API_TOKENS``              named tokens, ``name=token`` separated by commas
``AUTOCAL_API_TOKENS_FILE``         a file of ``name=token`` lines (``#`` comments)
``AUTOCAL_MIN_TOKEN_LENGTH``        shortest accepted token; shorter refuses to start (32)
``AUTOCAL_READ_AUTH``               1: read endpoints need a token too (0)
``AUTOCAL_AUTH_FAILURES``           failed authentications per client within the window
                                    before it is answered 429 (10)
``AUTOCAL_AUTH_WINDOW_S``           that window, in seconds (60)
``AUTOCAL_MAX_UPLOAD_BYTES``        largest accepted upload (2 GiB)
``AUTOCAL_HEARTBEAT_S``             worker heartbeat interval (10)
``AUTOCAL_STALE_AFTER_S``           a running job without heartbeat for this long is
                                    re-queued or failed (60)
``AUTOCAL_MAX_ATTEMPTS``            attempts before a crashed job is failed (3); jobs handed
                                    back by a worker shutting down (SIGTERM) are not counted
``AUTOCAL_JOB_TIMEOUT_S``           an attempt running longer than this is failed with that
                                    reason, even if it still sends heartbeats (21600 = 6 h;
                                    0 = no limit)
``AUTOCAL_JANITOR_AFTER_S``         the worker's janitor removes orphaned ``.staging-*`` and
                                    ``.part`` files older than this (21600 = 6 h)
``AUTOCAL_JANITOR_INTERVAL_S``      seconds between two janitor runs of a worker (3600; one
                                    also runs at start-up)
``AUTOCAL_FINGERPRINT_FULL_BYTES``  inputs up to this size are hashed whole at submission;
                                    larger ones by size, time and sampled blocks (64 MiB)
``AUTOCAL_DASK_SCHEDULER``          calibrations map their per-file sums over Dask: a
                                    scheduler address (tcp://host:8786), "local" for a
                                    LocalCluster, "" (default) to run in the worker
``AUTOCAL_READERS``                 processes that read a calibration's UVH5 files when
                                    Dask is not used: 0 (default) one per core for nights
                                    of at least two files and 256 MiB, 1 in the worker
==================================  ==========================================================
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Annotated

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict


def _default_state_dir() -> Path:
    return Path.home() / ".local" / "share" / "autocal"


class Settings(BaseSettings):
    """Settings of the API, the workers and the nightly runner."""

    model_config = SettingsConfigDict(env_prefix="AUTOCAL_", extra="ignore")

    state_dir: Path = Field(default_factory=_default_state_dir)
    database_url: str = ""
    data_roots: Annotated[list[Path], NoDecode] = Field(default_factory=list)
    api_token: str = ""
    api_tokens: str = ""
    api_tokens_file: Path | None = None
    min_token_length: int = Field(32, ge=1)
    read_auth: bool = False
    auth_failures: int = Field(10, ge=1)
    auth_window_s: float = Field(60.0, gt=0)
    max_upload_bytes: int = Field(2 * 1024**3, gt=0)
    max_body_bytes: int = Field(4 * 1024**2, gt=0)
    heartbeat_s: float = Field(10.0, gt=0)
    stale_after_s: float = Field(60.0, gt=0)
    max_attempts: int = Field(3, ge=1)
    job_timeout_s: float = Field(6 * 3600.0, ge=0)
    janitor_after_s: float = Field(6 * 3600.0, gt=0)
    janitor_interval_s: float = Field(3600.0, gt=0)
    fingerprint_full_bytes: int = Field(64 * 1024**2, ge=0)
    dask_scheduler: str = ""
    readers: int = Field(0, ge=0)

    @field_validator("data_roots", mode="before")
    @classmethod
    def _split_roots(cls, value: object) -> object:
        if isinstance(value, str):
            text = value.strip()
            if text.startswith("["):
                import json

                return json.loads(text)
            return [p for p in text.split(":") if p.strip()]
        return value

    def resolved_database_url(self) -> str:
        """Return the store URL (SQLite in the state folder unless configured)."""
        if self.database_url:
            return self.database_url
        self.state_dir.mkdir(parents=True, exist_ok=True)
        return f"sqlite:///{self.state_dir / 'jobs.sqlite'}"

    def resolved_data_roots(self) -> list[Path]:
        """Return the allowed input folders (resolved); the data folder when none is configured."""
        roots = list(self.data_roots)
        if not roots:
            from autocal.io.datasets import data_dir

            found = data_dir()
            roots = [found] if found is not None else []
        return [Path(r).expanduser().resolve() for r in roots]

    @property
    def products_dir(self) -> Path:
        """Where job products are written."""
        return self.state_dir / "jobs"

    @property
    def uploads_dir(self) -> Path:
        """Where uploaded inputs are kept (always an allowed data root)."""
        return self.state_dir / "uploads"


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """Return the process-wide settings (cached; tests clear the cache with ``cache_clear``)."""
    return Settings()
