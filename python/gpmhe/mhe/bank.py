"""EstimatorBank: n independent GPMHE estimators on one model, updated together.

This module validates the bank's settings and every sample's input, holds the public attributes
(one row per estimator) and builds a standalone `GPMHE` from any estimator (``bank[i]``). The
estimators themselves live in one Rust object (`gpmhe._core.EstimatorBank`, rust/src/mhe/bank.rs
through rust/src/python/bank.rs): one ``update(U, Y)`` is one Rust call that updates all of them,
in parallel on every core for a `LearnedModel` or a CasADi model compiled in the core.
"""

from __future__ import annotations

import dataclasses
import operator
import warnings

import numpy as np

from gpmhe import _core
from gpmhe._filterpy import (BANK_NAMES, REQUIRED, missing_attribute, one_argument_update,
                             refused_setting, renamed, required, window_attribute)
from gpmhe._threads import exclusive
from gpmhe._validation import (MAX_ABS, MagnitudeError, SettingsWarning, box, float_array, integer,
                               output_sample, real_array, within_limits)
from gpmhe.mhe.estimator import GPMHE, NO_NOISE_INFORMATION, check_interval
from gpmhe.mhe.settings import covariance, sample_covariance

__all__ = ["EstimatorBank"]

#: The keyword settings of GPMHE the bank takes (x0 is its own argument): all of them.
_SETTINGS = ("horizon", "eta", "P2", "P0", "Q0", "R0", "x_bounds", "form", "solver",
             "solver_options", "arrival_mean", "arrival_weight", "loss", "loss_scale", "p0",
             "P_p0", "p_bounds", "p_drift")

#: The parameter settings (a model with parameters), the same for every estimator.
_PARAMETERS = ("p0", "P_p0", "p_bounds", "p_drift")

#: The most estimators in one bank (a guard against a mistyped n, not a limit of the method).
_MAX_ESTIMATORS = 10_000_000


def _per_estimator(name, value, k, d):
    """Q0, R0 or a sample's R as (k, d, d) matrices: given once for all estimators (as GPMHE takes
    it: a scalar, the diagonal (d,) or the matrix (d, d)) or once per estimator ((k,) scalars when
    k != d, (k, d) diagonals when k != d, or (k, d, d) matrices); each symmetric positive
    definite."""
    a = float_array(name, 1.0 if value is None else value)
    if a.ndim == 0 or a.shape == (d,) or a.shape == (d, d):
        return np.tile(covariance(name, a, d), (k, 1, 1))
    if a.shape in ((k,), (k, d), (k, d, d)):
        return np.array([covariance(f"{name}[{i}]", a[i], d) for i in range(k)]).reshape(k, d, d)
    raise ValueError(f"{name}: expected one value (a scalar, shape ({d},) or ({d}, {d})) or one "
                     f"per estimator (shape ({k},), ({k}, {d}) or ({k}, {d}, {d})), got {a.shape}")


def _read_only(a):
    a = np.array(a, dtype=np.float64)
    a.flags.writeable = False
    return a


def _rows(name, value, k, d):
    """A (d,) vector for all estimators or (k, d) rows, as a new (k, d) float64 array."""
    a = real_array(name, value, copy=True)
    if a.shape == (d,):
        a = np.tile(a, (k, 1))
    elif a.shape != (k, d):
        raise ValueError(f"{name}: expected shape ({d},) or ({k}, {d}), got {a.shape}")
    return np.ascontiguousarray(a)


#: The settings a user may set between updates: GPMHE's weights.
_SETTABLE = ("P0", "P2", "Q0", "R0", "eta")

#: Names users of GPMHE or of other filters try to set, and what to use instead.
_DID_YOU_MEAN = {"R": "R0 (or update's R, for one sample)", "Q": "Q0",
                 "P": "P0 (the arrival covariance)",
                 "M": "horizon (fixed: build a new EstimatorBank)",
                 "N": "horizon (fixed: build a new EstimatorBank)"}


