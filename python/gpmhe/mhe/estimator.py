"""GPMHE: the GP-based moving horizon estimator of Wolff, Lopez & Müller, in filterpy's style.

The estimator is one Rust object (`gpmhe._core.MovingHorizon`, built once from the model's stage
model and the settings): it owns the sliding history, the warm start and everything the last
update reported, and with the default solver one ``update(u, y)`` is one Rust call (window, warm
start, solve, covariance, next arrival prior, record). This class validates every step's input
and reads its attributes from the core; its settings are one `MHESettings` value
(``settings.py``), SciPy's solvers are in ``solvers.py`` and checkpoints in ``checkpoint.py``.
See *Architecture* in the documentation.
"""

from __future__ import annotations

import warnings

import numpy as np

from gpmhe import _core
from gpmhe._filterpy import (REQUIRED, missing_attribute, one_argument_update, refused_setting,
                             renamed, required, window_attribute)
from gpmhe._threads import exclusive
from gpmhe._validation import SettingsWarning, finite_vector, integer, output_sample, positive_scalar
from gpmhe.mhe import checkpoint, solvers
from gpmhe.mhe.runs import Runs
from gpmhe.mhe.settings_view import SettingsView
from gpmhe.mhe.settings import WEIGHTS, MHESettings, sample_covariance

__all__ = ["GPMHE"]


def check_interval(dt, time_step, form, horizon):
    """A sample's interval ``dt`` checked: a positive number, for a model with a time step
    (``time_step`` not None) in a form and horizon that can use it; None stays None."""
    if dt is None:
        return None
    if time_step is None:
        raise ValueError("dt: the model has no time step (a learned or discrete-time model "
                         "takes one sample per step; KnownModel.from_ode makes a model that "
                         "integrates over each sample's interval)")
    if form == "prediction" and horizon == 1:
        raise ValueError("dt: the prediction form with horizon 1 cannot use it (its window "
                         "never holds the stage the interval belongs to); use horizon >= 2 "
                         "or the filtering form")
    return positive_scalar("dt", dt)


#: The warning of an estimator built without Q0, R0 and P2/P0 (each defaults to the identity).
NO_NOISE_INFORMATION = (
    "Q0, R0 and P2/P0 are all None: identity weights are assumed (unit process and output noise "
    "covariances and a unit initial covariance), which suits only a plant whose noises and "
    "initial error are of order one in its units. Give the noise covariances Q0 and R0 and the "
    "initial covariance P0; see the user guide, 'Weights from the GP variances'.")


