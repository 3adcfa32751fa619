"""Sparse GPs (SparseGaussianProcess, SparseMultiOutputGP): the exact GP recovered with the
inducing points at the data; the objective, its gradients and the predictions against an
independent dense numpy implementation and finite differences; the variance far from the data;
copies, pickles and files; input errors; and GP-MHE on the batch reactor against the exact GPs."""

import copy
import io
import pickle
import signal
import threading
import time
import warnings

import numpy as np
import pytest
from numpy.testing import assert_array_equal

from gpmhe import (GPMHE, GaussianProcess, LearnedModel, MultiOutputGP, SparseGaussianProcess,
                   SparseMultiOutputGP, _core)
from gpmhe.systems import batch_reactor as br

METHODS = ["vfe", "fitc"]


def problem(n, nd, seed, m=None):
    """Random data, theta and (with m) m well-separated inducing points from the data."""
    rng = np.random.default_rng(seed)
    D = rng.uniform(-2.0, 2.0, (n, nd))
    y = np.sin(1.5 * D).sum(axis=1) + 0.1 * rng.standard_normal(n)
    theta = np.log(np.concatenate([[rng.uniform(0.8, 1.5)], rng.uniform(0.6, 1.2, nd), [0.1]]))
    Z = None if m is None else D[_core.select_inducing(D, theta, m)]
    return D, y, theta, Z


# ----------------------------------------------------------------------------- dense reference


def kern(A, B, theta):
    """SE-ARD kernel matrix, and its derivatives w.r.t. theta = log([sf, ls.., se])."""
    sf2, ls = np.exp(2 * theta[0]), np.exp(theta[1:-1])
    diff2 = (A[:, None, :] - B[None, :, :]) ** 2 / ls**2
    K = sf2 * np.exp(-0.5 * diff2.sum(-1))
    dK = [2 * K] + [K * diff2[..., l] for l in range(len(ls))]
    return K, dK


