"""What differs between GPs of one output (`GaussianProcess`, `SparseGaussianProcess`) and of
several (`MultiOutputGP`, `SparseMultiOutputGP`): the shapes of the hyperparameters, of theta,
of the jitter and of the training objective. Everything else is ``base.py``'s `_GP`."""

from __future__ import annotations

from typing import Any, Union

import numpy as np

from gpmhe._validation import float_array
from gpmhe.gp.base import _GP
from gpmhe.gp.kernel import SEKernel, one_output

__all__: list = []


def _scalar(a: np.ndarray) -> float:
    return float(a.reshape(-1)[0])


class _OneOutput(_GP):
    """A GP of one output: sigma_f and sigma_eps are numbers, theta is (n_d + 2,), results drop
    the output axis."""

    _target = "y"
    _squeeze = True

    def _make_kernel(self, sigma_f: Any, lengthscales: Any, sigma_eps: Any, bounds: Any) -> SEKernel:
        return one_output(sigma_f, lengthscales, sigma_eps, bounds)

    @property
    def sigma_f(self) -> float:
        """Signal standard deviation: the initial value before ``fit``, the fitted one after.

        Setting it on a fitted GP factors the model again at the new value (no optimisation).
        """
        return _scalar(self.kernel.sigma_f)

    @sigma_f.setter
    def sigma_f(self, value: Any) -> None:
        self._set_kernel(sigma_f=value)

    @property
    def lengthscales(self) -> Union[float, np.ndarray]:
        """Length-scales (a number for all inputs, or shape (n_d,)); as ``sigma_f``."""
        ls = self.kernel.lengthscales
        return float(ls) if ls.ndim == 0 else ls.reshape(-1)

    @lengthscales.setter
    def lengthscales(self, value: Any) -> None:
        self._set_kernel(lengthscales=value)

    @property
    def sigma_eps(self) -> float:
        """Noise standard deviation; as ``sigma_f``."""
        return _scalar(self.kernel.sigma_eps)

    @sigma_eps.setter
    def sigma_eps(self, value: Any) -> None:
        self._set_kernel(sigma_eps=value)

    @property
    def theta(self) -> np.ndarray:
        """Log-hyperparameters log([sigma_f, lengthscales..., sigma_eps]), shape (n_d + 2,).

        Setting it on a fitted GP refactors the model at the new values (no optimisation); on an
        unfitted GP it sets the initial values ``sigma_f``, ``lengthscales`` and ``sigma_eps``.
        """
        fit = self._fitted
        if fit is not None:
            return fit.model.thetas[0]
        return self._kernel.theta(1, np.size(self._kernel.lengthscales))[0]

    @theta.setter
    def theta(self, value: Any) -> None:
        if self._fitted is not None:
            self._refactor(value)
            return
        theta = float_array("theta", value, 1)
        if theta.size < 3:
            raise ValueError(f"theta: needs n_d + 2 >= 3 values, got {theta.size}")
        self._kernel = self._kernel.with_theta(theta)

    @property
    def y_train(self) -> np.ndarray:
        """Training targets, shape (N,).

        Those of the last successful ``fit``; raises `NotFittedError` before it.
        """
        return self._out(self._fit_state().Y).copy()

    @property
    def jitter(self) -> float:
        """Diagonal jitter added to the kernel matrix to factor it (K + sigma_eps^2 I for an
        exact GP, K(Z, Z) for a sparse one).

        Normally 0; positive when the matrix was numerically singular.
        """
        return float(self._model().jitters[0])

    @property
    def log_marginal_likelihood_value(self) -> float:
        """The training objective at the current theta: the log marginal likelihood
        log p(y | D, theta) of an exact GP, the VFE bound or FITC's log marginal likelihood of a
        sparse one.

        Equal to ``log_marginal_likelihood()``; raises `NotFittedError` before ``fit``.
        """
        return float(self._model().log_marginal_likelihoods()[0])

    def _lml_result(self, theta: Any, eval_gradient: bool) -> Any:
        lml, grad = self._log_marginal_likelihood(theta, eval_gradient)
        return (float(lml[0]), grad[0]) if eval_gradient else float(lml[0])


class _ManyOutputs(_GP):
    """GPs of q outputs on shared inputs: each output has its own hyperparameters."""

    _target = "Y"
    _squeeze = False

    @property
    def sigma_f(self) -> np.ndarray:
        """Signal standard deviations: as given before ``fit`` (a scalar serves every output),
        shape (q,) after it.

        Setting it on a fitted GP factors the model again at the new values (no optimisation).
        """
        return self.kernel.sigma_f

    @sigma_f.setter
    def sigma_f(self, value: Any) -> None:
        self._set_kernel(sigma_f=value)

    @property
    def lengthscales(self) -> np.ndarray:
        """Length-scales: as given before ``fit``, shape (q, n_d) after it; as ``sigma_f``."""
        return self.kernel.lengthscales

    @lengthscales.setter
    def lengthscales(self, value: Any) -> None:
        self._set_kernel(lengthscales=value)

    @property
    def sigma_eps(self) -> np.ndarray:
        """Noise standard deviations: as given before ``fit``, shape (q,) after it; as
        ``sigma_f``."""
        return self.kernel.sigma_eps

    @sigma_eps.setter
    def sigma_eps(self, value: Any) -> None:
        self._set_kernel(sigma_eps=value)

    @property
    def n_outputs(self) -> int:
        """Number of outputs q.

        The number of columns of the training targets; raises `NotFittedError` before ``fit``.
        """
        return self._model().n_outputs

    @property
    def theta(self) -> np.ndarray:
        """Log-hyperparameters, shape (q, n_d + 2), one row per output.

        Each row is log([sigma_f, lengthscales..., sigma_eps]). Setting it refactors the fitted
        model at the new values without optimising.
        """
        return self._model().thetas

    @theta.setter
    def theta(self, value: Any) -> None:
        self._refactor(value)

    @property
    def y_train(self) -> np.ndarray:
        """Training targets, shape (N, q); raises `NotFittedError` before ``fit``."""
        return self._fit_state().Y.copy()

    @property
    def jitter(self) -> np.ndarray:
        """Diagonal jitter of each output's kernel factorisation, shape (q,).

        Normally 0; positive where a kernel matrix was numerically singular.
        """
        return self._model().jitters

    def _fit_targets(self, D: Any, Y: Any) -> "_ManyOutputs":
        """``fit(D, Y)`` with Y of shape (N, q) or (N,) (one output)."""
        try:
            y_ndim = 1 if np.ndim(Y) == 1 else 2
        except ValueError:  # (a ragged list: training_set names it)
            y_ndim = 2
        return self._fit(D, Y, y_ndim)

    def _lml_result(self, theta: Any, eval_gradient: bool) -> Any:
        lml, grad = self._log_marginal_likelihood(theta, eval_gradient)
        return (lml, grad) if eval_gradient else lml
