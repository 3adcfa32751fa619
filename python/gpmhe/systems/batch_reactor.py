"""The batch reactor 2A -> B of the GP-MHE paper's §V: model, simulator and the offline
training-data collection (5 or 3 measured trajectories). See the user guide, *Example systems*.

x1+ = x1 + T(-2 k1 x1² + 2 k2 x2) + w1,  x2+ = x2 + T(k1 x1² - k2 x2) + w2,  y = x1 + x2 + v,
T = 0.1, k1 = 0.16, k2 = 0.0064, w ~ N(0, 0.01² I), v ~ N(0, 0.1²), no control input (m = 0).
"""

from __future__ import annotations

import numpy as np

from gpmhe._validation import finite_vector as _finite_vector, integer as _integer

T = 0.1
K1 = 0.16
K2 = 0.0064
SIGMA_W = 0.01
SIGMA_V = 0.1
#: Std of the offline *state* measurements (the paper measures states with noise offline but does
#: not give the level; gpmhe fixes it to the process-noise level).
SIGMA_X_MEAS = 0.01
DIM_X, DIM_U, DIM_Y = 2, 0, 1

X0_TRAIN_5 = np.array([[3.0, 1.0], [1.2, 4.5], [0.5, 3.5], [1.0, 3.0], [2.0, 4.0]])
X0_TRAIN_3 = np.array([[0.5, 3.5], [1.0, 3.0], [2.0, 4.0]])
TRAIN_STEPS = 30  # 31 states per trajectory

X_TRUE0 = np.array([3.0, 1.0])
X_PRIOR0 = np.array([0.1, 4.5])  # the classic poor prior
X_BOUNDS = (np.array([0.1, 0.1]), np.array([4.5, 4.5]))
#: The paper's MHE settings with Q0, R0 as covariances (the weights are their inverses; see the
#: user guide, *Weights from the GP variances*) and the paper's arrival cost: the estimator's
#: earlier estimate x̂(t−M) as its mean (``arrival_mean="estimate"``) with the constant weight P2 (``arrival_weight="constant"``), the setting of the paper's stability
#: guarantee (`gpmhe.theory`). From the poor prior it recovers more slowly than the package's
#: default arrival cost (`RECOMMENDED_SETTINGS`; ``python -m gpmhe demo`` shows both): for a
#: similar plant, start from that one.
MHE_SETTINGS = dict(horizon=15, eta=0.91, P2=np.eye(2), Q0=1e-3 * np.eye(2), R0=1e-2 * np.eye(1),
                    arrival_mean="estimate", arrival_weight="constant")
#: The paper's horizon, discount and weights with `gpmhe.GPMHE`'s default arrival cost: the
#: smoothed mean of the previous window's first node, its weight updated as an EKF's covariance
#: (the previous window's information, so the weight follows the data instead of staying at P2).
#: The package's recommended setup on this plant.
RECOMMENDED_SETTINGS = dict(horizon=15, eta=0.91, P2=np.eye(2), Q0=1e-3 * np.eye(2),
                            R0=1e-2 * np.eye(1))
#: The paper's GP model for `gpmhe.LearnedModel.from_trajectories` (zero prior mean, maximum
#: likelihood in natural units), which the paper's comparison and its figures use.
PAPER_GP = dict(mean="zero", normalize=False, hyperprior=None)


def f(x, u=None):
    """One Euler step of the noise-free dynamics.

    x1+ = x1 + T(-2 k1 x1² + 2 k2 x2), x2+ = x2 + T(k1 x1² - k2 x2).

    Parameters
    ----------
    x : array_like of shape (2,)
        Concentrations (x1, x2) of A and B.
    u : object, default None
        Ignored (the reactor has no input); present for the `gpmhe.KnownModel` signature.

    Returns
    -------
    ndarray of shape (2,)
        The next state without noise.

    Examples
    --------
    >>> from gpmhe.systems import batch_reactor as br
    >>> print(br.f([3.0, 1.0]))
    [2.71328 1.14336]
    """
    x1, x2 = float(x[0]), float(x[1])
    return np.array(
        [x1 + T * (-2.0 * K1 * x1 * x1 + 2.0 * K2 * x2), x2 + T * (K1 * x1 * x1 - K2 * x2)]
    )


