"""`EXACT`, the exact GP as one of the approximations a GP class delegates to (the other is
``inducing.py``'s `Sparse`): its core model (`gpmhe._core.MultiGP`), its training objective (the
log marginal likelihood), its fit, and its leave-one-out errors.

An approximation has the methods ``fit``, ``rebuild``, ``objective``, ``loo``, ``save_entries``
and ``load_model``; the GP classes (``base.py``) hold the data, the kernel and the settings, and
leave building, refactoring and scoring the core model to them."""

from __future__ import annotations

from typing import Any, Callable, Optional, Tuple

import numpy as np

from gpmhe import _core
from gpmhe.gp.diagnostics import exact_loo
from gpmhe.gp.fit import Fitting, _maximise, _posterior

__all__: list = []


def _lml(D: np.ndarray, y: np.ndarray) -> Callable[[np.ndarray], Tuple[float, np.ndarray]]:
    """The log marginal likelihood of one output and its gradient as a function of theta.

    D and y must be validated (``training_set``): they are handed to the core as they are.
    """

    def lml(theta: np.ndarray) -> Tuple[float, np.ndarray]:
        value, grad = _core.log_marginal_likelihood(D, y, np.ascontiguousarray(theta), True)
        return float(value), np.asarray(grad)

    return lml


class _Exact:
    """Exact GP regression: O(N³) per fit evaluation, O(N²) per prediction."""

    #: Whether the models have inducing points.
    sparse = False

    def fit(self, D: np.ndarray, R: np.ndarray, coef: Any, theta0: np.ndarray,
            fitting: Optional[Fitting]) -> Tuple["_core.MultiGP", Any]:
        """(model, the fit's record or None): each output's log marginal likelihood plus
        log-prior maximised from theta0 (q, n_d + 2), or theta0 kept without ``fitting``."""
        if fitting is None:
            return _core.MultiGP(D, R, np.ascontiguousarray(theta0), coef), None
        rows, runs = [], []
        for o in range(R.shape[1]):
            shift = fitting.shift[o]
            objective = _posterior(_lml(D, np.ascontiguousarray(R[:, o])), shift, fitting.prior)
            t, _, values = _maximise(objective, theta0[o] - shift, fitting.log_bounds, fitting.n_restarts,
                                     fitting.rng, fitting.maxiter)
            rows.append(t + shift)
            runs.append(values)
        return _core.MultiGP(D, R, np.ascontiguousarray(rows), coef), fitting.record(runs)

    def rebuild(self, model: "_core.MultiGP", D: np.ndarray, R: np.ndarray, theta: np.ndarray) -> "_core.MultiGP":
        """The fitted model factored again at a new theta."""
        return _core.MultiGP(D, R, theta, model.mean)

    def objective(self, model: "_core.MultiGP", D: np.ndarray, R: np.ndarray, theta: Optional[np.ndarray],
                  eval_gradient: bool) -> Tuple[np.ndarray, Optional[np.ndarray]]:
        """(log marginal likelihood (q,), gradient (q, n_d + 2) or None) at theta (None: the
        model's)."""
        if theta is None:
            return model.log_marginal_likelihoods(), (model.log_marginal_likelihood_gradients() if eval_gradient else None)
        res = [_core.log_marginal_likelihood(D, np.ascontiguousarray(R[:, o]), np.ascontiguousarray(theta[o]),
                                             eval_gradient) for o in range(model.n_outputs)]
        return np.array([r[0] for r in res]), np.array([r[1] for r in res])

    def loo(self, model: "_core.MultiGP", D: np.ndarray) -> Callable:
        """``loo(o, r)`` of `gpmhe.gp.diagnostics.diagnose`: closed form, one O(N³)
        factorisation per output."""
        return exact_loo(D, model.thetas, model.jitters)

    def save_entries(self, model: "_core.MultiGP") -> dict:
        """The file entries of the model beyond data, theta and prior mean: none."""
        return {}

    def load_model(self, D: np.ndarray, R: np.ndarray, theta: np.ndarray, coef: Any, inducing: Any) -> "_core.MultiGP":
        """The model of a saved file's entries."""
        return _core.MultiGP(D, R, theta, coef)


#: The exact approximation (stateless: one instance serves every exact GP).
EXACT = _Exact()
