"""Tests of RecursiveGP.from_sparse and of the RGP-dKF on sparse GPs trained offline.

The references are the sparse GPs' own predictions, the inducing outputs' posterior written with
dense numpy from the sparse GP's data and hyperparameters (P = Kuu + Kuf Λ⁻¹ Kfu, explicit
solves), and a grid RecursiveGP that learned the same data: FITC's posterior of u is the exact
posterior under y_i ~ N(J_i u, σ_f² − J_i Kuu J_iᵀ + σ_ε²), which the recursive update applies
one measurement at a time, so a grid GP updated with the data equals the FITC GP whose inducing
points are the grid.
"""

import copy
import pickle

import numpy as np
import pytest

from gpmhe import (RGPEKF, GaussianProcess, MultiOutputGP, RecursiveGP, SparseGaussianProcess,
                   SparseMultiOutputGP)


def se_ard(a, b, sigma_f, lengthscales):
    d2 = (((a[:, None, :] - b[None, :, :]) / lengthscales) ** 2).sum(-1)
    return sigma_f**2 * np.exp(-0.5 * d2)


def truth(D):
    return np.sin(1.3 * D).sum(axis=1) + 0.4 * D[:, 0]


def fitted(method, nd, mean="zero", n=400, m=None, seed=0, **kw):
    rng = np.random.default_rng(seed)
    D = rng.uniform(-2.0, 2.0, (n, nd))
    y = truth(D) + 0.05 * rng.standard_normal(n)
    opts = dict(n_inducing=m or 15 * nd, method=method, mean=mean, random_state=0)
    return SparseGaussianProcess(**{**opts, **kw}).fit(D, y)


def dense_posterior(gp):
    """(μ_u, Σ_u, Kuu + δI) of a fitted SparseGaussianProcess, from its data with dense numpy."""
    theta = np.exp(gp.theta)
    sf, ls, se = theta[0], theta[1:-1], theta[-1]
    Z, D = gp.inducing_points, gp.D_train
    r = gp.y_train.copy()
    if gp.mean_coefficients is not None:
        r -= gp.mean_coefficients[0] + D @ gp.mean_coefficients[1:]
    Kuu = se_ard(Z, Z, sf, ls) + gp.jitter * np.eye(len(Z))
    Kuf = se_ard(Z, D, sf, ls)
    lam = np.full(len(r), se**2)
    if gp.method == "fitc":
        lam += sf**2 - np.einsum("ij,ij->j", Kuf, np.linalg.solve(Kuu, Kuf))
    P = Kuu + (Kuf / lam) @ Kuf.T
    mu = Kuu @ np.linalg.solve(P, Kuf @ (r / lam))
    Sigma = Kuu @ np.linalg.solve(P, Kuu)
    return mu, Sigma, Kuu


def rel_err(a, b):
    """max |a − b| relative to max |b|."""
    return np.max(np.abs(a - b)) / np.max(np.abs(b))


CASES = [(method, nd, mean) for method in ("vfe", "fitc") for nd in (1, 2) for mean in ("zero", "linear")]


@pytest.mark.parametrize("method, nd, mean", CASES)
def test_from_sparse_predicts_as_the_sparse_gp(method, nd, mean):
    sgp = fitted(method, nd, mean)
    gp = RecursiveGP.from_sparse(sgp)
    Dt = np.random.default_rng(1).uniform(-3.0, 3.0, (300, nd))
    m, s = gp.predict(Dt, return_std=True)
    ms, ss = sgp.predict(Dt, return_std=True)
    assert rel_err(m, ms) < 1e-9
    assert rel_err(s, ss) < 1e-9
    # as a fixed model inside the filter, too
    ekf = RGPEKF(1, lambda x, u, z: x + z, 1.0, 1.0, lambda x: x, [[1.0]], Q_x=0.0, R_x=0.1,
                 x0=[0.0], P0=1.0, gps=gp, pure_prediction=True)
    mk, sk = ekf.gp_predict(Dt, return_std=True)
    assert rel_err(mk, ms) < 1e-9 and rel_err(sk, ss) < 1e-9


