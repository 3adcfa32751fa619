"""CasADi models compiled for the estimator's core: CasADi's C code generation, the C compiler,
and gpmhe's cache of the shared libraries.

`library(functions)` returns the path of a shared library holding the given CasADi functions: it
generates their C code (CasADi's ``CodeGenerator``), and compiles it with ``$CC`` (default
``cc``) unless the cache already holds the library of exactly that code. The cache is a
directory of gpmhe's (``$GPMHE_CACHE_DIR``, else ``$XDG_CACHE_HOME/gpmhe`` or
``~/.cache/gpmhe``), never the working directory; each library sits next to the SHA-256 of its
bytes, checked before it is loaded, so a damaged or truncated file is compiled again instead of
loaded. The cache is bounded: a library's modification time records its last use, and after each
compilation the least recently used beyond ``$GPMHE_CACHE_MAX`` (default `MAX_LIBRARIES`) are
removed (`prune`); `clear_cache` empties it. Failures raise `CompileError` (the caller falls back
to Python callbacks and says so).
"""

from __future__ import annotations

import hashlib
import os
import pathlib
import platform
import shlex
import subprocess
import tempfile
import time

#: The C compiler's flags: optimised, position-independent, no fast-math or target-specific
#: instructions (the library computes what CasADi's own evaluation computes, bit for bit).
FLAGS = ("-O2", "-fPIC", "-shared")
#: The name of the generated C file's prefix (its size queries are ``<PREFIX>_casadi_int_size``).
PREFIX = "gpmhe_model"
#: The most libraries the cache keeps unless ``$GPMHE_CACHE_MAX`` says otherwise.
MAX_LIBRARIES = 200
#: Build directories older than this (seconds) belong to a compilation that was killed.
STALE_BUILD = 3600.0


class CompileError(RuntimeError):
    """The model could not be compiled or cached (no C compiler, an unwritable cache, code that
    CasADi cannot generate)."""


def cache_directory() -> pathlib.Path:
    """Where compiled models are kept: ``$GPMHE_CACHE_DIR``, else ``$XDG_CACHE_HOME/gpmhe``, else
    ``~/.cache/gpmhe`` (the ``casadi`` folder inside it)."""
    root = os.environ.get("GPMHE_CACHE_DIR")
    if not root:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        root = os.path.join(base, "gpmhe")
    return pathlib.Path(root) / "casadi"


def compiler() -> list:
    """The C compiler command: ``$CC`` split as a shell would, else ``cc``."""
    return shlex.split(os.environ.get("CC") or "cc")


def _generate(ca, functions) -> str:
    """The C source of `functions` (CasADi's code generation, in a throw-away directory)."""
    for fn in functions:
        if not fn.is_a("SXFunction"):
            raise CompileError(f"{fn.name()} keeps CasADi MX operations (such as the rootfinder of "
                               f"an implicit integration scheme), which CasADi generates no C code for")
    with tempfile.TemporaryDirectory(prefix="gpmhe-codegen-") as directory:
        generator = ca.CodeGenerator(PREFIX, {"with_header": False})
        for fn in functions:
            generator.add(fn)
        try:
            path = generator.generate(directory + os.sep)
        except RuntimeError as e:
            raise CompileError(f"CasADi cannot generate C code for this model: {_last_line(e)}") from None
        source = pathlib.Path(path).read_text()
    if "#error" in source:  # CasADi writes this where a part (a rootfinder) has no C code
        line = next(line for line in source.splitlines() if "#error" in line)
        raise CompileError(f"CasADi cannot generate C code for a part of this model "
                           f"({line.replace('#error', '').strip()})")
    return source


def _last_line(e) -> str:
    text = str(e).strip()
    return text.splitlines()[-1] if text else type(e).__name__


def _first_error(text: str) -> str:
    """The compiler's first line that says "error", else its last line."""
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    errors = [line for line in lines if "error" in line.lower()]
    return (errors or lines or ["no output"])[0 if errors else -1]


def _digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _cached(so: pathlib.Path, sha: pathlib.Path) -> bool:
    """Whether `so` is there and its bytes have the recorded checksum."""
    try:
        return sha.read_text().strip() == _digest(so.read_bytes())
    except OSError:
        return False


