"""`certify_ioss` and its `Certificate`: a quadratic δ-IOSS Lyapunov function of the learned model
on the box (the paper's Assumption 1), found by a semidefinite program, with the MHE design it
implies (P1, P2, η, the minimal horizon M̄ and μ)."""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg
import scipy.optimize

from gpmhe._validation import in_open_interval, integer, positive_scalar

from gpmhe.theory.common import _require_cvxpy, _check_model, _check_spd, _check_box, _Grid, _check_cells
from gpmhe.theory.posterior import _model_posteriors
from gpmhe.theory.weights import _weight_bounds
from gpmhe.theory.lmi import _jacobians, _check_pair, _interpolation_remainder, _LMIData, _SDP, _verified_eta, _random_pairs, _violation_18b

__all__ = ['Certificate', 'certify_ioss']


class Certificate:
    """A quadratic δ-IOSS Lyapunov function W(x, x̃) = ‖x − x̃‖²_P of a model on a box: the result
    of :func:`certify_ioss`.

    When `feasible` is True, Assumption 1 of the paper (eq. 18) holds for the model's mean
    functions on X × U with P1 = P2 = P, the discount `eta` and the weights `Q_inv`, `R_inv`; then
    Theorem 1 holds for the MHE run with ``mhe_options()`` and a horizon M ≥ ``min_horizon()``.

    Parameters
    ----------
    **fields
        Values of the attributes below (normally set by :func:`certify_ioss`); missing ones
        default to None (False for `feasible`).

    Attributes
    ----------
    feasible : bool
        Whether a certificate was found and passed all checks.
    reason : str
        Why not, when `feasible` is False; a summary otherwise.
    P : ndarray (n, n) or None
        The matrix of W.
    P1, P2 : ndarray (n, n) or None
        The bounds of (18a); both equal `P` for a quadratic W.
    eta : float or None
        The certified discount η of (18b).
    Q_inv, R_inv : ndarray
        Q_min⁻¹ and R_min⁻¹ used in (18b) (lower bounds of the MHE's weights over the box).
    weights : WeightBounds
        All four weight bounds (14)–(17).
    Q0, R0 : ndarray
        The constant covariance parts of the MHE's weights.
    x_bounds, u_bounds : tuple of ndarray
        The box X (and U) on which the certificate holds.
    C_hat : ndarray (p, n)
        The reference output Jacobian Ĉ of the output term's lower bound, chosen by the SDP
        (see Notes of :func:`certify_ioss`).
    eta_without_margin : float or None
        The η this P needs at the grid nodes alone (no allowance for the interpolation
        remainder): ``eta - eta_without_margin`` is the price of making the grid rigorous.
    jacobian_variation : tuple of float
        The bounds δ_A, δ_C of the spectral norm of the difference between ∂m_x/∂x (resp.
        ∂m_y/∂x) and its multilinear interpolation from the corners of a grid cell.
    margin_proved : bool
        True when δ_A, δ_C are proved bounds (learned models; known models with
        `jacobian_lipschitz`), False when estimated from finite differences.
    cells : ndarray of int
        Cells per dimension of the grid.
    check_pairs : int
        Number of random pairs (x, x̃, u) on which (18b) was re-checked after solving.
    check_worst : float or None
        The largest normalised violation of (18b) over those pairs (worst case over the
        disturbances), (LHS − RHS)/‖x − x̃‖²_P; ≤ 0 means it held on every pair.
    solver_status : str
        The SDP solver's last status.
    """

    def __init__(self, **fields):
        defaults = dict(feasible=False, reason="", P=None, eta=None, Q_inv=None, R_inv=None,
                        weights=None, Q0=None, R0=None, x_bounds=None, u_bounds=None, C_hat=None,
                        eta_without_margin=None, jacobian_variation=(0.0, 0.0),
                        margin_proved=False, cells=None, check_pairs=0, check_worst=None,
                        solver_status="")
        defaults.update(fields)
        for key, value in defaults.items():
            setattr(self, key, value)
        self.P1 = self.P2 = self.P

    def __repr__(self):
        if not self.feasible:
            return f"Certificate(feasible=False, reason={self.reason!r})"
        return (f"Certificate(feasible=True, eta={self.eta:.4f}, min_horizon={self.min_horizon()},"
                f" lambda(P)={np.round(np.linalg.eigvalsh(self.P), 4)})")

    def _need_feasible(self):
        if not self.feasible:
            raise ValueError(f"certificate: not feasible ({self.reason})")

    def min_horizon(self):
        """The minimal horizon M̄ of Theorem 1: the smallest M ≥ 1 with 4 λ_max(P2, P1) η^M < 1.

        Returns
        -------
        int
            M̄ = ⌊ln(4 λ_max(P2, P1)) / ln(1/η)⌋ + 1.

        Raises
        ------
        ValueError
            If the certificate is not feasible.

        Notes
        -----
        With P1 = P2 = P, λ_max(P2, P1) = 1 and M̄ = ⌊ln 4 / ln(1/η)⌋ + 1.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe.theory import Certificate
        >>> Certificate(feasible=True, P=np.eye(2), eta=0.9).min_horizon()
        14
        """
        self._need_feasible()
        lam = float(scipy.linalg.eigh(self.P2, self.P1, eigvals_only=True)[-1])
        M = int(math.floor(math.log(4.0 * lam) / -math.log(self.eta))) + 1
        while M > 1 and 4.0 * lam * self.eta ** (M - 1) < 1.0:  # guard against rounding
            M -= 1
        while 4.0 * lam * self.eta ** M >= 1.0:
            M += 1
        return max(M, 1)

    def mu(self, M):
        """The contraction μ of Theorem 1 for the horizon M: μ^M = 4 λ_max(P2, P1) η^M.

        Parameters
        ----------
        M : int
            The horizon, M ≥ 1.

        Returns
        -------
        float
            μ = (4 λ_max(P2, P1))^{1/M} η; below 1 exactly when M ≥ ``min_horizon()``.

        Raises
        ------
        ValueError
            If M is not a positive integer or the certificate is not feasible.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe.theory import Certificate
        >>> round(Certificate(feasible=True, P=np.eye(2), eta=0.9).mu(14), 4)
        0.9937
        """
        M = integer("M", M, 1)
        self._need_feasible()
        lam = float(scipy.linalg.eigh(self.P2, self.P1, eigvals_only=True)[-1])
        return (4.0 * lam) ** (1.0 / M) * self.eta

    def mhe_options(self, horizon=None):
        """Keyword arguments for :class:`gpmhe.GPMHE` that realise this certificate.

        Parameters
        ----------
        horizon : int, optional
            The MHE horizon M; default ``min_horizon()``. Must be ≥ ``min_horizon()``.

        Returns
        -------
        dict
            ``horizon``, ``eta``, ``P2`` (= P), ``Q0``, ``R0`` and ``x_bounds`` (the state
            constraint (10d) the theorem needs): ``GPMHE(model, x0, **cert.mhe_options())``.

        Raises
        ------
        ValueError
            If the certificate is not feasible or `horizon` < ``min_horizon()``.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe.theory import Certificate
        >>> cert = Certificate(feasible=True, P=np.eye(2), eta=0.9, Q0=np.eye(2), R0=np.eye(1),
        ...                    x_bounds=(np.zeros(2), np.ones(2)))
        >>> sorted(cert.mhe_options())
        ['P2', 'Q0', 'R0', 'eta', 'horizon', 'x_bounds']
        """
        self._need_feasible()
        M_bar = self.min_horizon()
        M = M_bar if horizon is None else integer("horizon", horizon, 1)
        if M < M_bar:
            raise ValueError(f"horizon: must be >= min_horizon() = {M_bar}, got {M}")
        return dict(horizon=M, eta=float(self.eta), P2=self.P.copy(), Q0=self.Q0.copy(),
                    R0=self.R0.copy(), x_bounds=(self.x_bounds[0].copy(), self.x_bounds[1].copy()))


