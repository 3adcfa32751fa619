"""KnownModel.from_casadi: values and Jacobians against numpy models and finite differences, the
mapped evaluation against per-point evaluation, the same estimates as the numpy KnownModel (batch
reactor, cart-pole), the signature checks, pickling, copying, saving and the error paths."""

import copy
import io
import pickle
import pathlib
import shutil
import warnings

import numpy as np
import pytest

from gpmhe import GPMHE, EstimatorBank, KnownModel, LearnedModel
from gpmhe.systems import batch_reactor as br
from gpmhe.systems import cart_pole as cp

from conftest import f3_jac_v, f3_v, h3_jac_v, h3_v, reactor_casadi, reactor_known_model

ca = pytest.importorskip("casadi")


# ---- the models -----------------------------------------------------------------------------
def synthetic_casadi_functions(kind="SX", row_vectors=False):
    """The f3/h3 system of conftest (n = 2, m = 1, p = 2)."""
    sym = getattr(ca, kind).sym
    x = sym("x", 1, 2) if row_vectors else sym("x", 2)
    u = sym("u", 1)
    f = ca.vertcat(0.9 * x[0] + 0.1 * x[1] + 0.1 * u[0],
                   -0.1 * ca.sin(x[0]) + 0.95 * x[1] + 0.05 * u[0])
    h = ca.vertcat(x[0], x[0] * x[1] + 0.2 * u[0])
    if row_vectors:
        f, h = f.T, h.T
    return ca.Function("f3", [x, u], [f]), ca.Function("h3", [x, u], [h])


def synthetic_numpy():
    return KnownModel(f3_v, h3_v, 2, 2, dim_u=1, f_jacobian=f3_jac_v, h_jacobian=h3_jac_v,
                      vectorized=True)


def points(k, m, seed=0):
    return np.random.default_rng(seed).uniform(0.1, 4.5, (k, 2 + m))


def cart_pole_points(k, seed=0):
    """[p, θ, v, ω, F] rows with the pole anywhere."""
    return np.random.default_rng(seed).uniform([-1, -3, -2, -5, -2], [1, 3, 2, 5, 2], (k, 5))


# ---- values and Jacobians -----------------------------------------------------------------
@pytest.mark.parametrize("k", [1, 2, 11])
def test_reactor_stage_eval_matches_the_numpy_model(k):
    d = points(k, 0)
    ours, ref = reactor_casadi().stage_eval(d), reactor_known_model(vectorized=True).stage_eval(d)
    for a, b in zip(ours, ref):
        assert a.shape == b.shape and a.dtype == np.float64 and a.flags.c_contiguous
        np.testing.assert_allclose(a, b, rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize("kind, row_vectors", [("SX", False), ("MX", False), ("SX", True)])
def test_synthetic_stage_eval_matches_numpy_and_finite_differences(kind, row_vectors):
    model = KnownModel.from_casadi(*synthetic_casadi_functions(kind, row_vectors))
    assert (model.dim_x, model.dim_u, model.dim_y, model.vectorized) == (2, 1, 2, True)
    d = points(7, 1, seed=2)
    ours, ref = model.stage_eval(d), synthetic_numpy().stage_eval(d)
    for a, b in zip(ours, ref):
        np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-14)
    assert np.all(ours[2][:, :, 2] == 0.0) and np.all(ours[6][:, :, 2] == 0.0)  # ∂/∂u reported 0
    fd = KnownModel(model.f, model.h, 2, 2, dim_u=1, vectorized=True).stage_eval(d)
    for i in (2, 6):
        np.testing.assert_allclose(ours[i], fd[i], rtol=1e-7, atol=1e-8)


