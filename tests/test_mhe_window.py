"""The MHE window problem assembled in Rust (gpmhe._core.MovingHorizon) against a plain numpy
implementation of the window cost (docs/user_guide/window.rst) and finite differences, and the two SciPy solver paths against each
other on single windows (with and without active bounds)."""

import numpy as np
import pytest

from gpmhe import GPMHE, KnownModel, _core
from gpmhe.systems import batch_reactor as br
from gpmhe.mhe import solvers

from conftest import check_window_derivatives, f3, h3, synthetic_learned_model


def synthetic_learned(f_residual):
    """GPs (fixed hyperparameters, no optimisation) on a 2-state, 1-input, 2-output system."""
    return synthetic_learned_model(60, f_residual)


def numpy_cost(model, z, u, y, present, x_prior, P2, q0, r0, eta, form):
    """The window cost (docs/user_guide/window.rst) written out: prior term, then the stages j = 1..M_t (node M_t - j)."""
    n = model.dim_x
    X = z.reshape(-1, n)
    Mt = X.shape[0] - 1
    dx = X[0] - x_prior
    J = 2 * eta**Mt * dx @ P2 @ dx
    for j in range(1, Mt + 1):
        i = Mt - j
        mx, vx, _, _, my, vy, _, _ = model.stage_eval(np.concatenate([X[i], u[i]])[None])
        w = X[i + 1] - mx[0]
        J += 2 * eta ** (j - 1) * w @ np.linalg.solve(np.diag(vx[0] + q0), w)
        if present[i]:
            v = y[i] - my[0]
            J += 2 * eta ** (j - 1) * v @ np.linalg.solve(np.diag(vy[0] + r0), v)
    if form == "filtering" and present[Mt]:
        mx, vx, _, _, my, vy, _, _ = model.stage_eval(np.concatenate([X[Mt], u[Mt]])[None])
        v = y[Mt] - my[0]
        J += 2 * v @ np.linalg.solve(np.diag(vy[0] + r0), v)
    return J


def known3():
    return KnownModel(f3, h3, dim_x=2, dim_y=2, dim_u=1)  # finite-difference Jacobians


@pytest.mark.parametrize("form", ["prediction", "filtering"])
@pytest.mark.parametrize("kind", ["known", "learned", "learned-residual"])
def test_window_matches_numpy_and_finite_differences(form, kind):
    model = {"known": known3, "learned": lambda: synthetic_learned(False),
             "learned-residual": lambda: synthetic_learned(True)}[kind]()
    rng = np.random.default_rng(7)
    nodes = 6
    P2 = np.array([[2.0, 0.3], [0.3, 1.0]])
    q0, r0, eta = np.array([1e-2, 2e-2]), np.array([3e-2, 1e-2]), 0.9
    S = np.ascontiguousarray(np.linalg.cholesky(P2).T)
    win = _core.MovingHorizon(model._stage_model(), eta, q0, r0, S, form == "filtering")
    u = rng.uniform(-1, 1, (nodes, 1))
    y = rng.uniform(-1, 1, (nodes, 2))
    present = [True, False, True, True, True, True]
    x_prior = np.array([0.2, -0.3])
    win.set_data(u, y, present, x_prior)
    z = rng.uniform(-1, 1, nodes * 2)

    ref = numpy_cost(model, z, u, y, present, x_prior, P2, q0, r0, eta, form)
    assert win.cost(z) == pytest.approx(ref, rel=1e-10)
    r = win.residuals(z)
    assert r @ r == pytest.approx(ref, rel=1e-12)
    n_out = sum(present[:-1]) + (present[-1] and form == "filtering")
    assert win.n_residuals == 2 + 2 * (nodes - 1) + 2 * n_out

    Jac = win.jacobian(z)
    np.testing.assert_allclose(win.gn_hessian(z), 2 * Jac.T @ Jac, rtol=1e-12, atol=1e-12)
    check_window_derivatives(win, z)


