"""Check that two builds of gpmhe give the same estimates: run every estimator on fixed seeds and
save what it produced, then compare two such files.

    python benches/compare_estimates.py run OUT.npz [--seeds 5]
    python benches/compare_estimates.py diff A.npz B.npz [--tol 1e-12]

`run` covers, on seeds 0 .. seeds−1 of the batch reactor: GP fits (θ, LML, predictions with
standard deviations and input gradients), GP-MHE on the learned model with every solver and both
forms (trust-constr and least-squares on a shorter run, they take ~0.5 s per update), the
exact-model MHE per point and vectorised, with missing outputs and from the poor prior, the EKF on
the GP model and the exact EKF; on the second-order system: the RGP-dKF (states, weights, GP
prediction) and the recursive GP alone. `diff` prints, per entry, the largest absolute difference
relative to max(1, |value|) and fails (exit code 1) if any exceeds `--tol` or an entry is
missing. To compare an installed build with a source tree, run `run` once with each on
PYTHONPATH.
"""

from __future__ import annotations

import argparse
import sys
import warnings

import numpy as np

STEPS = 40         # Rust solver and filters
SCIPY_STEPS = 12   # trust-constr, least-squares


def learned_model(seed):
    from gpmhe import LearnedModel
    from gpmhe.systems import batch_reactor as br

    data = br.training_data(5, rng=np.random.default_rng(1000 + seed))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return LearnedModel.from_trajectories(*data, n_restarts=1, random_state=seed)


def gp_entries(model, seed, out):
    rng = np.random.default_rng(seed)
    D = rng.uniform(0.1, 4.5, size=(7, 2))
    for name, gp in (("f", model.f_gp), ("h", model.h_gp)):
        out[f"s{seed}/gp_{name}/theta"] = np.asarray(gp.theta)
        out[f"s{seed}/gp_{name}/lml"] = np.atleast_1d(gp.log_marginal_likelihood())
        mean, std = gp.predict(D, return_std=True)
        out[f"s{seed}/gp_{name}/mean"], out[f"s{seed}/gp_{name}/std"] = mean, std
        for i, a in enumerate(gp.predict_with_gradients(D)):
            out[f"s{seed}/gp_{name}/grad{i}"] = a


def run_mhe(mhe, ys, steps):
    xs, Ps, costs = [], [], []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for t in range(steps):
            mhe.update(None, ys[t])
            xs.append(mhe.x.copy())
            Ps.append(mhe.P.copy())
            costs.append(mhe.cost)
    return {"x": np.array(xs), "P": np.array(Ps), "cost": np.array(costs),
            "x_window": mhe.x_window.copy(), "x_arrival": arrival_prior(mhe).copy()}


def arrival_prior(mhe):
    """The last window's arrival prior, under its name in the build that runs (x_prior in
    builds before it was renamed x_arrival), so that builds on either side can be compared."""
    return mhe.x_arrival if hasattr(type(mhe), "x_arrival") else mhe.x_prior


def mhe_entries(model, seed, out):
    from gpmhe import GPMHE, KnownModel
    from gpmhe.systems import batch_reactor as br

    _, y = br.simulate(br.X_TRUE0, STEPS, np.random.default_rng(seed))
    gapped = [None if t % 4 == 2 else y[t] for t in range(STEPS)]
    known = KnownModel(br.f, br.h, 2, 1, f_jacobian=br.f_jacobian, h_jacobian=br.h_jacobian)
    vect = KnownModel(br.f_batch, br.h_batch, 2, 1, f_jacobian=br.f_jacobian_batch,
                      h_jacobian=br.h_jacobian_batch, vectorized=True)
    runs = []
    for form in ("prediction", "filtering"):
        for solver, steps in (("gauss-newton", STEPS), ("trust-constr", SCIPY_STEPS),
                              ("least-squares", SCIPY_STEPS)):
            runs.append((f"gp/{form}/{solver}", model, y, solver, form, steps, {}))
        runs.append((f"gp/{form}/gn-dtol0", model, y, "gauss-newton", form, STEPS, {"dtol": 0}))
        runs.append((f"gp/{form}/gapped", model, gapped, "gauss-newton", form, STEPS, {}))
        runs.append((f"known/{form}", known, y, "gauss-newton", form, STEPS, {}))
        runs.append((f"known-vec/{form}/gapped", vect, gapped, "gauss-newton", form, STEPS, {}))
        runs.append((f"known/{form}/least-squares", known, y, "least-squares", form,
                     SCIPY_STEPS, {}))
    for name, mdl, ys, solver, form, steps, opts in runs:
        horizon = 5 if "gapped" in name else br.MHE_SETTINGS["horizon"]
        settings = dict(br.MHE_SETTINGS, horizon=horizon)
        mhe = GPMHE(mdl, x0=br.X_PRIOR0, x_bounds=br.X_BOUNDS, form=form, solver=solver,
                    solver_options=opts or None, **settings)
        for key, val in run_mhe(mhe, ys, steps).items():
            out[f"s{seed}/mhe/{name}/{key}"] = val