@pytest.mark.parametrize("method, nd, mean", CASES)
def test_weights_J_and_predictions_match_dense_numpy(method, nd, mean):
    # Fixed hyperparameters with well-conditioned K(Z, Z) and P, so that the dense reference's own
    # rounding (explicit solves with Kuu and P) stays far below the tolerance.
    sgp = fitted(method, nd, mean, m=10, optimizer=None, sigma_f=1.3, lengthscales=[0.6, 0.8][:nd],
                 sigma_eps=0.2)
    gp = RecursiveGP.from_sparse(sgp, sigma_r=0.03)
    mu, Sigma, Kj = dense_posterior(sgp)
    theta = np.exp(sgp.theta)
    sf, ls = theta[0], theta[1:-1]
    assert np.linalg.cond(Kj) < 1e7
    np.testing.assert_array_equal(gp.basis_vectors, sgp.inducing_points)
    np.testing.assert_allclose(gp.K, se_ard(sgp.inducing_points, sgp.inducing_points, sf, ls), rtol=1e-13)
    np.testing.assert_allclose([gp.sigma_K, *gp.lengthscales], [sf, *ls], rtol=1e-15)
    assert gp.jitter == sgp.jitter
    assert (gp.n_basis, gp.dim_zeta) == (len(sgp.inducing_points), nd)
    assert rel_err(gp.mean, mu) < 1e-8
    assert rel_err(gp.cov, Sigma) < 1e-8
    np.testing.assert_array_equal(gp.cov, gp.cov.T)
    if mean == "zero":
        assert gp.prior_mean is None
    else:
        np.testing.assert_array_equal(gp.prior_mean, sgp.mean_coefficients)
    coef = np.zeros(nd + 1) if gp.prior_mean is None else gp.prior_mean
    for zeta in np.random.default_rng(2).uniform(-2.5, 2.5, (5, nd)):
        J = np.linalg.solve(Kj, se_ard(sgp.inducing_points, zeta[None], sf, ls))[:, 0]
        assert rel_err(gp.J(zeta), J) < 1e-8
        m, s = gp.predict(zeta[None], return_std=True)
        var = sf**2 - J @ Kj @ J + J @ Sigma @ J + 0.03**2
        assert m[0] == pytest.approx(J @ mu + coef[0] + coef[1:] @ zeta, rel=1e-8, abs=1e-10)
        assert s[0] == pytest.approx(np.sqrt(var), rel=1e-8)


def test_output_of_a_multi_output_sparse_gp():
    rng = np.random.default_rng(3)
    D = rng.uniform(-2.0, 2.0, (300, 2))
    Y = np.column_stack([truth(D), np.cos(D[:, 1])]) + 0.05 * rng.standard_normal((300, 2))
    sgp = SparseMultiOutputGP(n_inducing=20, method="fitc", mean="linear").fit(D, Y)
    Dt = rng.uniform(-2.5, 2.5, (50, 2))
    ms, ss = sgp.predict(Dt, return_std=True)
    for o in (0, 1):
        gp = RecursiveGP.from_sparse(sgp, output=o)
        np.testing.assert_array_equal(gp.basis_vectors, sgp.inducing_points[o])
        m, s = gp.predict(Dt, return_std=True)
        assert rel_err(m, ms[:, o]) < 1e-9 and rel_err(s, ss[:, o]) < 1e-9


def test_learning_continues_a_fitc_model_exactly():
    """from_sparse(FITC on the first half) updated with the second half (var_y = σ_ε²) is the
    FITC model of all the data (same θ and Z)."""
    rng = np.random.default_rng(4)
    D = rng.uniform(-2.0, 2.0, (200, 1))
    y = truth(D) + 0.05 * rng.standard_normal(200)
    Z = np.linspace(-2.0, 2.0, 12)[:, None]
    opts = dict(method="fitc", inducing=Z, optimizer=None, sigma_f=1.5, lengthscales=0.6, sigma_eps=0.05)
    gp = RecursiveGP.from_sparse(SparseGaussianProcess(**opts).fit(D[:100], y[:100]))
    gp.update(D[100:], y[100:], 0.05**2)
    full = SparseGaussianProcess(**opts).fit(D, y)
    want = RecursiveGP.from_sparse(full)
    assert rel_err(gp.mean, want.mean) < 1e-8 and rel_err(gp.cov, want.cov) < 1e-8
    Dt = np.linspace(-2.5, 2.5, 40)
    assert rel_err(gp.predict(Dt), full.predict(Dt[:, None])) < 1e-8


