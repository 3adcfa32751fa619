"""Batch-reactor demo (the GP-MHE paper's §V; docs/user_guide/systems.rst): `python -m gpmhe demo [options]`.

Trains the GPs on 5 and on 3 measured trajectories, then estimates the state of one simulated run
from the poor prior x̂(0) = [0.1, 4.5] with GP-MHE (5 and 3 trajectories), the exact-model MHE,
filterpy's EKF on the exact model and an EKF on the GP model (5 trajectories). Prints an RMSE
table and the time per update; `--out fig.png` writes a figure like the paper's Fig. 1 (needs
matplotlib, the `plot` extra).

All estimates are of x(t) from outputs up to t−1 (the MHE's prediction form, the EKF's x̂(t|t−1)).
"""

from __future__ import annotations

import argparse
import functools
import sys
import time
import warnings

import numpy as np


def _progress(msg):
    print(msg, file=sys.stderr, flush=True)


def run_estimators(seed, steps, solver, n_restarts=3, log=_progress, models=None,
                   increment_model=False):
    """Simulate one run (seed) and run every estimator on it. Returns (truth (steps+1, 2),
    {name: (estimates (steps, 2) of x(1..steps), update times (steps,), failed windows)}, models).
    `solver` is one name or a list (each MHE runs once per solver; names get a suffix then);
    `increment_model` adds GP-MHE with f learned as an increment (5 trajectories)."""
    solvers = [solver] if isinstance(solver, str) else list(solver)
    from gpmhe import GPMHE, KnownModel, LearnedModel
    from gpmhe.baselines import GPEKF, ExactEKF
    from gpmhe.systems import batch_reactor as br

    rng = np.random.default_rng(seed)
    if models is None:
        models = {}
        data = {n_traj: br.training_data(n_traj, rng=rng) for n_traj in (5, 3)}
        kinds = [(5, False), (3, False)] + ([(5, True)] if increment_model else [])
        for n_traj, incr in kinds:
            log(f"training GPs on {n_traj} trajectories{' (f as increment)' if incr else ''} "
                f"(seed {seed}) ...")
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # optimiser chatter; the best restart is kept
                models[(n_traj, incr)] = LearnedModel.from_trajectories(
                    *data[n_traj], n_restarts=n_restarts, random_state=seed, f_residual=incr,
                    **br.PAPER_GP)
            log(f"  done in {time.perf_counter() - t0:.1f} s")
    x, y = br.simulate(br.X_TRUE0, steps, rng)
    # The vectorised model: one Python call per window evaluation instead of one per point; its
    # arithmetic equals br.f, br.h point by point, so the estimates are the per-point ones.
    known = KnownModel(br.f_batch, br.h_batch, 2, 1, f_jacobian=br.f_jacobian_batch,
                       h_jacobian=br.h_jacobian_batch, vectorized=True)
    estimators = {}
    for sv in solvers:
        tag = f" [{sv}]" if len(solvers) > 1 else ""
        mhe_kw = dict(x_bounds=br.X_BOUNDS, solver=sv, **br.MHE_SETTINGS)
        estimators[f"GP-MHE (5 traj.){tag}"] = GPMHE(models[(5, False)], br.X_PRIOR0, **mhe_kw)
        if (5, True) in models:
            estimators[f"GP-MHE (5, incr. f){tag}"] = GPMHE(models[(5, True)], br.X_PRIOR0,
                                                            **mhe_kw)
        estimators[f"GP-MHE (3 traj.){tag}"] = GPMHE(models[(3, False)], br.X_PRIOR0, **mhe_kw)
        estimators[f"exact-model MHE{tag}"] = GPMHE(known, br.X_PRIOR0, **mhe_kw)
    Q, R = br.SIGMA_W**2 * np.eye(2), br.SIGMA_V**2 * np.eye(1)
    ekfs = {
        "filterpy EKF (exact)": ExactEKF(br.f, br.f_jacobian, br.h, br.h_jacobian, br.X_PRIOR0,
                                         np.eye(2), Q, R),
        "GP-EKF (5 traj.)": GPEKF(models[(5, False)], br.X_PRIOR0, np.eye(2), Q, R),
    }
    results = {}
    for name, est in estimators.items():
        log(f"running {name} ({est.solver}) ...")
        xs, ts, failed = np.empty((steps, 2)), np.empty(steps), 0
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # counted in `failed` instead
            for t in range(steps):
                t0 = time.perf_counter()
                est.update(None, y[t])
                ts[t] = time.perf_counter() - t0
                xs[t] = est.x
                failed += not est.success
        results[name] = (xs, ts, failed)
    for name, ekf in ekfs.items():
        xs, ts = np.empty((steps, 2)), np.empty(steps)
        for t in range(steps):
            t0 = time.perf_counter()
            ekf.update(y[t])
            ekf.predict()
            ts[t] = time.perf_counter() - t0
            xs[t] = ekf.x.ravel()
        results[name] = (xs, ts, 0)
    return x, results, models


