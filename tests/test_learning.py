"""GPMHE with learning=True: the sparse f-GPs' inducing outputs estimated with the states
(python/gpmhe/mhe/estimator.py, rust/src/mhe/learning*.rs). The core's identities (the recursive
GP's posterior with the states measured, the Kalman filter of the pair on a linear model) are in
its own tests; these check the Python side: validation, the invariance without information,
copies, pickles and checkpoints, the learned model, the bank's refusal."""

import copy
import io
import pickle

import numpy as np
import pytest

from gpmhe import GPMHE, EstimatorBank, KnownModel, LearnedModel, SparseMultiOutputGP
from gpmhe.systems import batch_reactor as br

SETTINGS = dict(horizon=8, eta=0.91, P0=np.eye(2), Q0=1e-3, R0=1e-2, x_bounds=br.X_BOUNDS)


@pytest.fixture(scope="module")
def sparse_model():
    states, outputs = br.training_data(5, rng=0)
    return LearnedModel.from_trajectories(states, outputs, n_inducing=10)


@pytest.fixture(scope="module")
def run():
    return br.simulate(br.X_TRUE0, 40, np.random.default_rng(3))


def learner(model, drift=0.0, **kw):
    return GPMHE(model, x0=[3.0, 1.0], **{**SETTINGS, **kw}, learning=True,
                 learning_options={"drift": drift})


def test_settings_are_validated(sparse_model):
    states, outputs = br.training_data(5, rng=0, steps=10)
    exact = LearnedModel.from_trajectories(states, outputs)
    with pytest.raises(ValueError, match="learning: needs sparse f-GPs"):
        GPMHE(exact, x0=[3.0, 1.0], **SETTINGS, learning=True)
    known = KnownModel(br.f, br.h, dim_x=2, dim_y=1)
    with pytest.raises(ValueError, match="learning: needs a LearnedModel"):
        GPMHE(known, x0=[3.0, 1.0], **SETTINGS, learning=True)
    with pytest.raises(ValueError, match="learning: needs solver='gauss-newton'"):
        GPMHE(sparse_model, x0=[3.0, 1.0], **SETTINGS, learning=True, solver="least-squares")
    with pytest.raises(ValueError, match="learning_options: given without learning=True"):
        GPMHE(sparse_model, x0=[3.0, 1.0], **SETTINGS, learning_options={"drift": 1e-6})
    with pytest.raises(ValueError, match="learning_options: unknown option 'forget'"):
        GPMHE(sparse_model, x0=[3.0, 1.0], **SETTINGS, learning=True,
              learning_options={"forget": 1})
    with pytest.raises(ValueError, match="drift"):
        learner(sparse_model, drift=-1.0)
    with pytest.raises(ValueError, match="learning"):
        EstimatorBank(sparse_model, 2, [[3.0, 1.0]] * 2, **SETTINGS, learning=True)
    est = learner(sparse_model, drift=1e-7)
    assert est.learning and est.learning_options == {"drift": 1e-7}
    plain = GPMHE(sparse_model, x0=[3.0, 1.0], **SETTINGS)
    assert not plain.learning and plain.learning_options == {} and plain.learned_model is None


def test_without_outputs_or_drift_the_model_does_not_move(sparse_model):
    est = learner(sparse_model)
    g0, P0 = est._core.learning
    for _ in range(12):
        est.update(None, None)
    g, P = est._core.learning
    np.testing.assert_allclose(g, g0, rtol=0, atol=1e-10)
    np.testing.assert_allclose(P, P0, rtol=0, atol=1e-12)
    D = np.array([[2.0, 1.0], [0.5, 2.5]])
    mean, std = est.learned_model.f_gp.predict(D, return_std=True)
    mean0, std0 = sparse_model.f_gp.predict(D, return_std=True)
    np.testing.assert_allclose(mean, mean0, atol=1e-9)
    np.testing.assert_allclose(std, std0, atol=1e-9)


def test_learning_moves_the_model_and_its_uncertainty_shrinks(sparse_model, run):
    x, y = run
    est = learner(sparse_model)
    _, P0 = est._core.learning
    for t in range(40):
        est.update(None, y[t])
        assert est.success and np.all(np.isfinite(est.x))
    g, P = est._core.learning
    # Without drift data only add information: P ⪯ P0 (and P stays positive definite).
    assert np.trace(P) < np.trace(P0)
    assert np.linalg.eigvalsh(P0 - P).min() > -1e-12 * np.trace(P0)
    assert np.all(np.linalg.eigvalsh(P) > 0)
    assert not np.allclose(g, est._stage.fitted_posterior()[0], rtol=0, atol=1e-8)
    # The estimate stays as good as the fixed model's on the plant it was trained on.
    fixed = GPMHE(sparse_model, x0=[3.0, 1.0], **SETTINGS)
    xs = np.array([fixed.update(None, y[t]).copy() for t in range(40)])
    est2 = learner(sparse_model)
    xl = np.array([est2.update(None, y[t]).copy() for t in range(40)])
    rmse = lambda e: np.sqrt(np.mean(e ** 2))
    assert rmse(xl - x[1:41]) <= 1.05 * rmse(xs - x[1:41])


