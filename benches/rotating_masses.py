"""Benchmark: estimators of the rotating masses with the unknown inertia Θ1, on the same data.

    python benches/rotating_masses.py [--seeds 3] [--steps 50] [--restarts 1] [--quick]

The plant and setting are do-mpc's moving-horizon estimation example
(gpmhe.systems.rotating_masses): 8 states, y = φ1..3 + v, v ~ N(0, 0.1² I), Θ1 unknown (true
2.25e-4, guess 1e-4, bounds [1e-5, 1e-3]), horizon 10, arrival weights P_x = I and P_p = 10 (on
Θ1 in its own units), output weight P_v = I, no process noise, random step inputs. Per seed the
data are rm.simulate(steps, rng=seed) (RK4, 10 sub-steps per 0.1 s) and the initial estimate
rm.initial_estimate(10000 + seed); every estimator starts from x̂(0) and Θ̂1 = 1e-4, receives
y(1..T) (not y(0), which do-mpc's loop never sees) and u(0..T−1), and returns the filtered
x̂(t), Θ̂1(t) for t = 1..T. Estimators, each a function run_<name>(data, settings) ->
(xs, thetas, times, warnings):

* do-mpc's MHE (`run_dompc`): the example's continuous-time model (written here from rm's CasADi
  right-hand side) discretised by do-mpc's default orthogonal collocation (Radau, degree 2, one
  finite element per sample), Θ1 a do-mpc parameter estimated with `set_default_objective(P_x,
  P_v, P_p)`, its bounds, the set angles measured without noise (as in the example), IPOPT with
  its output suppressed. Note the data come from RK4 with 10 sub-steps: Radau's degree-2
  collocation over one 0.1 s element leaves ~10 % of a motor step (τ = 0.01 s) undecayed, a
  model mismatch that is do-mpc's example discretisation, not noise.
* filterpy's EKF and UKF (`run_ekf`, `run_ukf`) on the 9-state model z = [x; θ], Θ1 = 1e-4 θ
  (θ is O(1)), the discrete map RK4 with 10 sub-steps (gpmhe.discretize) and its exact Jacobian
  (rm.rhs_jacobian plus the analytic ∂F/∂θ column); P0 = blockdiag(P_x⁻¹, P_p⁻¹/1e-8)
  (P_p⁻¹ as Θ1's variance, in θ's units); R = P_v⁻¹ = I, the MHEs' output weight (the true
  σ_v² is 0.01), so that all estimators share one tuning; Q = 1e-6 I for numerical health only;
  θ clipped into its bounds after every update (a Kalman filter has no box; the MHEs do). The
  UKF uses Merwe's sigma points (α = 0.1, β = 2, κ = 0), all propagated in one vectorised call
  at their θ clipped into the bounds: P_p⁻¹ = 0.1 is a standard deviation of 0.32 in Θ1's
  units, 1400 times Θ1, so the unclipped sigma points reach negative and huge inertias (with
  α = 1e-3 and no clipping P loses definiteness within a few steps). A filter that fails is
  noted and holds its last estimate. The rows "tight Θ1 prior" give the filters Θ1's prior
  standard deviation 1e-4 (`TIGHT_THETA1_STD`) instead: the wide prior, not filterpy, is what
  throws Θ̂1 to a bound.
* gpmhe's GPMHE with the exact model (`run_gpmhe_casadi`, `run_gpmhe_numpy`), Θ1 the model's
  parameter: rm.known_model(theta1=None) (KnownModel.from_ode on the right-hand side of (x, u, Θ1),
  CasADi, or numpy with the analytic Jacobian; 10 RK4 sub-steps); the CasADi model compiled in
  the core (the default) and on Python callbacks (``native=False``, on CasADi's virtual machine
  and compiled by CasADi's JIT), rm.PARAMETER_SETTINGS (p0 =
  the guess, P_p0 = P_p⁻¹, p_bounds = Θ1's bounds); rm.MHE_SETTINGS for the states (P2 = P_x, R0 = P_v⁻¹,
  Q0 = 1e-8 I for "no process noise", η = 0.99) with gpmhe's default arrival cost (smoothed
  mean, EKF weight); the filtering form, the default Rust Gauss-Newton solver. The row
  "CasADi, do-mpc's arrival" uses do-mpc's arrival cost instead (the previous window's
  estimate of the new first node, constant weights: rm.MHE_SETTINGS').
* GP-MHE with a learned model (`run_gpmhe_learned`): LearnedModel.from_trajectories (defaults:
  linear prior mean, standardised, default hyperprior) on `TRAIN_TRAJECTORIES` simulated
  trajectories of the plant with the TRUE Θ1 (the learned model has no parameter), states
  measured with noise σ = `SIGMA_X_TRAIN`; then GPMHE with rm.MHE_SETTINGS in the filtering form.
  The fit time is reported separately.
* Reference (`run_gpmhe_known_theta`): GPMHE with the exact model and the true Θ1
  (rm.known_model(), rm.MHE_SETTINGS), what the estimators of Θ1 can at best approach.

Times are per update (do-mpc: `make_step` only; filterpy: predict + update; gpmhe: `update`),
all measured in this process in this run. Warnings count Python warnings raised during the
updates plus, for do-mpc, solves IPOPT did not report successful. Prints per estimator the
RMSE of x̂ over all 8 states and t = 1..T and over the second half (mean over seeds), the final
|Θ̂1 − Θ1|/Θ1 (mean and max over seeds), the median and p95 ms per update, the warnings, and
the median time's ratio to do-mpc's and to the EKF's. Without do-mpc installed the script runs
the rest and says so. Nothing is asserted: the numbers are for reading.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import tempfile
import time
import warnings

import numpy as np

from gpmhe import GPMHE, LearnedModel, discretize
from gpmhe.systems import rotating_masses as rm

#: Θ1 = SCALE · θ inside the filters, so that θ is O(1).
SCALE = 1e-4
THETA_GUESS = rm.THETA1_GUESS / SCALE
THETA_BOUNDS = (rm.THETA1_BOUNDS[0] / SCALE, rm.THETA1_BOUNDS[1] / SCALE)
#: The filters' process noise (θ units for the last state), for numerical health only.
FILTER_Q = 1e-6
#: Θ1's prior standard deviation in the "tight Θ1 prior" filter rows (the guess 1e-4 ± 1e-4;
#: do-mpc's P_p = 10 read as a covariance is ± 0.32).
TIGHT_THETA1_STD = 1e-4
#: Training data of the learned model: trajectories, steps each, state-measurement noise.
TRAIN_TRAJECTORIES, TRAIN_STEPS, SIGMA_X_TRAIN = 4, 50, 0.01
N_X = rm.DIM_X


# ---- data ---------------------------------------------------------------------------------
def make_data(seed, steps, n_train):
    """The run's true states, inputs, outputs and initial estimate, and the learned model's
    training trajectories (with the true Θ1)."""
    x, u, y = rm.simulate(steps, rng=seed)
    rng = np.random.default_rng(20000 + seed)
    train = {"states": [], "outputs": [], "inputs": []}
    for _ in range(n_train):
        xt, ut, yt = rm.simulate(TRAIN_STEPS, rng=rng, x0=rm.initial_estimate(rng))
        train["states"].append(xt + SIGMA_X_TRAIN * rng.standard_normal(xt.shape))
        train["outputs"].append(yt)
        train["inputs"].append(ut)
    return dict(seed=seed, x=x, u=u, y=y, x0=rm.initial_estimate(10000 + seed), train=train)


@contextlib.contextmanager
def captured_output(lines):
    """Send what C code and Python print to fds 1 and 2 to a file; append its lines to `lines`."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    with tempfile.TemporaryFile(mode="w+b") as f:
        os.dup2(f.fileno(), 1)
        os.dup2(f.fileno(), 2)
        try:
            yield
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)
            f.seek(0)
            lines.extend(line for line in f.read().decode(errors="replace").splitlines() if line.strip())


