"""EstimatorBank: n estimators updated together give, bit for bit, what n separate GPMHE
estimators give on the same data (learned and known models, both forms, missing outputs,
per-estimator x0, bounds and weights); bank[i] continues as estimator i; bad input is refused
with nothing changed; a failing estimator does not stop the others; copies and pickles."""

import copy
import pickle
import signal
import time
import warnings

import numpy as np
import pytest
from conftest import f3, h3, synthetic_learned_model
from numpy.testing import assert_array_equal

from gpmhe import GPMHE, EstimatorBank, KnownModel
from gpmhe.systems import batch_reactor as br

K, T = 4, 20
LEARNED = synthetic_learned_model(30)
KNOWN = KnownModel(f3, h3, dim_x=2, dim_y=2, dim_u=1)

# Per-estimator settings: x0, boxes and weights differ between the estimators.
X0 = np.array([[0.0, 0.0], [0.5, -0.5], [-1.0, 1.0], [0.2, 0.1]])
LB = np.array([[-3.0, -3.0], [-2.0, -3.0], [-3.0, -1.5], [-3.0, -3.0]])
UB = np.array([[3.0, 3.0], [3.0, 2.0], [3.0, 3.0], [1.0, 3.0]])
Q0 = np.array([1e-2, 2e-2, 1e-2, 5e-3])  # one scalar per estimator
R0 = np.array([[1e-1, 1e-1], [5e-2, 1e-1], [1e-1, 2e-1], [1e-1, 1e-1]])  # one diagonal each


def _data(seed=3):
    """Inputs (T, K, 1) and outputs (T, K, 2) of K simulated runs, with missing values."""
    rng = np.random.default_rng(seed)
    U = rng.uniform(-1, 1, (T, K, 1))
    Y = np.empty((T, K, 2))
    for i in range(K):
        x = np.array([0.3, -0.2]) + 0.1 * i
        for t in range(T):
            Y[t, i] = h3(x, U[t, i]) + 0.05 * rng.standard_normal(2)
            x = f3(x, U[t, i]) + 0.01 * rng.standard_normal(2)
    Y[3, 1] = np.nan  # estimator 1 has no output at t = 3
    Y[7, :, 0] = np.nan  # nobody at t = 7 (one NaN in a row makes the row missing)
    Y[12, 2, 1] = np.nan
    return U, Y


U_DATA, Y_DATA = _data()


def _settings(i, form):
    return dict(x0=X0[i], horizon=4, Q0=Q0[i], R0=R0[i], x_bounds=(LB[i], UB[i]), form=form)


def _bank(model, form, **extra):
    return EstimatorBank(model, K, X0, horizon=4, Q0=Q0, R0=R0, x_bounds=(LB, UB), form=form,
                         **extra)


def _separate(model, form, **extra):
    return [GPMHE(model, **_settings(i, form), **extra) for i in range(K)]


def _step_separate(mhes, u_rows, y_rows):
    for i, mhe in enumerate(mhes):
        y = y_rows[i]
        mhe.update(u_rows[i], None if np.isnan(y).any() else y)


def _assert_same(bank, mhes):
    for name in ("x", "P", "cost", "success", "nfev", "nit", "x_window", "x_arrival",
                 "projected_gradient"):
        assert_array_equal(getattr(bank, name), np.array([getattr(m, name) for m in mhes]),
                           err_msg=name)
    assert bank.t == mhes[0].t


@pytest.mark.parametrize("form", ["prediction", "filtering"])
@pytest.mark.parametrize("model", [LEARNED, KNOWN], ids=["learned", "known"])
def test_the_bank_matches_separate_estimators_bit_for_bit(model, form):
    bank, mhes = _bank(model, form), _separate(model, form)
    _assert_same(bank, mhes)
    for t in range(T):
        bank.update(U_DATA[t], Y_DATA[t])
        _step_separate(mhes, U_DATA[t], Y_DATA[t])
        _assert_same(bank, mhes)
    assert bank.threads >= 1 and (bank.threads == 1) == (model is KNOWN)


