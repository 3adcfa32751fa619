"""Discretisation of continuous-time models dx/dt = F(x, u) over one sample time, for
`KnownModel`: explicit Runge-Kutta 4 with sub-steps, and for stiff models the implicit midpoint
rule or backward Euler (Newton's method at every sub-step), each with the exact Jacobian of the
discrete map. See the user guide, *Physics models*.

The input u is held constant over the sample time (zero-order hold). With a CasADi right-hand
side the integrator is built symbolically (the implicit steps as CasADi rootfinders), so CasADi's
AD differentiates the discrete map exactly; with a numpy right-hand side the Jacobian is carried
through the integrator step by step (the variational equation, discretised by the same scheme).
"""

from __future__ import annotations

import sys

import numpy as np

from gpmhe._core import NumericalError
from gpmhe._validation import integer, one_of, positive_scalar

__all__ = ["discretize", "DiscreteDynamics", "METHODS"]

#: The integration schemes of `discretize`.
METHODS = ("rk4", "implicit-midpoint", "backward-euler")

#: The implicit schemes as θ-methods: z = x + h F(x + θ (z − x), u).
_THETA = {"implicit-midpoint": 0.5, "backward-euler": 1.0}


def is_casadi_function(obj):
    """Whether ``obj`` is a ``casadi.Function`` (without importing CasADi: if it is not imported,
    nothing is one)."""
    ca = sys.modules.get("casadi")
    return ca is not None and isinstance(obj, getattr(ca, "Function", ()))


def _settings(dt, substeps, method, fd_step, newton_tol, newton_max_iter):
    return (positive_scalar("dt", dt), integer("substeps", substeps, low=1),
            one_of("method", method, METHODS), positive_scalar("fd_step", fd_step),
            positive_scalar("newton_tol", newton_tol), integer("newton_max_iter", newton_max_iter, low=1))


