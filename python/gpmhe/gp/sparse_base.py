"""`_SparseGP`: what `SparseGaussianProcess` and `SparseMultiOutputGP` (``sparse.py``) share: the
VFE or FITC training objective on inducing points (the Rust core's `SparseMultiGP`), fitting,
saving and the inducing points; the exact classes supply the rest."""


from __future__ import annotations

import os
from typing import Any, Callable, List, Optional, Tuple, Union

import numpy as np

from gpmhe import _core
from gpmhe._core import NumericalError
from gpmhe._npz import NpzReader
from gpmhe._validation import boolean, float_array, integer, one_of, training_set
from gpmhe.gp import priors as _priors
from gpmhe.gp.base import _ExactGP, _settings, _settings_from
from gpmhe.gp.diagnostics import sparse_loo
from gpmhe.gp.fit import _maximise, _posterior
from gpmhe.gp.kernel import DEFAULT_BOUNDS, _Theta

__all__: list = []

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
        """``loo(o, r)`` of `gpmhe.gp.diagnostics.diagnose`: the sparse model's, O(N m²)."""
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


