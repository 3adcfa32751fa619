"""Interrupts: KeyboardInterrupt (Ctrl-C, or raised by user code) during an update, a GP fit or a
batch of recursive-GP updates propagates promptly and leaves the object as it was before the
call; a non-numerical exception from a model callback stops the update the same way; a
construction that could not finish (sigma_K = 1e200) fails fast."""

import signal
import subprocess
import sys
import threading
import time
import warnings

import numpy as np
import pytest

from gpmhe import GPMHE, GaussianProcess, KnownModel, RecursiveGP, _core
from gpmhe.systems import batch_reactor as br

ATTRS = ("x", "P", "x_window", "x_arrival", "cost", "success", "nit", "message", "t",
         "projected_gradient", "nfev")


def state(mhe):
    return {a: np.array(getattr(mhe, a), copy=True) for a in ATTRS if hasattr(mhe, a)}


def assert_same_state(a, b):
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


class CountingF:
    """br.f that raises `exc` at its k-th call (1-based; never if k is None)."""

    def __init__(self, k=None, exc=KeyboardInterrupt):
        self.k, self.exc, self.calls = k, exc, 0

    def __call__(self, x, u=None):
        self.calls += 1
        if self.calls == self.k:
            raise self.exc("raised inside f")
        return br.f(x)


def reactor_mhe(f, solver="gauss-newton"):
    model = KnownModel(f, br.h, 2, 1, f_jacobian=br.f_jacobian, h_jacobian=br.h_jacobian)
    return GPMHE(model, x0=[3.0, 1.0], x_bounds=br.X_BOUNDS, solver=solver, **br.MHE_SETTINGS)


@pytest.fixture(scope="module")
def outputs():
    return br.simulate(br.X_TRUE0, 12, np.random.default_rng(5))[1]


