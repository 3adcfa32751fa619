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
    f : callable, the noise-free x(t+1). Per point (default): f(x, u) -> (dim_x,) array for 1-D
        `x` (dim_x,) and `u` (dim_u,) (`u` is an empty array when dim_u = 0).
    h : callable, the noise-free output y(t): h(x, u) -> (dim_y,) array.
    dim_x, dim_y, dim_u : the dimensions n, p, m.
    f_jacobian, h_jacobian : optional callables returning ∂f/∂x (n, n) and ∂h/∂x (p, n); central
        finite differences with step `fd_step`·max(1, |x_i|) when not given.
    vectorized : bool (default False). If True, every callable receives all points of a window
        evaluation at once: `X` of shape (k, n) and `U` of shape (k, m) (k ≥ 1 rows; `U` has m = 0
        columns when dim_u = 0), and returns f(X, U) (k, n), h(X, U) (k, p),
        f_jacobian(X, U) (k, n, n), h_jacobian(X, U) (k, p, n); row i belongs to point i. Without
        Jacobians, the central differences stack the 2n shifted copies of X with X itself and
        call f (and h) once on those (2n+1)k rows. The callables must not modify X, U in place.
        `predict` calls f with k = 1.

    A window evaluation of the MHE (all M+1 window points) then costs one Python call per
    callable instead of k (per point: k calls each, plus 2nk without Jacobians), which is what
    bounds the exact-model MHE's time with the Rust solver (see README, "Real-time window
    solver"). Every returned array is checked for its shape and for NaN/inf in both modes; a
    violation raises ValueError naming the callable. At the window's start point, `GPMHE.update`
    then raises it and leaves the estimator's state unchanged; at a trial point of the Rust
    solver it only rejects that step (the SciPy solvers stop there: `success` False, a warning).

    The variances are zero, so the MHE weights reduce to Q0 and R0. Gradients with respect to u
    are not needed by the estimator (u is data) and are reported as zero.

    Attributes
    ----------
    f, h, f_jacobian, h_jacobian, dim_x, dim_y, dim_u, vectorized, fd_step : as given.
    """

    def __init__(self, f, h, dim_x, dim_y, dim_u=0, f_jacobian=None, h_jacobian=None,
                 fd_step=1e-6, vectorized=False):
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
        if not isinstance(vectorized, (bool, np.bool_)):
            raise ValueError(f"vectorized: must be True or False, got {vectorized!r}")
        self.f, self.h = f, h
        self.f_jacobian, self.h_jacobian = f_jacobian, h_jacobian
        self.dim_x, self.dim_y, self.dim_u = int(dim_x), int(dim_y), int(dim_u)
        self.fd_step = float(fd_step)
        self.vectorized = bool(vectorized)

    # ---- per point (vectorized=False) ------------------------------------------------------
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

    def _points_loop(self, d, k):
        n, m, p = self.dim_x, self.dim_u, self.dim_y
        mx, jx = np.empty((k, n)), np.empty((k, n, n))
        my, jy = np.empty((k, p)), np.empty((k, p, n))
        for i in range(k):
            x, u = d[i, :n].copy(), d[i, n:].copy()
            mx[i] = self._call(self.f, x, u, n, "f")
            jx[i] = self._jac(self.f, self.f_jacobian, x, u, n, "f")
            if p:
                my[i] = self._call(self.h, x, u, p, "h")
                jy[i] = self._jac(self.h, self.h_jacobian, x, u, p, "h")
        return mx, jx, my, jy

    # ---- vectorised (vectorized=True) ------------------------------------------------------
    def _call_batch(self, fn, X, U, size, name, rows="one row per point"):
        v = np.asarray(fn(X, U), dtype=np.float64)
        if v.shape != (X.shape[0], size):
            raise ValueError(f"{name}: returned shape {v.shape}, expected {(X.shape[0], size)} "
                             f"(vectorized=True: {rows})")
        return v

    def _value_and_jac_batch(self, fn, jac, X, U, size, name):
        """Values (k, size) and ∂/∂x (k, size, n) at all k points: the analytic Jacobian, or
        central differences from one call on the (2n+1)k stacked points."""
        k, n = X.shape
        if jac is not None:
            v = self._call_batch(fn, X, U, size, name)
            J = np.asarray(jac(X, U), dtype=np.float64)
            if J.shape != (k, size, n):
                raise ValueError(f"{name}_jacobian: returned shape {J.shape}, expected "
                                 f"{(k, size, n)} (vectorized=True: one matrix per point)")
            return v, J
        steps = self.fd_step * np.maximum(1.0, np.abs(X))          # (k, n), as per point
        shifted = np.repeat(X[None], 2 * n + 1, axis=0)              # (2n+1, k, n)
        idx = np.arange(n)
        shifted[1 + idx, :, idx] += steps.T                          # x + step_i e_i
        shifted[1 + n + idx, :, idx] -= steps.T                      # x − step_i e_i
        Us = np.tile(U, (2 * n + 1, 1))
        rows = f"one row per point: the {k} points and their {2 * n * k} finite-difference shifts"
        out = self._call_batch(fn, shifted.reshape(-1, n), Us, size, name, rows).reshape(
            2 * n + 1, k, size)
        J = (out[1:n + 1] - out[n + 1:]) / (2.0 * steps.T[:, :, None])  # (n, k, size)
        return out[0], np.ascontiguousarray(J.transpose(1, 2, 0))

    def _points_batch(self, d):
        n, p = self.dim_x, self.dim_y
        X, U = d[:, :n].copy(), d[:, n:].copy()  # contiguous; shared by the calls below
        mx, jx = self._value_and_jac_batch(self.f, self.f_jacobian, X, U, n, "f")
        if p:
            my, jy = self._value_and_jac_batch(self.h, self.h_jacobian, X, U, p, "h")
        else:
            my, jy = np.zeros((d.shape[0], 0)), np.zeros((d.shape[0], 0, n))
        return mx, jx, my, jy

    # ----------------------------------------------------------------------------------------
    def predict(self, x, u=None):
        """m_x: the one-step prediction f(x, u) as a (dim_x,) array."""
        x = np.asarray(x, dtype=np.float64).reshape(-1)
        u = np.zeros(0) if u is None else np.asarray(u, dtype=np.float64).reshape(-1)
        if self.vectorized:
            v = self._call_batch(self.f, x[None, :], u[None, :], self.dim_x, "f")[0]
        else:
            v = self._call(self.f, x, u, self.dim_x, "f")
        if not np.all(np.isfinite(v)):
            raise ValueError("f: returned NaN or inf")
        return v

    def stage_eval(self, d):
        """For points d (k, n+m): (mean_x, var_x, dmean_x, dvar_x, mean_y, var_y, dmean_y,
        dvar_y) with shapes (k,n), (k,n), (k,n,nd), (k,n,nd), (k,p), (k,p), (k,p,nd), (k,p,nd)."""
        n, m, p = self.dim_x, self.dim_u, self.dim_y
        nd = n + m
        d = _as_points(d, nd)
        k = d.shape[0]
        mx, jx, my, jy = self._points_batch(d) if self.vectorized else self._points_loop(d, k)
        fd = " (finite differences)"
        for a, name in ((mx, "f"), (my, "h"),
                        (jx, "f_jacobian" if self.f_jacobian is not None else "f" + fd),
                        (jy, "h_jacobian" if self.h_jacobian is not None else "h" + fd)):
            if not np.isfinite(a).all():
                raise ValueError(f"{name}: returned NaN or inf")
        if m:
            dmx, dmy = np.zeros((k, n, nd)), np.zeros((k, p, nd))
            dmx[:, :, :n], dmy[:, :, :n] = jx, jy
        else:
            dmx, dmy = np.ascontiguousarray(jx), np.ascontiguousarray(jy)
        return (np.ascontiguousarray(mx), np.zeros((k, n)), dmx, np.zeros((k, n, nd)),
                np.ascontiguousarray(my), np.zeros((k, p)), dmy, np.zeros((k, p, nd)))

    def _make_window(self, eta, q0, r0, p2_sqrt, filtering):
        return _core.MheWindow.with_callback(
            self.stage_eval, self.dim_x, self.dim_u, self.dim_y, eta, q0, r0, p2_sqrt, filtering,
            predict=lambda x, u: np.ascontiguousarray(self.predict(x, u), dtype=np.float64),
        )


def _trajectories(states, outputs, inputs, n, p, m):
    """Regression data (D_f, X_next, X_now, D_h, Y) from lists of measured trajectories."""
    if isinstance(states, np.ndarray) and states.ndim == 2:
        states, outputs = [states], [outputs]
        inputs = None if inputs is None else [inputs]
    states, outputs = list(states), list(outputs)
    if len(states) == 0 or len(outputs) != len(states):
        raise ValueError("outputs: need one output trajectory per state trajectory (at least one)")
    if inputs is not None:
        inputs = list(inputs)
        if len(inputs) != len(states):
            raise ValueError("inputs: need one input trajectory per state trajectory")
    Df, Xn, Xc, Dh, Yh = [], [], [], [], []
    for i, (X, Y) in enumerate(zip(states, outputs)):
        X = np.asarray(X, dtype=np.float64)
        Y = np.asarray(Y, dtype=np.float64)
        if Y.ndim == 1:
            Y = Y[:, None]
        if X.ndim != 2 or X.shape[0] < 2 or not np.all(np.isfinite(X)):
            raise ValueError(f"states[{i}]: must be a finite (T+1, n) array with T >= 1")
        if X.shape[1] != n:
            raise ValueError(f"states[{i}]: has {X.shape[1]} columns, states[0] has {n}")
        if Y.shape != (X.shape[0], p) or not np.all(np.isfinite(Y)):
            raise ValueError(f"outputs[{i}]: must be a finite ({X.shape[0]}, {p}) array")
        T = X.shape[0] - 1
        if m:
            U = np.asarray(inputs[i], dtype=np.float64)
            if U.ndim == 1:
                U = U[:, None]
            if U.shape not in ((T + 1, m), (T, m)) or not np.all(np.isfinite(U)):
                raise ValueError(f"inputs[{i}]: must be a finite ({T + 1}, {m}) or ({T}, {m}) array")
        else:
            U = np.zeros((T + 1, 0))
        Df.append(np.hstack([X[:T], U[:T]]))
        Xn.append(X[1:])
        Xc.append(X[:T])
        rows = U.shape[0]  # outputs usable where u is known
        Dh.append(np.hstack([X[:rows], U]))
        Yh.append(Y[:rows])
    return (np.vstack(Df), np.vstack(Xn), np.vstack(Xc), np.vstack(Dh), np.vstack(Yh))


class LearnedModel(_SharedOnCopy):
    """The GP model of GP-MHE: n independent GPs for f and p for h on inputs d = [x; u].

    m_x(d), σ²_x(d) are the f-GPs' posterior means and latent variances; with `f_residual=True`
    the f-GPs are trained on the increments x(t+1) − x(t) and m_x(d) = x + GP mean (a prior mean
    equal to the identity), otherwise on x(t+1) with zero prior mean, as in the paper.

    Build with `from_trajectories`; `f_gp`, `h_gp` are fitted `gpmhe.MultiOutputGP`s (their Rust
    models are handed to the estimator's window, which evaluates all GPs at all window points in
    one Rust call).
    """

    def __init__(self, f_gp, h_gp, dim_u=0, f_residual=False):
        from gpmhe.gp import MultiOutputGP

        if not isinstance(f_gp, MultiOutputGP) or f_gp._core_model is None:
            raise ValueError("f_gp: must be a fitted gpmhe.MultiOutputGP")
        if h_gp is not None and (not isinstance(h_gp, MultiOutputGP) or h_gp._core_model is None):
            raise ValueError("h_gp: must be a fitted gpmhe.MultiOutputGP or None")
        if not isinstance(dim_u, (int, np.integer)) or dim_u < 0:
            raise ValueError(f"dim_u: must be an integer >= 0, got {dim_u!r}")
        n = f_gp.n_outputs
        if f_gp.dim != n + dim_u:
            raise ValueError(f"f_gp: input dimension {f_gp.dim} is not dim_x + dim_u = {n + dim_u}")
        if h_gp is not None and h_gp.dim != n + dim_u:
            raise ValueError(f"h_gp: input dimension {h_gp.dim} is not dim_x + dim_u = {n + dim_u}")
        self.f_gp, self.h_gp = f_gp, h_gp
        self.dim_x, self.dim_u = n, int(dim_u)
        self.dim_y = 0 if h_gp is None else h_gp.n_outputs
        self.f_residual = bool(f_residual)

    @classmethod
    def from_trajectories(cls, states, outputs, inputs=None, f_residual=False, **gp_options):
        """Fit the GPs on measured trajectories: `states` a list of (T+1, n) arrays, `outputs` of
        (T+1, p), `inputs` of (T+1, m) or (T, m) (None when m = 0). The f-GPs regress x(t+1) (or
        x(t+1) − x(t) with `f_residual`) on d(t) = [x(t); u(t)], the h-GPs y(t) on d(t).
        `gp_options` go to `gpmhe.MultiOutputGP` (e.g. n_restarts, random_state)."""
        from gpmhe.gp import MultiOutputGP

        X0 = np.asarray(states[0] if not (isinstance(states, np.ndarray) and states.ndim == 2)
                        else states)
        Y0 = np.asarray(outputs[0] if not (isinstance(outputs, np.ndarray) and outputs.ndim == 2)
                        else outputs)
        if X0.ndim != 2:
            raise ValueError("states: must be a list of (T+1, n) arrays")
        n = X0.shape[1]
        p = 1 if Y0.ndim == 1 else Y0.shape[1]
        if inputs is None:
            m = 0
        else:
            U0 = np.asarray(inputs[0] if not (isinstance(inputs, np.ndarray) and inputs.ndim == 2)
                            else inputs)
            m = 1 if U0.ndim == 1 else U0.shape[1]
        Df, Xn, Xc, Dh, Yh = _trajectories(states, outputs, inputs, n, p, m)
        target = Xn - Xc if f_residual else Xn
        f_gp = MultiOutputGP(**gp_options).fit(Df, target)
        h_gp = MultiOutputGP(**gp_options).fit(Dh, Yh) if p else None
        return cls(f_gp, h_gp, dim_u=m, f_residual=f_residual)

    def predict(self, x, u=None):
        """m_x: the one-step prediction for one point, a (dim_x,) array."""
        x = np.asarray(x, dtype=np.float64).reshape(-1)
        u = np.zeros(0) if u is None else np.asarray(u, dtype=np.float64).reshape(-1)
        d = np.concatenate([x, u])[None, :]
        mean = self.f_gp.predict(d)[0]
        return mean + x if self.f_residual else mean

    def stage_eval(self, d):
        """As `KnownModel.stage_eval`: means, latent variances and their gradients at d (k, nd)."""
        n, p = self.dim_x, self.dim_y
        nd = n + self.dim_u
        d = _as_points(d, nd)
        k = d.shape[0]
        mx, vx, dmx, dvx = (np.array(a) for a in self.f_gp.predict_with_gradients(d))
        if self.f_residual:
            mx = mx + d[:, :n]
            dmx[:, np.arange(n), np.arange(n)] += 1.0
        if self.h_gp is not None:
            my, vy, dmy, dvy = self.h_gp.predict_with_gradients(d)
        else:
            my, vy, dmy, dvy = np.zeros((k, 0)), np.zeros((k, 0)), np.zeros((k, 0, nd)), np.zeros((k, 0, nd))
        return mx, vx, dmx, dvx, my, vy, dmy, dvy

    def _make_window(self, eta, q0, r0, p2_sqrt, filtering):
        h = None if self.h_gp is None else self.h_gp._core_model
        return _core.MheWindow.with_gp(self.f_gp._core_model, h, self.dim_u, self.f_residual,
                                       eta, q0, r0, p2_sqrt, filtering)

    def save(self, path):
        """Save both GPs and the settings to one `.npz` file (no pickle)."""
        import io

        blobs = {}
        for name, gp in (("f_gp", self.f_gp), ("h_gp", self.h_gp)):
            if gp is not None:
                buf = io.BytesIO()
                gp.save(buf)
                blobs[name] = np.frombuffer(buf.getvalue(), dtype=np.uint8)
        np.savez(path, kind="LearnedModel", dim_u=self.dim_u, f_residual=self.f_residual, **blobs)

    @classmethod
    def load(cls, path):
        """Load a model written by `save`."""
        import io

        from gpmhe.gp import MultiOutputGP

        with np.load(path, allow_pickle=False) as f:
            if str(f["kind"]) != "LearnedModel":
                raise ValueError(f"path: not a saved LearnedModel ({f['kind']})")
            gps = {name: MultiOutputGP.load(io.BytesIO(f[name].tobytes())) if name in f else None
                   for name in ("f_gp", "h_gp")}
            return cls(gps["f_gp"], gps["h_gp"], dim_u=int(f["dim_u"]),
                       f_residual=bool(f["f_residual"]))
