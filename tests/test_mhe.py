"""GPMHE end to end: convergence on the batch reactor from the poor prior (where filterpy's EKF
fails), both forms, missing outputs, a system with inputs and two outputs, bad input, solver
failure, filterpy's Saver, and that estimates are never NaN and stay inside the bounds."""

import warnings

import numpy as np
import pytest

from gpmhe import GPMHE, KnownModel, LearnedModel
from gpmhe.baselines import GPEKF, ExactEKF
from gpmhe.systems import batch_reactor as br

from conftest import f3_coupled as f3
from conftest import fitted_reactor_model, reactor_known_model
from conftest import h3_no_feedthrough as h3

SEEDS = (0, 1, 2)


@pytest.fixture(scope="module")
def gp5():
    return fitted_reactor_model(100, n_restarts=2)


@pytest.fixture(scope="module")
def known():
    return reactor_known_model()


def run(model, y, form="prediction", **kw):
    est = GPMHE(model, br.X_PRIOR0, x_bounds=br.X_BOUNDS, solver="least-squares", form=form,
                **br.MHE_SETTINGS, **kw)
    xs, Ps = est.batch_filter(y)
    return est, xs, Ps


def rmse(xs, truth):
    return float(np.sqrt(np.mean(np.sum((xs - truth) ** 2, axis=1))))


def check_sane(xs):
    lb, ub = br.X_BOUNDS
    assert np.all(np.isfinite(xs))
    assert np.all(xs >= lb - 1e-12) and np.all(xs <= ub + 1e-12)


def test_batch_reactor_gp_mhe_converges_where_the_ekf_fails(gp5, known):
    gp_err, exact_err, ekf_err, ekf_min = [], [], [], []
    for seed in SEEDS:
        x, y = br.simulate(br.X_TRUE0, 100, np.random.default_rng(seed))
        _, xs, _ = run(gp5, y[:100])            # xs[i] estimates x(i+1)
        check_sane(xs)
        gp_err.append(rmse(xs[19:], x[20:101]))
        _, xs, _ = run(known, y[:100])
        check_sane(xs)
        exact_err.append(rmse(xs[19:], x[20:101]))
        ekf = ExactEKF(br.f, br.f_jacobian, br.h, br.h_jacobian, br.X_PRIOR0, np.eye(2),
                       br.SIGMA_W**2 * np.eye(2), br.SIGMA_V**2)
        xe = []
        for t in range(100):
            ekf.update(y[t])
            ekf.predict()
            xe.append(ekf.x.ravel().copy())
        xe = np.array(xe)
        ekf_err.append(rmse(xe[19:], x[20:101]))
        ekf_min.append(xe[:, 0].min())
    assert np.mean(gp_err) < 0.6
    assert np.mean(exact_err) < 0.6
    assert np.mean(ekf_err) > 1.5
    assert max(ekf_min) < 0.0  # x̂1 negative in every run


def test_filtering_form_and_its_prior(gp5):
    x, y = br.simulate(br.X_TRUE0, 60, np.random.default_rng(4))
    est, xs, _ = run(gp5, y[:60], form="filtering")
    check_sane(xs)
    assert rmse(xs[19:], x[19:60]) < 0.6  # filtering: xs[i] estimates x(i)
    # The arrival prior is the one-step prediction of the filtered estimate at t - M_t - 1.
    est2 = GPMHE(gp5, br.X_PRIOR0, x_bounds=br.X_BOUNDS, solver="least-squares",
                 form="filtering", **br.MHE_SETTINGS)
    est2.batch_filter(y[:40])
    x_prev = est2.x.copy()  # x̂(39)
    est2.batch_filter(y[40:56])  # now t = 55, window 40..55, prior for x(40) = m_x(x̂(39))
    np.testing.assert_allclose(est2.x_arrival, gp5.predict(x_prev), rtol=1e-12)
    assert est2.x_window.shape == (16, 2)


def test_prediction_form_last_node_is_the_model_prediction(gp5):
    # The last node carries only a process residual, so x̂(t+1) = m_x(x̄_t) at the optimum
    # (away from the bounds): the prediction form predicts. Tight tolerances: the property holds
    # at the optimum, and where SciPy stops by default differs between its versions.
    x, y = br.simulate(br.X_TRUE0, 40, np.random.default_rng(6))
    est, xs, Ps = run(gp5, y[:40], solver_options=dict(ftol=1e-15, xtol=1e-15, gtol=1e-15))
    np.testing.assert_allclose(est.x, gp5.predict(est.x_window[-2]), atol=1e-6)
    assert est.x_window.shape == (16, 2)
    assert np.allclose(Ps[-1], Ps[-1].T) and np.all(np.linalg.eigvalsh(Ps[-1]) > 0)