def test_the_batch_reactor_learned_model_and_one_x0_for_all(reactor_gp):
    k = 3
    runs = [br.simulate(br.X_TRUE0, 15, np.random.default_rng(s))[1] for s in range(k)]
    bank = EstimatorBank(reactor_gp, k, br.X_PRIOR0, x_bounds=br.X_BOUNDS, **br.MHE_SETTINGS)
    mhes = [GPMHE(reactor_gp, x0=br.X_PRIOR0, x_bounds=br.X_BOUNDS, **br.MHE_SETTINGS)
            for _ in range(k)]
    for t in range(15):
        Y = np.array([y[t] for y in runs])
        bank.update(None, Y)
        for i in range(k):
            mhes[i].update(None, Y[i])
    _assert_same(bank, mhes)


@pytest.mark.parametrize("model", [LEARNED, KNOWN], ids=["learned", "known"])
def test_bank_item_continues_as_the_separate_estimator(model):
    bank, mhes = _bank(model, "prediction"), _separate(model, "prediction")
    for t in range(10):
        bank.update(U_DATA[t], Y_DATA[t])
        _step_separate(mhes, U_DATA[t], Y_DATA[t])
    items = [bank[i] for i in range(K)]
    assert bank[-1].t == 10 and len(bank) == K
    for item, mhe in zip(items, mhes):
        for name in ("t", "cost", "success", "nit", "nfev", "message", "projected_gradient"):
            assert getattr(item, name) == getattr(mhe, name), name
        assert_array_equal(item.x_bounds[0], mhe.x_bounds[0])
        assert_array_equal(item.Q0, mhe.Q0)
    for t in range(10, T):
        bank.update(U_DATA[t], Y_DATA[t])
        _step_separate(mhes, U_DATA[t], Y_DATA[t])
        _step_separate(items, U_DATA[t], Y_DATA[t])
    _assert_same(bank, mhes)
    _assert_same(bank, items)
    with pytest.raises(IndexError):
        bank[K]


def test_bad_input_is_refused_and_changes_nothing():
    bank, mhes = _bank(LEARNED, "prediction"), _separate(LEARNED, "prediction")
    bank.update(U_DATA[0], Y_DATA[0])
    _step_separate(mhes, U_DATA[0], Y_DATA[0])
    before = bank.x.copy(), bank.t
    Y_inf = Y_DATA[1].copy()
    Y_inf[2, 0] = np.inf
    for U, Y, arg in [(U_DATA[1][:3], Y_DATA[1], "U"), (U_DATA[1], Y_DATA[1][:, :1], "Y"),
                      (None, Y_DATA[1], "U"), (U_DATA[1], Y_inf, "Y"),
                      (U_DATA[1] * np.nan, Y_DATA[1], "U"), (U_DATA[1], "no", "Y")]:
        with pytest.raises(ValueError, match=f"^{arg}:"):
            bank.update(U, Y)
    assert_array_equal(bank.x, before[0])
    assert bank.t == before[1]
    for t in range(1, 4):  # ... and it continues as the separate estimators
        bank.update(U_DATA[t], Y_DATA[t])
        _step_separate(mhes, U_DATA[t], Y_DATA[t])
    _assert_same(bank, mhes)


@pytest.mark.parametrize("kwargs, arg", [
    (dict(n=0), "n"),
    (dict(n=2.0), "n"),
    (dict(solver="least-squares"), "solver"),
    (dict(x_bound=None), "x_bound"),
    (dict(Q0=[1.0, -1.0, 1.0, 1.0]), r"Q0\[1\]"),
    (dict(Q0=np.ones((3, 2))), "Q0"),
    (dict(R0=np.ones((K, 3))), "R0"),
    (dict(x0=np.zeros((3, 2))), "x0"),
    (dict(x0=[[0, 0], [0, 0], [0, 0], [5, 0]]), "x0"),
    (dict(x_bounds=(LB, LB)), "x_bounds"),
    (dict(x_bounds=(LB[:2], UB[:2])), "x_bounds"),
    (dict(horizon=0), "horizon"),
])
def test_bad_settings_raise_naming_the_argument(kwargs, arg):
    args = dict(n=K, x0=X0, horizon=4, x_bounds=(LB, UB))
    args.update(kwargs)
    with pytest.raises(ValueError, match=f"^{arg}"):
        EstimatorBank(LEARNED, **args)
    with pytest.raises(ValueError, match="^model"):
        EstimatorBank(object(), K, X0)


