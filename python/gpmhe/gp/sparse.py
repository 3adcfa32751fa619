"""Sparse (inducing-point) GP regression with the SE-ARD kernel, for thousands of training points.

``SparseGaussianProcess`` and ``SparseMultiOutputGP`` are the sparse counterparts of
`gpmhe.GaussianProcess` and `gpmhe.MultiOutputGP`: they take the same arguments, have the same
attributes and methods, and work wherever those do in `gpmhe.LearnedModel`, `gpmhe.GPMHE` and
the GP-EKF. They share the exact GPs' implementation (``base.py``'s `_GP`) and hand the fit and
the model to the inducing-point approximation (``inducing.py``'s `Sparse`); they are not
subclasses of the exact classes. Each output is summarised by m inducing
inputs Z, chosen from the training inputs by greedy conditional-variance selection (or given),
with the variational (VFE, Titsias 2009) or FITC approximation; the numerics are the Rust core's
(``gpmhe._core.SparseMultiGP``). The user guide page *Gaussian processes* (section *Sparse GPs*)
gives the formulas, the choice between VFE and FITC, the jitter policy and the costs.

With Kuu = K(Z, Z), Kuf = K(Z, X), Qff = Kfu Kuu^-1 Kuf and Lambda = sigma_eps^2 I (VFE) or
diag(Kff - Qff) + sigma_eps^2 I (FITC), a fit maximises over theta (and optionally Z)::

    F = log N(y | 0, Qff + Lambda) - [VFE] tr(Kff - Qff) / (2 sigma_eps^2),

and with P = Kuu + Kuf Lambda^-1 Kfu the prediction at d* is
mean k*^T P^-1 Kuf Lambda^-1 y, latent variance sigma_f^2 - k*^T (Kuu^-1 - P^-1) k*.
"""

from __future__ import annotations

import os
from typing import Any, List, Optional, Tuple, Union

import numpy as np

from gpmhe.gp.inducing import Sparse, read_settings
from gpmhe.gp.kernel import DEFAULT_BOUNDS
from gpmhe.gp.outputs import _ManyOutputs, _OneOutput

__all__ = ["SparseGaussianProcess", "SparseMultiOutputGP"]


class _Inducing:
    """The sparse classes' own settings (placed before `_OneOutput` or `_ManyOutputs` in their
    bases): the constructor's extra arguments, the approximation a fit hands the work to, the
    file entries and the inducing points."""

    def __init__(self, n_inducing: int, method: str, inducing: Any, optimize_inducing: bool, **settings: Any) -> None:
        approx = Sparse(n_inducing, method, inducing, optimize_inducing, self._squeeze)
        super().__init__(**settings)
        self.n_inducing, self.method = approx.n_inducing, approx.method
        self.inducing, self.optimize_inducing = approx.inducing, approx.optimize_inducing

    def _approximation(self) -> Sparse:
        # Built from the settings as they are now (validated again: they are plain attributes).
        return Sparse(self.n_inducing, self.method, self.inducing, self.optimize_inducing, self._squeeze)

    @classmethod
    def _read_extra(cls, f: Any, nd: int, q: int) -> tuple:
        return read_settings(f, nd, q, cls._squeeze)

    @property
    def inducing_points(self) -> Union[np.ndarray, List[np.ndarray]]:
        """Inducing inputs of the fitted model.

        An (m, n_d) array for `SparseGaussianProcess`; for `SparseMultiOutputGP` a list with one
        (m_o, n_d) array per output (each output has its own, chosen under its own kernel). m can
        be smaller than ``n_inducing``: see the user guide, *Sparse GPs*.
        """
        zs = self._model().inducing
        return zs[0] if self._squeeze else zs



