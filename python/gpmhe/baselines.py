"""EKF baselines of the GP-MHE paper's comparison, on filterpy's `ExtendedKalmanFilter`:

* `ExactEKF`: filterpy's EKF with a known nonlinear model (f, ∂f/∂x, h, ∂h/∂x): `predict_x` is
  overridden to propagate x through f, as filterpy's documentation suggests, and `predict`,
  `update` supply the model's Jacobians and h.
* `GPEKF`: the same filter on a `gpmhe.LearnedModel` (a GP-EKF): F and H are the GP mean
  Jacobians at the current estimate, and the GP latent variances are added to Q and R.

Loop per step t: `update(y(t))` gives x̂(t|t), then `predict(u(t))` gives x̂(t+1|t).
"""

from __future__ import annotations

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter

from gpmhe._validation import finite_vector, float_array, symmetric_matrix

__all__ = ["ExactEKF", "GPEKF"]


def ExactEKF(f, f_jacobian, h, h_jacobian, x0, P0, Q, R):
    """An EKF with a known nonlinear model: filterpy's `ExtendedKalmanFilter`, set up for it.

    The model is x(t+1) = f(x(t)) + w, w ~ N(0, Q), y(t) = h(x(t)) + v, v ~ N(0, R), without
    an input. ``predict()`` propagates x through f (filterpy's `predict_x` is overridden, as its
    documentation suggests) and P through F = ∂f/∂x at the current estimate:
    x⁻ = f(x), P⁻ = F P Fᵀ + Q. ``update(y)`` is filterpy's EKF update with H = ∂h/∂x and h at
    the predicted state.

    Parameters
    ----------
    f : callable
        Transition ``f(x) -> (dim_x,)`` for a 1-D x.
    f_jacobian : callable
        ``f_jacobian(x) -> (dim_x, dim_x)``, ∂f/∂x.
    h : callable
        Output ``h(x) -> (dim_y,)``.
    h_jacobian : callable
        ``h_jacobian(x) -> (dim_y, dim_x)``, ∂h/∂x.
    x0 : array_like of shape (dim_x,)
        Initial estimate x̂(0).
    P0 : array_like of shape (dim_x, dim_x)
        Initial covariance.
    Q : array_like of shape (dim_x, dim_x)
        Process-noise covariance.
    R : float or array_like of shape (dim_y, dim_y)
        Output-noise covariance.

    Returns
    -------
    filterpy.kalman.ExtendedKalmanFilter
        The filter (a subclass instance). Its ``x`` has shape (dim_x, 1), as in filterpy;
        ``update(y)`` ignores the ``HJacobian`` and ``Hx`` arguments (the model's are used).

    See Also
    --------
    GPEKF : The same filter on a learned model.
    gpmhe.GPMHE : The moving horizon estimator with `gpmhe.KnownModel`.

    Notes
    -----
    Per step t: ``update(y(t))`` gives x̂(t|t), then ``predict()`` gives x̂(t+1|t).

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe.baselines import ExactEKF
    >>> from gpmhe.systems import batch_reactor as br
    >>> x_true, y = br.simulate(br.X_TRUE0, 10, np.random.default_rng(0))
    >>> ekf = ExactEKF(br.f, br.f_jacobian, br.h, br.h_jacobian, x0=[3.0, 1.0],
    ...                P0=0.1 * np.eye(2), Q=1e-3 * np.eye(2), R=1e-2)
    >>> for t in range(10):
    ...     ekf.update(y[t])
    ...     ekf.predict()
    >>> ekf.x.shape
    (2, 1)
    >>> print(np.round(ekf.x.ravel(), 1), np.round(x_true[10], 1))  # x̂(10|9) and x(10)
    [1.5 1.7] [1.5 1.8]
    """

    class _ExactEKF(ExtendedKalmanFilter):
        def predict_x(self, u=0):
            """Propagate the estimate through f: x⁻ = f(x).

            Parameters
            ----------
            u : object, default 0
                Ignored (the model has no input).
            """
            self.x = np.asarray(f(self.x.ravel()), dtype=float).reshape(-1, 1)

        def predict(self, u=0):
            """Predict one step: x⁻ = f(x), P⁻ = F P Fᵀ + Q with F = ∂f/∂x at x.

            Parameters
            ----------
            u : object, default 0
                Ignored (the model has no input); kept for filterpy's signature.
            """
            self.F = np.asarray(f_jacobian(self.x.ravel()), dtype=float)
            super().predict(u)

        def update(self, z, HJacobian=None, Hx=None, R=None, args=(), hx_args=(), residual=np.subtract):
            """filterpy's EKF update with the measurement z, using the model's h and ∂h/∂x.

            Parameters
            ----------
            z : float or array_like of shape (dim_y,)
                The measurement y(t).
            HJacobian, Hx : object, default None
                Ignored (the model's ∂h/∂x and h are used).
            R : array_like or None, default None
                Output-noise covariance for this update only; None uses ``self.R``.
            args, hx_args : tuple, default ()
                Extra arguments, passed on to filterpy.
            residual : callable, default numpy.subtract
                Residual function, passed on to filterpy.
            """
            return super().update(
                _column(z), lambda x: np.asarray(h_jacobian(x.ravel()), dtype=float),
                lambda x: np.asarray(h(x.ravel()), dtype=float).reshape(-1, 1), R=R,
                args=args, hx_args=hx_args, residual=residual)

    _callables(f=f, f_jacobian=f_jacobian, h=h, h_jacobian=h_jacobian)
    x0, P0, Q, R = _initial_values(x0, P0, Q, R)
    ekf = _ExactEKF(dim_x=x0.size, dim_z=R.shape[0])
    ekf.x, ekf.P, ekf.Q, ekf.R = x0.reshape(-1, 1), P0, Q, R
    return ekf