def dense_objective(D, y, Z, theta, method, Dt):
    """The objective, its theta-gradient (dense matrix calculus, N x N) and mean and variance at
    Dt: dF = 1/2 tr((a a^T - C^-1) dC) - [VFE] d tr(Kff - Qff) / (2 se^2), C = Qff + Lambda."""
    n, nd = D.shape
    se2, sf2 = np.exp(2 * theta[-1]), np.exp(2 * theta[0])
    Kuu, dKuu = kern(Z, Z, theta)
    Kuf, dKuf = kern(Z, D, theta)
    Ki = np.linalg.inv(Kuu)
    Q = Kuf.T @ Ki @ Kuf
    lam = np.full(n, se2) if method == "vfe" else sf2 - np.diag(Q) + se2
    C = Q + np.diag(lam)
    Ci = np.linalg.inv(C)
    a = Ci @ y
    F = -0.5 * y @ a - 0.5 * np.linalg.slogdet(C)[1] - 0.5 * n * np.log(2 * np.pi)
    if method == "vfe":
        F -= np.sum(sf2 - np.diag(Q)) / (2 * se2)
    W = np.outer(a, a) - Ci
    grad = np.zeros(nd + 2)
    for k in range(nd + 2):
        if k <= nd:  # sigma_f and the length-scales act on the kernel matrices
            dQ = dKuf[k].T @ Ki @ Kuf + Kuf.T @ Ki @ dKuf[k] - Kuf.T @ Ki @ dKuu[k] @ Ki @ Kuf
            dkff = np.full(n, 2 * sf2 if k == 0 else 0.0)
            dse2 = 0.0
        else:
            dQ, dkff, dse2 = np.zeros((n, n)), np.zeros(n), 2 * se2
        dlam = np.full(n, dse2) if method == "vfe" else dkff - np.diag(dQ) + dse2
        grad[k] = 0.5 * np.sum(W * (dQ + np.diag(dlam)))
        if method == "vfe":
            tr = np.sum(sf2 - np.diag(Q))
            grad[k] -= np.sum(dkff - np.diag(dQ)) / (2 * se2) - tr * dse2 / (2 * se2**2)
    Ks, _ = kern(Z, Dt, theta)
    P = Kuu + Kuf @ np.diag(1 / lam) @ Kuf.T
    mean = Ks.T @ np.linalg.solve(P, Kuf @ (y / lam))
    var = sf2 - np.einsum("ij,ij->j", Ks, (Ki - np.linalg.inv(P)) @ Ks)
    return F, grad, mean, var


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("n, nd, m, seed", [(40, 1, 8, 0), (120, 2, 15, 1), (90, 3, 12, 2)])
def test_objective_gradient_and_predictions_match_dense_numpy(method, n, nd, m, seed):
    D, y, theta, Z = problem(n, nd, seed, m)
    Dt = np.random.default_rng(seed).uniform(-2.5, 2.5, (7, nd))
    F, grad, mean, var = dense_objective(D, y, Z, theta, method, Dt)
    value, g, _ = _core.sparse_objective(D, y, np.ascontiguousarray(Z), theta, method, True)
    np.testing.assert_allclose(value, F, rtol=1e-9)
    np.testing.assert_allclose(g, grad, rtol=1e-7, atol=1e-7 * np.max(np.abs(grad)))
    sf, ls, se = np.exp(theta[0]), np.exp(theta[1:-1]), np.exp(theta[-1])
    gp = SparseGaussianProcess(inducing=Z, method=method, sigma_f=sf, lengthscales=ls, sigma_eps=se,
                               optimizer=None).fit(D, y)
    assert gp.log_marginal_likelihood() == value
    mu, std = gp.predict(Dt, return_std=True)
    np.testing.assert_allclose(mu, mean, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(std**2, var, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("method", METHODS)
def test_gradients_match_finite_differences(method):
    D, y, theta, Z = problem(700, 2, 3, 10)  # more than one block of columns in the core
    Z = np.ascontiguousarray(Z + 0.05)  # off the data

    def f(t, z):
        return _core.sparse_objective(D, y, np.ascontiguousarray(z), t, method, False)[0]

    _, g, gz = _core.sparse_objective(D, y, Z, theta, method, True)
    h = 1e-6
    for i in range(len(theta)):
        e = np.zeros_like(theta)
        e[i] = h
        fd = (f(theta + e, Z) - f(theta - e, Z)) / (2 * h)
        assert abs(fd - g[i]) < 1e-5 * (1 + abs(fd)), (i, fd, g[i])
    for idx in [(0, 0), (3, 1), (9, 0)]:
        e = np.zeros_like(Z)
        e[idx] = h
        fd = (f(theta, Z + e) - f(theta, Z - e)) / (2 * h)
        assert abs(fd - gz[idx]) < 1e-5 * (1 + abs(fd)), (idx, fd, gz[idx])
    gp = SparseGaussianProcess(inducing=Z, method=method, optimizer=None).fit(D, y)
    Dt = np.array([[0.3, -0.7], [1.9, 0.1]])
    mean, var, dmean, dvar = gp.predict_with_gradients(Dt)
    for l in range(2):
        e = np.zeros(2)
        e[l] = h
        (mp, vp), (mm, vm) = gp.predict_with_gradients(Dt + e)[:2], gp.predict_with_gradients(Dt - e)[:2]
        np.testing.assert_allclose((mp - mm) / (2 * h), dmean[:, l], atol=1e-7)
        np.testing.assert_allclose((vp - vm) / (2 * h), dvar[:, l], atol=1e-7)


# ----------------------------------------------------------------------------- exact limit


@pytest.mark.parametrize("method", METHODS)
def test_inducing_points_at_the_data_reproduce_the_exact_gp(method):
    # With Z = D the formulas reach the exact GP through K(Z, Z)^-1: agreement to about
    # eps * cond(K), so a small well-conditioned set (cond(K) < 1e5).
    D, y, theta, _ = problem(20, 2, 4)
    Y = np.column_stack([y, np.cos(D[:, 1])])
    opts = dict(sigma_f=1.2, lengthscales=[0.8, 0.9], sigma_eps=0.1, optimizer=None)
    assert np.linalg.cond(kern(D, D, np.log([1.2, 0.8, 0.9, 0.1]))[0]) < 1e5
    Dt = np.random.default_rng(0).uniform(-2.5, 2.5, (9, 2))
    exact = MultiOutputGP(**opts).fit(D, Y)
    sparse = SparseMultiOutputGP(inducing=D, method=method, **opts).fit(D, Y)
    for a, b in zip(sparse.predict_with_gradients(Dt), exact.predict_with_gradients(Dt)):
        np.testing.assert_allclose(a, b, rtol=1e-8, atol=1e-8 * np.max(np.abs(b)))
    np.testing.assert_allclose(sparse.log_marginal_likelihood(), exact.log_marginal_likelihood(), rtol=1e-8)
    single = SparseGaussianProcess(inducing=D, method=method, **opts).fit(D, y)
    np.testing.assert_allclose(single.log_marginal_likelihood(), GaussianProcess(**opts).fit(D, y)
                               .log_marginal_likelihood(), rtol=1e-8)


def test_prior_mean_and_map_fit_match_the_exact_gp_with_inducing_points_at_the_data():
    """The learned models' settings (linear prior mean, normalize, default hyperprior): with Z = D
    the sparse objective is the exact LML, so the MAP fits, means and predictions agree."""
    D, y, _, _ = problem(25, 2, 7)
    noise = 0.1 * np.random.default_rng(7).standard_normal(len(D))
    Y = np.column_stack([y + 3.0 * D[:, 0], np.cos(D[:, 1]) - D[:, 1] + noise])
    opts = dict(mean="linear", normalize=True, hyperprior="default", lengthscales=1.0)
    exact = MultiOutputGP(**opts).fit(D, Y)
    sparse = SparseMultiOutputGP(inducing=D, **opts).fit(D, Y)
    np.testing.assert_allclose(sparse.mean_coefficients, exact.mean_coefficients, rtol=1e-12)
    # The same objective at the same θ, to rounding ...
    for theta in (exact.theta, sparse.theta):
        np.testing.assert_allclose(sparse.log_marginal_likelihood(theta),
                                   exact.log_marginal_likelihood(theta), rtol=1e-10)
    # ... maximised to the same optimum: equal within L-BFGS-B's stopping accuracy (here
    # 1e-6 nats; the second output's posterior is flat along a length-scale of 2.6, so θ agrees
    # only to about 1e-3 there, and the predictions to about 1e-4).
    best = [(d.restarts.max(), e.restarts.max())
            for d, e in zip(sparse.diagnostics(), exact.diagnostics())]
    np.testing.assert_allclose(*zip(*best), atol=1e-6)
    np.testing.assert_allclose(sparse.theta, exact.theta, atol=1e-3)
    Dt = np.random.default_rng(1).uniform(-2.5, 2.5, (7, 2))
    for a, b in zip(sparse.predict_with_gradients(Dt), exact.predict_with_gradients(Dt)):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-4 * np.max(np.abs(b)))
    # The prediction adds m(d) = b + w.d: far from the data the mean is the line.
    far = np.array([[50.0, -40.0]])
    line = sparse.mean_coefficients[:, 0] + far @ sparse.mean_coefficients[:, 1:].T
    np.testing.assert_allclose(sparse.predict(far), line, rtol=1e-9)
    # Restarted fits record every run; the bounds and prior apply in standardised units.
    d = sparse.diagnostics()
    assert len(d) == 2 and all(len(x.restarts) == 1 for x in d)


@pytest.mark.parametrize("method", METHODS)
def test_leave_one_out_errors_match_a_dense_computation(method):
    """diagnostics() of a sparse GP: the closed-form LOO of the model y ~ N(0, Qff + Lambda),
    computed block by block in O(N m^2), against a dense inverse of that covariance (and against
    the exact GP's LOO when Z = D)."""
    from gpmhe.gp.diagnostics import sparse_loo

    D, y, theta, Z = problem(60, 2, 8, m=12)
    Kuu, _ = kern(Z, Z, theta)
    Kuf, _ = kern(Z, D, theta)
    Q = Kuf.T @ np.linalg.solve(Kuu, Kuf)
    se2, sf2 = np.exp(2 * theta[-1]), np.exp(2 * theta[0])
    lam = np.full(len(D), se2) if method == "vfe" else sf2 - np.diag(Q) + se2
    Ci = np.linalg.inv(Q + np.diag(lam))
    e, var = sparse_loo(D, y, Z, theta, 0.0, method == "fitc", block=7)
    np.testing.assert_allclose(e, (Ci @ y) / np.diag(Ci), rtol=1e-7)
    np.testing.assert_allclose(var, 1.0 / np.diag(Ci), rtol=1e-7)
    D, y, _, _ = problem(20, 2, 4)
    opts = dict(sigma_f=1.2, lengthscales=[0.8, 0.9], sigma_eps=0.1, optimizer=None)
    exact = GaussianProcess(**opts).fit(D, y).diagnostics()[0]
    sparse = SparseGaussianProcess(inducing=D, method=method, **opts).fit(D, y).diagnostics()[0]
    assert sparse.loo_rmse == pytest.approx(exact.loo_rmse, rel=1e-7)
    assert sparse.loo_z_rms == pytest.approx(exact.loo_z_rms, rel=1e-7)


def test_prior_mean_survives_copies_pickles_and_files():
    D, y, _, _ = problem(200, 2, 9)
    Y = np.column_stack([y + D[:, 0], 2.0 - D[:, 1]])
    gp = SparseMultiOutputGP(n_inducing=15, mean="linear", normalize=True, hyperprior="default").fit(D, Y)
    Dt = np.random.default_rng(2).uniform(-3.0, 3.0, (5, 2))
    for other in (pickle.loads(pickle.dumps(gp)), copy.deepcopy(gp), SparseMultiOutputGP.load(_save(gp))):
        assert_array_equal(other.predict(Dt), gp.predict(Dt))
        assert_array_equal(other.mean_coefficients, gp.mean_coefficients)
        assert (other.mean, other.normalize, other.hyperprior) == ("linear", True, "default")
    core = pickle.loads(pickle.dumps(gp._core_model))
    assert_array_equal(core.mean, gp._core_model.mean)
    with pytest.raises(ValueError, match="mean"):
        _core.SparseMultiGP(D, Y, core.inducing, core.thetas, "vfe", np.zeros((2, 2)))


@pytest.mark.parametrize("method", METHODS)
def test_variance_returns_to_the_prior_far_from_the_data(method):
    D, y, _, _ = problem(300, 2, 5)
    gp = SparseGaussianProcess(n_inducing=20, method=method).fit(D, y)
    far = np.array([[40.0, 0.0], [0.0, -1e3]])
    mean, std = gp.predict(far, return_std=True)
    np.testing.assert_allclose(std, gp.sigma_f, rtol=1e-12)
    np.testing.assert_allclose(mean, 0.0, atol=1e-12)
    # Between: it grows with the distance from the data, monotonically along a ray.
    ray = np.column_stack([np.linspace(2.0, 12.0, 30), np.zeros(30)])
    assert np.all(np.diff(gp.predict(ray, return_std=True)[1]) >= -1e-12)


# ----------------------------------------------------------------------------- fitting


def test_fit_selects_and_optimises():
    D, y, _, _ = problem(2000, 1, 6)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        exact = GaussianProcess().fit(D[:400], y[:400])
        gp = SparseGaussianProcess(n_inducing=40).fit(D[:400], y[:400])
        fitc = SparseGaussianProcess(n_inducing=40, method="fitc").fit(D[:400], y[:400])
    # The VFE bound is below the exact LML, and close to it with enough points.
    assert gp.log_marginal_likelihood() <= exact.log_marginal_likelihood() + 1e-6
    assert gp.log_marginal_likelihood() > exact.log_marginal_likelihood() - 1.0
    assert fitc.sigma_eps == pytest.approx(0.1, rel=0.2)
    Dt = np.linspace(-2, 2, 50)[:, None]
    np.testing.assert_allclose(gp.predict(Dt), exact.predict(Dt), atol=2e-3)
    # Fewer points than asked for on 1-D data: the rest are determined by them.
    assert 1 <= len(gp.inducing_points) <= 40
    # Optimising Z as well never lowers the objective at the same m.
    few = SparseGaussianProcess(n_inducing=4, optimizer=None).fit(D, y)
    opt = SparseGaussianProcess(n_inducing=4, optimize_inducing=True).fit(D, y)
    fixed = SparseGaussianProcess(n_inducing=4).fit(D, y)
    assert len(few.inducing_points) == 4
    assert opt.log_marginal_likelihood() >= fixed.log_marginal_likelihood() - 1e-6
    assert not np.array_equal(opt.inducing_points, fixed.inducing_points)


def test_theta_setter_and_objective_at_other_theta():
    D, y, theta, Z = problem(100, 2, 7, 10)
    gp = SparseGaussianProcess(inducing=Z, optimizer=None).fit(D, y)
    value, grad = gp.log_marginal_likelihood(theta, eval_gradient=True)
    assert value == _core.sparse_objective(D, y, np.ascontiguousarray(Z), theta, "vfe", False)[0]
    gp.theta = theta
    assert gp.log_marginal_likelihood() == value
    assert_array_equal(gp.inducing_points, Z)
    np.testing.assert_allclose(gp.lengthscales, np.exp(theta[1:-1]))


# ----------------------------------------------------------------------------- copies and files


def test_copies_pickles_and_files_are_bit_identical(tmp_path):
    D, y, _, _ = problem(200, 2, 8)
    Y = np.column_stack([y, y**2])
    Dt = np.random.default_rng(1).uniform(-2, 2, (5, 2))
    models = [SparseGaussianProcess(n_inducing=12, method="fitc").fit(D, y),
              SparseMultiOutputGP(n_inducing=12, optimizer=None).fit(D, Y),
              SparseMultiOutputGP(inducing=[D[:5], D[5:12]], optimizer=None).fit(D, Y)]
    for gp in models:
        path = tmp_path / "gp.npz"
        gp.save(path)
        for other in (copy.deepcopy(gp), pickle.loads(pickle.dumps(gp)), type(gp).load(path)):
            assert type(other) is type(gp)
            for a, b in zip(other.predict_with_gradients(Dt), gp.predict_with_gradients(Dt)):
                assert_array_equal(a, b)
            assert_array_equal(other.theta, gp.theta)
            assert other.method == gp.method
    loaded = SparseMultiOutputGP.load(path)
    assert [len(z) for z in loaded.inducing] == [5, 7]  # given points are restored as given
    core = models[1]._core_model
    assert_array_equal(pickle.loads(pickle.dumps(core)).predict(Dt)[1], core.predict(Dt)[1])


def test_learned_model_and_gpmhe_continue_bit_identically():
    states, outputs = br.training_data(3, rng=1, steps=20)
    model = LearnedModel.from_trajectories(states, outputs, n_inducing=6, method="fitc", optimizer=None,
                                           sigma_f=2.0, lengthscales=2.0, sigma_eps=0.05)
    assert isinstance(model.f_gp, SparseMultiOutputGP) and isinstance(model.h_gp, SparseMultiOutputGP)
    buf = io.BytesIO()
    model.save(buf)
    buf.seek(0)
    loaded = LearnedModel.load(buf)
    assert isinstance(loaded.h_gp, SparseMultiOutputGP)
    for a, b in zip(loaded.stage_eval([[1.0, 2.0]]), model.stage_eval([[1.0, 2.0]])):
        assert_array_equal(a, b)
    _, ys = br.simulate(br.X_TRUE0, 12, np.random.default_rng(2))
    kw = dict(x_bounds=br.X_BOUNDS, **{**br.MHE_SETTINGS, "horizon": 4})
    ref = GPMHE(model, br.X_PRIOR0, **kw)
    out_ref = [ref.update(None, yt).copy() for yt in ys]
    est = GPMHE(model, br.X_PRIOR0, **kw)
    for yt in ys[:6]:
        est.update(None, yt)
    checkpoint = io.BytesIO()
    est.save(checkpoint)
    checkpoint.seek(0)
    for other in (copy.deepcopy(est), pickle.loads(pickle.dumps(est)), GPMHE.load(checkpoint, model)):
        assert_array_equal(np.array([other.update(None, yt).copy() for yt in ys[6:]]), out_ref[6:])


# ----------------------------------------------------------------------------- errors


@pytest.mark.parametrize("kwargs, arg", [
    (dict(n_inducing=0), "n_inducing"),
    (dict(n_inducing=2.5), "n_inducing"),
    (dict(method="dtc"), "method"),
    (dict(inducing=[[np.nan, 0.0]]), "inducing"),
    (dict(inducing=[1.0, 2.0]), "inducing"),
    (dict(optimize_inducing=1), "optimize_inducing"),
    (dict(sigma_f=-1.0), "sigma_f"),
])
def test_bad_settings_name_the_argument(kwargs, arg):
    with pytest.raises(ValueError, match=f"^{arg}"):
        SparseGaussianProcess(**kwargs)


def test_bad_fits_name_the_argument_and_leave_the_model_unchanged(tmp_path):
    D, y, _, _ = problem(50, 2, 9)
    gp = SparseGaussianProcess(n_inducing=5, optimizer=None).fit(D, y)
    before = gp.predict(D[:3])
    for bad, arg in [(SparseGaussianProcess(inducing=np.zeros((3, 3))), "inducing"),
                     (SparseMultiOutputGP(inducing=[D[:3]] * 3), "inducing")]:
        with pytest.raises(ValueError, match=f"^{arg}"):
            bad.fit(D, y)
    with pytest.raises(ValueError, match="^y"):
        gp.fit(D, y[:-1])
    assert_array_equal(gp.predict(D[:3]), before)
    with pytest.raises(ValueError, match="^D"):
        gp.predict(np.zeros((2, 3)))
    gp.save(tmp_path / "gp.npz")
    with np.load(tmp_path / "gp.npz") as f:
        entries = dict(f)
    np.savez(tmp_path / "bad.npz", **{**entries, "inducing_counts": np.array([99])})
    with pytest.raises(ValueError, match="inducing_counts"):
        SparseGaussianProcess.load(tmp_path / "bad.npz")
    with pytest.raises(ValueError, match="not a saved SparseGaussianProcess"):
        SparseGaussianProcess.load(_save(GaussianProcess(optimizer=None).fit(D, y)))
    with pytest.raises(ValueError, match="^method"):
        _core.sparse_objective(D, y, D[:3], np.zeros(4), "sor")
    with pytest.raises(ValueError, match="^z"):
        _core.sparse_objective(D, y, np.zeros((3, 1)), np.zeros(4), "vfe")


def _save(gp):
    buf = io.BytesIO()
    gp.save(buf)
    buf.seek(0)
    return buf


# ----------------------------------------------------------------------------- GP-MHE


def _rmse(model, x, y):
    est = GPMHE(model, br.X_PRIOR0, x_bounds=br.X_BOUNDS, **br.MHE_SETTINGS)
    xs = np.array([est.update(None, yt).copy() for yt in y[: len(x) - 1]])
    return float(np.sqrt(np.mean(np.sum((xs - x[1:]) ** 2, axis=1))))


def test_gpmhe_with_sparse_gps_on_the_batch_reactor():
    """GP-MHE on sparse GPs (VFE, up to 30 inducing points) of the 5 paper trajectories is within a
    few per cent of the exact GPs' RMSE (two seeds here; benches/bench_sparse.py measures 20)."""
    ratios = []
    for seed in (0, 1):
        rng = np.random.default_rng(seed)
        data = br.training_data(5, rng=rng)
        x, y = br.simulate(br.X_TRUE0, 100, rng)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            exact = LearnedModel.from_trajectories(*data, n_restarts=1, random_state=seed)
            sparse = LearnedModel.from_trajectories(*data, n_restarts=1, random_state=seed, n_inducing=30)
        ratios.append(_rmse(sparse, x, y) / _rmse(exact, x, y))
    assert np.mean(ratios) < 1.05, ratios


def test_bank_and_gp_ekf_run_on_sparse_gps():
    from gpmhe import EstimatorBank
    from gpmhe.baselines import GPEKF

    states, outputs = br.training_data(3, rng=3, steps=20)
    model = LearnedModel.from_trajectories(states, outputs, n_inducing=8, optimizer=None,
                                           sigma_f=2.0, lengthscales=2.0, sigma_eps=0.05)
    _, ys = br.simulate(br.X_TRUE0, 8, np.random.default_rng(4))
    kw = dict(horizon=4, Q0=1e-3, R0=1e-2, x_bounds=br.X_BOUNDS)
    x0 = [[3.0, 1.0], [1.0, 3.0]]
    bank = EstimatorBank(model, 2, x0, **kw)
    singles = [GPMHE(model, x, **kw) for x in x0]
    for yt in ys:
        out = bank.update(None, [yt, yt])
        assert_array_equal(out, np.array([s.update(None, yt) for s in singles]))
    ekf = GPEKF(model, x0=[3.0, 1.0], P0=0.1 * np.eye(2), Q=1e-3 * np.eye(2), R=1e-2)
    for yt in ys:
        ekf.update(yt)
        ekf.predict()
    assert np.all(np.isfinite(ekf.x))


@pytest.mark.skipif(not hasattr(signal, "setitimer"), reason="needs signal.setitimer")
def test_signal_during_a_long_sparse_fit_interrupts_it_promptly_and_keeps_the_gp():
    assert threading.current_thread() is threading.main_thread()
    D, y, _, _ = problem(300_000, 2, 10)
    gp = SparseGaussianProcess(n_inducing=200, method="fitc").fit(D[:50], y[:50])
    before = gp.predict(D[:5])
    fired = []

    def handler(signum, frame):
        fired.append(time.perf_counter())
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGALRM, handler)
    signal.setitimer(signal.ITIMER_REAL, 0.3)
    try:
        with pytest.raises(KeyboardInterrupt):
            gp.fit(D, y)  # tens of seconds
        raised = time.perf_counter()
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
    assert fired, "the fit finished before the signal"
    assert raised - fired[0] < 1.0  # the core checks between waves of blocks (~0.05 s of work)
    assert_array_equal(gp.predict(D[:5]), before)