def test_window_rejects_bad_data_and_keeps_the_previous_window():
    model = known3()
    win = _core.MovingHorizon(model._stage_model(), 0.9, np.ones(2), np.ones(2), np.eye(2), False)
    win.set_data(np.zeros((3, 1)), np.zeros((3, 2)), [True] * 3, np.zeros(2))
    with pytest.raises(ValueError, match="x_prior"):
        win.set_data(np.zeros((4, 1)), np.zeros((4, 2)), [True] * 4, np.array([0.0, np.nan]))
    assert win.n_nodes == 3
    with pytest.raises(ValueError, match="z"):
        win.cost(np.zeros(5))
    with pytest.raises(ValueError, match="Q0"):
        _core.MovingHorizon(model._stage_model(), 0.9, np.array([1.0, -1.0]), np.ones(2), np.eye(2), False)
    with pytest.raises(ValueError, match="eta"):
        _core.MovingHorizon(model._stage_model(), 1.5, np.ones(2), np.ones(2), np.eye(2), False)
    with pytest.raises(ValueError, match="y"):
        win.set_data(np.zeros((3, 1)), np.full((3, 2), np.inf), [True] * 3, np.zeros(2))
    assert win.n_nodes == 3


def test_callback_errors_propagate():
    def bad_f(x, u):
        raise ZeroDivisionError("boom")

    model = KnownModel(bad_f, h3, dim_x=2, dim_y=2, dim_u=1)
    win = _core.MovingHorizon(model._stage_model(), 0.9, np.ones(2), np.ones(2), np.eye(2), False)
    win.set_data(np.zeros((2, 1)), np.zeros((2, 2)), [True] * 2, np.zeros(2))
    with pytest.raises(ZeroDivisionError):
        win.cost(np.zeros(4))


@pytest.mark.parametrize("form", ["prediction", "filtering"])
@pytest.mark.parametrize("kind", ["known", "known-stage-eval", "learned", "learned-residual"])
def test_prepare_warm_start_shifts_predicts_and_clips(kind, form):
    """The Rust warm start (MovingHorizon.prepare, used by every solver path): the previous
    window's nodes that overlap the new window, then each new node predicted from the one before
    with the model's one-step prediction, all clipped into the inner box (the state box shrunk by
    1e-6 of its width); nodes already inside stay bit-identical (the learned model's reuse of GP
    values depends on it). Driven through the history: random windows are committed, and each
    next warm start is checked against this rule."""
    from gpmhe import _core
    model = known3() if kind.startswith("known") else synthetic_learned(kind == "learned-residual")
    lo, hi = np.array([-0.9, -2.0]), np.array([0.9, 2.0])
    settings = dict(horizon=3, x0=np.zeros(2), lower=lo, upper=hi)
    filtering = form == "filtering"
    if kind == "known-stage-eval":  # no predict callable: the window uses stage_eval's means
        win = _core.MovingHorizon(_core.StageModel.callback(model.stage_eval, 2, 1, 2), 0.9,
                                  np.ones(2), np.ones(2), np.eye(2), filtering, **settings)
    else:
        win = _core.MovingHorizon(model._stage_model(), 0.9, np.ones(2), np.ones(2), np.eye(2), filtering, **settings)
    inner = (lo + 1e-6 * (hi - lo), hi - 1e-6 * (hi - lo))
    rng = np.random.default_rng(5)
    prev, prev_s0, inputs = np.zeros((1, 2)), 0, []
    for t in range(6):
        u = rng.uniform(-1, 1, 1)
        inputs.append(u)
        z0, LB, UB = win.prepare(u, rng.uniform(-1, 1, 2))
        nodes = len(z0) // 2
        end = t + 1 if form == "prediction" else t
        s0 = max(0, end - 3)
        assert nodes == end - s0 + 1 and win.n_nodes == nodes
        np.testing.assert_array_equal(LB, np.tile(lo, nodes))
        np.testing.assert_array_equal(UB, np.tile(hi, nodes))
        first = s0 - prev_s0
        kept = min(nodes, len(prev) - first)
        assert kept >= 1
        expect = np.empty((nodes, 2))
        expect[:kept] = prev[first:first + kept]
        for i in range(kept, nodes):  # node i is time s0 + i, predicted with u(s0 + i − 1)
            expect[i] = model.predict(expect[i - 1], inputs[s0 + i - 1])
        z0 = z0.reshape(nodes, 2)
        np.testing.assert_allclose(z0, np.clip(expect, *inner), rtol=1e-13, atol=1e-14)
        inside = np.all((expect[:kept] >= inner[0]) & (expect[:kept] <= inner[1]), axis=1)
        assert np.array_equal(z0[:kept][inside], expect[:kept][inside])  # bit-identical
        np.testing.assert_allclose(win.predict_next(expect[0], u), model.predict(expect[0], u),
                                   rtol=1e-13, atol=1e-15)
        z = rng.uniform(-0.8, 0.8, (nodes, 2))
        z[0, 0] = 0.37123456789
        x_window, x_prior = win.commit(z.reshape(-1))
        np.testing.assert_array_equal(x_window, z)
        prev, prev_s0 = z, s0
    assert win.t == 6


