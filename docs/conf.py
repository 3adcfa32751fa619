"""Sphinx configuration of the gpmhe documentation.

Build with ``python -m sphinx -W -b html docs docs/_build/html`` after ``pip install ".[docs]"``.
The API reference comes from the installed package's numpydoc docstrings; the gallery runs every
``examples/plot_*.py`` script during the build and puts its output and figures in the pages.
"""

import os
import warnings

import gpmhe

project = "gpmhe"
author = "the gpmhe developers"
copyright = "2026, the gpmhe developers"
release = gpmhe.__version__
version = release

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
    "sphinx-mathjax-offline",  # MathJax from the package, not a CDN: pages render off-line
    "sphinx.ext.intersphinx",
    "numpydoc",
    "sphinx_gallery.gen_gallery",
]

# Offline builds: intersphinx inventories are not fetched (no links to other projects' docs).
intersphinx_mapping = {}

templates_path = []
exclude_patterns = ["_build", "README.md", "auto_examples/*.ipynb", "auto_examples/*.py.md5",
                    "auto_examples/*.zip"]
html_theme = "pydata_sphinx_theme"
html_title = f"gpmhe {release}"
html_theme_options = {"navigation_with_keys": False}
html_static_path = []

autosummary_generate = True
autodoc_default_options = {"members": True, "inherited-members": False}
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
# Every public docstring must carry these numpydoc sections (checked at build time).
numpydoc_validation_checks = {"PR01", "PR02", "PR03", "PR10", "RT02", "GL08"}

sphinx_gallery_conf = {
    "examples_dirs": os.path.join("..", "examples"),
    "gallery_dirs": "auto_examples",
    "filename_pattern": r"/plot_",
    "ignore_pattern": r"__init__\.py",
    "download_all_examples": False,
    "remove_config_comments": True,
    "within_subsection_order": "FileNameSortKey",
    "abort_on_example_error": True,
    "matplotlib_animations": False,
    # No computation-times pages: they load a table script from a CDN (the site must work
    # off-line); each example page states its own run time.
    "write_computation_times": False,
}

# matplotlib without a display
os.environ.setdefault("MPLBACKEND", "Agg")
warnings.filterwarnings("ignore", category=UserWarning, message="Matplotlib is currently using agg")
