"""Sphinx configuration of shadowlab's docs site (``make docs``; the tests build it with -W)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

project = "shadowlab"
author = "the shadowlab developers"
copyright = "2026, the shadowlab developers"
extensions = ["myst_parser", "sphinx.ext.autodoc", "sphinx.ext.napoleon"]
source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
root_doc = "index"
# hand-written family notes are included by the generated technique pages, not pages themselves
exclude_patterns = ["_build", "families/*", "bench/about.md"]
myst_heading_anchors = 4
myst_enable_extensions = ["dollarmath"]
autodoc_member_order = "bysource"
autodoc_typehints = "none"
html_theme = "alabaster"
html_static_path = []
suppress_warnings = ["myst.header"]
