"""Three discs on a shaft between two motors (do-mpc's moving-horizon estimation example): the
linear model in numpy and CasADi with the inertia Θ1 as its parameter, the discrete-time model,
a simulator and do-mpc's estimation setting. See the user guide, *Example systems*.

State x = [φ1, φ2, φ3, φ̇1, φ̇2, φ̇3, φm1, φm2]: the disc angles, their rates and the two motor
angles (rad, rad/s); input u = [φm1,set, φm2,set], the motors' set angles; output
y = [φ1, φ2, φ3] + v, v ~ N(0, 0.1² I). The discs are coupled by springs c1..c4 (motor 1 – disc 1
– disc 2 – disc 3 – motor 2) and damped by d1..d3; the motors follow their set angles with the
time constant τ:

    Θ1 φ̈1 = −c1 (φ1 − φm1) − c2 (φ1 − φ2) − d1 φ̇1,
    Θ2 φ̈2 = −c2 (φ2 − φ1) − c3 (φ2 − φ3) − d2 φ̇2,
    Θ3 φ̈3 = −c3 (φ3 − φ2) − c4 (φ3 − φm2) − d3 φ̇3,
    φ̇m = (φm,set − φm) / τ,

c = (2.697, 2.66, 3.05, 2.86)e-3, d = (6.78, 8.01, 8.82)e-5, τ = 0.01 s, Θ1 = Θ2 = Θ3 = 2.25e-4.
Sampled every T = 0.1 s with u held. The motors' time constant makes the model stiff for one RK4
step per sample (h/τ = 10 is far outside RK4's stability region): 10 RK4 sub-steps (h/τ = 1) are
stable for every Θ1 in the estimation bounds, or use an implicit scheme.

In do-mpc's example the inertia Θ1 is unknown (true 2.25e-4, initial guess 1e-4, bounds
[1e-5, 1e-3]); the estimator has horizon 10, arrival weights P_x = I (states) and P_p = 10
(parameter), output weight P_v = I and no process noise, over 50 steps of random step inputs.
"""

from __future__ import annotations

import functools

import numpy as np

from gpmhe._validation import finite_vector as _finite_vector, integer as _integer

__all__ = ["rhs", "rhs_jacobian", "h_batch", "h_jacobian_batch", "casadi_functions",
           "known_model", "random_inputs", "simulate", "initial_estimate"]

C = np.array([2.697e-3, 2.66e-3, 3.05e-3, 2.86e-3])
D = np.array([6.78e-5, 8.01e-5, 8.82e-5])
TAU = 0.01
THETA1 = 2.25e-4
THETA2 = 2.25e-4
THETA3 = 2.25e-4
T = 0.1
SUBSTEPS = 10
DIM_X, DIM_U, DIM_Y = 8, 2, 3
SIGMA_V = 0.1

#: The estimation setting: Θ1's initial guess and bounds.
THETA1_GUESS = 1e-4
THETA1_BOUNDS = (1e-5, 1e-3)
HORIZON = 10
STEPS = 50
#: Arrival weights of the states and of Θ1, and the output weight.
P_X = np.eye(DIM_X)
P_P = 10.0
P_V = np.eye(DIM_Y)
#: `gpmhe.GPMHE` settings for the states: P2 = P_X, R0 = P_V⁻¹, "no process noise" as a
#: process weight Q0⁻¹ = 1e8 I, and do-mpc's arrival cost (the previous window's estimate of
#: the new first node, ``arrival_mean="smoothed"``, with constant weights,
#: ``arrival_weight="constant"``), so that the comparison with do-mpc's example runs the same
#: estimation problem.
MHE_SETTINGS = dict(horizon=HORIZON, eta=0.99, P2=P_X, R0=np.linalg.inv(P_V), Q0=1e-8 * np.eye(DIM_X),
                    arrival_mean="smoothed", arrival_weight="constant")
