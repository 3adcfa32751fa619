"""Benchmark: how soon Ctrl-C stops a long call, and that the object is unchanged afterwards.

    python benches/interrupt_latency.py [--repeats 5] [--delay 0.325]

SIGALRM (signal.setitimer) fires `--delay` s into each long call; its handler raises
KeyboardInterrupt as Python's Ctrl-C handler does. Prints, per call, the median and worst time
from the signal to the KeyboardInterrupt reaching the caller over `--repeats` runs, and whether
the object kept its state. The calls: a batch of RecursiveGP updates (400 basis vectors,
400 000 points: the core checks for signals every 50 ms), GaussianProcess.fit on N = 1000 and
N = 2000 points (the check runs between the O(N³) factorisations, so one of them is the bound),
and a loop of GPMHE updates with the learned batch-reactor model (each update is one short core
call; Python sees the signal between them). Linux/macOS only (setitimer).
"""

from __future__ import annotations

import argparse
import signal
import time
import warnings

import numpy as np

from gpmhe import GPMHE, GaussianProcess, LearnedModel, RecursiveGP
from gpmhe.systems import batch_reactor as br


def interrupted_after(delay, call):
    """Runs call() with SIGALRM raising KeyboardInterrupt after `delay` s; returns the latency
    from the signal's delivery to the exception reaching the caller (None if call() finished
    first)."""

    def handler(signum, frame):
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGALRM, handler)
    start = time.perf_counter()
    signal.setitimer(signal.ITIMER_REAL, delay)
    try:
        call()
    except KeyboardInterrupt:
        return time.perf_counter() - (start + delay)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
    return None


def rgp_case():
    rgp = RecursiveGP([-2.0, -2.0], [2.0, 2.0], 20)
    rng = np.random.default_rng(0)
    zeta = rng.uniform(-2.0, 2.0, size=(400_000, 2))
    y = np.sin(zeta[:, 0])
    before = (rgp.mean.copy(), rgp.cov.copy())

    def kept():
        return np.array_equal(rgp.mean, before[0]) and np.array_equal(rgp.cov, before[1])

    return (lambda: rgp.update(zeta, y, 0.01)), kept


def gp_case(n):
    rng = np.random.default_rng(1)
    D = rng.uniform(-2.0, 2.0, size=(n, 2))
    y = np.sin(D[:, 0]) * np.cos(D[:, 1]) + 0.05 * rng.standard_normal(n)
    gp = GaussianProcess(n_restarts=100, random_state=0).fit(D[:30], y[:30])
    before = gp.predict(D[:20], return_std=True)

    def kept():
        after = gp.predict(D[:20], return_std=True)
        return all(np.array_equal(a, b) for a, b in zip(before, after))

    return (lambda: gp.fit(D, y)), kept


def mhe_case(model):
    ys = np.tile(br.simulate(br.X_TRUE0, 1000, np.random.default_rng(2))[1][:1000], (200, 1))
    mhe = GPMHE(model, x0=[3.0, 1.0], x_bounds=br.X_BOUNDS, **br.MHE_SETTINGS)
    mhe.batch_filter(ys[:20])
    state = {}

    def run():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            for y in ys[20:]:
                mhe.update(None, y)
                state["t"], state["x"] = mhe.t, mhe.x.copy()

    def kept():  # the attributes are those of the last completed update
        return mhe.t == state["t"] and np.array_equal(mhe.x, state["x"])

    return run, kept


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--delay", type=float, default=0.325)
    args = ap.parse_args(argv)
    states, outputs = br.training_data(5, rng=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = LearnedModel.from_trajectories(states, outputs, n_restarts=1, random_state=0, **br.PAPER_GP)
    cases = {
        "RecursiveGP.update (400 basis, 4e5 points)": rgp_case,
        "GaussianProcess.fit (N = 1000)": lambda: gp_case(1000),
        "GaussianProcess.fit (N = 2000)": lambda: gp_case(2000),
        "GPMHE.update loop (learned model)": lambda: mhe_case(model),
    }
    print(f"{'call':<44} {'median ms':>10} {'worst ms':>9} {'state kept':>11}")
    print("-" * 77)
    for name, make in cases.items():
        lat, kept_all = [], True
        for _ in range(args.repeats):
            call, kept = make()
            d = interrupted_after(args.delay, call)
            if d is None:
                print(f"{name:<44} finished before the signal")
                break
            lat.append(1e3 * d)
            kept_all &= kept()
        if lat:
            print(f"{name:<44} {np.median(lat):>10.1f} {max(lat):>9.1f} {str(kept_all):>11}",
                  flush=True)


if __name__ == "__main__":
    main()
