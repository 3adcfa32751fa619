"""Fitting a GP's hyperparameters, for the exact and the sparse GP alike: a training objective (a
log marginal likelihood or a sparse bound, plus an optional hyperprior) maximised with SciPy's
L-BFGS-B from the start and random restarts inside the bounds; the settings every fit uses
(`Fitting`), the test of whether a run converged, and the warning's source line."""

from __future__ import annotations

import warnings
from typing import Any, Callable, NamedTuple, Optional, Tuple

import numpy as np
import scipy.optimize

from gpmhe.gp import priors as _priors
from gpmhe._core import NumericalError
from gpmhe._validation import user_stacklevel

from gpmhe.gp.errors import ConvergenceWarning

__all__: list = []


class Fitting(NamedTuple):
    """What one fit of q outputs needs besides the data and the approximation: the log-bounds
    (n_d + 2, 2), each output's shift to the optimiser's units t = theta − shift (q, n_d + 2),
    the hyperprior rows, the random generator of the restarts and the L-BFGS-B limits."""

    log_bounds: np.ndarray
    shift: np.ndarray
    prior: Any
    rng: np.random.Generator
    n_restarts: int
    maxiter: int

    def record(self, runs: list) -> Tuple[np.ndarray, list]:
        """The fit's record for the diagnostics: natural-unit log-bounds per output
        (q, n_d + 2, 2) and every optimiser run's objective per output."""
        return self.log_bounds[None, :, :] + self.shift[:, :, None], runs


def _posterior(
    lml: Callable[[np.ndarray], Tuple[float, np.ndarray]],
    shift: np.ndarray,
    prior: Optional[Tuple[np.ndarray, np.ndarray]],
) -> Callable[[np.ndarray], Tuple[float, np.ndarray]]:
    """The fit's objective in the optimiser's units t = theta − shift: lml(t + shift) plus the
    log-prior of t (`gpmhe.gp.priors.log_prior`)."""

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

    def run(t0: np.ndarray, box: np.ndarray = log_bounds) -> Any:
        return scipy.optimize.minimize(
            negated,
            t0,
            jac=True,
            method="L-BFGS-B",
            bounds=box,
            # Tighter than SciPy's defaults: the LML is flat near its optimum.
            options={"maxiter": maxiter, "ftol": 1e-12, "gtol": 1e-9},
        )

    starts = [np.clip(theta0, log_bounds[:, 0], log_bounds[:, 1])]
    starts += [rng.uniform(log_bounds[:, 0], log_bounds[:, 1]) for _ in range(n_restarts)]
    best: Optional[Any] = None
    values = []
    for t0 in starts:
        res = run(t0)
        values.append(-float(res.fun))
        if np.isfinite(res.fun) and (best is None or res.fun < best.fun):
            best = res
    if best is None:
        raise NumericalError(
            "fit: no optimiser run reached a finite log marginal likelihood; "
            "check the data scaling and the bounds"
        )
    if _degenerate(best, log_bounds):
        # The data explained as noise (sigma_f pinned at its lower bound, or every length-scale
        # at its upper one): often reached because L-BFGS-B's first steps, scaled by a large
        # gradient, jump to the box's corner. Again from the start with steps of at most one
        # log-unit; the better result is kept.
        again = _short_steps(run, starts[0], log_bounds)
        values.append(-float(again.fun))
        if np.isfinite(again.fun) and again.fun < best.fun:
            best = again
    if _projected_gradient(best, log_bounds) > _gradient_tolerance(best):
        # L-BFGS-B can stop (even with status 0, "relative reduction small") where the gradient
        # is not small: a fresh run from there, without the old curvature pairs, often goes on.
        again = run(best.x)
        values.append(-float(again.fun))
        if np.isfinite(again.fun) and again.fun <= best.fun:
            best = again
    pg = _projected_gradient(best, log_bounds)
    if pg > _gradient_tolerance(best):
        warnings.warn(
            f"fit: L-BFGS-B stopped, twice, where the objective's projected gradient is still large "
            f"({pg:.3g}; status {best.status}: {best.message}); the best hyperparameters found are "
            f"used. Typical causes: an iteration limit (raise maxiter), badly scaled data (try "
            f"normalize=True), or a kernel matrix so ill-conditioned that the jitter changes from "
            f"one trial point to the next (fewer or less clustered training points, for a sparse GP "
            f"fewer inducing points, or a larger lower bound on sigma_eps)",
            ConvergenceWarning,
            stacklevel=user_stacklevel(),
        )
    if _degenerate(best, log_bounds):
        warnings.warn(
            "fit: the fitted GP explains the data as noise (sigma_f at its lower bound, or every "
            "length-scale at its upper one), also when the fit was repeated with short steps "
            "from the start. If the data are not pure noise this is a poor local optimum: try "
            "other initial values, n_restarts > 0, normalize=True or other bounds, and compare "
            "log_marginal_likelihood_value",
            ConvergenceWarning,
            stacklevel=user_stacklevel(),
        )
    return np.asarray(best.x, dtype=np.float64), -float(best.fun), np.array(values)


