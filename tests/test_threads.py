"""Threads: the heavy calls release the GIL, so estimators in different threads run in parallel
and give exactly the serial results; one estimator used from two threads at once raises a clear
RuntimeError in the second caller and stays consistent."""

import threading
import time

import numpy as np
import pytest

from gpmhe import GPMHE, KnownModel
from gpmhe.systems import batch_reactor as br

from conftest import fitted_reactor_model

STEPS = 60


@pytest.fixture(scope="module")
def learned():
    return fitted_reactor_model(11, n_restarts=1)


def outputs(seed):
    return br.simulate(br.X_TRUE0, STEPS, np.random.default_rng(seed))[1]


def run(model, ys):
    mhe = GPMHE(model, x0=[3.0, 1.0], x_bounds=br.X_BOUNDS, **br.MHE_SETTINGS)
    xs, Ps = mhe.batch_filter(ys)
    return xs, Ps, mhe.cost


def run_in_threads(jobs):
    results, errors = [None] * len(jobs), []
    barrier = threading.Barrier(len(jobs))

    def work(i, fn):
        try:
            barrier.wait()
            results[i] = fn()
        except BaseException as e:  # reported below
            errors.append(e)

    threads = [threading.Thread(target=work, args=(i, fn)) for i, fn in enumerate(jobs)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors
    return results


def test_two_estimators_in_two_threads_give_the_serial_results(learned):
    ys = [outputs(1), outputs(2)]
    serial = [run(learned, y) for y in ys]
    parallel = run_in_threads([lambda y=y: run(learned, y) for y in ys])
    for s, p in zip(serial, parallel):
        for a, b in zip(s, p):
            np.testing.assert_array_equal(a, b)


class RecordingCore:
    """Forwards to the estimator's Rust core and records the y of each update it completes, in
    the order the core recorded them."""

    def __init__(self, core):
        self.core, self.ys = core, []

    def update(self, u, y=None, r=None, u_last=None):
        rep = self.core.update(u, y, r, u_last)
        self.ys.append(y)
        return rep

    def __getattr__(self, name):
        return getattr(self.core, name)


def test_one_estimator_from_two_threads_raises_a_clear_error_and_stays_consistent(learned):
    ys = outputs(3)
    shared = GPMHE(learned, x0=[3.0, 1.0], x_bounds=br.X_BOUNDS, **br.MHE_SETTINGS)
    shared._core = recorder = RecordingCore(shared._core)
    refused = []

    def hammer():
        for y in ys:
            try:
                shared.update(None, y)
            except RuntimeError as e:
                refused.append(str(e))

    run_in_threads([hammer, hammer])
    for msg in refused:
        assert "GPMHE is in use by another thread" in msg
    # every update that returned was recorded once, and the estimator is consistent: it equals a
    # fresh estimator fed the accepted updates in the order they were recorded
    assert shared.t == len(recorder.ys) == 2 * len(ys) - len(refused)
    fresh = GPMHE(learned, x0=[3.0, 1.0], x_bounds=br.X_BOUNDS, **br.MHE_SETTINGS)
    fresh.batch_filter(recorder.ys)
    for a in ("x", "P", "x_window", "cost"):
        np.testing.assert_array_equal(getattr(fresh, a), getattr(shared, a), err_msg=a)


def test_update_from_inside_its_own_model_callback_is_refused():
    holder = {}

    def f(x, u=None):
        if "reenter" in holder:
            del holder["reenter"]
            holder["mhe"].update(None, [1.0])
        return br.f(x)

    mhe = GPMHE(KnownModel(f, br.h, 2, 1), x0=[3.0, 1.0], x_bounds=br.X_BOUNDS, **br.MHE_SETTINGS)
    holder["mhe"] = mhe
    mhe.update(None, [1.0])
    x, t = mhe.x.copy(), mhe.t
    holder["reenter"] = True
    with pytest.raises(RuntimeError, match="already updating in this thread"):
        mhe.update(None, [1.0])
    assert mhe.t == t
    np.testing.assert_array_equal(mhe.x, x)


def test_a_long_gp_prediction_releases_the_gil(learned):
    # While another thread predicts at many points, this thread keeps running Python code.
    gp = learned.f_gp
    D = np.random.default_rng(4).uniform(0.1, 4.5, size=(100_000, gp.dim))  # ~0.3 s
    worker = threading.Thread(target=gp.predict, args=(D,), kwargs=dict(return_std=True))
    ticks = 0
    worker.start()
    while worker.is_alive():
        ticks += 1
        time.sleep(0.0005)
    worker.join()
    # with the GIL held for the whole prediction this loop could not run during it
    assert ticks >= 50, ticks  # (~600 here with the GIL released)


def test_estimators_sharing_one_casadi_model_in_two_threads_give_the_serial_results():
    """One KnownModel.from_casadi model shared by two estimators, each updated in a thread of its
    own. The core reads the model's results after its callback returned; here each callback
    yields the GIL as it returns (what a thread switch at the end of the callback does, rarely,
    by itself), so another thread's callback runs in between: each thread must have result
    buffers of its own. Every run equals the serial run bit for bit."""
    ca = pytest.importorskip("casadi")
    import time

    from gpmhe import GPMHE, KnownModel
    from gpmhe.systems import batch_reactor as br

    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 0)
    k1, k2 = 0.16, 0.0064
    f = ca.Function("f", [x, u], [x + 0.1 * ca.vertcat(-2 * k1 * x[0] ** 2 + 2 * k2 * x[1],
                                                         k1 * x[0] ** 2 - k2 * x[1])])
    h = ca.Function("h", [x, u], [x[0] + x[1]])
    model = KnownModel.from_casadi(f, h)
    casadi_model = model._casadi
    for name in ("stage_callback", "predict_callback"):
        def yielding(*args, _call=getattr(casadi_model, name)):
            result = _call(*args)
            time.sleep(0)  # let the other thread run before the core reads the result
            return result
        setattr(casadi_model, name, yielding)
    ys = [br.simulate(br.X_TRUE0, 40, np.random.default_rng(s))[1] for s in (0, 1)]

    def run(i, out):
        est = GPMHE(model, x0=[3.0, 1.0], horizon=8, Q0=1e-3, R0=1e-2, x_bounds=br.X_BOUNDS)
        out[i] = np.array([est.update(None, y).copy() for y in ys[i]])

    serial = {}
    run(0, serial)
    run(1, serial)
    for _ in range(5):
        got = {}
        threads = [threading.Thread(target=run, args=(i, got)) for i in (0, 1)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        for i in (0, 1):
            np.testing.assert_array_equal(got[i], serial[i])
