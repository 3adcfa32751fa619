"""Benchmark: a bank of estimators on a compiled CasADi model, on 1, 2, ... threads.

    python benches/bench_bank_scaling.py [--n 64] [--samples 40] [--threads 1 2] [--seed 0]

Plants: the cart-pole (`gpmhe.systems.cart_pole`, its MHE settings), the rotating masses
(`gpmhe.systems.rotating_masses`, Θ1 known, its MHE settings), each estimator with its own
simulated run, and a fleet of rotating masses whose plants each have their own inertia Θ1
(spread ±40 % around the nominal one), each estimator estimating its plant's Θ1 from the same
prior (`rotating_masses.PARAMETER_SETTINGS`); the final relative error of Θ̂1 is printed. For each plant and each thread count (a fresh process with RAYON_NUM_THREADS set,
since rayon sizes its pool once per process; `--rounds` rounds that take the thread counts in
turn, so that a change in the machine's load hits all alike): the median and p95 time of one
`bank.update` of `--n` estimators on the model compiled in the core, over the samples after the
first window is full and over the rounds; in the one-thread process also the same bank on Python
callbacks (``native=False``, which updates its estimators one after another) and `--n` separate
`GPMHE` estimators updated in a Python loop, interleaved with the bank sample by sample. The speed-up is against the compiled bank on one thread; every bank's estimates
are checked against the separate estimators' bit for bit. Prints a table, asserts nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
import warnings

import numpy as np

from gpmhe import GPMHE, EstimatorBank
from gpmhe.systems import cart_pole as cp
from gpmhe.systems import rotating_masses as rm


def plant_data(name, n, samples, seed):
    """(model factory of `native`, x0 rows (n, dim_x), U (samples, n, m), Y (samples, n, p),
    settings)."""
    runs = []
    if name == "cart-pole":
        for i in range(n):
            _, u, y = cp.simulate(samples, rng=seed + i)
            runs.append((cp.X0, u[:samples], y[:samples]))
        return (lambda native: cp.known_model("casadi", native=native)), runs, cp.MHE_SETTINGS
    fleet = name == "rotating masses, each Θ1 estimated"
    for i in range(n):
        rng = np.random.default_rng(seed + i)
        theta1 = fleet_inertia(i, n) if fleet else rm.THETA1
        _, u, y = rm.simulate(samples, rng=rng, theta1=theta1)
        runs.append((rm.initial_estimate(rng), u[:samples], y[:samples]))
    if fleet:
        settings = dict(rm.MHE_SETTINGS, **rm.PARAMETER_SETTINGS)
        return (lambda native: rm.known_model(None, native=native)), runs, settings
    return (lambda native: rm.known_model(native=native)), runs, rm.MHE_SETTINGS


def fleet_inertia(i, n):
    """Plant i's inertia Θ1 in the fleet: evenly spread over ±40 % of the nominal one."""
    return rm.THETA1 * (0.6 + 0.8 * i / max(n - 1, 1))


def measure(name, n, samples, seed, separate):
    """One process's measurements: {"bank": times, "callbacks": times, "separate": times,
    "identical": bool} (the last three only with `separate`)."""
    build, runs, settings = plant_data(name, n, samples, seed)
    X0 = np.array([r[0] for r in runs])
    U = np.stack([r[1] for r in runs], axis=1)
    Y = np.stack([r[2] for r in runs], axis=1)
    warnings.simplefilter("ignore", RuntimeWarning)  # early windows may stop at max-iterations
    bank = EstimatorBank(build(True), n, X0, **settings)
    out = {"parallel": bool(bank._core.parallel)}
    steps = {"bank": lambda t: bank.update(U[t], Y[t])}
    if separate:  # the others interleaved with the bank sample by sample, so drift hits all alike
        slow = EstimatorBank(build(False), n, X0, **settings)
        ests = [GPMHE(build(True), X0[i], **settings) for i in range(n)]

        def loop(t):
            for i, est in enumerate(ests):
                est.update(U[t, i], Y[t, i])

        steps.update(callbacks=lambda t: slow.update(U[t], Y[t]), separate=loop)
    times = {key: [] for key in steps}
    for t in range(samples):
        for key, step in steps.items():
            t0 = time.perf_counter()
            step(t)
            times[key].append(time.perf_counter() - t0)
    out.update(times)
    if separate:
        xs = np.array([e.x for e in ests])
        out["identical"] = bool(np.array_equal(bank.x, xs) and np.array_equal(slow.x, xs))
    if bank.dim_p:
        truth = np.array([fleet_inertia(i, n) for i in range(n)])
        out["theta_error"] = float(np.max(np.abs(bank.p[:, 0] / truth - 1)))
    return out


def in_process(threads, args, name):
    env = dict(os.environ, RAYON_NUM_THREADS=str(threads))
    cmd = [sys.executable, __file__, "--child", name, "--n", str(args.n), "--samples",
           str(args.samples), "--seed", str(args.seed)] + (["--separate"] if threads == 1 else [])
    run = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
    return json.loads(run.stdout.strip().splitlines()[-1])


def row(label, times, skip, base):
    t = np.array(times[skip:]) * 1e3
    med = np.median(t)
    return f"| {label:44s} | {med:9.2f} | {np.percentile(t, 95):8.2f} | {base / med if base else 1:8.2f} |"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=64)
    ap.add_argument("--samples", type=int, default=40)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--child", default=None)
    ap.add_argument("--separate", action="store_true")
    args = ap.parse_args()
    if args.child:
        print(json.dumps(measure(args.child, args.n, args.samples, args.seed, args.separate)))
        return
    print(f"# A bank of {args.n} estimators on a compiled CasADi model ({os.cpu_count()} cores)\n")
    plants = (("cart-pole", cp.MHE_SETTINGS["horizon"]), ("rotating masses", rm.HORIZON),
              ("rotating masses, each Θ1 estimated", rm.HORIZON))
    for name, skip in plants:
        results = {k: {"bank": []} for k in args.threads}
        for _ in range(args.rounds):
            for k in args.threads:
                got = in_process(k, args, name)
                results[k]["bank"] += got["bank"][skip:]
                results[k].update({key: v for key, v in got.items() if key != "bank"})
        one = results[args.threads[0]]
        base = np.median(np.array(one["bank"]) * 1e3)
        skip_bank = 0  # the banks' warm-up samples are left out above
        print(f"## {name}: time per update of all {args.n} estimators (samples t ≥ {skip})\n")
        print("| estimators                                   | median ms |   p95 ms | speed-up |")
        print("|----------------------------------------------|-----------|----------|----------|")
        for k in args.threads:
            print(row(f"bank, compiled, {k} thread{'s' if k > 1 else ''}", results[k]["bank"],
                      skip_bank, base))
        if "callbacks" in one:
            print(row("bank, Python callbacks (serial)", one["callbacks"], skip, base))
            print(row(f"{args.n} separate GPMHE, compiled, Python loop", one["separate"], skip, base))
            print(f"\n(estimates of both banks equal the separate estimators' bit for bit: "
                  f"{one['identical']})")
        if "theta_error" in one:
            print(f"(largest relative error of the {args.n} estimates of Θ1 after "
                  f"{args.samples} samples: {one['theta_error']:.3f})")
        print()


if __name__ == "__main__":
    main()