class GPMHE(SettingsView, Runs):
    """Moving horizon estimator with a learned (GP) or known model, in filterpy's style.

    The system is x(t+1) = f(x(t), u(t)) + w(t), y(t) = h(x(t), u(t)) + v(t). With a
    `LearnedModel` (the paper's GP-MHE [1]_) f and h are replaced by GP posterior means m_x(d),
    m_y(d) at d = [x; u] and the GP latent variances σ²_x(d), σ²_y(d) enter the weights; with a
    `KnownModel` (the exact-model MHE) the variances are zero.

    At each step the estimator minimises over the window states z = (x̄_{t−M_t}, …, x̄_t), inside
    the box ``x_bounds``, the cost (the paper's eq. 10e)::

        J = 2 η^{M_t} ‖x̄_{t−M_t} − x̂(t−M_t)‖²_{P2}
            + Σ_{j=1}^{M_t} 2 η^{j−1} ( w̄ᵀ Q(d̄)⁻¹ w̄ + v̄ᵀ R(d̄)⁻¹ v̄ )(t−j),

    with w̄_j = x̄_{j+1} − m_x(d̄_j), v̄_j = y_j − m_y(d̄_j), d̄_j = [x̄_j; u_j],
    Q(d) = diag σ²_x(d) + Q0, R(d) = diag σ²_y(d) + R0 and M_t = min(t, M) (full information
    while t < M). Missing outputs (``y=None``) drop their v̄ term; NaN entries of y are channels
    not measured and drop their rows (with a full R0, v̄ is weighted by R's block of the
    measured channels). A sample given with its own covariance (``update(u, y, R=...)``) uses it
    in place of R0; an output that arrives late (`add_delayed`) enters at its own time. The
    estimate is the last window state, x̂(t) = x̄_t.

    The loop, next to filterpy's EKF::

        # filterpy EKF                            # GPMHE
        for u, y in zip(us, ys):                  for u, y in zip(us, ys):
            ekf.update(y, HJacobian, Hx)              mhe.update(u, y)
            x_filt = ekf.x      # x̂(t|t)              # form="filtering":  mhe.x is x̂(t)
            ekf.predict(u)                             # form="prediction": mhe.x is x̂(t+1)
            x_pred = ekf.x      # x̂(t+1|t)

    The t-th call ``update(u(t), y(t))`` (t = 0, 1, …) leaves ``x`` = x̂(t+1) in the prediction
    form (the paper's: the window ends one step after the newest output) and x̂(t) in the
    filtering form (the window ends at the newest output, which adds the term 2 v̄ᵀR⁻¹v̄ at time t
    to J); before any call ``x`` is the given x̂(0). The filtering form uses as arrival prior for
    x(t−M_t) the one-step prediction m_x(x̂(t−M_t−1), u) of its own filtered estimate (x0 when
    t−M_t = 0), so that no output is counted twice.

    Parameters
    ----------
    model : LearnedModel or KnownModel
        The model: means m_x, m_y, variances σ²_x, σ²_y and their gradients.
    x0 : array_like of shape (dim_x,)
        Initial estimate x̂(0); must lie in ``x_bounds``.
    horizon : int, default 15
        Window length M >= 1 (number of stages).
    eta : float, default 0.91
        Discount factor η in [0, 1]: older terms are weighted by η^{j−1} (1: no discount).
    P2 : float, array_like of shape (dim_x,) or (dim_x, dim_x), or None, default None
        Weight of the arrival prior, the inverse of the arrival covariance ``P0``: a scalar
        (times I), the diagonal, or a full symmetric positive definite matrix, as ``Q0``. None
        is the identity. Give P2 or P0, not both.
    Q0 : float, array_like of shape (dim_x,) or (dim_x, dim_x), or None, default None
        Process-noise covariance: a scalar (times I), the diagonal, or a full symmetric positive
        definite matrix. Its inverse (with the GP variances added to the diagonal) weights w̄.
        None is the identity.
    R0 : float, array_like of shape (dim_y,) or (dim_y, dim_y), or None, default None
        Output-noise covariance, as ``Q0``. None is the identity.
    x_bounds : tuple (lower, upper), or None, default None
        The box X for every window state: arrays of shape (dim_x,) (entries may be ±inf;
        lower < upper), or None for an unbounded side. None: unbounded.
    form : {"prediction", "filtering"}, default "prediction"
        Which estimate ``x`` holds after an update, see above.
    solver : {"gauss-newton", "trust-constr", "least-squares"}, default "gauss-newton"
        The window solver. "gauss-newton" is the real-time Rust solver: one Rust call per update,
        a bounded Gauss-Newton / Levenberg-Marquardt method with a block-tridiagonal
        factorisation (linear in the horizon) and a barrier phase that keeps early iterations off
        the bounds. "trust-constr" is SciPy's interior-point method with the exact gradient and
        the Gauss-Newton Hessian from Rust (slow, a general reference). "least-squares" is
        SciPy's bounded TRF on the stacked residuals with the Rust Jacobian. With a
        `KnownModel`, "gauss-newton" still solves in Rust but calls the model's Python
        functions at every window evaluation: once per window point, or once for all points
        with ``KnownModel(..., vectorized=True)``.
    solver_options : dict or None, default None
        Overrides of gpmhe's defaults. For "gauss-newton": ``max_iter`` (100), ``gtol`` (1e-6,
        on ‖z − Π(z − ∇J)‖∞ with Π the projection on the box), ``dtol`` (1e-2, see Notes),
        ``xtol`` (1e-12), ``ftol`` (1e-15), ``interior`` ("auto", "always" or "never": when the
        barrier phase runs), ``interior_zone`` (1e-5) and ``mu_init`` (0.1), ``mu_final``
        (1e-5), the first and last barrier parameter. For "trust-constr": gpmhe's ``dtol``
        (1e-4, its decrement stop, see Notes; 0 leaves the stop to SciPy's tests) and the
        "trust-constr" options of `scipy.optimize.minimize` (defaults gtol=1e-6, xtol=1e-8,
        maxiter=200, initial_barrier_parameter=0.1; SciPy's for the others). For
        "least-squares" the keywords of `scipy.optimize.least_squares` (defaults
        ftol=xtol=gtol=1e-10, max_nfev=200) except its ``loss`` and ``f_scale``, which would
        make it minimise another cost than the window's (give ``loss`` to GPMHE instead).

    P0 : float, array_like of shape (dim_x,) or (dim_x, dim_x), or None, default None
        The arrival covariance, the covariance form of ``P2`` (P2 = P0⁻¹, as filterpy's ``P``),
        in the forms ``Q0`` takes.
    arrival_mean : {"smoothed", "estimate", "filtered"}, default "smoothed"
        The arrival prior x̂(t−M_t) once the window slides: "smoothed" is the previous window's
        estimate of the new first node; "estimate" is the estimator's own earlier estimate of
        x(t−M_t) (the paper's); "filtered" is the prior of the node that leaves the window
        updated with its output and carried over its stage, linearised at the window's solution
        (the mean of the "ekf" weight's step). With "ekf" weights, "estimate" and "filtered"
        are the Kalman filter on a linear-Gaussian model (η = 1); see the user guide, *The
        window problem*, for how they compare on nonlinear plants.
    arrival_weight : {"ekf", "constant"}, default "ekf"
        The arrival weight: "ekf" updates the arrival covariance by an extended Kalman filter
        step over the node that leaves the window (starting from P0); "constant" keeps P2 (the
        paper's). The paper's setting is ``arrival_mean="estimate", arrival_weight="constant"``.
    p0 : array_like of shape (dim_p,) or None, default None
        The initial guess of a model's unknown constant parameters p (required when the model
        has parameters, ``dim_p > 0``; see `KnownModel`).
    P_p0 : float or array_like of shape (dim_p,) or (dim_p, dim_p), or None, default None
        Prior covariance of p around ``p0``; None: abs(p0)² on the diagonal (one relative unit).
    p_bounds : tuple (lower, upper) or None, default None
        Bounds of p, as ``x_bounds``.
    p_drift : float or array_like of shape (dim_p,) or None, default None
        Standard deviation of a random walk of p per step (p is estimated as a state with
        p(t+1) = p(t) plus this drift); None: 1e-4 · abs(p0), constant for any practical purpose.
    loss : {"squared", "huber", "cauchy"}, default "squared"
        The penalty ρ of each whitened output residual e (a row of R(d̄)^{-1/2} v̄, in standard
        deviations): v̄ᵀR⁻¹v̄ = Σ e² becomes Σ ρ(e). "huber": ρ = e² for abs(e) <= k,
        2k·abs(e) − k² beyond; "cauchy": ρ = k² log(1 + e²/k²). Both equal e² for small
        abs(e) and bound the pull of an outlier; see the user guide, *Data as plants send it*.
        "squared" is the cost above.
    loss_scale : float or None, default None
        The scale k of "huber" or "cauchy", in standard deviations; None: 1.345 (Huber) or
        2.385 (Cauchy). Not accepted with "squared".
    learning : bool, default False
        Keep learning the model online: the inducing outputs u of the sparse f-GPs (a
        `LearnedModel` with `SparseMultiOutputGP` f-GPs and no nominal model) are estimated by
        every window together with the states, from the fit's posterior of u as the prior; see
        the user guide, *Learning while estimating*. The arrival weight is then the joint
        prior's, whatever ``arrival_weight`` says; the prior mean of u follows
        ``arrival_mean`` (the last window's u when smoothed, the Kalman step's when filtered).
        Needs ``solver="gauss-newton"``.
    learning_options : dict or None, default None
        With ``learning``: ``drift``, the variance per step of a random walk of u (in the units
        of f squared; default 0: the plant does not change, what is learned is kept).

    Attributes
    ----------
    x : ndarray of shape (dim_x,)
        Current estimate: x̂(t+1) (prediction form) or x̂(t) (filtering form).
    P : ndarray of shape (dim_x, dim_x)
        Covariance estimate of ``x``: the last block of 4 H⁻¹ with H the Gauss-Newton Hessian of
        J (J is 4× a negative log-likelihood); with η < 1 (without learning) the covariance of
        the discounted estimate, the sandwich 4 H⁻¹GH⁻¹ with G the Gauss-Newton Hessian of the
        rows with their discounts applied twice. A linearisation, exact for linear-Gaussian
        models with the Kalman-filter settings and η = 1. Before the first update it is P2⁻¹;
        if H is singular it keeps its previous value.
    x_arrival : ndarray of shape (dim_x,)
        Arrival prior x̂(t−M_t) used in the last window: the mean the window's first node is
        tied to (not filterpy's ``x_prior``, the one-step prediction, which is ``x`` in the
        prediction form). ``x_prior`` is a deprecated alias of it (a `DeprecationWarning` on
        every use), removed in the next release.
    x_window : ndarray of shape (M_t + 1, dim_x)
        Optimal window trajectory z of the last update, oldest first (``x`` is its last row).
    P_window : ndarray of shape (M_t + 1, dim_x, dim_x)
        The covariance of every node of ``x_window``: the diagonal blocks of the matrix whose last
        block is ``P`` (4 H⁻¹ or the sandwich; on a linear-Gaussian model with the Kalman-filter
        settings, the RTS smoother's over the window). NaN where H was singular. Before the first
        update: [P2⁻¹].
    innovation : ndarray of shape (dim_y,)
        y(t) − ŷ for the last update's output, ŷ = m_y(x̂⁻, u(t)) the output predicted before
        y(t) was seen (x̂⁻: the previous ``x``, carried over the stage with u(t − 1) in the
        filtering form); NaN for channels not measured. Computed at the first read after a
        change (one or two model evaluations), from the estimator's state, then kept: NaN
        before the first update.
    S : ndarray of shape (dim_y, dim_y)
        Its covariance C P⁻ Cᵀ + R(t) + diag σ²_y(x̂⁻, u(t)), P⁻ the previous ``P`` (carried
        over the stage, + Q0 + diag σ²_x, in the filtering form), R(t) the sample's covariance
        or ``R0`` (Q0 and R0 as they are: after setting them, S is the one they would have
        given). With the Kalman-filter settings on a linear-Gaussian model: the Kalman
        filter's innovation and S.
    nis : float
        νᵀS⁻¹ν over the measured channels (NaN when none is measured): χ² with as many degrees
        of freedom as channels when the estimator is consistent (`gpmhe.consistency`).
    log_likelihood : float
        log N(y(t); ŷ, S) over the measured channels (0.0 when none is measured).
    cost : float
        Optimal cost J of the last window.
    success : bool
        Whether the last window's solver reported convergence.
    message : str
        The solver's message. With "gauss-newton" it starts with the stopping reason:
        gradient-tolerance, decrement-tolerance, step-tolerance, cost-tolerance, noise-floor
        (successes); max-iterations, no-progress (failures). With "trust-constr" it is
        "decrement-tolerance (...)" after gpmhe's decrement stop, else SciPy's message.
    nit : int
        Iterations of the last window's solver ("least-squares": function evaluations).
    nfev : int
        Window evaluations of the last update ("gauss-newton" only; 0 otherwise).
    projected_gradient : float
        Final ‖z − Π(z − ∇J)‖∞ of the last update ("gauss-newton" only; 0 otherwise).
    t : int
        Number of updates since construction or ``reset``.
    max_delay : int
        The largest ``age`` `add_delayed` accepts now.
    p : ndarray of shape (dim_p,)
        The estimate of the parameters (empty without parameters).
    P_p : ndarray of shape (dim_p, dim_p)
        Its covariance, the parameters' block of 4 H⁻¹ at the newest node.
    Q0, R0, P2, P0, eta
        The weights, settable between updates: each takes effect from the next update, is
        validated as in the constructor and changes nothing else (setting P2 or P0 restarts the
        "ekf" arrival weight; Q0, R0 and eta leave it as it is). Other names are rejected
        (``est.R = ...`` raises AttributeError).
    native : bool
        Whether the core evaluates the model without Python (and updates without the GIL): a
        `LearnedModel`, or a CasADi model compiled in the core.
    model, horizon, form, solver, solver_options, arrival_mean, arrival_weight, x_bounds
    loss, loss_scale
        The settings as given, read-only (``x_bounds`` as a (lower, upper) pair of arrays, ±inf
        where unbounded).
    p0, P_p0, p_bounds, p_drift
        The parameter settings (with parameters).
    learning, learning_options
        The learning settings (``learning_options`` as applied: ``{"drift": ...}``, empty
        without learning).
    learned_model : LearnedModel or None
        With ``learning``: the model as learned so far (the f-GPs with the current posterior
        of u), a fixed model like any other; None without.
    dim_x, dim_y, dim_u, dim_p : int
        The model's dimensions n, p, m and its number of parameters.

    Raises
    ------
    ValueError
        If ``model`` is not a `LearnedModel` or `KnownModel`, or a setting is invalid, the
        message naming it: not real numbers or the wrong shape; P2, P0, Q0 or R0 not symmetric
        positive definite, or both P2 and P0 given; ``eta`` outside [0, 1]; ``horizon`` < 1;
        lower >= upper; x0 outside the bounds; an unknown form, solver, solver option, arrival
        mean, arrival weight or loss; ``loss_scale`` with the squared loss; ``p0`` missing for
        a model with parameters, or a parameter setting for a model without.

    Warns
    -----
    gpmhe.SettingsWarning
        If Q0, R0, P2 and P0 are all None: every weight is then the identity, which is right
        only for a plant whose noises and initial error are of order one in its units:

        >>> import warnings
        >>> from gpmhe import GPMHE, KnownModel, SettingsWarning
        >>> plant = KnownModel(lambda x, u: 0.9 * x, lambda x, u: x, dim_x=1, dim_y=1)
        >>> with warnings.catch_warnings(record=True) as caught:
        ...     warnings.simplefilter("always")
        ...     _ = GPMHE(plant, x0=[0.0])               # no noise information: warns
        ...     _ = GPMHE(plant, x0=[0.0], R0=0.01)      # any of them given: silent
        >>> [(w.category.__name__, str(w.message)[:47]) for w in caught]
        [('SettingsWarning', 'Q0, R0 and P2/P0 are all None: identity weights')]

    See Also
    --------
    LearnedModel : The GP model of the GP-MHE.
    KnownModel : An exactly known model.
    gpmhe.baselines.GPEKF : The EKF on the same learned model.

    Notes
    -----
    ``dtol`` stops the "gauss-newton" solver (message "decrement-tolerance", a success) when its
    next Gauss-Newton step Δ predicts a decrease ½ΔᵀHΔ <= dtol. J is 4× a negative
    log-likelihood, so the window's Laplace posterior has covariance 4H⁻¹ and that step is
    √(dtol/2) ≈ 0.07 of its standard deviations long (for the default): the point returned is
    that close to the window optimum, far inside the estimation error, and its cost is within
    about dtol of the local minimum. ``dtol=0`` runs every window to ``gtol``. The solver also
    stops at the cost's rounding noise (message "noise-floor", a success): when a GP fit ran to
    a large σ_f, J is only accurate to about 1e-6 relative and its gradient to about 1e-3, so
    ``gtol`` cannot be reached; the solver stops once its next step predicts less decrease than
    that noise.

    ``dtol`` stops "trust-constr" (SciPy's interior-point method; message
    "decrement-tolerance", a success) by the same measure with the bounds: the decrease
    ‖r‖² − ‖r + J_r Δ‖² (J = ‖r‖², r the residuals, J_r their Jacobian) that the Gauss-Newton
    model predicts for its best step Δ inside the box is <= dtol; it is 0 exactly at a KKT point.
    The test runs once SciPy's barrier parameter is at most 1e-2 (earlier the barrier still
    steers the iterates off the bounds), at SciPy's iterate and after each of up to three
    projected Gauss-Newton steps from it (each must lower J); the first point that passes is
    returned. The default 1e-4 is 100 times below the Rust solver's, so that "trust-constr" can
    check it.

    On a solver failure (``success`` False, a `RuntimeWarning`), the window keeps whichever of
    the solver's last finite iterate and the warm start costs less; ``x`` is never NaN. Bad
    input to ``update`` raises ValueError and leaves the estimator unchanged.

    filterpy's ``Saver`` records every attribute of fixed shape (``x``, ``P``, ``x_arrival``,
    ``innovation``, ``S``, ``nis``, ``log_likelihood``, ``cost``, the solver statistics, ...), so
    ``Saver.to_array()`` works from the first update on. ``x_window`` and ``P_window``, whose
    length grows until the window is full, are not among them (they are read-only attributes
    but not properties, which ``Saver`` leaves out): record them yourself if you need them.

    See the user guide, *The window problem*, *Weights from GP variances* and *The window
    solver*.

    References
    ----------
    .. [1] T. M. Wolff, V. G. Lopez and M. A. Müller, "Robust Stability of Gaussian Process
       Based Moving Horizon Estimation".

    Examples
    --------
    Estimate the batch reactor's two concentrations from their measured sum, with the known
    model:

    >>> import numpy as np
    >>> from gpmhe import GPMHE, KnownModel
    >>> from gpmhe.systems import batch_reactor as br
    >>> model = KnownModel(br.f, br.h, dim_x=2, dim_y=1,
    ...                    f_jacobian=br.f_jacobian, h_jacobian=br.h_jacobian)
    >>> x_true, y = br.simulate(br.X_TRUE0, 10, np.random.default_rng(0))
    >>> mhe = GPMHE(model, x0=[3.0, 1.0], horizon=5, Q0=1e-3, R0=1e-2, x_bounds=br.X_BOUNDS)
    >>> for t in range(10):
    ...     x_hat = mhe.update(None, y[t])  # no input: u = None
    >>> mhe.t, mhe.success, mhe.x_window.shape
    (10, True, (6, 2))
    >>> print(np.round(mhe.x, 1), np.round(x_true[10], 1))  # x̂(10) and x(10)
    [1.6 1.6] [1.5 1.8]

    Full covariances are accepted; an invalid setting is refused, named in the message:

    >>> GPMHE(model, x0=[3.0, 1.0], Q0=[[1e-3, 5e-4], [5e-4, 1e-3]], R0=1e-2).Q0.shape
    (2, 2)
    >>> GPMHE(model, x0=[3.0, 1.0], Q0=1e-3, R0=1e-2, eta=1.5)
    Traceback (most recent call last):
        ...
    ValueError: eta: must be in [0, 1], got 1.5
    """

    def __init__(self, model, x0, horizon=15, eta=0.91, P2=None, Q0=None, R0=None,
                 x_bounds=None, form="prediction", solver="gauss-newton", solver_options=None,
                 P0=None, arrival_mean="smoothed", arrival_weight="ekf", p0=None, P_p0=None,
                 p_bounds=None, p_drift=None, loss="squared", loss_scale=None, learning=False,
                 learning_options=None):
        from gpmhe.models import KnownModel, LearnedModel

        if not isinstance(model, (KnownModel, LearnedModel)):
            raise ValueError("model: must be a gpmhe.LearnedModel or gpmhe.KnownModel, got "
                             f"{type(model).__name__}")
        dims = (model.dim_x, model.dim_y, model.dim_u, int(getattr(model, "dim_p", 0)))
        settings = MHESettings.build(
            dims, horizon=horizon, eta=eta, P2=P2, Q0=Q0, R0=R0, x_bounds=x_bounds, form=form,
            solver=solver, solver_options=solver_options, P0=P0, arrival_mean=arrival_mean,
            arrival_weight=arrival_weight, p0=p0, P_p0=P_p0, p_bounds=p_bounds, p_drift=p_drift,
            loss=loss, loss_scale=loss_scale, learning=learning, learning_options=learning_options)
        if settings.learning:
            if not isinstance(model, LearnedModel):
                raise ValueError("learning: needs a LearnedModel with sparse f-GPs, got a "
                                 f"{type(model).__name__}")
            model._check_learning()
        if Q0 is None and R0 is None and P2 is None and P0 is None:
            warnings.warn(NO_NOISE_INFORMATION, SettingsWarning, stacklevel=2)
        self._init(model, settings, x0)

    @classmethod
    def _from_settings(cls, model, settings, x0):
        """An estimator with validated ``settings`` (checkpoints, the bank's members)."""
        est = cls.__new__(cls)
        est._init(model, settings, x0)
        return est

    def _init(self, model, settings, x0):
        x0, _ = settings.check_state(x0)
        # The model the core runs: on [x; p̃] when the model has parameters.
        core_model = model._augment(settings.p_scale) if settings.dims[3] else model
        # A model with a time step runs with each sample's interval as its last input.
        timed = getattr(core_model, "_timed_model", lambda: None)()
        if timed is not None:
            core_model = timed
        object.__setattr__(self, "_dt", None if timed is None else core_model.dt)
        object.__setattr__(self, "model", model)
        object.__setattr__(self, "_settings", settings)
        object.__setattr__(self, "_core_model", core_model)
        stage = core_model._learning_stage_model() if settings.learning else core_model._stage_model()
        core = _core.MovingHorizon(stage, x0=settings.core_state(x0), **settings.core_arguments())
        if settings.learning:
            # The prior of the inducing outputs: the fit's posterior.
            g0, sigma0, _ = stage.fitted_posterior()
            core.enable_learning(g0, sigma0, settings.learning_drift)
        object.__setattr__(self, "_stage", stage)
        object.__setattr__(self, "_core", core)

    @property
    def learned_model(self):
        """The model as learned so far (``learning=True``): a `LearnedModel` whose f-GPs have the
        current posterior of their inducing outputs N(u, P_u) (the window's estimate after the
        last update; the fit's before any), a fixed model that saves, copies, predicts and can be
        certified like any other. None without learning."""
        post = self._core.learning
        if post is None:
            return None
        return self.model._with_f_posterior(self._stage.snapshot(*post))

    # ---- settings: one MHESettings value; the weights are settable -------------------------
    #: The attributes a user may set (each takes effect from the next update).
    _SETTABLE = frozenset(WEIGHTS + ("P0",))
    #: Names users of other estimators try, and what to use instead.
    _DID_YOU_MEAN = {"R": "R0", "Q": "Q0", "P": "P0 (the arrival covariance)", "x0": "reset(x0)",
                     "M": "horizon (fixed: build a new GPMHE)", "N": "horizon (fixed)"}

    def __setattr__(self, name, value):
        name = renamed(type(self), name) or name
        if name in self._SETTABLE:
            self._set_weights(**{name: value})
            return
        if name.startswith("_"):  # the class's own (and tests') private attributes
            object.__setattr__(self, name, value)
            return
        raise refused_setting(self, name, self._SETTABLE, self._DID_YOU_MEAN,
                              "the other settings are fixed at construction, the estimate "
                              "changes only through update and reset")

    def __getattr__(self, name):  # only for names the class and the instance do not have
        new = renamed(type(self), name)
        if new is None:
            raise missing_attribute(self, name)
        return getattr(self, new)

    def _set_weights(self, **changes):
        """A new settings value with ``changes``; exactly the changed weights go to the core
        (the others, and the arrival weight unless P2 changes, stay as they are). On error
        nothing changes; the settings follow the core's weights even when an interrupt lands
        right after the core took them."""
        settings, changed = self._settings.replace(**changes)
        try:
            weights = settings.core_weights(changed)
        except np.linalg.LinAlgError as e:
            raise ValueError(f"{', '.join(changed)}: {e}") from None
        version = self._core.weights_version
        try:
            self._core.set_weights(**weights)
        finally:
            if self._core.weights_version != version:
                object.__setattr__(self, "_settings", settings)

    @property
    def native(self):
        """Whether the core evaluates the model without Python (and updates without the GIL):
        True for a `LearnedModel` and a CasADi model compiled in the core, False for Python
        functions (see `KnownModel.from_casadi`, ``native``)."""
        return self._core.native


    def reset(self, x0, p0=None):
        """Forget the history and restart from the estimate x̂(0) = x0.

        Sets ``t`` to 0, ``x``, ``x_arrival`` to x0, ``x_window`` to x0 as one row, ``P`` to
        ``P0`` (= P2⁻¹), ``p`` to ``p0`` and ``P_p`` to ``P_p0``, and the solver statistics to
        their initial values. The settings (and weights set since construction) are kept.

        Parameters
        ----------
        x0 : array_like of shape (dim_x,)
            New initial estimate; must lie in ``x_bounds``.
        p0 : array_like of shape (dim_p,) or None, default None
            New parameter guess (a model with parameters only); None: the constructor's ``p0``.

        Raises
        ------
        ValueError
            If x0 or p0 has the wrong shape, is not finite or lies outside its bounds.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import GPMHE, KnownModel
        >>> model = KnownModel(lambda x, u: 0.9 * x, lambda x, u: x, dim_x=1, dim_y=1)
        >>> mhe = GPMHE(model, x0=[0.0], horizon=3)
        >>> _ = mhe.update(None, [1.0])
        >>> mhe.reset([2.0])
        >>> mhe.t, mhe.x
        (0, array([2.]))
        """
        x0, p0 = self._settings.check_state(x0, p0)
        self._core.reset(self._settings.core_state(x0, p0))

    # ---- the estimate and what the last update reported: read from the core ------------------
    # The core records an update in one step (or not at all), so these never disagree.
    @property
    def t(self):
        """Number of updates since construction or `reset`."""
        return self._core.t

    @property
    def x(self):
        """The current estimate x̂(t+1) (prediction form) or x̂(t) (filtering form)."""
        x = self._core.x
        return x[:self.dim_x].copy() if self.dim_p else x

    @window_attribute  # (not a property: see gpmhe/_filterpy.py)
    def x_window(self):
        """The last window's optimal trajectory (M_t + 1, dim_x), oldest first."""
        w = self._core.x_window
        return np.ascontiguousarray(w[:, :self.dim_x]) if self.dim_p else w

    @property
    def x_arrival(self):
        """The arrival prior x̂(t−M_t) of the last window (``x_prior`` is its deprecated
        alias)."""
        x = self._core.x_prior
        return x[:self.dim_x].copy() if self.dim_p else x

    @property
    def P(self):  # noqa: N802 (the paper's symbol)
        """Covariance estimate of ``x`` (dim_x, dim_x), see the class docstring."""
        c = self._core.covariance
        return np.ascontiguousarray(c[:self.dim_x, :self.dim_x]) if self.dim_p else c

    @window_attribute  # (not a property: see gpmhe/_filterpy.py)
    def P_window(self):  # noqa: N802
        """The covariance of every node of ``x_window`` (M_t + 1, dim_x, dim_x), see the class
        docstring; NaN when the last window's was not computable."""
        na = self.dim_x + self.dim_p
        blocks = self._core.window_covariance.reshape(-1, na, na)
        return np.ascontiguousarray(blocks[:, :self.dim_x, :self.dim_x])

    @property
    def innovation(self):
        """y(t) − ŷ for the newest output (dim_y,), ŷ predicted before y(t) was seen; NaN for
        channels not measured (and before the first update). See the class docstring."""
        return self._core.innovation()[0]

    @property
    def S(self):  # noqa: N802 (filterpy's and the Kalman filter's symbol)
        """The covariance of ``innovation`` (dim_y, dim_y), every channel."""
        return self._core.innovation()[1]

    @property
    def nis(self):
        """The normalised innovation squared νᵀS⁻¹ν over the measured channels (NaN when
        none is measured)."""
        return self._core.innovation()[2]

    @property
    def log_likelihood(self):
        """log N(y(t); ŷ, S) over the measured channels (0.0 when none is measured)."""
        return self._core.innovation()[3]

    @property
    def p(self):
        """The estimate of the parameters (dim_p,) (empty without parameters)."""
        return self._settings.scaling.parameters(self._core.x)

    @property
    def P_p(self):  # noqa: N802
        """The covariance of ``p`` (dim_p, dim_p)."""
        return self._settings.scaling.parameter_covariance(self._core.covariance)

    @property
    def cost(self):
        """Optimal cost J of the last window (0.0 before any update)."""
        return self._core.optimal_cost

    @property
    def success(self):
        """Whether the last window's solver reported convergence."""
        return self._core.success

    @property
    def nit(self):
        """Iterations of the last window's solver."""
        return self._core.nit

    @property
    def nfev(self):
        """Window evaluations of the last update ("gauss-newton"; 0 otherwise)."""
        return self._core.nfev

    @property
    def projected_gradient(self):
        """Final projected gradient of the last update ("gauss-newton"; 0 otherwise)."""
        return self._core.projected_gradient

    @property
    def message(self):
        """The solver's message for the last window."""
        return self._core.message

    def _check_step(self, u, y, R=None, dt=None):
        """The validated (u as the core takes it, y, whether y holds a measured channel, R as the
        core takes it or None, dt or None): u None stays None when the core may stand in for it
        (no input, or the filtering form; the core refuses it while an earlier update still
        waits for its input)."""
        m, p = self.dim_u, self.dim_y
        if R is not None:
            if y is None:
                raise ValueError("R: given without an output y")
            R = sample_covariance(R, p)
        dt = self._check_dt(dt)
        if u is None:
            if m and self.form != "filtering":
                raise ValueError(f"u: required (dim_u = {m}; only the filtering form accepts "
                                 "None, see set_input)")
        else:
            u = finite_vector("u", u, m, flatten=True)
        u_core = self._core_input(u)
        if y is None:
            return u_core, np.zeros(p), False, None, dt
        y, present = output_sample("y", y, p)
        if u is None and m and present and self._output_uses_input(self._core.last_input):
            raise ValueError("u: required, the model's output h depends on u (u=None is for "
                             "models whose h(x, u) does not use u)")
        return u_core, y, present, R, dt

    def _check_dt(self, dt):
        """``dt`` checked (see `check_interval`)."""
        return check_interval(dt, self._dt, self.form, self.horizon)

    def _core_input(self, u):
        """u as the core takes it: with the model's dt appended for a model with a time step
        (a placeholder until the next sample gives the interval), None kept when the core
        stands in for it."""
        if self._dt is None:
            return u
        if u is None:
            return None if self.dim_u else np.array([self._dt])
        out = np.empty(u.shape[0] + 1)  # (np.append costs a few µs per update)
        out[:-1] = u
        out[-1] = self._dt
        return out

    def _output_uses_input(self, u):
        """Whether the model's output mean h depends on u: probed once, at the current estimate
        and u, against u shifted in every entry (a model is a function of (x, u))."""
        known = self.__dict__.get("_h_uses_u")
        if known is None:
            x = self._settings.core_state(self.x, self.p)
            shifted = u + 1e-3 * (1.0 + np.abs(u))
            d = np.vstack([np.concatenate([x, u]), np.concatenate([x, shifted])])
            y0, y1 = self._core_model.stage_eval(d)[4]
            known = bool(np.any(np.abs(y1 - y0) > 1e-12 * (1.0 + np.abs(y0))))
            object.__setattr__(self, "_h_uses_u", known)
        return known

    def set_input(self, u):
        """Give u(t), the input applied after the last update, when that update had ``u=None``.

        In the filtering form, ``update(None, y(t))`` returns x̂(t) before u(t) is known (a
        controller computes it from x̂(t)); u(t) drives the next window's transition from x(t)
        to x(t+1), so it must be given before the next update.

        Parameters
        ----------
        u : array_like of shape (dim_u,)
            The input u(t).

        Raises
        ------
        ValueError
            If u is not a finite vector of dim_u values or no update is waiting for its input.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import GPMHE, KnownModel
        >>> model = KnownModel(lambda x, u: x + u, lambda x, u: x, dim_x=1, dim_y=1, dim_u=1)
        >>> mhe = GPMHE(model, x0=[0.0], horizon=3, form="filtering")
        >>> x_hat = mhe.update(None, [1.0])     # u(0) not known yet
        >>> mhe.set_input(-0.5 * x_hat)         # the controller's u(0) = -0.5 x̂(0)
        >>> _ = mhe.update(None, [0.6])
        """
        u = finite_vector("u", u, self.dim_u, flatten=True)
        self._core.set_last_input(self._core_input(u))  # refused unless an update waits for it

    @required
    def update(self, u, y=REQUIRED, R=None, dt=None):
        """Add the input and output of the next step, solve the window and update the estimate.

        The t-th call appends (u(t), y(t)), slides the window (it grows until it holds M stages),
        warm-starts it from the previous solution, solves it and sets ``x``, ``P``,
        ``x_window``, ``cost`` and the solver statistics.

        Parameters
        ----------
        u : array_like of shape (dim_u,) or None
            Input u(t); None when the model has no input (dim_u = 0), or in the filtering form
            when u(t) is not known yet (give it with `set_input` before the next update: it
            drives the transition to x(t+1); at the newest node it only enters h(x, u), so a
            model whose h depends on u needs it here: u=None with a measured y is then refused,
            checked once by evaluating h at two inputs).
        y : array_like of shape (dim_y,) or None
            Output y(t); None when there is no measurement at this step, NaN entries for
            channels not measured.
        R : float, array_like of shape (dim_y,) or (dim_y, dim_y), or None, default None
            This sample's output-noise covariance, as ``R0`` (a scalar times I, the diagonal or
            the matrix; the entries of channels not measured are not used), in place of ``R0``
            for as long as the sample is in the window (kept by copies and checkpoints). None:
            ``R0``; ``R=R0`` gives exactly the result without ``R``. Only with an output y.
        dt : float or None, default None
            The time since the previous sample (> 0), for a model with a time step
            (`KnownModel.from_ode`): the stage from the previous sample to this one integrates
            over it, u(t − 1) held, and keeps it while it is in the window (copies and
            checkpoints too). None: the model's ``dt``; ``dt=model.dt`` gives exactly the
            result without it. The first update after construction or `reset` has no previous
            sample and does not use it. The stage from this sample to the next is integrated
            over the model's ``dt`` until the next update gives its interval: in the prediction
            form x̂(t+1) is predicted over the model's ``dt``.

        Returns
        -------
        ndarray of shape (dim_x,)
            The new estimate ``x``: x̂(t+1) (prediction form) or x̂(t) (filtering form).

        Raises
        ------
        ValueError
            On bad input (shape, NaN or inf, a required u missing, u=None while h depends
            on u, ``dt`` not positive, ``dt`` for a model without a time step or in the
            prediction form with horizon 1) or bad output of a `KnownModel` callable (a wrong
            shape anywhere; NaN, inf or a ValueError at the window's start point); the
            estimator is then unchanged.
        Exception
            Any exception a `KnownModel` callable raises (``KeyboardInterrupt`` included) is
            passed on with the estimator unchanged, except a ``ValueError``,
            ``ArithmeticError`` or ``RuntimeError`` (or NaN or inf) at a point the solver only
            tries, which rejects that step.
        RuntimeError
            If the estimator is already being updated (from another thread, or from inside its
            own model callable).
        TypeError
            If called with one argument, as filterpy's ``update(z)``: the input comes first,
            ``update(None, y)`` when there is none.

        Warns
        -----
        RuntimeWarning
            If the window solver did not converge (``success`` False).

        Examples
        --------
        A scalar random walk observed directly, in the filtering form:

        >>> import numpy as np
        >>> from gpmhe import GPMHE, KnownModel
        >>> model = KnownModel(lambda x, u: x + u, lambda x, u: x, dim_x=1, dim_y=1, dim_u=1)
        >>> mhe = GPMHE(model, x0=[0.0], horizon=3, Q0=1.0, R0=1.0, form="filtering")
        >>> print(np.round(mhe.update([1.0], [2.0]), 3))  # x̂(0): halfway between x0 and y(0)
        [1.]
        >>> print(np.round(mhe.update([0.0], None), 3))  # x̂(1) = x̂(0) + u(0): no measurement
        [2.]
        >>> import copy
        >>> same = copy.deepcopy(mhe)
        >>> print(np.round(mhe.update([0.0], [4.0]), 3))  # y(2) with R0 = 1
        [3.468]
        >>> print(np.round(same.update([0.0], [4.0], R=3.0), 3))  # a noisier sample moves x̂ less
        [2.968]
        """
        if y is REQUIRED:
            raise one_argument_update(type(self))
        self._step(*self._check_step(u, y, R, dt))
        return self.x

    def add_delayed(self, y, age, R=None):
        """Add an output that was measured ``age`` steps before the newest one and arrives late.

        A lab assay, an analyser with a dead time: y belongs to time t_last − age, where t_last
        is the time of the output of the last `update`. It is written into the window's data at
        that time (next to the output already there, if any) and used from the next `update` on,
        as if it had arrived on time; ``x`` and the other attributes do not change now.

        Parameters
        ----------
        y : array_like of shape (dim_y,)
            The late output, NaN for channels not in it (at least one channel measured). A
            channel already measured at that time is refused.
        age : int
            How many steps before the newest output it was measured: 1 <= age <= ``max_delay``
            (older samples have left the window; they are refused, not folded into the arrival
            cost).
        R : float, array_like of shape (dim_y,) or (dim_y, dim_y), or None, default None
            Its output-noise covariance, as in `update` (None: ``R0``). Its channels are
            uncorrelated with those measured at that time before.

        Raises
        ------
        ValueError
            On bad input (shape, inf, no channel measured, a channel already measured at that
            time, an age outside 1 … ``max_delay``, R not symmetric positive definite); the
            estimator is then unchanged.

        Examples
        --------
        A concentration measured two steps ago arrives now:

        >>> import numpy as np
        >>> from gpmhe import GPMHE, KnownModel
        >>> model = KnownModel(lambda x, u: x, lambda x, u: x, dim_x=2, dim_y=2)
        >>> mhe = GPMHE(model, x0=[0.0, 0.0], horizon=5, Q0=1e-4, R0=1.0, form="filtering")
        >>> for t in range(4):
        ...     _ = mhe.update(None, [1.0, np.nan])  # only the first channel, every step
        >>> mhe.max_delay
        3
        >>> mhe.add_delayed([np.nan, 2.0], age=2)
        >>> print(np.round(mhe.update(None, [1.0, np.nan]), 2))  # x_2 was 0 before the assay
        [0.87 1.09]
        """
        p = self.dim_y
        y, present = output_sample("y", y, p)
        if not present:
            raise ValueError("y: has no measured channel (all NaN)")
        age = integer("age", age, low=1)
        r = None if R is None else sample_covariance(R, p)
        self._add_delayed(y, age, r)

    @exclusive
    def _add_delayed(self, y, age, r):
        self._core.add_delayed(y, age, r)

    @property
    def max_delay(self):
        """The largest ``age`` `add_delayed` accepts now (0 before the window holds an
        older output)."""
        return self._core.max_delay

    # ----------------------------------------------------------------------------------------
    @exclusive  # one update at a time per estimator (gpmhe/_threads.py)
    def _step(self, u, y, present, R=None, dt=None):
        """One update with validated input, recorded by the core in one step with everything it
        reports: the Rust solver in one call ("gauss-newton"), or a SciPy solver between the
        core's ``prepare`` and ``commit``. Nothing changes unless the core records the step.
        ``dt`` completes the last recorded input row with the interval that ends at this
        sample (nothing to complete before the first)."""
        core = self._core
        y, R = (y, R) if present else (None, None)
        u_last = None
        if dt is not None and core.t > 0:
            u_last = core.last_input.copy()
            u_last[-1] = dt
        if self.solver == "gauss-newton":
            core.update(u, y, R, u_last)
            if not core.success:  # (after the step is recorded: the warning may be an error)
                self._warn(core.message, core.t - 1, stacklevel=5)  # 5: past `exclusive`
            return
        try:
            z0, lb, ub = core.prepare(u, y, R, u_last)
            z, cost, success, nit, message = solvers.solve(
                self.solver, self._settings.solver_options, core, z0, lb, ub)
            if not success:  # (before the record: as an error it leaves nothing changed)
                self._warn(message, core.t, stacklevel=5)
            P_window = solvers.window_covariance(core, z, self.dim_x + self.dim_p)
            core.commit(z, cost, success, nit, message, P_window)
        except BaseException:
            core.abandon()  # the model's cache as before prepare: as if never started
            raise

    def _warn(self, message, t, stacklevel):
        """The RuntimeWarning of the window of update t whose solver did not converge
        (`stacklevel` points at the caller of `update` or `batch_filter`)."""
        warnings.warn(f"GPMHE window solver ({self.solver}) did not converge at t={t}: "
                      f"{message}; keeping the better of its last iterate and the warm start",
                      RuntimeWarning, stacklevel=stacklevel)

    # ---- checkpoints: save and load ---------------------------------------------------------
    def save(self, path):
        """Write the estimator's whole state (settings, history, attributes) to an ``.npz`` file.

        The file holds plain arrays only (no pickle); the model is not saved: give it again to
        `load`. An estimator loaded from the file continues exactly (bit for bit) as this one
        would with the same data.

        Parameters
        ----------
        path : str, os.PathLike or file-like object
            Destination, passed to `numpy.savez` (which appends ``.npz`` to a name without it).

        Raises
        ------
        ValueError
            If ``solver_options`` holds values that cannot be written (only numbers, strings,
            booleans, None, lists and dicts of them can).

        See Also
        --------
        load : Continue from the file.

        Examples
        --------
        >>> import io
        >>> import numpy as np
        >>> from gpmhe import GPMHE, KnownModel
        >>> from gpmhe.systems import batch_reactor as br
        >>> model = KnownModel(br.f, br.h, dim_x=2, dim_y=1)
        >>> _, y = br.simulate(br.X_TRUE0, 12, np.random.default_rng(0))
        >>> mhe = GPMHE(model, x0=[3.0, 1.0], horizon=5, Q0=1e-3, R0=1e-2, x_bounds=br.X_BOUNDS)
        >>> xs, _ = mhe.batch_filter(y[:6])
        >>> buf = io.BytesIO()
        >>> mhe.save(buf)
        >>> _ = buf.seek(0)
        >>> restored = GPMHE.load(buf, model)
        >>> restored.t
        6
        >>> a, _ = mhe.batch_filter(y[6:12])
        >>> b, _ = restored.batch_filter(y[6:12])
        >>> bool(np.array_equal(a, b))
        True
        """
        checkpoint.save(self, path)

    @classmethod
    def load(cls, path, model):
        """Continue an estimator from a file written by `save`.

        Parameters
        ----------
        path : str, os.PathLike or file-like object
            The ``.npz`` file. It is read without pickle (``allow_pickle=False``), so a file from
            an untrusted source cannot run code.
        model : LearnedModel or KnownModel
            The model the saved estimator ran on (models are not saved with the estimator). It
            must be of the same class and dimensions; for bit-identical continuation it must be
            the same model (for a `LearnedModel`, e.g. saved with `LearnedModel.save`).

        Returns
        -------
        GPMHE
            The estimator with the saved settings, history and attributes.

        Raises
        ------
        ValueError
            If the file cannot be read, is not a saved GPMHE, or an entry is missing, damaged or
            inconsistent (the message names the file and the entry), or if `model` does not fit.

        See Also
        --------
        save : Write the file.

        Examples
        --------
        >>> import io
        >>> import numpy as np
        >>> from gpmhe import GPMHE, KnownModel
        >>> from gpmhe.systems import batch_reactor as br
        >>> model = KnownModel(br.f, br.h, dim_x=2, dim_y=1)
        >>> mhe = GPMHE(model, x0=[3.0, 1.0], horizon=3, x_bounds=br.X_BOUNDS)
        >>> _ = mhe.update(None, [4.2])
        >>> buf = io.BytesIO()
        >>> mhe.save(buf)
        >>> _ = buf.seek(0)
        >>> loaded = GPMHE.load(buf, model)
        >>> loaded.t, bool(np.array_equal(loaded.x, mhe.x))
        (1, True)
        """
        return checkpoint.load(cls, path, model)
