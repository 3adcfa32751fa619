"""Input validation shared by the gpmhe modules: one set of helpers, so that a name means the same
check everywhere.

Every helper takes the argument's name first and the value second, returns the value converted
(float64 arrays, Python floats and ints) and raises `ValueError` with a message that starts with
the argument's name ("Q0: must be symmetric"). The modules call these where a public function or
constructor receives its arguments, once; the Rust core checks again what it reads (a second line
of defence that names the same arguments).

One rule for numbers (`real_array`, under every numeric helper): real numbers only (Python or
numpy ints and floats, and arrays of them). Strings (numeric ones too), bools, complex values and
other objects are refused rather than converted, and so are values of magnitude > `MAX_ABS`;
NaN and inf only where a helper says what they mean.
"""

from __future__ import annotations

import math
import os
import sys
from typing import Any, Optional, Sequence, Tuple

import numpy as np

from gpmhe._core import NumericalError

__all__ = [
    "MAX_ABS",
    "MAX_COUNT",
    "MagnitudeError",
    "SettingsWarning",
    "user_stacklevel",
    "within_limits",
    "real_array",
    "float_array",
    "box",
    "output_sample",
    "sequence_rows",
    "finite_vector",
    "positive",
    "positive_scalar",
    "integer",
    "in_open_interval",
    "one_of",
    "symmetric_matrix",
    "positive_diagonal",
    "points",
    "training_set",
    "boolean",
    "random_state",
    "options",
]

#: The largest magnitude accepted in a numeric argument: beyond it squares (variances, distances,
#: costs) overflow float64 (whose largest square root is about 1.3e154).
MAX_ABS = 1e150


class MagnitudeError(ValueError, NumericalError):
    """A value too large for float64 arithmetic (magnitude > MAX_ABS): bad input and a numerical
    failure at once, so either ``except ValueError`` or ``except gpmhe.NumericalError`` catches
    it."""


class SettingsWarning(UserWarning):
    """A setting that gpmhe had to assume, or one that has no effect with the others given.

    Emitted once per construction or fit (for example an estimator built without any noise
    information, which gets identity weights). Silence a reviewed case with
    ``warnings.filterwarnings("ignore", category=gpmhe.SettingsWarning)``.

    Examples
    --------
    Turn it into an error, for a plant's deployment script that must give every setting:

    >>> import warnings
    >>> from gpmhe import GPMHE, KnownModel, SettingsWarning
    >>> plant = KnownModel(lambda x, u: 0.9 * x, lambda x, u: x, dim_x=1, dim_y=1)
    >>> with warnings.catch_warnings():
    ...     warnings.simplefilter("error", SettingsWarning)
    ...     try:
    ...         GPMHE(plant, x0=[0.0])
    ...     except SettingsWarning as w:
    ...         print(str(w)[:47])
    Q0, R0 and P2/P0 are all None: identity weights
    """


#: Frames in files under this directory are gpmhe's own (see `user_stacklevel`).
_PACKAGE_DIR = os.path.dirname(os.path.abspath(__file__))


def user_stacklevel() -> int:
    """The ``stacklevel`` that makes a warning raised by the caller point at the first frame
    outside gpmhe (the user's line that led to it)."""
    frame, level = sys._getframe(1), 1
    while frame is not None and frame.f_code.co_filename.startswith(_PACKAGE_DIR):
        frame, level = frame.f_back, level + 1
    return level


def _not_numbers(name: str, value: Any) -> str:
    """The message for a value that is not a number or an array of numbers (of one shape)."""
    text = repr(value)
    text = text if len(text) <= 60 else text[:57] + "..."
    return f"{name}: must be a number or an array of numbers (all rows of one length), got {text}"


#: numpy's kinds of real numbers: floats, signed and unsigned integers (bool is kind "b").
_REAL_KINDS = "fiu"


