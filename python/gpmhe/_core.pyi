"""Type stubs of the Rust extension module gpmhe._core."""

from typing import Any, Callable

import numpy as np
import numpy.typing as npt

class NumericalError(RuntimeError):
    """A numerical failure on valid input (e.g. a matrix not positive definite after jitter)."""

def se_ard_kernel(
    a: npt.NDArray[np.float64],
    b: npt.NDArray[np.float64],
    sigma_f: float,
    lengthscales: npt.NDArray[np.float64],
) -> npt.NDArray[np.float64]: ...

# ===== GP =====

class MultiGP:
    """q independent SE-ARD GPs on shared inputs (rust/src/gp.rs); gpmhe.GaussianProcess is q = 1."""

    def __init__(
        self,
        x: npt.NDArray[np.float64],
        y: npt.NDArray[np.float64],
        thetas: npt.NDArray[np.float64],
        mean: npt.NDArray[np.float64] | None = None,
    ) -> None: ...
    @property
    def n_outputs(self) -> int: ...
    @property
    def dim(self) -> int: ...
    @property
    def n_train(self) -> int: ...
    @property
    def thetas(self) -> npt.NDArray[np.float64]: ...
    @property
    def mean(self) -> npt.NDArray[np.float64] | None: ...
    @property
    def jitters(self) -> npt.NDArray[np.float64]: ...
    def log_marginal_likelihoods(self) -> npt.NDArray[np.float64]: ...
    def log_marginal_likelihood_gradients(self) -> npt.NDArray[np.float64]: ...
    def predict(
        self, d: npt.NDArray[np.float64]
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]: ...
    def predict_with_gradients(
        self, d: npt.NDArray[np.float64]
    ) -> tuple[
        npt.NDArray[np.float64],
        npt.NDArray[np.float64],
        npt.NDArray[np.float64],
        npt.NDArray[np.float64],
    ]: ...
    def predict_mean(self, d: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]: ...
    # copies and pickles: immutable, so copies are the object itself; pickles as MultiGP(x, y,
    # thetas, mean), which factorises to the same GP bit for bit
    def __copy__(self) -> MultiGP: ...
    def __deepcopy__(self, _memo: Any) -> MultiGP: ...
    def __reduce__(self) -> tuple[Any, ...]: ...

def log_marginal_likelihood(
    x: npt.NDArray[np.float64],
    y: npt.NDArray[np.float64],
    theta: npt.NDArray[np.float64],
    eval_gradient: bool = False,
) -> tuple[float, npt.NDArray[np.float64]]: ...

# ===== sparse GP =====

class SparseMultiGP:
    """q independent sparse SE-ARD GPs on shared inputs, each with its own theta and inducing
    inputs (rust/src/sparse/); gpmhe.SparseGaussianProcess is q = 1. The prediction methods are
    MultiGP's."""

    def __init__(
        self,
        x: npt.NDArray[np.float64],
        y: npt.NDArray[np.float64],
        z: list[npt.NDArray[np.float64]],
        thetas: npt.NDArray[np.float64],
        method: str,
        mean: npt.NDArray[np.float64] | None = None,
        posterior: list[tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]] | None] | None = None,
    ) -> None:
        """`posterior`: per output None or (mean, covariance) of its inducing outputs, replacing
        the fit's."""
        ...
    def replaced_posterior(
        self,
    ) -> list[tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]] | None]:
        """Per output, the posterior of its inducing outputs that replaced the fit's, or None."""
        ...
    @property
    def n_outputs(self) -> int: ...
    @property
    def dim(self) -> int: ...
    @property
    def n_train(self) -> int: ...
    @property
    def method(self) -> str: ...
    @property
    def thetas(self) -> npt.NDArray[np.float64]: ...
    @property
    def inducing(self) -> list[npt.NDArray[np.float64]]: ...
    @property
    def mean(self) -> npt.NDArray[np.float64] | None: ...
    @property
    def jitters(self) -> npt.NDArray[np.float64]: ...
    def log_marginal_likelihoods(self) -> npt.NDArray[np.float64]:
        """The training objective of each output (VFE bound or FITC log marginal likelihood)."""
    def predict(
        self, d: npt.NDArray[np.float64]
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]: ...
    def predict_with_gradients(
        self, d: npt.NDArray[np.float64]
    ) -> tuple[
        npt.NDArray[np.float64],
        npt.NDArray[np.float64],
        npt.NDArray[np.float64],
        npt.NDArray[np.float64],
    ]: ...
    def predict_mean(self, d: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]: ...
    # immutable: copies are the object itself; pickles as SparseMultiGP(x, y, z, thetas, method, mean)
    def __copy__(self) -> SparseMultiGP: ...
    def __deepcopy__(self, _memo: Any) -> SparseMultiGP: ...
    def __reduce__(self) -> tuple[Any, ...]: ...

