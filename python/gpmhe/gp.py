"""Gaussian-process regression with the SE-ARD kernel, for learning the models of the estimators.

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
import types
import warnings
from typing import Any, Callable, Optional, Sequence, Tuple, Union

import numpy as np
import scipy.optimize

from gpmhe import _core, _priors
from gpmhe._core import NumericalError
from gpmhe._npz import NpzReader
from gpmhe.diagnostics import diagnose, exact_loo, summary_table
from gpmhe._validation import (
    boolean,
    float_array,
    integer,
    one_of,
    points,
    positive,
    positive_scalar,
    random_state as check_random_state,
    training_set,
)

__all__ = ["GaussianProcess", "MultiOutputGP", "ConvergenceWarning", "NotFittedError"]

#: Default hyperparameter bounds in natural units: (sigma_f, every length-scale, sigma_eps).
DEFAULT_BOUNDS = ((1e-3, 1e3), (1e-3, 1e3), (1e-5, 1e2))

_FORMAT_VERSION = 2  # 2: prior mean, normalize, hyperprior


class ConvergenceWarning(UserWarning):
    """The hyperparameter optimiser stopped without reporting convergence.

    Issued by `GaussianProcess.fit` and `MultiOutputGP.fit` when the best L-BFGS-B run (over the
    start and the random restarts) hit its iteration limit or failed its line search with a
    projected gradient that is not small. The best hyperparameters found are still used.

    See Also
    --------
    GaussianProcess.fit : Emits this warning.

    Examples
    --------
    Turn it into an error, e.g. in a test suite:

    >>> import warnings
    >>> from gpmhe import ConvergenceWarning
    >>> with warnings.catch_warnings():
    ...     warnings.simplefilter("error", ConvergenceWarning)
    ...     issubclass(ConvergenceWarning, UserWarning)
    True
    """


class NotFittedError(ValueError, AttributeError):
    """A method that needs a fitted model was called before ``fit``.

    It derives from both `ValueError` and `AttributeError` (as scikit-learn's error of the same
    name does), so either can be caught.

    See Also
    --------
    GaussianProcess.fit : Fit a single-output GP.
    MultiOutputGP.fit : Fit independent GPs for several outputs.

    Examples
    --------
    >>> from gpmhe import GaussianProcess, NotFittedError
    >>> try:
    ...     GaussianProcess().predict([[0.0]])
    ... except NotFittedError as err:
    ...     print(err)
    this GaussianProcess is not fitted yet; call fit(D, y) first
    """


# ----------------------------------------------------------------------------- theta


class _Theta:
    """theta = log([sigma_f, lengthscales..., sigma_eps]), one row per output, in one place.

    The public classes keep the hyperparameters in natural units (``sigma_f``, ``lengthscales``,
    ``sigma_eps``), the optimiser works on theta within log-bounds, and the core takes theta as a
    (q, n_d + 2) array: these are all of the conversions between them, and the bounds.
    """

    @staticmethod
    def from_natural(sigma_f: Any, lengthscales: Any, sigma_eps: Any, q: int, nd: int) -> np.ndarray:
        """(q, n_d + 2) theta from natural units broadcast over q outputs and n_d inputs."""
        try:
            sf = np.broadcast_to(sigma_f, (q,))
            se = np.broadcast_to(sigma_eps, (q,))
        except ValueError:
            raise ValueError(f"sigma_f, sigma_eps: expected a scalar or {q} values (one per output)") from None
        try:
            ls = np.broadcast_to(lengthscales, (q, nd))
        except ValueError:
            raise ValueError(
                f"lengthscales: expected a scalar, ({nd},) or ({q}, {nd}), got {np.shape(lengthscales)}"
            ) from None
        return np.log(np.column_stack([sf, ls, se]))

    @staticmethod
    def to_natural(theta: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(sigma_f (q,), lengthscales (q, n_d), sigma_eps (q,)) of a (q, n_d + 2) theta."""
        t = np.exp(theta)
        return t[:, 0].copy(), t[:, 1:-1].copy(), t[:, -1].copy()

    @staticmethod
    def log_bounds(bounds: Any, nd: Optional[int]) -> np.ndarray:
        """Natural-unit bounds -> (nd + 2, 2) bounds on theta. With nd None (n_d not known yet)
        only the form is checked and the rows are returned as given."""
        b = float_array("bounds", bounds)
        rows_ok = b.ndim == 2 and (b.shape[0] == 3 or (b.shape[0] > 3 if nd is None else b.shape[0] == nd + 2))
        if not rows_ok or b.shape[1] != 2:
            expected = "(n_d + 2, 2)" if nd is None else f"({nd + 2}, 2)"
            raise ValueError(
                f"bounds: expected shape (3, 2) (sigma_f, lengthscales, sigma_eps) or {expected}, got {b.shape}"
            )
        if not np.all(np.isfinite(b)) or np.any(b <= 0) or np.any(b[:, 0] > b[:, 1]):
            raise ValueError("bounds: need finite 0 < low <= high in every row")
        if b.shape[0] == 3 and nd is not None:
            b = np.vstack([b[0], np.repeat(b[1:2], nd, axis=0), b[2]])
        return np.log(b)


