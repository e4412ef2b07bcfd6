"""Temporary re-exports for the layout merge."""

from autocal.compare.comparison import compare  # noqa: F401
from autocal.compare.drift import auto_trend  # noqa: F401
from autocal.compare.errors import CompareError  # noqa: F401
from autocal.compare.report import OUTPUT_NAMES, write_comparison  # noqa: F401
