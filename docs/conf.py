"""Sphinx configuration: Markdown pages (MyST) and an API reference from the docstrings.

Builds offline (no intersphinx) and warning-free, cross-references checked:
`python3 -m sphinx -W -n --keep-going -b html docs OUT`.
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
    "sphinx.ext.autosummary",  # one page per public object (api.md's tables)
    "sphinx.ext.napoleon",
    "sphinx.ext.viewcode",  # "[source]" links to highlighted source pages, built offline
    "sphinx_copybutton",
]
source_suffix = {".md": "markdown", ".rst": "restructuredtext"}  # .rst: autosummary's pages
root_doc = "index"
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store", "_templates"]
templates_path = ["_templates"]
autosummary_generate = True  # into docs/generated/, at every build (git-ignored)


def _results_pages() -> None:
    """A page of the site for every results file a page links (`results/NAME.md`): the
    file itself, included, its plots beside it, so that the figures the docs cite read as
    pages instead of downloading raw Markdown. Made at every build into docs/results/
    (git-ignored), listed by speed.md's hidden toctree."""
    import pathlib
    import re
    docs = pathlib.Path(__file__).parent
    results = docs.parent / "benchmarks" / "results"
    out = docs / "results"
    if out.is_symlink():
        raise RuntimeError(f"{out} is a link: the build makes its pages there, in the docs")
    out.mkdir(exist_ok=True)
    cited = {m for page in docs.glob("*.md")
             for m in re.findall(r"\]\(results/([^)#]+\.md)\)", page.read_text())}

    def made(name: str) -> str:  # a page as the build makes it, of results file `name`
        return f"```{{include}} ../../benchmarks/results/{name}\n:relative-images:\n```\n"

    for name in sorted(cited):
        if not (results / name).is_file():
            continue  # the build's link check names it
        page = out / name
        if page.is_symlink():
            raise RuntimeError(f"{page} is a link: the build makes that page itself")
        if not page.is_file() or page.read_text() != made(name):
            page.write_text(made(name))
    for page in out.glob("*.md"):  # a page the build made that is no longer cited; no other
        if page.name not in cited and not page.is_symlink() and page.read_text() == made(
                page.name):
            page.unlink()


_results_pages()
myst_enable_extensions = ["colon_fence"]
myst_heading_anchors = 3

# `name` in the docstrings (reStructuredText) is code, as it is in the Markdown pages, not
# italic "interpreted text".
default_role = "code"

# The API reference documents what the docstrings say; MuJoCo, JAX and Warp need not be
# importable for it (the docs build on a plain CPU machine).
autodoc_mock_imports = ["jax", "jaxlib", "mujoco.mjx", "warp", "mujoco_warp"]
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_preserve_defaults = True  # control_spec=mujoco.mjtState.mjSTATE_CTRL, not 64
autodoc_default_options = {"members": True, "undoc-members": False, "show-inheritance": False}
napoleon_google_docstring = True
napoleon_numpy_docstring = True
napoleon_use_ivar = True  # "Attributes:" sections as fields, not second descriptions of the members

# Every cross-reference must resolve (`-n`), except those that cannot:
nitpicky = True
nitpick_ignore_regex = [
    # Types of other libraries in the signatures: the build is offline, without intersphinx.
    (r"py:.*", r"(numpy|torch|mujoco|jax|collections\.abc|typing|os|pathlib|abc|tensordict"
               r"|torchrl)(\..*)?"),
]
nitpick_ignore = [
    # Internal types in public signatures; the API reference does not document them.
    ("py:class", "simloader.sharding.Shard"),  # SimDataset.make_backend
    ("py:class", "simloader.backends.base.Backend"),  # SimDataset.make_backend, .stream
    ("py:class", "simloader.store.shards.StoredArray"),  # StoredDataset.arrays
    ("py:class", "simloader.controls._Given"),  # base class of controls.Constant, .FromArray
]

try:
    import furo  # noqa: F401

    html_theme = "furo"
except ImportError:
    html_theme = "alabaster"
html_title = f"simloader {release}"
html_static_path = ["_static"]
html_css_files = ["custom.css"]
html_logo = "_static/logo.svg"
html_favicon = "_static/favicon.svg"
# No repository link: the project's URL is not written anywhere in the repository yet; the
# API reference links each name to its source ("[source]", sphinx.ext.viewcode).
