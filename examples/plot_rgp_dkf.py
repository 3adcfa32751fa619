"""
The RGP-dKF: an EKF that learns a disturbance online
====================================================

The example of Husmann, Weishaupt & Aschemann: a second-order plant
ẋ = [[0, 1], [−4, −4]] x + [0, 1]ᵀ (u + z) driven by an unknown disturbance z(ζ) that depends on a
measured signal ζ. :class:`gpmhe.RGPEKF` appends the weights of a recursive GP
(:class:`gpmhe.RecursiveGP`, 25 basis vectors on ζ ∈ [−2, 2]) to the EKF state and learns z from
the state measurements alone — z itself is never measured.
"""

# %%
# The plant and the filter
# ------------------------
# :mod:`gpmhe.systems.second_order` simulates the plant (T = 0.01 s, Euler) with u a sequence of
# steps and ζ low-pass filtered noise; scenario S2 measures both states with low noise.
import matplotlib.pyplot as plt
import numpy as np

from gpmhe import RGPEKF, RecursiveGP
from gpmhe.systems import second_order as so

run = so.simulate(seed=0, noise="low", output="y2", duration=100.0)
gp = RecursiveGP(lower=-2.0, upper=2.0, n_points=25, sigma_K=30.0, L=4.0, sigma_r=0.3)
ekf = RGPEKF(dim_x=2, f=so.f, A=so.A_D, e=so.E_D, h=lambda x: x, H=np.eye(2),
             Q_x=so.Q_X, R_x=run.noise_std**2 * np.eye(2), x0=so.X0, P0=so.P0, gps=gp)

# %%
# The loop
# --------
# ``predict(u_k, ζ_k)`` then ``update(y_{k+1})``, as with filterpy. Snapshots of the learned
# function after 0.5 s and at the end.
snapshots = {}
for k in range(len(run.u)):
    ekf.predict(run.u[k], run.zeta[k])
    ekf.update(run.y[k + 1])
    if k + 1 in (50, len(run.u)):
        snapshots[(k + 1) * so.T] = ekf.gp_weights(0)

zeta = so.evaluation_grid(run)
for seconds, (mean, cov) in snapshots.items():
    g = gp.copy()               # the filter copied gp: it is still the untrained prior
    g.set_weights(mean, cov)
    m, s = g.predict(zeta, return_std=True)
    rmse, nll = so.rmse_nll(m, s, so.disturbance(zeta))
    print(f"after {seconds:5.1f} s: RMSE of z over the visited ζ range {rmse:.3f}, NLL {nll:.3f}")

# %%
# The learned function
# --------------------
# Mean ± 2 standard deviations against the true z(ζ); the grey band is the range of ζ the run
# visited (1–99 % quantiles). Outside it the GP keeps its prior uncertainty.
fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
grid = np.linspace(-2.0, 2.0, 300)
lo, hi = np.quantile(run.zeta, [0.01, 0.99])
for ax, (seconds, (mean, cov)) in zip(axes, snapshots.items()):
    g = gp.copy()
    g.set_weights(mean, cov)
    m, s = g.predict(grid, return_std=True)
    ax.axvspan(lo, hi, color="0.9", zorder=0)
    ax.fill_between(grid, m - 2 * s, m + 2 * s, alpha=0.3, label="GP ± 2σ")
    ax.plot(grid, m, label="GP mean")
    ax.plot(grid, so.disturbance(grid), "k--", label="true z(ζ)")
    ax.set_title(f"after {seconds:.1f} s")
    ax.set_xlabel("ζ")
    ax.set_ylim(-110, 90)
axes[0].set_ylabel("z")
axes[0].legend(loc="lower left", fontsize=8)
fig.tight_layout()
plt.show()
