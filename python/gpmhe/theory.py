"""The stability theory of GP-MHE as software: certify the detectability assumption of Theorem 1,
design the MHE's prior weight P2 and discount η from it, and evaluate the minimal horizon, the
model mismatch and the error bound of Wolff, Lopez & Müller (Theorem 1, Corollary 1).

Everything here is pure Python on top of the public models. The semidefinite programs need the
optional dependency cvxpy (with the Clarabel solver): ``pip install "gpmhe[theory]"``; cvxpy is
imported only when a function needs it.

The functions follow the paper's symbols: ``weight_bounds`` gives Q_min⁻¹, Q_max⁻¹, R_min⁻¹,
R_max⁻¹ of eqs. (14)–(17); ``certify_ioss`` finds a quadratic δ-IOSS Lyapunov function (18) and
returns a :class:`Certificate` (P1, P2, η, the minimal horizon M̄ and μ); ``mismatch`` gives
α₁^max, α₂^max of eqs. (19)–(20); ``corollary1`` the quantities (22)–(28); ``error_bound`` the
right-hand side of (21).
"""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg
import scipy.optimize

from gpmhe._validation import in_open_interval, integer, positive_scalar, symmetric_matrix

__all__ = [
    "WeightBounds",
    "weight_bounds",
    "Certificate",
    "certify_ioss",
    "Mismatch",
    "mismatch",
    "Corollary1",
    "corollary1",
    "error_bound",
]

_PAPER = ("T. M. Wolff, V. G. Lopez and M. A. Müller, \"Robust stability of Gaussian process "
          "based moving horizon estimation\", IEEE CDC 2023.")
_EPS = np.finfo(float).eps


# ============================================================================ input checking


def _require_cvxpy():
    try:
        import cvxpy
    except ImportError:
        raise ImportError(
            "gpmhe.theory needs cvxpy for its semidefinite programs: pip install \"gpmhe[theory]\" "
            "(or pip install cvxpy clarabel)"
        ) from None
    return cvxpy


def _check_model(model):
    for attr in ("dim_x", "dim_y", "dim_u", "stage_eval"):
        if not hasattr(model, attr):
            raise ValueError("model: must be a gpmhe.LearnedModel or gpmhe.KnownModel")
    return model


def _is_learned(model):
    return hasattr(model, "f_gp")


def _check_spd(name, a, dim):
    """A symmetric positive definite (dim, dim) matrix from a scalar, a (dim,) diagonal or a
    (dim, dim) matrix, symmetrised."""
    m = symmetric_matrix(name, a, dim, definite=True, vector_is_diagonal=True)
    return 0.5 * (m + m.T)


def _check_box(name, bounds, dim):
    """(lower, upper) float arrays of shape (dim,), finite, lower < upper."""
    if dim == 0:
        if bounds is not None and np.size(bounds[0]) + np.size(bounds[1]) != 0:
            raise ValueError(f"{name}: the model has no inputs of this kind; pass None")
        return np.zeros(0), np.zeros(0)
    if bounds is None:
        raise ValueError(f"{name}: required, a pair (lower, upper) of shape ({dim},)")
    try:
        lower, upper = bounds
        lower = np.asarray(lower, dtype=np.float64).reshape(-1)
        upper = np.asarray(upper, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: must be a pair (lower, upper) of arrays of shape ({dim},)") from None
    if lower.shape != (dim,) or upper.shape != (dim,):
        raise ValueError(f"{name}: lower and upper must have shape ({dim},), got {lower.shape}, "
                         f"{upper.shape}")
    if not (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper))):
        raise ValueError(f"{name}: must be finite (the theory needs a compact box)")
    if np.any(lower >= upper):
        raise ValueError(f"{name}: lower must be < upper in every component")
    return lower, upper


# ============================================================================ grid of the box


class _Grid:
    """The box X × U cut into cells: the cell centres (k, n_d) and the half-widths (n_d,)."""

    def __init__(self, lower, upper, cells):
        nd = lower.size
        counts = np.broadcast_to(np.asarray(cells, dtype=int), (nd,))
        width = (upper - lower) / counts
        axes = [lower[i] + (np.arange(counts[i]) + 0.5) * width[i] for i in range(nd)]
        mesh = np.meshgrid(*axes, indexing="ij")
        self.centers = np.column_stack([m.reshape(-1) for m in mesh])
        self.half = 0.5 * width
        self.counts = counts
        self.lower, self.upper = lower, upper

    def nodes(self):
        """The corners of all cells, ((counts+1).prod(), n_d)."""
        axes = [np.linspace(self.lower[i], self.upper[i], self.counts[i] + 1)
                for i in range(self.half.size)]
        mesh = np.meshgrid(*axes, indexing="ij")
        return np.column_stack([m.reshape(-1) for m in mesh])

    def vertices(self):
        """The 2^n_d corners of a cell relative to its centre, (2^n_d, n_d)."""
        nd = self.half.size
        signs = np.array(np.meshgrid(*([[-1.0, 1.0]] * nd), indexing="ij")).reshape(nd, -1).T
        return signs * self.half


def _default_cells(nd):
    return max(2, int(round(150 ** (1.0 / nd)))) if nd <= 6 else 2


def _check_cells(cells, nd):
    if cells is None:
        return np.full(nd, _default_cells(nd))
    c = np.asarray(cells)
    if c.ndim == 0:
        c = np.full(nd, c)
    if c.shape != (nd,) or not np.all(np.equal(np.mod(c, 1), 0)) or np.any(c < 1):
        raise ValueError(f"cells: must be a positive integer or {nd} positive integers, got {cells!r}")
    return c.astype(int)


# ============================================================================ SE-ARD posterior


class _SEPosterior:
    """One fitted SE-ARD GP output in NumPy, for the bounds the Rust core does not compute:
    the Hessian of the posterior mean, the posterior covariance of the gradient and the RKHS norm
    of the mean. Uses the same training data, hyperparameters and jitter as the fitted model."""

    def __init__(self, D, y, sigma_f, lengthscales, sigma_eps, jitter):
        self.D = np.asarray(D, dtype=np.float64)
        self.sf2 = float(sigma_f) ** 2
        self.sigma_f = float(sigma_f)
        self.ls = np.asarray(lengthscales, dtype=np.float64)
        K = self._kernel(self.D, self.D)
        Kn = K + (float(sigma_eps) ** 2 + float(jitter)) * np.eye(self.D.shape[0])
        self.chol = scipy.linalg.cho_factor(Kn, lower=True)
        self.alpha = scipy.linalg.cho_solve(self.chol, np.asarray(y, dtype=np.float64))
        self.rkhs_norm = math.sqrt(max(float(self.alpha @ K @ self.alpha), 0.0))

    def _kernel(self, a, b):
        r = (a[:, None, :] - b[None, :, :]) / self.ls
        return self.sf2 * np.exp(-0.5 * np.sum(r * r, axis=-1))

    def mean_hessian(self, d):
        """∂²m/∂d∂d at the points d (k, n_d) -> (k, n_d, n_d)."""
        k = self._kernel(d, self.D) * self.alpha                        # (k, N)
        r = (d[:, None, :] - self.D[None, :, :]) / self.ls ** 2        # (k, N, nd)
        H = np.einsum("kn,kni,knj->kij", k, r, r)
        H -= np.einsum("kn->k", k)[:, None, None] * np.diag(1.0 / self.ls ** 2)[None]
        return H

    def gradient_covariance(self, d):
        """Posterior covariance of ∇f at the points d (k, n_d) -> (k, n_d, n_d)."""
        kern = self._kernel(d, self.D)                                   # (k, N)
        r = (d[:, None, :] - self.D[None, :, :]) / self.ls ** 2         # (k, N, nd)
        G = -kern[:, :, None] * r                                        # ∂k(d, D_j)/∂d, (k, N, nd)
        k_pts, N, nd = G.shape
        V = scipy.linalg.solve_triangular(self.chol[0], G.transpose(1, 0, 2).reshape(N, -1),
                                          lower=True).reshape(N, k_pts, nd)
        prior = self.sf2 * np.diag(1.0 / self.ls ** 2)
        return prior[None] - np.einsum("nki,nkj->kij", V, V)


