"""Test systems and fitted models shared by the test files, defined once.

Plain helpers (import them: ``from conftest import f3, h3``) and session-wide fixtures:

* ``f3``, ``h3`` (with ``f3_jac``, ``h3_jac`` and the vectorised ``f3_v``, ``h3_v``, ``f3_jac_v``,
  ``h3_jac_v``): a synthetic system with n = 2 states, m = 1 input and p = 2 outputs.
* ``f3_coupled``, ``h3_no_feedthrough``: its variant with other coefficients (stronger coupling,
  no input in h) that test_mhe.py's estimation-accuracy test was tuned on.
* ``synthetic_learned_model``: GPs with fixed hyperparameters on the f3/h3 system.
* ``reactor_known_model``, ``fitted_reactor_model``: the batch reactor's exact model and a
  LearnedModel fitted to its simulated trajectories; the fixture ``reactor_gp`` (also
  ``reactor_model``) is the one fit that test_solver.py and test_mhe_window.py share.
"""

import warnings

import numpy as np
import pytest

from gpmhe import KnownModel, LearnedModel, MultiOutputGP
from gpmhe.systems import batch_reactor as br

# ----------------------------------------------------------------------------- the f3/h3 system


def f3(x, u):
    return np.array([0.9 * x[0] + 0.1 * x[1] + 0.1 * u[0],
                     -0.1 * np.sin(x[0]) + 0.95 * x[1] + 0.05 * u[0]])


def f3_jac(x, u):
    return np.array([[0.9, 0.1], [-0.1 * np.cos(x[0]), 0.95]])


def h3(x, u):
    return np.array([x[0], x[0] * x[1] + 0.2 * u[0]])


def h3_jac(x, u):
    return np.array([[1.0, 0.0], [x[1], x[0]]])


def f3_v(X, U):
    return np.column_stack([0.9 * X[:, 0] + 0.1 * X[:, 1] + 0.1 * U[:, 0],
                            -0.1 * np.sin(X[:, 0]) + 0.95 * X[:, 1] + 0.05 * U[:, 0]])


def f3_jac_v(X, U):
    J = np.zeros((len(X), 2, 2))
    J[:, 0, 0], J[:, 0, 1] = 0.9, 0.1
    J[:, 1, 0], J[:, 1, 1] = -0.1 * np.cos(X[:, 0]), 0.95
    return J


def h3_v(X, U):
    return np.column_stack([X[:, 0], X[:, 0] * X[:, 1] + 0.2 * U[:, 0]])


def h3_jac_v(X, U):
    J = np.zeros((len(X), 2, 2))
    J[:, 0, 0] = 1.0
    J[:, 1, 0], J[:, 1, 1] = X[:, 1], X[:, 0]
    return J


# The variant of test_mhe.py::test_inputs_and_two_outputs (its RMSE threshold holds for these).
def f3_coupled(x, u):
    return np.array([0.9 * x[0] + 0.2 * x[1] + 0.1 * u[0],
                     -0.1 * np.sin(x[0]) + 0.9 * x[1] + 0.1 * u[0]])


def h3_no_feedthrough(x, u):
    return np.array([x[0], x[0] * x[1]])


class Affine:
    """x ↦ M x (+ B u): a model function of a linear test plant that pickles (a class of this
    module, where a lambda would not)."""

    def __init__(self, M, B=None):
        self.M, self.B = M, B

    def __call__(self, x, u):
        return self.M @ x if self.B is None else self.M @ x + self.B @ u


class Constant:
    """(x, u) ↦ M: the Jacobian of `Affine`."""

    def __init__(self, M):
        self.M = M

    def __call__(self, x, u):
        return self.M


def linear_model(A, C, B=None):
    """The known model x(t+1) = A x (+ B u), y = C x, with its exact Jacobians."""
    return KnownModel(Affine(A, B), Affine(C), dim_x=A.shape[0], dim_y=C.shape[0],
                      dim_u=0 if B is None else B.shape[1], f_jacobian=Constant(A),
                      h_jacobian=Constant(C))