#: `gpmhe.GPMHE`'s parameter settings for Θ1 unknown (with ``known_model(theta1=None)``): the
#: guess, P_P as the prior weight of Θ1 in its own units (covariance P_P⁻¹), the bounds.
PARAMETER_SETTINGS = dict(p0=[THETA1_GUESS], P_p0=1.0 / P_P,
                          p_bounds=([THETA1_BOUNDS[0]], [THETA1_BOUNDS[1]]))

#: The true initial state, and the relative perturbation of the estimator's initial guess.
X0 = np.pi * np.array([1.0, 1.0, -1.5, 1.0, -5.0, 5.0, 0.0, 0.0])
X0_PERTURBATION = 0.5
#: The simulator's inputs: each step the set angles are kept with probability U_KEEP, else both
#: redrawn uniformly from [−U_MAX, U_MAX].
U_KEEP = 0.8
U_MAX = np.pi / 2


def _derivatives(x, u, theta1):
    """The 8 right-hand sides from the state's and input's entries (numpy arrays or CasADi
    expressions), Θ1 a number or a CasADi symbol."""
    phi, dphi, phim = x[0:3], x[3:6], x[6:8]
    c1, c2, c3, c4 = C
    d1, d2, d3 = D
    dd1 = (-c1 * (phi[0] - phim[0]) - c2 * (phi[0] - phi[1]) - d1 * dphi[0]) / theta1
    dd2 = (-c2 * (phi[1] - phi[0]) - c3 * (phi[1] - phi[2]) - d2 * dphi[1]) / THETA2
    dd3 = (-c3 * (phi[2] - phi[1]) - c4 * (phi[2] - phim[1]) - d3 * dphi[2]) / THETA3
    return [dphi[0], dphi[1], dphi[2], dd1, dd2, dd3, (u[0] - phim[0]) / TAU, (u[1] - phim[1]) / TAU]


def rhs(X, U, theta1=THETA1):
    """The right-hand side dx/dt = F(x, u; Θ1) for all rows at once.

    Parameters
    ----------
    X : array_like of shape (k, 8) or (8,)
        States, one per row.
    U : array_like of shape (k, 2) or (2,)
        Set angles of the motors.
    theta1 : float, default ``THETA1`` (2.25e-4)
        Inertia Θ1 of disc 1.

    Returns
    -------
    ndarray of the shape of X
        dx/dt of each row.

    Examples
    --------
    The discs at rest, motor 1 set to 1 rad:

    >>> import numpy as np
    >>> from gpmhe.systems import rotating_masses as rm
    >>> print(rm.rhs(np.zeros(8), [1.0, 0.0])[6:])
    [100.   0.]
    """
    X = np.asarray(X, dtype=np.float64)
    U = np.asarray(U, dtype=np.float64)
    parts = _derivatives([X[..., i] for i in range(DIM_X)], [U[..., 0], U[..., 1]], theta1)
    return np.stack(parts, axis=-1)


def _system_matrix(theta1):
    """A(Θ1) of the linear model dx/dt = A x + B u."""
    c1, c2, c3, c4 = C
    d1, d2, d3 = D
    A = np.zeros((DIM_X, DIM_X))
    A[0:3, 3:6] = np.eye(3)
    A[3, [0, 1, 3, 6]] = np.array([-(c1 + c2), c2, -d1, c1]) / theta1
    A[4, [0, 1, 2, 4]] = np.array([c2, -(c2 + c3), c3, -d2]) / THETA2
    A[5, [1, 2, 5, 7]] = np.array([c3, -(c3 + c4), -d3, c4]) / THETA3
    A[6, 6] = A[7, 7] = -1.0 / TAU
    return A