# ---- do-mpc -------------------------------------------------------------------------------
def import_dompc():
    """do_mpc, or the reason it cannot be imported (its import warns about optional features)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            import do_mpc
    except Exception as exc:  # noqa: BLE001 (any import failure: report it and go on)
        return None, f"{type(exc).__name__}: {exc}"
    return do_mpc, None


def run_dompc(data, settings):
    """do-mpc's MHE as in its example: continuous-time model, Θ1 estimated as a parameter."""
    import casadi as ca

    do_mpc = settings["do_mpc"]
    model = do_mpc.model.Model("continuous")
    phi = model.set_variable("_x", "phi", shape=(3, 1))
    dphi = model.set_variable("_x", "dphi", shape=(3, 1))
    phi_m = model.set_variable("_x", "phi_m", shape=(2, 1))
    phi_m_set = model.set_variable("_u", "phi_m_set", shape=(2, 1))
    theta1 = model.set_variable("_p", "Theta_1")
    F, _ = rm.casadi_functions(theta1=None)
    xdot = F(ca.vertcat(phi, dphi, phi_m), phi_m_set, theta1)
    model.set_rhs("phi", xdot[0:3])
    model.set_rhs("dphi", xdot[3:6])
    model.set_rhs("phi_m", xdot[6:8])
    model.set_meas("phi_meas", phi)  # with measurement noise v: weighted by P_v
    model.set_meas("phi_m_set_meas", phi_m_set, meas_noise=False)  # the inputs, exactly
    model.setup()

    mhe = do_mpc.estimator.MHE(model, ["Theta_1"])
    mhe.settings.n_horizon = rm.HORIZON
    mhe.settings.t_step = rm.T
    mhe.settings.meas_from_data = True
    mhe.settings.supress_ipopt_output()
    mhe.set_default_objective(rm.P_X, rm.P_V, rm.P_P * np.eye(1))
    mhe.bounds["lower", "_p_est", "Theta_1"] = rm.THETA1_BOUNDS[0]
    mhe.bounds["upper", "_p_est", "Theta_1"] = rm.THETA1_BOUNDS[1]
    mhe.setup()
    mhe.x0 = data["x0"]
    mhe.p_est0 = rm.THETA1_GUESS
    mhe.set_initial_guess()

    x, u, y = data["x"], data["u"], data["y"]
    xs, thetas, times, failed = [], [], [], 0
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for t in range(1, len(x)):
            meas = np.concatenate([y[t], u[t - 1]])  # do-mpc's y(t): φ(t) + v and u(t−1)
            t0 = time.perf_counter()
            x_hat = mhe.make_step(meas)
            times.append(time.perf_counter() - t0)
            failed += not mhe.solver_stats["success"]
            xs.append(np.asarray(x_hat, dtype=float).ravel())
            thetas.append(float(mhe.p_est0.cat.full().ravel()[0]))
    return np.array(xs), np.array(thetas), times, len(caught) + failed


