"""Copies, pickles and checkpoints: every public object deep-copies and pickles; a copied,
unpickled or checkpointed estimator is independent and continues bit-identically; damaged,
truncated or foreign files raise ValueError naming the file and the entry."""

import copy
import io
import pickle
import zipfile

import numpy as np
import pytest
from conftest import f3, h3, reactor_known_model, synthetic_learned_model
from numpy.testing import assert_array_equal

from gpmhe import (GPMHE, RGPEKF, GaussianProcess, KnownModel, LearnedModel, MultiOutputGP,
                   RecursiveGP, SparseGaussianProcess, _core)
from gpmhe.systems import batch_reactor as br

# ----------------------------------------------------------------------------- GPMHE


def _mhe_cases():
    """(model, settings, inputs, outputs) for both models, forms and solvers families."""
    rng = np.random.default_rng(3)
    T = 24
    us = rng.uniform(-1, 1, (T, 1))
    xs = [np.array([0.3, -0.2])]
    for u in us:
        xs.append(f3(xs[-1], u) + 0.01 * rng.standard_normal(2))
    ys = [h3(x, u) + 0.05 * rng.standard_normal(2) for x, u in zip(xs, us)]
    ys[5] = None  # a missing measurement inside the history
    learned = synthetic_learned_model(30)
    known = KnownModel(f3, h3, dim_x=2, dim_y=2, dim_u=1)
    return learned, known, us, ys


LEARNED, KNOWN, US, YS = _mhe_cases()


def _mhe(model, form, solver):
    return GPMHE(model, x0=[0.0, 0.0], horizon=4, Q0=1e-2, R0=1e-1, form=form, solver=solver,
                 x_bounds=([-3, -3], [3, 3]))


def _run(mhe, lo, hi):
    out = []
    for t in range(lo, hi):
        out.append((mhe.update(US[t], YS[t]).copy(), mhe.P.copy(), mhe.x_window.copy(), mhe.cost))
    return out


def _assert_same(a, b):
    assert len(a) == len(b)
    for (xa, Pa, wa, ca), (xb, Pb, wb, cb) in zip(a, b):
        assert_array_equal(xa, xb)
        assert_array_equal(Pa, Pb)
        assert_array_equal(wa, wb)
        assert ca == cb


def _checkpoint(mhe, model):
    buf = io.BytesIO()
    mhe.save(buf)
    buf.seek(0)
    return GPMHE.load(buf, model)


COPIES = {
    "deepcopy": lambda mhe, model: copy.deepcopy(mhe),
    "pickle": lambda mhe, model: pickle.loads(pickle.dumps(mhe)),
    "checkpoint": _checkpoint,
}


@pytest.mark.parametrize("how", sorted(COPIES))
@pytest.mark.parametrize("form", ["prediction", "filtering"])
@pytest.mark.parametrize("model_name", ["learned", "known"])
def test_gpmhe_copies_continue_bit_identically(how, form, model_name):
    model = LEARNED if model_name == "learned" else KNOWN
    solvers = ["gauss-newton"] + (["least-squares"] if how == "checkpoint" else [])
    for solver in solvers:
        reference = _run(_mhe(model, form, solver), 0, 20)
        for t in (0, 2, 9):  # before any update, while the window grows, after it is full
            mhe = _mhe(model, form, solver)
            _run(mhe, 0, t)
            other = COPIES[how](mhe, model)
            assert other.t == t
            # Both continue as the uninterrupted run, independently of each other.
            _assert_same(_run(mhe, t, 20), reference[t:])
            _assert_same(_run(other, t, 20), reference[t:])


def test_gpmhe_copy_is_independent():
    mhe = _mhe(LEARNED, "prediction", "gauss-newton")
    _run(mhe, 0, 6)
    other = copy.deepcopy(mhe)
    assert other._core is not mhe._core
    _run(other, 6, 9)  # advancing the copy leaves the original where it was
    assert (mhe.t, mhe._core.t) == (6, 6)
    assert (other.t, other._core.t) == (9, 9)


def test_filterpy_saver_records_independent_states():
    filterpy = pytest.importorskip("filterpy.common")
    mhe = _mhe(LEARNED, "prediction", "gauss-newton")
    saver = filterpy.Saver(mhe)
    for t in range(8):
        mhe.update(US[t], YS[t])
        saver.save()
    saver.to_array()
    assert saver.x.shape == (8, 2)
    assert_array_equal(saver.x[-1], mhe.x)
    # Each record holds its own core, at its own time.
    assert [c.t for c in saver._DL["_core"]] == list(range(1, 9))