def _not_taken(key):
    """The ValueError message for a keyword of the bank's constructor it does not take."""
    return f"{key}: not a setting of EstimatorBank (it takes x0 and {', '.join(_SETTINGS)})"


def _build(model, x0, lb, ub, q0, r0, common):
    """A `GPMHE` with estimator 0's settings (which validates the common settings) and the core
    bank made from it as its template: row i of the arrays for estimator i, on the core's state
    [x; p̃] when the model has parameters (`MHESettings`)."""
    k, p = len(x0), model.dim_y
    template = GPMHE(model, x0=x0[0], Q0=q0[0], R0=r0[0] if p else None,
                     x_bounds=(lb[0], ub[0]), **common)
    settings = template._settings
    scaling = settings.scaling
    bounds = [settings.scaling.bounds(lb[i], ub[i], settings.p_bounds) for i in range(k)]
    rows = dict(
        x0=np.array([settings.core_state(x) for x in x0]),
        lower=np.array([b[0] for b in bounds]), upper=np.array([b[1] for b in bounds]),
        q0=np.array([scaling.process_noise(q, settings.p_drift).reshape(-1) for q in q0]),
        r0=np.ascontiguousarray(r0.reshape(k, p * p)))
    return template, _core.EstimatorBank(template._core, *rows.values())


