"""Benchmark: the default window solver on stiff windows (large ratios between the residual
weights) and on the batch reactor, for which its defaults were tuned.

    python benches/stiff_windows.py [--seeds 3] [--steps 50] [--cases rm,rm9,cp,br,br-gp]
    python benches/stiff_windows.py --builds OLD_DIR NEW_DIR   # the same table for two builds

Cases (`--cases`, comma-separated):

* ``rm``: rotating masses (`gpmhe.systems.rotating_masses`), exact model, do-mpc's setting
  ``MHE_SETTINGS`` (process weight Q0⁻¹ = 1e8 I against output and arrival weights of 1),
  from ``initial_estimate(seed + 1)``, ``--steps`` updates.
* ``rm9``: the same with the inertia Θ1 estimated as a ninth state (dΘ1/dt = 0, scaled by 1e-4 so
  that it is O(1), bounds [0.1, 10], prior 1 with weight P_P = 10), true Θ1 = 2.25.
* ``cp``: the cart-pole (`gpmhe.systems.cart_pole`) in its near-deterministic setting (process
  weights up to 4e8), 2 × ``--steps`` updates.
* ``br``: the batch reactor from the poor prior with the exact model (paper's setting, bounds).
* ``br-gp``: the same with GP-MHE on 5 training trajectories (GPs fitted with 3 restarts).

Per case: window evaluations per update (median, p95, max), milliseconds per update (median,
p95; wall clock, shared machine), the whole-run RMSE of the estimates against the truth (all
states, x̂(t+1) after y(t); rm9 also Θ1's final relative error) and the number of windows whose
solver did not converge (RuntimeWarning). With ``--builds`` each seed runs once per build in
alternating worker processes (a build is a directory holding a `gpmhe` package with its
extension), and the table has one row per case and build.
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

CASES = ("rm", "rm9", "cp", "br", "br-gp")
THETA_SCALE = 1e-4


def rotating_masses_9(rm):
    """The rotating masses with s = Θ1 / 1e-4 as a ninth state, ds/dt = 0 (CasADi)."""
    import casadi as ca

    from gpmhe import KnownModel

    F, h = rm.casadi_functions(theta1=None)
    x, u = ca.SX.sym("x", 9), ca.SX.sym("u", 2)
    xdot = ca.vertcat(F(x[:8], u, THETA_SCALE * x[8]), 0)
    rhs = ca.Function("rm9", [x, u], [xdot])
    out = ca.Function("rm9_output", [x, u], [x[:3]])
    return KnownModel.from_ode(rhs, out, rm.T, substeps=rm.SUBSTEPS)


def setup(case, seed, steps):
    """(estimator, inputs or None, outputs, true states)."""
    from gpmhe import GPMHE, KnownModel, LearnedModel

    if case in ("rm", "rm9"):
        from gpmhe.systems import rotating_masses as rm

        x, u, y = rm.simulate(steps, rng=seed)
        x0 = rm.initial_estimate(seed + 1)
        if case == "rm":
            return GPMHE(rm.known_model(backend="numpy"), x0, **rm.MHE_SETTINGS), u, y, x
        s = rm.THETA1_GUESS / THETA_SCALE
        lo, hi = (b / THETA_SCALE for b in rm.THETA1_BOUNDS)
        settings = dict(rm.MHE_SETTINGS, P2=np.diag(np.r_[np.diag(rm.P_X), rm.P_P]),
                        Q0=1e-8 * np.eye(9))
        bounds = (np.r_[np.full(8, -np.inf), lo], np.r_[np.full(8, np.inf), hi])
        truth = np.c_[x, np.full(len(x), rm.THETA1 / THETA_SCALE)]
        mhe = GPMHE(rotating_masses_9(rm), np.r_[x0, s], x_bounds=bounds, **settings)
        return mhe, u, y, truth
    if case == "cp":
        from gpmhe.systems import cart_pole as cp

        x, u, y = cp.simulate(2 * steps, rng=seed)
        return GPMHE(cp.known_model("numpy"), cp.X0, **cp.MHE_SETTINGS), u, y, x
    from gpmhe.systems import batch_reactor as br

    rng = np.random.default_rng(seed)
    if case == "br":
        model = KnownModel(br.f_batch, br.h_batch, 2, 1, f_jacobian=br.f_jacobian_batch,
                           h_jacobian=br.h_jacobian_batch, vectorized=True)
    else:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = LearnedModel.from_trajectories(*br.training_data(5, rng=rng), n_restarts=3,
                                                   random_state=seed, **br.PAPER_GP)
    x, y = br.simulate(br.X_TRUE0, 2 * steps, rng)
    mhe = GPMHE(model, br.X_PRIOR0, x_bounds=br.X_BOUNDS, **br.MHE_SETTINGS)
    return mhe, None, y, x


def run_case(case, seed, steps):
    """One run: {nfev: [...], ms: [...], sq_err: sum of squared errors, count, warnings, theta}."""
    mhe, u, y, x = setup(case, seed, steps)
    nfev, ms, est = [], [], []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RuntimeWarning)
        for t in range(len(x) - 1):  # x̂(t+1) after y(t) against x(t+1)
            t0 = time.perf_counter()
            est.append(mhe.update(None if u is None else u[t], y[t]).copy())
            ms.append(1e3 * (time.perf_counter() - t0))
            nfev.append(int(mhe.nfev))
    err = np.array(est) - x[1:len(est) + 1]
    n_warn = sum(issubclass(w.category, RuntimeWarning) for w in caught)
    theta = float(est[-1][8] / x[-1, 8] - 1.0) if case == "rm9" else None
    return dict(nfev=nfev, ms=ms, sq_err=float(np.sum(err**2)), count=int(err.shape[0]),
                warnings=n_warn, theta=theta)


def run_all(cases, seeds, steps):
    return {case: [run_case(case, seed, steps) for seed in range(seeds)] for case in cases}


def summary(runs):
    nf = np.concatenate([r["nfev"] for r in runs])
    ms = np.concatenate([r["ms"] for r in runs])
    rmse = np.sqrt(sum(r["sq_err"] for r in runs) / sum(r["count"] for r in runs))
    theta = [r["theta"] for r in runs if r["theta"] is not None]
    extra = f" (Θ1 {np.mean(np.abs(theta)) * 100:.1f} %)" if theta else ""
    return (f"{np.median(nf):.0f} / {np.percentile(nf, 95):.0f} / {nf.max()} | "
            f"{np.median(ms):.2f} / {np.percentile(ms, 95):.2f} | {rmse:.4f}{extra} | "
            f"{sum(r['warnings'] for r in runs)}")


def worker(args):
    """Runs in a worker process (--builds): prints the runs of one seed as JSON."""
    warnings.simplefilter("ignore", UserWarning)
    out = {case: run_case(case, args.seed, args.steps) for case in args.cases.split(",")}
    print("JSON" + json.dumps(out))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--builds", nargs=2, metavar=("OLD_DIR", "NEW_DIR"))
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--seed", type=int, default=0, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    cases = args.cases.split(",")
    if unknown := set(cases) - set(CASES):
        ap.error(f"unknown cases {sorted(unknown)}")
    if args.worker:
        return worker(args)
    t0 = time.perf_counter()
    if args.builds:
        results = {b: {c: [] for c in cases} for b in args.builds}
        for seed in range(args.seeds):
            for build in args.builds:  # alternating, so a drift of the machine hits both
                env = dict(os.environ, PYTHONPATH=os.path.abspath(build))
                out = subprocess.run([sys.executable, os.path.abspath(__file__), "--worker",
                                      "--seed", str(seed), "--steps", str(args.steps),
                                      "--cases", args.cases], env=env, capture_output=True,
                                     text=True, check=True).stdout
                line = next(ln[4:] for ln in out.splitlines() if ln.startswith("JSON"))
                for case, run in json.loads(line).items():
                    results[build][case].append(run)
        rows = [(case, build, results[build][case]) for case in cases for build in args.builds]
    else:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            results = run_all(cases, args.seeds, args.steps)
        rows = [(case, "", results[case]) for case in cases]
    print(f"\n{args.seeds} seeds, {args.steps} updates (cp, br, br-gp: {2 * args.steps})\n")
    print("| case | build | nfev median / p95 / max | ms per update median / p95 | RMSE "
          "| windows not converged |")
    print("|---|---|---|---|---|---|")
    for case, build, runs in rows:
        print(f"| {case} | {os.path.basename(os.path.normpath(build)) if build else '-'} | "
              f"{summary(runs)} |")
    print(f"\n(total {time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