def test_prepare_rejects_bad_arguments_naming_them():
    """Bad input to prepare/update/commit raises ValueError naming it and leaves the estimator
    (its history and window) as it was."""
    from gpmhe import _core
    model = known3()
    win = _core.MovingHorizon(model._stage_model(), 0.9, np.ones(2), np.ones(2), np.eye(2), False, horizon=4,
                             x0=np.zeros(2))
    win.set_data(np.zeros((3, 1)), np.zeros((3, 2)), [True] * 3, np.zeros(2))
    for u, y, name in ((np.zeros(2), np.zeros(2), "u"), (np.zeros(1), np.zeros(3), "y"),
                       (np.full(1, np.nan), np.zeros(2), "u"), (np.zeros(1), np.full(2, np.inf), "y")):
        for call in (win.prepare, win.update):
            with pytest.raises(ValueError, match=name):
                call(u, y)
    assert win.n_nodes == 3 and win.t == 0  # the window's data were left as they were
    with pytest.raises(ValueError, match="z"):
        win.commit(np.zeros(4))  # nothing staged
    win.prepare(np.zeros(1), np.zeros(2))
    with pytest.raises(ValueError, match="z"):
        win.commit(np.zeros(3))
    with pytest.raises(ValueError, match="z"):
        win.commit(np.full(4, np.nan))
    assert win.t == 0
    with pytest.raises(ValueError, match="x"):
        win.predict_next(np.zeros(3), np.zeros(1))

    def bad_predict(x, u):
        return np.zeros(3)

    bad = _core.StageModel.callback(model.stage_eval, 2, 1, 2, predict=bad_predict)
    win2 = _core.MovingHorizon(bad, 0.9, np.ones(2), np.ones(2), np.eye(2), False, horizon=3,
                               x0=np.zeros(2))
    with pytest.raises(ValueError, match="predict"):
        win2.prepare(np.zeros(1), np.zeros(2))
    with pytest.raises(ValueError, match="predict"):
        win2.update(np.zeros(1), np.zeros(2))
    assert win2.t == 0
    with pytest.raises(ValueError, match="predict"):
        _core.StageModel.callback(model.stage_eval, 2, 1, 2, predict=3.0)