def test_known_model_pickles_with_module_functions_and_names_a_lambda():
    model = reactor_known_model()
    other = pickle.loads(pickle.dumps(model))
    x, u = np.array([1.0, 2.0]), np.zeros(0)
    assert_array_equal(other.predict(x, u), model.predict(x, u))
    bad = KnownModel(br.f, lambda x, u: x[:1], dim_x=2, dim_y=1)
    with pytest.raises(pickle.PicklingError, match="h="):
        pickle.dumps(bad)
    with pytest.raises(pickle.PicklingError, match="h="):
        pickle.dumps(GPMHE(bad, x0=[1.0, 1.0]))
    assert copy.deepcopy(bad) is bad  # models are immutable: copies share them


def test_models_and_gps_copy_and_pickle():
    D = np.random.default_rng(0).uniform(-1, 1, (7, 3))
    for gp in (LEARNED.f_gp, LEARNED.h_gp):
        for other in (copy.deepcopy(gp), pickle.loads(pickle.dumps(gp))):
            for a, b in zip(gp.predict_with_gradients(D), other.predict_with_gradients(D)):
                assert_array_equal(a, b)
    single = GaussianProcess(optimizer=None).fit(D, D[:, 0])
    for other in (copy.deepcopy(single), pickle.loads(pickle.dumps(single))):
        assert_array_equal(other.predict(D), single.predict(D))
    model = pickle.loads(pickle.dumps(LEARNED))
    assert_array_equal(model.predict([0.1, 0.2], [0.3]), LEARNED.predict([0.1, 0.2], [0.3]))
    # The Rust objects on their own.
    core = LEARNED.f_gp._core_model
    assert_array_equal(pickle.loads(pickle.dumps(core)).predict(D)[0], core.predict(D)[0])
    solver = pickle.loads(pickle.dumps(_core.WindowSolver(max_iter=7, interior="never")))
    assert isinstance(solver, _core.WindowSolver)


def test_moving_horizon_state_is_validated_and_atomic():
    mhe = _mhe(LEARNED, "prediction", "gauss-newton")
    _run(mhe, 0, 6)
    core = mhe._core
    state = core.__getstate__()
    before = pickle.dumps(core)
    for key, value in [("u", state["u"][:-1]), ("priors", np.full_like(state["priors"], np.nan)),
                       ("t", 99), ("present", state["present"].astype(float)),
                       ("cache_mean_x", state["cache_mean_x"][:-1]),
                       ("window_t0", 0)]:
        bad = dict(state, **{key: value})
        with pytest.raises(ValueError, match=key.split("_")[0]):
            core.__setstate__(bad)
    with pytest.raises(ValueError, match="x_window"):
        core.__setstate__({k: v for k, v in state.items() if k != "x_window"})
    assert pickle.dumps(core) == before


# ----------------------------------------------------------------------------- RGP, RGPEKF

A0 = np.array([[1.0, 0.1], [-0.2, 0.9]])
E0 = np.array([[0.0, 0.0], [0.1, 0.05]])


def rgp_f(x, u, z):
    return A0 @ x + E0 @ np.asarray(z)


def rgp_A(x, u, z):
    return A0


def rgp_h(x):
    return np.array([x[0] ** 2 + x[1]])


def rgp_H(x):
    return np.array([[2 * x[0], 1.0]])


def _sparse_gps():
    """Sparse GPs on the two GP inputs' domains: 1-D VFE with a linear prior mean, 2-D FITC."""
    rng = np.random.default_rng(1)
    D1 = rng.uniform(-1, 1, (80, 1))
    D2 = rng.uniform([0, 0], [1, 2], (80, 2))
    return (SparseGaussianProcess(n_inducing=6, mean="linear").fit(D1, np.sin(3 * D1[:, 0]) + 0.5),
            SparseGaussianProcess(n_inducing=8, method="fitc").fit(D2, np.cos(D2).sum(axis=1)))


SPARSE_GPS = _sparse_gps()