def discretize(rhs, dt, substeps=1, method="rk4", rhs_jacobian=None, fd_step=1e-6,
               newton_tol=1e-10, newton_max_iter=20):
    """The discrete-time map x(t+1) = f(x(t), u(t)) of a continuous-time model dx/dt = F(x, u).

    The sample time ``dt`` is split into ``substeps`` equal steps h = dt / substeps of the chosen
    scheme, u held constant:

    * ``"rk4"``: the classic explicit Runge-Kutta method of order 4. Stable only while h times
      the largest eigenvalue magnitude of ∂F/∂x stays below about 2.8: stiff models need many
      sub-steps, or an implicit scheme.
    * ``"implicit-midpoint"``: z = x + h F((x + z)/2, u), order 2, A-stable (stiff components
      are not damped: a fast mode oscillates in sign).
    * ``"backward-euler"``: z = x + h F(z, u), order 1, L-stable (stiff components decay at once).

    The implicit equations are solved by Newton's method from z = x, stopping when the residual's
    largest entry is at most ``newton_tol``.

    Parameters
    ----------
    rhs : callable or casadi.Function
        The right-hand side F. A numpy callable ``rhs(X, U)`` is vectorised: X of shape (k, n),
        U of shape (k, m) (m = 0 columns without input), returning (k, n), one row per point. A
        ``casadi.Function`` takes x or (x, u) (dense vectors) and returns dx/dt.
    dt : float
        Sample time (> 0).
    substeps : int, default 1
        Integration steps per sample time (>= 1).
    method : {"rk4", "implicit-midpoint", "backward-euler"}, default "rk4"
        The scheme.
    rhs_jacobian : callable or None, default None
        Numpy only: ``rhs_jacobian(X, U)`` returning ∂F/∂x of shape (k, n, n). None: central
        finite differences with step ``fd_step`` · max(1, abs(x_i)).
    fd_step : float, default 1e-6
        Numpy only: relative step of the finite differences.
    newton_tol : float, default 1e-10
        Implicit schemes: Newton's method stops when max abs(residual) <= newton_tol (CasADi:
        its rootfinder's ``abstol`` and ``abstolStep``).
    newton_max_iter : int, default 20
        Implicit schemes: the most Newton iterations per sub-step.

    Returns
    -------
    DiscreteDynamics or casadi.Function
        For a numpy ``rhs``, the map as a `DiscreteDynamics` (vectorised, with ``jacobian``);
        for a CasADi ``rhs``, a ``casadi.Function`` f(x, u) -> x_next with the inputs of ``rhs``,
        ready for `KnownModel.from_casadi` (expanded to SX where CasADi can).

    Raises
    ------
    ValueError
        If a setting is invalid, ``rhs`` is neither callable nor a CasADi function of the right
        signature, or ``rhs_jacobian`` is given with a CasADi ``rhs``.
    ImportError
        If ``rhs`` is a CasADi function and CasADi is older than 3.6.

    See Also
    --------
    KnownModel.from_ode : The discretised model with its output function, for `GPMHE`.

    Notes
    -----
    The Jacobian is the exact derivative of the discrete map (up to rounding, and to the finite
    differences of ∂F/∂x without ``rhs_jacobian``). RK4 carries S = ∂z/∂x(0) through its stages
    (k_i' = ∂F/∂x(z_i) (S + c_i h k_{i−1}')); an implicit step multiplies S by
    ∂z/∂x = (I − hθ A)⁻¹ (I + h(1 − θ) A), A = ∂F/∂x at the solution (the implicit function
    theorem; θ = 1/2 or 1).

    Examples
    --------
    A damped pendulum (angle, angular velocity) driven by a torque u, 4 RK4 steps per 0.1 s:

    >>> import numpy as np
    >>> from gpmhe import discretize
    >>> def pendulum(X, U):
    ...     return np.column_stack([X[:, 1], -9.81 * np.sin(X[:, 0]) - 0.5 * X[:, 1] + U[:, 0]])
    >>> f = discretize(pendulum, dt=0.1, substeps=4)
    >>> print(np.round(f([[0.5, 0.0]], [[0.0]]), 4))
    [[ 0.477  -0.4522]]
    >>> f.jacobian([[0.5, 0.0]], [[0.0]]).shape
    (1, 2, 2)
    """
    dt, substeps, method, fd_step, newton_tol, newton_max_iter = _settings(
        dt, substeps, method, fd_step, newton_tol, newton_max_iter)
    if is_casadi_function(rhs):
        if rhs_jacobian is not None:
            raise ValueError("rhs_jacobian: not used with a CasADi rhs (CasADi differentiates it)")
        return _casadi_discretize(rhs, dt, substeps, method, newton_tol, newton_max_iter)
    return DiscreteDynamics(rhs, dt, substeps, method, rhs_jacobian, fd_step, newton_tol,
                            newton_max_iter)


def _casadi_discretize(rhs, dt, substeps, method, newton_tol, newton_max_iter, timed=False):
    """The discrete map of a CasADi rhs(x[, u]) as a CasADi Function with rhs's inputs; with
    ``timed`` the interval is not ``dt`` but the last entry of the input v = [u; dt], so the map
    is f(x, v) (for the estimator's per-sample intervals)."""
    from gpmhe.models.casadi import _vec_call, import_casadi, signature

    ca = import_casadi("discretize with a CasADi rhs")
    n, m, n_out = signature(ca, "rhs", rhs)
    if n == 0:
        raise ValueError(f"rhs: the state x must have at least one value, got 0 in {rhs}")
    if n_out != n:
        raise ValueError(f"rhs: returns {n_out} values, expected one per state ({n}) in {rhs}")
    x = ca.MX.sym("x", n)
    if timed:
        v = ca.MX.sym("u", (m or 0) + 1)
        u, h = v[:m or 0], v[m or 0] / substeps
    else:
        u, h = ca.MX.sym("u", m or 0), dt / substeps
    z = x
    if method == "rk4":
        for _ in range(substeps):
            k1 = _vec_call(ca, rhs, z, u)
            k2 = _vec_call(ca, rhs, z + (h / 2) * k1, u)
            k3 = _vec_call(ca, rhs, z + (h / 2) * k2, u)
            k4 = _vec_call(ca, rhs, z + h * k3, u)
            z = z + (h / 6) * (k1 + 2 * k2 + 2 * k3 + k4)
    else:
        step = _implicit_step(ca, rhs, n, m, method, newton_tol, newton_max_iter,
                              None if timed else h)
        for _ in range(substeps):
            z = step(z, z, u, h) if timed else step(z, z, u)
    if timed:
        inputs, names = [x, v], ["x", "u"]
    else:
        inputs, names = ([x, u], ["x", "u"]) if m is not None else ([x], ["x"])
    f = ca.Function(f"{rhs.name()}_discrete", inputs, [z], names, ["x_next"])
    try:
        return f.expand()
    except RuntimeError:  # an MX-only operation in rhs
        return f


