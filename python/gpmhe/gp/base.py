"""`_ExactGP`, what `GaussianProcess` (``single.py``) and `MultiOutputGP` (``multi.py``) share:
Gaussian-process regression with the SE-ARD kernel on the Rust core's `MultiGP`.

The numerics run on the Rust core; the user guide page *Gaussian processes* describes the model,
the hyperparameter fit and the numerical safeguards in more detail.

``GaussianProcess`` is one zero-mean GP; ``MultiOutputGP`` is one independent GP per output column
on shared inputs, each with its own hyperparameters, predicted in one Rust call. Hyperparameters
are optimised in log space, theta = log([sigma_f, lengthscales..., sigma_eps]), by maximising the
log marginal likelihood with SciPy's L-BFGS-B and the analytic gradient from Rust, with optional
random restarts inside the bounds. Models are saved as ``.npz`` (no pickle).

Model (per output)::

    y_i = f(d_i) + eps_i,   eps_i ~ N(0, sigma_eps^2),   f ~ GP(0, k),
    k(d, d') = sigma_f^2 exp(-1/2 (d - d')^T diag(lengthscales)^-2 (d - d'))

Posterior at a test point d*: mean m(d*) = k*^T (K + sigma_eps^2 I)^-1 y and latent (noise-free)
variance var(d*) = sigma_f^2 - k*^T (K + sigma_eps^2 I)^-1 k*, computed as sigma_f^2 - ‖L^-1 k*‖^2.
If K + sigma_eps^2 I is numerically singular, the core adds a small diagonal jitter (from
1e-10 (sigma_f^2 + sigma_eps^2), growing tenfold up to 1e-6 (sigma_f^2 + sigma_eps^2)) and records
it in ``jitter``; beyond that it raises ``gpmhe.NumericalError``.
"""

from __future__ import annotations

import json
import os
from typing import Any, Callable, Optional, Sequence, Tuple, Union

import numpy as np

from gpmhe import _core
from gpmhe.gp import priors as _priors
from gpmhe._core import NumericalError
from gpmhe._npz import NpzReader
from gpmhe.gp.diagnostics import diagnose, exact_loo, summary_table
from gpmhe._validation import (
    boolean,
    float_array,
    integer,
    one_of,
    points,
    random_state as check_random_state,
    training_set,
)

from gpmhe.gp.errors import NotFittedError
from gpmhe.gp.kernel import DEFAULT_BOUNDS, _Theta
from gpmhe.gp.fit import _exact_lml, _maximise, _posterior

__all__: list = []

_FORMAT_VERSION = 2  # of saved GPs (2: prior mean, normalize, hyperprior)

def _settings(est: Any) -> dict:
    return dict(
        optimizer="" if est.optimizer is None else est.optimizer,
        n_restarts=est.n_restarts,
        bounds=np.asarray(est.bounds, dtype=np.float64),
        maxiter=est.maxiter,
        mean=est.mean,
        normalize=est.normalize,
        hyperprior=json.dumps(_priors.hyperprior_json(est.hyperprior)),
    )


def _settings_from(f: NpzReader) -> dict:
    opt = f.string("optimizer")
    settings = dict(
        optimizer=None if opt == "" else opt,
        n_restarts=f.integer("n_restarts"),
        bounds=f.floats("bounds"),
        maxiter=f.integer("maxiter"),
    )
    if f.version >= 2:  # older files: the zero mean, no hyperprior
        settings.update(mean=f.string("mean"), normalize=f.boolean("normalize"))
        try:
            settings["hyperprior"] = json.loads(f.string("hyperprior"))
        except ValueError:
            raise f.error("hyperprior", "is not JSON") from None
    return settings


