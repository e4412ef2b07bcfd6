"""Temporary re-exports for the layout merge."""

from autocal.tsky.compute import compute_tsky  # noqa: F401
from autocal.tsky.result import TskyError, TskyResult  # noqa: F401
from autocal.tsky.ringfft import tsky_harmonics  # noqa: F401