def _rgpekf(pure_prediction, basis="grid"):
    """Two GPs: on grids, or (basis="sparse") from sparse GPs, one with σ_p > 0 and one without
    (stored whitened in the augmented filter)."""
    if basis == "grid":
        gps = [RecursiveGP(-1, 1, 6, sigma_K=1.2, L=1.0, sigma_r=0.1, sigma_p=0.03),
               RecursiveGP([0, 0], [1, 2], [3, 4], sigma_K=0.7, L=2.0, sigma_r=0.2)]
    else:
        gps = [RecursiveGP.from_sparse(SPARSE_GPS[0], sigma_r=0.1, sigma_p=0.03),
               RecursiveGP.from_sparse(SPARSE_GPS[1], sigma_r=0.2)]
    return RGPEKF(2, f=rgp_f, A=rgp_A, e=E0, h=rgp_h, H=rgp_H, Q_x=0.01 * np.eye(2), R_x=0.1,
                  x0=[0.3, 0.1], P0=np.eye(2), gps=gps, pure_prediction=pure_prediction)


_rng = np.random.default_rng(0)
RGP_STEPS = [([_rng.uniform(-1, 1), _rng.uniform([0, 0], [1, 2])], _rng.standard_normal(1))
             for _ in range(16)]


def _rgp_run(ekf, lo, hi):
    out = []
    for zeta, y in RGP_STEPS[lo:hi]:
        ekf.predict(None, zeta)
        ekf.update(y)
        out.append((ekf.mu.copy(), ekf.C.copy(), ekf.log_likelihood))
    return out


def _rgp_checkpoint(ekf):
    buf = io.BytesIO()
    ekf.save(buf)
    buf.seek(0)
    return RGPEKF.load(buf, f=rgp_f, h=rgp_h, A=rgp_A, H=rgp_H)


RGP_COPIES = {"deepcopy": copy.deepcopy, "pickle": lambda e: pickle.loads(pickle.dumps(e)),
              "checkpoint": _rgp_checkpoint}


@pytest.mark.parametrize("basis", ["grid", "sparse"])
@pytest.mark.parametrize("how", sorted(RGP_COPIES))
@pytest.mark.parametrize("pure_prediction", [False, True])
def test_rgpekf_copies_continue_bit_identically(how, pure_prediction, basis):
    reference = _rgp_run(_rgpekf(pure_prediction, basis), 0, 16)
    for t in (0, 7):
        ekf = _rgpekf(pure_prediction, basis)
        _rgp_run(ekf, 0, t)
        other = RGP_COPIES[how](ekf)
        for name in ("x", "P", "z_pred", "mu", "C", "y", "S"):
            assert_array_equal(getattr(other, name), getattr(ekf, name), err_msg=name)
        assert_array_equal(other.log_likelihood, ekf.log_likelihood)  # NaN before any update
        for filt in (ekf, other):
            got = _rgp_run(filt, t, 16)
            assert len(got) == len(reference[t:])
            for (m, C, ll), (mr, Cr, llr) in zip(got, reference[t:]):
                assert_array_equal(m, mr)
                assert_array_equal(C, Cr)
                assert ll == llr
    # Between predict and update, too.
    ekf = _rgpekf(pure_prediction, basis)
    _rgp_run(ekf, 0, 7)
    ekf.predict(None, RGP_STEPS[7][0])
    other = RGP_COPIES[how](ekf)
    other.update(RGP_STEPS[7][1])
    assert_array_equal(_rgp_run(other, 8, 16)[-1][1], reference[-1][1])


def test_recursive_gp_copies_and_pickles():
    gp = RecursiveGP(-1, 1, 6)
    gp.update([0.3, -0.5], [1.0, 0.2], 0.01)
    for other in (copy.deepcopy(gp), pickle.loads(pickle.dumps(gp))):
        other.update(0.5, 2.0, 0.01)
        gp_next = gp.copy()
        gp_next.update(0.5, 2.0, 0.01)
        assert_array_equal(other.cov, gp_next.cov)
        assert_array_equal(other.mean, gp_next.mean)
    assert gp.mean[0] != other.mean[0] or not np.array_equal(gp.cov, other.cov)