def _posteriors(gp):
    """The `_SEPosterior` of each output of a fitted MultiOutputGP (on the targets minus its prior
    mean: an affine mean adds nothing to the Hessian and the variances)."""
    D, Y = gp.D_train, gp._residuals()
    sf, ls, se, jit = (np.atleast_1d(gp.sigma_f), np.atleast_2d(gp.lengthscales),
                       np.atleast_1d(gp.sigma_eps), np.atleast_1d(gp.jitter))
    return [_SEPosterior(D, Y[:, o], sf[o], ls[o], se[o], jit[o]) for o in range(Y.shape[1])]


def _check_no_nominal(model):
    if getattr(model, "nominal", None) is not None:
        raise ValueError("model: the bounds do not cover a LearnedModel with a nominal model (the "
                         "nominal functions' curvature is unknown)")


def _model_posteriors(model):
    """The `_SEPosterior`s of a LearnedModel's f-GPs and h-GPs (None for a KnownModel), built
    once per call of a public function: each factorises its N × N kernel matrix."""
    if not _is_learned(model):
        return None
    _check_no_nominal(model)
    return {"f": _posteriors(model.f_gp), "h": _posteriors(model.h_gp) if model.dim_y else []}


def _std_upper_bound(post, grid, std_at_centers):
    """A guaranteed upper bound of the posterior standard deviation σ(d) over the whole box.

    In the RKHS of the kernel (augmented by the noise coordinates), σ(d) is the distance of the
    feature of d from the span of the training features, so σ(d) ≤ σ(d_g) + ‖(I−Π)(φ(d)−φ(d_g))‖.
    Writing φ(d) − φ(d_g) = ∫₀¹ ∂_Δφ(d_g + sΔ) ds with Δ = d − d_g gives
    σ(d) ≤ σ(d_g) + sqrt(Δᵀ Σ_∇(d_g) Δ) + (√3/2) σ_f ‖Δ/φ‖², with Σ_∇ the posterior covariance of
    the gradient (the first term of the derivative's variation, the second its SE-kernel bound)."""
    cov = post.gradient_covariance(grid.centers)                         # (k, nd, nd)
    verts = grid.vertices()                                              # (2^nd, nd)
    quad = np.einsum("vi,kij,vj->kv", verts, cov, verts)
    first = np.sqrt(np.maximum(quad, 0.0)).max(axis=1)
    second = 0.5 * math.sqrt(3.0) * post.sigma_f * float(np.sum((grid.half / post.ls) ** 2))
    rounding = 1e2 * _EPS * post.sigma_f * math.sqrt(post.D.shape[0])
    return float(np.max(std_at_centers + first)) + second + rounding


def _jacobian_curvature(post, n):
    """Bounds κ_bc ≥ |∂³m/∂d_b ∂d_c²| over all of R^{n_d}, for b < n (state columns): (n, n_d).

    For m in the RKHS H of the SE kernel, |∂³m(d)| ≤ ‖m‖_H ‖∂³φ(d)‖ and ‖∂_b∂_c∂_c φ‖² is the
    prior variance of that derivative, σ_f² E[ω_b² ω_c⁴] / (φ_b² φ_c⁴) with ω ~ N(0, I)
    (E = 15 for b = c, else 3); ‖m‖_H² = αᵀKα for the posterior mean."""
    nd = post.ls.size
    moment = np.full((n, nd), 3.0)
    moment[np.arange(n), np.arange(n)] = 15.0
    return (post.rkhs_norm * post.sigma_f * np.sqrt(moment)
            / (post.ls[:n, None] * post.ls[None, :] ** 2))


# ============================================================================ weight bounds


class WeightBounds:
    """The bounds (14)–(17) of the MHE's weights Q(d)⁻¹ and R(d)⁻¹ over the box.

    Returned by :func:`weight_bounds`; the parameters become the attributes of the same name.

    Parameters
    ----------
    Q_min_inv, Q_max_inv, R_min_inv, R_max_inv : ndarray
        The four weight bounds.
    var_x_max, var_y_max : ndarray
        The variance bounds used.
    variance_bound : str
        Which variance bound was used.

    Attributes
    ----------
    Q_min_inv, Q_max_inv : ndarray, shape (n, n)
        Q_min⁻¹ ≤ Q(d)⁻¹ ≤ Q_max⁻¹ for all d in the box (eq. 14, 16, 17).
    R_min_inv, R_max_inv : ndarray, shape (p, p)
        R_min⁻¹ ≤ R(d)⁻¹ ≤ R_max⁻¹ (eq. 15).
    var_x_max, var_y_max : ndarray, shapes (n,) and (p,)
        The upper bounds of the posterior variances used (zero for a known model).
    variance_bound : str
        "prior" (σ_f² + σ_ε², eq. 16 as printed) or "posterior" (guaranteed maximum over the box).
    """

    def __init__(self, Q_min_inv, Q_max_inv, R_min_inv, R_max_inv, var_x_max, var_y_max,
                 variance_bound):
        self.Q_min_inv, self.Q_max_inv = Q_min_inv, Q_max_inv
        self.R_min_inv, self.R_max_inv = R_min_inv, R_max_inv
        self.var_x_max, self.var_y_max = var_x_max, var_y_max
        self.variance_bound = variance_bound

    def __repr__(self):
        return (f"WeightBounds(variance_bound={self.variance_bound!r}, var_x_max={self.var_x_max},"
                f" var_y_max={self.var_y_max})")


def _variance_maxima(model, variance_bound, grid, posts):
    """Upper bounds of the posterior variances (n,), (p,) of the model's GPs."""
    n, p = model.dim_x, model.dim_y
    if not _is_learned(model):
        return np.zeros(n), np.zeros(p)
    gps = [(model.f_gp, "f")] + ([(model.h_gp, "h")] if p else [])
    out = []
    for gp, key in gps:
        if variance_bound == "prior":
            out.append(np.atleast_1d(gp.sigma_f) ** 2 + np.atleast_1d(gp.sigma_eps) ** 2)
            continue
        _, std = gp.predict(grid.centers, return_std=True)
        std = np.atleast_2d(std.T).T if std.ndim == 1 else std
        bounds = [_std_upper_bound(post, grid, std[:, o]) for o, post in enumerate(posts[key])]
        out.append(np.minimum(np.square(bounds), np.atleast_1d(gp.sigma_f) ** 2))
    if not p:
        out.append(np.zeros(0))
    return out[0], out[1]


