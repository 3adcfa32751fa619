"""Benchmark: the batch-reactor comparison of the GP-MHE paper (docs/user_guide/systems.rst) over many seeds
and for each window solver.

    python benches/batch_reactor.py [--seeds 20] [--solvers least-squares,trust-constr]
                                    [--steps 100] [--jobs 2] [--restarts 3]

Per seed: fresh training data (5 and 3 trajectories, GPs fitted with restarts), one run from the
poor prior [0.1, 4.5]. Estimators: GP-MHE (5 traj., f on x(t+1) as in the paper), GP-MHE (5
traj., f as an increment x(t+1) - x(t)), GP-MHE (3 traj.), exact-model MHE, filterpy's EKF on the
exact model, an EKF on the GP model. Prints mean RMSE of x̂(t) (from outputs up to t-1) over the
whole run and over t >= 30, the mean final error, time per update (median and p95 over all
updates of all seeds) and its ratio to filterpy's EKF measured in the same processes.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import sys
import time

import numpy as np

from gpmhe.demos.batch_reactor import rmse, run_estimators


def one_seed(args):
    seed, steps, solvers, restarts = args
    truth, results, _ = run_estimators(seed, steps, solvers, restarts, log=lambda m: None,
                                       increment_model=True)
    out = {}
    for name, (xs, ts, failed) in results.items():
        out[name] = dict(all=rmse(xs, truth, 1), late=rmse(xs, truth, 30),
                         final=float(np.linalg.norm(xs[-1] - truth[-1])), times=ts,
                         failed=failed, neg=bool(xs[:, 0].min() < 0))
    return seed, out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--solvers", default="least-squares,trust-constr")
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--restarts", type=int, default=3)
    args = ap.parse_args(argv)
    solvers = [s for s in args.solvers.split(",") if s]
    tasks = [(seed, args.steps, solvers, args.restarts) for seed in range(args.seeds)]
    t0 = time.perf_counter()
    rows = {}
    with mp.get_context("spawn").Pool(args.jobs) if args.jobs > 1 else _Serial() as pool:
        for seed, out in pool.imap_unordered(one_seed, tasks):
            print(f"seed {seed} done ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
            for name, r in out.items():
                rows.setdefault(name, []).append(r)
    ekf_med = np.median(np.concatenate([r["times"] for r in rows["filterpy EKF (exact)"]]))
    print(f"\nBatch reactor from x̂(0) = [0.1, 4.5]: {args.seeds} seeds x {args.steps} steps, "
          f"solvers {', '.join(solvers)}, {args.jobs} processes, GP restarts {args.restarts}")
    print(f"{'estimator':40s} {'RMSE all':>8s} {'RMSE t>=30':>10s} {'final':>7s} {'x1<0 runs':>9s} "
          f"{'median ms':>9s} {'p95 ms':>8s} {'x EKF':>8s} {'failed':>6s}")
    for name, rs in rows.items():
        ts = np.concatenate([r["times"] for r in rs])
        med = np.median(ts)
        print(f"{name:40s} {np.mean([r['all'] for r in rs]):8.3f} "
              f"{np.mean([r['late'] for r in rs]):10.3f} {np.mean([r['final'] for r in rs]):7.3f} "
              f"{sum(r['neg'] for r in rs):9d} {1e3 * med:9.3f} {1e3 * np.percentile(ts, 95):8.2f} "
              f"{med / ekf_med:8.1f} {sum(r['failed'] for r in rs):6d}")
    print(f"(total {time.perf_counter() - t0:.0f} s; 'failed' = windows whose solver reported "
          f"no convergence; 'x EKF' = median time / filterpy EKF median time)")
    return 0


class _Serial:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def imap_unordered(self, f, tasks):
        return map(f, tasks)


if __name__ == "__main__":
    sys.exit(main())