# ----------------------------------------------- the same runs as monte_carlo factories (benches)


@functools.lru_cache(maxsize=None)
def _seed_model(seed, n_traj, incr, n_restarts):
    """The learned model run_estimators fits for this seed (the seed's rng draws the 5- then the
    3-trajectory data; the fit uses random_state=seed), fitted once per process."""
    from gpmhe import LearnedModel
    from gpmhe.systems import batch_reactor as br

    rng = np.random.default_rng(seed)
    data = {n: br.training_data(n, rng=rng) for n in (5, 3)}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return LearnedModel.from_trajectories(*data[n_traj], n_restarts=n_restarts,
                                              random_state=seed, f_residual=incr, **br.PAPER_GP)


def study_simulate(seed, steps):
    """run_estimators' run for this seed as ``monte_carlo``'s (U, Y, X): the seed's rng draws the
    training data first (discarded here), then the run; Y = y(0..steps−1), X = x(0..steps)."""
    from gpmhe.systems import batch_reactor as br

    rng = np.random.default_rng(seed)
    for n in (5, 3):
        br.training_data(n, rng=rng)
    x, y = br.simulate(br.X_TRUE0, steps, rng)
    return None, y[:steps], x


def study_estimator(seed, kind, solver="gauss-newton", n_restarts=3):
    """A fresh estimator of run_estimators for this seed: kind is "gp5", "gp5-incr", "gp3",
    "exact" (MHEs with `solver`), "ekf" (filterpy's EKF) or "gp-ekf" (GP-EKF on the 5-trajectory
    model); the EKFs are wrapped in `gpmhe.study.FilterAdapter` (update, then predict)."""
    from gpmhe import GPMHE, KnownModel
    from gpmhe.baselines import GPEKF, ExactEKF
    from gpmhe.study import FilterAdapter
    from gpmhe.systems import batch_reactor as br

    Q, R = br.SIGMA_W**2 * np.eye(2), br.SIGMA_V**2 * np.eye(1)
    if kind == "ekf":
        return FilterAdapter(ExactEKF(br.f, br.f_jacobian, br.h, br.h_jacobian, br.X_PRIOR0,
                                      np.eye(2), Q, R))
    if kind == "gp-ekf":
        return FilterAdapter(GPEKF(_seed_model(seed, 5, False, n_restarts), br.X_PRIOR0,
                                   np.eye(2), Q, R))
    if kind == "exact":
        model = KnownModel(br.f_batch, br.h_batch, 2, 1, f_jacobian=br.f_jacobian_batch,
                           h_jacobian=br.h_jacobian_batch, vectorized=True)
    else:
        n_traj, incr = {"gp5": (5, False), "gp5-incr": (5, True), "gp3": (3, False)}[kind]
        model = _seed_model(seed, n_traj, incr, n_restarts)
    return GPMHE(model, br.X_PRIOR0, x_bounds=br.X_BOUNDS, solver=solver, **br.MHE_SETTINGS)


