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
