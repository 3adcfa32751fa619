"""Benchmark of gpmhe's GP numerics against scikit-learn and a plain numpy/SciPy implementation.

Prints two tables (median and p95 time per call, ratios against gpmhe measured in the same run):

1. posterior mean + latent variance + both input gradients for k = 1, 16, 256 test points with
   N = 150, 1000, 5000 training points (n_d = 2): gpmhe ``GaussianProcess.predict_with_gradients``
   vs scikit-learn ``predict(return_std=True)`` (mean and std only, no gradients) vs numpy/SciPy
   (BLAS triangular solves, the same quantities as gpmhe);
2. log marginal likelihood + gradient w.r.t. theta at N = 150 and 1000.

All three run single-threaded by default (gpmhe's core is sequential; BLAS is limited to one thread
with threadpoolctl) so the ratios compare algorithms, not core counts; ``--blas-threads`` changes
that. Targets: one test point at N = 150 at least 20x faster than scikit-learn's
predict(return_std=True); N = 5000 with 256 test points within 2x of numpy/SciPy or faster.

    python benches/bench_gp.py            # full run (a few minutes, mostly N = 5000 set-up)
    python benches/bench_gp.py --quick    # N <= 1000 only, fewer repetitions
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np
import scipy.linalg as sla
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel
from threadpoolctl import threadpool_limits

import gpmhe
from gpmhe import GaussianProcess, _core

ND = 2
SIGMA_F, LENGTHSCALES, SIGMA_EPS = 1.3, np.array([0.8, 1.4]), 0.1


def data(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    D = rng.uniform(-2.0, 2.0, (n, ND))
    y = np.sin(2.0 * D[:, 0]) + np.cos(D[:, 1]) + SIGMA_EPS * rng.normal(size=n)
    return D, y, rng


def timeit(fn, min_sample_s: float, n_samples: int):
    """Median and p95 of the per-call time over n_samples samples; each sample runs fn enough
    times to last about min_sample_s."""
    fn()  # warm-up
    t0 = time.perf_counter()
    fn()
    once = max(time.perf_counter() - t0, 1e-7)
    reps = max(1, int(min_sample_s / once))
    samples = []
    for _ in range(n_samples):
        t0 = time.perf_counter()
        for _ in range(reps):
            fn()
        samples.append((time.perf_counter() - t0) / reps)
    return float(np.median(samples)), float(np.percentile(samples, 95))


# ----------------------------------------------------------------------------- numpy/SciPy reference


def np_kernel(A, B):
    a, b = A / LENGTHSCALES, B / LENGTHSCALES
    sq = (a**2).sum(1)[:, None] + (b**2).sum(1)[None, :] - 2.0 * a @ b.T
    return SIGMA_F**2 * np.exp(-0.5 * np.maximum(sq, 0.0))


def np_predict_with_gradients(D, L, alpha, Dt):
    """Mean, latent variance and input gradients with BLAS triangular solves."""
    Ks = np_kernel(Dt, D)  # (k, N)
    mean = Ks @ alpha
    V = sla.solve_triangular(L, Ks.T, lower=True, check_finite=False)
    var = np.maximum(SIGMA_F**2 - (V**2).sum(0), 0.0)
    B = sla.solve_triangular(L, V, lower=True, trans="T", check_finite=False).T  # (k, N)
    w = 1.0 / LENGTHSCALES**2
    Ka = Ks * alpha
    dmean = -w * (Dt * Ka.sum(1)[:, None] - Ka @ D)
    KB = Ks * B
    dvar = 2.0 * w * (Dt * KB.sum(1)[:, None] - KB @ D)
    return mean, var, dmean, dvar


def np_lml_and_grad(D, y, theta):
    sf, ls, se = np.exp(theta[0]), np.exp(theta[1:-1]), np.exp(theta[-1])
    a = D / ls
    sq = np.maximum((a**2).sum(1)[:, None] + (a**2).sum(1)[None, :] - 2.0 * a @ a.T, 0.0)
    Kf = sf**2 * np.exp(-0.5 * sq)
    K = Kf + se**2 * np.eye(len(y))
    L = sla.cholesky(K, lower=True, check_finite=False)
    alpha = sla.cho_solve((L, True), y, check_finite=False)
    lml = -0.5 * y @ alpha - np.log(np.diag(L)).sum() - 0.5 * len(y) * np.log(2 * np.pi)
    W = np.outer(alpha, alpha) - sla.cho_solve((L, True), np.eye(len(y)), check_finite=False)
    WK = W * Kf
    grad = [WK.sum()]
    for l in range(D.shape[1]):
        diff = (D[:, l][:, None] - D[:, l][None, :]) / ls[l]
        grad.append(0.5 * (WK * diff**2).sum())
    grad.append(se**2 * np.trace(W))
    return lml, np.array(grad)


# ----------------------------------------------------------------------------- benchmarks


def sklearn_model():
    k = ConstantKernel(SIGMA_F**2) * RBF(LENGTHSCALES) + WhiteKernel(SIGMA_EPS**2)
    return GaussianProcessRegressor(k, alpha=0.0, optimizer=None)


def fmt(t):
    return f"{t * 1e6:10.1f}" if t < 1e-2 else f"{t * 1e6:10.0f}"


def bench_predict(ns, ks, min_sample_s, n_samples):
    print("\n## Posterior mean + latent variance + input gradients (times in microseconds per call)")
    print(f"n_d = {ND}; sklearn computes mean and std only (it has no input gradients).")
    print("gpmhe = predict_with_gradients (mean, var, both gradients); gpmhe std = predict(return_std=True),")
    print("the same quantities as sklearn's predict(return_std=True). Ratios > 1: gpmhe is faster.")
    head = (
        f"{'N':>5} {'k':>4} | {'gpmhe med':>10} {'p95':>10} | {'gpmhe std':>10} |"
        f" {'sklearn med':>11} {'p95':>10} | {'numpy med':>10} {'p95':>10} |"
        f" {'sklearn/gpmhe':>13} {'sklearn/gpmhe std':>17} {'numpy/gpmhe':>11} | max|diff|"
    )
    print(head)
    print("-" * len(head))
    results = {}
    for n in ns:
        D, y, rng = data(n)
        gp = GaussianProcess(SIGMA_F, LENGTHSCALES, SIGMA_EPS, optimizer=None).fit(D, y)
        sk = sklearn_model().fit(D, y)
        for k in ks:
            Dt = rng.uniform(-2.0, 2.0, (k, ND))
            ours = gp.predict_with_gradients(Dt)
            ref = np_predict_with_gradients(D, sk.L_, sk.alpha_, Dt)
            diff = max(float(np.max(np.abs(a - b)) / max(1.0, np.max(np.abs(b)))) for a, b in zip(ours, ref))
            t_g = timeit(lambda: gp.predict_with_gradients(Dt), min_sample_s, n_samples)
            t_p = timeit(lambda: gp.predict(Dt, return_std=True), min_sample_s, n_samples)
            t_s = timeit(lambda: sk.predict(Dt, return_std=True), min_sample_s, n_samples)
            t_n = timeit(lambda: np_predict_with_gradients(D, sk.L_, sk.alpha_, Dt), min_sample_s, n_samples)
            results[(n, k)] = (t_g[0], t_s[0], t_n[0], t_p[0])
            print(
                f"{n:>5} {k:>4} | {fmt(t_g[0])} {fmt(t_g[1])} | {fmt(t_p[0])} |"
                f" {fmt(t_s[0]):>11} {fmt(t_s[1])} | {fmt(t_n[0])} {fmt(t_n[1])} |"
                f" {t_s[0] / t_g[0]:13.1f} {t_s[0] / t_p[0]:17.1f} {t_n[0] / t_g[0]:11.2f} | {diff:.1e}"
            )
    return results


def bench_lml(ns, min_sample_s, n_samples):
    print("\n## Log marginal likelihood + gradient w.r.t. theta (times in microseconds per call)")
    head = (
        f"{'N':>5} | {'gpmhe med':>10} {'p95':>10} | {'sklearn med':>11} {'p95':>10} |"
        f" {'numpy med':>10} {'p95':>10} | {'sklearn/gpmhe':>13} {'numpy/gpmhe':>11} | max|diff|"
    )
    print(head)
    print("-" * len(head))
    for n in ns:
        D, y, _ = data(n, seed=1)
        theta = np.log(np.concatenate([[SIGMA_F], LENGTHSCALES, [SIGMA_EPS]]))
        sk_theta = np.concatenate([[2 * theta[0]], theta[1:-1], [2 * theta[-1]]])
        sk = sklearn_model().fit(D, y)
        l1, g1 = _core.log_marginal_likelihood(D, y, theta, True)
        l2, g2 = np_lml_and_grad(D, y, theta)
        diff = max(abs(l1 - l2) / abs(l2), float(np.max(np.abs(g1 - g2)) / np.max(np.abs(g2))))
        t_g = timeit(lambda: _core.log_marginal_likelihood(D, y, theta, True), min_sample_s, n_samples)
        t_s = timeit(lambda: sk.log_marginal_likelihood(sk_theta, eval_gradient=True), min_sample_s, n_samples)
        t_n = timeit(lambda: np_lml_and_grad(D, y, theta), min_sample_s, n_samples)
        print(
            f"{n:>5} | {fmt(t_g[0])} {fmt(t_g[1])} | {fmt(t_s[0]):>11} {fmt(t_s[1])} |"
            f" {fmt(t_n[0])} {fmt(t_n[1])} | {t_s[0] / t_g[0]:13.1f} {t_n[0] / t_g[0]:11.2f} | {diff:.1e}"
        )


def bench_window(min_sample_s, n_samples):
    """The GP-MHE use: q = 3 outputs (2 f-GPs, 1 h-GP), 16 window points, N = 150."""
    from gpmhe import MultiOutputGP

    D, y, rng = data(150, seed=2)
    Y = np.column_stack([y, np.sin(D[:, 1]), D.sum(axis=1)])
    mgp = MultiOutputGP(SIGMA_F, LENGTHSCALES, SIGMA_EPS, optimizer=None).fit(D, Y)
    sks = [sklearn_model().fit(D, Y[:, o]) for o in range(3)]
    Dt = rng.uniform(-2.0, 2.0, (16, ND))
    core = mgp._core_model
    t_api = timeit(lambda: mgp.predict_with_gradients(Dt), min_sample_s, n_samples)
    t_core = timeit(lambda: core.predict_with_gradients(Dt), min_sample_s, n_samples)
    t_sk = timeit(lambda: [s.predict(Dt, return_std=True) for s in sks], min_sample_s, n_samples)
    print("\n## One GP-MHE window evaluation: q = 3 outputs, 16 points, N = 150 (microseconds per call)")
    print(f"MultiOutputGP.predict_with_gradients   median {fmt(t_api[0])}  p95 {fmt(t_api[1])}")
    print(f"_core.MultiGP.predict_with_gradients   median {fmt(t_core[0])}  p95 {fmt(t_core[1])}")
    print(f"3 x sklearn predict(return_std=True)   median {fmt(t_sk[0])}  p95 {fmt(t_sk[1])}"
          f"  ratio {t_sk[0] / t_api[0]:.1f}")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="N <= 1000, fewer repetitions")
    ap.add_argument("--blas-threads", type=int, default=1, help="BLAS threads for sklearn/numpy (default 1)")
    args = ap.parse_args()
    ns = [150, 1000] if args.quick else [150, 1000, 5000]
    min_sample_s, n_samples = (0.02, 7) if args.quick else (0.05, 15)
    print(f"gpmhe {gpmhe.__version__}, numpy {np.__version__}, Python {platform.python_version()}, "
          f"{platform.machine()}, BLAS threads = {args.blas_threads}")
    with threadpool_limits(limits=args.blas_threads):
        res = bench_predict(ns, [1, 16, 256], min_sample_s, n_samples)
        bench_lml([150, 1000], min_sample_s, n_samples)
        bench_window(min_sample_s, n_samples)
    print("\n## Goals")
    g, s, _, p = res[(150, 1)]
    print("1 point, N = 150 (goal >= 20x faster than sklearn predict(return_std=True)):")
    print(f"  gpmhe predict(return_std=True) is {s / p:.1f}x faster;"
          f" predict_with_gradients (also both gradients) is {s / g:.1f}x faster")
    if (5000, 256) in res:
        g, _, nmp, _ = res[(5000, 256)]
        print(f"256 points, N = 5000: gpmhe time / numpy-SciPy time = {g / nmp:.2f} (goal <= 2)")


if __name__ == "__main__":
    main()