@pytest.mark.parametrize("name, value", [
    ("Q0", np.array([3e-2, 1e-3, 2e-2, 1e-2])),  # one per estimator
    ("R0", np.array([[2e-1, 1e-1], [1e-1, 5e-2], [5e-2, 5e-2], [1e-1, 3e-1]])),
    ("eta", 0.8),
    ("P2", np.array([[2.0, 0.3], [0.3, 1.0]])),
])
@pytest.mark.parametrize("model, form", [(LEARNED, "prediction"), (KNOWN, "filtering")],
                         ids=["learned", "known"])
def test_a_weight_set_between_updates_acts_as_on_separate_estimators(model, form, name, value):
    bank, mhes = _bank(model, form), _separate(model, form)
    for t in range(8):
        bank.update(U_DATA[t], Y_DATA[t])
        _step_separate(mhes, U_DATA[t], Y_DATA[t])
    setattr(bank, name, value)
    for i, mhe in enumerate(mhes):
        setattr(mhe, name, value[i] if name in ("Q0", "R0") else value)
    assert bank.t == 8 and all(bank[i].t == 8 for i in range(K))  # the histories are kept
    for t in range(8, T):
        bank.update(U_DATA[t], Y_DATA[t])
        _step_separate(mhes, U_DATA[t], Y_DATA[t])
    _assert_same(bank, mhes)
    if name in ("Q0", "R0"):  # one matrix per estimator
        assert_array_equal(getattr(bank, name), [getattr(m, name) for m in mhes])
    else:
        assert_array_equal(getattr(bank, name), value)
    assert_array_equal(getattr(bank[2], name), getattr(mhes[2], name))


@pytest.mark.parametrize("name, value", [("Q0", -1.0), ("Q0", np.ones((3, 2))),
                                         ("Q0", [[1.0, 2.0], [2.0, 1.0]]), ("R0", np.nan),
                                         ("P0", [[1.0, 0.0], [1.0, 1.0]]),
                                         ("eta", 1.5), ("P2", -np.eye(2)), ("P2", "1")])
def test_a_refused_weight_raises_naming_it_and_changes_nothing(name, value):
    bank, twin = _bank(KNOWN, "prediction"), _bank(KNOWN, "prediction")
    for b in (bank, twin):
        b.update(U_DATA[0], Y_DATA[0])
    core = bank._core
    with pytest.raises(ValueError, match=f"^{name}"):
        setattr(bank, name, value)
    assert bank._core is core
    for w in ("Q0", "R0", "eta", "P2", "P0"):
        assert_array_equal(getattr(bank, w), getattr(twin, w))
    for b in (bank, twin):
        b.update(U_DATA[1], Y_DATA[1])
    assert_array_equal(bank.x, twin.x)


@pytest.mark.parametrize("name, message", [
    ("horizon", "EstimatorBank.horizon is read-only; the settable attributes are P0, P2, Q0, "
                "R0, eta (the other settings are fixed at construction: build a new "
                "EstimatorBank"),
    ("x0", "EstimatorBank.x0 is read-only"),
    ("x_bounds", "EstimatorBank.x_bounds is read-only"),
    ("form", "EstimatorBank.form is read-only"),
    ("x", "EstimatorBank.x is read-only; .* the estimates change only through update"),
    ("R", "no settable attribute 'R': did you mean R0"),
    ("P", "no settable attribute 'P': did you mean P0 (the arrival covariance)"),
    ("horizn", "EstimatorBank has no attribute 'horizn'; the settable ones are P0, P2, Q0, R0, "
               "eta"),
])
def test_other_attributes_cannot_be_set(name, message):
    bank = _bank(KNOWN, "prediction")
    before = {n: copy.deepcopy(getattr(bank, n)) for n in ("horizon", "x0", "form", "x")}
    with pytest.raises(AttributeError, match=message.replace("(", r"\(").replace(")", r"\)")):
        setattr(bank, name, 3)
    assert not hasattr(bank, "horizn")
    for n, v in before.items():
        assert_array_equal(getattr(bank, n), v)


