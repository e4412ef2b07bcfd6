"""The error a user causes by asking for a comparison that cannot be made."""

from __future__ import annotations

from autocal.errors import AutocalError


class CompareError(AutocalError):
    """The solution and the reference cannot be compared as asked."""
