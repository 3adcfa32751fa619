"""Tests of RecursiveGP and RGPEKF against independent numpy/scipy/scikit-learn computations.

The references here are written from the paper's equations with dense numpy (explicit solves, the
dense Ã C Ãᵀ of eq. 12–13), independent of the Rust kernels they check.
"""

import numpy as np
import pytest
from scipy.stats import multivariate_normal

import gpmhe
from gpmhe import RGPEKF, RecursiveGP


def kernel(a, b, sigma_K, L):
    d2 = ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)
    return sigma_K**2 * np.exp(-d2 / (2 * L))


class NumpyRGP:
    """Huber's RGP, eq. (2)–(4) with σ_r, σ_p, written with dense numpy solves."""

    def __init__(self, lower, upper, n, sigma_K, L, sigma_r, sigma_p):
        self.lower, self.scale = lower, (n - 1) / (upper - lower)
        self.X = np.arange(n, dtype=float)[:, None]
        self.sK, self.L, self.sr2, self.sp2 = sigma_K, L, sigma_r**2, sigma_p**2
        self.K = kernel(self.X, self.X, sigma_K, L)
        self.mean = np.zeros(n)
        self.cov = self.K.copy()

    def J(self, zeta):
        x = np.atleast_2d((zeta - self.lower) * self.scale)
        return np.linalg.solve(self.K, kernel(self.X, x, self.sK, self.L)).T  # (1, n)

    def update(self, zeta, y, var_y):
        J = self.J(zeta)
        cp = self.sK**2 + (J @ (self.cov - self.K) @ J.T).item()
        G = self.cov @ J.T / (cp + self.sr2 + var_y)
        self.mean = self.mean + G[:, 0] * (y - (J @ self.mean).item())
        self.cov = self.cov - G @ J @ self.cov + self.sp2 * np.eye(len(self.mean))


def test_kernel_matrix_and_J_match_dense_solve():
    gp = RecursiveGP(-1.0, 3.0, 9, sigma_K=2.0, L=1.5)
    ref = NumpyRGP(-1.0, 3.0, 9, 2.0, 1.5, 0.0, 0.0)
    np.testing.assert_allclose(gp.K, ref.K, rtol=1e-14)
    np.testing.assert_allclose(gp.basis_vectors[:, 0], np.linspace(-1, 3, 9), atol=1e-14)
    for z in [-1.3, 0.2, 1.77, 3.0]:
        np.testing.assert_allclose(gp.J(z), ref.J(z)[0], rtol=1e-8, atol=1e-10)


def test_recursive_updates_match_numpy_reference():
    rng = np.random.default_rng(0)
    gp = RecursiveGP(-2.0, 2.0, 12, sigma_K=3.0, L=2.0, sigma_r=0.1, sigma_p=0.01)
    ref = NumpyRGP(-2.0, 2.0, 12, 3.0, 2.0, 0.1, 0.01)
    for _ in range(60):
        z = rng.uniform(-2.5, 2.5)
        y = np.sin(2 * z) + 0.05 * rng.standard_normal()
        gp.update(z, y, 0.05**2)
        ref.update(z, y, 0.05**2)
    np.testing.assert_allclose(gp.mean, ref.mean, rtol=1e-8, atol=1e-9)
    np.testing.assert_allclose(gp.cov, ref.cov, rtol=1e-7, atol=1e-9)
    zs = np.linspace(-2, 2, 7)
    m, s = gp.predict(zs, return_std=True)
    J = np.vstack([ref.J(z) for z in zs])
    var = 9.0 - np.einsum("ij,jk,ik->i", J, ref.K - ref.cov, J) + 0.1**2
    np.testing.assert_allclose(m, J @ ref.mean, rtol=1e-8, atol=1e-9)
    np.testing.assert_allclose(s, np.sqrt(var), rtol=1e-7)


def test_two_dimensional_grid():
    gp = RecursiveGP([0.0, -1.0], [1.0, 1.0], [4, 3], sigma_K=1.0, L=1.0)
    assert gp.n_basis == 12
    bv = gp.basis_vectors
    # eq. (5): the first axis varies fastest
    np.testing.assert_allclose(bv[:4, 0], np.linspace(0, 1, 4))
    np.testing.assert_allclose(bv[::4, 1], [-1.0, 0.0, 1.0])
    # at a basis vector J is a unit vector, so the prediction is that weight
    rng = np.random.default_rng(1)
    for _ in range(30):
        gp.update(rng.uniform([0, -1], [1, 1]), rng.standard_normal(), 0.1)
    m = gp.predict(bv)
    np.testing.assert_allclose(m, gp.mean, atol=1e-8)