@pytest.mark.parametrize("exc", [KeyboardInterrupt, SystemExit, TypeError])
@pytest.mark.parametrize("solver", ["gauss-newton", "least-squares"])
def test_exception_from_a_known_model_at_any_call_propagates_and_changes_nothing(outputs, exc, solver):
    # How many calls of f the 9th update makes (warm start, window start point, trial points).
    probe = CountingF()
    twin = reactor_mhe(probe, solver)
    twin.batch_filter(outputs[:8])
    before = probe.calls
    twin.update(None, outputs[8])
    n_calls = probe.calls - before
    assert n_calls >= 5
    reference = reactor_mhe(br.f, solver)
    reference.batch_filter(outputs[:8])
    ref_state = state(reference)
    reference.update(None, outputs[8])
    reference.update(None, outputs[9])
    for k in sorted({1, 2, n_calls // 2, n_calls - 1, n_calls}):
        f = CountingF()
        mhe = reactor_mhe(f, solver)
        mhe.batch_filter(outputs[:8])
        f.k, f.exc = f.calls + k, exc
        with pytest.raises(exc, match="raised inside f"):
            mhe.update(None, outputs[8])
        assert_same_state(state(mhe), ref_state)
        # the next updates are bit-identical to those of an estimator that never saw it
        mhe.update(None, outputs[8])
        mhe.update(None, outputs[9])
        assert_same_state(state(mhe), state(reference))


def test_numerical_failure_of_a_known_model_at_a_trial_point_only_rejects_that_point(outputs):
    # ArithmeticError / RuntimeError from the model count as a failed trial point, not an error.
    probe = CountingF()
    mhe = reactor_mhe(probe)
    mhe.batch_filter(outputs[:8])
    before = probe.calls
    mhe.update(None, outputs[8])
    n_calls = probe.calls - before
    for k in range(n_calls // 2, n_calls + 1):
        f = CountingF()
        mhe = reactor_mhe(f)
        mhe.batch_filter(outputs[:8])
        f.k, f.exc = f.calls + k, FloatingPointError
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # (if the solve then stops early)
            mhe.update(None, outputs[8])
        assert np.all(np.isfinite(mhe.x)) and mhe.t == 9


def _training(n, seed=0):
    rng = np.random.default_rng(seed)
    D = rng.uniform(-2.0, 2.0, size=(n, 2))
    return D, np.sin(D[:, 0]) * np.cos(D[:, 1]) + 0.05 * rng.standard_normal(n)


def gp_state(gp, D):
    mean, std = gp.predict(D[:7], return_std=True)
    return (gp.sigma_f, tuple(gp.lengthscales), gp.sigma_eps, mean.tolist(), std.tolist())


def test_interrupt_from_the_fit_objective_leaves_the_gp_as_it_was(monkeypatch):
    D, y = _training(60)
    gp = GaussianProcess(n_restarts=1, random_state=0).fit(D[:30], y[:30])
    before = gp_state(gp, D)
    real, calls = _core.log_marginal_likelihood, [0]

    def objective(*args, **kwargs):
        calls[0] += 1
        if calls[0] == 5:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(_core, "log_marginal_likelihood", objective)
    with pytest.raises(KeyboardInterrupt):
        gp.fit(D, y)
    assert calls[0] == 5
    assert gp_state(gp, D) == before


def _interrupt_after(seconds):
    """Arms SIGALRM to raise KeyboardInterrupt after `seconds`; returns (fired, due, restore):
    `fired` gets the time the handler ran, `due` is when the signal was due."""
    fired = []

    def handler(signum, frame):
        fired.append(time.perf_counter())
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGALRM, handler)
    due = time.perf_counter() + seconds
    signal.setitimer(signal.ITIMER_REAL, seconds)

    def restore():
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)

    return fired, due, restore


@pytest.mark.skipif(not hasattr(signal, "setitimer"), reason="needs signal.setitimer")
def test_signal_during_a_long_gp_fit_interrupts_it_promptly_and_keeps_the_gp():
    assert threading.current_thread() is threading.main_thread()
    D, y = _training(1200, seed=1)
    gp = GaussianProcess(n_restarts=50, random_state=0).fit(D[:30], y[:30])
    before = gp_state(gp, D)
    fired, due, restore = _interrupt_after(0.33)
    try:
        with pytest.raises(KeyboardInterrupt):
            gp.fit(D, y)  # tens of seconds
        raised = time.perf_counter()
    finally:
        restore()
    assert fired, "the fit finished before the signal"
    # at most one O(N³) factorisation (~0.1 s at N = 1200) after the signal
    assert raised - due < 2.0
    assert gp_state(gp, D) == before


@pytest.mark.skipif(not hasattr(signal, "setitimer"), reason="needs signal.setitimer")
def test_signal_during_a_long_recursive_gp_batch_interrupts_it_and_keeps_the_weights():
    rgp = RecursiveGP([-2.0, -2.0], [2.0, 2.0], 20)  # 400 basis vectors, ~20 µs per point
    rng = np.random.default_rng(2)
    zeta = rng.uniform(-2.0, 2.0, size=(400_000, 2))  # ~10 s of updates without the GIL
    y = np.sin(zeta[:, 0])
    mean, cov = rgp.mean.copy(), rgp.cov.copy()
    fired, due, restore = _interrupt_after(0.33)
    try:
        with pytest.raises(KeyboardInterrupt):
            rgp.update(zeta, y, 0.01)
        raised = time.perf_counter()
    finally:
        restore()
    assert fired, "the batch finished before the signal"
    # the core checks for signals every 50 ms of work: well under a second on a loaded machine
    assert raised - due < 1.0
    np.testing.assert_array_equal(rgp.mean, mean)
    np.testing.assert_array_equal(rgp.cov, cov)


def test_sigma_k_whose_square_overflows_fails_fast_with_value_error():
    # in a subprocess, so that a regression (an endless loop) fails instead of hanging the suite
    code = ("import time; from gpmhe import RecursiveGP\n"
            "t = time.perf_counter()\n"
            "for s in (1e200, 1e-200):\n"
            "    try:\n"
            "        RecursiveGP(0.0, 1.0, 5, sigma_K=s)\n"
            "    except ValueError as e:\n"
            "        assert str(e).startswith('sigma_K'), e\n"
            "    else:\n"
            "        raise AssertionError(s)\n"
            "print(time.perf_counter() - t)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert float(out.stdout) < 1.0
