"""Reading gpmhe's ``.npz`` files (saved GPs, models and estimator checkpoints) safely.

Every file gpmhe writes is a plain `numpy.savez` archive without pickled objects, with a ``kind``
and a ``format_version`` entry. `NpzReader` opens one with ``allow_pickle=False`` and turns every
way a file can be wrong — not an npz file, truncated, another kind of file, an entry missing,
damaged or of the wrong dtype or shape — into a ValueError that names the file and the entry.
"""

from __future__ import annotations

import os
import zipfile

import numpy as np

# What reading a damaged archive or member can raise (numpy and zipfile are not consistent).
_READ_ERRORS = (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError, TypeError,
                NotImplementedError, RuntimeError)

_KINDS = {"f": "float", "i": "integer", "b": "bool", "U": "string"}


def file_name(path):
    """How messages name a file: its path, or the name of a file object if it has one."""
    if isinstance(path, (str, bytes, os.PathLike)):
        return repr(os.fsdecode(path))
    name = getattr(path, "name", None)
    return repr(name) if isinstance(name, str) else "(file object)"


class NpzReader:
    """An open gpmhe ``.npz`` file of one ``kind`` (a context manager).

    Raises ValueError (starting with "path:" and naming the file) if the file cannot be read as
    an npz archive, is not of this kind, or comes from a newer format version.
    """

    def __init__(self, path, kind, max_version, require_version=True):
        self.name = file_name(path)
        self.kind = kind
        try:
            self._f = np.load(path, allow_pickle=False)
        except _READ_ERRORS as e:
            raise ValueError(f"path: {self.name} is not a readable .npz file ({e})") from None
        if not isinstance(self._f, np.lib.npyio.NpzFile):
            self._f = None
            raise ValueError(f"path: {self.name} is a .npy file, not an .npz file")
        try:
            if "kind" not in self._f.files or self.string("kind") != kind:
                raise ValueError(f"path: {self.name} is not a saved {kind} file (its entry "
                                 f"'kind' is missing or not {kind!r})")
            self.version = 1  # files without an entry are of the first format
            if require_version or "format_version" in self._f.files:
                version = self.version = self.integer("format_version")
                if version > max_version:
                    raise ValueError(f"path: {self.name} was saved by a newer gpmhe (format "
                                     f"version {version} > {max_version})")
        except BaseException:
            self.close()
            raise

    def close(self):
        if self._f is not None:
            self._f.close()
            self._f = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __contains__(self, key):
        return key in self._f.files

    def state_error(self, prefix, e):
        """The ValueError for a state the core rejected with `e` (whose message starts with the
        name of the state's entry, as the file's entry `prefix` + name)."""
        key, _, rest = str(e).partition(":")
        return self.error(prefix + key, f"does not fit:{rest}")

    def error(self, key, what):
        """The ValueError for a bad entry."""
        return ValueError(f"path: {self.name}: entry {key!r} {what}")

    def raw(self, key):
        if key not in self._f.files:
            raise self.error(key, f"is missing (not a complete {self.kind} file)")
        try:
            return self._f[key]
        except _READ_ERRORS as e:
            raise self.error(key, f"cannot be read, the file is damaged ({e})") from None

    def array(self, key, kind="f", shape=None):
        """Entry `key` as an array of the dtype kind `kind` ("f" float64, "i" int64, "b" bool,
        "U" str); `shape` a tuple with None for any length (None: any shape)."""
        a = self.raw(key)
        ok = a.dtype.kind == kind or (kind == "f" and a.dtype.kind in "iu") or (
            kind == "i" and a.dtype.kind == "u")
        if not ok:
            raise self.error(key, f"must hold {_KINDS[kind]} values, got dtype {a.dtype}")
        if shape is not None and (a.ndim != len(shape) or any(
                s is not None and s != d for s, d in zip(shape, a.shape))):
            want = "(" + ", ".join("k" if s is None else str(s) for s in shape) + \
                   ("," if len(shape) == 1 else "") + ")"
            raise self.error(key, f"has shape {a.shape}, expected {want}")
        if kind == "f":
            a = np.asarray(a, dtype=np.float64, order="C")
            if key not in self.allow_nonfinite and not np.all(np.isfinite(a)):
                raise self.error(key, "holds NaN or infinite values")
        elif kind == "i":
            a = np.asarray(a, dtype=np.int64, order="C")
        return a

    #: Entries whose float values may be NaN or ±inf (box bounds, some statistics).
    allow_nonfinite = ()

    def floats(self, key, shape=None):
        return self.array(key, "f", shape)

    def float(self, key):
        return float(self.array(key, "f", ()))

    def integer(self, key, low=0):
        v = int(self.array(key, "i", ()))
        if v < low:
            raise self.error(key, f"must be >= {low}, got {v}")
        return v

    def boolean(self, key):
        return bool(self.array(key, "b", ()))

    def string(self, key):
        return str(self.array(key, "U", ()))
