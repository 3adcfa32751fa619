"""The sparse GPs' analytic gradients (θ and the inducing inputs Z) against central differences of
the same objective computed in extended precision (numpy's 80-bit long double: a Cholesky
factorisation and triangular solves written out here), for VFE and FITC, at condition numbers of
K(Z, Z) from 1e2 to 1e18 (the core then factors K(Z, Z) + δI with its jitter δ = c σ_f², and so
does the reference). Forming Kuu⁻¹ and P⁻¹ explicitly gave relative errors up to 0.66 here."""

import numpy as np
import pytest

from gpmhe import _core

LD = np.longdouble
pytestmark = pytest.mark.skipif(np.finfo(LD).eps > 1e-18, reason="needs 80-bit long double")


def _cholesky(A):
    n = len(A)
    L = np.zeros_like(A)
    for j in range(n):
        L[j, j] = np.sqrt(A[j, j] - (L[j, :j] ** 2).sum())
        for i in range(j + 1, n):
            L[i, j] = (A[i, j] - (L[i, :j] * L[j, :j]).sum()) / L[j, j]
    return L


def _solve_lower(L, B):
    X = np.array(B, dtype=LD)
    for i in range(len(L)):
        X[i] = (X[i] - L[i, :i] @ X[:i]) / L[i, i]
    return X


def reference(X, y, Z, theta, method, c):
    """The training objective (module docs of rust/src/sparse/objective.rs) in long double, with
    K(Z, Z) + c σ_f² I factored."""
    X, y, Z, theta = (np.asarray(a, dtype=LD) for a in (X, y, Z, theta))
    sf2, ls, s2 = np.exp(2 * theta[0]), np.exp(theta[1:-1]), np.exp(2 * theta[-1])

    def k(A, B):
        return sf2 * np.exp(-(((A[:, None, :] - B[None, :, :]) / ls) ** 2).sum(-1) / 2)

    m, N = len(Z), len(X)
    L = _cholesky(k(Z, Z) + c * sf2 * np.eye(m, dtype=LD))
    V = _solve_lower(L, k(Z, X))
    q = (V ** 2).sum(0)
    lam = np.full(N, s2) if method == "vfe" else np.maximum(sf2 - q, 0) + s2
    LB = _cholesky(np.eye(m, dtype=LD) + (V / lam) @ V.T)
    c_ = _solve_lower(LB, V @ (y / lam))
    F = (-N / 2 * np.log(2 * np.pi * LD(1)) - np.log(lam).sum() / 2 - np.log(np.diag(LB)).sum()
         - (y * y / lam).sum() / 2 + c_ @ c_ / 2)
    if method == "vfe":
        F -= (N * sf2 - q.sum()) / (2 * s2)
    return F


def jitter_factor(Z, theta):
    """The core's jitter policy (rust/src/sparse/mod.rs): the first of 0, 1e-10, ..., 1e-6
    (times σ_f²) with which K(Z, Z) factors with every pivot L_ii² >= 1e-11 σ_f²."""
    sf2, ls = np.exp(2 * theta[0]), np.exp(theta[1:-1])
    K = sf2 * np.exp(-0.5 * (((Z[:, None, :] - Z[None, :, :]) / ls) ** 2).sum(-1))
    for a in range(6):
        c = 0.0 if a == 0 else 1e-10 * 10 ** (a - 1)
        try:
            L = np.linalg.cholesky(K + c * sf2 * np.eye(len(Z)))
        except np.linalg.LinAlgError:
            continue
        if np.all(np.diag(L) ** 2 >= 1e-11 * sf2):
            return c
    raise AssertionError("no jitter works")


RNG = np.random.default_rng(1)
X = RNG.uniform(-1.0, 1.0, (50, 1))
Y = np.sin(3.0 * X[:, 0]) + 0.1 * RNG.standard_normal(50)
Z = np.linspace(-0.5, 0.5, 12)[:, None]


@pytest.mark.parametrize("method", ["vfe", "fitc"])
@pytest.mark.parametrize("sigma_f", [0.5, 2.0])
@pytest.mark.parametrize("lengthscale", [0.1, 0.3, 1.0, 3.0, 10.0])
def test_theta_gradient_matches_extended_precision(method, sigma_f, lengthscale):
    theta = np.log([sigma_f, lengthscale, 0.1])
    cond = np.linalg.cond(np.exp(-0.5 * ((Z - Z.T) / lengthscale) ** 2))
    c = jitter_factor(Z, theta)
    _, grad, _ = _core.sparse_objective(X, Y, Z, theta, method, True)
    h = LD("1e-5")
    fd = np.empty(3)
    for i in range(3):
        e = np.zeros(3, dtype=LD)
        e[i] = h
        t = theta.astype(LD)
        fd[i] = float((reference(X, Y, Z, t + e, method, c) - reference(X, Y, Z, t - e, method, c)) / (2 * h))
    err = np.max(np.abs(grad - fd)) / (1.0 + np.max(np.abs(fd)))
    assert err <= 1e-5, f"cond(Kuu) = {cond:.1e}: relative gradient error {err:.1e}"


@pytest.mark.parametrize("method", ["vfe", "fitc"])
@pytest.mark.parametrize("lengthscale", [0.3, 3.0])
def test_inducing_gradient_matches_extended_precision(method, lengthscale):
    theta = np.log([1.0, lengthscale, 0.1])
    c = jitter_factor(Z, theta)
    _, _, gz = _core.sparse_objective(X, Y, Z, theta, method, True)
    h = LD("1e-6")
    fd = np.empty(len(Z))
    for i in range(len(Z)):
        e = np.zeros_like(Z, dtype=LD)
        e[i, 0] = h
        Zl = Z.astype(LD)
        fd[i] = float((reference(X, Y, Zl + e, theta, method, c) - reference(X, Y, Zl - e, theta, method, c)) / (2 * h))
    err = np.max(np.abs(gz[:, 0] - fd)) / (1.0 + np.max(np.abs(fd)))
    # At ℓ = 0.3, cond(Kuu) ≈ 4e10 with no jitter: the gradient keeps about 4 digits (relative
    # error 1.1e-4 for VFE, 0.9e-4 for FITC on one x86_64 CPU, below 1e-4 on another with the
    # same code: the matrix-product kernels, chosen at run time, round differently); the
    # explicit inverses gave 0.66.
    assert err <= 3e-4, f"relative error {err:.1e}"
