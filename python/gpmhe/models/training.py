"""Regression data for `LearnedModel.from_trajectories` from measured logs: trajectories of
different lengths, with or without inputs, with missing samples (NaN entries drop the rows that
need them) and optional subsampling; and the nominal model whose residual the GPs learn.
"""

from __future__ import annotations

import numpy as np

from gpmhe._validation import float_array, integer

#: The GP settings `LearnedModel.from_trajectories` uses unless told otherwise (the user guide,
#: *Learned models*, gives the measurements behind them).
LEARNED_DEFAULTS = dict(mean="linear", normalize=True, hyperprior="default")

#: Its settings with a nominal model (f_nominal or h_nominal): the nominal model is the prior
#: mean, and the residual is assumed small next to the noise and smooth over the operating range
#: (`gpmhe.gp.priors`, ``RESIDUAL_HYPERPRIOR``).
RESIDUAL_DEFAULTS = dict(mean="zero", normalize=True, hyperprior="residual")


def first_trajectory(name, value):
    """The first trajectory of a list of them (or the one (T+1, k) array given) as a float64
    array, for its number of columns."""
    try:
        first = value if isinstance(value, np.ndarray) and value.ndim == 2 else value[0]
        a = np.asarray(first, dtype=np.float64)
    except (TypeError, ValueError, IndexError, KeyError) as exc:
        raise ValueError(f"{name}: must be a list of trajectories (2-D arrays) ({exc})") from None
    if a.ndim not in (1, 2):
        raise ValueError(f"{name}: must be a list of trajectories (2-D arrays), got shape {a.shape} first")
    return a


def _as_lists(states, outputs, inputs):
    if isinstance(states, np.ndarray) and states.ndim == 2:
        states, outputs = [states], [outputs]
        inputs = None if inputs is None else [inputs]
    states, outputs = list(states), list(outputs)
    if len(states) == 0 or len(outputs) != len(states):
        raise ValueError(f"outputs, states: need one output trajectory per state trajectory (at least "
                         f"one), got {len(outputs)} and {len(states)}")
    if inputs is not None:
        inputs = list(inputs)
        if len(inputs) != len(states):
            raise ValueError("inputs: need one input trajectory per state trajectory")
    return states, outputs, inputs


def _one(i, X, Y, U, n, p, m):
    """(X, Y, U) of trajectory i checked: (T+1, n), (T+1, p), (T+1 or T, m)."""
    X = float_array(f"states[{i}]", X, missing=True)
    Y = float_array(f"outputs[{i}]", Y, missing=True)
    if Y.ndim == 1:
        Y = Y[:, None]
    if X.ndim != 2 or X.shape[0] < 2:
        raise ValueError(f"states[{i}]: must be a (T+1, n) array with T >= 1")
    if X.shape[1] != n:
        raise ValueError(f"states[{i}]: has {X.shape[1]} columns, states[0] has {n}")
    if Y.shape != (X.shape[0], p):
        raise ValueError(f"outputs[{i}]: must be a ({X.shape[0]}, {p}) array")
    T = X.shape[0] - 1
    if m:
        U = float_array(f"inputs[{i}]", U, missing=True)
        if U.ndim == 1:
            U = U[:, None]
        if U.shape not in ((T + 1, m), (T, m)):
            raise ValueError(f"inputs[{i}]: must be a ({T + 1}, {m}) or ({T}, {m}) array")
    else:
        U = np.zeros((T + 1, 0))
    return X, Y, U


def regression_data(states, outputs, inputs, n, p, m):
    """(D_f, X_next, X_now, D_h, Y) over all trajectories. A transition is used where x(t), u(t)
    and x(t+1) are all finite, an output sample where x(t), u(t) and every entry of y(t) are."""
    states, outputs, inputs = _as_lists(states, outputs, inputs)
    Df, Xn, Xc, Dh, Yh = [], [], [], [], []
    for i, (X, Y) in enumerate(zip(states, outputs)):
        X, Y, U = _one(i, X, Y, None if inputs is None else inputs[i], n, p, m)
        T, rows = X.shape[0] - 1, U.shape[0]  # outputs usable where u is known
        d = np.hstack([X[:rows], U])
        keep_f = np.all(np.isfinite(d[:T]), axis=1) & np.all(np.isfinite(X[1:]), axis=1)
        keep_h = np.all(np.isfinite(d), axis=1) & np.all(np.isfinite(Y[:rows]), axis=1)
        Df.append(d[:T][keep_f])
        Xn.append(X[1:][keep_f])
        Xc.append(X[:T][keep_f])
        Dh.append(d[keep_h])
        Yh.append(Y[:rows][keep_h])
    out = tuple(np.vstack(a) for a in (Df, Xn, Xc, Dh, Yh))
    if out[0].shape[0] < 2:
        raise ValueError("states: fewer than 2 complete transitions (x(t), u(t), x(t+1) all finite)")
    if p and out[3].shape[0] < 2:
        raise ValueError("outputs: fewer than 2 complete output samples (x(t), u(t), y(t) all finite)")
    return out


def subsample(max_points, *arrays):
    """The rows of ``arrays`` (same length N) at max_points evenly spaced indices, or all of them
    when N <= max_points (or max_points is None)."""
    if max_points is None or arrays[0].shape[0] <= max_points:
        return arrays
    idx = np.unique(np.linspace(0, arrays[0].shape[0] - 1, max_points).round().astype(int))
    return tuple(a[idx] for a in arrays)


def check_max_points(value):
    return None if value is None else integer("max_points", value, low=2)


# ----------------------------------------------------------------------------- nominal model


class Zero:
    """The zero function of ``size`` outputs (and its zero Jacobian on n states), per point or
    vectorised: the nominal f or h a user did not give. Picklable."""

    def __init__(self, size, n, vectorized, jacobian=False):
        self.size, self.n, self.vectorized, self.jacobian = size, n, vectorized, jacobian

    def __call__(self, x, u):
        shape = (self.size, self.n) if self.jacobian else (self.size,)
        return np.zeros((x.shape[0],) + shape if self.vectorized else shape)


def nominal_model(f_nominal, h_nominal, n, p, m, options):
    """The KnownModel of the nominal f0, h0 (zero where None), or None when both are None."""
    from gpmhe.models.known import KnownModel

    if f_nominal is None and h_nominal is None:
        if options:
            raise ValueError("nominal_options: given without f_nominal or h_nominal")
        return None
    options = dict(options or {})
    unknown = set(options) - {"f_jacobian", "h_jacobian", "fd_step", "vectorized"}
    if unknown:
        raise ValueError(f"nominal_options: unknown keys {sorted(unknown)} (expected f_jacobian, "
                         "h_jacobian, fd_step, vectorized)")
    vec = options.get("vectorized", False)
    if f_nominal is None:
        f_nominal, options["f_jacobian"] = Zero(n, n, vec), Zero(n, n, vec, jacobian=True)
    if h_nominal is None:
        h_nominal, options["h_jacobian"] = Zero(p, n, vec), Zero(p, n, vec, jacobian=True)
    return KnownModel(f_nominal, h_nominal, n, p, m, **options)
