"""Models for the estimators: `LearnedModel` (GPs for f and h, the paper's GP-MHE) and
`KnownModel` (user callables, the exact-model MHE of the paper's comparison).

Both describe x(t+1) = f(x(t), u(t)) + w(t), y(t) = h(x(t), u(t)) + v(t) and give the estimator,
for a batch of points d = [x; u], the means m_x(d), m_y(d), the latent variances σ²_x(d), σ²_y(d)
(zero for a known model) and their gradients with respect to d (DESIGN.md §2, §3).
"""

from __future__ import annotations

import numpy as np

from gpmhe import _core

__all__ = ["KnownModel", "LearnedModel"]


def _as_points(d, nd):
    d = np.ascontiguousarray(d, dtype=np.float64)
    if d.ndim == 1:
        d = d.reshape(1, -1)
    if d.ndim != 2 or d.shape[1] != nd:
        raise ValueError(f"d: expected shape (k, {nd}), got {d.shape}")
    if not np.all(np.isfinite(d)):
        raise ValueError("d: contains NaN or inf")
    return d


class _SharedOnCopy:
    """Models are immutable after construction; `copy.deepcopy` (used by filterpy's Saver on the
    estimator's attributes) shares them instead of copying the Rust objects inside."""

    def __deepcopy__(self, memo):
        return self

    def __copy__(self):
        return self


class KnownModel(_SharedOnCopy):
    """An exactly known model for the exact-model MHE.

    Parameters
    ----------
    f : callable f(x, u) -> (dim_x,) array, the noise-free x(t+1) for one point (1-D arrays; `u`
        is an empty array when dim_u = 0).
    h : callable h(x, u) -> (dim_y,) array, the noise-free output y(t).
    dim_x, dim_y, dim_u : the dimensions n, p, m.
    f_jacobian, h_jacobian : optional callables returning ∂f/∂x (n, n) and ∂h/∂x (p, n); central
        finite differences with step `fd_step`·max(1, |x_i|) when not given.

    The variances are zero, so the MHE weights reduce to Q0 and R0. Gradients with respect to u
    are not needed by the estimator (u is data) and are reported as zero.
    """

    def __init__(self, f, h, dim_x, dim_y, dim_u=0, f_jacobian=None, h_jacobian=None, fd_step=1e-6):
        for name, fn in (("f", f), ("h", h)):
            if not callable(fn):
                raise ValueError(f"{name}: must be callable")
        for name, fn in (("f_jacobian", f_jacobian), ("h_jacobian", h_jacobian)):
            if fn is not None and not callable(fn):
                raise ValueError(f"{name}: must be callable or None")
        for name, v, lo in (("dim_x", dim_x, 1), ("dim_y", dim_y, 0), ("dim_u", dim_u, 0)):
            if not isinstance(v, (int, np.integer)) or v < lo:
                raise ValueError(f"{name}: must be an integer >= {lo}, got {v!r}")
        if not (np.isfinite(fd_step) and fd_step > 0):
            raise ValueError(f"fd_step: must be positive, got {fd_step!r}")
        self.f, self.h = f, h
        self.f_jacobian, self.h_jacobian = f_jacobian, h_jacobian
        self.dim_x, self.dim_y, self.dim_u = int(dim_x), int(dim_y), int(dim_u)
        self.fd_step = float(fd_step)

    def _call(self, fn, x, u, size, name):
        v = np.asarray(fn(x, u), dtype=np.float64).reshape(-1)
        if v.size != size:
            raise ValueError(f"{name}: returned {v.size} values, expected {size}")
        return v

    def _jac(self, fn, jac, x, u, size, name):
        if jac is not None:
            J = np.asarray(jac(x, u), dtype=np.float64)
            if J.shape != (size, self.dim_x):
                raise ValueError(f"{name}_jacobian: returned shape {J.shape}, expected {(size, self.dim_x)}")
            return J
        J = np.empty((size, self.dim_x))
        for i in range(self.dim_x):
            step = self.fd_step * max(1.0, abs(x[i]))
            xp, xm = x.copy(), x.copy()
            xp[i] += step
            xm[i] -= step
            J[:, i] = (self._call(fn, xp, u, size, name) - self._call(fn, xm, u, size, name)) / (2 * step)
        return J

    def predict(self, x, u=None):
        """m_x: the one-step prediction f(x, u) as a (dim_x,) array."""
        x = np.asarray(x, dtype=np.float64).reshape(-1)
        u = np.zeros(0) if u is None else np.asarray(u, dtype=np.float64).reshape(-1)
        return self._call(self.f, x, u, self.dim_x, "f")

    def stage_eval(self, d):
        """For points d (k, n+m): (mean_x, var_x, dmean_x, dvar_x, mean_y, var_y, dmean_y,
        dvar_y) with shapes (k,n), (k,n), (k,n,nd), (k,n,nd), (k,p), (k,p), (k,p,nd), (k,p,nd)."""
        n, m, p = self.dim_x, self.dim_u, self.dim_y
        nd = n + m
        d = _as_points(d, nd)
        k = d.shape[0]
        mx, dmx = np.zeros((k, n)), np.zeros((k, n, nd))
        my, dmy = np.zeros((k, p)), np.zeros((k, p, nd))
        for i in range(k):
            x, u = d[i, :n].copy(), d[i, n:].copy()
            mx[i] = self._call(self.f, x, u, n, "f")
            dmx[i, :, :n] = self._jac(self.f, self.f_jacobian, x, u, n, "f")
            if p:
                my[i] = self._call(self.h, x, u, p, "h")
                dmy[i, :, :n] = self._jac(self.h, self.h_jacobian, x, u, p, "h")
        return (mx, np.zeros((k, n)), dmx, np.zeros((k, n, nd)), my, np.zeros((k, p)), dmy,
                np.zeros((k, p, nd)))

    def _make_window(self, eta, q0, r0, p2_sqrt, filtering):
        return _core.MheWindow.with_callback(
            self.stage_eval, self.dim_x, self.dim_u, self.dim_y, eta, q0, r0, p2_sqrt, filtering
        )
