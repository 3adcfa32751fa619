"""Benchmark: irregular sampling on the cart-pole, each sample's interval against a fixed one.

    python benches/bench_jitter.py [--seeds 20] [--steps 200] [--jitter 0.5]

One table, one run. The cart-pole of `gpmhe.systems.cart_pole` (all four states measured, its
near-deterministic noise: σ_w up to 1e-4 per sample, σ_v up to 0.1) is sampled at intervals
T·(1 + U(−jitter, jitter)), T = 0.05 s: ±50 % by default. The plant is integrated over each
interval by RK4 with 20 sub-steps, the force held; process noise is added per sample. Per seed
(generator [seed, 7]): ``--steps`` samples from `cart_pole.X0`, forces as `cart_pole.simulate`
draws them. Every estimator starts at the true initial state and runs the model with T's 4 RK4
sub-steps per interval. Rows:

- GPMHE, each sample's interval: ``update(u, y, dt=...)`` with the CasADi model
  (`cart_pole.known_model`), filtering form, `cart_pole.MHE_SETTINGS`;
- GPMHE, fixed interval: the same without ``dt`` (every stage integrated over T);
- GPMHE, each sample's interval, ``arrival_mean="estimate"``: the first row with the arrival
  mean of the paper (the estimate's own prediction) instead of the smoothed one;
- filterpy UKF, each sample's interval: ``predict(dt=...)`` integrating the same numpy model
  (`gpmhe.discretize` over that interval), then ``update``; Q = diag(σ_w²), R = diag(σ_v²),
  P0 = P2⁻¹ (the MHE's arrival covariance), Merwe's sigma points (α = 0.1, β = 2, κ = 0);
- filterpy EKF, each sample's interval: the same model and its exact Jacobian over the interval.

Columns: RMSE of x̂(t) against x(t) over all states and samples (mean over seeds), of the angle θ
alone, the worst seed's RMSE, the MHE's mean solver iterations per update, and the time per
update in ms (median, p95, all seeds) with its ratio to the fixed-interval GPMHE's median (same
run).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter, MerweScaledSigmaPoints, UnscentedKalmanFilter

from gpmhe import GPMHE, discretize
from gpmhe.systems import cart_pole as cp

TRUTH_SUBSTEPS = 20


def plant(seed, steps, jitter):
    """True states (steps, 4), inputs (steps, 1), outputs (steps, 4) and the intervals (steps,):
    interval k ends at sample k (interval 0 is not used)."""
    rng = np.random.default_rng([seed, 7])
    dts = cp.T * (1.0 + rng.uniform(-jitter, jitter, steps))
    levels = rng.uniform(-cp.F_MAX, cp.F_MAX, size=steps // cp.U_HOLD + 1)
    u = np.repeat(levels, cp.U_HOLD)[:steps, None]
    x = np.empty((steps, cp.DIM_X))
    x[0] = cp.X0
    for k in range(1, steps):
        f = discretize(cp.rhs, dts[k], substeps=TRUTH_SUBSTEPS)
        x[k] = f(x[k - 1], u[k - 1]) + cp.SIGMA_W * rng.standard_normal(cp.DIM_X)
    y = x + cp.SIGMA_V * rng.standard_normal(x.shape)
    return x, u, y, dts


def run_mhe(model, timed, u, y, dts, **options):
    est = GPMHE(model, x0=cp.X0, form="filtering", **{**cp.MHE_SETTINGS, **options})
    xs, times, nit = [], [], []
    for k in range(len(y)):
        t0 = time.perf_counter()
        xs.append(est.update(u[k], y[k], dt=dts[k] if timed else None).copy())
        times.append(time.perf_counter() - t0)
        nit.append(est.nit)
    return np.array(xs), times, nit


class _Maps:
    """The model's discrete map (4 RK4 sub-steps) over any interval, built once per interval."""

    def __init__(self):
        self.cache = {}

    def __call__(self, dt):
        if dt not in self.cache:
            self.cache[dt] = discretize(cp.rhs, dt, substeps=cp.SUBSTEPS,
                                        rhs_jacobian=cp.rhs_jacobian)
        return self.cache[dt]


