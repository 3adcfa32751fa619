"""Benchmark: time per `update()` of the exact-model MHE on the cart-pole with a CasADi model,
against the same MHE on numpy models and filterpy's EKF.

    python benches/bench_casadi.py [--seed 0] [--steps 300] [--block 10] [--quick]

The cart-pole of `gpmhe.systems.cart_pole` (n = 4, m = 1, p = 4; RK4, 4 sub-steps per sample) in
its near-deterministic setting (`cart_pole.MHE_SETTINGS`: horizon 10, process weights up to 4e8,
arrival weight 0.005× the process weights), one simulated run of `--steps` samples from the true
initial state. Estimators (all with the Rust Gauss-Newton solver, except the EKF):

* CasADi: `KnownModel.from_ode` on CasADi functions, the SX virtual machine (one mapped call per
  window evaluation returns f, h and both Jacobians at all window points), and the same compiled
  (``jit=True``, needs a C compiler; left out without one);
* numpy, exact Jacobian: the vectorised numpy right-hand side with its analytic ∂F/∂x, the
  Jacobian of the discrete map carried through RK4 (`gpmhe.discretize`);
* numpy, finite differences: the vectorised discrete map, `KnownModel`'s central differences
  (one call on the 2n+1 shifted copies of the window points);
* filterpy's EKF (predict + update), on the CasADi model (`gpmhe.baselines.GPEKF` with a known
  model: zero variances).

The estimators run interleaved, `--block` steps each in turn, so that a drift of the machine's
speed hits all alike; the table gives the median and p95 of the time per update over the steps
after the first window is full (t ≥ M), and the ratio of the medians to the CasADi MHE and to
the EKF. Then the time split of one CasADi MHE update: the Python of `GPMHE.update` around the
one Rust call, and inside that call the model callbacks (the CasADi evaluation itself and the
Python around it) against the Rust solver.
"""

from __future__ import annotations

import argparse
import shutil
import time

import numpy as np
from bench_update import _TimedCore

from gpmhe import GPMHE
from gpmhe.baselines import GPEKF
from gpmhe.systems import cart_pole as cp


def mhe_step(mhe):
    def step(ut, yt):
        return mhe.update(ut, yt)
    return step


def ekf_step(ekf):
    def step(ut, yt):
        ekf.update(yt, u=ut)
        ekf.predict(u=ut)
        return ekf.x.ravel()
    return step


def interleaved_runs(steppers, u, y, block):
    """Runs every (name, step) over (u, y) in rounds of `block` steps; returns
    {name: (estimates (T, n), times (T,))}."""
    T = len(y)
    runs = {name: (np.empty((T, cp.DIM_X)), np.empty(T)) for name, _ in steppers}
    for start in range(0, T, block):
        for name, step in steppers:
            xs, ts = runs[name]
            for t in range(start, min(start + block, T)):
                t0 = time.perf_counter()
                xs[t] = step(u[t], y[t])
                ts[t] = time.perf_counter() - t0
    return runs


class Timed:
    """A callable that adds its calls' wall time to a list."""

    def __init__(self, fn):
        self.fn, self.times = fn, []

    def __call__(self, *args):
        t0 = time.perf_counter()
        out = self.fn(*args)
        self.times.append(time.perf_counter() - t0)
        return out


def comparison(x, u, y, block, jit):
    M = cp.MHE_SETTINGS["horizon"]
    models = {"CasADi (SX virtual machine)": cp.known_model("casadi")}
    if jit:
        models["CasADi, compiled (jit=True)"] = cp.known_model("casadi", jit=True)
    models["numpy, exact Jacobian through RK4"] = cp.known_model("numpy")
    models["numpy, finite differences"] = cp.known_model("numpy", jacobian="finite-differences")
    # The first M steps (excluded from the statistics) build the mapped CasADi functions for
    # every window size and compile them with jit.
    mhes = {name: GPMHE(model, cp.X0, **cp.MHE_SETTINGS) for name, model in models.items()}
    steppers = [("MHE, " + name, mhe_step(mhe)) for name, mhe in mhes.items()]
    ekf = GPEKF(models["CasADi (SX virtual machine)"], cp.X0, np.linalg.inv(cp.MHE_SETTINGS["P2"]),
                cp.MHE_SETTINGS["Q0"], cp.MHE_SETTINGS["R0"])
    steppers.append(("filterpy EKF (predict + update), CasADi model", ekf_step(ekf)))
    runs = interleaved_runs(steppers, u, y, block)
    base = np.median(runs["MHE, CasADi (SX virtual machine)"][1][M:])
    ekf_med = np.median(runs["filterpy EKF (predict + update), CasADi model"][1][M:])
    print(f"## Cart-pole, horizon {M}: time per update ({len(y) - M} updates with a full window, "
          f"t ≥ {M})\n")
    print("| estimator                                         | median ms |   p95 ms | ×CasADi MHE | ×EKF  | RMSE  |")
    print("|---------------------------------------------------|-----------|----------|-------------|-------|-------|")
    for name, (xs, ts) in runs.items():
        ts = ts[M:]
        med = np.median(ts)
        # prediction form: the MHE's x after update t is x̂(t+1); the EKF's after predict too
        rmse = np.sqrt(np.mean((xs[M:-1] - x[M + 1:]) ** 2))
        print(f"| {name:49s} | {med * 1e3:9.3f} | {np.percentile(ts, 95) * 1e3:8.3f} | "
              f"{med / base:11.2f} | {med / ekf_med:5.2f} | {rmse:.3f} |")
    nfev = [m.nfev for m in mhes.values()]
    print(f"\n(window evaluations in the last update: {nfev}; measurement noise σ_v = {cp.SIGMA_V})")
    return base


