"""The second-order example of the RGP-dKF paper (§4), its scenarios S1–S3 and the RGP-B baseline.

Plant (eq. 21, 22): ẋ = [[0, 1], [−4, −4]] x + [0, 1]ᵀ u + [0, 1]ᵀ z, with the hidden disturbance
z(ζ) = −10 (1 + 0.1 ζ + ζ³), discretised by explicit Euler:

    x_{k+1} = A_d x_k + b_d (u_k + z(ζ_k)),  A_d = I + T A_c,  b_d = T [0, 1]ᵀ,

outputs y₁ = x₁ or y₂ = x plus white Gaussian noise. The paper does not give the sampling time,
the noise levels, the ζ filter or the step input; gpmhe fixes them here (and the benchmark prints
them):

* sampling time T = 0.01 s; 100 s of data (10 000 steps) per run;
* ζ: first-order low-pass filtered Gaussian white noise, ζ_{k+1} = a ζ_k + √(1 − a²) σ_ζ w_k,
  a = exp(−T/τ_ζ), τ_ζ = 0.5 s, stationary std σ_ζ = 0.6, ζ_0 ~ N(0, σ_ζ²);
* u: steps every 2 s to a level drawn uniformly from [−10, 10];
* measurement noise std: "low" 0.01, "high" 0.1 (on every measured output);
* x_0 = 0, known to the filter (x̂_0 = 0, P_0 = 1e-4 I); no process noise in the plant.

The RGP (both estimators): ζ-grid on [−2, 2] with 25 basis vectors, σ_K = 30, L = 4 (length-scale
2 grid steps = 1/3 in ζ), σ_r = 0.3 (= 0.01 σ_K, the lower end of the paper's rule of thumb),
σ_p = 0 (as in the paper). The RGP-dKF uses Q_x = 1e-8 I and R_x = σ_v² I.

RGP-B (paper §4.1), only when both states are measured: the disturbance "measurement"
y_GP,k = e⁺ (y_{k+1} − A_d y_k − b_d u_k) with e = b_d (e⁺ = (eᵀe)⁻¹eᵀ) is fed to a plain
:class:`~gpmhe.RecursiveGP`; its noise σ_y,GP is a design parameter tuned per scenario.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gpmhe.rgp import RGPEKF, RecursiveGP

T = 0.01
DURATION = 100.0
A_C = np.array([[0.0, 1.0], [-4.0, -4.0]])
A_D = np.eye(2) + T * A_C
B_D = T * np.array([0.0, 1.0])
E_D = B_D
TAU_ZETA = 0.5
SIGMA_ZETA = 0.6
U_STEP_PERIOD = 2.0
U_RANGE = 10.0
NOISE = {"low": 0.01, "high": 0.1}
X0 = np.zeros(2)
P0 = 1e-4 * np.eye(2)
Q_X = 1e-8 * np.eye(2)

# RGP hyperparameters shared by RGP-dKF and RGP-B.
ZETA_BOUNDS = (-2.0, 2.0)
N_BASIS = 25
SIGMA_K = 30.0
L_GRID = 4.0
SIGMA_R = 0.3
SIGMA_P = 0.0

#: name -> (noise level, measured output): S1 high noise y₂, S2 low noise y₂, S3 low noise y₁.
SCENARIOS = {"S1": ("high", "y2"), "S2": ("low", "y2"), "S3": ("low", "y1")}


def disturbance(zeta: np.ndarray | float) -> np.ndarray:
    """The hidden function z(ζ) = −10 (1 + 0.1 ζ + ζ³)."""
    z = np.asarray(zeta, dtype=float)
    return -10.0 * (1.0 + 0.1 * z + z**3)


def output_matrix(output: str) -> np.ndarray:
    """C of y₁ = x₁ ("y1") or y₂ = x ("y2")."""
    if output == "y1":
        return np.array([[1.0, 0.0]])
    if output == "y2":
        return np.eye(2)
    raise ValueError(f"output: expected 'y1' or 'y2', got {output!r}")


@dataclass
class Run:
    """One simulated run: u[k], ζ[k], z[k] = z(ζ[k]) act from step k to k+1; x[k] is the state at
    step k (k = 0..steps) and y[k] = C x[k] + v[k] (y[0] unused by the estimators)."""

    u: np.ndarray
    zeta: np.ndarray
    z: np.ndarray
    x: np.ndarray
    y: np.ndarray
    C: np.ndarray
    noise_std: float
    info: dict = field(default_factory=dict)


def simulate(seed: int, noise: str = "low", output: str = "y2", duration: float = DURATION) -> Run:
    """Simulate the plant for ``duration`` seconds with the fixed settings above."""
    if noise not in NOISE:
        raise ValueError(f"noise: expected one of {list(NOISE)}, got {noise!r}")
    C = output_matrix(output)
    rng = np.random.default_rng(seed)
    steps = int(round(duration / T))
    a = np.exp(-T / TAU_ZETA)
    w = rng.standard_normal(steps)
    zeta = np.empty(steps)
    zeta[0] = SIGMA_ZETA * rng.standard_normal()
    g = np.sqrt(1.0 - a * a) * SIGMA_ZETA
    for k in range(1, steps):
        zeta[k] = a * zeta[k - 1] + g * w[k]
    per = int(round(U_STEP_PERIOD / T))
    levels = rng.uniform(-U_RANGE, U_RANGE, size=steps // per + 1)
    u = np.repeat(levels, per)[:steps]
    z = disturbance(zeta)
    x = np.empty((steps + 1, 2))
    x[0] = X0
    for k in range(steps):
        x[k + 1] = A_D @ x[k] + B_D * (u[k] + z[k])
    sd = NOISE[noise]
    y = x @ C.T + sd * rng.standard_normal((steps + 1, C.shape[0]))
    return Run(u, zeta, z, x, y, C, sd, {"seed": seed, "noise": noise, "output": output})


def make_gp() -> RecursiveGP:
    """A fresh RGP with the shared hyperparameters."""
    return RecursiveGP(
        ZETA_BOUNDS[0], ZETA_BOUNDS[1], N_BASIS, sigma_K=SIGMA_K, L=L_GRID,
        sigma_r=SIGMA_R, sigma_p=SIGMA_P,
    )


def f(x: np.ndarray, u: float, z: float) -> np.ndarray:
    """Euler transition x⁺ = A_d x + b_d (u + z)."""
    return A_D @ x + B_D * (u + z)


def make_rgp_dkf(run: Run, gp: RecursiveGP | None = None) -> RGPEKF:
    """The RGP-dKF for a run (A, e, H constant: the plant is linear in x and z)."""
    C = run.C
    return RGPEKF(
        dim_x=2, f=f, A=A_D, e=E_D, h=lambda x: C @ x, H=C, Q_x=Q_X,
        R_x=run.noise_std**2 * np.eye(C.shape[0]), x0=X0, P0=P0,
        gps=make_gp() if gp is None else gp,
    )


def run_rgp_dkf(run: Run, snapshots: tuple[int, ...] = ()) -> tuple[RGPEKF, dict[int, RGPEKF], np.ndarray]:
    """Filter a run with the RGP-dKF: predict(u_k, ζ_k), update(y_{k+1}). Returns the filter, the GP
    weights (mean, cov) after the requested numbers of steps, and the estimates x̂[k], k = 0..steps."""
    ekf = make_rgp_dkf(run)
    steps = len(run.u)
    xs = np.empty((steps + 1, 2))
    xs[0] = ekf.x
    snaps: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    want = set(snapshots)
    for k in range(steps):
        ekf.predict(run.u[k], run.zeta[k])
        ekf.update(run.y[k + 1])
        xs[k + 1] = ekf.x
        if k + 1 in want:
            snaps[k + 1] = ekf.gp_weights(0)
    return ekf, snaps, xs


def rgp_b_targets(run: Run) -> np.ndarray:
    """RGP-B's disturbance "measurements" y_GP,k = e⁺ (y_{k+1} − A_d y_k − b_d u_k), k = 0..steps−1."""
    if run.C.shape[0] != 2:
        raise ValueError("RGP-B needs both states measured (output 'y2')")
    pinv = E_D / (E_D @ E_D)
    resid = run.y[1:] - run.y[:-1] @ A_D.T - np.outer(run.u, B_D)
    return resid @ pinv