def weight_bounds(model, Q0, R0, variance_bound="prior", x_bounds=None, u_bounds=None, cells=None):
    """Bounds Q_min⁻¹ ≤ Q(d)⁻¹ ≤ Q_max⁻¹ and R_min⁻¹ ≤ R(d)⁻¹ ≤ R_max⁻¹ of the MHE's weights.

    The MHE weighs process residuals by Q(d)⁻¹ with Q(d) = diag σ²_x(d) + Q0 and output residuals
    by R(d)⁻¹ with R(d) = diag σ²_y(d) + R0. With an upper bound σ̄² of the posterior variances,
    Q_min⁻¹ = (diag σ̄²_x + Q0)⁻¹ and, since variances are non-negative, Q_max⁻¹ = Q0⁻¹.

    Parameters
    ----------
    model : LearnedModel or KnownModel
        The model of the MHE (a known model has zero variances, so both bounds equal Q0⁻¹, R0⁻¹).
    Q0, R0 : float, array (n,) or (p,), or matrix
        The constant covariance parts of Q(d) and R(d) (gpmhe's convention: covariances, the
        weights are their inverses).
    variance_bound : {"prior", "posterior"}
        "prior": σ̄² = σ_f² + σ_ε² of each GP, the paper's eq. (16), valid everywhere.
        "posterior": σ̄² = a guaranteed upper bound of the posterior variance over the box
        X × U (needs `x_bounds`), usually far smaller (see Notes).
    x_bounds, u_bounds : pair of arrays, optional
        The box X (and U when the model has inputs), for "posterior".
    cells : int or sequence of int, optional
        Cells per dimension of the grid of the box used by "posterior" (default: about 400 in
        total).

    Returns
    -------
    WeightBounds
        The four matrices and the variance bounds used.

    Raises
    ------
    ValueError
        On a bad model, non-finite or non-positive-definite Q0/R0, a missing or inverted box, or an
        unknown `variance_bound`.

    Notes
    -----
    Eqs. (14)–(17) of the paper:

    .. math:: Q_{\\min}^{-1} \\le Q_{\\bar d}^{-1} \\le Q_{\\max}^{-1}, \\quad
              Q_{\\min}^{-1} = [\\operatorname{diag}(\\bar\\sigma^2_{x_i}) + Q_0]^{-1},
              \\quad Q_{\\max}^{-1} = Q_0^{-1},

    and alike for R. Only points d in X × U enter the MHE, so the maximal posterior variance over
    that box is a valid σ̄². It is made a guaranteed bound (not a sampled maximum) by evaluating σ
    at the centres d_g of a grid of cells and adding, for every cell, the largest possible increase
    inside the cell: σ(d) ≤ σ(d_g) + max_Δ sqrt(Δᵀ Σ_∇(d_g) Δ) + (√3/2) σ_f ‖Δ/φ‖² with Σ_∇ the
    posterior covariance of the gradient at d_g and Δ ranging over the cell (the posterior standard
    deviation is the distance of the kernel feature of d from the span of the training features,
    and that distance changes by at most the posterior size of the feature's change).

    References
    ----------
    .. [1] T. M. Wolff, V. G. Lopez and M. A. Müller, "Robust stability of Gaussian process based
       moving horizon estimation", IEEE CDC 2023, eqs. (14)–(17).

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe import KnownModel
    >>> from gpmhe.theory import weight_bounds
    >>> model = KnownModel(lambda x, u: 0.5 * x, lambda x, u: x[:1], dim_x=2, dim_y=1)
    >>> wb = weight_bounds(model, Q0=1e-3, R0=1e-2)
    >>> np.diag(wb.Q_min_inv), np.diag(wb.R_max_inv)
    (array([1000., 1000.]), array([100.]))
    """
    model = _check_model(model)
    n, p, m = model.dim_x, model.dim_y, model.dim_u
    Q0 = _check_spd("Q0", Q0, n)
    R0 = _check_spd("R0", R0, p)
    if variance_bound not in ("prior", "posterior"):
        raise ValueError(f"variance_bound: must be 'prior' or 'posterior', got {variance_bound!r}")
    grid = None
    if variance_bound == "posterior" and _is_learned(model):
        xl, xu = _check_box("x_bounds", x_bounds, n)
        ul, uu = _check_box("u_bounds", u_bounds, m)
        grid = _Grid(np.concatenate([xl, ul]), np.concatenate([xu, uu]),
                     _check_cells(cells, n + m))
    posts = _model_posteriors(model) if grid is not None else None
    return _weight_bounds(model, Q0, R0, variance_bound, grid, posts)


def _weight_bounds(model, Q0, R0, variance_bound, grid, posts):
    var_x, var_y = _variance_maxima(model, variance_bound, grid, posts)
    Q_min_inv = np.linalg.inv(np.diag(var_x) + Q0)
    R_min_inv = np.linalg.inv(np.diag(var_y) + R0) if model.dim_y else np.zeros((0, 0))
    Q_max_inv = np.linalg.inv(Q0)
    R_max_inv = np.linalg.inv(R0) if model.dim_y else np.zeros((0, 0))
    sym = lambda a: 0.5 * (a + a.T)  # noqa: E731
    return WeightBounds(sym(Q_min_inv), sym(Q_max_inv), sym(R_min_inv), sym(R_max_inv),
                        var_x, var_y, variance_bound)


# ============================================================================ Jacobians on the grid


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


# ============================================================================ the certificate


class Certificate:
    """A quadratic δ-IOSS Lyapunov function W(x, x̃) = ‖x − x̃‖²_P of a model on a box: the result
    of :func:`certify_ioss`.

    When `feasible` is True, Assumption 1 of the paper (eq. 18) holds for the model's mean
    functions on X × U with P1 = P2 = P, the discount `eta` and the weights `Q_inv`, `R_inv`; then
    Theorem 1 holds for the MHE run with ``mhe_options()`` and a horizon M ≥ ``min_horizon()``.

    Parameters
    ----------
    **fields
        Values of the attributes below (normally set by :func:`certify_ioss`); missing ones
        default to None (False for `feasible`).

    Attributes
    ----------
    feasible : bool
        Whether a certificate was found and passed all checks.
    reason : str
        Why not, when `feasible` is False; a summary otherwise.
    P : ndarray (n, n) or None
        The matrix of W.
    P1, P2 : ndarray (n, n) or None
        The bounds of (18a); both equal `P` for a quadratic W.
    eta : float or None
        The certified discount η of (18b).
    Q_inv, R_inv : ndarray
        Q_min⁻¹ and R_min⁻¹ used in (18b) (lower bounds of the MHE's weights over the box).
    weights : WeightBounds
        All four weight bounds (14)–(17).
    Q0, R0 : ndarray
        The constant covariance parts of the MHE's weights.
    x_bounds, u_bounds : tuple of ndarray
        The box X (and U) on which the certificate holds.
    C_hat : ndarray (p, n)
        The reference output Jacobian Ĉ of the output term's lower bound, chosen by the SDP
        (see Notes of :func:`certify_ioss`).
    eta_without_margin : float or None
        The η this P needs at the grid nodes alone (no allowance for the interpolation
        remainder): ``eta - eta_without_margin`` is the price of making the grid rigorous.
    jacobian_variation : tuple of float
        The bounds δ_A, δ_C of the spectral norm of the difference between ∂m_x/∂x (resp.
        ∂m_y/∂x) and its multilinear interpolation from the corners of a grid cell.
    margin_proved : bool
        True when δ_A, δ_C are proved bounds (learned models; known models with
        `jacobian_lipschitz`), False when estimated from finite differences.
    cells : ndarray of int
        Cells per dimension of the grid.
    check_pairs : int
        Number of random pairs (x, x̃, u) on which (18b) was re-checked after solving.
    check_worst : float or None
        The largest normalised violation of (18b) over those pairs (worst case over the
        disturbances), (LHS − RHS)/‖x − x̃‖²_P; ≤ 0 means it held on every pair.
    solver_status : str
        The SDP solver's last status.
    """

    def __init__(self, **fields):
        defaults = dict(feasible=False, reason="", P=None, eta=None, Q_inv=None, R_inv=None,
                        weights=None, Q0=None, R0=None, x_bounds=None, u_bounds=None, C_hat=None,
                        eta_without_margin=None, jacobian_variation=(0.0, 0.0),
                        margin_proved=False, cells=None, check_pairs=0, check_worst=None,
                        solver_status="")
        defaults.update(fields)
        for key, value in defaults.items():
            setattr(self, key, value)
        self.P1 = self.P2 = self.P

    def __repr__(self):
        if not self.feasible:
            return f"Certificate(feasible=False, reason={self.reason!r})"
        return (f"Certificate(feasible=True, eta={self.eta:.4f}, min_horizon={self.min_horizon()},"
                f" lambda(P)={np.round(np.linalg.eigvalsh(self.P), 4)})")

    def _need_feasible(self):
        if not self.feasible:
            raise ValueError(f"certificate: not feasible ({self.reason})")

    def min_horizon(self):
        """The minimal horizon M̄ of Theorem 1: the smallest M ≥ 1 with 4 λ_max(P2, P1) η^M < 1.

        Returns
        -------
        int
            M̄ = ⌊ln(4 λ_max(P2, P1)) / ln(1/η)⌋ + 1.

        Raises
        ------
        ValueError
            If the certificate is not feasible.

        Notes
        -----
        With P1 = P2 = P, λ_max(P2, P1) = 1 and M̄ = ⌊ln 4 / ln(1/η)⌋ + 1.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe.theory import Certificate
        >>> Certificate(feasible=True, P=np.eye(2), eta=0.9).min_horizon()
        14
        """
        self._need_feasible()
        lam = float(scipy.linalg.eigh(self.P2, self.P1, eigvals_only=True)[-1])
        M = int(math.floor(math.log(4.0 * lam) / -math.log(self.eta))) + 1
        while M > 1 and 4.0 * lam * self.eta ** (M - 1) < 1.0:  # guard against rounding
            M -= 1
        while 4.0 * lam * self.eta ** M >= 1.0:
            M += 1
        return max(M, 1)

    def mu(self, M):
        """The contraction μ of Theorem 1 for the horizon M: μ^M = 4 λ_max(P2, P1) η^M.

        Parameters
        ----------
        M : int
            The horizon, M ≥ 1.

        Returns
        -------
        float
            μ = (4 λ_max(P2, P1))^{1/M} η; below 1 exactly when M ≥ ``min_horizon()``.

        Raises
        ------
        ValueError
            If M is not a positive integer or the certificate is not feasible.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe.theory import Certificate
        >>> round(Certificate(feasible=True, P=np.eye(2), eta=0.9).mu(14), 4)
        0.9937
        """
        M = integer("M", M, 1)
        self._need_feasible()
        lam = float(scipy.linalg.eigh(self.P2, self.P1, eigvals_only=True)[-1])
        return (4.0 * lam) ** (1.0 / M) * self.eta

    def mhe_options(self, horizon=None):
        """Keyword arguments for :class:`gpmhe.GPMHE` that realise this certificate.

        Parameters
        ----------
        horizon : int, optional
            The MHE horizon M; default ``min_horizon()``. Must be ≥ ``min_horizon()``.

        Returns
        -------
        dict
            ``horizon``, ``eta``, ``P2`` (= P), ``Q0``, ``R0`` and ``x_bounds`` (the state
            constraint (10d) the theorem needs): ``GPMHE(model, x0, **cert.mhe_options())``.

        Raises
        ------
        ValueError
            If the certificate is not feasible or `horizon` < ``min_horizon()``.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe.theory import Certificate
        >>> cert = Certificate(feasible=True, P=np.eye(2), eta=0.9, Q0=np.eye(2), R0=np.eye(1),
        ...                    x_bounds=(np.zeros(2), np.ones(2)))
        >>> sorted(cert.mhe_options())
        ['P2', 'Q0', 'R0', 'eta', 'horizon', 'x_bounds']
        """
        self._need_feasible()
        M_bar = self.min_horizon()
        M = M_bar if horizon is None else integer("horizon", horizon, 1)
        if M < M_bar:
            raise ValueError(f"horizon: must be >= min_horizon() = {M_bar}, got {M}")
        return dict(horizon=M, eta=float(self.eta), P2=self.P.copy(), Q0=self.Q0.copy(),
                    R0=self.R0.copy(), x_bounds=(self.x_bounds[0].copy(), self.x_bounds[1].copy()))