def _implicit_step(ca, rhs, n, m, method, newton_tol, newton_max_iter, h):
    """One θ-method sub-step of length ``h`` as a CasADi rootfinder z(z0, x, u); ``h`` None: of
    the length given as a fourth input, z(z0, x, u, h)."""
    from gpmhe.models.casadi import _vec_call

    theta = _THETA[method]
    zs, xs, us = ca.MX.sym("z", n), ca.MX.sym("x", n), ca.MX.sym("u", m or 0)
    extra = [] if h is not None else [ca.MX.sym("h")]
    if h is None:
        h = extra[0]
    residual = ca.Function("residual", [zs, xs, us] + extra,
                           [zs - xs - h * _vec_call(ca, rhs, xs + theta * (zs - xs), us)])
    try:
        residual = residual.expand()
    except RuntimeError:
        pass
    return ca.rootfinder(f"{rhs.name()}_{method.replace('-', '_')}", "newton", residual,
                         {"abstol": newton_tol, "abstolStep": newton_tol,
                          "max_iter": newton_max_iter, "error_on_fail": True,
                          # plain Newton from z = x, as the numpy scheme: CasADi's line search
                          # stalls on stiff steps (steps of 1e-2 where one full step converges)
                          "line_search": False})


class DiscreteDynamics:
    """The discrete map x(t+1) = f(x(t), u(t)) of dx/dt = F(x, u) with numpy callables, made by
    `discretize`.

    Calling it integrates all rows at once; `jacobian` and `value_and_jacobian` also return
    ∂f/∂x, carried through the integrator (see `discretize`, Notes). It pickles if ``rhs`` and
    ``rhs_jacobian`` do.

    Parameters
    ----------
    rhs : callable
        ``rhs(X, U)``: dx/dt for X (k, n) and U (k, m), returning (k, n).
    dt : float
        Sample time.
    substeps : int, default 1
        Integration steps per sample time.
    method : {"rk4", "implicit-midpoint", "backward-euler"}, default "rk4"
        The scheme.
    rhs_jacobian : callable or None, default None
        ``rhs_jacobian(X, U)``: ∂F/∂x of shape (k, n, n); None: central finite differences.
    fd_step : float, default 1e-6
        Relative step of the finite differences.
    newton_tol : float, default 1e-10
        Newton's stopping tolerance on the residual (implicit schemes).
    newton_max_iter : int, default 20
        The most Newton iterations per sub-step (implicit schemes).

    Attributes
    ----------
    rhs, rhs_jacobian : callable or None
        As given.
    dt, substeps, method, fd_step, newton_tol, newton_max_iter
        The settings.

    Raises
    ------
    ValueError
        If a setting is invalid or ``rhs`` (``rhs_jacobian``) is not callable.

    See Also
    --------
    discretize : Makes this object (the usual way).

    Examples
    --------
    Exponential decay dx/dt = −x integrated over one second: RK4's error shrinks with the fourth
    power of the step.

    >>> import numpy as np
    >>> from gpmhe import DiscreteDynamics
    >>> for substeps in (1, 2, 4):
    ...     f = DiscreteDynamics(lambda X, U: -X, dt=1.0, substeps=substeps)
    ...     print(substeps, f"{abs(f([1.0])[0] - np.exp(-1.0)):.1e}")
    1 7.1e-03
    2 2.9e-04
    4 1.5e-05
    """

    def __init__(self, rhs, dt, substeps=1, method="rk4", rhs_jacobian=None, fd_step=1e-6,
                 newton_tol=1e-10, newton_max_iter=20):
        if not callable(rhs):
            raise ValueError(f"rhs: must be callable or a casadi.Function, got {type(rhs).__name__}")
        if rhs_jacobian is not None and not callable(rhs_jacobian):
            raise ValueError("rhs_jacobian: must be callable or None")
        (self.dt, self.substeps, self.method, self.fd_step, self.newton_tol,
         self.newton_max_iter) = _settings(dt, substeps, method, fd_step, newton_tol, newton_max_iter)
        self.rhs, self.rhs_jacobian = rhs, rhs_jacobian

    def __repr__(self):
        name = getattr(self.rhs, "__name__", type(self.rhs).__name__)
        return (f"DiscreteDynamics({name}, dt={self.dt:g}, substeps={self.substeps}, "
                f"method={self.method!r})")

    # ---- evaluation -----------------------------------------------------------------------
    def __call__(self, X, U=None):
        """x(t+1) at every row of X (and U).

        Parameters
        ----------
        X : array_like of shape (k, n) or (n,)
            States, one per row (1-D: one state).
        U : array_like of shape (k, m) or (m,), or None, default None
            Inputs; None for no input.

        Returns
        -------
        ndarray of shape (k, n) or (n,)
            The next states (1-D for a 1-D X).

        Raises
        ------
        ValueError
            If X or U has the wrong shape or ``rhs`` returns the wrong shape.
        gpmhe.NumericalError
            If Newton's method does not converge (implicit schemes).

        Examples
        --------
        >>> from gpmhe import DiscreteDynamics
        >>> f = DiscreteDynamics(lambda X, U: U - X, dt=0.5, method="backward-euler")
        >>> print(f([1.0, 2.0], [1.0, 0.0]))
        [1.         1.33333333]
        """
        X2, U2, one = self._points(X, U)
        Z = self._integrate(X2, U2, jacobian=False)[0]
        return Z[0] if one else Z

    def jacobian(self, X, U=None):
        """∂f/∂x at every row of X (and U).

        Parameters
        ----------
        X : array_like of shape (k, n) or (n,)
            States, one per row (1-D: one state).
        U : array_like of shape (k, m) or (m,), or None, default None
            Inputs; None for no input.

        Returns
        -------
        ndarray of shape (k, n, n) or (n, n)
            The Jacobians of the discrete map ((n, n) for a 1-D X).

        Raises
        ------
        ValueError
            If X or U has the wrong shape or ``rhs`` (``rhs_jacobian``) returns the wrong shape.
        gpmhe.NumericalError
            If Newton's method does not converge (implicit schemes).

        Examples
        --------
        dx/dt = −2x over 0.1 s: f(x) = e^{−0.2} x, up to RK4's error.

        >>> import numpy as np
        >>> from gpmhe import DiscreteDynamics
        >>> f = DiscreteDynamics(lambda X, U: -2.0 * X, dt=0.1, substeps=2)
        >>> print(np.round(f.jacobian([1.0]), 6), np.round(np.exp(-0.2), 6))
        [[0.818731]] 0.818731
        """
        return self.value_and_jacobian(X, U)[1]

    def value_and_jacobian(self, X, U=None):
        """x(t+1) and ∂f/∂x at every row of X (and U), in one pass of the integrator.

        Parameters
        ----------
        X : array_like of shape (k, n) or (n,)
            States, one per row (1-D: one state).
        U : array_like of shape (k, m) or (m,), or None, default None
            Inputs; None for no input.

        Returns
        -------
        value : ndarray of shape (k, n) or (n,)
            The next states.
        jacobian : ndarray of shape (k, n, n) or (n, n)
            Their Jacobians.

        Raises
        ------
        ValueError
            If X or U has the wrong shape or ``rhs`` (``rhs_jacobian``) returns the wrong shape.
        gpmhe.NumericalError
            If Newton's method does not converge (implicit schemes).

        Examples
        --------
        >>> from gpmhe import DiscreteDynamics
        >>> f = DiscreteDynamics(lambda X, U: -X, dt=0.1, method="implicit-midpoint")
        >>> value, jac = f.value_and_jacobian([[2.0]])
        >>> print(value, jac)  # (1 − h/2) / (1 + h/2) = 0.9047...
        [[1.80952381]] [[[0.9047619]]]
        """
        X2, U2, one = self._points(X, U)
        Z, S = self._integrate(X2, U2, jacobian=True)
        return (Z[0], S[0]) if one else (Z, S)

    # ---- internals --------------------------------------------------------------------------
    def _integrate(self, X, U, jacobian, dt=None):
        """(Z, S) of the scheme over every row (S None without ``jacobian``); ``dt`` None: the
        map's own interval, else a (k, 1) column of each row's."""
        scheme = self._rk4 if self.method == "rk4" else self._implicit
        return scheme(X, U, jacobian, dt)

    @staticmethod
    def _points(X, U):
        """X (k, n), U (k, m) as float64 arrays and whether X was one 1-D state."""
        try:
            X = np.asarray(X, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError("X: must be an array of numbers") from None
        one = X.ndim == 1
        if one:
            X = X[None, :]
        if X.ndim != 2 or X.shape[1] == 0:
            raise ValueError(f"X: must have shape (k, n) or (n,) with n >= 1, got {X.shape}")
        k = X.shape[0]
        if U is None:
            return X, np.zeros((k, 0)), one
        try:
            U = np.asarray(U, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError("U: must be an array of numbers") from None
        if U.ndim == 1 and one:
            U = U[None, :]
        if U.ndim != 2 or U.shape[0] != k:
            raise ValueError(f"U: must have shape ({k}, m), one row per state, got {U.shape}")
        return X, U, one

    def _F(self, Z, U):
        v = np.asarray(self.rhs(Z, U), dtype=np.float64)
        if v.shape != Z.shape:
            raise ValueError(f"rhs: returned shape {v.shape}, expected {Z.shape} (one row per point)")
        return v

    def _FA(self, Z, U):
        """F (k, n) and A = ∂F/∂x (k, n, n) at the rows of Z."""
        k, n = Z.shape
        if self.rhs_jacobian is not None:
            A = np.asarray(self.rhs_jacobian(Z, U), dtype=np.float64)
            if A.shape != (k, n, n):
                raise ValueError(f"rhs_jacobian: returned shape {A.shape}, expected {(k, n, n)}")
            return self._F(Z, U), A
        steps = self.fd_step * np.maximum(1.0, np.abs(Z))           # (k, n)
        shifted = np.repeat(Z[None], 2 * n + 1, axis=0)              # (2n+1, k, n)
        idx = np.arange(n)
        shifted[1 + idx, :, idx] += steps.T
        shifted[1 + n + idx, :, idx] -= steps.T
        out = np.asarray(self.rhs(shifted.reshape(-1, n), np.tile(U, (2 * n + 1, 1))), dtype=np.float64)
        if out.shape != ((2 * n + 1) * k, n):
            raise ValueError(f"rhs: returned shape {out.shape}, expected {((2 * n + 1) * k, n)} "
                             f"(one row per point: {k} points and their finite-difference shifts)")
        out = out.reshape(2 * n + 1, k, n)
        A = (out[1:n + 1] - out[n + 1:]) / (2.0 * steps.T[:, :, None])  # (n, k, n): [j, i, :]
        return out[0], np.ascontiguousarray(A.transpose(1, 2, 0))

    def _steps(self, dt):
        """The sub-step length h for the state rows and for the (k, n, n) sensitivities: the
        scalar dt / substeps, or per row for a (k, 1) column of intervals ``dt``."""
        if dt is None:
            h = self.dt / self.substeps
            return h, h
        h = dt / self.substeps
        return h, h[:, :, None]

    def _rk4(self, X, U, jacobian, dt=None):
        h, hs = self._steps(dt)
        Z = X.copy()
        S = np.broadcast_to(np.eye(X.shape[1]), (X.shape[0],) + (X.shape[1],) * 2).copy() if jacobian else None
        for _ in range(self.substeps):
            if not jacobian:
                k1 = self._F(Z, U)
                k2 = self._F(Z + (h / 2) * k1, U)
                k3 = self._F(Z + (h / 2) * k2, U)
                k4 = self._F(Z + h * k3, U)
            else:
                k1, A = self._FA(Z, U)
                d1 = A @ S
                k2, A = self._FA(Z + (h / 2) * k1, U)
                d2 = A @ (S + (hs / 2) * d1)
                k3, A = self._FA(Z + (h / 2) * k2, U)
                d3 = A @ (S + (hs / 2) * d2)
                k4, A = self._FA(Z + h * k3, U)
                d4 = A @ (S + hs * d3)
                S = S + (hs / 6) * (d1 + 2.0 * d2 + 2.0 * d3 + d4)
            Z = Z + (h / 6) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        return Z, S

    def _implicit(self, X, U, jacobian, dt=None):
        """θ-method sub-steps z = x + h F(x + θ(z − x), u), Newton from z = x."""
        (h, hs), theta = self._steps(dt), _THETA[self.method]
        k, n = X.shape
        eye = np.eye(n)
        Z = X.copy()
        S = np.broadcast_to(eye, (k, n, n)).copy() if jacobian else None
        for _ in range(self.substeps):
            x = Z
            z = x.copy()
            for _ in range(self.newton_max_iter + 1):
                F, A = self._FA(x + theta * (z - x), U)
                r = z - x - h * F
                worst = float(np.max(np.abs(r)))
                if worst <= self.newton_tol:
                    break
                if not np.isfinite(worst):
                    raise NumericalError(f"discretize ({self.method}): Newton's method met NaN or inf")
                z = z - np.linalg.solve(eye - (hs * theta) * A, r[:, :, None])[:, :, 0]
            else:
                raise NumericalError(
                    f"discretize ({self.method}): Newton's method did not converge in "
                    f"{self.newton_max_iter} iterations (largest residual {worst:.3g} > newton_tol = "
                    f"{self.newton_tol:g}); try more substeps")
            if jacobian:
                # the implicit function theorem at the solution: ∂z/∂x
                S = np.linalg.solve(eye - (hs * theta) * A, eye + (hs * (1.0 - theta)) * A) @ S
            Z = z
        return Z, S


class TimedDynamics:
    """A `DiscreteDynamics` whose interval is given per point: the last column of U (k, m + 1)
    is each row's dt, the others are u. What the estimator runs for per-sample intervals
    (`GPMHE.update`'s ``dt``); with every dt equal to the map's own, the values are bit for bit
    the map's."""

    def __init__(self, dynamics):
        self.dynamics = dynamics

    def _run(self, X, U, jacobian):
        X2, U2, one = self.dynamics._points(X, U)
        Z, S = self.dynamics._integrate(X2, U2[:, :-1], jacobian, U2[:, -1:])
        return (Z[0], None if S is None else S[0]) if one else (Z, S)

    def __call__(self, X, U):
        return self._run(X, U, False)[0]

    def jacobian(self, X, U):
        return self._run(X, U, True)[1]

    def value_and_jacobian(self, X, U):
        return self._run(X, U, True)


class WithoutTime:
    """``fn(X, U)`` of a model's output (or its Jacobian) called with U's last column, the
    interval, left out: y = h(x, u) does not depend on it."""

    def __init__(self, fn):
        self.fn = fn

    def __call__(self, X, U):
        return self.fn(X, U[:, :-1])
