"""The input contract of every public entry point, checked with hypothesis.

1. Bad input (NaN/inf, wrong shapes and types, non-numeric strings, mixed lists, None where it is
   not allowed, negative counts, inverted bounds, non-PD matrices, unknown options, values whose
   squares overflow) raises ValueError (or gpmhe.NumericalError) naming the argument, never
   another exception.
2. A rejected call changes nothing: the public state is as before, and the next valid call gives
   bit-identical results to a twin that never saw the bad call.
3. Valid but hostile input (outliers, long runs of missing outputs, duplicate or constant training
   data, extreme scales, states on a bound, hyperparameters at their bounds) gives finite results
   or a documented exception.

Each (entry point, argument) pair draws its bad values from one pool: generic hostile values, the
valid value with one entry spoiled, the valid value with one entry too many or too few, and the
argument's own extras (negative counts, inverted bounds, unknown options, ...).
"""

import math
import re
import warnings

import numpy as np
import pytest
from conftest import f3, f3_jac, h3, h3_jac
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gpmhe import (
    SEKernel,
    GPMHE,
    RGPEKF,
    GaussianProcess,
    KnownModel,
    LearnedModel,
    MultiOutputGP,
    NumericalError,
    RecursiveGP,
    SparseGaussianProcess,
)
from gpmhe.baselines import GPEKF, ExactEKF

SETTINGS = settings(max_examples=100, deadline=None, derandomize=True, database=None,
                    suppress_health_check=list(HealthCheck))

# ----------------------------------------------------------------------------- hostile values


class _Opaque:
    """An object numpy cannot make a number of."""


GENERIC = [
    float("nan"), float("inf"), -float("inf"), "abc", "", None, [1.0, "a"], [[1.0], [2.0, 3.0]],
    _Opaque(), 1e200, -1e200, {}, {"a": 1}, 1j, b"abc", [], np.zeros((2, 3, 4)), [[[float("nan")]]],
    (None, None), [None, 1.0], np.array(["x", "y"]),
]
NON_BOOL = ["yes", None, 2, 1.5, float("nan"), [True], _Opaque()]
BAD_COUNTS = [-1, -5, 1.5, float("nan"), True, "3", None, [2, 3], 10**30]


