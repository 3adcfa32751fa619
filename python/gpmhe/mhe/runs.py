"""Whole runs through a `GPMHE`: `batch_filter` (`update` over a logged sequence, as filterpy's)
and `smooth` (the fixed-interval smoother of a logged run). A base class of `GPMHE`: the methods
run every sample through the same checks and step as `update` (`_check_step`, `_step`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from gpmhe._validation import sequence_rows

__all__ = ["Runs"]


def _renamed(error, message):
    """``error`` (a ValueError) with ``message``, of its class where that takes a message alone
    (a `gpmhe.MagnitudeError` stays one), else a plain ValueError."""
    try:
        return type(error)(message)
    except Exception:  # a class whose constructor wants more
        return ValueError(message)


class Runs:
    """`GPMHE`'s methods over whole runs (see the module docstring)."""

    def batch_filter(self, ys, us=None, Rs=None, dts=None):
        """Run `update` over a sequence of outputs (and inputs), as filterpy's ``batch_filter``.

        All input is validated before the first update, so bad input raises ValueError (naming
        the row) with the estimator unchanged.

        Parameters
        ----------
        ys : sequence of array_like of shape (dim_y,) or None, length T
            Outputs y(t); a row may be None (no measurement at that step).
        us : sequence of array_like of shape (dim_u,) or None, length T, or None, default None
            Inputs u(t); None when the model has no input.
        Rs : sequence of (float, array_like or None), length T, or None, default None
            Each sample's output covariance (`update`'s ``R``; a row None: ``R0``), as filterpy's
            ``Rs``: the R of a row whose output is None is not used. None: ``R0`` for all.
        dts : sequence of (float or None), length T, or None, default None
            Each sample's interval since the previous one (`update`'s ``dt``; a row None: the
            model's ``dt``). None: the model's ``dt`` for all.

        Returns
        -------
        xs : ndarray of shape (T, dim_x)
            ``x`` after each update.
        Ps : ndarray of shape (T, dim_x, dim_x)
            ``P`` after each update.

        Raises
        ------
        ValueError
            If a row has the wrong shape or ``us`` and ``ys`` differ in length.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import GPMHE, KnownModel
        >>> from gpmhe.systems import batch_reactor as br
        >>> model = KnownModel(br.f, br.h, dim_x=2, dim_y=1)
        >>> x_true, y = br.simulate(br.X_TRUE0, 20, np.random.default_rng(1))
        >>> mhe = GPMHE(model, x0=br.X_TRUE0, x_bounds=br.X_BOUNDS, **br.MHE_SETTINGS)
        >>> xs, Ps = mhe.batch_filter(y[:20])
        >>> xs.shape, Ps.shape
        ((20, 2), (20, 2, 2))
        >>> rmse = np.sqrt(np.mean((xs - x_true[1:21]) ** 2))
        >>> bool(rmse < 0.3)
        True
        """
        ys = sequence_rows("ys", ys)
        us = [None] * len(ys) if us is None else sequence_rows("us", us)
        Rs = [None] * len(ys) if Rs is None else list(Rs)
        dts = [None] * len(ys) if dts is None else list(np.ravel(dts) if np.ndim(dts) else [dts])
        other = {"us": us, "Rs": Rs, "dts": dts}
        wrong = [name for name, rows in other.items() if len(rows) != len(ys)]
        if wrong:
            raise ValueError(f"ys, {', '.join(wrong)}: ys has {len(ys)} rows but "
                             + ", ".join(f"{name} has {len(other[name])}" for name in wrong))
        steps = []
        for i, (u, y, R, dt) in enumerate(zip(us, ys, Rs, dts)):
            try:  # (no R without an output: filterpy's Rs has one for every row)
                steps.append(self._check_step(u, y, None if y is None else R, dt))
            except ValueError as e:  # "y: ..." -> "ys[i]: ... (at row i)", of the same class
                name, _, detail = str(e).partition(": ")
                raise _renamed(e, f"{name}s[{i}]: {detail} (at row {i})") from None
        xs = np.empty((len(steps), self.dim_x))
        Ps = np.empty((len(steps), self.dim_x, self.dim_x))
        if self.dim_u and any(step[0] is None for step in steps):
            raise ValueError("us: batch_filter needs every input (u=None is for update and "
                             "set_input)")
        for i, step in enumerate(steps):
            self._step(*step)
            xs[i], Ps[i] = self.x, self.P
        return xs, Ps

    def smooth(self, ys, us=None, Rs=None, dts=None):
        """The fixed-interval smoothed trajectory of a logged run, with its covariances.

        Runs this estimator's model and settings over the whole run in one window (the
        filtering form with a horizon as long as the run: full information), from this
        estimator's prior ``x`` and ``P`` for the first sample, and returns the last window and
        its covariances. The estimator itself does not change. The default solver runs every
        window to its gradient tolerance (``dtol=0`` unless ``solver_options`` give one).

        Parameters
        ----------
        ys, us, Rs, dts
            The run, as for `batch_filter` (``ys[0]`` is the first sample after the prior).

        Returns
        -------
        xs : ndarray of shape (T, dim_x)
            x̂(t | all T samples) for t = 0..T−1.
        Ps : ndarray of shape (T, dim_x, dim_x)
            Their covariances (``P_window`` of that window).

        Raises
        ------
        ValueError
            As `batch_filter`, or if the estimator has been updated (``t`` > 0: its prior is
            then not the prior of a new run; use a new estimator or `reset`).

        Notes
        -----
        On a linear-Gaussian model with η = 1 and no active bounds the result is the
        Rauch-Tung-Striebel smoother's (the arrival cost enters only at the first sample, as
        its prior). With η < 1 the older samples weigh less, as in every window, and ``Ps`` are
        the discounted estimates' covariances (``P_window``). The window
        grows to T nodes: every update solves the whole run so far, so the time grows with T².

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import GPMHE, KnownModel
        >>> model = KnownModel(lambda x, u: x, lambda x, u: x, dim_x=1, dim_y=1)
        >>> est = GPMHE(model, x0=[0.0], P0=100.0, Q0=1e-6, R0=1.0, eta=1.0)
        >>> xs, Ps = est.smooth([[1.0], [3.0], [2.0]])  # a constant: every node is the mean
        >>> print(np.round(xs.ravel(), 3), np.round(Ps[0, 0, 0], 3))
        [1.993 1.993 1.993] 0.332
        """
        if self.t:
            raise ValueError(f"smooth: the estimator has been updated (t = {self.t}); smooth "
                             "from a new estimator (or after reset)")
        ys = sequence_rows("ys", ys)
        if not len(ys):  # an empty run has no node: batch_filter's empty arrays (it checks the
            return self.batch_filter(ys, us, Rs, dts)  # other sequences and changes nothing)
        options = dict(self._settings.solver_options)
        if self.solver == "gauss-newton":  # off-line: to the gradient tolerance unless told
            options.setdefault("dtol", 0.0)
        settings = dataclasses.replace(self._settings, horizon=max(len(ys), 1), form="filtering",
                                       solver_options=options)
        full = type(self)._from_settings(self.model, settings, self.x)  # the same prior
        full.batch_filter(ys, us, Rs, dts)
        return full.x_window, full.P_window
