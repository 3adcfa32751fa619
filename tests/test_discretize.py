"""gpmhe.discretize and KnownModel.from_ode: the integrators against scipy's solve_ivp at tight
tolerances (each scheme's order of convergence), the Jacobians of the discrete map against
finite differences (numpy with and without ∂F/∂x, CasADi by AD), numpy against CasADi, stiff
stability, Newton's failure and the argument checks."""

import pickle

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy.integrate import solve_ivp

from gpmhe import DiscreteDynamics, KnownModel, NumericalError, discretize
from gpmhe.systems import cart_pole as cp

METHODS = {"rk4": 4, "implicit-midpoint": 2, "backward-euler": 1}

# A nonlinear test system: the Van der Pol oscillator with a forcing input, mildly stiff.
MU = 2.0


def vdp(X, U):
    return np.column_stack([X[:, 1], MU * (1 - X[:, 0] ** 2) * X[:, 1] - X[:, 0] + U[:, 0]])


def vdp_jacobian(X, U):
    J = np.zeros((X.shape[0], 2, 2))
    J[:, 0, 1] = 1.0
    J[:, 1, 0] = -2.0 * MU * X[:, 0] * X[:, 1] - 1.0
    J[:, 1, 1] = MU * (1 - X[:, 0] ** 2)
    return J


def vdp_casadi():
    ca = pytest.importorskip("casadi")
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    return ca.Function("vdp", [x, u], [ca.vertcat(x[1], MU * (1 - x[0] ** 2) * x[1] - x[0] + u[0])])


X_TEST = np.array([[1.5, -0.5], [-0.3, 2.0], [2.0, 0.0]])
U_TEST = np.array([[0.3], [-1.0], [0.0]])
DT = 0.2


def exact(x0, u, dt=DT):
    sol = solve_ivp(lambda t, x: vdp(x[None], np.array([[u]]))[0], (0.0, dt), x0, method="DOP853",
                    rtol=1e-13, atol=1e-13)
    return sol.y[:, -1]


def casadi_eval(f, X, U):
    return np.array([np.array(f(x, u)).ravel() for x, u in zip(X, U)])


@pytest.mark.parametrize("method", sorted(METHODS))
def test_convergence_order_against_solve_ivp(method):
    reference = np.array([exact(x, u[0]) for x, u in zip(X_TEST, U_TEST)])
    errors = []
    for substeps in (4, 8, 16, 32):
        f = discretize(vdp, DT, substeps=substeps, method=method, rhs_jacobian=vdp_jacobian,
                       newton_tol=1e-14)
        errors.append(np.abs(f(X_TEST, U_TEST) - reference).max())
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    order = METHODS[method]
    assert np.all(np.abs(orders - order) < 0.25), (errors, orders)
    if method == "rk4":
        assert errors[-1] < 1e-8


@pytest.mark.parametrize("analytic", [True, False])
@pytest.mark.parametrize("method", sorted(METHODS))
def test_numpy_jacobian_matches_finite_differences_of_the_map(method, analytic):
    f = discretize(vdp, DT, substeps=3, method=method, newton_tol=1e-13,
                   rhs_jacobian=vdp_jacobian if analytic else None)
    value, J = f.value_and_jacobian(X_TEST, U_TEST)
    np.testing.assert_array_equal(value, f(X_TEST, U_TEST))
    np.testing.assert_array_equal(J, f.jacobian(X_TEST, U_TEST))
    eps = 1e-6
    fd = np.stack([(f(X_TEST + eps * e, U_TEST) - f(X_TEST - eps * e, U_TEST)) / (2 * eps)
                   for e in np.eye(2)], axis=-1)
    np.testing.assert_allclose(J, fd, rtol=1e-6, atol=1e-7 if analytic else 1e-6)


