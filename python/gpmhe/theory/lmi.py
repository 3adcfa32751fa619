"""The linear matrix inequality of the δ-IOSS certificate (the paper's eq. (18)) over the grid:
the models' Jacobians at the cell nodes, the interpolation remainder, the semidefinite program, and
the a-posteriori check of the certificate at random pairs of points."""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg
import scipy.optimize


from gpmhe.theory.common import _require_cvxpy, _is_learned
from gpmhe.theory.posterior import _jacobian_curvature


def _jacobians(model, points):
    """∂m_x/∂x (k, n, n) and ∂m_y/∂x (k, p, n) at the points (k, n_d)."""
    n = model.dim_x
    out = model.stage_eval(points)
    return np.asarray(out[2])[:, :, :n], np.asarray(out[6])[:, :, :n]


def _check_pair(name, value):
    if value is None:
        return None
    vals = np.atleast_1d(np.asarray(value, dtype=np.float64))
    if vals.shape not in ((1,), (2,)) or not np.all(np.isfinite(vals)) or np.any(vals < 0):
        raise ValueError(f"{name}: must be one or two finite numbers >= 0 (for f and h)")
    return (float(vals[0]), float(vals[-1]))


def _interpolation_remainder(model, grid, A_nodes, C_nodes, lipschitz, curvature, posts):
    """Bounds δ_A, δ_C of ‖A(d) − Σ_v w_v(d) A(v)‖₂ over the box, where Σ_v w_v(d) A(v) is the
    multilinear interpolation of the Jacobian from the corners v of d's cell (a convex
    combination), and whether they are proved.

    Per entry and cell the interpolation error is at most Σ_c ½ h_c² max|∂²A_ij/∂d_c²| (h the
    half-widths), or 2 L ‖h‖ for a Jacobian with Lipschitz constant L; the spectral norm is
    bounded by the Frobenius norm of the entrywise bounds."""
    n, p = model.dim_x, model.dim_y
    h2 = grid.half ** 2
    if _is_learned(model):
        rA = np.stack([0.5 * _jacobian_curvature(post, n) @ h2 for post in posts["f"]])
        rC = (np.stack([0.5 * _jacobian_curvature(post, n) @ h2 for post in posts["h"]])
              if p else np.zeros((0, n)))
        return float(np.linalg.norm(rA)), float(np.linalg.norm(rC)), True
    bounds = []
    if curvature is not None:
        s = 0.5 * float(np.sum(h2))
        bounds.append((curvature[0] * s * n, curvature[1] * s * math.sqrt(n * p)))
    if lipschitz is not None:
        r = 2.0 * float(np.linalg.norm(grid.half))
        bounds.append((lipschitz[0] * r, lipschitz[1] * r))
    if bounds:
        return min(b[0] for b in bounds), min(b[1] for b in bounds), True
    # Known model without constants: estimate max|∂²A/∂d_c²| by second differences of the
    # Jacobians with the grid spacing (exact when the Jacobians are affine, e.g. quadratic f).
    nodes = grid.nodes()
    rA, rC = np.zeros((n, n)), np.zeros((p, n))
    for c in range(grid.half.size):
        step = np.zeros(grid.half.size)
        step[c] = 2.0 * grid.half[c]
        Ap, Cp = _jacobians(model, nodes + step)
        Am, Cm = _jacobians(model, nodes - step)
        rA += 0.5 * h2[c] * np.max(np.abs(Ap - 2 * A_nodes + Am), axis=0) / step[c] ** 2
        rC += 0.5 * h2[c] * (np.max(np.abs(Cp - 2 * C_nodes + Cm), axis=0) / step[c] ** 2
                             if p else 0.0)
    return float(np.linalg.norm(rA)), float(np.linalg.norm(rC)), False


# ============================================================================ the LMI


