"""The physics plants gpmhe.systems.rotating_masses and cart_pole: their numpy and CasADi forms
agree, the analytic Jacobians match finite differences, the simulators match scipy's solve_ivp
and are reproducible, and the exact-model MHE tracks them in their settings."""

import pathlib
import re
import textwrap

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from gpmhe import GPMHE
from gpmhe.systems import cart_pole as cp
from gpmhe.systems import rotating_masses as rm
from gpmhe.systems import batch_reactor as br

PLANTS = {"rotating_masses": rm, "cart_pole": cp}


def random_points(plant, k, seed=0):
    rng = np.random.default_rng(seed)
    return rng.normal(scale=2.0, size=(k, plant.DIM_X)), rng.normal(size=(k, plant.DIM_U))


def fd_jacobian(fn, X, U, eps=1e-6):
    return np.stack([(fn(X + eps * e, U) - fn(X - eps * e, U)) / (2 * eps)
                     for e in np.eye(X.shape[1])], axis=-1)


@pytest.mark.parametrize("name", sorted(PLANTS))
def test_rhs_jacobian_matches_finite_differences(name):
    plant = PLANTS[name]
    X, U = random_points(plant, 6)
    np.testing.assert_allclose(plant.rhs_jacobian(X, U), fd_jacobian(plant.rhs, X, U),
                               rtol=1e-6, atol=1e-6)
    assert plant.rhs(X, U).shape == X.shape
    np.testing.assert_array_equal(plant.rhs(X[0], U[0]), plant.rhs(X, U)[0])


@pytest.mark.parametrize("name", sorted(PLANTS))
def test_casadi_functions_match_numpy(name):
    pytest.importorskip("casadi")
    plant = PLANTS[name]
    F, h = plant.casadi_functions()
    X, U = random_points(plant, 4, seed=1)
    for x, u in zip(X, U):
        np.testing.assert_allclose(np.array(F(x, u)).ravel(), plant.rhs(x, u), rtol=1e-13, atol=1e-13)
        np.testing.assert_array_equal(np.array(h(x, u)).ravel(), plant.h_batch(x[None])[0])
    np.testing.assert_array_equal(plant.h_jacobian_batch(X)[0],
                                  np.eye(plant.DIM_Y, plant.DIM_X))


@pytest.mark.parametrize("name", sorted(PLANTS))
def test_known_models_agree_across_backends(name):
    pytest.importorskip("casadi")
    plant = PLANTS[name]
    X, U = random_points(plant, 5, seed=2)
    d = np.hstack([X, U])
    ours, ref = plant.known_model(backend="casadi").stage_eval(d), plant.known_model(backend="numpy").stage_eval(d)
    for a, b in zip(ours, ref):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10)
    with pytest.raises(ValueError, match="^backend: must be 'casadi' or 'numpy'"):
        plant.known_model(backend="jax")


def test_rotating_masses_parameter():
    X, U = random_points(rm, 3, seed=3)
    d = np.hstack([X, U])
    light, nominal = rm.known_model(1e-4, backend="numpy"), rm.known_model(backend="numpy")
    assert not np.allclose(light.stage_eval(d)[0], nominal.stage_eval(d)[0])
    np.testing.assert_array_equal(rm.rhs(X, U, theta1=rm.THETA1), rm.rhs(X, U))
    A = rm.rhs_jacobian(X, U, theta1=1e-4)[0]
    np.testing.assert_allclose(A[3, [0, 1, 3, 6]] * 1e-4,
                               [-(rm.C[0] + rm.C[1]), rm.C[1], -rm.D[0], rm.C[0]])
    pytest.importorskip("casadi")
    F, _ = rm.casadi_functions(theta1=None)
    assert F.n_in() == 3 and F.name_in(2) == "theta1"
    casadi_light = rm.known_model(1e-4)
    for a, b in zip(casadi_light.stage_eval(d), light.stage_eval(d)):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10)


def test_rotating_masses_with_theta1_as_the_parameter():
    """known_model(theta1=None): Θ1 is p; at any p it is the model with that Θ1 (numpy and
    CasADi), and the numpy Jacobian's Θ1 column agrees with central differences."""
    X, U = random_points(rm, 3, seed=4)
    P = np.array([[1e-4], [2.25e-4], [6e-4]])
    numpy_p = rm.known_model(None, backend="numpy")
    assert numpy_p.dim_p == 1
    for x, u, p in zip(X, U, P):
        np.testing.assert_allclose(numpy_p.predict(x, u, p),
                                   rm.known_model(p[0], backend="numpy").predict(x, u), rtol=1e-12)
    J = rm._rhs_jacobian_of_theta1(X, U, P)
    step = 1e-6 * P
    fd = (rm._rhs_of_theta1(X, U, P + step) - rm._rhs_of_theta1(X, U, P - step)) / (2 * step)
    np.testing.assert_allclose(J[:, :, 8], fd, rtol=1e-7, atol=1e-9)
    A = np.stack([rm.rhs_jacobian(X[:1], U[:1], theta1=p[0])[0] for p in P])
    np.testing.assert_allclose(J[:, :, :8], A, rtol=1e-12)
    pytest.importorskip("casadi")
    casadi_p = rm.known_model(None)
    assert casadi_p.dim_p == 1
    for x, u, p in zip(X, U, P):
        np.testing.assert_allclose(casadi_p.predict(x, u, p), numpy_p.predict(x, u, p), rtol=1e-10,
                                   atol=1e-10)