def ekf_entries(model, seed, out):
    from gpmhe.baselines import GPEKF, ExactEKF
    from gpmhe.systems import batch_reactor as br

    _, y = br.simulate(br.X_TRUE0, STEPS, np.random.default_rng(seed))
    Q, R = br.MHE_SETTINGS["Q0"], br.MHE_SETTINGS["R0"]
    for name, ekf in (("gpekf", GPEKF(model, br.X_PRIOR0, np.eye(2), Q, R)),
                      ("ekf", ExactEKF(br.f, br.f_jacobian, br.h, br.h_jacobian, br.X_PRIOR0,
                                        np.eye(2), Q, R))):
        xs = []
        for t in range(STEPS):
            ekf.update(y[t])
            ekf.predict()
            xs.append(np.ravel(ekf.x).copy())
        out[f"s{seed}/{name}/x"] = np.array(xs)


def rgp_entries(seed, out):
    from gpmhe.systems import second_order as so

    run = so.simulate(seed=200 + seed, noise="low", output="y2", duration=3.0)
    ekf, _, xs = so.run_rgp_dkf(run)
    out[f"s{seed}/rgpekf/x"] = xs
    out[f"s{seed}/rgpekf/P"] = ekf.P
    mean, cov = ekf.gp_weights()
    out[f"s{seed}/rgpekf/gp_mean"], out[f"s{seed}/rgpekf/gp_cov"] = mean, cov
    g = so.evaluation_grid(run, m=20)
    m, s = ekf.gp_predict(g, return_std=True)
    out[f"s{seed}/rgpekf/pred_mean"], out[f"s{seed}/rgpekf/pred_std"] = m, s
    gp, _ = so.run_rgp_b(run, sigma_y_gp=0.05)
    out[f"s{seed}/rgp/mean"], out[f"s{seed}/rgp/cov"] = gp.mean, gp.cov
    m, s = gp.predict(g, return_std=True)
    out[f"s{seed}/rgp/pred_mean"], out[f"s{seed}/rgp/pred_std"] = m, s


def run(path, seeds):
    out = {}
    for seed in range(seeds):
        print(f"seed {seed} ...", file=sys.stderr, flush=True)
        model = learned_model(seed)
        gp_entries(model, seed, out)
        mhe_entries(model, seed, out)
        ekf_entries(model, seed, out)
        rgp_entries(seed, out)
    np.savez(path, **out)
    print(f"wrote {len(out)} arrays to {path}")


def diff(path_a, path_b, tol):
    a, b = np.load(path_a), np.load(path_b)
    missing = sorted(set(a.files) ^ set(b.files))
    worst, failed = 0.0, list(missing)
    groups = {}
    for key in sorted(set(a.files) & set(b.files)):
        va, vb = a[key], b[key]
        if va.shape != vb.shape:
            failed.append(key)
            continue
        scale = np.maximum(1.0, np.abs(va))
        d = float(np.max(np.abs(va - vb) / scale, initial=0.0))
        group = key.split("/", 1)[1].rsplit("/", 1)[0]
        groups[group] = max(groups.get(group, 0.0), d)
        worst = max(worst, d)
        if not d <= tol:
            failed.append(key)
    for group, d in sorted(groups.items()):
        print(f"{group:40s} {d:.3e}")
    print(f"{len(a.files)} arrays compared; largest relative difference {worst:.3e} "
          f"(tolerance {tol:.0e})")
    if failed:
        print("FAILED:", ", ".join(failed[:20]))
        return 1
    return 0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("out")
    r.add_argument("--seeds", type=int, default=5)
    d = sub.add_parser("diff")
    d.add_argument("a")
    d.add_argument("b")
    d.add_argument("--tol", type=float, default=1e-12)
    args = ap.parse_args(argv)
    if args.cmd == "run":
        run(args.out, args.seeds)
        return 0
    return diff(args.a, args.b, args.tol)


if __name__ == "__main__":
    sys.exit(main())