@pytest.mark.parametrize("key, message", [
    ("x_bound", "x_bound: not a setting of EstimatorBank"),
    ("R", "R: not a setting of EstimatorBank .*R0"),
    ("p0", "p0: the model has no parameters"),
])
def test_a_keyword_the_bank_does_not_take_is_named_with_what_to_give(key, message):
    with pytest.raises(ValueError, match=message):
        EstimatorBank(KNOWN, K, X0, **{key: 1.0})


def test_a_solver_failure_in_one_estimator_does_not_stop_the_others():
    # max_iter=1 stops most windows before convergence: those report success False.
    bank = _bank(LEARNED, "prediction", solver_options=dict(max_iter=1))
    mhes = _separate(LEARNED, "prediction", solver_options=dict(max_iter=1))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        bank.update(U_DATA[0], Y_DATA[0])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _step_separate(mhes, U_DATA[0], Y_DATA[0])
    _assert_same(bank, mhes)
    failed = np.flatnonzero(~bank.success)
    assert failed.size > 0
    assert len(caught) == 1 and issubclass(caught[0].category, RuntimeWarning)
    assert ", ".join(map(str, failed)) in str(caught[0].message)


class _Refuses:
    """f3 that raises a (non-numerical) ValueError for an input above `limit`."""

    def __init__(self, limit):
        self.limit = limit

    def __call__(self, x, u):
        if u[0] > self.limit:
            raise ValueError("input out of range")
        return f3(x, u)


def test_a_model_exception_leaves_every_estimator_unchanged():
    model = KnownModel(_Refuses(5.0), h3, dim_x=2, dim_y=2, dim_u=1)
    bank, mhes = _bank(model, "prediction"), _separate(model, "prediction")
    bank.update(U_DATA[0], Y_DATA[0])
    _step_separate(mhes, U_DATA[0], Y_DATA[0])
    U_bad = U_DATA[1].copy()
    U_bad[2] = 9.0  # estimator 2's model call fails after 0 and 1 were updated
    with pytest.raises(ValueError, match="input out of range"):
        bank.update(U_bad, Y_DATA[1])
    assert bank.t == 1
    for t in range(1, 5):
        bank.update(U_DATA[t], Y_DATA[t])
        _step_separate(mhes, U_DATA[t], Y_DATA[t])
    _assert_same(bank, mhes)


@pytest.mark.parametrize("model", [LEARNED, KNOWN], ids=["learned", "known"])
def test_copies_and_pickles_continue_identically(model):
    bank = _bank(model, "filtering")
    for t in range(6):
        bank.update(U_DATA[t], Y_DATA[t])
    copies = [copy.deepcopy(bank), copy.copy(bank), pickle.loads(pickle.dumps(bank))]
    for t in range(6, 12):
        bank.update(U_DATA[t], Y_DATA[t])
        for c in copies:
            c.update(U_DATA[t], Y_DATA[t])
    for c in copies:
        for name in ("x", "P", "cost", "success", "nfev", "x_window"):
            assert_array_equal(getattr(c, name), getattr(bank, name), err_msg=name)
        assert c.t == bank.t and c[1].message == bank[1].message