class _LMIData:
    """The data of the gridded LMI at the grid nodes, normalised by ν = λ_max(Q_min⁻¹) (the LMI
    is homogeneous in (P, Q⁻¹, R⁻¹, λ), so P is solved for in these units and scaled back)."""

    def __init__(self, A, C, dA, dC, Q_inv, R_inv):
        self.nu = float(np.linalg.eigvalsh(Q_inv)[-1])
        self.A, self.C, self.dA, self.dC = A, C, float(dA), float(dC)
        self.Qi = Q_inv / self.nu
        self.Ri = R_inv / self.nu
        self.n, self.p = A.shape[1], C.shape[1]
        self.Ri_chol = np.linalg.cholesky(self.Ri) if self.p else np.zeros((0, 0))
        self.use_A = self.dA > 0
        self.use_C = bool(self.p) and self.dC > 0


def _lmi_blocks(data, g, P, eta, C_hat, lamA, lamC, cp):
    """The block matrix of node g whose negative semidefiniteness is the sufficient condition.

    Block rows: Δx, Δw, the Schur row of P, then (if δ_A > 0) the A-remainder multiplier, (if
    δ_C > 0) the C-remainder multiplier, and (if p > 0) the Schur row of Ĉᵀ R⁻¹ Ĉ. Affine in
    (P, η P, Ĉ, λ_A, λ_C)."""
    n, p = data.n, data.p
    I, Z = np.eye(n), np.zeros((n, n))
    A = data.A[g]
    X11 = -eta * P
    if p:
        RC = data.Ri @ C_hat
        Cg = data.C[g]
        X11 = X11 - (Cg.T @ RC + RC.T @ Cg)
    if data.use_A:
        X11 = X11 + lamA * I
    if data.use_C:
        X11 = X11 + (lamC * data.dC ** 2) * I
    rows = [[X11, Z, A.T @ P], [Z, -data.Qi, P], [P @ A, P, -P]]
    extra = []  # (column block for rows 1..3, diagonal block)
    if data.use_A:
        extra.append(([Z, Z, data.dA * P], -lamA * I))
    if data.use_C:
        zc = np.zeros((n, p))
        extra.append(([RC.T, zc, zc], -lamC * np.eye(p)))
    if p:
        zc = np.zeros((n, p))
        extra.append(([C_hat.T @ data.Ri_chol, zc, zc], -np.eye(p)))
    sizes = [blk.shape[0] for _, blk in extra]
    for i, (col, diag) in enumerate(extra):
        for r, blk in zip(rows, col):
            r.append(blk)
    for i, (col, diag) in enumerate(extra):
        row = [c.T for c in col]
        for j in range(len(extra)):
            row.append(diag if i == j else np.zeros((sizes[i], sizes[j])))
        rows.append(row)
    return cp.bmat(rows) if cp is not None else np.block(rows)


def _sym_basis(n):
    """A basis of the symmetric n × n matrices (n(n+1)/2 matrices)."""
    basis = []
    for i in range(n):
        for j in range(i, n):
            E = np.zeros((n, n))
            E[i, j] = E[j, i] = 1.0
            basis.append(E)
    return basis