def sparse_objective(
    x: npt.NDArray[np.float64],
    y: npt.NDArray[np.float64],
    z: npt.NDArray[np.float64],
    theta: npt.NDArray[np.float64],
    method: str,
    eval_gradient: bool = False,
) -> tuple[float, npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """(value, d/dtheta, d/dz) of the sparse training objective (gradients empty unless asked)."""

def select_inducing(
    x: npt.NDArray[np.float64], theta: npt.NDArray[np.float64], m: int
) -> npt.NDArray[np.int64]:
    """Indices of at most m rows of x by greedy conditional-variance selection."""

# ===== RGP =====
# Recursive GP and RGP-dKF kernels (rust/src/rgp/); the public classes are gpmhe.RecursiveGP and
# gpmhe.RGPEKF in gpmhe/rgp/ekf.py. Arrays are float64, C-contiguous.

class RecursiveGPCore:
    def __init__(
        self,
        lower: npt.NDArray[np.float64],
        upper: npt.NDArray[np.float64],
        n_points: list[int],
        sigma_k: float,
        l: float,
        sigma_r: float,
        sigma_p: float,
    ) -> None: ...
    @classmethod
    def from_points(
        cls,
        points: npt.NDArray[np.float64],
        sigma_k: float,
        lengthscales: npt.NDArray[np.float64],
        jitter: float,
        prior_mean: npt.NDArray[np.float64] | None,
        sigma_r: float,
        sigma_p: float,
    ) -> RecursiveGPCore:
        """A fresh GP (weights N(0, K)) with basis vectors at `points` (m, n_X), SE-ARD kernel
        (sigma_k, lengthscales in zeta units), exactly `jitter` on K's diagonal, the prior mean's
        coefficients [b, w_1, ...] or None."""
    @classmethod
    def from_sparse(
        cls, model: SparseMultiGP, output: int, sigma_r: float, sigma_p: float
    ) -> RecursiveGPCore:
        """The GP that predicts as output `output` of a fitted sparse GP: basis vectors at its
        inducing inputs, its kernel, jitter and prior mean, weights N(mu_u, Sigma_u)."""
    def copy(self) -> RecursiveGPCore: ...
    def update(self, zeta: npt.NDArray[np.float64], y: float, var_y: float) -> float: ...
    def update_many(
        self,
        zeta: npt.NDArray[np.float64],
        y: npt.NDArray[np.float64],
        var_y: npt.NDArray[np.float64],
    ) -> npt.NDArray[np.float64]: ...
    def predict(
        self, zeta: npt.NDArray[np.float64]
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]: ...
    def j_row(self, zeta: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]: ...
    def set_weights(
        self, mean: npt.NDArray[np.float64], cov: npt.NDArray[np.float64]
    ) -> None: ...
    @property
    def mean(self) -> npt.NDArray[np.float64]: ...
    @property
    def cov(self) -> npt.NDArray[np.float64]: ...
    @property
    def basis_vectors(self) -> npt.NDArray[np.float64]: ...
    @property
    def kernel_matrix(self) -> npt.NDArray[np.float64]: ...
    @property
    def jitter(self) -> float: ...
    @property
    def sigma_k(self) -> float: ...
    @property
    def lengthscales(self) -> npt.NDArray[np.float64]:
        """The kernel's length-scales in zeta units."""
    @property
    def prior_mean(self) -> npt.NDArray[np.float64] | None: ...
    @property
    def is_grid(self) -> bool: ...
    # copies and pickles: a copy is independent; pickles as (constructor or from_points,
    # its arguments, (mean, cov as stored)) and continues bit-identically
    def __copy__(self) -> RecursiveGPCore: ...
    def __deepcopy__(self, _memo: Any) -> RecursiveGPCore: ...
    def __reduce__(self) -> tuple[Any, ...]: ...
    def __setstate__(
        self, state: tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]
    ) -> None: ...

