"""Benchmark: outliers in the measurements, robust output penalties against the squared one and
filterpy's EKF, on the batch reactor.

    python benches/bench_outliers.py [--seeds 20] [--steps 100] [--rate 0.05] [--size 20]

One table, one run. The paper's GP model is fitted once (the 5 training trajectories of
generator 0, 3 restarts, as in the demo). Per seed: a test run of ``--steps`` steps from the
true initial state (generator [seed, 1]), and the same run with a fraction ``--rate`` of its
samples (drawn at random, generator [seed, 2]) moved by ``--size`` output standard deviations
(σ_v = 0.1) up or down. Every estimator starts from the paper's poor prior [0.1, 4.5]; the
MHEs with the paper's M = 15, η = 0.91, Q0 = 1e-3 I, R0 = 1e-2 and gpmhe's default arrival
cost, the EKFs with Q = σ_w² I,
R = σ_v², P0 = I. Columns: RMSE of x̂(t) after the transient (t > 20) without and with
outliers (mean and standard deviation over seeds), the runs whose estimate leaves the region of the truth after
the transient (an error ‖x̂(t) − x(t)‖∞ > 0.5, a ninth of the states' range, at some t > 20)
with outliers, and the median time per update with outliers.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from gpmhe import GPMHE, KnownModel, LearnedModel
from gpmhe.baselines import GPEKF, ExactEKF
from gpmhe.systems import batch_reactor as br

#: An error larger than this (in the states' units) after the transient leaves the region.
REGION = 0.5
TRANSIENT = 20


def estimators(gp, known):
    """(name, factory) of every row; a factory returns a step y -> x̂."""
    paper = {k: v for k, v in br.MHE_SETTINGS.items() if not k.startswith("arrival")}
    kw = dict(x_bounds=br.X_BOUNDS, **paper)  # gpmhe's default arrival cost
    Q, R = br.SIGMA_W ** 2 * np.eye(2), br.SIGMA_V ** 2 * np.eye(1)

    def mhe(model, **extra):
        def make():
            est = GPMHE(model, br.X_PRIOR0, **kw, **extra)
            return lambda y: est.update(None, y)
        return make

    def ekf(build):
        def make():
            f = build()

            def step(y):
                f.update(y)
                f.predict()
                return f.x.ravel()
            return step
        return make

    return [
        ("GP-MHE, squared", mhe(gp)),
        ("GP-MHE, huber (k = 1.345)", mhe(gp, loss="huber")),
        ("GP-MHE, cauchy (k = 2.385)", mhe(gp, loss="cauchy")),
        ("exact-model MHE, squared", mhe(known)),
        ("exact-model MHE, huber", mhe(known, loss="huber")),
        ("exact-model MHE, cauchy", mhe(known, loss="cauchy")),
        ("filterpy EKF, exact model", ekf(lambda: ExactEKF(br.f, br.f_jacobian, br.h, br.h_jacobian,
                                                         br.X_PRIOR0, np.eye(2), Q, R))),
        ("filterpy EKF, GP model (GP-EKF)", ekf(lambda: GPEKF(gp, br.X_PRIOR0, np.eye(2), Q, R))),
    ]


def with_outliers(y, rate, size, rng):
    """y with round(rate · len(y)) samples moved by ±size σ_v."""
    out = y.copy()
    at = rng.choice(len(y), int(round(rate * len(y))), replace=False)
    out[at] += size * br.SIGMA_V * rng.choice([-1.0, 1.0], (len(at), 1))
    return out


def run(step, y, x):
    """Errors x̂(t+1) − x(t+1) (steps, 2) and times per update of one estimator over y."""
    errors, times = np.empty((len(y), 2)), np.empty(len(y))
    for t, yt in enumerate(y):
        t0 = time.perf_counter()
        xt = np.asarray(step(yt), dtype=float)
        times[t] = time.perf_counter() - t0
        errors[t] = xt - x[t + 1] if np.all(np.isfinite(xt)) else np.inf
    return errors, times


def rmse(errors):
    """RMSE of x̂ after the transient."""
    return float(np.sqrt(np.mean(np.sum(errors[TRANSIENT:] ** 2, axis=1))))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--rate", type=float, default=0.05)
    ap.add_argument("--size", type=float, default=20.0)
    args = ap.parse_args()
    gp = LearnedModel.from_trajectories(*br.training_data(5, rng=np.random.default_rng(0)),
                                        n_restarts=3, random_state=0, **br.PAPER_GP)
    known = KnownModel(br.f, br.h, 2, 1, f_jacobian=br.f_jacobian, h_jacobian=br.h_jacobian)
    rows = estimators(gp, known)
    res = {name: dict(clean=[], dirty=[], left=0, times=[]) for name, _ in rows}
    for seed in range(args.seeds):
        x, y = br.simulate(br.X_TRUE0, args.steps, np.random.default_rng([seed, 1]))
        y = y[:args.steps]
        dirty = with_outliers(y, args.rate, args.size, np.random.default_rng([seed, 2]))
        for name, make in rows:
            r = res[name]
            r["clean"].append(rmse(run(make(), y, x)[0]))
            errors, times = run(make(), dirty, x)
            r["dirty"].append(rmse(errors))
            r["left"] += bool(np.any(np.abs(errors[TRANSIENT:]) > REGION))
            r["times"].extend(times)
    print(f"batch reactor, {args.seeds} seeds x {args.steps} steps; outliers: "
          f"{args.rate:.0%} of the samples moved by {args.size:g} sigma_v")
    print(f"| {'estimator':<32} | {'RMSE, clean':>15} | {'RMSE, outliers':>15} | {'left':>6} | {'ms/update':>9} |")
    print(f"|{'-' * 34}|{'-' * 17}|{'-' * 17}|{'-' * 8}|{'-' * 11}|")
    for name, _ in rows:
        r = res[name]
        c, d = np.array(r["clean"]), np.array(r["dirty"])
        print(f"| {name:<32} | {c.mean():6.3f} ± {c.std():5.3f} | {d.mean():6.3f} ± {d.std():5.3f} | "
              f"{r['left']:>2}/{args.seeds:<3} | {np.median(r['times']) * 1e3:9.3f} |")


if __name__ == "__main__":
    main()