def test_update_is_prepare_then_solve_then_commit():
    """MovingHorizon.update (GPMHE's one Rust call per update) gives exactly prepare, solve and
    commit, and in the filtering form the next arrival prior is the model's prediction from the
    last node."""
    from gpmhe import _core
    model = synthetic_learned(False)
    rng = np.random.default_rng(9)
    lo, hi = np.full(2, -1.5), np.full(2, 1.5)
    for filtering in (False, True):
        settings = dict(horizon=3, x0=np.zeros(2), lower=lo, upper=hi)
        w1 = _core.MovingHorizon(model._stage_model(), 0.9, np.full(2, 0.1), np.full(2, 0.1), np.eye(2), filtering,
                                solver=_core.WindowSolver(), **settings)
        w2 = _core.MovingHorizon(model._stage_model(), 0.9, np.full(2, 0.1), np.full(2, 0.1), np.eye(2), filtering,
                                **settings)
        priors, next_priors, estimates = [], [], []
        for t in range(6):
            u, y = rng.uniform(-1, 1, 1), rng.uniform(-1, 1, 2)
            w1.update(u, y)
            z0, LB, UB = w2.prepare(u, y)
            ref = _core.WindowSolver().solve(w2, z0, LB, UB)
            # The solver's P is the last block of 4H⁻¹; with η = 0.9 the update reports the
            # discounted estimate's covariance 4H⁻¹GH⁻¹ (tests/test_uncertainty.py).
            H = w2.gn_hessian(ref[0])
            np.testing.assert_allclose(ref[8], 4 * np.linalg.inv(H)[-2:, -2:], rtol=1e-10)
            sandwich = solvers.window_covariance(w2, ref[0], 2)[-4:].reshape(2, 2)
            x_window, x_prior = w2.commit(ref[0])
            np.testing.assert_array_equal(w1.x_window, x_window)
            np.testing.assert_array_equal(w1.x_prior, x_prior)
            cost, status, success, nit, nfev, pg, interior = ref[1:8]
            assert (w1.optimal_cost, w1.success, w1.nit, w1.nfev, w1.projected_gradient) == (
                cost, success, nit, nfev, pg)
            assert w1.message == (f"{status} (projected gradient {pg:.2e}, {interior} interior "
                                  "its)")
            np.testing.assert_allclose(w1.covariance, sandwich, rtol=1e-10, atol=1e-15)
            # The prior of the first node, time s0: x̂(s0) from update s0 − 1 (prediction
            # form), or m_x(x̂(s0 − 1), u(s0 − 1)) from update s0 − 1 (filtering form).
            s0 = max(0, t - 3) if filtering else max(0, t - 2)
            expect = np.zeros(2) if s0 == 0 else (next_priors if filtering else estimates)[s0 - 1]
            np.testing.assert_array_equal(x_prior, expect)
            next_priors.append(w1.predict_next(x_window[-1], u))
            estimates.append(x_window[-1])


@pytest.mark.parametrize("bounds", ["paper", "active"])
def test_solvers_reach_the_same_cost_on_single_windows(reactor_model, bounds):
    """After a converged run, re-solve the current window from the same warm start with both
    SciPy paths; the non-convex problem is well posed here, so the optimal costs agree."""
    rng = np.random.default_rng(5)
    x, y = br.simulate(br.X_TRUE0, 40, rng)
    lb, ub = br.X_BOUNDS
    if bounds == "active":  # x2 capped inside its true range: the bound is active at the optimum
        ub = np.array([4.5, 1.8])
    est = GPMHE(reactor_model, np.clip(x[0], lb, ub), x_bounds=(lb, ub), solver="least-squares",
                **br.MHE_SETTINGS)
    for t in range(30):
        est.update(None, y[t])
    win = est._core
    nodes = est.x_window.shape[0]
    z0 = np.clip(est.x_window.reshape(-1) + 0.05 * rng.standard_normal(2 * nodes),
                 np.tile(lb, nodes) + 1e-3, np.tile(ub, nodes) - 1e-3)
    LB, UB = np.tile(lb, nodes), np.tile(ub, nodes)
    from gpmhe.mhe import solvers
    z_ls, _, ok_ls, _, _ = solvers.solve(
        "least-squares", dict(ftol=1e-15, xtol=1e-15, gtol=1e-12, max_nfev=2000), win, z0, LB, UB)
    z_tc, _, _, _, _ = solvers.solve(  # to gtol
        "trust-constr", dict(gtol=1e-10, xtol=1e-12, maxiter=3000, dtol=0.0), win, z0, LB, UB)
    assert ok_ls
    c_ls, c_tc = win.cost(z_ls), win.cost(z_tc)
    # least-squares reaches a KKT point: projected-gradient residual small relative to the
    # gradient at the start.
    g0 = np.max(np.abs(win.cost_grad(z0)[1]))
    _, g = win.cost_grad(z_ls)
    assert np.max(np.abs(z_ls - np.clip(z_ls - g, LB, UB))) <= 1e-5 * g0
    if bounds == "paper":
        assert abs(c_ls - c_tc) <= 1e-6 * max(c_ls, c_tc)
    else:
        assert np.any(np.isclose(z_ls.reshape(-1, 2)[:, 1], 1.8, atol=1e-8))
        # With many active bounds SciPy's trust-constr stalls on its xtol test slightly above
        # the KKT point (3e-5 relative here, also with an exact Hessian): it never does better.
        assert c_tc >= c_ls * (1 - 1e-6)
        assert c_tc <= c_ls * (1 + 1e-4)