def test_pickles_keep_per_estimator_weights_when_n_equals_dim_x():
    q0 = np.array([[1e-2, 2e-2], [3e-2, 4e-2]])[:, :, None] * np.eye(2)  # n = dim_x = 2: one each
    bank = EstimatorBank(KNOWN, 2, X0[:2], horizon=3, Q0=q0)
    assert_array_equal(bank.Q0, q0)
    bank.update(U_DATA[0][:2], Y_DATA[0][:2])
    restored = pickle.loads(pickle.dumps(bank))
    assert_array_equal(restored.Q0, q0)
    for b in (bank, restored):
        b.update(U_DATA[1][:2], Y_DATA[1][:2])
    assert_array_equal(restored.x, bank.x)


@pytest.mark.skipif(not hasattr(signal, "setitimer"), reason="needs signal.setitimer")
def test_a_signal_stops_a_parallel_update_promptly_with_every_estimator_unchanged():
    n = 30_000  # ~1-2 s per update without the interrupt
    bank = EstimatorBank(synthetic_learned_model(300), n, [0.0, 0.0], horizon=15)
    x, P = bank.x.copy(), bank.P.copy()
    states = [bank._core.member_state(i) for i in (0, n - 1)]  # updated and restored; never run
    fired = []

    def handler(signum, frame):
        fired.append(time.perf_counter())
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGALRM, handler)
    due = time.perf_counter() + 0.2
    signal.setitimer(signal.ITIMER_REAL, 0.2)
    try:
        with pytest.raises(KeyboardInterrupt):
            bank.update(np.zeros((n, 1)), np.full((n, 2), 0.3))
        raised = time.perf_counter()
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
    assert fired, "the update finished before the signal"
    assert raised - due < 1.0
    assert bank.t == 0
    assert_array_equal(bank.x, x)
    assert_array_equal(bank.P, P)
    for i, state in zip((0, n - 1), states):
        after = bank._core.member_state(i)
        for key in state:
            assert_array_equal(after[key], state[key], err_msg=f"{i}: {key}")


# ---- every GPMHE setting: full weights, P0, per-sample full R, parameters --------------------
Q0_FULL = np.array([[[1e-2, 4e-3], [4e-3, 2e-2]], [[2e-2, 0.0], [0.0, 1e-2]],
                    [[1e-2, -2e-3], [-2e-3, 5e-3]], [[5e-3, 1e-3], [1e-3, 5e-3]]])
R0_FULL = np.array([[[1e-1, 3e-2], [3e-2, 1e-1]], [[5e-2, 0.0], [0.0, 1e-1]],
                    [[1e-1, -2e-2], [-2e-2, 2e-1]], [[1e-1, 1e-2], [1e-2, 1e-1]]])
R_SAMPLE = np.array([[[2e-1, 5e-2], [5e-2, 1e-1]], [[1e-1, 0.0], [0.0, 1e-1]],
                     [[3e-1, 0.0], [0.0, 1e-2]], [[1e-1, -3e-2], [-3e-2, 1e-1]]])
P0 = np.array([[0.5, 0.1], [0.1, 0.3]])


@pytest.mark.parametrize("model", [LEARNED, KNOWN], ids=["learned", "known"])
def test_full_weights_p0_and_per_sample_covariances_match_separate_estimators(model):
    settings = dict(horizon=4, P0=P0, form="filtering")
    bank = EstimatorBank(model, K, X0, Q0=Q0_FULL, R0=R0_FULL, x_bounds=(LB, UB), **settings)
    mhes = [GPMHE(model, x0=X0[i], Q0=Q0_FULL[i], R0=R0_FULL[i], x_bounds=(LB[i], UB[i]),
                  **settings) for i in range(K)]
    assert_array_equal(bank.Q0, Q0_FULL)
    assert_array_equal(bank.P0, mhes[0].P0)
    for t in range(T):
        R = R_SAMPLE if t % 3 == 1 else None  # a full covariance per estimator for this sample
        if t == 10:  # a new arrival covariance and one full Q0 for all, set between updates
            for est in [bank] + mhes:
                est.P0 = 2 * P0
                est.Q0 = Q0_FULL[0]
        bank.update(U_DATA[t], Y_DATA[t], R=R)
        for i, m in enumerate(mhes):
            y = None if np.isnan(Y_DATA[t, i]).any() else Y_DATA[t, i]
            m.update(U_DATA[t, i], y, R=None if R is None or y is None else R[i])
        _assert_same(bank, mhes)
    assert_array_equal(bank.P2, mhes[0].P2)
    assert_array_equal(bank.Q0, np.array([m.Q0 for m in mhes]))
    twin, item = pickle.loads(pickle.dumps(bank)), bank[2]  # the settings travel with them
    for b in (bank, twin):
        b.update(U_DATA[0], Y_DATA[0], R=R_SAMPLE)
    item.update(U_DATA[0, 2], Y_DATA[0, 2], R=R_SAMPLE[2])
    assert_array_equal(twin.x, bank.x)
    assert_array_equal(item.x, bank.x[2])


