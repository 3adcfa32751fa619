"""What a filterpy user meets in gpmhe: the arrival prior's old name ``x_prior`` as a deprecated
alias of ``x_arrival`` (and no gpmhe code path using it), filterpy's ``Saver`` on every
estimator without ``ignore``, filterpy's one-argument ``update(z)`` and attribute names answered
with what to use instead."""

import copy
import inspect
import io
import pickle
import re
import warnings

import numpy as np
import pytest
from filterpy.common import Saver
from numpy.testing import assert_array_equal

from conftest import reactor_known_model
from gpmhe import GPMHE, EstimatorBank, KnownModel
from gpmhe.systems import batch_reactor as br

YS = br.simulate(br.X_TRUE0, 8, np.random.default_rng(0))[1]


def _mhe(**settings):
    settings = {"horizon": 3, "Q0": 1e-3, "R0": 1e-2, "x_bounds": br.X_BOUNDS, **settings}
    return GPMHE(reactor_known_model(), x0=[3.0, 1.0], **settings)


def _bank():
    return EstimatorBank(reactor_known_model(), 2, [3.0, 1.0], horizon=3, Q0=1e-3, R0=1e-2,
                         x_bounds=br.X_BOUNDS)


def _one_deprecation(caught, cls):
    assert [w.category for w in caught] == [DeprecationWarning]
    assert f"{cls}.x_prior is deprecated" in str(caught[0].message)
    assert f"use {cls}.x_arrival" in str(caught[0].message)
    assert caught[0].filename == __file__  # points at the code that used the old name


@pytest.mark.parametrize("make", [_mhe, _bank], ids=["GPMHE", "EstimatorBank"])
def test_x_prior_reads_x_arrival_with_one_deprecation_warning(make):
    est = make()
    for y in YS[:5]:
        est.update(None, y if make is _mhe else [y, y])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        old = est.x_prior
    _one_deprecation(caught, type(est).__name__)
    assert_array_equal(old, est.x_arrival)


@pytest.mark.parametrize("make", [_mhe, _bank], ids=["GPMHE", "EstimatorBank"])
def test_setting_x_prior_warns_and_is_refused_as_x_arrival_is(make):
    est = make()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(AttributeError, match="x_arrival"):
            est.x_prior = [1.0, 1.0]
    _one_deprecation(caught, type(est).__name__)
    with pytest.raises(AttributeError, match="x_arrival"):
        est.x_arrival = [1.0, 1.0]
    assert_array_equal(est.x_arrival, [3.0, 1.0] if make is _mhe else [[3.0, 1.0]] * 2)