def _se_gp_sklearn(X, y, Xs, sigma_K, L, alpha):
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel

    k = ConstantKernel(sigma_K**2, "fixed") * RBF(np.sqrt(L), "fixed")
    reg = GaussianProcessRegressor(k, alpha=alpha, optimizer=None, normalize_y=False)
    reg.fit(X, y)
    return reg.predict(Xs, return_std=True)


def test_approaches_batch_gp_posterior_on_basis_vectors():
    """Many noise-free samples: the RGP weights approach the exact batch GP posterior (same
    kernel, scikit-learn) at the basis vectors; the gap shrinks as data accumulate."""
    rng = np.random.default_rng(2)
    lo, hi, n, sK, L = 0.0, 4.0, 9, 1.0, 1.0
    truth = lambda z: np.sin(1.3 * z) + 0.3 * z  # noqa: E731
    zs = rng.uniform(lo, hi, 3000)
    gaps = []
    gp = RecursiveGP(lo, hi, n, sigma_K=sK, L=L)
    done = 0
    for m in (100, 3000):
        for z in zs[done:m]:
            gp.update(z, truth(z), 0.0)
        done = m
        Xn = ((zs[:m] - lo) * (n - 1) / (hi - lo))[:, None]
        mean_b, _ = _se_gp_sklearn(Xn, truth(zs[:m]), np.arange(n)[:, None], sK, L, 1e-8)
        gaps.append(np.max(np.abs(gp.mean - mean_b)))
    # 30x the data shrinks the gap about 10x; at 3000 samples it is < 1 % of the function's range
    assert gaps[1] < 0.2 * gaps[0], gaps
    assert gaps[1] < 1e-2, gaps
    # and the batch posterior itself is close to the truth at the basis vectors
    np.testing.assert_allclose(mean_b, truth(gp.basis_vectors[:, 0]), atol=1e-3)


def test_exact_at_basis_vectors_equals_batch_gp():
    """Observations exactly at basis vectors: J is a unit vector and the RGP is the exact GP."""
    rng = np.random.default_rng(3)
    gp = RecursiveGP(0.0, 8.0, 9, sigma_K=1.5, L=2.0)
    idx = rng.integers(0, 9, 25)
    ys = rng.standard_normal(25)
    for i, y in zip(idx, ys):
        gp.update(float(i), y, 0.04)
    mean_b, std_b = _se_gp_sklearn(idx[:, None].astype(float), ys, np.arange(9)[:, None], 1.5, 2.0, 0.04)
    np.testing.assert_allclose(gp.mean, mean_b, rtol=1e-8, atol=1e-9)
    np.testing.assert_allclose(np.sqrt(np.diag(gp.cov)), std_b, rtol=1e-7, atol=1e-9)


@pytest.mark.parametrize("sigma_p", [0.02, 0.0])  # 0: RGPEKF stores the weights whitened
def test_rgpekf_reproduces_recursive_gp_section_3_5(sigma_p):
    """Paper §3.5: with A = 0, f = z (the state is the GP output) and H = 1, RGPEKF is RGP."""
    rng = np.random.default_rng(4)
    gp = RecursiveGP(-2.0, 2.0, 15, sigma_K=2.0, L=2.0, sigma_r=0.05, sigma_p=sigma_p)
    var_y = 0.1**2
    ekf = RGPEKF(1, f=lambda x, u, z: np.array([z]), A=[[0.0]], e=[1.0], h=lambda x: x, H=[[1.0]],
                 Q_x=0.0, R_x=var_y, x0=[0.0], P0=1.0, gps=gp)
    for _ in range(300):
        z = rng.uniform(-2.2, 2.2)
        y = np.tanh(2 * z) + 0.1 * rng.standard_normal()
        ekf.predict(None, z)
        ekf.update(y)
        gp.update(z, y, var_y)
        m, c = ekf.gp_weights()
        np.testing.assert_allclose(m, gp.mean, rtol=0, atol=1e-10 * (1 + np.abs(gp.mean).max()))
        np.testing.assert_allclose(c, gp.cov, rtol=0, atol=1e-10)
    zs = np.linspace(-2, 2, 11)
    np.testing.assert_allclose(ekf.gp_predict(zs), gp.predict(zs), atol=1e-10)