def certify_ioss(model, x_bounds, Q0, R0, u_bounds=None, eta=None, P=None, *,
                 variance_bound="posterior", cells=None, jacobian_lipschitz=None,
                 jacobian_curvature=None,
                 max_condition=1e4, eta_tol=1e-3, n_check=100_000, seed=0, solver=None):
    """Search a quadratic δ-IOSS Lyapunov function of the model on a box (Assumption 1, eq. 18).

    Finds P ≻ 0 and η ∈ (0, 1) such that W(x, x̃) = ‖x − x̃‖²_P satisfies, for all x, x̃ ∈ X,
    u ∈ U and all disturbances w, w̃,

    ‖m_x(x, u) + w − m_x(x̃, u) − w̃‖²_P ≤ η ‖x − x̃‖²_P + ‖w − w̃‖²_{Q_min⁻¹}
    + ‖m_y(x, u) − m_y(x̃, u)‖²_{R_min⁻¹},

    i.e. (18b) with P1 = P2 = P. η is minimised (bisection to `eta_tol`) unless given; P is
    searched unless given.

    Parameters
    ----------
    model : LearnedModel or KnownModel
        The model whose mean functions m_x, m_y the MHE uses.
    x_bounds : pair of arrays (n,)
        The box X = [lower, upper] (the MHE's state constraint).
    Q0, R0 : float, array or matrix
        The constant covariance parts of the MHE's weights (gpmhe's convention).
    u_bounds : pair of arrays (m,), optional
        The box U of the control inputs (required when the model has inputs).
    eta : float, optional
        Fix η ∈ (0, 1) instead of minimising it.
    P : array (n, n), optional
        Fix the matrix of W (symmetric positive definite) and only minimise η.
    variance_bound : {"posterior", "prior"}
        How the posterior variances in Q_min⁻¹, R_min⁻¹ are bounded: the guaranteed maximum over
        the box (default) or the paper's σ_f² + σ_ε² (see :func:`weight_bounds`).
    cells : int or sequence of int, optional
        Grid cells per dimension of X × U (default about 400 cells in total).
    jacobian_lipschitz : float or pair of float, optional
        For a KnownModel: Lipschitz constants of d ↦ ∂f/∂x(d) and d ↦ ∂h/∂x(d) (spectral norm,
        Euclidean norm on d); the grid remainder is then at most 2 L ‖h‖ (h the cell
        half-widths).
    jacobian_curvature : float or pair of float, optional
        For a KnownModel: bounds of the absolute second derivatives ∂²A_ij/∂d_c² and
        ∂²C_ij/∂d_c² over the box (entries of the Jacobians A = ∂f/∂x, C = ∂h/∂x, every
        coordinate c of d); 0 when f and h are quadratic. The remainder is then at most Σ_c ½ h_c² times the bound per entry, which
        shrinks with the square of the cell size. With either constant the grid margin is proved;
        with neither, it is estimated from second differences of the Jacobians
        (``margin_proved`` False). Both are ignored for learned models, whose bounds are computed
        from the GPs.
    max_condition : float
        Upper bound of the condition number of P (keeps P usable as the MHE's prior weight).
    eta_tol : float
        Bisection tolerance on η.
    n_check : int
        Random pairs on which (18b) is re-checked after solving (0 skips the check).
    seed : int
        Seed of the random pairs.
    solver : str, optional
        A cvxpy solver name; default Clarabel, then SCS.

    Returns
    -------
    Certificate
        ``feasible`` with P, η, ``min_horizon()``, ``mhe_options()``, or the reason for failure.

    Raises
    ------
    ValueError
        On invalid arguments (the message names the argument).
    ImportError
        If cvxpy is not installed (``pip install "gpmhe[theory]"``).

    Notes
    -----
    **From pairs to a differential inequality.** With Δ = x − x̃ and Δw = w − w̃, the mean value
    theorem along the segment from x̃ to x (inside the convex box) gives
    m_x(x) − m_x(x̃) = Ā Δ and m_y(x) − m_y(x̃) = C̄ Δ with Ā = ∫₀¹ A(x̃ + sΔ) ds,
    C̄ = ∫₀¹ C(x̃ + sΔ) ds, A = ∂m_x/∂x, C = ∂m_y/∂x. The state term ‖ĀΔ + Δw‖²_P is convex in Ā,
    so it is at most the average of ‖A(·)Δ + Δw‖²_P along the segment (Jensen). The output term
    enters with the opposite sign and ‖C̄Δ‖² is *not* bounded below by the average of ‖C(·)Δ‖²
    (Jensen goes the wrong way), so the pointwise LMI with C(x)ᵀR⁻¹C(x) alone does not imply
    (18b) unless C is constant. gpmhe uses instead the lower bound, affine in C,

    .. math:: \\|C\\Delta\\|^2_{R^{-1}} \\ge \\Delta^\\top (C^\\top R^{-1} \\hat C
              + \\hat C^\\top R^{-1} C - \\hat C^\\top R^{-1} \\hat C) \\Delta
              = \\|C\\Delta\\|^2_{R^{-1}} - \\|(C - \\hat C)\\Delta\\|^2_{R^{-1}},

    valid for any fixed Ĉ. Being affine, it averages along the segment exactly, so the pointwise
    condition, for all d in X × U,

    .. math:: \\begin{bmatrix} A^\\top P A - \\eta P - S(d) & A^\\top P \\\\ P A & P - Q^{-1}
              \\end{bmatrix} \\preceq 0, \\quad S = C^\\top R^{-1}\\hat C + \\hat C^\\top
              R^{-1} C - \\hat C^\\top R^{-1}\\hat C,

    implies (18b) for every pair. It is exact for a linear output map (C = Ĉ) and costs
    ‖(C − Ĉ)Δ‖²_{R⁻¹} otherwise.

    Ĉ is a decision variable of the semidefinite program (the condition is jointly convex in P
    and Ĉ once Ĉᵀ R⁻¹ Ĉ is written as a Schur complement).

    **From the grid to the box.** The box is cut into cells and the condition, written as an LMI
    affine in A and C (Schur complement), is imposed at the cell corners. Inside a cell, A(d) is
    the multilinear interpolation of its corner values — a convex combination, for which the
    affine LMI follows from the corners — plus a remainder with ‖·‖₂ ≤ δ_A (and alike δ_C for C).
    Each corner's LMI is made robust against any such remainder (Petersen's lemma, one multiplier
    per corner and remainder). Per entry the remainder is at most Σ_c ½ h_c² max abs(∂²A_ij/∂d_c²);
    for a GP the third derivatives of the posterior mean are bounded by its RKHS norm
    sqrt(αᵀKα) times the SE kernel's derivative bounds σ_f sqrt(15)/(φ_b φ_c²), so δ_A, δ_C are
    proved.

    **η and P.** η is minimised by bisection; a final solve `eta_tol` above the smallest η
    returns a well-scaled P. Among the feasible P the one with the largest smallest eigenvalue
    and condition number ≤ `max_condition` is returned.

    **Checks.** The η reported is recomputed in NumPy from the solver's P, Ĉ and multipliers (a
    Schur complement and a generalised eigenvalue per grid node), not taken from the solver.
    Then (18b) itself, in its worst case over the disturbances, is evaluated on `n_check` random
    pairs (a third uniform, a third close together, a third close together along the null space
    of Ĉ); a violation makes the certificate infeasible.

    **Proved and sampled.** For learned models and for known models with `jacobian_lipschitz`,
    the certificate is a proof up to floating-point rounding and the solver-independent NumPy
    recomputation; the random pairs are an independent sampled check. For known models without
    Lipschitz constants the grid margin is a finite-difference estimate.

    References
    ----------
    .. [1] T. M. Wolff, V. G. Lopez and M. A. Müller, "Robust stability of Gaussian process based
       moving horizon estimation", IEEE CDC 2023, Assumption 1, Theorem 1.
    .. [2] J. D. Schiller, S. Muntwiler, J. Köhler, M. N. Zeilinger and M. A. Müller, "A Lyapunov
       function for robust stability of moving horizon estimation", IEEE Trans. Automat. Control
       68(12), 2023, Sec. IV (LMI conditions for δ-IOSS).

    Examples
    --------
    A linear system whose unmeasured mode is stable:

    >>> import numpy as np
    >>> from gpmhe import KnownModel
    >>> from gpmhe.theory import certify_ioss
    >>> A = np.array([[1.0, 0.1], [0.0, 0.8]])
    >>> model = KnownModel(lambda x, u: A @ x, lambda x, u: x[:1], dim_x=2, dim_y=1,
    ...                    f_jacobian=lambda x, u: A, h_jacobian=lambda x, u: np.eye(1, 2))
    >>> cert = certify_ioss(model, (-np.ones(2), np.ones(2)), Q0=1e-2, R0=1e-2, cells=1,
    ...                     jacobian_lipschitz=0.0, n_check=1000)
    >>> cert.feasible, cert.eta < 0.7
    (True, True)
    """
    model = _check_model(model)
    n, p, m = model.dim_x, model.dim_y, model.dim_u
    xl, xu = _check_box("x_bounds", x_bounds, n)
    ul, uu = _check_box("u_bounds", u_bounds, m)
    Q0 = _check_spd("Q0", Q0, n)
    R0 = _check_spd("R0", R0, p)
    if eta is not None:
        eta = in_open_interval("eta", eta, 0.0, 1.0)
    if P is not None:
        P = _check_spd("P", P, n)
    if variance_bound not in ("prior", "posterior"):
        raise ValueError(f"variance_bound: must be 'prior' or 'posterior', got {variance_bound!r}")
    lip = _check_pair("jacobian_lipschitz", jacobian_lipschitz)
    curv = _check_pair("jacobian_curvature", jacobian_curvature)
    max_condition = positive_scalar("max_condition", max_condition)
    if max_condition < 1:
        raise ValueError(f"max_condition: must be >= 1, got {max_condition!r}")
    eta_tol = positive_scalar("eta_tol", eta_tol)
    n_check = integer("n_check", n_check, 0)
    seed = integer("seed", seed, 0)
    if solver is not None and not isinstance(solver, str):
        raise ValueError(f"solver: must be a cvxpy solver name or None, got {solver!r}")
    _require_cvxpy()

    lower, upper = np.concatenate([xl, ul]), np.concatenate([xu, uu])
    grid = _Grid(lower, upper, _check_cells(cells, n + m))
    posts = _model_posteriors(model)
    wb = _weight_bounds(model, Q0, R0, variance_bound, grid, posts)
    A, C = _jacobians(model, grid.nodes())
    dA, dC, proved = _interpolation_remainder(model, grid, A, C, lip, curv, posts)
    data = _LMIData(A, C, dA, dC, wb.Q_min_inv, wb.R_min_inv)
    common = dict(Q_inv=wb.Q_min_inv, R_inv=wb.R_min_inv, weights=wb, Q0=Q0, R0=R0,
                  x_bounds=(xl, xu), u_bounds=(ul, uu),
                  jacobian_variation=(dA, dC), margin_proved=proved,
                  cells=grid.counts)

    P_n, C_hat, lamA, lamC, eta_v, status = _search(data, eta, None if P is None else P / data.nu,
                                             max_condition, eta_tol, solver)
    if P_n is None or not eta_v < 1.0:
        why = ("no P satisfies the gridded LMI" + (f" with eta = {eta}" if eta is not None else
                                                     " for any eta < 1")
               + f" (solver status: {status}); the model may not be detectable on this box, or "
               "the weight bounds / grid margin are too conservative (try variance_bound="
               "'posterior' or more cells)")
        return Certificate(reason=why, solver_status=str(status), **common)
    eta_cert = eta if eta is not None else min(1.0 - 1e-12, eta_v * (1 + 1e-9) + 1e-12)
    if eta is not None and eta_v > eta:
        return Certificate(reason=f"the solver's P needs eta = {eta_v:.6g} > {eta} after the "
                           "independent re-check", solver_status=str(status), **common)
    P_out = 0.5 * (P_n + P_n.T) * data.nu
    no_margin = _LMIData(A, C, 0.0, 0.0, wb.Q_min_inv, wb.R_min_inv)
    eta_grid = _verified_eta(no_margin, P_n, C_hat, np.zeros(A.shape[0]), np.zeros(A.shape[0]))
    common["C_hat"] = C_hat
    worst = None
    if n_check:
        d, d2 = _random_pairs(lower, upper, n, n_check, np.random.default_rng(seed), C_hat)
        worst = float(np.max(_violation_18b(model, P_out, eta_cert, wb.Q_min_inv, wb.R_min_inv,
                                            d, d2)))
        if worst > 1e-9:
            return Certificate(reason=f"(18b) fails on random pairs (worst normalised violation "
                               f"{worst:.3g}): the grid margin is not sufficient",
                               P=P_out, eta=eta_cert, check_pairs=n_check, check_worst=worst,
                               solver_status=str(status), **common)
    summary = (f"W = |x - x~|_P^2 certified on the box with eta = {eta_cert:.6g} "
               f"({'proved' if proved else 'estimated'} grid margin, "
               f"{n_check} random pairs re-checked)")
    return Certificate(feasible=True, reason=summary, P=P_out, eta=eta_cert,
                       eta_without_margin=float(eta_grid), check_pairs=n_check,
                       check_worst=worst, solver_status=str(status), **common)