def _grid_pair(method, nd):
    """A grid RecursiveGP that learned 300 noisy samples with var_y = σ_ε², and the sparse GP of
    `method` fitted to them with the grid as fixed inducing points and the same kernel."""
    lo, hi, npts, sK, L, se = -2.0, 2.0, 9, 1.5, 2.0, 0.1
    rng = np.random.default_rng(5)
    D = rng.uniform(lo, hi, (300, nd))
    y = truth(D) + se * rng.standard_normal(300)
    grid = RecursiveGP([lo] * nd, [hi] * nd, npts, sigma_K=sK, L=L)
    grid.update(D if nd > 1 else D[:, 0], y, se**2)
    spacing = (hi - lo) / (npts - 1)
    sgp = SparseGaussianProcess(method=method, inducing=grid.basis_vectors, optimizer=None, sigma_f=sK,
                                lengthscales=np.sqrt(L) * spacing, sigma_eps=se).fit(D, y)
    return grid, sgp


@pytest.mark.parametrize("nd", [1, 2])
def test_grid_gp_that_learned_the_data_is_the_fitc_gp_on_the_grid(nd):
    grid, sgp = _grid_pair("fitc", nd)
    gp = RecursiveGP.from_sparse(sgp)
    assert rel_err(gp.K, grid.K) < 1e-12
    assert rel_err(gp.mean, grid.mean) < 1e-8 and rel_err(gp.cov, grid.cov) < 1e-8


def _run(gp, pure_prediction, steps=60):
    """An RGP-dKF on x⁺ = A x + e z(ζ), y = x[0] + v, with data from the truth; its estimates."""
    A0 = np.array([[0.9, 0.1], [-0.1, 0.8]])
    e0 = np.array([0.0, 0.2])
    ekf = RGPEKF(2, f=lambda x, u, z: A0 @ x + e0 * z, A=A0, e=e0, h=lambda x: x[:1], H=[[1.0, 0.0]],
                 Q_x=1e-4, R_x=1e-3, x0=[0.2, -0.1], P0=0.1, gps=gp, pure_prediction=pure_prediction)
    rng = np.random.default_rng(6)
    x = np.array([0.3, 0.0])
    out = []
    for _ in range(steps):
        zeta = rng.uniform(-2.0, 2.0, gp.dim_zeta)
        ekf.predict(None, zeta)
        x = A0 @ x + e0 * truth(zeta[None])[0]
        ekf.update([x[0] + 0.03 * rng.standard_normal()])
        out.append(np.concatenate([ekf.x, ekf.P.ravel(), ekf.z_pred]))
    return np.array(out), ekf


@pytest.mark.parametrize("pure_prediction", [True, False])
@pytest.mark.parametrize("method", ["fitc", "vfe"])
def test_rgp_dkf_on_a_sparse_gp_equals_it_on_the_grid_gp(method, pure_prediction):
    """The same model on both sides: the sparse GP on the grid (FITC: the grid GP learned the
    same data; VFE: the grid GP is given the sparse GP's weights), in pure prediction and with
    learning."""
    grid, sgp = _grid_pair(method, 1)
    gp = RecursiveGP.from_sparse(sgp)
    if method == "vfe":
        grid.set_weights(gp.mean, gp.cov)
    got, ekf = _run(gp, pure_prediction)
    want, ekf_grid = _run(grid, pure_prediction)
    assert rel_err(got, want) < 1e-8
    assert rel_err(ekf.gp_weights()[0], ekf_grid.gp_weights()[0]) < 1e-8
    if pure_prediction:
        np.testing.assert_array_equal(ekf.gp_weights()[0], gp.mean)


def test_pure_prediction_feeds_the_sparse_gp_mean_and_variance():
    """One step of the filter with a linear-mean sparse GP, against the formulas of §3.2 with the
    sparse GP's own prediction: x⁻ = A x + e m(ζ), P⁻ = A P Aᵀ + Q + e (s² + σ_r²) eᵀ."""
    sgp = fitted("vfe", 1, "linear")
    gp = RecursiveGP.from_sparse(sgp, sigma_r=0.02)
    A0 = np.array([[1.0, 0.05], [-0.05, 0.95]])
    e0 = np.array([0.0, 0.5])
    seen = []

    def f(x, u, z):
        seen.append(z)
        return A0 @ x + e0 * z

    ekf = RGPEKF(2, f=f, A=A0, e=e0, h=lambda x: x[:1], H=[[1, 0]], Q_x=1e-6, R_x=1e-2, x0=[0.5, 0.0],
                 P0=0.1, gps=gp, pure_prediction=True)
    P0 = ekf.P
    ekf.predict(None, 1.7)
    m, s = sgp.predict([[1.7]], return_std=True)
    assert seen[-1] == pytest.approx(m[0], rel=1e-10)
    np.testing.assert_allclose(ekf.z_pred, m, rtol=1e-10)
    np.testing.assert_allclose(ekf.x, A0 @ [0.5, 0.0] + e0 * m[0], rtol=1e-10)
    np.testing.assert_allclose(ekf.P, A0 @ P0 @ A0.T + 1e-6 * np.eye(2) + np.outer(e0, e0) * (s[0]**2 + 0.02**2),
                               rtol=1e-9)


