"""The default window solver on stiff windows: the rotating masses in do-mpc's setting, whose
process weight Q0⁻¹ = 1e8 I dwarfs the output and arrival weights of 1. Every window converges
(no RuntimeWarning) in a few evaluations, to the estimates of windows solved to first-order
optimality, also with the inertia Θ1 estimated as a ninth state (a nonlinear model)."""

import warnings

import numpy as np
import pytest

from gpmhe import GPMHE, KnownModel
from gpmhe.systems import rotating_masses as rm


def run(mhe, u, y):
    """Estimates and window evaluations of every update; a RuntimeWarning (a window whose solver
    did not converge) fails the test."""
    est, nfev = [], []
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        for ut, yt in zip(u, y):
            est.append(mhe.update(ut, yt).copy())
            assert mhe.success, (mhe.t, mhe.message)
            nfev.append(mhe.nfev)
    return np.array(est), np.array(nfev)


@pytest.mark.parametrize("arrival", [("estimate", "constant"), ("smoothed", "ekf"),
                                     ("smoothed", "constant")])
def test_exact_model_mhe_solves_every_rotating_masses_window_in_few_evaluations(arrival):
    x, u, y = rm.simulate(30, rng=2)
    model = rm.known_model(backend="numpy")
    settings = dict(rm.MHE_SETTINGS, arrival_mean=arrival[0], arrival_weight=arrival[1])
    est, nfev = run(GPMHE(model, rm.initial_estimate(3), **settings), u, y)
    # The model is linear: one Gauss-Newton step solves a window, one more evaluation confirms.
    assert nfev.max() <= 3, nfev
    # Stopping on the decrement (dtol = 1e-2) gives the estimates of windows run to the gradient
    # tolerance: the decrement is that of the undamped step, which the process weights
    # do not hide.
    ref, _ = run(GPMHE(model, rm.initial_estimate(3), solver_options={"dtol": 0.0}, **settings),
                 u, y)
    rmse = [np.sqrt(np.mean((e[:-1] - x[1:])[-10:, :3] ** 2)) for e in (est, ref)]
    assert rmse[0] < 1.5 * rm.SIGMA_V
    if arrival != ("smoothed", "constant"):
        np.testing.assert_allclose(est, ref, atol=1e-3)
    else:
        # do-mpc's arrival cost carries each window's smoothed estimate into the next with the
        # weak weight P_x = I: a cost left within dtol of the optimum moves the weakly
        # determined directions by up to ~0.1, statistically nothing, and the accuracy stays.
        np.testing.assert_allclose(est, ref, atol=0.1)
        assert abs(rmse[0] - rmse[1]) < 0.1 * rmse[1]


def test_theta1_as_a_ninth_state_converges_in_every_window():
    ca = pytest.importorskip("casadi")
    F, h = rm.casadi_functions(theta1=None)
    scale = 1e-4  # s = Θ1 / 1e-4 is O(1)
    xs, us = ca.SX.sym("x", 9), ca.SX.sym("u", 2)
    rhs = ca.Function("rm9", [xs, us], [ca.vertcat(F(xs[:8], us, scale * xs[8]), 0)])
    out = ca.Function("rm9_y", [xs, us], [xs[:3]])
    model = KnownModel.from_ode(rhs, out, rm.T, substeps=rm.SUBSTEPS)
    x, u, y = rm.simulate(40, rng=1)
    lo, hi = (b / scale for b in rm.THETA1_BOUNDS)
    mhe = GPMHE(model, np.r_[rm.initial_estimate(2), rm.THETA1_GUESS / scale],
                x_bounds=(np.r_[np.full(8, -np.inf), lo], np.r_[np.full(8, np.inf), hi]),
                **dict(rm.MHE_SETTINGS, P2=np.diag(np.r_[np.diag(rm.P_X), rm.P_P]),
                       Q0=1e-8 * np.eye(9)))
    est, nfev = run(mhe, u, y)
    # Long Gauss-Newton steps along the curved valley of the 1e8 process weights are corrected
    # back into it instead of being cut to a crawl (which ran every window to the iteration cap).
    assert np.median(nfev) <= 10 and nfev.max() <= 40, nfev
    assert abs(est[-1, 8] * scale / rm.THETA1 - 1.0) < 0.05