def rhs_jacobian(X, U, theta1=THETA1):
    """∂F/∂x of `rhs` for all rows (constant: the model is linear).

    Parameters
    ----------
    X : array_like of shape (k, 8)
        States, one per row (only their number is used).
    U : array_like of shape (k, 2)
        Inputs (not used).
    theta1 : float, default ``THETA1``
        Inertia Θ1 of disc 1.

    Returns
    -------
    ndarray of shape (k, 8, 8)
        The system matrix A(Θ1), once per row.

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe.systems import rotating_masses as rm
    >>> A = rm.rhs_jacobian(np.zeros((1, 8)), np.zeros((1, 2)))[0]
    >>> print(np.round(A[3], 3))
    [-23.809  11.822   0.     -0.301   0.      0.     11.987   0.   ]
    """
    return np.broadcast_to(_system_matrix(theta1), (np.shape(X)[0], DIM_X, DIM_X)).copy()


_A_UNIT_THETA1 = _system_matrix(1.0)


def _rhs_of_theta1(X, U, P):
    """`rhs` with Θ1 = P[:, 0] per row (the model with Θ1 as its parameter)."""
    return rhs(X, U, theta1=np.asarray(P, dtype=np.float64)[:, 0])


def _rhs_jacobian_of_theta1(X, U, P):
    """∂F/∂[x; Θ1] per row: A(Θ1) (only its row 3 depends on Θ1, as 1/Θ1) and the column
    ∂F/∂Θ1 = [0, 0, 0, −φ̈1/Θ1, 0, 0, 0, 0]."""
    X = np.asarray(X, dtype=np.float64)
    theta1 = np.asarray(P, dtype=np.float64)[:, 0]
    J = np.empty((X.shape[0], DIM_X, DIM_X + 1))
    J[:, :, :DIM_X] = _A_UNIT_THETA1
    J[:, :, DIM_X] = 0.0
    J[:, 3, :DIM_X] /= theta1[:, None]
    J[:, 3, DIM_X] = -(X @ _A_UNIT_THETA1[3]) / theta1**2  # φ̈1 = (A(1) x)_3 / Θ1
    return J


def _h_of_theta1(X, U, P):
    return h_batch(X)


def _h_jacobian_of_theta1(X, U, P):
    return np.broadcast_to(np.eye(DIM_Y, DIM_X + 1), (np.shape(X)[0], DIM_Y, DIM_X + 1)).copy()


def h_batch(X, U=None):
    """The measured disc angles y = [φ1, φ2, φ3] (noise-free) for all rows.

    Parameters
    ----------
    X : array_like of shape (k, 8)
        States, one per row.
    U : object, default None
        Ignored.

    Returns
    -------
    ndarray of shape (k, 3)
        The first three columns of X.

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe.systems import rotating_masses as rm
    >>> rm.h_batch(np.arange(8.0)[None, :]).tolist()
    [[0.0, 1.0, 2.0]]
    """
    return np.array(np.asarray(X, dtype=np.float64)[:, :DIM_Y])


def h_jacobian_batch(X, U=None):
    """∂h/∂x = [I 0] for all rows.

    Parameters
    ----------
    X : array_like of shape (k, 8)
        States, one per row (only their number is used).
    U : object, default None
        Ignored.

    Returns
    -------
    ndarray of shape (k, 3, 8)
        The selection of the disc angles.

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe.systems import rotating_masses as rm
    >>> rm.h_jacobian_batch(np.zeros((2, 8))).shape
    (2, 3, 8)
    """
    return np.broadcast_to(np.eye(DIM_Y, DIM_X), (np.shape(X)[0], DIM_Y, DIM_X)).copy()