# ---- the 9-state model [x; θ] -------------------------------------------------------------
def aug_rhs(Z, U):
    """d[x; θ]/dt for all rows: rm.rhs with Θ1 = SCALE θ, and dθ/dt = 0."""
    Z = np.atleast_2d(Z)
    return np.column_stack([rm.rhs(Z[:, :N_X], U, theta1=SCALE * Z[:, N_X]), np.zeros(len(Z))])


def aug_rhs_jacobian(Z, U):
    """∂F/∂[x; θ]: the Jacobian with respect to [x; Θ1] of the model with Θ1 as its parameter
    (rm.known_model(theta1=None)), its Θ1 column times SCALE, and a zero row for dθ/dt."""
    Z = np.atleast_2d(Z)
    J = np.zeros((len(Z), N_X + 1, N_X + 1))
    J[:, :N_X, :] = rm._rhs_jacobian_of_theta1(Z[:, :N_X], U, SCALE * Z[:, N_X:])
    J[:, :N_X, N_X] *= SCALE
    return J


def aug_h(Z, U=None):
    return np.array(np.atleast_2d(Z)[:, :rm.DIM_Y])


def aug_h_jacobian(Z, U=None):
    return np.broadcast_to(np.eye(rm.DIM_Y, N_X + 1), (len(np.atleast_2d(Z)), rm.DIM_Y, N_X + 1)).copy()


