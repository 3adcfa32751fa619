"""Every ``pip install`` the documentation, the examples and the package's messages show works as
written: gpmhe is on no package index, so a line that installs it by name (``gpmhe[casadi]``) must
say where the wheels are (``--find-links``); every extra a line names exists in pyproject.toml;
and the extras table of the getting-started page lists exactly pyproject.toml's extras."""

import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
SKIP = ("auto_examples", "generated", "_build", "__pycache__")
FILES = sorted(
    p for pattern in ("docs/**/*.rst", "examples/**/*", "python/gpmhe/**/*.py", "benches/**/*",
                      "scripts/*", "README.md")
    for p in ROOT.glob(pattern)
    if p.is_file() and p.suffix in (".rst", ".py", ".md", ".sh", "")
    and not any(part in SKIP for part in p.relative_to(ROOT).parts)
)
# A command ends where the text around it goes on: at the end of an inline literal, a shell
# operator, a comment, a closing parenthesis or the next command.
COMMAND = re.compile(r"pip install\b(.*?)(?=``|`|&&|;|\||#|\)|pip install\b|$)")
GPMHE_BY_NAME = re.compile(r"gpmhe(\[[^\]]*\])?([<>=!~].*)?")
EXTRAS = re.compile(r"\[([\w,\s-]+)\]")


def pyproject_extras():
    text = (ROOT / "pyproject.toml").read_text()
    section = re.search(r"^\[project\.optional-dependencies\]\n(.*?)(?=^\[)", text, re.S | re.M)
    return set(re.findall(r"^([\w-]+)\s*=", section.group(1), re.M))


def unclosed_literal(line):
    """Whether ``line`` opens an inline literal (``rst`` or `markdown`) that it does not close."""
    line = line.replace("```", "")  # a markdown code fence
    return line.count("``") % 2 == 1 or line.replace("``", "").count("`") % 2 == 1


def logical_lines(text):
    """The lines of ``text``, with a shell line continued by a backslash, and an inline literal
    wrapped onto the next line, joined to the next."""
    lines = text.replace("\\\n", " ").splitlines()
    while lines:
        line = lines.pop(0)
        while unclosed_literal(line) and lines:
            line += " " + lines.pop(0).strip()
        yield line.strip()


def install_commands(text):
    """The arguments of every ``pip install`` in ``text``."""
    for line in logical_lines(text):
        for match in COMMAND.finditer(line):
            yield line, match.group(1).replace('\\"', '"').split()


def gpmhe_by_name(args):
    """The arguments that name gpmhe as a package to find on an index."""
    return [a for a in args if GPMHE_BY_NAME.fullmatch(a.strip("'\""))]


def test_files_and_commands_are_found():
    names = {str(p.relative_to(ROOT)) for p in FILES}
    assert {"README.md", "docs/getting_started.rst", "python/gpmhe/models/casadi.py",
            "examples/README.rst", "scripts/build_wheel.sh"} <= names
    lines = [line for p in FILES for line, _ in install_commands(p.read_text())]
    assert len(lines) >= 15
    assert pyproject_extras() >= {"casadi", "distributed", "plot", "test", "theory"}


@pytest.mark.parametrize("line, verdict", [
    ('pip install "gpmhe[casadi]"', "by name"),
    ("needs ``pip install 'gpmhe[plot]'``)", "by name"),
    ('"(or pip install \\"gpmhe[theory]\\")"', "by name"),
    ("pip install gpmhe==0.1.0", "by name"),
    ('pip install ".[casadi]" && python -m gpmhe demo', "fine"),
    ('pip install --no-index --find-links wheelhouse "gpmhe[casadi]"', "fine"),
    ("pip install casadi (or, in a clone of gpmhe: pip install .)", "fine"),
    ("needed: ``pip install\n'gpmhe[plot]'`` in a wrapped literal", "by name"),
    ('pip install --no-index \\\n    --find-links wheelhouse "gpmhe[casadi]"', "fine"),
])
def test_the_check_tells_a_name_from_a_path(line, verdict):
    commands = list(install_commands(line))
    named = [a for _, args in commands if "--find-links" not in args for a in gpmhe_by_name(args)]
    assert bool(named) == (verdict == "by name"), commands


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_install_lines_work_as_written(path):
    extras = pyproject_extras()
    for line, args in install_commands(path.read_text()):
        if "--find-links" not in args and "-f" not in args:
            assert not gpmhe_by_name(args), (
                f"{path.name}: `{line}` installs gpmhe from a package index, where it is not; "
                "use `pip install \".[extra]\"` (a clone) or `pip install --no-index --find-links "
                "wheelhouse \"gpmhe[extra]\"` (a wheelhouse, see docs/getting_started.rst)")
        for arg in args:
            if GPMHE_BY_NAME.fullmatch(arg.strip("'\"")) or arg.strip("'\"").startswith(".["):
                for group in EXTRAS.findall(arg):
                    named = {e.strip() for e in group.split(",")}
                    assert named <= extras, f"{path.name}: `{line}` names no extra {named - extras}"


def test_the_extras_table_lists_every_extra():
    page = (ROOT / "docs" / "getting_started.rst").read_text()
    table = re.search(r"^(=+  =+)\n.*?\n\1\n(.*?)\n\1\n", page, re.S | re.M)
    assert table, "the getting-started page has no extras table"
    listed = re.findall(r"^``([\w-]+)``", table.group(2), re.M)
    assert len(listed) == len(set(listed))
    assert set(listed) == pyproject_extras()
