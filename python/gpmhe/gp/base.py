"""`_GP`, what every GP class shares (`GaussianProcess`, `MultiOutputGP` and their sparse
counterparts): the kernel (`SEKernel`, the owner of θ), the fit settings, the fitted state, and
fit, predict, diagnostics, save and load. What differs between exact and sparse GPs is an
*approximation* object the class delegates to (``exact.py``'s `EXACT` or ``inducing.py``'s
`Sparse`); what differs between one and several outputs is ``outputs.py``.

The numerics run on the Rust core; the user guide page *Gaussian processes* describes the model,
the hyperparameter fit and the numerical safeguards.

Model (per output)::

    y_i = f(d_i) + eps_i,   eps_i ~ N(0, sigma_eps^2),   f ~ GP(m, k),
    k(d, d') = sigma_f^2 exp(-1/2 (d - d')^T diag(lengthscales)^-2 (d - d'))

Hyperparameters are optimised in log space, theta = log([sigma_f, lengthscales..., sigma_eps]),
by maximising the training objective (the exact log marginal likelihood or a sparse bound) with
SciPy's L-BFGS-B and the analytic gradient from Rust, with optional random restarts inside the
bounds. If K + sigma_eps^2 I (sparse: K(Z, Z)) is numerically singular, the core adds a small
diagonal jitter (from 1e-10 (sigma_f^2 + sigma_eps^2), growing tenfold up to
1e-6 (sigma_f^2 + sigma_eps^2)) and records it in ``jitter``; beyond that it raises
``gpmhe.NumericalError``. Models are saved as ``.npz`` (no pickle).
"""

from __future__ import annotations

import json
import os
from typing import Any, NamedTuple, Optional, Sequence, Union

import numpy as np

from gpmhe._core import NumericalError
from gpmhe._npz import NpzReader
from gpmhe._validation import (
    boolean,
    float_array,
    integer,
    one_of,
    points,
    random_state as check_random_state,
    training_set,
)
from gpmhe.gp import priors as _priors
from gpmhe.gp.diagnostics import diagnose, summary_table
from gpmhe.gp.errors import NotFittedError
from gpmhe.gp.exact import EXACT
from gpmhe.gp.fit import Fitting
from gpmhe.gp.kernel import DEFAULT_BOUNDS, SEKernel

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


class _Fit(NamedTuple):
    """A fitted GP's state, replaced as a whole (one assignment): the core model, the training
    data (N, n_d) and (N, q), the approximation that built the model, and the fit's record for
    the diagnostics (natural-unit log-bounds (q, n_d + 2, 2) and every optimiser run's
    objective per output; None without an optimiser)."""

    model: Any
    D: np.ndarray
    Y: np.ndarray
    approx: Any
    record: Any