def certify_ioss(model, x_bounds, Q0, R0, u_bounds=None, eta=None, P=None, *,
                 variance_bound="posterior", cells=None, jacobian_lipschitz=None,
                 jacobian_curvature=None,
                 max_condition=1e4, eta_tol=1e-3, n_check=100_000, seed=0, solver=None):
    """Search a quadratic δ-IOSS Lyapunov function of the model on a box (Assumption 1, eq. 18).

    Finds P ≻ 0 and η ∈ (0, 1) such that W(x, x̃) = ‖x − x̃‖²_P satisfies, for all x, x̃ ∈ X,
    u ∈ U and all disturbances w, w̃,

    ‖m_x(x, u) + w − m_x(x̃, u) − w̃‖²_P ≤ η ‖x − x̃‖²_P + ‖w − w̃‖²_{Q_min⁻¹}
    + ‖m_y(x, u) − m_y(x̃, u)‖²_{R_min⁻¹},

    i.e. (18b) with P1 = P2 = P. η is minimised (bisection to `eta_tol`) unless given; P is
    searched unless given.

    Parameters
    ----------
    model : LearnedModel or KnownModel
        The model whose mean functions m_x, m_y the MHE uses.
    x_bounds : pair of arrays (n,)
        The box X = [lower, upper] (the MHE's state constraint).
    Q0, R0 : float, array or matrix
        The constant covariance parts of the MHE's weights (gpmhe's convention).
    u_bounds : pair of arrays (m,), optional
        The box U of the control inputs (required when the model has inputs).
    eta : float, optional
        Fix η ∈ (0, 1) instead of minimising it.
    P : array (n, n), optional
        Fix the matrix of W (symmetric positive definite) and only minimise η.
    variance_bound : {"posterior", "prior"}
        How the posterior variances in Q_min⁻¹, R_min⁻¹ are bounded: the guaranteed maximum over
        the box (default) or the paper's σ_f² + σ_ε² (see :func:`weight_bounds`).
    cells : int or sequence of int, optional
        Grid cells per dimension of X × U (default about 400 cells in total).
    jacobian_lipschitz : float or pair of float, optional
        For a KnownModel: Lipschitz constants of d ↦ ∂f/∂x(d) and d ↦ ∂h/∂x(d) (spectral norm,
        Euclidean norm on d); the grid remainder is then at most 2 L ‖h‖ (h the cell
        half-widths).
    jacobian_curvature : float or pair of float, optional
        For a KnownModel: bounds of the absolute second derivatives ∂²A_ij/∂d_c² and
        ∂²C_ij/∂d_c² over the box (entries of the Jacobians A = ∂f/∂x, C = ∂h/∂x, every
        coordinate c of d); 0 when f and h are quadratic. The remainder is then at most Σ_c ½ h_c² times the bound per entry, which
        shrinks with the square of the cell size. With either constant the grid margin is proved;
        with neither, it is estimated from second differences of the Jacobians
        (``margin_proved`` False). Both are ignored for learned models, whose bounds are computed
        from the GPs.
    max_condition : float
        Upper bound of the condition number of P (keeps P usable as the MHE's prior weight).
    eta_tol : float
        Bisection tolerance on η.
    n_check : int
        Random pairs on which (18b) is re-checked after solving (0 skips the check).
    seed : int
        Seed of the random pairs.
    solver : str, optional
        A cvxpy solver name; default Clarabel, then SCS.

    Returns
    -------
    Certificate
        ``feasible`` with P, η, ``min_horizon()``, ``mhe_options()``, or the reason for failure.

    Raises
    ------
    ValueError
        On invalid arguments (the message names the argument).
    ImportError
        If cvxpy is not installed (``pip install cvxpy clarabel``, the ``theory`` extra).

    Notes
    -----
    **From pairs to a differential inequality.** With Δ = x − x̃ and Δw = w − w̃, the mean value
    theorem along the segment from x̃ to x (inside the convex box) gives
    m_x(x) − m_x(x̃) = Ā Δ and m_y(x) − m_y(x̃) = C̄ Δ with Ā = ∫₀¹ A(x̃ + sΔ) ds,
    C̄ = ∫₀¹ C(x̃ + sΔ) ds, A = ∂m_x/∂x, C = ∂m_y/∂x. The state term ‖ĀΔ + Δw‖²_P is convex in Ā,
    so it is at most the average of ‖A(·)Δ + Δw‖²_P along the segment (Jensen). The output term
    enters with the opposite sign and ‖C̄Δ‖² is *not* bounded below by the average of ‖C(·)Δ‖²
    (Jensen goes the wrong way), so the pointwise LMI with C(x)ᵀR⁻¹C(x) alone does not imply
    (18b) unless C is constant. gpmhe uses instead the lower bound, affine in C,

    .. math:: \\|C\\Delta\\|^2_{R^{-1}} \\ge \\Delta^\\top (C^\\top R^{-1} \\hat C
              + \\hat C^\\top R^{-1} C - \\hat C^\\top R^{-1} \\hat C) \\Delta
              = \\|C\\Delta\\|^2_{R^{-1}} - \\|(C - \\hat C)\\Delta\\|^2_{R^{-1}},

    valid for any fixed Ĉ. Being affine, it averages along the segment exactly, so the pointwise
    condition, for all d in X × U,

    .. math:: \\begin{bmatrix} A^\\top P A - \\eta P - S(d) & A^\\top P \\\\ P A & P - Q^{-1}
              \\end{bmatrix} \\preceq 0, \\quad S = C^\\top R^{-1}\\hat C + \\hat C^\\top
              R^{-1} C - \\hat C^\\top R^{-1}\\hat C,

    implies (18b) for every pair. It is exact for a linear output map (C = Ĉ) and costs
    ‖(C − Ĉ)Δ‖²_{R⁻¹} otherwise.

    Ĉ is a decision variable of the semidefinite program (the condition is jointly convex in P
    and Ĉ once Ĉᵀ R⁻¹ Ĉ is written as a Schur complement).

    **From the grid to the box.** The box is cut into cells and the condition, written as an LMI
    affine in A and C (Schur complement), is imposed at the cell corners. Inside a cell, A(d) is
    the multilinear interpolation of its corner values — a convex combination, for which the
    affine LMI follows from the corners — plus a remainder with ‖·‖₂ ≤ δ_A (and alike δ_C for C).
    Each corner's LMI is made robust against any such remainder (Petersen's lemma, one multiplier
    per corner and remainder). Per entry the remainder is at most Σ_c ½ h_c² max abs(∂²A_ij/∂d_c²);
    for a GP the third derivatives of the posterior mean are bounded by its RKHS norm
    sqrt(αᵀKα) times the SE kernel's derivative bounds σ_f sqrt(15)/(φ_b φ_c²), so δ_A, δ_C are
    proved.

    **η and P.** η is minimised by bisection; a final solve `eta_tol` above the smallest η
    returns a well-scaled P. Among the feasible P the one with the largest smallest eigenvalue
    and condition number ≤ `max_condition` is returned.

    **Checks.** The η reported is recomputed in NumPy from the solver's P, Ĉ and multipliers (a
    Schur complement and a generalised eigenvalue per grid node), not taken from the solver.
    Then (18b) itself, in its worst case over the disturbances, is evaluated on `n_check` random
    pairs (a third uniform, a third close together, a third close together along the null space
    of Ĉ); a violation makes the certificate infeasible.

    **Proved and sampled.** For learned models and for known models with `jacobian_lipschitz`,
    the certificate is a proof up to floating-point rounding and the solver-independent NumPy
    recomputation; the random pairs are an independent sampled check. For known models without
    Lipschitz constants the grid margin is a finite-difference estimate.

    References
    ----------
    .. [1] T. M. Wolff, V. G. Lopez and M. A. Müller, "Robust stability of Gaussian process based
       moving horizon estimation", IEEE CDC 2023, Assumption 1, Theorem 1.
    .. [2] J. D. Schiller, S. Muntwiler, J. Köhler, M. N. Zeilinger and M. A. Müller, "A Lyapunov
       function for robust stability of moving horizon estimation", IEEE Trans. Automat. Control
       68(12), 2023, Sec. IV (LMI conditions for δ-IOSS).

    Examples
    --------
    A linear system whose unmeasured mode is stable:

    >>> import numpy as np
    >>> from gpmhe import KnownModel
    >>> from gpmhe.theory import certify_ioss
    >>> A = np.array([[1.0, 0.1], [0.0, 0.8]])
    >>> model = KnownModel(lambda x, u: A @ x, lambda x, u: x[:1], dim_x=2, dim_y=1,
    ...                    f_jacobian=lambda x, u: A, h_jacobian=lambda x, u: np.eye(1, 2))
    >>> cert = certify_ioss(model, (-np.ones(2), np.ones(2)), Q0=1e-2, R0=1e-2, cells=1,
    ...                     jacobian_lipschitz=0.0, n_check=1000)
    >>> cert.feasible, cert.eta < 0.7
    (True, True)
    """
    model = _check_model(model)
    n, p, m = model.dim_x, model.dim_y, model.dim_u
    xl, xu = _check_box("x_bounds", x_bounds, n)
    ul, uu = _check_box("u_bounds", u_bounds, m)
    Q0 = _check_spd("Q0", Q0, n)
    R0 = _check_spd("R0", R0, p)
    if eta is not None:
        eta = in_open_interval("eta", eta, 0.0, 1.0)
    if P is not None:
        P = _check_spd("P", P, n)
    if variance_bound not in ("prior", "posterior"):
        raise ValueError(f"variance_bound: must be 'prior' or 'posterior', got {variance_bound!r}")
    lip = _check_pair("jacobian_lipschitz", jacobian_lipschitz)
    curv = _check_pair("jacobian_curvature", jacobian_curvature)
    max_condition = positive_scalar("max_condition", max_condition)
    if max_condition < 1:
        raise ValueError(f"max_condition: must be >= 1, got {max_condition!r}")
    eta_tol = positive_scalar("eta_tol", eta_tol)
    n_check = integer("n_check", n_check, 0)
    seed = integer("seed", seed, 0)
    if solver is not None and not isinstance(solver, str):
        raise ValueError(f"solver: must be a cvxpy solver name or None, got {solver!r}")
    _require_cvxpy()

    lower, upper = np.concatenate([xl, ul]), np.concatenate([xu, uu])
    grid = _Grid(lower, upper, _check_cells(cells, n + m))
    posts = _model_posteriors(model)
    wb = _weight_bounds(model, Q0, R0, variance_bound, grid, posts)
    A, C = _jacobians(model, grid.nodes())
    dA, dC, proved = _interpolation_remainder(model, grid, A, C, lip, curv, posts)
    data = _LMIData(A, C, dA, dC, wb.Q_min_inv, wb.R_min_inv)
    common = dict(Q_inv=wb.Q_min_inv, R_inv=wb.R_min_inv, weights=wb, Q0=Q0, R0=R0,
                  x_bounds=(xl, xu), u_bounds=(ul, uu),
                  jacobian_variation=(dA, dC), margin_proved=proved,
                  cells=grid.counts)

    P_n, C_hat, lamA, lamC, eta_v, status = _search(data, eta, None if P is None else P / data.nu,
                                             max_condition, eta_tol, solver)
    if P_n is None or not eta_v < 1.0:
        why = ("no P satisfies the gridded LMI" + (f" with eta = {eta}" if eta is not None else
                                                     " for any eta < 1")
               + f" (solver status: {status}); the model may not be detectable on this box, or "
               "the weight bounds / grid margin are too conservative (try variance_bound="
               "'posterior' or more cells)")
        return Certificate(reason=why, solver_status=str(status), **common)
    eta_cert = eta if eta is not None else min(1.0 - 1e-12, eta_v * (1 + 1e-9) + 1e-12)
    if eta is not None and eta_v > eta:
        return Certificate(reason=f"the solver's P needs eta = {eta_v:.6g} > {eta} after the "
                           "independent re-check", solver_status=str(status), **common)
    P_out = 0.5 * (P_n + P_n.T) * data.nu
    no_margin = _LMIData(A, C, 0.0, 0.0, wb.Q_min_inv, wb.R_min_inv)
    eta_grid = _verified_eta(no_margin, P_n, C_hat, np.zeros(A.shape[0]), np.zeros(A.shape[0]))
    common["C_hat"] = C_hat
    worst = None
    if n_check:
        d, d2 = _random_pairs(lower, upper, n, n_check, np.random.default_rng(seed), C_hat)
        worst = float(np.max(_violation_18b(model, P_out, eta_cert, wb.Q_min_inv, wb.R_min_inv,
                                            d, d2)))
        if worst > 1e-9:
            return Certificate(reason=f"(18b) fails on random pairs (worst normalised violation "
                               f"{worst:.3g}): the grid margin is not sufficient",
                               P=P_out, eta=eta_cert, check_pairs=n_check, check_worst=worst,
                               solver_status=str(status), **common)
    summary = (f"W = |x - x~|_P^2 certified on the box with eta = {eta_cert:.6g} "
               f"({'proved' if proved else 'estimated'} grid margin, "
               f"{n_check} random pairs re-checked)")
    return Certificate(feasible=True, reason=summary, P=P_out, eta=eta_cert,
                       eta_without_margin=float(eta_grid), check_pairs=n_check,
                       check_worst=worst, solver_status=str(status), **common)


