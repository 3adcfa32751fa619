"""`GaussianProcess`: one exact GP with the SE-ARD kernel (see the package docs and the user
guide, *Gaussian processes*). The implementation every GP class shares is ``base.py``'s `_GP`,
with the one-output shapes of ``outputs.py``; the docstrings here are the class's own."""


from __future__ import annotations

import os
from typing import Any, Optional, Sequence, Tuple, Union

import numpy as np

from gpmhe.gp.kernel import DEFAULT_BOUNDS
from gpmhe.gp.outputs import _OneOutput

__all__ = ["GaussianProcess"]

class GaussianProcess(_OneOutput):
    """Exact GP regression of one output with the SE-ARD kernel.

    Model, for training inputs d_i (rows of D, n_d columns) and targets y_i::

        y_i = f(d_i) + eps_i,   eps_i ~ N(0, sigma_eps^2),   f ~ GP(m0, k),
        k(d, d') = sigma_f^2 exp(-1/2 (d - d')^T diag(lengthscales)^-2 (d - d')),

    with the prior mean m0 = 0 by default (``mean``). The posterior at a test point d* has mean
    m(d*) = m0(d*) + k*^T (K + sigma_eps^2 I)^-1 (y - m0(D)) and latent (noise-free) variance
    var(d*) = sigma_f^2 - k*^T (K + sigma_eps^2 I)^-1 k*. With an
    optimizer, ``fit`` chooses theta = log([sigma_f, lengthscales..., sigma_eps]) by maximising
    the log marginal likelihood.

    Parameters
    ----------
    sigma_f : float, default 1.0
        Signal standard deviation sigma_f (the initial value when optimised). Must be > 0.
    lengthscales : float or array_like of shape (n_d,), default 1.0
        Length-scales of the input dimensions; a scalar is used for every input dimension.
    sigma_eps : float, default 0.1
        Standard deviation sigma_eps of the noise on the targets y.
    optimizer : {"L-BFGS-B", None}, default "L-BFGS-B"
        "L-BFGS-B" maximises the log marginal likelihood over theta in ``fit`` (SciPy's L-BFGS-B
        with the analytic gradient); None keeps the given hyperparameters.
    n_restarts : int, default 0
        Extra optimiser runs from theta drawn uniformly inside the log-bounds; the run with the
        largest log marginal likelihood is kept.
    bounds : sequence of (low, high) pairs, default ``DEFAULT_BOUNDS``
        Bounds in natural units, either 3 rows (sigma_f, every length-scale, sigma_eps) or
        n_d + 2 rows (sigma_f, one row per length-scale, sigma_eps). The default is
        ((1e-3, 1e3), (1e-3, 1e3), (1e-5, 1e2)).
    random_state : int, numpy.random.Generator or None, default None
        Seed of the random restart points (only used when ``n_restarts`` > 0).
    maxiter : int, default 15000
        Iteration limit of each L-BFGS-B run.
    mean : {"zero", "constant", "linear"}, default "zero"
        Prior mean m(d): zero (the paper's model and scikit-learn's), the targets' mean, or
        b + w·d fitted by least squares; fitted first, then the GP regresses y − m(d) and
        every prediction adds m(d) (and w to the gradients).
    normalize : bool, default False
        Whether ``bounds`` and ``hyperprior`` are in units of the data's spread: length-scales
        relative to each input's standard deviation, sigma_f and sigma_eps relative to that of
        y − m(d). The hyperparameters themselves (initial and fitted) stay in natural units.
    hyperprior : None, "default", "residual" or dict, default None
        Log-normal priors on sigma_f, the length-scales and sigma_eps, added to the log marginal
        likelihood the optimiser maximises (a MAP fit). A dict maps any of ``"sigma_f"``,
        ``"lengthscales"``, ``"sigma_eps"`` to (median, standard deviation of the log);
        "default" is sigma_f ~ (1, 1.5), lengthscales ~ (1, 1.5), sigma_eps ~ (0.1, 1.5);
        "residual" (for the residual of a nominal model: small, smooth) is sigma_f ~ (0.1, 1.5),
        lengthscales ~ (10, 1.5), sigma_eps ~ (1, 1.5); both are meant for ``normalize=True``.
        None: maximum likelihood.

    Attributes
    ----------
    kernel : SEKernel
        The kernel with the current hyperparameters and ``bounds``: the initial values before
        ``fit``, the fitted ones after it.
    sigma_f, lengthscales, sigma_eps : float, float or ndarray of shape (n_d,), float
        Signal standard deviation, length-scales and noise standard deviation: the initial
        values before ``fit``, the fitted ones after it (the length-scales then of shape
        (n_d,)). Setting one on a fitted GP refactors the model at the new value without
        optimising, as for ``theta``.
    theta : ndarray of shape (n_d + 2,)
        log([sigma_f, lengthscales..., sigma_eps]); setting it on a fitted GP refactors the model
        at the new values without optimising.
    D_train : ndarray of shape (N, n_d)
        Training inputs of the last successful ``fit``.
    y_train : ndarray of shape (N,)
        Training targets of the last successful ``fit``.
    jitter : float
        Diagonal jitter the Cholesky factorisation of K + sigma_eps^2 I needed (normally 0).
    log_marginal_likelihood_value : float
        log p(y | D, theta) at the current theta.
    dim : int
        Input dimension n_d of the fitted model.
    bounds : ndarray of shape (3, 2) or (n_d + 2, 2)
        The bounds as given (those of ``kernel``).
    optimizer, n_restarts, random_state, maxiter, mean, normalize, hyperprior
        The settings as given.

    Raises
    ------
    ValueError
        If a hyperparameter is not finite and positive, or a setting is invalid.

    See Also
    --------
    MultiOutputGP : Independent GPs for several outputs on shared inputs.
    LearnedModel : The GP model of the moving horizon estimator.

    Notes
    -----
    The variance returned by ``predict`` and ``predict_with_gradients`` is that of the latent f,
    without sigma_eps^2. If K + sigma_eps^2 I is numerically singular, a small diagonal jitter
    (from 1e-10 (sigma_f^2 + sigma_eps^2), growing tenfold up to 1e-6 (sigma_f^2 + sigma_eps^2))
    is added and recorded in ``jitter``; beyond that `gpmhe.NumericalError` is raised. See the
    user guide, *Gaussian processes*.

    Examples
    --------
    Learn sin(d) from 20 noisy samples and predict at two points:

    >>> import numpy as np
    >>> from gpmhe import GaussianProcess
    >>> rng = np.random.default_rng(0)
    >>> D = np.linspace(0.0, 5.0, 20)[:, None]
    >>> y = np.sin(D[:, 0]) + 0.05 * rng.standard_normal(20)
    >>> gp = GaussianProcess(sigma_f=1.0, lengthscales=1.0, sigma_eps=0.1).fit(D, y)
    >>> mean, std = gp.predict([[1.0], [2.5]], return_std=True)
    >>> print(np.round(mean, 2), np.round(np.sin([1.0, 2.5]), 2))
    [0.86 0.57] [0.84 0.6 ]
    >>> bool(np.all(std < 0.05))
    True
    """

    _kind = "GaussianProcess"

    def __init__(
        self,
        sigma_f: Union[float, np.ndarray] = 1.0,
        lengthscales: Union[float, Sequence[float], np.ndarray] = 1.0,
        sigma_eps: Union[float, np.ndarray] = 0.1,
        optimizer: Optional[str] = 'L-BFGS-B',
        n_restarts: int = 0,
        bounds: Any = DEFAULT_BOUNDS,
        random_state: Union[None, int, np.random.Generator] = None,
        maxiter: int = 15000,
        mean: str = 'zero',
        normalize: bool = False,
        hyperprior: Any = None,
    ) -> None:
        super().__init__(sigma_f=sigma_f, lengthscales=lengthscales, sigma_eps=sigma_eps, optimizer=optimizer, n_restarts=n_restarts, bounds=bounds, random_state=random_state, maxiter=maxiter, mean=mean, normalize=normalize, hyperprior=hyperprior)

    def predict(self, D: Any, return_std: bool = False):
        """Posterior mean, and optionally standard deviation, of the latent f at test points.

        Parameters
        ----------
        D : array_like of shape (k, n_d)
            Test points.
        return_std : bool, default False
            Also return the posterior standard deviation of the latent (noise-free) f.

        Returns
        -------
        mean : ndarray of shape (k,)
            Posterior mean m(d) at each test point.
        std : ndarray of shape (k,)
            Posterior standard deviation of f (without sigma_eps); only returned if
            ``return_std`` is True.

        Raises
        ------
        NotFittedError
            Before ``fit``.
        ValueError
            If D has the wrong shape or contains NaN or inf.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import GaussianProcess
        >>> D = np.linspace(0.0, 5.0, 20)[:, None]
        >>> gp = GaussianProcess(sigma_eps=0.01, optimizer=None).fit(D, np.sin(D[:, 0]))
        >>> print(np.round(gp.predict([[1.0], [2.0]]), 2))
        [0.84 0.91]
        """
        return super().predict(D, return_std)

    def predict_with_gradients(self, D: Any) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Posterior mean and latent variance with their gradients with respect to the input.

        Parameters
        ----------
        D : array_like of shape (k, n_d)
            Test points.

        Returns
        -------
        mean : ndarray of shape (k,)
            Posterior mean m(d).
        var : ndarray of shape (k,)
            Latent (noise-free) posterior variance var(d).
        dmean_dd : ndarray of shape (k, n_d)
            Gradient of the mean with respect to d, one row per point.
        dvar_dd : ndarray of shape (k, n_d)
            Gradient of the variance with respect to d.

        Examples
        --------
        The gradient of a GP fitted to sin approximates cos:

        >>> import numpy as np
        >>> from gpmhe import GaussianProcess
        >>> D = np.linspace(0.0, 5.0, 20)[:, None]
        >>> gp = GaussianProcess(sigma_eps=0.01, optimizer=None).fit(D, np.sin(D[:, 0]))
        >>> mean, var, dmean, dvar = gp.predict_with_gradients([[1.0]])
        >>> print(np.round(dmean, 2), np.round(np.cos(1.0), 2))
        [[0.54]] 0.54
        """
        return super().predict_with_gradients(D)

    def save(self, path: Union[str, os.PathLike]) -> None:
        """Save the fitted model and its settings to an ``.npz`` file (no pickle).

        The training data, theta and the optimiser settings are stored; ``random_state`` is not.

        Parameters
        ----------
        path : str, os.PathLike or file-like object
            Destination, passed to `numpy.savez` (which appends ``.npz`` to a file name without
            it).

        See Also
        --------
        load : Read the file back.

        Examples
        --------
        >>> import io
        >>> import numpy as np
        >>> from gpmhe import GaussianProcess
        >>> D = np.linspace(0.0, 5.0, 20)[:, None]
        >>> gp = GaussianProcess(optimizer=None).fit(D, np.sin(D[:, 0]))
        >>> buf = io.BytesIO()
        >>> gp.save(buf)
        >>> _ = buf.seek(0)
        >>> bool(np.array_equal(GaussianProcess.load(buf).predict(D), gp.predict(D)))
        True
        """
        return super().save(path)

    @classmethod
    def load(cls, path: Union[str, os.PathLike]) -> "GaussianProcess":
        """Load a model written by ``save``.

        Parameters
        ----------
        path : str, os.PathLike or file-like object
            The ``.npz`` file.

        Returns
        -------
        GaussianProcess
            The fitted model, with the saved settings (``random_state`` None).

        Raises
        ------
        ValueError
            If the file is not a saved `GaussianProcess` or was written by a newer gpmhe.

        Examples
        --------
        >>> import io
        >>> import numpy as np
        >>> from gpmhe import GaussianProcess
        >>> D = np.linspace(0.0, 5.0, 20)[:, None]
        >>> buf = io.BytesIO()
        >>> GaussianProcess(sigma_f=2.0, optimizer=None).fit(D, np.sin(D[:, 0])).save(buf)
        >>> _ = buf.seek(0)
        >>> GaussianProcess.load(buf)
        GaussianProcess(sigma_f=2, lengthscales=[1.], sigma_eps=0.1, fitted)
        """
        return super().load(path)

    # -- fitting -----------------------------------------------------------------------------

    def fit(self, D: Any, y: Any) -> "GaussianProcess":
        """Fit the GP to training data, optimising the hyperparameters if an optimizer is set.

        Parameters
        ----------
        D : array_like of shape (N, n_d)
            Training inputs, N >= 2 finite rows.
        y : array_like of shape (N,)
            Training targets.

        Returns
        -------
        GaussianProcess
            ``self``, fitted.

        Raises
        ------
        ValueError
            If D or y have the wrong shape or contain NaN or inf.
        gpmhe.NumericalError
            If no optimiser run reached a finite log marginal likelihood, or the kernel matrix
            cannot be factored even with jitter.

        Warns
        -----
        ConvergenceWarning
            If the best optimiser run stopped without converging.

        Notes
        -----
        A failed fit leaves the model unchanged.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import GaussianProcess
        >>> D = np.linspace(0.0, 5.0, 20)[:, None]
        >>> gp = GaussianProcess(optimizer=None).fit(D, np.sin(D[:, 0]))
        >>> gp.D_train.shape, gp.dim
        ((20, 1), 1)
        """
        return self._fit(D, y, 1)

    def log_marginal_likelihood(
        self, theta: Any = None, eval_gradient: bool = False
    ) -> Union[float, Tuple[float, np.ndarray]]:
        """Log marginal likelihood log p(y | D, theta) of the training data.

        Parameters
        ----------
        theta : array_like of shape (n_d + 2,) or None, default None
            Log-hyperparameters at which to evaluate it; None uses the current ``theta``.
        eval_gradient : bool, default False
            Also return the gradient with respect to theta.

        Returns
        -------
        lml : float
            The log marginal likelihood.
        grad : ndarray of shape (n_d + 2,)
            Its gradient with respect to theta; only returned if ``eval_gradient`` is True.

        Examples
        --------
        At the optimum found by ``fit`` the gradient vanishes:

        >>> import numpy as np
        >>> from gpmhe import GaussianProcess
        >>> rng = np.random.default_rng(0)
        >>> D = np.linspace(0.0, 5.0, 20)[:, None]
        >>> y = np.sin(D[:, 0]) + 0.05 * rng.standard_normal(20)
        >>> gp = GaussianProcess(sigma_eps=0.1).fit(D, y)
        >>> lml, grad = gp.log_marginal_likelihood(eval_gradient=True)
        >>> bool(np.max(np.abs(grad)) < 1e-3), bool(lml > gp.log_marginal_likelihood([0, 0, -1]))
        (True, True)
        """
        return self._lml_result(theta, eval_gradient)

    def __repr__(self) -> str:
        state = "fitted" if self._fitted is not None else "not fitted"
        return (
            f"GaussianProcess(sigma_f={self.sigma_f:.4g}, lengthscales={np.round(self.lengthscales, 4)}, "
            f"sigma_eps={self.sigma_eps:.4g}, {state})"
        )