def check_window_derivatives(win, z, h=1e-6):
    """A core window's gradient and Jacobian at z against central differences of its cost and
    residuals (step h), and the gradient against 2 Jᵀr."""
    r, (_, g), jac = win.residuals(z), win.cost_grad(z), win.jacobian(z)
    np.testing.assert_allclose(g, 2 * jac.T @ r, rtol=1e-12, atol=1e-12)
    fd_g, fd_J = np.empty_like(z), np.empty_like(jac)
    for c in range(z.size):
        e = np.zeros_like(z)
        e[c] = h
        fd_g[c] = (win.cost(z + e) - win.cost(z - e)) / (2 * h)
        fd_J[:, c] = (win.residuals(z + e) - win.residuals(z - e)) / (2 * h)
    np.testing.assert_allclose(g, fd_g, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(jac, fd_J, rtol=1e-5, atol=1e-5)


def synthetic_learned_model(n_points, f_residual=False):
    """GPs (fixed hyperparameters, no optimisation) on n_points random inputs of the f3/h3
    system (2 states, 1 input, 2 outputs)."""
    rng = np.random.default_rng(3)
    D = rng.uniform(-1.5, 1.5, size=(n_points, 3))
    Xn = np.array([f3(d[:2], d[2:]) for d in D])
    Y = np.array([h3(d[:2], d[2:]) for d in D])
    target = Xn - D[:, :2] if f_residual else Xn
    opts = dict(sigma_f=1.0, lengthscales=[0.8, 0.9, 1.1], sigma_eps=0.05, optimizer=None)
    return LearnedModel(MultiOutputGP(**opts).fit(D, target), MultiOutputGP(**opts).fit(D, Y),
                        dim_u=1, f_residual=f_residual)


# ----------------------------------------------------------------------------- the batch reactor


def reactor_known_model(vectorized=False, jacobians=True):
    """The batch reactor's exact model, per point or vectorised, with or without its analytic
    Jacobians."""
    if vectorized:
        fns = (br.f_batch, br.h_batch, br.f_jacobian_batch, br.h_jacobian_batch)
    else:
        fns = (br.f, br.h, br.f_jacobian, br.h_jacobian)
    jac = dict(f_jacobian=fns[2], h_jacobian=fns[3]) if jacobians else {}
    return KnownModel(fns[0], fns[1], 2, 1, vectorized=vectorized, **jac)


#: The paper's GP model (zero prior mean, maximum likelihood in natural units).
PAPER_GP = dict(mean="zero", normalize=False, hyperprior=None)


def reactor_casadi(jit=False, native=True):
    """The batch reactor as CasADi functions (`KnownModel.from_casadi`; CasADi imported here)."""
    import casadi as ca

    x = ca.SX.sym("x", 2)
    rate = br.K1 * x[0] ** 2 - br.K2 * x[1]
    f = ca.Function("f", [x], [x + br.T * ca.vertcat(-2 * rate, rate)])
    h = ca.Function("h", [x], [x[0] + x[1]])
    return KnownModel.from_casadi(f, h, jit=jit, native=native)


def fitted_reactor_model(rng, n_restarts, n_trajectories=5, **options):
    """A LearnedModel fitted to n_trajectories simulated batch-reactor trajectories (the
    generator seeded with rng), random_state 0, with the paper's GP model unless ``options`` say
    otherwise; convergence and fit warnings are not what tests check."""
    states, outputs = br.training_data(n_trajectories, rng=rng)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return LearnedModel.from_trajectories(states, outputs, n_restarts=n_restarts, random_state=0,
                                              **{**PAPER_GP, **options})


@pytest.fixture(scope="session")
def reactor_gp():
    """The batch reactor fitted to seed 11's five trajectories, one restart."""
    return fitted_reactor_model(11, n_restarts=1)


@pytest.fixture(scope="session")
def reactor_model(reactor_gp):
    """``reactor_gp`` under the name test_mhe_window.py uses."""
    return reactor_gp
