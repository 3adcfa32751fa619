"""The estimator's uncertainty beyond P: the covariance of every window node (``P_window``),
the innovation of each output with its covariance ``S``, the NIS and the log-likelihood. On a
linear-Gaussian model with the Kalman-filter settings they are filterpy's KalmanFilter's and its
RTS smoother's; with a learned model ``S`` carries the GP variances (a dense numpy computation);
and the χ² tests of `gpmhe.consistency`."""

import copy
import io
import pickle

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from gpmhe import GPMHE
from gpmhe.consistency import chi2_test, nees

from conftest import linear_model, synthetic_learned_model

A = np.array([[0.9, 0.2], [-0.1, 0.8]])
B = np.array([[0.0], [0.5]])
C = np.array([[1.0, 0.0], [0.5, 1.0]])
Q = np.array([[0.01, 0.004], [0.004, 0.02]])
R = np.array([[0.04, 0.01], [0.01, 0.02]])
LINEAR = linear_model(A, C, B)


def data(steps=30, seed=0):
    rng = np.random.default_rng(seed)
    x, xs, us, ys = np.array([1.0, -1.0]), [], [], []
    for _ in range(steps):
        u = rng.uniform(-1, 1, 1)
        xs.append(x)
        ys.append(C @ x + rng.multivariate_normal(np.zeros(2), R))
        us.append(u)
        x = A @ x + B @ u + rng.multivariate_normal(np.zeros(2), Q)
    return np.array(xs), np.array(us), np.array(ys)


def kalman_like(form, horizon, **kw):
    return GPMHE(LINEAR, x0=[0.0, 0.0], horizon=horizon, eta=1.0, P0=np.eye(2), Q0=Q, R0=R,
                 form=form, arrival_mean="estimate", arrival_weight="ekf",
                 solver_options=kw.pop("solver_options", dict(dtol=0.0, gtol=1e-10)), **kw)


def kalman():
    kf = KalmanFilter(dim_x=2, dim_z=2, dim_u=1)
    kf.F, kf.B, kf.H, kf.Q, kf.R, kf.P, kf.x = A, B, C, Q, R, np.eye(2), np.zeros(2)
    return kf


def rts(xs, Ps):
    """RTS smoother over filtered (x, P) with the constant model: smoothed covariances."""
    Psm = [Ps[-1]]
    for k in range(len(xs) - 2, -1, -1):
        Pp = A @ Ps[k] @ A.T + Q
        G = Ps[k] @ A.T @ np.linalg.inv(Pp)
        Psm.insert(0, Ps[k] + G @ (Psm[0] - Pp) @ G.T)
    return np.array(Psm)


@pytest.mark.parametrize("horizon", [1, 4, 30])
@pytest.mark.parametrize("form", ["filtering", "prediction"])
def test_innovation_S_and_likelihood_are_the_kalman_filters(form, horizon):
    _, us, ys = data()
    est, kf = kalman_like(form, horizon), kalman()
    for t, (u, y) in enumerate(zip(us, ys)):
        if t == 7:
            y = np.array([y[0], np.nan])  # one channel missing: the filter updates with the other
        est.update(u, y)
        if t == 7:
            kf.update(y[:1], R=R[:1, :1], H=C[:1])
            np.testing.assert_allclose(est.innovation[0], kf.y[0], atol=1e-9)
            assert np.isnan(est.innovation[1])
            np.testing.assert_allclose(est.S[:1, :1], kf.S, atol=1e-9)
        else:
            kf.update(y)
            np.testing.assert_allclose(est.innovation, kf.y, atol=1e-9)
            np.testing.assert_allclose(est.S, kf.S, atol=1e-9)
        np.testing.assert_allclose(est.log_likelihood, kf.log_likelihood, atol=1e-8)
        nu = kf.y.ravel()
        np.testing.assert_allclose(est.nis, nu @ np.linalg.solve(kf.S, nu), atol=1e-8)
        kf.predict(u=u)