def _search(data, eta, P_fixed, max_condition, eta_tol, solver):
    """Fixed P, fixed η, or bisection on η. Returns (P, Ĉ, λ_A, λ_C, verified η, status)."""
    fail = (None, None, None, None, math.inf)
    if P_fixed is not None or eta is not None:
        P_n, C_hat, la, lc, status = _SDP(data, P_fixed, max_condition, solver).solve(eta)
        if P_n is None:
            return fail + (status,)
        return P_n, C_hat, la, lc, _verified_eta(data, P_n, C_hat, la, lc), status
    sdp = _SDP(data, None, max_condition, solver)
    best, status = None, None
    lo, hi = 0.0, 1.0 - 1e-6
    trial = hi
    while True:
        P_n, C_hat, la, lc, status = sdp.solve(trial)
        eta_v = _verified_eta(data, P_n, C_hat, la, lc) if P_n is not None else math.inf
        if eta_v < 1.0:
            if best is None or eta_v < best[4]:
                best = (P_n, C_hat, la, lc, eta_v, status)
            hi = min(trial, eta_v)
        elif best is None:
            return fail + (status,)
        else:
            lo = trial
        if hi - lo <= eta_tol:
            break
        trial = 0.5 * (lo + hi)
    # At the smallest feasible η the feasible set is thin and the P found there is nearly
    # singular; one more solve, eta_tol above it, returns a well-scaled P.
    relaxed = min(best[4] + eta_tol, 1.0 - 1e-6)
    P_n, C_hat, la, lc, status = sdp.solve(relaxed)
    eta_v = _verified_eta(data, P_n, C_hat, la, lc) if P_n is not None else math.inf
    if eta_v < 1.0 and np.linalg.eigvalsh(P_n)[0] > np.linalg.eigvalsh(best[0])[0]:
        return P_n, C_hat, la, lc, eta_v, status
    return best


