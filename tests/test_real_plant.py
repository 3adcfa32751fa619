"""GPMHE on real-plant settings: weights changed between updates, full covariances, channels not
measured, eta = 1, one-sided bounds, the input given after the update, unknown parameters and the
arrival cost (checked against a Kalman filter, a dense evaluation of the window cost and models
without the missing channel)."""

import copy

import numpy as np
import pytest

from gpmhe import GPMHE, EstimatorBank, KnownModel
from gpmhe.systems import batch_reactor as br

A = np.array([[0.9, 0.2], [-0.1, 0.8]])
B = np.array([[0.0], [0.5]])
C = np.array([[1.0, 0.0], [0.5, 1.0]])


def _f(x, u):
    return A @ x + B @ u


def _h(x, u):
    return C @ x


def _linear(outputs=(0, 1)):
    rows = list(outputs)
    return KnownModel(_f, lambda x, u: C[rows] @ x, dim_x=2, dim_y=len(rows), dim_u=1,
                      f_jacobian=lambda x, u: A, h_jacobian=lambda x, u: C[rows])


def _data(steps=40, seed=0):
    rng = np.random.default_rng(seed)
    x, xs, us, ys = np.array([1.0, -1.0]), [], [], []
    for _ in range(steps):
        u = rng.uniform(-1, 1, 1)
        ys.append(C @ x + 0.1 * rng.standard_normal(2))
        us.append(u)
        xs.append(x)
        x = A @ x + B @ u + 0.05 * rng.standard_normal(2)
    return np.array(xs), np.array(us), np.array(ys)


@pytest.mark.parametrize("horizon", [1, 4])
@pytest.mark.parametrize("form", ["filtering", "prediction"])
@pytest.mark.parametrize("mean", ["estimate", "filtered"])
def test_linear_mhe_with_ekf_arrival_weight_is_the_kalman_filter(mean, form, horizon):
    Q, R, P0 = np.array([[0.01, 0.004], [0.004, 0.02]]), np.array([[0.04, 0.01], [0.01, 0.02]]), np.eye(2)
    _, us, ys = _data()
    est = GPMHE(_linear(), x0=[0.0, 0.0], horizon=horizon, eta=1.0, P0=P0, Q0=Q, R0=R, form=form,
                arrival_mean=mean, arrival_weight="ekf", solver_options=dict(dtol=0.0, gtol=1e-10))
    x, P = np.zeros(2), P0.copy()
    for u, y in zip(us, ys):
        # Kalman filter: update with y(t), then x̂(t|t); predict with u(t): x̂(t+1|t).
        K = P @ C.T @ np.linalg.inv(C @ P @ C.T + R)
        x, P = x + K @ (y - C @ x), (np.eye(2) - K @ C) @ P
        est.update(u, y)
        if form == "filtering":
            np.testing.assert_allclose(est.x, x, atol=1e-7)
            np.testing.assert_allclose(est.P, P, atol=1e-7)
        x, P = A @ x + B @ u, A @ P @ A.T + Q
        if form == "prediction":
            np.testing.assert_allclose(est.x, x, atol=1e-7)
            np.testing.assert_allclose(est.P, P, atol=1e-7)
    # The constant-weight MHE (the paper's) and the smoothed mean differ once the window slides
    # (with M = 1 in the prediction form the smoothed node is the prediction itself).
    others = [dict(arrival_mean="estimate", arrival_weight="constant")]
    if not (form == "prediction" and horizon == 1):
        others.append(dict(arrival_mean="smoothed", arrival_weight="ekf"))
    for other in others:
        xs, _ = GPMHE(_linear(), x0=[0.0, 0.0], horizon=horizon, eta=1.0, P0=P0, Q0=Q, R0=R,
                      form=form, **other).batch_filter(ys, us)
        assert np.abs(xs[-1] - est.x).max() > 1e-4


