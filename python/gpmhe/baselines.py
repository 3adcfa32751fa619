"""EKF baselines of the paper's comparison, on filterpy's `ExtendedKalmanFilter` (filterpy is a
test/benchmark extra, imported on first use):

* `ExactEKF`: filterpy's EKF with a known nonlinear model (f, ∂f/∂x, h, ∂h/∂x); only `predict_x`
  is overridden to propagate x through f, as filterpy's documentation suggests.
* `GPEKF`: the same filter on a `gpmhe.LearnedModel` (a GP-EKF): F and H are the GP mean
  Jacobians at the current estimate, and the GP latent variances are added to Q and R.

Loop per step t: `update(y(t))` gives x̂(t|t), then `predict(u(t))` gives x̂(t+1|t).
"""

from __future__ import annotations

import numpy as np

__all__ = ["ExactEKF", "GPEKF"]


def _ekf_base():
    try:
        from filterpy.kalman import ExtendedKalmanFilter
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("the EKF baselines need filterpy: pip install 'gpmhe[test]'") from e
    return ExtendedKalmanFilter


def ExactEKF(f, f_jacobian, h, h_jacobian, x0, P0, Q, R):
    """filterpy's ExtendedKalmanFilter for x+ = f(x) + w, y = h(x) + v (no input). Call
    `ekf.update(y)` then `ekf.predict()`; `ekf.x` is (dim_x, 1) as in filterpy."""
    base = _ekf_base()

    class _ExactEKF(base):
        def predict_x(self, u=0):
            self.x = np.asarray(f(self.x.ravel()), dtype=float).reshape(-1, 1)

        def predict(self, u=0):
            self.F = np.asarray(f_jacobian(self.x.ravel()), dtype=float)
            super().predict(u)

        def update(self, z, HJacobian=None, Hx=None, R=None, args=(), hx_args=(), residual=np.subtract):
            return super().update(
                np.atleast_1d(z), lambda x: np.asarray(h_jacobian(x.ravel()), dtype=float),
                lambda x: np.asarray(h(x.ravel()), dtype=float).reshape(-1, 1), R=R,
                args=args, hx_args=hx_args, residual=residual)

    x0 = np.asarray(x0, dtype=float).reshape(-1)
    R = np.atleast_2d(np.asarray(R, dtype=float))
    ekf = _ExactEKF(dim_x=x0.size, dim_z=R.shape[0])
    ekf.x = x0.reshape(-1, 1).copy()
    ekf.P = np.asarray(P0, dtype=float).copy()
    ekf.Q = np.asarray(Q, dtype=float).copy()
    ekf.R = R.copy()
    return ekf


def GPEKF(model, x0, P0, Q, R):
    """An EKF on a learned (or any `stage_eval`) model: F = ∂m_x/∂x, Q + diag σ²_x(d̂) in the
    prediction; H = ∂m_y/∂x, R + diag σ²_y(d̂) in the update, all at the current estimate.
    `predict(u)`, `update(y, u=None)`; `x` is (dim_x, 1) as in filterpy."""
    base = _ekf_base()
    n, m = model.dim_x, model.dim_u

    def point(x, u):
        u = np.zeros(m) if u is None or m == 0 else np.asarray(u, dtype=float).reshape(-1)
        return np.concatenate([x.ravel(), u])[None, :]

    class _GPEKF(base):
        def predict(self, u=None):
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
            _, _, _, _, my, vy, dmy, _ = model.stage_eval(point(self.x, u))
            H = dmy[0][:, :n]
            R_eff = self.R + np.diag(vy[0])
            return super().update(np.atleast_1d(z), lambda x: H, lambda x: my[0].reshape(-1, 1),
                                  R=R_eff)

    x0 = np.asarray(x0, dtype=float).reshape(-1)
    R = np.atleast_2d(np.asarray(R, dtype=float))
    ekf = _GPEKF(dim_x=n, dim_z=R.shape[0])
    ekf.x = x0.reshape(-1, 1).copy()
    ekf.P = np.asarray(P0, dtype=float).copy()
    ekf.Q = np.asarray(Q, dtype=float).copy()
    ekf.R = R.copy()
    return ekf
