"""The second-order example of the RGP-dKF paper (§4), its scenarios S1–S3 and the RGP-B baseline.

See the user guide, *Example systems* and *The RGP-dKF*.

Plant (eq. 21, 22): ẋ = [[0, 1], [−4, −4]] x + [0, 1]ᵀ u + [0, 1]ᵀ z, with the hidden disturbance
z(ζ) = −10 (1 + 0.1 ζ + ζ³), discretised by explicit Euler:

    x_{k+1} = A_d x_k + b_d (u_k + z(ζ_k)),  A_d = I + T A_c,  b_d = T [0, 1]ᵀ,

outputs y₁ = x₁ or y₂ = x plus white Gaussian noise. The paper does not give the sampling time,
the noise levels, the ζ filter or the step input; gpmhe fixes them here:

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

__all__ = [
    "Run", "disturbance", "output_matrix", "simulate", "make_gp", "f", "make_rgp_dkf",
    "run_rgp_dkf", "rgp_b_targets", "run_rgp_b", "evaluation_grid", "rmse_nll",
]

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
    """The hidden disturbance z(ζ) = −10 (1 + 0.1 ζ + ζ³).

    Parameters
    ----------
    zeta : float or ndarray
        Input(s) ζ.

    Returns
    -------
    ndarray
        z(ζ), the shape of ``zeta``.

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe.systems import second_order as so
    >>> print(so.disturbance(np.array([0.0, 1.0])))
    [-10. -21.]
    """
    z = np.asarray(zeta, dtype=float)
    return -10.0 * (1.0 + 0.1 * z + z**3)


def output_matrix(output: str) -> np.ndarray:
    """Output matrix C of y₁ = x₁ ("y1") or y₂ = x ("y2").

    Parameters
    ----------
    output : {"y1", "y2"}
        The measured output.

    Returns
    -------
    ndarray of shape (1, 2) or (2, 2)
        C.

    Raises
    ------
    ValueError
        For another ``output``.

    Examples
    --------
    >>> from gpmhe.systems import second_order as so
    >>> print(so.output_matrix("y1"))
    [[1. 0.]]
    """
    if output == "y1":
        return np.array([[1.0, 0.0]])
    if output == "y2":
        return np.eye(2)
    raise ValueError(f"output: expected 'y1' or 'y2', got {output!r}")


@dataclass
class Run:
    """One simulated run of the plant, as returned by `simulate`.

    u[k], ζ[k] and z[k] = z(ζ[k]) act from step k to k+1; x[k] is the state at step k
    (k = 0..steps) and y[k] = C x[k] + v[k] (y[0] is not used by the estimators).

    Parameters
    ----------
    u : ndarray of shape (steps,)
        Inputs u[k].
    zeta : ndarray of shape (steps,)
        GP inputs ζ[k].
    z : ndarray of shape (steps,)
        Disturbances z(ζ[k]).
    x : ndarray of shape (steps + 1, 2)
        True states.
    y : ndarray of shape (steps + 1, p)
        Measurements, p = 1 ("y1") or 2 ("y2").
    C : ndarray of shape (p, 2)
        Output matrix.
    noise_std : float
        Measurement-noise standard deviation.
    info : dict, optional
        The simulation settings (seed, noise, output).

    Examples
    --------
    >>> from gpmhe.systems import second_order as so
    >>> run = so.simulate(0, duration=0.5)
    >>> run.u.shape, run.x.shape, run.y.shape, run.info["output"]
    ((50,), (51, 2), (51, 2), 'y2')
    """

    u: np.ndarray
    zeta: np.ndarray
    z: np.ndarray
    x: np.ndarray
    y: np.ndarray
    C: np.ndarray
    noise_std: float
    info: dict = field(default_factory=dict)


def simulate(seed: int, noise: str = "low", output: str = "y2", duration: float = DURATION) -> Run:
    """Simulate the plant for ``duration`` seconds with the settings of the module description.

    Parameters
    ----------
    seed : int
        Seed of ζ, u and the measurement noise.
    noise : {"low", "high"}, default "low"
        Measurement-noise level (standard deviation 0.01 or 0.1).
    output : {"y1", "y2"}, default "y2"
        Measured output: x₁ or both states.
    duration : float, default ``DURATION`` (100.0)
        Length in seconds; the run has round(duration / T) steps.

    Returns
    -------
    Run
        The inputs, disturbances, states and measurements.

    Raises
    ------
    ValueError
        For an unknown ``noise`` or ``output``.

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe.systems import second_order as so
    >>> run = so.simulate(0, noise="high", output="y1", duration=1.0)
    >>> run.y.shape, run.noise_std
    ((101, 1), 0.1)
    >>> bool(np.allclose(run.z, so.disturbance(run.zeta)))
    True
    """
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
    """A fresh RGP with the hyperparameters shared by the RGP-dKF and RGP-B.

    ζ-grid on ``ZETA_BOUNDS`` with ``N_BASIS`` basis vectors, σ_K = ``SIGMA_K``, L = ``L_GRID``,
    σ_r = ``SIGMA_R``, σ_p = ``SIGMA_P``.

    Returns
    -------
    RecursiveGP
        The GP with zero mean weights.

    Examples
    --------
    >>> from gpmhe.systems import second_order as so
    >>> so.make_gp()
    RecursiveGP(lower=[-2.0], upper=[2.0], n_points=[25], sigma_K=30.0, L=4.0,
                sigma_r=0.3, sigma_p=0.0)
    """
    return RecursiveGP(
        ZETA_BOUNDS[0], ZETA_BOUNDS[1], N_BASIS, sigma_K=SIGMA_K, L=L_GRID,
        sigma_r=SIGMA_R, sigma_p=SIGMA_P,
    )


def f(x: np.ndarray, u: float, z: float) -> np.ndarray:
    """Euler transition x⁺ = A_d x + b_d (u + z), the ``f`` of the RGP-dKF.

    Parameters
    ----------
    x : ndarray of shape (2,)
        State.
    u : float
        Input.
    z : float
        Disturbance.

    Returns
    -------
    ndarray of shape (2,)
        The next state.

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe.systems import second_order as so
    >>> print(so.f(np.zeros(2), 1.0, 2.0))
    [0.   0.03]
    """
    return A_D @ x + B_D * (u + z)


def make_rgp_dkf(run: Run, gp: RecursiveGP | None = None) -> RGPEKF:
    """The RGP-dKF for a run, with the module's settings.

    A = A_d, e = b_d and H = C are constant (the plant is linear in x and z); Q_x = ``Q_X``,
    R_x = noise_std² I, x̂_0 = ``X0``, P_0 = ``P0``.

    Parameters
    ----------
    run : Run
        The run (for C and the noise level).
    gp : RecursiveGP or None, default None
        The GP to start from; None is a fresh `make_gp`.

    Returns
    -------
    RGPEKF
        The filter.

    Examples
    --------
    >>> from gpmhe.systems import second_order as so
    >>> kf = so.make_rgp_dkf(so.simulate(0, duration=0.1))
    >>> kf.mu.shape  # two states and 25 weights
    (27,)
    """
    C = run.C
    return RGPEKF(
        dim_x=2, f=f, A=A_D, e=E_D, h=lambda x: C @ x, H=C, Q_x=Q_X,
        R_x=run.noise_std**2 * np.eye(C.shape[0]), x0=X0, P0=P0,
        gps=make_gp() if gp is None else gp,
    )


def run_rgp_dkf(run: Run, snapshots: tuple[int, ...] = ()) -> tuple[RGPEKF, dict[int, tuple[np.ndarray, np.ndarray]], np.ndarray]:
    """Filter a run with the RGP-dKF: predict(u_k, ζ_k), then update(y_{k+1}), for every step.

    Parameters
    ----------
    run : Run
        The run to filter.
    snapshots : tuple of int, default ()
        Step counts after which to record the GP weights.

    Returns
    -------
    ekf : RGPEKF
        The filter after the last step.
    snapshots : dict
        Step count -> (mean, cov) of the GP weights after that many steps.
    xs : ndarray of shape (steps + 1, 2)
        The estimates x̂[k], k = 0..steps.

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe.systems import second_order as so
    >>> run = so.simulate(0, duration=1.0)
    >>> ekf, snaps, xs = so.run_rgp_dkf(run, snapshots=(50,))
    >>> xs.shape, list(snaps), snaps[50][0].shape
    ((101, 2), [50], (25,))
    >>> bool(np.abs(xs - run.x).max() < 0.05)
    True
    """
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
    """RGP-B's disturbance "measurements" y_GP,k = e⁺ (y_{k+1} − A_d y_k − b_d u_k).

    Parameters
    ----------
    run : Run
        A run with both states measured (output "y2").

    Returns
    -------
    ndarray of shape (steps,)
        y_GP,k for k = 0..steps−1.

    Raises
    ------
    ValueError
        If the run measures only x₁.

    Examples
    --------
    Without noise the targets are the disturbances:

    >>> import numpy as np
    >>> from gpmhe.systems import second_order as so
    >>> run = so.simulate(0, duration=0.5)
    >>> run.y = run.x  # noise-free measurements
    >>> bool(np.allclose(so.rgp_b_targets(run), run.z))
    True
    """
    if run.C.shape[0] != 2:
        raise ValueError("RGP-B needs both states measured (output 'y2')")
    pinv = E_D / (E_D @ E_D)
    resid = run.y[1:] - run.y[:-1] @ A_D.T - np.outer(run.u, B_D)
    return resid @ pinv


def run_rgp_b(run: Run, sigma_y_gp: float, snapshots: tuple[int, ...] = ()) -> tuple[RecursiveGP, dict]:
    """RGP-B: a plain `RecursiveGP` fed with `rgp_b_targets` at ζ_k.

    Parameters
    ----------
    run : Run
        A run with both states measured.
    sigma_y_gp : float
        Noise standard deviation σ_y,GP assumed for the targets (a design parameter).
    snapshots : tuple of int, default ()
        Step counts after which to record the GP weights.

    Returns
    -------
    gp : RecursiveGP
        The GP after all targets.
    snapshots : dict
        Step count -> (mean, cov) of the weights, for the requested counts within the run and
        always for the final count (steps).

    Examples
    --------
    >>> from gpmhe.systems import second_order as so
    >>> run = so.simulate(0, duration=1.0)
    >>> gp, snaps = so.run_rgp_b(run, 1.0, snapshots=(50,))
    >>> sorted(snaps)
    [50, 100]
    """
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
    """Evaluation points spanning the ζ range a run visited (its 1 % to 99 % quantiles).

    Parameters
    ----------
    run : Run
        The run.
    m : int, default 200
        Number of points.

    Returns
    -------
    ndarray of shape (m,)
        Evenly spaced points.

    Examples
    --------
    >>> from gpmhe.systems import second_order as so
    >>> grid = so.evaluation_grid(so.simulate(0, duration=1.0), m=5)
    >>> grid.shape
    (5,)
    """
    lo, hi = np.quantile(run.zeta, [0.01, 0.99])
    return np.linspace(lo, hi, m)


def rmse_nll(mean: np.ndarray, std: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """RMSE of a predicted mean and the average negative log predictive density of the truth.

    NLL = mean(½ log(2π σ²) + ½ (truth − mean)² / σ²).

    Parameters
    ----------
    mean : ndarray
        Predicted means.
    std : ndarray
        Predicted standard deviations σ (> 0).
    truth : ndarray
        True values.

    Returns
    -------
    rmse : float
        Root-mean-square error of ``mean``.
    nll : float
        Average negative log-likelihood of ``truth`` under N(mean, std²).

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe.systems import second_order as so
    >>> rmse, nll = so.rmse_nll(np.zeros(2), np.ones(2), np.array([1.0, -1.0]))
    >>> print(rmse, round(nll, 4))
    1.0 1.4189
    """
    err = truth - mean
    var = std**2
    return float(np.sqrt(np.mean(err**2))), float(np.mean(0.5 * np.log(2 * np.pi * var) + 0.5 * err**2 / var))
