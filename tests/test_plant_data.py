"""Data as plants send it: a covariance given with each output sample (``update(u, y, R=...)``)
and outputs that arrive late (``add_delayed``), against a Kalman filter with a time-varying R,
against the same data arriving on time, and through copies, checkpoints and banks."""

import copy
import pickle

import numpy as np
import pytest

from gpmhe import GPMHE, EstimatorBank, KnownModel

from conftest import linear_model, synthetic_learned_model

A = np.array([[0.9, 0.2], [-0.1, 0.8]])
B = np.array([[0.0], [0.5]])
C = np.array([[1.0, 0.0], [0.5, 1.0]])
Q = np.array([[0.01, 0.004], [0.004, 0.02]])
R0 = np.array([[0.04, 0.01], [0.01, 0.02]])
LINEAR = linear_model(A, C, B)


def data(steps=40, seed=0):
    rng = np.random.default_rng(seed)
    x, us, ys, Rs = np.array([1.0, -1.0]), [], [], []
    for _ in range(steps):
        u = rng.uniform(-1, 1, 1)
        L = np.diag(rng.uniform(0.05, 0.4, 2))  # each sample's own noise level
        ys.append(C @ x + L @ rng.standard_normal(2))
        Rs.append(L @ L)
        us.append(u)
        x = A @ x + B @ u + 0.05 * rng.standard_normal(2)
    return np.array(us), np.array(ys), np.array(Rs)


def kalman_like(**kw):
    """The MHE settings that are the Kalman filter on a linear-Gaussian model."""
    return GPMHE(LINEAR, x0=[0.0, 0.0], horizon=4, eta=1.0, P0=np.eye(2), Q0=Q, R0=R0,
                 form="filtering", arrival_mean="estimate", arrival_weight="ekf",
                 solver_options=dict(dtol=0.0, gtol=1e-10), **kw)


def test_a_covariance_per_sample_is_the_kalman_filter_with_a_time_varying_R():
    us, ys, Rs = data()
    est = kalman_like()
    x, P = np.zeros(2), np.eye(2)
    for u, y, R in zip(us, ys, Rs):
        K = P @ C.T @ np.linalg.inv(C @ P @ C.T + R)
        x, P = x + K @ (y - C @ x), (np.eye(2) - K @ C) @ P
        est.update(u, y, R=R)
        np.testing.assert_allclose(est.x, x, atol=1e-7)
        np.testing.assert_allclose(est.P, P, atol=1e-7)
        x, P = A @ x + B @ u, A @ P @ A.T + Q
    # With R0 for every sample the estimates differ: R reached the window.
    plain = kalman_like()
    xs, _ = plain.batch_filter(ys, us)
    assert np.abs(xs[-1] - est.x).max() > 1e-3


@pytest.mark.parametrize("solver", ["gauss-newton", "least-squares"])
@pytest.mark.parametrize("r0", [R0, np.diag(np.diag(R0))])
def test_R_equal_to_R0_is_bit_identical_to_no_R(solver, r0):
    us, ys, _ = data(25)
    kw = dict(x0=[0.0, 0.0], horizon=5, Q0=Q, R0=r0, solver=solver)
    a, b = GPMHE(LINEAR, **kw), GPMHE(LINEAR, **kw)
    for u, y in zip(us, ys):
        np.testing.assert_array_equal(a.update(u, y), b.update(u, y, R=r0))
        np.testing.assert_array_equal(a.P, b.P)


def test_bad_R_is_refused_naming_it_and_changes_nothing():
    us, ys, _ = data(5)
    est = GPMHE(LINEAR, x0=[0.0, 0.0], horizon=3, Q0=Q, R0=R0)
    est.update(us[0], ys[0])
    before = est._core.__getstate__()
    for R, y, match in [([[1.0, 2.0], [2.0, 1.0]], ys[1], "R"), ([1.0, 2.0, 3.0], ys[1], "R"),
                        (-1.0, ys[1], "R"), (np.nan, ys[1], "R"), (1.0, None, "R: given without")]:
        with pytest.raises(ValueError, match=match):
            est.update(us[1], y, R=R)
    after = est._core.__getstate__()
    assert all(np.array_equal(before[k], after[k]) for k in before)


