"""Benchmark: stability certificates of the batch reactor's models (the table of the user-guide
page "Stability guarantee").

    python benches/stability.py

For the exact model and the GP models learned from 5 and 3 training trajectories (the paper's
initial states, data seed 100, one hyperparameter restart), certify Assumption 1 of the GP-MHE
paper on X = [0.1, 4.5]² with Q0 = 1e-3 I, R0 = 1e-2, once with the guaranteed bound on the
posterior variance over the box ("posterior") and once with the paper's σ_f² + σ_ε² ("prior").
Prints Q_min⁻¹, R_min⁻¹, η, the minimal horizon M̄, the eigenvalues of P and the time per
certificate. Needs the theory extra (cvxpy, Clarabel).
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from gpmhe import KnownModel, LearnedModel
from gpmhe.systems import batch_reactor as br
from gpmhe.theory import certify_ioss

Q0, R0 = 1e-3 * np.eye(2), 1e-2 * np.eye(1)


def models():
    exact = KnownModel(br.f_batch, br.h_batch, 2, 1, f_jacobian=br.f_jacobian_batch,
                       h_jacobian=br.h_jacobian_batch, vectorized=True)
    out = {"exact": (exact, dict(jacobian_curvature=0.0), ["—"])}
    for n_traj in (5, 3):
        states, outputs = br.training_data(n_traj, rng=100)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            gp = LearnedModel.from_trajectories(states, outputs, n_restarts=1, random_state=0, **br.PAPER_GP)
        out[f"GP, {n_traj} trajectories"] = (gp, {}, ["posterior", "prior"])
    return out


def main() -> int:
    print("| model | variance bound | Q_min^-1 | R_min^-1 | eta | M_bar | eig(P) | seconds |")
    print("|---|---|---|---|---|---|---|---|")
    for name, (model, extra, bounds) in models().items():
        for bound in bounds:
            kw = dict(extra) if bound == "—" else dict(extra, variance_bound=bound)
            t0 = time.perf_counter()
            cert = certify_ioss(model, br.X_BOUNDS, Q0, R0, **kw)
            secs = time.perf_counter() - t0
            if not cert.feasible:
                print(f"| {name} | {bound} | no certificate: {cert.reason} | | | | | {secs:.1f} |")
                continue
            q = ", ".join(f"{v:.4g}" for v in np.diag(cert.Q_inv))
            eig = ", ".join(f"{v:.3g}" for v in np.linalg.eigvalsh(cert.P))
            print(f"| {name} | {bound} | diag({q}) | {cert.R_inv.item():.4g} | {cert.eta:.4f} "
                  f"| {cert.min_horizon()} | {eig} | {secs:.1f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
