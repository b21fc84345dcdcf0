"""Sphinx configuration of the sb3-cql documentation: ``sphinx-build -W docs docs/_build/html``."""

import sb3_cql

project = "sb3-cql"
author = "sb3-cql contributors"
copyright = "2026, sb3-cql contributors"
version = release = sb3_cql.__version__

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.viewcode",
]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build"]
myst_enable_extensions = ["colon_fence"]
myst_heading_anchors = 3

# The API reference follows the code's own signatures; keyword documentation is the docstrings' ``:param:`` lines.
autodoc_member_order = "bysource"
autodoc_typehints = "signature"
autodoc_preserve_defaults = True

html_theme = "sphinx_rtd_theme"  # the theme of Stable-Baselines3's and RL-Zoo3's documentation
html_title = f"sb3-cql {release}"
html_show_sourcelink = False
