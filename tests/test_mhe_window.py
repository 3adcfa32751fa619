"""The MHE window problem assembled in Rust (gpmhe._core.MheWindow) against a plain numpy
implementation of the window cost (docs/user_guide/window.rst) and finite differences, and the two SciPy solver paths against each
other on single windows (with and without active bounds)."""

import numpy as np
import pytest

from gpmhe import GPMHE, KnownModel
from gpmhe.systems import batch_reactor as br

from conftest import f3, h3, synthetic_learned_model


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
    win = model._make_window(eta, q0, r0, S, form == "filtering")
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

    cost, g = win.cost_grad(z)
    Jac = win.jacobian(z)
    np.testing.assert_allclose(g, 2 * Jac.T @ r, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(win.gn_hessian(z), 2 * Jac.T @ Jac, rtol=1e-12, atol=1e-12)
    h = 1e-6
    fd_g = np.empty_like(z)
    fd_J = np.empty_like(Jac)
    for c in range(z.size):
        e = np.zeros_like(z)
        e[c] = h
        fd_g[c] = (win.cost(z + e) - win.cost(z - e)) / (2 * h)
        fd_J[:, c] = (win.residuals(z + e) - win.residuals(z - e)) / (2 * h)
    np.testing.assert_allclose(g, fd_g, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(Jac, fd_J, rtol=1e-5, atol=1e-5)


def test_window_rejects_bad_data_and_keeps_the_previous_window():
    model = known3()
    win = model._make_window(0.9, np.ones(2), np.ones(2), np.eye(2), False)
    win.set_data(np.zeros((3, 1)), np.zeros((3, 2)), [True] * 3, np.zeros(2))
    with pytest.raises(ValueError, match="x_prior"):
        win.set_data(np.zeros((4, 1)), np.zeros((4, 2)), [True] * 4, np.array([0.0, np.nan]))
    assert win.n_nodes == 3
    with pytest.raises(ValueError, match="z"):
        win.cost(np.zeros(5))
    with pytest.raises(ValueError, match="Q0"):
        model._make_window(0.9, np.array([1.0, -1.0]), np.ones(2), np.eye(2), False)
    with pytest.raises(ValueError, match="eta"):
        model._make_window(1.0, np.ones(2), np.ones(2), np.eye(2), False)


def test_callback_errors_propagate():
    def bad_f(x, u):
        raise ZeroDivisionError("boom")

    model = KnownModel(bad_f, h3, dim_x=2, dim_y=2, dim_u=1)
    win = model._make_window(0.9, np.ones(2), np.ones(2), np.eye(2), False)
    win.set_data(np.zeros((2, 1)), np.zeros((2, 2)), [True] * 2, np.zeros(2))
    with pytest.raises(ZeroDivisionError):
        win.cost(np.zeros(4))


@pytest.mark.parametrize("kind", ["known", "known-stage-eval", "learned", "learned-residual"])
def test_prepare_warm_start_shifts_predicts_and_clips(kind):
    """The Rust warm start (MheWindow.prepare, used by every solver path): the previous window's
    rows from `first` on, then each new node predicted from the one before with the model's
    one-step prediction, all clipped into the inner box; rows already inside stay bit-identical
    (the learned model's reuse of GP values depends on it)."""
    model = known3() if kind.startswith("known") else synthetic_learned(kind == "learned-residual")
    if kind == "known-stage-eval":  # no predict callable: the window uses stage_eval's means
        from gpmhe import _core
        win = _core.MheWindow.with_callback(model.stage_eval, 2, 1, 2, 0.9, np.ones(2),
                                            np.ones(2), np.eye(2), False)
    else:
        win = model._make_window(0.9, np.ones(2), np.ones(2), np.eye(2), False)
    rng = np.random.default_rng(5)
    prev = rng.uniform(-1, 1, (4, 2))
    prev[1, 0] = 0.37123456789
    u = rng.uniform(-1, 1, (5, 1))
    lo, hi = np.array([-0.9, -2.0]), np.array([0.9, 2.0])
    args = (u, np.zeros((5, 2)), [True] * 5, np.zeros(2))
    for first in (1, 3, -1):
        z0 = win.prepare(*args, prev, first, lo, hi).reshape(5, 2)
        expect = np.empty((5, 2))
        kept = 0 if first < 0 else min(5, 4 - first)
        expect[:kept] = prev[first:first + kept]
        for i in range(kept, 5):
            expect[i] = prev[-1] if i == 0 else model.predict(expect[i - 1], u[i - 1])
        np.testing.assert_allclose(z0, np.clip(expect, lo, hi), rtol=1e-13, atol=1e-14)
        np.testing.assert_allclose(win.predict_next(expect[0], u[0]),
                                   model.predict(expect[0], u[0]), rtol=1e-13, atol=1e-15)
    z0 = win.prepare(*args, prev, 1, lo, hi).reshape(5, 2)
    assert z0[0, 0] == prev[1, 0]  # bit-identical inside the box
    assert win.n_nodes == 5


def test_prepare_rejects_bad_arguments_naming_them():
    model = known3()
    win = model._make_window(0.9, np.ones(2), np.ones(2), np.eye(2), False)
    win.set_data(np.zeros((3, 1)), np.zeros((3, 2)), [True] * 3, np.zeros(2))
    args = (np.zeros((4, 1)), np.zeros((4, 2)), [True] * 4, np.zeros(2))
    box = (np.full(2, -1.0), np.full(2, 1.0))
    with pytest.raises(ValueError, match="prev_window"):
        win.prepare(*args, np.zeros((3, 3)), 1, *box)
    with pytest.raises(ValueError, match="prev_window"):
        win.prepare(*args, np.full((3, 2), np.nan), 1, *box)
    with pytest.raises(ValueError, match="lower_inner"):
        win.prepare(*args, np.zeros((3, 2)), 1, np.full(2, 1.0), np.full(2, -1.0))
    assert win.n_nodes == 3  # the window's data were left as they were
    with pytest.raises(ValueError, match="x"):
        win.predict_next(np.zeros(3), np.zeros(1))

    def bad_predict(x, u):
        return np.zeros(3)

    from gpmhe import _core
    win2 = _core.MheWindow.with_callback(model.stage_eval, 2, 1, 2, 0.9, np.ones(2), np.ones(2),
                                         np.eye(2), False, predict=bad_predict)
    with pytest.raises(ValueError, match="predict"):
        win2.prepare(*args, np.zeros((3, 2)), 1, *box)
    with pytest.raises(ValueError, match="predict"):
        _core.MheWindow.with_callback(model.stage_eval, 2, 1, 2, 0.9, np.ones(2), np.ones(2),
                                      np.eye(2), False, predict=3.0)


def test_solver_step_is_prepare_then_solve():
    """WindowSolver.step (GPMHE's one Rust call per update) gives exactly prepare + solve, and in
    the filtering form the model's prediction from the last node."""
    from gpmhe import _core
    model = synthetic_learned(False)
    rng = np.random.default_rng(9)
    prev = rng.uniform(-1, 1, (4, 2))
    u, y = rng.uniform(-1, 1, (5, 1)), rng.uniform(-1, 1, (5, 2))
    lo, hi = np.full(2, -1.4), np.full(2, 1.4)
    LB, UB = np.full(10, -1.5), np.full(10, 1.5)
    for filtering in (False, True):
        args = (u, y, [True] * 5, np.zeros(2), prev, 1, lo, hi)
        w1 = model._make_window(0.9, np.full(2, 0.1), np.full(2, 0.1), np.eye(2), filtering)
        w2 = model._make_window(0.9, np.full(2, 0.1), np.full(2, 0.1), np.eye(2), filtering)
        out, x_next = _core.WindowSolver().step(w1, *args, LB, UB)
        ref = _core.WindowSolver().solve(w2, w2.prepare(*args), LB, UB)
        np.testing.assert_array_equal(out[0], ref[0])
        assert out[1:8] == ref[1:8]
        np.testing.assert_array_equal(out[8], ref[8])
        if filtering:
            np.testing.assert_array_equal(x_next, w2.predict_next(out[0][-2:], u[-1]))
        else:
            assert x_next is None


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
    win = est._core.window
    nodes = est.x_window.shape[0]
    z0 = np.clip(est.x_window.reshape(-1) + 0.05 * rng.standard_normal(2 * nodes),
                 np.tile(lb, nodes) + 1e-3, np.tile(ub, nodes) - 1e-3)
    LB, UB = np.tile(lb, nodes), np.tile(ub, nodes)
    est.solver_options = dict(ftol=1e-15, xtol=1e-15, gtol=1e-12, max_nfev=2000)
    z_ls, _, ok_ls, _ = est._solve_least_squares(win, z0, LB, UB)
    est.solver_options = dict(gtol=1e-10, xtol=1e-12, maxiter=3000)
    z_tc, _, _, _ = est._solve_trust_constr(win, z0, LB, UB)
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
