"""Benchmark: EstimatorBank against n separate GPMHE estimators, at the paper's size.

    python benches/bench_bank.py [--seed 0] [--sizes 1 10 100 1000] [--samples 30]
                                 [--samples-large 10] [--block 5]

The batch reactor's learned model (gpmhe.systems.batch_reactor; GPs fitted to 5 training
trajectories with 3 restarts, as in bench_update.py), M = 15 and the paper's weights, every
estimator from the poor prior br.X_PRIOR0 with its own simulated outputs (one simulated run per
estimator). For each n: a bank of n estimators and n separate `GPMHE` objects get the same
samples in the same run, interleaved in blocks of `--block` samples so that a drift in the
machine's speed hits both alike. Per sample: the time of one `bank.update` against the time of
the n separate `update` calls (median and p95 over the samples, transient included), the time
per estimator, the speed-up of the medians, the number of threads the bank ran on (rayon's pool,
`RAYON_NUM_THREADS` to change it), and whether the bank's estimates equal the separate ones bit
for bit. n >= 1000 runs `--samples-large` samples. Prints a table, asserts nothing.
"""

from __future__ import annotations

import argparse
import os
import time
import warnings

import numpy as np

from gpmhe import GPMHE, EstimatorBank, LearnedModel
from gpmhe.systems import batch_reactor as br


def run(model, n, samples, block, seed):
    """(bank times, separate times, identical) for n estimators over `samples` samples."""
    rng = np.random.default_rng(seed + n)
    Y = np.stack([br.simulate(br.X_TRUE0, samples, rng)[1][:samples] for _ in range(n)], axis=1)
    settings = dict(x_bounds=br.X_BOUNDS, **br.MHE_SETTINGS)
    bank = EstimatorBank(model, n, br.X_PRIOR0, **settings)
    separate = [GPMHE(model, x0=br.X_PRIOR0, **settings) for _ in range(n)]
    t_bank, t_sep = np.empty(samples), np.empty(samples)
    for start in range(0, samples, block):
        stop = min(start + block, samples)
        for t in range(start, stop):
            t0 = time.perf_counter()
            bank.update(None, Y[t])
            t_bank[t] = time.perf_counter() - t0
        for t in range(start, stop):
            t0 = time.perf_counter()
            for i, mhe in enumerate(separate):
                mhe.update(None, Y[t, i])
            t_sep[t] = time.perf_counter() - t0
    same = (np.array_equal(bank.x, np.array([m.x for m in separate]))
            and np.array_equal(bank.P, np.array([m.P for m in separate]))
            and np.array_equal(bank.cost, np.array([m.cost for m in separate])))
    return t_bank, t_sep, same


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sizes", type=int, nargs="+", default=[1, 10, 100, 1000])
    ap.add_argument("--samples", type=int, default=30)
    ap.add_argument("--samples-large", type=int, default=10)
    ap.add_argument("--block", type=int, default=5)
    args = ap.parse_args()

    rng = np.random.default_rng(args.seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        data = br.training_data(5, rng=rng)
        model = LearnedModel.from_trajectories(*data, n_restarts=3, random_state=args.seed, **br.PAPER_GP)
    n_train = sum(len(states) - 1 for states in data[0])
    warnings.simplefilter("ignore", RuntimeWarning)  # a rare unconverged window: not timed here
    threads = EstimatorBank(model, 1, br.X_PRIOR0).threads
    print(f"batch reactor, learned model ({n_train} training points per f-GP), M = 15, from "
          f"x0 = {br.X_PRIOR0}; {os.cpu_count()} CPUs, bank threads = {threads}")
    head = (f"{'n':>5} {'samples':>7} | {'bank median':>11} {'p95':>9} | {'separate median':>15} "
            f"{'p95':>9} | {'per estimator bank':>18} {'separate':>9} | {'speed-up':>8} "
            f"{'threads':>7} {'identical':>9}")
    print(head)
    print("-" * len(head))
    ms = 1e3
    for n in args.sizes:
        samples = args.samples_large if n >= 1000 else args.samples
        tb, ts, same = run(model, n, samples, args.block, args.seed)
        mb, ms_ = np.median(tb), np.median(ts)
        print(f"{n:>5} {samples:>7} | {mb * ms:>8.2f} ms {np.percentile(tb, 95) * ms:>6.2f} ms | "
              f"{ms_ * ms:>12.2f} ms {np.percentile(ts, 95) * ms:>6.2f} ms | "
              f"{mb / n * 1e6:>15.0f} µs {ms_ / n * 1e6:>6.0f} µs | {ms_ / mb:>7.2f}x "
              f"{threads:>7} {'yes' if same else 'NO':>9}", flush=True)


if __name__ == "__main__":
    main()