# ----------------------------------------------------------------------------- optimisation


def _exact_lml(D: np.ndarray, y: np.ndarray) -> Callable[[np.ndarray], Tuple[float, np.ndarray]]:
    """The exact GP's log marginal likelihood and its gradient as a function of theta.

    D and y must be validated (``training_set``): they are handed to the core as they are.
    """

    def lml(theta: np.ndarray) -> Tuple[float, np.ndarray]:
        value, grad = _core.log_marginal_likelihood(D, y, np.ascontiguousarray(theta), True)
        return float(value), np.asarray(grad)

    return lml


def _posterior(
    lml: Callable[[np.ndarray], Tuple[float, np.ndarray]],
    shift: np.ndarray,
    prior: Optional[Tuple[np.ndarray, np.ndarray]],
) -> Callable[[np.ndarray], Tuple[float, np.ndarray]]:
    """The fit's objective in the optimiser's units t = theta − shift: lml(t + shift) plus the
    log-prior of t (`gpmhe._priors.log_prior`)."""

    def objective(t: np.ndarray) -> Tuple[float, np.ndarray]:
        value, grad = lml(t + shift)
        lp, lp_grad = _priors.log_prior(prior, t)
        return value + lp, grad + lp_grad

    return objective


def _maximise(
    objective: Callable[[np.ndarray], Tuple[float, np.ndarray]],
    theta0: np.ndarray,
    log_bounds: np.ndarray,
    n_restarts: int,
    rng: np.random.Generator,
    maxiter: int,
) -> Tuple[np.ndarray, float, np.ndarray]:
    """Best (theta, value, values of all runs) of L-BFGS-B runs maximising ``objective`` from
    theta0 and n_restarts uniform random starts inside the log-bounds.

    ``objective(theta)`` returns (value, gradient) of the quantity to maximise (a log marginal
    likelihood or a training bound, plus a log-prior). Raises NumericalError if no run produced a
    finite value.
    """

    def negated(theta: np.ndarray) -> Tuple[float, np.ndarray]:
        try:
            value, grad = objective(theta)
        except NumericalError:
            # Outside the numerically usable region: report it as infinitely bad so the line
            # search backs off.
            return np.inf, np.zeros_like(theta)
        except ValueError as err:
            # The data are valid, so the only input the core can refuse here is a trial theta
            # beyond what float64 represents (exp(theta) or sigma^2 overflowing): as bad as a
            # numerical failure. Any other ValueError is a genuine input error and surfaces.
            if str(err).startswith("theta"):
                return np.inf, np.zeros_like(theta)
            raise
        return -value, -grad

    starts = [np.clip(theta0, log_bounds[:, 0], log_bounds[:, 1])]
    starts += [rng.uniform(log_bounds[:, 0], log_bounds[:, 1]) for _ in range(n_restarts)]
    best: Optional[Tuple[np.ndarray, float, bool]] = None
    values = []
    for t0 in starts:
        res = scipy.optimize.minimize(
            negated,
            t0,
            jac=True,
            method="L-BFGS-B",
            bounds=log_bounds,
            # Tighter than SciPy's defaults: the LML is flat near its optimum.
            options={"maxiter": maxiter, "ftol": 1e-12, "gtol": 1e-9},
        )
        values.append(-float(res.fun))
        if np.isfinite(res.fun) and (best is None or -res.fun > best[1]):
            best = (np.asarray(res.x, dtype=np.float64), float(-res.fun), _converged(res, log_bounds))
    if best is None:
        raise NumericalError(
            "fit: no optimiser run reached a finite log marginal likelihood; "
            "check the data scaling and the bounds"
        )
    if not best[2]:
        warnings.warn(
            "fit: L-BFGS-B stopped before convergence (iteration limit, or a failed line search "
            "with a large projected gradient); the best hyperparameters found are used",
            ConvergenceWarning,
            stacklevel=4,  # _maximise <- _ExactGP._fit <- fit <- the caller of fit
        )
    return best[0], best[1], np.array(values)


