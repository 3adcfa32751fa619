"""The cart-pole with all four states measured, in a near-deterministic moving-horizon setting
(tiny process noise, large process weights): model in numpy and CasADi, simulator and the MHE
settings. See the user guide, *Example systems*.

State x = [p, θ, v, ω]: cart position p (m), pole angle θ from upright (rad), their rates v, ω;
input the horizontal force F (N) on the cart; output y = x + v_meas. The frictionless equations
of Barto, Sutton & Anderson (1983), l the half-length of the pole, M = m_c + m_p:

    a  = (F + m_p l ω² sin θ) / M,
    θ̈ = (g sin θ − a cos θ) / (l (4/3 − m_p cos²θ / M)),
    p̈ = a − m_p l θ̈ cos θ / M,

sampled every T = 0.05 s with F held, integrated by RK4 with 4 sub-steps (`gpmhe.discretize`).
m_c = 1 kg, m_p = 0.1 kg, l = 0.5 m, g = 9.81 m/s². The plant has process noise
w ~ N(0, diag(σ_w²)), σ_w = (5e-5, 5e-5, 1e-4, 1e-4), and measurement noise
v_meas ~ N(0, diag(σ_v²)), σ_v = (0.02, 0.02, 0.1, 0.1).
"""

from __future__ import annotations

import numpy as np

from gpmhe._validation import finite_vector as _finite_vector, integer as _integer

__all__ = ["rhs", "rhs_jacobian", "h_batch", "h_jacobian_batch", "casadi_functions",
           "known_model", "simulate"]

M_CART = 1.0
M_POLE = 0.1
L = 0.5  # half-length of the pole
G = 9.81
T = 0.05
SUBSTEPS = 4
DIM_X, DIM_U, DIM_Y = 4, 1, 4

SIGMA_W = np.array([5e-5, 5e-5, 1e-4, 1e-4])
SIGMA_V = np.array([0.02, 0.02, 0.1, 0.1])
#: The process weights Q0⁻¹ = diag(1/σ_w²): up to 4e8.
PROCESS_WEIGHTS = 1.0 / SIGMA_W**2
#: The arrival weight relative to the process weights: P2 = 0.005 Q0⁻¹.
ARRIVAL_FACTOR = 0.005
#: `gpmhe.GPMHE` settings: horizon 10, Q0 and R0 the noise covariances, the arrival weight
#: P2 = ARRIVAL_FACTOR · Q0⁻¹ and little discounting. The arrival cost is gpmhe's default (the
#: smoothed mean of the previous window, its weight updated as an EKF's covariance from P2): on
#: this swinging pendulum the smoothed mean re-anchors each window, where the estimator's own
#: earlier estimate (``arrival_mean="estimate"``) doubles the error with the EKF weight and
#: diverges with the paper's constant one (the user guide's *The window problem* compares them).
MHE_SETTINGS = dict(horizon=10, eta=0.99, Q0=np.diag(SIGMA_W**2), R0=np.diag(SIGMA_V**2),
                    P2=ARRIVAL_FACTOR * np.diag(PROCESS_WEIGHTS))

#: Initial state: the pole 0.2 rad from upright, at rest (it falls and swings round).
X0 = np.array([0.0, 0.2, 0.0, 0.0])
#: The simulator's force: a new level every U_HOLD samples, uniform in [−F_MAX, F_MAX] N.
F_MAX = 2.0
U_HOLD = 10


def _accelerations(sin, cos, omega, force):
    """(p̈, θ̈) from sin θ, cos θ, ω and F (numpy arrays or CasADi expressions)."""
    total = M_CART + M_POLE
    a = (force + M_POLE * L * omega * omega * sin) / total
    theta_dd = (G * sin - a * cos) / (L * (4.0 / 3.0 - M_POLE * cos * cos / total))
    return a - M_POLE * L * theta_dd * cos / total, theta_dd


def rhs(X, U):
    """The right-hand side dx/dt = F(x, u) for all rows at once.

    Parameters
    ----------
    X : array_like of shape (k, 4) or (4,)
        States [p, θ, v, ω], one per row.
    U : array_like of shape (k, 1) or (1,)
        Forces F.

    Returns
    -------
    ndarray of the shape of X
        [v, ω, p̈, θ̈] of each row.

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe.systems import cart_pole as cp
    >>> print(np.round(cp.rhs([0.0, 0.2, 0.0, 0.0], [0.0]), 4))
    [ 0.      0.     -0.1394  3.1283]
    """
    X = np.asarray(X, dtype=np.float64)
    U = np.asarray(U, dtype=np.float64)
    sin, cos = np.sin(X[..., 1]), np.cos(X[..., 1])
    p_dd, theta_dd = _accelerations(sin, cos, X[..., 3], U[..., 0])
    return np.stack([X[..., 2], X[..., 3], p_dd, theta_dd], axis=-1)


