"""The robust output penalties (``loss="huber"`` / ``"cauchy"``): the window cost against a numpy
implementation of Σ ρ(e) and finite differences, the solvers against each other, the squared
loss as the limit, the effect on an outlier, and the setting's way through copies, pickles,
checkpoints and banks."""

import copy
import pickle

import numpy as np
import pytest

from gpmhe import GPMHE, EstimatorBank, KnownModel, _core
from gpmhe.mhe import solvers

from conftest import check_window_derivatives, f3, h3, linear_model, synthetic_learned_model


def rho(loss, k, e):
    """The penalty of a whitened residual e, as the user guide defines it."""
    if loss == "huber":
        return np.where(np.abs(e) <= k, e * e, 2 * k * np.abs(e) - k * k)
    if loss == "cauchy":
        return k * k * np.log1p(e * e / (k * k))
    return e * e


def robust_cost(model, z, u, y, present, x_prior, P2, q0, R0, eta, form, loss, k):
    """The window cost written out with ρ on the whitened output residuals L⁻¹v̄ (L Lᵀ = diag
    σ²_y + R0)."""
    n = model.dim_x
    X = z.reshape(-1, n)
    Mt = X.shape[0] - 1
    dx = X[0] - x_prior
    J = 2 * eta**Mt * dx @ P2 @ dx

    def output(i, weight):
        _, _, _, _, my, vy, _, _ = model.stage_eval(np.concatenate([X[i], u[i]])[None])
        e = np.linalg.solve(np.linalg.cholesky(np.diag(vy[0]) + R0), y[i] - my[0])
        return weight * np.sum(rho(loss, k, e))

    for j in range(1, Mt + 1):
        i = Mt - j
        mx, vx, _, _, _, _, _, _ = model.stage_eval(np.concatenate([X[i], u[i]])[None])
        w = X[i + 1] - mx[0]
        J += 2 * eta ** (j - 1) * w @ np.linalg.solve(np.diag(vx[0] + q0), w)
        if present[i]:
            J += output(i, 2 * eta ** (j - 1))
    if form == "filtering" and present[Mt]:
        J += output(Mt, 2.0)
    return J


@pytest.mark.parametrize("form", ["prediction", "filtering"])
@pytest.mark.parametrize("loss", ["huber", "cauchy"])
@pytest.mark.parametrize("full_r0", [False, True])
@pytest.mark.parametrize("kind", ["known", "learned"])
def test_window_cost_is_the_robust_cost(form, loss, full_r0, kind):
    """Cost, residuals, gradient and Jacobian of a window with residuals on both sides of k."""
    model = (KnownModel(f3, h3, dim_x=2, dim_y=2, dim_u=1) if kind == "known"
             else synthetic_learned_model(60, False))
    rng = np.random.default_rng(11)
    nodes, k = 6, 0.7
    P2 = np.array([[2.0, 0.3], [0.3, 1.0]])
    q0 = np.array([1e-2, 2e-2])
    R0 = np.array([[3e-2, 1e-2], [1e-2, 2e-2]]) if full_r0 else np.diag([3e-2, 1e-2])
    r0 = R0.reshape(-1) if full_r0 else np.diag(R0).copy()
    S = np.ascontiguousarray(np.linalg.cholesky(P2).T)
    win = _core.MovingHorizon(model._stage_model(), 0.9, q0, r0, S, form == "filtering",
                              loss=loss, loss_scale=k)
    u = rng.uniform(-1, 1, (nodes, 1))
    y = rng.uniform(-1, 1, (nodes, 2))
    y[2, 0] = np.nan  # one channel not measured
    present = [True, False, True, True, True, True]
    x_prior = np.array([0.2, -0.3])
    win.set_data(u, y, present, x_prior)
    z = rng.uniform(-1, 1, nodes * 2)

    def ref_cost(z):
        """Node 2 has one measured channel: the other nodes by `robust_cost`, node 2 alone."""
        pres = list(present)
        pres[2] = False
        total = robust_cost(model, z, u, y, pres, x_prior, P2, q0, R0, 0.9, form, loss, k)
        X = z.reshape(-1, 2)
        _, _, _, _, my, vy, _, _ = model.stage_eval(np.concatenate([X[2], u[2]])[None])
        e = (y[2, 1] - my[0, 1]) / np.sqrt(vy[0, 1] + R0[1, 1])
        return total + 2 * 0.9 ** (nodes - 1 - 3) * rho(loss, k, e)

    r = win.residuals(z)
    whitened = np.abs(r[2:]) / np.sqrt(2)
    assert win.cost(z) == pytest.approx(ref_cost(z), rel=1e-10)
    assert r @ r == pytest.approx(win.cost(z), rel=1e-12)
    check_window_derivatives(win, z)
    assert whitened.max() > 3 * k  # the data put residuals well beyond the scale


