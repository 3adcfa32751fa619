"""Benchmark: time per `update()` of the exact-model MHE on the cart-pole with a CasADi model,
against the same MHE on numpy models and filterpy's EKF.

    python benches/bench_casadi.py [--seed 0] [--steps 300] [--block 10] [--quick]

The cart-pole of `gpmhe.systems.cart_pole` (n = 4, m = 1, p = 4; RK4, 4 sub-steps per sample) in
its near-deterministic setting (`cart_pole.MHE_SETTINGS`: horizon 10, process weights up to 4e8,
arrival weight 0.005× the process weights), one simulated run of `--steps` samples from the true
initial state. Estimators (all with the Rust Gauss-Newton solver, except the EKF):

* CasADi compiled in the core (the default, ``native=True``): `KnownModel.from_ode` on CasADi
  functions, their generated C code compiled once and called by the Rust core point by point,
  without Python;
* CasADi callbacks (``native=False``): the same functions called back through Python, on the SX
  virtual machine (one mapped call per window evaluation returns f, h and both Jacobians at all
  window points), and the same compiled by CasADi's JIT (``jit=True``); the compiled rows need a
  C compiler and are left out without one;
* numpy, exact Jacobian: the vectorised numpy right-hand side with its analytic ∂F/∂x, the
  Jacobian of the discrete map carried through RK4 (`gpmhe.discretize`);
* numpy, finite differences: the vectorised discrete map, `KnownModel`'s central differences
  (one call on the 2n+1 shifted copies of the window points);
* filterpy's EKF (predict + update), on the CasADi model (`gpmhe.baselines.GPEKF` with a known
  model: zero variances).

The estimators run interleaved, `--block` steps each in turn, so that a drift of the machine's
speed hits all alike; the table gives the median and p95 of the time per update over the steps
after the first window is full (t ≥ M), and the ratio of the medians to the CasADi MHE on
callbacks (the SX virtual machine) and to the EKF; once with the default stopping rule and once
solved to the precision acados solves to (``dtol=0``). Then the time split of one CasADi MHE
update: the Python of `GPMHE.update` around the one Rust call, and inside that call the model
callbacks (the CasADi evaluation itself and the Python around it) against the Rust solver.
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


BASE = "MHE, CasADi callbacks (SX virtual machine)"
EKF = "filterpy EKF (predict + update), CasADi model"


def comparison(x, u, y, block, jit, dtol=None):
    """The table of one stopping rule (`dtol` None: the default); returns the medians by name."""
    M = cp.MHE_SETTINGS["horizon"]
    models = {}
    if jit:
        models["CasADi, compiled in the core (native)"] = cp.known_model("casadi")
    models["CasADi callbacks (SX virtual machine)"] = cp.known_model("casadi", native=False)
    if jit:
        models["CasADi callbacks, jit=True"] = cp.known_model("casadi", jit=True, native=False)
    models["numpy, exact Jacobian through RK4"] = cp.known_model("numpy")
    models["numpy, finite differences"] = cp.known_model("numpy", jacobian="finite-differences")
    options = {} if dtol is None else {"solver_options": {"dtol": dtol}}
    # The first M steps (excluded from the statistics) build the mapped CasADi functions for
    # every window size and compile them with jit.
    mhes = {name: GPMHE(model, cp.X0, **cp.MHE_SETTINGS, **options) for name, model in models.items()}
    steppers = [("MHE, " + name, mhe_step(mhe)) for name, mhe in mhes.items()]
    ekf = GPEKF(models["CasADi callbacks (SX virtual machine)"], cp.X0,
                np.linalg.inv(cp.MHE_SETTINGS["P2"]), cp.MHE_SETTINGS["Q0"], cp.MHE_SETTINGS["R0"])
    steppers.append((EKF, ekf_step(ekf)))
    runs = interleaved_runs(steppers, u, y, block)
    base = np.median(runs[BASE][1][M:])
    ekf_med = np.median(runs[EKF][1][M:])
    rule = "the default stopping rule" if dtol is None else f"dtol = {dtol:g}"
    print(f"## Cart-pole, horizon {M}, {rule}: time per update ({len(y) - M} updates with a full "
          f"window, t ≥ {M})\n")
    print("| estimator                                         | median ms |   p95 ms | ×callbacks | ×EKF  | RMSE  |")
    print("|---------------------------------------------------|-----------|----------|------------|-------|-------|")
    medians = {}
    for name, (xs, ts) in runs.items():
        ts = ts[M:]
        med = medians[name] = np.median(ts)
        # prediction form: the MHE's x after update t is x̂(t+1); the EKF's after predict too
        rmse = np.sqrt(np.mean((xs[M:-1] - x[M + 1:]) ** 2))
        print(f"| {name:49s} | {med * 1e3:9.3f} | {np.percentile(ts, 95) * 1e3:8.3f} | "
              f"{med / base:10.2f} | {med / ekf_med:5.2f} | {rmse:.3f} |")
    nfev = [m.nfev for m in mhes.values()]
    print(f"\n(window evaluations in the last update: {nfev}; measurement noise σ_v = {cp.SIGMA_V})\n")
    return medians


def _timed_callbacks(cas, triggers):
    """Times the CasADi evaluations inside the callbacks of this thread (their buffers exist once
    every window size has been evaluated)."""
    for key, (buf, trigger, out, arrays) in list(cas._callback.items()):
        timed = Timed(trigger)
        timed.times = triggers
        cas._callback[key] = (buf, timed, out, arrays)
    for key, (buf, trigger, point, result) in list(cas._predictor.items()):
        timed = Timed(trigger)
        timed.times = triggers
        cas._predictor[key] = (buf, timed, point, result)


def time_split(u, y, jit):
    """Where a CasADi MHE's update time goes, measured inside the updates: the Rust call, and in
    it the model callbacks and, inside them, the CasADi evaluations (each timer adds well under
    1 µs). The model compiled in the core has no callbacks: its evaluations are in the Rust call."""
    M = cp.MHE_SETTINGS["horizon"]
    print("\n## Time split of one CasADi MHE update (medians over t ≥ M)\n")
    print("| model                         | update µs | Python around Rust µs | Rust call µs | "
          "callbacks µs (calls) | CasADi evaluations µs | Python in callbacks µs | Rust solver µs |")
    print("|-------------------------------|-----------|-----------------------|--------------|"
          "----------------------|-----------------------|------------------------|----------------|")
    variants = [("compiled in the core (native)", dict(), jit),
                ("callbacks, SX virtual machine", dict(native=False), True),
                ("callbacks, jit=True", dict(jit=True, native=False), jit)]
    for name, options, available in variants:
        if not available:
            continue
        model = cp.known_model("casadi", **options)
        cas = model._timed_model()._casadi  # what the core runs (the model with intervals)
        stage, predict = Timed(cas.stage_callback), Timed(cas.predict_callback)
        cas.stage_callback, cas.predict_callback = stage, predict  # the core's callbacks, if any
        mhe = GPMHE(model, cp.X0, **cp.MHE_SETTINGS)
        core = mhe._core = _TimedCore(mhe._core)
        triggers = []
        rows = {key: [] for key in ("total", "rust", "callbacks", "calls", "casadi")}
        for t in range(len(y)):
            if t == M:
                _timed_callbacks(cas, triggers)
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
        print(f"| {name:29s} | {med['total']:9.0f} | {np.median(r['total'] - r['rust']) * 1e6:21.0f} | "
              f"{med['rust']:12.0f} | {med['callbacks']:11.0f} ({med['calls']:.0f})     | "
              f"{med['casadi']:21.0f} | {np.median(r['callbacks'] - r['casadi']) * 1e6:22.0f} | "
              f"{np.median(r['rust'] - r['callbacks']) * 1e6:14.0f} |")
    print("\n(callbacks: the stage evaluations and one-step predictions the Rust solver calls back; "
          "CasADi evaluations: the mapped functions' evaluations inside them; Python in callbacks: "
          "the rest (buffers, checks, reshapes); Rust solver: the Rust call minus its callbacks, "
          "i.e. the solver, the window assembly (with a compiled model: its evaluations) and the "
          "arrays passed to and from Python)")


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
    medians = comparison(x, u, y, args.block, jit)
    exact = comparison(x, u, y, args.block, jit, dtol=0.0)
    time_split(u, y, jit)
    base = medians[BASE]
    goal = 0.5e-3
    print(f"\nGoal: median update < {goal * 1e3:.1f} ms for the CasADi model on callbacks: "
          f"{base * 1e3:.3f} ms ({'met' if base < goal else f'{base / goal:.1f}× too slow'}).")
    if jit:
        native, jitted = exact["MHE, CasADi, compiled in the core (native)"], exact["MHE, CasADi callbacks, jit=True"]
        print(f"Goal: solved to dtol = 0, the model compiled in the core at <= 0.7× the jit=True "
              f"callbacks: {native / jitted:.2f}× ({'met' if native <= 0.7 * jitted else 'not met'}).")


if __name__ == "__main__":
    main()
