"""Irregular sampling: ``update(u, y, dt=...)`` with a continuous-time model (`KnownModel.from_ode`)
integrates each stage over its own interval. Checked against the Kalman filter of the exact
discretisation of a linear ODE at random intervals (numpy and CasADi models, both forms), and
through copies, checkpoints, banks, the SciPy solver path and the refusals."""

import copy
import io
import pickle

import numpy as np
import pytest
import scipy.linalg

from gpmhe import GPMHE, EstimatorBank, KnownModel, discretize

from conftest import synthetic_learned_model

A = np.array([[0.0, 1.0], [-2.0, -0.4]])  # a damped oscillator driven by u
B = np.array([[0.0], [1.0]])
C = np.array([[1.0, 0.0]])
Q = np.array([[2e-3, 5e-4], [5e-4, 4e-3]])
R = np.array([[0.01]])
DT = 0.1


def rhs(X, U):
    return X @ A.T + U @ B.T


def out(X, U):
    return X @ C.T


def numpy_model(dt=DT):
    return KnownModel.from_ode(rhs, out, dt, dim_x=2, dim_y=1, dim_u=1, substeps=8)


def casadi_model():
    ca = pytest.importorskip("casadi")
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    f = ca.Function("osc", [x, u], [ca.mtimes(ca.DM(A), x) + ca.mtimes(ca.DM(B), u)])
    h = ca.Function("pos", [x, u], [x[0]])
    return KnownModel.from_ode(f, h, DT, substeps=8)


def exact(dt):
    """The exact discretisation (zero-order hold) over dt: x+ = Ad x + Bd u."""
    M = scipy.linalg.expm(np.block([[A, B], [np.zeros((1, 3))]]) * dt)
    return M[:2, :2], M[:2, 2:]


def data(steps=40, seed=0):
    rng = np.random.default_rng(seed)
    dts = DT * (1.0 + rng.uniform(-0.5, 0.5, steps))  # ±50 % jitter
    x, us, ys = np.array([1.0, 0.0]), rng.uniform(-1, 1, (steps, 1)), []
    for k in range(steps):
        if k:
            Ad, Bd = exact(dts[k])
            x = Ad @ x + Bd @ us[k - 1] + rng.multivariate_normal(np.zeros(2), Q)
        ys.append(C @ x + 0.1 * rng.standard_normal(1))
    return us, np.array(ys), dts


def kalman_like(model, form="filtering", horizon=4, **kw):
    """The MHE settings that are the Kalman filter on a linear-Gaussian model."""
    kw.setdefault("solver_options", dict(dtol=0.0, gtol=1e-10))
    return GPMHE(model, x0=[0.0, 0.0], horizon=horizon, eta=1.0, P0=np.eye(2), Q0=Q, R0=R,
                 form=form, arrival_mean="estimate", arrival_weight="ekf", **kw)


def kalman(us, ys, dts):
    """The Kalman filter x̂(k|k), P(k|k) with the exact discretisation over each interval."""
    x, P, xs, Ps = np.zeros(2), np.eye(2), [], []
    for k, y in enumerate(ys):
        if k:
            Ad, Bd = exact(dts[k])
            x, P = Ad @ x + Bd @ us[k - 1], Ad @ P @ Ad.T + Q
        K = P @ C.T @ np.linalg.inv(C @ P @ C.T + R)
        x, P = x + K @ (y - C @ x), (np.eye(2) - K @ C) @ P
        xs.append(x)
        Ps.append(P)
    return np.array(xs), np.array(Ps)


@pytest.mark.parametrize("horizon", [1, 4, 40])
@pytest.mark.parametrize("make", [numpy_model, casadi_model])
def test_each_interval_gives_the_kalman_filter_of_the_exact_discretisation(make, horizon):
    us, ys, dts = data()
    est = kalman_like(make(), horizon=horizon)
    xs_ref, Ps_ref = kalman(us, ys, dts)
    for k, (u, y, dt) in enumerate(zip(us, ys, dts)):
        est.update(u, y, dt=dt)
        np.testing.assert_allclose(est.x, xs_ref[k], atol=1e-7)
        np.testing.assert_allclose(est.P, Ps_ref[k], atol=1e-7)
    # A fixed interval does not: the jitter is large enough to tell.
    fixed, _ = kalman_like(make(), horizon=horizon).batch_filter(ys, us)
    assert np.abs(fixed - xs_ref).max() > 1e-2


def test_the_prediction_form_predicts_over_the_model_dt_from_the_filtered_estimate():
    us, ys, dts = data(25)
    est = kalman_like(numpy_model(), form="prediction", horizon=3)
    xs_ref, _ = kalman(us, ys, dts)
    Ad, Bd = exact(DT)
    for k, (u, y, dt) in enumerate(zip(us, ys, dts)):
        est.update(u, y, dt=dt)
        # Node t of the window is x̂(t|t); the estimate is its prediction over the model's dt.
        np.testing.assert_allclose(est.x_window[-2], xs_ref[k], atol=1e-7)
        np.testing.assert_allclose(est.x, Ad @ xs_ref[k] + Bd @ u, atol=1e-7)