class RGPEKFCore:
    def __init__(
        self,
        x0: npt.NDArray[np.float64],
        p0: npt.NDArray[np.float64],
        gps: list[RecursiveGPCore],
        augmented: bool,
    ) -> None: ...
    def set_constant_jacobians(
        self,
        a: npt.NDArray[np.float64] | None = None,
        e: npt.NDArray[np.float64] | None = None,
        h: npt.NDArray[np.float64] | None = None,
    ) -> None:
        """Stores constant A, e, H; predict/update then take None for them."""
    def predict_step(
        self,
        f: Callable[..., Any],
        u: Any,
        zeta: float | npt.NDArray[np.float64],
        a_fn: Callable[..., Any] | None,
        e_fn: Callable[..., Any] | None,
        q_x: npt.NDArray[np.float64],
    ) -> None:
        """J_k at zeta, then f(x, u, z), A, e (None: stored constants) and the covariance prediction."""
    def update_step(
        self,
        y: Any,
        h: Callable[..., Any],
        h_fn: Callable[..., Any] | None,
        r: float | npt.NDArray[np.float64],
        dim_y: int | None,
        learning: bool,
    ) -> float:
        """h(x⁻), H (None: stored constant), ν = y − h(x⁻) and the EKF update; the log-likelihood."""
    def set_x(self, x: npt.NDArray[np.float64]) -> None: ...
    def set_p(self, p: npt.NDArray[np.float64]) -> None:
        """Replaces the state covariance; the states' cross-covariance with the weights is reset to 0."""
    @property
    def z_pred(self) -> npt.NDArray[np.float64]: ...
    def gp_predict(
        self, index: int, zeta: npt.NDArray[np.float64]
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]: ...
    def gp_weights(
        self, index: int
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]: ...
    @property
    def x(self) -> npt.NDArray[np.float64]: ...
    @property
    def P(self) -> npt.NDArray[np.float64]: ...
    @property
    def mu(self) -> npt.NDArray[np.float64]: ...
    @property
    def C(self) -> npt.NDArray[np.float64]: ...
    @property
    def innovation(self) -> npt.NDArray[np.float64]: ...
    @property
    def S(self) -> npt.NDArray[np.float64]: ...
    @property
    def log_likelihood(self) -> float: ...
    # copies, pickles and checkpoints: a copy is independent and continues bit-identically
    def __copy__(self) -> RGPEKFCore: ...
    def __deepcopy__(self, _memo: Any) -> RGPEKFCore: ...
    def __reduce__(self) -> tuple[Any, ...]: ...
    def __getstate__(self) -> dict[str, Any]:
        """`mu`, `cov` (as stored), `gp_mean_<i>`, `gp_cov_<i>`, `j`, `dvar`, `mu_zp`, `z_pred`,
        `inferred` (bool), `innovation`, `S`, `log_likelihood`, and `A_const`, `e_const`,
        `H_const` when set."""
        ...
    def __setstate__(self, state: dict[str, Any]) -> None:
        """Restore `__getstate__` of a filter with the same dimensions and GPs; every entry is
        checked (ValueError naming it) and nothing changes on error."""
        ...

# ===== Moving horizon estimator =====

from typing import Callable

_F = npt.NDArray[np.float64]

