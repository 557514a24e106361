"""Sphinx configuration of servobench's documentation.

Build it from the checkout (offline; warnings are errors)::

    pip install -e ".[docs]"
    sphinx-build -W -b html docs docs/_build/html

The pages are MyST Markdown (``*.md``); the API reference (``api.rst``) is
generated from the docstrings of the names in ``servobench.__all__``; the
figures are drawn during the build from real runs on ``sim://`` by the local
extension ``_ext/sim_figures.py`` (directive ``sim-figure``).
tests/test_docs.py builds the site and runs every code example in it.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import servobench

DOCS = Path(__file__).resolve().parent
sys.path.insert(0, str(DOCS / "_ext"))
os.environ.setdefault("MPLBACKEND", "Agg")  # the figures are drawn without a display

project = "servobench"
author = "the servobench authors"
copyright = "the servobench authors"  # noqa: A001 -- Sphinx's name
release = version = servobench.__version__

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sim_figures",
    "cli_help",
]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "_ext", ".gitignore"]
# Offline from a fresh clone: no intersphinx, no remote images, nothing fetched.

myst_enable_extensions = ["colon_fence", "deflist"]
myst_heading_anchors = 3  # [text](page.md#a-heading) links to headings

# numpydoc-style docstrings (Parameters / Returns / Raises / Attributes)
napoleon_google_docstring = False
napoleon_numpy_docstring = True
napoleon_use_ivar = True  # a class's Attributes as fields, not as duplicate object entries
napoleon_use_param = False  # "a, b : float" stays one entry, as written
napoleon_use_rtype = False
autodoc_member_order = "bysource"
autodoc_typehints = "none"  # the docstrings state each type, with its unit
# results are made by servobench, not by their users: no constructor signatures
autodoc_class_signature = "separated"
autodoc_default_options = {"exclude-members": "__init__, __new__"}

html_theme = "furo"
html_title = f"servobench {release}"
html_static_path: list[str] = []
html_show_sourcelink = False
pygments_style = "sphinx"
