"""gpmhe.theory: certificates of Assumption 1 (linear models checked against the LMI with NumPy,
an undetectable model refused, the exact batch reactor and its 5- and 3-trajectory GP models
certified, every certificate re-checked on 10^5 random pairs by an independent implementation of
(18b)), the minimal horizon, the error bound (21) by hand and against a simulated MHE run, the
variance and Lipschitz bounds against dense sampling, and bad input."""

import math
import sys
import numpy as np
import pytest

pytest.importorskip("cvxpy")

from gpmhe import GPMHE, KnownModel  # noqa: E402
from gpmhe.systems import batch_reactor as br  # noqa: E402
from conftest import fitted_reactor_model, reactor_known_model  # noqa: E402
from gpmhe.theory import (  # noqa: E402
    Certificate,
    certify_ioss,
    corollary1,
    error_bound,
    mismatch,
    weight_bounds,
)

Q0 = 1e-3 * np.eye(2)
R0 = 1e-2 * np.eye(1)


def linear_model(A, C):
    A, C = np.asarray(A, float), np.asarray(C, float)
    return KnownModel(lambda X, U: X @ A.T, lambda X, U: X @ C.T, A.shape[0], C.shape[0],
                      f_jacobian=lambda X, U: np.broadcast_to(A, (len(X),) + A.shape),
                      h_jacobian=lambda X, U: np.broadcast_to(C, (len(X),) + C.shape),
                      vectorized=True)


@pytest.fixture(scope="module")
def exact():
    return reactor_known_model(vectorized=True)


def fit_gp(n_trajectories):
    return fitted_reactor_model(100, n_restarts=1, n_trajectories=n_trajectories)


@pytest.fixture(scope="module")
def gp5():
    return fit_gp(5)


@pytest.fixture(scope="module")
def gp3():
    return fit_gp(3)


@pytest.fixture(scope="module")
def cert_exact(exact):
    # f is quadratic in x, so its Jacobian is affine: zero curvature, the gridded LMI is exact.
    return certify_ioss(exact, br.X_BOUNDS, Q0, R0, jacobian_curvature=0.0)


@pytest.fixture(scope="module")
def cert_gp5(gp5):
    return certify_ioss(gp5, br.X_BOUNDS, Q0, R0, variance_bound="posterior")


@pytest.fixture(scope="module")
def cert_gp3(gp3):
    return certify_ioss(gp3, br.X_BOUNDS, Q0, R0, variance_bound="posterior", n_check=20_000)


# ------------------------------------------------------------------------------ linear models


def lmi_max_eig(A, C, P, eta, Q_inv, R_inv):
    """λ_max of [A I]ᵀ P [A I] − diag(η P + Cᵀ R⁻¹ C, Q⁻¹): the exact condition for linear
    models (≤ 0 means (18b) holds for every pair and disturbance)."""
    n = A.shape[0]
    AI = np.hstack([A, np.eye(n)])
    M = AI.T @ P @ AI - np.block([[eta * P + C.T @ R_inv @ C, np.zeros((n, n))],
                                  [np.zeros((n, n)), Q_inv]])
    return np.linalg.eigvalsh(0.5 * (M + M.T))[-1]


def test_linear_detectable_model_gets_a_certificate_that_satisfies_the_lmi():
    A = np.array([[1.1, 0.2], [0.0, 0.7]])   # unstable mode measured, stable mode not
    C = np.array([[1.0, 0.0]])
    box = (-np.ones(2), np.ones(2))
    cert = certify_ioss(linear_model(A, C), box, Q0=0.1, R0=0.1, cells=2, jacobian_curvature=0.0,
                        n_check=2000)
    assert cert.feasible, cert.reason
    assert cert.margin_proved and cert.jacobian_variation == (0.0, 0.0)
    assert 0 < cert.eta < 1
    assert np.all(np.linalg.eigvalsh(cert.P) > 0)
    lam = lmi_max_eig(A, C, cert.P, cert.eta, cert.Q_inv, cert.R_inv)
    assert lam <= 1e-9 * np.abs(cert.P).max()
    # η is minimal up to the bisection tolerance: the LMI fails for a clearly smaller η with this P
    assert lmi_max_eig(A, C, cert.P, cert.eta - 0.05, cert.Q_inv, cert.R_inv) > 0
    # a given η inside the feasible range is kept
    fixed = certify_ioss(linear_model(A, C), box, Q0=0.1, R0=0.1, cells=2, eta=0.9,
                         jacobian_curvature=0.0, n_check=0)
    assert fixed.feasible and fixed.eta == 0.9
    assert lmi_max_eig(A, C, fixed.P, 0.9, fixed.Q_inv, fixed.R_inv) <= 1e-9 * np.abs(fixed.P).max()