class _ExactGP:
    """The one implementation behind `GaussianProcess` and `MultiOutputGP`.

    q independent SE-ARD GPs on shared inputs in one ``_core.MultiGP``; the training data are kept
    as (N, n_d) and (N, q) arrays and theta as (q, n_d + 2). `GaussianProcess` is the q = 1 case:
    with ``_squeeze`` its results drop the output axis. The subclasses add the natural-unit
    attributes (``_check_hyperparameters``, ``_store``), what differs in their API (``fit``'s
    argument name, the shapes of theta, the LML and the jitter, the properties) and ``__repr__``;
    `_documented` gives each its own copies of the shared methods with its docstrings.
    """

    #: The class name, in messages and as the ``kind`` of saved files.
    _kind = "_ExactGP"
    #: The target's name in ``fit`` (for messages).
    _target = "Y"
    #: One output: drop the output axis of predictions, theta, the LML and the saved targets.
    _squeeze = False

    def __init__(
        self,
        sigma_f: Union[float, np.ndarray] = 1.0,
        lengthscales: Union[float, Sequence[float], np.ndarray] = 1.0,
        sigma_eps: Union[float, np.ndarray] = 0.1,
        optimizer: Optional[str] = "L-BFGS-B",
        n_restarts: int = 0,
        bounds: Any = DEFAULT_BOUNDS,
        random_state: Union[None, int, np.random.Generator] = None,
        maxiter: int = 15000,
        mean: str = "zero",
        normalize: bool = False,
        hyperprior: Any = None,
    ) -> None:
        self._check_hyperparameters(sigma_f, lengthscales, sigma_eps)
        self.optimizer = one_of("optimizer", optimizer, ("L-BFGS-B", None))
        self.n_restarts = integer("n_restarts", n_restarts)
        _Theta.log_bounds(bounds, None)  # validate the form now; expanded once n_d is known
        self.bounds = bounds
        self.random_state = check_random_state("random_state", random_state)
        self.maxiter = integer("maxiter", maxiter, low=1)
        self.mean = _priors.check_mean(mean)
        self.normalize = boolean("normalize", normalize)
        self.hyperprior = _priors.check_hyperprior(hyperprior)
        self._core_model: Optional[_core.MultiGP] = None
        self._D: Optional[np.ndarray] = None
        self._Y: Optional[np.ndarray] = None
        #: The fit's record for `diagnostics`: natural-unit log-bounds (q, n_d + 2, 2) and the
        #: objective of every optimiser run per output; None without an optimiser.
        self._fit_record: Optional[Tuple[np.ndarray, list]] = None
        self._diagnostics: Optional[list] = None

    def _check_hyperparameters(self, sigma_f: Any, lengthscales: Any, sigma_eps: Any) -> None:
        """Set sigma_f, lengthscales and sigma_eps (natural units) from the constructor's values."""
        raise NotImplementedError

    def _store(self, sigma_f: np.ndarray, lengthscales: np.ndarray, sigma_eps: np.ndarray) -> None:
        """Set sigma_f, lengthscales and sigma_eps from their (q,), (q, n_d), (q,) values."""
        raise NotImplementedError

    # -- state -------------------------------------------------------------------------------

    def _set_model(self, model: "_core.MultiGP", D: np.ndarray, Y: np.ndarray) -> None:
        self._core_model, self._D, self._Y = model, D, Y
        self._diagnostics = None
        self._store(*_Theta.to_natural(model.thetas))

    def _residuals(self) -> np.ndarray:
        """The targets the GPs regress: y − m(D) with the fitted prior mean."""
        return _priors.residuals(self._core_model.mean, self._D, self._Y)

    def _model(self) -> "_core.MultiGP":
        if self._core_model is None:
            raise NotFittedError(f"this {self._kind} is not fitted yet; call fit(D, {self._target}) first")
        return self._core_model

    def _theta_rows(self, value: Any) -> np.ndarray:
        """A theta argument of the fitted model (n_d + 2,) or (q, n_d + 2) as (q, n_d + 2)."""
        m = self._model()
        theta = float_array("theta", value, 1 if self._squeeze else 2)
        shape = (m.dim + 2,) if self._squeeze else (m.n_outputs, m.dim + 2)
        if theta.shape != shape:
            raise ValueError(f"theta: expected shape {shape}, got {theta.shape}")
        return theta.reshape(m.n_outputs, m.dim + 2)

    def _refactor(self, theta: Any) -> None:
        """Factor the fitted model again at a new theta (the ``theta`` setter)."""
        m = self._model()
        core = _core.MultiGP(self._D, self._residuals(), self._theta_rows(theta), m.mean)
        self._set_model(core, self._D, self._Y)
        self._fit_record = None

    @property
    def dim(self) -> int:
        return self._model().dim

    @property
    def D_train(self) -> np.ndarray:
        self._model()
        return self._D.copy()

    @property
    def y_train(self) -> np.ndarray:
        self._model()
        return self._out(self._Y).copy()

    def _out(self, a: np.ndarray) -> np.ndarray:
        """A per-point result (k, q, ...) as it is returned: (k, ...) for one output."""
        return a.reshape(a.shape[:1] + a.shape[2:]) if self._squeeze else a

    # -- fitting -----------------------------------------------------------------------------

    def _fit(self, D: Any, Y: Any, y_ndim: int) -> "_ExactGP":
        D, Y = training_set(D, Y, y_ndim)
        if y_ndim == 1:
            Y = Y.reshape(-1, 1)
        q, nd = Y.shape[1], D.shape[1]
        coef = _priors.fit_mean(self.mean, D, Y)
        R = _priors.residuals(coef, D, Y)
        theta = _Theta.from_natural(self.sigma_f, self.lengthscales, self.sigma_eps, q, nd)
        record = None
        if self.optimizer is not None:
            theta, record = self._optimise(D, R, theta)
        self._set_model(_core.MultiGP(D, R, np.ascontiguousarray(theta), coef), D, Y)
        self._fit_record = record
        return self

    def _optimise(self, D: np.ndarray, R: np.ndarray, theta0: np.ndarray) -> Tuple[np.ndarray, Tuple[np.ndarray, list]]:
        """(theta (q, n_d + 2), the fit's record) maximising each output's log marginal likelihood
        plus log-prior from theta0. The optimiser works on theta − log_scales (standardised
        units with ``normalize``), where the bounds and the hyperprior apply."""
        q, nd = R.shape[1], D.shape[1]
        log_bounds = _Theta.log_bounds(self.bounds, nd)
        shift = _priors.log_scales(self.normalize, D, R)
        prior = _priors.prior_rows(self.hyperprior, nd)
        rng = np.random.default_rng(self.random_state)
        rows, runs = [], []
        for o in range(q):  # a loop, not a comprehension: the warning's stacklevel counts frames
            objective = _posterior(_exact_lml(D, np.ascontiguousarray(R[:, o])), shift[o], prior)
            t, _, values = _maximise(objective, theta0[o] - shift[o], log_bounds, self.n_restarts, rng, self.maxiter)
            rows.append(t + shift[o])
            runs.append(values)
        return np.array(rows), (log_bounds[None, :, :] + shift[:, :, None], runs)

    def _log_marginal_likelihood(self, theta: Any, eval_gradient: bool) -> Tuple[np.ndarray, np.ndarray]:
        """(lml (q,), grad (q, n_d + 2) or None) at theta, None for the current one."""
        m = self._model()
        eval_gradient = boolean("eval_gradient", eval_gradient)
        if theta is None:
            lml = m.log_marginal_likelihoods()
            return lml, (m.log_marginal_likelihood_gradients() if eval_gradient else None)
        theta = self._theta_rows(theta)
        R = self._residuals()
        res = [
            _core.log_marginal_likelihood(
                self._D, np.ascontiguousarray(R[:, o]), np.ascontiguousarray(theta[o]), bool(eval_gradient)
            )
            for o in range(m.n_outputs)
        ]
        return np.array([r[0] for r in res]), np.array([r[1] for r in res])

    # -- diagnostics -------------------------------------------------------------------------

    @property
    def mean_coefficients(self) -> Optional[np.ndarray]:
        """The fitted prior mean m(d) = b + w·d as rows [b, w...], shape (q, n_d + 1) ((n_d + 1,)
        for `GaussianProcess`); None for ``mean="zero"``. Raises `NotFittedError` before ``fit``."""
        coef = self._model().mean
        return coef[0].copy() if (coef is not None and self._squeeze) else coef

    def diagnostics(self) -> list:
        """Diagnostics of the fit, one `gpmhe.FitDiagnostics` per output.

        The fitted hyperparameters, which of them sit at a bound, every optimiser run's objective,
        and leave-one-out errors (closed form, one dense O(N³) factorisation per output, computed
        once per fit) against the noise level and against a straight line.

        Returns
        -------
        list of FitDiagnostics
            One per output (one for `GaussianProcess`).

        Raises
        ------
        NotFittedError
            Before ``fit``.

        Examples
        --------
        A GP held at a tiny sigma_f cannot follow a line that a straight line fits:

        >>> import numpy as np
        >>> from gpmhe import GaussianProcess
        >>> D = np.linspace(0.0, 5.0, 30)[:, None]
        >>> y = 2.0 * D[:, 0] + 0.1 * np.sin(3.0 * D[:, 0])
        >>> bad = GaussianProcess(sigma_f=1e-3, sigma_eps=1.0, optimizer=None).fit(D, y)
        >>> bad.diagnostics()[0].collapsed
        True
        >>> GaussianProcess(mean="linear").fit(D, y).diagnostics()[0].collapsed
        False
        """
        m = self._model()
        if self._diagnostics is None:
            self._diagnostics = diagnose(self._D, self._residuals(), m.thetas, m.log_marginal_likelihoods(),
                                         self._fit_record, self._loo())
        return list(self._diagnostics)

    def _loo(self) -> Callable:
        """``loo(o, r)`` of `gpmhe.gp.diagnostics.diagnose` for this model."""
        m = self._model()
        return exact_loo(self._D, m.thetas, m.jitters)

    def summary(self) -> str:
        """A printable table of `diagnostics`, one row per output, with the problems found.

        Returns
        -------
        str
            The table.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import GaussianProcess
        >>> D = np.linspace(0.0, 5.0, 30)[:, None]
        >>> gp = GaussianProcess(mean="linear").fit(D, 2.0 * D[:, 0] + np.sin(D[:, 0]))
        >>> print(gp.summary().splitlines()[0])
        GaussianProcess (mean="linear", N=30)
        """
        self._model()
        title = f'{self._kind} (mean="{self.mean}", N={self._D.shape[0]})'
        return summary_table(title, self.diagnostics())

    # -- prediction --------------------------------------------------------------------------

    def predict(self, D: Any, return_std: bool = False):
        m = self._model()
        D = points("D", D, m.dim)
        if not boolean("return_std", return_std):
            return self._out(m.predict_mean(D))
        mean, var = m.predict(D)
        return self._out(mean), np.sqrt(self._out(var))

    def predict_with_gradients(self, D: Any) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        m = self._model()
        mean, var, dmean, dvar = m.predict_with_gradients(points("D", D, m.dim))
        return self._out(mean), self._out(var), self._out(dmean), self._out(dvar)

    # -- persistence -------------------------------------------------------------------------

    def save(self, path: Union[str, os.PathLike]) -> None:
        model = self._model()
        theta, Y = model.thetas, self._Y
        if self._squeeze:
            theta, Y = theta[0], Y[:, 0]
        prior_mean = {} if model.mean is None else {"mean_coefficients": model.mean}
        np.savez(path, format_version=_FORMAT_VERSION, kind=self._kind, D=self._D, y=Y, theta=theta,
                 **prior_mean, **_settings(self))

    @classmethod
    def load(cls, path: Union[str, os.PathLike]) -> "_ExactGP":
        # Every entry is checked (a ValueError names the file and the entry): see gpmhe._npz.
        with NpzReader(path, cls._kind, _FORMAT_VERSION) as f:
            D = f.floats("D", (None, None))
            y_shape, t_shape = ((None,), (D.shape[1] + 2,)) if cls._squeeze else \
                ((None, None), (None, D.shape[1] + 2))
            Y, theta = f.floats("y", y_shape), f.floats("theta", t_shape)
            q = 1 if cls._squeeze else Y.shape[1]
            try:
                gp = cls(**_settings_from(f))
            except ValueError as e:
                raise ValueError(f"path: {f.name}: bad settings ({e})") from None
            coef = None if gp.mean == "zero" else f.floats("mean_coefficients", (q, D.shape[1] + 1))
            name = f.name
        if cls._squeeze:
            Y, theta = Y.reshape(-1, 1), theta.reshape(1, -1)
        try:
            model = _core.MultiGP(D, _priors.residuals(coef, D, Y), theta, coef)
        except (ValueError, NumericalError) as e:
            raise ValueError(f"path: {name}: entries 'D', 'y', 'theta' do not make a GP ({e})") from None
        gp._set_model(model, D, Y)
        return gp
