"""χ² consistency tests of an estimator's uncertainty over a run: the normalised estimation error
squared (NEES, needs the true states: simulations) and the normalised innovation squared (NIS,
needs only the data: a running plant). See the user guide, *Uncertainty*.

A consistent estimator's NEES at a step is χ² with n degrees of freedom (n states), its NIS χ²
with as many as channels measured; the mean of N independent such values lies, with probability
1 − α, in the two-sided band of χ²(Σ dof) / N. A mean above the band: the estimator is
over-confident (its covariance too small); below: under-confident. The NIS of a consistent
estimator is white, so the steps of one run are independent; its NEES is correlated from step
to step, so take one value per independent (Monte Carlo) run.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from gpmhe._validation import float_array, positive_scalar

__all__ = ["nees", "chi2_test", "Chi2Test"]


def nees(x_true, x_hat, P):
    """The normalised estimation error squared (x − x̂)ᵀP⁻¹(x − x̂) of each step.

    Parameters
    ----------
    x_true, x_hat : array_like of shape (T, n)
        The true states and the estimates.
    P : array_like of shape (T, n, n)
        The estimates' covariances (``GPMHE.P`` after each update, as `GPMHE.batch_filter`
        returns them).

    Returns
    -------
    ndarray of shape (T,)
        The NEES of each step.

    Raises
    ------
    ValueError
        If the shapes disagree or a covariance is not positive definite (naming the step).

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe.consistency import nees
    >>> print(nees([[1.0, 0.0]], [[0.0, 0.0]], [np.diag([0.5, 1.0])]))
    [2.]
    """
    x_true, x_hat, P = float_array("x_true", x_true), float_array("x_hat", x_hat), float_array("P", P)
    if x_true.ndim != 2 or x_hat.shape != x_true.shape:
        raise ValueError(f"x_true, x_hat: need the same shape (T, n), got {x_true.shape} and "
                         f"{x_hat.shape}")
    T, n = x_true.shape
    if P.shape != (T, n, n):
        raise ValueError(f"P: expected shape {(T, n, n)}, got {P.shape}")
    out = np.empty(T)
    for t in range(T):
        try:
            L = np.linalg.cholesky(P[t])
        except np.linalg.LinAlgError:
            raise ValueError(f"P: not positive definite at step {t}") from None
        w = np.linalg.solve(L, x_true[t] - x_hat[t])
        out[t] = w @ w
    return out


@dataclass(frozen=True)
class Chi2Test:
    """The result of `chi2_test`.

    Attributes
    ----------
    mean : float
        The mean of the values over the steps used.
    lower, upper : float
        The two-sided (1 − α) band of the mean of a consistent estimator.
    consistent : bool
        Whether ``mean`` lies in the band.
    steps : int
        The number of steps used (values that are NaN are left out).
    dof : float
        The mean degrees of freedom per step (the mean the values should have).
    """

    mean: float
    lower: float
    upper: float
    consistent: bool
    steps: int
    dof: float


def chi2_test(values, dof, alpha=0.05):
    """Whether the mean of χ²-distributed values (NEES or NIS over a run) is consistent.

    Parameters
    ----------
    values : array_like of shape (T,)
        Independent NEES or NIS values: the NIS of every step of a run, or the NEES of one step
        of each of T independent runs (NaN: no value, left out: e.g. ``nis`` of an update
        without a measurement).
    dof : int or array_like of shape (T,)
        The degrees of freedom of each step: n for the NEES, the number of measured channels for
        the NIS.
    alpha : float, default 0.05
        The test's level: the band holds a consistent estimator's mean with probability 1 − α.

    Returns
    -------
    Chi2Test
        A frozen dataclass: ``mean`` (of the values used), ``lower`` and ``upper`` (the band of a
        consistent estimator's mean), ``consistent`` (whether the mean lies in it), ``steps``
        (the values used) and ``dof`` (the mean degrees of freedom per value, what the mean
        should be).

    Raises
    ------
    ValueError
        If no step has a value, a degree of freedom is not positive, or ``alpha`` is not in
        (0, 1).

    Examples
    --------
    Values drawn from χ²(2) pass; twice as large (a covariance too small by 2) do not:

    >>> import numpy as np
    >>> from gpmhe.consistency import chi2_test
    >>> values = np.random.default_rng(1).chisquare(2, size=500)
    >>> chi2_test(values, dof=2).consistent, chi2_test(2 * values, dof=2).consistent
    (True, False)
    """
    values = np.ravel(float_array("values", values, missing=True))
    dof = np.broadcast_to(float_array("dof", dof), values.shape)
    alpha = positive_scalar("alpha", alpha)
    if not alpha < 1.0:
        raise ValueError(f"alpha: must be in (0, 1), got {alpha}")
    used = np.isfinite(values)
    if not used.any():
        raise ValueError("values: no step has a value")
    if np.any(dof[used] <= 0):
        raise ValueError("dof: must be positive at every step with a value")
    N, total = int(used.sum()), float(dof[used].sum())
    mean = float(values[used].mean())
    lower = float(stats.chi2.ppf(alpha / 2, total)) / N
    upper = float(stats.chi2.ppf(1 - alpha / 2, total)) / N
    return Chi2Test(mean, lower, upper, lower <= mean <= upper, N, total / N)