def GPEKF(model, x0, P0, Q, R):
    """An EKF on a learned model (a GP-EKF), on filterpy's `ExtendedKalmanFilter`.

    The model's means replace f and h and its latent variances are added to the noise
    covariances, all evaluated at the current estimate d̂ = [x̂; u]:

    * ``predict(u=None)``: x⁻ = m_x(d̂), P⁻ = F P Fᵀ + Q + diag σ²_x(d̂) with F = ∂m_x/∂x;
    * ``update(y, u=None)``: filterpy's EKF update with H = ∂m_y/∂x, the prediction m_y(d̂) and
      the noise covariance R + diag σ²_y(d̂).

    Parameters
    ----------
    model : LearnedModel or KnownModel
        Any model with ``stage_eval``, ``dim_x`` and ``dim_u`` (a `gpmhe.KnownModel` gives an
        ordinary EKF).
    x0 : array_like of shape (dim_x,)
        Initial estimate x̂(0).
    P0 : array_like of shape (dim_x, dim_x)
        Initial covariance.
    Q : array_like of shape (dim_x, dim_x)
        Process-noise covariance (the GP variances are added at each prediction).
    R : float or array_like of shape (dim_y, dim_y)
        Output-noise covariance (the GP variances are added at each update).

    Returns
    -------
    filterpy.kalman.ExtendedKalmanFilter
        The filter (a subclass instance) with methods ``predict(u=None)`` and
        ``update(z, u=None)``; ``x`` has shape (dim_x, 1), as in filterpy, and ``Q``, ``R`` stay
        as given.

    See Also
    --------
    ExactEKF : The EKF with a known model.
    gpmhe.GPMHE : The moving horizon estimator on the same learned model.

    Notes
    -----
    Per step t: ``update(y(t), u(t))`` gives x̂(t|t), then ``predict(u(t))`` gives x̂(t+1|t).

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe import LearnedModel
    >>> from gpmhe.baselines import GPEKF
    >>> from gpmhe.systems import batch_reactor as br
    >>> states, outputs = br.training_data(3, rng=0, steps=10)
    >>> model = LearnedModel.from_trajectories(states, outputs)
    >>> x_true, y = br.simulate(br.X_TRUE0, 10, np.random.default_rng(0))
    >>> ekf = GPEKF(model, x0=[3.0, 1.0], P0=0.1 * np.eye(2), Q=1e-3 * np.eye(2), R=1e-2)
    >>> for t in range(10):
    ...     ekf.update(y[t])
    ...     ekf.predict()
    >>> print(np.round(ekf.x.ravel(), 1), np.round(x_true[10], 1))  # x̂(10|9) and x(10)
    [1.7 1.6] [1.5 1.8]
    """
    if not all(hasattr(model, a) for a in ("dim_x", "dim_y", "dim_u", "stage_eval")):
        raise ValueError("model: must be a gpmhe.LearnedModel or gpmhe.KnownModel")
    n, m = model.dim_x, model.dim_u

    def point(x, u):
        # The model's input d = [x; u] as one row.
        u = np.zeros(m) if u is None or m == 0 else np.asarray(u, dtype=float).reshape(-1)
        return np.concatenate([x.ravel(), u])[None, :]

    class _GPEKF(ExtendedKalmanFilter):
        def predict(self, u=None):
            """Predict one step: x⁻ = m_x(d̂), P⁻ = F P Fᵀ + Q + diag σ²_x(d̂), d̂ = [x; u].

            Parameters
            ----------
            u : array_like of shape (dim_u,) or None, default None
                Input u(t); None when the model has no input.
            """
            mx, vx, dmx, _, _, _, _, _ = model.stage_eval(point(self.x, u))
            self.F = dmx[0][:, :n]
            Q0 = self.Q
            self.Q = Q0 + np.diag(vx[0])
            try:
                self.x = mx[0].reshape(-1, 1)
                self.P = self.F @ self.P @ self.F.T + self.Q
            finally:
                self.Q = Q0
            self.x_prior, self.P_prior = self.x.copy(), self.P.copy()

        def update(self, z, u=None):
            """EKF update with H = ∂m_y/∂x, m_y(d̂) and the noise R + diag σ²_y(d̂) at d̂ = [x; u].

            Parameters
            ----------
            z : float or array_like of shape (dim_y,)
                The measurement y(t).
            u : array_like of shape (dim_u,) or None, default None
                Input u(t); None when the model has no input.
            """
            _, _, _, _, my, vy, dmy, _ = model.stage_eval(point(self.x, u))
            H = dmy[0][:, :n]
            R_eff = self.R + np.diag(vy[0])
            return super().update(_column(z), lambda x: H, lambda x: my[0].reshape(-1, 1), R=R_eff)

    x0, P0, Q, R = _initial_values(x0, P0, Q, R, n=n, p=model.dim_y)
    ekf = _GPEKF(dim_x=n, dim_z=R.shape[0])
    ekf.x, ekf.P, ekf.Q, ekf.R = x0.reshape(-1, 1), P0, Q, R
    return ekf