def _spoiled(valid):
    """The valid value with one entry replaced by NaN, ±inf or an overflowing square."""
    out = []
    try:
        a = np.array(valid, dtype=np.float64)
    except (TypeError, ValueError):
        return out
    if a.size == 0:
        return out
    for bad in (np.nan, np.inf, -np.inf, 1e200, -1e200):
        b = a.copy().reshape(-1)
        b[b.size // 2] = bad
        out.append(b.reshape(a.shape))
        out.append(b.reshape(a.shape).tolist())
    return out


def _resized(valid):
    """The valid value flattened with one entry too many or too few."""
    try:
        a = np.array(valid, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        return []
    return [np.append(a, 0.5), a[:-1]] if a.size else [np.ones(3)]


def bad_values(valid, extras=(), allow=(), numeric=True, generic=True):
    """A strategy of bad values for an argument whose valid value is ``valid``."""
    pool = [v for v in GENERIC if generic]
    if numeric:  # True: spoiled and resized; "spoil": only spoiled (any size is valid)
        pool += _spoiled(valid) + ([] if numeric == "spoil" else _resized(valid))
    pool += list(extras)
    return st.sampled_from([v for v in pool if not any(repr(v) == repr(a) for a in allow)])


# ----------------------------------------------------------------------------- state snapshots


def _freeze(v):
    if isinstance(v, np.ndarray):
        return v.copy()
    if isinstance(v, tuple) and hasattr(v, "_fields"):  # a named tuple
        return type(v)(*(_freeze(x) for x in v))
    if isinstance(v, (list, tuple)):
        return type(v)(_freeze(x) for x in v)
    if isinstance(v, dict):
        return {k: _freeze(x) for k, x in v.items()}
    return v


def snapshot(obj, public_only=False):
    """vars(obj) and the values of its public properties (exceptions recorded by type)."""
    state = {k: _freeze(v) for k, v in vars(obj).items() if not (public_only and k.startswith("_"))}
    for name in dir(type(obj)):
        if not name.startswith("_") and isinstance(getattr(type(obj), name, None), property):
            try:
                state["@" + name] = _freeze(getattr(obj, name))
            except Exception as e:  # noqa: BLE001 (an unfitted GP's properties raise)
                state["@" + name] = type(e)
    return state


def assert_same(a, b, strict=True, path="state"):
    """Equal values (arrays bit for bit, NaN equal to NaN); other objects identical (strict) or
    of the same type."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        assert a.shape == b.shape and a.dtype == b.dtype, path
        assert np.array_equal(a, b, equal_nan=a.dtype.kind in "fc"), path
    elif isinstance(a, (list, tuple)):
        assert type(a) is type(b) and len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, strict, f"{path}[{i}]")
    elif isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), path
        for k in a:
            assert_same(a[k], b[k], strict, f"{path}.{k}")
    elif a is None or isinstance(a, (bool, int, float, str, type, np.generic)):
        assert type(a) is type(b) and (a == b or (a != a and b != b)), (path, a, b)
    elif isinstance(a, SEKernel):  # a value (a fitted GP's kernel is made from the model on access)
        assert type(b) is SEKernel and a == b, path
    elif strict:
        assert a is b, path
    else:
        assert type(a) is type(b), path


# ----------------------------------------------------------------------------- the objects

D2 = np.linspace(0.0, 3.0, 8)[:, None]
Y1 = np.sin(D2[:, 0])
Y2 = np.column_stack([np.sin(D2[:, 0]), np.cos(D2[:, 0])])
GP_OPTS = dict(sigma_f=1.0, lengthscales=0.7, sigma_eps=0.1, optimizer=None)


def make_gp():
    return GaussianProcess(**GP_OPTS).fit(D2, Y1)


def make_mgp():
    return MultiOutputGP(**GP_OPTS).fit(D2, Y2)


def _learned():
    rng = np.random.default_rng(3)
    D = rng.uniform(-1.5, 1.5, size=(15, 3))
    Xn = np.array([f3(d[:2], d[2:]) for d in D])
    Y = np.array([h3(d[:2], d[2:]) for d in D])
    opts = dict(sigma_f=1.0, lengthscales=[0.8, 0.9, 1.1], sigma_eps=0.05, optimizer=None)
    return LearnedModel(MultiOutputGP(**opts).fit(D, Xn), MultiOutputGP(**opts).fit(D, Y), dim_u=1)


LEARNED = _learned()
KNOWN = KnownModel(f3, h3, dim_x=2, dim_y=2, dim_u=1, f_jacobian=f3_jac, h_jacobian=h3_jac)
TRAJ_X = [np.cumsum(np.full((6, 2), 0.1), axis=0)]
TRAJ_Y = [TRAJ_X[0] ** 2]
TRAJ_U = [np.linspace(0, 1, 6)[:, None]]

MHE_KW = dict(model=KNOWN, x0=[0.1, 0.2], horizon=3, eta=0.9, P2=np.eye(2), Q0=[0.1, 0.2],
              R0=0.1, x_bounds=([-5.0, -5.0], [5.0, 5.0]), form="prediction",
              solver="gauss-newton", solver_options={"max_iter": 50})


def make_mhe(model=KNOWN, **kw):
    mhe = GPMHE(**{**MHE_KW, "model": model, **kw})
    mhe.update([0.1], [0.1, 0.2])
    return mhe


RGP_KW = dict(lower=[0.0, -1.0], upper=[1.0, 1.0], n_points=[3, 4], sigma_K=1.5, L=0.5,
              sigma_r=0.01, sigma_p=0.001)


def make_rgp():
    gp = RecursiveGP(**RGP_KW)
    gp.update([0.5, 0.0], 1.0, 0.01)
    return gp


def make_sparse():
    return SparseGaussianProcess(n_inducing=4, mean="linear", **GP_OPTS).fit(D2, Y1)


def _from_sparse(obj, **kw):
    return RecursiveGP.from_sparse(**{"gp": obj, **kw})


def _from_sparse_next(sgp):
    return RecursiveGP.from_sparse(sgp).predict([0.3, 1.1], return_std=True), sgp.predict([[0.3]])


def _rf(x, u, z):
    return np.array([0.9 * x[0] + z, 0.8 * x[1] + 0.1 * x[0]])


def _rh(x):
    return np.array([x[0] + x[1]])


RGPEKF_KW = dict(dim_x=2, f=_rf, A=[[0.9, 0.0], [0.1, 0.8]], e=[[1.0], [0.0]], h=_rh, H=[[1.0, 1.0]],
                 Q_x=0.01 * np.eye(2), R_x=0.1, x0=[0.1, 0.2], P0=np.eye(2),
                 gps=RecursiveGP(0.0, 1.0, 5), learning=True, pure_prediction=False)


def _rf2(x, u, z):
    return np.array([0.9 * x[0] + z[0], 0.8 * x[1] + z[1]])


RGPEKF2_KW = {**RGPEKF_KW, "f": _rf2, "e": np.eye(2),
              "gps": [RecursiveGP(0.0, 1.0, 5), RecursiveGP([0.0, 0.0], [1.0, 1.0], [3, 3])]}


def make_rgpekf2():
    ekf = RGPEKF(**RGPEKF2_KW)
    ekf.predict(None, [0.3, [0.5, 0.5]])
    ekf.update([0.5])
    return ekf


def _rgpekf2_next(ekf):
    ekf.predict(None, [0.6, [0.1, 0.9]])
    ekf.update([0.4])
    return ekf.x, ekf.P, ekf.z_pred, ekf.mu, ekf.C


def make_rgpekf():
    ekf = RGPEKF(**RGPEKF_KW)
    ekf.predict(None, 0.3)
    ekf.update([0.5])
    return ekf


def _ef(x):
    return np.array([0.9 * x[0], 0.8 * x[1]])


EKF_KW = dict(f=_ef, f_jacobian=lambda x: np.diag([0.9, 0.8]), h=lambda x: np.array([x[0] + x[1]]),
              h_jacobian=lambda x: np.array([[1.0, 1.0]]), x0=[0.1, 0.2], P0=np.eye(2),
              Q=0.01 * np.eye(2), R=0.1)
GPEKF_KW = dict(model=LEARNED, x0=[0.1, 0.2], P0=np.eye(2), Q=0.01 * np.eye(2), R=0.1 * np.eye(2))

# ----------------------------------------------------------------------------- the cases
#
# Each case: (id, make, call, valid kwargs, {argument: extra bad values or a bad_values
# strategy}, next valid call or None). ``make`` builds a fresh object (None for constructors),
# ``call(obj, **kw)`` calls the entry point.

NOT_PD = [[[1.0, 2.0], [2.0, 1.0]], [[1.0, 0.5], [0.4, 1.0]], -np.eye(2), np.zeros((2, 2)) - 1]
NOT_PD_OR_ZERO = NOT_PD + [np.zeros((2, 2))]


def _set(obj, **kw):
    """A property setter: ``_set(obj, x=v)`` is ``obj.x = v``."""
    (name, value), = kw.items()
    setattr(obj, name, value)


def _ctor(cls):
    return lambda obj, **kw: cls(**kw)


def _method(name):
    return lambda obj, **kw: getattr(obj, name)(**kw)


def _gp_next(gp):
    return gp.predict([[0.3], [1.1]], return_std=True), gp.log_marginal_likelihood(eval_gradient=True)


def _mhe_next(mhe):
    return mhe.update([0.2], [0.3, 0.1]).copy(), mhe.P.copy()


def _rgp_next(gp):
    return gp.update([0.4, 0.2], 0.5, 0.01), gp.predict([[0.2, 0.3]], return_std=True)


def _rgpekf_next(ekf):
    ekf.predict(None, 0.6)
    ekf.update([0.4])
    return ekf.x, ekf.P, ekf.z_pred


GP_CTOR = dict(sigma_f=1.0, lengthscales=0.7, sigma_eps=0.1, optimizer="L-BFGS-B", n_restarts=0,
               bounds=((1e-3, 1e3), (1e-3, 1e3), (1e-5, 1e2)), random_state=0, maxiter=100)
GP_CTOR_EXTRAS = dict(
    sigma_f=[0.0, -1.0], lengthscales=[0.0, -1.0, [1.0, -1.0]], sigma_eps=[0.0, -1.0],
    optimizer=["bogus", "l-bfgs-b", 3], n_restarts=BAD_COUNTS, maxiter=BAD_COUNTS + [0],
    bounds=[((1e3, 1e-3), (1e-3, 1e3), (1e-5, 1e2)), ((0.0, 1.0),) * 3, ((-1.0, 1.0),) * 3, ((1.0, 2.0),)],
    random_state=["abc", -1, 1.5, float("nan"), _Opaque()],
)

CASES = []


def case(id, make, call, kw, extras, after=None, allow=None, numeric=None, generic=None):
    """Add one case per argument of ``kw`` listed in ``extras``."""
    allow, numeric, generic = allow or {}, numeric or {}, generic or {}
    for arg, ex in extras.items():
        CASES.append(pytest.param(make, call, kw, arg,
                                  bad_values(kw[arg], ex, allow.get(arg, ()), numeric.get(arg, True),
                                             generic.get(arg, True)),
                                  after, id=f"{id}-{arg}"))


for cls, mk, tgt in ((GaussianProcess, make_gp, "y"), (MultiOutputGP, make_mgp, "Y")):
    name = cls.__name__
    case(name, None, _ctor(cls), GP_CTOR, GP_CTOR_EXTRAS,
         allow=dict(optimizer=[None], random_state=[None, []]),
         numeric=dict(optimizer=False, random_state=False, n_restarts=False, maxiter=False,
                      sigma_f="spoil", lengthscales="spoil", sigma_eps="spoil"))
    Yv = Y1 if cls is GaussianProcess else Y2
    case(name, mk, lambda obj, tgt=tgt, **kw: obj.fit(kw["D"], kw[tgt]), {"D": D2, tgt: Yv},
         {"D": [np.ones((1, 1)), np.ones((8, 0))], tgt: [Yv[:1]]}, _gp_next)
    case(name, mk, _method("predict"), dict(D=[[0.5], [1.5]], return_std=True),
         dict(D=[[[0.5, 1.0]]], return_std=NON_BOOL), _gp_next, numeric=dict(return_std=False),
         generic=dict(return_std=False))
    case(name, mk, _method("predict_with_gradients"), dict(D=[[0.5], [1.5]]), dict(D=[]), _gp_next)
    th = make_gp().theta if cls is GaussianProcess else make_mgp().theta
    case(name, mk, _method("log_marginal_likelihood"), dict(theta=th, eval_gradient=True),
         dict(theta=[th + 800.0], eval_gradient=NON_BOOL), _gp_next, allow=dict(theta=[None]),
         numeric=dict(eval_gradient=False), generic=dict(eval_gradient=False))
    case(name, mk, _set, dict(theta=th), dict(theta=[th + 800.0, th - 800.0]), _gp_next)

case("LearnedModel", None, _ctor(LearnedModel),
     dict(f_gp=LEARNED.f_gp, h_gp=LEARNED.h_gp, dim_u=1, f_residual=False),
     dict(f_gp=[MultiOutputGP(), make_gp()], h_gp=[MultiOutputGP(), make_gp(), make_mgp()],
          dim_u=BAD_COUNTS + [0, 2], f_residual=NON_BOOL),
     allow=dict(h_gp=[None]), numeric=dict(f_gp=False, h_gp=False, dim_u=False, f_residual=False),
     generic=dict(f_residual=False))
case("LearnedModel.from_trajectories", None, lambda obj, **kw: LearnedModel.from_trajectories(
     **kw, optimizer=None), dict(states=TRAJ_X, outputs=TRAJ_Y, inputs=TRAJ_U, f_residual=False),
     dict(states=[[np.ones((1, 2))], [np.ones(6)]], outputs=[[np.ones((5, 2))]],
          inputs=[[np.ones((3, 1))]], f_residual=NON_BOOL),
     # NaN marks a missing sample in a log (its rows are dropped), so NaN-spoiled logs are valid.
     allow=dict(inputs=[None] + _spoiled(TRAJ_U)[:2], states=_spoiled(TRAJ_X)[:2],
                outputs=_spoiled(TRAJ_Y)[:2]),
     numeric=dict(f_residual=False), generic=dict(f_residual=False))
for mname, model in (("LearnedModel", LEARNED), ("KnownModel", KNOWN)):
    case(mname, lambda model=model: model, _method("predict"), dict(x=[0.1, 0.2], u=[0.3]),
         dict(x=[[0.1, 0.2, 0.3]], u=[[0.1, 0.2]]),
         lambda m: m.predict([0.2, 0.1], [0.1]))
    case(mname, lambda model=model: model, _method("stage_eval"), dict(d=[[0.1, 0.2, 0.3]]),
         dict(d=[[0.1, 0.2]]), lambda m: m.stage_eval([[0.2, 0.1, 0.0]]))
case("KnownModel", None, _ctor(KnownModel),
     dict(f=f3, h=h3, dim_x=2, dim_y=2, dim_u=1, f_jacobian=f3_jac, h_jacobian=h3_jac,
          fd_step=1e-6, vectorized=False),
     dict(f=[1.0], h=[1.0], dim_x=BAD_COUNTS + [0], dim_y=BAD_COUNTS, dim_u=BAD_COUNTS,
          f_jacobian=[1.0], h_jacobian=[1.0], fd_step=[0.0, -1e-6], vectorized=NON_BOOL),
     allow=dict(f_jacobian=[None], h_jacobian=[None]),
     numeric=dict(f=False, h=False, dim_x=False, dim_y=False, dim_u=False, f_jacobian=False,
                  h_jacobian=False, vectorized=False),
     generic=dict(vectorized=False))

case("GPMHE", None, _ctor(GPMHE), MHE_KW,
     dict(model=[LEARNED.f_gp, 1.0], x0=[[10.0, 0.0]], horizon=BAD_COUNTS + [0],
          eta=[1.0 + 1e-9, -0.1, 2.0, [0.5, 0.5]], P2=NOT_PD_OR_ZERO, Q0=NOT_PD + [0.0, -1.0],
          R0=NOT_PD + [0.0, -1.0],
          x_bounds=[([5.0, 5.0], [-5.0, -5.0]), ([0.0, 0.0],), 1.0, ([np.nan, 0.0], [1.0, 1.0]),
                    ([1.0, 1.0], [1.0, 1.0])],
          form=["bogus", "Prediction", 1], solver=["bogus", 1, "GAUSS-NEWTON"],
          solver_options=[{"max_iter": -1}, {"max_iter": 1.5}, {"max_iter": "a"}, {"bogus": 1},
                          {"gtol": float("nan")}, {"gtol": -1.0}, {"interior": "bogus"},
                          {"max_iter": 10**30}, [("max_iter", 3)], "abc"]),
     allow=dict(P2=[None], Q0=[None], R0=[None], x_bounds=[None, (None, None)],
                solver_options=[None, {}]),
     numeric=dict(R0="spoil", model=False, horizon=False, form=False, solver=False, solver_options=False,
                  x_bounds=False))
for solver, opts in (("trust-constr", {"maxiter": 50}), ("least-squares", {"max_nfev": 50})):
    case(f"GPMHE[{solver}]", None, _ctor(GPMHE), {**MHE_KW, "solver": solver, "solver_options": opts},
         dict(solver_options=[{"bogus": 1}, {"max_iter": 3}, {"maxiter": -1}, {"max_nfev": "a"},
                              {"gtol": float("nan")}, {"dtol": -1.0}, {"method": "trf"},
                              {"bounds": None}, {"loss": "huber"}, {"f_scale": 2.0}]),
         allow=dict(solver_options=[None, {}]), numeric=dict(solver_options=False))
for mname, model in (("known", KNOWN), ("learned", LEARNED)):
    mk = (lambda model=model: make_mhe(model))
    case(f"GPMHE[{mname}].update", mk, _method("update"), dict(u=[0.1], y=[0.2, 0.3]),
         dict(u=[], y=[[], [np.inf, 0.3], [0.2, -np.inf], [1e200, 0.0]]), _mhe_next,
         allow=dict(y=[None]), numeric=dict(y=False))
    case(f"GPMHE[{mname}].batch_filter", mk, _method("batch_filter"),
         dict(ys=[[0.2, 0.3], None, [0.1, 0.1]], us=[[0.1], [0.2], [0.3]]),
         dict(ys=[[[0.2, 0.3], [np.inf, 0.1]], [[0.2, 0.3], "ab"], [[0.2, 0.3], [1e200, 0.0]]],
              us=[[[0.1]], [[0.1], [0.2], None], [[0.1], [0.2], [np.inf]]]),
         _mhe_next, numeric=dict(ys=False, us=False))
    case(f"GPMHE[{mname}].reset", mk, _method("reset"), dict(x0=[0.0, 0.1]),
         dict(x0=[[9.0, 0.0], [-9.0, 0.0]]), _mhe_next)

case("RecursiveGP", None, _ctor(RecursiveGP), RGP_KW,
     dict(lower=[[2.0, 0.0]], upper=[[0.0, 1.0], [0.0, -1.0]], n_points=BAD_COUNTS + [1, [3, 1], [3, 4, 5]],
          sigma_K=[0.0, -1.0], L=[0.0, -1.0], sigma_r=[-1.0], sigma_p=[-1.0]),
     numeric=dict(n_points=False), allow=dict(n_points=[[2, 3]]))
case("RecursiveGP.update", make_rgp, _method("update"), dict(zeta=[0.5, 0.5], y=0.3, var_y=0.01),
     dict(zeta=[[0.5]], y=[[0.3, 0.2]], var_y=[-1.0]), _rgp_next)
case("RecursiveGP.update[many]", make_rgp, _method("update"),
     dict(zeta=[[0.5, 0.5], [0.2, 0.1]], y=[0.3, 0.1], var_y=[0.01, 0.02]),
     dict(zeta=[[0.5, 0.5]], y=[[0.3, 0.1, 0.2]], var_y=[[-1.0, 0.1]]), _rgp_next,
     numeric=dict(var_y="spoil"))
case("RecursiveGP.predict", make_rgp, _method("predict"), dict(zeta=[[0.5, 0.5]], return_std=True),
     dict(zeta=[[0.5]], return_std=NON_BOOL), _rgp_next, numeric=dict(return_std=False),
     generic=dict(return_std=False), allow=dict(zeta=[[], np.zeros(0)]))
case("RecursiveGP.J", make_rgp, lambda obj, **kw: obj.J(**kw), dict(zeta=[0.5, 0.5]), dict(zeta=[]),
     _rgp_next)
case("RecursiveGP.set_weights", make_rgp, _method("set_weights"), dict(mean=np.zeros(12), cov=np.eye(12)),
     dict(mean=[], cov=[-np.eye(12), np.ones((12, 12)) - 2 * np.eye(12), np.triu(np.ones((12, 12)))]),
     _rgp_next)

case("RecursiveGP.from_sparse", make_sparse, _from_sparse, dict(sigma_r=0.01, sigma_p=0.0, output=0),
     dict(sigma_r=[-1.0], sigma_p=[-1.0], output=BAD_COUNTS + [1]), _from_sparse_next,
     numeric=dict(output=False))
case("RecursiveGP.from_sparse[gp]", None, lambda obj, **kw: RecursiveGP.from_sparse(**kw), dict(gp=make_sparse()),
     dict(gp=[RecursiveGP, SparseGaussianProcess(), make_gp(), make_mgp(), make_rgp()]),
     numeric=dict(gp=False))
case("RGPEKF", None, _ctor(RGPEKF), RGPEKF_KW,
     dict(dim_x=BAD_COUNTS + [0], f=[1.0], A=[[[1.0]]], e=[[[1.0, 1.0]]], h=[1.0], H=[[[1.0, 1.0, 1.0]]],
          Q_x=NOT_PD, R_x=[0.0, -1.0, -np.eye(1), np.eye(2)], x0=[[1.0]], P0=NOT_PD,
          gps=[[], [1.0], RecursiveGP], learning=NON_BOOL, pure_prediction=NON_BOOL),
     numeric=dict(dim_x=False, f=False, h=False, gps=False, learning=False, pure_prediction=False),
     generic=dict(learning=False, pure_prediction=False))
case("RGPEKF.predict", make_rgpekf, _method("predict"), dict(u=None, zeta=0.5),
     dict(zeta=[[0.5, 0.5]]), _rgpekf_next)
case("RGPEKF[2 GPs].predict", make_rgpekf2, _method("predict"), dict(u=None, zeta=[0.3, [0.2, 0.5]]),
     dict(zeta=[[0.3], [0.3, [0.2]], [0.3, [0.2, np.nan]], [np.nan, [0.2, 0.5]], [0.3, [0.2, 1e200]],
                [0.3, [0.2, 0.5], [1.0]], [0.3, "ab"], (0.3, None), np.ones(3)]),
     _rgpekf2_next, numeric=dict(zeta=False), allow=dict(zeta=[[[1.0], [2.0, 3.0]]]))
case("RGPEKF.update", make_rgpekf, _method("update"), dict(y=[0.4]), dict(y=[[0.4, 0.1]]),
     _rgpekf_next)
case("RGPEKF.gp_predict", make_rgpekf, _method("gp_predict"), dict(zeta=[0.5], index=0, return_std=True),
     dict(zeta=[np.ones((1, 2))], index=BAD_COUNTS + [1], return_std=NON_BOOL), _rgpekf_next,
     numeric=dict(zeta="spoil", index=False, return_std=False), generic=dict(return_std=False),
     allow=dict(zeta=[[], np.zeros(0)]))
case("RGPEKF.gp_weights", make_rgpekf, _method("gp_weights"), dict(index=0), dict(index=BAD_COUNTS + [1]),
     _rgpekf_next, numeric=dict(index=False))
case("RGPEKF.x", make_rgpekf, _set, dict(x=[0.1, 0.2]), dict(x=[[0.1, 0.2, 0.3]]), _rgpekf_next)
case("RGPEKF.P", make_rgpekf, _set, dict(P=np.eye(2)), dict(P=NOT_PD), _rgpekf_next)

case("ExactEKF", None, _ctor(ExactEKF), EKF_KW,
     dict(f=[1.0], f_jacobian=[1.0], h=[1.0], h_jacobian=[1.0], x0=[], P0=NOT_PD,
          Q=NOT_PD, R=[0.0, -1.0, [[1.0, 2.0], [2.0, 1.0]]]),
     numeric=dict(f=False, f_jacobian=False, h=False, h_jacobian=False, x0="spoil"))
case("GPEKF", None, _ctor(GPEKF), GPEKF_KW,
     dict(model=[1.0, LEARNED.f_gp], x0=[[0.1, 0.2, 0.3]], P0=NOT_PD, Q=NOT_PD,
          R=[0.0, -1.0, [[1.0, 2.0], [2.0, 1.0]], np.eye(3)]),
     numeric=dict(model=False))


# ----------------------------------------------------------------------------- 1 and 2


@pytest.mark.parametrize("make, call, kw, arg, bad, after", CASES)
@SETTINGS
@given(data=st.data())
def test_bad_input_is_rejected_and_changes_nothing(make, call, kw, arg, bad, after, data):
    value = data.draw(bad, label=arg)
    obj = make() if make else None
    twin = make() if make else None
    before = snapshot(obj) if obj is not None else None
    kw_bad = {**kw, arg: value}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises((ValueError, NumericalError)) as err:
            call(obj, **kw_bad)
    name = {"Y": "y"}.get(arg, arg)  # (MultiOutputGP's targets are y in every message)
    named = re.search(rf"(^|[\s,(]){re.escape(name)}(\[\d+\])?[:,]", str(err.value))
    assert named, f"{arg}={value!r}: the message does not name it: {err.value}"
    if obj is not None:
        assert_same(snapshot(obj), before)
        if after is not None:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                assert_same(after(obj), after(twin), strict=False, path="next call")
            assert_same(snapshot(obj, public_only=True), snapshot(twin, public_only=True), strict=False)


def _failing_f(x, u, z):
    return np.ones(3) if u == "bad" else np.array([0.9 * x[0] + z, 0.8 * x[1]])


def test_rgpekf_predict_rejected_by_f_changes_nothing():
    """A predict whose f fails leaves z_pred (and all else) as before."""
    ekf, twin = (RGPEKF(**{**RGPEKF_KW, "f": _failing_f}) for _ in range(2))
    for e in (ekf, twin):
        e.predict(None, 0.3)
        e.update([0.5])
    before = snapshot(ekf)
    with pytest.raises(ValueError, match="f"):
        ekf.predict("bad", 0.9)
    assert_same(snapshot(ekf), before)
    assert_same(_rgpekf_next(ekf), _rgpekf_next(twin), strict=False)


def _f_raising(x, u):
    if u[0] > 100:
        raise ValueError("f: refuses u > 100")
    return f3(x, u)


def test_mhe_update_rejected_by_the_model_changes_nothing():
    model = KnownModel(_f_raising, h3, dim_x=2, dim_y=2, dim_u=1)
    mhe, twin = make_mhe(model), make_mhe(model)
    before = snapshot(mhe)
    with pytest.raises(ValueError, match="f"):
        mhe.update([1e3], [0.1, 0.2])
    assert_same(snapshot(mhe), before)
    assert_same(_mhe_next(mhe), _mhe_next(twin), strict=False)


def test_cases_cover_every_entry_point():
    ids = {p.id.split("-")[0] for p in CASES}
    for name in ("GaussianProcess", "MultiOutputGP", "LearnedModel", "LearnedModel.from_trajectories",
                 "KnownModel", "GPMHE", "GPMHE[known].update", "GPMHE[learned].batch_filter",
                 "GPMHE[known].reset", "RecursiveGP", "RecursiveGP.update", "RecursiveGP.predict",
                 "RecursiveGP.J", "RecursiveGP.set_weights", "RecursiveGP.from_sparse",
                 "RecursiveGP.from_sparse[gp]", "RGPEKF", "RGPEKF.predict",
                 "RGPEKF.update", "RGPEKF.gp_predict", "RGPEKF.gp_weights", "RGPEKF.x", "RGPEKF.P",
                 "ExactEKF", "GPEKF"):
        assert name in ids, name


# ----------------------------------------------------------------------------- 3. hostile but valid


def _finite(*arrays):
    for a in arrays:
        assert np.all(np.isfinite(np.asarray(a, dtype=np.float64)))


@pytest.mark.parametrize("model", [KNOWN, LEARNED], ids=["known", "learned"])
@pytest.mark.parametrize("form", ["prediction", "filtering"])
@SETTINGS
@given(ys=st.lists(st.one_of(st.none(), st.sampled_from([1e6, -1e6, 0.0, 1.0, 1e-300])),
                   min_size=1, max_size=12))
def test_mhe_outliers_and_missing_outputs_stay_finite_and_bounded(model, form, ys):
    mhe = GPMHE(**{**MHE_KW, "model": model, "form": form})
    lb, ub = mhe.x_bounds
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for y in ys:
            mhe.update([0.1], None if y is None else [y, -y])
            _finite(mhe.x, mhe.P, mhe.x_window, mhe.cost)
            assert np.all(mhe.x >= lb) and np.all(mhe.x <= ub)


def test_mhe_long_run_without_outputs_and_pinned_state():
    mhe = GPMHE(**{**MHE_KW, "x0": [5.0, -5.0]})  # both states on a bound
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for _ in range(60):
            mhe.update([1.0], None)
            _finite(mhe.x, mhe.P)
        xs, Ps = mhe.batch_filter([[5.0, 25.0]] * 10, [[0.0]] * 10)
    _finite(xs, Ps)
    assert np.all(np.abs(xs) <= 5.0)


@pytest.mark.parametrize("cls", [GaussianProcess, MultiOutputGP])
@SETTINGS
@given(kind=st.sampled_from(["duplicate", "constant_y", "constant_D", "huge_scale", "tiny_scale", "outlier"]),
       optimize=st.booleans())
def test_gp_on_degenerate_data_is_finite_or_numerical_error(cls, kind, optimize):
    D = np.linspace(0.0, 1.0, 6)[:, None]
    y = np.sin(3 * D[:, 0])
    if kind == "duplicate":
        D, y = np.vstack([D, D]), np.concatenate([y, y + 1e-3])
    elif kind == "constant_y":
        y = np.full(6, 3.0)
    elif kind == "constant_D":
        D = np.ones((6, 1))
    elif kind == "huge_scale":
        D, y = D * 1e8, y * 1e8
    elif kind == "tiny_scale":
        D, y = D * 1e-8, y * 1e-8
    elif kind == "outlier":
        y = y.copy()
        y[2] = 1e6
    gp = cls(random_state=0, **({} if optimize else {"optimizer": None}))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            gp.fit(D, y if cls is GaussianProcess else y[:, None])
    except NumericalError:
        return
    mean, std = gp.predict(D[:3], return_std=True)
    _finite(mean, std, gp.theta, gp.log_marginal_likelihood())


@pytest.mark.parametrize("theta", [[np.log(1e-3), np.log(1e-3), np.log(1e-5)], [np.log(1e3)] * 2 + [np.log(1e2)],
                                   [np.log(1e3), np.log(1e-3), np.log(1e-5)], [np.log(1e-3), np.log(1e3), np.log(1e2)]])
def test_gp_hyperparameters_at_their_bounds_stay_finite(theta):
    gp = make_gp()
    try:
        gp.theta = theta
    except NumericalError:
        return
    mean, var, dmean, dvar = gp.predict_with_gradients([[0.3], [1e3], [-1e3]])
    _finite(mean, var, dmean, dvar, gp.log_marginal_likelihood(eval_gradient=True)[1])
    assert np.all(var >= 0)


@SETTINGS
@given(ys=st.lists(st.sampled_from([1e6, -1e6, 0.0, 1e-300]), min_size=1, max_size=20),
       zetas=st.lists(st.sampled_from([0.0, 1.0, 0.5, -1e6, 1e6]), min_size=20, max_size=20))
def test_recursive_gp_outliers_stay_finite(ys, zetas):
    gp = RecursiveGP(0.0, 1.0, 5, sigma_K=2.0)
    for y, z in zip(ys, zetas):
        _finite(gp.update(z, y, 1e-3))
    mean, std = gp.predict(np.array(zetas), return_std=True)
    _finite(mean, std, gp.mean, gp.cov)


@SETTINGS
@given(steps=st.lists(st.one_of(st.none(), st.sampled_from([1e6, -1e6, 0.0])), min_size=1, max_size=30))
def test_rgpekf_outliers_and_missing_outputs_stay_finite(steps):
    ekf = RGPEKF(**RGPEKF_KW)
    for y in steps:
        ekf.predict(None, 0.3)
        if y is not None:
            try:
                ekf.update([y])
            except NumericalError:
                pass
        _finite(ekf.x, ekf.P, ekf.mu, ekf.C)


def test_extreme_scales_of_known_model_stay_finite():
    big = KnownModel(lambda x, u: 0.5 * x, lambda x, u: 1e6 * x, dim_x=1, dim_y=1)
    mhe = GPMHE(big, x0=[1e-6], horizon=4, Q0=1e-12, R0=1e6)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        xs, Ps = mhe.batch_filter([[1e9], None, [-1e9], [0.0]] * 3)
    _finite(xs, Ps)
    assert math.isfinite(mhe.cost)


def test_diverging_models_raise_instead_of_overflowing():
    """A model that drives the state beyond 1e150 raises ValueError (its square would overflow)
    with the estimator unchanged, instead of leaving inf in x or P."""
    ekf = RGPEKF(**{**RGPEKF_KW, "f": lambda x, u, z: 2.0 * x + z, "A": 2.0 * np.eye(2)})
    with pytest.raises(ValueError, match="f"):
        for _ in range(1000):
            before = snapshot(ekf)
            ekf.predict(None, 0.3)
            _finite(ekf.x, ekf.P)
    assert_same(snapshot(ekf), before)
    model = KnownModel(lambda x, u: 1e100 * x, lambda x, u: x, dim_x=1, dim_y=1)
    mhe = GPMHE(model, x0=[1.0], horizon=3)
    with pytest.raises(ValueError, match="f"):
        for _ in range(5):
            before = snapshot(mhe)
            mhe.update(None, [1.0])
    assert_same(snapshot(mhe), before)


@pytest.mark.parametrize("sigma_f, lengthscale, sigma_eps",
                         [(1e-3, 1e-3, 1e-5), (1e3, 1e-3, 1e-5), (1e-3, 1e3, 1e2), (1e3, 1e3, 1e2)])
def test_mhe_on_gps_at_their_hyperparameter_bounds_stays_finite(sigma_f, lengthscale, sigma_eps):
    rng = np.random.default_rng(3)
    D = rng.uniform(-1.5, 1.5, size=(15, 3))
    opts = dict(sigma_f=sigma_f, lengthscales=lengthscale, sigma_eps=sigma_eps, optimizer=None)
    model = LearnedModel(MultiOutputGP(**opts).fit(D, 0.9 * D[:, :2]), MultiOutputGP(**opts).fit(D, D[:, :2]),
                         dim_u=1)
    mhe = GPMHE(**{**MHE_KW, "model": model})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for t in range(8):
            mhe.update([0.1], None if t % 3 == 0 else [0.3, 1e6 if t == 4 else 0.2])
            _finite(mhe.x, mhe.P, mhe.cost)
