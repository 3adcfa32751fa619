"""
Uncertainty: window covariances, innovations and χ² tests
=========================================================

On a linear-Gaussian plant with the Kalman-filter settings the MHE's innovation, its covariance
``S`` and the log-likelihood are the Kalman filter's, and its NEES and NIS pass the χ² tests of
`gpmhe.consistency`. ``P_window`` gives every node of the window its covariance.
"""

# %%
# A linear-Gaussian plant, the MHE and filterpy's Kalman filter
# -------------------------------------------------------------
import matplotlib.pyplot as plt
import numpy as np
from filterpy.kalman import KalmanFilter

from gpmhe import GPMHE, KnownModel
from gpmhe.consistency import chi2_test, nees

A = np.array([[1.0, 0.1], [-0.05, 0.95]])  # a lightly damped oscillator, position measured
C = np.array([[1.0, 0.0]])
Q, R = np.diag([1e-4, 4e-4]), np.array([[0.01]])
model = KnownModel(lambda x, u: A @ x, lambda x, u: C @ x, dim_x=2, dim_y=1)

def simulate(rng, steps):
    """True states from x(0) ~ N(0, I) (the estimators' prior) and the measured positions."""
    x = np.empty((steps, 2))
    x[0] = rng.standard_normal(2)
    for t in range(1, steps):
        x[t] = A @ x[t - 1] + rng.multivariate_normal(np.zeros(2), Q)
    return x, x @ C.T + rng.normal(0.0, 0.1, (steps, 1))


def estimator():
    return GPMHE(model, x0=[0.0, 0.0], P0=np.eye(2), horizon=10, eta=1.0, Q0=Q, R0=R,
                 form="filtering", arrival_mean="estimate", arrival_weight="ekf",
                 solver_options=dict(dtol=0.0))  # each window solved to its gradient tolerance


rng = np.random.default_rng(1)
steps = 100
x, y = simulate(rng, steps)
est = estimator()
kf = KalmanFilter(dim_x=2, dim_z=1)
kf.F, kf.H, kf.Q, kf.R, kf.P, kf.x = A, C, Q, R, np.eye(2), np.zeros(2)
loglik, kf_loglik = 0.0, 0.0
for t in range(steps):
    est.update(None, y[t])
    kf.update(y[t])
    assert np.allclose(est.innovation, kf.y, atol=1e-6) and np.allclose(est.S, kf.S, atol=1e-6)
    loglik += est.log_likelihood
    kf_loglik += kf.log_likelihood
    kf.predict()
print(f"log-likelihood of the run: {loglik:.4f} (Kalman filter: {kf_loglik:.4f})")
assert abs(loglik - kf_loglik) < 1e-6

# %%
# χ² tests over Monte Carlo runs
# ------------------------------
# The test assumes independent values. The NIS of a consistent estimator is white, so every
# step of every run counts; the NEES of one run is correlated from step to step, so it is taken
# once per run (at the last step) over independent runs. A covariance three times too small
# fails. (At level α = 0.05 a consistent estimator fails the test in 5 % of experiments.)
nees_last, nees_shrunk, nis = [], [], []
for run in range(100):
    x_run, y_run = simulate(rng, 60)
    xs, Ps = estimator().batch_filter(y_run)
    nees_last.append(nees(x_run[-1:], xs[-1:], Ps[-1:])[0])
    nees_shrunk.append(nees(x_run[-1:], xs[-1:], Ps[-1:] / 3)[0])
    est_run = estimator()
    for t in range(60):
        est_run.update(None, y_run[t])
        nis.append(est_run.nis)
print(chi2_test(nees_last, dof=2))
print(chi2_test(nis, dof=1))
assert chi2_test(nees_last, dof=2).consistent and chi2_test(nis, dof=1).consistent
assert not chi2_test(nees_shrunk, dof=2).consistent

# %%
# The window and its covariances
# ------------------------------
window, band = est.x_window, 2.0 * np.sqrt(est.P_window[:, 0, 0])
times = np.arange(steps - len(window), steps)
fig, ax = plt.subplots(figsize=(7, 3.2))
ax.plot(times, x[times, 0], "k-", label="truth")
ax.plot(times, y[times, 0], "k.", ms=4, label="measured")
ax.plot(times, window[:, 0], "C0-", label="window (smoothed)")
ax.fill_between(times, window[:, 0] - band, window[:, 0] + band, color="C0", alpha=0.25,
                label="±2σ from P_window")
ax.set_xlabel("t")
ax.set_ylabel("position")
ax.legend(loc="best", fontsize=8)
fig.tight_layout()
plt.show()
