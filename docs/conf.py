"""Sphinx configuration of the docs site (`make docs`; why these tools: tooling.md)."""

import dataclasses
import re
import sys
from importlib import metadata
from pathlib import Path

import jupytext

DOCS = Path(__file__).parent
ROOT = DOCS.parent
sys.path.insert(0, str(ROOT))  # autodoc imports the package from this checkout

project = "fenics_elasto"
author = "the fenics_elasto authors"
copyright = "2026, " + author
release = version = metadata.version("fenics_elasto")

# No napoleon: the docstrings are prose without Google/NumPy sections, and it read a property's
# "Stopped by Ctrl-C: ..." as a type.
extensions = ["myst_parser", "sphinx.ext.autodoc", "sphinx.ext.mathjax"]
myst_enable_extensions = ["dollarmath", "amsmath"]
myst_heading_anchors = 3
highlight_language = "none"  # a block without a language (commands, output) stays plain text
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store"]
# The package re-exports names from its modules (fe.Scene is fenics_elasto.model.scene.Scene),
# so a type hint may find two targets for one class; either is right.
suppress_warnings = ["ref.python"]

# Members in source order; type hints in the signature, names without their modules.
autodoc_member_order = "bysource"
autodoc_typehints = "signature"
autodoc_typehints_format = "short"
autodoc_preserve_defaults = True

html_theme = "furo"
html_title = f"fenics_elasto {release}"
html_static_path = ["_static"]
html_css_files = ["tables.css"]

# The demos are jupytext percent scripts in demos/ (DOLFINx's way): each becomes a
# Markdown page in docs/demos/ before Sphinx reads the sources. The pages are generated
# (not in git); links that the script writes relative to demos/ point into docs/ here.
LITERATE_DEMOS = ["letter_a_poisson.py", "prostate_elastography.py", "real_prostate.py"]


def write_demo_pages() -> None:
    out = DOCS / "demos"
    out.mkdir(exist_ok=True)
    for page in out.glob("*.md"):  # a demo taken off the list leaves no page behind
        if page.with_suffix(".py").name not in LITERATE_DEMOS:
            page.unlink()
    for name in LITERATE_DEMOS:
        notebook = jupytext.read(ROOT / "demos" / name, fmt="py:percent")
        notebook.metadata = {}
        text = jupytext.writes(notebook, fmt="md")
        text = re.sub(r"\]\(\.\./docs/", "](../", text)
        footer = f"\n\n---\n\nThe script: {{download}}`demos/{name} <../../demos/{name}>`; run it with `python demos/{name}`.\n"
        page = out / name.replace(".py", ".md")
        if not page.exists() or page.read_text() != text + footer:
            page.write_text(text + footer)


write_demo_pages()


def _plain_bars(app, what, name, obj, options, lines: list[str]) -> None:
    """The docstrings write norms as |x|, which reST reads as a substitution: keep the bars."""
    lines[:] = [line.replace("|", r"\|") for line in lines]


def _short_dataclass(app, what, name, obj, options, signature, return_annotation):
    """A dataclass with many fields is made by a function (load_scene, Scene.from_mesh), not by
    its field list: leave that list out of the heading."""
    if what == "class" and dataclasses.is_dataclass(obj) and len(dataclasses.fields(obj)) > 6:
        return "", None
    return None


def setup(app):
    app.connect("autodoc-process-docstring", _plain_bars)
    app.connect("autodoc-process-signature", _short_dataclass)
