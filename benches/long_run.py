"""Benchmark: a long run of GPMHE updates — memory stays flat, every estimate stays finite.

    python benches/long_run.py [--updates 100000] [--model known|learned|both] [--seed 0]

The batch reactor (gpmhe.systems.batch_reactor) run as a sequence of batches of `BATCH` steps,
each from the paper's initial state (one batch of 10^5 steps would let the noise drive the true
concentrations negative and the simulation to overflow), `--updates` steps in all, every tenth
output missing. One GPMHE with the paper's settings (M = 15) and the default Rust solver
estimates it across the batch changes (where the true state jumps), with the exact model
(KnownModel, vectorised, analytic Jacobians) and/or the learned
model (GPs fitted to the five training trajectories, one restart). Prints, per model: updates,
wall time, median and p95 time per update, the process's resident set size (RSS, Linux
/proc/self/statm) after the first update, in the middle and at the end, the number of updates
whose x, P or cost was not finite, and how many windows stopped without converging (a
RuntimeWarning each, counted, not shown). Nothing is asserted: the numbers are for reading.
"""

from __future__ import annotations

import argparse
import os
import time
import warnings

import numpy as np

from gpmhe import GPMHE, KnownModel, LearnedModel
from gpmhe.systems import batch_reactor as br


BATCH = 1000


def outputs(updates, seed):
    """`updates` outputs of consecutive batches of BATCH steps, each from X_TRUE0."""
    rng = np.random.default_rng(seed)
    batches = -(-updates // BATCH)
    return np.concatenate([br.simulate(br.X_TRUE0, BATCH, rng)[1][:BATCH]
                           for _ in range(batches)])[:updates]


def rss_mb():
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return float("nan")


def make_model(kind, seed):
    if kind == "known":
        return KnownModel(br.f_batch, br.h_batch, 2, 1, vectorized=True,
                          f_jacobian=br.f_jacobian_batch, h_jacobian=br.h_jacobian_batch)
    states, outputs = br.training_data(5, rng=seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return LearnedModel.from_trajectories(states, outputs, n_restarts=1, random_state=0, **br.PAPER_GP)


def run(kind, updates, seed):
    model = make_model(kind, seed)
    ys = outputs(updates, seed)
    missing = np.zeros(updates, bool)
    missing[::10] = True
    mhe = GPMHE(model, x0=[3.0, 1.0], x_bounds=br.X_BOUNDS, **br.MHE_SETTINGS)
    times = np.empty(updates)
    rss = {}
    non_finite = not_converged = 0
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for i in range(updates):
            t0 = time.perf_counter()
            mhe.update(None, None if missing[i] else ys[i])
            times[i] = time.perf_counter() - t0
            non_finite += not (np.isfinite(mhe.x).all() and np.isfinite(mhe.P).all()
                               and np.isfinite(mhe.cost))
            not_converged += not mhe.success
            if i in (0, updates // 2, updates - 1):
                rss[i] = rss_mb()
    wall = time.perf_counter() - start
    ms = 1e3 * times
    return dict(model=kind, updates=updates, wall=wall, median=np.median(ms),
                p95=np.percentile(ms, 95), rss_start=rss[0], rss_mid=rss[updates // 2],
                rss_end=rss[updates - 1], non_finite=non_finite, not_converged=not_converged)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--updates", type=int, default=100_000)
    ap.add_argument("--model", choices=("known", "learned", "both"), default="both")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if args.updates < 2:
        ap.error("--updates: need at least 2")
    kinds = ("known", "learned") if args.model == "both" else (args.model,)
    head = (f"{'model':<8} {'updates':>8} {'wall s':>8} {'median ms':>10} {'p95 ms':>8} "
            f"{'RSS start MB':>13} {'RSS mid MB':>11} {'RSS end MB':>11} {'non-finite':>11} "
            f"{'not conv.':>10}")
    print(head)
    print("-" * len(head))
    for kind in kinds:
        r = run(kind, args.updates, args.seed)
        print(f"{r['model']:<8} {r['updates']:>8} {r['wall']:>8.1f} {r['median']:>10.3f} "
              f"{r['p95']:>8.3f} {r['rss_start']:>13.1f} {r['rss_mid']:>11.1f} "
              f"{r['rss_end']:>11.1f} {r['non_finite']:>11} {r['not_converged']:>10}", flush=True)


if __name__ == "__main__":
    main()