# ============================================================================ model mismatch


class Mismatch:
    """The model mismatch (19)–(20) of a learned model against known true functions.

    Returned by :func:`mismatch`.

    Parameters
    ----------
    alpha_1, alpha_2 : float
        α₁^max and α₂^max.
    argmax_1, argmax_2 : ndarray (n_d,)
        Where they were found.

    Attributes
    ----------
    alpha_1, alpha_2 : float
        α₁^max = max ‖f − m_x‖_{Q_max⁻¹} and α₂^max = max ‖h − m_y‖_{R_max⁻¹} over X × U.
    alpha : float
        α^max = max(α₁^max, α₂^max), the last term of the bound (21).
    argmax_1, argmax_2 : ndarray (n_d,)
        The points d = [x; u] where the maxima were found.
    """

    def __init__(self, alpha_1, alpha_2, argmax_1, argmax_2):
        self.alpha_1, self.alpha_2 = float(alpha_1), float(alpha_2)
        self.alpha = max(self.alpha_1, self.alpha_2)
        self.argmax_1, self.argmax_2 = argmax_1, argmax_2

    def __repr__(self):
        return f"Mismatch(alpha_1={self.alpha_1:.6g}, alpha_2={self.alpha_2:.6g})"


def _true_values(fn, d, n, size, vectorized, name):
    X, U = d[:, :n].copy(), d[:, n:].copy()
    if vectorized:
        out = np.asarray(fn(X, U), dtype=np.float64)
    else:
        out = np.array([np.asarray(fn(x, u), dtype=np.float64).reshape(-1) for x, u in zip(X, U)])
    if out.shape != (d.shape[0], size) or not np.all(np.isfinite(out)):
        raise ValueError(f"{name}: must return finite values of shape ({size},) per point")
    return out


def mismatch(model, f, h, x_bounds, Q0, R0, u_bounds=None, *, n_samples=4096, n_local=5, seed=0,
             vectorized=False):
    """The maximal mismatch α₁^max, α₂^max (eqs. 19–20) between true functions and the model.

    For simulation studies in which the true f and h are known. The maxima over X × U are found
    by dense random sampling followed by bounded local maximisation (L-BFGS-B) from the best
    samples: a lower estimate of the true maximum, not a guaranteed bound.

    Parameters
    ----------
    model : LearnedModel or KnownModel
        The model whose means m_x, m_y the MHE uses.
    f, h : callable
        The true noise-free functions, f(x, u) -> (n,), h(x, u) -> (p,) per point (or, with
        `vectorized`, for arrays X (k, n), U (k, m)).
    x_bounds : pair of arrays (n,)
        The box X.
    Q0, R0 : float, array or matrix
        The constant covariance parts of the weights; Q_max⁻¹ = Q0⁻¹, R_max⁻¹ = R0⁻¹ (eq. 17).
    u_bounds : pair of arrays (m,), optional
        The box U (required when the model has inputs).
    n_samples : int
        Random points of the dense sampling.
    n_local : int
        Local maximisations started from the best samples.
    seed : int
        Seed of the sampling.
    vectorized : bool
        Whether f and h take arrays of points.

    Returns
    -------
    Mismatch
        α₁^max, α₂^max, α^max and where they were found.

    Raises
    ------
    ValueError
        On invalid arguments or if f, h return values of the wrong shape or non-finite values.

    Notes
    -----
    .. math:: \\alpha_1^{\\max} = \\max_{x\\in X, u\\in U} \\|f(x,u) - m_{+,x}(d)\\|_{Q_{\\max}^{-1}},
              \\quad \\alpha_2^{\\max} = \\max_{x\\in X, u\\in U} \\|h(x,u) - m_{+,y}(d)\\|_{R_{\\max}^{-1}}.

    References
    ----------
    .. [1] T. M. Wolff, V. G. Lopez and M. A. Müller, "Robust stability of Gaussian process based
       moving horizon estimation", IEEE CDC 2023, eqs. (19)–(21).

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe import KnownModel
    >>> from gpmhe.theory import mismatch
    >>> model = KnownModel(lambda x, u: 0.5 * x, lambda x, u: x[:1], dim_x=1, dim_y=1)
    >>> mm = mismatch(model, lambda x, u: 0.6 * x, lambda x, u: x[:1], (np.zeros(1), np.ones(1)),
    ...               Q0=1.0, R0=1.0, n_samples=64)
    >>> round(mm.alpha_1, 6), mm.alpha_2
    (0.1, 0.0)
    """
    model = _check_model(model)
    n, p, m = model.dim_x, model.dim_y, model.dim_u
    for name, fn in (("f", f), ("h", h)):
        if not callable(fn):
            raise ValueError(f"{name}: must be callable")
    xl, xu = _check_box("x_bounds", x_bounds, n)
    ul, uu = _check_box("u_bounds", u_bounds, m)
    Qmax_inv = np.linalg.inv(_check_spd("Q0", Q0, n))
    Rmax_inv = np.linalg.inv(_check_spd("R0", R0, p)) if p else np.zeros((0, 0))
    n_samples = integer("n_samples", n_samples, 1)
    n_local = integer("n_local", n_local, 0)
    seed = integer("seed", seed, 0)
    if not isinstance(vectorized, (bool, np.bool_)):
        raise ValueError(f"vectorized: must be True or False, got {vectorized!r}")
    lower, upper = np.concatenate([xl, ul]), np.concatenate([xu, uu])
    rng = np.random.default_rng(seed)
    d = np.vstack([rng.uniform(lower, upper, size=(n_samples, lower.size)),
                   lower, upper, 0.5 * (lower + upper)])

    def errors(points):
        mx, my = _means(model, points)
        ex = _true_values(f, points, n, n, vectorized, "f") - mx
        ey = _true_values(h, points, n, p, vectorized, "h") - my if p else np.zeros((len(points), 0))
        return (np.sqrt(np.maximum(np.einsum("ki,ij,kj->k", ex, Qmax_inv, ex), 0.0)),
                np.sqrt(np.maximum(np.einsum("ki,ij,kj->k", ey, Rmax_inv, ey), 0.0)))

    samples = errors(d)
    results = []
    for which in range(2):
        values = samples[which]
        best = int(np.argmax(values))
        best_val, best_pt = float(values[best]), d[best].copy()
        if which == 1 and not p:
            results.append((0.0, best_pt))
            continue
        for start in d[np.argsort(values)[::-1][:n_local]]:
            res = scipy.optimize.minimize(lambda z: -errors(z[None, :])[which][0], start,
                                          method="L-BFGS-B", bounds=list(zip(lower, upper)))
            if -res.fun > best_val:
                best_val, best_pt = float(-res.fun), np.asarray(res.x, dtype=float)
        results.append((best_val, best_pt))
    return Mismatch(results[0][0], results[1][0], results[0][1], results[1][1])


