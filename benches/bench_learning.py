"""A GP-MHE that keeps learning (``GPMHE(..., learning=True)``) against the fixed GP-MHE, the MHE
on the exact model with the drifting rate estimated as a parameter, and filterpy's EKF on the
fixed GP model, on the batch reactor (docs/user_guide/learning.rst, *Benchmark*).

Two scenarios, ``--seeds`` runs each (200 steps, the reactor's noise, x̂(0) = [3, 1], the paper's
weights with the default arrival cost in the filtering form, so every row estimates x(t) from
y(0..t)):

* **drift**: GPs trained offline on the nominal plant (5 trajectories); online the first rate
  constant k1 falls linearly by 40 % over the first 100 steps and stays there;
* **3 trajectories**: GPs trained on the paper's 3 trajectories only, no drift.

Rows: the fixed GP-MHE and the learning one on sparse f-GPs with m inducing points each (sparse
h-GP too), the MHE on the reactor's own equations (with k1 estimated as a parameter, p_drift
1e-3, in the drift scenario; exact in the other), and filterpy's EKF on the fixed GP model
(``gpmhe.baselines.GPEKF``). The RGP-dKF (``gpmhe.RGPEKF``) does not apply: its GPs' inputs are
measured signals, the reactor's GP inputs are its unmeasured states. In the drift scenario, also
the MHE on the reactor's equations with k1 at its value after the drift: exact from step 100 on,
the best a model can do there. Columns: RMSE of x̂(t) over
steps 1-100 and 101-200, the mean error norm over the last 20 steps, ms per update (median, p95)
and × the fixed GP-MHE's median (the same run, interleaved per seed).

    python benches/bench_learning.py            # 20 seeds (about 2 minutes)
    python benches/bench_learning.py --seeds 3  # a quick look
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

from gpmhe import GPMHE, KnownModel, LearnedModel
from gpmhe.baselines import GPEKF
from gpmhe.systems import batch_reactor as br

STEPS = 200
SETTINGS = dict(br.RECOMMENDED_SETTINGS, x_bounds=br.X_BOUNDS, form="filtering")
X0 = np.array([3.0, 1.0])


def simulate(seed, drift):
    """The reactor with k1 falling by 40 % over 100 steps (``drift``), or nominal."""
    return reactor_run(br.X_TRUE0, STEPS + 1, np.random.default_rng(1000 + seed), drift)


def reactor_run(x0, rows, rng, drift=True):
    """`rows` states from x0 and their outputs, with k1 falling by 40 % over the first 100 steps
    and constant after (``drift``), or nominal."""
    x = np.empty((rows, 2))
    x[0] = x0
    for t in range(rows - 1):
        k1 = br.K1 * (1.0 - 0.4 * min(t / 100.0, 1.0)) if drift else br.K1
        x[t + 1] = f_k1(x[t], k1) + br.SIGMA_W * rng.standard_normal(2)
    y = x.sum(axis=1, keepdims=True) + br.SIGMA_V * rng.standard_normal((rows, 1))
    return x, y


def f_k1(x, k1):
    x1, x2 = x
    return np.array([x1 + br.T * (-2.0 * k1 * x1 ** 2 + 2.0 * br.K2 * x2),
                     x2 + br.T * (k1 * x1 ** 2 - br.K2 * x2)])


def parametric_model():
    """The reactor's equations with k1 = p[0] unknown."""
    def f(x, u, p):
        return f_k1(x, p[0])

    def h(x, u, p):
        return np.array([x[0] + x[1]])

    return KnownModel(f, h, dim_x=2, dim_y=1, dim_p=1)


def drifted_model():
    """The reactor's equations with k1 at its value after the drift (0.6 k1): the exact model
    from step 100 on, an oracle no estimator can beat there by knowing the model better."""
    def f(x, u):
        return f_k1(x, 0.6 * br.K1)

    def h(x, u):
        return np.array([x[0] + x[1]])

    return KnownModel(f, h, dim_x=2, dim_y=1)


