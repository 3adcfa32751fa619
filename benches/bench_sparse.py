"""Benchmark: GP-MHE with sparse GPs against exact GPs on the batch reactor, as the training set grows.

    python benches/bench_sparse.py [--seeds 20] [--big-seeds 2] [--steps 100] [--quick] [--rows 3,15]

One table, one run. Each row is a kind of GP model (exact, or sparse VFE with m inducing points
asked for) learned from the batch reactor's simulated trajectories with N points per GP
(trajectories of 31 states: the paper's 5 of `gpmhe.systems.batch_reactor.training_data`, N = 150,
and N/30 - 5 more from random initial states in the box, measured alike; N = 1,500 is 50
trajectories). Per seed: fresh training data (generator
[seed, 0]), the hyperparameter fit (`LearnedModel.from_trajectories` with the paper's GP model
`batch_reactor.PAPER_GP`, 3 restarts as in the demo
for exact GPs with N <= 500 and sparse GPs with N <= 2,000, none above, as fits get long), then GP-MHE with the paper's settings for `--steps` steps from the
poor prior [0.1, 4.5] on a test run shared by all rows (generator [seed, 1]), interleaved in
blocks of 10 steps with filterpy's EKF (exact model, predict + update) so that a drift in the
machine's speed hits both alike. The last row takes m training inputs drawn at random as fixed
inducing points instead of choosing them: a fit with exactly m = 200 points. Columns: the inducing points the fit kept (median over the GPs
and seeds; fewer than asked when the rest of the inputs are determined by them to 1e-8 sigma_f^2,
see the user guide), the median fit time of the whole model (3 GPs: n = 2 for f, p = 1 for h),
median and p95 of the time per update over all updates of all seeds, the ratio of the medians to
the EKF's in the same runs, and the RMSE of x̂(t) over the run (mean and standard deviation over
seeds). Rows with N >= 2,000 exact or N >= 10^4 sparse run `--big-seeds` seeds only (their fits
take minutes).

`--quick`: 2 seeds, 40 steps, N <= 10^4.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
from bench_update import ekf_step, interleaved_runs, rmse

from gpmhe import GPMHE, LearnedModel
from gpmhe.baselines import ExactEKF
from gpmhe.systems import batch_reactor as br

# (label, N per GP, m asked for or None for the exact GP)
ROWS = [
    ("exact", 150, None),
    ("exact", 500, None),
    ("exact", 2000, None),
    ("sparse VFE", 150, 25),
    ("sparse VFE", 150, 50),
    ("sparse FITC", 150, 50),
    ("sparse VFE", 500, 50),
    ("sparse VFE", 1500, 50),
    ("sparse VFE", 2000, 25),
    ("sparse VFE", 2000, 50),
    ("sparse VFE", 2000, 100),
    ("sparse VFE", 10000, 50),
    ("sparse VFE", 10000, 100),
    ("sparse VFE", 10000, 200),
    ("sparse VFE", 100000, 200),
    ("VFE given Z", 100000, 200),
]


def training_data(n_traj, rng):
    """The paper's 5 training trajectories, and n_traj - 5 more from initial states drawn
    uniformly in the estimator's box, measured alike (states with noise SIGMA_X_MEAS)."""
    states, outputs = br.training_data(5, rng=rng)
    lb, ub = br.X_BOUNDS
    for _ in range(n_traj - 5):
        x, y = br.simulate(rng.uniform(lb, ub), br.TRAIN_STEPS, rng)
        states.append(x + br.SIGMA_X_MEAS * rng.standard_normal(x.shape))
        outputs.append(y)
    return states, outputs


def fit(label, n_points, m, seed):
    """(model, fit seconds, inducing points kept per GP) for one row and seed."""
    n_traj = max(5, round(n_points / br.TRAIN_STEPS))
    data = training_data(n_traj, np.random.default_rng([seed, 0]))
    restarts = 3 if n_points <= (500 if m is None else 2000) else 0
    # The paper's GP model (zero mean, maximum likelihood), as every table in the performance page.
    opts = dict(n_restarts=restarts, random_state=seed, **br.PAPER_GP)
    if m is not None:
        opts.update(n_inducing=m, method="fitc" if "FITC" in label else "vfe")
    if "given" in label:  # m distinct training inputs drawn at random: exactly m points
        D = np.vstack([x[:-1] for x in data[0]])
        opts.update(inducing=D[np.random.default_rng([seed, 2]).choice(len(D), m, replace=False)])
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # optimiser chatter: the best run is used
        model = LearnedModel.from_trajectories(*data, **opts)
    seconds = time.perf_counter() - t0
    kept = [] if m is None else [len(z) for g in (model.f_gp, model.h_gp) for z in g.inducing_points]
    return model, seconds, kept


