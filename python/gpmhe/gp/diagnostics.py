"""Fit diagnostics of the GPs: per output the fitted hyperparameters, which of them sit at a
bound, the objective of every optimiser run, and leave-one-out (LOO) errors in closed form
against the noise level and against a straight line (dense O(N³) for the exact GPs, O(N m²) for
the sparse ones). The GP classes' and `LearnedModel`'s ``diagnostics()`` return them;
``summary()`` prints them.
"""

from __future__ import annotations

from typing import Callable, List, Optional, Tuple

import numpy as np
import scipy.linalg

from gpmhe import _core

__all__ = ["FitDiagnostics", "FitWarning"]

#: A hyperparameter within this distance (in log units, 0.1 %) of a bound is "at" it.
AT_BOUND = 1e-3
#: The GP has collapsed when its LOO RMSE exceeds this multiple of a straight line's.
COLLAPSE_RATIO = 1.25
#: The GP is miscalibrated when its standardised LOO residuals have an RMS above this (or below
#: its inverse).
CALIBRATION_LIMIT = 3.0


class FitWarning(UserWarning):
    """A fitted GP looks unreliable: a hyperparameter sits at a bound, the GP predicts held-out
    targets worse than a straight line (collapsed), or its variances do not match its errors.
    The message carries the numbers; `LearnedModel.summary` prints them all.

    Examples
    --------
    >>> import warnings
    >>> import numpy as np
    >>> from gpmhe import FitWarning, LearnedModel
    >>> X = [np.cumsum(np.full((40, 1), 0.1), axis=0)]
    >>> with warnings.catch_warnings(record=True) as caught:
    ...     warnings.simplefilter("always")
    ...     _ = LearnedModel.from_trajectories(X, X, optimizer=None, sigma_f=1e-3, sigma_eps=1.0,
    ...                                        mean="zero")
    >>> any(issubclass(w.category, FitWarning) for w in caught)
    True
    """


class FitDiagnostics:
    """Diagnostics of one fitted GP output (``diagnostics()`` of the GP classes builds them).

    Parameters
    ----------
    output : int
        The output's index.
    sigma_f : float
        Fitted signal standard deviation.
    lengthscales : ndarray of shape (n_d,)
        Fitted length-scales.
    sigma_eps : float
        Fitted noise standard deviation.
    at_lower, at_upper : tuple of str
        Hyperparameters (``"sigma_f"``, ``"lengthscales[i]"``, ``"sigma_eps"``) within 0.1 % of
        their lower or upper bound (empty without an optimiser).
    restarts : ndarray
        The objective (log marginal likelihood plus log-prior) each optimiser run reached, in
        run order (the first from the initial hyperparameters); empty without an optimiser.
    log_marginal_likelihood : float
        log p(y | D, theta) of the GP at the fitted theta (on the targets minus the prior mean).
    loo_rmse : float
        Root-mean-square leave-one-out error: each target predicted from all the others, in
        closed form (Rasmussen & Williams, eq. 5.12).
    loo_z_rms : float
        RMS of the LOO errors divided by their predictive standard deviations (about 1 for a
        calibrated GP).
    line_rmse : float
        The LOO RMSE of a least-squares straight line b + w·d on the same targets.
    target_std : float
        Standard deviation of the targets the GP regresses.

    Attributes
    ----------
    collapsed : bool
        See the property.
    problems, warnings : list of str
        See the properties.

    Notes
    -----
    Every parameter is also an attribute of the same name.

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe import GaussianProcess
    >>> D = np.linspace(0.0, 5.0, 30)[:, None]
    >>> dg = GaussianProcess(mean="linear").fit(D, D[:, 0] + 0.1 * np.sin(D[:, 0])).diagnostics()[0]
    >>> dg.collapsed, len(dg.restarts)
    (False, 1)
    """

    def __init__(self, output, sigma_f, lengthscales, sigma_eps, at_lower, at_upper, restarts,
                 log_marginal_likelihood, loo_rmse, loo_z_rms, line_rmse, target_std):
        self.output, self.sigma_f, self.lengthscales, self.sigma_eps = output, sigma_f, lengthscales, sigma_eps
        self.at_lower, self.at_upper, self.restarts = at_lower, at_upper, restarts
        self.log_marginal_likelihood, self.loo_rmse, self.loo_z_rms = log_marginal_likelihood, loo_rmse, loo_z_rms
        self.line_rmse, self.target_std = line_rmse, target_std

    def __repr__(self):
        return f"FitDiagnostics(output={self.output}, problems={self.problems})"

    @property
    def collapsed(self) -> bool:
        """True if the GP predicts held-out targets worse than a straight line (by 25 %) with an
        error of the order of its noise level (at least half of sigma_eps): the noise term has
        absorbed signal a line would have explained."""
        return bool(self.loo_rmse > COLLAPSE_RATIO * self.line_rmse and self.loo_rmse >= 0.5 * self.sigma_eps)

    @property
    def problems(self) -> List[str]:
        """What looks wrong, in words with the numbers (empty for a sound fit): `warnings` and a
        miscalibration (LOO errors more than 3 times, or less than a third of, their predicted
        standard deviations)."""
        out = self.warnings
        if not 1 / CALIBRATION_LIMIT <= self.loo_z_rms <= CALIBRATION_LIMIT:
            out.append(f"miscalibrated: LOO errors are {self.loo_z_rms:.3g} x their predicted standard deviation")
        return out

    @property
    def warnings(self) -> List[str]:
        """The problems `LearnedModel.from_trajectories` warns about: a hyperparameter at a bound
        of the fit, a collapsed GP."""
        out = []
        if self.at_lower:
            out.append("at lower bound: " + ", ".join(self.at_lower))
        if self.at_upper:
            out.append("at upper bound: " + ", ".join(self.at_upper))
        if self.collapsed:
            out.append(f"collapsed: LOO RMSE {self.loo_rmse:.3g} > {COLLAPSE_RATIO} x a straight "
                       f"line's {self.line_rmse:.3g} (sigma_f {self.sigma_f:.3g}, sigma_eps {self.sigma_eps:.3g})")
        return out