def test_parts_evaluate_the_functions_at_the_rows():
    f, h = synthetic_casadi_functions()
    model = KnownModel.from_casadi(f, h)
    d = points(5, 1, seed=4)
    X, U = d[:, :2], d[:, 2:]
    np.testing.assert_allclose(model.f(X, U), f3_v(X, U), rtol=1e-14)
    np.testing.assert_allclose(model.h(X, U), h3_v(X, U), rtol=1e-14)
    np.testing.assert_allclose(model.f_jacobian(X, U), f3_jac_v(X, U), rtol=1e-14)
    np.testing.assert_allclose(model.h_jacobian(X, U), h3_jac_v(X, U), rtol=1e-14)
    np.testing.assert_allclose(model.predict(X[0], U[0]), f3_v(X[:1], U[:1])[0], rtol=1e-14)
    assert "f3" in repr(model.f) and "Jacobian" in repr(model.h_jacobian)
    with pytest.raises(ValueError, match="f: X and U must have dim_x"):
        model.f(X, np.zeros((5, 2)))


def test_mapped_evaluation_equals_per_point_evaluation():
    model = cp.known_model("casadi")
    d = cart_pole_points(11, seed=5)
    together = model.stage_eval(d)
    apart = [model.stage_eval(row) for row in d]
    for i, a in enumerate(together):
        np.testing.assert_array_equal(a, np.concatenate([p[i] for p in apart]))
    F, h = cp.casadi_functions()  # the user's functions, called one point at a time
    f_disc = model._casadi.f
    for row, value in zip(d, together[0]):
        np.testing.assert_allclose(value, np.array(f_disc(row[:4], row[4:])).ravel(), rtol=1e-14)
    assert set(k for (part, k) in model._casadi._maps if part == "stage") == {1, 11}


def test_cart_pole_casadi_matches_the_numpy_model():
    d = cart_pole_points(6, seed=8)
    ours, ref = cp.known_model("casadi").stage_eval(d), cp.known_model("numpy").stage_eval(d)
    for a, b in zip(ours, ref):
        np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-12)


def test_no_input_and_no_output():
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 0)
    f = ca.Function("f", [x, u], [2.0 * x])            # an empty u input: dim_u = 0
    model = KnownModel.from_casadi(f, None)
    assert (model.dim_x, model.dim_u, model.dim_y) == (2, 0, 0)
    mx, _, dmx, _, my, vy, dmy, _ = model.stage_eval(np.ones((3, 2)))
    assert my.shape == (3, 0) and dmy.shape == (3, 0, 2)
    np.testing.assert_array_equal(dmx, np.broadcast_to(2.0 * np.eye(2), (3, 2, 2)))
    h = ca.Function("h", [x], [x[0]])                   # h of x alone next to f(x, u)
    g = ca.Function("g", [x, ca.SX.sym("u", 1)], [x + 1])
    assert KnownModel.from_casadi(g, h).dim_u == 1


def test_within_gpmhe_stage_eval_results_are_fresh_and_writable():
    model = reactor_casadi()
    a = model.stage_eval(points(3, 0))
    b = model.stage_eval(points(3, 0))
    assert all(x.flags.writeable for x in a)
    a[1][:] = 5.0  # the variances: the caller's own arrays
    assert np.all(b[1] == 0.0)


def test_core_callbacks_reuse_read_only_arrays_with_the_same_values():
    model = cp.known_model("casadi")
    cas = model._casadi
    d1, d2 = cart_pole_points(11, seed=1), cart_pole_points(11, seed=2)
    first = cas.stage_callback(d1)
    expected = [a.copy() for a in first]
    for a, b in zip(expected, model.stage_eval(d1)):
        np.testing.assert_array_equal(a, b)
    assert all(not a.flags.writeable and a.flags.c_contiguous for a in first)
    second = cas.stage_callback(d2)
    assert all(a is b for a, b in zip(first, second))  # shared: the core copies them at once
    np.testing.assert_array_equal(second[0], model.stage_eval(d2)[0])
    x, u = d1[0, :4], d1[0, 4:]
    np.testing.assert_array_equal(cas.predict_callback(x, u), model.predict(x, u))


