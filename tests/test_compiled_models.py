"""CasADi models compiled for the estimator's core (``native=True``, the default): bit-identical
estimates to the same model called back through Python (discrete, sampled with per-sample
intervals, with parameters; both forms; the bank), the cache (reused, outside the working
directory, a damaged library compiled again), the fallback without a C compiler (one warning),
values out of range failing as a Python model's do, pickles, threads and interrupts; the cache
bounded to its most recently used libraries and cleared on request."""

import copy
import os
import pathlib
import pickle
import signal
import threading
import time
import warnings

import numpy as np
import pytest

from gpmhe import GPMHE, EstimatorBank, KnownModel, SettingsWarning
from gpmhe.models import compiled
from gpmhe.models.base import ModelDomainError
from gpmhe.systems import batch_reactor as br
from gpmhe.systems import cart_pole as cp
from gpmhe.systems import rotating_masses as rm

from conftest import reactor_casadi

ca = pytest.importorskip("casadi")


@pytest.fixture
def cache(tmp_path, monkeypatch):
    """An empty cache directory of this test's own."""
    monkeypatch.setenv("GPMHE_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path / "cache" / "casadi"


def reactor(native=True):
    return reactor_casadi(native=native)


def run(est, ys, us=None, dts=None):
    """Every update's x, P, x_window, P_window, innovation and S, stacked."""
    out = []
    for t, y in enumerate(ys):
        kwargs = {} if dts is None else {"dt": dts[t]}
        est.update(None if us is None else us[t], y, **kwargs)
        out.append(np.concatenate([est.x, est.P.ravel(), est.x_window[0],
                                   est.P_window[0].ravel(), est.innovation, est.S.ravel()]))
    return np.array(out)


def both(build, ys, us=None, dts=None, **settings):
    """The runs of the compiled and the called-back model, and the compiled estimator."""
    runs, estimators = [], []
    for native in (True, False):
        est = GPMHE(build(native), **settings)
        assert est.native is native
        runs.append(run(est, ys, us, dts))
        estimators.append(est)
    return runs, estimators[0]


# ---- the same estimates, bit for bit ----------------------------------------------------------
@pytest.mark.parametrize("form", ["prediction", "filtering"])
def test_a_discrete_model_gives_the_callbacks_estimates_bit_for_bit(form):
    _, y = br.simulate(br.X_TRUE0, 40, np.random.default_rng(3))
    (a, b), _ = both(reactor, y, x0=br.X_PRIOR0, x_bounds=br.X_BOUNDS, form=form,
                     **br.RECOMMENDED_SETTINGS)
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("jittered", [False, True])
def test_a_sampled_model_with_per_sample_intervals_gives_the_callbacks_estimates(jittered):
    x, u, y = cp.simulate(80, rng=1)
    dts = cp.T * np.random.default_rng(5).uniform(0.5, 1.5, 80) if jittered else None
    (a, b), _ = both(lambda native: cp.known_model("casadi", native=native), y[:80], u, dts,
                     x0=cp.X0, form="filtering", **cp.MHE_SETTINGS)
    np.testing.assert_array_equal(a, b)


def test_a_model_with_parameters_gives_the_callbacks_estimates_and_parameters():
    rng = np.random.default_rng(0)
    U = rm.random_inputs(25, rng)
    truth = rm.known_model(backend="numpy")
    x = [rm.X0]
    for t in range(25):
        x.append(truth.predict(x[-1], U[t]))
    ys = np.array(x)[:25, :3] + 0.01 * rng.normal(size=(25, 3))
    estimates = []
    for native in (True, False):
        est = GPMHE(rm.known_model(None, substeps=2, native=native), rm.initial_estimate(1),
                    form="filtering", **rm.MHE_SETTINGS, **rm.PARAMETER_SETTINGS)
        assert est.native is native
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # early windows stop at max-iterations
            estimates.append([np.concatenate([est.update(U[t], ys[t]), est.p, est.P_p.ravel()])
                              for t in range(25)])
    np.testing.assert_array_equal(estimates[0], estimates[1])


def test_a_compiled_bank_runs_in_parallel_and_equals_separate_estimators():
    _, y = br.simulate(br.X_TRUE0, 15, np.random.default_rng(4))
    Y = np.stack([y + 0.01 * i for i in range(4)], axis=1)  # (T, 4, 1)
    bank = EstimatorBank(reactor(), 4, br.X_PRIOR0, x_bounds=br.X_BOUNDS, **br.RECOMMENDED_SETTINGS)
    assert bank._core.parallel
    singles = [GPMHE(reactor(native=False), br.X_PRIOR0, x_bounds=br.X_BOUNDS,
                     **br.RECOMMENDED_SETTINGS) for _ in range(4)]
    for t in range(len(y)):
        bank.update(None, Y[t])
        for i, est in enumerate(singles):
            est.update(None, Y[t, i])
        np.testing.assert_array_equal(bank.x, np.array([e.x for e in singles]))
        np.testing.assert_array_equal(bank.P, np.array([e.P for e in singles]))


def fleet(k, singles_native):
    """A compiled bank of k rotating-mass estimators of Θ1 and k separate ones (their model
    compiled or called back)."""
    settings = dict(form="filtering", **rm.MHE_SETTINGS, **rm.PARAMETER_SETTINGS)
    bank = EstimatorBank(rm.known_model(None, substeps=2), k, rm.initial_estimate(1), **settings)
    singles = [GPMHE(rm.known_model(None, substeps=2, native=singles_native),
                     rm.initial_estimate(1), **settings) for _ in range(k)]
    return bank, singles


def run_fleet(bank, singles, U, Y, dts=None):
    """Each sample into the bank and the separate estimators; x, p and P_p equal after each."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # early windows stop at max-iterations
        for t in range(len(Y)):
            bank.update(np.tile(U[t], (len(singles), 1)), Y[t],
                        **({} if dts is None else {"dt": dts[t]}))
            for i, est in enumerate(singles):
                est.update(U[t], Y[t, i], **({} if dts is None else {"dt": dts[t, i]}))
            for name in ("x", "p", "P_p"):
                np.testing.assert_array_equal(getattr(bank, name),
                                              np.array([getattr(e, name) for e in singles]))


def test_a_fleet_of_rotating_masses_each_estimating_its_own_inertia_runs_as_one_bank():
    rng = np.random.default_rng(2)
    k, steps = 4, 12
    U = rm.random_inputs(steps, rng)
    Y = np.empty((steps, k, 3))
    for i, theta1 in enumerate([1.5e-4, 2.25e-4, 3e-4, 4e-4]):  # four plants, four inertias
        truth = rm.known_model(backend="numpy", theta1=theta1)
        x = rm.X0.copy()
        for t in range(steps):
            Y[t, i] = x[:3] + 0.01 * rng.normal(size=3)
            x = truth.predict(x, U[t])
    bank, singles = fleet(k, singles_native=False)
    assert bank._core.parallel and bank.dim_p == 1
    run_fleet(bank, singles, U, Y)


def test_a_fleet_with_parameters_takes_each_samples_interval_as_separate_estimators_do():
    rng = np.random.default_rng(3)
    k, steps = 2, 8
    U = rm.random_inputs(steps, rng)
    _, _, y = rm.simulate(steps, rng=rng)
    Y = np.stack([y[:steps], y[:steps] + 0.01], axis=1)
    dts = rm.T * rng.uniform(0.7, 1.3, (steps, k))
    run_fleet(*fleet(k, singles_native=True), U, Y, dts)


# ---- the cache --------------------------------------------------------------------------------
def replace(path, data):
    """`path` replaced by a new file holding `data`."""
    path.unlink()
    path.write_bytes(data)


def test_the_library_is_compiled_once_into_the_cache_and_reused(cache, monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)
    est = GPMHE(reactor(), br.X_PRIOR0, **br.RECOMMENDED_SETTINGS)
    assert est.native
    libraries = sorted(cache.glob("*.so"))
    assert len(libraries) == 1 and (cache / (libraries[0].stem + ".sha256")).exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cache"]  # nothing in the cwd

    def no_compiler(*args, **kwargs):
        raise AssertionError("compiled again although the cache holds the library")

    monkeypatch.setattr(compiled.subprocess, "run", no_compiler)
    again = GPMHE(reactor(), br.X_PRIOR0, **br.RECOMMENDED_SETTINGS)  # a new model object
    assert again.native


def scaled_reactor(c):
    """A small CasADi model of its own for each constant `c` (so, one library each)."""
    xs = ca.SX.sym("x", 2)
    f = ca.Function("scaled_f", [xs], [xs * c])
    h = ca.Function("scaled_h", [xs], [xs[0] + xs[1]])
    return KnownModel.from_casadi(f, h)


def build(model):
    return GPMHE(model, x0=[1.0, 1.0], Q0=1e-2, R0=1e-2, horizon=3)


def test_the_cache_keeps_the_most_recently_used_libraries(cache, monkeypatch):
    monkeypatch.setenv("GPMHE_CACHE_MAX", "2")
    build(scaled_reactor(0.9))
    time.sleep(0.05)  # (modification times order the libraries)
    build(scaled_reactor(0.8))
    first = {p.name for p in cache.glob("*.so")}
    assert len(first) == 2
    time.sleep(0.05)
    build(scaled_reactor(0.9))  # used again: now the most recent
    time.sleep(0.05)
    est = build(scaled_reactor(0.7))  # compiled; the 0.8 library, least recently used, goes
    assert est.native
    kept = {p.name for p in cache.glob("*.so")}
    assert len(kept) == 2 and len(kept & first) == 1
    assert len(list(cache.glob("*.sha256"))) == 2
    again = build(scaled_reactor(0.7))
    np.testing.assert_array_equal(est.update(None, [1.9]), again.update(None, [1.9]))


def test_clear_cache_removes_every_library_and_the_next_model_compiles_again(cache):
    old = build(scaled_reactor(0.9))
    stale = cache / "build-killed"
    stale.mkdir()
    (stale / "gpmhe_model.c").write_text("/* a compilation that was killed */")
    os.utime(stale, (0, 0))
    assert compiled.clear_cache() == 1
    assert not list(cache.glob("*.so")) and not stale.exists()
    assert compiled.clear_cache() == 0
    new = build(scaled_reactor(0.9))
    assert new.native and len(list(cache.glob("*.so"))) == 1
    np.testing.assert_array_equal(old.update(None, [1.9]), new.update(None, [1.9]))


@pytest.mark.parametrize("value", ["0", "many", "-3"])
def test_a_bad_cache_limit_runs_the_model_as_callbacks_with_a_warning_naming_it(cache, monkeypatch,
                                                                              value):
    monkeypatch.setenv("GPMHE_CACHE_MAX", value)
    with pytest.warns(SettingsWarning, match=r"\$GPMHE_CACHE_MAX: must be a whole number"):
        est = build(scaled_reactor(0.6))
    assert not est.native and not list(cache.glob("*.so"))


@pytest.mark.parametrize("damage", ["truncate", "garbage", "checksum", "delete-checksum"])
def test_a_damaged_library_is_compiled_again_not_loaded(cache, damage):
    _, y = br.simulate(br.X_TRUE0, 10, np.random.default_rng(1))
    reference = run(GPMHE(reactor(), br.X_PRIOR0, **br.RECOMMENDED_SETTINGS), y)
    so = next(cache.glob("*.so"))
    sha = so.with_suffix(".sha256")
    # A new file in its place (as a copy or a disk would leave it): the library this process
    # has loaded keeps its own pages, as the operating system keeps them for a replaced file.
    if damage == "truncate":
        replace(so, so.read_bytes()[:500])
    elif damage == "garbage":
        replace(so, b"\x7fELF" + os.urandom(2000))
    elif damage == "checksum":
        sha.write_text("0" * 64)
    else:
        sha.unlink()
    with warnings.catch_warnings():
        warnings.simplefilter("error", SettingsWarning)  # no fallback: compiled again
        est = GPMHE(reactor(), br.X_PRIOR0, **br.RECOMMENDED_SETTINGS)
    assert est.native
    np.testing.assert_array_equal(run(est, y), reference)
    assert compiled._cached(so, sha)


def test_a_library_that_does_not_load_is_compiled_again_once(cache):
    """A cached library whose checksum matches but that the core cannot load (not loaded before
    in this process) is compiled again once, then used."""
    x = ca.SX.sym("x", 2)
    f = ca.Function("f_once", [x], [0.5 * x + 0.123456789])  # a model no other test compiles
    h = ca.Function("h_once", [x], [x[0]])
    model = KnownModel.from_casadi(f, h)
    functions = [model._casadi._build(part, name, jit=False)
                 for part, name in model._casadi._NATIVE.items()]
    so = pathlib.Path(compiled.library(ca, functions))  # compiled, not loaded
    replace(so, b"not a library")
    so.with_suffix(".sha256").write_text(compiled._digest(b"not a library"))
    with warnings.catch_warnings():
        warnings.simplefilter("error", SettingsWarning)
        est = GPMHE(model, [1.0, 1.0], R0=1.0)
    assert est.native and so.read_bytes() != b"not a library"


# ---- without a compiler -------------------------------------------------------------------------
def test_without_a_compiler_the_model_runs_as_callbacks_with_one_warning(cache, monkeypatch):
    monkeypatch.setenv("CC", "/nonexistent/cc")
    _, y = br.simulate(br.X_TRUE0, 10, np.random.default_rng(2))
    model = reactor()
    with pytest.warns(SettingsWarning, match=r"runs as Python callbacks.*C compiler") as caught:
        est = GPMHE(model, br.X_PRIOR0, **br.RECOMMENDED_SETTINGS)
    assert len(caught) == 1 and caught[0].filename == __file__
    with warnings.catch_warnings():
        warnings.simplefilter("error", SettingsWarning)  # the same model does not warn again
        second = GPMHE(model, br.X_PRIOR0, **br.RECOMMENDED_SETTINGS)
    assert not est.native and not second.native
    reference = GPMHE(reactor(native=False), br.X_PRIOR0, **br.RECOMMENDED_SETTINGS)
    np.testing.assert_array_equal(run(est, y), run(reference, y))


def test_an_unwritable_cache_runs_the_model_as_callbacks_with_one_warning(tmp_path, monkeypatch):
    blocker = tmp_path / "not-a-directory"
    blocker.write_text("a file where the cache directory would go")
    monkeypatch.setenv("GPMHE_CACHE_DIR", str(blocker))
    with pytest.warns(SettingsWarning, match="cannot write the compiled model"):
        est = GPMHE(reactor(), br.X_PRIOR0, **br.RECOMMENDED_SETTINGS)
    assert not est.native
    assert blocker.read_text() == "a file where the cache directory would go"


def test_an_implicit_scheme_has_no_c_code_and_runs_as_callbacks():
    model = rm.known_model(method="implicit-midpoint", substeps=1)
    with pytest.warns(SettingsWarning, match="no C code|Code generation not supported"):
        est = GPMHE(model, rm.X0, **rm.MHE_SETTINGS)
    assert not est.native


def test_native_false_never_compiles(cache, monkeypatch):
    monkeypatch.setattr(compiled.subprocess, "run", lambda *a, **k: pytest.fail("compiled"))
    with warnings.catch_warnings():
        warnings.simplefilter("error", SettingsWarning)
        est = GPMHE(reactor(native=False), br.X_PRIOR0, **br.RECOMMENDED_SETTINGS)
    assert not est.native and not cache.exists()


# ---- bad values, pickles, threads, interrupts ---------------------------------------------------
@pytest.mark.parametrize("native", [True, False])
def test_a_value_out_of_range_fails_as_a_python_models_does(native):
    x = ca.SX.sym("x", 1)
    model = KnownModel.from_casadi(ca.Function("f", [x], [ca.log(x)]),
                                   ca.Function("h", [x], [x]), native=native)
    mhe = GPMHE(model, [-1.0], horizon=3, R0=1.0)
    with pytest.raises(ModelDomainError, match=r"^f: returned NaN or inf .*\(CasADi model\)"):
        mhe.update(None, [0.0])
    assert mhe.t == 0


def test_pickles_and_copies_continue_bit_for_bit_and_rebuild_from_the_cache(cache):
    x, u, y = cp.simulate(20, rng=2)
    est = GPMHE(cp.known_model("casadi"), cp.X0, **cp.MHE_SETTINGS)
    for t in range(10):
        est.update(u[t], y[t])
    clones = [pickle.loads(pickle.dumps(est)), copy.deepcopy(est)]
    assert all(c.native for c in clones)
    for t in range(10, 20):
        a = est.update(u[t], y[t])
        for c in clones:
            np.testing.assert_array_equal(c.update(u[t], y[t]), a)


def test_threads_sharing_one_compiled_model_get_their_own_estimates():
    model = cp.known_model("casadi")
    runs = [cp.simulate(40, rng=seed) for seed in range(4)]
    serial = [run(GPMHE(model, cp.X0, **cp.MHE_SETTINGS), y, u) for _, u, y in runs]
    results = [None] * 4

    def work(i):
        _, u, y = runs[i]
        results[i] = run(GPMHE(model, cp.X0, **cp.MHE_SETTINGS), y, u)

    threads = [threading.Thread(target=work, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for a, b in zip(results, serial):
        np.testing.assert_array_equal(a, b)


@pytest.mark.skipif(not hasattr(signal, "setitimer"), reason="needs signal.setitimer")
def test_an_interrupt_during_a_compiled_banks_updates_leaves_whole_updates():
    _, y = br.simulate(br.X_TRUE0, 400, np.random.default_rng(6))
    k = 300
    bank = EstimatorBank(reactor(), k, br.X_PRIOR0, x_bounds=br.X_BOUNDS, **br.RECOMMENDED_SETTINGS)
    shadow = EstimatorBank(reactor(), k, br.X_PRIOR0, x_bounds=br.X_BOUNDS, **br.RECOMMENDED_SETTINGS)

    def handler(signum, frame):
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGALRM, handler)
    signal.setitimer(signal.ITIMER_REAL, 0.3)
    done = 0
    try:
        with pytest.raises(KeyboardInterrupt):
            for yt in y:
                bank.update(None, np.repeat(yt[None], k, axis=0))
                done += 1
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
    # the signal may land after an update returned and before the count went up
    assert 0 < done < len(y) - 1 and bank.t in (done, done + 1)
    for yt in y[:bank.t]:
        shadow.update(None, np.repeat(yt[None], k, axis=0))
    np.testing.assert_array_equal(bank.x, shadow.x)
    bank.update(None, np.repeat(y[bank.t][None], k, axis=0))  # and it goes on
    shadow.update(None, np.repeat(y[shadow.t][None], k, axis=0))
    np.testing.assert_array_equal(bank.x, shadow.x)