class SparseGaussianProcess(_Inducing, _OneOutput):
    """Sparse GP regression of one output with the SE-ARD kernel and m inducing points.

    The model of `GaussianProcess` (y_i = f(d_i) + eps_i, f ~ GP(m0, k)), approximated through the
    values of f at m inducing inputs Z: fitting costs O(N m^2) per objective evaluation and
    O(N + m^2) memory instead of O(N^3) and O(N^2), and a prediction O(m^2) per point instead of
    O(N^2). With Kuu = K(Z, Z), Kuf = K(Z, D), Qff = Kfu Kuu^-1 Kuf and the diagonal noise
    Lambda = sigma_eps^2 I (VFE) or diag(Kff - Qff) + sigma_eps^2 I (FITC), ``fit`` maximises::

        F = log N(y | 0, Qff + Lambda) - [VFE only] tr(Kff - Qff) / (2 sigma_eps^2)

    and with P = Kuu + Kuf Lambda^-1 Kfu the posterior at d* has mean
    k*^T P^-1 Kuf Lambda^-1 y and latent variance sigma_f^2 - k*^T (Kuu^-1 - P^-1) k*, which
    returns to sigma_f^2 far from the inducing points (it does not collapse to 0 as DTC's
    does); with a prior mean m0 (``mean``), y stands for y - m0(D) and the mean adds m0(d*).
    With Z equal to the training inputs both methods reproduce `GaussianProcess`.

    It has every attribute and method of `GaussianProcess` and works wherever the exact GP does
    in `LearnedModel`, `GPMHE` and the GP-EKF (it is not a subclass of it: test for a sparse GP
    with ``isinstance(gp, SparseGaussianProcess)``).

    Parameters
    ----------
    n_inducing : int, default 100
        Number of inducing points m to choose from the training inputs (at most N; fewer when the
        remaining inputs are determined by the chosen ones, e.g. duplicated inputs).
    method : {"vfe", "fitc"}, default "vfe"
        The approximation: VFE (Titsias' variational bound, GPflow's SGPR) or FITC (GPflow's
        GPRFITC). VFE is the default: its objective is a lower bound on the exact log marginal
        likelihood, so more inducing points never make it worse, and it does not underestimate the
        noise as FITC can.
    inducing : array_like of shape (m, n_d) or None, default None
        Fixed inducing inputs instead of choosing them.
    optimize_inducing : bool, default False
        Also optimise the inducing inputs jointly with theta (m n_d more parameters, within the
        bounding box of the training inputs) after the hyperparameter fit.
    sigma_f, lengthscales, sigma_eps, optimizer, n_restarts, bounds, random_state, maxiter
        As for `GaussianProcess`: initial hyperparameters (kept with ``optimizer=None``) and the
        settings of the L-BFGS-B fit of the training objective.
    mean, normalize, hyperprior
        As for `GaussianProcess`: the prior mean fitted by least squares first (the sparse GP
        regresses y − m(d)), the data-relative units of ``bounds`` and ``hyperprior``, and the
        log-normal hyperparameter priors added to the training objective.

    Attributes
    ----------
    kernel : SEKernel
        The kernel with the current hyperparameters and ``bounds`` (the fitted ones after ``fit``).
    inducing_points : ndarray of shape (m, n_d)
        The fitted inducing inputs.
    sigma_f, lengthscales, sigma_eps, theta, D_train, y_train, dim, jitter
        As for `GaussianProcess` (``jitter``: the diagonal jitter added to K(Z, Z) to factor it,
        normally 0).
    log_marginal_likelihood_value : float
        The training objective at the current theta (the VFE bound or FITC's log marginal
        likelihood).
    n_inducing, method, inducing, optimize_inducing, optimizer, n_restarts, bounds, random_state, maxiter, mean, normalize, hyperprior
        The settings as given.

    Raises
    ------
    ValueError
        If a hyperparameter is not finite and positive, or a setting is invalid.

    See Also
    --------
    GaussianProcess : The exact GP.
    SparseMultiOutputGP : Independent sparse GPs for several outputs.

    Notes
    -----
    See the user guide, *Gaussian processes*, section *Sparse GPs*, for the choice of method and
    of m, the inducing-point selection, the jitter policy and the costs.

    Examples
    --------
    2,000 noisy samples of sin, 10 inducing points:

    >>> import numpy as np
    >>> from gpmhe import SparseGaussianProcess
    >>> rng = np.random.default_rng(0)
    >>> D = rng.uniform(0.0, 10.0, (2000, 1))
    >>> y = np.sin(D[:, 0]) + 0.1 * rng.standard_normal(2000)
    >>> gp = SparseGaussianProcess(n_inducing=10).fit(D, y)
    >>> gp
    SparseGaussianProcess(method='vfe', m=10, N=2000, fitted)
    >>> mean = gp.predict([[1.0], [2.5]])
    >>> print(np.round(mean, 2), np.round(np.sin([1.0, 2.5]), 2))
    [0.84 0.6 ] [0.84 0.6 ]
    >>> round(gp.sigma_eps, 2)
    0.1
    """

    def __init__(
        self,
        n_inducing: int = 100,
        method: str = 'vfe',
        inducing: Any = None,
        optimize_inducing: bool = False,
        sigma_f: Union[float, np.ndarray] = 1.0,
        lengthscales: Any = 1.0,
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
        super().__init__(n_inducing=n_inducing, method=method, inducing=inducing, optimize_inducing=optimize_inducing, sigma_f=sigma_f, lengthscales=lengthscales, sigma_eps=sigma_eps, optimizer=optimizer, n_restarts=n_restarts, bounds=bounds, random_state=random_state, maxiter=maxiter, mean=mean, normalize=normalize, hyperprior=hyperprior)

    def fit(self, D: Any, y: Any) -> "SparseGaussianProcess":
        """Fit the sparse GP to training data: choose the inducing points and the hyperparameters.

        Without given ``inducing`` points, ``n_inducing`` training inputs are chosen by greedy
        conditional-variance selection under the initial kernel; with an optimizer the training
        objective is maximised over theta, the points are chosen again under the fitted kernel, and theta
        is refined. With ``optimize_inducing`` the inducing inputs are then optimised jointly with theta.

        Parameters
        ----------
        D : array_like of shape (N, n_d)
            Training inputs, N >= 2 finite rows.
        y : array_like of shape (N,)
            Training targets.

        Returns
        -------
        SparseGaussianProcess
            ``self``, fitted.

        Raises
        ------
        ValueError
            If D or the targets have the wrong shape or contain NaN or inf, or the given inducing points
            do not match n_d.
        gpmhe.NumericalError
            If no optimiser run reached a finite objective, or K(Z, Z) cannot be factored even with
            jitter.

        Warns
        -----
        ConvergenceWarning
            If an optimiser run stopped without converging.

        Notes
        -----
        A failed fit leaves the model unchanged.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import SparseGaussianProcess
        >>> rng = np.random.default_rng(0)
        >>> D = np.linspace(0.0, 10.0, 500)[:, None]
        >>> gp = SparseGaussianProcess(n_inducing=5).fit(D, np.sin(D[:, 0]) + 0.1 * rng.standard_normal(500))
        >>> gp.inducing_points.shape
        (5, 1)
        """
        return self._fit(D, y, 1)

    def diagnostics(self) -> list:
        """Diagnostics of the fit, one `gpmhe.FitDiagnostics` per output.

        As for the exact GP: the fitted hyperparameters, which of them sit at a bound, every optimiser
        run's objective, and leave-one-out errors against the noise level and against a straight line.
        The LOO errors are those of the sparse model itself (the Gaussian model with covariance
        Qff + Lambda), in closed form in O(N m^2) per output, computed once per fit.

        Returns
        -------
        list of FitDiagnostics
            One per output (one for `SparseGaussianProcess`).

        Raises
        ------
        NotFittedError
            Before ``fit``.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import SparseGaussianProcess
        >>> D = np.linspace(0.0, 10.0, 500)[:, None]
        >>> gp = SparseGaussianProcess(n_inducing=20, mean="linear").fit(D, np.sin(D[:, 0]) + 0.5 * D[:, 0])
        >>> [d.collapsed for d in gp.diagnostics()]
        [False]
        """
        return super().diagnostics()

    def log_marginal_likelihood(self, theta: Any = None, eval_gradient: bool = False) -> Union[float, Tuple[float, np.ndarray]]:
        """The training objective: the VFE bound or FITC's log marginal likelihood.

        For ``method="vfe"`` this is Titsias' collapsed lower bound on log p(y | D, theta); for
        ``method="fitc"`` the log marginal likelihood of the FITC model. Both are evaluated with the
        fitted inducing points.

        Parameters
        ----------
        theta : array_like of shape (n_d + 2,) or None, default None
            Log-hyperparameters at which to evaluate it; None uses the current ``theta``.
        eval_gradient : bool, default False
            Also return the gradient with respect to theta.

        Returns
        -------
        objective : float
            The training objective.
        grad : ndarray of shape (n_d + 2,)
            Its gradient with respect to theta; only returned if ``eval_gradient`` is True.

        Examples
        --------
        With the inducing points at the training inputs, VFE's bound is the exact GP's log marginal
        likelihood:

        >>> import numpy as np
        >>> from gpmhe import GaussianProcess, SparseGaussianProcess
        >>> D = np.linspace(0.0, 5.0, 20)[:, None]
        >>> Y = np.sin(D[:, 0])
        >>> exact = GaussianProcess(optimizer=None).fit(D, Y)
        >>> sparse = SparseGaussianProcess(inducing=D, optimizer=None).fit(D, Y)
        >>> bool(np.allclose(sparse.log_marginal_likelihood(), exact.log_marginal_likelihood()))
        True
        """
        return self._lml_result(theta, eval_gradient)

    def predict(self, D: Any, return_std: bool = False):
        """Posterior mean, and optionally latent standard deviation, at test points.

        O(m n_d) per point and output for the mean, O(m^2) for the standard deviation. Far from the
        inducing points the standard deviation returns to sigma_f.

        Parameters
        ----------
        D : array_like of shape (k, n_d)
            Test points.
        return_std : bool, default False
            Also return the posterior standard deviation of the latent (noise-free) f.

        Returns
        -------
        mean : ndarray of shape (k,)
            Posterior means.
        std : ndarray of shape (k,)
            Latent posterior standard deviations; only returned if ``return_std`` is True.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import SparseGaussianProcess
        >>> D = np.linspace(0.0, 10.0, 300)[:, None]
        >>> gp = SparseGaussianProcess(n_inducing=15, sigma_eps=0.01, optimizer=None).fit(D, np.sin(D[:, 0]))
        >>> mean, std = gp.predict([[5.0], [100.0]], return_std=True)
        >>> bool(np.all(std[0] < 0.05)), bool(np.allclose(std[1], gp.sigma_f))
        (True, True)
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
            Posterior means.
        var : ndarray of shape (k,)
            Latent (noise-free) posterior variances.
        dmean_dd : ndarray of shape (k, n_d)
            Gradients of the means with respect to d.
        dvar_dd : ndarray of shape (k, n_d)
            Gradients of the variances with respect to d.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import SparseGaussianProcess
        >>> D = np.linspace(0.0, 5.0, 200)[:, None]
        >>> gp = SparseGaussianProcess(n_inducing=15, sigma_eps=0.01, optimizer=None).fit(D, np.sin(D[:, 0]))
        >>> mean, var, dmean, dvar = gp.predict_with_gradients([[1.0]])
        >>> dmean.shape
        (1, 1)
        """
        return super().predict_with_gradients(D)

    def save(self, path: Union[str, os.PathLike]) -> None:
        """Save the fitted model, its inducing points and its settings to an ``.npz`` file (no pickle).

        ``random_state`` is not saved; given ``inducing`` points are restored as the fitted ones.

        Parameters
        ----------
        path : str, os.PathLike or file-like object
            Destination, passed to `numpy.savez`.

        See Also
        --------
        load : Read the file back.

        Examples
        --------
        >>> import io
        >>> import numpy as np
        >>> from gpmhe import SparseGaussianProcess
        >>> D = np.linspace(0.0, 5.0, 50)[:, None]
        >>> gp = SparseGaussianProcess(n_inducing=10, optimizer=None).fit(D, np.sin(D[:, 0]))
        >>> buf = io.BytesIO()
        >>> gp.save(buf)
        >>> _ = buf.seek(0)
        >>> bool(np.array_equal(SparseGaussianProcess.load(buf).predict(D), gp.predict(D)))
        True
        """
        return super().save(path)

    @classmethod
    def load(cls, path: Union[str, os.PathLike]) -> "SparseGaussianProcess":
        """Load a model written by ``save``.

        Parameters
        ----------
        path : str, os.PathLike or file-like object
            The ``.npz`` file.

        Returns
        -------
        SparseGaussianProcess
            The fitted model, with the saved settings (``random_state`` None).

        Raises
        ------
        ValueError
            If the file is not a saved `SparseGaussianProcess` or was written by a newer gpmhe.

        Examples
        --------
        >>> import io
        >>> import numpy as np
        >>> from gpmhe import SparseGaussianProcess
        >>> D = np.linspace(0.0, 5.0, 50)[:, None]
        >>> buf = io.BytesIO()
        >>> SparseGaussianProcess(n_inducing=10, method="fitc", optimizer=None).fit(D, np.sin(D[:, 0])).save(buf)
        >>> _ = buf.seek(0)
        >>> SparseGaussianProcess.load(buf).method
        'fitc'
        """
        return super().load(path)

    _kind = "SparseGaussianProcess"

    def __repr__(self) -> str:
        if self._core_model is None:
            return f"SparseGaussianProcess(method={self.method!r}, n_inducing={self.n_inducing}, not fitted)"
        m = self._core_model
        return f"SparseGaussianProcess(method={m.method!r}, m={len(m.inducing[0])}, N={m.n_train}, fitted)"


class SparseMultiOutputGP(_Inducing, _ManyOutputs):
    """Independent sparse SE-ARD GPs, one per output column, on shared inputs.

    Each output o is a `SparseGaussianProcess` of its own, with its own hyperparameters and its
    own inducing points (chosen under its own kernel). It has every attribute and method of
    `MultiOutputGP` (it is not a subclass of it), so it can serve as the f- and h-GPs of a `LearnedModel` (``LearnedModel.from_trajectories(...,
    n_inducing=...)`` builds them), and `GPMHE` and the GP-EKF run on it unchanged.

    Parameters
    ----------
    n_inducing : int, default 100
        Number of inducing points m to choose from the training inputs (at most N; fewer when the
        remaining inputs are determined by the chosen ones, e.g. duplicated inputs).
    method : {"vfe", "fitc"}, default "vfe"
        The approximation: VFE (Titsias' variational bound, GPflow's SGPR) or FITC (GPflow's
        GPRFITC). VFE is the default: its objective is a lower bound on the exact log marginal
        likelihood, so more inducing points never make it worse, and it does not underestimate the
        noise as FITC can.
    inducing : array_like of shape (m, n_d) or None, default None
        Fixed inducing inputs instead of choosing them (the same for every output); a list of q (m_o, n_d) arrays gives each output its own.
    optimize_inducing : bool, default False
        Also optimise the inducing inputs jointly with theta (m n_d more parameters, within the
        bounding box of the training inputs) after the hyperparameter fit.
    sigma_f, lengthscales, sigma_eps, optimizer, n_restarts, bounds, random_state, maxiter
        As for `MultiOutputGP`: initial hyperparameters (kept with ``optimizer=None``) and the
        settings of the L-BFGS-B fit of the training objective.
    mean, normalize, hyperprior
        As for `MultiOutputGP`: the prior mean fitted by least squares first (the sparse GP
        regresses y − m(d)), the data-relative units of ``bounds`` and ``hyperprior``, and the
        log-normal hyperparameter priors added to the training objective.

    Attributes
    ----------
    kernel : SEKernel
        The kernel with the current hyperparameters and ``bounds`` (the fitted ones after ``fit``).
    inducing_points : list of ndarray of shape (m_o, n_d)
        The fitted inducing inputs of each output.
    sigma_f, lengthscales, sigma_eps, theta, n_outputs, dim, D_train, y_train, jitter
        As for `MultiOutputGP` (``jitter``: the one added to each output's K(Z, Z)).
    n_inducing, method, inducing, optimize_inducing, optimizer, n_restarts, bounds, random_state, maxiter, mean, normalize, hyperprior
        The settings as given.

    See Also
    --------
    SparseGaussianProcess : One output, and the model's equations.
    MultiOutputGP : The exact GPs.

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe import SparseMultiOutputGP
    >>> D = np.random.default_rng(0).uniform(-1.0, 1.0, (1000, 2))
    >>> Y = np.column_stack([np.sin(D[:, 0]), D[:, 0] * D[:, 1]])
    >>> gp = SparseMultiOutputGP(n_inducing=40, sigma_eps=0.01, optimizer=None).fit(D, Y)
    >>> gp
    SparseMultiOutputGP(q=2, n_d=2, N=1000, method='vfe', m=[40, 40], fitted)
    >>> print(np.round(gp.predict([[0.5, 0.2]]), 2))
    [[0.48 0.1 ]]
    """

    def __init__(
        self,
        n_inducing: int = 100,
        method: str = 'vfe',
        inducing: Any = None,
        optimize_inducing: bool = False,
        sigma_f: Union[float, np.ndarray] = 1.0,
        lengthscales: Any = 1.0,
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
        super().__init__(n_inducing=n_inducing, method=method, inducing=inducing, optimize_inducing=optimize_inducing, sigma_f=sigma_f, lengthscales=lengthscales, sigma_eps=sigma_eps, optimizer=optimizer, n_restarts=n_restarts, bounds=bounds, random_state=random_state, maxiter=maxiter, mean=mean, normalize=normalize, hyperprior=hyperprior)

    def fit(self, D: Any, Y: Any) -> "SparseMultiOutputGP":
        """Fit the sparse GPs to training data: choose the inducing points and the hyperparameters.

        Without given ``inducing`` points, ``n_inducing`` training inputs are chosen by greedy
        conditional-variance selection under the initial kernel; with an optimizer the training
        objective is maximised over theta, the points are chosen again under the fitted kernel, and theta
        is refined. With ``optimize_inducing`` the inducing inputs are then optimised jointly with theta.

        Parameters
        ----------
        D : array_like of shape (N, n_d)
            Training inputs, N >= 2 finite rows.
        Y : array_like of shape (N, q) or (N,)
            Training targets, one column per output (a 1-D Y is one output).

        Returns
        -------
        SparseMultiOutputGP
            ``self``, fitted.

        Raises
        ------
        ValueError
            If D or the targets have the wrong shape or contain NaN or inf, or the given inducing points
            do not match n_d.
        gpmhe.NumericalError
            If no optimiser run reached a finite objective, or K(Z, Z) cannot be factored even with
            jitter.

        Warns
        -----
        ConvergenceWarning
            If an optimiser run stopped without converging.

        Notes
        -----
        A failed fit leaves the model unchanged.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import SparseMultiOutputGP
        >>> rng = np.random.default_rng(0)
        >>> D = np.linspace(0.0, 10.0, 500)[:, None]
        >>> gp = SparseMultiOutputGP(n_inducing=5).fit(D, np.column_stack([np.sin(D[:, 0]), np.cos(D[:, 0])]) + 0.1 * rng.standard_normal((500, 2)))
        >>> [z.shape for z in gp.inducing_points]
        [(5, 1), (5, 1)]
        """
        return self._fit_targets(D, Y)

    def diagnostics(self) -> list:
        """Diagnostics of the fit, one `gpmhe.FitDiagnostics` per output.

        As for the exact GP: the fitted hyperparameters, which of them sit at a bound, every optimiser
        run's objective, and leave-one-out errors against the noise level and against a straight line.
        The LOO errors are those of the sparse model itself (the Gaussian model with covariance
        Qff + Lambda), in closed form in O(N m^2) per output, computed once per fit.

        Returns
        -------
        list of FitDiagnostics
            One per output.

        Raises
        ------
        NotFittedError
            Before ``fit``.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import SparseMultiOutputGP
        >>> D = np.linspace(0.0, 10.0, 500)[:, None]
        >>> gp = SparseMultiOutputGP(n_inducing=20, mean="linear").fit(D, np.column_stack([np.sin(D[:, 0]), np.cos(D[:, 0])]) + 0.5 * D)
        >>> [d.collapsed for d in gp.diagnostics()]
        [False, False]
        """
        return super().diagnostics()

    def log_marginal_likelihood(self, theta: Any = None, eval_gradient: bool = False):
        """The training objective: the VFE bound or FITC's log marginal likelihood.

        For ``method="vfe"`` this is Titsias' collapsed lower bound on log p(y | D, theta); for
        ``method="fitc"`` the log marginal likelihood of the FITC model. Both are evaluated with the
        fitted inducing points.

        Parameters
        ----------
        theta : array_like of shape (q, n_d + 2) or None, default None
            Log-hyperparameters at which to evaluate it; None uses the current ``theta``.
        eval_gradient : bool, default False
            Also return the gradient with respect to theta.

        Returns
        -------
        objective : ndarray of shape (q,)
            The training objective.
        grad : ndarray of shape (q, n_d + 2)
            Its gradient with respect to theta; only returned if ``eval_gradient`` is True.

        Examples
        --------
        With the inducing points at the training inputs, VFE's bound is the exact GP's log marginal
        likelihood:

        >>> import numpy as np
        >>> from gpmhe import MultiOutputGP, SparseMultiOutputGP
        >>> D = np.linspace(0.0, 5.0, 20)[:, None]
        >>> Y = np.column_stack([np.sin(D[:, 0]), np.cos(D[:, 0])])
        >>> exact = MultiOutputGP(optimizer=None).fit(D, Y)
        >>> sparse = SparseMultiOutputGP(inducing=D, optimizer=None).fit(D, Y)
        >>> bool(np.allclose(sparse.log_marginal_likelihood(), exact.log_marginal_likelihood()))
        True
        """
        return self._lml_result(theta, eval_gradient)

    def predict(self, D: Any, return_std: bool = False):
        """Posterior means, and optionally latent standard deviations, at test points.

        O(m n_d) per point and output for the mean, O(m^2) for the standard deviation. Far from the
        inducing points the standard deviation returns to sigma_f.

        Parameters
        ----------
        D : array_like of shape (k, n_d)
            Test points.
        return_std : bool, default False
            Also return the posterior standard deviation of the latent (noise-free) f.

        Returns
        -------
        mean : ndarray of shape (k, q)
            Posterior means.
        std : ndarray of shape (k, q)
            Latent posterior standard deviations; only returned if ``return_std`` is True.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import SparseMultiOutputGP
        >>> D = np.linspace(0.0, 10.0, 300)[:, None]
        >>> gp = SparseMultiOutputGP(n_inducing=15, sigma_eps=0.01, optimizer=None).fit(D, np.column_stack([np.sin(D[:, 0]), np.cos(D[:, 0])]))
        >>> mean, std = gp.predict([[5.0], [100.0]], return_std=True)
        >>> bool(np.all(std[0] < 0.05)), bool(np.allclose(std[1], gp.sigma_f))
        (True, True)
        """
        return super().predict(D, return_std)

    def predict_with_gradients(self, D: Any) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Posterior means and latent variances with their gradients with respect to the input.

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
            Gradients of the means with respect to d.
        dvar_dd : ndarray of shape (k, q, n_d)
            Gradients of the variances with respect to d.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import SparseMultiOutputGP
        >>> D = np.linspace(0.0, 5.0, 200)[:, None]
        >>> gp = SparseMultiOutputGP(n_inducing=15, sigma_eps=0.01, optimizer=None).fit(D, np.column_stack([np.sin(D[:, 0]), np.cos(D[:, 0])]))
        >>> mean, var, dmean, dvar = gp.predict_with_gradients([[1.0]])
        >>> dmean.shape
        (1, 2, 1)
        """
        return super().predict_with_gradients(D)

    def save(self, path: Union[str, os.PathLike]) -> None:
        """Save the fitted model, its inducing points and its settings to an ``.npz`` file (no pickle).

        ``random_state`` is not saved; given ``inducing`` points are restored as the fitted ones.

        Parameters
        ----------
        path : str, os.PathLike or file-like object
            Destination, passed to `numpy.savez`.

        See Also
        --------
        load : Read the file back.

        Examples
        --------
        >>> import io
        >>> import numpy as np
        >>> from gpmhe import SparseMultiOutputGP
        >>> D = np.linspace(0.0, 5.0, 50)[:, None]
        >>> gp = SparseMultiOutputGP(n_inducing=10, optimizer=None).fit(D, np.column_stack([np.sin(D[:, 0]), np.cos(D[:, 0])]))
        >>> buf = io.BytesIO()
        >>> gp.save(buf)
        >>> _ = buf.seek(0)
        >>> bool(np.array_equal(SparseMultiOutputGP.load(buf).predict(D), gp.predict(D)))
        True
        """
        return super().save(path)

    @classmethod
    def load(cls, path: Union[str, os.PathLike]) -> "SparseMultiOutputGP":
        """Load a model written by ``save``.

        Parameters
        ----------
        path : str, os.PathLike or file-like object
            The ``.npz`` file.

        Returns
        -------
        SparseMultiOutputGP
            The fitted model, with the saved settings (``random_state`` None).

        Raises
        ------
        ValueError
            If the file is not a saved `SparseMultiOutputGP` or was written by a newer gpmhe.

        Examples
        --------
        >>> import io
        >>> import numpy as np
        >>> from gpmhe import SparseMultiOutputGP
        >>> D = np.linspace(0.0, 5.0, 50)[:, None]
        >>> buf = io.BytesIO()
        >>> SparseMultiOutputGP(n_inducing=10, method="fitc", optimizer=None).fit(D, np.column_stack([np.sin(D[:, 0]), np.cos(D[:, 0])])).save(buf)
        >>> _ = buf.seek(0)
        >>> SparseMultiOutputGP.load(buf).method
        'fitc'
        """
        return super().load(path)

    _kind = "SparseMultiOutputGP"

    def __repr__(self) -> str:
        if self._core_model is None:
            return f"SparseMultiOutputGP(method={self.method!r}, n_inducing={self.n_inducing}, not fitted)"
        m = self._core_model
        return (f"SparseMultiOutputGP(q={m.n_outputs}, n_d={m.dim}, N={m.n_train}, method={m.method!r}, "
                f"m={[len(z) for z in m.inducing]}, fitted)")
