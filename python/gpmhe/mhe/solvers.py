"""SciPy's window solvers for `GPMHE` ("trust-constr", "least-squares"): general reference
methods on the same Rust window the real-time solver works on.

The estimator stages a window with the core's ``prepare``; `solve` runs the chosen SciPy method
on the window's cost, gradient, Gauss-Newton Hessian, residuals and Jacobian (all evaluated by
the core), keeps the better of its result and the warm start, and returns what the core's
``commit`` records, with the covariance of the newest node (`window_covariance`). See the user
guide, *The SciPy reference solvers*.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.optimize import Bounds, least_squares, lsq_linear, minimize

__all__ = ["solve", "window_covariance", "gn_decrement"]

#: The "trust-constr" decrement stop: tested once SciPy's barrier parameter is at most this (two
#: reductions from its initial 0.1), at the iterate and after up to TC_GN_STEPS projected
#: Gauss-Newton steps from it.
TC_DECREMENT_BARRIER = 1e-2
TC_GN_STEPS = 3


def gn_decrement(window, z, lb, ub):
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


class _Trials:
    """The staged window as SciPy's methods see it: at a point where the model cannot be
    evaluated (it raised an ArithmeticError, such as `gpmhe.models.base.ModelDomainError` for
    NaN output, or a RuntimeError, such as `gpmhe.NumericalError`) the values are non-finite
    instead, and SciPy's trust-region methods reject that step and shrink the region, as the
    Rust solver does. The start point is evaluated on the window itself (`solve`), where such a
    failure is an error."""

    _FAILED = (ArithmeticError, RuntimeError)

    def __init__(self, window):
        self.window = window
        self._n_residuals = None  # known from the first evaluation (at the start point)

    def cost(self, z):
        try:
            return self.window.cost(z)
        except self._FAILED:
            return np.inf

    def cost_grad(self, z):
        try:
            return self.window.cost_grad(z)
        except self._FAILED:
            return np.inf, np.full(len(z), np.nan)

    def residuals(self, z):
        try:
            r = self.window.residuals(z)
        except self._FAILED:
            if self._n_residuals is None:
                raise
            return np.full(self._n_residuals, np.nan)
        self._n_residuals = len(r)
        return r

    def jacobian(self, z):
        try:
            return self.window.jacobian(z)
        except self._FAILED:
            if self._n_residuals is None:
                raise
            return np.full((self._n_residuals, len(z)), np.nan)

    def gn_hessian(self, z):
        try:
            return self.window.gn_hessian(z)
        except self._FAILED:
            return np.full((len(z), len(z)), np.nan)


def solve(solver, options, window, z0, lb, ub):
    """Solve the staged window with SciPy's ``solver`` from z0 and keep the better of the result
    and z0: returns (z, cost, success, nit, message)."""
    cost0 = window.cost(z0)
    method = _trust_constr if solver == "trust-constr" else _least_squares
    try:
        z, nit, ok, message = method(options, _Trials(window), z0, lb, ub)
        z = np.clip(np.asarray(z, dtype=np.float64), lb, ub)
        cost = window.cost(z) if np.all(np.isfinite(z)) else np.inf
    except (ValueError, ArithmeticError, np.linalg.LinAlgError, RuntimeError) as e:
        z, nit, ok, message, cost = z0, 0, False, f"solver raised: {e}", np.inf
    if not np.isfinite(cost) or cost > cost0:
        if ok:
            message = f"solver returned a point costlier than its start ({message})"
        z, cost, ok = z0.copy(), cost0, False
    return z, float(cost), bool(ok), int(nit), str(message)


def window_covariance(window, z, n):
    """Every diagonal n×n block of 4 H⁻¹ at z, stacked (nodes·n·n,), or with discounted rows
    (η < 1) of the sandwich 4 H⁻¹GH⁻¹, G = 2JᵀWJ with W the rows' discounts (the Rust solve
    returns the same blocks from its block-tridiagonal factorisation); None if H is singular."""
    H = window.gn_hessian(z)
    try:
        Hinv = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return None
    discounts = window.row_discounts(z)
    if np.any(discounts != 1.0):
        jac = window.jacobian(z)
        Hinv = Hinv @ (2.0 * jac.T @ (discounts[:, None] * jac)) @ Hinv
    nodes = len(z) // n
    blocks = np.array([Hinv[i * n:(i + 1) * n, i * n:(i + 1) * n] for i in range(nodes)])
    blocks = 2.0 * (blocks + blocks.transpose(0, 2, 1))
    return blocks.ravel() if np.all(np.isfinite(blocks)) else None


def _trust_constr(user_options, window, z0, lb, ub):
    """SciPy's interior-point method, stopped by the Gauss-Newton decrement (`gn_decrement`)."""
    options = dict(gtol=1e-6, xtol=1e-8, maxiter=200, initial_barrier_parameter=0.1)
    options.update(user_options)
    dtol = options.pop("dtol", 1e-4)
    stop = {}

    def decrement_stop(xk, state):
        # SciPy's (xk, state) callback of "trust-constr" (every SciPy >= 1.10): True stops the
        # solve with status 3. Not while the barrier steers the iterates away from the bounds
        # (and from the bound-pinned local minima there). Without finite bounds SciPy runs its
        # SQP method, which has no barrier.
        if not getattr(state, "barrier_parameter", 0.0) <= TC_DECREMENT_BARRIER:
            return False
        z = np.clip(xk, lb, ub)
        decrement, step, cost = gn_decrement(window, z, lb, ub)
        # SciPy's barrier method creeps along flat directions close to a bound; a few projected
        # Gauss-Newton steps from its iterate (each must lower J) finish there.
        for k in range(TC_GN_STEPS + 1):
            if decrement <= dtol:
                stop.update(z=z, decrement=decrement, steps=k)
                return True
            if k == TC_GN_STEPS or step is None:
                return False
            z_new = np.clip(z + step, lb, ub)
            decrement_new, step_new, cost_new = gn_decrement(window, z_new, lb, ub)
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


def _least_squares(user_options, window, z0, lb, ub):
    """SciPy's bounded trust-region reflective method on the stacked residuals."""
    options = dict(ftol=1e-10, xtol=1e-10, gtol=1e-10, max_nfev=200)
    options.update(user_options)
    res = least_squares(window.residuals, z0, jac=window.jacobian, bounds=(lb, ub),
                        method="trf", **options)
    return res.x, res.nfev, res.status > 0, res.message