def test_P_window_is_the_rts_smoothers_over_the_window():
    _, us, ys = data(25)
    for form, horizon in (("filtering", 6), ("filtering", 30), ("prediction", 6)):
        est, kf = kalman_like(form, horizon), kalman()
        filtered = []
        for t, (u, y) in enumerate(zip(us, ys)):
            est.update(u, y)
            kf.update(y)
            filtered.append((kf.x.copy(), kf.P.copy()))
            smoothed = rts(*map(np.array, zip(*filtered)))
            if form == "prediction":  # the last node is x(t+1): its prediction's covariance
                smoothed = np.concatenate([smoothed, [A @ kf.P @ A.T + Q]])
            np.testing.assert_allclose(est.P_window, smoothed[-len(est.x_window):], atol=1e-8)
            np.testing.assert_array_equal(est.P_window[-1], est.P)
            kf.predict(u=u)


def test_the_scipy_path_gives_the_same_window_covariances():
    _, us, ys = data(12)
    a = kalman_like("filtering", 5)
    b = kalman_like("filtering", 5, solver="least-squares",
                    solver_options=dict(xtol=1e-14, ftol=1e-14, gtol=1e-14))
    for u, y in zip(us, ys):
        a.update(u, y)
        b.update(u, y)
        np.testing.assert_allclose(a.P_window, b.P_window, rtol=1e-6, atol=1e-10)


def test_before_any_update_nothing_is_innovated_and_the_window_is_the_prior():
    est = kalman_like("filtering", 4)
    assert np.all(np.isnan(est.innovation)) and np.all(np.isnan(est.S)) and np.isnan(est.nis)
    np.testing.assert_array_equal(est.P_window, [est.P])
    est.update([0.0], None)  # no output: nothing measured, the likelihood of nothing is 1
    assert np.all(np.isnan(est.innovation)) and np.isnan(est.nis)
    assert est.log_likelihood == 0.0 and np.all(np.isfinite(est.S))