def rhs_jacobian(X, U):
    """∂F/∂x of `rhs` for all rows at once (analytic).

    Parameters
    ----------
    X : array_like of shape (k, 4)
        States, one per row.
    U : array_like of shape (k, 1)
        Forces.

    Returns
    -------
    ndarray of shape (k, 4, 4)
        The Jacobians.

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe.systems import cart_pole as cp
    >>> J = cp.rhs_jacobian([[0.0, 0.0, 0.0, 0.0]], [[0.0]])
    >>> print(np.round(J[0], 3))
    [[ 0.     0.     1.     0.   ]
     [ 0.     0.     0.     1.   ]
     [ 0.    -0.718  0.     0.   ]
     [ 0.    15.792  0.    -0.   ]]
    """
    X = np.asarray(X, dtype=np.float64)
    U = np.asarray(U, dtype=np.float64)
    theta, omega, force = X[:, 1], X[:, 3], U[:, 0]
    sin, cos = np.sin(theta), np.cos(theta)
    total = M_CART + M_POLE
    a = (force + M_POLE * L * omega * omega * sin) / total
    da_dtheta = M_POLE * L * omega * omega * cos / total
    da_domega = 2.0 * M_POLE * L * omega * sin / total
    num = G * sin - a * cos
    den = L * (4.0 / 3.0 - M_POLE * cos * cos / total)
    dnum_dtheta = G * cos + a * sin - da_dtheta * cos
    dden_dtheta = L * 2.0 * M_POLE * cos * sin / total
    theta_dd = num / den
    dtdd_dtheta = (dnum_dtheta * den - num * dden_dtheta) / den**2
    dtdd_domega = -cos * da_domega / den
    c = M_POLE * L / total
    J = np.zeros((X.shape[0], 4, 4))
    J[:, 0, 2] = 1.0
    J[:, 1, 3] = 1.0
    J[:, 2, 1] = da_dtheta - c * (dtdd_dtheta * cos - theta_dd * sin)
    J[:, 2, 3] = da_domega - c * cos * dtdd_domega
    J[:, 3, 1] = dtdd_dtheta
    J[:, 3, 3] = dtdd_domega
    return J


def h_batch(X, U=None):
    """The measured output y = x (noise-free) for all rows.

    Parameters
    ----------
    X : array_like of shape (k, 4)
        States, one per row.
    U : object, default None
        Ignored.

    Returns
    -------
    ndarray of shape (k, 4)
        A copy of X.

    Examples
    --------
    >>> from gpmhe.systems import cart_pole as cp
    >>> cp.h_batch([[1.0, 2.0, 3.0, 4.0]]).tolist()
    [[1.0, 2.0, 3.0, 4.0]]
    """
    return np.array(X, dtype=np.float64)


def h_jacobian_batch(X, U=None):
    """∂h/∂x = I for all rows.

    Parameters
    ----------
    X : array_like of shape (k, 4)
        States, one per row (only their number is used).
    U : object, default None
        Ignored.

    Returns
    -------
    ndarray of shape (k, 4, 4)
        Identities.

    Examples
    --------
    >>> from gpmhe.systems import cart_pole as cp
    >>> cp.h_jacobian_batch([[0.0] * 4, [1.0] * 4]).shape
    (2, 4, 4)
    """
    return np.broadcast_to(np.eye(4), (np.shape(X)[0], 4, 4)).copy()


def casadi_functions():
    """The right-hand side and the output as CasADi functions (needs CasADi).

    Returns
    -------
    rhs : casadi.Function
        ``rhs(x, u)``: dx/dt, x of 4 values, u of 1.
    h : casadi.Function
        ``h(x, u)``: y = x.

    Raises
    ------
    ImportError
        If CasADi is not installed.

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe.systems import cart_pole as cp
    >>> F, h = cp.casadi_functions()
    >>> x, u = np.array([0.0, 0.2, 0.0, 0.0]), np.array([0.5])
    >>> bool(np.allclose(np.array(F(x, u)).ravel(), cp.rhs(x, u), rtol=1e-14))
    True
    """
    from gpmhe.models.casadi import import_casadi

    ca = import_casadi("gpmhe.systems.cart_pole.casadi_functions")
    x, u = ca.SX.sym("x", DIM_X), ca.SX.sym("u", DIM_U)
    p_dd, theta_dd = _accelerations(ca.sin(x[1]), ca.cos(x[1]), x[3], u[0])
    F = ca.Function("cart_pole", [x, u], [ca.vertcat(x[2], x[3], p_dd, theta_dd)], ["x", "u"], ["xdot"])
    h = ca.Function("cart_pole_output", [x, u], [x], ["x", "u"], ["y"])
    return F, h


