"""A fit is called converged only where it is: whatever status SciPy's L-BFGS-B reports, the
projected gradient at the result must be small; otherwise the fit runs again from there, and
warns (ConvergenceWarning, with what to do) if that does not converge either. Checked with a
gradient that is made wrong on purpose (as a sparse GP's was when K(Z, Z) was ill-conditioned)
and with an iteration limit."""

import warnings

import numpy as np

import gpmhe.gp.exact
from gpmhe import ConvergenceWarning, GaussianProcess
from gpmhe import _core

RNG = np.random.default_rng(4)
D = RNG.uniform(-3.0, 3.0, (60, 2))
Y = np.sin(D[:, 0]) * np.cos(0.5 * D[:, 1]) + 0.05 * RNG.standard_normal(60)


def _fit(**kw):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        gp = GaussianProcess(**kw).fit(D, Y)
    return gp, [w for w in caught if issubclass(w.category, ConvergenceWarning)]


def test_a_wrong_gradient_is_not_called_converged(monkeypatch):
    """With the gradient's sign flipped in two components L-BFGS-B cannot make progress and
    stops (SciPy may call that converged): the fit says so with a ConvergenceWarning."""
    good, caught = _fit()
    assert not caught
    true = _core.log_marginal_likelihood

    def wrong(D_, y_, theta, eval_gradient):
        value, grad = true(D_, y_, theta, eval_gradient)
        return value, grad * np.array([1.0, -1.0, -1.0, 1.0])

    monkeypatch.setattr(gpmhe.gp.exact._core, "log_marginal_likelihood", wrong)
    bad, caught = _fit()
    monkeypatch.setattr(gpmhe.gp.exact._core, "log_marginal_likelihood", true)
    assert len(caught) == 1 and "projected gradient is still large" in str(caught[0].message)
    assert bad.log_marginal_likelihood() < good.log_marginal_likelihood() - 1e-3  # it did stop short


def test_an_iteration_limit_warns_with_advice():
    gp, caught = _fit(maxiter=1)
    assert len(caught) == 1
    message = str(caught[0].message)
    assert "projected gradient is still large" in message and "raise maxiter" in message
    assert caught[0].filename == __file__  # points at the caller's fit


def test_a_converged_fit_has_a_small_projected_gradient():
    gp, caught = _fit(n_restarts=2, random_state=0)
    assert not caught
    lml, grad = gp.log_marginal_likelihood(eval_gradient=True)
    assert np.max(np.abs(grad)) <= 1e-3 * max(1.0, abs(lml))


def _smooth_2d(seed, n=500, m=20):
    """bench_sparse_fit.py's data: N noisy samples of a smooth function, m inducing inputs."""
    rng = np.random.default_rng(seed)
    D_ = rng.uniform(-2.0, 2.0, (n, 2))
    y = np.sin(2.0 * D_[:, 0]) + 0.5 * D_[:, 0] * np.cos(1.5 * D_[:, 1]) + 0.1 * rng.standard_normal(n)
    return D_, y, D_[rng.choice(n, m, replace=False)]


def test_a_first_step_into_the_noise_only_corner_is_taken_again_with_short_steps():
    """From sigma_f = 1, l = 1, sigma_eps = 0.1 the gradient on this data set is ~1e4 and plain
    L-BFGS-B's first step lands in the corner sigma_f = lower bound, l = upper bounds (bound
    -581, the data explained as noise, a KKT point it then calls converged). The fit repeats
    from the start with short steps and reaches the signal (a bound near 215)."""
    from scipy.optimize import minimize

    from gpmhe import SparseGaussianProcess

    D_, y, Z = _smooth_2d(8)
    start = dict(sigma_f=1.0, lengthscales=1.0, sigma_eps=0.1)
    gp = SparseGaussianProcess(n_inducing=20, inducing=Z, **start)
    t0, log_bounds = gp.kernel.theta(1, 2)[0], gp.kernel.log_bounds(2)

    def negated(t):
        value, grad, _ = _core.sparse_objective(D_, y, Z, t, "vfe", True)
        return -value, -grad

    plain = minimize(negated, t0, jac=True, method="L-BFGS-B", bounds=log_bounds)
    assert -plain.fun < -500 and plain.x[0] == log_bounds[0][0]  # what the fit must not keep
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)  # the optimum is ill-conditioned
        gp.fit(D_, y)
    assert gp.log_marginal_likelihood_value > 200
    assert gp.theta[0] > log_bounds[0][0] + 1


def test_a_fit_left_in_the_corner_says_so(monkeypatch):
    """If the repeat also ends in the noise-only corner (here: made to repeat the plain run),
    the fit warns instead of returning the corner silently."""
    import gpmhe.gp.fit
    from gpmhe import SparseGaussianProcess

    monkeypatch.setattr(gpmhe.gp.fit, "_short_steps", lambda run, t0, log_bounds: run(t0))
    D_, y, Z = _smooth_2d(8)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        gp = SparseGaussianProcess(n_inducing=20, inducing=Z, sigma_f=1.0, lengthscales=1.0,
                                   sigma_eps=0.1).fit(D_, y)
    messages = [str(w.message) for w in caught if issubclass(w.category, ConvergenceWarning)]
    assert any("explains the data as noise" in m for m in messages), messages
    assert gp.log_marginal_likelihood_value < -500