def test_weights_set_between_updates_take_effect_and_unknown_names_are_rejected():
    _, us, ys = _data()
    a = GPMHE(_linear(), x0=[0.0, 0.0], horizon=5, Q0=0.01, R0=0.01)
    a.batch_filter(ys[:10], us[:10])
    b = copy.deepcopy(a)
    new = dict(Q0=np.array([[0.02, 0.005], [0.005, 0.01]]), R0=[0.03, 0.05], P2=2 * np.eye(2), eta=1.0)
    for key, value in new.items():
        setattr(a, key, value)
    reference = GPMHE(_linear(), x0=[0.0, 0.0], horizon=5, **new)
    reference._core.__setstate__(b._core.__getstate__())
    reference._core.set_weights(1.0, new["Q0"].reshape(-1), np.array([0.03, 0.05]),
                                np.linalg.cholesky(new["P2"]).T.copy())
    xa, _ = a.batch_filter(ys[10:20], us[10:20])
    xr, _ = reference.batch_filter(ys[10:20], us[10:20])
    xb, _ = b.batch_filter(ys[10:20], us[10:20])
    np.testing.assert_array_equal(xa, xr)
    assert np.abs(xa - xb).max() > 1e-6
    np.testing.assert_array_equal(a.R0, np.diag([0.03, 0.05]))
    np.testing.assert_allclose(a.P0, 0.5 * np.eye(2))
    for name, hint in (("R", "R0"), ("Q", "Q0"), ("horizon", "read-only"), ("x", "read-only"),
                       ("bogus", "no attribute")):
        with pytest.raises(AttributeError, match=hint):
            setattr(a, name, 0.5)
    before = (a.Q0, a.eta)
    with pytest.raises(ValueError, match="Q0"):
        a.Q0 = [[1.0, 2.0], [2.0, 1.0]]
    with pytest.raises(ValueError, match="eta"):
        a.eta = 1.5
    np.testing.assert_array_equal(a.Q0, before[0])
    assert a.eta == before[1]


def test_full_covariances_enter_the_window_cost_as_their_inverse():
    Q = np.array([[0.02, 0.005], [0.005, 0.01]])
    R = np.array([[0.04, 0.01], [0.01, 0.02]])
    _, us, ys = _data()
    est = GPMHE(_linear(), x0=[0.0, 0.0], horizon=3, eta=0.8, P2=np.eye(2), Q0=Q, R0=R,
                arrival_mean="estimate", arrival_weight="constant")
    est.batch_filter(ys[:5], us[:5])
    z0, _, _ = est._core.prepare(us[5], ys[5])
    z = z0 + 0.1
    nodes = z.reshape(-1, 2)
    mt = len(nodes) - 1
    dx = nodes[0] - est._core.__getstate__()["priors"][-1 - (mt - 1)]
    J = 2 * 0.8 ** mt * dx @ dx
    for i in range(mt):  # prediction form: outputs of nodes 0..M_t-1
        w = 2 * 0.8 ** (mt - 1 - i)
        v, e = ys[6 - mt + i] - C @ nodes[i], nodes[i + 1] - _f(nodes[i], us[6 - mt + i])
        J += w * (v @ np.linalg.solve(R, v) + e @ np.linalg.solve(Q, e))
    assert est._core.cost(z) == pytest.approx(J, rel=1e-12)


@pytest.mark.parametrize("R0", [np.diag([0.04, 0.02]), np.array([[0.04, 0.01], [0.01, 0.02]])])
def test_a_nan_channel_is_dropped_as_if_the_model_did_not_measure_it(R0):
    _, us, ys = _data()
    both = GPMHE(_linear(), x0=[0.0, 0.0], horizon=4, Q0=0.01, R0=R0)
    second = GPMHE(_linear((1,)), x0=[0.0, 0.0], horizon=4, Q0=0.01, R0=R0[1, 1])
    for u, y in zip(us[:15], ys[:15]):  # channel 0 never measured
        np.testing.assert_allclose(both.update(u, [np.nan, y[1]]), second.update(u, y[1:]),
                                   atol=1e-9)
    assert both.success
    # All channels NaN is a missing sample.
    a, b = copy.deepcopy(both), copy.deepcopy(both)
    np.testing.assert_array_equal(a.update(us[15], [np.nan, np.nan]), b.update(us[15], None))