def estimators(models, drift):
    """(name, factory) of every row; a factory returns ``step(y) -> x̂``."""
    def mhe(model, **kw):
        def make():
            est = GPMHE(model, x0=X0, **SETTINGS, **kw)
            return lambda y: est.update(None, y)
        return make

    def ekf(model):
        def make():
            kf = GPEKF(model, x0=X0, P0=np.linalg.inv(SETTINGS["P2"]), Q=SETTINGS["Q0"],
                       R=SETTINGS["R0"])

            def step(y):
                kf.update(y)
                x = kf.x.ravel().copy()
                kf.predict()
                return x
            return step
        return make

    rows = [("fixed GP-MHE (m=30)", mhe(models[30]))]
    for m in sorted(models):
        rows.append((f"learning GP-MHE (m={m})", mhe(models[m], learning=True)))
    rows.append(("learning GP-MHE (m=30, drift 1e-7)",
                 mhe(models[30], learning=True, learning_options={"drift": 1e-7})))
    if drift:
        rows.append(("exact model, k1 estimated", mhe(parametric_model(), p0=[br.K1], p_drift=1e-3)))
        rows.append(("exact model, final k1 known", mhe(drifted_model())))
    else:
        rows.append(("exact model", mhe(KnownModel(br.f, br.h, dim_x=2, dim_y=1,
                                                   f_jacobian=br.f_jacobian,
                                                   h_jacobian=br.h_jacobian))))
    rows.append(("filterpy EKF, fixed GP model", ekf(models[30])))
    return rows


def run(rows, seeds, drift):
    """Per row: errors (seeds, STEPS, 2) and update times."""
    errors = {name: [] for name, _ in rows}
    times = {name: [] for name, _ in rows}
    for seed in range(seeds):
        x, y = simulate(seed, drift)
        for name, make in rows:
            step = make()
            est = np.empty((STEPS, 2))
            for t in range(STEPS):
                t0 = time.perf_counter()
                est[t] = step(y[t])
                times[name].append(time.perf_counter() - t0)
            errors[name].append(est - x[:STEPS])
    return {k: np.array(v) for k, v in errors.items()}, times


def table(title, errors, times):
    base = np.median(times[next(iter(times))])
    print(f"\n{title}\n")
    print(f"{'estimator':38s} {'RMSE 1-100':>10s} {'RMSE 101-200':>12s} {'final':>7s} "
          f"{'median ms':>9s} {'p95 ms':>7s} {'× fixed':>7s}")
    for name, e in errors.items():
        rmse = lambda a: np.sqrt(np.mean(a ** 2))
        final = np.mean(np.linalg.norm(e[:, -20:], axis=2))
        med, p95 = np.median(times[name]) * 1e3, np.percentile(times[name], 95) * 1e3
        print(f"{name:38s} {rmse(e[:, 1:101]):10.4f} {rmse(e[:, 101:]):12.4f} {final:7.4f} "
              f"{med:9.3f} {p95:7.3f} {med / (base * 1e3):7.2f}")


def model_change(seeds):
    """The median over the drift scenario's runs and steps 50-200 of |f(x; 0.6 k1) − f(x; k1)|:
    how much the drift changes the one-step map where the reactor runs."""
    d = [np.linalg.norm(f_k1(xt, 0.6 * br.K1) - f_k1(xt, br.K1))
         for seed in range(seeds) for xt in simulate(seed, True)[0][50:]]
    return float(np.median(d))


def models(n_trajectories, sizes):
    states, outputs = br.training_data(n_trajectories, rng=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return {m: LearnedModel.from_trajectories(states, outputs, n_inducing=m) for m in sizes}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    args = ap.parse_args()
    sizes = (20, 30, 50)
    for title, n_traj, drift in (("drift: k1 −40 % over steps 0-100, GPs from 5 trajectories",
                                  5, True),
                                 ("no drift, GPs from 3 trajectories", 3, False)):
        rows = estimators(models(n_traj, sizes), drift)
        errors, times = run(rows, args.seeds, drift)
        table(f"{title} ({args.seeds} seeds, {STEPS} steps)", errors, times)
        if drift:
            print(f"\nFrom step 50 on, the drift changes the one-step map by "
                  f"{model_change(args.seeds):.4f} (median; the process noise's σ_w = "
                  f"{br.SIGMA_W:g})")


if __name__ == "__main__":
    main()