def _converged(res: Any, log_bounds: np.ndarray) -> bool:
    """Whether an L-BFGS-B result is an optimum. A failed line search (status 2) counts as
    converged when the projected gradient is tiny relative to the LML: on ill-conditioned data the
    LML is only accurate to ~1e-9 relative and the line search cannot make further progress."""
    if res.status == 0:
        return True
    if res.status != 2 or res.jac is None:
        return False
    x, g = np.asarray(res.x), np.asarray(res.jac)
    at_bound = ((x <= log_bounds[:, 0]) & (g > 0)) | ((x >= log_bounds[:, 1]) & (g < 0))
    projected = np.where(at_bound, 0.0, g)
    return bool(np.max(np.abs(projected)) <= 1e-3 * max(1.0, abs(res.fun)))


# ----------------------------------------------------------------------------- persistence


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


# ----------------------------------------------------------------------------- the implementation


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
        """Diagnostics of the fit, one `gpmhe.diagnostics.FitDiagnostics` per output.

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
        """``loo(o, r)`` of `gpmhe.diagnostics.diagnose` for this model."""
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


# ----------------------------------------------------------------------------- docstrings

# The docstrings of the methods both public classes have, written once: `_documented` fills them
# in for each class with the fields below (its name, shapes, wording and examples).
_TEST_POINTS = """Parameters
----------
D : array_like of shape (k, n_d)
    Test points."""
_FILE_EXAMPLE = """Examples
--------
>>> import io
>>> import numpy as np
>>> from gpmhe import {cls}
>>> D = np.linspace(0.0, 5.0, 20)[:, None]"""
_DOCS = {
    "dim": """{dim_summary}

The number of columns of the training inputs; raises `NotFittedError` before ``fit``.
""",
    "D_train": """Training inputs, shape (N, n_d).

Those of the last successful ``fit``; raises `NotFittedError` before it.
""",
    "y_train": """Training targets, shape {y_shape}.

Those of the last successful ``fit``; raises `NotFittedError` before it.
""",
    "fit": """{fit_summary}

Parameters
----------
D : array_like of shape (N, n_d)
    Training inputs, N >= 2 finite rows.
{target}

Returns
-------
{cls}
    ``self``, fitted.

Raises
------
ValueError
    If D or {y} have the wrong shape or contain NaN or inf.
gpmhe.NumericalError
    {fit_numerical}

Warns
-----
ConvergenceWarning
    {fit_warns}

Notes
-----
A failed fit leaves the model unchanged.

Examples
--------
>>> import numpy as np
>>> from gpmhe import {cls}
{fit_example}
""",
    "predict": """{predict_summary}

""" + _TEST_POINTS + """
return_std : bool, default False
    {return_std}

Returns
-------
{predict_returns}

Examples
--------
>>> import numpy as np
>>> from gpmhe import {cls}
>>> D = np.linspace(0.0, 5.0, 20)[:, None]
{predict_example}
""",
    "predict_with_gradients": """{pwg_summary}

