"""One user at a time for the estimators' Rust cores.

The Rust core of an estimator is mutated by every update and released from the GIL while it
works, so a second thread calling into the same estimator meanwhile would find it busy (pyo3's
"Already borrowed") or, on the SciPy solver paths that call the core several times per update,
interleave with the first update. `exclusive` makes such an overlap a clear ``RuntimeError``
raised before anything changes; the first update is unaffected. Different estimators never
wait for each other. The registry lives here, not on the objects, so copying and pickling them
is unaffected.

A KeyboardInterrupt (Ctrl-C) must never leave an object marked busy: CPython runs signal
handlers (and switches threads) only at calls and backward jumps, so the registration (a
membership test and a store) and the removal (a delete) below contain no call, and the removal
runs in a ``finally`` whatever the method raised.
"""

from __future__ import annotations

import functools
import threading

_busy: dict = {}  # id(obj) -> ident of the thread using it


def exclusive(method):
    """Decorates a method that must not overlap with itself (or another decorated method) on
    the same object; an overlap raises RuntimeError in the second caller."""

    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        key, me = id(self), threading.get_ident()
        mine = False
        try:
            if key not in _busy:  # (no call from here to `mine = True`: see the module docs)
                _busy[key] = me
                mine = True
            else:
                _refuse(self, _busy.get(key), me)
            return method(self, *args, **kwargs)
        finally:
            if mine:
                del _busy[key]

    return wrapper


def _refuse(obj, owner, me):
    name = type(obj).__name__
    if owner == me:
        raise RuntimeError(f"{name} is already updating in this thread (an update was started "
                           f"from inside a model callback); it is unchanged")
    raise RuntimeError(f"{name} is in use by another thread; use one estimator per thread or "
                       f"serialise the calls with a lock (this call changed nothing)")
