"""Benchmark: how the GP model's settings decide GP-MHE's accuracy on the batch reactor.

    python benches/learned_models.py [--seeds 20] [--restarts 3]

Per seed (the seeds and data of gpmhe.demos.batch_reactor): fresh training data (5 and 3
trajectories), one run of 100 steps from the poor prior [0.1, 4.5]. Estimators: GP-MHE with the
paper's GP model (zero prior mean, maximum likelihood) and with LearnedModel's defaults (linear
prior mean, standardised bounds, default hyperprior) on 5 and 3 trajectories; the nominal model
with k1 30 % off, alone and plus a GP residual learned from the 3 trajectories (with the residual
defaults, and with the full model's hyperprior="default" for comparison); the exact model plus a
GP residual from the same data (what a perfect nominal model gives with a residual); the
exact-model MHE; filterpy's EKF on the exact model. Prints per estimator the RMSE of x̂ over
t >= 30 (mean over seeds), the seeds whose final error is below 0.3, the model's one-step error
along the true run (RMS of m_x(x(t)) − f(x(t)) over t < 30 and t >= 30, mean over seeds), the
median time per update and its ratio to the EKF's, all measured in this run.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

from gpmhe import GPMHE, KnownModel, LearnedModel
from gpmhe.baselines import ExactEKF
from gpmhe.demos.batch_reactor import rmse, study_simulate
from gpmhe.systems import batch_reactor as br

STEPS, LATE = 100, 30
PAPER = dict(mean="zero", normalize=False, hyperprior=None)


def f_k1_off(X, U):
    """The reactor's f (vectorised) with k1 30 % below its true value: the nominal model."""
    k1 = 0.7 * br.K1
    x1, x2 = X[:, 0], X[:, 1]
    return np.column_stack([x1 + br.T * (-2 * k1 * x1**2 + 2 * br.K2 * x2),
                            x2 + br.T * (k1 * x1**2 - br.K2 * x2)])


def models(seed, restarts):
    """name -> model (or "ekf") for this seed; the data are drawn as the demo draws them."""
    rng = np.random.default_rng(seed)
    data = {n: br.training_data(n, rng=rng) for n in (5, 3)}
    fit = dict(n_restarts=restarts, random_state=seed, warn=False)
    nominal = KnownModel(f_k1_off, br.h_batch, 2, 1, h_jacobian=br.h_jacobian_batch, vectorized=True)
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for n in (5, 3):
            out[f"GP-MHE, {n} traj., paper GP"] = LearnedModel.from_trajectories(*data[n], **fit, **PAPER)
            out[f"GP-MHE, {n} traj., defaults"] = LearnedModel.from_trajectories(*data[n], **fit)
        out["nominal (k1 -30 %) alone"] = nominal
        k1_off = dict(f_nominal=f_k1_off, h_nominal=br.h_batch,
                      nominal_options=dict(h_jacobian=br.h_jacobian_batch, vectorized=True))
        out["nominal + GP residual, 3 traj."] = LearnedModel.from_trajectories(*data[3], **k1_off, **fit)
        out['  same, hyperprior="default"'] = LearnedModel.from_trajectories(
            *data[3], **k1_off, hyperprior="default", **fit)
        out["exact f, h + GP residual, 3 traj."] = LearnedModel.from_trajectories(
            *data[3], f_nominal=br.f_batch, h_nominal=br.h_batch, nominal_options=dict(
                f_jacobian=br.f_jacobian_batch, h_jacobian=br.h_jacobian_batch, vectorized=True), **fit)
    out["exact-model MHE"] = KnownModel(br.f_batch, br.h_batch, 2, 1, f_jacobian=br.f_jacobian_batch,
                                        h_jacobian=br.h_jacobian_batch, vectorized=True)
    out["filterpy EKF (exact)"] = "ekf"
    return out


def run(model, Y):
    """Estimates x̂(t+1) from y(0..t) (est[i] -> x(i+1)) and the seconds per update."""
    if isinstance(model, str):
        Q, R = br.SIGMA_W**2 * np.eye(2), br.SIGMA_V**2 * np.eye(1)
        est = ExactEKF(br.f, br.f_jacobian, br.h, br.h_jacobian, br.X_PRIOR0, np.eye(2), Q, R)
        step = lambda y: (est.update(y), est.predict())  # noqa: E731
    else:
        est = GPMHE(model, br.X_PRIOR0, x_bounds=br.X_BOUNDS, **br.MHE_SETTINGS)
        step = lambda y: est.update(None, y)  # noqa: E731
    xs, times = [], []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for y in Y:
            t0 = time.perf_counter()
            step(y)
            times.append(time.perf_counter() - t0)
            xs.append(np.asarray(est.x, dtype=float).ravel().copy())
    return np.array(xs), times


def one_step_error(model, X):
    """RMS of the model's one-step mean minus the true f at the true states X (x(0..STEPS−1)),
    over t < LATE and t >= LATE."""
    err = model.stage_eval(X)[0] - br.f_batch(X)
    return [float(np.sqrt(np.mean(err[:LATE] ** 2))), float(np.sqrt(np.mean(err[LATE:] ** 2)))]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--restarts", type=int, default=3, help="GP hyperparameter restarts")
    args = ap.parse_args(argv)
    late, final, times, f_err = {}, {}, {}, {}
    for seed in range(args.seeds):
        _, Y, X = study_simulate(seed, STEPS)
        for name, model in models(seed, args.restarts).items():
            est, t = run(model, Y)
            late.setdefault(name, []).append(rmse(est, X, LATE))
            final.setdefault(name, []).append(float(np.linalg.norm(est[-1] - X[STEPS])))
            times.setdefault(name, []).extend(t)
            if not isinstance(model, str):
                f_err.setdefault(name, []).append(one_step_error(model, X[:STEPS]))
    ekf = np.median(times["filterpy EKF (exact)"])
    print(f"batch reactor, {args.seeds} seeds, {STEPS} steps, {args.restarts} restarts per GP fit")
    print(f"{'estimator':34} {'RMSE t>=30':>10} {'final<0.3':>10} {'f err t<30':>10} {'t>=30':>7} "
          f"{'ms/update':>10} {'p95 ms':>8} {'vs EKF':>7}")
    for name in late:
        t = np.array(times[name]) * 1e3
        err = (f"{np.mean(f_err[name], axis=0)[0]:10.4f} {np.mean(f_err[name], axis=0)[1]:7.4f}"
               if name in f_err else f"{'-':>10} {'-':>7}")
        print(f"{name:34} {np.mean(late[name]):10.3f} {np.sum(np.array(final[name]) < 0.3):>6}/{args.seeds:<3} "
              f"{err} {np.median(t):10.3f} {np.percentile(t, 95):8.3f} {np.median(t) / 1e3 / ekf:6.1f}x")


if __name__ == "__main__":
    main()
