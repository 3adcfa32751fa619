"""The settable weights of GPMHE (Q0, R0, P2, P0, eta) change exactly what they name: writing one
leaves the others and the EKF arrival weight as they were (only P2 and P0, the arrival weight's
own setting, restart it), so writing back the same value changes nothing at all."""

import numpy as np
import pytest

from gpmhe import GPMHE, KnownModel
from gpmhe.systems import batch_reactor as br

WEIGHTS = ("Q0", "R0", "P2", "eta")


def reactor(**kw):
    model = KnownModel(br.f, br.h, 2, 1, f_jacobian=br.f_jacobian, h_jacobian=br.h_jacobian)
    settings = dict(horizon=5, eta=0.95, Q0=1e-3, R0=1e-2, arrival_weight="ekf",
                    arrival_mean="smoothed")
    return GPMHE(model, x0=[3.0, 1.0], x_bounds=br.X_BOUNDS, **{**settings, **kw})


@pytest.fixture(scope="module")
def ys():
    return br.simulate(br.X_TRUE0, 40, np.random.default_rng(2))[1]


@pytest.mark.parametrize("name", ["Q0", "R0", "eta"])
def test_writing_back_the_same_weight_every_step_changes_nothing(ys, name):
    est, twin = reactor(), reactor()
    for y in ys:
        setattr(est, name, getattr(est, name))
        est.update(None, y)
        twin.update(None, y)
        np.testing.assert_array_equal(est.x, twin.x)
        np.testing.assert_array_equal(est.P, twin.P)
    np.testing.assert_array_equal(est._core.arrival_weight, twin._core.arrival_weight)


@pytest.mark.parametrize("name, value", [("Q0", np.diag([2e-3, 5e-4])), ("R0", 0.02),
                                         ("eta", 0.8), ("P2", 3.0 * np.eye(2)),
                                         ("P0", 0.5 * np.eye(2))])
def test_each_setter_changes_only_what_it_names(ys, name, value):
    est = reactor()
    est.batch_filter(ys[:12])
    before = {w: np.array(getattr(est, w)) for w in WEIGHTS}
    arrival = est._core.arrival_weight
    assert not np.allclose(arrival, est.P2)  # the EKF recursion has moved it
    setattr(est, name, value)
    changed = "P2" if name == "P0" else name
    for w in WEIGHTS:
        if w == changed:
            expect = np.linalg.inv(value) if name == "P0" else (
                value * np.eye(1) if w == "R0" else value)
            np.testing.assert_allclose(getattr(est, w), expect, rtol=1e-15)
        else:
            np.testing.assert_array_equal(getattr(est, w), before[w], err_msg=w)
    if changed == "P2":  # the arrival weight restarts from the new P2
        np.testing.assert_allclose(est._core.arrival_weight, est.P2, rtol=1e-14)
    else:
        np.testing.assert_array_equal(est._core.arrival_weight, arrival)


def test_a_weight_set_between_updates_equals_an_estimator_built_with_it_from_then_on(ys):
    """With the constant arrival weight (nothing recursive), Q0 set after 10 updates gives what
    an estimator built with that Q0 gives on the same windows once the old ones have left."""
    est = reactor(arrival_weight="constant", arrival_mean="estimate", eta=1.0)
    built = reactor(arrival_weight="constant", arrival_mean="estimate", eta=1.0, Q0=4e-3)
    est.batch_filter(ys[:10])
    built.batch_filter(ys[:10])
    est.Q0 = 4e-3
    np.testing.assert_array_equal(est.Q0, built.Q0)
    # The same window problem from here: one update of each from the same history and warm
    # start gives the same estimate.
    built._core.__setstate__(est._core.__getstate__())
    est.update(None, ys[10])
    built.update(None, ys[10])
    np.testing.assert_array_equal(est.x, built.x)


class _InterruptedAfterSetWeights:
    """The core of an estimator whose set_weights is followed at once by a Ctrl-C (the signal's
    handler runs as the call returns), or that is interrupted before the call (``before``)."""

    def __init__(self, core, before):
        self._real, self._before = core, before

    def set_weights(self, **kw):
        if self._before:
            raise KeyboardInterrupt
        self._real.set_weights(**kw)
        raise KeyboardInterrupt

    def __getattr__(self, name):
        return getattr(self._real, name)


@pytest.mark.parametrize("before", [False, True])
def test_an_interrupt_around_a_setter_keeps_settings_and_core_together(ys, before):
    est, twin = reactor(), reactor()
    est.batch_filter(ys[:10])
    twin.batch_filter(ys[:10])
    real = est._core
    est._core = _InterruptedAfterSetWeights(real, before)
    with pytest.raises(KeyboardInterrupt):
        est.Q0 = 4e-3
    est._core = real
    if not before:  # the core took the new Q0: so do the settings, as on the twin
        twin.Q0 = 4e-3
    np.testing.assert_array_equal(est.Q0, twin.Q0)
    np.testing.assert_array_equal(est.batch_filter(ys[10:])[0], twin.batch_filter(ys[10:])[0])


@pytest.mark.parametrize("name", ["Q0", "P2", "P0"])
@pytest.mark.parametrize("form, matrix", [(0.5, 0.5 * np.eye(2)),
                                          ([0.5, 2.0], np.diag([0.5, 2.0])),
                                          ([[0.5, 0.1], [0.1, 2.0]], [[0.5, 0.1], [0.1, 2.0]])],
                         ids=["scalar", "diagonal", "matrix"])
def test_the_weight_matrices_take_the_same_forms_in_the_constructor_and_when_set(name, form,
                                                                                matrix):
    """Q0, P2 and P0 (R0 is checked by the same code as Q0): a scalar times I, the diagonal or
    a symmetric positive definite matrix, in the constructor and when set."""
    expect = np.linalg.inv(matrix) if name == "P0" else np.asarray(matrix)
    shown = "P2" if name == "P0" else name
    built = reactor(**{name: form})
    np.testing.assert_allclose(getattr(built, shown), expect, rtol=1e-15)
    est = reactor()
    setattr(est, name, form)
    np.testing.assert_allclose(getattr(est, shown), expect, rtol=1e-15)


@pytest.mark.parametrize("name", ["Q0", "R0", "P2", "P0"])
@pytest.mark.parametrize("bad", [[0.5, -1.0], [[1.0, 0.5], [0.4, 1.0]], np.ones(3), [np.nan, 1.0]],
                         ids=["negative", "asymmetric", "shape", "nan"])
def test_the_weight_matrices_refuse_the_same_values(name, bad):
    est = reactor()
    before = est.Q0, est.R0, est.P2
    for build in (lambda: reactor(**{name: bad}), lambda: setattr(est, name, bad)):
        with pytest.raises(ValueError, match=f"^{name}: "):
            build()
    for a, b in zip(before, (est.Q0, est.R0, est.P2)):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("name", ["Q0", "R0", "P2", "P0"])
def test_a_weight_read_is_read_only_so_an_in_place_change_is_refused_not_ignored(name):
    est = GPMHE(KnownModel(br.f, br.h, 2, 1), [1.0, 1.0], Q0=0.1, R0=0.2)
    before = getattr(est, name).copy()
    with pytest.raises(ValueError, match="read-only"):
        getattr(est, name)[0, 0] = 5.0
    np.testing.assert_array_equal(getattr(est, name), before)
    setattr(est, name, 2.0 * before)  # the way to change it
    np.testing.assert_allclose(getattr(est, name), 2.0 * before)
