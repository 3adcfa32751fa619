"""Benchmark: a lab assay that arrives late, on the batch reactor.

    python benches/bench_late_assay.py [--seeds 20] [--steps 100] [--every 20] [--delay 10]

One table, one run. The batch reactor's total concentration y₁ = x₁ + x₂ is measured every step
(σ = 0.1, as in the paper); an assay of x₁ (σ = 0.05) is taken every ``--every`` steps and
arrives ``--delay`` steps later. Per seed (generator [seed, 1]): 100 steps from the true state
[3, 1]; every estimator starts from x̂(0) = [2, 2] with the exact model. Rows:

- MHE, late assay: ``add_delayed`` when it arrives (its own covariance, ``R=``);
- MHE, no assay: the assay dropped;
- MHE, assay as if current: written as a measurement of the step at which it arrives;
- full information: the same MHE with a horizon longer than the run (every output kept);
- filterpy EKF, assay as if current: a second, sequential update with the stale value when it
  arrives; filterpy EKF, no assay.

The MHEs run M = 15, η = 1, Q0 = 1e-4 I, R0 = diag(0.01, 0.0025), filtering form, gpmhe's
default arrival cost; the EKFs Q = 1e-4 I, the same R, P0 = I. Columns: RMSE of x̂(t) over the run
after step 20, of x₁ alone, both mean over seeds, and the median time per update (for
``add_delayed``, the update after it includes the call).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter

from gpmhe import GPMHE, KnownModel
from gpmhe.systems import batch_reactor as br

SIGMA_ASSAY = 0.05
R0 = np.diag([br.SIGMA_V ** 2, SIGMA_ASSAY ** 2])
X0 = np.array([2.0, 2.0])
H = np.array([[1.0, 1.0], [1.0, 0.0]])


def h2(x, u=None):
    return H @ x


def h2_jacobian(x, u=None):
    return H


MODEL = KnownModel(br.f, h2, dim_x=2, dim_y=2, f_jacobian=br.f_jacobian, h_jacobian=h2_jacobian)


def plant(seed, steps, every, delay):
    """States (steps + 1, 2), the measured sums (steps,), and the assays: {arrival time: (time
    taken, value)}."""
    rng = np.random.default_rng([seed, 1])
    x, y = br.simulate(br.X_TRUE0, steps, rng)
    assays = {t + delay: (t, x[t, 0] + SIGMA_ASSAY * rng.standard_normal())
              for t in range(0, steps - delay, every)}
    return x, y[:steps, 0], assays


def mhe_rows(steps):
    kw = dict(horizon=15, eta=1.0, Q0=br.SIGMA_W ** 2, R0=R0, x_bounds=br.X_BOUNDS, form="filtering")
    return {
        "MHE, late assay (add_delayed)": lambda: (GPMHE(MODEL, X0, **kw), "late"),
        "MHE, no assay": lambda: (GPMHE(MODEL, X0, **kw), "drop"),
        "MHE, assay as if current": lambda: (GPMHE(MODEL, X0, **kw), "current"),
        "full information, late assay": lambda: (GPMHE(MODEL, X0, **{**kw, "horizon": steps + 2}),
                                                 "late"),
    }


def run_mhe(est, how, y, assays):
    xs, times = [], []
    for t, yt in enumerate(y):
        sample = np.array([yt, np.nan])
        t0 = time.perf_counter()
        if t in assays and how == "late":
            taken, value = assays[t]
            est.add_delayed([np.nan, value], age=t - 1 - taken)
        elif t in assays and how == "current":
            sample[1] = assays[t][1]
        xs.append(est.update(None, sample).copy())
        times.append(time.perf_counter() - t0)
    return np.array(xs), times


def run_ekf(use_assay, y, assays):
    ekf = ExtendedKalmanFilter(dim_x=2, dim_z=1)
    ekf.x, ekf.P, ekf.Q = X0.reshape(-1, 1).copy(), np.eye(2), 1e-4 * np.eye(2)
    xs, times = [], []
    for t, yt in enumerate(y):
        t0 = time.perf_counter()
        ekf.update(np.array([[yt]]), lambda x: H[:1], lambda x: H[:1] @ x, R=R0[:1, :1])
        if use_assay and t in assays:  # the stale assay as a measurement of now
            ekf.update(np.array([[assays[t][1]]]), lambda x: H[1:], lambda x: H[1:] @ x,
                       R=R0[1:, 1:])
        xs.append(ekf.x.ravel().copy())
        ekf.F = br.f_jacobian(ekf.x.ravel())
        ekf.P = ekf.F @ ekf.P @ ekf.F.T + ekf.Q
        ekf.x = br.f(ekf.x.ravel()).reshape(-1, 1)
        times.append(time.perf_counter() - t0)
    return np.array(xs), times


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--every", type=int, default=20)
    ap.add_argument("--delay", type=int, default=10)
    args = ap.parse_args()
    names = list(mhe_rows(args.steps)) + ["filterpy EKF, assay as if current", "filterpy EKF, no assay"]
    res = {name: dict(rmse=[], rmse1=[], times=[]) for name in names}
    for seed in range(args.seeds):
        x, y, assays = plant(seed, args.steps, args.every, args.delay)
        runs = {name: run_mhe(*make(), y, assays) for name, make in mhe_rows(args.steps).items()}
        runs["filterpy EKF, assay as if current"] = run_ekf(True, y, assays)
        runs["filterpy EKF, no assay"] = run_ekf(False, y, assays)
        for name, (xs, times) in runs.items():
            err = xs[20:] - x[20:args.steps]  # filtering form: x̂(t) against x(t)
            res[name]["rmse"].append(np.sqrt(np.mean(np.sum(err ** 2, axis=1))))
            res[name]["rmse1"].append(np.sqrt(np.mean(err[:, 0] ** 2)))
            res[name]["times"].extend(times)
    print(f"batch reactor, {args.seeds} seeds x {args.steps} steps; an assay of x1 every "
          f"{args.every} steps, {args.delay} steps late")
    print(f"| {'estimator':<36} | {'RMSE x':>8} | {'RMSE x1':>8} | {'ms/update':>9} |")
    print(f"|{'-' * 38}|{'-' * 10}|{'-' * 10}|{'-' * 11}|")
    for name in names:
        r = res[name]
        print(f"| {name:<36} | {np.mean(r['rmse']):8.4f} | {np.mean(r['rmse1']):8.4f} | "
              f"{np.median(r['times']) * 1e3:9.3f} |")


if __name__ == "__main__":
    main()