def test_copies_pickles_and_checkpoints_continue_bit_for_bit(sparse_model, run, tmp_path):
    _, y = run
    est = learner(sparse_model, drift=1e-7)
    for t in range(15):
        est.update(None, y[t])
    path = tmp_path / "learner.npz"
    est.save(path)
    others = [copy.deepcopy(est), pickle.loads(pickle.dumps(est)), GPMHE.load(path, sparse_model)]
    for t in range(15, 30):
        a = est.update(None, y[t]).copy()
        for o in others:
            assert np.array_equal(o.update(None, y[t]), a)
            assert np.array_equal(o._core.learning[0], est._core.learning[0])
            assert np.array_equal(o.P, est.P)
            assert np.array_equal(o.S, est.S) and np.array_equal(o.innovation, est.innovation)
    assert all(o.learning_options == {"drift": 1e-7} for o in others)


def test_a_file_without_the_joint_posterior_before_reports_nan_until_it_is_known(
        sparse_model, run, tmp_path):
    # Format 8 kept g and its covariance but not their cross covariance with the newest state
    # nor the posterior before the last update: the filtering form's innovation needs both.
    _, y = run
    est = learner(sparse_model, form="filtering")
    for t in range(10):
        est.update(None, y[t])
    path = tmp_path / "old.npz"
    est.save(path)
    entries = {k: v for k, v in np.load(path).items()
               if k not in ("core_learning_xg_cov", "core_learning_g_before",
                            "core_learning_g_cov_before", "core_learning_xg_cov_before")}
    entries["format_version"] = np.array(8)
    np.savez(path, **entries)
    old = GPMHE.load(path, sparse_model)
    assert np.all(np.isnan(old.innovation)) and np.all(np.isnan(old.S))
    np.testing.assert_array_equal(old.update(None, y[10]), est.update(None, y[10]))
    assert np.all(np.isnan(old.S)) and np.all(np.isfinite(est.S))  # the cross one was missing
    np.testing.assert_array_equal(old.update(None, y[11]), est.update(None, y[11]))
    np.testing.assert_array_equal(old.S, est.S)
    np.testing.assert_array_equal(old.innovation, est.innovation)


def test_bad_input_and_reset_leave_the_learning_state_as_documented(sparse_model, run):
    _, y = run
    est = learner(sparse_model)
    for t in range(10):
        est.update(None, y[t])
    before = [a.copy() for a in est._core.learning]
    with pytest.raises(ValueError):
        est.update(None, [np.inf])
    assert all(np.array_equal(a, b) for a, b in zip(est._core.learning, before))
    est.reset([3.0, 1.0])
    fresh = learner(sparse_model)
    assert all(np.array_equal(a, b) for a, b in zip(est._core.learning, fresh._core.learning))


def test_the_learned_model_is_a_fixed_model_that_saves_and_certifies(sparse_model, run):
    _, y = run
    est = learner(sparse_model)
    for t in range(30):
        est.update(None, y[t])
    learned = est.learned_model
    assert isinstance(learned, LearnedModel) and isinstance(learned.f_gp, SparseMultiOutputGP)
    D = np.array([[2.0, 1.0], [0.5, 2.5], [1.0, 1.0]])
    mean, std = learned.f_gp.predict(D, return_std=True)
    assert not np.allclose(mean, sparse_model.f_gp.predict(D), rtol=0, atol=1e-8)
    # The posterior it was made of: mean J u, variance σ² − J K Jᵀ + J P_u Jᵀ (the core's).
    buf = io.BytesIO()
    learned.f_gp.save(buf)
    buf.seek(0)
    again = SparseMultiOutputGP.load(buf)
    m2, s2 = again.predict(D, return_std=True)
    assert np.array_equal(m2, mean) and np.array_equal(s2, std)
    assert np.array_equal(pickle.loads(pickle.dumps(learned)).predict(D[0]), learned.predict(D[0]))
    # It is a model like any other: an estimator runs on it, the theory bounds its weights.
    fixed = GPMHE(learned, x0=[3.0, 1.0], **SETTINGS)
    fixed.update(None, y[0])
    assert fixed.success
    from gpmhe.theory import weight_bounds
    wb = weight_bounds(learned, 1e-3, 1e-2)
    assert np.all(np.isfinite(wb.Q_min_inv))


@pytest.mark.parametrize("form", ["prediction", "filtering"])
def test_the_innovation_is_predicted_from_the_state_before_the_output(sparse_model, run, form):
    # ŷ = y − ν and S are made before y(t) is seen: two estimators given different y(t) agree on
    # them bit for bit (the model's g after the update, which learned from y(t), must not enter).
    _, y = run
    est = learner(sparse_model, form=form)
    for t in range(12):
        est.update(None, y[t])
    other = copy.deepcopy(est)
    est.update(None, y[12])
    other.update(None, y[12] + 0.5)
    assert not np.array_equal(est.x, other.x)
    np.testing.assert_array_equal(y[12] - est.innovation, y[12] + 0.5 - other.innovation)
    np.testing.assert_array_equal(est.S, other.S)