def test_given_P_only_minimises_eta():
    A = np.array([[0.5, 0.1], [0.0, 0.6]])
    C = np.array([[1.0, 1.0]])
    P = np.diag([0.2, 0.3])
    cert = certify_ioss(linear_model(A, C), (-np.ones(2), np.ones(2)), Q0=1.0, R0=1.0, P=P,
                        cells=1, jacobian_curvature=0.0, n_check=1000)
    assert cert.feasible, cert.reason
    np.testing.assert_allclose(cert.P, P, rtol=1e-12)
    assert lmi_max_eig(A, C, P, cert.eta, cert.Q_inv, cert.R_inv) <= 1e-9
    assert lmi_max_eig(A, C, P, cert.eta - 1e-3, cert.Q_inv, cert.R_inv) > 0  # minimal


def test_unstable_unobservable_mode_is_refused():
    A = np.array([[0.5, 0.0], [0.0, 1.2]])    # x2 grows and is never measured
    C = np.array([[1.0, 0.0]])
    cert = certify_ioss(linear_model(A, C), (-np.ones(2), np.ones(2)), Q0=0.1, R0=0.1, cells=1,
                        jacobian_curvature=0.0, n_check=100)
    assert cert.feasible is False
    assert "no P satisfies" in cert.reason
    assert cert.P is None and cert.eta is None
    with pytest.raises(ValueError, match="not feasible"):
        cert.min_horizon()


# ------------------------------------------------------------------------------ batch reactor


def test_exact_batch_reactor_is_certified(cert_exact, exact):
    assert cert_exact.feasible, cert_exact.reason
    assert cert_exact.margin_proved
    print(f"\nexact model: eta = {cert_exact.eta:.4f}, M_bar = {cert_exact.min_horizon()} "
          f"(paper: eta = 0.91, M = 15); P = {cert_exact.P.round(5).tolist()}")
    assert 0.8 < cert_exact.eta < 0.95
    # The paper's η = 0.91 is itself certifiable, and its minimal horizon is the paper's M = 15.
    paper = certify_ioss(exact, br.X_BOUNDS, Q0, R0, eta=0.91, jacobian_curvature=0.0,
                         n_check=10_000)
    assert paper.feasible, paper.reason
    assert paper.min_horizon() == 15
    opts = paper.mhe_options()
    assert opts["eta"] == 0.91 and opts["horizon"] == 15
    GPMHE(exact, br.X_PRIOR0, **opts)  # accepted as is


@pytest.mark.parametrize("name", ["cert_gp5", "cert_gp3"])
def test_gp_models_are_certified_with_the_posterior_variance_bound(name, request):
    cert = request.getfixturevalue(name)
    assert cert.feasible, cert.reason
    assert cert.margin_proved
    assert cert.weights.variance_bound == "posterior"
    assert cert.jacobian_variation[0] > 0 and cert.jacobian_variation[1] > 0
    assert cert.eta_without_margin <= cert.eta < 1
    print(f"\n{name}: eta = {cert.eta:.4f}, M_bar = {cert.min_horizon()}, "
          f"Q_min^-1 = {np.diag(cert.Q_inv).round(2)}, R_min^-1 = {cert.R_inv.round(3)}, "
          f"margins (dA, dC) = {np.round(cert.jacobian_variation, 5)}")


