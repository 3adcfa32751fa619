"""GaussianProcess / MultiOutputGP error handling: bad input raises ValueError naming the argument,
numerical failure raises gpmhe.NumericalError, and a failed fit or theta update leaves a fitted
model exactly as it was."""

import numpy as np
import pytest

import gpmhe
import gpmhe.gp.exact
from gpmhe import GaussianProcess, MultiOutputGP, NotFittedError, NumericalError
from gpmhe import _core


@pytest.fixture
def data():
    rng = np.random.default_rng(0)
    D = rng.uniform(-2, 2, (30, 2))
    y = np.sin(D).sum(axis=1)
    return D, y


@pytest.fixture
def fitted(data):
    D, y = data
    return GaussianProcess(n_restarts=0).fit(D, y)


def snapshot(gp, Dt):
    return (gp.theta.copy(), *gp.predict_with_gradients(Dt))


def assert_unchanged(before, after):
    for a, b in zip(before, after):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize(
    "kwargs, arg",
    [
        (dict(sigma_f=0.0), "sigma_f"),
        (dict(sigma_f=-1.0), "sigma_f"),
        (dict(sigma_f=np.nan), "sigma_f"),
        (dict(sigma_f=[1.0, 2.0]), "sigma_f"),
        (dict(lengthscales=[1.0, -2.0]), "lengthscales"),
        (dict(lengthscales=np.inf), "lengthscales"),
        (dict(lengthscales=[[1.0]]), "lengthscales"),
        (dict(sigma_eps=0.0), "sigma_eps"),
        (dict(optimizer="bfgs"), "optimizer"),
        (dict(n_restarts=-1), "n_restarts"),
        (dict(n_restarts=1.5), "n_restarts"),
        (dict(bounds=((1, 2), (1, 2))), "bounds"),
        (dict(bounds=((1, 2), (0, 2), (1, 2))), "bounds"),
        (dict(bounds=((3, 2), (1, 2), (1, 2))), "bounds"),
    ],
)
def test_bad_constructor_arguments(kwargs, arg):
    with pytest.raises(ValueError, match=arg):
        GaussianProcess(**kwargs)


@pytest.mark.parametrize(
    "make, arg",
    [
        (lambda D, y: (np.where(np.arange(D.size).reshape(D.shape) == 3, np.nan, D), y), "D"),
        (lambda D, y: (D, np.where(np.arange(y.size) == 0, np.inf, y)), "y"),
        (lambda D, y: (D[:, 0], y), "D"),
        (lambda D, y: (D, y[:, None]), "y"),
        (lambda D, y: (D, y[:-1]), "y"),
        (lambda D, y: (D[:1], y[:1]), "D"),
        (lambda D, y: (np.array([["a", "b"], ["c", "d"]]), y[:2]), "D"),
    ],
)
def test_bad_training_data(data, make, arg):
    D, y = make(*data)
    with pytest.raises(ValueError, match=arg):
        GaussianProcess(optimizer=None).fit(D, y)


def test_lengthscales_of_wrong_length(data):
    with pytest.raises(ValueError, match="lengthscales"):
        GaussianProcess(lengthscales=[1.0, 1.0, 1.0], optimizer=None).fit(*data)


def test_not_fitted():
    gp = GaussianProcess()
    for call in (
        lambda: gp.predict(np.zeros((1, 2))),
        lambda: gp.predict_with_gradients(np.zeros((1, 2))),
        lambda: gp.log_marginal_likelihood(),
        lambda: gp.save("unused.npz"),
    ):
        with pytest.raises(NotFittedError, match="fit"):
            call()
    with pytest.raises(NotFittedError):
        MultiOutputGP().predict(np.zeros((1, 2)))


def test_bad_prediction_points(fitted):
    with pytest.raises(ValueError, match="D"):
        fitted.predict(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="D"):
        fitted.predict_with_gradients(np.zeros(2))
    with pytest.raises(ValueError, match="D"):
        fitted.predict(np.array([[0.0, np.nan]]))
    with pytest.raises(ValueError, match="theta"):
        fitted.log_marginal_likelihood(np.zeros(3))
    with pytest.raises(ValueError, match="theta"):
        fitted.log_marginal_likelihood(np.array([0.0, 0.0, np.nan, 0.0]))


def test_failed_fit_leaves_model_unchanged(data, fitted):
    D, y = data
    Dt = D[:4] + 0.1
    before = snapshot(fitted, Dt)
    bad_y = y.copy()
    bad_y[5] = np.nan
    with pytest.raises(ValueError, match="y"):
        fitted.fit(D, bad_y)
    with pytest.raises(ValueError, match="lengthscales"):
        fitted.fit(D[:, :1].repeat(3, axis=1), y)  # n_d = 3, but 2 fitted length-scales
    assert_unchanged(before, snapshot(fitted, Dt))
    np.testing.assert_array_equal(fitted.D_train, D)


def test_numerical_failure_in_fit_leaves_model_unchanged(data, fitted, monkeypatch):
    D, y = data
    Dt = D[:4] + 0.1
    before = snapshot(fitted, Dt)

    def always_fails(*args, **kwargs):
        raise NumericalError("simulated failure")

    monkeypatch.setattr(gpmhe.gp.exact._core, "log_marginal_likelihood", always_fails)
    with pytest.raises(NumericalError, match="fit"):
        fitted.fit(D + 1.0, y)
    monkeypatch.undo()
    assert_unchanged(before, snapshot(fitted, Dt))