# ============================================================================ Corollary 1


class Corollary1:
    """The quantities (22)–(28) of Corollary 1 for a learned model.

    Returned by :func:`corollary1`.

    Parameters
    ----------
    **fields
        Values of the attributes below except `alpha`, which is computed.

    Attributes
    ----------
    tau, delta : float
        The grid constant τ and the failure probability δ per GP.
    covering_number : int
        B(τ, X × U): points of a grid of the box with every point within τ of one of them.
    beta : float
        β(τ) = 2 log(B(τ)/δ), eq. (22).
    L_m_x, L_m_y : ndarray (n,), (p,)
        Guaranteed Lipschitz constants (Euclidean) of the posterior means over the box.
    omega_x, omega_y : ndarray (n,), (p,)
        Moduli of continuity ω_σ(τ) of the posterior standard deviations.
    gamma_f, gamma_h : ndarray (n,), (p,)
        γ_{f_i}(τ), γ_{h_j}(τ) of eqs. (23)–(26).
    sigma_x_max, sigma_y_max : ndarray (n,), (p,)
        Guaranteed upper bounds of the posterior standard deviations over the box.
    Delta_x, Delta_y : float
        Δ_x^max(τ), Δ_y^max(τ) of eqs. (27)–(28).
    alpha : float
        max(Δ_x, Δ_y): the mismatch term to pass to :func:`error_bound` for the bound (29).
    probability : float
        (1 − δ)^{n+p}, the probability with which (29) holds.
    """

    def __init__(self, **fields):
        for key, value in fields.items():
            setattr(self, key, value)
        self.alpha = max(self.Delta_x, self.Delta_y)

    def __repr__(self):
        return (f"Corollary1(tau={self.tau}, delta={self.delta}, beta={self.beta:.4g}, "
                f"Delta_x={self.Delta_x:.4g}, Delta_y={self.Delta_y:.4g}, "
                f"probability={self.probability:.4g})")


def _gradient_variation(post, grid):
    """Bounds |∂m/∂d_b(d) − ∂m/∂d_b(d_g)| over each cell (k, n_d): the Hessian at the centre plus
    its variation over the cell, |∂_bc m(x) − ∂_bc m(z)| ≤ ‖m‖_H σ_f sqrt(c_bc) ‖(x−z)/φ‖/(φ_b φ_c)
    (c_bb = 15, else 3)."""
    H = np.abs(post.mean_hessian(grid.centers))
    nd = grid.half.size
    c = np.full((nd, nd), 3.0)
    np.fill_diagonal(c, 15.0)
    lip = post.rkhs_norm * post.sigma_f * np.sqrt(c) / np.outer(post.ls, post.ls)
    scaled = float(np.linalg.norm(grid.half / post.ls))
    return H @ grid.half + 0.5 * scaled * (lip @ grid.half)[None, :]


def _per_output(name, value, size):
    arr = np.broadcast_to(np.asarray(value, dtype=np.float64), (size,)) if size else np.zeros(0)
    if not np.all(np.isfinite(arr)) or np.any(arr < 0):
        raise ValueError(f"{name}: must be finite and >= 0 (a number or one per component)")
    return arr.copy()


def corollary1(model, x_bounds, Q0, R0, tau, delta, L_f, L_h, u_bounds=None, *, cells=None):
    """The quantities (22)–(28) of Corollary 1 (probabilistic mismatch bound) for a learned model.

    Parameters
    ----------
    model : LearnedModel
        The GP model.
    x_bounds : pair of arrays (n,)
        The box X.
    Q0, R0 : float, array or matrix
        The constant covariance parts of the weights (Q_max⁻¹ = Q0⁻¹, R_max⁻¹ = R0⁻¹).
    tau : float
        The grid constant τ > 0.
    delta : float
        The failure probability δ ∈ (0, 1) per GP.
    L_f, L_h : float or array
        Lipschitz constants of the true f_i (n values or one) and h_j (p values or one),
        assumed known (Assumption 2).
    u_bounds : pair of arrays (m,), optional
        The box U (required when the model has inputs).
    cells : int or sequence of int, optional
        Cells per dimension of the grid used for the guaranteed maxima over the box.

    Returns
    -------
    Corollary1
        β, γ, the Lipschitz constants of the means, the moduli of continuity, Δ_x, Δ_y, the
        probability and ``alpha`` = max(Δ_x, Δ_y) for :func:`error_bound`.

    Raises
    ------
    ValueError
        On invalid arguments or if `model` is not a LearnedModel.

    Notes
    -----
    Following Lederer, Umlauf & Hirche (2019) as used in the paper:

    .. math:: \\beta(\\tau) = 2\\log\\frac{B(\\tau)}{\\delta}, \\quad
              \\gamma_{f_i}(\\tau) = (L_{m_{x_i}} + L_{f_i})\\tau
              + \\sqrt{\\beta(\\tau)}\\,\\omega_{\\sigma_{x_i}}(\\tau),

    .. math:: \\Delta_x^{\\max}(\\tau) = \\sqrt{\\lambda_{\\max}(Q_{\\max}^{-1})}
              \\sum_i \\max_{d} \\big(\\sqrt{\\beta(\\tau)}\\sigma_{x_i}(d) + \\gamma_{f_i}(\\tau)\\big).

    Computed, not guessed: B(τ) counts a grid of the box whose cells have half-diagonal ≤ τ; the
    Lipschitz constants of the means are the largest gradient norms at the cell centres plus a
    proved bound of the gradient's variation in a cell (the Hessian at the centre and the SE
    kernel bound on its change); the modulus of continuity of the posterior standard deviation
    is ω(τ) = σ_f sqrt(2(1 − exp(−τ²/(2 φ_min²)))) (the posterior standard deviation changes by at
    most the prior distance of the kernel features); max σ is the guaranteed bound of
    :func:`weight_bounds`.

    References
    ----------
    .. [1] T. M. Wolff, V. G. Lopez and M. A. Müller, "Robust stability of Gaussian process based
       moving horizon estimation", IEEE CDC 2023, Corollary 1, eqs. (22)–(29).
    .. [2] A. Lederer, J. Umlauf and S. Hirche, "Uniform error bounds for Gaussian process
       regression with application to safe control", NeurIPS 2019, Thm. 3.1.

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe import LearnedModel
    >>> from gpmhe.theory import corollary1
    >>> rng = np.random.default_rng(0)
    >>> X = [np.column_stack([np.linspace(0, 1, 20), np.linspace(1, 0, 20)])]
    >>> Y = [X[0].sum(axis=1, keepdims=True)]
    >>> model = LearnedModel.from_trajectories(X, Y, optimizer=None)
    >>> c1 = corollary1(model, (np.zeros(2), np.ones(2)), 1e-2, 1e-2, tau=1e-3, delta=0.01,
    ...                 L_f=1.0, L_h=1.5)
    >>> c1.probability == 0.99 ** 3, c1.Delta_x > 0
    (True, True)
    """
    model = _check_model(model)
    if not _is_learned(model):
        raise ValueError("model: corollary1 needs a LearnedModel (its bounds come from the GPs)")
    n, p, m = model.dim_x, model.dim_y, model.dim_u
    xl, xu = _check_box("x_bounds", x_bounds, n)
    ul, uu = _check_box("u_bounds", u_bounds, m)
    Qmax_inv = np.linalg.inv(_check_spd("Q0", Q0, n))
    Rmax_inv = np.linalg.inv(_check_spd("R0", R0, p)) if p else np.zeros((0, 0))
    tau = positive_scalar("tau", tau)
    delta = positive_scalar("delta", delta)
    if not delta < 1:
        raise ValueError(f"delta: must be in (0, 1), got {delta!r}")
    L_f = _per_output("L_f", L_f, n)
    L_h = _per_output("L_h", L_h, p)
    lower, upper = np.concatenate([xl, ul]), np.concatenate([xu, uu])
    nd = lower.size
    grid = _Grid(lower, upper, _check_cells(cells, nd))
    side = 2.0 * tau / math.sqrt(nd)
    covering = int(np.prod(np.ceil((upper - lower) / side)))
    beta = 2.0 * math.log(covering / delta)
    out = model.stage_eval(grid.centers)
    grads = {"x": np.asarray(out[2]), "y": np.asarray(out[6])}
    result = {}
    _check_no_nominal(model)
    for key, gp, size in (("x", model.f_gp, n), ("y", model.h_gp, p)):
        if not size:
            result[key] = [np.zeros(0)] * 3
            continue
        posts = _posteriors(gp)
        _, std = gp.predict(grid.centers, return_std=True)
        std = std.reshape(len(grid.centers), size)
        lips, omegas, sig = [], [], []
        for o, post in enumerate(posts):
            g = np.abs(grads[key][:, o, :]) + _gradient_variation(post, grid)
            lips.append(float(np.max(np.linalg.norm(g, axis=1))))
            phi_min = float(np.min(post.ls))
            omegas.append(post.sigma_f * math.sqrt(2.0 * (1.0 - math.exp(-tau ** 2 / (2 * phi_min ** 2)))))
            sig.append(min(_std_upper_bound(post, grid, std[:, o]), post.sigma_f))
        result[key] = [np.array(lips), np.array(omegas), np.array(sig)]
    (Lmx, omx, sx), (Lmy, omy, sy) = result["x"], result["y"]
    gamma_f = (Lmx + L_f) * tau + math.sqrt(beta) * omx
    gamma_h = (Lmy + L_h) * tau + math.sqrt(beta) * omy
    Delta_x = math.sqrt(float(np.linalg.eigvalsh(Qmax_inv)[-1])) * float(np.sum(math.sqrt(beta) * sx + gamma_f))
    Delta_y = (math.sqrt(float(np.linalg.eigvalsh(Rmax_inv)[-1])) * float(np.sum(math.sqrt(beta) * sy + gamma_h))
               if p else 0.0)
    return Corollary1(tau=tau, delta=delta, covering_number=covering, beta=beta, L_m_x=Lmx,
                      L_m_y=Lmy, omega_x=omx, omega_y=omy, gamma_f=gamma_f, gamma_h=gamma_h,
                      sigma_x_max=sx, sigma_y_max=sy, Delta_x=Delta_x, Delta_y=Delta_y,
                      probability=(1.0 - delta) ** (n + p))


