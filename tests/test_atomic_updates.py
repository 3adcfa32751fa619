"""Atomic updates: a Ctrl-C (SIGINT from a timer thread) landing anywhere in a tight update loop
leaves the estimator exactly as after some whole number of updates. It then continues bit for bit
like a twin that was never interrupted and given the same data, and its checkpoint loads and
continues the same way. Covers GPMHE on a learned model (the core runs without the GIL and checks
for signals), on a learned model that keeps learning, on a known model (signals land in the
Python model functions), on the SciPy solver path, and the parallel EstimatorBank."""

import io
import signal
import threading

import numpy as np
import pytest

from gpmhe import GPMHE, EstimatorBank, KnownModel, LearnedModel
from gpmhe.systems import batch_reactor as br

ATTRS = ("t", "x", "P", "x_window", "x_arrival", "cost", "success", "nit", "nfev",
         "projected_gradient", "message")
TRIES = 40


def snapshot(est):
    return {a: np.array(getattr(est, a), copy=True) for a in ATTRS if hasattr(est, a)}


def assert_twins(a, b):
    sa, sb = snapshot(a), snapshot(b)
    for key in sa:
        np.testing.assert_array_equal(sa[key], sb[key], err_msg=key)


@pytest.fixture(scope="module")
def outputs():
    return br.simulate(br.X_TRUE0, 400, np.random.default_rng(3))[1][:, 0]


@pytest.fixture(autouse=True)
def ctrl_c_raises_keyboard_interrupt():
    """Python's own SIGINT handler, whatever the process inherited (a process started in the
    background may have SIGINT ignored)."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def run_until_interrupted(step, rng):
    """Runs `step()` in a loop until a SIGINT sent after a random delay stops it."""
    timer = threading.Timer(rng.uniform(0.0, 0.02), signal.pthread_kill,
                            (threading.main_thread().ident, signal.SIGINT))
    try:
        timer.start()  # (on a busy machine the signal can come before start returns)
        while True:
            step()
    except KeyboardInterrupt:
        pass
    finally:
        timer.cancel()
        while True:  # a loop ended by another error: its signal may still be on the way
            try:
                timer.join()
                break
            except KeyboardInterrupt:
                pass


def interrupted_like_a_twin(make, feed, rng, tries=TRIES):
    """Interrupts one estimator `tries` times, catching a twin up after each; returns both."""
    est, twin = make(), make()
    for _ in range(tries):
        run_until_interrupted(lambda: feed(est), rng)
        assert twin.t <= est.t
        while twin.t < est.t:
            feed(twin)
        assert_twins(est, twin)
    for _ in range(5):
        feed(est)
        feed(twin)
    assert_twins(est, twin)
    return est, twin


def learned_mhe(reactor_model, **options):
    return GPMHE(reactor_model, x0=[3.0, 1.0], x_bounds=br.X_BOUNDS,
                 **{**br.MHE_SETTINGS, **options})


def feeder(outputs):
    def feed(est):
        est.update(None, [outputs[est.t % len(outputs)]])
    return feed


@pytest.mark.parametrize("form", ["prediction", "filtering"])
def test_interrupted_learned_gp_mhe_continues_like_its_twin_and_checkpoints(
        reactor_model, outputs, form):
    rng = np.random.default_rng(0)
    feed = feeder(outputs)
    est, twin = interrupted_like_a_twin(lambda: learned_mhe(reactor_model, form=form), feed, rng)
    buf = io.BytesIO()
    est.save(buf)
    buf.seek(0)
    loaded = GPMHE.load(buf, reactor_model)
    assert_twins(loaded, est)
    for _ in range(5):
        feed(loaded)
        feed(twin)
    assert_twins(loaded, twin)


def test_interrupted_learning_gp_mhe_continues_like_its_twin_and_checkpoints(outputs):
    states, outs = br.training_data(5, rng=0)
    model = LearnedModel.from_trajectories(states, outs, n_inducing=12)
    rng = np.random.default_rng(1)
    feed = feeder(outputs)
    make = lambda: learned_mhe(model, form="filtering", learning=True,  # noqa: E731
                               learning_options={"drift": 1e-9})
    est, twin = interrupted_like_a_twin(make, feed, rng, tries=20)
    for a, b in zip(est._core.learning, twin._core.learning):
        np.testing.assert_array_equal(a, b)
    buf = io.BytesIO()
    est.save(buf)
    buf.seek(0)
    loaded = GPMHE.load(buf, model)
    for _ in range(5):
        feed(loaded)
        feed(twin)
    assert_twins(loaded, twin)
    for a, b in zip(loaded._core.learning, twin._core.learning):
        np.testing.assert_array_equal(a, b)


def test_interrupted_known_model_mhe_continues_like_its_twin():
    model = KnownModel(br.f, br.h, 2, 1, f_jacobian=br.f_jacobian, h_jacobian=br.h_jacobian)
    ys = br.simulate(br.X_TRUE0, 100, np.random.default_rng(4))[1][:, 0]
    interrupted_like_a_twin(
        lambda: GPMHE(model, x0=[3.0, 1.0], x_bounds=br.X_BOUNDS, **br.MHE_SETTINGS),
        feeder(ys), np.random.default_rng(1))


def test_interrupted_scipy_solver_path_continues_like_its_twin(reactor_model, outputs):
    interrupted_like_a_twin(
        lambda: learned_mhe(reactor_model, horizon=5, solver="least-squares"),
        feeder(outputs), np.random.default_rng(2), tries=15)


def test_interrupted_parallel_bank_continues_like_its_twin(reactor_model, outputs):
    k = 8
    rng_y = np.random.default_rng(5)
    Y = outputs[:, None, None] + 0.01 * rng_y.normal(size=(len(outputs), k, 1))
    x0 = np.column_stack([np.linspace(1.0, 3.5, k), np.linspace(3.5, 1.0, k)])

    def make():
        return EstimatorBank(reactor_model, k, x0, x_bounds=br.X_BOUNDS, **br.MHE_SETTINGS)

    def feed(bank):
        bank.update(None, Y[bank.t % len(Y)])

    est, twin = interrupted_like_a_twin(make, feed, np.random.default_rng(6), tries=25)
    assert est.t > 0
    member = est[3]
    np.testing.assert_array_equal(member.x, est.x[3])
    np.testing.assert_array_equal(member.P, est.P[3])
    assert member.message == twin[3].message
