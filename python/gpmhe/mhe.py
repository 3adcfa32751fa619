"""GPMHE: the GP-based moving horizon estimator of Wolff, Lopez & Müller, in filterpy's style.

This module validates the settings and every step's input, holds the public attributes and runs
SciPy's solvers. The estimator itself is one Rust object (`gpmhe._core.MovingHorizon`, built once
with the model, horizon, weights, form, state box and solver settings): it owns the sliding
history and the warm start, and with the default solver one ``update(u, y)`` is one Rust call
(window, warm start, solve, covariance, next arrival prior). SciPy's solvers evaluate the same
Rust window between ``prepare`` and ``commit``. See *Architecture* in the documentation.
"""

from __future__ import annotations

import inspect
import warnings

import numpy as np
import scipy.linalg
from scipy.optimize import Bounds, least_squares, lsq_linear, minimize

from gpmhe import _core
from gpmhe._threads import exclusive
from gpmhe._validation import (
    MAX_ABS,
    box,
    finite_vector,
    integer,
    one_of,
    options,
    positive,
    positive_scalar,
    symmetric_matrix,
    within_limits,
)

__all__ = ["GPMHE"]

#: The largest horizon accepted (the history keeps M + 2 steps).
_MAX_HORIZON = 1_000_000

#: The options each solver accepts (see `gpmhe._validation.options`): gpmhe's own for the Rust
#: solver; for SciPy's, the keywords of `scipy.optimize.least_squares` and of `minimize`'s
#: "trust-constr" options except those gpmhe sets itself (the problem, its bounds and method),
#: plus gpmhe's decrement stop ``dtol`` for "trust-constr".
_SOLVER_OPTIONS = {
    "gauss-newton": dict(max_iter="count", gtol="tol", xtol="tol", ftol="tol", dtol="tol",
                         interior=("auto", "always", "never"), interior_zone="tol",
                         mu_init="positive", mu_final="positive"),
    "trust-constr": dict(dtol="tol", xtol="tol", gtol="tol", barrier_tol="tol",
                         sparse_jacobian=None, maxiter="count", verbose=(0, 1, 2, 3),
                         finite_diff_rel_step=None, initial_constr_penalty="positive",
                         initial_tr_radius="positive",
                         initial_barrier_parameter="positive", initial_barrier_tolerance="positive",
                         factorization_method=None, disp=(True, False)),
    "least-squares": {
        **{k: None for k in inspect.signature(least_squares).parameters
           if k not in ("fun", "x0", "jac", "bounds", "method", "args", "kwargs")},
        **dict(ftol="tol", xtol="tol", gtol="tol", max_nfev="count?", verbose=(0, 1, 2),
               f_scale="positive"),
    },
}

#: The "trust-constr" decrement stop (see `GPMHE._solve_trust_constr`): tested once SciPy's
#: barrier parameter is at most this (two reductions from its initial 0.1), at the iterate and
#: after up to _TC_GN_STEPS projected Gauss-Newton steps from it.
_TC_DECREMENT_BARRIER = 1e-2
_TC_GN_STEPS = 3

_NO_INPUT = np.zeros(0)  # u when dim_u = 0 (shared, read-only)
_NO_INPUT.flags.writeable = False


def _check_eta(eta):
    eta = positive_scalar("eta", eta, allow_zero=True)
    if eta > 1.0:
        raise ValueError(f"eta: must be in [0, 1], got {eta!r}")
    return eta


def _covariance(name, value, n):
    """A symmetric positive definite covariance (n, n) from None (the identity), a scalar, the
    diagonal or the matrix."""
    if n == 0:
        return np.zeros((0, 0))
    return symmetric_matrix(name, 1.0 if value is None else value, n, definite=True,
                            vector_is_diagonal=True)


def _is_diagonal(a):
    return bool(np.all(a == np.diag(np.diag(a))))


def _output(name, y, p):
    """y(t) of p values (NaN entries are channels not measured, inf is refused) and whether any
    channel is measured. A Python loop over the values: cheaper than numpy's reductions for
    the few values of one sample."""
    try:
        a = np.asarray(y)
        if a.dtype.kind not in "fiu":
            raise TypeError
        a = a.astype(np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: must be {p} numbers (NaN for a channel not measured)") from None
    if a.shape != (p,):
        raise ValueError(f"{name}: expected shape ({p},), got {a.shape}")
    measured = False
    for v in a.tolist():
        if v == v:  # not NaN
            if not -MAX_ABS <= v <= MAX_ABS:
                raise ValueError(f"{name}: contains inf or a value of magnitude > {MAX_ABS:g} "
                                 "(NaN marks a channel not measured)")
            measured = True
    return a, measured


def _rows(name, value):
    """The rows of a sequence (a list, tuple or array; strings, dicts and sets are refused)."""
    if isinstance(value, (str, bytes, dict, set)) or not hasattr(value, "__len__"):
        raise ValueError(f"{name}: must be a sequence of rows, got {type(value).__name__}")
    try:
        return list(value)
    except TypeError:
        raise ValueError(f"{name}: must be a sequence of rows, got {type(value).__name__}") from None


def _gn_decrement(window, z, lb, ub):
    """The Gauss-Newton decrement at z in the box [lb, ub]: (decrement, step, cost).

    J = ‖r‖² with r the window's residuals and J_r their Jacobian; the Gauss-Newton model
    ‖r + J_r Δ‖² of J(z + Δ), minimised over the steps that stay in the box (a bounded linear
    least-squares problem), predicts the decrease ``decrement`` = ‖r‖² − ‖r + J_r Δ‖² by the
    step Δ = ``step``. Without active bounds the decrement is ½ ∇Jᵀ H⁻¹ ∇J (H = 2 J_rᵀ J_r);
    it is 0 exactly at first-order (KKT) points of the box-constrained problem. If r or J_r is
    not finite: (inf, None, inf).
    """
    r, jac = window.residuals(z), window.jacobian(z)
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(jac))):
        return np.inf, None, np.inf
    cost = float(r @ r)
    step = lsq_linear(jac, -r, bounds=(lb - z, ub - z), method="bvls").x
    return max(cost - float(np.sum((r + jac @ step) ** 2)), 0.0), step, cost


