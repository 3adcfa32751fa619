"""
Learn f and h from logged data
==============================

GP-MHE needs no equations: Gaussian processes learn x(t+1) = f(x, u) and y = h(x, u) from logged
trajectories in which the states were measured (as in a commissioning or lab campaign, where
extra sensors are available), and the estimator then runs on the plant's ordinary outputs.

The plant is the two-tank system of :ref:`sphx_glr_auto_examples_plot_known_model.py`, but its
equations are used only to *generate* the logs. The learned estimator is compared with the MHE on
the exact model, and the GP's posterior standard deviation shows where the learned model can be
trusted: the MHE weighs each model residual by the inverse of that variance plus ``Q0``.
"""

# %%
# The logs
# --------
# Four runs of 100 samples with the pump switching at random: inputs (T, 1), states (T+1, 2)
# measured with small noise, outputs (T+1, 2).
import matplotlib.pyplot as plt
import numpy as np

from gpmhe import GPMHE, KnownModel, LearnedModel

T, a1, a2 = 0.5, 0.30, 0.25


def f(X, U):
    q1 = a1 * np.sqrt(np.maximum(X[:, 0], 0.0))
    q2 = a2 * np.sqrt(np.maximum(X[:, 1], 0.0))
    return np.column_stack([X[:, 0] + T * (U[:, 0] - q1), X[:, 1] + T * (q1 - q2)])


def h(X, U):
    return np.column_stack([a2 * np.sqrt(np.maximum(X[:, 1], 0.0)), X[:, 0]])


def simulate(x0, u, rng, sigma_w=0.01, sigma_v=(0.02, 0.05)):
    x = np.empty((len(u) + 1, 2))
    x[0] = x0
    for t in range(len(u)):
        x[t + 1] = np.maximum(f(x[t:t + 1], u[t:t + 1])[0] + sigma_w * rng.normal(size=2), 0.0)
    y = h(x, np.zeros((len(x), 1))) + np.asarray(sigma_v) * rng.normal(size=(len(x), 2))
    return x, y


rng = np.random.default_rng(7)
states, outputs, inputs = [], [], []
for x0 in ([0.5, 0.5], [2.0, 1.0], [1.0, 2.5], [3.0, 3.0]):
    u = np.repeat(rng.uniform(0.05, 0.6, 10), 10)[:, None]         # 100 steps
    x, y = simulate(x0, u, rng)
    states.append(x + 0.01 * rng.normal(size=x.shape))              # lab measurements of x
    outputs.append(y)
    inputs.append(u)

# %%
# Fitting the model
# -----------------
# One GP per state for x(t+1) and one per output for y(t), each on d = [x; u], with
# hyperparameters by maximum marginal likelihood (three restarts). Each GP's prior mean is a
# linear function of d, fitted with it (the default ``mean="linear"``), so the GP learns only
# what a linear model misses; for a slow, integrating plant like this one that linear part is
# close to x(t+1) ≈ x(t), the increment model.
model = LearnedModel.from_trajectories(states, outputs, inputs, n_restarts=3, random_state=0)
print("f-GPs: sigma_f", np.round(model.f_gp.sigma_f, 3), " sigma_eps",
      np.round(model.f_gp.sigma_eps, 4))
print("h-GPs: sigma_f", np.round(model.h_gp.sigma_f, 3), " sigma_eps",
      np.round(model.h_gp.sigma_eps, 4))

# %%
# Estimating on a new run
# -----------------------
# Same settings for both estimators; only the model differs. The new run's pump levels stay
# within the range the logs covered: a GP learns nothing about states it has not seen (its mean
# falls back to the prior there), which is what the posterior standard deviation below shows.
u_test = np.repeat(rng.uniform(0.1, 0.4, 9), 20)[:, None]            # 180 steps
x_test, y_test = simulate([1.5, 0.8], u_test, rng)
settings = dict(horizon=20, eta=0.95, Q0=1e-4, R0=np.array([0.02, 0.05]) ** 2,
                x_bounds=([0.0, 0.0], [10.0, 10.0]), form="filtering")
estimators = {
    "GP-MHE (learned)": GPMHE(model, x0=[0.5, 2.0], **settings),
    "MHE (exact model)": GPMHE(KnownModel(f, h, 2, 2, dim_u=1, vectorized=True),
                               x0=[0.5, 2.0], **settings),
}
est = {name: np.empty((len(u_test), 2)) for name in estimators}
for t in range(len(u_test)):
    for name, e in estimators.items():
        est[name][t] = e.update(u_test[t], y_test[t])
for name, xs in est.items():
    err = np.linalg.norm(xs - x_test[:-1], axis=1)
    print(f"{name:18s} RMSE {np.sqrt(np.mean(err**2)):.3f}   for t >= 20: "
          f"{np.sqrt(np.mean(err[20:]**2)):.3f}")

# %%
# Estimates and the model's confidence
# ------------------------------------
# Left: the unmeasured lower level. Right: the f-GP's posterior standard deviation for the lower
# level over the (x₂, u) plane at x₁ = 1, with the training data: far from the data the GP
# says so, and the MHE trusts the measurements more there.
fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 4))
time = T * np.arange(len(u_test))
ax0.plot(time, x_test[:-1, 1], "k-", lw=2, label="true")
for name, xs in est.items():
    ax0.plot(time, xs[:, 1], label=name)
ax0.set_xlabel("time [s]")
ax0.set_ylabel("lower level (not measured)")
ax0.legend(fontsize=8)

g2, gu = np.meshgrid(np.linspace(0.0, 4.0, 60), np.linspace(0.0, 0.8, 60))
D = np.column_stack([np.ones(g2.size), g2.ravel(), gu.ravel()])
_, std = model.f_gp.predict(D, return_std=True)
c = ax1.contourf(g2, gu, std[:, 1].reshape(g2.shape), levels=20)
fig.colorbar(c, ax=ax1, label="posterior std of the next $x_2$")
for x, u in zip(states, inputs):
    ax1.plot(x[:-1, 1], u[:, 0], "w.", ms=3)
ax1.set_xlabel("$x_2$")
ax1.set_ylabel("u")
fig.tight_layout()
plt.show()