""" + _TEST_POINTS + """

Returns
-------
{pwg_returns}

Examples
--------
{pwg_example}
""",
    "save": """Save the fitted model and its settings to an ``.npz`` file (no pickle).

The training data, theta and the optimiser settings are stored; ``random_state`` is not.

Parameters
----------
path : str, os.PathLike or file-like object
    Destination, passed to `numpy.savez` (which appends ``.npz`` to a file name without
    it).

See Also
--------
load : Read the file back.

""" + _FILE_EXAMPLE + """
>>> gp = {cls}(optimizer=None).fit(D, {example_targets})
>>> buf = io.BytesIO()
>>> gp.save(buf)
>>> _ = buf.seek(0)
>>> bool(np.array_equal({cls}.load(buf).predict(D), gp.predict(D)))
True
""",
    "load": """Load a model written by ``save``.

Parameters
----------
path : str, os.PathLike or file-like object
    The ``.npz`` file.

Returns
-------
{cls}
    The fitted model, with the saved settings (``random_state`` None).

Raises
------
ValueError
    If the file is not a saved `{cls}` or was written by a newer gpmhe.

""" + _FILE_EXAMPLE + """
>>> buf = io.BytesIO()
>>> {load_example}
>>> _ = buf.seek(0)
>>> {cls}.load(buf)
{load_repr}
""",
}

# Each field's text for GaussianProcess, then for MultiOutputGP.
_DOC_FIELDS = {
    "cls": ("GaussianProcess", "MultiOutputGP"),
    "dim_summary": ("Input dimension n_d of the fitted model.", "Input dimension n_d."),
    "y_shape": ("(N,)", "(N, q)"),
    "y": ("y", "Y"),
    "example_targets": ("np.sin(D[:, 0])", "np.column_stack([D, D ** 2])"),
    "fit_summary": (
        "Fit the GP to training data, optimising the hyperparameters if an optimizer is set.",
        "Fit one GP per output column, optimising each output's hyperparameters if set.",
    ),
    "target": (
        """y : array_like of shape (N,)
    Training targets.""",
        """Y : array_like of shape (N, q) or (N,)
    Training targets, one column per output (a 1-D Y is one output).""",
    ),
    "fit_numerical": (
        """If no optimiser run reached a finite log marginal likelihood, or the kernel matrix
    cannot be factored even with jitter.""",
        "If an output's fit failed numerically (see `GaussianProcess.fit`).",
    ),
    "fit_warns": (
        "If the best optimiser run stopped without converging.",
        "If the optimiser did not converge for some output.",
    ),
    "fit_example": (
        """>>> D = np.linspace(0.0, 5.0, 20)[:, None]
>>> gp = GaussianProcess(optimizer=None).fit(D, np.sin(D[:, 0]))
>>> gp.D_train.shape, gp.dim
((20, 1), 1)""",
        """>>> D = np.random.default_rng(0).uniform(size=(10, 3))
>>> gp = MultiOutputGP(optimizer=None).fit(D, D[:, :2] ** 2)
>>> gp.n_outputs, gp.dim, gp.lengthscales.shape
(2, 3, (2, 3))""",
    ),
    "predict_summary": (
        "Posterior mean, and optionally standard deviation, of the latent f at test points.",
        "Posterior means, and optionally latent standard deviations, of all outputs.",
    ),
    "return_std": (
        "Also return the posterior standard deviation of the latent (noise-free) f.",
        "Also return the posterior standard deviations of the latent (noise-free) outputs.",
    ),
    "predict_returns": (
        """mean : ndarray of shape (k,)
    Posterior mean m(d) at each test point.
std : ndarray of shape (k,)
    Posterior standard deviation of f (without sigma_eps); only returned if
    ``return_std`` is True.

Raises
------
NotFittedError
    Before ``fit``.
ValueError
    If D has the wrong shape or contains NaN or inf.""",
        """mean : ndarray of shape (k, q)
    Posterior means, one column per output.