def test_eta_one_and_one_sided_bounds():
    model = KnownModel(br.f, br.h, dim_x=2, dim_y=1)
    x_true, y = br.simulate(br.X_TRUE0, 30, np.random.default_rng(0))
    settings = {**br.MHE_SETTINGS, "eta": 1.0}
    a = GPMHE(model, x0=br.X_PRIOR0, x_bounds=(br.X_BOUNDS[0], None), **settings)
    b = GPMHE(model, x0=br.X_PRIOR0, x_bounds=(br.X_BOUNDS[0], [np.inf, np.inf]), **settings)
    xa, _ = a.batch_filter(y[:30])
    xb, _ = b.batch_filter(y[:30])
    np.testing.assert_array_equal(xa, xb)
    assert np.sqrt(np.mean((xa[10:] - x_true[11:31]) ** 2)) < 0.3
    assert GPMHE(model, x0=br.X_PRIOR0, x_bounds=(None, None)).x_bounds[1][0] == np.inf


def test_filtering_form_takes_the_input_after_the_update():
    _, us, ys = _data()
    a = GPMHE(_linear(), x0=[0.0, 0.0], horizon=4, form="filtering", Q0=0.01, R0=0.01)
    b = GPMHE(_linear(), x0=[0.0, 0.0], horizon=4, form="filtering", Q0=0.01, R0=0.01)
    for u, y in zip(us[:12], ys[:12]):
        xa = a.update(None, y)
        a.set_input(u)
        np.testing.assert_allclose(xa, b.update(u, y), atol=1e-12)
    with pytest.raises(ValueError, match="set_input"):
        a.update(None, ys[12])
        a.update(None, ys[13])
    with pytest.raises(ValueError, match="u"):
        GPMHE(_linear(), x0=[0.0, 0.0]).update(None, ys[0])  # prediction form needs u(t)


def test_u_none_is_refused_when_the_output_depends_on_u():
    _, us, ys = _data()
    feedthrough = KnownModel(_f, lambda x, u: C @ x + np.array([0.0, 0.3 * u[0]]), dim_x=2,
                             dim_y=2, dim_u=1)
    est = GPMHE(feedthrough, x0=[0.0, 0.0], horizon=4, form="filtering")
    est.update(us[0], ys[0])
    before = copy.deepcopy(est)
    with pytest.raises(ValueError, match="depends on u"):
        est.update(None, ys[1])
    np.testing.assert_array_equal(est.x_window, before.x_window)
    assert est.t == before.t
    est.update(None, None)  # no measurement: u(t) is not used at the newest node
    est.set_input(us[1])
    # The probe is once per estimator; a model without feedthrough passes it.
    plain = GPMHE(_linear(), x0=[0.0, 0.0], horizon=4, form="filtering")
    plain.update(None, ys[0])
    assert plain._h_uses_u is False


def test_u_none_with_casadi_outputs():
    ca = pytest.importorskip("casadi")
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    f = ca.Function("f", [x, u], [ca.mtimes(ca.DM(A), x) + ca.mtimes(ca.DM(B), u)])
    _, us, ys = _data()
    for h_expr, uses in ((ca.mtimes(ca.DM(C), x), False), (ca.mtimes(ca.DM(C), x) + u, True)):
        model = KnownModel.from_casadi(f, ca.Function("h", [x, u], [h_expr]))
        est = GPMHE(model, x0=[0.0, 0.0], horizon=4, form="filtering")
        if uses:
            with pytest.raises(ValueError, match="depends on u"):
                est.update(None, ys[0])
        else:
            est.update(None, ys[0])
            est.set_input(us[0])