def run_row(label, n_points, m, seeds, steps):
    """Per-row results over the seeds: fit times, update times, EKF times, RMSEs, m kept."""
    out = dict(fit=[], upd=[], ekf=[], rmse=[], kept=[], n=0)
    Q, R = br.SIGMA_W ** 2 * np.eye(2), br.SIGMA_V ** 2 * np.eye(1)
    kw = dict(x_bounds=br.X_BOUNDS, **br.MHE_SETTINGS)
    for seed in seeds:
        model, seconds, kept = fit(label, n_points, m, seed)
        out["n"] = model.f_gp.D_train.shape[0]
        x, y = br.simulate(br.X_TRUE0, steps, np.random.default_rng([seed, 1]))
        est = GPMHE(model, br.X_PRIOR0, **kw)
        ekf = ExactEKF(br.f, br.f_jacobian, br.h, br.h_jacobian, br.X_PRIOR0, np.eye(2), Q, R)
        runs = interleaved_runs([("ekf", ekf_step(ekf), steps),
                                 ("mhe", lambda yt: est.update(None, yt), steps)], y, 10)
        out["fit"].append(seconds)
        out["upd"].extend(runs["mhe"][1])
        out["ekf"].extend(runs["ekf"][1])
        out["rmse"].append(rmse(runs["mhe"][0], x))
        out["kept"].extend(kept)
    return out


def print_row(label, m, seeds, r):
    med, p95 = np.median(r["upd"]) * 1e3, np.percentile(r["upd"], 95) * 1e3
    ratio = np.median(r["upd"]) / np.median(r["ekf"])
    kept = "-" if m is None else f"{m}/{np.median(r['kept']):.0f}"
    print(f"| {label:<11} | {r['n']:6d} | {kept:>7} | {len(seeds):5d} | {np.median(r['fit']):8.2f} | "
          f"{med:9.3f} | {p95:8.3f} | {ratio:6.1f} | {np.mean(r['rmse']):.3f} ± {np.std(r['rmse']):.3f} |",
          flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--big-seeds", type=int, default=2)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--quick", action="store_true", help="2 seeds, 40 steps, N <= 10^4")
    ap.add_argument("--rows", default=None,
                    help="only these rows of the table, 1-based and comma-separated (e.g. 3,15,16): "
                         "each row's numbers are the same as in the whole table")
    args = ap.parse_args(argv)
    seeds, big, steps = (2, 1, 40) if args.quick else (args.seeds, args.big_seeds, args.steps)
    rows = [r for r in ROWS if not (args.quick and r[1] > 10000)]
    if args.rows:
        rows = [rows[int(i) - 1] for i in args.rows.split(",")]
    t_start = time.perf_counter()
    print(f"\n## GP-MHE on the batch reactor with exact and sparse GPs ({steps} steps per run; "
          f"{seeds} seeds, {big} for the large rows)\n")
    print("| GPs         | N / GP | m asked/kept | seeds | fit s (3 GPs) | median ms | p95 ms | ×EKF | "
          "RMSE mean ± sd |")
    print("|-------------|--------|---------|-------|----------|-----------|----------|--------|"
          "----------------|")
    results = {}
    for label, n_points, m in rows:
        large = (m is None and n_points >= 2000) or (m is not None and n_points >= 10000)
        row_seeds = list(range(big if large else seeds))
        r = run_row(label, n_points, m, row_seeds, steps)
        results[(label, n_points, m)] = r
        print_row(label, m, row_seeds, r)
    summary(results)
    print(f"\ntotal benchmark time {time.perf_counter() - t_start:.0f} s")
    return 0


def summary(results):
    """The issue's goals, from the table's rows."""
    def med(key, what="upd"):
        return np.median(results[key][what]) if key in results else np.nan

    ex150, ex2000 = ("exact", 150, None), ("exact", 2000, None)
    sp2000 = ("sparse VFE", 2000, 50)
    print(f"\nN = 2,000, m = 50: median update {med(sp2000) * 1e3:.3f} ms = "
          f"{med(sp2000) / med(sp2000, 'ekf'):.1f}× filterpy's EKF in the same runs (goal <= 3×), "
          f"{med(ex2000) / med(sp2000):.0f}× faster than the exact GPs at N = 2,000 (goal >= 20×)")
    for key in [("sparse VFE", 150, 25), ("sparse VFE", 150, 50), ("sparse FITC", 150, 50),
                ("sparse VFE", 1500, 50)]:
        if key in results and ex150 in results:
            a, b = np.array(results[key]["rmse"]), np.array(results[ex150]["rmse"])
            k = min(len(a), len(b))
            print(f"{key[0]}, N = {key[1]}, m = {key[2]}: mean RMSE {np.mean(a):.3f} vs exact on the 5 "
                  f"trajectories {np.mean(b):.3f} (ratio {np.mean(a) / np.mean(b):.3f}; same seeds, "
                  f"per-seed ratio median {np.median(a[:k] / b[:k]):.3f})")
    for big in [("sparse VFE", 100000, 200), ("VFE given Z", 100000, 200)]:
        if big in results:
            print(f"N = 10^5, {big[0]}, m = 200 (kept {np.median(results[big]['kept']):.0f}): fit of "
                  f"the 3 GPs {med(big, 'fit'):.1f} s ({med(big, 'fit') / 3:.1f} s per GP; goal < 60 s)")


if __name__ == "__main__":
    raise SystemExit(main())