std : ndarray of shape (k, q)
    Latent posterior standard deviations; only returned if ``return_std`` is True.""",
    ),
    "predict_example": (
        """>>> gp = GaussianProcess(sigma_eps=0.01, optimizer=None).fit(D, np.sin(D[:, 0]))
>>> print(np.round(gp.predict([[1.0], [2.0]]), 2))
[0.84 0.91]""",
        """>>> gp = MultiOutputGP(sigma_eps=0.01, optimizer=None).fit(D, np.column_stack([D, -D]))
>>> mean, std = gp.predict([[1.0], [2.0]], return_std=True)
>>> print(np.round(mean, 2))
[[ 1. -1.]
 [ 2. -2.]]
>>> std.shape
(2, 2)""",
    ),
    "pwg_summary": (
        "Posterior mean and latent variance with their gradients with respect to the input.",
        "Posterior means and latent variances of all outputs with their input gradients.",
    ),
    "pwg_returns": (
        """mean : ndarray of shape (k,)
    Posterior mean m(d).
var : ndarray of shape (k,)
    Latent (noise-free) posterior variance var(d).
dmean_dd : ndarray of shape (k, n_d)
    Gradient of the mean with respect to d, one row per point.
dvar_dd : ndarray of shape (k, n_d)
    Gradient of the variance with respect to d.""",
        """mean : ndarray of shape (k, q)
    Posterior means.
var : ndarray of shape (k, q)
    Latent (noise-free) posterior variances.
dmean_dd : ndarray of shape (k, q, n_d)
    Gradients of the means with respect to d: [i, o, :] belongs to point i, output o.
dvar_dd : ndarray of shape (k, q, n_d)
    Gradients of the variances with respect to d.""",
    ),
    "pwg_example": (
        """The gradient of a GP fitted to sin approximates cos:

