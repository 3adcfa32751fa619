"""Trial points are trials: a model that returns NaN or inf, or raises ValueError, at a point a
solver only tries rejects that step (a shorter step, more damping); the update goes on and ends
where a model defined everywhere would. Only a failure at the window's start point ends the
update, with a ValueError naming the function, and leaves the estimator as it was.

The plant: x(t+1) = 0.9 x + 0.1, y = log x + v (true x near 1). From a start far above it the
first Gauss-Newton step on log x lands at x < 0, where log is NaN (numpy), raises ValueError
(``math.log``) or is NaN (CasADi)."""

import math
import warnings

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from gpmhe import GPMHE, KnownModel

SOLVERS = ["gauss-newton", "least-squares", "trust-constr"]


def _data(steps=25, seed=0):
    rng = np.random.default_rng(seed)
    x, ys = 1.0, []
    for _ in range(steps):
        ys.append(math.log(x) + 0.05 * rng.standard_normal())
        x = 0.9 * x + 0.1
    return ys


class Counted:
    """h = log x, counting the calls at x <= 0 (so a test can check that trials went there)."""

    def __init__(self, kind):
        self.kind, self.outside = kind, 0

    def __call__(self, X, U):
        if np.any(np.asarray(X) <= 0):
            self.outside += 1
        if self.kind == "math":
            return [math.log(X[0])]  # ValueError: math domain error at x <= 0
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.log(X)


def _model(kind):
    h = Counted(kind)
    if kind == "vectorized":
        return KnownModel(lambda X, U: 0.9 * X + 0.1, h, dim_x=1, dim_y=1, vectorized=True), h
    return KnownModel(lambda x, u: 0.9 * x + 0.1, h, dim_x=1, dim_y=1), h


def _run(model, solver, x0, ys):
    est = GPMHE(model, horizon=5, x0=[x0], Q0=1e-2 * np.eye(1), R0=2.5e-3 * np.eye(1), P0=np.eye(1),
                solver=solver)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # SciPy's own notes on rejected points
        xs = [est.update(None, [y]) for y in ys]
    return est, np.array(xs)


@pytest.mark.parametrize("kind", ["numpy", "math", "vectorized"])
@pytest.mark.parametrize("solver", SOLVERS)
def test_a_trial_outside_the_model_domain_is_rejected(kind, solver):
    ys = _data()
    model, h = _model(kind)
    est, xs = _run(model, solver, 10.0, ys)
    assert h.outside > 0, "no trial left the domain: the test proves nothing"
    assert est.success and np.all(np.isfinite(xs))
    # The same problem from a start inside the domain's well-behaved region never leaves it and
    # ends at the same estimates.
    ref_model, ref_h = _model(kind)
    _, ref = _run(ref_model, solver, 1.0, ys)
    assert ref_h.outside == 0
    np.testing.assert_allclose(xs[-10:], ref[-10:], atol=2e-4)


def test_a_casadi_model_rejects_the_trial_too():
    ca = pytest.importorskip("casadi")
    x = ca.SX.sym("x", 1)
    f = ca.Function("f", [x], [0.9 * x + 0.1])
    h = ca.Function("h", [x], [ca.log(x)])
    ys = _data()
    _, xs = _run(KnownModel.from_casadi(f, h), "gauss-newton", 10.0, ys)
    _, ref = _run(KnownModel.from_casadi(f, h), "gauss-newton", 1.0, ys)
    assert np.all(np.isfinite(xs))
    np.testing.assert_allclose(xs[-10:], ref[-10:], atol=2e-4)


@settings(max_examples=15, deadline=None)
@given(x0=st.floats(0.05, 50.0), seed=st.integers(0, 2**16))
def test_no_start_makes_an_update_fail(x0, seed):
    model, _ = _model("numpy")
    est, xs = _run(model, "gauss-newton", x0, _data(12, seed))
    assert np.all(np.isfinite(xs)) and np.all(xs > 0)


@pytest.mark.parametrize("kind", ["numpy", "math"])
def test_a_failure_at_the_start_point_is_an_error_and_changes_nothing(kind):
    """An input where f cannot be evaluated at any state (u < 0 under a square root) makes the
    window's start point fail: a ValueError naming f, the estimator unchanged."""

    def f(x, u):
        return x * (math.sqrt(u[0]) if kind == "math" else np.sqrt(u[0]))

    model = KnownModel(f, lambda x, u: x, dim_x=1, dim_y=1, dim_u=1)
    est = GPMHE(model, horizon=3, x0=[1.0], Q0=np.eye(1), R0=1e-2 * np.eye(1), P0=np.eye(1))
    est.update([1.0], [1.0])
    est.update([1.0], [1.1])
    t, x, window = est.t, est.x.copy(), est.x_window.copy()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        with pytest.raises(ValueError, match=r"^f: "):
            est.update([-1.0], [1.0])
    assert est.t == t and np.array_equal(est.x, x) and np.array_equal(est.x_window, window)
    est.update([1.0], [1.0])  # and it goes on
    assert est.t == t + 1