def test_filtering_innovation_covariance_counts_the_uncertainty_of_g(sparse_model, run):
    # x̂(t − 1) and g are jointly uncertain: the predicted output covariance is larger than the
    # one of a fixed model at the same estimate with the same variances given g, by the
    # (positive semidefinite) contribution of g's covariance through ∂m_x/∂g.
    _, y = run
    est = learner(sparse_model, form="filtering")
    for t in range(12):
        est.update(None, y[t])
    state = est._core.__getstate__()
    assert state["learning_xg_cov"].shape == (2, est._core.learning[0].size)
    np.testing.assert_array_equal(state["learning_g_before"], state["learning_g_before"])
    est.update(None, y[12])
    after = est._core.__getstate__()
    np.testing.assert_array_equal(after["learning_g_before"], state["learning_g"])
    np.testing.assert_array_equal(after["learning_g_cov_before"], state["learning_g_cov"])
    np.testing.assert_array_equal(after["learning_xg_cov_before"], state["learning_xg_cov"])
    assert np.all(np.isfinite(est.S)) and est.S[0, 0] > 0


def test_the_prior_mean_of_g_goes_with_the_arrival_mean_of_x(sparse_model, run):
    # "smoothed": the next window's prior of g is centred on this window's g, as its prior of x
    # on this window's x̄_1; "filtered": both are the EKF step's.
    _, y = run
    for mean in ("smoothed", "filtered"):
        est = learner(sparse_model, arrival_mean=mean, drift=1e-7)
        for t in range(12):
            est.update(None, y[t])
        state = est._core.__getstate__()
        same = np.array_equal(state["learning_arrival_g"], state["learning_g"])
        assert same == (mean == "smoothed"), mean


def test_a_drifting_model_stays_consistent_with_the_data_when_the_states_are_measured():
    # Both concentrations measured, k1 falling by 40 %: with a drift the windows' cost stays of
    # the order of their number of residuals (a smoothed x̄ next to the filter's ĝ in the prior
    # made it ten times that) and the error stays near the fixed model's.
    states, _ = br.training_data(5, rng=0)
    rng = np.random.default_rng(7)
    model = LearnedModel.from_trajectories(
        states, [s + 0.05 * rng.standard_normal(s.shape) for s in states], n_inducing=20)
    x = np.empty((161, 2))
    x[0] = br.X_TRUE0
    for t in range(160):
        k1 = br.K1 * (1.0 - 0.4 * min(t / 80.0, 1.0))
        x1, x2 = x[t]
        x[t + 1] = x[t] + br.T * np.array([-2 * k1 * x1 ** 2 + 2 * br.K2 * x2,
                                           k1 * x1 ** 2 - br.K2 * x2]) \
            + br.SIGMA_W * rng.standard_normal(2)
    y = x + 0.05 * rng.standard_normal(x.shape)
    kw = dict(horizon=15, eta=1.0, P0=np.eye(2), Q0=br.SIGMA_W ** 2, R0=0.05 ** 2,
              x_bounds=br.X_BOUNDS, form="filtering")
    fixed = GPMHE(model, x0=[3.0, 1.0], **kw)
    drifting = GPMHE(model, x0=[3.0, 1.0], **kw, learning=True, learning_options={"drift": 1e-7})
    costs, errors = {"fixed": [], "drift": []}, {"fixed": [], "drift": []}
    for t in range(160):
        for name, est in (("fixed", fixed), ("drift", drifting)):
            errors[name].append(est.update(None, y[t]) - x[t])
            costs[name].append(est.cost)
    rmse = {k: np.sqrt(np.mean(np.array(e[80:]) ** 2)) for k, e in errors.items()}
    assert np.median(costs["drift"][80:]) < 2 * np.median(costs["fixed"][80:]), costs
    assert rmse["drift"] < 1.5 * rmse["fixed"], rmse


def test_the_window_hessian_of_a_learner_covers_its_global_variables(sparse_model, run):
    """The window's dense Gauss-Newton Hessian has a row and column per inducing output too
    (2JᵀJ over [x̄; g]), and P is the nodes' last block of its 4H⁻¹ for every η."""
    x, y = run
    for eta in (1.0, 0.91):
        est = learner(sparse_model, eta=eta)
        for t in range(20):
            est.update(None, y[t])
        z = np.concatenate([est.x_window.ravel(), est._core.learning[0]])
        H, J = est._core.gn_hessian(z), est._core.jacobian(z)
        assert H.shape == (z.size, z.size) == (J.shape[1], J.shape[1])
        np.testing.assert_allclose(H, 2 * J.T @ J, rtol=1e-10, atol=1e-12 * np.abs(H).max())
        nx = est.x_window.size
        np.testing.assert_allclose(est.P, 4 * np.linalg.inv(H)[nx - 2:nx, nx - 2:nx],
                                   rtol=1e-7, atol=1e-14)