# ---- the estimator ------------------------------------------------------------------------
@pytest.mark.parametrize("form", ["prediction", "filtering"])
def test_reactor_estimates_equal_the_numpy_models(form):
    x, y = br.simulate(br.X_TRUE0, 40, np.random.default_rng(3))
    estimates = []
    for model in (reactor_casadi(), reactor_known_model(vectorized=True), reactor_known_model()):
        mhe = GPMHE(model, br.X_PRIOR0, x_bounds=br.X_BOUNDS, form=form, **br.MHE_SETTINGS)
        estimates.append(np.array([mhe.update(None, yt).copy() for yt in y]))
    np.testing.assert_allclose(estimates[0], estimates[1], rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(estimates[0], estimates[2], rtol=1e-9, atol=1e-10)


def test_cart_pole_estimates_equal_the_numpy_models():
    x, u, y = cp.simulate(60, rng=1)
    estimates = []
    for model in (cp.known_model("casadi"), cp.known_model("numpy")):
        mhe = GPMHE(model, cp.X0, **cp.MHE_SETTINGS)
        estimates.append(np.array([mhe.update(ut, yt).copy() for ut, yt in zip(u, y)]))
    np.testing.assert_allclose(estimates[0], estimates[1], rtol=1e-7, atol=1e-8)
    rmse = np.sqrt(np.mean((estimates[0][:-1] - x[1:]) ** 2, axis=0))
    assert np.all(rmse < 0.5 * cp.SIGMA_V)  # better than the measurements


def test_scipy_solvers_and_the_bank_run_on_a_casadi_model():
    x, y = br.simulate(br.X_TRUE0, 8, np.random.default_rng(4))
    for solver in ("least-squares", "trust-constr"):
        ref, mhe = (GPMHE(model, br.X_PRIOR0, x_bounds=br.X_BOUNDS, solver=solver, **br.MHE_SETTINGS)
                    for model in (reactor_known_model(), reactor_casadi()))
        for yt in y:
            ref.update(None, yt)
            mhe.update(None, yt)
        np.testing.assert_allclose(mhe.x, ref.x, rtol=1e-6, atol=1e-8)
    ref = GPMHE(reactor_known_model(), br.X_PRIOR0, x_bounds=br.X_BOUNDS, **br.MHE_SETTINGS)
    for yt in y:
        ref.update(None, yt)
    bank = EstimatorBank(reactor_casadi(), 3, br.X_PRIOR0, x_bounds=br.X_BOUNDS, **br.MHE_SETTINGS)
    for yt in y:
        bank.update(None, np.repeat(yt[None], 3, axis=0))
    np.testing.assert_allclose(bank.x, np.repeat(ref.x[None], 3, axis=0), rtol=1e-9)


def test_nominal_model_of_a_learned_model():
    states, outputs = br.training_data(3, rng=0, steps=10)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ours = LearnedModel.from_trajectories(states, outputs, f_nominal=reactor_casadi().f,
                                              h_nominal=reactor_casadi().h,
                                              nominal_options={"vectorized": True},
                                              optimizer=None)
        ref = LearnedModel.from_trajectories(states, outputs, f_nominal=br.f_batch, h_nominal=br.h_batch,
                                             nominal_options={"vectorized": True}, optimizer=None)
    d = points(4, 0)
    for a, b in zip(ours.stage_eval(d), ref.stage_eval(d)):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12)


# ---- bad model output -----------------------------------------------------------------------
def test_nan_output_raises_naming_the_function_and_leaves_the_estimator_unchanged():
    x = ca.SX.sym("x", 1)
    f = ca.Function("f", [x], [ca.log(x)])  # NaN for x < 0
    h = ca.Function("h", [x], [x])
    model = KnownModel.from_casadi(f, h)
    with pytest.raises(ValueError, match=r"^f: returned NaN"):
        model.stage_eval([[-1.0]])
    with pytest.raises(ValueError, match=r"^f: returned NaN"):
        model.predict([-1.0])
    mhe = GPMHE(model, [-1.0], horizon=3)
    with pytest.raises(ValueError, match="f"):
        mhe.update(None, [0.0])
    assert mhe.t == 0