def _column(z):
    """A measurement as the column filterpy's update compares with h(x) (p, 1): a flat (p,)
    array would broadcast against it to (p, p)."""
    return np.asarray(z, dtype=float).reshape(-1, 1)


def _initial_values(x0, P0, Q, R, n=None, p=None):
    """x0 as a vector (of n values if given), P0 and Q as symmetric positive semi-definite (n, n)
    matrices, R as a symmetric positive definite (p, p) matrix (a scalar R is R I, 1 x 1 if p is
    not known): float64 copies, errors naming the argument."""
    if n is None:
        x0 = float_array("x0", x0, copy=True)
        if x0.size == 0 or x0.ndim > 2 or (x0.ndim == 2 and 1 not in x0.shape):
            raise ValueError(f"x0: expected a vector (or a row or column), got shape {x0.shape}")
        n = x0.size
    x0 = finite_vector("x0", x0, n, flatten=True).copy()
    P0, Q = symmetric_matrix("P0", P0, n), symmetric_matrix("Q", Q, n)
    if p is None:
        r = float_array("R", R)
        p = r.shape[0] if r.ndim == 2 else 1
    return x0, P0, Q, symmetric_matrix("R", R, p, definite=True)


def _callables(**fns):
    """Refuse any of the named functions that is not callable."""
    for name, fn in fns.items():
        if not callable(fn):
            raise ValueError(f"{name}: must be callable")
