"""What both models share: their immutability under copies (`SharedOnCopy`), the check that
their callables pickle (`check_picklable`), the conversion of one point (`point`), and the error
of a model that cannot be evaluated at a point (`ModelDomainError`, `call_user`)."""

from __future__ import annotations

import numpy as np

from gpmhe._validation import finite_vector

__all__ = ["SharedOnCopy", "check_picklable", "point", "ModelDomainError", "call_user"]


class ModelDomainError(ValueError, ArithmeticError):
    """A model function returned NaN, inf or a value beyond the magnitude limit at a point, or
    raised ValueError there (``math.log`` of a negative number, say).

    For a caller it is a ValueError naming the function. For the window solver it is an
    ArithmeticError: the core treats it as a numerical failure of that evaluation, so a trial
    point of a step is rejected (a shorter step, more damping) instead of ending the update; at
    the window's start point (the warm start) it ends the update and reaches the caller.
    """


def call_user(fn, name, *args):
    """``fn(*args)`` with a ValueError it raises turned into a `ModelDomainError` naming ``name``
    (any other exception passes as it is: ArithmeticError is already a numerical failure, and a
    TypeError or a bug's other errors end the update)."""
    try:
        return fn(*args)
    except ModelDomainError:
        raise
    except ValueError as e:
        raise ModelDomainError(f"{name}: raised ValueError at this point ({e})") from e


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