def test_missing_outputs(gp5):
    x, y = br.simulate(br.X_TRUE0, 60, np.random.default_rng(8))
    ys = [None if t % 3 == 1 else y[t] for t in range(60)]
    est, xs, _ = run(gp5, ys)
    check_sane(xs)
    assert rmse(xs[29:], x[30:61]) < 0.6
    # window after t = 59: 15 stages (times 45..59), outputs missing at t % 3 == 1 (5 of them)
    assert est._core.n_residuals == 2 + 15 * 2 + 10


def simulate3(x0, steps, rng, sw=0.01, sv=0.02):
    u = np.sin(0.3 * np.arange(steps + 1))[:, None]
    X = np.empty((steps + 1, 2))
    X[0] = x0
    for t in range(steps):
        X[t + 1] = f3(X[t], u[t]) + sw * rng.standard_normal(2)
    Y = np.array([h3(X[t], u[t]) for t in range(steps + 1)]) + sv * rng.standard_normal((steps + 1, 2))
    return X, Y, u


@pytest.mark.parametrize("kind", ["known", "learned"])
def test_inputs_and_two_outputs(kind):
    rng = np.random.default_rng(9)
    if kind == "known":
        model = KnownModel(f3, h3, dim_x=2, dim_y=2, dim_u=1)  # finite-difference Jacobians
    else:
        trajs = [simulate3(x0, 30, rng) for x0 in ([1.0, 1.0], [-1.0, 0.5], [0.5, -1.0], [0.0, 0.0])]
        model = LearnedModel.from_trajectories([t[0] for t in trajs], [t[1] for t in trajs],
                                               inputs=[t[2] for t in trajs], random_state=0)
        assert (model.dim_x, model.dim_u, model.dim_y) == (2, 1, 2)
    X, Y, U = simulate3([0.8, 0.6], 40, rng)
    for form in ("prediction", "filtering"):
        est = GPMHE(model, [-0.5, -0.5], horizon=8, eta=0.9, Q0=1e-4, R0=4e-4,
                    x_bounds=([-3, -3], [3, 3]), form=form, solver="least-squares")
        xs, _ = est.batch_filter(Y[:40], U[:40])
        assert np.all(np.isfinite(xs))
        truth = X[1:41] if form == "prediction" else X[:40]
        assert rmse(xs[20:], truth[20:]) < 0.1


def test_bad_inputs_raise_and_leave_the_state(gp5, known):
    with pytest.raises(ValueError, match="horizon"):
        GPMHE(known, br.X_PRIOR0, horizon=0)
    with pytest.raises(ValueError, match="eta"):
        GPMHE(known, br.X_PRIOR0, eta=1.5)
    with pytest.raises(ValueError, match="P2"):
        GPMHE(known, br.X_PRIOR0, P2=-np.eye(2))
    with pytest.raises(ValueError, match="Q0"):
        GPMHE(known, br.X_PRIOR0, Q0=[1.0, 0.0])
    with pytest.raises(ValueError, match="R0"):
        GPMHE(known, br.X_PRIOR0, R0=np.nan)
    with pytest.raises(ValueError, match="x_bounds"):
        GPMHE(known, br.X_PRIOR0, x_bounds=([1, 1], [0, 2]))
    with pytest.raises(ValueError, match="x0"):
        GPMHE(known, [5.0, 1.0], x_bounds=br.X_BOUNDS)
    with pytest.raises(ValueError, match="form"):
        GPMHE(known, br.X_PRIOR0, form="smoothing")
    with pytest.raises(ValueError, match="solver"):
        GPMHE(known, br.X_PRIOR0, solver="newton")
    with pytest.raises(ValueError, match="model"):
        GPMHE(object(), br.X_PRIOR0)
    est = GPMHE(gp5, br.X_PRIOR0, x_bounds=br.X_BOUNDS, solver="least-squares", **br.MHE_SETTINGS)
    est.update(None, [3.9])
    before = {k: np.copy(getattr(est, k)) for k in ("x", "x_arrival", "x_window", "P", "cost", "t")}
    for bad in ([np.inf], [1.0, 2.0], np.inf, (None,)):
        with pytest.raises(ValueError, match="y"):
            est.update(None, bad)
    with pytest.raises(ValueError, match="u"):
        est.update([1.0], [3.9])
    with pytest.raises(ValueError, match="row 1"):
        est.batch_filter([[3.9], [-np.inf]])
    for k, v in before.items():
        np.testing.assert_array_equal(getattr(est, k), v)