def test_numerical_error_from_core(data):
    D, y = data
    with pytest.raises(NumericalError):
        GaussianProcess(optimizer=None).fit(D, np.full_like(y, 1e200))
    assert issubclass(NumericalError, RuntimeError)


def test_bad_theta_assignment_leaves_model_unchanged(data, fitted):
    D, _ = data
    Dt = D[:3]
    before = snapshot(fitted, Dt)
    for bad in (np.zeros(3), [0.0, np.nan, 0.0, 0.0], [800.0, 0.0, 0.0, 0.0]):
        with pytest.raises(ValueError, match="theta"):
            fitted.theta = bad
    assert_unchanged(before, snapshot(fitted, Dt))


def test_multi_output_errors(data):
    D, y = data
    Y = np.column_stack([y, 2 * y])
    with pytest.raises(ValueError, match="sigma_f"):
        MultiOutputGP(sigma_f=[1.0, 2.0, 3.0], optimizer=None).fit(D, Y)
    with pytest.raises(ValueError, match="lengthscales"):
        MultiOutputGP(lengthscales=np.ones((3, 2)), optimizer=None).fit(D, Y)
    with pytest.raises(ValueError, match="y"):
        MultiOutputGP(optimizer=None).fit(D, Y[:-1])
    mgp = MultiOutputGP(optimizer=None).fit(D, Y)
    before = (mgp.theta.copy(), *mgp.predict_with_gradients(D[:3]))
    with pytest.raises(ValueError, match="theta"):
        mgp.theta = np.zeros((3, 4))
    Ybad = Y.copy()
    Ybad[0, 1] = np.inf
    with pytest.raises(ValueError, match="y"):
        mgp.fit(D, Ybad)
    assert_unchanged(before, (mgp.theta, *mgp.predict_with_gradients(D[:3])))


def test_core_rejects_non_contiguous_and_mismatched_arrays(data):
    D, y = data
    theta = np.log([1.0, 1.0, 1.0, 0.1])
    Y, thetas = y[:, None].copy(), theta[None, :].copy()
    with pytest.raises(ValueError, match="x"):
        _core.MultiGP(np.asfortranarray(D), Y, thetas)
    with pytest.raises(ValueError, match="x"):
        _core.log_marginal_likelihood(D, y, np.log([1.0, 1.0, 0.1]))
    with pytest.raises(ValueError, match="y"):
        _core.MultiGP(D, y[:-1, None].copy(), thetas)
    with pytest.raises(ValueError, match="thetas"):
        _core.MultiGP(D, Y, theta[None, :3].copy())
    with pytest.raises(TypeError):
        _core.MultiGP(D.astype(np.float32), Y, thetas)
    gp = _core.MultiGP(D, Y, thetas)
    with pytest.raises(ValueError, match="D"):
        gp.predict(np.zeros((2, 3)))


def test_load_rejects_other_files(tmp_path):
    path = tmp_path / "other.npz"
    np.savez(path, a=np.zeros(3))
    with pytest.raises(ValueError, match="path"):
        GaussianProcess.load(path)


def test_input_error_in_the_fit_is_raised_not_counted_as_a_bad_theta(data, monkeypatch):
    # The optimiser's objective counts numerical failures and a trial theta the core cannot
    # represent as +inf, but a genuine input error surfaces as the ValueError naming the argument.
    D, y = data

    def refuses(message):
        def core(*args, **kwargs):
            raise ValueError(message)
        return core

    monkeypatch.setattr(gpmhe.gp.exact._core, "log_marginal_likelihood", refuses("y: simulated input error"))
    with pytest.raises(ValueError, match="^y: simulated"):
        GaussianProcess().fit(D, y)
    monkeypatch.setattr(gpmhe.gp.exact._core, "log_marginal_likelihood", refuses("theta: exp(theta[0]) overflows"))
    with pytest.raises(NumericalError, match="fit"):
        GaussianProcess().fit(D, y)


def test_extreme_length_scales_are_refused_or_handled():
    """Length-scales whose inverse square overflows are refused naming the argument; a finite
    objective never comes with a NaN gradient; the smallest accepted length-scale still
    predicts the targets at the training inputs (k(d, d) = sigma_f^2, not 0 * inf)."""
    rng = np.random.default_rng(0)
    D = rng.uniform(-1.0, 1.0, (20, 2))
    y = np.sin(D[:, 0])
    gp = GaussianProcess(optimizer=None).fit(D, y)
    with pytest.raises(ValueError, match=r"^theta: length-scale exp\(theta\[1\]\)"):
        gp.log_marginal_likelihood([0.0, -400.0, -400.0, -2.0], eval_gradient=True)
    lml, grad = gp.log_marginal_likelihood([0.0, -300.0, -300.0, -2.0], eval_gradient=True)
    assert np.isfinite(lml) and np.all(np.isfinite(grad))
    with pytest.raises(ValueError, match=r"^lengthscales: .* too small"):
        GaussianProcess(lengthscales=1e-200, optimizer=None)
    tiny = GaussianProcess(lengthscales=1e-150, sigma_eps=1e-3, optimizer=None).fit(D, y)
    np.testing.assert_allclose(tiny.predict(D), y, rtol=1e-5, atol=1e-5)