def casadi_functions(theta1=THETA1):
    """The right-hand side and the output as CasADi functions (needs CasADi).

    Parameters
    ----------
    theta1 : float or None, default ``THETA1``
        Inertia Θ1 of disc 1; None: Θ1 is the right-hand side's third input (to estimate it,
        e.g. as an extra state with dΘ1/dt = 0).

    Returns
    -------
    rhs : casadi.Function
        ``rhs(x, u)`` (or ``rhs(x, u, theta1)``): dx/dt, x of 8 values, u of 2.
    h : casadi.Function
        ``h(x, u)``: the disc angles.

    Raises
    ------
    ImportError
        If CasADi is not installed.

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe.systems import rotating_masses as rm
    >>> F, h = rm.casadi_functions(theta1=None)
    >>> x, u = np.linspace(-1.0, 1.0, 8), np.array([0.5, -0.5])
    >>> bool(np.allclose(np.array(F(x, u, 1e-4)).ravel(), rm.rhs(x, u, theta1=1e-4)))
    True
    """
    from gpmhe.models.casadi import import_casadi

    ca = import_casadi("gpmhe.systems.rotating_masses.casadi_functions")
    x, u = ca.SX.sym("x", DIM_X), ca.SX.sym("u", DIM_U)
    inputs, names = [x, u], ["x", "u"]
    if theta1 is None:
        theta1 = ca.SX.sym("theta1")
        inputs, names = inputs + [theta1], names + ["theta1"]
    xdot = ca.vertcat(*_derivatives([x[i] for i in range(DIM_X)], [u[0], u[1]], theta1))
    F = ca.Function("rotating_masses", inputs, [xdot], names, ["xdot"])
    h = ca.Function("rotating_masses_output", [x, u], [x[:DIM_Y]], ["x", "u"], ["y"])
    return F, h


def known_model(theta1=THETA1, backend="casadi", method="rk4", substeps=SUBSTEPS, jit=False,
                native=True):
    """The sampled model with inertia Θ1 as a `gpmhe.KnownModel` (`gpmhe.KnownModel.from_ode`).

    Parameters
    ----------
    theta1 : float or None, default ``THETA1`` (2.25e-4)
        Inertia Θ1 of disc 1; None: Θ1 is the model's unknown parameter p = [Θ1]
        (``dim_p = 1``), to estimate with `gpmhe.GPMHE`'s ``p0`` (do-mpc's setting).
    backend : {"casadi", "numpy"}, default "casadi"
        CasADi functions, or the numpy `rhs` with its Jacobian `rhs_jacobian`.
    method : {"rk4", "implicit-midpoint", "backward-euler"}, default "rk4"
        The integration scheme (see `gpmhe.discretize`).
    substeps : int, default ``SUBSTEPS`` (10)
        Integration steps per sample time.
    jit : bool, default False
        CasADi only: compile the model for Python's evaluations.
    native : bool, default True
        CasADi only: the estimator's core runs the model compiled, without Python (see
        `gpmhe.KnownModel.from_casadi`); False: through Python callbacks.

    Returns
    -------
    KnownModel
        The model x(t+1) = f(x, u), y = [φ1, φ2, φ3] (f(x, u, p) with ``theta1=None``).

    Raises
    ------
    ValueError
        If ``backend`` is unknown or a setting is invalid.

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe.systems import rotating_masses as rm
    >>> model = rm.known_model(backend="numpy")
    >>> model.dim_x, model.dim_u, model.dim_y
    (8, 2, 3)
    >>> print(np.round(model.predict(np.zeros(8), [1.0, 0.0])[6:], 6))  # exact: 1 − e⁻¹⁰
    [0.999945 0.      ]
    >>> rm.known_model(None, backend="numpy").dim_p      # Θ1 unknown
    1
    """
    from gpmhe.models import KnownModel

    if backend == "casadi":
        F, h = casadi_functions(theta1)
        return KnownModel.from_ode(F, h, T, substeps=substeps, method=method, jit=jit,
                                   native=native)
    if backend != "numpy":
        raise ValueError(f"backend: must be 'casadi' or 'numpy', got {backend!r}")
    if theta1 is None:
        return KnownModel.from_ode(_rhs_of_theta1, _h_of_theta1, T, DIM_X, DIM_Y, DIM_U,
                                   substeps=substeps, method=method,
                                   rhs_jacobian=_rhs_jacobian_of_theta1,
                                   h_jacobian=_h_jacobian_of_theta1, dim_p=1)
    return KnownModel.from_ode(functools.partial(rhs, theta1=theta1), h_batch, T, DIM_X, DIM_Y,
                               DIM_U, substeps=substeps, method=method,
                               rhs_jacobian=functools.partial(rhs_jacobian, theta1=theta1),
                               h_jacobian=h_jacobian_batch)


