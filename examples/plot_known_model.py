"""
Your own plant with a KnownModel
================================

When the model is known, :class:`gpmhe.KnownModel` wraps its Python functions and
:class:`gpmhe.GPMHE` becomes a classic moving horizon estimator. The plant here has an input and
two outputs: two tanks in series, fed by a pump (the input u), with the outflow of the lower tank
and the level of the upper tank measured. The flows go with the square root of the levels, so the
model is nonlinear, and the box constraint "levels are non-negative" is part of what the MHE
knows and a Kalman filter does not. The MHE runs next to filterpy's unscented Kalman filter on
the same data.
"""

# %%
# The model
# ---------
# ``f(x, u)`` returns x(t+1) and ``h(x, u)`` the noise-free outputs; with ``vectorized=True``
# they receive all window points at once (rows of ``X`` and ``U``), which is much faster than a
# Python call per point. Without Jacobians, gpmhe takes central finite differences.
import matplotlib.pyplot as plt
import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

from gpmhe import GPMHE, KnownModel

T = 0.5                      # sampling time [s]
a1, a2 = 0.30, 0.25          # outflow coefficients: q = a √level


def f(X, U):
    """Euler step of the tank levels for k points: X (k, 2), U (k, 1) -> (k, 2)."""
    q1 = a1 * np.sqrt(np.maximum(X[:, 0], 0.0))
    q2 = a2 * np.sqrt(np.maximum(X[:, 1], 0.0))
    return np.column_stack([X[:, 0] + T * (U[:, 0] - q1), X[:, 1] + T * (q1 - q2)])


def h(X, U):
    """Measured: the lower tank's outflow and the upper tank's level, (k, 2)."""
    return np.column_stack([a2 * np.sqrt(np.maximum(X[:, 1], 0.0)), X[:, 0]])


model = KnownModel(f, h, dim_x=2, dim_y=2, dim_u=1, vectorized=True)

# %%
# A simulated run
# ---------------
# The pump switches between levels; the lower tank's level is never measured directly.
rng = np.random.default_rng(3)
steps = 200
u = np.repeat(rng.uniform(0.1, 0.6, steps // 25 + 1), 25)[:steps + 1, None]  # u(0..steps)
sigma_w, sigma_v = 0.01, np.array([0.02, 0.05])
x = np.empty((steps + 1, 2))
x[0] = [1.0, 0.5]
for t in range(steps):
    x[t + 1] = np.maximum(f(x[t:t + 1], u[t:t + 1])[0] + sigma_w * rng.normal(size=2), 0.0)
y = h(x, np.zeros((steps + 1, 1))) + sigma_v * rng.normal(size=(steps + 1, 2))

# %%
# The estimators
# --------------
# Both start from the same wrong guess. The MHE uses the filtering form, so that after
# ``update(u(t), y(t))`` its ``x`` is x̂(t), the same estimate as the UKF's after ``update``.
x0_guess = np.array([0.2, 2.0])
Q0, R0 = sigma_w**2 * np.eye(2), np.diag(sigma_v**2)
mhe = GPMHE(model, x0=x0_guess, horizon=20, eta=0.95, P2=np.eye(2), Q0=Q0, R0=R0,
            x_bounds=([0.0, 0.0], [10.0, 10.0]), form="filtering")

points = MerweScaledSigmaPoints(2, alpha=0.3, beta=2.0, kappa=0.0)
ukf = UnscentedKalmanFilter(dim_x=2, dim_z=2, dt=T, points=points,
                            fx=lambda s, dt, uk: f(s[None], uk[None])[0],
                            hx=lambda s: h(s[None], np.zeros((1, 1)))[0])
ukf.x, ukf.P, ukf.Q, ukf.R = x0_guess.copy(), np.eye(2), Q0, R0

est_mhe, est_ukf = np.empty((steps + 1, 2)), np.empty((steps + 1, 2))
for t in range(steps + 1):
    if t > 0:
        ukf.predict(uk=u[t - 1])
    ukf.update(y[t])
    est_ukf[t] = ukf.x
    est_mhe[t] = mhe.update(u[t], y[t])   # u(t) acts from t to t+1

for name, xs in (("GPMHE, known model", est_mhe), ("filterpy UKF", est_ukf)):
    err = np.linalg.norm(xs - x, axis=1)
    print(f"{name:20s} RMSE {np.sqrt(np.mean(err**2)):.3f}   "
          f"for t >= 20: {np.sqrt(np.mean(err[20:]**2)):.3f}")

# %%
# The unmeasured level
# --------------------
fig, axes = plt.subplots(2, 1, sharex=True, figsize=(7, 5.5))
time = T * np.arange(steps + 1)
for i, ax in enumerate(axes):
    ax.plot(time, x[:, i], "k-", lw=2, label="true")
    ax.plot(time, est_mhe[:, i], label="GPMHE (KnownModel)")
    ax.plot(time, est_ukf[:, i], label="filterpy UKF")
    ax.set_ylabel(["upper level (measured)", "lower level (not measured)"][i])
axes[0].legend(fontsize=8)
axes[-1].set_xlabel("time [s]")
fig.tight_layout()
plt.show()
