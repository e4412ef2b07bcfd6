"""Temporary re-exports for the layout merge."""

from autocal.diagnosis.errors import DiagnoseError  # noqa: F401
from autocal.diagnosis.report import write_diagnosis  # noqa: F401