@pytest.mark.parametrize("solver", ["gauss-newton", "least-squares"])
def test_dt_equal_to_the_model_dt_is_bit_identical_to_no_dt(solver):
    us, ys, _ = data(20)
    a, b = (GPMHE(numpy_model(), x0=[0.0, 0.0], horizon=5, Q0=Q, R0=R, solver=solver)
            for _ in range(2))
    for u, y in zip(us, ys):
        a.update(u, y)
        b.update(u, y, dt=DT)
        assert np.array_equal(a.x, b.x) and np.array_equal(a.P, b.P)


def test_the_scipy_path_takes_the_intervals_too():
    us, ys, dts = data(20)
    xs_ref, _ = kalman(us, ys, dts)
    est = kalman_like(numpy_model(), solver="least-squares",
                      solver_options=dict(xtol=1e-14, ftol=1e-14, gtol=1e-14))
    xs, _ = est.batch_filter(ys, us, dts=dts)
    np.testing.assert_allclose(xs, xs_ref, atol=1e-6)


def test_an_input_given_later_keeps_the_interval():
    """update(None, y, dt) + set_input(u) in the filtering form is the on-time update."""
    us, ys, dts = data(15)
    on_time, late = kalman_like(numpy_model()), kalman_like(numpy_model())
    for u, y, dt in zip(us, ys, dts):
        on_time.update(u, y, dt=dt)
        late.update(None, y, dt=dt)
        late.set_input(u)
        np.testing.assert_allclose(late.x, on_time.x, atol=1e-12)


def test_a_model_with_parameters_integrates_over_each_interval():
    def rhs_p(X, U, P):
        return np.column_stack([X[:, 1], -P[:, 0] * X[:, 0] - 0.4 * X[:, 1] + U[:, 0]])

    model = KnownModel.from_ode(rhs_p, lambda X, U, P: X[:, :1], DT, 2, 1, 1, dim_p=1,
                                substeps=8)
    us, ys, dts = data(40)
    kw = dict(x0=[0.0, 0.0], horizon=8, Q0=Q, R0=R, p0=[1.0], P_p0=1.0, form="filtering")
    timed, fixed = GPMHE(model, **kw), GPMHE(model, **kw)
    timed.batch_filter(ys, us, dts=dts)
    fixed.batch_filter(ys, us)
    # The data were made with stiffness 2: the per-sample intervals estimate it better.
    assert abs(timed.p[0] - 2.0) < abs(fixed.p[0] - 2.0)
    assert abs(timed.p[0] - 2.0) < 0.25


def test_models_without_a_time_step_and_bad_intervals_are_refused_and_change_nothing():
    us, ys, _ = data(5)
    plain = KnownModel(lambda x, u: x, lambda x, u: x[:1], dim_x=2, dim_y=1, dim_u=1)
    learned = synthetic_learned_model(30)
    # A discrete map from `discretize` given to from_casadi has lost its right-hand side.
    ca = pytest.importorskip("casadi")
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    f = discretize(ca.Function("osc", [x, u], [ca.mtimes(ca.DM(A), x) + u]), DT)
    discrete = KnownModel.from_casadi(f, ca.Function("h", [x, u], [x[0]]))
    for model, u in ((plain, us[0]), (learned, np.zeros(learned.dim_u)), (discrete, us[0])):
        est = GPMHE(model, x0=np.zeros(model.dim_x), horizon=3)
        with pytest.raises(ValueError, match="^dt: the model has no time step"):
            est.update(u, np.zeros(model.dim_y), dt=0.1)
        assert est.t == 0
    est = GPMHE(numpy_model(), x0=[0.0, 0.0], horizon=3)
    est.update(us[0], ys[0])
    before = copy.deepcopy(est)
    for bad in (0.0, -0.1, np.nan, np.inf, "0.1", [0.1, 0.2]):
        with pytest.raises(ValueError, match="^dt:"):
            est.update(us[1], ys[1], dt=bad)
    with pytest.raises(ValueError, match=r"^dts\[1\]:"):
        est.batch_filter(ys[:2], us[:2], dts=[0.1, -1.0])
    with pytest.raises(ValueError, match="dts"):
        est.batch_filter(ys[:2], us[:2], dts=[0.1])
    assert est.t == 1 and np.array_equal(est.x_window, before.x_window)
    one = GPMHE(numpy_model(), x0=[0.0, 0.0], horizon=1)
    with pytest.raises(ValueError, match="horizon 1"):
        one.update(us[0], ys[0], dt=0.1)
    # The filtering form with horizon 1 takes it.
    GPMHE(numpy_model(), x0=[0.0, 0.0], horizon=1, form="filtering").update(us[0], ys[0], dt=0.1)