@pytest.mark.parametrize("solver, options", [("gauss-newton", dict(max_iter=1, dtol=0.0)),
                                             ("least-squares", dict(max_nfev=1))])
def test_non_convergence_warning_as_error_leaves_a_consistent_estimator(gp5, solver, options):
    """With warnings turned into errors, a window that did not converge raises; the estimator is
    then either unchanged (SciPy paths: the warning comes before the step is recorded) or fully
    updated (Rust path): its attributes always match the core's history."""
    _, y = br.simulate(br.X_TRUE0, 3, np.random.default_rng(2))
    est = GPMHE(gp5, br.X_PRIOR0, x_bounds=br.X_BOUNDS, solver=solver, solver_options=options,
                **br.MHE_SETTINGS)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        with pytest.raises(RuntimeWarning, match="did not converge at t=0"):
            est.update(None, y[0])
    assert est.t == est._core.t
    assert est.t == (1 if solver == "gauss-newton" else 0)
    np.testing.assert_array_equal(est.x, est.x_window[-1])
    assert est.x_window.shape[0] == est.t + 1


def test_solver_failure_keeps_a_finite_estimate(gp5):
    x, y = br.simulate(br.X_TRUE0, 5, np.random.default_rng(2))
    est = GPMHE(gp5, br.X_PRIOR0, x_bounds=br.X_BOUNDS, solver="trust-constr",
                solver_options=dict(maxiter=1), **br.MHE_SETTINGS)
    with pytest.warns(RuntimeWarning, match="did not converge"):
        est.update(None, y[0])
        est.update(None, y[1])
    assert not est.success
    assert np.all(np.isfinite(est.x)) and np.all(np.isfinite(est.x_window))
    win = est._core
    assert est.cost == pytest.approx(win.cost(est.x_window.reshape(-1)))


def test_saver_reset_and_batch_filter_match_update(gp5):
    from filterpy.common import Saver

    x, y = br.simulate(br.X_TRUE0, 20, np.random.default_rng(3))
    est = GPMHE(gp5, br.X_PRIOR0, x_bounds=br.X_BOUNDS, solver="least-squares", **br.MHE_SETTINGS)
    saver = Saver(est)  # from t = 0, while the window still grows
    xs_loop = []
    for t in range(20):
        est.update(None, y[t])
        saver.save()
        xs_loop.append(est.x.copy())
    saver.to_array()
    assert saver.x.shape == (20, 2)
    np.testing.assert_allclose(saver.x, np.array(xs_loop))
    est.reset(br.X_PRIOR0)
    assert est.t == 0 and np.array_equal(est.x, br.X_PRIOR0)
    xs, _ = est.batch_filter(y[:20])
    np.testing.assert_allclose(xs, np.array(xs_loop), rtol=1e-10, atol=1e-12)


def test_learned_model_save_load_round_trip(gp5, tmp_path):
    path = tmp_path / "model.npz"
    gp5.save(path)
    loaded = LearnedModel.load(path)
    d = np.array([[1.0, 2.0], [0.5, 3.0]])
    for a, b in zip(gp5.stage_eval(d), loaded.stage_eval(d)):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)


def test_f_residual_option_and_gp_ekf_run():
    states, outputs = br.training_data(3, rng=5)
    model = LearnedModel.from_trajectories(states, outputs, f_residual=True, optimizer=None,
                                           sigma_f=1.0, lengthscales=2.0, sigma_eps=0.02)
    assert model.f_residual
    x = np.array([1.0, 2.0])
    # the increment GP mean is added to x
    np.testing.assert_allclose(model.predict(x), x + model.f_gp.predict(x[None])[0])
    ekf = GPEKF(model, br.X_PRIOR0, np.eye(2), 1e-4 * np.eye(2), 1e-2)
    ekf.update(3.9)
    ekf.predict()
    assert np.all(np.isfinite(ekf.x))