def _compile(source: str, so: pathlib.Path, sha: pathlib.Path) -> None:
    """Compiles `source` into `so` (written under a temporary name, then renamed, so that a
    concurrent reader never sees half a library) and records its checksum in `sha`."""
    directory = so.parent
    try:
        directory.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(prefix="build-", dir=directory) as build:
            c_file, lib = os.path.join(build, PREFIX + ".c"), os.path.join(build, "model.so")
            pathlib.Path(c_file).write_text(source)
            cmd = [*compiler(), *FLAGS, "-o", lib, c_file, "-lm"]
            try:
                run = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
            except (OSError, subprocess.SubprocessError) as e:
                raise CompileError(f"the C compiler {shlex.join(compiler())!r} did not run: {e}") from None
            if run.returncode != 0:
                raise CompileError(f"the C compiler failed ({shlex.join(cmd[:1])}): "
                                   f"{_first_error(run.stderr or run.stdout)}")
            data = pathlib.Path(lib).read_bytes()
            tmp_sha = os.path.join(build, "model.sha256")
            pathlib.Path(tmp_sha).write_text(_digest(data) + "\n")
            os.replace(lib, so)
            os.replace(tmp_sha, sha)
    except OSError as e:
        raise CompileError(f"cannot write the compiled model to {directory}: {e}") from None


def library(ca, functions, rebuild: bool = False) -> str:
    """The path of a shared library with `functions` compiled (from the cache if it holds the
    library of the same code, compiler and flags; `rebuild` compiles again in any case)."""
    source = _generate(ca, functions)
    key = _digest("\0".join([source, shlex.join(compiler()), " ".join(FLAGS), platform.machine(),
                             ca.__version__]).encode())
    directory = cache_directory()
    so, sha = directory / f"{key}.so", directory / f"{key}.sha256"
    if rebuild or not _cached(so, sha):
        limit = max_libraries()  # (a bad $GPMHE_CACHE_MAX fails before anything is compiled)
        _compile(source, so, sha)
        prune(limit)
    else:
        try:
            os.utime(so)  # its last use, for `prune`
        except OSError:
            pass  # a read-only cache still serves its libraries
    return str(so)


def max_libraries() -> int:
    """The most libraries the cache keeps: ``$GPMHE_CACHE_MAX``, else `MAX_LIBRARIES`."""
    value = os.environ.get("GPMHE_CACHE_MAX")
    if value is None or value == "":
        return MAX_LIBRARIES
    try:
        limit = int(value)
    except ValueError:
        limit = 0
    if limit < 1:
        raise CompileError(f"$GPMHE_CACHE_MAX: must be a whole number >= 1, got {value!r}")
    return limit


def _libraries(directory: pathlib.Path) -> list:
    """The cache's libraries, most recently used first."""
    found = []
    for so in directory.glob("*.so"):
        try:
            found.append((so.stat().st_mtime, so))
        except OSError:
            pass  # removed meanwhile by another process
    return [so for _, so in sorted(found, key=lambda item: item[0], reverse=True)]


def _remove(so: pathlib.Path) -> bool:
    """Removes a library and its checksum (a process that has it loaded keeps its copy)."""
    removed = False
    for path in (so, so.with_suffix(".sha256")):
        try:
            path.unlink()
            removed = True
        except OSError:
            pass
    return removed


def prune(keep: int = None) -> int:
    """Remove the least recently used compiled models beyond the most recent `keep`.

    Also removes the build directories a killed compilation left behind. A process that has a
    removed library loaded keeps using it; one that asks for it again compiles it again.

    Parameters
    ----------
    keep : int or None, default None
        How many libraries to keep; None: ``$GPMHE_CACHE_MAX``, else `MAX_LIBRARIES` (200).

    Returns
    -------
    int
        The number of libraries removed.
    """
    keep = max_libraries() if keep is None else keep
    directory = cache_directory()
    removed = sum(_remove(so) for so in _libraries(directory)[keep:])
    for build in directory.glob("build-*"):
        try:
            if time.time() - build.stat().st_mtime > STALE_BUILD:
                for f in build.iterdir():
                    f.unlink()
                build.rmdir()
        except OSError:
            pass
    return removed


def clear_cache() -> int:
    """Remove every compiled model from gpmhe's cache (`cache_directory`).

    The next estimator on a CasADi model compiles its library again; estimators running
    meanwhile keep the library they have loaded.

    Returns
    -------
    int
        The number of libraries removed.
    """
    return prune(0)
