"""Learned models: prior means (against scikit-learn and a numpy formula), hyperpriors (against a
direct computation of the MAP objective; the named "residual" prior), fit diagnostics (the
collapse warning fires on a collapsed fit and not on a good one), nominal model plus GP residual
(against f0 + m(d) and its Jacobian; with the true f0 the residual is ~0 and the estimates match
the exact-model MHE; the residual defaults carry a correction beyond the training data), and
training from logs with missing samples and subsampling."""

import io
import pickle
import warnings

import numpy as np
import pytest
import scipy.optimize

from conftest import reactor_known_model
from gpmhe import GPMHE, GaussianProcess, LearnedModel, MultiOutputGP, _core
from gpmhe.gp.diagnostics import FitWarning
from gpmhe.systems import batch_reactor as br

RNG = np.random.default_rng(3)
D1 = np.sort(RNG.uniform(0.0, 5.0, 40))[:, None]
Y1 = 1.5 * D1[:, 0] - 2.0 + np.sin(2.0 * D1[:, 0]) + 0.05 * RNG.standard_normal(40)


# ----------------------------------------------------------------------------- prior means


def test_constant_mean_matches_scikit_learn_normalize_y_mean_shift():
    """scikit-learn's GPR with normalize_y and a kernel fixed at theta equals a constant prior
    mean when the kernel is rescaled by the targets' variance (its normalisation)."""
    sk = pytest.importorskip("sklearn.gaussian_process")
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    sf, ls, se, s = 0.8, 0.7, 0.1, float(np.std(Y1))
    kernel = ConstantKernel(sf**2, "fixed") * RBF(ls, "fixed") + WhiteKernel(se**2, "fixed")
    gpr = sk.GaussianProcessRegressor(kernel, optimizer=None, normalize_y=True).fit(D1, Y1)
    ours = GaussianProcess(sigma_f=sf * s, lengthscales=ls, sigma_eps=se * s, optimizer=None,
                           mean="constant").fit(D1, Y1)
    T = np.linspace(-1.0, 6.0, 9)[:, None]
    m_sk, s_sk = gpr.predict(T, return_std=True)
    m, std = ours.predict(T, return_std=True)
    np.testing.assert_allclose(m, m_sk, rtol=1e-7, atol=1e-8)
    # scikit-learn's std includes the white noise; ours is latent.
    np.testing.assert_allclose(std**2 + (se * s) ** 2, s_sk**2, rtol=1e-8)
    np.testing.assert_allclose(ours.mean_coefficients, [np.mean(Y1), 0.0])


