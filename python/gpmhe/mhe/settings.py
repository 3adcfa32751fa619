"""The settings of a moving-horizon estimator, in one immutable value validated once.

`MHESettings` is the single definition of every setting of `GPMHE` (and of the settings an
`EstimatorBank` shares): its type, default, validation and how it reaches the Rust core. The
estimator keeps one value; a weight set between updates builds a new value with `replace`, which
validates only what changed and tells the estimator what to hand to the core. Checkpoints write
and read a value with `entries` / `from_file`. With a model's unknown parameters p the core runs
on the augmented state [x; p̃], p = s ⊙ p̃: the ``core_*`` methods hand the core weights,
bounds and x̂(0) augmented by `gpmhe.models.parameters.Scaling`.
"""

from __future__ import annotations

import dataclasses
import inspect
import json
from typing import Any, Dict, Optional, Tuple

import numpy as np
from scipy.optimize import least_squares

from gpmhe import _core
from gpmhe._validation import boolean, box, finite_vector, integer, one_of, options, positive
from gpmhe.models.parameters import Scaling
from gpmhe._validation import positive_scalar, symmetric_matrix

__all__ = ["MHESettings", "SOLVERS"]

#: The largest horizon accepted (the history keeps M + 2 steps).
MAX_HORIZON = 1_000_000

#: The window solvers and the options each accepts (see `gpmhe._validation.options`): gpmhe's own
#: for the Rust solver; for SciPy's, the keywords of `scipy.optimize.least_squares` (but its loss:
#: `REFUSED_OPTIONS`) and of `minimize`'s "trust-constr" options except those gpmhe sets itself
#: (the problem, its bounds and method), plus gpmhe's decrement stop ``dtol`` for "trust-constr".
SOLVERS = {
    "gauss-newton": dict(max_iter="count", gtol="tol", xtol="tol", ftol="tol", dtol="tol",
                         interior=("auto", "always", "never"), interior_zone="tol",
                         mu_init="positive", mu_final="positive"),
    "trust-constr": dict(dtol="tol", xtol="tol", gtol="tol", barrier_tol="tol",
                         sparse_jacobian=None, maxiter="count", verbose=(0, 1, 2, 3),
                         finite_diff_rel_step=None, initial_constr_penalty="positive",
                         initial_tr_radius="positive",
                         initial_barrier_parameter="positive", initial_barrier_tolerance="positive",
                         factorization_method=None, disp=(True, False)),
    "least-squares": {
        **{k: None for k in inspect.signature(least_squares).parameters
           if k not in ("fun", "x0", "jac", "bounds", "method", "args", "kwargs", "loss",
                        "f_scale")},
        **dict(ftol="tol", xtol="tol", gtol="tol", max_nfev="count?", verbose=(0, 1, 2)),
    },
}

#: Options of a SciPy solver that would make it minimise another cost than the window's (the
#: reference solvers solve the same problem as the Rust one), with what to use instead.
REFUSED_OPTIONS = {
    "least-squares": {
        key: ("SciPy's robust loss would apply to every residual (prior and process rows too) and "
              "make the solver minimise another cost than the window's; give GPMHE's loss= and "
              "loss_scale= (the output rows' penalty, the same for every solver) instead")
        for key in ("loss", "f_scale")},
}

#: The output penalties and their default scales k (in standard deviations of the whitened
#: residual): the usual 95 %-efficiency constants of Huber's and Cauchy's M-estimators.
LOSS_SCALES = {"squared": 1.0, "huber": 1.345, "cauchy": 2.385}

#: The settings a user may change between updates (each takes effect from the next one).
WEIGHTS = ("Q0", "R0", "P2", "eta")


def _eta(value):
    eta = positive_scalar("eta", value, allow_zero=True)
    if eta > 1.0:
        raise ValueError(f"eta: must be in [0, 1], got {value!r}")
    return eta


def covariance(name, value, n):
    """A symmetric positive definite (n, n) matrix (Q0, R0, P2, P0: each takes the same forms)
    from None (the identity), a scalar, the diagonal or the matrix."""
    if n == 0:
        return np.zeros((0, 0))
    return symmetric_matrix(name, 1.0 if value is None else value, n, definite=True,
                            vector_is_diagonal=True)


def sample_covariance(R, p):
    """The covariance ``R`` given with one output sample (as ``R0``: a scalar, the diagonal or
    the matrix), validated, in the core's form (see `_flat`)."""
    return _flat(covariance("R", R, p))


def _frozen(a):
    a = np.array(a, dtype=np.float64)
    a.flags.writeable = False
    return a