class StageModel:
    """The model of a `MovingHorizon`: the learned GPs, a compiled CasADi model or a known
    model's Python functions."""

    @staticmethod
    def gp(
        f_gp: MultiGP | SparseMultiGP,
        h_gp: MultiGP | SparseMultiGP | None,
        dim_u: int,
        f_residual: bool,
    ) -> StageModel:
        """f's GPs (dim_x outputs) and h's (dim_y outputs; None when dim_y = 0) on [x; u];
        `f_residual`: f's GPs model x(t+1) − x(t)."""
        ...
    @staticmethod
    def learning(
        f_gp: SparseMultiGP,
        h_gp: MultiGP | SparseMultiGP | None,
        dim_u: int,
        f_residual: bool,
    ) -> StageModel:
        """As `gp`, with sparse f-GPs whose inducing outputs the estimator learns."""
        ...
    def fitted_posterior(self) -> tuple[_F, _F, list[int]]:
        """A learning model's fitted posterior of the inducing outputs (mean, covariance) and
        the start of each f-GP's block."""
        ...
    def snapshot(self, mean: _F, cov: _F) -> SparseMultiGP:
        """A learning model's f-GPs with the posterior N(mean, cov) of their inducing outputs."""
        ...
    @property
    def learns(self) -> bool: ...
    @staticmethod
    def callback(
        stage_eval: Callable[[_F], tuple[_F, _F, _F, _F, _F, _F, _F, _F]],
        dim_x: int,
        dim_u: int,
        dim_y: int,
        predict: Callable[[_F, _F], _F] | None = None,
    ) -> StageModel:
        """`predict(x, u)`: the one-step prediction used for warm starts and the filtering
        form's arrival prior (None: the means of `stage_eval` at one point)."""
        ...
    @staticmethod
    def compiled(
        path: str,
        stage: str,
        predict: str,
        dim_x: int,
        dim_u: int,
        dim_y: int,
        rebuild: Callable[[], StageModel],
    ) -> StageModel:
        """The shared library at `path` (CasADi's generated C code, compiled) with the functions
        `stage` (f, ∂f/∂dᵀ, h, ∂h/∂dᵀ of one point d) and `predict` (f); `rebuild()` returns the
        model again (pickles call it). ValueError if it does not load or has other shapes."""
        ...
    @property
    def native(self) -> bool:
        """Whether the model runs without Python (the GPs or a compiled CasADi model)."""
        ...
    @property
    def dims(self) -> tuple[int, int, int]: ...
    def evaluate(self, d: _F) -> tuple[_F, _F, _F, _F, _F, _F, _F, _F]:
        """The learned model's (mean_x, var_x, dmean_x, dvar_x, mean_y, var_y, dmean_y, dvar_y)
        at the points d (k, n + m), as the estimator's core evaluates them (ValueError for a
        callback model)."""
        ...
    def predict(self, x: _F, u: _F) -> _F:
        """The learned model's one-step prediction m_x(x, u) (ValueError for a callback model)."""
        ...
    # copies and pickles: immutable (copies are the object itself); pickles as its constructor
    # call (the GPs' data, or the callables, which must then be picklable)
    def __copy__(self) -> StageModel: ...
    def __deepcopy__(self, _memo: Any) -> StageModel: ...
    def __reduce__(self) -> tuple[Any, ...]: ...

class ArrivalMean:
    """The arrival prior's mean: `Estimate` (the estimator's own earlier estimate), `Smoothed`
    (the previous window's estimate of the new first node) or `Filtered` (the leaving node's
    prior filtered with its output and carried over its stage at the window's solution)."""

    Estimate: ArrivalMean
    Smoothed: ArrivalMean
    Filtered: ArrivalMean
    @staticmethod
    def from_name(name: str) -> ArrivalMean:
        """From "estimate", "smoothed" or "filtered" (ValueError naming arrival_mean otherwise)."""
        ...
    @property
    def name(self) -> str: ...
    def __reduce__(self) -> tuple[Any, ...]: ...
    def __eq__(self, value: object, /) -> bool: ...
    def __ne__(self, value: object, /) -> bool: ...
    def __int__(self) -> int: ...
    def __repr__(self) -> str: ...

class ArrivalWeight:
    """The arrival weight: `Constant` (P2) or `Ekf` (updated by an EKF step over the node that
    leaves the window)."""

    Constant: ArrivalWeight
    Ekf: ArrivalWeight
    @staticmethod
    def from_name(name: str) -> ArrivalWeight:
        """From "constant" or "ekf" (ValueError naming arrival_weight otherwise)."""
        ...
    @property
    def name(self) -> str: ...
    def __reduce__(self) -> tuple[Any, ...]: ...
    def __eq__(self, value: object, /) -> bool: ...
    def __ne__(self, value: object, /) -> bool: ...
    def __int__(self) -> int: ...
    def __repr__(self) -> str: ...