def _bound_names(theta: np.ndarray, bound: np.ndarray, nd: int) -> Tuple[str, ...]:
    names = ["sigma_f"] + [f"lengthscales[{i}]" for i in range(nd)] + ["sigma_eps"]
    return tuple(n for n, t, b in zip(names, theta, bound) if abs(t - b) < AT_BOUND)


def _loo(D: np.ndarray, r: np.ndarray, theta: np.ndarray, jitter: float) -> Tuple[np.ndarray, np.ndarray]:
    """LOO errors and predictive variances of the GP at theta on targets r (dense, O(N³))."""
    sf, ls, se = np.exp(theta[0]), np.exp(theta[1:-1]), np.exp(theta[-1])
    K = _core.se_ard_kernel(D, D, sf, ls)
    K[np.diag_indices_from(K)] += se * se + jitter
    Kinv = scipy.linalg.cho_solve(scipy.linalg.cho_factor(K, lower=True), np.eye(len(r)))
    diag = np.diag(Kinv)
    return (Kinv @ r) / diag, 1.0 / diag


def sparse_loo(D: np.ndarray, r: np.ndarray, Z: np.ndarray, theta: np.ndarray, jitter: float,
               fitc: bool, block: int = 4096) -> Tuple[np.ndarray, np.ndarray]:
    """LOO errors and predictive variances of one sparse output on targets r: the closed form
    for the Gaussian model y ~ N(0, Σ), Σ = Qff + Λ, that the sparse GP is (Λ = σ_ε² I for VFE,
    diag(Kff − Qff) + σ_ε² I for FITC): e_i = [Σ⁻¹ r]_i / [Σ⁻¹]_ii, with the Woodbury form
    Σ⁻¹ = Λ⁻¹ − Λ⁻¹ V^T B⁻¹ V Λ⁻¹, V = L⁻¹ Kuf, L L^T = Kuu + jitter I, B = I + V Λ⁻¹ V^T.
    O(N m²) time and O(m · block) memory: Kuf is formed block by block, three times."""
    sf, ls, se2 = np.exp(theta[0]), np.exp(theta[1:-1]), np.exp(2.0 * theta[-1])
    L = scipy.linalg.cholesky(_core.se_ard_kernel(Z, Z, sf, ls) + jitter * np.eye(len(Z)), lower=True)
    blocks = [slice(i, min(i + block, len(D))) for i in range(0, len(D), block)]

    def V(s: slice) -> np.ndarray:
        return scipy.linalg.solve_triangular(L, _core.se_ard_kernel(Z, D[s], sf, ls), lower=True)

    lam, B = np.empty(len(D)), np.eye(len(Z))
    for s in blocks:
        v = V(s)
        lam[s] = se2 + (np.maximum(sf * sf - np.sum(v * v, axis=0), 0.0) if fitc else 0.0)
        B += (v / lam[s]) @ v.T
    LB = scipy.linalg.cholesky(B, lower=True)

    def W(s: slice) -> np.ndarray:  # L_B⁻¹ V Λ⁻¹ on the block's columns
        return scipy.linalg.solve_triangular(LB, V(s) / lam[s], lower=True)

    wr, diag = np.zeros(len(Z)), 1.0 / lam
    for s in blocks:
        w = W(s)
        wr += w @ r[s]
        diag[s] -= np.sum(w * w, axis=0)
    inv_r = r / lam
    for s in blocks:
        inv_r[s] -= W(s).T @ wr
    return inv_r / diag, 1.0 / diag


