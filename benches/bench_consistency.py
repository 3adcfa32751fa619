"""Benchmark: is the estimators' uncertainty consistent? NEES and NIS over Monte Carlo runs.

    python benches/bench_consistency.py [--runs 100] [--steps 100]

One table, one run, no timing. Every estimator runs in the filtering form (x̂(t) after y(t))
with its process and output covariances equal to the plant's noise, from a prior that matches
how the initial state is drawn. Per plant and row, ``--runs`` independent runs (generator
[run, plant]):

- NEES: (x − x̂)ᵀP⁻¹(x − x̂) at the last step of each run (one value per run: a run's NEES is
  correlated from step to step), its mean and the 95 % band of a consistent estimator's mean
  (χ²(n·runs)/runs, `gpmhe.consistency.chi2_test`);
- NIS: ``nis`` of every update after step 20 of every run (white when consistent), its mean and
  band (dof: the one output);
- RMSE of x̂ at the last step over the runs.

Plants:

(a) linear-Gaussian, x(t+1) = A x + w, y = C x + v (2 states, position measured), x(0) ~ N(0, I),
    prior 0 with P0 = I; rows: GPMHE with the Kalman-filter settings (``arrival_mean="estimate",
    arrival_weight="ekf"``, η = 1), GPMHE with gpmhe's default arrival cost (η = 1 and the
    default η = 0.91) at M = 5 and M = 15, filterpy's KalmanFilter;
(b) the batch reactor with its exact model (σ_w = 0.01, σ_v = 0.1), x(0) = [3, 1] + N(0, 0.1² I),
    prior [3, 1], P0 = 0.1² I, M = 15, the state box; rows as in (a) with filterpy's EKF;
(c) the same plant with GP-MHE on the GPs of the demo (5 training trajectories, 3 restarts):
    the default arrival cost, η = 1 and the paper's η = 0.91; then sparse GPs (30 inducing
    points) fixed (η = 1) and learning (``learning=True``, η = 1 and 0.91);
(d) the reactor of (c) whose first rate constant falls by 40 % over the first 100 steps and
    stays there (as in ``bench_learning.py``), runs of 2 × ``--steps`` steps, the sparse GPs of
    (c) trained on the nominal plant: fixed, and learning (η = 0.91) with no drift and with the
    drifts q = 1e-7 and 1e-6 per step.
"""

from __future__ import annotations

import argparse

import numpy as np
from filterpy.kalman import KalmanFilter

from gpmhe import GPMHE, KnownModel, LearnedModel
from gpmhe.baselines import ExactEKF
from gpmhe.consistency import chi2_test, nees
from gpmhe.systems import batch_reactor as br
from bench_learning import reactor_run as reactor_run_with_drift

TRANSIENT = 20
A = np.array([[1.0, 0.1], [-0.05, 0.95]])
C = np.array([[1.0, 0.0]])
Q_LIN, R_LIN = np.diag([1e-4, 4e-4]), np.array([[0.01]])


def f_lin(x, u):
    return A @ x


def h_lin(x, u):
    return C @ x


LINEAR = KnownModel(f_lin, h_lin, 2, 1, f_jacobian=lambda x, u: A, h_jacobian=lambda x, u: C)
REACTOR = KnownModel(br.f, br.h, 2, 1, f_jacobian=br.f_jacobian, h_jacobian=br.h_jacobian)
KALMAN_LIKE = dict(arrival_mean="estimate", arrival_weight="ekf", eta=1.0)


def linear_run(rng, steps):
    x = np.empty((steps, 2))
    x[0] = rng.standard_normal(2)
    for t in range(1, steps):
        x[t] = A @ x[t - 1] + rng.multivariate_normal(np.zeros(2), Q_LIN)
    return x, x @ C.T + rng.normal(0.0, np.sqrt(R_LIN[0, 0]), (steps, 1))


def reactor_run(rng, steps):
    x0 = br.X_TRUE0 + 0.1 * rng.standard_normal(2)
    x, y = br.simulate(x0, steps - 1, rng)
    return x, y


def drifting_reactor_run(rng, steps):
    """The reactor with k1 falling by 40 % over the first 100 steps (constant after)."""
    return reactor_run_with_drift(br.X_TRUE0 + 0.1 * rng.standard_normal(2), steps, rng)


def mhe_rows(model, x0, P0, Q, R, horizon, bounds=None, etas=(1.0,), rows=None):
    if rows is None:
        rows = [(f"GPMHE, Kalman-filter settings, M = {horizon}",
                 dict(horizon=horizon, **KALMAN_LIKE))]
        for eta in etas:
            rows.append((f"GPMHE, default arrival cost, M = {horizon}, η = {eta:g}",
                         dict(horizon=horizon, eta=eta)))
    out = []
    for name, kw in rows:
        def make(kw=kw):
            est = GPMHE(model, x0, P0=P0, Q0=Q, R0=R, form="filtering", x_bounds=bounds, **kw)

            def step(y):
                est.update(None, y)
                return est.x, est.P, est.nis
            return step
        out.append((name, make))
    return out


def filterpy_row(name, build):
    """A row of a filterpy filter made by ``build()``: predict (after the first sample), update."""
    def make():
        kf, first = build(), [True]

        def step(y):
            if not first[0]:
                kf.predict()
            first[0] = False
            kf.update(y)
            nu = kf.y.ravel()
            return np.ravel(kf.x).copy(), kf.P.copy(), float(nu @ np.linalg.solve(kf.S, nu))
        return step
    return (name, make)


