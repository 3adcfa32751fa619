"""`corollary1`: the quantities of the paper's Corollary 1 (eqs. (22)–(28)) from GP error bounds
and Lipschitz constants."""

from __future__ import annotations

import math

import numpy as np

from gpmhe._validation import positive_scalar

from gpmhe.theory.common import _check_model, _is_learned, _check_spd, _check_box, _Grid, _check_cells
from gpmhe.theory.posterior import _posteriors, _check_no_nominal, _std_upper_bound

__all__ = ['Corollary1', 'corollary1']


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