def test_linear_mean_predictions_and_gradients_match_a_dense_numpy_formula():
    D = RNG.uniform(-1.0, 1.0, (30, 2))
    Y = np.column_stack([D @ [2.0, -1.0] + 0.3 * np.sin(3 * D[:, 0]), np.cos(D[:, 1])])
    gp = MultiOutputGP(sigma_f=0.5, lengthscales=[0.6, 0.9], sigma_eps=0.05, optimizer=None,
                       mean="linear").fit(D, Y)
    A = np.hstack([np.ones((30, 1)), D])
    coef = np.linalg.lstsq(A, Y, rcond=None)[0].T
    np.testing.assert_allclose(gp.mean_coefficients, coef, rtol=1e-10, atol=1e-12)
    T = RNG.uniform(-1.5, 1.5, (7, 2))
    mean, var, dmean, _ = gp.predict_with_gradients(T)
    for o in range(2):
        K = _core.se_ard_kernel(D, D, 0.5, np.array([0.6, 0.9])) + 0.05**2 * np.eye(30)
        Ks = _core.se_ard_kernel(T, D, 0.5, np.array([0.6, 0.9]))
        r = Y[:, o] - A @ coef[o]
        alpha = np.linalg.solve(K, r)
        m_ref = coef[o, 0] + T @ coef[o, 1:] + Ks @ alpha
        v_ref = 0.25 - np.sum(Ks * np.linalg.solve(K, Ks.T).T, axis=1)
        np.testing.assert_allclose(mean[:, o], m_ref, rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(var[:, o], v_ref, rtol=1e-7, atol=1e-10)
        h = 1e-6
        for j in range(2):
            e = np.zeros(2)
            e[j] = h
            fd = (gp.predict(T + e)[:, o] - gp.predict(T - e)[:, o]) / (2 * h)
            np.testing.assert_allclose(dmean[:, o, j], fd, rtol=1e-6, atol=1e-7)


def test_prior_mean_survives_pickle_save_load_and_theta_setter():
    gp = GaussianProcess(mean="linear", normalize=True, hyperprior="default").fit(D1, Y1)
    T = np.linspace(0.0, 6.0, 5)[:, None]
    buf = io.BytesIO()
    gp.save(buf)
    buf.seek(0)
    for other in (pickle.loads(pickle.dumps(gp)), GaussianProcess.load(buf)):
        assert np.array_equal(other.predict(T), gp.predict(T))
        assert other.mean == "linear" and other.hyperprior == "default" and other.normalize
    before = gp.predict(T)
    gp.theta = gp.theta  # refactor at the same theta keeps the mean
    assert np.array_equal(gp.predict(T), before)


# ----------------------------------------------------------------------------- hyperpriors


def test_map_fit_maximises_lml_plus_the_log_normal_prior_in_standardised_units():
    prior = {"sigma_f": (0.5, 1.0), "lengthscales": (2.0, 0.5), "sigma_eps": (0.05, 2.0)}
    gp = GaussianProcess(mean="linear", normalize=True, hyperprior=prior).fit(D1, Y1)
    A = np.hstack([np.ones((40, 1)), D1])
    r = Y1 - A @ np.linalg.lstsq(A, Y1, rcond=None)[0]
    shift = np.log([np.std(r), np.std(D1), np.std(r)])
    mu, sd = np.log([0.5, 2.0, 0.05]), np.array([1.0, 0.5, 2.0])

    def neg(t):  # independent: the core's LML at natural theta plus the prior of standardised theta
        lml = _core.log_marginal_likelihood(D1, r, t + shift, False)[0]
        return -(lml - 0.5 * np.sum(((t - mu) / sd) ** 2))

    ref = scipy.optimize.minimize(neg, mu, method="Nelder-Mead",
                                  options={"xatol": 1e-9, "fatol": 1e-12, "maxiter": 20000})
    np.testing.assert_allclose(gp.theta, ref.x + shift, atol=1e-4)
    assert -ref.fun <= gp.diagnostics()[0].restarts.max() + 1e-8


def test_hyperprior_keeps_the_reactor_fits_off_the_bounds():
    states, outputs = br.training_data(5, rng=np.random.default_rng(1))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        paper = LearnedModel.from_trajectories(states, outputs, random_state=1, warn=False,
                                               mean="zero", normalize=False, hyperprior=None)
        default = LearnedModel.from_trajectories(states, outputs, random_state=1, warn=False)
    assert np.max(paper.f_gp.lengthscales) > 100  # the paper's fit runs towards its bound
    for dg in default.diagnostics()["f"] + default.diagnostics()["h"]:
        assert dg.warnings == [] and dg.sigma_f < 1.0


def test_named_residual_hyperprior_is_its_dict_and_survives_save_load():
    spec = {"sigma_f": (0.1, 1.5), "lengthscales": (10.0, 1.5), "sigma_eps": (1.0, 1.5)}
    named = GaussianProcess(normalize=True, hyperprior="residual", n_restarts=2, random_state=0).fit(D1, Y1)
    given = GaussianProcess(normalize=True, hyperprior=spec, n_restarts=2, random_state=0).fit(D1, Y1)
    default = GaussianProcess(normalize=True, hyperprior="default", n_restarts=2, random_state=0).fit(D1, Y1)
    np.testing.assert_array_equal(named.theta, given.theta)
    assert not np.allclose(named.theta, default.theta, atol=1e-3)  # a different prior, a different fit
    buf = io.BytesIO()
    named.save(buf)
    buf.seek(0)
    loaded = GaussianProcess.load(buf)
    assert loaded.hyperprior == "residual"
    np.testing.assert_array_equal(loaded.predict(D1[:5]), named.predict(D1[:5]))


def test_bad_prior_options_are_refused_naming_the_argument():
    for kwargs, name in (({"mean": "quadratic"}, "mean"), ({"normalize": 1}, "normalize"),
                         ({"hyperprior": "flat"}, "hyperprior"),
                         ({"hyperprior": {"sigma_f": (-1.0, 1.0)}}, "hyperprior"),
                         ({"hyperprior": {"noise": (1.0, 1.0)}}, "hyperprior")):
        with pytest.raises(ValueError, match=name):
            GaussianProcess(**kwargs)


# ----------------------------------------------------------------------------- diagnostics


def test_collapse_warning_fires_on_a_collapsed_fit_and_not_on_a_good_one():
    rng = np.random.default_rng(0)
    X = [np.cumsum(rng.normal(0, 0.3, (60, 1)), axis=0) for _ in range(3)]
    Y = [x.copy() for x in X]
    collapsed = dict(optimizer=None, sigma_f=1e-3, sigma_eps=1.0, mean="zero")
    with pytest.warns(FitWarning, match="f-GP 1: collapsed"):
        LearnedModel.from_trajectories(X, Y, **collapsed)
    with warnings.catch_warnings():
        warnings.simplefilter("error", FitWarning)
        good = LearnedModel.from_trajectories(X, Y, random_state=0)
    dg = good.diagnostics()["f"][0]
    assert not dg.collapsed and dg.at_lower == () and len(dg.restarts) == 1
    assert "no problems found" in good.summary()


def test_loo_errors_match_refitting_without_each_point():
    gp = GaussianProcess(sigma_f=1.2, lengthscales=0.8, sigma_eps=0.1, optimizer=None,
                         mean="linear").fit(D1[:15], Y1[:15])
    r = Y1[:15] - (gp.mean_coefficients[0] + gp.mean_coefficients[1] * D1[:15, 0])
    errs = []
    for i in range(15):
        keep = np.arange(15) != i
        loo = GaussianProcess(sigma_f=1.2, lengthscales=0.8, sigma_eps=0.1, optimizer=None).fit(D1[:15][keep], r[keep])
        errs.append(r[i] - loo.predict(D1[i:i + 1])[0])
    np.testing.assert_allclose(gp.diagnostics()[0].loo_rmse, np.sqrt(np.mean(np.square(errs))), rtol=1e-8)


def test_bound_detection_names_the_hyperparameter():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gp = GaussianProcess(bounds=((1e-3, 1e3), (1e-3, 1e3), (0.5, 1.0))).fit(D1, Y1)
    assert gp.diagnostics()[0].at_lower == ("sigma_eps",)


# ----------------------------------------------------------------------------- nominal + residual


def _f0_batch(X, U):  # the reactor with k1 30 % off
    k1 = 0.7 * br.K1
    x1, x2 = X[:, 0], X[:, 1]
    return np.column_stack([x1 + br.T * (-2 * k1 * x1**2 + 2 * br.K2 * x2), x2 + br.T * (k1 * x1**2 - br.K2 * x2)])


def test_residual_model_is_f0_plus_the_gp_with_jacobians():
    states, outputs = br.training_data(3, rng=np.random.default_rng(2))
    model = LearnedModel.from_trajectories(states, outputs, f_nominal=_f0_batch, h_nominal=br.h_batch,
                                           nominal_options={"vectorized": True}, random_state=0, warn=False)
    d = np.array([[2.0, 3.0], [0.5, 4.0], [3.5, 0.5]])
    mx, vx, dmx, _, my, vy, dmy, _ = model.stage_eval(d)
    gm, gv, gdm, _ = model.f_gp.predict_with_gradients(d)
    np.testing.assert_allclose(mx, _f0_batch(d, None) + gm, rtol=1e-12)
    np.testing.assert_allclose(vx, gv)
    J0 = np.array([[[1 - 4 * br.T * 0.7 * br.K1 * x1, 2 * br.T * br.K2],
                    [2 * br.T * 0.7 * br.K1 * x1, 1 - br.T * br.K2]] for x1 in d[:, 0]])
    np.testing.assert_allclose(dmx, J0 + gdm, atol=1e-7)
    np.testing.assert_allclose(my, br.h_batch(d, None) + model.h_gp.predict(d), rtol=1e-12)
    np.testing.assert_allclose(model.predict(d[0]), mx[0], rtol=1e-12)


def test_with_the_true_f0_the_residual_is_near_zero_and_estimates_match_the_exact_mhe():
    states, outputs = br.training_data(3, rng=np.random.default_rng(4))
    model = LearnedModel.from_trajectories(states, outputs, f_nominal=br.f, h_nominal=br.h,
                                           random_state=0, warn=False)
    grid = np.array([[x1, x2] for x1 in (0.5, 1.5, 2.5) for x2 in (1.0, 2.5, 4.0)])
    resid_f = model.f_gp.predict(grid)
    assert np.max(np.abs(resid_f)) < 1e-2  # below the 1e-2 noise on the training states
    x_true, y = br.simulate(br.X_TRUE0, 40, np.random.default_rng(5))
    # Along the run (x2 below the training data's range) the residuals fitted to pure noise stay
    # small too: below a tenth of the 0.1 output noise for h.
    assert np.max(np.abs(model.f_gp.predict(x_true))) < 1e-2
    assert np.max(np.abs(model.h_gp.predict(x_true))) < 1e-2
    est = {name: GPMHE(m, br.X_PRIOR0, x_bounds=br.X_BOUNDS, **br.MHE_SETTINGS)
           for name, m in (("residual", model), ("exact", reactor_known_model(True)))}
    xs = {name: [] for name in est}
    for t in range(40):
        for name, e in est.items():
            e.update(None, y[t])
            xs[name].append(e.x.copy())
    late = slice(20, 40)  # after the transient from the poor prior
    diff = np.sqrt(np.mean(np.sum((np.array(xs["residual"]) - np.array(xs["exact"]))[late] ** 2, axis=1)))
    err = np.sqrt(np.mean(np.sum((np.array(xs["exact"]) - x_true[:40])[late] ** 2, axis=1)))
    assert diff < 0.3 * err, (diff, err)  # the two estimators differ far less than they err


def test_a_nominal_model_switches_the_defaults_to_the_residual_settings():
    states, outputs = br.training_data(3, rng=np.random.default_rng(2))
    fit = dict(optimizer=None, warn=False)
    residual = LearnedModel.from_trajectories(states, outputs, f_nominal=_f0_batch,
                                              nominal_options={"vectorized": True}, **fit)
    alone = LearnedModel.from_trajectories(states, outputs, **fit)
    told = LearnedModel.from_trajectories(states, outputs, f_nominal=_f0_batch, hyperprior="default",
                                          mean="linear", nominal_options={"vectorized": True}, **fit)
    for gp in (residual.f_gp, residual.h_gp):
        assert (gp.mean, gp.normalize, gp.hyperprior) == ("zero", True, "residual")
    for gp in (alone.f_gp, alone.h_gp):
        assert (gp.mean, gp.normalize, gp.hyperprior) == ("linear", True, "default")
    assert (told.f_gp.mean, told.f_gp.hyperprior) == ("linear", "default")  # options win


@pytest.mark.parametrize("seed", [2, 3])
def test_residual_defaults_carry_the_correction_to_where_the_estimator_runs(seed):
    """The reactor's training data have x2 >= 3, a run from [3, 1] has x2 < 2.5 for its first 30
    steps. The residual of the k1-off model depends on x1 only: with the residual defaults the
    GP carries it there (long length-scale in x2), with the full model's hyperprior it fades
    back to the nominal model's error within a spread of the data."""
    states, outputs = br.training_data(3, rng=np.random.default_rng(seed))
    kw = dict(f_nominal=_f0_batch, h_nominal=br.h_batch, nominal_options={"vectorized": True},
              random_state=0, warn=False)
    residual = LearnedModel.from_trajectories(states, outputs, **kw)
    default = LearnedModel.from_trajectories(states, outputs, hyperprior="default", **kw)
    x, _ = br.simulate(br.X_TRUE0, 30, np.random.default_rng(100 + seed))
    P = x[:30]
    assert np.max(P[:, 1]) < np.min(np.vstack(states)[:, 1])  # outside the data

    def one_step_rmse(mean):
        return np.sqrt(np.mean((mean - br.f_batch(P)) ** 2))

    e_res, e_def = (one_step_rmse(m.stage_eval(P)[0]) for m in (residual, default))
    e_nom = one_step_rmse(_f0_batch(P, None))
    assert e_res < 0.9 * e_def and e_res < 0.8 * e_nom, (e_res, e_def, e_nom)
    ls = residual.f_gp.lengthscales[0]  # the x1-residual's length-scales: short in x1, long in x2
    assert ls[1] > 2 * ls[0], ls


def test_nominal_options_are_checked_and_save_needs_the_nominal():
    states, outputs = br.training_data(3, rng=np.random.default_rng(2))
    with pytest.raises(ValueError, match="nominal_options"):
        LearnedModel.from_trajectories(states, outputs, f_nominal=br.f, nominal_options={"jac": 1})
    with pytest.raises(ValueError, match="f_residual"):
        LearnedModel.from_trajectories(states, outputs, f_nominal=br.f, f_residual=True)
    model = LearnedModel.from_trajectories(states, outputs, f_nominal=br.f, optimizer=None, warn=False)
    assert model.nominal.h(np.ones(2), np.zeros(0)).shape == (1,)  # a zero h0
    buf = io.BytesIO()
    model.save(buf)
    buf.seek(0)
    with pytest.raises(ValueError, match="nominal"):
        LearnedModel.load(buf)
    buf.seek(0)
    loaded = LearnedModel.load(buf, nominal=model.nominal)
    assert np.array_equal(loaded.predict([1.0, 2.0]), model.predict([1.0, 2.0]))
    clone = pickle.loads(pickle.dumps(model))
    assert np.array_equal(clone.stage_eval([[1.0, 2.0]])[0], model.stage_eval([[1.0, 2.0]])[0])


# ----------------------------------------------------------------------------- training from logs


def test_missing_samples_drop_only_the_rows_that_need_them():
    states, outputs = br.training_data(3, rng=np.random.default_rng(6))
    holey_x, holey_y = [s.copy() for s in states], [o.copy() for o in outputs]
    holey_x[0][5, 1] = np.nan  # loses transitions 4->5 and 5->6 and output sample 5
    holey_y[1][7] = np.nan  # loses output sample 7 of trajectory 1 only
    model = LearnedModel.from_trajectories(holey_x, holey_y, optimizer=None, warn=False)
    full = LearnedModel.from_trajectories(states, outputs, optimizer=None, warn=False)
    assert model.f_gp.D_train.shape[0] == full.f_gp.D_train.shape[0] - 2
    assert model.h_gp.D_train.shape[0] == full.h_gp.D_train.shape[0] - 2
    assert np.all(np.isfinite(model.f_gp.D_train)) and np.all(np.isfinite(model.h_gp.y_train))
    with pytest.raises(ValueError, match="inf"):
        LearnedModel.from_trajectories([np.full((3, 2), np.inf)], [np.zeros(3)])


def test_trajectories_of_different_lengths_and_subsampling():
    rng = np.random.default_rng(7)
    X = [rng.normal(size=(n, 2)) for n in (11, 31, 6)]
    Y = [x[:, :1] for x in X]
    model = LearnedModel.from_trajectories(X, Y, optimizer=None, warn=False)
    assert model.f_gp.D_train.shape[0] == 10 + 30 + 5
    small = LearnedModel.from_trajectories(X, Y, optimizer=None, warn=False, max_points=20)
    assert small.f_gp.D_train.shape[0] == 20 and small.h_gp.D_train.shape[0] == 20
    with pytest.raises(ValueError, match="max_points"):
        LearnedModel.from_trajectories(X, Y, max_points=1)


def test_stage_eval_follows_a_gp_refitted_after_the_model_was_built():
    """LearnedModel.stage_eval and predict read the core's view of the GPs, which is cached; a GP
    whose theta is set afterwards (refitted in place) is read afresh, as the GP itself predicts."""
    states, outputs = br.training_data(3, rng=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = LearnedModel.from_trajectories(states, outputs, n_restarts=0, random_state=0)
    d = np.array([[2.0, 1.0], [1.0, 3.0]])
    before = model.stage_eval(d)[0].copy()
    theta = model.f_gp.theta.copy()
    theta[:, 1] += 0.3
    model.f_gp.theta = theta
    after = model.stage_eval(d)[0]
    assert not np.array_equal(before, after)
    np.testing.assert_allclose(after, model.f_gp.predict(d), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(model.predict(d[0]), model.f_gp.predict(d[:1])[0], rtol=1e-12)