def f_jacobian(x, u=None):
    """Jacobian ∂f/∂x of `f`.

    Parameters
    ----------
    x : array_like of shape (2,)
        State.
    u : object, default None
        Ignored.

    Returns
    -------
    ndarray of shape (2, 2)
        ∂f/∂x at x.

    Examples
    --------
    >>> from gpmhe.systems import batch_reactor as br
    >>> print(br.f_jacobian([1.0, 0.0]))
    [[0.936   0.00128]
     [0.032   0.99936]]
    """
    x1 = float(x[0])
    return np.array([[1.0 - 4.0 * T * K1 * x1, 2.0 * T * K2], [2.0 * T * K1 * x1, 1.0 - T * K2]])


def h(x, u=None):
    """The measured total concentration y = x1 + x2 (noise-free).

    Parameters
    ----------
    x : array_like of shape (2,)
        State.
    u : object, default None
        Ignored.

    Returns
    -------
    ndarray of shape (1,)
        x1 + x2.

    Examples
    --------
    >>> from gpmhe.systems import batch_reactor as br
    >>> print(br.h([3.0, 1.0]))
    [4.]
    """
    return np.array([float(x[0]) + float(x[1])])


def h_jacobian(x, u=None):
    """Jacobian ∂h/∂x of `h`, constant.

    Parameters
    ----------
    x : array_like of shape (2,)
        State (not used: h is linear).
    u : object, default None
        Ignored.

    Returns
    -------
    ndarray of shape (1, 2)
        [[1, 1]].

    Examples
    --------
    >>> from gpmhe.systems import batch_reactor as br
    >>> print(br.h_jacobian([3.0, 1.0]))
    [[1. 1.]]
    """
    return np.array([[1.0, 1.0]])


def f_batch(X, U=None):
    """`f` for k points at once, the ``KnownModel(..., vectorized=True)`` form.

    The same arithmetic as `f`, so the values are identical.

    Parameters
    ----------
    X : array_like of shape (k, 2)
        States, one per row.
    U : object, default None
        Ignored.

    Returns
    -------
    ndarray of shape (k, 2)
        f of each row.

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe.systems import batch_reactor as br
    >>> X = np.array([[3.0, 1.0], [1.0, 2.0]])
    >>> bool(np.array_equal(br.f_batch(X), np.array([br.f(x) for x in X])))
    True
    """
    X = np.asarray(X, dtype=np.float64)
    x1, x2 = X[:, 0], X[:, 1]
    out = np.empty((X.shape[0], 2))
    out[:, 0] = x1 + T * (-2.0 * K1 * x1 * x1 + 2.0 * K2 * x2)
    out[:, 1] = x2 + T * (K1 * x1 * x1 - K2 * x2)
    return out


def f_jacobian_batch(X, U=None):
    """`f_jacobian` for k points at once.

    Parameters
    ----------
    X : array_like of shape (k, 2)
        States, one per row.
    U : object, default None
        Ignored.

    Returns
    -------
    ndarray of shape (k, 2, 2)
        ∂f/∂x at each row.

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe.systems import batch_reactor as br
    >>> J = br.f_jacobian_batch([[3.0, 1.0], [1.0, 2.0]])
    >>> J.shape, bool(np.allclose(J[1], br.f_jacobian([1.0, 2.0])))
    ((2, 2, 2), True)
    """
    X = np.asarray(X, dtype=np.float64)
    x1 = X[:, 0]
    J = np.empty((X.shape[0], 2, 2))
    J[:, 0, 0] = 1.0 - 4.0 * T * K1 * x1
    J[:, 0, 1] = 2.0 * T * K2
    J[:, 1, 0] = 2.0 * T * K1 * x1
    J[:, 1, 1] = 1.0 - T * K2
    return J


def h_batch(X, U=None):
    """`h` for k points at once.

    Parameters
    ----------
    X : array_like of shape (k, 2)
        States, one per row.
    U : object, default None
        Ignored.

    Returns
    -------
    ndarray of shape (k, 1)
        x1 + x2 of each row.

    Examples
    --------
    >>> from gpmhe.systems import batch_reactor as br
    >>> print(br.h_batch([[3.0, 1.0], [1.0, 2.0]]))
    [[4.]
     [3.]]
    """
    X = np.asarray(X, dtype=np.float64)
    return X[:, 0:1] + X[:, 1:2]