def violation_18b(mean, cert, n_pairs, rng):
    """Independent check of (18b): random pairs (a third uniform, a third close together, a third
    close together along x1 − x2, which the output y = x1 + x2 does not see) and, per pair, a
    random and the worst-case disturbance difference Δw* = (Q⁻¹ − P)⁻¹ P a; returns
    max (LHS − RHS) / ‖Δ‖²_P."""
    lo, hi = cert.x_bounds
    x = rng.uniform(lo, hi, size=(n_pairs, 2))
    xt = rng.uniform(lo, hi, size=(n_pairs, 2))
    third = n_pairs // 3
    xt[:third] = x[:third] + 0.02 * rng.standard_normal((third, 2))
    xt[third:2 * third] = x[third:2 * third] + np.outer(0.02 * rng.standard_normal(third), [1, -1])
    xt = np.clip(xt, lo, hi)
    mx, my = mean(x)
    mxt, myt = mean(xt)
    a, b, dx = mx - mxt, my - myt, x - xt
    P, Qi, Ri = cert.P, cert.Q_inv, cert.R_inv
    worst_w = np.linalg.solve(Qi - P, P @ a.T).T
    random_w = 0.05 * rng.standard_normal(a.shape)
    out = -np.inf
    for dw in (worst_w, random_w):
        e = a + dw
        lhs = np.einsum("ki,ij,kj->k", e, P, e)
        base = np.einsum("ki,ij,kj->k", dx, P, dx)
        rhs = (cert.eta * base + np.einsum("ki,ij,kj->k", dw, Qi, dw)
               + np.einsum("ki,ij,kj->k", b, Ri, b))
        out = max(out, float(np.max((lhs - rhs) / base)))
    return out


def test_certificates_hold_on_random_pairs(cert_exact, cert_gp5, gp5):
    rng = np.random.default_rng(12345)
    exact_mean = lambda X: (br.f_batch(X), br.h_batch(X))  # noqa: E731
    gp_mean = lambda X: (gp5.f_gp.predict(X), gp5.h_gp.predict(X))  # noqa: E731
    for cert, mean in ((cert_exact, exact_mean), (cert_gp5, gp_mean)):
        assert cert.feasible
        assert cert.check_pairs == 100_000 and cert.check_worst <= 0
        assert violation_18b(mean, cert, 100_000, rng) <= 1e-9


def test_the_check_catches_a_certificate_that_is_too_good(cert_exact):
    # The same P with a smaller η than certified must violate (18b) somewhere: the check can fail.
    rng = np.random.default_rng(7)
    bad = Certificate(feasible=True, P=cert_exact.P, eta=cert_exact.eta - 0.05,
                      Q_inv=cert_exact.Q_inv, R_inv=cert_exact.R_inv, x_bounds=cert_exact.x_bounds)
    exact_mean = lambda X: (br.f_batch(X), br.h_batch(X))  # noqa: E731
    assert violation_18b(exact_mean, bad, 100_000, rng) > 0


# ------------------------------------------------------------------------------ weight bounds


def test_posterior_variance_bound_is_an_upper_bound(gp3):
    wb = weight_bounds(gp3, Q0, R0, variance_bound="posterior", x_bounds=br.X_BOUNDS, cells=8)
    prior = weight_bounds(gp3, Q0, R0)
    xs = np.linspace(0.1, 4.5, 301)
    grid = np.array(np.meshgrid(xs, xs)).reshape(2, -1).T
    var_x = gp3.f_gp.predict(grid, return_std=True)[1].max(axis=0) ** 2
    var_y = gp3.h_gp.predict(grid, return_std=True)[1].max(axis=0) ** 2
    assert np.all(wb.var_x_max >= var_x) and np.all(wb.var_y_max >= var_y)
    assert np.all(wb.var_x_max <= 1.2 * var_x)                          # and tight
    assert np.all(wb.var_x_max <= prior.var_x_max)
    np.testing.assert_allclose(prior.var_x_max, gp3.f_gp.sigma_f ** 2 + gp3.f_gp.sigma_eps ** 2)
    np.testing.assert_allclose(wb.Q_min_inv, np.linalg.inv(np.diag(wb.var_x_max) + Q0))
    np.testing.assert_allclose(wb.Q_max_inv, np.linalg.inv(Q0))
    assert np.all(np.linalg.eigvalsh(wb.Q_max_inv - wb.Q_min_inv) >= 0)