def test_rotating_masses_rk4_stable_over_the_parameter_bounds():
    for theta1 in rm.THETA1_BOUNDS:
        A = rm.rhs_jacobian(np.zeros((1, 8)), None, theta1=theta1)[0]
        h = rm.T / rm.SUBSTEPS
        z = h * np.linalg.eigvals(A)
        R = 1 + z + z**2 / 2 + z**3 / 6 + z**4 / 24  # RK4's stability function
        assert np.all(np.abs(R) < 1.0)
    z = rm.T * np.linalg.eigvals(rm.rhs_jacobian(np.zeros((1, 8)), None)[0])
    assert np.any(np.abs(1 + z + z**2 / 2 + z**3 / 6 + z**4 / 24) > 1.0)  # one step is not


@pytest.mark.parametrize("name", sorted(PLANTS))
def test_simulator_matches_solve_ivp_and_is_reproducible(name):
    plant = PLANTS[name]
    steps = 30
    if plant is rm:
        x, u, y = rm.simulate(steps, rng=5)
        x2, u2, y2 = rm.simulate(steps, rng=5)
        tol = 1e-5
    else:
        x, u, y = cp.simulate(steps, rng=5, sigma_w=0.0)
        x2, u2, y2 = cp.simulate(steps, rng=5, sigma_w=0.0)
        tol = 1e-6
    for a, b in ((x, x2), (u, u2), (y, y2)):
        np.testing.assert_array_equal(a, b)
    assert x.shape == (steps + 1, plant.DIM_X) and u.shape == (steps + 1, plant.DIM_U)
    assert y.shape == (steps + 1, plant.DIM_Y)
    xt = x[0].copy()
    for t in range(steps):
        sol = solve_ivp(lambda _, z: plant.rhs(z, u[t]), (0.0, plant.T), xt, method="DOP853",
                        rtol=1e-12, atol=1e-12)
        xt = sol.y[:, -1]
        np.testing.assert_allclose(x[t + 1], xt, atol=tol * max(1.0, np.abs(xt).max()))
        xt = x[t + 1]  # per step: the simulator's own state
    noise = y - x[:, :plant.DIM_Y]
    assert 0.3 * np.min(plant.SIGMA_V) < noise.std() < 3 * np.max(plant.SIGMA_V)


def test_rotating_masses_inputs_and_initial_estimate():
    u = rm.random_inputs(400, rng=7)
    assert np.all(u[0] == 0.0) and np.abs(u).max() <= rm.U_MAX
    changed = np.any(u[1:] != u[:-1], axis=1)
    assert 0.1 < changed.mean() < 0.3  # redrawn with probability 1 − U_KEEP = 0.2
    assert np.all(np.all(u[1:] != u[:-1], axis=1) == changed)  # both set angles together
    x0 = rm.initial_estimate(0)
    np.testing.assert_array_equal(x0, rm.initial_estimate(0))
    assert np.all(x0[6:] == 0.0) and not np.allclose(x0, rm.X0)


def test_exact_model_mhe_tracks_the_rotating_masses():
    x, u, y = rm.simulate(rng=0)
    mhe = GPMHE(rm.known_model(backend="numpy"), rm.initial_estimate(1), **rm.MHE_SETTINGS)
    est = np.array([mhe.update(ut, yt).copy() for ut, yt in zip(u, y)])
    rmse = np.sqrt(np.mean((est[:-1] - x[1:])[:, :3] ** 2, axis=1))  # of the disc angles
    # The arrival weight P_x = I is as strong as the outputs: the poor initial guess fades slowly.
    assert rmse[-10:].mean() < 1.5 * rm.SIGMA_V
    assert rmse[:10].mean() > 3 * rmse[-10:].mean()


def test_physics_models_guide_runs_as_written(capsys):
    pytest.importorskip("casadi")
    guide = pathlib.Path(__file__).resolve().parents[1] / "docs" / "user_guide" / "physics_models.rst"
    blocks = re.findall(r"^\.\. code-block:: python\n\n(.*?)(?=^\S|\Z)", guide.read_text(encoding="utf-8"),
                        re.S | re.M)
    assert len(blocks) == 4
    ns = {"__name__": "__guide__"}
    for block in blocks:
        exec(compile(textwrap.dedent(block), str(guide), "exec"), ns)
    np.testing.assert_allclose(ns["estimates_casadi"], ns["estimates"], atol=1e-9)
    assert np.linalg.norm(ns["mhe"].x - ns["xs"][-1]) < 0.15  # angle noise 0.05
    np.testing.assert_allclose(ns["pendulum_casadi"].predict([1.0, 0.0], [0.5]),
                               ns["pendulum_model"].predict([1.0, 0.0], [0.5]), rtol=1e-12)


@pytest.mark.parametrize("call, name", [
    (lambda: br.simulate(np.zeros(3), 5, np.random.default_rng(0)), "x0"),
    (lambda: br.simulate([np.nan, 1.0], 5, np.random.default_rng(0)), "x0"),
    (lambda: br.simulate(br.X_TRUE0, 2.5, np.random.default_rng(0)), "steps"),
    (lambda: cp.simulate(5, np.random.default_rng(0), x0=np.zeros(5)), "x0"),
    (lambda: rm.simulate(5, np.random.default_rng(0), x0="abc"), "x0"),
])
def test_simulators_name_a_bad_argument(call, name):
    with pytest.raises(ValueError, match=f"^{name}:"):
        call()