class MovingHorizon:
    """The moving-horizon estimator's core (rust/src/mhe/): built once with the model, the
    window weights and form, the horizon, x̂(0), the state box and the solver settings; owns the
    sliding history and the warm start. `update(u, y)` is one whole update; `prepare`, the
    window methods (`cost`, ...) and `commit` are its steps for other solvers."""

    def __init__(
        self,
        model: StageModel,
        eta: float,
        q0: _F,
        r0: _F,
        p2_sqrt: _F,
        filtering: bool,
        horizon: int = 1,
        x0: _F | None = None,
        lower: _F | None = None,
        upper: _F | None = None,
        solver: WindowSolver | None = None,
        arrival_mean: ArrivalMean = ...,
        arrival_weight: ArrivalWeight = ...,
        loss: str = "squared",
        loss_scale: float = 1.0,
    ) -> None:
        """`q0`, `r0`: Q0, R0 as diagonals or flattened matrices; `p2_sqrt`: S with P2 = SᵀS;
        `filtering`: the form; `horizon`: M; `x0`: x̂(0) (zeros if None); `lower`, `upper`: the
        state box (±inf if None); `solver`: the solver settings (defaults if None); the arrival
        cost (defaults: the paper's, `ArrivalMean.Estimate`, `ArrivalWeight.Constant`); the
        output penalty `loss` ("squared", "huber" or "cauchy") with scale `loss_scale`."""
        ...
    def reset(self, x0: _F) -> None:
        """Forget every step: t = 0, x̂(0) = x0 with covariance P2⁻¹."""
        ...
    def enable_learning(self, g0: _F, sigma0: _F, drift: float) -> None:
        """Learn the model's global variables from the prior N(g0, sigma0) with a random walk
        of variance `drift` per step (before the first update only)."""
        ...
    @property
    def learning(self) -> tuple[_F, _F] | None:
        """(g, its covariance) after the last update; None if the estimator does not learn."""
        ...
    def set_weights(
        self,
        eta: float | None = None,
        q0: _F | None = None,
        r0: _F | None = None,
        p2_sqrt: _F | None = None,
    ) -> None:
        """Replace the weights given from the next update on and keep the others; only a new
        P2 restarts the arrival weight. On error nothing changes."""
        ...
    @property
    def native(self) -> bool:
        """Whether the model runs without Python (the learned GPs or a compiled CasADi model)."""
        ...
    @property
    def weights_version(self) -> int:
        """How many times `set_weights` replaced weights (a copy keeps the count)."""
        ...
    def set_last_input(self, u: _F) -> None:
        """Give u(t − 1) to the last update, which was given None; refused otherwise."""
        ...
    @property
    def last_input(self) -> _F:
        """u(t − 1) (zeros before the first update)."""
        ...
    @property
    def arrival_weight(self) -> _F:
        """The next window's arrival weight SᵀS (n, n)."""
        ...
    def update(
        self, u: _F | None, y: _F | None = None, r: _F | None = None, u_last: _F | None = None
    ) -> None:
        """One whole update (u None: not known yet, filtering form or no input; r: the
        covariance of y, p or p² values, None for R0; u_last: u(t − 1) as this sample completes
        it, e.g. with the interval that ends here, None: as recorded), recorded with what it
        reports (the properties below) in one step; on error nothing changes."""
        ...
    def prepare(
        self, u: _F | None, y: _F | None = None, r: _F | None = None, u_last: _F | None = None
    ) -> tuple[_F, _F, _F]:
        """Stage the next window without recording it: (z0, lower, upper)."""
        ...
    def add_delayed(self, y: _F, age: int, r: _F | None = None) -> None:
        """Record an output measured `age` steps before the newest one (NaN: channels not in
        it; r: its covariance, None for R0) for the windows from the next update on."""
        ...
    @property
    def max_delay(self) -> int:
        """The largest age `add_delayed` accepts now."""
        ...
    def commit(
        self,
        z: _F,
        cost: float | None = None,
        success: bool = True,
        nit: int = 0,
        message: str = "",
        P_window: _F | None = None,
    ) -> tuple[_F, _F]:
        """Record the staged window's solution with another solver's report (cost None:
        evaluated here; P_window: every node's covariance block, flattened, the last one the
        estimate's; None: keep the previous covariance, NaN blocks): (x_window, x_prior)."""
        ...
    def abandon(self) -> None:
        """Drop the staged window and put the learned model's cache back as before `prepare`."""
        ...
    def set_data(self, u: _F, y: _F, y_present: list[bool], x_prior: _F) -> None:
        """Set a window directly (tests, diagnostics; it cannot be committed)."""
        ...
    def predict_next(self, x: _F, u: _F) -> _F:
        """The model's one-step prediction m_x(x, u)."""
        ...
    @property
    def t(self) -> int: ...
    # what the last update reported (before any: x̂(0), P2⁻¹, zeros, success, "")
    @property
    def x(self) -> _F: ...
    @property
    def x_window(self) -> _F: ...
    @property
    def x_prior(self) -> _F: ...
    @property
    def covariance(self) -> _F: ...
    @property
    def window_covariance(self) -> _F:
        """Every node's covariance block of the last window, flattened (NaN: not computable)."""
        ...
    def innovation(self) -> tuple[_F, _F, float, float, int]:
        """The newest output's (innovation, S, NIS, log-likelihood, measured channels),
        computed now with the model (the learned model's cache left as it was)."""
        ...
    @property
    def optimal_cost(self) -> float: ...
    @property
    def success(self) -> bool: ...
    @property
    def nit(self) -> int: ...
    @property
    def nfev(self) -> int: ...
    @property
    def projected_gradient(self) -> float: ...
    @property
    def message(self) -> str: ...
    @property
    def input_pending(self) -> bool: ...
    @property
    def n_nodes(self) -> int: ...
    @property
    def n_residuals(self) -> int: ...
    def rounding_noise(self, z: _F) -> tuple[float, float]:
        """(noise of J, largest noise of ∇J) at z, estimated from the GPs' rounding."""
        ...
    def cost(self, z: _F) -> float: ...
    def cost_grad(self, z: _F) -> tuple[float, _F]: ...
    def gn_hessian(self, z: _F) -> _F: ...
    def residuals(self, z: _F) -> _F: ...
    def jacobian(self, z: _F) -> _F: ...
    def row_discounts(self, z: _F) -> _F: ...
    # copies, pickles and checkpoints: a copy is independent (the GPs are shared, immutable)
    # and continues bit-identically; the state is the history and, for the learned model, the
    # cache of its last evaluation
    def __copy__(self) -> MovingHorizon: ...
    def __deepcopy__(self, _memo: Any) -> MovingHorizon: ...
    def __reduce__(self) -> tuple[Any, ...]: ...
    def __getstate__(self) -> dict[str, Any]:
        """`t`, `window_t0` (int), `u` (rows, m), `y` (rows, p), `present` (rows,) bool,
        `priors` (k, n), `x_window` (nodes, n), `arrival_sqrt` (n, n), the last report
        `outcome_x_prior`, `outcome_P`, `outcome_cost`, `outcome_success`, `outcome_nit`,
        `outcome_nfev`, `outcome_projected_gradient`, `outcome_message`,
        `outcome_input_pending`, and for the learned model `cache_d`, `cache_mean_x`, ... (1-D)."""
        ...
    def __setstate__(self, state: dict[str, Any]) -> None:
        """Restore `__getstate__` of an estimator with the same settings; every entry is
        checked (ValueError naming it) and nothing changes on error."""
        ...

