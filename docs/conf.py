"""Sphinx configuration: the API reference of nanofrictor (``identify`` and ``design``).

Build: ``python -m sphinx -W -b html docs docs/_build/html`` (CI builds it with warnings as
errors).
"""

import os
import sys

sys.path.insert(0, os.path.abspath(".."))

from identify import __version__  # noqa: E402

project = "nanofrictor"
author = "the nanofrictor developers"
copyright = "2026, the nanofrictor developers"
version = release = __version__

extensions = ["sphinx.ext.autodoc", "sphinx.ext.autosummary", "numpydoc", "sphinx.ext.mathjax"]
exclude_patterns = ["_build", "*.md", "*.json", "*.png"]
autodoc_typehints = "none"  # numpydoc sections carry the types and units
autodoc_member_order = "bysource"
numpydoc_show_class_members = False
numpydoc_validation_checks: set = set()
html_theme = "alabaster"
