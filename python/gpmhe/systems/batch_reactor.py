"""The batch reactor 2A -> B of the GP-MHE paper's §V (DESIGN.md §4): model, simulator and the
offline training-data collection (5 or 3 measured trajectories).

x1+ = x1 + T(-2 k1 x1² + 2 k2 x2) + w1,  x2+ = x2 + T(k1 x1² - k2 x2) + w2,  y = x1 + x2 + v,
T = 0.1, k1 = 0.16, k2 = 0.0064, w ~ N(0, 0.01² I), v ~ N(0, 0.1²), no control input (m = 0).
"""

from __future__ import annotations

import numpy as np

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
#: The paper's MHE settings with Q0, R0 as covariances (DESIGN.md §3).
MHE_SETTINGS = dict(horizon=15, eta=0.91, P2=np.eye(2), Q0=1e-3 * np.eye(2), R0=1e-2 * np.eye(1))


def f(x, u=None):
    """One Euler step of the noise-free dynamics; `u` is ignored (m = 0)."""
    x1, x2 = float(x[0]), float(x[1])
    return np.array(
        [x1 + T * (-2.0 * K1 * x1 * x1 + 2.0 * K2 * x2), x2 + T * (K1 * x1 * x1 - K2 * x2)]
    )


def f_jacobian(x, u=None):
    """∂f/∂x (2, 2)."""
    x1 = float(x[0])
    return np.array([[1.0 - 4.0 * T * K1 * x1, 2.0 * T * K2], [2.0 * T * K1 * x1, 1.0 - T * K2]])


def h(x, u=None):
    """The measured total concentration y = x1 + x2, shape (1,)."""
    return np.array([float(x[0]) + float(x[1])])


def h_jacobian(x, u=None):
    """∂h/∂x (1, 2)."""
    return np.array([[1.0, 1.0]])


def f_batch(X, U=None):
    """`f` for k points at once (the `KnownModel(..., vectorized=True)` form): X (k, 2) ->
    (k, 2); the same arithmetic as `f`, so the values are identical."""
    X = np.asarray(X, dtype=np.float64)
    x1, x2 = X[:, 0], X[:, 1]
    out = np.empty((X.shape[0], 2))
    out[:, 0] = x1 + T * (-2.0 * K1 * x1 * x1 + 2.0 * K2 * x2)
    out[:, 1] = x2 + T * (K1 * x1 * x1 - K2 * x2)
    return out


def f_jacobian_batch(X, U=None):
    """∂f/∂x for k points: X (k, 2) -> (k, 2, 2)."""
    X = np.asarray(X, dtype=np.float64)
    x1 = X[:, 0]
    J = np.empty((X.shape[0], 2, 2))
    J[:, 0, 0] = 1.0 - 4.0 * T * K1 * x1
    J[:, 0, 1] = 2.0 * T * K2
    J[:, 1, 0] = 2.0 * T * K1 * x1
    J[:, 1, 1] = 1.0 - T * K2
    return J


def h_batch(X, U=None):
    """`h` for k points: X (k, 2) -> (k, 1)."""
    X = np.asarray(X, dtype=np.float64)
    return X[:, 0:1] + X[:, 1:2]


def h_jacobian_batch(X, U=None):
    """∂h/∂x for k points: X (k, 2) -> (k, 1, 2)."""
    return np.ones((np.shape(X)[0], 1, 2))


def simulate(x0, steps, rng, sigma_w=SIGMA_W, sigma_v=SIGMA_V):
    """True states (steps+1, 2) and noisy outputs (steps+1, 1) from x0 with process noise."""
    x = np.empty((steps + 1, DIM_X))
    x[0] = np.asarray(x0, dtype=float)
    for t in range(steps):
        x[t + 1] = f(x[t]) + sigma_w * rng.standard_normal(DIM_X)
    y = x.sum(axis=1, keepdims=True) + sigma_v * rng.standard_normal((steps + 1, DIM_Y))
    return x, y


def training_data(n_trajectories=5, rng=None, steps=TRAIN_STEPS, sigma_x=SIGMA_X_MEAS):
    """Offline data as the paper collects it: `n_trajectories` (5 or 3) simulated runs of
    `steps`+1 states from the paper's initial conditions, with states measured with noise of std
    `sigma_x` and outputs with noise SIGMA_V. Returns (states, outputs): lists of (steps+1, 2) and
    (steps+1, 1) arrays, the input of `LearnedModel.from_trajectories`."""
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
