"""KnownModel with vectorised callables (`vectorized=True`) against the per-point form: the same
stage evaluations, window cost/gradient and estimates on the batch reactor and on a synthetic
system with an input and two outputs; vectorised finite differences against analytic Jacobians;
bad shapes / NaN from each callable raise ValueError naming it and leave the estimator as it was."""

import copy
import warnings

import numpy as np
import pytest

from gpmhe import GPMHE, KnownModel, _core
from gpmhe.systems import batch_reactor as br

from conftest import f3, f3_jac, f3_jac_v, f3_v, h3, h3_jac, h3_jac_v, h3_v, reactor_known_model


# ---- the reactor and the synthetic system with m = 1, p = 2 (tests/conftest.py) -------------
reactor = reactor_known_model


def synthetic(vectorized, jacobians=True):
    fns = (f3_v, h3_v, f3_jac_v, h3_jac_v) if vectorized else (f3, h3, f3_jac, h3_jac)
    jac = dict(f_jacobian=fns[2], h_jacobian=fns[3]) if jacobians else {}
    return KnownModel(fns[0], fns[1], 2, 2, dim_u=1, vectorized=vectorized, **jac)


SYSTEMS = {"reactor": (reactor, 0), "synthetic": (synthetic, 1)}


def points(m, k=16, seed=0):
    return np.random.default_rng(seed).uniform(0.1, 4.5, (k, 2 + m))


@pytest.mark.parametrize("jacobians", [True, False])
@pytest.mark.parametrize("system", sorted(SYSTEMS))
def test_stage_eval_matches_the_per_point_form(system, jacobians):
    make, m = SYSTEMS[system]
    for k in (1, 16):
        d = points(m, k)
        per_point = make(False, jacobians).stage_eval(d)
        vec = make(True, jacobians).stage_eval(d)
        for a, b in zip(per_point, vec):
            assert a.shape == b.shape and b.dtype == np.float64 and b.flags.c_contiguous
            np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("system", sorted(SYSTEMS))
def test_vectorised_finite_differences_match_analytic_jacobians(system):
    make, m = SYSTEMS[system]
    d = points(m, 16, seed=3)
    exact = make(True, True).stage_eval(d)
    fd = make(True, False).stage_eval(d)
    assert np.any(exact[2] != fd[2])  # really differenced, not the analytic Jacobian
    for i in (2, 6):  # dmean_x, dmean_y
        np.testing.assert_allclose(fd[i], exact[i], rtol=1e-6, atol=1e-6)
    for i in (0, 4):
        np.testing.assert_array_equal(fd[i], exact[i])


@pytest.mark.parametrize("form", ["prediction", "filtering"])
@pytest.mark.parametrize("system", sorted(SYSTEMS))
def test_window_cost_and_gradient_match(system, form):
    make, m = SYSTEMS[system]
    rng = np.random.default_rng(7)
    nodes = 6
    wins = []
    for vectorized in (False, True):
        model = make(vectorized)
        p = model.dim_y
        win = _core.MovingHorizon(model._stage_model(), 0.9, np.array([1e-2, 2e-2]), np.full(p, 3e-2),
                                 np.array([[1.2, 0.3], [0.0, 1.0]]), form == "filtering")
        wins.append(win)
    u = rng.uniform(-1, 1, (nodes, m))
    y = rng.uniform(0, 5, (nodes, p))
    present = [True, False, True, True, True, True]
    for win in wins:
        win.set_data(u, y, present, np.array([2.0, 1.0]))
    z = rng.uniform(0.1, 4.5, nodes * 2)
    (c0, g0), (c1, g1) = (w.cost_grad(z) for w in wins)
    assert c1 == pytest.approx(c0, rel=1e-12)
    np.testing.assert_allclose(g1, g0, rtol=1e-12, atol=1e-12 * np.abs(g0).max())
    np.testing.assert_allclose(wins[1].jacobian(z), wins[0].jacobian(z), rtol=1e-12, atol=1e-12)