AUG_F = discretize(aug_rhs, rm.T, substeps=rm.SUBSTEPS, rhs_jacobian=aug_rhs_jacobian)


# ---- filterpy ----------------------------------------------------------------------------
def _filter_prior(data, theta1_std=None):
    """z0 = [x̂(0); θ guess], P0 = blockdiag(P_x⁻¹, var θ): by default P_p⁻¹ as Θ1's variance
    (θ's is P_p⁻¹ / SCALE²), else ``theta1_std``² / SCALE²."""
    z0 = np.append(data["x0"], THETA_GUESS)
    P0 = np.zeros((N_X + 1, N_X + 1))
    P0[:N_X, :N_X] = np.linalg.inv(rm.P_X)
    P0[N_X, N_X] = (1.0 / rm.P_P if theta1_std is None else theta1_std**2) / SCALE**2
    return z0, P0


def _run_filter(kf, data, settings, name, get_z, set_theta):
    """predict(u(t−1)), update(y(t)), θ clipped into its bounds, for t = 1..T. A filter that
    fails (e.g. P no longer positive definite) counts one warning, is noted, and keeps its
    last estimate for the remaining steps."""
    x, u, y = data["x"], data["u"], data["y"]
    xs, thetas, times, failed = [], [], [], 0
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for t in range(1, len(x)):
            t0 = time.perf_counter()
            try:
                kf.predict(u=u[t - 1])
                kf.update(y[t])
            except (np.linalg.LinAlgError, ValueError, FloatingPointError) as exc:
                failed = 1
                settings["notes"].append(f"{name}, seed {data['seed']}: failed at t={t} "
                                         f"({type(exc).__name__}: {exc}); last estimate kept")
                xs += [xs[-1] if xs else data["x0"]] * (len(x) - t)
                thetas += [thetas[-1] if thetas else rm.THETA1_GUESS] * (len(x) - t)
                break
            set_theta(np.clip(get_z()[N_X], *THETA_BOUNDS))
            times.append(time.perf_counter() - t0)
            z = get_z()
            xs.append(z[:N_X].copy())
            thetas.append(SCALE * z[N_X])
    return np.array(xs), np.array(thetas), times, len(caught) + failed


def run_ekf(data, settings, theta1_std=None, name="filterpy EKF"):
    """filterpy's ExtendedKalmanFilter on [x; θ] (see the module docstring)."""
    from filterpy.kalman import ExtendedKalmanFilter

    class EKF(ExtendedKalmanFilter):
        def predict_x(self, u=0):
            self.x = self._next.reshape(-1, 1)

        def predict(self, u=0):
            self._next, self.F = AUG_F.value_and_jacobian(self.x.ravel(), u)
            super().predict(u)

        def update(self, z):
            super().update(np.reshape(z, (-1, 1)), lambda s: aug_h_jacobian(s.ravel())[0],
                           lambda s: aug_h(s.ravel()).reshape(-1, 1))

    z0, P0 = _filter_prior(data, theta1_std)
    ekf = EKF(dim_x=N_X + 1, dim_z=rm.DIM_Y, dim_u=rm.DIM_U)
    ekf.x, ekf.P = z0.reshape(-1, 1), P0
    ekf.Q, ekf.R = FILTER_Q * np.eye(N_X + 1), np.linalg.inv(rm.P_V)

    def set_theta(v):
        ekf.x[N_X, 0] = v
    return _run_filter(ekf, data, settings, name, lambda: ekf.x.ravel(), set_theta)


