"""What a user of filterpy brings to gpmhe's estimators, met where it would trip them up.

* Renamed attributes (`RENAMED`: ``x_prior``, whose name meant filterpy's one-step prediction,
  is ``x_arrival``) keep working for one release: reading or setting the old name warns
  (`renamed`) and uses the new one.
* filterpy's attribute names that an estimator does not have (``predict``, ``x_post``, ``y``,
  ...) raise an AttributeError that names the estimator's own (`missing_attribute`).
* Setting an attribute an estimator does not take (filterpy's ``R``, a read-only setting)
  raises an AttributeError that says what to set instead (`refused_setting`).
* filterpy's one-argument ``update(z)`` raises a TypeError that shows gpmhe's ``update(u, y)``
  (`REQUIRED`, `required`, `one_argument_update`).
* Attributes whose shape grows while the window fills are `window_attribute` descriptors, not
  properties: filterpy's ``Saver`` records every property at each ``save()``, and its
  ``to_array()`` needs one shape per attribute.
"""

from __future__ import annotations

import inspect
import warnings

__all__ = ["RENAMED", "FILTERPY_NAMES", "BANK_NAMES", "REQUIRED", "renamed", "refused_setting",
           "missing_attribute", "required", "one_argument_update", "window_attribute"]

#: Renamed attributes, old name -> new name: the old name works for one release, with a warning.
RENAMED = {"x_prior": "x_arrival"}

#: filterpy's attributes the estimators do not have -> what to use instead.
FILTERPY_NAMES = {
    "predict": "update, which predicts too: with form='prediction' x is then x̂(t+1), "
               "filterpy's x after predict",
    "x_post": "x with form='filtering' (x̂(t) from y(0..t))",
    "P_prior": "P (the covariance of x in either form)",
    "P_post": "P (the covariance of x in either form)",
    "y": "innovation (y(t) minus the output predicted before it was seen)",
    "likelihood": "log_likelihood (numpy.exp of it)",
    "mahalanobis": "nis (the square of filterpy's mahalanobis)",
}

#: The names of `FILTERPY_NAMES` whose replacement an `EstimatorBank` has (it reports no
#: innovations).
BANK_NAMES = ("predict", "x_post", "P_prior", "P_post")


def renamed(owner, name):
    """The new name of attribute ``name`` of class ``owner`` if it was renamed, after a
    `DeprecationWarning` pointed at the code that used the old name (two frames up: the caller
    of ``__getattr__`` or ``__setattr__``); None if it was not renamed."""
    new = RENAMED.get(name)
    if new is not None:
        cls = owner.__name__
        warnings.warn(f"{cls}.{name} is deprecated and will be removed in the next release: use "
                      f"{cls}.{new}, the arrival prior of the last window (filterpy's x_prior, "
                      "the one-step prediction, is x with form='prediction')",
                      DeprecationWarning, stacklevel=3)
    return new


def missing_attribute(obj, name, names=tuple(FILTERPY_NAMES)):
    """The AttributeError for attribute ``name`` that ``obj`` does not have, naming what to use
    instead when the name is one of filterpy's ``names`` (those `FILTERPY_NAMES` that ``obj``
    has a replacement for)."""
    message = f"{type(obj).__name__!r} object has no attribute {name!r}"
    hint = FILTERPY_NAMES.get(name) if name in names else None
    if hint is not None:
        message += f" (filterpy's {name}); use {hint}"
    error = AttributeError(message)
    error.name, error.obj = name, obj  # Python's "Did you mean" for other names (3.10 and on)
    return error


def refused_setting(obj, name, settable, hints, fixed):
    """The AttributeError for setting `name` on `obj`, which takes only the `settable` names:
    the name to use instead if `hints` has one, else that there is no such attribute, else that
    it is read-only, with `fixed` saying how the setting does change."""
    owner, names = type(obj).__name__, ", ".join(sorted(settable))
    hint = hints.get(name)
    if hint is not None:
        return AttributeError(f"{owner} has no settable attribute {name!r}: did you mean {hint}?")
    if not hasattr(obj, name):
        return AttributeError(f"{owner} has no attribute {name!r}; the settable ones are {names}")
    return AttributeError(f"{owner}.{name} is read-only; the settable attributes are {names} "
                          f"({fixed})")


class _Required:
    """The type of `REQUIRED`."""

    def __repr__(self):
        return "<required>"


#: The default of a required argument whose absence gets its own message.
REQUIRED = _Required()


def required(method):
    """``method`` with its parameters that default to `REQUIRED` shown as required in its
    signature (for `inspect` and the documentation), which they are: the default only lets the
    method answer a call without them with its own TypeError."""
    signature = inspect.signature(method)
    parameters = [p.replace(default=inspect.Parameter.empty) if p.default is REQUIRED else p
                  for p in signature.parameters.values()]
    method.__signature__ = signature.replace(parameters=parameters)
    return method


def one_argument_update(owner, u="u", y="y"):
    """The TypeError of ``owner.update`` called with one argument, as filterpy's ``update(z)``."""
    return TypeError(f"{owner.__name__}.update({u}, {y}) takes the input first and then the "
                     f"output; give {u}=None when there is no input: filterpy's "
                     f"update(z) is update(None, z)")


class window_attribute:  # noqa: N801 (used as a decorator, like property)
    """A read-only attribute computed by ``fget``, as a `property`, for a value whose shape grows
    while the window fills (``x_window``, ``P_window``).

    It is not a `property` so that filterpy's ``Saver``, which records every property of the
    object at each ``save()`` and whose ``to_array()`` needs one shape per attribute, leaves it
    out; everything else treats it as a read-only property.
    """

    def __init__(self, fget):
        self.fget = fget
        self.__doc__ = fget.__doc__
        self.__name__ = fget.__name__

    def __set_name__(self, owner, name):
        self.__name__ = name

    def __get__(self, obj, owner=None):
        return self if obj is None else self.fget(obj)

    def __set__(self, obj, value):
        raise AttributeError(f"{type(obj).__name__}.{self.__name__} is read-only")
