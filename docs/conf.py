"""Sphinx configuration of the autocal documentation (``make docs``).

The pages are Markdown (MyST); the API reference is generated from the docstrings (numpydoc)
by autosummary over whatever modules the packages hold at build time. Before the build reads
any page, :func:`generate` writes what is derived from the code into folders that are not
committed (``.gitignore``):

- ``api/``: the API reference's index and, through autosummary, one page per module;
- ``_generated/cli.md``: every command's ``--help`` from :func:`autocal.cli.main.build_parser`;
- ``_generated/openapi.json`` and ``_generated/openapi.md``: the REST service's OpenAPI schema
  and its operations, from :func:`autocal.service.app.create_app` (offline, a throw-away
  SQLite store);
- ``_generated/benchmarks/``: ``benchmarks/README.md`` and its result pages, copied so that
  their relative links resolve.
"""

from __future__ import annotations

import argparse
import json
import os
import pkgutil
import shutil
import tempfile
from pathlib import Path

from pygments.lexers.special import TextLexer
from sphinx.application import Sphinx

import autocal

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent

project = "autocal"
author = "the autocal developers"
copyright = "the autocal developers"  # noqa: A001  (Sphinx's name)
release = autocal.__version__
version = release

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.viewcode",
    "numpydoc",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
templates_path = ["_templates"]
# docs/results and docs/paper are written by the result scripts: their Markdown is included
# into the pages (``{include}``), their figures shown; they are not pages of their own.
exclude_patterns = ["_build", "results/**", "paper/**", "_generated/*.md"]

# MyST: Markdown pages with anchors on headings (``page.md#a-heading``).
myst_heading_anchors = 4
myst_enable_extensions = ["colon_fence", "deflist"]

# API reference: autodoc documents each object once, in the module that defines it (names a
# module re-exports are skipped), numpydoc renders the docstrings.
autosummary_generate = ["api/index.rst"]
autosummary_generate_overwrite = True
autosummary_imported_members = False
autodoc_default_options = {
    "members": True,
    "show-inheritance": True,
    "ignore-module-all": True,
}
autodoc_member_order = "bysource"
autodoc_typehints = "none"
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_validation_checks: set[str] = set()

html_theme = "furo"
html_title = f"autocal {release}"
html_static_path = ["_static"]
html_css_files = ["autocal.css"]

#: Top-level packages installed from folders beside autocal/ (pyproject's package-dir).
EXTRA_PACKAGES = ("autocal.io", "autocal.service")


def _write(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` unless it already holds exactly that."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if not path.exists() or path.read_text(encoding="utf-8") != text:
        path.write_text(text, encoding="utf-8")


def _top_level_modules() -> list[str]:
    """Return autocal's public modules and packages, ``autocal.io`` and ``autocal.service``."""
    names = [
        f"autocal.{info.name}"
        for info in pkgutil.iter_modules(autocal.__path__)
        if not info.name.startswith("_")
    ]
    return sorted(set(names) | set(EXTRA_PACKAGES))


def _top_level_names() -> list[tuple[str, str]]:
    """Return ``(name, defining object path)`` for the names ``import autocal`` offers."""
    rows = []
    for name in autocal.__all__:
        if name.startswith("_"):
            continue
        obj = getattr(autocal, name)
        module = getattr(obj, "__module__", None)
        rows.append((name, f"{module}.{name}" if module else f"autocal.{name}"))
    return rows


def write_api_index() -> None:
    """Write ``api/index.rst``: the top-level names and an autosummary of every module."""
    lines = [
        "API reference",
        "=============",
        "",
        "Generated from the docstrings at build time: one page per module of the packages",
        "(the stages ``core``, ``sky``, ``tsky``, ``fit``, ``pipeline``, ``compare``,",
        "``diagnosis``, ``edges``, ``simulate``, ``cli``; the file formats ``autocal.io``; the",
        "job service ``autocal.service``). Each object is documented once, in the module that",
        "defines it.",
        "",
        "``import autocal`` offers",
        "-------------------------",
        "",
        ".. list-table::",
        "   :header-rows: 1",
        "",
        "   * - name",
        "     - defined in",
    ]
    for name, target in _top_level_names():
        lines += [f"   * - ``autocal.{name}``", f"     - :py:obj:`{target}`"]
    lines += [
        "",
        "Modules",
        "-------",
        "",
        ".. autosummary::",
        "   :toctree: generated",
        "   :recursive:",
        "",
    ]
    lines += [f"   {name}" for name in _top_level_modules()]
    _write(DOCS / "api" / "index.rst", "\n".join(lines) + "\n")


def _subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """Return the sub-command parsers of ``parser`` in the order they were added."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def write_cli_reference() -> None:
    """Write ``_generated/cli.md``: ``autocal --help`` and every command's ``--help``."""
    from autocal.cli.main import build_parser

    saved = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "100"
    try:
        parser = build_parser()
        parts = [
            "### `autocal --help`",
            "",
            "```text",
            parser.format_help().rstrip(),
            "```",
        ]
        for name, sub in _subcommands(parser).items():
            parts += [
                "",
                f"### `autocal {name} --help`",
                "",
                "```text",
                sub.format_help().rstrip(),
                "```",
            ]
    finally:
        if saved is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = saved
    _write(DOCS / "_generated" / "cli.md", "\n".join(parts) + "\n")