class _SDP:
    """The gridded LMI as a cvxpy problem, built once (η is a parameter, so a bisection re-solves
    without rebuilding). Variables: P, the reference output Jacobian Ĉ and the multipliers. With
    `P_fixed` None: for a given η, maximise λ_min(P) subject to cond(P) ≤ max_condition;
    otherwise minimise η for that P.

    Each node's block matrix is affine in the variables; it is assembled from its coefficient
    matrices (computed with NumPy) as one matrix-vector product per node."""

    def __init__(self, data, P_fixed, max_condition, solver):
        cp = self.cp = _require_cvxpy()
        k, n, p = data.A.shape[0], data.n, data.p
        self.data, self.solver, self.fixed = data, solver, P_fixed is not None
        basis = _sym_basis(n)
        zero, zc = np.zeros((n, n)), np.zeros((p, n))
        c_basis = []
        for i in range(p):
            for j in range(n):
                E = np.zeros((p, n))
                E[i, j] = 1.0
                c_basis.append(E)
        self.lamA = cp.Variable(k, nonneg=True) if data.use_A else None
        self.lamC = cp.Variable(k, nonneg=True) if data.use_C else None
        self.c = cp.Variable(len(c_basis)) if p else None
        if P_fixed is None:
            self.p = cp.Variable(len(basis))
            self.s = cp.Variable(nonneg=True)
            self.eta = cp.Parameter(nonneg=True)
            P_expr = sum(self.p[j] * basis[j] for j in range(len(basis)))
            cons = [P_expr >> self.s * np.eye(n), P_expr << max_condition * self.s * np.eye(n)]
            objective = cp.Maximize(self.s)
        else:
            self.p = np.array([P_fixed[i, j] for i in range(n) for j in range(i, n)])
            self.eta = cp.Variable()
            cons = []
            objective = cp.Minimize(self.eta)
        strict = 1e-9

        def lmi(g, P=zero, eta=0.0, C_hat=zc, lamA=0.0, lamC=0.0):
            return _lmi_blocks(data, g, P, eta, C_hat, lamA, lamC, None)

        for g in range(k):
            base = lmi(g)
            size = base.shape[0]
            coeff_P = np.column_stack([(lmi(g, P=E) - base).reshape(-1) for E in basis])
            coeff_eta = np.column_stack([(lmi(g, P=E, eta=1.0) - lmi(g, P=E)).reshape(-1)
                                         for E in basis])
            vec = base.reshape(-1) + coeff_P @ self.p + self.eta * (coeff_eta @ self.p)
            if p:
                coeff_C = np.column_stack([(lmi(g, C_hat=E) - base).reshape(-1) for E in c_basis])
                vec = vec + coeff_C @ self.c
            if data.use_A:
                vec = vec + self.lamA[g] * (lmi(g, lamA=1.0) - base).reshape(-1)
            if data.use_C:
                # the C-remainder block couples λ_C with Ĉ only through separate entries
                vec = vec + self.lamC[g] * (lmi(g, lamC=1.0) - base).reshape(-1)
            M = cp.reshape(vec, (size, size), order="C")
            cons.append(0.5 * (M + M.T) << -strict * np.eye(size))
        self.problem = cp.Problem(objective, cons)
        self.basis, self.c_basis = basis, c_basis

    def solve(self, eta=None):
        """Returns (P (normalised units), Ĉ, λ_A (k,), λ_C (k,), status); P None on failure."""
        import warnings

        cp, k = self.cp, self.data.A.shape[0]
        if eta is not None:
            self.eta.value = float(eta)
        name = self.solver or ("CLARABEL" if "CLARABEL" in cp.installed_solvers() else "SCS")
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                self.problem.solve(solver=name)
            status = self.problem.status
        except cp.error.SolverError as exc:
            status = f"solver error ({exc})"
        if status not in ("optimal", "optimal_inaccurate"):
            return None, None, None, None, status
        if self.fixed:
            p = self.p
        else:
            if self.s.value is None or self.s.value <= 1e-9:
                return None, None, None, None, "degenerate P"
            p = self.p.value
        P = sum(p[j] * self.basis[j] for j in range(len(self.basis)))
        C_hat = (sum(self.c.value[j] * self.c_basis[j] for j in range(len(self.c_basis)))
                 if self.data.p else np.zeros((0, self.data.n)))
        la = np.maximum(self.lamA.value, 0.0) if self.lamA is not None else np.zeros(k)
        lc = np.maximum(self.lamC.value, 0.0) if self.lamC is not None else np.zeros(k)
        return 0.5 * (P + P.T), C_hat, la, lc, status