def test_a_full_weight_that_is_not_positive_definite_is_refused_naming_the_estimator():
    bad = Q0_FULL.copy()
    bad[2] = [[1.0, 2.0], [2.0, 1.0]]
    with pytest.raises(ValueError, match=r"^Q0\[2\]: must be .*positive definite"):
        EstimatorBank(KNOWN, K, X0, Q0=bad)
    bank = _bank(KNOWN, "prediction")
    with pytest.raises(ValueError, match=r"^R\[2\]"):
        bank.update(U_DATA[0], Y_DATA[0], R=bad)
    assert bank.t == 0


def _with_parameter(x, u, p):
    """f3 with its damping 0.95 as the parameter p."""
    return np.array([0.9 * x[0] + 0.1 * x[1] + 0.1 * u[0],
                     -0.1 * np.sin(x[0]) + p[0] * x[1] + 0.05 * u[0]])


def _h_with_parameter(x, u, p):
    return h3(x, u)


PARAMETRISED = KnownModel(_with_parameter, _h_with_parameter, dim_x=2, dim_y=2, dim_u=1, dim_p=1)
P_SETTINGS = dict(p0=[0.8], P_p0=0.05, p_bounds=([0.5], [1.0]), p_drift=1e-3)


def test_a_bank_estimates_each_estimators_own_parameters_as_separate_estimators_do():
    bank = _bank(PARAMETRISED, "filtering", **P_SETTINGS)
    mhes = _separate(PARAMETRISED, "filtering", **P_SETTINGS)
    assert bank.dim_p == 1 and bank.p.shape == (K, 1) and bank.P_p.shape == (K, 1, 1)
    assert_array_equal(bank.p0, [0.8])
    for t in range(T):
        bank.update(U_DATA[t], Y_DATA[t])
        _step_separate(mhes, U_DATA[t], Y_DATA[t])
        _assert_same(bank, mhes)
        assert_array_equal(bank.p, np.array([m.p for m in mhes]))
        assert_array_equal(bank.P_p, np.array([m.P_p for m in mhes]))
    assert len(np.unique(bank.p)) == K  # each its own estimate
    item = bank[1]
    assert_array_equal(item.p, mhes[1].p)
    restored = pickle.loads(pickle.dumps(bank))
    for b in (bank, restored, item):
        one = b is item
        b.update(U_DATA[0, 1] if one else U_DATA[0], Y_DATA[0, 1] if one else Y_DATA[0])
    assert_array_equal(restored.p, bank.p)
    assert_array_equal(item.p, bank.p[1])
    with pytest.raises(ValueError, match="^p0"):  # one prior for all: p̃'s scale comes from it
        _bank(PARAMETRISED, "filtering", **dict(P_SETTINGS, p0=np.full((K, 1), 0.8)))
    with pytest.raises(ValueError, match="^p0: required"):
        _bank(PARAMETRISED, "filtering")