def test_the_samples_covariances_survive_copies_pickles_and_checkpoints(tmp_path):
    us, ys, Rs = data(30)
    ys = ys.copy()
    ys[10, 1] = np.nan  # room for a late value of channel 1
    est = GPMHE(LINEAR, x0=[0.0, 0.0], horizon=6, Q0=Q, R0=R0)
    for t in range(15):
        est.update(us[t], ys[t], R=Rs[t])
    est.add_delayed([np.nan, 0.3], age=4, R=[1.0, 0.05])
    twins = [copy.deepcopy(est), pickle.loads(pickle.dumps(est))]
    est.save(tmp_path / "c.npz")
    twins.append(GPMHE.load(tmp_path / "c.npz", LINEAR))
    rest = [est.update(us[t], ys[t], R=Rs[t]).copy() for t in range(15, 30)]
    for twin in twins:
        np.testing.assert_array_equal([twin.update(us[t], ys[t], R=Rs[t]) for t in range(15, 30)], rest)


def assay_run(form, model, steps=14, at=5, age=3, solver_options=None):
    """Channel 1 measured at time `at` only, arriving `age` steps late, against on time: the
    estimates after the late one's next update, with a window over the whole run."""
    us, ys, _ = data(steps, seed=3)
    ys = ys.copy()
    late = ys[at].copy()
    ys[:, 1] = np.nan
    kw = dict(x0=[0.0, 0.0], horizon=steps + 2, Q0=Q, R0=np.diag(np.diag(R0)), form=form,
              solver_options=solver_options or dict(dtol=0.0, gtol=1e-12))
    on_time, delayed = GPMHE(model, **kw), GPMHE(model, **kw)
    out = []
    for t in range(steps):
        y_on = late if t == at else ys[t]
        on_time.update(us[t], y_on)
        delayed.update(us[t], ys[t])
        if t == at + age:
            assert delayed.max_delay >= age
            delayed.add_delayed([np.nan, late[1]], age=age)
        if t > at + age:
            out.append((on_time.x.copy(), delayed.x.copy(), on_time.x_window.copy(),
                        delayed.x_window.copy()))
    return out