def real_array(name: str, value: Any, *, copy: bool = False) -> np.ndarray:
    """``value`` as a float64 array if it holds real numbers only (see the module docs); a new
    array with ``copy``. Values are not checked for NaN, inf or magnitude here."""
    try:
        a = np.asarray(value)
    except (TypeError, ValueError):
        raise ValueError(_not_numbers(name, value)) from None
    if a.dtype.kind not in _REAL_KINDS:
        if a.dtype.kind == "O":  # e.g. numpy scalars in a list with Python numbers
            try:
                a = np.asarray(value, dtype=np.float64) if all(
                    _is_real(v) for v in a.ravel().tolist()) else None
            except (TypeError, ValueError, OverflowError):
                a = None
            if a is None:
                raise ValueError(_not_numbers(name, value)) from None
        else:
            what = {"b": "bools", "c": "complex values", "U": "strings", "S": "bytes"}.get(
                a.dtype.kind, f"values of type {a.dtype}")
            raise ValueError(f"{name}: must be real numbers, got {what} "
                             f"({_short(value)}; convert them first if they are numbers)")
    if isinstance(value, (list, tuple)) and _has_bool(value):  # numpy makes [True, 0.5] floats
        raise ValueError(f"{name}: must be real numbers, got bools ({_short(value)})")
    if a.dtype != np.float64:
        try:
            a = a.astype(np.float64)
        except OverflowError:
            raise MagnitudeError(f"{name}: contains a value of magnitude > {MAX_ABS:g}") from None
    elif copy:
        a = a.copy()
    return a


def _has_bool(value: Any) -> bool:
    """Whether a nested list or tuple holds a bool (or a bool array)."""
    if isinstance(value, (bool, np.bool_)):
        return True
    if isinstance(value, (list, tuple)):
        return any(_has_bool(v) for v in value)
    return isinstance(value, np.ndarray) and value.dtype.kind == "b"


def _is_real(v: Any) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def within_limits(a: np.ndarray) -> bool:
    """Whether every value of the float64 array ``a`` is of magnitude <= MAX_ABS (NaN is not):
    a Python loop for the few values of a per-step input (cheaper than numpy's reductions
    there), one reduction otherwise."""
    if a.size <= 16:
        return all(-MAX_ABS <= v <= MAX_ABS for v in a.ravel().tolist())
    return bool(np.abs(a).max() <= MAX_ABS)


def _check_values(name: str, a: np.ndarray) -> None:
    """Raise ValueError naming ``name`` unless every value of ``a`` is finite and of magnitude
    <= MAX_ABS."""
    if not within_limits(a):
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name}: contains NaN or inf")
        raise MagnitudeError(f"{name}: contains a value of magnitude > {MAX_ABS:g} (its square overflows)")


def float_array(name: str, value: Any, ndim: Optional[int] = None, *, copy: bool = False,
                missing: bool = False) -> np.ndarray:
    """A finite C-contiguous float64 array; ``ndim`` fixes the number of dimensions.

    With ``copy`` the result never shares memory with ``value`` (for values an object keeps);
    with ``missing`` NaN entries are allowed (they mark missing samples; inf is not).
    """
    a = real_array(name, value, copy=copy)
    if ndim is not None and a.ndim != ndim:
        raise ValueError(f"{name}: expected a {ndim}-D array, got shape {a.shape}")
    if missing and np.any(np.isinf(a)):
        raise ValueError(f"{name}: contains inf (mark a missing sample with NaN)")
    _check_values(name, a[~np.isnan(a)] if missing else a)
    return a if a.flags.c_contiguous else np.ascontiguousarray(a)  # (ascontiguousarray makes 0-D 1-D)


def finite_vector(name: str, value: Any, n: int, *, flatten: bool = False) -> np.ndarray:
    """A finite float64 vector of shape (n,) (a new array). With ``flatten`` any shape of n
    values is accepted (a row or column vector, say) and the result may share memory with
    ``value`` (for values passed on at once, as an estimator's per-step input)."""
    if flatten:
        if type(value) is np.ndarray and value.dtype == np.float64:  # the per-step fast path
            a = value.reshape(-1)
        else:
            a = real_array(name, value).reshape(-1)
        if a.shape == (n,) and within_limits(a):
            return a
        a = float_array(name, a)  # the NaN/inf message
    else:
        a = float_array(name, value, copy=True)
    if a.shape != (n,):
        raise ValueError(f"{name}: expected shape ({n},), got {a.shape}")
    return a


