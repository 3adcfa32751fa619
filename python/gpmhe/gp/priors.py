"""What a GP fit assumes before it sees the hyperparameters: the prior mean (zero, constant or
linear, fitted by least squares before theta), the data scales of ``normalize`` and the log-normal
hyperparameter priors (``hyperprior``). `gpmhe.gp` uses these in ``fit``; the user guide,
*Gaussian processes*, explains the choices.
"""

from __future__ import annotations

from typing import Any, Optional, Tuple

import numpy as np

from gpmhe._validation import one_of

MEANS = ("zero", "constant", "linear")

#: The ``hyperprior="default"`` priors: (median, standard deviation of the log) in the units the
#: bounds use (standardised with ``normalize=True``): a length-scale about the spread of the
#: inputs, a signal about the spread of the targets, noise about a tenth of it, each within a
#: factor e^1.5 ≈ 4.5 per standard deviation.
DEFAULT_HYPERPRIOR = {"sigma_f": (1.0, 1.5), "lengthscales": (1.0, 1.5), "sigma_eps": (0.1, 1.5)}

#: The ``hyperprior="residual"`` priors, for the residual of a nominal model (the default of
#: `gpmhe.LearnedModel.from_trajectories` with ``f_nominal`` or ``h_nominal``): what a nominal
#: model misses (a wrong parameter, a missing term) is assumed to be of unknown and often small
#: size next to the noise, and smooth over the whole operating range. So sigma_f about a tenth of
#: the targets' spread and sigma_eps about all of it (the reverse of "default", which assumes the
#: targets are mostly signal), and length-scales about 10 spreads of the inputs, so that the GP
#: carries its correction beyond the training data rather than falling back to the nominal model
#: within a spread of them, and can leave out an input the residual does not depend on. Data
#: that need a larger signal or shorter length-scales still get them. The user guide, *Learned
#: models*, has the measurements.
RESIDUAL_HYPERPRIOR = {"sigma_f": (0.1, 1.5), "lengthscales": (10.0, 1.5), "sigma_eps": (1.0, 1.5)}

#: The named hyperpriors.
NAMED_HYPERPRIORS = {"default": DEFAULT_HYPERPRIOR, "residual": RESIDUAL_HYPERPRIOR}


# ----------------------------------------------------------------------------- prior mean


def check_mean(mean: Any) -> str:
    return one_of("mean", mean, MEANS)


def fit_mean(kind: str, D: np.ndarray, Y: np.ndarray) -> Optional[np.ndarray]:
    """Least-squares coefficients (q, n_d + 1), rows [b, w...], of the prior mean ``kind`` on
    (D, Y) (N, n_d), (N, q); None for the zero mean."""
    if kind == "zero":
        return None
    q, nd = Y.shape[1], D.shape[1]
    coef = np.zeros((q, nd + 1))
    if kind == "constant":
        coef[:, 0] = Y.mean(axis=0)
        return coef
    A = np.hstack([np.ones((D.shape[0], 1)), D])
    sol, *_ = np.linalg.lstsq(A, Y, rcond=None)
    coef[:] = sol.T
    return coef


def residuals(coef: Optional[np.ndarray], D: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """The targets the GPs regress, Y − m(D) (N, q), C-contiguous; Y itself for the zero mean."""
    if coef is None:
        return Y
    return np.ascontiguousarray(Y - (coef[:, 0] + D @ coef[:, 1:].T))


# ----------------------------------------------------------------------------- scales


def log_scales(normalize: bool, D: np.ndarray, R: np.ndarray) -> np.ndarray:
    """(q, n_d + 2) offsets from standardised to natural theta: log([s_y, s_d..., s_y]) per output
    with s_d the inputs' and s_y the residual targets' standard deviations (zeros without
    ``normalize``; a constant column counts as scale 1)."""
    q, nd = R.shape[1], D.shape[1]
    if not normalize:
        return np.zeros((q, nd + 2))

    def spread(a: np.ndarray) -> np.ndarray:
        s = a.std(axis=0)
        return np.where(s > 0, s, 1.0)

    sd, sy = np.log(spread(D)), np.log(spread(R))
    return np.column_stack([sy, np.broadcast_to(sd, (q, nd)), sy])


# ----------------------------------------------------------------------------- hyperpriors


def check_hyperprior(value: Any) -> Any:
    """None, "default", "residual" or a dict of (median > 0, log-sd > 0) pairs for some of
    sigma_f, lengthscales (a pair, or a median per input with one log-sd) and sigma_eps."""
    if value is None or (isinstance(value, str) and value in NAMED_HYPERPRIORS):
        return value
    if not isinstance(value, dict):
        raise ValueError(f'hyperprior: must be None, "default", "residual" or a dict, got {value!r}')
    for key, pair in value.items():
        if key not in DEFAULT_HYPERPRIOR:
            raise ValueError(f"hyperprior: unknown key {key!r} (expected sigma_f, lengthscales, sigma_eps)")
        try:
            median, sd = pair
            median = np.asarray(median, dtype=np.float64)
            sd = float(sd)
        except (TypeError, ValueError):
            raise ValueError(f"hyperprior: {key} must be a (median, log-sd) pair, got {pair!r}") from None
        if median.ndim > (1 if key == "lengthscales" else 0) or not np.all(np.isfinite(median)) \
                or np.any(median <= 0) or not np.isfinite(sd) or sd <= 0:
            raise ValueError(f"hyperprior: {key} needs a finite median > 0 and a log-sd > 0, got {pair!r}")
    return value


def hyperprior_json(hyperprior: Any) -> Any:
    """The hyperprior as JSON-serialisable values (for saved files); `check_hyperprior` accepts
    the result."""
    if not isinstance(hyperprior, dict):
        return hyperprior
    return {k: [np.asarray(m, dtype=np.float64).tolist(), float(sd)] for k, (m, sd) in hyperprior.items()}


def prior_rows(hyperprior: Any, nd: int) -> Optional[Tuple[np.ndarray, np.ndarray]]:
    """(mu, sd) of the normal prior on theta (n_d + 2 values each, in the bounds' units), or
    None without a prior; a key the dict omits has no prior (sd = inf)."""
    if hyperprior is None:
        return None
    spec = NAMED_HYPERPRIORS[hyperprior] if isinstance(hyperprior, str) else hyperprior
    mu, sd = np.zeros(nd + 2), np.full(nd + 2, np.inf)
    for key, cols in (("sigma_f", slice(0, 1)), ("lengthscales", slice(1, nd + 1)), ("sigma_eps", slice(nd + 1, nd + 2))):
        if key in spec:
            median, s = spec[key]
            try:
                mu[cols] = np.log(np.broadcast_to(np.asarray(median, dtype=np.float64), (cols.stop - cols.start,)))
            except ValueError:
                raise ValueError(f"hyperprior: {key}: expected 1 or {nd} medians, got {np.size(median)}") from None
            sd[cols] = s
    return mu, sd


def log_prior(rows: Optional[Tuple[np.ndarray, np.ndarray]], theta: np.ndarray) -> Tuple[float, np.ndarray]:
    """log p(theta) (up to a constant) and its gradient; (0, 0) without a prior."""
    if rows is None:
        return 0.0, np.zeros_like(theta)
    mu, sd = rows
    z = np.where(np.isfinite(sd), (theta - mu) / sd, 0.0)
    grad = np.where(np.isfinite(sd), -z / sd, 0.0)
    return float(-0.5 * np.sum(z * z)), grad