# ---- signatures -----------------------------------------------------------------------------
def test_signature_errors_name_the_argument():
    x, u, X = ca.SX.sym("x", 2), ca.SX.sym("u", 1), ca.SX.sym("X", 2, 2)
    f = ca.Function("f", [x, u], [x])
    h = ca.Function("h", [x, u], [x[0]])
    x3 = ca.SX.sym("x", 3)
    cases = [
        (dict(f=lambda x, u: x, h=h), r"^f: must be a casadi.Function"),
        (dict(f=f, h=br.h), r"^h: must be a casadi.Function"),
        (dict(f=ca.Function("f", [x, u, ca.SX.sym("p"), ca.SX.sym("q")], [x]), h=h), r"^f: must take x or \(x, u\).* got 4"),
        (dict(f=ca.Function("f", [x, u, ca.SX.sym("p", 0)], [x]), h=h), r"^f: its third input p must have"),
        (dict(f=ca.Function("f", [x, u], [x, x]), h=h), r"^f: must have one output, got 2"),
        (dict(f=ca.Function("f", [X, u], [X[:, 0]]), h=h),
         r"^f: input 0 \('i0'\) must be a vector, got shape \(2, 2\)"),
        (dict(f=ca.Function("f", [x, u], [ca.vertcat(x, u)]), h=h), r"^f: returns 3 values, expected"),
        (dict(f=f, h=ca.Function("h", [x3, u], [x3[0]])),
         r"^h: its input x has 3 values"),
        (dict(f=f, h=ca.Function("h", [x, ca.SX.sym("u", 2)], [x[0]])), r"^h: its input u has 2 values"),
        (dict(f=ca.Function("f", [x], [x]), h=h), r"^h: its input u has 1 values, f's has 0"),
        (dict(f=f, h=ca.Function("h", [x, u], [ca.repmat(x, 1, 2)])), r"^h: output 0 .* must be a vector"),
        (dict(f=f, h=h, jit="yes"), r"^jit: must be True or False"),
    ]
    for kwargs, match in cases:
        with pytest.raises(ValueError, match=match):
            KnownModel.from_casadi(**kwargs)
    xs = ca.SX.sym("x", ca.Sparsity.lower(2))
    sparse = ca.Function("f", [ca.vec(xs), u], [ca.vec(xs)[:2]])
    with pytest.raises(ValueError, match=r"^f: input 0 .* must be dense"):
        KnownModel.from_casadi(sparse, h)


def test_missing_casadi_raises_import_error_with_an_install_hint(monkeypatch):
    f, h = synthetic_casadi_functions()
    monkeypatch.setitem(__import__("sys").modules, "casadi", None)
    with pytest.raises(ImportError, match=r"KnownModel.from_casadi needs CasADi .*pip install casadi"):
        KnownModel.from_casadi(f, h)
    with pytest.raises(ImportError, match=r"cart_pole.casadi_functions needs CasADi"):
        cp.casadi_functions()


# ---- pickling, copying, saving ----------------------------------------------------------------
def test_pickle_copy_and_save_load():
    model = cp.known_model("casadi")
    assert copy.deepcopy(model) is model and copy.copy(model) is model
    d = cart_pole_points(4, seed=6)
    restored = pickle.loads(pickle.dumps(model))
    assert type(restored) is KnownModel and restored._casadi is not None
    for a, b in zip(model.stage_eval(d), restored.stage_eval(d)):
        np.testing.assert_array_equal(a, b)
    x, u, y = cp.simulate(12, rng=2)
    mhe = GPMHE(model, cp.X0, **cp.MHE_SETTINGS)
    for t in range(6):
        mhe.update(u[t], y[t])
    clone = pickle.loads(pickle.dumps(mhe))
    buf = io.BytesIO()
    mhe.save(buf)
    buf.seek(0)
    loaded = GPMHE.load(buf, restored)
    for t in range(6, 12):
        a, b, c = (e.update(u[t], y[t]) for e in (mhe, clone, loaded))
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, c)