def test_known_model_weight_bounds_are_the_inverse_covariances(exact):
    wb = weight_bounds(exact, Q0, R0)
    for a in (wb.Q_min_inv, wb.Q_max_inv):
        np.testing.assert_allclose(a, np.linalg.inv(Q0))
    np.testing.assert_allclose(wb.R_min_inv, [[100.0]])


def test_full_covariances_are_taken_by_the_theory_and_by_the_estimator_it_tunes(gp3):
    """docs/user_guide/stability.rst: Q0 and R0 may be full symmetric positive definite matrices,
    in the theory functions as in GPMHE; the bounds (14)-(17) hold in the Loewner order."""
    Q_full = np.array([[1e-3, 4e-4], [4e-4, 2e-3]])
    wb = weight_bounds(gp3, Q_full, R0)
    np.testing.assert_allclose(wb.Q_max_inv, np.linalg.inv(Q_full))
    np.testing.assert_allclose(wb.Q_min_inv, np.linalg.inv(np.diag(wb.var_x_max) + Q_full))
    gap = np.linalg.eigvalsh(wb.Q_max_inv - wb.Q_min_inv)
    assert np.all(gap >= -1e-9 * np.abs(wb.Q_max_inv).max())
    model = linear_model([[0.5, 0.1], [0.0, 0.6]], [[1.0, 0.0]])
    cert = certify_ioss(model, (-np.ones(2), np.ones(2)), Q_full, R0, cells=1)
    assert cert.feasible
    est = GPMHE(model, [0.0, 0.0], **cert.mhe_options(cert.min_horizon()))
    np.testing.assert_array_equal(est.Q0, Q_full)


# ------------------------------------------------------------------------------ horizon and bound


@pytest.mark.parametrize("eta", [0.5, 0.9, 0.91, 0.95, 0.999])
def test_min_horizon_matches_the_closed_form(eta):
    cert = Certificate(feasible=True, P=np.diag([1.0, 3.0]), eta=eta)
    M = cert.min_horizon()
    assert 4 * eta ** M < 1 <= 4 * eta ** (M - 1)
    assert M == math.floor(math.log(4) / math.log(1 / eta)) + 1
    assert cert.mu(M) < 1 <= cert.mu(M - 1) if M > 1 else cert.mu(M) < 1
    assert cert.mu(M) == pytest.approx(4 ** (1 / M) * eta)


def test_error_bound_against_a_hand_computation():
    P = np.array([[2.0, 0.5], [0.5, 1.0]])
    Q0_, R0_ = np.diag([0.5, 2.0]), np.array([[4.0]])
    cert = Certificate(feasible=True, P=P, eta=0.6, Q0=Q0_, R0=R0_)
    M = 5
    mu = 4 ** (1 / M) * 0.6
    e0 = np.array([0.3, -0.2])
    w = np.array([[0.1, 0.0], [0.0, 0.2], [0.05, 0.05]])
    v = np.array([[0.4], [0.0], [1.0]])
    alpha = 0.01
    got = error_bound(cert, M, e0, w, v, alpha)
    r = mu ** 0.25
    c = 12 / (1 - r)
    expected = []
    for t in range(4):
        terms = [6 * mu ** (t / 2) * math.sqrt(e0 @ P @ e0), c * alpha]
        for q in range(t):
            wj, vj = w[t - q - 1], v[t - q - 1]
            terms.append(c * r ** q * math.sqrt(wj @ np.linalg.inv(Q0_) @ wj))
            terms.append(c * r ** q * math.sqrt(vj @ np.linalg.inv(R0_) @ vj))
        expected.append(max(terms))
    np.testing.assert_allclose(got, expected, rtol=1e-12)
    with pytest.raises(ValueError, match="M: must be >="):
        error_bound(cert, 1, e0, w, v, alpha)