class EstimatorBank:
    """n independent `MovingHorizon` estimators with one template's settings (rust/src/mhe/bank.rs),
    updated together: in parallel without the GIL on the learned model or a compiled CasADi model
    (shared), one after another with the GIL on a callback model. See `gpmhe.EstimatorBank`."""

    def __init__(
        self, template: MovingHorizon, x0: _F, lower: _F, upper: _F, q0: _F, r0: _F
    ) -> None:
        """Row i of `x0`, `lower`, `upper` (k, n), `q0` (k, n or n²), `r0` (k, p or p²):
        estimator i's x̂(0), box and Q0, R0 (diagonals or row-major matrices); the rest (model,
        η, P2, form, horizon, solver settings) from `template`."""
        ...
    def __len__(self) -> int: ...
    @property
    def parallel(self) -> bool:
        """Whether updates run in parallel (the learned model or a compiled CasADi model)."""
        ...
    @staticmethod
    def threads() -> int:
        """Threads of a parallel update (rayon's pool; `RAYON_NUM_THREADS`)."""
        ...
    def update(
        self,
        u: _F,
        y: _F,
        present: npt.NDArray[np.bool_],
        r: _F | None = None,
        u_last: _F | None = None,
    ) -> None:
        """One update of every estimator (rows of `u` (k, m), `y` (k, p); `present[i]` False:
        estimator i's y is missing; row i of `r` (k, p or p²): its y's covariance, the diagonal
        or the row-major matrix, None for R0; row i of `u_last`: its last input row as this
        sample completes it), recorded with what each reports (the properties below) once every
        estimator has succeeded; on error no estimator changes."""
        ...
    @property
    def last_inputs(self) -> _F:
        """Each estimator's last recorded input row (k, m; zeros before the first update)."""
        ...
    # what the last update reported, one row per estimator
    @property
    def t(self) -> int: ...
    @property
    def x(self) -> _F: ...
    @property
    def x_window(self) -> _F: ...
    @property
    def x_prior(self) -> _F: ...
    @property
    def covariance(self) -> _F: ...
    @property
    def optimal_cost(self) -> _F: ...
    @property
    def success(self) -> npt.NDArray[np.bool_]: ...
    @property
    def nit(self) -> npt.NDArray[np.int64]: ...
    @property
    def nfev(self) -> npt.NDArray[np.int64]: ...
    @property
    def projected_gradient(self) -> _F: ...
    @property
    def messages(self) -> list[str]: ...
    def member(self, i: int) -> MovingHorizon:
        """Estimator i as an independent `MovingHorizon`."""
        ...
    def member_state(self, i: int) -> dict[str, Any]:
        """Estimator i's `MovingHorizon.__getstate__`."""
        ...
    def reset(self, indices: list[int], x0: _F) -> None:
        """Restarts estimator `indices[j]` from row j of `x0` (the core's state x̂(0)); on error
        no estimator changes."""
        ...
    def add_delayed(self, i: int, y: _F, age: int, r: _F | None = None) -> None:
        """Record a late output for estimator i (`MovingHorizon.add_delayed`)."""
        ...
    @property
    def max_delay(self) -> int:
        """The largest age `add_delayed` accepts now."""
        ...
    def set_member_state(self, i: int, state: dict[str, Any]) -> None:
        """Restore estimator i from `member_state` (checked; nothing changes on error)."""
        ...
    def __copy__(self) -> EstimatorBank: ...
    def __deepcopy__(self, _memo: Any) -> EstimatorBank: ...

