"""The examples in the documentation's pages (``docs/**/*.rst``): every page with ``>>>`` lines
runs as a doctest, so a statement a page shows stops the build the day it stops being true."""

import doctest
import pathlib

import pytest

DOCS = pathlib.Path(__file__).resolve().parent.parent / "docs"
SKIP = ("auto_examples", "generated", "_build")
PAGES = sorted(p for p in DOCS.rglob("*.rst")
               if not any(part in SKIP for part in p.parts) and ">>>" in p.read_text())


def test_the_pages_with_examples_are_found():
    assert DOCS / "user_guide" / "limitations.rst" in PAGES
    page = str(DOCS / "user_guide" / "limitations.rst")
    assert doctest.testfile(page, module_relative=False, report=False,
                            optionflags=doctest.ELLIPSIS).attempted >= 8


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(DOCS)))
def test_a_pages_examples_run(page):
    result = doctest.testfile(str(page), module_relative=False, report=True,
                              optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples failed in {page}"
