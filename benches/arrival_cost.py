"""The arrival cost on three plants: the paper's (the estimator's own estimate of x(t − M), P2
constant), the smoothed mean (the previous window's estimate of the new first node), the
filtered mean (the leaving node's prior updated with its output and carried over its stage at
the window's solution) and the EKF update of the arrival weight, in the six combinations.

Plants: the batch reactor of the GP-MHE paper (exact model, its setting), the cart-pole with
nearly deterministic dynamics and full-state noisy measurements (`gpmhe.systems.cart_pole`, its
`MHE_SETTINGS`), and the rotating masses with the inertia Θ1 estimated as a parameter
(`gpmhe.systems.rotating_masses`, do-mpc's setting). Prints, per plant and arrival cost, the RMSE
of the estimates over the second half of each run (mean over seeds), the runs that diverged
(RMSE > 10× the best) and the median window evaluations per update.

    python benches/arrival_cost.py [--seeds 5]
"""

import argparse
import warnings

import numpy as np

from gpmhe import GPMHE, KnownModel
from gpmhe.systems import batch_reactor as br
from gpmhe.systems import cart_pole as cp
from gpmhe.systems import rotating_masses as rm

COMBOS = [("estimate", "constant"), ("smoothed", "constant"), ("filtered", "constant"),
          ("estimate", "ekf"), ("smoothed", "ekf"), ("filtered", "ekf")]


def reactor(seed, mean, weight):
    model = KnownModel(br.f_batch, br.h_batch, dim_x=2, dim_y=1, vectorized=True,
                       f_jacobian=br.f_jacobian_batch, h_jacobian=br.h_jacobian_batch)
    x, y = br.simulate(br.X_TRUE0, 60, np.random.default_rng(seed))
    est = GPMHE(model, x0=br.X_PRIOR0, x_bounds=br.X_BOUNDS,
                **{**br.MHE_SETTINGS, "arrival_mean": mean, "arrival_weight": weight})
    xs, nfev = [], []
    for t in range(60):
        xs.append(est.update(None, y[t]).copy())
        nfev.append(est.nfev)
    return np.array(xs)[30:] - x[31:61], nfev


def cart_pole(seed, mean, weight):
    rng = np.random.default_rng(seed)
    steps = 200
    x, u, y = cp.simulate(steps, rng)
    est = GPMHE(cp.known_model("casadi"), x0=y[0], arrival_mean=mean, arrival_weight=weight,
                **cp.MHE_SETTINGS)
    xs, nfev = [], []
    for t in range(steps):
        xs.append(est.update(u[t], y[t]).copy())
        nfev.append(est.nfev)
    return np.array(xs)[steps // 2:] - x[steps // 2 + 1:steps + 1], nfev


def rotating_masses(seed, mean, weight):
    rng = np.random.default_rng(seed)
    x, u, y = rm.simulate(rm.STEPS, rng)
    x0 = rm.initial_estimate(rng)
    est = GPMHE(rm.known_model(theta1=None), x0=x0, **rm.PARAMETER_SETTINGS,
                **{**rm.MHE_SETTINGS, "arrival_mean": mean, "arrival_weight": weight})
    xs, nfev = [], []
    for t in range(rm.STEPS):
        xs.append(est.update(u[t], y[t]).copy())
        nfev.append(est.nfev)
    return np.array(xs)[rm.STEPS // 2:] - x[rm.STEPS // 2 + 1:rm.STEPS + 1], nfev


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    args = ap.parse_args()
    print(f"{'plant':<16}{'arrival mean':<14}{'weight':<10}{'RMSE':>9}{'diverged':>10}"
          f"{'nfev med':>10}{'warnings':>10}")
    for name, run in (("batch reactor", reactor), ("cart-pole", cart_pole),
                      ("rotating masses", rotating_masses)):
        results = {}
        for mean, weight in COMBOS:
            rmses, nfevs, warned = [], [], 0
            for seed in range(args.seeds):
                with warnings.catch_warnings(record=True) as w:
                    warnings.simplefilter("always")
                    err, nfev = run(seed, mean, weight)
                warned += len(w)
                rmses.append(float(np.sqrt(np.mean(err ** 2))))
                nfevs += nfev
            results[mean, weight] = (rmses, nfevs, warned)
        best = min(np.median(r[0]) for r in results.values())
        for (mean, weight), (rmses, nfevs, warned) in results.items():
            diverged = sum(r > 10 * best for r in rmses)
            print(f"{name:<16}{mean:<14}{weight:<10}{np.mean(rmses):9.4f}{diverged:>7}/{len(rmses):<2}"
                  f"{np.median(nfevs):10.0f}{warned:10d}")


if __name__ == "__main__":
    main()