def test_a_function_casadi_cannot_serialise_raises_pickling_error():
    class Twice(ca.Callback):
        def __init__(self):
            ca.Callback.__init__(self)
            self.construct("twice", {})

        def get_n_in(self):
            return 1

        def get_n_out(self):
            return 1

        def eval(self, arg):
            return [2 * arg[0]]

    twice = Twice()
    x = ca.MX.sym("x", 1)
    f = ca.Function("f", [x], [twice(x)])
    model = KnownModel.from_casadi(f, ca.Function("h", [x], [x]))
    np.testing.assert_allclose(model.predict([1.5]), [3.0])  # MX (not expandable) works
    with pytest.raises(pickle.PicklingError, match="KnownModel: cannot pickle f="):
        pickle.dumps(model)


@pytest.mark.skipif(shutil.which("gcc") is None and shutil.which("cc") is None,
                    reason="CasADi's JIT needs a C compiler")
def test_jit_compiled_model_matches_and_pickles():
    model = reactor_casadi(jit=True)
    d = points(5, 0, seed=7)
    ref = reactor_casadi().stage_eval(d)
    for a, b in zip(model.stage_eval(d), ref):
        np.testing.assert_allclose(a, b, rtol=1e-14, atol=1e-15)
    restored = pickle.loads(pickle.dumps(model))
    assert restored._casadi.jit
    np.testing.assert_allclose(restored.stage_eval(d)[0], ref[0], rtol=1e-14)


# ---------------------------------------------------------------------- validation at construction


def test_free_symbols_are_refused_at_construction():
    x, free = ca.MX.sym("x", 2), ca.MX.sym("k")
    f = ca.Function("f", [x], [free * x], {"allow_free": True})
    h = ca.Function("h", [x], [x[0]])
    with pytest.raises(ValueError, match=r"^f: depends on symbols that are not its inputs \(k\)"):
        KnownModel.from_casadi(f, h)
    with pytest.raises(ValueError, match=r"^h: depends on symbols"):
        KnownModel.from_casadi(ca.Function("g", [x], [0.5 * x]), ca.Function("h", [x], [free * x[0]],
                                                                            {"allow_free": True}))


def test_parameter_sizes_of_f_and_h_must_agree():
    x, u, p, q = ca.SX.sym("x", 1), ca.SX.sym("u", 1), ca.SX.sym("p", 1), ca.SX.sym("q", 2)
    f = ca.Function("f", [x, u, p], [p * x + u])
    h = ca.Function("h", [x, u, q], [x + q[0]])
    with pytest.raises(ValueError, match=r"^h: its input p has 2 values, f's has 1"):
        KnownModel.from_casadi(f, h)


def test_jit_compiles_outside_the_working_directory(tmp_path, monkeypatch):
    import glob
    import tempfile

    pattern = str(pathlib.Path(tempfile.gettempdir()) / "gpmhe-jit-*")
    before = set(glob.glob(pattern))
    monkeypatch.chdir(tmp_path)
    model = reactor_casadi(jit=True)
    est = GPMHE(model, br.X_PRIOR0, x_bounds=br.X_BOUNDS, **br.MHE_SETTINGS)
    est.update(None, [4.0])
    assert np.all(np.isfinite(est.x))
    assert list(tmp_path.iterdir()) == []
    assert set(glob.glob(pattern)) == before


def test_jit_without_a_compiler_is_refused_at_construction(tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path))  # no gcc, no cc
    with pytest.raises(ValueError, match=r"^jit: CasADi could not compile"):
        reactor_casadi(jit=True)
