"""GaussianProcess / MultiOutputGP: parity with scikit-learn, analytic gradients against finite
differences, fitting at least as well as scikit-learn, multi-output layout and save/load."""

import warnings

import numpy as np
import pytest
from sklearn.exceptions import ConvergenceWarning as SkConvergenceWarning
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

from gpmhe import GaussianProcess, MultiOutputGP
from gpmhe import _core


def random_problem(n, nd, seed):
    rng = np.random.default_rng(seed)
    D = rng.uniform(-2.0, 2.0, (n, nd))
    y = np.sin(1.5 * D).sum(axis=1) + 0.3 * D[:, 0] ** 2 + 0.1 * rng.normal(size=n)
    sigma_f = rng.uniform(0.5, 2.0)
    lengthscales = rng.uniform(0.5, 2.0, nd)
    sigma_eps = rng.uniform(0.05, 0.3)
    Dt = rng.uniform(-2.5, 2.5, (13, nd))
    return D, y, sigma_f, lengthscales, sigma_eps, Dt


def sklearn_gp(sigma_f, lengthscales, sigma_eps, noise_kernel=True):
    """scikit-learn's GP with the same hyperparameters, not optimised, no extra alpha."""
    k = ConstantKernel(sigma_f**2, "fixed") * RBF(lengthscales, "fixed")
    if noise_kernel:
        k = ConstantKernel(sigma_f**2) * RBF(lengthscales) + WhiteKernel(sigma_eps**2)
        return GaussianProcessRegressor(k, alpha=0.0, optimizer=None)
    return GaussianProcessRegressor(k, alpha=sigma_eps**2, optimizer=None)


def assert_rel(actual, desired, rtol=1e-8):
    scale = np.max(np.abs(desired))
    np.testing.assert_allclose(actual, desired, rtol=rtol, atol=rtol * scale)


@pytest.mark.parametrize(
    "n, nd, seed",
    [(5, 1, 0), (30, 2, 1), (120, 3, 2), (500, 4, 3), (500, 1, 4), (64, 4, 5)],
)
def test_parity_with_sklearn(n, nd, seed):
    D, y, sf, ls, se, Dt = random_problem(n, nd, seed)
    gp = GaussianProcess(sf, ls, se, optimizer=None).fit(D, y)
    sk = sklearn_gp(sf, ls, se).fit(D, y)
    sk_latent = sklearn_gp(sf, ls, se, noise_kernel=False).fit(D, y)

    mean, std = gp.predict(Dt, return_std=True)
    sk_mean, sk_std = sk.predict(Dt, return_std=True)
    _, sk_latent_std = sk_latent.predict(Dt, return_std=True)
    assert_rel(mean, sk_mean)
    # scikit-learn's std with a WhiteKernel includes the noise; ours is the latent f's.
    assert_rel(np.sqrt(std**2 + se**2), sk_std)
    assert_rel(std, sk_latent_std)

    # LML and gradient. scikit-learn's theta is log([sigma_f^2, lengthscales, sigma_eps^2]), so
    # d/dlog(sigma_f) = 2 d/dlog(sigma_f^2), likewise for sigma_eps.
    lml, grad = gp.log_marginal_likelihood(eval_gradient=True)
    sk_lml, sk_grad = sk.log_marginal_likelihood(sk.kernel_.theta, eval_gradient=True)
    assert lml == pytest.approx(sk_lml, rel=1e-8)
    sk_grad_ours = sk_grad.copy()
    sk_grad_ours[0] *= 2.0
    sk_grad_ours[-1] *= 2.0
    assert_rel(grad, sk_grad_ours)


def test_lml_at_other_theta_matches_sklearn():
    D, y, sf, ls, se, _ = random_problem(80, 2, 11)
    gp = GaussianProcess(sf, ls, se, optimizer=None).fit(D, y)
    theta = np.log([0.7, 1.9, 0.4, 0.2])
    sk = sklearn_gp(1.0, np.ones(2), 0.1).fit(D, y)
    sk_theta = np.array([2 * theta[0], theta[1], theta[2], 2 * theta[3]])
    lml, grad = gp.log_marginal_likelihood(theta, eval_gradient=True)
    sk_lml, sk_grad = sk.log_marginal_likelihood(sk_theta, eval_gradient=True)
    assert lml == pytest.approx(sk_lml, rel=1e-8)
    assert_rel(grad, sk_grad * np.array([2.0, 1.0, 1.0, 2.0]))
    assert gp.log_marginal_likelihood(theta) == pytest.approx(lml, rel=1e-14)