def run(model, ys, us=None, form="prediction", x0=br.X_PRIOR0, bounds=br.X_BOUNDS, **kw):
    est = GPMHE(model, x0, x_bounds=bounds, form=form, **{**br.MHE_SETTINGS, **kw})
    xs, Ps = est.batch_filter(ys, us)
    return est, xs, Ps


@pytest.mark.parametrize("jacobians", [True, False])
def test_batch_reactor_estimates_match(jacobians):
    x, y = br.simulate(br.X_TRUE0, 30, np.random.default_rng(2))
    _, xs0, Ps0 = run(reactor(False, jacobians), y[:30])
    est, xs1, Ps1 = run(reactor(True, jacobians), y[:30])
    assert est.solver == "gauss-newton"
    np.testing.assert_allclose(xs1, xs0, rtol=0, atol=1e-9)
    np.testing.assert_allclose(Ps1, Ps0, rtol=1e-9, atol=1e-12)
    assert np.sqrt(np.mean(np.sum((xs1[19:] - x[20:31]) ** 2, axis=1))) < 0.5  # it estimates


@pytest.mark.parametrize("form", ["prediction", "filtering"])
def test_system_with_input_estimates_match(form):
    rng = np.random.default_rng(4)
    T = 12
    us = rng.uniform(-1, 1, (T, 1))
    x = np.empty((T + 1, 2))
    x[0] = [0.5, -0.3]
    for t in range(T):
        x[t + 1] = f3(x[t], us[t]) + 0.01 * rng.standard_normal(2)
    ys = np.array([h3(x[t], us[t]) for t in range(T)]) + 0.05 * rng.standard_normal((T, 2))
    kw = dict(x0=np.zeros(2), bounds=(np.full(2, -3.0), np.full(2, 3.0)), horizon=5,
              P2=np.eye(2), Q0=1e-4 * np.eye(2), R0=2.5e-3 * np.eye(2), form=form)
    _, xs0, _ = run(synthetic(False, False), ys, us, **kw)
    _, xs1, _ = run(synthetic(True, False), ys, us, **kw)
    np.testing.assert_allclose(xs1, xs0, rtol=0, atol=1e-9)
    truth = x[1:] if form == "prediction" else x[:T]
    assert np.max(np.abs(xs1[-4:] - truth[-4:])) < 0.2


def test_predict_both_modes_and_options():
    for model in (reactor(False), reactor(True)):
        np.testing.assert_array_equal(model.predict([3.0, 1.0]), br.f(np.array([3.0, 1.0])))
        assert copy.deepcopy(model) is model and copy.copy(model) is model
    for model in (synthetic(False), synthetic(True)):
        np.testing.assert_allclose(model.predict([0.3, 0.2], [0.5]), f3([0.3, 0.2], [0.5]),
                                   rtol=1e-15)
    assert reactor(True).vectorized and not reactor(False).vectorized
    with pytest.raises(ValueError, match="vectorized"):
        KnownModel(br.f_batch, br.h_batch, 2, 1, vectorized="yes")


class Faulty:
    """The vectorised reactor model whose callable `name` misbehaves (`fault`) while `on` is set,
    only on window evaluations (k > 1: `predict` in the warm start calls f with k = 1)."""

    def __init__(self, name, fault):
        self.name, self.fault, self.on = name, fault, False
        good = dict(f=br.f_batch, h=br.h_batch, f_jacobian=br.f_jacobian_batch,
                    h_jacobian=br.h_jacobian_batch)
        wrapped = {key: self._wrap(key, fn) for key, fn in good.items()}
        self.model = KnownModel(wrapped["f"], wrapped["h"], 2, 1, vectorized=True,
                                f_jacobian=wrapped["f_jacobian"], h_jacobian=wrapped["h_jacobian"])

    def _wrap(self, key, fn):
        def call(X, U):
            out = fn(X, U)
            if not (self.on and key == self.name and len(X) > 1):
                return out
            if self.fault == "nan":
                out = out.copy()
                out[-1, 0] = np.nan
                return out
            if self.fault == "transposed":
                return np.ascontiguousarray(np.swapaxes(out, 0, 1))
            return out[:-1]  # one row short
        return call


