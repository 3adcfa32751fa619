"""Benchmark: the batch-reactor comparison of the GP-MHE paper (docs/user_guide/systems.rst) over many seeds
and for each window solver, run with gpmhe.monte_carlo on a Dask LocalCluster of processes.

    python benches/batch_reactor.py [--seeds 20] [--solvers least-squares,trust-constr]
                                    [--steps 100] [--jobs 2] [--restarts 3]
                                    [--serial | --scheduler tcp://host:8786]

Per seed: fresh training data (5 and 3 trajectories, GPs fitted with restarts), one run from the
poor prior [0.1, 4.5]. Estimators: GP-MHE (5 traj., f on x(t+1) as in the paper), GP-MHE (5
traj., f as an increment x(t+1) - x(t)), GP-MHE (3 traj.), exact-model MHE, filterpy's EKF on the
exact model, an EKF on the GP model. Prints mean RMSE of x̂(t) (from outputs up to t-1) over the
whole run and over t >= 30, the mean final error, time per update (median and p95 over all
updates of all seeds) and its ratio to filterpy's EKF measured on the same workers.

`--jobs N` worker processes (one thread each) on a LocalCluster; `--serial` runs in this process;
`--scheduler ADDRESS` uses a running cluster instead. The runs (seeds, data, models, estimators)
are gpmhe.demos.batch_reactor.run_estimators', so the numbers are the same either way.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import sys
import time

import numpy as np

from gpmhe import monte_carlo
from gpmhe.demos.batch_reactor import study_factories, study_simulate

LATE = 30  # "RMSE t>=30"


def rmse_all(est, truth, times):
    return float(np.sqrt(np.mean(np.sum((est - truth) ** 2, axis=1))))


def rmse_late(est, truth, times):  # est[i] estimates x(i + 1): rows i >= LATE - 1 are t >= LATE
    return rmse_all(est[LATE - 1:], truth[LATE - 1:], times)


def final(est, truth, times):
    return float(np.linalg.norm(est[-1] - truth[-1]))


def negative_x1(est, truth, times):
    return float(est[:, 0].min() < 0)


METRICS = {"all": rmse_all, "late": rmse_late, "final": final, "neg": negative_x1}


@contextlib.contextmanager
def dask_client(args):
    """None (--serial), a client of the cluster at --scheduler, or of a new LocalCluster."""
    if args.serial:
        yield None
        return
    from distributed import Client, LocalCluster

    if args.scheduler:
        with Client(args.scheduler) as client:
            yield client
        return
    with LocalCluster(n_workers=args.jobs, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster, Client(cluster) as client:
        yield client


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--solvers", default="least-squares,trust-constr")
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--jobs", type=int, default=2, help="LocalCluster worker processes")
    ap.add_argument("--restarts", type=int, default=3)
    ap.add_argument("--serial", action="store_true", help="run in this process, no cluster")
    ap.add_argument("--scheduler", default=None, help="address of a running Dask scheduler")
    args = ap.parse_args(argv)
    args.serial = args.serial or (args.jobs <= 1 and not args.scheduler)
    solvers = [s for s in args.solvers.split(",") if s]
    factories = study_factories(solvers, args.restarts, increment_model=True)
    simulate = functools.partial(study_simulate, steps=args.steps)
    t0 = time.perf_counter()
    with dask_client(args) as client:
        where = ("in-process" if client is None else
                 f"{len(client.nthreads())} Dask workers" if args.scheduler else
                 f"{args.jobs} processes")
        result = monte_carlo(factories, simulate, range(args.seeds), metrics=METRICS,
                             client=client)
    table = result.table
    failed_runs = table[table.error.notna()]
    for _, row in failed_runs.iterrows():
        print(f"run failed: {row.estimator}, seed {row.seed}: {row.error}", file=sys.stderr)

    def times(name):
        return np.concatenate([ts for (n, _), ts in result.times.items() if n == name])

    ekf_med = np.median(times("filterpy EKF (exact)"))
    print(f"\nBatch reactor from x̂(0) = [0.1, 4.5]: {args.seeds} seeds x {args.steps} steps, "
          f"solvers {', '.join(solvers)}, {where}, GP restarts {args.restarts}")
    print(f"{'estimator':40s} {'RMSE all':>8s} {'RMSE t>=30':>10s} {'final':>7s} {'x1<0 runs':>9s} "
          f"{'median ms':>9s} {'p95 ms':>8s} {'x EKF':>8s} {'failed':>6s}")
    for name in factories:
        rs = table[(table.estimator == name) & table.error.isna()]
        ts = times(name)
        med = np.median(ts)
        print(f"{name:40s} {rs['all'].mean():8.3f} {rs['late'].mean():10.3f} "
              f"{rs['final'].mean():7.3f} {int(rs['neg'].sum()):9d} {1e3 * med:9.3f} "
              f"{1e3 * np.percentile(ts, 95):8.2f} {med / ekf_med:8.1f} "
              f"{int(rs['unconverged'].sum()):6d}")
    print(f"(total {time.perf_counter() - t0:.0f} s; 'failed' = windows whose solver reported "
          f"no convergence; 'x EKF' = median time / filterpy EKF median time"
          + (f"; {len(failed_runs)} runs failed, see above" if len(failed_runs) else "") + ")")
    return 0


if __name__ == "__main__":
    sys.exit(main())