def _first_paragraph(text: str) -> str:
    """Return the first paragraph of ``text`` on one line."""
    return " ".join(text.strip().split("\n\n")[0].split())


def write_openapi() -> None:
    """Write the service's OpenAPI schema and a Markdown table of its operations."""
    from autocal.service.app import create_app
    from autocal.service.settings import Settings
    from autocal.service.store import JobStore

    with tempfile.TemporaryDirectory() as tmp:
        settings = Settings(state_dir=tmp, api_token="docs-build-token-not-a-secret-0123456789")
        store = JobStore(f"sqlite:///{tmp}/jobs.sqlite")
        try:
            spec = create_app(settings, store).openapi()
        finally:
            store.engine.dispose()
    _write(DOCS / "_generated" / "openapi.json", json.dumps(spec, indent=2, sort_keys=True) + "\n")
    rows = ["| operation | summary |", "|---|---|"]
    for path, operations in spec["paths"].items():
        for method, op in operations.items():
            text = _first_paragraph(op.get("description") or op.get("summary") or "")
            text = text.replace("|", "\\|")
            rows.append(f"| `{method.upper()} {path}` | {text} |")
    _write(DOCS / "_generated" / "openapi.md", "\n".join(rows) + "\n")


def copy_benchmarks() -> None:
    """Copy ``benchmarks/README.md`` and ``benchmarks/results`` into ``_generated``."""
    target = DOCS / "_generated" / "benchmarks"
    _write(target / "README.md", (ROOT / "benchmarks" / "README.md").read_text("utf-8"))
    results = ROOT / "benchmarks" / "results"
    for path in sorted(results.iterdir()):
        if path.suffix == ".md":
            # Result pages are reached from the benchmarks page's links, not a toctree.
            text = "---\norphan: true\n---\n\n" + path.read_text("utf-8")
            _write(target / "results" / path.name, text)
        elif path.is_file():
            (target / "results").mkdir(parents=True, exist_ok=True)
            shutil.copyfile(path, target / "results" / path.name)


def skip_library_internals(
    app: Sphinx, what: str, name: str, obj: object, skip: bool, options: object
) -> bool | None:
    """Skip members that a library adds with its own docstring.

    pydantic's ``model_config`` and SQLAlchemy's declarative ``metadata`` and ``registry``.
    """
    module = type(obj).__module__ or ""
    if name == "model_config" and isinstance(obj, dict):
        return True
    if name in ("metadata", "registry") and module.startswith("sqlalchemy"):
        return True
    return None


def generate(app: Sphinx) -> None:
    """Write every page derived from the code (connected before autosummary runs)."""
    write_api_index()
    write_cli_reference()
    write_openapi()
    copy_benchmarks()


def setup(app: Sphinx) -> None:
    """Connect this file's hooks (Sphinx calls this after loading the configuration)."""
    # deploy/README.md (included in the service page) has a crontab block; Pygments has no
    # crontab lexer, so it is shown as plain text.
    app.add_lexer("cron", TextLexer)
    # Before autosummary's own handler (priority 500), so that api/index.rst exists for it.
    app.connect("builder-inited", generate, priority=400)
    app.connect("autodoc-skip-member", skip_library_internals)