@pytest.mark.parametrize("fault", ["nan", "transposed", "short"])
@pytest.mark.parametrize("name", ["f", "h", "f_jacobian", "h_jacobian"])
def test_bad_callable_output_raises_and_leaves_the_estimator_unchanged(name, fault):
    faulty = Faulty(name, fault)
    d = points(0, 5)
    faulty.on = True
    with pytest.raises(ValueError, match=f"^{name}: returned"):
        faulty.model.stage_eval(d)
    faulty.on = False

    x, y = br.simulate(br.X_TRUE0, 8, np.random.default_rng(5))
    est = GPMHE(faulty.model, br.X_PRIOR0, x_bounds=br.X_BOUNDS, **br.MHE_SETTINGS)
    for t in range(4):
        est.update(None, y[t])
    before = (est.x.copy(), est.x_window.copy(), est.P.copy(), est.t, est.cost)
    faulty.on = True
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a clean failure: no "did not converge" warning either
        with pytest.raises(ValueError, match=f"^{name}: returned"):
            est.update(None, y[4])
    np.testing.assert_array_equal(est.x, before[0])
    np.testing.assert_array_equal(est.x_window, before[1])
    np.testing.assert_array_equal(est.P, before[2])
    assert (est.t, est.cost) == before[3:]
    # ... and it carries on as if the failed call had not happened
    faulty.on = False
    ref = GPMHE(reactor(True), br.X_PRIOR0, x_bounds=br.X_BOUNDS, **br.MHE_SETTINGS)
    for t in range(6):
        ref.update(None, y[t])
    for t in range(4, 6):
        est.update(None, y[t])
    np.testing.assert_allclose(est.x, ref.x, rtol=0, atol=1e-12)


def test_finite_difference_errors_and_predict_name_the_callable():
    bad = KnownModel(lambda X, U: np.full((len(X), 2), np.nan), br.h_batch, 2, 1, vectorized=True)
    with pytest.raises(ValueError, match="^f: returned NaN"):
        bad.predict([1.0, 1.0])
    with pytest.raises(ValueError, match="^f: returned NaN"):
        bad.stage_eval(points(0, 3))

    def nan_off_centre(X, U):  # finite at the points, NaN at the shifted copies
        out = br.h_batch(X)
        out[3:] = np.nan
        return out
    bad = KnownModel(br.f_batch, nan_off_centre, 2, 1, vectorized=True)
    with pytest.raises(ValueError, match=r"^h \(finite differences\): returned NaN"):
        bad.stage_eval(points(0, 3))
    per_point = KnownModel(br.f, lambda x, u: np.array([np.inf]), 2, 1)
    with pytest.raises(ValueError, match="^h: returned NaN"), np.errstate(invalid="ignore"):
        per_point.stage_eval(points(0, 3))
    wrong_rows = KnownModel(lambda X, U: br.f_batch(X)[:1], br.h_batch, 2, 1, vectorized=True)
    with pytest.raises(ValueError, match=r"^f: returned shape \(1, 2\), expected \(15, 2\) .*the 3 points and "
                       r"their 12 finite-difference shifts"):
        wrong_rows.stage_eval(points(0, 3))


@pytest.mark.parametrize("dim_u", [0, 1])
def test_no_outputs(dim_u):
    """dim_y = 0: h is never called; both modes agree on the stage evaluation and a short run."""
    def never(*args):
        raise AssertionError("h called with dim_y = 0")
    per_point = KnownModel(lambda x, u: br.f(x), never, 2, 0, dim_u=dim_u)
    vec = KnownModel(lambda X, U: br.f_batch(X), never, 2, 0, dim_u=dim_u, vectorized=True)
    d = points(dim_u, 7)
    for a, b in zip(per_point.stage_eval(d), vec.stage_eval(d)):
        assert a.shape == b.shape
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12)
    us = np.zeros((5, dim_u))
    xs = [GPMHE(model, br.X_PRIOR0, x_bounds=br.X_BOUNDS, horizon=3, Q0=1e-3)
          .batch_filter([None] * 5, us if dim_u else None)[0] for model in (per_point, vec)]
    np.testing.assert_allclose(xs[1], xs[0], rtol=0, atol=1e-9)