class EstimatorBank:
    """n independent `GPMHE` estimators on one model, updated together with one call per sample.

    Every estimator has the same model, dimensions and settings (those of `GPMHE`) except its
    initial estimate ``x0``, its state box ``x_bounds`` and its weights ``Q0``, ``R0``, which may
    be given once for all or once per estimator. With a model's unknown parameters p, each
    estimator estimates its own p from the same prior (``p0``, ``P_p0``, ``p_bounds``,
    ``p_drift``), e.g. one inertia per machine of a fleet. ``update(U, Y)`` takes one row of
    inputs and outputs per estimator and updates all of them in one call into the Rust core: with a
    `LearnedModel` or a CasADi model compiled in the core (`KnownModel.from_casadi`,
    `KnownModel.from_ode` with ``native=True``, the default) the estimators are solved in
    parallel on all cores (rayon, without the GIL); with a `KnownModel` whose functions are
    Python, they run one after another in that call (with the GIL). Each estimator gives, bit
    for bit, what a separate `GPMHE` with its settings gives on its rows of data: the bank is a
    faster way to run many of them, e.g. for a Monte Carlo study or one estimator per unit of a
    fleet.

    Parameters
    ----------
    model : LearnedModel or KnownModel
        The model of every estimator. A `LearnedModel`'s GPs are shared by the estimators, not
        copied.
    n : int
        The number of estimators, >= 1.
    x0 : array_like of shape (dim_x,) or (n, dim_x)
        The initial estimates x̂(0): one for all estimators or one row per estimator; each must
        lie in its ``x_bounds``.
    **gpmhe_options
        The settings of `GPMHE`: ``horizon``, ``eta``, ``P2`` or ``P0``, ``form``,
        ``solver_options``, ``arrival_mean``, ``arrival_weight``, ``loss``, ``loss_scale`` and
        the parameter settings ``p0``, ``P_p0``, ``p_bounds``, ``p_drift`` as there (the same for
        all estimators), and

        * ``Q0``, ``R0``: one value as `GPMHE` takes it (a scalar, the diagonal or a symmetric
          positive definite matrix) or one per estimator: shape (n,) scalars, (n, dim)
          diagonals or (n, dim, dim) matrices (where n equals the dimension, a 1-D or square
          2-D value is read as one value for all);
        * ``x_bounds``: a pair (lower, upper), each of shape (dim_x,) (one box for all) or
          (n, dim_x) (one per estimator);
        * ``solver``: only "gauss-newton" (the Rust solver) is supported.

    Attributes
    ----------
    x : ndarray of shape (n, dim_x)
        Row i is estimator i's current estimate (`GPMHE.x`).
    P : ndarray of shape (n, dim_x, dim_x)
        The covariance estimates (`GPMHE.P`).
    x_arrival : ndarray of shape (n, dim_x)
        The arrival priors of the last windows (`GPMHE.x_arrival`; ``x_prior`` is a deprecated
        alias, removed in the next release).
    x_window : ndarray of shape (n, M_t + 1, dim_x)
        The last windows' optimal trajectories.
    cost : ndarray of shape (n,)
        The last windows' optimal costs.
    success : ndarray of shape (n,), bool
        Whether each window's solver converged.
    nit, nfev : ndarray of shape (n,), int
        Iterations and window evaluations of each estimator's last update.
    projected_gradient : ndarray of shape (n,)
        Each solver's final projected gradient.
    t : int
        Number of updates since construction.
    p : ndarray of shape (n, dim_p)
        Each estimator's estimate of the parameters (`GPMHE.p`; no columns without).
    P_p : ndarray of shape (n, dim_p, dim_p)
        Their covariances (`GPMHE.P_p`).
    threads : int
        The number of threads an update runs on (1 for a model of Python functions).
    Q0, R0 : ndarray of shape (n, dim_x, dim_x), (n, dim_y, dim_y)
        Each estimator's Q0 and R0; settable between updates (see Notes).
    eta : float
        The discount factor η of every estimator; settable.
    P2, P0 : ndarray of shape (dim_x, dim_x)
        The arrival weight of every estimator and its inverse, the arrival covariance;
        settable (either).
    model, horizon, form, solver, solver_options, arrival_mean, arrival_weight, loss, loss_scale
        The common settings, read-only.
    p0, P_p0, p_bounds, p_drift
        The parameter settings (a model with parameters only), read-only.
    x0 : ndarray of shape (n, dim_x)
        Each estimator's x̂(0), read-only.
    x_bounds : tuple of two ndarrays of shape (n, dim_x)
        Each estimator's box (lower, upper), read-only.
    dim_x, dim_y, dim_u, dim_p : int
        The model's dimensions.

    Raises
    ------
    ValueError
        If a setting is invalid (as for `GPMHE`, naming the argument and, for a per-estimator
        value, the estimator), a keyword is not among the settings above, ``solver`` is not
        "gauss-newton", or ``p0`` is missing for a model with parameters (one ``p0`` for all:
        the scale of p̃ in the window comes from it).

    See Also
    --------
    GPMHE : One estimator.

    Notes
    -----
    ``Q0``, ``R0``, ``P2`` (or ``P0``) and ``eta`` can be set between updates, as `GPMHE`'s
    weights: the new value is validated as in the constructor (``Q0`` and ``R0`` once for all or
    once per estimator), and every estimator uses it from the next update on exactly as a
    `GPMHE` whose weight was set; nothing else changes (only ``P2``/``P0`` restarts the "ekf"
    arrival weight). A refused value raises ValueError and leaves the bank as it was. Setting
    any other name raises AttributeError: the other settings are fixed at construction (build a
    new bank). Setting a weight builds a new core with it and moves every estimator's state
    over, in a time that grows with n.

    A solver failure of one estimator (its ``success`` False) does not stop the others; one
    `RuntimeWarning` per update names the estimators that failed. An error (bad input, an
    interrupt, or an exception raised by a `KnownModel` function) leaves every estimator as it
    was: the estimators' updates are recorded only once every one has succeeded.

    Examples
    --------
    Three estimators of the batch reactor from different initial estimates, each with its own
    measurements:

    >>> import numpy as np
    >>> from gpmhe import EstimatorBank, KnownModel
    >>> from gpmhe.systems import batch_reactor as br
    >>> model = KnownModel(br.f, br.h, dim_x=2, dim_y=1)
    >>> x0 = [[3.0, 1.0], [1.0, 3.0], [2.0, 2.0]]
    >>> bank = EstimatorBank(model, 3, x0, horizon=5, Q0=1e-3, R0=1e-2, x_bounds=br.X_BOUNDS)
    >>> runs = [br.simulate(br.X_TRUE0, 10, np.random.default_rng(s)) for s in range(3)]
    >>> for t in range(10):
    ...     x_hat = bank.update(None, [y[t] for _, y in runs])
    >>> bank.x.shape, bank.t, bool(bank.success.all())
    ((3, 2), 10, True)
    >>> len(bank), bank[1].t
    (3, 10)

    The weights can be set between updates (once for all or once per estimator); the other
    settings are fixed:

    >>> bank.R0 = [2e-2, 1e-2, 5e-3]                  # one R0 per estimator
    >>> bank.R0.ravel()
    array([0.02 , 0.01 , 0.005])
    >>> bank.horizon = 10
    Traceback (most recent call last):
        ...
    AttributeError: EstimatorBank.horizon is read-only; the settable attributes are P0, P2, Q0, R0, eta ...
    """

    def __init__(self, model, n, x0, **gpmhe_options):
        for key in gpmhe_options:
            if key not in _SETTINGS:
                raise ValueError(_not_taken(key))
        from gpmhe.models import KnownModel, LearnedModel

        if not isinstance(model, (KnownModel, LearnedModel)):
            raise ValueError("model: must be a gpmhe.LearnedModel or gpmhe.KnownModel, got "
                             f"{type(model).__name__}")
        k = integer("n", n, low=1, high=_MAX_ESTIMATORS)
        solver = gpmhe_options.get("solver", "gauss-newton")
        if not (isinstance(solver, str) and solver == "gauss-newton"):
            raise ValueError(f"solver: the bank runs only 'gauss-newton', got {solver!r}")
        d, p = model.dim_x, model.dim_y
        opts = dict(gpmhe_options)
        q0 = _per_estimator("Q0", opts.pop("Q0", None), k, d)
        r0 = _per_estimator("R0", opts.pop("R0", None), k, p)
        lb, ub = box("x_bounds", opts.pop("x_bounds", None), d, rows=k)
        x0 = _rows("x0", float_array("x0", x0), k, d)
        bad = np.flatnonzero(np.any((x0 < lb) | (x0 > ub), axis=1))
        if bad.size:
            raise ValueError(f"x0: must lie inside x_bounds (estimator {bad[0]})")
        if all(gpmhe_options.get(w) is None for w in ("Q0", "R0", "P2", "P0")):
            warnings.warn(NO_NOISE_INFORMATION, SettingsWarning, stacklevel=2)
        template, core = _build(model, x0, lb, ub, q0, r0, opts)
        self._adopt(template, core, model, x0, q0, r0, (lb, ub))

    def _adopt(self, template, core, model, x0, q0, r0, x_bounds):
        """Takes the core bank and the common settings of its `template` (a `GPMHE`)."""
        s = template._settings
        # (Set through __dict__: the bank's own __setattr__ is for its users.)
        self.__dict__.update(
            _core=core, _settings=s, model=model, _dt=template._dt, dim_x=model.dim_x,
            dim_y=model.dim_y, dim_u=model.dim_u, dim_p=s.dims[3], horizon=s.horizon,
            eta=s.eta, form=s.form, P2=s.P2, solver_options=template.solver_options,
            solver="gauss-newton", arrival_mean=s.arrival_mean, arrival_weight=s.arrival_weight,
            loss=s.loss, loss_scale=s.loss_scale if s.loss != "squared" else None,
            x0=x0, Q0=_read_only(q0), R0=_read_only(r0), x_bounds=x_bounds)
        if self.dim_p:
            self.__dict__.update(p0=s.p0, P_p0=s.P_p0, p_bounds=s.p_bounds, p_drift=s.p_drift)

    def _common(self, **changes):
        """The settings every estimator shares, as `GPMHE` takes them, with ``changes``."""
        common = dict(horizon=self.horizon, eta=self.eta, P2=self.P2, form=self.form,
                      solver="gauss-newton", solver_options=self.solver_options,
                      arrival_mean=self.arrival_mean, arrival_weight=self.arrival_weight,
                      loss=self.loss, loss_scale=self.loss_scale)
        if self.dim_p:
            common.update({name: getattr(self, name) for name in _PARAMETERS})
        common.update(changes)
        return common

    @property
    def P0(self):  # noqa: N802
        """The arrival covariance P0 = P2⁻¹ of every estimator (dim_x, dim_x); settable."""
        return np.linalg.inv(self.P2)

    # ---- the estimates and what the last update reported: read from the core ---------------
    # (The core records an update of every estimator in one step, or none.)
    @property
    def t(self):
        """Number of updates since construction."""
        return self._core.t

    # With parameters the core's state is [x; p̃] (`MHESettings`): x is its first dim_x values.
    @property
    def x(self):
        """The estimates (n, dim_x)."""
        return np.ascontiguousarray(self._core.x[:, :self.dim_x])

    @property
    def x_arrival(self):
        """The last arrival priors (n, dim_x) (``x_prior`` is their deprecated alias)."""
        return np.ascontiguousarray(self._core.x_prior[:, :self.dim_x])

    @window_attribute  # (not a property: see gpmhe/_filterpy.py)
    def x_window(self):
        """The last windows' optimal trajectories (n, M_t + 1, dim_x)."""
        return np.ascontiguousarray(self._core.x_window[:, :, :self.dim_x])

    @property
    def P(self):  # noqa: N802
        """The covariance estimates (n, dim_x, dim_x)."""
        return np.ascontiguousarray(self._core.covariance[:, :self.dim_x, :self.dim_x])

    @property
    def p(self):
        """The estimates of the parameters (n, dim_p) (`GPMHE.p`; no columns without)."""
        return self._settings.scaling.parameters(self._core.x)

    @property
    def P_p(self):  # noqa: N802
        """The covariances of ``p`` (n, dim_p, dim_p) (`GPMHE.P_p`)."""
        return self._settings.scaling.parameter_covariance(self._core.covariance)

    @property
    def cost(self):
        """The last windows' optimal costs (n,)."""
        return self._core.optimal_cost

    @property
    def success(self):
        """Whether each solver converged (n,)."""
        return self._core.success

    @property
    def nit(self):
        """Each solver's iterations (n,)."""
        return self._core.nit

    @property
    def nfev(self):
        """Each update's window evaluations (n,)."""
        return self._core.nfev

    @property
    def projected_gradient(self):
        """Each solver's final projected gradient (n,)."""
        return self._core.projected_gradient


    def __len__(self):
        return len(self._core)

    def __getattr__(self, name):  # only for names the class and the instance do not have
        new = renamed(type(self), name)
        if new is None:
            raise missing_attribute(self, name, BANK_NAMES)
        return getattr(self, new)

    def __setattr__(self, name, value):
        name = renamed(type(self), name) or name
        if name in _SETTABLE:
            self._set_weight(name, value)
            return
        if name.startswith("_"):  # the class's own (and tests') private attributes
            object.__setattr__(self, name, value)
            return
        raise refused_setting(self, name, _SETTABLE, _DID_YOU_MEAN,
                              "the other settings are fixed at construction: build a new "
                              "EstimatorBank; the estimates change only through update")

    @exclusive  # not while an update runs (gpmhe/_threads.py)
    def _set_weight(self, name, value):
        """Set weight ``name`` of every estimator, validated as in the constructor, from the next
        update on, as `GPMHE`'s setter does (only P2 or P0 restarts the arrival weight). The
        core bank has no setter: a new one is built with the new weight and every estimator's
        state (its history and arrival weight) moved into it; the bank changes only once that is
        done."""
        k, d, p = len(self), self.dim_x, self.dim_y
        q0, r0, common = self.Q0, self.R0, self._common()
        if name == "Q0":
            q0 = _per_estimator("Q0", value, k, d)
        elif name == "R0":
            r0 = _per_estimator("R0", value, k, p)
        elif name == "P0":
            del common["P2"]
            common["P0"] = value
        else:
            common[name] = value
        lb, ub = self.x_bounds
        template, core = _build(self.model, self.x0, lb, ub, q0, r0, common)
        restart = name in ("P0", "P2")  # a new P2 is the next window's arrival weight
        arrival = template._settings.core_weights(("P2",))["p2_sqrt"] if restart else None
        for i in range(k):
            state = self._core.member_state(i)
            if arrival is not None:
                state["arrival_sqrt"] = arrival
            core.set_member_state(i, state)
        self._adopt(template, core, self.model, self.x0, q0, r0, self.x_bounds)

    @property
    def threads(self):
        """The number of threads an update runs on (1 for a model of Python functions)."""
        return _core.EstimatorBank.threads() if self._core.parallel else 1

    # ----------------------------------------------------------------------------------------
    def _check_sample(self, U, Y):
        k, m, p = len(self), self.dim_u, self.dim_y
        if U is None:
            if m:
                raise ValueError(f"U: required (dim_u = {m})")
            U = np.zeros((k, 0))
        else:
            U = float_array("U", U)
            if U.shape != (k, m):
                raise ValueError(f"U: expected shape ({k}, {m}), got {U.shape}")
        if Y is None:
            return U, np.zeros((k, p)), np.zeros(k, dtype=bool)
        Y = real_array("Y", Y, copy=True)
        if Y.shape != (k, p):
            raise ValueError(f"Y: expected shape ({k}, {p}), got {Y.shape}")
        missing = np.isnan(Y)
        present = ~missing.any(axis=1)
        Y[missing] = 0.0
        if not within_limits(Y):
            if not np.all(np.isfinite(Y)):
                raise ValueError("Y: contains inf (NaN marks a missing value)")
            raise MagnitudeError(f"Y: contains a value of magnitude > {MAX_ABS:g} (its square "
                                 "overflows)")
        Y[~present] = 0.0
        return U, Y, present

    @required
    def update(self, U, Y=REQUIRED, R=None, dt=None):
        """Add one sample for every estimator, solve their windows and update the estimates.

        Row i of ``U`` and ``Y`` is estimator i's (u(t), y(t)) (`GPMHE.update`). All estimators
        are updated in one call into the Rust core: in parallel on all cores for a
        `LearnedModel` or a compiled CasADi model, one after another for Python functions.

        Parameters
        ----------
        U : array_like of shape (n, dim_u) or None
            The inputs; None when the model has no input (dim_u = 0).
        Y : array_like of shape (n, dim_y) or None
            The outputs. A NaN marks a missing value: a row with any NaN means estimator i has
            no measurement at this step (as ``GPMHE.update(u, None)``; the row's other values are
            not used). None: no estimator has a measurement.
        R : float or array_like, or None, default None
            This sample's output-noise covariance (`GPMHE.update`'s ``R``): one for all
            estimators (a scalar, the diagonal (dim_y,) or the matrix) or one per estimator
            ((n,) scalars, (n, dim_y) diagonals or (n, dim_y, dim_y) matrices), as ``R0``.
            None: each estimator's ``R0``.
        dt : float, array_like of shape (n,), or None, default None
            The time since the previous sample (`GPMHE.update`'s ``dt``), one for all estimators
            or one each; only for a model with a time step. None: the model's ``dt``.

        Returns
        -------
        ndarray of shape (n, dim_x)
            The new estimates ``x``.

        Raises
        ------
        ValueError
            On bad input (shape, inf, a required U missing) or bad output of a `KnownModel`
            function; every estimator is then unchanged.
        Exception
            Any exception a `KnownModel` function raises, as for `GPMHE.update` (every
            estimator unchanged).
        RuntimeError
            If the bank is already being updated (from another thread).
        TypeError
            If called with one argument: the inputs come first, ``update(None, Y)`` when the
            model has none.

        Warns
        -----
        RuntimeWarning
            Once per update if any estimator's window solver did not converge, naming them.
            The others are updated as usual.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import EstimatorBank, KnownModel
        >>> model = KnownModel(lambda x, u: x + u, lambda x, u: x, dim_x=1, dim_y=1, dim_u=1)
        >>> bank = EstimatorBank(model, 2, [0.0], horizon=3, form="filtering")
        >>> print(np.round(bank.update([[1.0], [1.0]], [[2.0], [np.nan]]), 3))
        [[1.]
         [0.]]
        """
        if Y is REQUIRED:
            raise one_argument_update(type(self), "U", "Y")
        U, Y, present = self._check_sample(U, Y)
        k, p = len(self), self.dim_y
        R = None if R is None else _per_estimator("R", R, k, p).reshape(k, p * p)
        self._step(U, Y, present, R, self._intervals(dt))
        return self.x

    def reset(self, x0, p0=None):
        """Restart every estimator from a new initial estimate, as `GPMHE.reset` does for each.

        Every estimator forgets its history (``t`` = 0): x̂(0) = its row of ``x0``, ``P`` =
        ``P0``, p = its row of ``p0`` (the parameters' scale stays that of the constructor's
        ``p0``) and ``P_p`` = ``P_p0``. The settings and the weights set since construction are
        kept. Each estimator then continues as a `GPMHE` reset the same way.

        Parameters
        ----------
        x0 : array_like of shape (dim_x,) or (n, dim_x)
            The new initial estimates, one for all or one row per estimator; each must lie in
            its estimator's ``x_bounds``.
        p0 : array_like of shape (dim_p,) or (n, dim_p), or None, default None
            New parameter guesses, one for all or one row per estimator, inside ``p_bounds``
            (a model with parameters only); None: the constructor's ``p0``.

        Raises
        ------
        ValueError
            If ``x0`` or ``p0`` has the wrong shape, is not finite or lies outside its bounds
            (naming the estimator); no estimator changes.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import EstimatorBank, KnownModel
        >>> model = KnownModel(lambda x, u: 0.9 * x, lambda x, u: x, dim_x=1, dim_y=1)
        >>> bank = EstimatorBank(model, 3, [0.0], horizon=3, Q0=0.1, R0=0.1)
        >>> _ = bank.update(None, [[1.0], [1.0], [1.0]])
        >>> bank.reset([[1.0], [2.0], [3.0]])
        >>> bank.t, bank.x.ravel()
        (0, array([1., 2., 3.]))
        """
        k = len(self)
        x0 = _rows("x0", float_array("x0", x0), k, self.dim_x)
        if p0 is None:
            p0 = [None] * k
        elif not self.dim_p:
            raise ValueError("p0: the model has no parameters (dim_p = 0)")
        else:
            p0 = _rows("p0", float_array("p0", p0), k, self.dim_p)
        lb, ub = self.x_bounds
        core = []
        for i in range(k):
            settings = dataclasses.replace(self._settings, x_bounds=(lb[i], ub[i]))
            try:
                x, p = settings.check_state(x0[i], p0[i])
            except ValueError as e:
                raise ValueError(f"{e} (estimator {i})") from None
            core.append(settings.core_state(x, p))
        self._reset(list(range(k)), np.array(core))

    @exclusive
    def _reset(self, indices, x0):
        self._core.reset(indices, x0)

    def _intervals(self, dt):
        """``dt`` checked as one interval per estimator (n,), or None."""
        if dt is None:
            return None
        values = np.ravel(float_array("dt", dt))
        if values.size == 1:
            values = np.full(len(self), values[0])
        if values.size != len(self):
            raise ValueError(f"dt: expected a number or {len(self)} values, got {values.size}")
        return np.array([check_interval(v, self._dt, self.form, self.horizon) for v in values])

    def add_delayed(self, i, y, age, R=None):
        """Add a late output for estimator i, as `GPMHE.add_delayed` (used from the next
        `update` on).

        Parameters
        ----------
        i : int
            The estimator.
        y : array_like of shape (dim_y,)
            The output, NaN for channels not in it.
        age : int
            Steps before the newest output it was measured, 1 <= age <= ``max_delay``.
        R : float, array_like of shape (dim_y,) or (dim_y, dim_y), or None, default None
            Its covariance (None: estimator i's ``R0``).

        Raises
        ------
        ValueError
            On bad input (as `GPMHE.add_delayed`); the bank is then unchanged.
        IndexError
            If there is no estimator i.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import EstimatorBank, KnownModel
        >>> model = KnownModel(lambda x, u: x, lambda x, u: x, dim_x=1, dim_y=1)
        >>> bank = EstimatorBank(model, 2, [0.0], horizon=4, form="filtering")
        >>> for t in range(3):
        ...     _ = bank.update(None, [[1.0], [np.nan]])  # estimator 1 measures nothing
        >>> bank.add_delayed(1, [1.0], age=1)
        >>> print(np.round(bank.update(None, [[1.0], [np.nan]]), 3))  # estimator 1 was at 0
        [[0.932]
         [0.698]]
        """
        i = self._index(i)
        y, present = output_sample("y", y, self.dim_y)
        if not present:
            raise ValueError("y: has no measured channel (all NaN)")
        age = integer("age", age, low=1)
        r = None if R is None else sample_covariance(R, self.dim_y)
        self._add_delayed(i, y, age, r)

    @exclusive
    def _add_delayed(self, i, y, age, r):
        self._core.add_delayed(i, y, age, r)

    @property
    def max_delay(self):
        """The largest ``age`` `add_delayed` accepts now (the same for every estimator)."""
        return self._core.max_delay

    @exclusive  # one update at a time per bank (gpmhe/_threads.py)
    def _step(self, U, Y, present, R=None, dt=None):
        if self._dt is not None:  # the interval as the last input, a placeholder until the next
            U = np.column_stack([U, np.full(len(U), self._dt)])
        u_last = None
        if dt is not None and self.t > 0:
            u_last = np.array(self._core.last_inputs)
            u_last[:, -1] = dt
        self._core.update(U, Y, present, R, u_last)
        failed = np.flatnonzero(~self.success)
        if failed.size:
            shown = ", ".join(map(str, failed[:20])) + (", ..." if failed.size > 20 else "")
            warnings.warn(f"EstimatorBank: the window solver did not converge at t={self.t - 1} "
                          f"for {failed.size} estimator(s): {shown}; each keeps the better of its "
                          f"last iterate and its warm start", RuntimeWarning, stacklevel=4)

    # ----------------------------------------------------------------------------------------
    def _gpmhe(self, i):
        """A GPMHE with estimator i's settings (and a fresh history)."""
        lb, ub = self.x_bounds
        return GPMHE(self.model, x0=self.x0[i], Q0=self.Q0[i],
                     R0=self.R0[i] if self.dim_y else None, x_bounds=(lb[i], ub[i]),
                     **self._common())

    def _index(self, i):
        """Estimator i's position (negative i counts from the end); IndexError if none."""
        k = len(self)
        i = operator.index(i)
        if not -k <= i < k:
            raise IndexError(f"i: the bank has {k} estimators, got {i}")
        return i % k

    def __getitem__(self, i):
        """Estimator i as a standalone `GPMHE`: an independent copy with its settings, history
        and attributes, which continues exactly (bit for bit) as estimator i would."""
        i = self._index(i)
        mhe = self._gpmhe(i)
        mhe._core.__setstate__(self._core.member_state(i))  # the history and the last report
        return mhe

    # ---- copies and pickles -------------------------------------------------------------------
    def __getstate__(self):
        """The settings, the attributes and every estimator's core state (pickling needs a
        picklable model, as for `GPMHE`)."""
        # Q0, R0 as (n, dim, dim) matrices: unambiguous also where n equals the dimension.
        settings = dict(self._common(), Q0=self.Q0, R0=self.R0 if self.dim_y else None,
                        x_bounds=self.x_bounds)
        return dict(model=self.model, n=len(self), x0=self.x0, settings=settings,
                    cores=[self._core.member_state(i) for i in range(len(self))])

    def __setstate__(self, state):
        self.__init__(state["model"], state["n"], state["x0"], **state["settings"])
        for i, core in enumerate(state["cores"]):
            self._core.set_member_state(i, core)

    def __deepcopy__(self, memo):
        import copy

        new = object.__new__(type(self))
        for key, value in self.__dict__.items():
            new.__dict__[key] = value if key == "model" else copy.deepcopy(value, memo)
        return new