def known_model(backend="casadi", jacobian="exact", substeps=SUBSTEPS, jit=False, native=True):
    """The sampled cart-pole as a `gpmhe.KnownModel` (`gpmhe.KnownModel.from_ode`).

    Parameters
    ----------
    backend : {"casadi", "numpy"}, default "casadi"
        CasADi functions (AD Jacobians, one mapped call per window evaluation) or the numpy
        `rhs`.
    jacobian : {"exact", "finite-differences"}, default "exact"
        Numpy only: the Jacobian of the discrete map carried through RK4 with `rhs_jacobian`,
        or `gpmhe.KnownModel`'s finite differences of the discrete map.
    substeps : int, default ``SUBSTEPS`` (4)
        RK4 steps per sample time.
    jit : bool, default False
        CasADi only: compile the model for Python's evaluations (see
        `gpmhe.KnownModel.from_casadi`).
    native : bool, default True
        CasADi only: the estimator's core runs the model compiled, without Python (see
        `gpmhe.KnownModel.from_casadi`); False: through Python callbacks.

    Returns
    -------
    KnownModel
        The model x(t+1) = f(x, u), y = x.

    Raises
    ------
    ValueError
        If ``backend`` or ``jacobian`` is unknown.

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe.systems import cart_pole as cp
    >>> exact = cp.known_model("numpy")
    >>> fd = cp.known_model("numpy", jacobian="finite-differences")
    >>> d = np.array([[0.0, 0.2, 0.1, -0.3, 1.0]])
    >>> bool(np.allclose(exact.stage_eval(d)[2], fd.stage_eval(d)[2], atol=1e-7))
    True
    """
    from gpmhe.models.discretization import discretize
    from gpmhe.models import KnownModel

    if backend == "casadi":
        F, h = casadi_functions()
        return KnownModel.from_ode(F, h, T, substeps=substeps, jit=jit, native=native)
    if backend != "numpy":
        raise ValueError(f"backend: must be 'casadi' or 'numpy', got {backend!r}")
    if jacobian == "exact":
        return KnownModel.from_ode(rhs, h_batch, T, DIM_X, DIM_Y, DIM_U, substeps=substeps,
                                   rhs_jacobian=rhs_jacobian, h_jacobian=h_jacobian_batch)
    if jacobian != "finite-differences":
        raise ValueError(f"jacobian: must be 'exact' or 'finite-differences', got {jacobian!r}")
    return KnownModel(discretize(rhs, T, substeps=substeps), h_batch, DIM_X, DIM_Y, DIM_U,
                      vectorized=True)


def simulate(steps, rng, x0=X0, sigma_w=SIGMA_W, sigma_v=SIGMA_V, substeps=SUBSTEPS):
    """Simulate the cart-pole under random force steps, with process and measurement noise.

    x(t+1) = f(x(t), u(t)) + w(t), y(t) = x(t) + v(t) for t = 0..steps; u(t) holds a level drawn
    uniformly from [−F_MAX, F_MAX] for U_HOLD samples.

    Parameters
    ----------
    steps : int
        Number of steps T.
    rng : int or numpy.random.Generator
        Seed or generator of the inputs and the noise.
    x0 : array_like of shape (4,), default ``X0``
        Initial state.
    sigma_w, sigma_v : float or array_like of shape (4,), default ``SIGMA_W``, ``SIGMA_V``
        Standard deviations of the process and measurement noise.
    substeps : int, default ``SUBSTEPS`` (4)
        RK4 steps per sample time.

    Returns
    -------
    x : ndarray of shape (steps + 1, 4)
        True states x(0..T).
    u : ndarray of shape (steps + 1, 1)
        Inputs u(0..T).
    y : ndarray of shape (steps + 1, 4)
        Noisy outputs y(0..T).

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe.systems import cart_pole as cp
    >>> x, u, y = cp.simulate(20, rng=0)
    >>> x.shape, u.shape, y.shape
    ((21, 4), (21, 1), (21, 4))
    >>> bool(np.abs(u).max() <= cp.F_MAX)
    True
    """
    steps = _integer("steps", steps, low=1)
    from gpmhe.models.discretization import discretize

    rng = np.random.default_rng(rng)
    f = discretize(rhs, T, substeps=substeps)
    levels = rng.uniform(-F_MAX, F_MAX, size=steps // U_HOLD + 1)
    u = np.repeat(levels, U_HOLD)[:steps + 1, None]
    x = np.empty((steps + 1, DIM_X))
    x[0] = _finite_vector("x0", x0, DIM_X)
    for t in range(steps):
        x[t + 1] = f(x[t], u[t]) + sigma_w * rng.standard_normal(DIM_X)
    y = x + sigma_v * rng.standard_normal(x.shape)
    return x, u, y