def test_the_first_update_has_no_interval_to_use():
    us, ys, _ = data(3)
    a, b = (GPMHE(numpy_model(), x0=[0.0, 0.0], horizon=3, form="filtering") for _ in range(2))
    a.update(us[0], ys[0], dt=0.05)
    b.update(us[0], ys[0])
    assert np.array_equal(a.x, b.x)


def test_the_intervals_survive_copies_pickles_and_checkpoints():
    us, ys, dts = data(30)
    est = GPMHE(numpy_model(), x0=[0.0, 0.0], horizon=6, Q0=Q, R0=R)
    est.batch_filter(ys[:15], us[:15], dts=dts[:15])
    buf = io.BytesIO()
    est.save(buf)
    buf.seek(0)
    twins = [copy.deepcopy(est), pickle.loads(pickle.dumps(est)), GPMHE.load(buf, numpy_model())]
    ref, _ = est.batch_filter(ys[15:], us[15:], dts=dts[15:])
    for twin in twins:
        xs, _ = twin.batch_filter(ys[15:], us[15:], dts=dts[15:])
        assert np.array_equal(xs, ref)


def test_a_checkpoint_from_before_intervals_continues_with_the_model_dt(tmp_path):
    """A file of format 5 (no interval column) loads with every interval the model's dt."""
    us, ys, _ = data(20)
    est = GPMHE(numpy_model(), x0=[0.0, 0.0], horizon=6, Q0=Q, R0=R)
    est.batch_filter(ys[:10], us[:10])
    path = tmp_path / "est.npz"
    est.save(path)
    entries = dict(np.load(path))
    entries["core_u"] = entries["core_u"][:, :-1]
    entries["format_version"] = np.array(5)
    np.savez(path, **entries)
    old = GPMHE.load(path, numpy_model())
    a, _ = old.batch_filter(ys[10:], us[10:])
    b, _ = est.batch_filter(ys[10:], us[10:])
    assert np.array_equal(a, b)


def test_a_bank_takes_each_estimators_interval():
    us, ys, dts = data(20)
    rng = np.random.default_rng(3)
    jitter = dts[:, None] * rng.uniform(0.8, 1.2, (20, 3))
    kw = dict(horizon=5, Q0=np.diag(Q), R0=np.diag(R), form="filtering")
    bank = EstimatorBank(numpy_model(), 3, [0.0, 0.0], **kw)
    lone = [GPMHE(numpy_model(), x0=[0.0, 0.0], **kw) for _ in range(3)]
    for k in range(20):
        U, Y = np.repeat(us[k][None], 3, axis=0), np.repeat(ys[k][None], 3, axis=0)
        bank.update(U, Y, dt=jitter[k])
        for i, est in enumerate(lone):
            est.update(us[k], ys[k], dt=jitter[k, i])
    assert np.array_equal(bank.x, np.array([est.x for est in lone]))
    with pytest.raises(ValueError, match="^dt:"):
        bank.update(U, Y, dt=[0.1, 0.1])
    with pytest.raises(ValueError, match="^dt:"):
        bank.update(U, Y, dt=-0.1)
    assert bank.t == 20


@pytest.mark.parametrize("method", ["rk4", "implicit-midpoint", "backward-euler"])
def test_an_interval_per_point_is_the_map_of_that_interval(method):
    """The maps the estimator runs: row i integrated over its own dt equals the map built with
    that dt (numpy, values and Jacobians bit for bit; CasADi to rounding, or to Newton's
    tolerance for the implicit schemes)."""
    from gpmhe.models.discretization import DiscreteDynamics, TimedDynamics

    rng = np.random.default_rng(4)
    X, U, dts = rng.normal(size=(5, 2)), rng.normal(size=(5, 1)), rng.uniform(0.05, 0.3, 5)
    kw = dict(substeps=3, method=method)
    timed = TimedDynamics(DiscreteDynamics(rhs, DT, **kw))
    values, jacobians = timed.value_and_jacobian(X, np.column_stack([U, dts]))
    ca = pytest.importorskip("casadi")
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    crhs = ca.Function("osc", [x, u], [ca.mtimes(ca.DM(A), x) + ca.mtimes(ca.DM(B), u)])
    model = KnownModel.from_ode(crhs, ca.Function("h", [x, u], [x[0]]), DT, **kw)._timed_model()
    for i, dt in enumerate(dts):
        alone = DiscreteDynamics(rhs, dt, **kw)
        v, J = alone.value_and_jacobian(X[i:i + 1], U[i:i + 1])
        assert np.array_equal(values[i], v[0]) and np.array_equal(jacobians[i], J[0])
        d = np.concatenate([X[i], U[i], [dt]])[None]
        mean, _, dmean = model.stage_eval(d)[:3]
        tol = 1e-12 if method == "rk4" else 1e-9
        np.testing.assert_allclose(mean[0], v[0], rtol=tol, atol=tol)
        np.testing.assert_allclose(dmean[0][:, :2], J[0], rtol=10 * tol, atol=10 * tol)