@pytest.mark.parametrize("method", sorted(METHODS))
def test_casadi_matches_numpy_and_its_jacobian_finite_differences(method):
    ca = pytest.importorskip("casadi")
    fc = discretize(vdp_casadi(), DT, substeps=3, method=method, newton_tol=1e-13)
    assert isinstance(fc, ca.Function) and fc.n_in() == 2 and fc.name_out(0) == "x_next"
    fn = discretize(vdp, DT, substeps=3, method=method, rhs_jacobian=vdp_jacobian, newton_tol=1e-13)
    np.testing.assert_allclose(casadi_eval(fc, X_TEST, U_TEST), fn(X_TEST, U_TEST), rtol=1e-11, atol=1e-12)
    model = KnownModel.from_casadi(fc, None)
    d = np.hstack([X_TEST, U_TEST])
    J = model.stage_eval(d)[2][:, :, :2]
    np.testing.assert_allclose(J, fn.jacobian(X_TEST, U_TEST), rtol=1e-9, atol=1e-10)
    eps = 1e-6
    fd = np.stack([(casadi_eval(fc, X_TEST + eps * e, U_TEST) - casadi_eval(fc, X_TEST - eps * e, U_TEST))
                   / (2 * eps) for e in np.eye(2)], axis=-1)
    np.testing.assert_allclose(J, fd, rtol=1e-6, atol=1e-7)


def test_casadi_rk4_is_expanded_and_rhs_of_x_alone():
    ca = pytest.importorskip("casadi")
    assert discretize(vdp_casadi(), DT, substeps=2).is_a("SXFunction")
    x = ca.SX.sym("x", 1)
    f = discretize(ca.Function("decay", [x], [-x]), 1.0, substeps=4)  # x alone: one input
    assert f.n_in() == 1
    assert abs(float(f(1.0)) - np.exp(-1.0)) < 2e-5


def test_stiff_model_needs_substeps_or_an_implicit_scheme():
    lam = np.array([-1.0, -1000.0])

    def stiff(X, U):
        return X * lam

    x0 = np.array([[1.0, 1.0]])
    assert np.abs(discretize(stiff, 0.1, substeps=5)(x0)).max() > 1e3           # RK4 unstable
    assert np.abs(discretize(stiff, 0.1, substeps=50)(x0)[0, 1]) < 1e-10       # stable, damped
    be = discretize(stiff, 0.1, substeps=1, method="backward-euler")(x0)[0]
    np.testing.assert_allclose(be, 1.0 / (1.0 - 0.1 * lam))                     # L-stable
    mid = discretize(stiff, 0.1, substeps=1, method="implicit-midpoint")(x0)[0]
    np.testing.assert_allclose(mid, (1 + 0.05 * lam) / (1 - 0.05 * lam))       # |R| < 1, sign flips
    assert -1.0 < mid[1] < -0.9


def test_newton_failure_raises_numerical_error():
    def blowup(X, U):
        return X**2

    f = discretize(blowup, 1.0, method="backward-euler", newton_max_iter=5)
    with pytest.raises(NumericalError, match="Newton's method"):
        f([[1.0]])  # z = 1 + z² has no real solution


def test_one_point_and_no_input_shapes():
    f = discretize(lambda X, U: -X, 0.5, substeps=2)
    assert f([1.0, 2.0]).shape == (2,) and f.jacobian([1.0, 2.0]).shape == (2, 2)
    assert f([[1.0, 2.0]]).shape == (1, 2)
    g = discretize(vdp, DT)
    np.testing.assert_array_equal(g(X_TEST[0], U_TEST[0]), g(X_TEST[:1], U_TEST[:1])[0])
    assert "vdp" in repr(g) and "rk4" in repr(g)
    assert isinstance(pickle.loads(pickle.dumps(g)), DiscreteDynamics)


