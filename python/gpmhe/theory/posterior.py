"""The SE-ARD posterior of the learned model's GPs as the certificate's bounds need it (the
Hessian of the mean, the covariance of the gradient, the RKHS norm of the mean), in numpy on the
Rust core's kernel (`gpmhe._core.se_ard_kernel`, the one SE-ARD implementation)."""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg
import scipy.optimize

from gpmhe import _core
from gpmhe.gp import SparseGaussianProcess, SparseMultiOutputGP
from gpmhe.theory.common import _is_learned
from gpmhe.theory.constants import _EPS


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
        return _core.se_ard_kernel(np.ascontiguousarray(a, dtype=np.float64),
                                   np.ascontiguousarray(b, dtype=np.float64), self.sigma_f,
                                   np.ascontiguousarray(self.ls))

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
    mean: an affine mean adds nothing to the Hessian and the variances). Sparse GPs are refused:
    these are the exact posterior's formulas, and a sparse GP's posterior differs from it."""
    if isinstance(gp, (SparseGaussianProcess, SparseMultiOutputGP)):
        raise ValueError(f"model: the bounds are derived for exact GPs; this model's GPs are a {type(gp).__name__} "
                         f"(fit the LearnedModel without n_inducing to certify it)")
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