@pytest.mark.parametrize("form", ["prediction", "filtering"])
def test_a_late_output_gives_the_estimate_it_would_have_given_on_time(form):
    for x_on, x_late, w_on, w_late in assay_run(form, LINEAR):
        np.testing.assert_allclose(x_late, x_on, rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(w_late, w_on, rtol=1e-9, atol=1e-10)


@pytest.mark.parametrize("form", ["prediction", "filtering"])
def test_a_late_output_with_a_learned_model(form):
    """The same to the solver's precision (the GP cost carries rounding noise; on this model
    both estimators stop at max-iterations in the first window after the late output, so the
    comparison starts one update later)."""
    model = synthetic_learned_model(60, False)
    with pytest.warns(RuntimeWarning, match="did not converge"):
        runs = assay_run(form, model, solver_options=dict(dtol=0.0))
    for x_on, x_late, _, _ in runs[1:]:
        np.testing.assert_allclose(x_late, x_on, atol=1e-5)


def test_a_late_output_with_a_casadi_model():
    ca = pytest.importorskip("casadi")
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    f = ca.Function("f", [x, u], [ca.DM(A) @ x + ca.DM(B) @ u])
    h = ca.Function("h", [x, u], [ca.DM(C) @ x])
    model = KnownModel.from_casadi(f, h)
    for x_on, x_late, _, _ in assay_run("filtering", model):
        np.testing.assert_allclose(x_late, x_on, rtol=1e-9, atol=1e-10)


def test_a_late_output_is_refused_where_it_cannot_go_and_changes_nothing():
    us, ys, _ = data(10)
    ys[:, 1] = np.nan
    est = GPMHE(LINEAR, x0=[0.0, 0.0], horizon=4, Q0=Q, R0=R0, form="filtering")
    with pytest.raises(ValueError, match="age"):
        est.add_delayed([np.nan, 1.0], age=1)  # nothing recorded yet
    for t in range(8):
        est.update(us[t], ys[t])
    assert est.max_delay == 3  # the window of the next update starts 3 outputs back
    before = est._core.__getstate__()
    for y, age, match in [([np.nan, 1.0], 0, "age"), ([np.nan, 1.0], 4, "age"),
                          ([1.0, np.nan], 1, "channel 0 is already measured"),
                          ([np.nan, np.nan], 1, "no measured channel"),
                          ([np.nan, np.inf], 1, "y"), ([1.0], 1, "y"),
                          ([np.nan, 1.0], 2.5, "age")]:
        with pytest.raises(ValueError, match=match):
            est.add_delayed(y, age)
    with pytest.raises(ValueError, match="R"):
        est.add_delayed([np.nan, 1.0], 1, R=[[1.0, 3.0], [3.0, 1.0]])
    after = est._core.__getstate__()
    for key in before:
        np.testing.assert_array_equal(after[key], before[key])
    est.add_delayed([np.nan, 1.0], age=3)
    with pytest.raises(ValueError, match="channel 1 is already measured"):
        est.add_delayed([np.nan, 2.0], age=3)


def test_a_late_output_only_changes_the_windows_from_the_next_update_on():
    us, ys, _ = data(12)
    ys[:, 1] = np.nan
    est = GPMHE(LINEAR, x0=[0.0, 0.0], horizon=5, Q0=Q, R0=R0)
    for t in range(8):
        est.update(us[t], ys[t])
    other = copy.deepcopy(est)
    x_before = est.x.copy()
    est.add_delayed([np.nan, 0.8], age=2)
    np.testing.assert_array_equal(est.x, x_before)
    assert np.abs(est.update(us[8], ys[8]) - other.update(us[8], ys[8])).max() > 1e-4


def test_a_bank_takes_late_outputs_per_estimator():
    """Estimator 1 misses the samples of times 3 and 4; the one of time 4 arrives at time 6."""
    us, ys, _ = data(10)
    kw = dict(horizon=5, Q0=np.diag(Q), R0=np.diag(R0), form="filtering")
    bank = EstimatorBank(LINEAR, 2, [0.0, 0.0], **kw)
    alone = [GPMHE(LINEAR, [0.0, 0.0], **kw) for _ in range(2)]
    for t in range(10):
        missed = t in (3, 4)
        bank.update(np.tile(us[t], (2, 1)), [ys[t], np.full(2, np.nan) if missed else ys[t]])
        alone[0].update(us[t], ys[t])
        alone[1].update(us[t], None if missed else ys[t])
        if t == 6:
            bank.add_delayed(1, ys[4], age=2, R=0.05)
            alone[1].add_delayed(ys[4], age=2, R=0.05)
    np.testing.assert_array_equal(bank.x[0], alone[0].x)
    np.testing.assert_array_equal(bank.x[1], alone[1].x)
    assert np.abs(bank.x[1] - bank.x[0]).max() > 1e-4
    with pytest.raises(IndexError):
        bank.add_delayed(5, [np.nan, 0.7], age=1)
    assert bank.max_delay == 4


def test_batch_filter_and_banks_take_each_samples_covariance():
    us, ys, Rs = data(12)
    kw = dict(horizon=4, Q0=np.diag(Q), R0=np.diag(R0))
    one = GPMHE(LINEAR, [0.0, 0.0], **kw)
    xs = [one.update(u, y, R=R).copy() for u, y, R in zip(us, ys, Rs)]
    batch, _ = GPMHE(LINEAR, [0.0, 0.0], **kw).batch_filter(ys, us, Rs=list(Rs))
    np.testing.assert_array_equal(batch, xs)
    with pytest.raises(ValueError, match=r"Rs\[3\]"):
        GPMHE(LINEAR, [0.0, 0.0], **kw).batch_filter(ys[:5], us[:5], Rs=[None, None, None, -1.0, None])
    # A bank: estimator 0 with R0, estimator 1 with the samples' R (one each).
    bank = EstimatorBank(LINEAR, 2, [0.0, 0.0], **kw)
    plain = GPMHE(LINEAR, [0.0, 0.0], **kw)
    for u, y, R in zip(us, ys, Rs):
        # (n, dim_y, dim_y): with n = dim_y an (n, dim_y) array would be one diagonal matrix
        bank.update(np.tile(u, (2, 1)), np.tile(y, (2, 1)), R=[np.diag(np.diag(R0)), R])
        plain.update(u, y)
    np.testing.assert_array_equal(bank.x[0], plain.x)
    np.testing.assert_array_equal(bank.x[1], xs[-1])
    with pytest.raises(ValueError, match="^R: must be .*positive definite"):
        bank.update(np.tile(us[0], (2, 1)), np.tile(ys[0], (2, 1)), R=[[1.0, 2.0], [2.0, 1.0]])
    assert bank.t == len(ys)


def test_a_checkpoint_keeps_samples_with_a_channel_not_measured(tmp_path):
    us, ys, _ = data(20)
    ys[3, 1] = ys[8, 0] = np.nan  # in the history when saved
    est = GPMHE(LINEAR, x0=[0.0, 0.0], horizon=8, Q0=Q, R0=R0)
    est.batch_filter(ys[:10], us[:10])
    est.save(tmp_path / "est.npz")
    again = GPMHE.load(tmp_path / "est.npz", LINEAR)
    a, _ = est.batch_filter(ys[10:], us[10:])
    b, _ = again.batch_filter(ys[10:], us[10:])
    assert np.array_equal(a, b)