def run_ukf(data, settings, theta1_std=None, name="filterpy UKF"):
    """filterpy's UnscentedKalmanFilter on [x; θ], its sigma points propagated in one call at
    their θ clipped into the bounds."""
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    class UKF(UnscentedKalmanFilter):
        def compute_process_sigmas(self, dt, fx=None, **fx_args):
            sigmas = np.array(self.points_fn.sigma_points(self.x, self.P))
            sigmas[:, N_X] = np.clip(sigmas[:, N_X], *THETA_BOUNDS)
            self.sigmas_f = AUG_F(sigmas, np.broadcast_to(fx_args["u"], (len(sigmas), rm.DIM_U)))

    def fx(z, dt, u):  # filterpy's signature; the vectorised compute_process_sigmas is used
        return AUG_F(z, u)

    points = MerweScaledSigmaPoints(N_X + 1, alpha=0.1, beta=2.0, kappa=0.0)
    ukf = UKF(dim_x=N_X + 1, dim_z=rm.DIM_Y, dt=rm.T, hx=lambda z: z[:rm.DIM_Y], fx=fx, points=points)
    z0, P0 = _filter_prior(data, theta1_std)
    ukf.x, ukf.P = z0, P0
    ukf.Q, ukf.R = FILTER_Q * np.eye(N_X + 1), np.linalg.inv(rm.P_V)

    def set_theta(v):
        ukf.x[N_X] = v
    return _run_filter(ukf, data, settings, name, lambda: ukf.x, set_theta)


def run_ekf_tight(data, settings):
    """The EKF with Θ1's prior standard deviation `TIGHT_THETA1_STD` instead of P_p^(-1/2)."""
    return run_ekf(data, settings, TIGHT_THETA1_STD, "filterpy EKF, tight Θ1 prior")


def run_ukf_tight(data, settings):
    """The UKF with Θ1's prior standard deviation `TIGHT_THETA1_STD` instead of P_p^(-1/2)."""
    return run_ukf(data, settings, TIGHT_THETA1_STD, "filterpy UKF, tight Θ1 prior")


# ---- gpmhe --------------------------------------------------------------------------------
def _run_gpmhe(est, split, data):
    """update(u(0), None) (x̂(0) = the prior), then update(u(t), y(t)) for t = 1..T (timed);
    `split(est)` -> (x̂, Θ̂1)."""
    x, u, y = data["x"], data["u"], data["y"]
    xs, thetas, times = [], [], []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        est.update(u[0], None)
        for t in range(1, len(x)):
            t0 = time.perf_counter()
            est.update(u[t], y[t])
            times.append(time.perf_counter() - t0)
            x_hat, theta = split(est)
            xs.append(x_hat)
            thetas.append(theta)
    return np.array(xs), np.array(thetas), times, len(caught)


def _parameter_gpmhe(data, backend, arrival=None, jit=False, native=True):
    """GPMHE with the exact model and Θ1 as its parameter (rm.known_model(theta1=None),
    rm.PARAMETER_SETTINGS), rm.MHE_SETTINGS for the states with gpmhe's default arrival cost
    unless `arrival` (arrival_mean, arrival_weight) is given."""
    settings = {k: v for k, v in rm.MHE_SETTINGS.items() if not k.startswith("arrival_")}
    if arrival is not None:
        settings.update(arrival_mean=arrival[0], arrival_weight=arrival[1])
    est = GPMHE(rm.known_model(None, backend=backend, jit=jit, native=native), data["x0"],
                form="filtering",
                **rm.PARAMETER_SETTINGS, **settings)
    return est, lambda e: (e.x.copy(), float(e.p[0]))


def run_gpmhe_casadi(data, settings):
    """GPMHE, exact model in CasADi compiled in the core, Θ1 estimated as the model's
    parameter."""
    return _run_gpmhe(*_parameter_gpmhe(data, "casadi"), data)