def run_mhe(model, cert, x, y, steps):
    est = GPMHE(model, br.X_PRIOR0, **cert.mhe_options())
    xs, _ = est.batch_filter(y[:steps])      # row t is x̂(t+1) (prediction form)
    return np.vstack([br.X_PRIOR0, xs])      # x̂(0), …, x̂(steps)


def test_simulated_runs_stay_below_their_bounds(exact, gp5, cert_exact, cert_gp5):
    steps = 60
    rng = np.random.default_rng(3)
    x = np.empty((steps + 1, 2))
    x[0] = br.X_TRUE0
    w = br.SIGMA_W * rng.standard_normal((steps, 2))
    v = br.SIGMA_V * rng.standard_normal((steps + 1, 1))
    for t in range(steps):
        x[t + 1] = br.f(x[t]) + w[t]
    assert np.all((x >= 0.1) & (x <= 4.5))          # the theorem needs x(t) in X
    y = x.sum(axis=1, keepdims=True) + v
    alpha_gp = mismatch(gp5, br.f, br.h, br.X_BOUNDS, Q0, R0, n_samples=2000).alpha
    for model, cert, alpha in ((exact, cert_exact, 0.0), (gp5, cert_gp5, alpha_gp)):
        xhat = run_mhe(model, cert, x, y, steps)
        e = xhat - x
        realised = np.sqrt(np.einsum("ti,ij,tj->t", e, cert.P, e))
        bound = error_bound(cert, cert.min_horizon(), xhat[0] - x[0], w, v[:steps], alpha)
        assert np.all(realised <= bound)
        assert realised[-1] < realised[0]                # and the estimate did converge


# ------------------------------------------------------------------------------ mismatch, Cor. 1


def test_mismatch(exact, gp3):
    assert mismatch(exact, br.f, br.h, br.X_BOUNDS, Q0, R0, n_samples=200).alpha == 0.0
    mm = mismatch(gp3, br.f, br.h, br.X_BOUNDS, Q0, R0, n_samples=2000)
    rng = np.random.default_rng(1)
    X = rng.uniform(0.1, 4.5, size=(5000, 2))
    err_x = np.sqrt(1000) * np.linalg.norm(br.f_batch(X) - gp3.f_gp.predict(X), axis=1)
    assert mm.alpha_1 >= err_x.max() * (1 - 1e-6)      # local maximisation beats sampling
    assert mm.alpha == max(mm.alpha_1, mm.alpha_2)


def test_corollary1_quantities(gp3):
    c1 = corollary1(gp3, br.X_BOUNDS, Q0, R0, tau=1e-3, delta=0.01, L_f=1.0, L_h=1.5, cells=10)
    side = 2e-3 / math.sqrt(2)
    assert c1.covering_number == math.ceil(4.4 / side) ** 2
    assert c1.beta == pytest.approx(2 * math.log(c1.covering_number / 0.01))
    assert c1.probability == pytest.approx(0.99 ** 3)
    # the Lipschitz constants of the means bound sampled finite-difference slopes
    rng = np.random.default_rng(2)
    a = rng.uniform(0.1, 4.5, size=(20000, 2))
    b = np.clip(a + 1e-3 * rng.standard_normal(a.shape), 0.1, 4.5)
    slope = (np.abs(gp3.f_gp.predict(a) - gp3.f_gp.predict(b))
             / np.linalg.norm(a - b, axis=1)[:, None]).max(axis=0)
    assert np.all(c1.L_m_x >= slope)
    gamma = (c1.L_m_x + 1.0) * 1e-3 + math.sqrt(c1.beta) * c1.omega_x
    np.testing.assert_allclose(c1.gamma_f, gamma)
    expected = math.sqrt(1000) * np.sum(math.sqrt(c1.beta) * c1.sigma_x_max + gamma)
    assert c1.Delta_x == pytest.approx(expected)
    assert c1.alpha == max(c1.Delta_x, c1.Delta_y)