def test_argument_errors():
    for kwargs, match in [
        (dict(rhs=vdp, dt=0.0), r"^dt: must be finite and > 0"),
        (dict(rhs=vdp, dt=0.1, substeps=0), r"^substeps: must be an integer >= 1"),
        (dict(rhs=vdp, dt=0.1, method="euler"), r"^method: must be 'rk4', 'implicit-midpoint' or"),
        (dict(rhs="vdp", dt=0.1), r"^rhs: must be callable or a casadi.Function"),
        (dict(rhs=vdp, dt=0.1, rhs_jacobian=3), r"^rhs_jacobian: must be callable or None"),
        (dict(rhs=vdp, dt=0.1, newton_tol=-1), r"^newton_tol: must be finite and > 0"),
    ]:
        with pytest.raises(ValueError, match=match):
            discretize(**kwargs)
    f = discretize(lambda X, U: X[:, :1], 0.1)
    with pytest.raises(ValueError, match=r"^rhs: returned shape \(3, 1\), expected \(3, 2\)"):
        f(X_TEST, U_TEST)
    g = discretize(vdp, 0.1, rhs_jacobian=lambda X, U: np.zeros((2, 2)))
    with pytest.raises(ValueError, match=r"^rhs_jacobian: returned shape \(2, 2\), expected \(3, 2, 2\)"):
        g.jacobian(X_TEST, U_TEST)
    with pytest.raises(ValueError, match=r"^U: must have shape \(3, m\)"):
        g(X_TEST, U_TEST[:2])


def test_casadi_argument_errors():
    ca = pytest.importorskip("casadi")
    x = ca.SX.sym("x", 2)
    with pytest.raises(ValueError, match="rhs_jacobian: not used with a CasADi rhs"):
        discretize(vdp_casadi(), 0.1, rhs_jacobian=vdp_jacobian)
    with pytest.raises(ValueError, match=r"^rhs: returns 1 values, expected one per state"):
        discretize(ca.Function("F", [x], [x[0]]), 0.1)
    with pytest.raises(ValueError, match=r"^rhs: must take x or \(x, u\)"):
        discretize(ca.Function("F", [x, x[0:0], ca.SX.sym("p")], [x], {"allow_free": True}), 0.1)


# ---- KnownModel.from_ode ------------------------------------------------------------------------
def test_from_ode_numpy_model_uses_one_integration_per_evaluation():
    calls = []

    def counted(X, U):
        calls.append(X.shape[0])
        return vdp(X, U)

    model = KnownModel.from_ode(counted, lambda X, U: X[:, :1], DT, dim_x=2, dim_y=1, dim_u=1,
                                substeps=2, rhs_jacobian=vdp_jacobian)
    d = np.hstack([X_TEST, U_TEST])
    mx, _, dmx, _, my, _, dmy, _ = model.stage_eval(d)
    assert len(calls) == 2 * 4  # RK4: 4 stages per sub-step, values and Jacobian together
    f = discretize(vdp, DT, substeps=2, rhs_jacobian=vdp_jacobian)
    np.testing.assert_array_equal(mx, f(X_TEST, U_TEST))
    np.testing.assert_array_equal(dmx[:, :, :2], f.jacobian(X_TEST, U_TEST))
    assert np.all(dmx[:, :, 2] == 0.0)
    np.testing.assert_allclose(dmy, np.broadcast_to([[1.0, 0.0, 0.0]], (3, 1, 3)), atol=1e-9)
    assert model.vectorized and model.f.__class__ is DiscreteDynamics
    np.testing.assert_array_equal(model.predict(X_TEST[0], U_TEST[0]), mx[0])


def test_from_ode_casadi_model_and_dimension_checks():
    ca = pytest.importorskip("casadi")
    F = vdp_casadi()
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    h = ca.Function("h", [x, u], [x[0]])
    model = KnownModel.from_ode(F, h, DT, substeps=4, dim_x=2, dim_u=1)
    ref = KnownModel.from_ode(vdp, lambda X, U: X[:, :1], DT, dim_x=2, dim_y=1, dim_u=1, substeps=4,
                              rhs_jacobian=vdp_jacobian)
    d = np.hstack([X_TEST, U_TEST])
    for a, b in zip(model.stage_eval(d), ref.stage_eval(d)):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-9)
    with pytest.raises(ValueError, match=r"^dim_x: 3 disagrees with the CasADi functions' 2"):
        KnownModel.from_ode(F, h, DT, dim_x=3)
    with pytest.raises(ValueError, match=r"^h_jacobian: not used with CasADi functions"):
        KnownModel.from_ode(F, h, DT, h_jacobian=lambda X, U: None)
    with pytest.raises(ValueError, match=r"^h: a casadi.Function needs a CasADi rhs"):
        KnownModel.from_ode(vdp, h, DT, dim_x=2, dim_y=1, dim_u=1)
    with pytest.raises(ValueError, match=r"^h: must be a casadi.Function"):
        KnownModel.from_ode(F, lambda X, U: X, DT)


