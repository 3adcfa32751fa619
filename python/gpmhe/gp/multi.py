"""`MultiOutputGP`: independent SE-ARD GPs, one per output column, on shared inputs, predicted in
one Rust call (the form `LearnedModel` uses for f and h). The implementation it shares with
every GP class is ``base.py``'s `_GP`, with the several-output shapes of ``outputs.py``; the
docstrings here are the class's own."""


from __future__ import annotations

import os
from typing import Any, Optional, Sequence, Tuple, Union

import numpy as np

from gpmhe.gp.kernel import DEFAULT_BOUNDS
from gpmhe.gp.outputs import _ManyOutputs

__all__ = ["MultiOutputGP"]

class MultiOutputGP(_ManyOutputs):
    """Independent SE-ARD GPs, one per output column, on shared inputs.

    Each output o = 1..q is a `GaussianProcess` model of its own (Y[:, o] = f_o(D) + eps_o,
    f_o ~ GP(0, k_o)) with its own hyperparameters sigma_f[o], lengthscales[o, :],
    sigma_eps[o]. The outputs are fitted one after the other with the same optimiser settings
    and predicted in one Rust call. This is the form `LearnedModel` uses for f and h.

    Parameters
    ----------
    sigma_f : float or array_like of shape (q,), default 1.0
        Initial signal standard deviations (a scalar is used for every output).
    lengthscales : float or array_like of shape (n_d,) or (q, n_d), default 1.0
        Initial length-scales, broadcast over outputs and input dimensions.
    sigma_eps : float or array_like of shape (q,), default 0.1
        Initial noise standard deviations.
    optimizer : {"L-BFGS-B", None}, default "L-BFGS-B"
        As for `GaussianProcess`; None keeps the given hyperparameters.
    n_restarts : int, default 0
        Extra random optimiser starts per output.
    bounds : sequence of (low, high) pairs, default ``DEFAULT_BOUNDS``
        As for `GaussianProcess`; the same bounds serve every output.
    random_state : int, numpy.random.Generator or None, default None
        Seed of the restart points (one generator shared by all outputs).
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
        The kernel with the current hyperparameters and ``bounds`` (the fitted ones after
        ``fit``).
    sigma_f, lengthscales, sigma_eps : ndarray of shapes (q,), (q, n_d), (q,)
        Signal standard deviations, length-scales and noise standard deviations (the fitted
        ones after ``fit``). Setting one on a fitted model refactors it at the new values without
        optimising, as for ``theta``.
    theta : ndarray of shape (q, n_d + 2)
        One row log([sigma_f, lengthscales..., sigma_eps]) per output; settable on a fitted
        model.
    n_outputs : int
        Number of outputs q.
    dim : int
        Input dimension n_d.
    D_train : ndarray of shape (N, n_d)
        Training inputs.
    y_train : ndarray of shape (N, q)
        Training targets.
    jitter : ndarray of shape (q,)
        Diagonal jitter each output's factorisation needed (normally 0).
    bounds : ndarray of shape (3, 2) or (n_d + 2, 2)
        The bounds as given (those of ``kernel``).
    optimizer, n_restarts, random_state, maxiter, mean, normalize, hyperprior
        The settings as given.

    See Also
    --------
    GaussianProcess : One output, and the model's equations.
    LearnedModel.from_trajectories : Fits the f- and h-GPs of an estimator.

    Examples
    --------
    Two outputs, sin and cos of one input:

    >>> import numpy as np
    >>> from gpmhe import MultiOutputGP
    >>> D = np.linspace(0.0, 5.0, 20)[:, None]
    >>> Y = np.column_stack([np.sin(D[:, 0]), np.cos(D[:, 0])])
    >>> gp = MultiOutputGP(sigma_eps=0.01).fit(D, Y)
    >>> gp
    MultiOutputGP(q=2, n_d=1, N=20, fitted)
    >>> gp.theta.shape
    (2, 3)
    >>> print(np.round(gp.predict([[1.0]]), 2), np.round([np.sin(1.0), np.cos(1.0)], 2))
    [[0.84 0.54]] [0.84 0.54]
    """

    _kind = "MultiOutputGP"

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
        """Posterior means, and optionally latent standard deviations, of all outputs.

        Parameters
        ----------
        D : array_like of shape (k, n_d)
            Test points.
        return_std : bool, default False
            Also return the posterior standard deviations of the latent (noise-free) outputs.

        Returns
        -------
        mean : ndarray of shape (k, q)
            Posterior means, one column per output.
        std : ndarray of shape (k, q)
            Latent posterior standard deviations; only returned if ``return_std`` is True.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import MultiOutputGP
        >>> D = np.linspace(0.0, 5.0, 20)[:, None]
        >>> gp = MultiOutputGP(sigma_eps=0.01, optimizer=None).fit(D, np.column_stack([D, -D]))
        >>> mean, std = gp.predict([[1.0], [2.0]], return_std=True)
        >>> print(np.round(mean, 2))
        [[ 1. -1.]
         [ 2. -2.]]
        >>> std.shape
        (2, 2)
        """
        return super().predict(D, return_std)

    def predict_with_gradients(self, D: Any) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Posterior means and latent variances of all outputs with their input gradients.

        Parameters
        ----------
        D : array_like of shape (k, n_d)
            Test points.

        Returns
        -------
        mean : ndarray of shape (k, q)
            Posterior means.
        var : ndarray of shape (k, q)
            Latent (noise-free) posterior variances.
        dmean_dd : ndarray of shape (k, q, n_d)
            Gradients of the means with respect to d: [i, o, :] belongs to point i, output o.
        dvar_dd : ndarray of shape (k, q, n_d)
            Gradients of the variances with respect to d.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import MultiOutputGP
        >>> D = np.random.default_rng(1).uniform(-1.0, 1.0, size=(40, 2))
        >>> Y = np.column_stack([np.sin(D[:, 0]), D[:, 0] * D[:, 1]])
        >>> gp = MultiOutputGP(sigma_eps=0.01).fit(D, Y)
        >>> mean, var, dmean, dvar = gp.predict_with_gradients([[0.5, 0.2]])
        >>> dmean.shape
        (1, 2, 2)
        >>> print(round(float(dmean[0, 0, 0]), 2), round(float(np.cos(0.5)), 2))  # d sin(d1)/d d1
        0.88 0.88
        >>> print(np.round(dmean[0, 1], 2))  # gradient of d1 d2 at (0.5, 0.2)
        [0.2 0.5]
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
        >>> from gpmhe import MultiOutputGP
        >>> D = np.linspace(0.0, 5.0, 20)[:, None]
        >>> gp = MultiOutputGP(optimizer=None).fit(D, np.column_stack([D, D ** 2]))
        >>> buf = io.BytesIO()
        >>> gp.save(buf)
        >>> _ = buf.seek(0)
        >>> bool(np.array_equal(MultiOutputGP.load(buf).predict(D), gp.predict(D)))
        True
        """
        return super().save(path)

    @classmethod
    def load(cls, path: Union[str, os.PathLike]) -> "MultiOutputGP":
        """Load a model written by ``save``.

        Parameters
        ----------
        path : str, os.PathLike or file-like object
            The ``.npz`` file.

        Returns
        -------
        MultiOutputGP
            The fitted model, with the saved settings (``random_state`` None).

        Raises
        ------
        ValueError
            If the file is not a saved `MultiOutputGP` or was written by a newer gpmhe.

        Examples
        --------
        >>> import io
        >>> import numpy as np
        >>> from gpmhe import MultiOutputGP
        >>> D = np.linspace(0.0, 5.0, 20)[:, None]
        >>> buf = io.BytesIO()
        >>> MultiOutputGP(optimizer=None).fit(D, np.column_stack([D, D ** 2])).save(buf)
        >>> _ = buf.seek(0)
        >>> MultiOutputGP.load(buf)
        MultiOutputGP(q=2, n_d=1, N=20, fitted)
        """
        return super().load(path)

    def fit(self, D: Any, Y: Any) -> "MultiOutputGP":
        """Fit one GP per output column, optimising each output's hyperparameters if set.

        Parameters
        ----------
        D : array_like of shape (N, n_d)
            Training inputs, N >= 2 finite rows.
        Y : array_like of shape (N, q) or (N,)
            Training targets, one column per output (a 1-D Y is one output).

        Returns
        -------
        MultiOutputGP
            ``self``, fitted.

        Raises
        ------
        ValueError
            If D or Y have the wrong shape or contain NaN or inf.
        gpmhe.NumericalError
            If an output's fit failed numerically (see `GaussianProcess.fit`).

        Warns
        -----
        ConvergenceWarning
            If the optimiser did not converge for some output.

        Notes
        -----
        A failed fit leaves the model unchanged.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import MultiOutputGP
        >>> D = np.random.default_rng(0).uniform(size=(10, 3))
        >>> gp = MultiOutputGP(optimizer=None).fit(D, D[:, :2] ** 2)
        >>> gp.n_outputs, gp.dim, gp.lengthscales.shape
        (2, 3, (2, 3))
        """
        return self._fit_targets(D, Y)

    def log_marginal_likelihood(self, theta: Any = None, eval_gradient: bool = False):
        """Log marginal likelihood of each output's training data.

        Parameters
        ----------
        theta : array_like of shape (q, n_d + 2) or None, default None
            Log-hyperparameters, one row per output; None uses the current ``theta``.
        eval_gradient : bool, default False
            Also return the gradients with respect to theta.

        Returns
        -------
        lml : ndarray of shape (q,)
            The log marginal likelihood of each output.
        grad : ndarray of shape (q, n_d + 2)
            Their gradients; only returned if ``eval_gradient`` is True.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import MultiOutputGP
        >>> D = np.linspace(0.0, 5.0, 20)[:, None]
        >>> gp = MultiOutputGP().fit(D, np.column_stack([np.sin(D[:, 0]), np.cos(D[:, 0])]))
        >>> lml, grad = gp.log_marginal_likelihood(eval_gradient=True)
        >>> lml.shape, grad.shape
        ((2,), (2, 3))
        """
        return self._lml_result(theta, eval_gradient)

    def __repr__(self) -> str:
        fit = self._fitted
        if fit is None:
            return "MultiOutputGP(not fitted)"
        return f"MultiOutputGP(q={self.n_outputs}, n_d={self.dim}, N={fit.D.shape[0]}, fitted)"