def _search(data, eta, P_fixed, max_condition, eta_tol, solver):
    """Fixed P, fixed η, or bisection on η. Returns (P, Ĉ, λ_A, λ_C, verified η, status)."""
    fail = (None, None, None, None, math.inf)
    if P_fixed is not None or eta is not None:
        P_n, C_hat, la, lc, status = _SDP(data, P_fixed, max_condition, solver).solve(eta)
        if P_n is None:
            return fail + (status,)
        return P_n, C_hat, la, lc, _verified_eta(data, P_n, C_hat, la, lc), status
    sdp = _SDP(data, None, max_condition, solver)
    best, status = None, None
    lo, hi = 0.0, 1.0 - 1e-6
    trial = hi
    while True:
        P_n, C_hat, la, lc, status = sdp.solve(trial)
        eta_v = _verified_eta(data, P_n, C_hat, la, lc) if P_n is not None else math.inf
        if eta_v < 1.0:
            if best is None or eta_v < best[4]:
                best = (P_n, C_hat, la, lc, eta_v, status)
            hi = min(trial, eta_v)
        elif best is None:
            return fail + (status,)
        else:
            lo = trial
        if hi - lo <= eta_tol:
            break
        trial = 0.5 * (lo + hi)
    # At the smallest feasible η the feasible set is thin and the P found there is nearly
    # singular; one more solve, eta_tol above it, returns a well-scaled P.
    relaxed = min(best[4] + eta_tol, 1.0 - 1e-6)
    P_n, C_hat, la, lc, status = sdp.solve(relaxed)
    eta_v = _verified_eta(data, P_n, C_hat, la, lc) if P_n is not None else math.inf
    if eta_v < 1.0 and np.linalg.eigvalsh(P_n)[0] > np.linalg.eigvalsh(best[0])[0]:
        return P_n, C_hat, la, lc, eta_v, status
    return best