def box(name: str, bounds: Any, n: int, rows: Optional[int] = None) -> Tuple[np.ndarray, np.ndarray]:
    """(lower, upper) float64 arrays of shape (n,) — or (rows, n), each side given once for all
    rows as (n,) or per row as (rows, n) — from None (unbounded) or a pair whose sides may be None
    (unbounded) or hold ±inf entries; finite entries of magnitude <= MAX_ABS, no NaN, and
    lower < upper (errors name the row)."""
    sides = (None, None) if bounds is None else bounds
    if isinstance(sides, (str, bytes, dict)):
        raise ValueError(f"{name}: must be a pair (lower, upper)")
    try:
        lower, upper = sides
    except (TypeError, ValueError):
        raise ValueError(f"{name}: must be a pair (lower, upper)") from None
    shape = (n,) if rows is None else (rows, n)
    out = []
    for side, fill in ((lower, -np.inf), (upper, np.inf)):
        a = np.full(shape, fill) if side is None else real_array(name, side)
        if rows is not None and a.shape == (n,):
            a = np.tile(a, (rows, 1))
        if a.shape != shape:
            alt = f"({n},)" if rows is None else f"({n},) or ({rows}, {n})"
            raise ValueError(f"{name}: lower and upper must have shape {alt} (or be None), "
                             f"got {a.shape}")
        if np.any(np.isnan(a)):
            raise ValueError(f"{name}: contains NaN (use -inf or inf, or None, for no bound)")
        if not within_limits(a[np.isfinite(a)]):
            raise MagnitudeError(f"{name}: contains a finite value of magnitude > {MAX_ABS:g} "
                                 "(use -inf or inf for no bound)")
        out.append(np.ascontiguousarray(a))
    bad = np.any(out[0] >= out[1], axis=-1)
    if np.any(bad):
        where = "" if rows is None else f" (estimator {int(np.flatnonzero(bad)[0])})"
        raise ValueError(f"{name}: lower must be < upper{where}")
    return out[0], out[1]