class GPMHE:
    """Moving horizon estimator with a learned (GP) or known model, in filterpy's style.

    The system is x(t+1) = f(x(t), u(t)) + w(t), y(t) = h(x(t), u(t)) + v(t). With a
    `LearnedModel` (the paper's GP-MHE [1]_) f and h are replaced by GP posterior means m_x(d),
    m_y(d) at d = [x; u] and the GP latent variances σ²_x(d), σ²_y(d) enter the weights; with a
    `KnownModel` (the exact-model MHE) the variances are zero.

    At each step the estimator minimises over the window states z = (x̄_{t−M_t}, …, x̄_t), inside
    the box ``x_bounds``, the cost (the paper's eq. 10e)::

        J = 2 η^{M_t} ‖x̄_{t−M_t} − x̂(t−M_t)‖²_{P2}
            + Σ_{j=1}^{M_t} 2 η^{j−1} ( w̄ᵀ Q(d̄)⁻¹ w̄ + v̄ᵀ R(d̄)⁻¹ v̄ )(t−j),

    with w̄_j = x̄_{j+1} − m_x(d̄_j), v̄_j = y_j − m_y(d̄_j), d̄_j = [x̄_j; u_j],
    Q(d) = diag σ²_x(d) + Q0, R(d) = diag σ²_y(d) + R0 and M_t = min(t, M) (full information
    while t < M). Missing outputs (``y=None``) drop their v̄ term; NaN entries of y are channels
    not measured and drop their rows (with a full R0, v̄ is weighted by R's block of the
    measured channels). The estimate is the last window
    state, x̂(t) = x̄_t.

    The loop, next to filterpy's EKF::

        # filterpy EKF                            # GPMHE
        for u, y in zip(us, ys):                  for u, y in zip(us, ys):
            ekf.update(y, HJacobian, Hx)              mhe.update(u, y)
            x_filt = ekf.x      # x̂(t|t)              # form="filtering":  mhe.x is x̂(t)
            ekf.predict(u)                             # form="prediction": mhe.x is x̂(t+1)
            x_pred = ekf.x      # x̂(t+1|t)

    The t-th call ``update(u(t), y(t))`` (t = 0, 1, …) leaves ``x`` = x̂(t+1) in the prediction
    form (the paper's: the window ends one step after the newest output) and x̂(t) in the
    filtering form (the window ends at the newest output, which adds the term 2 v̄ᵀR⁻¹v̄ at time t
    to J); before any call ``x`` is the given x̂(0). The filtering form uses as arrival prior for
    x(t−M_t) the one-step prediction m_x(x̂(t−M_t−1), u) of its own filtered estimate (x0 when
    t−M_t = 0), so that no output is counted twice.

    Parameters
    ----------
    model : LearnedModel or KnownModel
        The model: means m_x, m_y, variances σ²_x, σ²_y and their gradients.
    x0 : array_like of shape (dim_x,)
        Initial estimate x̂(0); must lie in ``x_bounds``.
    horizon : int, default 15
        Window length M >= 1 (number of stages).
    eta : float, default 0.91
        Discount factor η in [0, 1]: older terms are weighted by η^{j−1} (1: no discount).
    P2 : array_like of shape (dim_x, dim_x) or None, default None
        Symmetric positive definite weight of the arrival prior, the inverse of the arrival
        covariance ``P0``; None is the identity. Give P2 or P0, not both.
    Q0 : float, array_like of shape (dim_x,) or (dim_x, dim_x), or None, default None
        Process-noise covariance: a scalar (times I), the diagonal, or a full symmetric positive
        definite matrix. Its inverse (with the GP variances added to the diagonal) weights w̄.
        None is the identity.
    R0 : float, array_like of shape (dim_y,) or (dim_y, dim_y), or None, default None
        Output-noise covariance, as ``Q0``. None is the identity.
    x_bounds : tuple (lower, upper), or None, default None
        The box X for every window state: arrays of shape (dim_x,) (entries may be ±inf;
        lower < upper), or None for an unbounded side. None: unbounded.
    form : {"prediction", "filtering"}, default "prediction"
        Which estimate ``x`` holds after an update, see above.
    solver : {"gauss-newton", "trust-constr", "least-squares"}, default "gauss-newton"
        The window solver. "gauss-newton" is the real-time Rust solver: one Rust call per update,
        a bounded Gauss-Newton / Levenberg-Marquardt method with a block-tridiagonal
        factorisation (linear in the horizon) and a barrier phase that keeps early iterations off
        the bounds. "trust-constr" is SciPy's interior-point method with the exact gradient and
        the Gauss-Newton Hessian from Rust (slow, a general reference). "least-squares" is
        SciPy's bounded TRF on the stacked residuals with the Rust Jacobian. With a
        `KnownModel`, "gauss-newton" still solves in Rust but calls the model's Python
        functions at every window evaluation: once per window point, or once for all points
        with ``KnownModel(..., vectorized=True)``.
    solver_options : dict or None, default None
        Overrides of gpmhe's defaults. For "gauss-newton": ``max_iter`` (100), ``gtol`` (1e-6,
        on ‖z − Π(z − ∇J)‖∞ with Π the projection on the box), ``dtol`` (1e-2, see Notes),
        ``xtol`` (1e-12), ``ftol`` (1e-15), ``interior`` ("auto", "always" or "never": when the
        barrier phase runs), ``interior_zone`` (1e-5) and ``mu_init`` (0.1), ``mu_final``
        (1e-5), the first and last barrier parameter. For "trust-constr": gpmhe's ``dtol``
        (1e-4, its decrement stop, see Notes; 0 leaves the stop to SciPy's tests) and the
        "trust-constr" options of `scipy.optimize.minimize` (defaults gtol=1e-6, xtol=1e-8,
        maxiter=200, initial_barrier_parameter=0.1; SciPy's for the others). For
        "least-squares" the keywords of `scipy.optimize.least_squares` (defaults
        ftol=xtol=gtol=1e-10, max_nfev=200).

    P0 : array_like of shape (dim_x, dim_x) or None, default None
        The arrival covariance, the covariance form of ``P2`` (P2 = P0⁻¹, as filterpy's ``P``).
    arrival_mean : {"smoothed", "estimate"}, default "smoothed"
        The arrival prior x̂(t−M_t) once the window slides: "smoothed" is the previous window's
        estimate of the new first node; "estimate" is the estimator's own earlier estimate of
        x(t−M_t) (the paper's).
    arrival_weight : {"ekf", "constant"}, default "ekf"
        The arrival weight: "ekf" updates the arrival covariance by an extended Kalman filter
        step over the node that leaves the window (starting from P0); "constant" keeps P2 (the
        paper's). The paper's setting is ``arrival_mean="estimate", arrival_weight="constant"``.
    p0 : array_like of shape (dim_p,) or None, default None
        The initial guess of a model's unknown constant parameters p (required when the model
        has parameters, ``dim_p > 0``; see `KnownModel`).
    P_p0 : float or array_like of shape (dim_p,) or (dim_p, dim_p), or None, default None
        Prior covariance of p around ``p0``; None: abs(p0)² on the diagonal (one relative unit).
    p_bounds : tuple (lower, upper) or None, default None
        Bounds of p, as ``x_bounds``.
    p_drift : float or array_like of shape (dim_p,) or None, default None
        Standard deviation of a random walk of p per step (p is estimated as a state with
        p(t+1) = p(t) plus this drift); None: 1e-4 · abs(p0), constant for any practical purpose.

    Attributes
    ----------
    x : ndarray of shape (dim_x,)
        Current estimate: x̂(t+1) (prediction form) or x̂(t) (filtering form).
    P : ndarray of shape (dim_x, dim_x)
        Covariance estimate of ``x``: the last block of 4 H⁻¹ with H the Gauss-Newton Hessian of
        J (J is 4× a negative log-likelihood). A rough indication, exact only for linear-Gaussian
        models and η = 1. Before the first update it is P2⁻¹; if H is singular it keeps its
        previous value.
    x_prior : ndarray of shape (dim_x,)
        Arrival prior x̂(t−M_t) used in the last window.
    x_window : ndarray of shape (M_t + 1, dim_x)
        Optimal window trajectory z of the last update, oldest first (``x`` is its last row).
    cost : float
        Optimal cost J of the last window.
    success : bool
        Whether the last window's solver reported convergence.
    message : str
        The solver's message. With "gauss-newton" it starts with the stopping reason:
        gradient-tolerance, decrement-tolerance, step-tolerance, cost-tolerance, noise-floor
        (successes); max-iterations, no-progress (failures). With "trust-constr" it is
        "decrement-tolerance (...)" after gpmhe's decrement stop, else SciPy's message.
    nit : int
        Iterations of the last window's solver ("least-squares": function evaluations).
    nfev : int
        Window evaluations of the last update ("gauss-newton" only; 0 otherwise).
    projected_gradient : float
        Final ‖z − Π(z − ∇J)‖∞ of the last update ("gauss-newton" only; 0 otherwise).
    t : int
        Number of updates since construction or ``reset``.
    p : ndarray of shape (dim_p,)
        The estimate of the parameters (empty without parameters).
    P_p : ndarray of shape (dim_p, dim_p)
        Its covariance, the parameters' block of 4 H⁻¹ at the newest node.
    Q0, R0, P2, P0, eta
        The weights, settable between updates (each takes effect from the next update and is
        validated as in the constructor; setting P2 or P0 restarts the "ekf" arrival weight).
        Other names are rejected (``est.R = ...`` raises AttributeError).
    model, horizon, form, solver, solver_options, arrival_mean, arrival_weight, x_bounds
        The settings as given, read-only (``x_bounds`` as a (lower, upper) pair of arrays, ±inf
        where unbounded).
    p0, P_p0, p_bounds, p_drift
        The parameter settings (with parameters).
    dim_x, dim_y, dim_u, dim_p : int
        The model's dimensions n, p, m and its number of parameters.

    Raises
    ------
    ValueError
        If a setting is invalid (shapes, P2 not positive definite, Q0 or R0 not positive
        diagonal, lower >= upper, x0 outside the bounds, an unknown solver or solver option).

    See Also
    --------
    LearnedModel : The GP model of the GP-MHE.
    KnownModel : An exactly known model.
    gpmhe.baselines.GPEKF : The EKF on the same learned model.

    Notes
    -----
    ``dtol`` stops the "gauss-newton" solver (message "decrement-tolerance", a success) when its
    next Gauss-Newton step Δ predicts a decrease ½ΔᵀHΔ <= dtol. J is 4× a negative
    log-likelihood, so the window's Laplace posterior has covariance 4H⁻¹ and that step is
    √(dtol/2) ≈ 0.07 of its standard deviations long (for the default): the point returned is
    that close to the window optimum, far inside the estimation error, and its cost is within
    about dtol of the local minimum. ``dtol=0`` runs every window to ``gtol``. The solver also
    stops at the cost's rounding noise (message "noise-floor", a success): when a GP fit ran to
    a large σ_f, J is only accurate to about 1e-6 relative and its gradient to about 1e-3, so
    ``gtol`` cannot be reached; the solver stops once its next step predicts less decrease than
    that noise.

    ``dtol`` stops "trust-constr" (SciPy's interior-point method; message
    "decrement-tolerance", a success) by the same measure with the bounds: the decrease
    ‖r‖² − ‖r + J_r Δ‖² (J = ‖r‖², r the residuals, J_r their Jacobian) that the Gauss-Newton
    model predicts for its best step Δ inside the box is <= dtol; it is 0 exactly at a KKT point.
    The test runs once SciPy's barrier parameter is at most 1e-2 (earlier the barrier still
    steers the iterates off the bounds), at SciPy's iterate and after each of up to three
    projected Gauss-Newton steps from it (each must lower J); the first point that passes is
    returned. The default 1e-4 is 100 times below the Rust solver's, so that "trust-constr" can
    check it.

    On a solver failure (``success`` False, a `RuntimeWarning`), the window keeps whichever of
    the solver's last finite iterate and the warm start costs less; ``x`` is never NaN. Bad
    input to ``update`` raises ValueError and leaves the estimator unchanged.

    With filterpy's ``Saver`` every attribute is recorded; ``Saver.to_array()`` needs equal
    shapes, so pass ``ignore=("x_window",)`` if you save during the full-information phase
    (t < M), where the window grows.

    See the user guide, *The window problem*, *Weights from GP variances* and *The window
    solver*.

    References
    ----------
    .. [1] T. M. Wolff, V. G. Lopez and M. A. Müller, "Robust Stability of Gaussian Process
       Based Moving Horizon Estimation".

    Examples
    --------
    Estimate the batch reactor's two concentrations from their measured sum, with the known
    model:

    >>> import numpy as np
    >>> from gpmhe import GPMHE, KnownModel
    >>> from gpmhe.systems import batch_reactor as br
    >>> model = KnownModel(br.f, br.h, dim_x=2, dim_y=1,
    ...                    f_jacobian=br.f_jacobian, h_jacobian=br.h_jacobian)
    >>> x_true, y = br.simulate(br.X_TRUE0, 10, np.random.default_rng(0))
    >>> mhe = GPMHE(model, x0=[3.0, 1.0], horizon=5, Q0=1e-3, R0=1e-2, x_bounds=br.X_BOUNDS)
    >>> for t in range(10):
    ...     x_hat = mhe.update(None, y[t])  # no input: u = None
    >>> mhe.t, mhe.success, mhe.x_window.shape
    (10, True, (6, 2))
    >>> print(np.round(mhe.x, 1), np.round(x_true[10], 1))  # x̂(10) and x(10)
    [1.6 1.6] [1.5 1.8]
    """

    def __init__(self, model, x0, horizon=15, eta=0.91, P2=None, Q0=None, R0=None,
                 x_bounds=None, form="prediction", solver="gauss-newton", solver_options=None,
                 P0=None, arrival_mean="smoothed", arrival_weight="ekf", p0=None, P_p0=None,
                 p_bounds=None, p_drift=None):
        with self._writing():
            for attr in ("dim_x", "dim_y", "dim_u", "predict", "_make_window"):
                if not hasattr(model, attr):
                    raise ValueError("model: must be a gpmhe.LearnedModel or gpmhe.KnownModel")
            n, p = model.dim_x, model.dim_y
            self.model, self.dim_x, self.dim_y, self.dim_u = model, n, p, model.dim_u
            self.dim_p = int(getattr(model, "dim_p", 0))
            self.horizon = integer("horizon", horizon, low=1, high=_MAX_HORIZON)
            self.form = one_of("form", form, ("prediction", "filtering"))
            self.solver = one_of("solver", solver, tuple(self._SOLVERS))
            self.solver_options = dict(options("solver_options", solver_options,
                                               _SOLVER_OPTIONS[self.solver]) or {})
            self.arrival_mean = one_of("arrival_mean", arrival_mean, ("estimate", "smoothed"))
            self.arrival_weight = one_of("arrival_weight", arrival_weight, ("constant", "ekf"))
            if P2 is not None and P0 is not None:
                raise ValueError("P2, P0: give the arrival weight P2 or its covariance P0, not both")
            self._eta = _check_eta(eta)
            self._Q0, self._R0 = _covariance("Q0", Q0, n), _covariance("R0", R0, p)
            self._P2 = (np.linalg.inv(_covariance("P0", P0, n)) if P0 is not None
                        else symmetric_matrix("P2", np.eye(n) if P2 is None else P2, n, definite=True))
            self.x_bounds = box("x_bounds", x_bounds, n)
            self._parameters(p0, P_p0, p_bounds, p_drift)
            x0 = self._check_x0(x0)
            rust_solver = self._rust_solver() if self.solver == "gauss-newton" else None
            lb, ub = self._core_bounds()
            core_model = model._augment(self._p_scale) if self.dim_p else model
            w = self._core_weights()
            self._core = core_model._make_window(
                w["eta"], w["q0"], w["r0"], w["p2_sqrt"], self.form == "filtering",
                horizon=self.horizon,
                x0=self._core_x0(x0), lower=lb, upper=ub, solver=rust_solver,
                arrival_mean=self.arrival_mean, arrival_weight=self.arrival_weight)
            self._core_model = core_model
        self.reset(x0)

    # ---- settings: weights that take effect, parameters, the attribute guard ---------------
    #: The attributes a user may set (each takes effect from the next update).
    _SETTABLE = frozenset({"Q0", "R0", "P2", "P0", "eta"})
    #: Names users of other estimators try, and what to use instead.
    _DID_YOU_MEAN = {"R": "R0", "Q": "Q0", "P": "P0 (the arrival covariance)", "x0": "reset(x0)",
                     "M": "horizon (fixed: build a new GPMHE)", "N": "horizon (fixed)"}

    def __setattr__(self, name, value):
        if name in self._SETTABLE or name.startswith("_") or self.__dict__.get("_unlocked"):
            object.__setattr__(self, name, value)
            return
        hint = self._DID_YOU_MEAN.get(name)
        if hint is not None:
            raise AttributeError(f"GPMHE has no settable attribute {name!r}: did you mean {hint}?")
        if not hasattr(self, name):
            raise AttributeError(f"GPMHE has no attribute {name!r}; the settable ones are "
                                 f"{', '.join(sorted(self._SETTABLE))}")
        raise AttributeError(f"GPMHE.{name} is read-only; the settable attributes are "
                             f"{', '.join(sorted(self._SETTABLE))} (the other settings are fixed "
                             "at construction, the estimate changes only through update and reset)")

    class _Unlock:
        def __init__(self, owner):
            self.owner = owner

        def __enter__(self):
            self.before = self.owner.__dict__.get("_unlocked", False)
            object.__setattr__(self.owner, "_unlocked", True)

        def __exit__(self, *exc):
            object.__setattr__(self.owner, "_unlocked", self.before)

    def _writing(self):
        """A context in which the estimator's own code sets its read-only attributes."""
        return self._Unlock(self)

    @property
    def Q0(self):  # noqa: N802 (the paper's symbol)
        """Process-noise covariance Q0 (dim_x, dim_x); setting it takes effect from the next
        update (a scalar, the diagonal or the matrix, as in the constructor)."""
        return self._Q0.copy()

    @Q0.setter
    def Q0(self, value):  # noqa: N802
        self._set_weights(Q0=_covariance("Q0", value, self.dim_x))

    @property
    def R0(self):  # noqa: N802
        """Output-noise covariance R0 (dim_y, dim_y); settable as ``Q0``."""
        return self._R0.copy()

    @R0.setter
    def R0(self, value):  # noqa: N802
        self._set_weights(R0=_covariance("R0", value, self.dim_y))

    @property
    def P2(self):  # noqa: N802
        """Arrival weight P2 (dim_x, dim_x), the inverse of the arrival covariance ``P0``;
        setting it (or ``P0``) takes effect from the next update and restarts an "ekf" arrival
        weight from it."""
        return self._P2.copy()

    @P2.setter
    def P2(self, value):  # noqa: N802
        self._set_weights(P2=symmetric_matrix("P2", value, self.dim_x, definite=True))

    @property
    def P0(self):  # noqa: N802
        """Arrival covariance P0 = P2⁻¹ (dim_x, dim_x); settable (sets P2)."""
        return np.linalg.inv(self._P2)

    @P0.setter
    def P0(self, value):  # noqa: N802
        self._set_weights(P2=np.linalg.inv(_covariance("P0", value, self.dim_x)))

    @property
    def eta(self):
        """Discount factor η in [0, 1]; settable."""
        return self._eta

    @eta.setter
    def eta(self, value):
        self._set_weights(eta=_check_eta(value))

    def _set_weights(self, **new):
        """Replace validated weights and hand exactly those to the core (the others, and the
        arrival weight unless P2 changes, stay as they are); on error nothing changes."""
        old = {key: getattr(self, "_" + key) for key in new}
        for key, value in new.items():
            object.__setattr__(self, "_" + key, value)
        try:
            self._core.set_weights(**self._core_weights(new))
        except (ValueError, np.linalg.LinAlgError) as e:
            for key, value in old.items():
                object.__setattr__(self, "_" + key, value)
            raise ValueError(str(e)) from None

    def _parameters(self, p0, P_p0, p_bounds, p_drift):
        """Validate the parameter settings (a model with dim_p > 0 needs p0)."""
        k = self.dim_p
        if not k:
            for name, v in (("p0", p0), ("P_p0", P_p0), ("p_bounds", p_bounds), ("p_drift", p_drift)):
                if v is not None:
                    raise ValueError(f"{name}: the model has no parameters (dim_p = 0)")
            self.p_bounds, self._p_scale = None, np.ones(0)
            self.P_p0, self.p_drift = np.zeros((0, 0)), np.zeros(0)
            return
        if p0 is None:
            raise ValueError(f"p0: required, the model has {k} parameter(s) (dim_p = {k})")
        self.p0 = finite_vector("p0", p0, k, flatten=True).copy()
        self.p_bounds = box("p_bounds", p_bounds, k)
        if np.any(self.p0 < self.p_bounds[0]) or np.any(self.p0 > self.p_bounds[1]):
            raise ValueError("p0: must lie inside p_bounds")
        scale = np.abs(self.p0)
        span = self.p_bounds[1] - self.p_bounds[0]
        scale = np.where(scale > 0, scale, np.where(np.isfinite(span), span, 1.0))
        self._p_scale = scale
        self.P_p0 = _covariance("P_p0", np.diag(scale ** 2) if P_p0 is None else P_p0, k)
        drift = 1e-4 * scale if p_drift is None else p_drift
        self.p_drift = np.broadcast_to(positive("p_drift", drift), (k,)).astype(np.float64)

    def _core_weights(self, names=("eta", "Q0", "R0", "P2")):
        """The core's weights among ``names``: ``eta``, ``q0`` and ``r0`` (Q0 and R0: their
        diagonals when diagonal, else flattened), ``p2_sqrt`` (S with P2 = SᵀS), all on the
        augmented state [x; p̃] when the model has parameters."""
        s = self._p_scale
        flat = lambda a: np.ascontiguousarray(np.diag(a) if _is_diagonal(a) else a.reshape(-1))  # noqa: E731
        out = {}
        if "eta" in names:
            out["eta"] = self._eta
        if "Q0" in names:
            Q0 = self._Q0
            if self.dim_p:
                Q0 = scipy.linalg.block_diag(Q0, np.diag((self.p_drift / s) ** 2))
            out["q0"] = flat(Q0)
        if "R0" in names:
            out["r0"] = flat(self._R0) if self.dim_y else np.zeros(0)
        if "P2" in names:
            P2 = self._P2
            if self.dim_p:
                P2 = scipy.linalg.block_diag(P2, s[:, None] * np.linalg.inv(self.P_p0) * s[None, :])
            out["p2_sqrt"] = np.ascontiguousarray(np.linalg.cholesky(P2).T)
        return out

    def _core_bounds(self):
        lb, ub = self.x_bounds
        if self.dim_p:
            plb, pub = self.p_bounds
            lb, ub = np.concatenate([lb, plb / self._p_scale]), np.concatenate([ub, pub / self._p_scale])
        return lb, ub

    def _check_x0(self, x0):
        x0 = finite_vector("x0", x0, self.dim_x, flatten=True).copy()
        lb, ub = self.x_bounds
        if np.any(x0 < lb) or np.any(x0 > ub):
            raise ValueError("x0: must lie inside x_bounds")
        return x0

    def _core_x0(self, x0, p=None):
        if not self.dim_p:
            return x0
        return np.concatenate([x0, (self.p0 if p is None else p) / self._p_scale])

    def reset(self, x0, p0=None):
        """Forget the history and restart from the estimate x̂(0) = x0.

        Sets ``t`` to 0, ``x``, ``x_prior`` to x0, ``x_window`` to x0 as one row, ``P`` to
        ``P0`` (= P2⁻¹), ``p`` to ``p0`` and ``P_p`` to ``P_p0``, and the solver statistics to
        their initial values. The settings (and weights set since construction) are kept.

        Parameters
        ----------
        x0 : array_like of shape (dim_x,)
            New initial estimate; must lie in ``x_bounds``.
        p0 : array_like of shape (dim_p,) or None, default None
            New parameter guess (a model with parameters only); None: the constructor's ``p0``.

        Raises
        ------
        ValueError
            If x0 or p0 has the wrong shape, is not finite or lies outside its bounds.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import GPMHE, KnownModel
        >>> model = KnownModel(lambda x, u: 0.9 * x, lambda x, u: x, dim_x=1, dim_y=1)
        >>> mhe = GPMHE(model, x0=[0.0], horizon=3)
        >>> _ = mhe.update(None, [1.0])
        >>> mhe.reset([2.0])
        >>> mhe.t, mhe.x
        (0, array([2.]))
        """
        x0 = self._check_x0(x0)
        if p0 is not None:
            if not self.dim_p:
                raise ValueError("p0: the model has no parameters (dim_p = 0)")
            p0 = finite_vector("p0", p0, self.dim_p, flatten=True).copy()
            if np.any(p0 < self.p_bounds[0]) or np.any(p0 > self.p_bounds[1]):
                raise ValueError("p0: must lie inside p_bounds")
        self._core.reset(self._core_x0(x0, p0))

    # ---- the estimate and what the last update reported: read from the core ------------------
    # The core records an update in one step (or not at all), so these never disagree.
    @property
    def t(self):
        """Number of updates since construction or `reset`."""
        return self._core.t

    @property
    def x(self):
        """The current estimate x̂(t+1) (prediction form) or x̂(t) (filtering form)."""
        x = self._core.x
        return x[:self.dim_x].copy() if self.dim_p else x

    @property
    def x_window(self):
        """The last window's optimal trajectory (M_t + 1, dim_x), oldest first."""
        w = self._core.x_window
        return np.ascontiguousarray(w[:, :self.dim_x]) if self.dim_p else w

    @property
    def x_prior(self):
        """The arrival prior x̂(t−M_t) of the last window."""
        x = self._core.x_prior
        return x[:self.dim_x].copy() if self.dim_p else x

    @property
    def P(self):  # noqa: N802 (the paper's symbol)
        """Covariance estimate of ``x`` (dim_x, dim_x), see the class docstring."""
        c = self._core.covariance
        return np.ascontiguousarray(c[:self.dim_x, :self.dim_x]) if self.dim_p else c

    @property
    def p(self):
        """The estimate of the parameters (dim_p,) (empty without parameters)."""
        if not self.dim_p:
            return np.zeros(0)
        return self._core.x[self.dim_x:] * self._p_scale

    @property
    def P_p(self):  # noqa: N802
        """The covariance of ``p`` (dim_p, dim_p)."""
        n, s = self.dim_x, self._p_scale
        if not self.dim_p:
            return np.zeros((0, 0))
        return s[:, None] * self._core.covariance[n:, n:] * s[None, :]

    @property
    def cost(self):
        """Optimal cost J of the last window (0.0 before any update)."""
        return self._core.optimal_cost

    @property
    def success(self):
        """Whether the last window's solver reported convergence."""
        return self._core.success

    @property
    def nit(self):
        """Iterations of the last window's solver."""
        return self._core.nit

    @property
    def nfev(self):
        """Window evaluations of the last update ("gauss-newton"; 0 otherwise)."""
        return self._core.nfev

    @property
    def projected_gradient(self):
        """Final projected gradient of the last update ("gauss-newton"; 0 otherwise)."""
        return self._core.projected_gradient

    @property
    def message(self):
        """The solver's message for the last window."""
        return self._core.message

    def _check_step(self, u, y):
        """The validated (u, y, whether y holds a measured channel): u None stays None when
        the core may stand in for it (no input, or the filtering form; the core refuses it
        while an earlier update still waits for its input)."""
        m, p = self.dim_u, self.dim_y
        if u is None:
            if m and self.form != "filtering":
                raise ValueError(f"u: required (dim_u = {m}; only the filtering form accepts "
                                 "None, see set_input)")
        else:
            u = finite_vector("u", u, m, flatten=True)
        if y is None:
            return u, np.zeros(p), False
        y, present = _output("y", y, p)
        if u is None and m and present and self._output_uses_input(self._core.last_input):
            raise ValueError("u: required, the model's output h depends on u (u=None is for "
                             "models whose h(x, u) does not use u)")
        return u, y, present

    def _output_uses_input(self, u):
        """Whether the model's output mean h depends on u: probed once, at the current estimate
        and u, against u shifted in every entry (a model is a function of (x, u))."""
        known = self.__dict__.get("_h_uses_u")
        if known is None:
            x = self._core_x0(self.x, self.p) if self.dim_p else self.x
            shifted = u + 1e-3 * (1.0 + np.abs(u))
            d = np.vstack([np.concatenate([x, u]), np.concatenate([x, shifted])])
            y0, y1 = self._core_model.stage_eval(d)[4]
            known = bool(np.any(np.abs(y1 - y0) > 1e-12 * (1.0 + np.abs(y0))))
            object.__setattr__(self, "_h_uses_u", known)
        return known

    def set_input(self, u):
        """Give u(t), the input applied after the last update, when that update had ``u=None``.

        In the filtering form, ``update(None, y(t))`` returns x̂(t) before u(t) is known (a
        controller computes it from x̂(t)); u(t) drives the next window's transition from x(t)
        to x(t+1), so it must be given before the next update.

        Parameters
        ----------
        u : array_like of shape (dim_u,)
            The input u(t).

        Raises
        ------
        ValueError
            If u is not a finite vector of dim_u values or no update is waiting for its input.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import GPMHE, KnownModel
        >>> model = KnownModel(lambda x, u: x + u, lambda x, u: x, dim_x=1, dim_y=1, dim_u=1)
        >>> mhe = GPMHE(model, x0=[0.0], horizon=3, form="filtering")
        >>> x_hat = mhe.update(None, [1.0])     # u(0) not known yet
        >>> mhe.set_input(-0.5 * x_hat)         # the controller's u(0) = -0.5 x̂(0)
        >>> _ = mhe.update(None, [0.6])
        """
        u = finite_vector("u", u, self.dim_u, flatten=True)
        self._core.set_last_input(u)  # refused unless an update waits for its input

    def update(self, u, y):
        """Add the input and output of the next step, solve the window and update the estimate.

        The t-th call appends (u(t), y(t)), slides the window (it grows until it holds M stages),
        warm-starts it from the previous solution, solves it and sets ``x``, ``P``,
        ``x_window``, ``cost`` and the solver statistics.

        Parameters
        ----------
        u : array_like of shape (dim_u,) or None
            Input u(t); None when the model has no input (dim_u = 0), or in the filtering form
            when u(t) is not known yet (give it with `set_input` before the next update: it
            drives the transition to x(t+1); at the newest node it only enters h(x, u), so a
            model whose h depends on u needs it here: u=None with a measured y is then refused,
            checked once by evaluating h at two inputs).
        y : array_like of shape (dim_y,) or None
            Output y(t); None when there is no measurement at this step, NaN entries for
            channels not measured.

        Returns
        -------
        ndarray of shape (dim_x,)
            The new estimate ``x``: x̂(t+1) (prediction form) or x̂(t) (filtering form).

        Raises
        ------
        ValueError
            On bad input (shape, NaN or inf, a required u missing, u=None while h depends
            on u) or bad output of a `KnownModel` callable; the estimator is then unchanged.
        Exception
            Any exception a `KnownModel` callable raises (``KeyboardInterrupt`` included) is
            passed on with the estimator unchanged, except an ``ArithmeticError`` or
            ``RuntimeError`` at a trial point of the solver, which only rejects that point.
        RuntimeError
            If the estimator is already being updated (from another thread, or from inside its
            own model callable).

        Warns
        -----
        RuntimeWarning
            If the window solver did not converge (``success`` False).

        Examples
        --------
        A scalar random walk observed directly, in the filtering form:

        >>> import numpy as np
        >>> from gpmhe import GPMHE, KnownModel
        >>> model = KnownModel(lambda x, u: x + u, lambda x, u: x, dim_x=1, dim_y=1, dim_u=1)
        >>> mhe = GPMHE(model, x0=[0.0], horizon=3, Q0=1.0, R0=1.0, form="filtering")
        >>> print(np.round(mhe.update([1.0], [2.0]), 3))  # x̂(0): halfway between x0 and y(0)
        [1.]
        >>> print(np.round(mhe.update([0.0], None), 3))  # x̂(1) = x̂(0) + u(0): no measurement
        [2.]
        """
        self._step(*self._check_step(u, y))
        return self.x

    def batch_filter(self, ys, us=None):
        """Run `update` over a sequence of outputs (and inputs), as filterpy's ``batch_filter``.

        All input is validated before the first update, so bad input raises ValueError (naming
        the row) with the estimator unchanged.

        Parameters
        ----------
        ys : sequence of array_like of shape (dim_y,) or None, length T
            Outputs y(t); a row may be None (no measurement at that step).
        us : sequence of array_like of shape (dim_u,) or None, length T, or None, default None
            Inputs u(t); None when the model has no input.

        Returns
        -------
        xs : ndarray of shape (T, dim_x)
            ``x`` after each update.
        Ps : ndarray of shape (T, dim_x, dim_x)
            ``P`` after each update.

        Raises
        ------
        ValueError
            If a row has the wrong shape or ``us`` and ``ys`` differ in length.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import GPMHE, KnownModel
        >>> from gpmhe.systems import batch_reactor as br
        >>> model = KnownModel(br.f, br.h, dim_x=2, dim_y=1)
        >>> x_true, y = br.simulate(br.X_TRUE0, 20, np.random.default_rng(1))
        >>> mhe = GPMHE(model, x0=br.X_TRUE0, x_bounds=br.X_BOUNDS, **br.MHE_SETTINGS)
        >>> xs, Ps = mhe.batch_filter(y[:20])
        >>> xs.shape, Ps.shape
        ((20, 2), (20, 2, 2))
        >>> rmse = np.sqrt(np.mean((xs - x_true[1:21]) ** 2))
        >>> bool(rmse < 0.3)
        True
        """
        ys = _rows("ys", ys)
        us = [None] * len(ys) if us is None else _rows("us", us)
        if len(us) != len(ys):
            raise ValueError(f"us, ys: us has {len(us)} rows but ys has {len(ys)}")
        steps = []
        for i, (u, y) in enumerate(zip(us, ys)):
            try:
                steps.append(self._check_step(u, y))
            except ValueError as e:  # "y: ..." -> "ys[i]: ... (at row i)"
                name, _, detail = str(e).partition(": ")
                raise ValueError(f"{name}s[{i}]: {detail} (at row {i})") from None
        xs = np.empty((len(steps), self.dim_x))
        Ps = np.empty((len(steps), self.dim_x, self.dim_x))
        if self.dim_u and any(u is None for u, _, _ in steps):
            raise ValueError("us: batch_filter needs every input (u=None is for update and "
                             "set_input)")
        for i, step in enumerate(steps):
            self._step(*step)
            xs[i], Ps[i] = self.x, self.P
        return xs, Ps

    # ----------------------------------------------------------------------------------------
    @exclusive  # one update at a time per estimator (gpmhe/_threads.py)
    def _step(self, u, y, present):
        """One update with validated input, recorded by the core in one step with everything it
        reports: the Rust solver in one call ("gauss-newton"), or a SciPy solver between the
        core's ``prepare`` and ``commit``. Nothing changes unless the core records the step."""
        core = self._core
        y = y if present else None
        if self.solver == "gauss-newton":
            core.update(u, y)
            if not core.success:  # (after the step is recorded: the warning may be an error)
                self._warn(core.message, core.t - 1, stacklevel=5)  # 5: past `exclusive`
            return
        try:
            z0, lb, ub = core.prepare(u, y)
            z, cost, success, nit, message = self._solve(core, z0, lb, ub)
            core.commit(z, cost, success, nit, message, self._window_covariance(core, z))
        except BaseException:
            core.abandon()  # the model's cache as before prepare: as if never started
            raise

    def _warn(self, message, t, stacklevel):
        """The RuntimeWarning of the window of update t whose solver did not converge
        (`stacklevel` points at the caller of `update` or `batch_filter`)."""
        warnings.warn(f"GPMHE window solver ({self.solver}) did not converge at t={t}: "
                      f"{message}; keeping the better of its last iterate and the warm start",
                      RuntimeWarning, stacklevel=stacklevel)

    def _window_covariance(self, window, z):
        """The last block of 4 H⁻¹ at z for the SciPy paths (the Rust solve returns the same
        block from its block-tridiagonal factorisation); None if H is singular."""
        n = self.dim_x + self.dim_p
        H = window.gn_hessian(z)
        try:
            Hinv_last = np.linalg.solve(H, np.eye(len(z))[:, -n:])[-n:]
            P = 4.0 * 0.5 * (Hinv_last + Hinv_last.T)
        except np.linalg.LinAlgError:
            return None
        return P if np.all(np.isfinite(P)) else None

    # ---- solvers: one method per solver, dispatched through _SOLVERS ------------------------
    def _solve(self, window, z0, lb, ub):
        """The SciPy paths: solve from z0, keep the better of the result and z0."""
        cost0 = window.cost(z0)
        try:
            z, nit, ok, message = getattr(self, self._SOLVERS[self.solver])(window, z0, lb, ub)
            z = np.clip(np.asarray(z, dtype=np.float64), lb, ub)
            cost = window.cost(z) if np.all(np.isfinite(z)) else np.inf
        except (ValueError, ArithmeticError, np.linalg.LinAlgError, RuntimeError) as e:
            z, nit, ok, message, cost = z0, 0, False, f"solver raised: {e}", np.inf
        if not np.isfinite(cost) or (cost0 is not None and cost > cost0):
            cost0 = window.cost(z0) if cost0 is None else cost0
            if ok:
                message = f"solver returned a point costlier than its start ({message})"
            z, cost, ok = z0.copy(), cost0, False
        if not ok:  # (before the core records the step: as an error, it leaves nothing changed)
            self._warn(message, self.t, stacklevel=6)  # 6: past `exclusive`
        return z, float(cost), bool(ok), int(nit), str(message)

    def _solve_trust_constr(self, window, z0, lb, ub):
        """SciPy's interior-point method, stopped by the Gauss-Newton decrement (see
        `_gn_decrement` and the user guide, *The SciPy reference solvers*)."""
        options = dict(gtol=1e-6, xtol=1e-8, maxiter=200, initial_barrier_parameter=0.1)
        options.update(self.solver_options)
        dtol = options.pop("dtol", 1e-4)
        stop = {}

        def decrement_stop(xk, state):
            # SciPy's (xk, state) callback of "trust-constr" (every SciPy >= 1.10): True stops
            # the solve with status 3. Not while the barrier steers the iterates away from the
            # bounds (and from the bound-pinned local minima there). Without finite bounds SciPy
            # runs its SQP method, which has no barrier.
            if not getattr(state, "barrier_parameter", 0.0) <= _TC_DECREMENT_BARRIER:
                return False
            z = np.clip(xk, lb, ub)
            decrement, step, cost = _gn_decrement(window, z, lb, ub)
            # SciPy's barrier method creeps along flat directions close to a bound; a few
            # projected Gauss-Newton steps from its iterate (each must lower J) finish there.
            for k in range(_TC_GN_STEPS + 1):
                if decrement <= dtol:
                    stop.update(z=z, decrement=decrement, steps=k)
                    return True
                if k == _TC_GN_STEPS or step is None:
                    return False
                z_new = np.clip(z + step, lb, ub)
                decrement_new, step_new, cost_new = _gn_decrement(window, z_new, lb, ub)
                if not cost_new < cost:
                    return False
                z, decrement, step, cost = z_new, decrement_new, step_new, cost_new
            return False

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "delta_grad == 0.0" chatter
            res = minimize(window.cost_grad, z0, jac=True, hess=window.gn_hessian,
                           method="trust-constr", bounds=Bounds(lb, ub), options=options,
                           callback=decrement_stop if dtol > 0 else None)
        if stop:  # SciPy's status 3, stopped by the callback: this success
            barrier = getattr(res, "barrier_parameter", None)
            message = (f"decrement-tolerance (Gauss-Newton decrement {stop['decrement']:.2e} "
                       f"after {stop['steps']} Gauss-Newton steps"
                       + ("" if barrier is None else f", barrier parameter {barrier:.1e}") + ")")
            return stop["z"], res.nit, True, message
        return res.x, res.nit, res.status in (1, 2), res.message

    def _solve_least_squares(self, window, z0, lb, ub):
        options = dict(ftol=1e-10, xtol=1e-10, gtol=1e-10, max_nfev=200)
        options.update(self.solver_options)
        res = least_squares(window.residuals, z0, jac=window.jacobian, bounds=(lb, ub),
                            method="trf", **options)
        return res.x, res.nfev, res.status > 0, res.message

    def _rust_solver(self):
        """The Rust solver settings, validating solver_options."""
        try:
            return _core.WindowSolver(**self.solver_options)
        except (TypeError, ValueError) as e:
            raise ValueError(f"solver_options: {e}") from None

    _SOLVERS = {
        "gauss-newton": None,  # the Rust core's own solver: `_core.MovingHorizon.update`
        "trust-constr": "_solve_trust_constr",
        "least-squares": "_solve_least_squares",
    }

    # ---- checkpoints: save and load ---------------------------------------------------------
    @staticmethod
    def _read_outcome(f, n, k, scale):
        """The core's record of the last update (core_outcome_*) in a file of format >= 3."""
        na = n + k
        return {"outcome_x_prior": f.floats("core_outcome_x_prior", (na,)),
                "outcome_P": f.floats("core_outcome_P", (na, na)),
                "outcome_cost": f.float("core_outcome_cost"),
                "outcome_success": f.boolean("core_outcome_success"),
                "outcome_nit": f.integer("core_outcome_nit"),
                "outcome_nfev": f.integer("core_outcome_nfev"),
                "outcome_projected_gradient": f.float("core_outcome_projected_gradient"),
                "outcome_message": f.string("core_outcome_message"),
                "outcome_input_pending": f.boolean("core_outcome_input_pending")}

    @staticmethod
    def _outcome_of_format2(f, t_core, n, k, scale):
        """The core's record of the last update from the attributes a file of format 1 or 2
        saved beside the core's state (P and P_p become the blocks of the augmented
        covariance; their cross-covariance was not saved and is zero)."""
        t = f.integer("t")
        if t != t_core:
            raise f.error("core_t", f"is {t_core} but entry 't' is {t}")
        P = f.floats("P", (n, n))
        x_prior = f.floats("x_prior", (n,))
        if k:
            P = scipy.linalg.block_diag(P, f.floats("P_p", (k, k)) / np.outer(scale, scale))
            x_prior = np.concatenate([x_prior, f.floats("p", (k,)) / scale])
        return {"outcome_x_prior": x_prior, "outcome_P": np.ascontiguousarray(P),
                "outcome_cost": f.float("cost"), "outcome_success": f.boolean("success"),
                "outcome_nit": f.integer("nit"), "outcome_nfev": f.integer("nfev"),
                "outcome_projected_gradient": f.float("projected_gradient"),
                "outcome_message": f.string("message"),
                "outcome_input_pending": (f.boolean("input_pending") if f.version >= 2
                                          else False)}

    # (Copies and pickles need no code here: the Rust core copies and pickles itself with its
    # whole state; its model's GPs are shared, not copied.)

    # 2: arrival cost, full weights, parameters, pending input; 3: the estimate and the last
    # update's report only in the core's state (core_outcome_*), not also as attributes.
    _CHECKPOINT_VERSION = 3

    def save(self, path):
        """Write the estimator's whole state (settings, history, attributes) to an ``.npz`` file.

        The file holds plain arrays only (no pickle); the model is not saved: give it again to
        `load`. An estimator loaded from the file continues exactly (bit for bit) as this one
        would with the same data.

        Parameters
        ----------
        path : str, os.PathLike or file-like object
            Destination, passed to `numpy.savez` (which appends ``.npz`` to a name without it).

        Raises
        ------
        ValueError
            If ``solver_options`` holds values that cannot be written (only numbers, strings,
            booleans, None, lists and dicts of them can).

        See Also
        --------
        load : Continue from the file.

        Examples
        --------
        >>> import io
        >>> import numpy as np
        >>> from gpmhe import GPMHE, KnownModel
        >>> from gpmhe.systems import batch_reactor as br
        >>> model = KnownModel(br.f, br.h, dim_x=2, dim_y=1)
        >>> _, y = br.simulate(br.X_TRUE0, 12, np.random.default_rng(0))
        >>> mhe = GPMHE(model, x0=[3.0, 1.0], horizon=5, Q0=1e-3, R0=1e-2, x_bounds=br.X_BOUNDS)
        >>> xs, _ = mhe.batch_filter(y[:6])
        >>> buf = io.BytesIO()
        >>> mhe.save(buf)
        >>> _ = buf.seek(0)
        >>> restored = GPMHE.load(buf, model)
        >>> restored.t
        6
        >>> a, _ = mhe.batch_filter(y[6:12])
        >>> b, _ = restored.batch_filter(y[6:12])
        >>> bool(np.array_equal(a, b))
        True
        """
        import json

        try:
            options = json.dumps(self.solver_options)
        except (TypeError, ValueError) as e:
            raise ValueError(f"solver_options: cannot be saved ({e})") from None
        core = self._core.__getstate__()
        lb, ub = self.x_bounds
        k = self.dim_p
        parameters = {} if not k else dict(
            p0=self.p0, P_p0=self.P_p0, p_lower=self.p_bounds[0], p_upper=self.p_bounds[1],
            p_drift=self.p_drift)
        np.savez(
            path, kind="GPMHE", format_version=self._CHECKPOINT_VERSION,
            model_kind=type(self.model).__name__, dim_x=self.dim_x, dim_y=self.dim_y,
            dim_u=self.dim_u, dim_p=k, horizon=self.horizon, eta=self.eta, P2=self.P2,
            Q0=self.Q0, R0=self.R0, x_lower=lb, x_upper=ub, form=self.form, solver=self.solver,
            solver_options=options, arrival_mean=self.arrival_mean,
            arrival_weight=self.arrival_weight, **parameters,
            **{"core_" + key: value for key, value in core.items()})

    @classmethod
    def load(cls, path, model):
        """Continue an estimator from a file written by `save`.

        Parameters
        ----------
        path : str, os.PathLike or file-like object
            The ``.npz`` file. It is read without pickle (``allow_pickle=False``), so a file from
            an untrusted source cannot run code.
        model : LearnedModel or KnownModel
            The model the saved estimator ran on (models are not saved with the estimator). It
            must be of the same class and dimensions; for bit-identical continuation it must be
            the same model (for a `LearnedModel`, e.g. saved with `LearnedModel.save`).

        Returns
        -------
        GPMHE
            The estimator with the saved settings, history and attributes.

        Raises
        ------
        ValueError
            If the file cannot be read, is not a saved GPMHE, or an entry is missing, damaged or
            inconsistent (the message names the file and the entry), or if `model` does not fit.

        See Also
        --------
        save : Write the file.

        Examples
        --------
        >>> import io
        >>> import numpy as np
        >>> from gpmhe import GPMHE, KnownModel
        >>> from gpmhe.systems import batch_reactor as br
        >>> model = KnownModel(br.f, br.h, dim_x=2, dim_y=1)
        >>> mhe = GPMHE(model, x0=[3.0, 1.0], horizon=3, x_bounds=br.X_BOUNDS)
        >>> _ = mhe.update(None, [4.2])
        >>> buf = io.BytesIO()
        >>> mhe.save(buf)
        >>> _ = buf.seek(0)
        >>> loaded = GPMHE.load(buf, model)
        >>> loaded.t, bool(np.array_equal(loaded.x, mhe.x))
        (1, True)
        """
        import json

        from gpmhe._npz import NpzReader

        with NpzReader(path, "GPMHE", cls._CHECKPOINT_VERSION) as f:
            f.allow_nonfinite = ("x_lower", "x_upper", "p_lower", "p_upper", "cost",
                                 "projected_gradient", "core_outcome_cost",
                                 "core_outcome_projected_gradient")
            v2 = f.version >= 2
            kind = f.string("model_kind")
            if kind not in ("LearnedModel", "KnownModel"):
                raise f.error("model_kind", f"must be 'LearnedModel' or 'KnownModel', got {kind!r}")
            if type(model).__name__ != kind:
                raise ValueError(f"model: the file {f.name} was saved with a {kind} (entry "
                                 f"'model_kind'), got {type(model).__name__}")
            n, p, m = (f.integer(key) for key in ("dim_x", "dim_y", "dim_u"))
            k = f.integer("dim_p") if v2 else 0
            if (getattr(model, "dim_x", None), getattr(model, "dim_y", None),
                    getattr(model, "dim_u", None), getattr(model, "dim_p", 0)) != (n, p, m, k):
                raise ValueError(f"model: the file {f.name} was saved with dim_x={n}, "
                                 f"dim_y={p}, dim_u={m}, dim_p={k}")
            settings = dict(
                horizon=f.integer("horizon", low=1), eta=f.float("eta"),
                P2=f.floats("P2", (n, n)), Q0=f.floats("Q0", (n, n)),
                R0=f.floats("R0", (p, p)) if p else None, form=f.string("form"),
                solver=f.string("solver"))
            if v2:
                settings.update(arrival_mean=f.string("arrival_mean"),
                                arrival_weight=f.string("arrival_weight"))
            if k:
                settings.update(p0=f.floats("p0", (k,)), P_p0=f.floats("P_p0", (k, k)),
                                p_bounds=(f.floats("p_lower", (k,)), f.floats("p_upper", (k,))),
                                p_drift=f.floats("p_drift", (k,)))
            lb, ub = f.floats("x_lower", (n,)), f.floats("x_upper", (n,))
            try:
                options = json.loads(f.string("solver_options"))
            except ValueError as e:
                raise f.error("solver_options", f"is not valid ({e})") from None
            try:
                mhe = cls(model, x0=np.clip(np.zeros(n), lb, ub), x_bounds=(lb, ub),
                          solver_options=options, **settings)
            except ValueError as e:
                raise ValueError(f"path: {f.name}: the saved settings are invalid ({e})") from None
            na = n + k
            state = {"t": f.integer("core_t"), "window_t0": f.integer("core_window_t0"),
                     "present": f.array("core_present", "b", (None,))}
            for key, cols in (("u", m), ("y", p), ("priors", na), ("x_window", na)):
                state[key] = f.floats("core_" + key, (None, cols))
            if v2:
                state["arrival_sqrt"] = f.floats("core_arrival_sqrt", (na, na))
            if kind == "LearnedModel":
                for key in ("d", "mean_x", "var_x", "dmean_x", "dvar_x", "mean_y", "var_y",
                            "dmean_y", "dvar_y"):
                    state["cache_" + key] = f.floats("core_cache_" + key, (None,))
            state.update(cls._read_outcome(f, n, k, mhe._p_scale) if f.version >= 3
                         else cls._outcome_of_format2(f, state["t"], n, k, mhe._p_scale))
            try:
                mhe._core.__setstate__(state)
            except ValueError as e:
                raise f.state_error("core_", e) from None
        return mhe
