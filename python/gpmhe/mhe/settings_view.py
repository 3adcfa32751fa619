"""The settings of a `GPMHE` as read-only attributes: a base class of `GPMHE` whose properties
read its one `MHESettings` value (``self._settings``). The weights among them (Q0, R0, P2, P0,
eta) are settable through `GPMHE.__setattr__`, which validates the new value and replaces the
settings and the core's weights together; the arrays returned here are read-only, so that an
in-place change is refused instead of lost.
"""

from __future__ import annotations

import numpy as np

__all__ = ["SettingsView"]


class SettingsView:
    """Read-only properties over ``self._settings`` (an `MHESettings`)."""

    @property
    def Q0(self):  # noqa: N802 (the paper's symbol)
        """Process-noise covariance Q0 (dim_x, dim_x), a read-only array; setting the attribute
        takes effect from the next update (a scalar, the diagonal or the matrix, as in the
        constructor) and changes nothing else."""
        return self._settings.Q0

    @property
    def R0(self):  # noqa: N802
        """Output-noise covariance R0 (dim_y, dim_y), read-only; settable as ``Q0``."""
        return self._settings.R0

    @property
    def P2(self):  # noqa: N802
        """Arrival weight P2 (dim_x, dim_x), read-only, the inverse of the arrival covariance
        ``P0``; setting it (or ``P0``) takes effect from the next update and restarts an "ekf"
        arrival weight from it."""
        return self._settings.P2

    @property
    def P0(self):  # noqa: N802
        """Arrival covariance P0 = P2⁻¹ (dim_x, dim_x), read-only; settable (sets P2)."""
        P0 = np.linalg.inv(self._settings.P2)
        P0.flags.writeable = False  # an in-place change would change nothing: refused
        return P0

    @property
    def eta(self):
        """Discount factor η in [0, 1]; settable."""
        return self._settings.eta

    @property
    def dim_x(self):
        """The model's state dimension n."""
        return self._settings.dims[0]

    @property
    def dim_y(self):
        """The model's output dimension p."""
        return self._settings.dims[1]

    @property
    def dim_u(self):
        """The model's input dimension m."""
        return self._settings.dims[2]

    @property
    def dim_p(self):
        """The number of parameters."""
        return self._settings.dims[3]

    @property
    def learning(self):
        """Whether the f-GPs keep learning online (see `GPMHE`, ``learning``)."""
        return self._settings.learning

    @property
    def learning_options(self):
        """The learning settings as applied: ``{"drift": ...}`` (empty without learning)."""
        s = self._settings
        return {"drift": s.learning_drift} if s.learning else {}

    @property
    def horizon(self):
        """The window length M."""
        return self._settings.horizon

    @property
    def form(self):
        """The form, "prediction" or "filtering"."""
        return self._settings.form

    @property
    def solver(self):
        """The window solver."""
        return self._settings.solver

    @property
    def solver_options(self):
        """The solver options given (a copy)."""
        return dict(self._settings.solver_options)

    @property
    def arrival_mean(self):
        """The arrival mean, "smoothed", "estimate" or "filtered"."""
        return self._settings.arrival_mean

    @property
    def arrival_weight(self):
        """The arrival weight, "ekf" or "constant"."""
        return self._settings.arrival_weight

    @property
    def loss(self):
        """The output penalty, "squared", "huber" or "cauchy"."""
        return self._settings.loss

    @property
    def loss_scale(self):
        """The penalty's scale k (1.0 for "squared")."""
        return self._settings.loss_scale

    @property
    def x_bounds(self):
        """The state box (lower, upper), ±inf where unbounded."""
        return tuple(b.copy() for b in self._settings.x_bounds)

    @property
    def p0(self):
        """The parameters' initial guess."""
        return self._settings.p0.copy()

    @property
    def P_p0(self):  # noqa: N802
        """The parameters' prior covariance."""
        return self._settings.P_p0.copy()

    @property
    def p_bounds(self):
        """The parameters' bounds (lower, upper), or None."""
        return None if self._settings.p_bounds is None else tuple(b.copy() for b in self._settings.p_bounds)

    @property
    def p_drift(self):
        """The parameters' random-walk standard deviation per step."""
        return self._settings.p_drift.copy()
