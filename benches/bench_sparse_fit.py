"""Benchmark: gpmhe's sparse-GP fit against GPyTorch's SGPR from the same inducing points.

    python benches/bench_sparse_fit.py [--seeds 20] [--n 500] [--m 20] [--iters 1000]

Needs ``torch`` and ``gpytorch`` (not dependencies of gpmhe; any CPU build will do). One table,
one run. Per seed (generator ``seed``): N inputs uniform in [-2, 2]^2, targets
f(d) = sin(2 d_1) + d_1 cos(1.5 d_2) / 2 plus noise of standard deviation 0.1, m of the training
inputs drawn at random as inducing points, and 2,000 test inputs. Both fits maximise the same
objective, Titsias' collapsed VFE bound with the SE-ARD kernel and a zero mean, from the same
start (sigma_f = 1, lengthscales 1, sigma_eps = 0.1) and the same points:

- gpmhe: ``SparseGaussianProcess(method="vfe", inducing=Z)`` (L-BFGS-B on the analytic
  gradient), and with ``optimize_inducing=True`` (the points move too);
- GPyTorch: ``InducingPointKernel`` on a ``ScaleKernel(RBFKernel(ard_num_dims=2))`` in float64,
  trained as its SGPR tutorial does (Adam, learning rate 0.05, ``--iters`` steps on
  ``ExactMarginalLogLikelihood``), with the points frozen or trained alike.

Columns: the bound each fit reached, both evaluated by gpmhe's core at the fitted (theta, Z) (the
objective is checked to be GPyTorch's own: the largest difference between GPyTorch's
``ExactMarginalLogLikelihood`` times N and gpmhe's bound at the same parameters is printed),
the mean over seeds and the number of seeds where gpmhe's bound is at least GPyTorch's - 0.01;
the test RMSE against the noise-free f (mean and standard deviation over seeds); the median fit time.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from gpmhe import SparseGaussianProcess, _core

try:
    import gpytorch
    import torch
except ImportError as exc:  # pragma: no cover - the benchmark's own requirement
    raise SystemExit(f"this benchmark needs torch and gpytorch ({exc})")

START = dict(sigma_f=1.0, lengthscales=1.0, sigma_eps=0.1)


def data(seed, n, m):
    """Training inputs and targets, the inducing points and the test set of one seed."""
    rng = np.random.default_rng(seed)

    def f(d):
        return np.sin(2.0 * d[:, 0]) + 0.5 * d[:, 0] * np.cos(1.5 * d[:, 1])

    D = rng.uniform(-2.0, 2.0, (n, 2))
    y = f(D) + 0.1 * rng.standard_normal(n)
    Z = D[rng.choice(n, m, replace=False)]
    D_test = rng.uniform(-2.0, 2.0, (2000, 2))
    return D, y, Z, D_test, f(D_test)


def bound(D, y, Z, theta):
    """The VFE bound at (theta, Z) by gpmhe's core."""
    value, _, _ = _core.sparse_objective(D, y, np.ascontiguousarray(Z), np.ascontiguousarray(theta), "vfe", False)
    return float(value)


def vfe_mean(D, y, Z, theta, D_test):
    """The VFE predictive mean at D_test from (theta, Z): a dense numpy formula shared by both
    rows, so that the RMSE compares the fitted parameters, not the prediction code."""
    sf2, ell, s2 = np.exp(2 * theta[0]), np.exp(theta[1:-1]), np.exp(2 * theta[-1])

    def k(A, B):
        d = (A[:, None, :] - B[None, :, :]) / ell
        return sf2 * np.exp(-0.5 * np.sum(d * d, axis=2))

    Kuu, Kuf = k(Z, Z) + 1e-8 * sf2 * np.eye(len(Z)), k(Z, D)
    A = s2 * Kuu + Kuf @ Kuf.T
    return k(D_test, Z) @ np.linalg.solve(A, Kuf @ y)


class SGPR(gpytorch.models.ExactGP):
    """GPyTorch's SGPR, as its tutorial builds it."""

    def __init__(self, D, y, Z, likelihood):
        super().__init__(D, y, likelihood)
        self.mean_module = gpytorch.means.ZeroMean()
        base = gpytorch.kernels.ScaleKernel(gpytorch.kernels.RBFKernel(ard_num_dims=D.shape[1]))
        self.covar_module = gpytorch.kernels.InducingPointKernel(base, inducing_points=Z.clone(), likelihood=likelihood)

    def forward(self, x):
        return gpytorch.distributions.MultivariateNormal(self.mean_module(x), self.covar_module(x))


