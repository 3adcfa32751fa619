"""One user at a time for the estimators' Rust cores.

The Rust core of an estimator is mutated by every update and released from the GIL while it
works, so a second thread calling into the same estimator meanwhile would find it busy (pyo3's
"Already borrowed") or, on the SciPy solver paths that call the core several times per update,
interleave with the first update. `exclusive` makes such an overlap a clear ``RuntimeError``
raised before anything changes; the first update is unaffected. Different estimators never
wait for each other. The registry lives here, not on the objects, so copying and pickling them
is unaffected.
"""

from __future__ import annotations

import functools
import threading

_lock = threading.Lock()
_busy: dict = {}  # id(obj) -> ident of the thread using it


def exclusive(method):
    """Decorates a method that must not overlap with itself (or another decorated method) on
    the same object; an overlap raises RuntimeError in the second caller."""

    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        key, me = id(self), threading.get_ident()
        with _lock:
            owner = _busy.get(key)
            if owner is None:
                _busy[key] = me
        if owner is not None:
            name = type(self).__name__
            if owner == me:
                raise RuntimeError(f"{name} is already updating in this thread (an update was "
                                   f"started from inside a model callback); it is unchanged")
            raise RuntimeError(f"{name} is in use by another thread; use one estimator per thread "
                               f"or serialise the calls with a lock (this call changed nothing)")
        try:
            return method(self, *args, **kwargs)
        finally:
            with _lock:
                del _busy[key]

    return wrapper