def test_rgpekf_checkpoints_of_the_first_format_still_load():
    """A version-1 file (grids only, no 'gp<i>_basis' entries) loads and continues exactly."""
    ekf = _rgpekf(False)
    _rgp_run(ekf, 0, 5)
    buf = io.BytesIO()
    ekf.save(buf)
    entries = {k: v for k, v in _entries(buf.getvalue()).items() if not k.endswith("_basis")}
    assert {k for k in _entries(buf.getvalue())} - set(entries) == {"gp0_basis", "gp1_basis"}
    old = io.BytesIO()
    np.savez(old, **{**entries, "format_version": 1})
    old.seek(0)
    loaded = RGPEKF.load(old, f=rgp_f, h=rgp_h, A=rgp_A, H=rgp_H)
    for got, want in zip(_rgp_run(loaded, 5, 16), _rgp_run(ekf, 5, 16)):
        assert_array_equal(got[1], want[1])
    # A version-2 file with an unknown basis is refused, naming the entry.
    bad = io.BytesIO()
    np.savez(bad, **{**_entries(buf.getvalue()), "gp1_basis": "hexagonal"})
    bad.seek(0)
    with pytest.raises(ValueError, match="'gp1_basis' must be 'grid' or 'points'"):
        RGPEKF.load(bad, f=rgp_f, h=rgp_h, A=rgp_A, H=rgp_H)


def test_recursive_gp_from_sparse_copies_and_pickles():
    gp = RecursiveGP.from_sparse(SPARSE_GPS[0], sigma_r=0.05)
    gp.update([0.3, -0.5], [1.0, 0.2], 0.01)
    for other in (copy.deepcopy(gp), pickle.loads(pickle.dumps(gp)), gp.copy()):
        assert (other.n_points, other.lower) == (None, None)
        assert_array_equal(other.prior_mean, gp.prior_mean)
        other.update(0.5, 2.0, 0.01)
        gp_next = gp.copy()
        gp_next.update(0.5, 2.0, 0.01)
        assert_array_equal(other.cov, gp_next.cov)
        assert_array_equal(other.mean, gp_next.mean)
    assert not np.array_equal(gp.mean, other.mean)


def test_rgpekf_filterpy_saver():
    filterpy = pytest.importorskip("filterpy.common")
    ekf = _rgpekf(False)
    saver = filterpy.Saver(ekf)
    for zeta, y in RGP_STEPS[:5]:
        ekf.predict(None, zeta)
        ekf.update(y)
        saver.save()
    saver.to_array()
    assert saver.x.shape == (5, 2)
    assert_array_equal(saver.P[-1], ekf.P)


def test_rgpekf_load_needs_the_functions_it_was_built_with():
    buf = io.BytesIO()
    _rgpekf(False).save(buf)
    buf.seek(0)
    with pytest.raises(ValueError, match="^A: "):
        RGPEKF.load(buf, f=rgp_f, h=rgp_h, H=rgp_H)


# ----------------------------------------------------------------------------- damaged files


def _saved(kind):
    """(bytes of a saved file of `kind`, its loader)."""
    buf = io.BytesIO()
    if kind == "GaussianProcess":
        D = np.random.default_rng(1).uniform(-1, 1, (6, 2))
        GaussianProcess(optimizer=None).fit(D, D[:, 0]).save(buf)
        load = GaussianProcess.load
    elif kind == "MultiOutputGP":
        LEARNED.f_gp.save(buf)
        load = MultiOutputGP.load
    elif kind == "LearnedModel":
        LEARNED.save(buf)
        load = LearnedModel.load
    elif kind == "GPMHE":
        mhe = _mhe(LEARNED, "filtering", "gauss-newton")
        _run(mhe, 0, 6)
        mhe.save(buf)

        def load(path):
            return GPMHE.load(path, LEARNED)
    else:
        ekf = _rgpekf(False, "sparse" if kind == "RGPEKF[sparse]" else "grid")
        _rgp_run(ekf, 0, 3)
        ekf.save(buf)

        def load(path):
            return RGPEKF.load(path, f=rgp_f, h=rgp_h, A=rgp_A, H=rgp_H)
    return buf.getvalue(), load


KINDS = ["GaussianProcess", "MultiOutputGP", "LearnedModel", "GPMHE", "RGPEKF", "RGPEKF[sparse]"]


def _entries(data):
    with np.load(io.BytesIO(data), allow_pickle=False) as f:
        return {k: f[k] for k in f.files}


def _write(path, entries):
    np.savez(path, **entries)
    return path