def _verified_eta(data, P, C_hat, lamA, lamC):
    """The smallest η for which every cell's LMI holds with this P and these λ (NumPy, per cell:
    a Schur complement and a generalised eigenvalue), or inf if some cell fails for every η."""
    n = data.n
    try:
        L = np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        return math.inf
    Linv = np.linalg.inv(L)
    worst = -math.inf
    for g in range(data.A.shape[0]):
        M = _lmi_blocks(data, g, P, 0.0, C_hat, lamA[g], lamC[g], None)
        M = 0.5 * (M + M.T)
        X11, X12, X22 = M[:n, :n], M[:n, n:], M[n:, n:]
        ev = np.linalg.eigvalsh(X22)
        if ev[-1] >= -1e-12 * max(1.0, abs(ev[0])):
            return math.inf
        Z = X11 - X12 @ np.linalg.solve(X22, X12.T)
        worst = max(worst, float(np.linalg.eigvalsh(Linv @ Z @ Linv.T)[-1]))
    return worst


# ============================================================================ a-posteriori check


def _means(model, d):
    """m_x (k, n), m_y (k, p) at the points d (k, n_d), with the model's own arithmetic."""
    n, p = model.dim_x, model.dim_y
    if _is_learned(model):
        mx = np.asarray(model.f_gp.predict(d))
        if model.f_residual:
            mx = mx + d[:, :n]
        my = np.asarray(model.h_gp.predict(d)) if p else np.zeros((d.shape[0], 0))
        return mx.reshape(-1, n), my.reshape(-1, p)
    X, U = d[:, :n].copy(), d[:, n:].copy()
    if model.vectorized:
        mx = np.asarray(model.f(X, U), dtype=float).reshape(-1, n)
        my = np.asarray(model.h(X, U), dtype=float).reshape(-1, p) if p else np.zeros((d.shape[0], 0))
        return mx, my
    mx = np.array([np.asarray(model.f(x, u), dtype=float).reshape(n) for x, u in zip(X, U)])
    my = (np.array([np.asarray(model.h(x, u), dtype=float).reshape(p) for x, u in zip(X, U)])
          if p else np.zeros((d.shape[0], 0)))
    return mx, my


def _random_pairs(lower, upper, n, n_pairs, rng, C_hat):
    """Pairs (d, d̃) in the box with the same input part: a third uniform, a third close
    together, a third close together along the null space of Ĉ (state differences the outputs
    barely see, where (18b) is tightest)."""
    nd = lower.size
    d = rng.uniform(lower, upper, size=(n_pairs, nd))
    other = rng.uniform(lower, upper, size=(n_pairs, nd))
    third = n_pairs // 3
    width = upper - lower
    other[:third] = d[:third] + 1e-2 * width * rng.uniform(-1, 1, size=(third, nd))
    null = scipy.linalg.null_space(C_hat) if C_hat.shape[0] else np.eye(n)
    if null.shape[1]:
        step = rng.standard_normal((third, null.shape[1])) @ null.T       # (third, n)
        scale = 1e-2 * float(np.min(width[:n]))
        other[third:2 * third, :n] = d[third:2 * third, :n] + scale * step
    other = np.clip(other, lower, upper)
    other[:, n:] = d[:, n:]
    return d, other


def _violation_18b(model, P, eta, Q_inv, R_inv, d, d_other):
    """Normalised violation of (18b) at the pairs: (worst case over w − w̃ of the left side minus
    the right side) / ‖x − x̃‖²_P, one value per pair; ≤ 0 means (18b) holds there.

    The worst case over the disturbance difference Δw of ‖a + Δw‖²_P − ‖Δw‖²_{Q⁻¹} is
    aᵀ(P⁻¹ − Q)⁻¹a (valid when Q⁻¹ − P is positive definite), with a = m_x(d) − m_x(d̃)."""
    n = model.dim_x
    mx, my = _means(model, d)
    mx2, my2 = _means(model, d_other)
    a, b = mx - mx2, my - my2
    dx = d[:, :n] - d_other[:, :n]
    worst_w = np.linalg.inv(np.linalg.inv(P) - np.linalg.inv(Q_inv))
    lhs = np.einsum("ki,ij,kj->k", a, worst_w, a)
    base = np.einsum("ki,ij,kj->k", dx, P, dx)
    rhs = eta * base + np.einsum("ki,ij,kj->k", b, R_inv, b)
    return (lhs - rhs) / np.maximum(base, np.finfo(float).tiny)