def test_from_ode_numpy_argument_errors():
    with pytest.raises(ValueError, match=r"^dim_x, dim_y: required with a numpy rhs"):
        KnownModel.from_ode(vdp, lambda X, U: X, DT)
    with pytest.raises(ValueError, match=r"^jit: only with CasADi functions"):
        KnownModel.from_ode(vdp, lambda X, U: X, DT, dim_x=2, dim_y=2, dim_u=1, jit=True)


def test_missing_casadi_raises_import_error(monkeypatch):
    ca = pytest.importorskip("casadi")
    F = vdp_casadi()
    monkeypatch.setattr("gpmhe.models.discretization.is_casadi_function", lambda obj: isinstance(obj, ca.Function))
    monkeypatch.setitem(__import__("sys").modules, "casadi", None)
    with pytest.raises(ImportError, match=r"discretize with a CasADi rhs needs CasADi .*pip install casadi"):
        discretize(F, 0.1)


def test_importing_gpmhe_does_not_import_casadi():
    import subprocess
    import sys

    code = ("import sys, gpmhe, gpmhe.systems.cart_pole, gpmhe.systems.rotating_masses; "
            "m = gpmhe.systems.cart_pole.known_model('numpy'); print('casadi' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_cart_pole_model_pickles_without_casadi():
    model = cp.known_model("numpy")
    restored = pickle.loads(pickle.dumps(model))
    d = np.array([[0.1, 0.2, 0.3, 0.4, 0.5]])
    for a, b in zip(model.stage_eval(d), restored.stage_eval(d)):
        np.testing.assert_array_equal(a, b)


# ------------------------------------------------------------- CasADi's implicit steps converge


def stiff_numpy(k):
    def rhs(X, U):
        return np.column_stack([-k * (X[:, 0] - np.cos(X[:, 1])), -0.1 * X[:, 1] + U[:, 0]])
    return rhs


def stiff_casadi(k):
    ca = pytest.importorskip("casadi")
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    return ca.Function("stiff", [x, u], [ca.vertcat(-k * (x[0] - ca.cos(x[1])), -0.1 * x[1] + u[0])])


@pytest.mark.parametrize("method", ["backward-euler", "implicit-midpoint"])
@settings(max_examples=25, deadline=None)
@given(k=st.sampled_from([1e1, 1e3, 1e4, 1e6]), x0=st.floats(-3.0, 3.0), x1=st.floats(-3.0, 3.0),
       u=st.floats(-1.0, 1.0))
def test_casadi_implicit_steps_converge_where_numpy_does(method, k, x0, x1, u):
    """The stiff model [-k (x0 - cos x1), -0.1 x1 + u]: the numpy scheme's Newton converges in a
    few steps; CasADi's rootfinder (plain Newton, as numpy's) reaches the same point."""
    fn = discretize(stiff_numpy(k), 0.1, method=method)
    fc = discretize(stiff_casadi(k), 0.1, method=method)
    X, U = np.array([[x0, x1]]), np.array([[u]])
    np.testing.assert_allclose(casadi_eval(fc, X, U), fn(X, U), rtol=1e-9, atol=1e-9)


def test_a_casadi_step_that_does_not_converge_names_itself():
    ca = pytest.importorskip("casadi")
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    rhs = ca.Function("cubic", [x, u], [ca.vertcat(-50 * x[0] ** 3, -x[1])])
    h = ca.Function("h", [x, u], [x[1]])
    model = KnownModel.from_ode(rhs, h, 0.1, method="backward-euler", newton_max_iter=1)
    with pytest.raises(NumericalError, match=r"^cubic_backward_euler: the implicit step's Newton "
                                             r"iteration did not converge"):
        model.predict([3.0, 1.0], [0.0])
