"""Benchmark: what the Rust solver's decrement stop (`dtol`) costs in accuracy and saves in work.

    python benches/stopping.py [--seeds 20] [--dtols 0,1e-5,1e-3,1e-2] [--steps 100] [--jobs 2]
                               [--case gp5|gp3|exact|filtering]

Per seed: the batch reactor's training data (5 or 3 trajectories, GPs fitted with 3 restarts, as
in `gpmhe.demos.batch_reactor`), one run of the estimator from the poor prior for each `dtol`
(0: every window to the projected-gradient tolerance 1e-6). `--case`: GP-MHE with 5 trajectories
in the paper's prediction form (gp5, the default), with 3 trajectories (gp3), the exact-model
MHE (exact, vectorised KnownModel) or GP-MHE with 5 trajectories in the filtering form
(filtering). Prints, per seed and dtol, the whole-run RMSE of the estimates (x̂(t+1) after y(t),
or x̂(t) in the filtering form); then per dtol the mean RMSE, the largest per-seed RMSE change
against the first dtol listed, the median and mean window evaluations per update and the median
time per update (process time; both processes share the 2 cores, so compare dtols with each
other, not with other tables).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import sys
import time
import warnings

import numpy as np


CASES = {"gp5": "GP-MHE (5 traj.)", "gp3": "GP-MHE (3 traj.)", "exact": "exact-model MHE",
         "filtering": "GP-MHE (5 traj.), filtering form"}


def one_seed(args):
    seed, steps, dtols, case = args
    from gpmhe import GPMHE, KnownModel, LearnedModel
    from gpmhe.systems import batch_reactor as br

    rng = np.random.default_rng(seed)
    data = {n_traj: br.training_data(n_traj, rng=rng) for n_traj in (5, 3)}
    if case == "exact":
        model = KnownModel(br.f_batch, br.h_batch, 2, 1, f_jacobian=br.f_jacobian_batch,
                           h_jacobian=br.h_jacobian_batch, vectorized=True)
    else:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = LearnedModel.from_trajectories(*data[3 if case == "gp3" else 5],
                                                   n_restarts=3, random_state=seed, **br.PAPER_GP)
    form = "filtering" if case == "filtering" else "prediction"
    x, y = br.simulate(br.X_TRUE0, steps, rng)
    out = {}
    for dtol in dtols:
        est = GPMHE(model, br.X_PRIOR0, x_bounds=br.X_BOUNDS, solver_options={"dtol": dtol},
                    form=form, **br.MHE_SETTINGS)
        xs, nfev, ts = [], [], []
        for t in range(steps):
            t0 = time.process_time()
            xs.append(est.update(None, y[t]).copy())
            ts.append(time.process_time() - t0)
            nfev.append(est.nfev)
        # The prediction form's x is x̂(t+1) after y(t), the filtering form's x̂(t).
        shift = 0 if form == "filtering" else 1
        err = np.array(xs) - x[shift:steps + shift]
        out[dtol] = (float(np.sqrt(np.mean(np.sum(err**2, axis=1)))), nfev, ts)
    return seed, out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--dtols", default="0,1e-5,1e-3,1e-2")
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--case", choices=CASES, default="gp5")
    args = ap.parse_args(argv)
    dtols = [float(d) for d in args.dtols.split(",")]
    tasks = [(seed, args.steps, dtols, args.case) for seed in range(args.seeds)]
    t0 = time.perf_counter()
    results = {}
    with mp.get_context("spawn").Pool(args.jobs) as pool:
        for seed, out in pool.imap_unordered(one_seed, tasks):
            results[seed] = out
            print(f"seed {seed:2d}: RMSE " + "  ".join(f"{out[d][0]:.5f}" for d in dtols),
                  file=sys.stderr, flush=True)
    seeds = sorted(results)
    ref = np.array([results[s][dtols[0]][0] for s in seeds])
    print(f"\n{CASES[args.case]}, batch reactor from the poor prior: {len(seeds)} seeds x "
          f"{args.steps} steps\n")
    print("| dtol | mean RMSE | largest per-seed RMSE change | median (mean) window evaluations "
          "| median ms per update |")
    print("|---|---|---|---|---|")
    for d in dtols:
        r = np.array([results[s][d][0] for s in seeds])
        nf = np.concatenate([results[s][d][1] for s in seeds])
        ts = np.concatenate([results[s][d][2] for s in seeds])
        change = np.max(np.abs(r - ref) / ref) * 100
        print(f"| {d:g} | {np.mean(r):.4f} | {change:.2f} % | {np.median(nf):.0f} "
              f"({np.mean(nf):.1f}) | {np.median(ts) * 1e3:.3f} |")
    print(f"\n(total {time.perf_counter() - t0:.0f} s; RMSE change relative to dtol={dtols[0]:g})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