A = np.array([[1.0, 0.1], [-0.2, 0.95]])
C = np.array([[1.0, 0.0]])


def linear_plant(steps, rng, outliers=()):
    """x(t+1) = A x + w, y = x_0 + v (σ_v = 0.1), with 20σ outliers at the given times."""
    x = np.zeros((steps + 1, 2))
    x[0] = [1.0, 0.0]
    for t in range(steps):
        x[t + 1] = A @ x[t] + 0.02 * rng.standard_normal(2)
    y = x[:steps, :1] + 0.1 * rng.standard_normal((steps, 1))
    for t in outliers:
        y[t] += 2.0
    return linear_model(A, C), x, y


def run(est, y):
    xs, Ps = [], []
    for t in range(len(y)):
        xs.append(est.update(None, y[t]).copy())
        Ps.append(est.P.copy())
    return np.array(xs), np.array(Ps)


@pytest.mark.parametrize("form", ["prediction", "filtering"])
def test_a_huber_scale_beyond_every_residual_is_the_squared_loss_bit_for_bit(form):
    model, _, y = linear_plant(40, np.random.default_rng(1))
    kw = dict(x0=[0.0, 0.0], horizon=6, Q0=4e-4, R0=1e-2, form=form)
    x_sq, P_sq = run(GPMHE(model, **kw), y)
    x_hu, P_hu = run(GPMHE(model, loss="huber", loss_scale=1e9, **kw), y)
    np.testing.assert_array_equal(x_sq, x_hu)
    np.testing.assert_array_equal(P_sq, P_hu)
    explicit, _ = run(GPMHE(model, loss="squared", **kw), y)
    np.testing.assert_array_equal(x_sq, explicit)


@pytest.mark.parametrize("loss", ["huber", "cauchy"])
def test_an_outlier_moves_a_robust_estimate_far_less(loss):
    """One 20σ outlier: the squared loss follows it, the robust ones stay near the estimate
    without it."""
    steps, at = 40, 25
    model, _, clean = linear_plant(steps, np.random.default_rng(2))
    _, _, dirty = linear_plant(steps, np.random.default_rng(2), outliers=[at])
    kw = dict(x0=[1.0, 0.0], horizon=8, Q0=4e-4, R0=1e-2, form="filtering")
    ref, _ = run(GPMHE(model, loss=loss, **kw), clean)
    robust, _ = run(GPMHE(model, loss=loss, **kw), dirty)
    squared, _ = run(GPMHE(model, **kw), dirty)
    plain, _ = run(GPMHE(model, **kw), clean)
    jump_sq = np.abs(squared[at] - plain[at]).max()
    jump_rb = np.abs(robust[at] - ref[at]).max()
    assert jump_sq > 0.1
    assert jump_rb < 0.25 * jump_sq


