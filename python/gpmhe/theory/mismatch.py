"""`mismatch`: the largest model mismatch α₁^max, α₂^max between the learned model and the true
f, h over the box (the paper's eqs. (19)–(20))."""

from __future__ import annotations


import numpy as np
import scipy.linalg
import scipy.optimize

from gpmhe._validation import integer

from gpmhe.theory.common import _check_model, _check_spd, _check_box
from gpmhe.theory.lmi import _means

__all__ = ['Mismatch', 'mismatch']


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