def study_factories(solvers, n_restarts=3, increment_model=True):
    """run_estimators' estimators as ``monte_carlo`` factories (name -> factory(seed)), named and
    ordered as run_estimators names them."""
    factories = {}
    for sv in solvers:
        tag = f" [{sv}]" if len(solvers) > 1 else ""
        kinds = [("GP-MHE (5 traj.)", "gp5")]
        kinds += [("GP-MHE (5, incr. f)", "gp5-incr")] if increment_model else []
        kinds += [("GP-MHE (3 traj.)", "gp3"), ("exact-model MHE", "exact")]
        for name, kind in kinds:
            factories[name + tag] = functools.partial(study_estimator, kind=kind, solver=sv,
                                                      n_restarts=n_restarts)
    factories["filterpy EKF (exact)"] = functools.partial(study_estimator, kind="ekf")
    factories["GP-EKF (5 traj.)"] = functools.partial(study_estimator, kind="gp-ekf",
                                                      n_restarts=n_restarts)
    return factories


def rmse(est, truth, start):
    """RMSE of ‖x̂(t) − x(t)‖ over t ≥ start; est[i] estimates truth[i + 1]."""
    err = est[start - 1:] - truth[start:]
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m gpmhe demo", description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=100, help="time steps (default 100)")
    ap.add_argument("--seed", type=int, default=0, help="random seed (data and run)")
    ap.add_argument("--solver", default="gauss-newton",
                    help="GP-MHE window solver: gauss-newton (default, the Rust solver), "
                         "least-squares (SciPy TRF) or trust-constr (SciPy interior point, "
                         "~0.3-1 s per step)")
    ap.add_argument("--restarts", type=int, default=3, help="GP hyperparameter restarts")
    ap.add_argument("--out", default=None, help="write a Fig.-1-like PNG here (needs matplotlib)")
    args = ap.parse_args(argv)
    if args.steps < 21:
        ap.error("--steps must be at least 21 (the RMSE is reported over t >= 20)")

    truth, results, _ = run_estimators(args.seed, args.steps, args.solver, args.restarts)
    print(f"\nBatch reactor, prior x̂(0) = [0.1, 4.5], true x(0) = [3, 1], {args.steps} steps, "
          f"seed {args.seed}, MHE solver: {args.solver}")
    print(f"{'estimator':22s} {'RMSE all':>9s} {'RMSE t>=20':>11s} {'final err':>10s} "
          f"{'min x1':>8s} {'ms/update':>10s} {'failed':>7s}")
    for name, (xs, ts, failed) in results.items():
        final = float(np.linalg.norm(xs[-1] - truth[-1]))
        print(f"{name:22s} {rmse(xs, truth, 1):9.3f} {rmse(xs, truth, 20):11.3f} {final:10.3f} "
              f"{xs[:, 0].min():8.3f} {1e3 * np.median(ts):10.2f} {failed:7d}")
    if args.out:
        try:
            import matplotlib

            matplotlib.use("Agg")
            import matplotlib.pyplot as plt
        except ImportError:
            print("--out needs matplotlib: pip install 'gpmhe[plot]'", file=sys.stderr)
            return 1
        fig, axes = plt.subplots(2, 1, sharex=True, figsize=(7, 6))
        t = np.arange(args.steps + 1)
        for i, ax in enumerate(axes):
            ax.plot(t, truth[:, i], "k-", lw=2, label="true")
            for name, (xs, _, _) in results.items():
                ax.plot(t[1:], xs[:, i], lw=1, label=name)
            ax.set_ylabel(f"x{i + 1}")
            ax.set_ylim(-1.5, 5)
        axes[0].legend(fontsize=7, ncol=2)
        axes[-1].set_xlabel("t")
        fig.suptitle("Batch reactor: estimates from the prior [0.1, 4.5]")
        fig.tight_layout()
        fig.savefig(args.out, dpi=120)
        print(f"figure written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
