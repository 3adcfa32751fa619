"""What both models share: their immutability under copies (`SharedOnCopy`), the check that
their callables pickle (`check_picklable`) and the conversion of one point (`point`)."""

from __future__ import annotations

import numpy as np

from gpmhe._validation import finite_vector

__all__ = ["SharedOnCopy", "check_picklable", "point"]


def point(x, u, n, m):
    """A model's point (x, u) as finite vectors of n and m values; u may be None when m = 0."""
    if u is None:
        if m:
            raise ValueError(f"u: required (dim_u = {m})")
        u = np.zeros(0)
    return finite_vector("x", x, n, flatten=True), finite_vector("u", u, m, flatten=True)


class SharedOnCopy:
    """Models are immutable after construction; `copy.deepcopy` (used by filterpy's Saver on the
    estimator's attributes) shares them instead of copying the Rust objects inside."""

    def __deepcopy__(self, memo):
        return self

    def __copy__(self):
        return self


def check_picklable(owner, callables):
    """Raise `pickle.PicklingError` naming the first of `callables` (name -> callable or None)
    that cannot be pickled (a lambda, a local function, ...)."""
    import pickle

    for name, fn in callables.items():
        if fn is None:
            continue
        try:
            pickle.dumps(fn)
        except Exception as e:  # pickle raises PicklingError, AttributeError, TypeError, ...
            raise pickle.PicklingError(
                f"{owner}: cannot pickle {name}={fn!r} ({e}); to pickle or copy it to another "
                f"process, give {name} as a module-level function (or another picklable "
                f"callable)") from None
