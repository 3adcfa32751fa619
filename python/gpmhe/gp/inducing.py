"""`Sparse`, the inducing-point approximation (VFE or FITC) a sparse GP class delegates to, as
``exact.py``'s `EXACT` is for the exact ones: its settings, the choice of inducing points, the
training objective (the Rust core's `sparse_objective`), the fit, the leave-one-out errors and
the file entries of `gpmhe._core.SparseMultiGP` models."""

from __future__ import annotations

from typing import Any, Callable, List, Optional, Tuple

import numpy as np

from gpmhe import _core
from gpmhe._validation import boolean, float_array, integer, one_of
from gpmhe.gp import priors as _priors
from gpmhe.gp.diagnostics import sparse_loo
from gpmhe.gp.fit import Fitting, _maximise, _posterior

__all__: list = []

#: The approximations.
METHODS = ("vfe", "fitc")


def _objective(D: np.ndarray, y: np.ndarray, Z: np.ndarray, method: str):
    """The sparse training objective and its theta-gradient as a function of theta (Z fixed)."""

    def objective(theta: np.ndarray) -> Tuple[float, np.ndarray]:
        value, grad, _ = _core.sparse_objective(D, y, Z, np.ascontiguousarray(theta), method, True)
        return float(value), np.asarray(grad)

    return objective


def _joint_objective(D: np.ndarray, y: np.ndarray, method: str, shift: np.ndarray, prior: Any):
    """The objective plus log-prior as a function of [t, Z.ravel()] with theta = t + shift (the
    optimiser's units, see `gpmhe.gp.fit._posterior`), with its gradient."""
    nd = D.shape[1]

    def objective(packed: np.ndarray) -> Tuple[float, np.ndarray]:
        t, Z = packed[: nd + 2], packed[nd + 2 :].reshape(-1, nd)
        value, grad, gz = _core.sparse_objective(
            D, y, np.ascontiguousarray(Z), np.ascontiguousarray(t + shift), method, True
        )
        lp, lp_grad = _priors.log_prior(prior, t)
        return float(value) + lp, np.concatenate([grad + lp_grad, gz.ravel()])

    return objective


def check_inducing(inducing: Any, one_output: bool) -> Any:
    """The ``inducing`` setting: None, a finite (m, n_d) array or (several outputs only) a list
    of such arrays, one per output."""
    if inducing is None:
        return None
    if isinstance(inducing, (list, tuple)) and not one_output and inducing and \
            all(np.ndim(z) == 2 for z in inducing):
        return [float_array("inducing", z, 2, copy=True) for z in inducing]
    z = float_array("inducing", inducing, 2, copy=True)
    if z.shape[0] < 1 or z.shape[1] < 1:
        raise ValueError(f"inducing: expected shape (m, n_d) with m >= 1, got {z.shape}")
    return z


