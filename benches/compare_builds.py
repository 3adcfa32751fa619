"""Time two builds of gpmhe against each other: the update times of bench_update.py's estimators
(batch reactor, paper's size, seed 0) with each build, in alternating rounds on the same machine.

    python benches/compare_builds.py OLD_DIR NEW_DIR [--rounds 3] [--steps 60]

OLD_DIR and NEW_DIR are directories that hold a `gpmhe` package with its built extension
(e.g. a checkout's `python/` with `_core.abi3.so` copied in). Each round runs one worker process
per build, old first then new; a worker fits the GPs, runs every estimator of bench_update's
first table (trust-constr excepted: it takes ~0.5 s per update) interleaved over `--steps`
updates, and reports the times. The pooled times of all rounds give, per estimator and build, the
median and p95 of the time per update and the ratio new/old. Alternating the builds spreads a
drift of the machine's speed over both.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import warnings

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))


def worker(steps, seed):
    """Runs in a worker process: prints {name: [seconds per update]} as JSON."""
    sys.path.insert(0, HERE)
    import bench_update as bu
    from gpmhe.systems import batch_reactor as br

    warnings.simplefilter("ignore")
    rng = np.random.default_rng(seed)
    gp5, gp5_2r, known, known_vec = bu.fit_models(seed, rng)
    models = dict(gp5=gp5, gp5_2r=gp5_2r, known=known, known_vec=known_vec)
    _, y = br.simulate(br.X_TRUE0, steps, rng)
    kw = dict(x_bounds=br.X_BOUNDS, **br.MHE_SETTINGS)
    rows = [r for r in bu.MHE_ROWS if r[2] != "trust-constr"]
    steppers, _, _ = bu.make_steppers(models, kw, steps, steps, rows)
    runs = bu.interleaved_runs(steppers, y, 10)
    print("JSON" + json.dumps({name: ts.tolist() for name, (_, ts) in runs.items()}))


def run_worker(path, steps, seed):
    env = dict(os.environ, PYTHONPATH=os.path.abspath(path))
    out = subprocess.run([sys.executable, os.path.abspath(__file__), "--worker",
                          "--steps", str(steps), "--seed", str(seed)],
                         env=env, capture_output=True, text=True, check=True).stdout
    return json.loads(next(line[4:] for line in out.splitlines() if line.startswith("JSON")))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("old", nargs="?")
    ap.add_argument("new", nargs="?")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        worker(args.steps, args.seed)
        return 0
    if not (args.old and args.new):
        ap.error("OLD_DIR and NEW_DIR are required")
    pooled = {"old": {}, "new": {}}
    for r in range(args.rounds):
        for build in ("old", "new"):
            print(f"round {r + 1}/{args.rounds}: {build} build ...", file=sys.stderr, flush=True)
            for name, ts in run_worker(getattr(args, build), args.steps, args.seed).items():
                pooled[build].setdefault(name, []).extend(ts)
    print(f"\n## Time per update, old vs new build ({args.rounds} alternating rounds of "
          f"{args.steps} updates each, seed {args.seed})\n")
    print(f"| {'estimator':<46} | old median ms | new median ms | new/old | old p95 ms "
          f"| new p95 ms | new/old |")
    print("|" + "-" * 48 + "|---------------|---------------|---------|------------|"
          "------------|---------|")
    for name in pooled["old"]:
        old, new = np.array(pooled["old"][name]) * 1e3, np.array(pooled["new"][name]) * 1e3
        mo, mn = np.median(old), np.median(new)
        po, pn = np.percentile(old, 95), np.percentile(new, 95)
        print(f"| {name:<46} | {mo:13.3f} | {mn:13.3f} | {mn / mo:7.2f} | {po:10.3f} "
              f"| {pn:10.3f} | {pn / po:7.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
