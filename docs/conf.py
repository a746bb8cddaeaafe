"""Sphinx configuration: Markdown pages (MyST) and an API reference from the docstrings.

Builds offline (no intersphinx) and warning-free: `sphinx-build -W --keep-going -b html docs OUT`.
"""

import os
import sys

sys.path.insert(0, os.path.abspath(".."))

import simloader  # noqa: E402

project = "simloader"
author = "simloader contributors"
copyright = "2026, simloader contributors"
release = simloader.__version__
version = release

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
]
source_suffix = {".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store"]
myst_enable_extensions = ["colon_fence"]
myst_heading_anchors = 3

# The API reference documents what the docstrings say; MuJoCo, JAX and Warp need not be
# importable for it (the docs build on a plain CPU machine).
autodoc_mock_imports = ["jax", "jaxlib", "mujoco.mjx", "warp", "mujoco_warp"]
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_default_options = {"members": True, "undoc-members": False, "show-inheritance": False}
napoleon_google_docstring = True
napoleon_numpy_docstring = True
napoleon_use_ivar = True  # "Attributes:" sections as fields, not second descriptions of the members

# Docstrings written for readers of the source are not all valid reStructuredText; their
# formatting slips are not worth failing the build over, everything else is.
suppress_warnings = ["docutils"]

try:
    import furo  # noqa: F401

    html_theme = "furo"
except ImportError:
    html_theme = "alabaster"
html_title = f"simloader {release}"
html_static_path = ["_static"]