def _filter_start(kf):
    kf.x = cp.X0.astype(float).copy()
    kf.P = np.linalg.inv(cp.MHE_SETTINGS["P2"])
    kf.Q, kf.R = np.diag(cp.SIGMA_W ** 2), np.diag(cp.SIGMA_V ** 2)


def run_ukf(u, y, dts):
    maps = _Maps()
    points = MerweScaledSigmaPoints(cp.DIM_X, alpha=0.1, beta=2.0, kappa=0.0)
    ukf = UnscentedKalmanFilter(cp.DIM_X, cp.DIM_Y, cp.T, hx=lambda x: x,
                                fx=lambda x, dt, u: maps(dt)(x, u), points=points)
    _filter_start(ukf)
    xs, times = [], []
    for k in range(len(y)):
        t0 = time.perf_counter()
        if k:
            ukf.predict(dt=dts[k], u=u[k - 1])
        ukf.update(y[k])
        xs.append(ukf.x.copy())
        times.append(time.perf_counter() - t0)
    return np.array(xs), times, []


def run_ekf(u, y, dts):
    maps = _Maps()
    ekf = ExtendedKalmanFilter(cp.DIM_X, cp.DIM_Y)
    _filter_start(ekf)
    eye = np.eye(cp.DIM_X)
    xs, times = [], []
    for k in range(len(y)):
        t0 = time.perf_counter()
        if k:
            x_next, F = maps(dts[k]).value_and_jacobian(ekf.x, u[k - 1])
            ekf.x, ekf.P = x_next, F @ ekf.P @ F.T + ekf.Q
        ekf.update(y[k], lambda x: eye, lambda x: x)
        xs.append(ekf.x.copy())
        times.append(time.perf_counter() - t0)
    return np.array(xs), times, []


ROWS = ("GPMHE, each sample's interval (dt=)", "GPMHE, fixed interval T",
        "GPMHE, each interval, estimate mean", "filterpy UKF, each sample's interval",
        "filterpy EKF, each sample's interval")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--jitter", type=float, default=0.5)
    args = ap.parse_args()
    model = cp.known_model("casadi")
    res = {name: dict(rmse=[], rmse_theta=[], times=[], nit=[]) for name in ROWS}
    for seed in range(args.seeds):
        x, u, y, dts = plant(seed, args.steps, args.jitter)
        runs = dict(zip(ROWS, (run_mhe(model, True, u, y, dts), run_mhe(model, False, u, y, dts),
                               run_mhe(model, True, u, y, dts, arrival_mean="estimate"),
                               run_ukf(u, y, dts), run_ekf(u, y, dts))))
        for name, (xs, times, nit) in runs.items():
            err = xs - x
            res[name]["rmse"].append(np.sqrt(np.mean(np.sum(err ** 2, axis=1))))
            res[name]["rmse_theta"].append(np.sqrt(np.mean(err[:, 1] ** 2)))
            res[name]["times"].extend(times[1:])  # (the first update builds caches)
            res[name]["nit"].extend(nit)
    base = np.median(res[ROWS[1]]["times"])
    print(f"cart-pole, {args.seeds} seeds x {args.steps} samples, intervals T(1 ± U({args.jitter:g})), "
          f"T = {cp.T} s")
    print(f"| {'estimator':<38} | {'RMSE x':>8} | {'RMSE θ':>8} | {'worst':>8} | "
          f"{'iter.':>5} | {'median ms':>9} | {'p95 ms':>7} | {'× fixed':>7} |")
    print(f"|{'-' * 40}|{'-' * 10}|{'-' * 10}|{'-' * 10}|{'-' * 7}|{'-' * 11}|{'-' * 9}|{'-' * 9}|")
    for name in ROWS:
        r = res[name]
        t = np.array(r["times"]) * 1e3
        nit = f"{np.mean(r['nit']):5.2f}" if r["nit"] else f"{'—':>5}"
        print(f"| {name:<38} | {np.mean(r['rmse']):8.4f} | {np.mean(r['rmse_theta']):8.4f} | "
              f"{np.max(r['rmse']):8.4f} | {nit} | {np.median(t):9.3f} | {np.percentile(t, 95):7.3f} | "
              f"{np.median(t) / (base * 1e3):7.2f} |")


if __name__ == "__main__":
    main()