def _line_loo_rmse(D: np.ndarray, r: np.ndarray) -> float:
    """LOO RMSE of least squares on [1, d] (the hat matrix's closed form)."""
    A = np.hstack([np.ones((D.shape[0], 1)), D])
    Q, _ = np.linalg.qr(A)
    h = np.clip(np.sum(Q * Q, axis=1), 0.0, 1.0 - 1e-12)
    e = (r - Q @ (Q.T @ r)) / (1.0 - h)
    return float(np.sqrt(np.mean(e * e)))


def exact_loo(D: np.ndarray, thetas: np.ndarray, jitters: np.ndarray) -> Callable:
    """``loo(o, r)`` of `diagnose` for an exact GP: output o's dense closed form."""
    return lambda o, r: _loo(D, r, thetas[o], float(jitters[o]))


def diagnose(D: np.ndarray, R: np.ndarray, thetas: np.ndarray, lmls: np.ndarray,
             record: Optional[Tuple[np.ndarray, list]], loo: Callable) -> List[FitDiagnostics]:
    """FitDiagnostics of every output of a fitted GP: inputs D (N, n_d), regressed targets
    R (N, q), natural theta (q, n_d + 2), the fit's record (natural log-bounds (q, n_d + 2, 2)
    and the runs' objectives) or None, and ``loo(o, r)`` giving output o's LOO errors and
    predictive variances on targets r (`exact_loo`, or the sparse model's)."""
    nd = D.shape[1]
    out = []
    for o in range(R.shape[1]):
        r = R[:, o]
        e, var = loo(o, r)
        lower = upper = ()
        runs = np.zeros(0)
        if record is not None:
            bounds, all_runs = record
            lower = _bound_names(thetas[o], bounds[o, :, 0], nd)
            upper = _bound_names(thetas[o], bounds[o, :, 1], nd)
            runs = np.asarray(all_runs[o], dtype=np.float64)
        t = np.exp(thetas[o])
        out.append(FitDiagnostics(
            output=o, sigma_f=float(t[0]), lengthscales=t[1:-1].copy(), sigma_eps=float(t[-1]),
            at_lower=lower, at_upper=upper, restarts=runs, log_marginal_likelihood=float(lmls[o]),
            loo_rmse=float(np.sqrt(np.mean(e * e))), loo_z_rms=float(np.sqrt(np.mean(e * e / var))),
            line_rmse=_line_loo_rmse(D, r), target_std=float(np.std(r)),
        ))
    return out


def summary_table(title: str, diags: List[FitDiagnostics], names: Optional[List[str]] = None) -> str:
    """A plain-text table of diagnostics, one row per output, and the problems below it."""
    rows = [title, f"{'output':>10} {'sigma_f':>9} {'lengthscales':>24} {'sigma_eps':>9} {'LOO RMSE':>9} "
            f"{'line':>9} {'LOO z':>6} {'runs (best)':>16}"]
    notes = []
    for d in diags:
        name = names[d.output] if names else str(d.output)
        ls = np.array2string(d.lengthscales, precision=2, max_line_width=1000, separator=" ")
        runs = f"{len(d.restarts)} ({np.max(d.restarts):.4g})" if len(d.restarts) else "-"
        rows.append(f"{name:>10} {d.sigma_f:9.3g} {ls:>24} {d.sigma_eps:9.3g} {d.loo_rmse:9.3g} "
                    f"{d.line_rmse:9.3g} {d.loo_z_rms:6.2f} {runs:>16}")
        notes += [f"  {name}: {p}" for p in d.problems]
    return "\n".join(rows + (notes or ["  no problems found"]))