def sgpr(D, y, Z, iters, train_points, theta_at=None):
    """Fit GPyTorch's SGPR; returns (theta, Z, seconds). With ``theta_at`` no training: the
    model's ExactMarginalLogLikelihood times N at that theta instead of seconds."""
    Dt, yt = torch.tensor(D), torch.tensor(y)
    likelihood = gpytorch.likelihoods.GaussianLikelihood(noise_constraint=gpytorch.constraints.GreaterThan(1e-8))
    model = SGPR(Dt, yt, torch.tensor(Z), likelihood).double()
    likelihood.double()
    t = START if theta_at is None else None
    sf, ell, se = ((t["sigma_f"], [t["lengthscales"]] * D.shape[1], t["sigma_eps"]) if t else
                   (np.exp(theta_at[0]), np.exp(theta_at[1:-1]), np.exp(theta_at[-1])))
    model.covar_module.base_kernel.outputscale = sf**2
    model.covar_module.base_kernel.base_kernel.lengthscale = torch.tensor(ell)
    likelihood.noise = se**2
    model.covar_module.inducing_points.requires_grad_(train_points)
    mll = gpytorch.mlls.ExactMarginalLogLikelihood(likelihood, model)
    model.train()
    likelihood.train()
    if theta_at is not None:
        with gpytorch.settings.max_cholesky_size(10**6):
            return float(mll(model(Dt), yt)) * len(y)
    optimizer = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=0.05)
    start = time.perf_counter()
    with gpytorch.settings.max_cholesky_size(10**6):
        for _ in range(iters):
            optimizer.zero_grad()
            loss = -mll(model(Dt), yt)
            loss.backward()
            optimizer.step()
    seconds = time.perf_counter() - start
    k = model.covar_module.base_kernel
    theta = np.concatenate([
        [0.5 * np.log(float(k.outputscale))],
        np.log(k.base_kernel.lengthscale.detach().numpy().ravel()),
        [0.5 * np.log(float(likelihood.noise))],
    ])
    return theta, model.covar_module.inducing_points.detach().numpy().copy(), seconds


def gpmhe_fit(D, y, Z, train_points):
    """Fit gpmhe's sparse GP; returns (theta, Z, seconds)."""
    gp = SparseGaussianProcess(n_inducing=len(Z), method="vfe", inducing=Z, optimize_inducing=train_points, **START)
    start = time.perf_counter()
    gp.fit(D, y)
    return gp.theta, np.asarray(gp.inducing_points), time.perf_counter() - start


def row(label, fits, seeds):
    """One line of the table from per-seed (bound, rmse, seconds)."""
    b, r, s = (np.array(v) for v in zip(*fits))
    return f"{label:<36} {b.mean():>10.2f} {r.mean():>8.4f} ± {r.std():.4f} {np.median(s) * 1e3:>10.1f}"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--n", type=int, default=500)
    ap.add_argument("--m", type=int, default=20)
    ap.add_argument("--iters", type=int, default=1000)
    args = ap.parse_args()
    torch.set_num_threads(1)
    print(f"N = {args.n}, m = {args.m}, {args.seeds} seeds; torch {torch.__version__}, gpytorch {gpytorch.__version__}")
    print(f"{'fit':<36} {'bound':>10} {'test RMSE':>17} {'fit ms':>10}")
    for train_points in (False, True):
        rows = {"gpmhe": [], "gpytorch": []}
        wins, agree = 0, 0.0
        for seed in range(args.seeds):
            D, y, Z, D_test, f_test = data(seed, args.n, args.m)
            per = {}
            for name, fit in (("gpmhe", gpmhe_fit), ("gpytorch", lambda *a: sgpr(*a[:3], args.iters, a[3]))):
                theta, Zf, seconds = fit(D, y, Z, train_points)
                rmse = float(np.sqrt(np.mean((vfe_mean(D, y, Zf, theta, D_test) - f_test) ** 2)))
                per[name] = (bound(D, y, Zf, theta), rmse, seconds, theta, Zf)
                rows[name].append(per[name][:3])
            wins += per["gpmhe"][0] >= per["gpytorch"][0] - 0.01
            theta, Zf = per["gpmhe"][3:]
            agree = max(agree, abs(sgpr(D, y, Zf, 0, False, theta_at=theta) - per["gpmhe"][0]))
        points = "points trained" if train_points else "points fixed"
        print(row(f"gpmhe VFE, {points}", rows["gpmhe"], args.seeds))
        print(row(f"GPyTorch SGPR (Adam), {points}", rows["gpytorch"], args.seeds))
        print(f"  gpmhe's bound >= GPyTorch's - 0.01 on {wins}/{args.seeds} seeds; "
              f"GPyTorch's objective - gpmhe's at gpmhe's optimum: max |difference| {agree:.2e}")


if __name__ == "__main__":
    main()