def time_split(u, y, jit):
    """Where the CasADi MHE's update time goes, measured inside the updates: the model callbacks
    and, inside them, the CasADi evaluations are timed (each timer adds well under 1 µs)."""
    M = cp.MHE_SETTINGS["horizon"]
    print("\n## Time split of one CasADi MHE update (medians over t ≥ M)\n")
    print("| model                | update µs | Python around Rust µs | Rust call µs | "
          "callbacks µs (calls) | CasADi evaluations µs | Python in callbacks µs | Rust solver µs |")
    print("|----------------------|-----------|-----------------------|--------------|"
          "----------------------|-----------------------|------------------------|----------------|")
    for name, jit_flag in (("SX virtual machine", False), ("compiled (jit=True)", True)):
        if jit_flag and not jit:
            continue
        model = cp.known_model("casadi", jit=jit_flag)
        cas = model._casadi
        stage, predict = Timed(cas.stage_callback), Timed(cas.predict_callback)
        cas.stage_callback, cas.predict_callback = stage, predict  # instance attributes: the core's callbacks
        mhe = GPMHE(model, cp.X0, **cp.MHE_SETTINGS)
        core = mhe._core = _TimedCore(mhe._core)
        triggers = []
        rows = {key: [] for key in ("total", "rust", "callbacks", "calls", "casadi")}
        for t in range(len(y)):
            if t == M:  # every window size has its callback buffer now: time their evaluations
                for k, (buf, trigger, out, arrays) in list(cas._callback.items()):
                    timed = Timed(trigger)
                    timed.times = triggers
                    cas._callback[k] = (buf, timed, out, arrays)
                buf, trigger, point, result = cas._predictor
                timed = Timed(trigger)
                timed.times = triggers
                cas._predictor = (buf, timed, point, result)
            s0, p0, r0, c0 = len(stage.times), len(predict.times), len(core.times), len(triggers)
            t0 = time.perf_counter()
            mhe.update(u[t], y[t])
            total = time.perf_counter() - t0
            if t >= M:
                rows["total"].append(total)
                rows["rust"].append(sum(core.times[r0:]))
                rows["callbacks"].append(sum(stage.times[s0:]) + sum(predict.times[p0:]))
                rows["calls"].append(len(stage.times) - s0 + len(predict.times) - p0)
                rows["casadi"].append(sum(triggers[c0:]))
        r = {key: np.array(v) for key, v in rows.items()}
        med = {key: np.median(v) * (1 if key == "calls" else 1e6) for key, v in r.items()}
        print(f"| {name:20s} | {med['total']:9.0f} | {np.median(r['total'] - r['rust']) * 1e6:21.0f} | "
              f"{med['rust']:12.0f} | {med['callbacks']:11.0f} ({med['calls']:.0f})     | "
              f"{med['casadi']:21.0f} | {np.median(r['callbacks'] - r['casadi']) * 1e6:22.0f} | "
              f"{np.median(r['rust'] - r['callbacks']) * 1e6:14.0f} |")
    print("\n(callbacks: the stage evaluations and one-step predictions the Rust solver calls back; "
          "CasADi evaluations: the mapped functions' evaluations inside them; Python in callbacks: "
          "the rest (buffers, checks, reshapes); Rust solver: the Rust call minus its callbacks, "
          "i.e. the solver, the window assembly and the arrays passed to and from Python)")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--block", type=int, default=10,
                    help="steps per estimator per round of the interleaved timing")
    ap.add_argument("--quick", action="store_true", help="a short run")
    args = ap.parse_args(argv)
    steps = 40 if args.quick else args.steps
    jit = shutil.which("gcc") is not None or shutil.which("cc") is not None
    x, u, y = cp.simulate(steps, rng=args.seed)
    print(f"# gpmhe exact-model MHE with CasADi: cart-pole, seed {args.seed}, {steps} steps"
          + ("" if jit else " (no C compiler: no jit rows)") + "\n")
    base = comparison(x, u, y, args.block, jit)
    time_split(u, y, jit)
    goal = 0.5e-3
    print(f"\nGoal: median update < {goal * 1e3:.1f} ms for the CasADi model: "
          f"{base * 1e3:.3f} ms ({'met' if base < goal else f'{base / goal:.1f}× too slow'}).")


if __name__ == "__main__":
    main()
