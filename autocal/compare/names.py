"""The comparison's product file names (a module of its own: cheap to import)."""

from __future__ import annotations

#: Product kind -> file name of what :func:`autocal.compare.report.write_comparison` writes.
OUTPUT_NAMES = {"json": "compare.json", "png": "compare.png", "h5": "compare.h5"}