def run_rgp_b(run: Run, sigma_y_gp: float, snapshots: tuple[int, ...] = ()) -> tuple[RecursiveGP, dict]:
    """RGP-B: a plain RecursiveGP fed with rgp_b_targets at ζ_k with noise std ``sigma_y_gp``."""
    gp = make_gp()
    targets = rgp_b_targets(run)
    var = float(sigma_y_gp) ** 2
    snaps = {}
    start = 0
    for stop in sorted(s for s in set(snapshots) if 0 < s <= len(targets)) + [len(targets)]:
        if stop > start:
            gp.update(run.zeta[start:stop], targets[start:stop], var)
        snaps[stop] = (gp.mean.copy(), gp.cov.copy())
        start = stop
    return gp, snaps


def evaluation_grid(run: Run, m: int = 200) -> np.ndarray:
    """m points spanning the visited ζ range (its 1 % to 99 % quantiles) of a run."""
    lo, hi = np.quantile(run.zeta, [0.01, 0.99])
    return np.linspace(lo, hi, m)


def rmse_nll(mean: np.ndarray, std: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """RMSE of the mean and the average negative log predictive density of the truth."""
    err = truth - mean
    var = std**2
    return float(np.sqrt(np.mean(err**2))), float(np.mean(0.5 * np.log(2 * np.pi * var) + 0.5 * err**2 / var))