def output_sample(name: str, y: Any, p: int) -> Tuple[np.ndarray, bool]:
    """One output sample y(t) of p values (NaN entries are channels not measured; inf, values of
    magnitude > MAX_ABS (a `MagnitudeError`) and anything but real numbers are refused) and
    whether any channel is measured. A Python loop over the values: cheaper than numpy's
    reductions for the few values of one sample."""
    try:
        a = np.asarray(y)
        if a.dtype.kind not in _REAL_KINDS or (isinstance(y, (list, tuple)) and _has_bool(y)):
            raise TypeError
        a = a.astype(np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: must be {p} real numbers (NaN for a channel not measured)") from None
    if a.shape != (p,):
        raise ValueError(f"{name}: expected shape ({p},), got {a.shape}")
    measured = False
    for v in a.tolist():
        if v == v:  # not NaN
            if not -MAX_ABS <= v <= MAX_ABS:
                if math.isinf(v):
                    raise ValueError(f"{name}: contains inf (NaN marks a channel not measured)")
                raise MagnitudeError(f"{name}: contains a value of magnitude > {MAX_ABS:g} (its "
                                     "square overflows)")
            measured = True
    return a, measured


def sequence_rows(name: str, value: Any) -> list:
    """The rows of a sequence (a list, tuple or array; strings, dicts and sets are refused)."""
    if isinstance(value, (str, bytes, dict, set)) or not hasattr(value, "__len__"):
        raise ValueError(f"{name}: must be a sequence of rows, got {type(value).__name__}")
    try:
        return list(value)
    except TypeError:
        raise ValueError(f"{name}: must be a sequence of rows, got {type(value).__name__}") from None


def positive(name: str, value: Any, *, allow_zero: bool = False) -> np.ndarray:
    """A float64 array (of any shape, a scalar gives shape ()) of finite values > 0 (>= 0 with
    ``allow_zero``)."""
    a = real_array(name, value)
    if not np.all(np.isfinite(a)) or np.any(a < 0 if allow_zero else a <= 0) or np.any(a > MAX_ABS):
        raise _not_positive(name, value, allow_zero, huge=bool(np.any(np.isfinite(a) & (np.abs(a) > MAX_ABS))))
    return a


def _not_positive(name: str, value: Any, allow_zero: bool, huge: bool) -> ValueError:
    """The error of `positive` and `positive_scalar`: a `MagnitudeError` for a finite value of
    magnitude > MAX_ABS (``huge``), as everywhere."""
    error = MagnitudeError if huge else ValueError
    return error(f"{name}: must be finite and {'>= 0' if allow_zero else '> 0'} (at most "
                 f"{MAX_ABS:g}), got {value!r}")


def positive_scalar(name: str, value: Any, *, allow_zero: bool = False) -> float:
    """A finite number > 0 (>= 0 with ``allow_zero``) as a Python float; arrays are refused."""
    a = real_array(name, value)
    if a.ndim != 0:
        raise ValueError(f"{name}: must be a number, got an array of shape {a.shape}")
    v = float(a)
    if not (math.isfinite(v) and (v >= 0.0 if allow_zero else v > 0.0) and v <= MAX_ABS):
        raise _not_positive(name, value, allow_zero, huge=math.isfinite(v) and abs(v) > MAX_ABS)
    return v


#: The largest count (dimension, number of points or iterations) accepted: the Rust core's
#: sizes are machine integers.
MAX_COUNT = 2**31 - 1


def integer(name: str, value: Any, low: int = 0, high: int = MAX_COUNT) -> int:
    """An integer in [low, high] (Python or numpy int; bool and float are refused) as a Python
    int."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise ValueError(f"{name}: must be an integer >= {low}, got {value!r}")
    if value > high:
        raise ValueError(f"{name}: must be an integer <= {high}, got {value!r}")
    return int(value)


def in_open_interval(name: str, value: Any, low: float, high: float) -> float:
    """A number in the open interval (low, high) as a Python float."""
    a = real_array(name, value)
    if a.ndim != 0:
        raise ValueError(f"{name}: must be a number in ({low:g}, {high:g}), got {value!r}")
    v = float(a)
    if not (math.isfinite(v) and low < v < high):
        raise ValueError(f"{name}: must be in ({low:g}, {high:g}), got {value!r}")
    return v


def one_of(name: str, value: Any, options: Sequence[Any]) -> Any:
    """``value`` if it equals one of ``options`` (compared with ==; None is allowed as an option)."""
    if not any(value is o or (o is not None and isinstance(value, type(o)) and value == o) for o in options):
        choices = ", ".join(repr(o) for o in options[:-1]) + f" or {options[-1]!r}"
        raise ValueError(f"{name}: must be {choices}, got {value!r}")
    return value


def symmetric_matrix(
    name: str, value: Any, n: int, *, definite: bool = False, vector_is_diagonal: bool = False
) -> np.ndarray:
    """A symmetric positive semi-definite (n, n) matrix (positive definite with ``definite``)
    from a matrix or a scalar (times the identity); with ``vector_is_diagonal`` also from a
    (n,) diagonal. The matrix is returned as given (a new C-contiguous array), not symmetrised:
    symmetry is checked to a relative 1e-10, definiteness on its symmetric part."""
    a = float_array(name, value, copy=True)
    if a.ndim == 0:
        a = a * np.eye(n)
    elif vector_is_diagonal and a.shape == (n,):
        a = np.diag(a)
    if a.shape != (n, n):
        shapes = f"a scalar, shape ({n},) or ({n}, {n})" if vector_is_diagonal else f"a scalar or shape ({n}, {n})"
        raise ValueError(f"{name}: expected {shapes}, got {a.shape}")
    if n == 0:
        return np.ascontiguousarray(a)
    scale = max(1.0, float(np.abs(a).max()))
    if not np.allclose(a, a.T, rtol=1e-10, atol=1e-14 * scale):
        raise ValueError(f"{name}: must be symmetric")
    low = float(np.linalg.eigvalsh(0.5 * (a + a.T))[0])
    if definite and low <= 0:
        raise ValueError(f"{name}: must be positive definite")
    if not definite and low < -1e-12 * scale:
        raise ValueError(f"{name}: must be positive semi-definite")
    return np.ascontiguousarray(a)


def positive_diagonal(name: str, value: Any, n: int, *, allow_full: bool = True) -> np.ndarray:
    """The positive diagonal, shape (n,), of a diagonal covariance given as a scalar (times the
    identity), a (n,) vector or a (n, n) matrix. Off-diagonal entries of a matrix are refused
    unless ``allow_full``, which takes the diagonal of any matrix."""
    a = float_array(name, value)
    if a.ndim == 0:
        diag = np.full(n, float(a))
    elif a.shape == (n,):
        diag = a.copy()
    elif a.shape == (n, n):
        if not allow_full and np.any(a != np.diag(np.diag(a))):
            raise ValueError(f"{name}: only diagonal matrices are supported (the paper's Q0, R0 are diagonal)")
        diag = np.diag(a).copy()
    else:
        raise ValueError(f"{name}: expected a scalar, shape ({n},) or ({n}, {n}), got {a.shape}")
    if np.any(diag <= 0):
        raise ValueError(f"{name}: diagonal must be positive")
    return diag


def points(name: str, value: Any, nd: int, *, one_point: bool = False) -> np.ndarray:
    """Points as a C-contiguous float64 (k, nd) array of finite values of magnitude <= MAX_ABS;
    with ``one_point`` a 1-D value is one point."""
    a = value
    if not (type(a) is np.ndarray and a.dtype == np.float64 and a.flags.c_contiguous):
        a = np.ascontiguousarray(real_array(name, a))
    if one_point and a.ndim == 1:
        a = a.reshape(1, -1)
    if a.ndim != 2 or a.shape[1] != nd:
        raise ValueError(f"{name}: expected shape (k, {nd}), got {a.shape}")
    _check_values(name, a)
    return a


def training_set(D: Any, y: Any, y_ndim: int) -> Tuple[np.ndarray, np.ndarray]:
    """Training inputs D (N, n_d), N >= 2, n_d >= 1, and targets y, (N,) or (N, q) by ``y_ndim``,
    as finite C-contiguous float64 arrays of their own (a model can keep them); errors name D or y
    (MultiOutputGP's Y too: the targets are y throughout the documentation)."""
    D = float_array("D", D, 2, copy=True)
    y = float_array("y", y, y_ndim, copy=True)
    n = D.shape[0]
    if n < 2:
        raise ValueError(f"D: needs at least 2 training points, got {n}")
    if D.shape[1] < 1:
        raise ValueError("D: needs at least one input dimension")
    if y.shape[0] != n:
        raise ValueError(f"y: expected {n} rows (one per row of D), got {y.shape[0]}")
    if y_ndim == 2 and y.shape[1] < 1:
        raise ValueError("y: needs at least one output column")
    return D, y


def boolean(name: str, value: Any) -> bool:
    """True or False (a Python or numpy bool; other values, 0 and 1 included, are refused)."""
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name}: must be True or False, got {value!r}")
    return bool(value)


def random_state(name: str, value: Any) -> Any:
    """A seed `numpy.random.default_rng` accepts (None, an int >= 0, a sequence of them, a
    SeedSequence, BitGenerator or Generator), returned as given."""
    if isinstance(value, (bool, float, str, bytes)):
        raise ValueError(f"{name}: must be None, an integer >= 0 or a numpy Generator, got {value!r}")
    try:
        np.random.default_rng(value)
    except (TypeError, ValueError, OverflowError) as exc:
        raise ValueError(f"{name}: must be None, an integer >= 0 or a numpy Generator ({exc})") from None
    return value


def options(name: str, value: Any, spec: dict) -> dict:
    """A dict of keyword options (None is empty) whose keys are in ``spec``, as a new dict.

    ``spec`` maps each accepted key to the check of its value: "count" (an integer >= 1, or None
    with "count?"), "tol" (a finite number >= 0, at most MAX_ABS), "positive" (> 0), a tuple of
    allowed values, or None (any value: checked by the function it is passed to). Errors name
    ``name`` and the key ("solver_options: max_iter: must be an integer >= 1, got -1").
    """
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise ValueError(f"{name}: must be a dict or None, got {type(value).__name__}")
    out = {}
    for key, v in value.items():
        if key not in spec:
            known = ", ".join(sorted(spec))
            raise ValueError(f"{name}: unknown option {key!r} (accepted: {known})")
        kind = spec[key]
        try:
            if kind == "count" or (kind == "count?" and v is not None):
                v = integer(str(key), v, low=1)
            elif kind in ("tol", "positive"):
                v = positive_scalar(str(key), v, allow_zero=kind == "tol")
            elif isinstance(kind, tuple):
                v = one_of(str(key), v, kind)
        except ValueError as exc:  # (a MagnitudeError stays one)
            raise (MagnitudeError if isinstance(exc, MagnitudeError) else ValueError)(
                f"{name}: {exc}") from None
        out[key] = v
    return out
