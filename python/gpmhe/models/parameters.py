"""Unknown constant parameters p of a known model, estimated with the states (see the user guide,
*Physics models*, "Unknown parameters").

A model with parameters, f(x, u, p) and h(x, u, p), is run by the estimator on the augmented
state [x; p̃] with p = s ⊙ p̃: s is the parameters' scale (so that p̃ is of order one for the
solver, whatever the units of p) and p̃ is constant (p̃(t+1) = p̃(t) for a discrete map,
dp̃/dt = 0 for a right-hand side). The functions here build the augmented callables (numpy, per
point or vectorised) and CasADi functions, from which `gpmhe.models.KnownModel` builds the
augmented model when an estimator asks for it; `Scaling` maps the estimator's quantities between
p and p̃ (the state, its bounds, covariance and weights). Nothing else knows of the scaling.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

__all__ = ["augment_numpy", "augment_casadi", "Scaling"]


def _check(name, a, shape):
    if a.shape != shape:
        raise ValueError(f"{name}: returned shape {a.shape}, expected {shape}")
    return a


class _Part:
    """One augmented numpy callable (picklable when the wrapped one is): ``role`` "f" (the map
    or right-hand side), "h", "f_jacobian" or "h_jacobian" of the user's ``fn`` of (x, u, p)."""

    def __init__(self, role, fn, n, n_p, rows, scale, vectorized, continuous):
        self.role, self.fn, self.n, self.n_p, self.rows = role, fn, n, n_p, rows
        self.scale = np.asarray(scale, dtype=np.float64)
        self.vectorized, self.continuous = vectorized, continuous

    def __call__(self, X, U):
        single = not self.vectorized
        if single:
            X, U = X[None, :], U[None, :]
        n, n_p, k = self.n, self.n_p, X.shape[0]
        x, pt = X[:, :n], X[:, n:]
        args = (x[0], U[0], pt[0] * self.scale) if single else (x, U, pt * self.scale)
        v = np.asarray(self.fn(*args), dtype=np.float64)
        if self.role == "h":
            return v
        if self.role == "f":
            v = v.reshape(k, -1)
            nxt = np.zeros_like(pt) if self.continuous else pt
            out = np.hstack([v, nxt])
            return out[0] if single else out
        J = _check(self.role, v.reshape((k,) + v.shape[-2:]) if single else v,
                   (k, self.rows, n + n_p))
        extra = n_p if self.role == "f_jacobian" else 0
        out = np.zeros((k, self.rows + extra, n + n_p))
        out[:, :self.rows, :n], out[:, :self.rows, n:] = J[:, :, :n], J[:, :, n:] * self.scale
        if extra and not self.continuous:
            out[:, self.rows:, n:] = np.eye(n_p)
        return out[0] if single else out


def augment_numpy(fns, n, n_p, dim_y, scale, vectorized, continuous):
    """The augmented (f, h, f_jacobian, h_jacobian) of numpy callables ``fns`` taking (x, u, p)
    (per point) or (X, U, P) (vectorised); Jacobians are ∂/∂[x; p] (None: finite differences of
    the augmented functions). ``continuous``: f is a right-hand side (dp̃/dt = 0)."""
    roles = ("f", "h", "f_jacobian", "h_jacobian")
    rows = (n, dim_y, n, dim_y)
    return tuple(None if fn is None else _Part(role, fn, n, n_p, r, scale, vectorized, continuous)
                 for role, fn, r in zip(roles, fns, rows))


def augment_casadi(f, h, n, n_p, scale, continuous):
    """The augmented CasADi functions of f(x, u, p) (a map or a right-hand side) and h (of x,
    (x, u) or (x, u, p); or None)."""
    import casadi as ca

    from gpmhe.models.casadi import check_no_free

    check_no_free(ca, "f", f)
    n_u = f.numel_in(1)
    if h is not None:
        check_no_free(ca, "h", h)
        for i, (label, size) in enumerate((("x", n), ("u", n_u), ("p", n_p))[:h.n_in()]):
            if h.numel_in(i) != size:
                raise ValueError(f"h: its input {label} has {h.numel_in(i)} values, f's has {size} in {h}")
    xa, u = ca.SX.sym("x", n + n_p), ca.SX.sym("u", n_u)
    x, pt = xa[:n], xa[n:]
    p = pt * ca.DM(np.asarray(scale, dtype=np.float64))
    nxt = ca.vertcat(f(x, u, p), ca.SX.zeros(n_p) if continuous else pt)
    fa = ca.Function(f.name() + "_with_parameters", [xa, u], [nxt], ["x", "u"], ["xf"])
    if h is None:
        return fa, None
    args = [x, u, p][:h.n_in()]
    ha = ca.Function(h.name() + "_with_parameters", [xa, u], [h(*args)], ["x", "u"], ["y"])
    return fa, ha


class Scaling:
    """The estimator's quantities on the augmented state [x; p̃], p = s ⊙ p̃, for n states and
    the scale ``s`` of the parameters (k values; k = 0: no parameters, every map the identity)."""

    def __init__(self, n, scale):
        self.n, self.s = n, np.asarray(scale, dtype=np.float64)

    @property
    def k(self):
        return self.s.size

    def state(self, x, p):
        """[x; p / s]."""
        return np.concatenate([x, p / self.s]) if self.k else x

    def bounds(self, lb, ub, p_bounds):
        """The box of [x; p̃] from the state's and the parameters' boxes."""
        if not self.k:
            return lb, ub
        return np.concatenate([lb, p_bounds[0] / self.s]), np.concatenate([ub, p_bounds[1] / self.s])

    def process_noise(self, Q0, p_drift):
        """The process-noise covariance of [x; p̃]: Q0 and the random walk of p̃ (p_drift / s)²."""
        if not self.k:
            return Q0
        return scipy.linalg.block_diag(Q0, np.diag((p_drift / self.s) ** 2))

    def arrival_weight(self, P2, P_p0):
        """The arrival weight of [x; p̃]: P2 and the prior weight s P_p0⁻¹ s of p̃."""
        if not self.k:
            return P2
        s = self.s
        return scipy.linalg.block_diag(P2, s[:, None] * np.linalg.inv(P_p0) * s[None, :])

    def parameters(self, z):
        """p from the augmented state z (or the rows of a stack of them, (..., n + k))."""
        return z[..., self.n:] * self.s

    def covariance(self, P, P_p):
        """The covariance of [x; p̃] from those of x and p (no cross-covariance)."""
        if not self.k:
            return P
        return scipy.linalg.block_diag(P, P_p / np.outer(self.s, self.s))

    def parameter_covariance(self, C):
        """The covariance of p from that of [x; p̃] (or of each of a stack, (..., n + k, n + k))."""
        n, s = self.n, self.s
        return s[:, None] * C[..., n:, n:] * s[None, :]
