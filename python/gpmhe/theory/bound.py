"""`error_bound`: the right-hand side of the paper's error bound (21) for a certified design."""

from __future__ import annotations

import math

import numpy as np

from gpmhe._validation import integer, positive_scalar

from gpmhe.theory.certificate import Certificate

__all__ = ['error_bound']


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
