"""Sparse (inducing-point) GP regression with the SE-ARD kernel, for thousands of training points.

``SparseGaussianProcess`` and ``SparseMultiOutputGP`` are the sparse counterparts of
`gpmhe.GaussianProcess` and `gpmhe.MultiOutputGP` (and subclasses of them: they take the same
arguments, have the same attributes and methods, and work wherever those do, in
`gpmhe.LearnedModel`, `gpmhe.GPMHE` and the GP-EKF). Each output is summarised by m inducing
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
import types
from typing import Any, Callable, List, Optional, Tuple, Union

import numpy as np

from gpmhe import _core, _priors
from gpmhe._core import NumericalError
from gpmhe._npz import NpzReader
from gpmhe.diagnostics import sparse_loo
from gpmhe._validation import boolean, float_array, integer, one_of, training_set
from gpmhe.gp import (
    DEFAULT_BOUNDS,
    GaussianProcess,
    MultiOutputGP,
    _ExactGP,
    _maximise,
    _posterior,
    _settings,
    _settings_from,
    _Theta,
)

__all__ = ["SparseGaussianProcess", "SparseMultiOutputGP"]

#: The approximations.
METHODS = ("vfe", "fitc")

_FORMAT_VERSION = 2  # 2: prior mean, normalize, hyperprior


def _objective(D: np.ndarray, y: np.ndarray, Z: np.ndarray, method: str):
    """The sparse training objective and its theta-gradient as a function of theta (Z fixed)."""

    def objective(theta: np.ndarray) -> Tuple[float, np.ndarray]:
        value, grad, _ = _core.sparse_objective(D, y, Z, np.ascontiguousarray(theta), method, True)
        return float(value), np.asarray(grad)

    return objective


def _joint_objective(D: np.ndarray, y: np.ndarray, method: str, shift: np.ndarray, prior: Any):
    """The objective plus log-prior as a function of [t, Z.ravel()] with theta = t + shift (the
    optimiser's units, see `gpmhe.gp._posterior`), with its gradient."""
    nd = D.shape[1]

    def objective(packed: np.ndarray) -> Tuple[float, np.ndarray]:
        t, Z = packed[: nd + 2], packed[nd + 2 :].reshape(-1, nd)
        value, grad, gz = _core.sparse_objective(
            D, y, np.ascontiguousarray(Z), np.ascontiguousarray(t + shift), method, True
        )
        lp, lp_grad = _priors.log_prior(prior, t)
        return float(value) + lp, np.concatenate([grad + lp_grad, gz.ravel()])

    return objective


class _SparseGP:
    """The sparse behaviour, placed before `GaussianProcess` or `MultiOutputGP` in a class's bases:
    it replaces what differs from the exact GP (the constructor's extra settings, the fit, the
    training objective, the refactoring at a new theta, save and load) and adds the inducing
    points; everything else (theta, the natural-unit attributes, predictions, training data,
    jitter) is the exact classes' code working on a ``_core.SparseMultiGP``, which has the same
    prediction methods as ``_core.MultiGP``."""

    def __init__(
        self,
        n_inducing: int = 100,
        method: str = "vfe",
        inducing: Any = None,
        optimize_inducing: bool = False,
        sigma_f: Union[float, np.ndarray] = 1.0,
        lengthscales: Any = 1.0,
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
        _ExactGP.__init__(
            self, sigma_f=sigma_f, lengthscales=lengthscales, sigma_eps=sigma_eps,
            optimizer=optimizer, n_restarts=n_restarts, bounds=bounds,
            random_state=random_state, maxiter=maxiter, mean=mean, normalize=normalize,
            hyperprior=hyperprior,
        )
        self.n_inducing = integer("n_inducing", n_inducing, low=1)
        self.method = one_of("method", method, METHODS)
        self.inducing = self._check_inducing(inducing)
        self.optimize_inducing = boolean("optimize_inducing", optimize_inducing)

    # -- inducing points ---------------------------------------------------------------------

    def _check_inducing(self, inducing: Any) -> Any:
        """None, a finite (m, n_d) array or (multi-output only) a list of q such arrays."""
        if inducing is None:
            return None
        if isinstance(inducing, (list, tuple)) and not self._squeeze and inducing and \
                all(np.ndim(z) == 2 for z in inducing):
            return [float_array("inducing", z, 2, copy=True) for z in inducing]
        z = float_array("inducing", inducing, 2, copy=True)
        if z.shape[0] < 1 or z.shape[1] < 1:
            raise ValueError(f"inducing: expected shape (m, n_d) with m >= 1, got {z.shape}")
        return z

    def _fixed_inducing(self, q: int, nd: int) -> Optional[List[np.ndarray]]:
        """The given inducing points as q (m_o, n_d) arrays, or None (choose them)."""
        if self.inducing is None:
            return None
        zs = self.inducing if isinstance(self.inducing, list) else [self.inducing] * q
        if len(zs) != q:
            raise ValueError(f"inducing: expected {q} sets of inducing points (one per output), got {len(zs)}")
        for z in zs:
            if z.shape[1] != nd or z.shape[0] < 1:
                raise ValueError(f"inducing: expected shape (m, {nd}), got {z.shape}")
        return zs

    def _select(self, D: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """n_inducing rows of D by greedy conditional-variance selection under theta's kernel."""
        idx = _core.select_inducing(D, np.ascontiguousarray(theta), self.n_inducing)
        return np.ascontiguousarray(D[idx])

    # -- fitting -----------------------------------------------------------------------------

    def _fit(self, D: Any, Y: Any, y_ndim: int) -> "_SparseGP":
        D, Y = training_set(D, Y, y_ndim)
        if y_ndim == 1:
            Y = Y.reshape(-1, 1)
        q, nd = Y.shape[1], D.shape[1]
        coef = _priors.fit_mean(self.mean, D, Y)
        R = _priors.residuals(coef, D, Y)
        theta = _Theta.from_natural(self.sigma_f, self.lengthscales, self.sigma_eps, q, nd)
        fixed = self._fixed_inducing(q, nd)
        record = None
        if self.optimizer is None:
            zs = [fixed[o] if fixed is not None else self._select(D, theta[o]) for o in range(q)]
        else:
            theta, zs, record = self._optimise(D, R, theta, fixed)
        self._set_model(_core.SparseMultiGP(D, R, zs, np.ascontiguousarray(theta), self.method, coef), D, Y)
        self._fit_record = record
        return self

    def _optimise(self, D: np.ndarray, R: np.ndarray, theta0: np.ndarray,
                  fixed: Optional[List[np.ndarray]]) -> Tuple[np.ndarray, List[np.ndarray], Tuple[np.ndarray, list]]:
        """(theta (q, n_d + 2), inducing points per output, the fit's record): each output's
        training objective plus log-prior maximised from theta0, in the optimiser's units
        t = theta − log_scales as for the exact GP. Chosen points: optimise theta, choose them
        again under the fitted kernel, refine theta, and keep the better round."""
        q, nd = R.shape[1], D.shape[1]
        log_bounds = _Theta.log_bounds(self.bounds, nd)
        shift = _priors.log_scales(self.normalize, D, R)
        prior = _priors.prior_rows(self.hyperprior, nd)
        rng = np.random.default_rng(self.random_state)
        rows, zs, runs = [], [], []
        for o in range(q):  # a loop: _maximise's warning's stacklevel counts frames
            y, t = np.ascontiguousarray(R[:, o]), theta0[o] - shift[o]
            z = fixed[o] if fixed is not None else self._select(D, theta0[o])
            best, values = None, []
            for i, restarts in enumerate([self.n_restarts] if fixed is not None else [self.n_restarts, 0]):
                if i > 0:
                    z = self._select(D, t + shift[o])
                objective = _posterior(_objective(D, y, z, self.method), shift[o], prior)
                t, value, run_values = _maximise(objective, t, log_bounds, restarts, rng, self.maxiter)
                values.extend(run_values)
                if best is None or value > best[0]:
                    best = (value, t.copy(), z)
            _, t, z = best
            if self.optimize_inducing:
                box = np.tile(np.column_stack([D.min(axis=0), D.max(axis=0)]), (z.shape[0], 1))
                packed = _maximise(_joint_objective(D, y, self.method, shift[o], prior),
                                   np.concatenate([t, z.ravel()]), np.vstack([log_bounds, box]), 0, rng,
                                   self.maxiter)[0]
                t, z = packed[: nd + 2], np.ascontiguousarray(packed[nd + 2 :].reshape(-1, nd))
            rows.append(t + shift[o])
            zs.append(z)
            runs.append(np.array(values))
        return np.array(rows), zs, (log_bounds[None, :, :] + shift[:, :, None], runs)

    def _refactor(self, theta: Any) -> None:
        """Factor the fitted model again at a new theta, with the same inducing points."""
        m = self._model()
        model = _core.SparseMultiGP(self._D, self._residuals(), m.inducing, self._theta_rows(theta), m.method,
                                    m.mean)
        self._set_model(model, self._D, self._Y)
        self._fit_record = None

    def _log_marginal_likelihood(self, theta: Any, eval_gradient: bool) -> Tuple[np.ndarray, Any]:
        """(objective (q,), grad (q, n_d + 2) or None) at theta, None for the current one."""
        m = self._model()
        eval_gradient = boolean("eval_gradient", eval_gradient)
        if theta is None and not eval_gradient:
            return m.log_marginal_likelihoods(), None
        theta = m.thetas if theta is None else self._theta_rows(theta)
        R = self._residuals()
        res = [
            _core.sparse_objective(self._D, np.ascontiguousarray(R[:, o]), z,
                                   np.ascontiguousarray(theta[o]), m.method, eval_gradient)
            for o, z in enumerate(m.inducing)
        ]
        return np.array([r[0] for r in res]), np.array([r[1] for r in res])

    def _loo(self) -> Callable:
        """``loo(o, r)`` of `gpmhe.diagnostics.diagnose`: the sparse model's, O(N m²)."""
        m = self._model()
        zs, thetas, jitters, fitc = m.inducing, m.thetas, m.jitters, m.method == "fitc"
        return lambda o, r: sparse_loo(self._D, r, zs[o], thetas[o], float(jitters[o]), fitc)

    # -- persistence -------------------------------------------------------------------------

    def save(self, path: Union[str, os.PathLike]) -> None:
        m = self._model()
        theta, Y = m.thetas, self._Y
        if self._squeeze:
            theta, Y = theta[0], Y[:, 0]
        zs = m.inducing
        prior_mean = {} if m.mean is None else {"mean_coefficients": m.mean}
        np.savez(
            path, format_version=_FORMAT_VERSION, kind=self._kind, D=self._D, y=Y, theta=theta, **prior_mean,
            inducing=np.vstack(zs), inducing_counts=np.array([len(z) for z in zs], dtype=np.int64),
            method=m.method, n_inducing=self.n_inducing, optimize_inducing=self.optimize_inducing,
            inducing_given=self.inducing is not None, **_settings(self),
        )

    @classmethod
    def load(cls, path: Union[str, os.PathLike]) -> "_SparseGP":
        # Every entry is checked (a ValueError names the file and the entry): see gpmhe._npz.
        with NpzReader(path, cls._kind, _FORMAT_VERSION) as f:
            D = f.floats("D", (None, None))
            nd = D.shape[1]
            y_shape, t_shape = ((None,), (nd + 2,)) if cls._squeeze else ((None, None), (None, nd + 2))
            Y, theta = f.floats("y", y_shape), f.floats("theta", t_shape)
            Z, counts = f.floats("inducing", (None, nd)), f.array("inducing_counts", "i", (None,))
            q = 1 if cls._squeeze else theta.shape[0]
            if len(counts) != q or np.any(counts < 1) or counts.sum() != len(Z):
                raise f.error("inducing_counts", f"must be {q} positive counts summing to {len(Z)}")
            zs = np.split(Z, np.cumsum(counts)[:-1])
            given = f.boolean("inducing_given")
            try:
                gp = cls(n_inducing=f.integer("n_inducing", 1), method=f.string("method"),
                         inducing=(zs[0] if cls._squeeze else list(zs)) if given else None,
                         optimize_inducing=f.boolean("optimize_inducing"), **_settings_from(f))
            except ValueError as e:
                raise ValueError(f"path: {f.name}: bad settings ({e})") from None
            coef = None if gp.mean == "zero" else f.floats("mean_coefficients", (q, nd + 1))
            name = f.name
        if cls._squeeze:
            Y, theta = Y.reshape(-1, 1), theta.reshape(1, -1)
        try:
            model = _core.SparseMultiGP(D, _priors.residuals(coef, D, Y), [np.ascontiguousarray(z) for z in zs],
                                        theta, gp.method, coef)
        except (ValueError, NumericalError) as e:
            raise ValueError(f"path: {name}: entries 'D', 'y', 'theta', 'inducing' do not make a "
                             f"sparse GP ({e})") from None
        gp._set_model(model, D, Y)
        return gp

    # -- attributes --------------------------------------------------------------------------

    @property
    def inducing_points(self) -> Union[np.ndarray, List[np.ndarray]]:
        """Inducing inputs of the fitted model.

        An (m, n_d) array for `SparseGaussianProcess`; for `SparseMultiOutputGP` a list with one
        (m_o, n_d) array per output (each output has its own, chosen under its own kernel). m can
        be smaller than ``n_inducing``: see the user guide, *Sparse GPs*.
        """
        zs = self._model().inducing
        return zs[0] if self._squeeze else zs


# ----------------------------------------------------------------------------- docstrings

# The docstrings of the methods both public classes have, written once (as gpmhe.gp does for the
# exact classes): `_sparse_documented` fills in text `which` of each field below.
_DOCS = {
    "fit": """Fit the sparse GP{s} to training data: choose the inducing points and the hyperparameters.

Without given ``inducing`` points, ``n_inducing`` training inputs are chosen by greedy
conditional-variance selection under the initial kernel; with an optimizer the training
objective is maximised over theta, the points are chosen again under the fitted kernel, and theta
is refined. With ``optimize_inducing`` the inducing inputs are then optimised jointly with theta.

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
>>> from gpmhe import {cls}
>>> rng = np.random.default_rng(0)
>>> D = np.linspace(0.0, 10.0, 500)[:, None]
>>> gp = {cls}(n_inducing=5).fit(D, {example_targets} + 0.1 * rng.standard_normal({noise_shape}))
>>> {n_inducing_example}
""",
    "diagnostics": """Diagnostics of the fit, one `gpmhe.diagnostics.FitDiagnostics` per output.

As for the exact GP: the fitted hyperparameters, which of them sit at a bound, every optimiser
run's objective, and leave-one-out errors against the noise level and against a straight line.
The LOO errors are those of the sparse model itself (the Gaussian model with covariance
Qff + Lambda), in closed form in O(N m^2) per output, computed once per fit.

Returns
-------
list of FitDiagnostics
    One per output{one_for}.

Raises
------
NotFittedError
    Before ``fit``.

Examples
--------
>>> import numpy as np
>>> from gpmhe import {cls}
>>> D = np.linspace(0.0, 10.0, 500)[:, None]
>>> gp = {cls}(n_inducing=20, mean="linear").fit(D, {example_targets} + {trend})
>>> [d.collapsed for d in gp.diagnostics()]
{collapsed_example}
""",
    "log_marginal_likelihood": """The training objective: the VFE bound or FITC's log marginal likelihood.

For ``method="vfe"`` this is Titsias' collapsed lower bound on log p(y | D, theta); for
``method="fitc"`` the log marginal likelihood of the FITC model. Both are evaluated with the
fitted inducing points.

Parameters
----------
theta : array_like of shape {theta_shape} or None, default None
    Log-hyperparameters at which to evaluate it; None uses the current ``theta``.
eval_gradient : bool, default False
    Also return the gradient with respect to theta.

Returns
-------
objective : {obj_type}
    The training objective.
grad : ndarray of shape {theta_shape}
    Its gradient with respect to theta; only returned if ``eval_gradient`` is True.

Examples
--------
With the inducing points at the training inputs, VFE's bound is the exact GP's log marginal
likelihood:

>>> import numpy as np
>>> from gpmhe import {exact_cls}, {cls}
>>> D = np.linspace(0.0, 5.0, 20)[:, None]
>>> Y = {example_targets}
>>> exact = {exact_cls}(optimizer=None).fit(D, Y)
>>> sparse = {cls}(inducing=D, optimizer=None).fit(D, Y)
>>> bool(np.allclose(sparse.log_marginal_likelihood(), exact.log_marginal_likelihood()))
True
""",
    "predict": """Posterior mean{s}, and optionally latent standard deviation{s}, at test points.

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
mean : ndarray of shape {k_shape}
    Posterior means.
std : ndarray of shape {k_shape}
    Latent posterior standard deviations; only returned if ``return_std`` is True.

Examples
--------
>>> import numpy as np
>>> from gpmhe import {cls}
>>> D = np.linspace(0.0, 10.0, 300)[:, None]
>>> gp = {cls}(n_inducing=15, sigma_eps=0.01, optimizer=None).fit(D, {example_targets})
>>> mean, std = gp.predict([[5.0], [100.0]], return_std=True)
>>> bool(np.all(std[0] < 0.05)), bool(np.allclose(std[1], gp.sigma_f))
(True, True)
""",
    "predict_with_gradients": """Posterior mean{s} and latent variance{s} with their gradients with respect to the input.

Parameters
----------
D : array_like of shape (k, n_d)
    Test points.

Returns
-------
mean : ndarray of shape {k_shape}
    Posterior means.
var : ndarray of shape {k_shape}
    Latent (noise-free) posterior variances.
dmean_dd : ndarray of shape {kd_shape}
    Gradients of the means with respect to d.
dvar_dd : ndarray of shape {kd_shape}
    Gradients of the variances with respect to d.

Examples
--------
>>> import numpy as np
>>> from gpmhe import {cls}
>>> D = np.linspace(0.0, 5.0, 200)[:, None]
>>> gp = {cls}(n_inducing=15, sigma_eps=0.01, optimizer=None).fit(D, {example_targets})
>>> mean, var, dmean, dvar = gp.predict_with_gradients([[1.0]])
>>> dmean.shape
{dmean_shape}
""",
    "save": """Save the fitted model, its inducing points and its settings to an ``.npz`` file (no pickle).

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
>>> from gpmhe import {cls}
>>> D = np.linspace(0.0, 5.0, 50)[:, None]
>>> gp = {cls}(n_inducing=10, optimizer=None).fit(D, {example_targets})
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

Examples
--------
>>> import io
>>> import numpy as np
>>> from gpmhe import {cls}
>>> D = np.linspace(0.0, 5.0, 50)[:, None]
>>> buf = io.BytesIO()
>>> {cls}(n_inducing=10, method="fitc", optimizer=None).fit(D, {example_targets}).save(buf)
>>> _ = buf.seek(0)
>>> {cls}.load(buf).method
'fitc'
""",
}

# Each field's text for SparseGaussianProcess, then for SparseMultiOutputGP.
_DOC_FIELDS = {
    "cls": ("SparseGaussianProcess", "SparseMultiOutputGP"),
    "exact_cls": ("GaussianProcess", "MultiOutputGP"),
    "one_for": (" (one for `SparseGaussianProcess`)", ""),
    "collapsed_example": ("[False]", "[False, False]"),
    "trend": ("0.5 * D[:, 0]", "0.5 * D"),
    "s": ("", "s"),
    "target": ("""y : array_like of shape (N,)
    Training targets.""", """Y : array_like of shape (N, q) or (N,)
    Training targets, one column per output (a 1-D Y is one output)."""),
    "example_targets": ("np.sin(D[:, 0])", "np.column_stack([np.sin(D[:, 0]), np.cos(D[:, 0])])"),
    "n_inducing_example": ("gp.inducing_points.shape\n(5, 1)",
                           "[z.shape for z in gp.inducing_points]\n[(5, 1), (5, 1)]"),
    "noise_shape": ("500", "(500, 2)"),
    "theta_shape": ("(n_d + 2,)", "(q, n_d + 2)"),
    "obj_type": ("float", "ndarray of shape (q,)"),
    "k_shape": ("(k,)", "(k, q)"),
    "kd_shape": ("(k, n_d)", "(k, q, n_d)"),
    "dmean_shape": ("(1, 1)", "(1, 2, 1)"),
    "inducing_multi": ("", " (the same for every output); a list of q (m_o, n_d) arrays gives each output its own"),
}


def _sparse_documented(which: int) -> Any:
    """Class decorator: the class's own copies of ``__init__``, the methods in ``_DOCS`` (with
    their docstrings filled in with text ``which`` of each field) and ``inducing_points``, so the
    API reference and the docstring checks see them on the class (see gpmhe.gp._documented)."""

    def own_copy(cls: type, f: Any, doc: Optional[str]) -> Any:
        g = types.FunctionType(f.__code__, f.__globals__, f.__name__, f.__defaults__, f.__closure__)
        g.__kwdefaults__, g.__module__, g.__doc__ = f.__kwdefaults__, __name__, doc
        g.__qualname__ = f"{cls.__name__}.{f.__name__}"
        g.__annotations__ = dict(f.__annotations__)
        return g

    def decorate(cls: type) -> type:
        cls.__init__ = own_copy(cls, _SparseGP.__init__, None)
        fields = {key: texts[which] for key, texts in _DOC_FIELDS.items()}
        params = _COMMON_PARAMETERS.format(**fields).replace("\n", "\n    ")
        cls.__doc__ = cls.__doc__.replace("%PARAMETERS%", params)
        for name, template in _DOCS.items():
            member = next(base.__dict__[name] for base in cls.__mro__ if name in base.__dict__)
            doc = template.format(**fields)
            if isinstance(member, classmethod):
                setattr(cls, name, classmethod(own_copy(cls, member.__func__, doc)))
            else:
                setattr(cls, name, own_copy(cls, member, doc))
        cls.inducing_points = _SparseGP.__dict__["inducing_points"]
        return cls

    return decorate


_COMMON_PARAMETERS = """n_inducing : int, default 100
    Number of inducing points m to choose from the training inputs (at most N; fewer when the
    remaining inputs are determined by the chosen ones, e.g. duplicated inputs).
method : {{"vfe", "fitc"}}, default "vfe"
    The approximation: VFE (Titsias' variational bound, GPflow's SGPR) or FITC (GPflow's
    GPRFITC). VFE is the default: its objective is a lower bound on the exact log marginal
    likelihood, so more inducing points never make it worse, and it does not underestimate the
    noise as FITC can.
inducing : array_like of shape (m, n_d) or None, default None
    Fixed inducing inputs instead of choosing them{inducing_multi}.
optimize_inducing : bool, default False
    Also optimise the inducing inputs jointly with theta (m n_d more parameters, within the
    bounding box of the training inputs) after the hyperparameter fit.
sigma_f, lengthscales, sigma_eps, optimizer, n_restarts, bounds, random_state, maxiter
    As for `{exact_cls}`: initial hyperparameters (kept with ``optimizer=None``) and the
    settings of the L-BFGS-B fit of the training objective.
mean, normalize, hyperprior
    As for `{exact_cls}`: the prior mean fitted by least squares first (the sparse GP
    regresses y − m(d)), the data-relative units of ``bounds`` and ``hyperprior``, and the
    log-normal hyperparameter priors added to the training objective."""


@_sparse_documented(0)
class SparseGaussianProcess(_SparseGP, GaussianProcess):
    """Sparse GP regression of one output with the SE-ARD kernel and m inducing points.

    The model of `GaussianProcess` (y_i = f(d_i) + eps_i, f ~ GP(0, k)), approximated through the
    values of f at m inducing inputs Z: fitting costs O(N m^2) per objective evaluation and
    O(N + m^2) memory instead of O(N^3) and O(N^2), and a prediction O(m^2) per point instead of
    O(N^2). With Kuu = K(Z, Z), Kuf = K(Z, D), Qff = Kfu Kuu^-1 Kuf and the diagonal noise
    Lambda = sigma_eps^2 I (VFE) or diag(Kff - Qff) + sigma_eps^2 I (FITC), ``fit`` maximises::

        F = log N(y | 0, Qff + Lambda) - [VFE only] tr(Kff - Qff) / (2 sigma_eps^2)

    and with P = Kuu + Kuf Lambda^-1 Kfu the posterior at d* has mean
    k*^T P^-1 Kuf Lambda^-1 y and latent variance sigma_f^2 - k*^T (Kuu^-1 - P^-1) k*, which
    returns to sigma_f^2 far from the inducing points (it does not collapse to 0 as DTC's
    does). With Z equal to the training inputs both methods reproduce `GaussianProcess`.

    A subclass of `GaussianProcess`: every attribute and method of it is available, and it works
    wherever the exact GP does.

    Parameters
    ----------
    %PARAMETERS%

    Attributes
    ----------
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

    _kind = "SparseGaussianProcess"

    def __repr__(self) -> str:
        if self._core_model is None:
            return f"SparseGaussianProcess(method={self.method!r}, n_inducing={self.n_inducing}, not fitted)"
        m = self._core_model
        return f"SparseGaussianProcess(method={m.method!r}, m={len(m.inducing[0])}, N={m.n_train}, fitted)"


@_sparse_documented(1)
class SparseMultiOutputGP(_SparseGP, MultiOutputGP):
    """Independent sparse SE-ARD GPs, one per output column, on shared inputs.

    Each output o is a `SparseGaussianProcess` of its own, with its own hyperparameters and its
    own inducing points (chosen under its own kernel). A subclass of `MultiOutputGP`, so it can
    serve as the f- and h-GPs of a `LearnedModel` (``LearnedModel.from_trajectories(...,
    n_inducing=...)`` builds them), and `GPMHE` and the GP-EKF run on it unchanged.

    Parameters
    ----------
    %PARAMETERS%

    Attributes
    ----------
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

    _kind = "SparseMultiOutputGP"

    def __repr__(self) -> str:
        if self._core_model is None:
            return f"SparseMultiOutputGP(method={self.method!r}, n_inducing={self.n_inducing}, not fitted)"
        m = self._core_model
        return (f"SparseMultiOutputGP(q={m.n_outputs}, n_d={m.dim}, N={m.n_train}, method={m.method!r}, "
                f"m={[len(z) for z in m.inducing]}, fitted)")