def _flat(a):
    """A covariance as the core takes it: its diagonal when diagonal, else flattened."""
    return np.ascontiguousarray(np.diag(a) if np.all(a == np.diag(np.diag(a))) else a.reshape(-1))


@dataclasses.dataclass(frozen=True)
class MHESettings:
    """Every setting of a `GPMHE` on a model with dimensions (n, p, m) and k parameters, validated
    (see `GPMHE` for their meaning). Arrays are read-only; build a changed value with
    `replace`."""

    dims: Tuple[int, int, int, int]
    horizon: int
    eta: float
    P2: np.ndarray
    Q0: np.ndarray
    R0: np.ndarray
    x_bounds: Tuple[np.ndarray, np.ndarray]
    form: str
    solver: str
    solver_options: Dict[str, Any]
    arrival_mean: str
    arrival_weight: str
    loss: str
    loss_scale: float
    # the unknown parameters (dim_p > 0): guess, prior covariance, bounds, drift per step, and
    # the scale s of p = s ⊙ p̃
    p0: np.ndarray
    P_p0: np.ndarray
    p_bounds: Optional[Tuple[np.ndarray, np.ndarray]]
    p_drift: np.ndarray
    p_scale: np.ndarray
    # a learned model whose f-GPs keep learning online: on, and the random-walk variance of
    # their inducing outputs per step
    learning: bool = False
    learning_drift: float = 0.0

    # ---- building and changing --------------------------------------------------------------
    @classmethod
    def build(cls, dims, horizon=15, eta=0.91, P2=None, Q0=None, R0=None, x_bounds=None,
              form="prediction", solver="gauss-newton", solver_options=None, P0=None,
              arrival_mean="smoothed", arrival_weight="ekf", p0=None, P_p0=None, p_bounds=None,
              p_drift=None, loss="squared", loss_scale=None, learning=False,
              learning_options=None):
        """The validated settings of an estimator on a model of dimensions ``dims`` = (n, p, m,
        k); ValueError naming the first invalid argument."""
        n, p, _, k = dims
        solver = one_of("solver", solver, tuple(SOLVERS))
        if P2 is not None and P0 is not None:
            raise ValueError("P2, P0: give the arrival weight P2 or its covariance P0, not both")
        P2 = (np.linalg.inv(covariance("P0", P0, n)) if P0 is not None
              else covariance("P2", P2, n))
        lb, ub = box("x_bounds", x_bounds, n)
        return cls(
            dims=tuple(dims), horizon=integer("horizon", horizon, low=1, high=MAX_HORIZON),
            eta=_eta(eta), P2=_frozen(P2), Q0=_frozen(covariance("Q0", Q0, n)),
            R0=_frozen(covariance("R0", R0, p)), x_bounds=(_frozen(lb), _frozen(ub)),
            form=one_of("form", form, ("prediction", "filtering")), solver=solver,
            solver_options=cls._solver_options(solver, solver_options),
            arrival_mean=one_of("arrival_mean", arrival_mean, ("estimate", "smoothed", "filtered")),
            arrival_weight=one_of("arrival_weight", arrival_weight, ("constant", "ekf")),
            **cls._loss(loss, loss_scale), **cls._parameters(k, p0, P_p0, p_bounds, p_drift),
            **cls._learning(learning, learning_options, solver, k))

    @staticmethod
    def _learning(learning, learning_options, solver, k):
        """Whether the model learns online, and its drift (``learning_options``: ``drift``, the
        variance per step of the random walk of the inducing outputs, default 0)."""
        learning = boolean("learning", learning)
        opts = dict(options("learning_options", learning_options, dict(drift="tol")))
        if opts and not learning:
            raise ValueError("learning_options: given without learning=True")
        if learning and solver != "gauss-newton":
            raise ValueError(f"learning: needs solver='gauss-newton' (the window estimates the "
                             f"GPs' inducing outputs with the states), got {solver!r}")
        if learning and k:
            raise ValueError("learning: not with a model's parameters (dim_p > 0)")
        return dict(learning=learning, learning_drift=float(opts.get("drift", 0.0)))

    @staticmethod
    def _solver_options(solver, solver_options):
        """``solver_options`` validated for ``solver``; options that would change the cost the
        solver minimises are refused (`REFUSED_OPTIONS`)."""
        if isinstance(solver_options, dict):
            for key, why in REFUSED_OPTIONS.get(solver, {}).items():
                if key in solver_options:
                    raise ValueError(f"solver_options: {key!r} is not accepted for {solver!r}: "
                                     f"{why}")
        return dict(options("solver_options", solver_options, SOLVERS[solver]))

    @staticmethod
    def _loss(loss, loss_scale):
        """The output penalty and its scale (None: the loss's default, `LOSS_SCALES`)."""
        loss = one_of("loss", loss, tuple(LOSS_SCALES))
        if loss == "squared":
            if loss_scale is not None:
                raise ValueError("loss_scale: the squared loss has no scale (give loss='huber' "
                                 "or 'cauchy')")
            return dict(loss=loss, loss_scale=1.0)
        scale = LOSS_SCALES[loss] if loss_scale is None else positive_scalar("loss_scale", loss_scale)
        return dict(loss=loss, loss_scale=scale)

    @staticmethod
    def _parameters(k, p0, P_p0, p_bounds, p_drift):
        """The parameter settings (a model with k > 0 parameters needs p0)."""
        if not k:
            for name, v in (("p0", p0), ("P_p0", P_p0), ("p_bounds", p_bounds),
                            ("p_drift", p_drift)):
                if v is not None:
                    raise ValueError(f"{name}: the model has no parameters (dim_p = 0)")
            return dict(p0=_frozen(np.zeros(0)), P_p0=_frozen(np.zeros((0, 0))), p_bounds=None,
                        p_drift=_frozen(np.zeros(0)), p_scale=_frozen(np.ones(0)))
        if p0 is None:
            raise ValueError(f"p0: required, the model has {k} parameter(s) (dim_p = {k})")
        p0 = finite_vector("p0", p0, k, flatten=True).copy()
        lb, ub = box("p_bounds", p_bounds, k)
        if np.any(p0 < lb) or np.any(p0 > ub):
            raise ValueError("p0: must lie inside p_bounds")
        scale, span = np.abs(p0), ub - lb
        scale = np.where(scale > 0, scale, np.where(np.isfinite(span), span, 1.0))
        P_p0 = covariance("P_p0", np.diag(scale ** 2) if P_p0 is None else P_p0, k)
        drift = 1e-4 * scale if p_drift is None else p_drift
        drift = positive("p_drift", drift)
        if drift.shape not in ((), (k,)):
            raise ValueError(f"p_drift: expected a scalar or shape ({k},), got {drift.shape}")
        return dict(p0=_frozen(p0), P_p0=_frozen(P_p0), p_bounds=(_frozen(lb), _frozen(ub)),
                    p_drift=_frozen(np.broadcast_to(drift, (k,))), p_scale=_frozen(scale))

    def replace(self, **changes):
        """A new value with the weights ``changes`` (names of `WEIGHTS`, or P0 for P2) validated
        as in `build`; returns (settings, names of the changed weights)."""
        n, p = self.dims[0], self.dims[1]
        new = {}
        for name, value in changes.items():
            if name == "Q0":
                new["Q0"] = _frozen(covariance("Q0", value, n))
            elif name == "R0":
                new["R0"] = _frozen(covariance("R0", value, p))
            elif name == "P2":
                new["P2"] = _frozen(covariance("P2", value, n))
            elif name == "P0":
                new["P2"] = _frozen(np.linalg.inv(covariance("P0", value, n)))
            elif name == "eta":
                new["eta"] = _eta(value)
            else:
                raise ValueError(f"{name}: not a weight ({', '.join(WEIGHTS)}, P0)")
        return dataclasses.replace(self, **new), tuple(new)

    # ---- what the core takes (on [x; p̃] with parameters) -----------------------------------
    @property
    def scaling(self):
        """The map between the estimator's quantities and the core's state [x; p̃]."""
        return Scaling(self.dims[0], self.p_scale)

    def core_weights(self, names=WEIGHTS):
        """The core's weights among ``names``: ``eta``, ``q0`` and ``r0`` (Q0, R0: diagonals when
        diagonal, else flattened), ``p2_sqrt`` (S with P2 = SᵀS)."""
        out = {}
        if "eta" in names:
            out["eta"] = self.eta
        if "Q0" in names:
            out["q0"] = _flat(self.scaling.process_noise(self.Q0, self.p_drift))
        if "R0" in names:
            out["r0"] = _flat(self.R0) if self.dims[1] else np.zeros(0)
        if "P2" in names:
            P2 = self.scaling.arrival_weight(self.P2, self.P_p0)
            out["p2_sqrt"] = np.ascontiguousarray(np.linalg.cholesky(P2).T)
        return out

    def core_bounds(self):
        """The box of the core's state."""
        return self.scaling.bounds(*self.x_bounds, self.p_bounds)

    def core_state(self, x, p=None):
        """The core's state for x and the parameters p (None: p0)."""
        return self.scaling.state(x, self.p0 if p is None else p)

    def core_solver(self):
        """The Rust solver's settings (None for SciPy's solvers)."""
        if self.solver != "gauss-newton":
            return None
        try:
            return _core.WindowSolver(**self.solver_options)
        except (TypeError, ValueError) as e:
            raise ValueError(f"solver_options: {e}") from None

    def core_arguments(self):
        """The keyword arguments of `gpmhe._core.MovingHorizon` after the model."""
        w = self.core_weights()
        lb, ub = self.core_bounds()
        return dict(eta=w["eta"], q0=w["q0"], r0=w["r0"], p2_sqrt=w["p2_sqrt"],
                    filtering=self.form == "filtering", horizon=self.horizon, lower=lb,
                    upper=ub, solver=self.core_solver(),
                    arrival_mean=_core.ArrivalMean.from_name(self.arrival_mean),
                    arrival_weight=_core.ArrivalWeight.from_name(self.arrival_weight),
                    loss=self.loss, loss_scale=self.loss_scale)

    def check_state(self, x0, p0=None):
        """x0 (and p0) validated against the bounds, as new arrays."""
        n, k = self.dims[0], self.dims[3]
        x0 = finite_vector("x0", x0, n, flatten=True).copy()
        lb, ub = self.x_bounds
        if np.any(x0 < lb) or np.any(x0 > ub):
            raise ValueError("x0: must lie inside x_bounds")
        if p0 is not None:
            if not k:
                raise ValueError("p0: the model has no parameters (dim_p = 0)")
            p0 = finite_vector("p0", p0, k, flatten=True).copy()
            if np.any(p0 < self.p_bounds[0]) or np.any(p0 > self.p_bounds[1]):
                raise ValueError("p0: must lie inside p_bounds")
        return x0, p0

    # ---- checkpoints -------------------------------------------------------------------------
    def entries(self):
        """The settings as plain arrays and strings for an ``.npz`` file."""
        try:
            options_json = json.dumps(self.solver_options)
        except (TypeError, ValueError) as e:
            raise ValueError(f"solver_options: cannot be saved ({e})") from None
        lb, ub = self.x_bounds
        out = dict(horizon=self.horizon, eta=self.eta, P2=self.P2, Q0=self.Q0, R0=self.R0,
                   x_lower=lb, x_upper=ub, form=self.form, solver=self.solver,
                   solver_options=options_json, arrival_mean=self.arrival_mean,
                   arrival_weight=self.arrival_weight, loss=self.loss,
                   loss_scale=self.loss_scale)
        if self.dims[3]:
            out.update(p0=self.p0, P_p0=self.P_p0, p_lower=self.p_bounds[0],
                       p_upper=self.p_bounds[1], p_drift=self.p_drift)
        if self.learning:
            out.update(learning=True, learning_drift=self.learning_drift)
        return out

    @classmethod
    def from_file(cls, f, dims):
        """The settings in the open checkpoint ``f`` (a `gpmhe._npz.NpzReader`) of a model of
        dimensions ``dims``; ValueError naming the file and the entry."""
        n, p, _, k = dims
        raw = dict(horizon=f.integer("horizon", low=1), eta=f.float("eta"),
                   P2=f.floats("P2", (n, n)), Q0=f.floats("Q0", (n, n)),
                   R0=f.floats("R0", (p, p)) if p else None, form=f.string("form"),
                   solver=f.string("solver"),
                   x_bounds=(f.floats("x_lower", (n,)), f.floats("x_upper", (n,))))
        if f.version >= 2:
            raw.update(arrival_mean=f.string("arrival_mean"),
                       arrival_weight=f.string("arrival_weight"))
        else:  # format 1 ran the paper's arrival cost
            raw.update(arrival_mean="estimate", arrival_weight="constant")
        if f.version >= 4:  # earlier formats had the squared loss only
            raw["loss"], scale = f.string("loss"), f.float("loss_scale")
            if raw["loss"] != "squared":  # the squared loss's saved scale is always 1
                raw["loss_scale"] = scale
        if f.version >= 8 and "learning" in f:
            raw.update(learning=f.boolean("learning"),
                       learning_options=dict(drift=f.float("learning_drift")))
        if k:
            raw.update(p0=f.floats("p0", (k,)), P_p0=f.floats("P_p0", (k, k)),
                       p_bounds=(f.floats("p_lower", (k,)), f.floats("p_upper", (k,))),
                       p_drift=f.floats("p_drift", (k,)))
        try:
            raw["solver_options"] = json.loads(f.string("solver_options"))
        except ValueError as e:
            raise f.error("solver_options", f"is not valid ({e})") from None
        try:
            return cls.build(dims, **raw)
        except ValueError as e:
            raise ValueError(f"path: {f.name}: the saved settings are invalid ({e})") from None
