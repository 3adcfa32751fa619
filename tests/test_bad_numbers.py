"""One rule for numbers at every public entry point: an argument that should hold real numbers
refuses numeric strings, complex values, bools, magnitudes above 1e150 and NaN (where NaN does
not mean "not measured") with a ValueError whose message starts with the argument's name, and
the object it was given to stays as it was."""

import re

import numpy as np
import pytest

from gpmhe import (GPMHE, RGPEKF, EstimatorBank, GaussianProcess, KnownModel, LearnedModel,
                   MultiOutputGP, NumericalError, RecursiveGP, SparseGaussianProcess, discretize)
from gpmhe._validation import MagnitudeError
from gpmhe.systems import batch_reactor as br

SCALARS = {"numeric string": "0.5", "complex": 0.5 + 0j, "bool": True, "huge": 1e200,
           "nan": float("nan")}


def vectors(n, good=0.5):
    """The bad values as vectors of n entries (the first entry bad, the others good)."""
    return {kind: [bad] + [good] * (n - 1) for kind, bad in SCALARS.items()}


def model():
    return KnownModel(br.f, br.h, dim_x=2, dim_y=1)


def model_u():
    return KnownModel(lambda x, u: 0.9 * x + u, lambda x, u: x[:1], dim_x=2, dim_y=1, dim_u=2)


def param_model():
    return KnownModel(lambda x, u, p: p[0] * x, lambda x, u, p: x[:1], dim_x=2, dim_y=1,
                      dim_p=1)


def mhe(**kw):
    return GPMHE(model(), x0=[3.0, 1.0], horizon=3, **kw)


def mhe_u(**kw):
    return GPMHE(model_u(), x0=[1.0, 1.0], horizon=3, **kw)


def fitted_gp():
    D = np.linspace(0, 1, 8)[:, None]
    return GaussianProcess(optimizer=None).fit(D, np.sin(D[:, 0]))


def rgpekf():
    gp = RecursiveGP(lower=-1.0, upper=1.0, n_points=5)
    return RGPEKF(dim_x=1, f=lambda x, u, z: x + z, A=np.eye(1), e=np.ones((1, 1)),
                  h=lambda x: x, H=np.eye(1), Q_x=1e-4, R_x=1e-2, x0=[0.0], P0=1.0, gps=gp)


D8 = np.linspace(0, 1, 8)[:, None]

# (argument name, value shape ("scalar" or n), call with a value, kinds that are not bad there)
ENTRY_POINTS = [
    ("x0", 2, lambda v: GPMHE(model(), x0=v), ()),
    ("eta", "scalar", lambda v: mhe(eta=v), ()),
    ("Q0", "scalar", lambda v: mhe(Q0=v), ()),
    ("R0", "scalar", lambda v: mhe(R0=v), ()),
    ("P2", "scalar", lambda v: mhe(P2=v), ()),
    ("P0", "scalar", lambda v: mhe(P0=v), ()),
    ("x_bounds", 2, lambda v: mhe(x_bounds=(v, None)), ()),
    ("solver_options", "scalar", lambda v: mhe(solver_options={"gtol": v}), ()),
    ("p0", 1, lambda v: GPMHE(param_model(), x0=[1.0, 1.0], p0=v), ()),
    ("P_p0", "scalar", lambda v: GPMHE(param_model(), x0=[1.0, 1.0], p0=[0.5], P_p0=v), ()),
    ("p_bounds", 1, lambda v: GPMHE(param_model(), x0=[1.0, 1.0], p0=[0.5], p_bounds=(v, None)),
     ()),
    ("p_drift", "scalar", lambda v: GPMHE(param_model(), x0=[1.0, 1.0], p0=[0.5], p_drift=v), ()),
    ("u", 2, lambda v: mhe_u().update(v, [1.0]), ()),
    ("y", 1, lambda v: mhe().update(None, v), ("nan",)),  # NaN: a channel not measured
    ("x0", 2, lambda v: mhe().reset(v), ()),
    ("ys[0]", 1, lambda v: mhe().batch_filter([v]), ("nan",)),
    ("n", "scalar", lambda v: EstimatorBank(model(), v, [3.0, 1.0]), ()),
    ("x0", 2, lambda v: EstimatorBank(model(), 2, v), ()),
    ("Q0", "scalar", lambda v: EstimatorBank(model(), 2, [3.0, 1.0], Q0=v), ()),
    ("x_bounds", 2, lambda v: EstimatorBank(model(), 2, [3.0, 1.0], x_bounds=(v, [9.0, 9.0])),
     ()),
    ("U", 2, lambda v: EstimatorBank(model_u(), 1, [1.0, 1.0]).update([v], [[1.0]]), ()),
    ("Y", 1, lambda v: EstimatorBank(model(), 1, [3.0, 1.0]).update(None, [v]), ("nan",)),
    ("sigma_f", "scalar", lambda v: GaussianProcess(sigma_f=v), ()),
    ("lengthscales", "scalar", lambda v: GaussianProcess(lengthscales=v), ()),
    ("D", 8, lambda v: GaussianProcess(optimizer=None).fit(np.array(v, dtype=object)[:, None],
                                                           np.zeros(8)), ()),
    ("y", 8, lambda v: GaussianProcess(optimizer=None).fit(D8, v), ()),
    ("D", 8, lambda v: fitted_gp().predict(np.array(v, dtype=object)[:, None]), ()),
    ("y", 8, lambda v: MultiOutputGP(optimizer=None).fit(  # its targets are y in the docs
        D8, np.array(v, dtype=object)[:, None]), ()),
    ("inducing", 3, lambda v: SparseGaussianProcess(
        inducing=np.array(v, dtype=object)[:, None]).fit(D8, np.zeros(8)), ()),
    ("dt", "scalar", lambda v: discretize(lambda x, u: -x, v), ()),
    ("fd_step", "scalar", lambda v: KnownModel(br.f, br.h, 2, 1, fd_step=v), ()),
    ("lower", "scalar", lambda v: RecursiveGP(lower=v, upper=2.0, n_points=5), ()),
    ("sigma_K", "scalar", lambda v: RecursiveGP(lower=-1.0, upper=1.0, n_points=5, sigma_K=v),
     ()),
    ("x0", 1, lambda v: RGPEKF(dim_x=1, f=lambda x, u, z: x, A=np.eye(1), e=np.ones((1, 1)),
                               h=lambda x: x, H=np.eye(1), Q_x=1e-4, R_x=1e-2, x0=v, P0=1.0,
                               gps=RecursiveGP(-1.0, 1.0, 5)), ()),
    ("y", 1, lambda v: rgpekf().update(v), ()),
    ("zeta", 1, lambda v: rgpekf().predict(0.0, v), ()),
]


