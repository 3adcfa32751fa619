"""Benchmark: the overhead of gpmhe.monte_carlo, serially and on a LocalCluster of 2 processes.

    python benches/bench_study.py [--seeds 1000] [--steps 20] [--workers 2]

Runs of the batch reactor (docs/user_guide/systems.rst) from the poor prior: the exact-model MHE
(vectorised KnownModel, default solver) and filterpy's EKF on the exact model, each over every
seed. For each estimator, prints the total time and the time per run of

* a plain loop: simulate, build the estimator, update T times (timed per update, as the harness
  does), the default metrics — the same work without the harness;
* monte_carlo serially (client=None): its overhead over the plain loop;
* monte_carlo on a LocalCluster(n_workers=2, threads_per_worker=1, processes=True), cluster
  startup excluded (printed separately): its speed-up over the plain loop;

each the best of --repeat interleaved runs (a shared machine's load varies),

and the bytes the cluster run sends: the scattered payload (factories, simulate, metrics, and the
model they hold) once per worker, and one task's result. Asserts nothing.
"""

from __future__ import annotations

import argparse
import functools
import pickle
import sys
import time

import numpy as np

from gpmhe import GPMHE, KnownModel, monte_carlo
from gpmhe.baselines import ExactEKF
from gpmhe.study import FilterAdapter, default_metrics
from gpmhe.systems import batch_reactor as br

MODEL = KnownModel(br.f_batch, br.h_batch, 2, 1, f_jacobian=br.f_jacobian_batch,
                   h_jacobian=br.h_jacobian_batch, vectorized=True)


def simulate(seed, steps):
    x, y = br.simulate(br.X_TRUE0, steps, np.random.default_rng(seed))
    return None, y[:steps], x


def exact_mhe():
    return GPMHE(MODEL, br.X_PRIOR0, x_bounds=br.X_BOUNDS, **br.MHE_SETTINGS)


def exact_ekf():
    return FilterAdapter(ExactEKF(br.f, br.f_jacobian, br.h, br.h_jacobian, br.X_PRIOR0,
                                  np.eye(2), br.SIGMA_W**2 * np.eye(2),
                                  br.SIGMA_V**2 * np.eye(1)))


ESTIMATORS = {"exact-model MHE": exact_mhe, "filterpy EKF (exact)": exact_ekf}


def plain_loop(factory, sim, seeds):
    """The study without the harness: same runs, same per-update timing, same metrics."""
    metrics = default_metrics()
    rows = []
    for seed in seeds:
        _, y, x = sim(seed)
        est = factory()
        xs, ts = np.empty((len(y), 2)), np.empty(len(y))
        for t in range(len(y)):
            t0 = time.perf_counter()
            est.update(None, y[t])
            ts[t] = time.perf_counter() - t0
            xs[t] = est.x
        rows.append({k: fn(xs, x[1:], ts) for k, fn in metrics.items()})
    return rows


def main(argv=None):
    """Time the three ways and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=1000)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3, help="timings are the best of this many")
    args = ap.parse_args(argv)
    seeds = list(range(args.seeds))
    sim = functools.partial(simulate, steps=args.steps)
    from distributed import Client, LocalCluster

    t0 = time.perf_counter()
    cluster = LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True,
                           dashboard_address=None)
    client = Client(cluster)
    startup = time.perf_counter() - t0
    results = {}
    try:
        for name, factory in ESTIMATORS.items():
            one = {name: factory}
            plain_loop(factory, sim, seeds[:20])  # warm-up (imports, first calls)
            best = {"plain": np.inf, "serial": np.inf, "cluster": np.inf}
            for _ in range(args.repeat):  # interleaved, so that load changes hit all three
                t0 = time.perf_counter()
                plain_loop(factory, sim, seeds)
                best["plain"] = min(best["plain"], time.perf_counter() - t0)
                t0 = time.perf_counter()
                serial = monte_carlo(one, sim, seeds, progress=False)
                best["serial"] = min(best["serial"], time.perf_counter() - t0)
                t0 = time.perf_counter()
                dist = monte_carlo(one, sim, seeds, client=client, progress=False)
                best["cluster"] = min(best["cluster"], time.perf_counter() - t0)
            cols = ["rmse", "rmse_late", "final_error"]
            same = serial.table[cols].equals(dist.table[cols])
            results[name] = (best["plain"], best["serial"], best["cluster"], same)
            print(f"{name}: " + ", ".join(f"{k} {v:.1f} s" for k, v in best.items()),
                  file=sys.stderr, flush=True)
    finally:
        client.close()
        cluster.close()

    import cloudpickle

    payload = len(cloudpickle.dumps((ESTIMATORS, sim, default_metrics())))
    from gpmhe.study import _run_chunk

    chunk = len(pickle.dumps(_run_chunk((ESTIMATORS, sim, default_metrics()),
                                        "exact-model MHE", seeds[:10])))
    n = len(seeds)
    print(f"\nmonte_carlo overhead: {n} seeds x {args.steps} steps per estimator; "
          f"LocalCluster({args.workers} processes, 1 thread each), startup {startup:.1f} s "
          f"(not included)")
    print(f"{'estimator':22s} {'plain s':>8s} {'ms/run':>7s} {'serial s':>9s} {'ms/run':>7s} "
          f"{'overhead':>9s} {'cluster s':>10s} {'ms/run':>7s} {'speed-up':>9s} {'same':>5s}")
    for name, (plain, t_serial, t_dist, same) in results.items():
        print(f"{name:22s} {plain:8.2f} {1e3 * plain / n:7.2f} {t_serial:9.2f} "
              f"{1e3 * t_serial / n:7.2f} {100 * (t_serial / plain - 1):8.1f}% {t_dist:10.2f} "
              f"{1e3 * t_dist / n:7.2f} {plain / t_dist:8.2f}x {str(same):>5s}")
    print(f"sent per worker once: the payload, {payload / 1e3:.1f} kB pickled; per task of 10 "
          f"seeds back: {chunk / 1e3:.1f} kB ({args.steps} update times per run). 'same' = "
          f"metrics except time equal to the serial run's.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