class WindowSolver:
    """The real-time bounded Gauss-Newton window solver (rust/src/solver/): settings (given to
    `MovingHorizon`) and work buffers for solving a set window directly."""

    def __init__(
        self,
        max_iter: int = 100,
        gtol: float = 1e-6,
        xtol: float = 1e-12,
        ftol: float = 1e-15,
        dtol: float = 1e-2,
        interior: str = "auto",
        interior_zone: float = 1e-5,
        mu_init: float = 0.1,
        mu_final: float = 1e-5,
    ) -> None: ...
    def solve(
        self,
        window: MovingHorizon,
        z0: npt.NDArray[np.float64],
        lower: npt.NDArray[np.float64],
        upper: npt.NDArray[np.float64],
    ) -> tuple[npt.NDArray[np.float64], float, str, bool, int, int, float, int,
               npt.NDArray[np.float64] | None]:
        """(z, cost, status, success, nit, nfev, projected_gradient, interior_iterations, P);
        status is one of gradient-tolerance, decrement-tolerance, step-tolerance,
        cost-tolerance, noise-floor (successes), max-iterations, no-progress. P: the last n×n
        block of 4(2JᵀJ)⁻¹ at z, symmetrised (None if singular)."""
        ...
    def __reduce__(self) -> tuple[Any, ...]:
        """Pickles as its constructor call with the settings."""
        ...