def test_weights_set_mid_run_on_a_bank_with_parameters_act_as_on_separate_estimators():
    bank = _bank(PARAMETRISED, "prediction", **P_SETTINGS)
    mhes = _separate(PARAMETRISED, "prediction", **P_SETTINGS)
    for t in range(T):
        if t == 6:
            for est in [bank] + mhes:
                est.P0 = 0.5 * np.eye(2)  # restarts the arrival weight of [x; p]
        if t == 12:
            bank.Q0 = Q0_FULL
            for i, m in enumerate(mhes):
                m.Q0 = Q0_FULL[i]
        bank.update(U_DATA[t], Y_DATA[t])
        _step_separate(mhes, U_DATA[t], Y_DATA[t])
        _assert_same(bank, mhes)
        assert_array_equal(bank.p, np.array([m.p for m in mhes]))
        assert_array_equal(bank.P_p, np.array([m.P_p for m in mhes]))


def test_an_exception_in_a_bank_with_parameters_leaves_every_estimator_and_p_unchanged():
    def refuses(x, u, p):
        if u[0] > 5.0:
            raise ValueError("input out of range")
        return _with_parameter(x, u, p)

    model = KnownModel(refuses, _h_with_parameter, dim_x=2, dim_y=2, dim_u=1, dim_p=1)
    bank = _bank(model, "filtering", **P_SETTINGS)
    for t in range(3):
        bank.update(U_DATA[t], Y_DATA[t])
    before = {name: copy.deepcopy(getattr(bank, name)) for name in ("x", "P", "p", "P_p")}
    U_bad = U_DATA[3].copy()
    U_bad[3] = 9.0  # the last estimator fails after the others were solved
    with pytest.raises(ValueError, match="input out of range"):
        bank.update(U_bad, Y_DATA[3])
    assert bank.t == 3
    for name, value in before.items():
        assert_array_equal(getattr(bank, name), value, err_msg=name)


@pytest.mark.parametrize("model, extra", [(LEARNED, {}), (PARAMETRISED, P_SETTINGS)],
                         ids=["learned", "parameters"])
def test_reset_restarts_every_estimator_as_separate_resets_do(model, extra):
    bank, mhes = _bank(model, "filtering", **extra), _separate(model, "filtering", **extra)
    for t in range(8):
        bank.update(U_DATA[t], Y_DATA[t])
        _step_separate(mhes, U_DATA[t], Y_DATA[t])
    x0 = X0[::-1].copy()
    x0[3] = [0.5, 0.2]  # inside estimator 3's box
    p0 = np.array([[0.6], [0.7], [0.8], [0.9]]) if extra else None
    bank.reset(x0, p0)
    for i, m in enumerate(mhes):
        m.reset(x0[i], None if p0 is None else p0[i])
    assert bank.t == 0
    _assert_same(bank, mhes)
    for t in range(8, T):
        bank.update(U_DATA[t], Y_DATA[t])
        _step_separate(mhes, U_DATA[t], Y_DATA[t])
    _assert_same(bank, mhes)
    if extra:
        assert_array_equal(bank.p, np.array([m.p for m in mhes]))


def test_a_refused_reset_names_the_estimator_and_changes_nothing():
    bank = _bank(PARAMETRISED, "prediction", **P_SETTINGS)
    bank.update(U_DATA[0], Y_DATA[0])
    x, p = bank.x.copy(), bank.p.copy()
    outside = X0.copy()
    outside[2] = [5.0, 0.0]  # estimator 2's box ends at 3
    with pytest.raises(ValueError, match=r"^x0: must lie inside x_bounds \(estimator 2\)"):
        bank.reset(outside)
    with pytest.raises(ValueError, match=r"^p0: must lie inside p_bounds \(estimator 0\)"):
        bank.reset(X0, p0=[2.0])
    with pytest.raises(ValueError, match=r"^x0: expected shape"):
        bank.reset(np.zeros((3, 2)))
    with pytest.raises(ValueError, match="^p0: the model has no parameters"):
        _bank(KNOWN, "prediction").reset(X0, p0=[1.0])
    assert bank.t == 1
    assert_array_equal(bank.x, x)
    assert_array_equal(bank.p, p)