def _degenerate(res: Any, log_bounds: np.ndarray) -> bool:
    """Whether an L-BFGS-B result (of the negated objective, in [log sigma_f, log lengthscales...,
    log sigma_eps]) is pinned in the noise-only corner: sigma_f at its lower bound or every
    length-scale at its upper one, with the objective pushing against the bound."""
    if res.jac is None or not np.all(np.isfinite(res.jac)):
        return False
    x, g, tol = np.asarray(res.x), np.asarray(res.jac), 1e-8 * (1.0 + np.abs(log_bounds))
    low = (x <= log_bounds[:, 0] + tol[:, 0]) & (g > 0)
    high = (x >= log_bounds[:, 1] - tol[:, 1]) & (g < 0)
    return bool(low[0] or high[1:-1].all())


def _short_steps(run: Callable, t0: np.ndarray, log_bounds: np.ndarray, radius: float = 1.0) -> Any:
    """L-BFGS-B from t0 inside boxes of half-width ``radius`` around the current point, moved
    while the result sits on an edge of its box that is not a bound, then once in the whole box."""
    t = np.asarray(t0, dtype=np.float64)
    for _ in range(50):
        box = np.column_stack([np.maximum(log_bounds[:, 0], t - radius), np.minimum(log_bounds[:, 1], t + radius)])
        res = run(t, box)
        if not np.isfinite(res.fun):
            break
        edge = ((box[:, 0] > log_bounds[:, 0]) & (res.x <= box[:, 0])) | \
            ((box[:, 1] < log_bounds[:, 1]) & (res.x >= box[:, 1]))
        t = np.asarray(res.x, dtype=np.float64)
        if not edge.any():
            break
    return run(t)


def _projected_gradient(res: Any, log_bounds: np.ndarray) -> float:
    """The largest component of the gradient at an L-BFGS-B result projected on the box (the
    components pushing against an active bound count as zero); inf without a finite gradient."""
    if res.jac is None or not np.all(np.isfinite(res.jac)):
        return np.inf
    x, g = np.asarray(res.x), np.asarray(res.jac)
    at_bound = ((x <= log_bounds[:, 0]) & (g > 0)) | ((x >= log_bounds[:, 1]) & (g < 0))
    return float(np.max(np.abs(np.where(at_bound, 0.0, g)), initial=0.0))


def _gradient_tolerance(res: Any) -> float:
    """Whether a run converged is judged on its projected gradient, whatever status SciPy
    reports: at most 1e-3 (1 + |objective|). The objective (a log likelihood in nats) is only
    accurate to ~1e-9 relative on ill-conditioned data, so a line search may fail close to the
    optimum; a gradient this small means an optimum to that accuracy."""
    return 1e-3 * max(1.0, abs(float(res.fun)))