def test_theta_gradient_matches_finite_differences():
    D, y, sf, ls, se, _ = random_problem(60, 3, 7)
    gp = GaussianProcess(sf, ls, se, optimizer=None).fit(D, y)
    theta = gp.theta
    _, grad = gp.log_marginal_likelihood(theta, eval_gradient=True)
    h = 1e-5
    for i in range(theta.size):
        e = np.zeros_like(theta)
        e[i] = h
        fd = (gp.log_marginal_likelihood(theta + e) - gp.log_marginal_likelihood(theta - e)) / (2 * h)
        assert grad[i] == pytest.approx(fd, rel=1e-6, abs=1e-6)


@pytest.mark.parametrize("nd", [1, 2, 4])
def test_input_gradients_match_finite_differences(nd):
    D, y, sf, ls, se, Dt = random_problem(70, nd, 20 + nd)
    gp = GaussianProcess(sf, ls, se, optimizer=None).fit(D, y)
    mean, var, dmean, dvar = gp.predict_with_gradients(Dt)
    assert mean.shape == var.shape == (len(Dt),)
    assert dmean.shape == dvar.shape == (len(Dt), nd)
    assert np.all(var >= 0)
    h = 1e-6
    for l in range(nd):
        e = np.zeros(nd)
        e[l] = h
        mp, vp, _, _ = gp.predict_with_gradients(Dt + e)
        mm, vm, _, _ = gp.predict_with_gradients(Dt - e)
        np.testing.assert_allclose(dmean[:, l], (mp - mm) / (2 * h), rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(dvar[:, l], (vp - vm) / (2 * h), rtol=1e-6, atol=1e-7)


def test_predict_with_gradients_agrees_with_predict():
    D, y, sf, ls, se, Dt = random_problem(50, 2, 3)
    gp = GaussianProcess(sf, ls, se, optimizer=None).fit(D, y)
    mean, std = gp.predict(Dt, return_std=True)
    m2, v2, _, _ = gp.predict_with_gradients(Dt)
    np.testing.assert_array_equal(mean, m2)
    np.testing.assert_allclose(std**2, v2, rtol=1e-14)
    # Without return_std only the means are computed (no triangular solves): the same numbers.
    np.testing.assert_array_equal(gp.predict(Dt), mean)


# ----------------------------------------------------------------------------- fitting


def batch_reactor_training_data(seed=0, x0s=((3, 1), (1.2, 4.5), (0.5, 3.5), (1, 3), (2, 4))):
    """Offline data of the batch reactor (docs/user_guide/systems.rst): 5 trajectories of 31 states, Euler T = 0.1, process noise
    std 0.01, states measured with noise std 0.01 and y = x1 + x2 with noise std 0.1.
    Returns GP inputs x(t) (150, 2), targets x(t+1) (150, 2) and y(t) (150,)."""
    rng = np.random.default_rng(seed)
    T, k1, k2 = 0.1, 0.16, 0.0064
    inputs, next_states, outputs = [], [], []
    for x0 in x0s:
        x = np.array(x0, dtype=float)
        traj = [x]
        for _ in range(30):
            x1, x2 = x
            x = np.array(
                [x1 + T * (-2 * k1 * x1**2 + 2 * k2 * x2), x2 + T * (k1 * x1**2 - k2 * x2)]
            ) + 0.01 * rng.normal(size=2)
            traj.append(x)
        traj = np.array(traj)
        meas = traj + 0.01 * rng.normal(size=traj.shape)
        y = traj.sum(axis=1) + 0.1 * rng.normal(size=len(traj))
        inputs.append(meas[:-1])
        next_states.append(meas[1:])
        outputs.append(y[:-1])
    return np.vstack(inputs), np.vstack(next_states), np.concatenate(outputs)


BOUNDS = ((1e-2, 1e3), (1e-2, 1e3), (1e-3, 1e1))


def sklearn_fit(D, y, n_restarts, seed):
    k = ConstantKernel(1.0, (BOUNDS[0][0] ** 2, BOUNDS[0][1] ** 2)) * RBF(
        np.ones(D.shape[1]), BOUNDS[1]
    ) + WhiteKernel(0.01, (BOUNDS[2][0] ** 2, BOUNDS[2][1] ** 2))
    sk = GaussianProcessRegressor(k, alpha=0.0, n_restarts_optimizer=n_restarts, random_state=seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SkConvergenceWarning)
        return sk.fit(D, y)


def batch_reactor_targets():
    D, Xn, y = batch_reactor_training_data()
    return [("f1", D, Xn[:, 0]), ("f2", D, Xn[:, 1]), ("h", D, y)]


@pytest.mark.parametrize("name, D, y", batch_reactor_targets(), ids=["f1", "f2", "h"])
def test_fit_no_worse_than_sklearn_on_batch_reactor(name, D, y):
    n_restarts = 2
    gp = GaussianProcess(1.0, 1.0, 0.1, n_restarts=n_restarts, bounds=BOUNDS, random_state=0)
    gp.fit(D, y)
    sk = sklearn_fit(D, y, n_restarts, seed=0)
    assert gp.log_marginal_likelihood_value >= sk.log_marginal_likelihood_value_ - 1e-6
    # The fitted model is consistent with its own LML.
    assert gp.log_marginal_likelihood() == pytest.approx(gp.log_marginal_likelihood_value)


@pytest.mark.parametrize("seed, nd", [(0, 1), (1, 2), (2, 3)])
def test_fit_no_worse_than_sklearn_on_random_functions(seed, nd):
    rng = np.random.default_rng(100 + seed)
    D = rng.uniform(-3, 3, (60, nd))
    w = rng.normal(size=(nd, 3))
    y = np.sin(D @ w).sum(axis=1) + 0.05 * rng.normal(size=60)
    gp = GaussianProcess(n_restarts=3, bounds=BOUNDS, random_state=seed).fit(D, y)
    sk = sklearn_fit(D, y, 3, seed)
    assert gp.log_marginal_likelihood_value >= sk.log_marginal_likelihood_value_ - 1e-6


def test_fit_recovers_the_noise_level():
    rng = np.random.default_rng(5)
    D = rng.uniform(-3, 3, (300, 1))
    y = np.sin(D[:, 0]) + 0.2 * rng.normal(size=300)
    gp = GaussianProcess(random_state=0).fit(D, y)
    assert gp.sigma_eps == pytest.approx(0.2, rel=0.15)
    assert np.max(np.abs(gp.predict(D) - np.sin(D[:, 0]))) < 0.15


def test_restarts_are_reproducible_and_never_worse():
    D, Xn, _ = batch_reactor_training_data(seed=3)
    y = Xn[:, 0]
    # A poor start: tiny length-scale, large noise.
    start = dict(sigma_f=0.05, lengthscales=0.02, sigma_eps=5.0, bounds=BOUNDS)
    single = GaussianProcess(**start, n_restarts=0).fit(D, y)
    a = GaussianProcess(**start, n_restarts=3, random_state=1).fit(D, y)
    b = GaussianProcess(**start, n_restarts=3, random_state=1).fit(D, y)
    np.testing.assert_array_equal(a.theta, b.theta)
    assert a.log_marginal_likelihood_value >= single.log_marginal_likelihood_value - 1e-9


def test_optimizer_none_keeps_hyperparameters():
    D, y, *_ = random_problem(20, 2, 9)
    gp = GaussianProcess(1.5, [0.5, 2.0], 0.2, optimizer=None).fit(D, y)
    np.testing.assert_allclose(np.exp(gp.theta), [1.5, 0.5, 2.0, 0.2], rtol=1e-15)
    assert gp.sigma_f == pytest.approx(1.5) and gp.sigma_eps == pytest.approx(0.2)


def test_theta_setter_refactors_without_optimising():
    D, y, *_ = random_problem(40, 2, 12)
    gp = GaussianProcess(optimizer=None).fit(D, y)
    new = np.log([2.0, 0.3, 0.6, 0.05])
    gp.theta = new
    np.testing.assert_allclose(gp.theta, new)
    ref = GaussianProcess(2.0, [0.3, 0.6], 0.05, optimizer=None).fit(D, y)
    np.testing.assert_array_equal(gp.predict(D[:5]), ref.predict(D[:5]))


def test_fit_accepts_non_contiguous_and_integer_input():
    rng = np.random.default_rng(0)
    big = rng.uniform(-2, 2, (40, 4))
    D = big[:, ::2]  # a non-contiguous view
    y = np.sin(D).sum(axis=1)
    gp = GaussianProcess(optimizer=None).fit(D, y)
    ref = GaussianProcess(optimizer=None).fit(np.ascontiguousarray(D), y)
    Di = np.array([[0, 1], [1, -1]])
    np.testing.assert_array_equal(gp.predict(Di), ref.predict(Di.astype(float)))


# ----------------------------------------------------------------------------- multi-output


def multi_problem():
    rng = np.random.default_rng(4)
    D = rng.uniform(-2, 2, (80, 2))
    Y = np.column_stack([np.sin(D[:, 0]), D[:, 0] * D[:, 1], np.cos(2 * D[:, 1])])
    Y += 0.05 * rng.normal(size=Y.shape)
    return D, Y, rng.uniform(-2, 2, (9, 2))


def test_multi_output_matches_independent_gps():
    D, Y, Dt = multi_problem()
    mgp = MultiOutputGP(n_restarts=1, random_state=0).fit(D, Y)
    mean, var, dmean, dvar = mgp.predict_with_gradients(Dt)
    q, nd = 3, 2
    assert mean.shape == var.shape == (9, q)
    assert dmean.shape == dvar.shape == (9, q, nd)
    assert mgp.theta.shape == (q, nd + 2)
    assert mgp.lengthscales.shape == (q, nd)
    assert isinstance(mgp._core_model, _core.MultiGP)
    for o in range(q):
        sf, ls, se = mgp.sigma_f[o], mgp.lengthscales[o], mgp.sigma_eps[o]
        gp = GaussianProcess(sf, ls, se, optimizer=None).fit(D, Y[:, o])
        m, v, dm, dv = gp.predict_with_gradients(Dt)
        np.testing.assert_allclose(mean[:, o], m, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(var[:, o], v, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(dmean[:, o], dm, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(dvar[:, o], dv, rtol=1e-12, atol=1e-14)
        # And each output is fitted as well as a single GP fitted alone with the same settings.
        single = GaussianProcess(n_restarts=1, random_state=0).fit(D, Y[:, o])
        lml = mgp.log_marginal_likelihood()[o]
        assert lml >= single.log_marginal_likelihood_value - 1e-3 * abs(lml)
    mean2, std2 = mgp.predict(Dt, return_std=True)
    np.testing.assert_array_equal(mean2, mean)
    np.testing.assert_array_equal(mgp.predict(Dt), mean)
    np.testing.assert_allclose(std2**2, var, rtol=1e-14)


def test_multi_output_lml_gradient_and_theta_setter():
    D, Y, Dt = multi_problem()
    mgp = MultiOutputGP(optimizer=None, sigma_f=[1.0, 2.0, 0.5], lengthscales=[[1, 1], [2, 1], [1, 0.5]]).fit(D, Y)
    lml, grad = mgp.log_marginal_likelihood(eval_gradient=True)
    assert lml.shape == (3,) and grad.shape == (3, 4)
    for o in range(3):
        ref = GaussianProcess(
            mgp.sigma_f[o], mgp.lengthscales[o], mgp.sigma_eps[o], optimizer=None
        ).fit(D, Y[:, o])
        rl, rg = ref.log_marginal_likelihood(eval_gradient=True)
        assert lml[o] == pytest.approx(rl, rel=1e-12)
        np.testing.assert_allclose(grad[o], rg, rtol=1e-10, atol=1e-12)
    new = mgp.theta + 0.1
    mgp.theta = new
    np.testing.assert_allclose(mgp.theta, new)


def test_multi_output_one_dimensional_y():
    D, Y, Dt = multi_problem()
    mgp = MultiOutputGP(optimizer=None).fit(D, Y[:, 0])
    assert mgp.predict(Dt).shape == (9, 1)


# ----------------------------------------------------------------------------- persistence


def test_save_load_roundtrip(tmp_path):
    D, y, sf, ls, se, Dt = random_problem(40, 2, 8)
    gp = GaussianProcess(n_restarts=1, random_state=0, bounds=BOUNDS).fit(D, y)
    path = tmp_path / "gp.npz"
    gp.save(path)
    loaded = GaussianProcess.load(path)
    for a, b in zip(gp.predict_with_gradients(Dt), loaded.predict_with_gradients(Dt)):
        np.testing.assert_array_equal(a, b)
    assert loaded.n_restarts == 1
    np.testing.assert_array_equal(np.asarray(loaded.bounds), np.asarray(BOUNDS))

    D, Y, Dt = multi_problem()
    mgp = MultiOutputGP(optimizer=None).fit(D, Y)
    mgp.save(tmp_path / "mgp.npz")
    mloaded = MultiOutputGP.load(tmp_path / "mgp.npz")
    assert mloaded.optimizer is None
    for a, b in zip(mgp.predict_with_gradients(Dt), mloaded.predict_with_gradients(Dt)):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="path"):
        GaussianProcess.load(tmp_path / "mgp.npz")


def test_per_dimension_bounds_are_respected():
    D, y, *_ = random_problem(50, 2, 13)
    bounds = [(0.1, 10.0), (0.5, 0.5), (0.1, 10.0), (0.2, 0.2)]  # phi_1 and sigma_eps fixed
    gp = GaussianProcess(bounds=bounds, random_state=0).fit(D, y)
    assert gp.lengthscales[0] == pytest.approx(0.5, rel=1e-12)
    assert gp.sigma_eps == pytest.approx(0.2, rel=1e-12)
    assert 0.1 <= gp.lengthscales[1] <= 10.0
    with pytest.raises(ValueError, match="bounds"):
        GaussianProcess(bounds=bounds).fit(D[:, :1], y)  # 4 rows do not fit n_d = 1