def test_scipy_paths_reach_the_gauss_newton_window_optimum():
    """The robust window solved by the Rust solver and by SciPy's least-squares: same cost."""
    model, _, y = linear_plant(30, np.random.default_rng(3), outliers=[20, 24])
    kw = dict(x0=[1.0, 0.0], horizon=10, Q0=4e-4, R0=1e-2, loss="cauchy",
              solver_options=dict(dtol=0.0, gtol=1e-10))
    est = GPMHE(model, **kw)
    run(est, y)
    win = est._core
    z0 = est.x_window.reshape(-1) + 0.05
    lb, ub = np.full(z0.size, -np.inf), np.full(z0.size, np.inf)
    z_ls, _, ok, _, _ = solvers.solve("least-squares", dict(ftol=1e-15, xtol=1e-15, gtol=1e-14,
                                                            max_nfev=2000), win, z0, lb, ub)
    assert ok
    assert win.cost(z_ls) == pytest.approx(win.cost(est.x_window.reshape(-1)), rel=1e-8)


def test_settings_are_checked_and_read_only():
    model, _, _ = linear_plant(2, np.random.default_rng(0))
    est = GPMHE(model, [0, 0], loss="cauchy")
    assert (est.loss, est.loss_scale) == ("cauchy", 2.385)
    assert (GPMHE(model, [0, 0]).loss, GPMHE(model, [0, 0]).loss_scale) == ("squared", 1.0)
    with pytest.raises(AttributeError):
        est.loss = "huber"
    for kw, name in [(dict(loss="l1"), "loss"), (dict(loss="huber", loss_scale=0.0), "loss_scale"),
                     (dict(loss="huber", loss_scale=np.inf), "loss_scale"),
                     (dict(loss="huber", loss_scale="1"), "loss_scale"),
                     (dict(loss_scale=2.0), "loss_scale")]:
        with pytest.raises(ValueError, match=name):
            GPMHE(model, [0, 0], **kw)


def test_the_loss_survives_copies_pickles_checkpoints_and_banks(tmp_path):
    model, _, y = linear_plant(30, np.random.default_rng(4), outliers=[5, 12])
    kw = dict(horizon=5, Q0=4e-4, R0=1e-2, loss="huber", loss_scale=1.1)
    est = GPMHE(model, [1.0, 0.0], **kw)
    run(est, y[:15])
    twins = [copy.deepcopy(est), pickle.loads(pickle.dumps(est))]
    est.save(tmp_path / "c.npz")
    twins.append(GPMHE.load(tmp_path / "c.npz", model))
    rest, _ = run(est, y[15:])
    for twin in twins:
        assert (twin.loss, twin.loss_scale) == ("huber", 1.1)
        np.testing.assert_array_equal(run(twin, y[15:])[0], rest)
    bank = EstimatorBank(model, 2, [1.0, 0.0], arrival_mean="estimate", **kw)
    for t in range(30):
        bank.update(None, np.tile(y[t], (2, 1)))
    alone, _ = run(GPMHE(model, [1.0, 0.0], arrival_mean="estimate", **kw), y)
    np.testing.assert_array_equal(bank.x[1], alone[-1])
    again = pickle.loads(pickle.dumps(bank))
    assert (again.loss, again.loss_scale, again.arrival_mean) == ("huber", 1.1, "estimate")
    assert bank[0].loss == "huber"


def test_scipys_own_loss_is_refused_by_the_least_squares_reference_solver():
    # SciPy's loss would robustify the prior and process rows too: another cost than the
    # window's, which GPMHE's loss= defines for every solver.
    model = KnownModel(lambda x, u: x, lambda x, u: x, dim_x=1, dim_y=1)
    for key, value in (("loss", "huber"), ("f_scale", 2.0)):
        with pytest.raises(ValueError, match=f"solver_options: '{key}' is not accepted.*loss="):
            GPMHE(model, [0.0], Q0=1.0, R0=1.0, solver="least-squares",
                  solver_options={key: value})
    est = GPMHE(model, [0.0], Q0=1.0, R0=1.0, solver="least-squares", loss="huber",
                solver_options={"x_scale": "jac"})
    est.update(None, [5.0])
    assert est.success
