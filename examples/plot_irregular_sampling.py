"""
Irregular sampling
==================

The cart-pole's four states are measured at intervals jittered by ±50 % around T = 0.05 s. A model
from ``KnownModel.from_ode`` integrates each stage of the window over its own interval when
``update`` is given ``dt``, the time since the previous sample; without it every stage is
integrated over T, and the estimator, which trusts its model (process weights up to 4e8), is
pulled off the truth.
"""

# %%
# The plant, sampled irregularly
# ------------------------------
import matplotlib.pyplot as plt
import numpy as np

from gpmhe import GPMHE, discretize
from gpmhe.systems import cart_pole as cp

rng = np.random.default_rng(2)
steps = 150
dts = cp.T * (1.0 + rng.uniform(-0.5, 0.5, steps))  # dts[k]: from sample k − 1 to sample k
u = np.repeat(rng.uniform(-cp.F_MAX, cp.F_MAX, steps // cp.U_HOLD + 1), cp.U_HOLD)[:steps, None]
x = np.empty((steps, 4))
x[0] = cp.X0
for k in range(1, steps):
    x[k] = discretize(cp.rhs, dts[k], substeps=20)(x[k - 1], u[k - 1])
    x[k] += cp.SIGMA_W * rng.standard_normal(4)
y = x + cp.SIGMA_V * rng.standard_normal(x.shape)
times = np.cumsum(np.concatenate([[0.0], dts[1:]]))

# %%
# Each sample's interval, or a fixed one
# --------------------------------------
model = cp.known_model("casadi")  # KnownModel.from_ode: model.dt is T
print("model.dt =", model.dt)


def run(with_intervals):
    est = GPMHE(model, x0=cp.X0, form="filtering", **cp.MHE_SETTINGS)
    return np.array([est.update(u[k], y[k], dt=dts[k] if with_intervals else None).copy()
                     for k in range(steps)])


each, fixed = run(True), run(False)
rmse = {name: np.sqrt(np.mean(np.sum((xs - x) ** 2, axis=1)))
        for name, xs in (("each interval", each), ("fixed interval", fixed))}
print(rmse)
assert rmse["each interval"] < rmse["fixed interval"] / 5

# %%
# ``dt=model.dt`` is exactly no ``dt``
# ------------------------------------
a = GPMHE(model, x0=cp.X0, form="filtering", **cp.MHE_SETTINGS)
b = GPMHE(model, x0=cp.X0, form="filtering", **cp.MHE_SETTINGS)
for k in range(20):
    assert np.array_equal(a.update(u[k], y[k]), b.update(u[k], y[k], dt=model.dt))

fig, axes = plt.subplots(2, 1, figsize=(7, 4.5), sharex=True)
for ax, i, label in zip(axes, (0, 1), ("cart position p (m)", "pole angle θ (rad)")):
    ax.plot(times, x[:, i], "k-", lw=1.5, label="truth")
    ax.plot(times, each[:, i], "C0--", label="GPMHE, dt per sample")
    ax.plot(times, fixed[:, i], "C3:", label="GPMHE, fixed dt")
    ax.set_ylabel(label)
axes[0].legend(loc="best", fontsize=8)
axes[1].set_xlabel("time (s)")
fig.tight_layout()
plt.show()