# ------------------------------------------------------------------------------ bad input


@pytest.mark.parametrize("kwargs, arg", [
    (dict(x_bounds=([0.1, 0.1], [4.5])), "x_bounds"),
    (dict(x_bounds=([4.5, 0.1], [0.1, 4.5])), "x_bounds"),
    (dict(x_bounds=([0.1, np.nan], [4.5, 4.5])), "x_bounds"),
    (dict(x_bounds=None), "x_bounds"),
    (dict(Q0=-1.0), "Q0"),
    (dict(Q0=np.array([[1.0, 2.0], [0.0, 1.0]])), "Q0"),
    (dict(R0=np.inf), "R0"),
    (dict(R0=np.ones((2, 2))), "R0"),
    (dict(eta=1.0), "eta"),
    (dict(eta=0.0), "eta"),
    (dict(eta="a"), "eta"),
    (dict(P=np.array([[1.0, 0.0], [0.0, -1.0]])), "P"),
    (dict(variance_bound="max"), "variance_bound"),
    (dict(cells=0), "cells"),
    (dict(cells=[3]), "cells"),
    (dict(jacobian_curvature=-1.0), "jacobian_curvature"),
    (dict(jacobian_lipschitz=[1, 2, 3]), "jacobian_lipschitz"),
    (dict(max_condition=0.5), "max_condition"),
    (dict(n_check=-1), "n_check"),
    (dict(u_bounds=([0.0], [1.0])), "u_bounds"),
])
def test_bad_input_names_the_argument(exact, kwargs, arg):
    args = dict(x_bounds=br.X_BOUNDS, Q0=Q0, R0=R0)
    args.update(kwargs)
    with pytest.raises(ValueError, match=arg):
        certify_ioss(exact, **args)


def test_bad_input_elsewhere(exact, gp3):
    with pytest.raises(ValueError, match="model"):
        certify_ioss(object(), br.X_BOUNDS, Q0, R0)
    with pytest.raises(TypeError):
        certify_ioss(exact, br.X_BOUNDS, Q0, R0, unknown_option=1)
    with pytest.raises(ValueError, match="x_bounds"):
        weight_bounds(gp3, Q0, R0, variance_bound="posterior")
    with pytest.raises(ValueError, match="delta"):
        corollary1(gp3, br.X_BOUNDS, Q0, R0, tau=1e-3, delta=1.5, L_f=1, L_h=1)
    with pytest.raises(ValueError, match="model"):
        corollary1(exact, br.X_BOUNDS, Q0, R0, tau=1e-3, delta=0.1, L_f=1, L_h=1)
    with pytest.raises(ValueError, match="f"):
        mismatch(gp3, None, br.h, br.X_BOUNDS, Q0, R0)
    cert = Certificate(feasible=True, P=np.eye(2), eta=0.5, Q0=Q0, R0=R0)
    for kwargs, arg in ((dict(x0_error=[1.0]), "x0_error"), (dict(w=np.zeros((3, 3))), "w"),
                        (dict(v=np.zeros((2, 1))), "v"), (dict(alpha=-1.0), "alpha"),
                        (dict(w=np.full((3, 2), np.nan)), "w")):
        args = dict(x0_error=[1.0, 0.0], w=np.zeros((3, 2)), v=np.zeros((3, 1)), alpha=0.0)
        args.update(kwargs)
        with pytest.raises(ValueError, match=arg):
            error_bound(cert, 10, **args)
    with pytest.raises(ValueError, match="horizon"):
        Certificate(feasible=True, P=np.eye(2), eta=0.9, Q0=Q0, R0=R0,
                    x_bounds=br.X_BOUNDS).mhe_options(horizon=3)


def test_missing_cvxpy_tells_how_to_install(exact, monkeypatch):
    monkeypatch.setitem(sys.modules, "cvxpy", None)
    with pytest.raises(ImportError, match=r"gpmhe\[theory\]"):
        certify_ioss(exact, br.X_BOUNDS, Q0, R0)