@pytest.mark.parametrize("kind", KINDS)
def test_a_file_missing_any_entry_raises_naming_it(kind, tmp_path):
    data, load = _saved(kind)
    entries = _entries(data)
    load(io.BytesIO(data))  # the complete file loads
    # Optional: h_gp (a model without outputs), a LearnedModel's version (older files have none).
    optional = {"h_gp"} | ({"format_version"} if kind == "LearnedModel" else set())
    for key in entries:
        if key in optional:
            continue
        path = _write(tmp_path / f"no_{key}.npz", {k: v for k, v in entries.items() if k != key})
        with pytest.raises(ValueError, match=f"no_{key}.npz") as err:
            load(path)
        assert repr(key) in str(err.value) or (key == "kind" and "not a saved" in str(err.value))


@pytest.mark.parametrize("kind", KINDS)
def test_an_entry_of_the_wrong_dtype_or_shape_raises_naming_it(kind, tmp_path):
    data, load = _saved(kind)
    entries = _entries(data)
    for key, value in entries.items():
        if key in ("kind", "format_version"):
            continue
        wrong = np.zeros(value.shape) if value.dtype.kind == "U" else \
            np.array(["text"] * max(value.size, 1)).reshape(value.shape)
        for label, bad in (("dtype", wrong), ("shape", np.zeros(value.shape + (2,)))):
            path = _write(tmp_path / f"{label}_{key}.npz", dict(entries, **{key: bad}))
            with pytest.raises(ValueError, match=f"{label}_{key}.npz") as err:
                load(path)
            assert key in str(err.value), (key, label, str(err.value))


@pytest.mark.parametrize("kind", KINDS)
def test_truncated_foreign_and_non_npz_files_raise(kind, tmp_path):
    data, load = _saved(kind)
    half = tmp_path / "half.npz"
    half.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="half.npz"):
        load(half)
    text = tmp_path / "notes.npz"
    text.write_text("not an archive\n")
    with pytest.raises(ValueError, match="notes.npz"):
        load(text)
    npy = tmp_path / "array.npy"
    np.save(npy, np.zeros(3))
    with pytest.raises(ValueError, match="array.npy"):
        load(npy)
    other_kind = "GPMHE" if kind.startswith("RGPEKF") else "RGPEKF"
    other = tmp_path / "other.npz"
    other.write_bytes(_saved(other_kind)[0])
    with pytest.raises(ValueError, match="other.npz"):
        load(other)
    # A member whose bytes are damaged (the archive's index intact).
    damaged = tmp_path / "damaged.npz"
    with zipfile.ZipFile(io.BytesIO(data)) as src, zipfile.ZipFile(damaged, "w") as dst:
        for info in src.infolist():
            raw = src.read(info)
            dst.writestr(info, raw[: len(raw) // 2] if info.filename != "kind.npy" else raw)
    with pytest.raises(ValueError, match="damaged.npz"):
        load(damaged)


def test_gpmhe_load_checks_the_model(tmp_path):
    data, _ = _saved("GPMHE")
    with pytest.raises(ValueError, match="^model: "):
        GPMHE.load(io.BytesIO(data), KNOWN)
    with pytest.raises(ValueError, match="^model: "):
        GPMHE.load(io.BytesIO(data), reactor_known_model())


def test_a_checkpoint_of_the_previous_format_loads_and_continues_as_it_would_have():
    """tests/data/gpmhe_checkpoint_format2.npz was written by gpmhe with checkpoint format 2 (the
    estimate and the last report kept as attributes beside the core's state) after 8 updates of
    the batch reactor in the filtering form; ..._continuation.npz holds what that estimator gave
    on the next 6 outputs. Loaded now, it continues bit for bit the same."""
    import pathlib

    from gpmhe import GPMHE, KnownModel
    from gpmhe.systems import batch_reactor as br

    data = pathlib.Path(__file__).with_name("data")
    model = KnownModel(br.f, br.h, dim_x=2, dim_y=1)
    est = GPMHE.load(data / "gpmhe_checkpoint_format2.npz", model)
    ref = np.load(data / "gpmhe_checkpoint_format2_continuation.npz")
    assert est.t == 8 and est.form == "filtering" and est.horizon == 5
    xs = np.array([est.update(None, ref["y"][t]).copy() for t in range(8, 14)])
    np.testing.assert_array_equal(xs, ref["xs"])
    # P was 4H⁻¹ when the file was written; with η < 1 it is now the discounted estimate's
    # covariance 4H⁻¹GH⁻¹, never larger (G ≤ H).
    assert est.eta < 1
    assert np.linalg.eigvalsh(ref["P"] - est.P).min() > -1e-15 and np.all(np.diag(est.P) > 0)
    assert est.cost == ref["cost"] and est.t == ref["t"]