def cases():
    for name, shape, call, allowed in ENTRY_POINTS:
        for kind, scalar in SCALARS.items():
            if kind in allowed:
                continue
            value = scalar if shape == "scalar" else vectors(shape)[kind]
            yield pytest.param(name, call, value, id=f"{name}-{kind}-{call.__code__.co_firstlineno}")


@pytest.mark.parametrize("name, call, value", list(cases()))
def test_a_bad_number_is_refused_naming_the_argument(name, call, value):
    with pytest.raises(ValueError, match="^" + re.escape(name) + r"(?!\w)"):
        call(value)


@pytest.mark.parametrize(
    "name, call, value",
    [pytest.param(name, call, 1e200 if shape == "scalar" else vectors(shape)["huge"],
                  id=f"{name}-{call.__code__.co_firstlineno}")
     for name, shape, call, _ in ENTRY_POINTS if name != "n"])  # n: not an integer
def test_a_too_large_number_raises_magnitude_error_everywhere(name, call, value):
    """The outputs (y, Y, a row of batch_filter) as every other argument: a MagnitudeError, both
    a ValueError and a gpmhe.NumericalError (docs/reliability.rst)."""
    with pytest.raises(MagnitudeError, match="^" + re.escape(name) + r"(?!\w)") as err:
        call(value)
    assert isinstance(err.value, ValueError) and isinstance(err.value, NumericalError)


@pytest.mark.parametrize("setter", ["Q0", "R0", "P2", "P0", "eta"])
@pytest.mark.parametrize("kind", list(SCALARS))
def test_a_bad_weight_is_refused_and_the_estimator_is_unchanged(setter, kind):
    est, twin = mhe(), mhe()
    ys = br.simulate(br.X_TRUE0, 6, np.random.default_rng(0))[1]
    est.batch_filter(ys[:3])
    twin.batch_filter(ys[:3])
    with pytest.raises(ValueError, match="^" + setter + r"(?!\w)"):
        setattr(est, setter, SCALARS[kind])
    for name in ("Q0", "R0", "P2", "eta"):
        np.testing.assert_array_equal(getattr(est, name), getattr(twin, name))
    np.testing.assert_array_equal(est.batch_filter(ys[3:])[0], twin.batch_filter(ys[3:])[0])


def test_a_bad_number_in_a_learned_models_training_data_is_refused():
    states, outputs = br.training_data(3, rng=0)
    bad = [s.astype(object) for s in states]
    bad[0][0, 0] = "3.0"
    with pytest.raises(ValueError, match=r"^states\b"):
        LearnedModel.from_trajectories(bad, outputs)


def test_a_bool_among_the_numbers_of_an_output_is_refused():
    """numpy turns [True, 0.5] into floats; an output sample refuses it like any bool."""
    model = KnownModel(lambda x, u: x, lambda x, u: x, dim_x=2, dim_y=2)
    est = GPMHE(model, x0=[0.0, 0.0], horizon=2)
    with pytest.raises(ValueError, match="^y: must be 2 real numbers"):
        est.update(None, [True, 0.5])
    assert est.t == 0