def random_inputs(steps, rng):
    """Random step inputs: u(0) = 0; then at every step both set angles are kept with
    probability ``U_KEEP`` (0.8), else redrawn uniformly from [−U_MAX, U_MAX].

    Parameters
    ----------
    steps : int
        Number of steps T.
    rng : int or numpy.random.Generator
        Seed or generator.

    Returns
    -------
    ndarray of shape (steps + 1, 2)
        Inputs u(0..T).

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe.systems import rotating_masses as rm
    >>> u = rm.random_inputs(50, rng=0)
    >>> u.shape, bool(np.abs(u).max() <= rm.U_MAX)
    ((51, 2), True)
    """
    rng = np.random.default_rng(rng)
    u = np.zeros((steps + 1, DIM_U))
    for t in range(1, steps + 1):
        new = rng.uniform(-U_MAX, U_MAX, DIM_U)
        u[t] = u[t - 1] if rng.uniform() < U_KEEP else new
    return u


def simulate(steps=STEPS, rng=None, x0=X0, theta1=THETA1, sigma_v=SIGMA_V, substeps=SUBSTEPS):
    """Simulate the plant under `random_inputs` with measurement noise (no process noise).

    x(t+1) = f(x(t), u(t)) (RK4, ``substeps`` steps per sample), y(t) = [φ1, φ2, φ3](t) + v(t),
    v ~ N(0, sigma_v² I), for t = 0..steps.

    Parameters
    ----------
    steps : int, default ``STEPS`` (50)
        Number of steps T.
    rng : int, numpy.random.Generator or None, default None
        Seed or generator of the inputs and the noise; None is not reproducible.
    x0 : array_like of shape (8,), default ``X0``
        Initial state.
    theta1 : float, default ``THETA1``
        The true inertia Θ1.
    sigma_v : float, default ``SIGMA_V`` (0.1)
        Measurement-noise standard deviation.
    substeps : int, default ``SUBSTEPS`` (10)
        RK4 steps per sample time.

    Returns
    -------
    x : ndarray of shape (steps + 1, 8)
        True states x(0..T).
    u : ndarray of shape (steps + 1, 2)
        Inputs u(0..T).
    y : ndarray of shape (steps + 1, 3)
        Noisy outputs y(0..T).

    Examples
    --------
    >>> from gpmhe.systems import rotating_masses as rm
    >>> x, u, y = rm.simulate(rng=0)
    >>> x.shape, u.shape, y.shape
    ((51, 8), (51, 2), (51, 3))
    """
    steps = _integer("steps", steps, low=1)
    from gpmhe.models.discretization import discretize

    rng = np.random.default_rng(rng)
    u = random_inputs(steps, rng)
    f = discretize(functools.partial(rhs, theta1=theta1), T, substeps=substeps)
    x = np.empty((steps + 1, DIM_X))
    x[0] = _finite_vector("x0", x0, DIM_X)
    for t in range(steps):
        x[t + 1] = f(x[t], u[t])
    y = x[:, :DIM_Y] + sigma_v * rng.standard_normal((steps + 1, DIM_Y))
    return x, u, y


def initial_estimate(rng, x0=X0):
    """The estimator's initial guess: each entry of the true x0 perturbed by a relative
    N(0, X0_PERTURBATION²) error, x̂(0) = x0 (1 + 0.5 n), as do-mpc's example does.

    Parameters
    ----------
    rng : int or numpy.random.Generator
        Seed or generator.
    x0 : array_like of shape (8,), default ``X0``
        The true initial state.

    Returns
    -------
    ndarray of shape (8,)
        x̂(0).

    Examples
    --------
    >>> from gpmhe.systems import rotating_masses as rm
    >>> rm.initial_estimate(0).shape
    (8,)
    """
    rng = np.random.default_rng(rng)
    x0 = np.asarray(x0, dtype=np.float64)
    return x0 * (1.0 + X0_PERTURBATION * rng.standard_normal(x0.shape))
