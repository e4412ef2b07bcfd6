"""The diagnosis's input error."""

from __future__ import annotations

from autocal.errors import AutocalError


class DiagnoseError(AutocalError):
    """Invalid diagnosis input."""