def test_copies_and_pickles_continue_bit_identically():
    gp = RecursiveGP.from_sparse(fitted("fitc", 2, "linear"), sigma_r=0.01, sigma_p=0.001)
    rng = np.random.default_rng(7)
    Z, y = rng.uniform(-2, 2, (20, 2)), rng.standard_normal(20)
    gp.update(Z[:10], y[:10], 0.01)
    copies = [gp.copy(), copy.deepcopy(gp)] + [pickle.loads(pickle.dumps(gp, protocol=p)) for p in (2, 4, 5)]
    gp.update(Z[10:], y[10:], 0.01)
    for other in copies:
        assert repr(other) == repr(gp)
        other.update(Z[10:], y[10:], 0.01)
        np.testing.assert_array_equal(other.mean, gp.mean)
        np.testing.assert_array_equal(other.cov, gp.cov)
        np.testing.assert_array_equal(other.predict(Z), gp.predict(Z))


def test_attributes_and_repr():
    sgp = fitted("vfe", 2, "linear")
    gp = RecursiveGP.from_sparse(sgp, sigma_r=0.1)
    assert gp.lower is None and gp.upper is None and gp.n_points is None and gp.L is None
    assert (gp.sigma_r, gp.sigma_p) == (0.1, 0.0)
    assert repr(gp).startswith(f"RecursiveGP(points: n_basis={len(sgp.inducing_points)}, dim_zeta=2, sigma_K=")
    assert "prior_mean=" in repr(gp)
    grid = RecursiveGP([0.0, 1.0], [2.0, 4.0], [5, 4], L=2.0)
    np.testing.assert_allclose(grid.lengthscales, np.sqrt(2.0) * np.array([0.5, 1.0]), rtol=1e-15)
    assert grid.prior_mean is None


def _sparse_state(sgp):
    return sgp.theta.copy(), sgp.inducing_points.copy(), sgp.predict([[0.3]], return_std=True)


@pytest.mark.parametrize("gp, kw, arg", [
    (GaussianProcess(optimizer=None).fit(np.zeros((3, 1)) + [[0], [1], [2]], [0.0, 1.0, 0.0]), {}, "gp"),
    (MultiOutputGP(optimizer=None).fit([[0.0], [1.0], [2.0]], [[0.0, 1.0]] * 3), {}, "gp"),
    (SparseGaussianProcess(), {}, "gp"),
    (SparseMultiOutputGP(), {}, "gp"),
    (RecursiveGP(0.0, 1.0, 5), {}, "gp"),
    (None, {}, "gp"),
    ("sparse", {"output": 1}, "output"),
    ("sparse", {"output": -1}, "output"),
    ("sparse", {"output": True}, "output"),
    ("sparse", {"output": 0.0}, "output"),
    ("sparse", {"sigma_r": -0.1}, "sigma_r"),
    ("sparse", {"sigma_r": np.nan}, "sigma_r"),
    ("sparse", {"sigma_p": np.inf}, "sigma_p"),
    ("sparse", {"sigma_p": [0.1]}, "sigma_p"),
])
def test_bad_input_raises_naming_the_argument_and_changes_nothing(gp, kw, arg):
    sgp = fitted("vfe", 1, m=6) if gp == "sparse" else gp
    before = _sparse_state(sgp) if gp == "sparse" else None
    with pytest.raises(ValueError, match=f"^{arg}: "):
        RecursiveGP.from_sparse(sgp, **kw)
    if before is not None:
        for a, b in zip(_sparse_state(sgp), before):
            np.testing.assert_array_equal(np.asarray(a, dtype=object), np.asarray(b, dtype=object))