def test_ekfs_with_several_outputs_keep_x_a_column():
    # filterpy compares z with h(x) of shape (p, 1): a flat z of p > 1 values used to broadcast
    # the innovation to (p, p) and x to (n, p).
    from conftest import f3_jac, f3_v, h3, h3_jac, h3_jac_v, h3_v

    model = KnownModel(f3_v, h3_v, 2, 2, dim_u=1, f_jacobian=None, h_jacobian=h3_jac_v, vectorized=True)
    P0, Q, R = np.eye(2), 1e-2 * np.eye(2), np.diag([0.1, 0.2])
    x0, u, z = np.array([0.5, -0.2]), np.array([0.3]), np.array([0.7, 0.1])
    ekf = GPEKF(model, x0, P0, Q, R)
    ekf.update(z, u=u)
    H = h3_jac(x0, u)
    K = P0 @ H.T @ np.linalg.inv(H @ P0 @ H.T + R)
    expected = x0 + K @ (z - h3(x0, u))
    assert ekf.x.shape == (2, 1)
    np.testing.assert_allclose(ekf.x.ravel(), expected, rtol=1e-12)
    ekf.predict(u=u)
    assert ekf.x.shape == (2, 1)
    exact = ExactEKF(lambda x: f3_v(x[None], u[None])[0], lambda x: f3_jac(x, u),
                     lambda x: h3(x, u), lambda x: h3_jac(x, u), x0, P0, Q, R)
    exact.update(z)
    assert exact.x.shape == (2, 1)
    np.testing.assert_allclose(exact.x.ravel(), expected, rtol=1e-12)


def test_demo_runs_and_prints_the_table(capsys, tmp_path):
    import importlib.util

    from gpmhe.demos.batch_reactor import main

    plot = importlib.util.find_spec("matplotlib") is not None  # the optional `plot` extra
    args = ["--steps", "21", "--restarts", "0"] + (["--out", str(tmp_path / "fig.png")] if plot else [])
    assert main(args) == 0
    out = capsys.readouterr().out
    for name in ("gpmhe's defaults", "the paper's setup", "GP-MHE, 5 trajectories",
                 "GP-MHE, 3 trajectories", "MHE, exact model", "EKF, GP model (5 traj.)",
                 "filterpy EKF, exact model", "MHE solver: gauss-newton", "Reading the table"):
        assert name in out
    assert out.count("GP-MHE, 5 trajectories") == 3  # a row per setup and the reading
    if plot:
        assert (tmp_path / "fig.png").stat().st_size > 0


def test_the_demo_reading_follows_the_numbers():
    """The sentences under the table are worded from its numbers: swap which setup wins and the
    words change with them."""
    from gpmhe.demos import batch_reactor as demo

    truth = np.zeros((22, 2))

    def row(err, low=0.2):  # x̂ off by err in both states after the transient, x̂1 once at low
        xs = np.full((21, 2), err)
        xs[0, 0] = low
        return xs, np.zeros(21), 0

    results = {s: {r: row(0.1 if s == "gpmhe's defaults" else 0.3) for r in demo.ROWS}
               for s in demo.SETUPS}
    results[None] = {demo.EKF_ROW: row(0.2)}
    text = " ".join(demo._reading(truth, results).split())
    assert "lower than" in text and "comes from the arrival cost" in text
    assert "below zero" not in text and "wrong state" not in text
    results = {s: {r: row(0.3 if s == "gpmhe's defaults" else 0.1, low=-0.5) for r in demo.ROWS}
               for s in demo.SETUPS}
    results[None] = {demo.EKF_ROW: row(3.0, low=-3.0)}
    text = " ".join(demo._reading(truth, results).split())
    assert "higher than" in text and "below zero" in text and "wrong state" in text


def test_the_command_line_help_is_plain_text(capsys):
    from gpmhe.__main__ import main

    for argv in (["--help"], ["demo", "--help"], ["demo", "rgp", "--help"]):
        try:
            code = main(argv)
        except SystemExit as exc:  # argparse's --help
            code = exc.code
        assert code == 0
        text = capsys.readouterr().out
        assert "usage: python -m gpmhe demo" in text
        for markup in ("``", ":doc:", ":func:", ".rst", ".py"):
            assert markup not in text, (argv, markup)