"""Benchmark: the SciPy window solvers against the Rust solver on the same windows.

    python benches/trust_constr.py [--seeds 3] [--steps 60] [--jobs 2] [--quick]

Per seed: the batch reactor's training data (5 trajectories, GPs fitted with 3 restarts, the
paper's GP settings, as in `gpmhe.demos.batch_reactor`) and one run of each estimator from the
poor prior [0.1, 4.5] (transient included), the estimators interleaved 10 steps at a time so that
a drift in the machine's speed hits all alike. Before each update the estimator's core is copied
and the copy's window (same data, same warm start) is solved by the Rust solver run to its
projected-gradient tolerance (``dtol=0``): the reference. Per window: whether the solver reported
convergence, its iterations (function evaluations for least-squares), the process time of the
update, the cost excess (J - J_ref) / J_ref over the reference and the largest state difference
max |x - x_GN| over the window. The window problem is not convex: a few windows of the transient
have several local minima, and there a solver can end in another one than the reference (a
negative excess: a better one); the maxima of the excess and of |x - x_GN| come from those.

Rows: the Rust solver ("gauss-newton", defaults: it stops on the Gauss-Newton decrement 1e-2),
least-squares and trust-constr with their defaults, and trust-constr with its decrement stop off
(``dtol=0``, SciPy's own tests only), also with a small initial barrier parameter (1e-4). The
time ratio is the median time per update over the gauss-newton row's, in the same run.
`--quick`: 2 seeds x 30 steps (a smoke test, not a measurement).
"""

from __future__ import annotations

import argparse
import copy
import multiprocessing as mp
import sys
import time
import warnings

import numpy as np

#: (label, solver, solver_options); the first is the time baseline.
ROWS = [
    ("gauss-newton", "gauss-newton", {}),
    ("least-squares", "least-squares", {}),
    ("trust-constr", "trust-constr", {}),
    ("trust-constr dtol=0", "trust-constr", {"dtol": 0.0}),
    ("trust-constr dtol=0, barrier 1e-4", "trust-constr",
     {"dtol": 0.0, "initial_barrier_parameter": 1e-4}),
]
BLOCK = 10


def one_seed(args):
    seed, steps = args
    from gpmhe import GPMHE, LearnedModel, _core
    from gpmhe.systems import batch_reactor as br

    rng = np.random.default_rng(seed)
    data = br.training_data(5, rng=rng)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = LearnedModel.from_trajectories(*data, n_restarts=3, random_state=seed,
                                               **br.PAPER_GP)
    _, y = br.simulate(br.X_TRUE0, steps, rng)
    reference = _core.WindowSolver(dtol=0.0, max_iter=500)
    no_input = np.zeros(0)
    ests = {label: GPMHE(model, br.X_PRIOR0, x_bounds=br.X_BOUNDS, solver=solver,
                         solver_options=opts, **br.MHE_SETTINGS)
            for label, solver, opts in ROWS}
    out = {label: [] for label in ests}  # rows (converged, nit, seconds, excess, dx)
    for start in range(0, steps, BLOCK):
        for label, est in ests.items():
            for t in range(start, min(start + BLOCK, steps)):
                ref = copy.copy(est._core)
                z0, lb, ub = ref.prepare(no_input, y[t])
                z_ref, c_ref = reference.solve(ref, z0, lb, ub)[:2]
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)  # counted as not converged
                    t0 = time.process_time()
                    est.update(None, y[t])
                    dt = time.process_time() - t0
                dx = float(np.max(np.abs(est.x_window.reshape(-1) - z_ref)))
                out[label].append((est.success, est.nit, dt, (est.cost - c_ref) / c_ref, dx))
    return seed, out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="2 seeds x 30 steps")
    args = ap.parse_args(argv)
    if args.quick:
        args.seeds, args.steps = 2, 30
    tasks = [(seed, args.steps) for seed in range(args.seeds)]
    t0 = time.perf_counter()
    results = {}
    with mp.get_context("spawn").Pool(args.jobs) as pool:
        for seed, out in pool.imap_unordered(one_seed, tasks):
            results[seed] = out
            print(f"seed {seed} done ({time.perf_counter() - t0:.0f} s)", file=sys.stderr,
                  flush=True)
    rows = {label: np.array([r for s in sorted(results) for r in results[s][label]])
            for label, _, _ in ROWS}
    base = np.median(rows[ROWS[0][0]][:, 2])
    print(f"\nBatch reactor from the poor prior, paper GP (5 traj.): {args.seeds} seeds x "
          f"{args.steps} steps = {args.seeds * args.steps} windows per solver; reference: the "
          f"Rust solver with dtol=0 on the same window\n")
    print("| solver | converged | iterations median (p95) | ms per update median (p95) "
          "| time / gauss-newton | cost excess median / p95 / max | max abs(x - x_GN) |")
    print("|---|---|---|---|---|---|---|")
    for label, _, _ in ROWS:
        r = rows[label]
        ok, nit, ms, ex, dx = r[:, 0], r[:, 1], 1e3 * r[:, 2], r[:, 3], r[:, 4]
        print(f"| {label} | {100 * np.mean(ok):.1f} % | {np.median(nit):.0f} "
              f"({np.percentile(nit, 95):.0f}) | {np.median(ms):.2f} ({np.percentile(ms, 95):.1f}) "
              f"| {np.median(r[:, 2]) / base:.0f}x | {np.median(ex):.1e} / "
              f"{np.percentile(ex, 95):.1e} / {np.max(ex):.1e} "
              f"| {np.max(dx):.1e} |")
    print(f"\n(total {time.perf_counter() - t0:.0f} s; process time, both processes share the "
          f"machine: compare rows with each other; cost excess (J - J_ref) / J_ref)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