def test_S_of_a_learned_model_carries_the_gp_variances():
    """Dense numpy from the model's own stage_eval: S = C P⁻ Cᵀ + R0 + diag σ²_y, P⁻ = A P Aᵀ
    + Q0 + diag σ²_x at the previous estimate (filtering form)."""
    model = synthetic_learned_model(40)
    est = GPMHE(model, x0=[0.2, -0.1], horizon=5, form="filtering", Q0=1e-3, R0=1e-2)
    rng = np.random.default_rng(2)
    for _ in range(6):
        x_before, P_before, u_before = est.x, est.P, rng.uniform(-1, 1, 1)
        est.update(u_before, rng.normal(size=2) * 0.3)
    u, y = rng.uniform(-1, 1, 1), rng.normal(size=2) * 0.3
    x_before, P_before = est.x, est.P
    est.update(u, y)
    mx, vx, dmx, _, _, _, _, _ = model.stage_eval(np.concatenate([x_before, u_before])[None])
    Pm = dmx[0][:, :2] @ P_before @ dmx[0][:, :2].T + 1e-3 * np.eye(2) + np.diag(vx[0])
    _, _, _, _, my, vy, dmy, _ = model.stage_eval(np.concatenate([mx[0], u])[None])
    S = dmy[0][:, :2] @ Pm @ dmy[0][:, :2].T + 1e-2 * np.eye(2) + np.diag(vy[0])
    np.testing.assert_allclose(est.S, S, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(est.innovation, y - my[0], rtol=1e-10, atol=1e-12)


def test_reading_the_innovation_changes_nothing_later():
    """A learned model's evaluation cache decides which values later updates reuse: reading
    the innovation leaves it as it was, so the estimates stay bit-identical."""
    model = synthetic_learned_model(40)
    rng = np.random.default_rng(5)
    steps = [(rng.uniform(-1, 1, 1), rng.normal(size=2) * 0.3) for _ in range(12)]
    a, b = (GPMHE(model, x0=[0.2, -0.1], horizon=4, Q0=1e-3, R0=1e-2) for _ in range(2))
    for u, y in steps:
        a.update(u, y)
        b.update(u, y)
        _ = b.innovation, b.S, b.nis, b.log_likelihood
        assert np.array_equal(a.x, b.x) and np.array_equal(a.P_window, b.P_window)


def test_the_uncertainty_survives_copies_pickles_and_checkpoints(tmp_path):
    _, us, ys = data(15)
    est = kalman_like("filtering", 5)
    est.batch_filter(ys, us)
    buf = io.BytesIO()
    est.save(buf)
    buf.seek(0)
    for twin in (copy.deepcopy(est), pickle.loads(pickle.dumps(est)), GPMHE.load(buf, LINEAR)):
        np.testing.assert_array_equal(twin.P_window, est.P_window)
        np.testing.assert_array_equal(twin.innovation, est.innovation)
        np.testing.assert_array_equal(twin.S, est.S)
    # A file from before these were kept: unknown (NaN) until the next update, then right.
    path = tmp_path / "old.npz"
    est.save(path)
    entries = {k: v for k, v in np.load(path).items()
               if k not in ("core_outcome_x_before", "core_outcome_P_before",
                            "core_outcome_P_window")}
    entries["format_version"] = np.array(6)
    np.savez(path, **entries)
    old = GPMHE.load(path, LINEAR)
    assert np.all(np.isnan(old.innovation)) and np.all(np.isnan(old.P_window))
    old.update(us[0], ys[0])
    est.update(us[0], ys[0])
    np.testing.assert_array_equal(old.innovation, est.innovation)


def test_a_consistent_kalman_like_run_passes_the_chi2_tests_and_a_shrunk_one_fails():
    """NIS: every step of one run (white for a consistent estimator); NEES: the last step of
    independent runs (one run's NEES is correlated from step to step)."""
    _, us, ys = data(400, seed=3)
    est = kalman_like("filtering", 5)
    nis = []
    for u, y in zip(us, ys):
        est.update(u, y)
        nis.append(est.nis)
    assert chi2_test(nis, dof=2).consistent
    last = []
    for seed in range(200):
        x_true, us, ys = data(25, seed=100 + seed)
        xs, Ps = kalman_like("filtering", 5).batch_filter(ys, us)
        last.append((x_true[-1], xs[-1], Ps[-1]))
    x_true, xs, Ps = map(np.array, zip(*last))
    assert chi2_test(nees(x_true, xs, Ps), dof=2).consistent
    shrunk = chi2_test(nees(x_true, xs, Ps / 3), dof=2)
    assert not shrunk.consistent and shrunk.mean > shrunk.upper
    assert not chi2_test(np.array(nis) * 3, dof=2).consistent


def test_chi2_test_refuses_what_it_cannot_judge():
    with pytest.raises(ValueError, match="^values:"):
        chi2_test([np.nan, np.nan], dof=2)
    with pytest.raises(ValueError, match="^dof:"):
        chi2_test([1.0, 2.0], dof=[2, 0])
    with pytest.raises(ValueError, match="^alpha:"):
        chi2_test([1.0], dof=1, alpha=1.5)
    with pytest.raises(ValueError, match="^P: not positive definite at step 1"):
        nees([[0.0], [0.0]], [[0.0], [0.0]], [[[1.0]], [[-1.0]]])


def test_smooth_is_the_rts_smoother_of_the_whole_run_and_changes_nothing():
    _, us, ys = data(30)
    kf = kalman()
    xs_f, Ps_f = [], []
    for u, y in zip(us, ys):
        kf.update(y)
        xs_f.append(kf.x.copy())
        Ps_f.append(kf.P.copy())
        kf.predict(u=u)
    # filterpy's RTS smoother gives the covariances (its means leave out the input B u).
    _, Ps_r, _, _ = kf.rts_smoother(np.array(xs_f), np.array(Ps_f), Fs=[A] * 30, Qs=[Q] * 30)
    Psm, xsm = rts(xs_f, Ps_f), [xs_f[-1]]  # the means with the input, by the same recursion
    for k in range(28, -1, -1):
        Pp = A @ Ps_f[k] @ A.T + Q
        G = Ps_f[k] @ A.T @ np.linalg.inv(Pp)
        xsm.insert(0, xs_f[k] + G @ (xsm[0] - (A @ xs_f[k] + B @ us[k])))
    for form in ("prediction", "filtering"):
        est = kalman_like(form, 4)
        xs, Ps = est.smooth(ys, us)
        np.testing.assert_allclose(xs, np.array(xsm), atol=1e-7)
        np.testing.assert_allclose(Ps, Psm, atol=1e-8)
        np.testing.assert_allclose(Ps, Ps_r, atol=1e-8)  # filterpy's covariances agree
        assert est.t == 0 and est.horizon == 4 and est.form == form
        xs0, Ps0 = est.smooth([], [])  # an empty run: no node, as batch_filter gives none
        assert xs0.shape == (0, 2) and Ps0.shape == (0, 2, 2) and est.t == 0
        with pytest.raises(ValueError, match="^ys, us: ys has 0 rows but us has 2"):
            est.smooth([], us[:2])
        est.update(us[0], ys[0])
        with pytest.raises(ValueError, match="^smooth: the estimator has been updated"):
            est.smooth(ys, us)


def _fresh(est):
    """The innovation quantities computed anew: a checkpoint does not keep them."""
    buf = io.BytesIO()
    est.save(buf)
    buf.seek(0)
    twin = GPMHE.load(buf, est.model)
    return twin.innovation, twin.S, twin.nis, twin.log_likelihood


def _same(est):
    kept = (est.innovation, est.S, est.nis, est.log_likelihood)
    for a, b in zip(kept, _fresh(est)):
        np.testing.assert_array_equal(a, b)


def test_the_innovation_is_kept_until_something_it_reads_changes():
    """Read once, kept for the other reads; after every change of the history, the weights or
    the last input the next read is the new state's (compared with a fresh computation)."""
    calls = []

    def f(x, u):
        calls.append(1)
        return A @ x + B @ u

    def h(x, u):
        calls.append(1)
        return C @ x

    from gpmhe import KnownModel
    model = KnownModel(f, h, 2, 2, dim_u=1, f_jacobian=lambda x, u: A,
                       h_jacobian=lambda x, u: C)
    _, us, ys = data(12)
    est = GPMHE(model, x0=[0.0, 0.0], horizon=4, P0=np.eye(2), Q0=Q, R0=R, form="filtering")
    for t in range(6):
        est.update(us[t], ys[t])
    calls.clear()
    first = est.innovation.copy()
    n_first = len(calls)
    assert n_first > 0
    _ = est.S, est.nis, est.log_likelihood, est.innovation
    assert len(calls) == n_first  # kept
    _same(est)
    changes = [
        lambda e: e.update(us[6], ys[6]),
        lambda e: setattr(e, "R0", 2 * R),
        lambda e: setattr(e, "Q0", 3 * Q),
        lambda e: e.update(us[7], ys[7], R=0.5 * R),
        lambda e: e.update(None, [ys[8][0], np.nan]),  # u(8) not known yet ...
        lambda e: e.set_input(us[8]),                   # ... given
        lambda e: e.update(us[9], ys[9]),
        lambda e: e.add_delayed([np.nan, 0.3], age=1),  # the newest sample is unchanged
        lambda e: e.update(us[10], None),               # no output: NaN innovation
        lambda e: e.reset([0.5, 0.5]),
        lambda e: e.update(us[11], ys[11]),
    ]
    for change in changes:
        _ = est.innovation  # kept before the change
        change(est)
        _same(est)
    assert not np.array_equal(first, est.innovation)
    # A state loaded into the same object replaces what was kept.
    other = GPMHE(model, x0=[0.0, 0.0], horizon=4, P0=np.eye(2), Q0=Q, R0=R, form="filtering")
    other.update(us[0], ys[0])
    _ = est.innovation
    est._core.__setstate__(other._core.__getstate__())
    _same(est)
    np.testing.assert_array_equal(est.innovation, other.innovation)