def _dense_prediction(C, A, e, Js, D, Qx, sp2, n):
    """Eq. (12)–(13) with dense matrices; e (n, q), Js list of (n_b,), D (q,), sp2 (q,)."""
    N = C.shape[0]
    At = np.eye(N)
    At[:n, :n] = A
    o = n
    Qz = []
    for g, J in enumerate(Js):
        At[:n, o : o + len(J)] = np.outer(e[:, g], J)
        Qz += [sp2[g]] * len(J)
        o += len(J)
    et = np.zeros((N, e.shape[1]))
    et[:n] = e
    Q = np.zeros((N, N))
    Q[:n, :n] = Qx
    Q[n:, n:] = np.diag(Qz)
    return At @ C @ At.T + et @ np.diag(D) @ et.T + Q


def test_structured_prediction_equals_dense_formula_two_gps():
    rng = np.random.default_rng(5)
    n = 3
    gps = [RecursiveGP(-1, 1, 6, sigma_K=1.2, L=1.0, sigma_r=0.1, sigma_p=0.03),
           RecursiveGP([0, 0], [1, 2], [3, 4], sigma_K=0.7, L=2.0, sigma_r=0.2)]
    A0 = rng.standard_normal((n, n))
    e0 = rng.standard_normal((n, 2))
    Hm = rng.standard_normal((2, n))
    ekf = RGPEKF(n, f=lambda x, u, z: A0 @ x + e0 @ z + u, A=lambda x, u, z: A0,
                 e=lambda x, u, z: e0, h=lambda x: Hm @ x, H=lambda x: Hm,
                 Q_x=0.01 * np.eye(n), R_x=0.1 * np.eye(2), x0=rng.standard_normal(n), P0=np.eye(n), gps=gps)
    for step in range(6):
        zeta = [rng.uniform(-1, 1), rng.uniform([0, 0], [1, 2])]
        C0, mu0 = ekf.C, ekf.mu
        Js = [gps[0].J(zeta[0]), gps[1].J(zeta[1])]
        D = np.array([g.sigma_K**2 - J @ g.K @ J + g.sigma_r**2 for g, J in zip(gps, Js)])
        ekf.predict(np.ones(n), zeta)
        dense = _dense_prediction(C0, A0, e0, Js, D, 0.01 * np.eye(n), [0.03**2, 0.0], n)
        np.testing.assert_allclose(ekf.C, dense, rtol=1e-10, atol=1e-12)
        zp = np.array([Js[0] @ mu0[n : n + 6], Js[1] @ mu0[n + 6 :]])
        np.testing.assert_allclose(ekf.z_pred, zp, atol=1e-12)
        np.testing.assert_allclose(ekf.x, A0 @ mu0[:n] + e0 @ zp + 1, atol=1e-12)
        # update 4a: the dense EKF formulas with H̃ = [H, 0]
        y = rng.standard_normal(2)
        Ct, mut = ekf.C, ekf.mu
        Ht = np.hstack([Hm, np.zeros((2, Ct.shape[0] - n))])
        S = Ht @ Ct @ Ht.T + 0.1 * np.eye(2)
        Kg = Ct @ Ht.T @ np.linalg.inv(S)
        ekf.update(y)
        np.testing.assert_allclose(ekf.mu, mut + Kg @ (y - Hm @ mut[:n]), rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(ekf.C, Ct - Kg @ Ht @ Ct, rtol=1e-9, atol=1e-10)
        assert ekf.log_likelihood == pytest.approx(
            multivariate_normal(Hm @ mut[:n], S).logpdf(y), rel=1e-10)


def test_variant_4b_updates_states_only():
    rng = np.random.default_rng(6)
    n = 2
    A0 = np.array([[1.0, 0.1], [0.0, 0.9]])
    ekf = RGPEKF(n, f=lambda x, u, z: A0 @ x + np.array([0, 0.1]) * z, A=A0, e=[0.0, 0.1],
                 h=lambda x: x[:1], H=[[1.0, 0.0]], Q_x=1e-4, R_x=0.01, x0=[0, 0], P0=1.0,
                 gps=RecursiveGP(-1, 1, 5, sigma_K=1.0, L=1.0, sigma_r=0.1))
    for _ in range(5):  # learn a bit so that C has cross-covariances
        ekf.predict(None, rng.uniform(-1, 1))
        ekf.update([rng.standard_normal()])
    ekf.learning = False
    ekf.predict(None, 0.3)
    Ct, mut = ekf.C, ekf.mu
    y = np.array([0.7])
    ekf.update(y)
    Pxx, Cxz = Ct[:n, :n], Ct[:n, n:]
    H = np.array([[1.0, 0.0]])
    Kx = Pxx @ H.T / (H @ Pxx @ H.T + 0.01)
    np.testing.assert_allclose(ekf.mu[n:], mut[n:], atol=0)  # weights not learned
    np.testing.assert_allclose(ekf.C[n:, n:], Ct[n:, n:], atol=0)
    np.testing.assert_allclose(ekf.x, mut[:n] + Kx[:, 0] * (y - mut[0]), atol=1e-12)
    np.testing.assert_allclose(ekf.P, Pxx - Kx @ H @ Pxx, atol=1e-12)
    np.testing.assert_allclose(ekf.C[:n, n:], Cxz - Kx @ H @ Cxz, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(ekf.C) > -1e-10)


def test_pure_prediction_mode_uses_gp_as_noisy_input():
    gp = RecursiveGP(-2, 2, 9, sigma_K=2.0, L=2.0, sigma_r=0.05)
    rng = np.random.default_rng(7)
    for z in rng.uniform(-2, 2, 200):
        gp.update(z, np.sin(z), 1e-4)
    A0 = np.array([[1.0, 0.05], [-0.05, 0.95]])
    e0 = np.array([0.0, 0.05])
    ekf = RGPEKF(2, f=lambda x, u, z: A0 @ x + e0 * z, A=A0, e=e0, h=lambda x: x[:1], H=[[1, 0]],
                 Q_x=1e-6, R_x=1e-2, x0=[0.5, 0.0], P0=0.1, gps=gp, pure_prediction=True)
    assert ekf.C.shape == (2, 2)
    P0 = ekf.P
    ekf.predict(None, 0.4)
    m, s = gp.predict([0.4], return_std=True)
    np.testing.assert_allclose(ekf.x, A0 @ [0.5, 0.0] + e0 * m[0], atol=1e-12)
    np.testing.assert_allclose(ekf.P, A0 @ P0 @ A0.T + 1e-6 * np.eye(2) + np.outer(e0, e0) * s[0] ** 2,
                               rtol=1e-10, atol=1e-15)
    w_before = ekf.gp_weights()[0].copy()
    ekf.update([0.3])
    np.testing.assert_array_equal(ekf.gp_weights()[0], w_before)


def _bad_filter():
    return RGPEKF(2, f=lambda x, u, z: x + z, A=np.eye(2), e=[1.0, 0.0], h=lambda x: x, H=np.eye(2),
                  Q_x=0.01, R_x=0.1, x0=[0, 0], P0=1.0, gps=RecursiveGP(0, 1, 5))


@pytest.mark.parametrize(
    "kwargs, arg",
    [({"lower": 1.0, "upper": 0.0}, "upper"), ({"n_points": 1}, "n_points"),
     ({"sigma_K": -1.0}, "sigma_K"), ({"L": 0.0}, "L"), ({"sigma_r": np.nan}, "sigma_r"),
     ({"sigma_p": -0.1}, "sigma_p"), ({"lower": np.inf}, "lower")],
)
def test_recursive_gp_rejects_bad_construction(kwargs, arg):
    args = {"lower": 0.0, "upper": 1.0, "n_points": 5} | kwargs
    with pytest.raises(ValueError, match=arg):
        RecursiveGP(**args)


def test_bad_inputs_raise_and_leave_state():
    gp = RecursiveGP(0, 1, 5, sigma_r=0.1)
    gp.update(0.5, 1.0, 0.1)
    m, c = gp.mean.copy(), gp.cov.copy()
    for args, arg in [((np.nan, 1.0, 0.1), "zeta"), ((0.5, np.inf, 0.1), "y"),
                      ((0.5, 1.0, -1.0), "var_y"), (([0.1, 0.2], 1.0, 0.1), "zeta")]:
        with pytest.raises(ValueError, match=arg):
            gp.update(*args)
    np.testing.assert_array_equal(gp.mean, m)
    np.testing.assert_array_equal(gp.cov, c)
    with pytest.raises(ValueError, match="zeta"):
        gp.predict(np.array([[0.1, 0.2]]))

    ekf = _bad_filter()
    ekf.predict(None, 0.5)
    ekf.update([0.1, 0.2])
    mu, C = ekf.mu, ekf.C
    with pytest.raises(ValueError, match="zeta"):
        ekf.predict(None, np.nan)
    with pytest.raises(ValueError, match="zeta"):
        ekf.predict(None, [0.1, 0.2])
    with pytest.raises(ValueError, match="y"):
        ekf.update([np.nan, 0.0])
    with pytest.raises(ValueError, match="y"):
        ekf.update([1.0, 2.0, 3.0])
    ekf.f = lambda x, u, z: np.array([np.nan, 0.0])
    with pytest.raises(ValueError, match="f"):
        ekf.predict(None, 0.5)
    np.testing.assert_array_equal(ekf.mu, mu)
    np.testing.assert_array_equal(ekf.C, C)
    with pytest.raises(ValueError, match="Q_x"):
        RGPEKF(2, f=lambda x, u, z: x, A=np.eye(2), e=[1, 0], h=lambda x: x, H=np.eye(2),
               Q_x=-np.eye(2), R_x=0.1, x0=[0, 0], P0=1.0, gps=RecursiveGP(0, 1, 5))
    with pytest.raises(ValueError, match="x0"):
        RGPEKF(2, f=lambda x, u, z: x, A=np.eye(2), e=[1, 0], h=lambda x: x, H=np.eye(2),
               Q_x=0.0, R_x=0.1, x0=[0, 0, 0], P0=1.0, gps=RecursiveGP(0, 1, 5))
    with pytest.raises(ValueError, match="gps"):
        RGPEKF(2, f=lambda x, u, z: x, A=np.eye(2), e=[1, 0], h=lambda x: x, H=np.eye(2),
               Q_x=0.0, R_x=0.1, x0=[0, 0], P0=1.0, gps=[])


def test_x_and_P_are_settable_filterpy_style():
    ekf = _bad_filter()
    ekf.predict(None, 0.5)
    ekf.update([0.1, 0.2])
    mu, C = ekf.mu, ekf.C
    for value, arg in [([1.0, np.nan], "x"), ([1.0, 2.0, 3.0], "x"), ("a", "x")]:
        with pytest.raises(ValueError, match=arg):
            ekf.x = value
    for value, arg in [(np.array([[1.0, 2.0], [0.0, 1.0]]), "P"), (-np.eye(2), "P"),
                       (np.eye(3), "P"), ([[np.inf, 0], [0, 1]], "P")]:
        with pytest.raises(ValueError, match=arg):
            ekf.P = value
    np.testing.assert_array_equal(ekf.mu, mu)
    np.testing.assert_array_equal(ekf.C, C)

    ekf.x = np.array([0.3, -0.7])
    np.testing.assert_array_equal(ekf.x, [0.3, -0.7])
    np.testing.assert_array_equal(ekf.mu[2:], mu[2:])  # the GP weights are untouched
    P = np.array([[2.0, 0.5], [0.5, 1.0]])
    ekf.P = P
    np.testing.assert_array_equal(ekf.P, P)
    C2 = ekf.C
    np.testing.assert_array_equal(C2[2:, 2:], C[2:, 2:])
    np.testing.assert_array_equal(C2[:2, 2:], 0.0)  # cross-covariance reset: C stays PSD
    np.testing.assert_array_equal(C2[2:, :2], 0.0)
    ekf.P = 3.0  # a scalar means 3 I, as in the constructor
    np.testing.assert_array_equal(ekf.P, 3.0 * np.eye(2))
    # the next step starts from the assigned state: f(x, u, z) = x + z, A = I, e = [1, 0]
    ekf.x = [1.0, 2.0]
    ekf.predict(None, 0.5)
    z = float(ekf.z_pred[0])
    np.testing.assert_allclose(ekf.x, [1.0 + z, 2.0 + z], rtol=0, atol=1e-15)
    np.testing.assert_allclose(ekf.P[1, 1], 3.0 + 0.01, rtol=1e-14)
    # update evaluates h at the assigned state
    ekf.x = [5.0, 6.0]
    ekf.update([5.0, 6.0])
    np.testing.assert_array_equal(ekf.y, [0.0, 0.0])


def test_indefinite_innovation_raises_numerical_error_and_keeps_state():
    # S = H P Hᵀ + R_x = 0: P stays 0 (no process noise, e = 0) and R_x = 0 is semi-definite
    ekf = RGPEKF(1, f=lambda x, u, z: x, A=[[1.0]], e=[0.0], h=lambda x: x, H=lambda x: [[1.0]],
                 Q_x=0.0, R_x=np.array([[1e-3]]), x0=[0.0], P0=0.0, gps=RecursiveGP(0, 1, 3))
    ekf.R_x = np.array([[0.0]])
    ekf.predict(None, 0.5)
    mu, C = ekf.mu, ekf.C
    with pytest.raises(gpmhe.NumericalError):
        ekf.update([0.2])
    np.testing.assert_array_equal(ekf.mu, mu)
    np.testing.assert_array_equal(ekf.C, C)


def test_batch_update_equals_sequential_and_is_atomic():
    rng = np.random.default_rng(8)
    zs, ys = rng.uniform(-1, 1, 50), rng.standard_normal(50)
    a = RecursiveGP(-1, 1, 7, sigma_K=1.0, L=1.0, sigma_r=0.05)
    b = a.copy()
    preds = [a.update(z, y, 0.01) for z, y in zip(zs, ys)]
    np.testing.assert_array_equal(b.update(zs, ys, 0.01), preds)
    np.testing.assert_array_equal(b.mean, a.mean)
    np.testing.assert_array_equal(b.cov, a.cov)
    bad = ys.copy()
    bad[30] = np.nan
    with pytest.raises(ValueError, match="y"):
        b.update(zs, bad, 0.01)
    with pytest.raises(ValueError, match="zeta"):
        b.update(zs[:10], ys, 0.01)
    np.testing.assert_array_equal(b.mean, a.mean)


def _linear_filter(f=None, A=None, e=None, h=None, H=None):
    A0 = np.array([[1.0, 0.1], [-0.2, 0.9]])
    e0 = np.array([0.0, 0.1])
    return RGPEKF(2, f=f or (lambda x, u, z: A0 @ x + e0 * z), A=A0 if A is None else A,
                  e=e0 if e is None else e, h=h or (lambda x: x), H=np.eye(2) if H is None else H,
                  Q_x=1e-3, R_x=0.1, x0=[0.2, -0.1], P0=0.5,
                  gps=RecursiveGP(-1, 1, 7, sigma_K=1.0, L=1.0, sigma_r=0.1))


def test_step_reads_any_numeric_results_like_float64_arrays():
    """The one-call steps read float64 arrays directly and convert anything else (lists, column
    vectors, ints, non-contiguous arrays) as np.ascontiguousarray would: same filter either way."""
    A0 = np.array([[1.0, 0.1], [-0.2, 0.9]])
    e0 = np.array([0.0, 0.1])
    ref = _linear_filter(h=lambda x: np.array([x[0], x[0]]),
                         H=lambda x: np.array([[1.0, 0.0], [1.0, 0.0]]))
    other = _linear_filter(
        f=lambda x, u, z: (A0 @ x + e0 * z).reshape(2, 1).tolist(),  # nested list, a column
        A=lambda x, u, z: np.asfortranarray(A0),  # not C-contiguous
        e=lambda x, u, z: [[0], [0.1]],  # (n, 1) list with an int
        h=lambda x: np.stack([x, x])[:, 0],  # a strided view
        H=lambda x: np.array([[1, 0], [1, 0]]),  # int dtype
    )
    rng = np.random.default_rng(9)
    for _ in range(5):
        z, y = rng.uniform(-1, 1), rng.standard_normal(2)
        ref.predict(None, z)
        other.predict(None, np.float64(z))
        ref.update(y)
        other.update(list(y))
        np.testing.assert_array_equal(other.mu, ref.mu)
        np.testing.assert_array_equal(other.C, ref.C)
    # a scalar measurement as a float when p = 1
    one = RGPEKF(1, f=lambda x, u, z: x + z, A=[[1.0]], e=[1.0], h=lambda x: x[0], H=[[1.0]],
                 Q_x=0.0, R_x=0.1, x0=[0.0], P0=1.0, gps=RecursiveGP(0, 1, 3))
    one.predict(None, 0.5)
    one.update(0.25)
    np.testing.assert_array_equal(one.y, [0.25 - float(one.z_pred[0])])


@pytest.mark.parametrize(
    "kwargs, bad_step, arg",
    [({"f": lambda x, u, z: "abc"}, "predict", "f"),
     ({"f": lambda x, u, z: np.zeros(3)}, "predict", "f"),
     ({"f": lambda x, u, z: np.array([np.inf, 0.0])}, "predict", "f"),
     ({"A": lambda x, u, z: np.eye(3)}, "predict", "A"),
     ({"A": lambda x, u, z: np.ones(4)}, "predict", "A"),
     ({"e": lambda x, u, z: np.zeros(3)}, "predict", "e"),
     ({"e": lambda x, u, z: [np.nan, 0.0]}, "predict", "e"),
     ({}, "zeta-str", "zeta"),
     ({"h": lambda x: x[:1]}, "update", "h"),
     ({"h": lambda x: None}, "update", "h"),
     ({"H": lambda x: np.eye(3)}, "update", "H"),
     ({"H": lambda x: [[1.0, "a"], [0, 1]]}, "update", "H"),
     ({}, "y-str", "y"),
     ({}, "y-size", "y"),
     ({}, "R-nan", "R_x")],
)
def test_step_rejects_bad_inputs_and_results_and_keeps_state(kwargs, bad_step, arg):
    ekf = _linear_filter(**kwargs)
    if bad_step != "predict":
        ekf.predict(None, 0.3)
    mu, C = ekf.mu, ekf.C
    with pytest.raises(ValueError, match=arg):
        if bad_step == "predict":
            ekf.predict(None, 0.3)
        elif bad_step == "zeta-str":
            ekf.predict(None, "abc")
        elif bad_step == "y-str":
            ekf.update("ab")
        elif bad_step == "y-size":
            ekf.update([1.0, 2.0, 3.0])
        elif bad_step == "R-nan":
            ekf.R_x = np.array([[np.nan, 0.0], [0.0, 1.0]])
            ekf.update([0.1, 0.2])
        else:
            ekf.update([0.1, 0.2])
    np.testing.assert_array_equal(ekf.mu, mu)
    np.testing.assert_array_equal(ekf.C, C)


def test_reassigned_noise_covariances_take_effect():
    """Q_x and R_x are read at every step, as in filterpy."""
    ekf = _linear_filter(H=lambda x: np.eye(2))  # p unknown until the first y: R_x stays a scalar
    ekf.predict(None, 0.3)
    P = ekf.P
    ekf.update([0.1, 0.2])
    np.testing.assert_allclose(ekf.S, P + 0.1 * np.eye(2), rtol=1e-12)
    ekf.predict(None, 0.3)
    P = ekf.P
    ekf.R_x = 2.5 * np.eye(2)
    ekf.update([0.1, 0.2])
    np.testing.assert_allclose(ekf.S, P + 2.5 * np.eye(2), rtol=1e-12)
    P = ekf.P
    ekf.Q_x = np.diag([0.3, 0.4])
    ekf.predict(None, 0.3)
    # e = [0, 0.1]: the first state's variance is (A P Aᵀ)₀₀ + Q₀₀, without GP terms
    A0 = np.array([[1.0, 0.1], [-0.2, 0.9]])
    assert ekf.P[0, 0] == pytest.approx((A0 @ P @ A0.T)[0, 0] + 0.3, rel=1e-12)


@pytest.mark.parametrize("name, bad, message", [
    ("R_x", -100.0, "R_x: must be finite and > 0"),
    ("R_x", 0.0, "R_x: must be finite and > 0"),
    ("R_x", -np.eye(2), "R_x: must be positive semi-definite"),
    ("R_x", [[1.0, 0.5], [0.0, 1.0]], "R_x: must be symmetric"),
    ("R_x", np.eye(3), r"R_x: expected a scalar or shape \(2, 2\)"),
    ("R_x", [0.1, 0.1], r"R_x: expected a \(p, p\) matrix or a scalar"),
    ("R_x", [[np.nan, 0.0], [0.0, 1.0]], "R_x: contains NaN"),
    ("R_x", [[1e200, 0.0], [0.0, 1.0]], "R_x: contains a value of magnitude"),
    ("Q_x", -1.0, "Q_x: must be positive semi-definite"),
    ("Q_x", [[1.0, 2.0], [2.0, 1.0]], "Q_x: must be positive semi-definite"),
    ("Q_x", [[1.0, 0.5], [0.0, 1.0]], "Q_x: must be symmetric"),
    ("Q_x", np.eye(3), r"Q_x: expected a scalar or shape \(2, 2\)"),
    ("Q_x", [[np.inf, 0.0], [0.0, 1.0]], "Q_x: contains NaN or inf"),
    ("Q_x", "0.1", "Q_x: must be real numbers"),
])
def test_an_assigned_noise_covariance_is_validated_as_in_the_constructor(name, bad, message):
    ekf, twin = _linear_filter(), _linear_filter()
    with pytest.raises(ValueError, match=name):  # (a wrong shape as "H, R_x: ...")
        RGPEKF(2, f=lambda x, u, z: x, A=np.eye(2), e=[0.0, 0.1], h=lambda x: x, H=np.eye(2),
               **{"Q_x": 1e-3, "R_x": 0.1, name: bad}, x0=[0.0, 0.0], P0=0.5,
               gps=RecursiveGP(-1, 1, 7))
    before = getattr(ekf, name).copy()
    with pytest.raises(ValueError, match=message):
        setattr(ekf, name, bad)
    np.testing.assert_array_equal(getattr(ekf, name), before)
    for f in (ekf, twin):  # the filter runs on as if nothing had been assigned
        f.predict(None, 0.3)
        f.update([0.1, 0.2])
    np.testing.assert_array_equal(ekf.mu, twin.mu)
    np.testing.assert_array_equal(ekf.C, twin.C)
    assert np.all(np.linalg.eigvalsh(ekf.P) > 0)


def test_valid_noise_covariances_are_taken_as_in_the_constructor():
    ekf = _linear_filter()
    ekf.R_x = 0.3  # a scalar times I, as in the constructor
    np.testing.assert_array_equal(ekf.R_x, 0.3 * np.eye(2))
    ekf.Q_x = 0.0
    np.testing.assert_array_equal(ekf.Q_x, np.zeros((2, 2)))
    with pytest.raises(ValueError, match="read-only"):  # not changed behind the validation
        ekf.R_x[0, 0] = -1.0
    np.testing.assert_array_equal(ekf.R_x, 0.3 * np.eye(2))
    # p unknown (H a function, R_x a scalar) until the first update, which fixes it
    late = _linear_filter(H=lambda x: np.eye(2))
    assert late.dim_y is None and late.y.shape == (0,)
    late.R_x = 0.2
    late.predict(None, 0.3)
    late.update([0.1, 0.2])
    assert late.dim_y == 2
    np.testing.assert_array_equal(late.R_x, 0.2 * np.eye(2))
    with pytest.raises(ValueError, match="y: expected shape"):
        late.update([0.1, 0.2, 0.3])


def test_innovation_and_its_covariance_have_their_shapes_before_the_first_update():
    from filterpy.common import Saver

    ekf = _linear_filter()
    assert ekf.y.shape == (2,) and np.all(np.isnan(ekf.y))
    assert ekf.S.shape == (2, 2) and np.all(np.isnan(ekf.S))
    # no measurement yet: no likelihood either (0 would read as a perfect fit)
    assert np.isnan(ekf.log_likelihood) and np.isnan(ekf.likelihood)
    saver = Saver(ekf, save_current=True)
    for k in range(3):
        ekf.predict(None, 0.1 * k)
        ekf.update([0.1, 0.2])
        saver.save()
    saver.to_array()
    assert saver.y.shape == (4, 2) and saver.S.shape == (4, 2, 2)
    assert np.all(np.isnan(saver.y[0])) and np.all(np.isfinite(saver.y[1:]))
    np.testing.assert_array_equal(saver.S[-1], ekf.S)
    assert np.isnan(saver.log_likelihood[0]) and np.all(np.isfinite(saver.log_likelihood[1:]))