class Sparse:
    """The inducing-point approximation with a sparse GP's settings (validated here, once)."""

    #: Whether the models have inducing points.
    sparse = True

    def __init__(self, n_inducing: Any, method: Any, inducing: Any, optimize_inducing: Any, one_output: bool) -> None:
        self.n_inducing = integer("n_inducing", n_inducing, low=1)
        self.method = one_of("method", method, METHODS)
        self.inducing = check_inducing(inducing, one_output)
        self.optimize_inducing = boolean("optimize_inducing", optimize_inducing)

    # -- inducing points ---------------------------------------------------------------------

    def _fixed(self, q: int, nd: int) -> Optional[List[np.ndarray]]:
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

    def fit(self, D: np.ndarray, R: np.ndarray, coef: Any, theta0: np.ndarray,
            fitting: Optional[Fitting]) -> Tuple["_core.SparseMultiGP", Any]:
        """(model, the fit's record or None). Without ``fitting``: theta0 kept, the points given
        or chosen under theta0's kernel. With it, per output: optimise theta, choose the points
        again under the fitted kernel, refine theta and keep the better round (given points:
        one round), then optionally optimise the points jointly with theta."""
        q, nd = R.shape[1], D.shape[1]
        fixed = self._fixed(q, nd)
        if fitting is None:
            zs = [fixed[o] if fixed is not None else self._select(D, theta0[o]) for o in range(q)]
            return _core.SparseMultiGP(D, R, zs, np.ascontiguousarray(theta0), self.method, coef), None
        rows, zs, runs = [], [], []
        for o in range(q):
            t, z, values = self._fit_output(D, np.ascontiguousarray(R[:, o]), theta0[o], fitting, o,
                                            None if fixed is None else fixed[o])
            rows.append(t)
            zs.append(z)
            runs.append(values)
        model = _core.SparseMultiGP(D, R, zs, np.ascontiguousarray(rows), self.method, coef)
        return model, fitting.record(runs)

    def _fit_output(self, D: np.ndarray, y: np.ndarray, theta0: np.ndarray, fitting: Fitting, o: int,
                    fixed: Optional[np.ndarray]) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(theta (n_d + 2,), inducing points, every run's objective) of output o."""
        nd, shift = D.shape[1], fitting.shift[o]
        t = theta0 - shift
        z = fixed if fixed is not None else self._select(D, theta0)
        best, values = None, []
        for i, restarts in enumerate([fitting.n_restarts] if fixed is not None else [fitting.n_restarts, 0]):
            if i > 0:
                z = self._select(D, t + shift)
            objective = _posterior(_objective(D, y, z, self.method), shift, fitting.prior)
            t, value, run_values = _maximise(objective, t, fitting.log_bounds, restarts, fitting.rng, fitting.maxiter)
            values.extend(run_values)
            if best is None or value > best[0]:
                best = (value, t.copy(), z)
        _, t, z = best
        if self.optimize_inducing:
            box = np.tile(np.column_stack([D.min(axis=0), D.max(axis=0)]), (z.shape[0], 1))
            packed = _maximise(_joint_objective(D, y, self.method, shift, fitting.prior),
                               np.concatenate([t, z.ravel()]), np.vstack([fitting.log_bounds, box]), 0,
                               fitting.rng, fitting.maxiter)[0]
            t, z = packed[: nd + 2], np.ascontiguousarray(packed[nd + 2 :].reshape(-1, nd))
        return t + shift, z, np.array(values)

    # -- the fitted model --------------------------------------------------------------------

    @staticmethod
    def rebuild(model: "_core.SparseMultiGP", D: np.ndarray, R: np.ndarray, theta: np.ndarray) -> "_core.SparseMultiGP":
        """The fitted model factored again at a new theta, with the same inducing points."""
        return _core.SparseMultiGP(D, R, model.inducing, theta, model.method, model.mean)

    @staticmethod
    def objective(model: "_core.SparseMultiGP", D: np.ndarray, R: np.ndarray, theta: Optional[np.ndarray],
                  eval_gradient: bool) -> Tuple[np.ndarray, Optional[np.ndarray]]:
        """(training objective (q,), gradient (q, n_d + 2) or None) at theta (None: the model's)."""
        if theta is None and not eval_gradient:
            return model.log_marginal_likelihoods(), None
        theta = model.thetas if theta is None else theta
        res = [_core.sparse_objective(D, np.ascontiguousarray(R[:, o]), z, np.ascontiguousarray(theta[o]),
                                      model.method, eval_gradient) for o, z in enumerate(model.inducing)]
        return np.array([r[0] for r in res]), np.array([r[1] for r in res])

    @staticmethod
    def loo(model: "_core.SparseMultiGP", D: np.ndarray) -> Callable:
        """``loo(o, r)`` of `gpmhe.gp.diagnostics.diagnose`: the sparse model's, O(N m²)."""
        zs, thetas, jitters, fitc = model.inducing, model.thetas, model.jitters, model.method == "fitc"
        return lambda o, r: sparse_loo(D, r, zs[o], thetas[o], float(jitters[o]), fitc)

    def save_entries(self, model: "_core.SparseMultiGP") -> dict:
        """The file entries of the model and the settings beyond the exact GP's."""
        zs = model.inducing
        # A posterior of the inducing outputs that replaced the fit's (a GP that learned online):
        # the data alone would give the fit's.
        replaced = {}
        for o, post in enumerate(model.replaced_posterior()):
            if post is not None:
                replaced[f"posterior_mean_{o}"], replaced[f"posterior_cov_{o}"] = post
        return dict(inducing=np.vstack(zs), inducing_counts=np.array([len(z) for z in zs], dtype=np.int64),
                    method=model.method, n_inducing=self.n_inducing, optimize_inducing=self.optimize_inducing,
                    inducing_given=self.inducing is not None, **replaced)

    def load_model(self, D: np.ndarray, R: np.ndarray, theta: np.ndarray, coef: Any,
                   inducing: Tuple[List[np.ndarray], Any]) -> "_core.SparseMultiGP":
        """The model of a saved file's entries (``inducing``: the points per output and the
        replaced posteriors, `read_settings`)."""
        zs, posterior = inducing
        return _core.SparseMultiGP(D, R, [np.ascontiguousarray(z) for z in zs], theta, self.method, coef,
                                   posterior)


def read_settings(f: Any, nd: int, q: int, one_output: bool) -> Tuple[dict, Tuple[List[np.ndarray], Any]]:
    """(the sparse constructor's settings, (the inducing points per output, the posteriors of
    the inducing outputs that replaced the fit's: None, or one entry per output, None or (mean,
    covariance))) of a saved file."""
    Z, counts = f.floats("inducing", (None, nd)), f.array("inducing_counts", "i", (None,))
    if len(counts) != q or np.any(counts < 1) or counts.sum() != len(Z):
        raise f.error("inducing_counts", f"must be {q} positive counts summing to {len(Z)}")
    zs = np.split(Z, np.cumsum(counts)[:-1])
    given = (zs[0] if one_output else list(zs)) if f.boolean("inducing_given") else None
    settings = dict(n_inducing=f.integer("n_inducing", 1), method=f.string("method"), inducing=given,
                    optimize_inducing=f.boolean("optimize_inducing"))
    posterior = [(f.floats(f"posterior_mean_{o}", (len(z),)), f.floats(f"posterior_cov_{o}", (len(z), len(z))))
                 if f"posterior_mean_{o}" in f else None for o, z in enumerate(zs)]
    return settings, (zs, posterior if any(p is not None for p in posterior) else None)