def run_gpmhe_casadi_callbacks(data, settings):
    """As `run_gpmhe_casadi` on Python callbacks (``native=False``)."""
    return _run_gpmhe(*_parameter_gpmhe(data, "casadi", native=False), data)


def run_gpmhe_casadi_jit(data, settings):
    """As `run_gpmhe_casadi_callbacks` with the CasADi model compiled by CasADi's JIT
    (``jit=True``). Building the estimator plus its slowest update (which may include
    compiling) are also kept in settings["compile_seconds"]."""
    t0 = time.perf_counter()
    est, split = _parameter_gpmhe(data, "casadi", jit=True, native=False)
    built = time.perf_counter() - t0
    xs, thetas, times, n_warn = _run_gpmhe(est, split, data)
    settings.setdefault("compile_seconds", []).append(built + max(times))
    return xs, thetas, times, n_warn


def run_gpmhe_numpy(data, settings):
    """GPMHE, exact model in numpy (analytic Jacobian), Θ1 estimated as the model's parameter."""
    return _run_gpmhe(*_parameter_gpmhe(data, "numpy"), data)


def run_gpmhe_casadi_dompc_arrival(data, settings):
    """As `run_gpmhe_casadi` with do-mpc's arrival cost: smoothed mean, constant weight."""
    return _run_gpmhe(*_parameter_gpmhe(data, "casadi", ("smoothed", "constant")), data)


def run_gpmhe_known_theta(data, settings):
    """Reference: GPMHE with the exact model and the TRUE Θ1 (rm.known_model, rm.MHE_SETTINGS)."""
    est = GPMHE(rm.known_model(), data["x0"], **{**rm.MHE_SETTINGS, "form": "filtering"})
    return _run_gpmhe(est, lambda e: (e.x.copy(), np.nan), data)


def fit_learned(data, settings):
    """The learned model on the seed's training trajectories (true Θ1) and its fit seconds."""
    tr = data["train"]
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = LearnedModel.from_trajectories(tr["states"], tr["outputs"], tr["inputs"],
                                               n_restarts=settings["restarts"],
                                               random_state=data["seed"], **settings["gp_options"])
    return model, time.perf_counter() - t0, len(caught)


def run_gpmhe_learned(data, settings):
    """GP-MHE on the learned model (no Θ1: its Θ̂1 is NaN)."""
    model, seconds, fit_warnings = fit_learned(data, settings)
    settings.setdefault("fit_seconds", []).append(seconds)
    settings["fit_warnings"] = settings.get("fit_warnings", 0) + fit_warnings
    est = GPMHE(model, data["x0"], **{**rm.MHE_SETTINGS, "form": "filtering"})
    return _run_gpmhe(est, lambda e: (e.x.copy(), np.nan), data)


# ---- the table ----------------------------------------------------------------------------
ESTIMATORS = {
    "do-mpc MHE (collocation)": run_dompc,
    "filterpy EKF": run_ekf,
    "filterpy UKF": run_ukf,
    "  EKF, tight Θ1 prior": run_ekf_tight,
    "  UKF, tight Θ1 prior": run_ukf_tight,
    "GPMHE exact, CasADi, native": run_gpmhe_casadi,
    "  CasADi callbacks": run_gpmhe_casadi_callbacks,
    "  CasADi callbacks, jit": run_gpmhe_casadi_jit,
    "GPMHE exact, numpy": run_gpmhe_numpy,
    "  CasADi, do-mpc's arrival": run_gpmhe_casadi_dompc_arrival,
    "GP-MHE learned (true Θ1)": run_gpmhe_learned,
    "ref.: GPMHE, Θ1 known": run_gpmhe_known_theta,
}