def kalman():
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.F, kf.H, kf.Q, kf.R, kf.P, kf.x = A, C, Q_LIN, R_LIN, np.eye(2), np.zeros(2)
    return kf


def evaluate(rows, simulate, plant, runs, steps):
    """{row: (NEES test, NIS test, RMSE)} over ``runs`` runs."""
    out = {}
    for name, make in rows:
        last, nis, err = [], [], []
        for run in range(runs):
            x, y = simulate(np.random.default_rng([run, plant]), steps)
            step = make()
            for t in range(steps):
                xh, P, v = step(y[t])
                if t >= TRANSIENT:
                    nis.append(v)
            last.append((x[-1], xh, P))
            err.append(xh - x[-1])
        xt, xs, Ps = map(np.array, zip(*last))
        out[name] = (chi2_test(nees(xt, xs, Ps), dof=2), chi2_test(nis, dof=1),
                     float(np.sqrt(np.mean(np.sum(np.array(err) ** 2, axis=1)))))
    return out


def print_table(title, results):
    print(f"\n{title}")
    width = max(46, *(len(name) for name in results))
    print(f"| {'estimator':<{width}} | {'NEES':>6} | {'95 % band':>14} | {'NIS':>6} | "
          f"{'95 % band':>14} | {'RMSE':>7} |")
    print(f"|{'-' * (width + 2)}|{'-' * 8}|{'-' * 16}|{'-' * 8}|{'-' * 16}|{'-' * 9}|")
    for name, (ne, ni, rmse) in results.items():
        mark = lambda r: "" if r.consistent else ("↑" if r.mean > r.upper else "↓")  # noqa: E731
        print(f"| {name:<{width}} | {ne.mean:5.2f}{mark(ne):1} | [{ne.lower:5.2f}, {ne.upper:5.2f}] | "
              f"{ni.mean:5.2f}{mark(ni):1} | [{ni.lower:5.2f}, {ni.upper:5.2f}] | {rmse:7.4f} |")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=100)
    ap.add_argument("--steps", type=int, default=100)
    args = ap.parse_args()
    lin = mhe_rows(LINEAR, [0.0, 0.0], np.eye(2), Q_LIN, R_LIN, 5, etas=(1.0, 0.91))
    lin += mhe_rows(LINEAR, [0.0, 0.0], np.eye(2), Q_LIN, R_LIN, 15, etas=(1.0, 0.91))[1:]
    lin.append(filterpy_row("filterpy KalmanFilter", kalman))
    print_table("(a) linear-Gaussian plant (n = 2, p = 1)",
                evaluate(lin, linear_run, 0, args.runs, args.steps))
    Q, R, P0 = br.SIGMA_W ** 2 * np.eye(2), br.SIGMA_V ** 2 * np.eye(1), 0.01 * np.eye(2)
    react = mhe_rows(REACTOR, br.X_TRUE0, P0, Q, R, 15, br.X_BOUNDS, etas=(1.0, 0.91))
    react.append(filterpy_row("filterpy EKF, exact model", lambda: ExactEKF(
        br.f, br.f_jacobian, br.h, br.h_jacobian, br.X_TRUE0, P0, Q, R)))
    print_table("(b) batch reactor, exact model",
                evaluate(react, reactor_run, 1, args.runs, args.steps))
    gp = LearnedModel.from_trajectories(*br.training_data(5, rng=np.random.default_rng(0)),
                                        n_restarts=3, random_state=0, **br.PAPER_GP)
    learned = mhe_rows(gp, br.X_TRUE0, P0, Q, R, 15, br.X_BOUNDS, etas=(1.0, 0.91))
    sparse = LearnedModel.from_trajectories(*br.training_data(5, rng=np.random.default_rng(0)),
                                            n_restarts=3, random_state=0, n_inducing=30,
                                            **br.PAPER_GP)
    learned += mhe_rows(sparse, br.X_TRUE0, P0, Q, R, 15, br.X_BOUNDS, rows=[
        ("GPMHE, sparse GPs (m = 30), η = 1", dict(horizon=15, eta=1.0)),
        ("GPMHE, sparse GPs (m = 30) learning, η = 1",
         dict(horizon=15, eta=1.0, learning=True)),
        ("GPMHE, sparse GPs (m = 30) learning, η = 0.91",
         dict(horizon=15, eta=0.91, learning=True))])
    print_table("(c) batch reactor, GP model (5 training trajectories)",
                evaluate(learned, reactor_run, 1, args.runs, args.steps))
    drifting = mhe_rows(sparse, br.X_TRUE0, P0, Q, R, 15, br.X_BOUNDS, rows=[
        ("GPMHE, sparse GPs (m = 30), η = 1", dict(horizon=15, eta=1.0))] + [
        (f"GPMHE, sparse GPs (m = 30) learning, η = 0.91, q = {q:g}",
         dict(horizon=15, eta=0.91, learning=True, learning_options={"drift": q}))
        for q in (0.0, 1e-7, 1e-6)])
    print_table("(d) batch reactor, k1 −40 % over steps 0-100, GPs of (c) on the nominal plant",
                evaluate(drifting, drifting_reactor_run, 2, args.runs, 2 * args.steps))
    print("\n↑: above the band (over-confident), ↓: below (under-confident)")


if __name__ == "__main__":
    main()