def h_jacobian_batch(X, U=None):
    """`h_jacobian` for k points at once.

    Parameters
    ----------
    X : array_like of shape (k, 2)
        States, one per row (only their number is used).
    U : object, default None
        Ignored.

    Returns
    -------
    ndarray of shape (k, 1, 2)
        Ones.

    Examples
    --------
    >>> from gpmhe.systems import batch_reactor as br
    >>> br.h_jacobian_batch([[3.0, 1.0], [1.0, 2.0]]).shape
    (2, 1, 2)
    """
    return np.ones((np.shape(X)[0], 1, 2))


def simulate(x0, steps, rng, sigma_w=SIGMA_W, sigma_v=SIGMA_V):
    """Simulate the reactor with process and measurement noise.

    x(t+1) = f(x(t)) + w(t), w ~ N(0, sigma_w² I), y(t) = x1(t) + x2(t) + v(t),
    v ~ N(0, sigma_v²), for t = 0..steps.

    Parameters
    ----------
    x0 : array_like of shape (2,)
        Initial state x(0).
    steps : int
        Number of steps T.
    rng : numpy.random.Generator
        Source of the noise.
    sigma_w : float, default ``SIGMA_W`` (0.01)
        Process-noise standard deviation.
    sigma_v : float, default ``SIGMA_V`` (0.1)
        Output-noise standard deviation.

    Returns
    -------
    x : ndarray of shape (steps + 1, 2)
        True states x(0..T).
    y : ndarray of shape (steps + 1, 1)
        Noisy outputs y(0..T).

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe.systems import batch_reactor as br
    >>> x, y = br.simulate(br.X_TRUE0, 5, np.random.default_rng(0), sigma_w=0.0, sigma_v=0.0)
    >>> x.shape, y.shape
    ((6, 2), (6, 1))
    >>> print(x[1], y[0])
    [2.71328 1.14336] [4.]
    """
    steps = _integer("steps", steps, low=1)
    x = np.empty((steps + 1, DIM_X))
    x[0] = _finite_vector("x0", x0, DIM_X)
    for t in range(steps):
        x[t + 1] = f(x[t]) + sigma_w * rng.standard_normal(DIM_X)
    y = x.sum(axis=1, keepdims=True) + sigma_v * rng.standard_normal((steps + 1, DIM_Y))
    return x, y


def training_data(n_trajectories=5, rng=None, steps=TRAIN_STEPS, sigma_x=SIGMA_X_MEAS):
    """Offline training data as the paper collects it.

    Simulates ``n_trajectories`` runs (with `simulate` and its default noise levels) from the
    paper's initial conditions (``X0_TRAIN_5`` or ``X0_TRAIN_3``) and measures their states with
    noise of standard deviation ``sigma_x``; the outputs carry the noise ``SIGMA_V``.

    Parameters
    ----------
    n_trajectories : {5, 3}, default 5
        Which of the paper's two training sets.
    rng : int, numpy.random.Generator or None, default None
        Seed or generator (passed to `numpy.random.default_rng`); None is not reproducible.
    steps : int, default ``TRAIN_STEPS`` (30)
        Steps per trajectory.
    sigma_x : float, default ``SIGMA_X_MEAS`` (0.01)
        Standard deviation of the state measurements.

    Returns
    -------
    states : list of ndarray of shape (steps + 1, 2)
        Measured states.
    outputs : list of ndarray of shape (steps + 1, 1)
        Measured outputs.

    Raises
    ------
    ValueError
        If ``n_trajectories`` is not 5 or 3.

    See Also
    --------
    gpmhe.LearnedModel.from_trajectories : Fits the GPs on these lists.

    Examples
    --------
    >>> from gpmhe.systems import batch_reactor as br
    >>> states, outputs = br.training_data(3, rng=0, steps=10)
    >>> len(states), states[0].shape, outputs[0].shape
    (3, (11, 2), (11, 1))
    """
    if n_trajectories == 5:
        x0s = X0_TRAIN_5
    elif n_trajectories == 3:
        x0s = X0_TRAIN_3
    else:
        raise ValueError(f"n_trajectories: must be 5 or 3 (the paper's sets), got {n_trajectories}")
    rng = np.random.default_rng(rng)
    states, outputs = [], []
    for x0 in x0s:
        x, y = simulate(x0, steps, rng)
        states.append(x + sigma_x * rng.standard_normal(x.shape))
        outputs.append(y)
    return states, outputs
