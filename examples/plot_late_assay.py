"""
Late lab assays and samples with their own noise
================================================

The batch reactor's total concentration y₁ = x₁ + x₂ is measured every step; a lab assay of x₁
is taken every 20 steps and its result arrives 10 steps later. ``add_delayed`` puts it at the
time it was taken. Used as if it were current, the same assay pulls the estimate off the truth.
"""

# %%
# The plant, the sensor and the lab
# ---------------------------------
import matplotlib.pyplot as plt
import numpy as np

from gpmhe import GPMHE, KnownModel
from gpmhe.systems import batch_reactor as br

H = np.array([[1.0, 1.0], [1.0, 0.0]])  # y = [x1 + x2 (sensor), x1 (lab)]
model = KnownModel(br.f, lambda x, u=None: H @ x, dim_x=2, dim_y=2,
                   f_jacobian=br.f_jacobian, h_jacobian=lambda x, u=None: H)
rng = np.random.default_rng(4)
steps, every, delay = 100, 20, 10
x, y = br.simulate(br.X_TRUE0, steps, rng)
assays = {t + delay: (t, x[t, 0] + 0.05 * rng.standard_normal())
          for t in range(0, steps - delay, every)}
settings = dict(horizon=15, eta=1.0, Q0=br.SIGMA_W ** 2, R0=[0.01, 0.0025],
                x_bounds=br.X_BOUNDS, form="filtering")


def run(how):
    """x̂(t) over the run with the assays used late (``add_delayed``), as if current, or not."""
    est = GPMHE(model, [2.0, 2.0], **settings)
    out = []
    for t in range(steps):
        sample = np.array([y[t, 0], np.nan])
        if t in assays and how == "late":
            taken, value = assays[t]
            est.add_delayed([np.nan, value], age=t - 1 - taken)
        elif t in assays and how == "as if current":
            sample[1] = assays[t][1]
        out.append(est.update(None, sample).copy())
    return np.array(out)


runs = {how: run(how) for how in ("late", "as if current", "dropped")}
for how, xs in runs.items():
    err = np.sqrt(np.mean(np.sum((xs[20:] - x[20:steps]) ** 2, axis=1)))
    print(f"assay {how:>13}: RMSE after step 20 {err:.4f}")

# %%
# On time or late: the same estimate
# ----------------------------------
# With a window that still holds the assay's time, the estimate after the next update is the one
# the assay would have given had it arrived with its sample. Here the two are compared with a
# window longer than the run (every output kept).
full = dict(settings, horizon=steps + 2, solver_options=dict(dtol=0.0, gtol=1e-12))
on_time, late = GPMHE(model, [2.0, 2.0], **full), GPMHE(model, [2.0, 2.0], **full)
for t in range(31):
    on_time.update(None, [y[t, 0], assays[30][1] if t == 20 else np.nan])
    late.update(None, [y[t, 0], np.nan])
    if t == 30:
        late.add_delayed([np.nan, assays[30][1]], age=10)  # taken at 20; the newest output is 30
a, b = on_time.update(None, [y[31, 0], np.nan]), late.update(None, [y[31, 0], np.nan])
print("on time:", a, " late:", b)
assert np.allclose(a, b, rtol=1e-9, atol=1e-10)

# %%
# A sample with its own covariance
# --------------------------------
# ``R=R0`` is exactly no ``R``; a larger one makes the sample count less.
same, noisier = GPMHE(model, [2.0, 2.0], **settings), GPMHE(model, [2.0, 2.0], **settings)
plain = GPMHE(model, [2.0, 2.0], **settings)
for t in range(10):
    sample = [y[t, 0], np.nan]
    assert np.array_equal(same.update(None, sample, R=[0.01, 0.0025]), plain.update(None, sample))
    noisier.update(None, sample, R=[0.04, 0.0025])  # this sensor reports half the precision
print("R = R0:", same.x, " R = 4 R0 on the sensor:", noisier.x, " truth:", x[9])

fig, ax = plt.subplots(figsize=(7, 3.2))
ax.plot(x[:steps, 0], "k", lw=1, label="x₁ (true)")
for how, xs in runs.items():
    ax.plot(xs[:, 0], label=f"assay {how}")
for t in assays:
    ax.axvline(t, color="0.85", lw=0.8, zorder=0)
ax.set_xlabel("t")
ax.set_ylabel("x₁")
ax.set_title("assays arrive 10 steps late (grey: arrivals)")
ax.legend()
fig.tight_layout()
plt.show()