def rmse(xs, truth):
    return float(np.sqrt(np.mean((xs - truth) ** 2)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--steps", type=int, default=rm.STEPS)
    ap.add_argument("--restarts", type=int, default=1, help="GP hyperparameter restarts")
    ap.add_argument("--quick", action="store_true",
                    help="1 seed, 20 steps, 2 training trajectories")
    args = ap.parse_args(argv)
    if args.quick:
        args.seeds, args.steps = 1, min(args.steps, 20)
    settings = dict(restarts=args.restarts, gp_options={}, notes=[],
                    n_train=2 if args.quick else TRAIN_TRAJECTORIES)
    do_mpc, why = import_dompc()
    settings["do_mpc"] = do_mpc
    estimators = {k: v for k, v in ESTIMATORS.items() if do_mpc is not None or v is not run_dompc}

    results = {name: dict(all=[], late=[], theta=[], times=[], warnings=0) for name in estimators}
    console = {name: [] for name in estimators}
    half = args.steps // 2
    for seed in range(args.seeds):
        data = make_data(seed, args.steps, settings["n_train"])
        truth = data["x"][1:]
        for name, run in estimators.items():
            with captured_output(console[name]):
                xs, thetas, times, n_warn = run(data, settings)
            r = results[name]
            r["all"].append(rmse(xs, truth))
            r["late"].append(rmse(xs[half:], truth[half:]))
            r["theta"].append(abs(thetas[-1] - rm.THETA1) / rm.THETA1)
            r["times"].extend(times)
            r["warnings"] += n_warn

    print(f"rotating masses (do-mpc's MHE example): {args.seeds} seeds, {args.steps} steps, "
          f"horizon {rm.HORIZON}; RMSE over the 8 states, t = 1..{args.steps} and t > {half}")
    print(f"do-mpc {do_mpc.__version__}" if do_mpc is not None
          else f"do-mpc not available ({why}): its row is left out")
    refs = ("do-mpc MHE (collocation)", "filterpy EKF", "  CasADi callbacks")
    ref = {k: np.median(results[k]["times"]) for k in refs if k in results}
    print(f"{'estimator':27} {'RMSE':>7} {'2nd half':>8} {'|dΘ1|/Θ1':>9} {'(max)':>7} {'ms med':>7} "
          f"{'p95':>7} {'warn':>5} {'/do-mpc':>8} {'/EKF':>7} {'/callb.':>7}")
    for name, r in results.items():
        t = np.array(r["times"]) * 1e3
        med = np.median(t) / 1e3
        theta = np.array(r["theta"])
        th = (f"{np.mean(theta):9.3f} {np.max(theta):7.3f}" if np.all(np.isfinite(theta))
              else f"{'-':>9} {'-':>7}")
        ratios = [f"{med / ref[k]:.2f}" if k in ref else "-" for k in refs]
        print(f"{name:27} {np.mean(r['all']):7.3f} {np.mean(r['late']):8.3f} {th} {np.median(t):7.2f} "
              f"{np.percentile(t, 95):7.2f} {r['warnings']:5d} {ratios[0]:>8} {ratios[1]:>7} "
              f"{ratios[2]:>7}")
    fit = settings.get("fit_seconds", [])
    if fit:
        print(f"learned model: {settings['n_train']} x {TRAIN_STEPS} training steps, "
              f"{settings['restarts']} restart(s), fit {np.mean(fit):.1f} s per seed "
              f"(max {np.max(fit):.1f} s), "
              f"{settings.get('fit_warnings', 0)} fit warnings")
    compiled = settings.get("compile_seconds", [])
    if compiled:
        print(f"compiled CasADi model (jit=True): building the estimator and its slowest update "
              f"(compiling) took {np.mean(compiled):.2f} s (mean over seeds; CasADi may reuse an "
              f"earlier compilation)")
    for note in settings["notes"]:
        print("note:", note)
    for name, lines in console.items():
        if lines:
            print(f"{name}: {len(lines)} console lines captured, e.g. {' / '.join(lines[:2])[:150]!r}")


if __name__ == "__main__":
    main()