>>> import numpy as np
>>> from gpmhe import GaussianProcess
>>> D = np.linspace(0.0, 5.0, 20)[:, None]
>>> gp = GaussianProcess(sigma_eps=0.01, optimizer=None).fit(D, np.sin(D[:, 0]))
>>> mean, var, dmean, dvar = gp.predict_with_gradients([[1.0]])
>>> print(np.round(dmean, 2), np.round(np.cos(1.0), 2))
[[0.54]] 0.54""",
        """>>> import numpy as np
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
[0.2 0.5]""",
    ),
    "load_example": (
        "GaussianProcess(sigma_f=2.0, optimizer=None).fit(D, np.sin(D[:, 0])).save(buf)",
        "MultiOutputGP(optimizer=None).fit(D, np.column_stack([D, D ** 2])).save(buf)",
    ),
    "load_repr": (
        "GaussianProcess(sigma_f=2, lengthscales=[1.], sigma_eps=0.1, fitted)",
        "MultiOutputGP(q=2, n_d=1, N=20, fitted)",
    ),
}


#: The prior-mean, scaling and hyperprior parameters both GP classes take (and the sparse ones
#: by reference), written once: `_documented` puts them in place of ``%PRIOR_PARAMETERS%``.
_PRIOR_PARAMETERS = """mean : {"zero", "constant", "linear"}, default "zero"
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
    None: maximum likelihood."""


def _documented(which: int) -> Any:
    """Class decorator: gives the class its own copy of each `_ExactGP` method and property in
    ``_DOCS`` (or keeps the one it defines), its docstring filled in with text ``which`` of each
    field (0: GaussianProcess, 1: MultiOutputGP), and its own ``__init__``. The copies are the
    class's own members, so the API reference, its docstring checks (which look up the class of
    ``__init__`` by its qualified name) and the doctests see them on the class."""

    def own_copy(cls: type, f: Any, doc: Optional[str]) -> Any:
        g = types.FunctionType(f.__code__, f.__globals__, f.__name__, f.__defaults__, f.__closure__)
        g.__kwdefaults__, g.__module__, g.__doc__ = f.__kwdefaults__, f.__module__, doc
        g.__qualname__ = f"{cls.__name__}.{f.__name__}"
        g.__annotations__ = {k: (f"'{cls.__name__}'" if v == "'_ExactGP'" else v) for k, v in f.__annotations__.items()}
        return g

    def decorate(cls: type) -> type:
        cls.__init__ = own_copy(cls, _ExactGP.__init__, None)
        cls.__doc__ = cls.__doc__.replace("%PRIOR_PARAMETERS%", _PRIOR_PARAMETERS.replace("\n", "\n    "))
        fields = {key: texts[which] for key, texts in _DOC_FIELDS.items()}
        for name, template in _DOCS.items():
            doc = template.format(**fields)
            member = cls.__dict__[name] if name in cls.__dict__ else _ExactGP.__dict__[name]
            if isinstance(member, property):
                setattr(cls, name, property(member.fget, member.fset, member.fdel, doc))
            elif isinstance(member, classmethod):
                setattr(cls, name, classmethod(own_copy(cls, member.__func__, doc)))
            elif name in cls.__dict__:
                member.__doc__ = doc
            else:
                setattr(cls, name, own_copy(cls, member, doc))
        return cls

    return decorate


# ----------------------------------------------------------------------------- single output


@_documented(0)
class GaussianProcess(_ExactGP):
    """Exact GP regression of one output with the SE-ARD kernel.

    Model, for training inputs d_i (rows of D, n_d columns) and targets y_i::

        y_i = f(d_i) + eps_i,   eps_i ~ N(0, sigma_eps^2),   f ~ GP(0, k),
        k(d, d') = sigma_f^2 exp(-1/2 (d - d')^T diag(lengthscales)^-2 (d - d')).

    The posterior at a test point d* has mean m(d*) = k*^T (K + sigma_eps^2 I)^-1 y and latent
    (noise-free) variance var(d*) = sigma_f^2 - k*^T (K + sigma_eps^2 I)^-1 k*. With an
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
    %PRIOR_PARAMETERS%

    Attributes
    ----------
    sigma_f : float
        Signal standard deviation (the fitted value after ``fit``).
    lengthscales : float or ndarray of shape (n_d,)
        Length-scales (an ndarray of shape (n_d,) after ``fit``).
    sigma_eps : float
        Noise standard deviation (the fitted value after ``fit``).
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
    optimizer, n_restarts, bounds, random_state, maxiter, mean, normalize, hyperprior
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
    _target = "y"
    _squeeze = True

    def _check_hyperparameters(self, sigma_f: Any, lengthscales: Any, sigma_eps: Any) -> None:
        self.sigma_f = positive_scalar("sigma_f", sigma_f)
        ls = positive("lengthscales", lengthscales)
        if ls.ndim > 1 or ls.size == 0:
            raise ValueError("lengthscales: must be a positive scalar or a 1-D array")
        self.lengthscales = ls.copy() if ls.ndim == 1 else float(ls)
        self.sigma_eps = positive_scalar("sigma_eps", sigma_eps)

    def _store(self, sigma_f: np.ndarray, lengthscales: np.ndarray, sigma_eps: np.ndarray) -> None:
        self.sigma_f, self.lengthscales, self.sigma_eps = float(sigma_f[0]), lengthscales[0], float(sigma_eps[0])

    # -- state -------------------------------------------------------------------------------

    @property
    def theta(self) -> np.ndarray:
        """Log-hyperparameters log([sigma_f, lengthscales..., sigma_eps]), shape (n_d + 2,).

        Setting it on a fitted GP refactors the model at the new values (no optimisation); on an
        unfitted GP it sets the initial values ``sigma_f``, ``lengthscales`` and ``sigma_eps``.
        """
        if self._core_model is not None:
            return self._core_model.thetas[0]
        return _Theta.from_natural(self.sigma_f, self.lengthscales, self.sigma_eps, 1, np.size(self.lengthscales))[0]

    @theta.setter
    def theta(self, value: Any) -> None:
        if self._core_model is not None:
            self._refactor(value)
            return
        theta = float_array("theta", value, 1)
        if theta.size < 3:
            raise ValueError(f"theta: needs n_d + 2 >= 3 values, got {theta.size}")
        p = np.exp(theta)
        if not np.all(np.isfinite(p)):
            raise ValueError("theta: exp(theta) overflows")
        self._store(*_Theta.to_natural(theta[None, :]))

    @property
    def jitter(self) -> float:
        """Diagonal jitter added to K + sigma_eps^2 I to factor it.

        Normally 0; positive when the kernel matrix was numerically singular.
        """
        return float(self._model().jitters[0])

    @property
    def log_marginal_likelihood_value(self) -> float:
        """Log marginal likelihood log p(y | D, theta) at the current theta.

        Equal to ``log_marginal_likelihood()``; raises `NotFittedError` before ``fit``.
        """
        return float(self._model().log_marginal_likelihoods()[0])

    # -- fitting -----------------------------------------------------------------------------

    def fit(self, D: Any, y: Any) -> "GaussianProcess":
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
        lml, grad = self._log_marginal_likelihood(theta, eval_gradient)
        return (float(lml[0]), grad[0]) if eval_gradient else float(lml[0])

    # -- prediction --------------------------------------------------------------------------

    # -- persistence -------------------------------------------------------------------------

    def __repr__(self) -> str:
        state = "fitted" if self._core_model is not None else "not fitted"
        return (
            f"GaussianProcess(sigma_f={self.sigma_f:.4g}, lengthscales={np.round(self.lengthscales, 4)}, "
            f"sigma_eps={self.sigma_eps:.4g}, {state})"
        )


# ----------------------------------------------------------------------------- multi output


@_documented(1)
class MultiOutputGP(_ExactGP):
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
    %PRIOR_PARAMETERS%

    Attributes
    ----------
    sigma_f : ndarray of shape (q,)
        Signal standard deviations (fitted after ``fit``).
    lengthscales : ndarray of shape (q, n_d)
        Length-scales (fitted after ``fit``).
    sigma_eps : ndarray of shape (q,)
        Noise standard deviations (fitted after ``fit``).
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
    optimizer, n_restarts, bounds, random_state, maxiter, mean, normalize, hyperprior
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

    def _check_hyperparameters(self, sigma_f: Any, lengthscales: Any, sigma_eps: Any) -> None:
        self.sigma_f = positive("sigma_f", sigma_f)
        self.lengthscales = positive("lengthscales", lengthscales)
        self.sigma_eps = positive("sigma_eps", sigma_eps)
        if 0 in (self.sigma_f.size, self.sigma_eps.size, self.lengthscales.size):
            raise ValueError("sigma_f, lengthscales, sigma_eps: must not be empty")
        if self.sigma_f.ndim > 1 or self.sigma_eps.ndim > 1 or self.lengthscales.ndim > 2:
            raise ValueError("sigma_f, sigma_eps: scalar or (q,); lengthscales: scalar, (n_d,) or (q, n_d)")

    def _store(self, sigma_f: np.ndarray, lengthscales: np.ndarray, sigma_eps: np.ndarray) -> None:
        self.sigma_f, self.lengthscales, self.sigma_eps = sigma_f, lengthscales, sigma_eps

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
    def jitter(self) -> np.ndarray:
        """Diagonal jitter of each output's kernel factorisation, shape (q,).

        Normally 0; positive where a kernel matrix was numerically singular.
        """
        return self._model().jitters

    def fit(self, D: Any, Y: Any) -> "MultiOutputGP":
        try:
            y_ndim = 1 if np.ndim(Y) == 1 else 2
        except ValueError:  # (a ragged list: training_set names it)
            y_ndim = 2
        return self._fit(D, Y, y_ndim)

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
        lml, grad = self._log_marginal_likelihood(theta, eval_gradient)
        return (lml, grad) if eval_gradient else lml

    def __repr__(self) -> str:
        if self._core_model is None:
            return "MultiOutputGP(not fitted)"
        return f"MultiOutputGP(q={self.n_outputs}, n_d={self.dim}, N={self._D.shape[0]}, fitted)"
