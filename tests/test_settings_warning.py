"""`gpmhe.SettingsWarning`: one warning where gpmhe assumes a setting the user did not give (an
estimator without any noise information gets identity weights) or where a setting has no effect
(``f_residual`` with the linear prior mean); none where the user gave what is needed, and none
when an estimator is rebuilt from one that was built already (copies, pickles, checkpoints)."""

import copy
import pickle
import warnings

import numpy as np
import pytest

from gpmhe import GPMHE, EstimatorBank, KnownModel, LearnedModel, SettingsWarning
from gpmhe.systems import batch_reactor as br


def _f(x, u):
    return 0.9 * x


def _h(x, u):
    return x


def _plant():
    return KnownModel(_f, _h, dim_x=1, dim_y=1)


def _caught(build):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = build()
    return result, [w for w in caught if issubclass(w.category, SettingsWarning)]


def test_no_noise_information_warns_once_naming_the_weights_and_the_page():
    est, caught = _caught(lambda: GPMHE(_plant(), x0=[0.0]))
    assert len(caught) == 1
    message = str(caught[0].message)
    for name in ("Q0", "R0", "P2/P0", "identity", "Weights from the GP variances"):
        assert name in message
    assert caught[0].filename == __file__  # points at the caller's line
    np.testing.assert_array_equal(est.Q0, np.eye(1))  # what the warning says was assumed
    np.testing.assert_array_equal(est.R0, np.eye(1))
    np.testing.assert_array_equal(est.P2, np.eye(1))


@pytest.mark.parametrize("given", [dict(Q0=0.1), dict(R0=0.1), dict(P2=2.0), dict(P0=0.5)])
def test_any_noise_information_silences_it(given):
    _, caught = _caught(lambda: GPMHE(_plant(), x0=[0.0], **given))
    assert caught == []


def test_invalid_settings_raise_without_the_warning_first():
    with warnings.catch_warnings():
        warnings.simplefilter("error", SettingsWarning)
        with pytest.raises(ValueError, match="horizon"):
            GPMHE(_plant(), x0=[0.0], horizon=0)


def test_copies_pickles_and_checkpoints_of_a_warned_estimator_stay_silent(tmp_path):
    with pytest.warns(SettingsWarning):
        est = GPMHE(_plant(), x0=[0.0], horizon=3)
    est.update(None, [1.0])
    est.save(tmp_path / "est.npz")
    for rebuild in (lambda: copy.deepcopy(est), lambda: pickle.loads(pickle.dumps(est)),
                    lambda: GPMHE.load(tmp_path / "est.npz", _plant())):
        again, caught = _caught(rebuild)
        assert caught == []
        assert again.x == pytest.approx(est.x, abs=0)


def test_a_bank_warns_once_and_only_without_noise_information():
    _, caught = _caught(lambda: EstimatorBank(_plant(), 3, [0.0], horizon=3))
    assert len(caught) == 1 and "identity weights" in str(caught[0].message)
    _, caught = _caught(lambda: EstimatorBank(_plant(), 3, [0.0], horizon=3, R0=0.1))
    assert caught == []


def test_f_residual_with_the_linear_mean_warns_and_changes_nothing():
    states, outputs = br.training_data(3, rng=0, steps=10)
    kw = dict(optimizer=None, sigma_eps=0.01)
    plain, caught = _caught(lambda: LearnedModel.from_trajectories(states, outputs, **kw))
    assert caught == []
    residual, caught = _caught(
        lambda: LearnedModel.from_trajectories(states, outputs, f_residual=True, **kw))
    assert len(caught) == 1 and "mean='linear'" in str(caught[0].message)
    for point in ([2.0, 4.0], [0.5, 1.0], [3.0, 0.2]):
        np.testing.assert_allclose(residual.predict(point), plain.predict(point), rtol=1e-9,
                                   atol=1e-12)


def test_f_residual_with_a_zero_mean_is_silent_and_changes_the_model():
    states, outputs = br.training_data(3, rng=0, steps=10)
    kw = dict(optimizer=None, sigma_eps=0.01, mean="zero")
    plain = LearnedModel.from_trajectories(states, outputs, **kw)
    residual, caught = _caught(
        lambda: LearnedModel.from_trajectories(states, outputs, f_residual=True, **kw))
    assert caught == []
    far = [8.0, 8.0]  # far from the data the zero-mean GP falls to 0, x + GP does not
    assert np.abs(residual.predict(far) - plain.predict(far)).max() > 1.0