def test_no_code_path_of_gpmhe_uses_the_old_name(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        est = _mhe(form="filtering")
        saver = Saver(est, save_current=True)
        for y in YS[:4]:
            est.update(None, y)
            saver.save()
        saver.to_array()
        est.save(tmp_path / "est.npz")
        for other in (GPMHE.load(tmp_path / "est.npz", est.model), copy.deepcopy(est),
                      pickle.loads(pickle.dumps(est))):
            assert_array_equal(other.x_arrival, est.x_arrival)
            other.update(None, YS[4])
        est.batch_filter(YS[4:])
        _mhe().smooth(YS)
        est.reset([3.0, 1.0])
        bank = _bank()
        bank.update(None, [YS[0], YS[1]])
        assert_array_equal(bank[1].x_arrival, bank.x_arrival[1])
        pickle.loads(pickle.dumps(bank))
        assert hasattr(est, "x_arrival") and not hasattr(est, "predict")


def _run_with_saver(est, steps):
    saver = Saver(est, save_current=True)
    for u, y in steps:
        est.update(u, y)
        saver.save()
    saver.to_array()
    return saver


@pytest.mark.parametrize("form", ["prediction", "filtering"])
def test_saver_needs_no_ignore_and_records_each_step(form):
    est = _mhe(form=form)
    steps = [(None, YS[0]), (None, None), (None, [np.nan]), (None, YS[3]), (None, YS[4])]
    xs, Ps, innovations = [est.x], [est.P], [est.innovation]
    saver = Saver(est, save_current=True)
    for u, y in steps:
        est.update(u, y)
        saver.save()
        xs.append(est.x)
        Ps.append(est.P)
        innovations.append(est.innovation)
    saver.to_array()
    assert saver.x.shape == (6, 2) and saver.P.shape == (6, 2, 2)
    assert saver.S.shape == (6, 1, 1) and saver.x_arrival.shape == (6, 2)
    assert_array_equal(saver.x, xs)
    assert_array_equal(saver.P, Ps)
    assert_array_equal(saver.innovation, innovations)  # NaN before the first output and without
    assert_array_equal(saver.t, range(6))
    assert np.isnan(saver.log_likelihood[0])  # before the first update
    assert_array_equal(saver.log_likelihood[[2, 3]], 0.0)  # no measured channel
    # The window attributes grow while the window fills: Saver does not record them.
    assert "x_window" not in saver.keys and "P_window" not in saver.keys
    assert "x_prior" not in saver.keys  # the deprecated alias is not recorded either
    assert est.x_window.shape == (4, 2)


def test_saver_on_an_estimator_with_inputs_and_parameters():
    model = KnownModel(lambda x, u, p: p[0] * x + u, lambda x, u, p: x, dim_x=1, dim_y=1,
                       dim_u=1, dim_p=1)
    est = GPMHE(model, x0=[0.0], horizon=2, Q0=0.01, R0=0.01, p0=[0.5], form="filtering")
    saver = Saver(est, save_current=True)
    for u, y in [([1.0], [1.0]), (None, [1.4]), ([0.0], None), ([1.0], [2.5])]:
        if est.t == 2:
            est.set_input([0.5])  # the input of the step that was updated with u=None
        est.update(u, y)
        saver.save()  # also while an update waits for its input
    saver.to_array()
    assert saver.x.shape == (5, 1) and saver.p.shape == (5, 1) and saver.P_p.shape == (5, 1, 1)
    assert_array_equal(saver.p[-1], est.p)


def test_saver_on_a_bank():
    bank = _bank()
    saver = _run_with_saver(bank, [(None, [YS[t], YS[t + 1]]) for t in range(5)])
    assert saver.x.shape == (6, 2, 2) and saver.x_arrival.shape == (6, 2, 2)
    assert_array_equal(saver.x[-1], bank.x)
    assert "x_window" not in saver.keys


@pytest.mark.parametrize("make, call", [(_mhe, "GPMHE.update(u, y)"),
                                        (_bank, "EstimatorBank.update(U, Y)")])
def test_filterpys_one_argument_update_says_what_to_call(make, call):
    est = make()
    with pytest.raises(TypeError, match=r"takes the input first.*update\(None, z\)") as error:
        est.update(YS[0] if make is _mhe else [YS[0], YS[1]])
    assert str(error.value).startswith(call)
    assert est.t == 0
    signature = inspect.signature(est.update)
    assert list(signature.parameters)[:2] == ["u" if make is _mhe else "U",
                                              "y" if make is _mhe else "Y"]
    assert all(p.default is inspect.Parameter.empty for p in list(signature.parameters.values())[:2])


@pytest.mark.parametrize("name, use", [("predict", "update"), ("x_post", "x"), ("P_prior", "P"),
                                       ("P_post", "P"), ("y", "innovation"),
                                       ("likelihood", "log_likelihood"), ("mahalanobis", "nis")])
def test_filterpys_attribute_names_say_what_to_use(name, use):
    ests = [_mhe(), _bank()] if name in ("predict", "x_post", "P_prior", "P_post") else [_mhe()]
    for est in ests:
        with pytest.raises(AttributeError, match=f"filterpy's {name}") as error:
            getattr(est, name)
        assert re.search(rf"; use {use}[ ,]", str(error.value))
        assert hasattr(est, use)  # what it names is there


@pytest.mark.parametrize("name", ["y", "likelihood", "mahalanobis"])
def test_a_bank_names_no_innovation_attribute_it_does_not_have(name):
    with pytest.raises(AttributeError, match=rf"^'EstimatorBank' object has no attribute '{name}'$"):
        getattr(_bank(), name)


def test_other_missing_attributes_raise_the_usual_error():
    est = _mhe()
    with pytest.raises(AttributeError, match=r"^'GPMHE' object has no attribute 'x_hat'$"):
        est.x_hat  # noqa: B018
    assert getattr(est, "x_hat", None) is None
    buf = io.BytesIO()
    pickle.dump(est, buf)  # pickle's look-ups of optional methods are unaffected
    buf.seek(0)
    assert pickle.load(buf).t == 0


def test_batch_filter_takes_filterpys_rs_with_one_r_for_every_row():
    rows = [YS[0], None, YS[2]]
    est, other = _mhe(), _mhe()
    xs, _ = est.batch_filter(rows, Rs=[0.04, 0.04, 0.01])
    for y, r in zip(rows, [0.04, None, 0.01]):
        other.update(None, y, R=r)
    assert_array_equal(xs[-1], other.x)
    with pytest.raises(ValueError, match="R: given without an output y"):
        other.update(None, None, R=0.04)  # a single update still refuses it