def _scalar_with_parameter(x, u, p):
    return np.array([p[0] * x[0] + u[0]])


def test_a_parameter_is_estimated_with_the_states():
    rng = np.random.default_rng(3)
    a_true, x, us, ys = 0.7, 1.0, [], []
    for _ in range(60):
        u = rng.uniform(-1, 1, 1)
        ys.append([x + 0.05 * rng.standard_normal()])
        us.append(u)
        x = a_true * x + u[0]
    model = KnownModel(_scalar_with_parameter, lambda x, u, p: x, dim_x=1, dim_y=1, dim_u=1, dim_p=1)
    est = GPMHE(model, x0=[0.0], horizon=8, Q0=1e-6, R0=0.05 ** 2, p0=[0.3], P_p0=1.0,
                p_bounds=([0.0], [0.99]))
    est.batch_filter(ys, us)
    assert abs(est.p[0] - a_true) < 0.02
    assert est.P_p.shape == (1, 1) and 0 < est.P_p[0, 0] < 1e-3
    assert est.x.shape == (1,) and est.x_window.shape[1] == 1
    # The same estimator on the state augmented by hand (p~ = p / 0.3, constant).
    hand = KnownModel(lambda z, u: np.array([0.3 * z[1] * z[0] + u[0], z[1]]),
                      lambda z, u: z[:1], dim_x=2, dim_y=1, dim_u=1)
    ref = GPMHE(hand, x0=[0.0, 1.0], horizon=8, Q0=np.diag([1e-6, 1e-8]), R0=0.05 ** 2,
                P2=np.diag([1.0, 0.09]), x_bounds=([-np.inf, 0.0], [np.inf, 0.99 / 0.3]))
    xs, _ = ref.batch_filter(ys, us)
    assert est.p[0] == pytest.approx(0.3 * xs[-1, 1], abs=1e-6)
    # Checkpoints continue bit for bit.
    twin = copy.deepcopy(est)
    np.testing.assert_array_equal(twin.update(us[0], ys[0]), est.update(us[0], ys[0]))
    np.testing.assert_array_equal(twin.p, est.p)
    with pytest.raises(ValueError, match="p0"):
        GPMHE(model, x0=[0.0])


def test_the_filtered_arrival_mean_runs_everywhere_the_others_do(tmp_path):
    """A learned model, a robust penalty and missing channels; checkpoints and banks keep it."""
    from conftest import synthetic_learned_model

    model = synthetic_learned_model(40)
    rng = np.random.default_rng(7)
    steps = [(rng.uniform(-1, 1, 1), rng.normal(size=2) * 0.3) for _ in range(20)]
    steps[5][1][1] = np.nan
    kw = dict(horizon=4, Q0=1e-3, R0=[1e-2, 1e-2], arrival_mean="filtered", loss="huber")
    est = GPMHE(model, [0.2, -0.1], **kw)
    for u, y in steps[:10]:
        est.update(u, y)
    est.save(tmp_path / "est.npz")
    again = GPMHE.load(tmp_path / "est.npz", model)
    assert again.arrival_mean == "filtered"
    bank = EstimatorBank(model, 2, [0.2, -0.1], **kw)
    lone = GPMHE(model, [0.2, -0.1], **kw)
    for u, y in steps:
        y = np.nan_to_num(y)  # (a bank takes a row with a NaN as not measured at all)
        lone.update(u, y)
        bank.update(np.array([u, u]), np.array([y, y]))
    for u, y in steps[10:]:
        est.update(u, y)
        again.update(u, y)
    assert np.array_equal(est.x, again.x) and np.all(np.isfinite(est.x))
    assert np.array_equal(bank.x[0], lone.x) and np.array_equal(bank.x[1], lone.x)