# ============================================================================ the error bound


def _noise_array(name, a, T, dim):
    try:
        arr = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: must be an array of shape (T, {dim})") from None
    if arr.ndim == 1 and dim == 1:
        arr = arr[:, None]
    if arr.ndim != 2 or arr.shape[1] != dim or (T is not None and arr.shape[0] != T):
        raise ValueError(f"{name}: expected shape ({'T' if T is None else T}, {dim}), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: contains NaN or inf")
    return arr


def _discounted_max(values, r):
    """B[t] = max_{q in [0, t-1]} r^q values[t-q-1] for t = 0..T (B[0] = 0)."""
    out = np.zeros(values.size + 1)
    for t in range(1, values.size + 1):
        out[t] = max(values[t - 1], r * out[t - 1])
    return out


def error_bound(cert, M, x0_error, w, v, alpha):
    """The right-hand side of the error bound (21) of Theorem 1 for t = 0, …, T.

    Parameters
    ----------
    cert : Certificate
        A feasible certificate of the model the MHE uses (P1, P2, η, Q_max⁻¹, R_max⁻¹).
    M : int
        The MHE horizon, M ≥ ``cert.min_horizon()``.
    x0_error : array (n,)
        The initial estimation error x̂(0) − x(0).
    w : array (T, n)
        The true process disturbances w(0), …, w(T−1).
    v : array (T, p)
        The true measurement noise v(0), …, v(T−1).
    alpha : float
        The mismatch α^max (eqs. 19–20, :func:`mismatch`; 0 for the exact model), or
        ``corollary1(...).alpha`` for the probabilistic bound (29).

    Returns
    -------
    ndarray (T + 1,)
        Upper bounds of ‖x̂(t) − x(t)‖_{P1}, t = 0, …, T.

    Raises
    ------
    ValueError
        On wrong shapes, non-finite values, a negative `alpha`, an infeasible certificate or
        M < ``cert.min_horizon()``.

    Notes
    -----
    With μ from μ^M = 4 λ_max(P2, P1) η^M and ρ = μ^{1/4},

    .. math:: \\|\\hat x(t) - x(t)\\|_{P_1} \\le \\max\\Big\\{6\\sqrt{\\mu}^{\\,t}
              \\|\\hat x(0) - x(0)\\|_{P_2},\\ \\max_{q\\in[0,t-1]} \\frac{12\\rho^q}{1-\\rho}
              \\|w(t-q-1)\\|_{Q_{\\max}^{-1}},\\ \\max_{q\\in[0,t-1]}\\frac{12\\rho^q}{1-\\rho}
              \\|v(t-q-1)\\|_{R_{\\max}^{-1}},\\ \\frac{12}{1-\\rho}\\alpha^{\\max}\\Big\\}.

    It holds for the exact minimiser of every window problem of the prediction-form MHE (10) run
    with P2, η of the certificate, Q0, R0, the constraint x̂ ∈ X, and true states in X.

    References
    ----------
    .. [1] T. M. Wolff, V. G. Lopez and M. A. Müller, "Robust stability of Gaussian process based
       moving horizon estimation", IEEE CDC 2023, Theorem 1, eq. (21).
    .. [2] J. D. Schiller, S. Muntwiler, J. Köhler, M. N. Zeilinger and M. A. Müller, "A Lyapunov
       function for robust stability of moving horizon estimation", IEEE Trans. Automat. Control
       68(12), 2023, Cor. 1.

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe.theory import Certificate, error_bound
    >>> cert = Certificate(feasible=True, P=np.eye(1), eta=0.5, Q0=np.eye(1), R0=np.eye(1))
    >>> b = error_bound(cert, M=3, x0_error=[1.0], w=np.zeros((2, 1)), v=np.zeros((2, 1)),
    ...                 alpha=0.0)
    >>> np.round(b, 4)
    array([6.    , 5.3454, 4.7622])
    """
    if not isinstance(cert, Certificate):
        raise ValueError("cert: must be a gpmhe.theory.Certificate")
    M = integer("M", M, 1)
    mu = cert.mu(M)
    if not mu < 1.0:
        raise ValueError(f"M: must be >= cert.min_horizon() = {cert.min_horizon()} (mu = {mu:.4g})")
    n = cert.P.shape[0]
    e0 = np.asarray(x0_error, dtype=np.float64).reshape(-1) if np.ndim(x0_error) <= 1 else None
    if e0 is None or e0.shape != (n,) or not np.all(np.isfinite(e0)):
        raise ValueError(f"x0_error: must be a finite array of shape ({n},)")
    w = _noise_array("w", w, None, n)
    T = w.shape[0]
    Qmax_inv = np.linalg.inv(cert.Q0)                      # eq. (17)
    p = cert.R0.shape[0]
    Rmax_inv = np.linalg.inv(cert.R0) if p else np.zeros((0, 0))
    v = _noise_array("v", v, T, p)
    alpha = positive_scalar("alpha", alpha, allow_zero=True)
    rho = mu ** 0.25
    gain = 12.0 / (1.0 - rho)
    nw = np.sqrt(np.maximum(np.einsum("ti,ij,tj->t", w, Qmax_inv, w), 0.0))
    nv = np.sqrt(np.maximum(np.einsum("ti,ij,tj->t", v, Rmax_inv, v), 0.0))
    t = np.arange(T + 1)
    initial = 6.0 * mu ** (t / 2.0) * math.sqrt(float(e0 @ cert.P2 @ e0))
    return np.maximum.reduce([initial, gain * _discounted_max(nw, rho),
                              gain * _discounted_max(nv, rho), np.full(T + 1, gain * alpha)])