class _GP:
    """The one implementation behind the GP classes: q independent SE-ARD GPs on shared inputs
    in one core model. `GaussianProcess` and its sparse counterpart are the q = 1 case (``outputs.py``:
    with ``_squeeze`` their results drop the output axis). Subclasses give the class name
    (``_kind``), the target's name in messages (``_target``), and the approximation
    (``_approximation``, exact unless overridden) with its file entries (``_read_extra``)."""

    #: The class name, in messages and as the ``kind`` of saved files.
    _kind = "_GP"
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
        self._kernel = self._make_kernel(sigma_f, lengthscales, sigma_eps, bounds)
        self.optimizer = one_of("optimizer", optimizer, ("L-BFGS-B", None))
        self.n_restarts = integer("n_restarts", n_restarts)
        self.random_state = check_random_state("random_state", random_state)
        self.maxiter = integer("maxiter", maxiter, low=1)
        self.mean = _priors.check_mean(mean)
        self.normalize = boolean("normalize", normalize)
        self.hyperprior = _priors.check_hyperprior(hyperprior)
        self._fitted: Optional[_Fit] = None
        self._diagnostics: Optional[tuple] = None  # (the _Fit they describe, the list)

    def _make_kernel(self, sigma_f: Any, lengthscales: Any, sigma_eps: Any, bounds: Any) -> SEKernel:
        """The kernel of these values (the output-count classes check the shapes they take)."""
        return SEKernel(sigma_f, lengthscales, sigma_eps, bounds)

    def _approximation(self) -> Any:
        """The approximation a fit uses (the sparse classes return theirs, built from their
        settings as they are now)."""
        return EXACT

    @classmethod
    def _read_extra(cls, f: NpzReader, nd: int, q: int) -> tuple:
        """(constructor settings, inducing points) a saved file holds beyond the exact GP's."""
        return {}, None

    # -- the kernel --------------------------------------------------------------------------

    @property
    def kernel(self) -> SEKernel:
        """The kernel with the current hyperparameters and their bounds.

        Before ``fit`` the initial values given; after it the fitted ones (from the core
        model: theta has one home).
        """
        fit = self._fitted
        return self._kernel if fit is None else self._kernel.with_theta(fit.model.thetas)

    def _set_kernel(self, **values: Any) -> None:
        """Set hyperparameters or bounds (natural units): before ``fit`` the initial values; on a
        fitted GP the model is factored again at the new values (no optimisation)."""
        current = dict(sigma_f=self.sigma_f, lengthscales=self.lengthscales, sigma_eps=self.sigma_eps,
                       bounds=self._kernel.bounds)
        current.update(values)
        new = self._make_kernel(**current)
        fit = self._fitted
        if fit is None:
            self._kernel = new
            return
        q, nd = fit.model.n_outputs, fit.model.dim
        if set(values) != {"bounds"}:
            self._refactor_rows(new.theta(q, nd))
        self._kernel = self._kernel.with_bounds(new.bounds)

    @property
    def bounds(self) -> np.ndarray:
        """(low, high) of sigma_f, the length-scales and sigma_eps in natural units, shape (3, 2)
        or (n_d + 2, 2): the fit keeps theta within their logarithms."""
        return self._kernel.bounds

    @bounds.setter
    def bounds(self, value: Any) -> None:
        self._set_kernel(bounds=value)

    # -- state -------------------------------------------------------------------------------

    @property
    def _core_model(self) -> Any:
        """The fitted core model (`gpmhe._core.MultiGP` or `SparseMultiGP`), or None."""
        fit = self._fitted
        return None if fit is None else fit.model

    def _fit_state(self) -> _Fit:
        fit = self._fitted
        if fit is None:
            raise NotFittedError(f"this {self._kind} is not fitted yet; call fit(D, {self._target}) first")
        return fit

    def _model(self) -> Any:
        return self._fit_state().model

    def _residuals(self) -> np.ndarray:
        """The targets the GPs regress: y − m(D) with the fitted prior mean."""
        fit = self._fit_state()
        return _priors.residuals(fit.model.mean, fit.D, fit.Y)

    def _theta_rows(self, value: Any) -> np.ndarray:
        """A theta argument of the fitted model (n_d + 2,) or (q, n_d + 2) as (q, n_d + 2)."""
        m = self._model()
        theta = float_array("theta", value, 1 if self._squeeze else 2)
        shape = (m.dim + 2,) if self._squeeze else (m.n_outputs, m.dim + 2)
        if theta.shape != shape:
            raise ValueError(f"theta: expected shape {shape}, got {theta.shape}")
        return theta.reshape(m.n_outputs, m.dim + 2)

    def _refactor(self, theta: Any) -> None:
        """Factor the fitted model again at a new theta (no optimisation)."""
        self._refactor_rows(self._theta_rows(theta))

    def _refactor_rows(self, rows: np.ndarray) -> None:
        fit = self._fit_state()
        model = fit.approx.rebuild(fit.model, fit.D, self._residuals(), np.ascontiguousarray(rows))
        self._fitted = _Fit(model, fit.D, fit.Y, fit.approx, None)

    @property
    def dim(self) -> int:
        """Input dimension n_d of the fitted model.

        The number of columns of the training inputs; raises `NotFittedError` before ``fit``.
        """
        return self._model().dim

    @property
    def D_train(self) -> np.ndarray:
        """Training inputs, shape (N, n_d).

        Those of the last successful ``fit``; raises `NotFittedError` before it.
        """
        return self._fit_state().D.copy()

    def _out(self, a: np.ndarray) -> np.ndarray:
        """A per-point result (k, q, ...) as it is returned: (k, ...) for one output."""
        return a.reshape(a.shape[:1] + a.shape[2:]) if self._squeeze else a

    # -- fitting -----------------------------------------------------------------------------

    def _fit(self, D: Any, Y: Any, y_ndim: int) -> "_GP":
        D, Y = training_set(D, Y, y_ndim)
        if y_ndim == 1:
            Y = Y.reshape(-1, 1)
        q, nd = Y.shape[1], D.shape[1]
        approx = self._approximation()
        coef = _priors.fit_mean(self.mean, D, Y)
        R = _priors.residuals(coef, D, Y)
        theta0 = self.kernel.theta(q, nd)
        fitting = None
        if self.optimizer is not None:
            fitting = Fitting(self._kernel.log_bounds(nd), _priors.log_scales(self.normalize, D, R),
                              _priors.prior_rows(self.hyperprior, nd), np.random.default_rng(self.random_state),
                              self.n_restarts, self.maxiter)
        model, record = approx.fit(D, R, coef, theta0, fitting)
        self._fitted = _Fit(model, D, Y, approx, record)
        return self

    def _log_marginal_likelihood(self, theta: Any, eval_gradient: bool) -> tuple:
        """(objective (q,), grad (q, n_d + 2) or None) at theta, None for the current one."""
        fit = self._fit_state()
        eval_gradient = boolean("eval_gradient", eval_gradient)
        rows = None if theta is None else self._theta_rows(theta)
        return fit.approx.objective(fit.model, fit.D, self._residuals(), rows, eval_gradient)

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
        and leave-one-out errors (closed form: one dense O(N³) factorisation per output for an exact
        GP, O(N m²) for a sparse one; computed once per fit) against the noise level and against a straight line.

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
        fit = self._fit_state()
        cached = self._diagnostics
        if cached is None or cached[0] is not fit:
            m = fit.model
            cached = (fit, diagnose(fit.D, self._residuals(), m.thetas, m.log_marginal_likelihoods(), fit.record,
                                    fit.approx.loo(m, fit.D)))
            self._diagnostics = cached
        return list(cached[1])

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
        fit = self._fit_state()
        title = f'{self._kind} (mean="{self.mean}", N={fit.D.shape[0]})'
        return summary_table(title, self.diagnostics())

    # -- prediction --------------------------------------------------------------------------

    def predict(self, D: Any, return_std: bool = False):
        m = self._model()
        D = points("D", D, m.dim)
        if not boolean("return_std", return_std):
            return self._out(m.predict_mean(D))
        mean, var = m.predict(D)
        return self._out(mean), np.sqrt(self._out(var))

    def predict_with_gradients(self, D: Any) -> tuple:
        m = self._model()
        mean, var, dmean, dvar = m.predict_with_gradients(points("D", D, m.dim))
        return self._out(mean), self._out(var), self._out(dmean), self._out(dvar)

    # -- persistence -------------------------------------------------------------------------

    def save(self, path: Union[str, os.PathLike]) -> None:
        fit = self._fit_state()
        model = fit.model
        theta, Y = model.thetas, fit.Y
        if self._squeeze:
            theta, Y = theta[0], Y[:, 0]
        prior_mean = {} if model.mean is None else {"mean_coefficients": model.mean}
        np.savez(path, format_version=_FORMAT_VERSION, kind=self._kind, D=fit.D, y=Y, theta=theta,
                 **prior_mean, **self._approximation().save_entries(model), **_settings(self))

    @classmethod
    def load(cls, path: Union[str, os.PathLike]) -> "_GP":
        # Every entry is checked (a ValueError names the file and the entry): see gpmhe._npz.
        with NpzReader(path, cls._kind, _FORMAT_VERSION) as f:
            D = f.floats("D", (None, None))
            nd = D.shape[1]
            y_shape, t_shape = ((None,), (nd + 2,)) if cls._squeeze else ((None, None), (None, nd + 2))
            Y, theta = f.floats("y", y_shape), f.floats("theta", t_shape)
            q = 1 if cls._squeeze else theta.shape[0]
            extra, inducing = cls._read_extra(f, nd, q)
            try:
                gp = cls(**extra, **_settings_from(f))
            except ValueError as e:
                raise ValueError(f"path: {f.name}: bad settings ({e})") from None
            coef = None if gp.mean == "zero" else f.floats("mean_coefficients", (q, nd + 1))
            name = f.name
        if cls._squeeze:
            Y, theta = Y.reshape(-1, 1), theta.reshape(1, -1)
        approx = gp._approximation()
        try:
            model = approx.load_model(D, _priors.residuals(coef, D, Y), theta, coef, inducing)
        except (ValueError, NumericalError) as e:
            entries, what = ("'D', 'y', 'theta', 'inducing'", "sparse GP") if approx.sparse else ("'D', 'y', 'theta'", "GP")
            raise ValueError(f"path: {name}: entries {entries} do not make a {what} ({e})") from None
        gp._fitted = _Fit(model, D, Y, approx, None)
        return gp
