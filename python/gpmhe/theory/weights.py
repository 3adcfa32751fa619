"""`weight_bounds`: the bounds Q_min⁻¹, Q_max⁻¹, R_min⁻¹, R_max⁻¹ of the GP-MHE weights over the box
(the paper's eqs. (14)–(17))."""

from __future__ import annotations


import numpy as np


from gpmhe.theory.common import _check_model, _is_learned, _check_spd, _check_box, _Grid, _check_cells
from gpmhe.theory.posterior import _model_posteriors, _std_upper_bound

__all__ = ['WeightBounds', 'weight_bounds']


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


