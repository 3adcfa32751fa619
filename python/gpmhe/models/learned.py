"""`LearnedModel`: GPs for f and h learned from logged trajectories (the GP-MHE of Wolff, Lopez &
Müller), optionally on top of a nominal `KnownModel`.

It gives the estimator, for a batch of points d = [x; u], the GP means m_x(d), m_y(d), the latent
variances σ²_x(d), σ²_y(d) and their gradients (`stage_eval`); the Rust core evaluates the GPs
itself (`_stage_model`). See the user guide, *Learned models* and *Weights from GP variances*.
"""

from __future__ import annotations

import copy

import warnings

import numpy as np

from gpmhe import _core
from gpmhe._npz import NpzReader
from gpmhe._validation import SettingsWarning, boolean, integer, points
from gpmhe.models import training
from gpmhe.models.base import SharedOnCopy, point
from gpmhe.models.known import KnownModel

__all__ = ["LearnedModel"]

_FORMAT_VERSION = 2  # of LearnedModel files (2: has_nominal; the GPs' prior means and settings)


def _dimensions(states, outputs, inputs):
    """(n, p, m) from the first trajectory of each list."""
    X0 = training.first_trajectory("states", states)
    Y0 = training.first_trajectory("outputs", outputs)
    if X0.ndim != 2:
        raise ValueError("states: must be a list of (T+1, n) arrays")
    p = 1 if Y0.ndim == 1 else Y0.shape[1]
    if inputs is None:
        return X0.shape[1], p, 0
    U0 = training.first_trajectory("inputs", inputs)
    return X0.shape[1], p, 1 if U0.ndim == 1 else U0.shape[1]


def _saved_kind(data):
    """The ``kind`` entry of a saved GP's bytes ('' if unreadable: the loader reports it)."""
    import io

    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as f:
            return str(f["kind"])
    except Exception:  # noqa: BLE001 (any damage: MultiOutputGP.load names it)
        return ""


#: Options only sparse GPs take: given to `LearnedModel.from_trajectories`, they select them.
_SPARSE_OPTIONS = {"n_inducing", "method", "inducing", "optimize_inducing"}


class LearnedModel(SharedOnCopy):
    """The GP model of GP-MHE: n independent GPs for f and p for h on inputs d = [x; u].

    The model x(t+1) = f(x, u) + w, y = h(x, u) + v is replaced by GP regressions on
    d = [x; u]: m_x(d), σ²_x(d) are the f-GPs' posterior means and latent variances, m_y(d),
    σ²_y(d) those of the h-GPs. With ``f_residual=True`` the f-GPs are trained on the increments
    x(t+1) − x(t) and m_x(d) = x + GP mean (a prior mean equal to the identity), otherwise on
    x(t+1), as in the paper [1]_. With a ``nominal`` model (f0, h0), the GPs learn the residuals
    x(t+1) − f0(x, u) and y − h0(x, u), and m_x = f0 + GP mean, m_y = h0 + GP mean (with their
    Jacobians added too); the variances are the GPs'. `GPMHE` adds the variances to its weights:
    Q(d) = diag σ²_x(d) + Q0, R(d) = diag σ²_y(d) + R0.

    Usually built with `from_trajectories`. Without a nominal model, the Rust models of ``f_gp``
    and ``h_gp`` are handed to the estimator's window, which evaluates all GPs at all window points
    in one Rust call; with one, the window calls `stage_eval` (the nominal model's Python
    callables plus the GPs), as for a `KnownModel`.

    Parameters
    ----------
    f_gp : MultiOutputGP
        Fitted GPs of f: n outputs on n + m inputs (exact, or sparse: a `SparseMultiOutputGP`).
    h_gp : MultiOutputGP or None
        Fitted GPs of h: p outputs on n + m inputs; None for no outputs (p = 0).
    dim_u : int, default 0
        Number of inputs m.
    f_residual : bool, default False
        Whether ``f_gp`` models the increments x(t+1) − x(t) rather than x(t+1).
    nominal : KnownModel or None, default None
        The nominal model (f0, h0) whose residuals the GPs model; its dimensions must match.
        Not together with ``f_residual`` (which is the nominal f0(x, u) = x).

    Attributes
    ----------
    f_gp : MultiOutputGP
        The GPs of f.
    h_gp : MultiOutputGP or None
        The GPs of h.
    dim_x, dim_y, dim_u : int
        The dimensions n, p, m.
    f_residual : bool
        As given.
    nominal : KnownModel or None
        As given.

    Raises
    ------
    ValueError
        If a GP is not a fitted `MultiOutputGP` (or `SparseMultiOutputGP`) or its input dimension
        is not n + m, or the nominal model is not a `KnownModel` of the model's dimensions or is
        given together with ``f_residual``.

    See Also
    --------
    KnownModel : An exactly known model.
    GPMHE : The estimator that uses the model.
    MultiOutputGP : The GPs inside.

    Notes
    -----
    See the user guide, *Gaussian processes* and *Weights from GP variances*.

    References
    ----------
    .. [1] T. M. Wolff, V. G. Lopez and M. A. Müller, "Robust Stability of Gaussian Process
       Based Moving Horizon Estimation".

    Examples
    --------
    Learn the batch reactor from three short noisy trajectories:

    >>> import numpy as np
    >>> from gpmhe import LearnedModel
    >>> from gpmhe.systems import batch_reactor as br
    >>> states, outputs = br.training_data(3, rng=0, steps=10)
    >>> model = LearnedModel.from_trajectories(states, outputs)
    >>> model.dim_x, model.dim_y, model.dim_u
    (2, 1, 0)
    >>> print(np.round(model.predict([2.0, 4.0]), 2), np.round(br.f([2.0, 4.0]), 2))
    [1.88 4.06] [1.88 4.06]
    """

    def __init__(self, f_gp, h_gp, dim_u=0, f_residual=False, nominal=None):
        from gpmhe.gp import MultiOutputGP, SparseMultiOutputGP

        gp_classes = (MultiOutputGP, SparseMultiOutputGP)
        if not isinstance(f_gp, gp_classes) or f_gp._core_model is None:
            raise ValueError("f_gp: must be a fitted gpmhe.MultiOutputGP or SparseMultiOutputGP")
        if h_gp is not None and (not isinstance(h_gp, gp_classes) or h_gp._core_model is None):
            raise ValueError("h_gp: must be a fitted gpmhe.MultiOutputGP, SparseMultiOutputGP or None")
        dim_u = integer("dim_u", dim_u)
        f_residual = boolean("f_residual", f_residual)
        n = f_gp.n_outputs
        if f_gp.dim != n + dim_u:
            raise ValueError(f"f_gp, dim_u: input dimension {f_gp.dim} is not dim_x + dim_u = {n + dim_u}")
        if h_gp is not None and h_gp.dim != n + dim_u:
            raise ValueError(f"h_gp, dim_u: input dimension {h_gp.dim} is not dim_x + dim_u = {n + dim_u}")
        p = 0 if h_gp is None else h_gp.n_outputs
        if nominal is not None:
            if not isinstance(nominal, KnownModel):
                raise ValueError("nominal: must be a gpmhe.KnownModel or None")
            if (nominal.dim_x, nominal.dim_y, nominal.dim_u) != (n, p, dim_u):
                raise ValueError(f"nominal: dimensions (dim_x, dim_y, dim_u) = "
                                 f"{(nominal.dim_x, nominal.dim_y, nominal.dim_u)}, the GPs' are {(n, p, dim_u)}")
            if f_residual:
                raise ValueError("nominal, f_residual: give one (f_residual is the nominal f0(x, u) = x)")
        self.f_gp, self.h_gp = f_gp, h_gp
        self.dim_x, self.dim_u = n, int(dim_u)
        self.dim_y = p
        self.f_residual = f_residual
        self.nominal = nominal

    @classmethod
    def from_trajectories(cls, states, outputs, inputs=None, f_residual=False, f_nominal=None,
                          h_nominal=None, nominal_options=None, max_points=None, warn=True,
                          **gp_options):
        """Fit the GPs of f and h on measured trajectories.

        The f-GPs regress x(t+1) (minus the nominal f0(x(t), u(t)), or minus x(t) with
        ``f_residual``) on d(t) = [x(t); u(t)], the h-GPs y(t) (minus h0) on d(t), over all
        trajectories. Unless ``gp_options`` say otherwise the GPs have a linear prior mean fitted
        by least squares, standardised bounds and the default log-normal hyperprior
        (``mean="linear", normalize=True, hyperprior="default"``); ``mean="zero",
        normalize=False, hyperprior=None`` is the paper's model. With a nominal model the
        defaults are ``mean="zero", normalize=True, hyperprior="residual"``: the nominal model is
        the prior mean, and the residual is assumed small next to the noise and smooth over the
        operating range (length-scales of about 10 standard deviations of the data unless the
        data say otherwise), so that its correction carries beyond the training data and an
        exact nominal model is left nearly unchanged. The user guide, *Learned models*,
        compares them.

        Parameters
        ----------
        states : sequence of array_like of shape (T+1, n), or one such array
            Measured state trajectories x(0..T) (T >= 1; T may differ between trajectories).
            NaN marks a missing sample: a transition is used where x(t), u(t) and x(t+1) are all
            finite.
        outputs : sequence of array_like of shape (T+1, p) or (T+1,)
            Measured outputs y(0..T), one per state trajectory; an output sample is used where
            x(t), u(t) and every entry of y(t) are finite.
        inputs : sequence of array_like of shape (T+1, m) or (T, m), or None, default None
            Inputs u(0..T) or u(0..T-1); None when there is no input (m = 0). With T rows,
            the output y(T) is not used.
        f_residual : bool, default False
            Regress the increments x(t+1) − x(t) (the nominal f0(x, u) = x, computed in Rust).
            It changes the fit only with ``mean="zero"`` or ``"constant"``: the default
            ``mean="linear"`` fits a linear function of d = [x; u] already, which contains x, so
            with it the increments give the same GPs (a `gpmhe.SettingsWarning` says so).
        f_nominal, h_nominal : callable or None, default None
            Nominal model f0(x, u) and h0(x, u) in `KnownModel`'s form (per point, or
            vectorised with ``nominal_options={"vectorized": True}``); the GPs learn what it
            misses. None: zero (the GP alone).
        nominal_options : dict or None, default None
            `KnownModel` arguments of the nominal model: ``f_jacobian``, ``h_jacobian`` (else
            finite differences), ``fd_step``, ``vectorized``.
        max_points : int or None, default None
            Use at most this many regression points per GP (evenly spaced over the data);
            exact GPs cost O(N³) to fit and O(N²) per window point.
        warn : bool, default True
            Warn (`gpmhe.FitWarning`) when a fitted GP sits at a bound or has collapsed (see
            `diagnostics`; a miscalibrated GP is reported there, not warned about).
        **gp_options
            Passed to both `MultiOutputGP` constructors (e.g. ``n_restarts``, ``random_state``,
            ``optimizer``, ``sigma_eps``, ``mean``, ``normalize``, ``hyperprior``, ``bounds``).
            With any of the sparse GPs' own options (``n_inducing``, ``method``, ``inducing``,
            ``optimize_inducing``) the GPs are `SparseMultiOutputGP` instead, for long
            trajectories (thousands of samples).

        Returns
        -------
        LearnedModel
            The model with fitted GPs.

        Raises
        ------
        ValueError
            If the trajectories' shapes do not match, contain inf, or leave fewer than 2
            complete samples, or an option is invalid.

        Warns
        -----
        ConvergenceWarning
            If a hyperparameter fit did not converge.
        FitWarning
            If a fitted GP looks unreliable (with ``warn``); the message has the numbers.
        SettingsWarning
            If ``f_residual=True`` with ``mean="linear"`` (the default), where it has no effect.

        Examples
        --------
        Without hyperparameter optimisation, on a linear system with an input:

        >>> import numpy as np
        >>> from gpmhe import LearnedModel
        >>> rng = np.random.default_rng(0)
        >>> U = rng.uniform(-1.0, 1.0, size=(30, 1))
        >>> X = np.zeros((31, 1))
        >>> for t in range(30):
        ...     X[t + 1] = 0.9 * X[t] + U[t]
        >>> model = LearnedModel.from_trajectories([X], [2.0 * X], [U], optimizer=None,
        ...                                        sigma_eps=0.01)
        >>> model.dim_x, model.dim_y, model.dim_u
        (1, 1, 1)
        >>> print(np.round(model.predict([0.5], [0.2]), 2))
        [0.65]

        Sparse GPs with (at most) 6 inducing points each:

        >>> from gpmhe.systems import batch_reactor as br
        >>> states, outputs = br.training_data(5, rng=0)
        >>> sparse = LearnedModel.from_trajectories(states, outputs, n_inducing=6)
        >>> type(sparse.f_gp).__name__, [len(z) for z in sparse.f_gp.inducing_points]
        ('SparseMultiOutputGP', [6, 6])
        """
        from gpmhe.gp import MultiOutputGP, SparseMultiOutputGP

        gp_class = SparseMultiOutputGP if _SPARSE_OPTIONS & set(gp_options) else MultiOutputGP
        f_residual, warn = boolean("f_residual", f_residual), boolean("warn", warn)
        max_points = training.check_max_points(max_points)
        has_nominal = f_nominal is not None or h_nominal is not None
        defaults = training.RESIDUAL_DEFAULTS if has_nominal else training.LEARNED_DEFAULTS
        gp_options = {**defaults, **gp_options}
        try:
            gp_class(**gp_options)  # the options' own checks, before any fit
        except TypeError as exc:
            raise ValueError(f"gp_options: {exc}") from None
        n, p, m = _dimensions(states, outputs, inputs)
        nominal = training.nominal_model(f_nominal, h_nominal, n, p, m, nominal_options)
        if nominal is not None and f_residual:
            raise ValueError("f_nominal, f_residual: give one (f_residual is the nominal f0(x, u) = x)")
        if f_residual and gp_options.get("mean") == "linear":
            warnings.warn("f_residual=True has no effect with mean='linear' (the default): the linear "
                          "mean contains x already, so the increments give the same GPs; use it with "
                          "mean='zero' or 'constant'", SettingsWarning, stacklevel=2)
        Df, Xn, Xc, Dh, Yh = training.regression_data(states, outputs, inputs, n, p, m)
        Df, Xn, Xc = training.subsample(max_points, Df, Xn, Xc)
        Dh, Yh = training.subsample(max_points, Dh, Yh)
        target_f, target_h = Xn - Xc if f_residual else Xn, Yh
        if nominal is not None:
            target_f = Xn - nominal._values(Df, nominal.f, n, "f")
            target_h = Yh - nominal._values(Dh, nominal.h, p, "h") if p else Yh
        f_gp = gp_class(**gp_options).fit(Df, target_f)
        h_gp = gp_class(**gp_options).fit(Dh, target_h) if p else None
        model = cls(f_gp, h_gp, dim_u=m, f_residual=f_residual, nominal=nominal)
        if warn:
            model._warn_problems()
        return model

    def predict(self, x, u=None):
        """One-step prediction m_x(d) at one point d = [x; u].

        Parameters
        ----------
        x : array_like of shape (dim_x,)
            State.
        u : array_like of shape (dim_u,) or None, default None
            Input; None when dim_u = 0.

        Returns
        -------
        ndarray of shape (dim_x,)
            The f-GPs' posterior mean (plus x with ``f_residual``).

        Raises
        ------
        ValueError
            If x or u is not a finite vector of dim_x or dim_u values (u missing when dim_u > 0).

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import LearnedModel
        >>> from gpmhe.systems import batch_reactor as br
        >>> states, outputs = br.training_data(3, rng=0, steps=10)
        >>> model = LearnedModel.from_trajectories(states, outputs, optimizer=None,
        ...                                        sigma_eps=0.01)
        >>> print(np.round(model.predict([2.0, 4.0]), 1), np.round(br.f([2.0, 4.0]), 1))
        [1.9 4.1] [1.9 4.1]
        """
        x, u = point(x, u, self.dim_x, self.dim_u)
        mean = self._gp_stage_model().predict(x, u)  # (plus x with f_residual)
        if self.nominal is not None:
            return mean + self.nominal.predict(x, u)
        return mean

    def stage_eval(self, d):
        """Means, latent variances and their gradients at a batch of points d = [x; u].

        Parameters
        ----------
        d : array_like of shape (k, n + m) or (n + m,)
            Points [x; u], one per row (a 1-D array is one point).

        Returns
        -------
        mean_x : ndarray of shape (k, n)
            m_x(d).
        var_x : ndarray of shape (k, n)
            σ²_x(d), the f-GPs' latent variances.
        dmean_x : ndarray of shape (k, n, n + m)
            ∂m_x/∂d.
        dvar_x : ndarray of shape (k, n, n + m)
            ∂σ²_x/∂d.
        mean_y : ndarray of shape (k, p)
            m_y(d).
        var_y : ndarray of shape (k, p)
            σ²_y(d).
        dmean_y : ndarray of shape (k, p, n + m)
            ∂m_y/∂d.
        dvar_y : ndarray of shape (k, p, n + m)
            ∂σ²_y/∂d.

        See Also
        --------
        KnownModel.stage_eval : The same for a known model.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import LearnedModel
        >>> from gpmhe.systems import batch_reactor as br
        >>> states, outputs = br.training_data(3, rng=0, steps=10)
        >>> model = LearnedModel.from_trajectories(states, outputs, optimizer=None,
        ...                                        sigma_eps=0.01)
        >>> mx, vx, dmx, dvx, my, vy, dmy, dvy = model.stage_eval([[2.0, 4.0], [1.0, 3.0]])
        >>> mx.shape, vx.shape, dmx.shape, my.shape, dmy.shape
        ((2, 2), (2, 2), (2, 2, 2), (2, 1), (2, 1, 2))
        >>> bool(np.all(vx > 0))
        True
        """
        d = points("d", d, self.dim_x + self.dim_u, one_point=True)
        parts = self._gp_stage_model().evaluate(d)  # the core's evaluation, residual included
        return parts if self.nominal is None else self._add_nominal(d, parts)

    # ---- diagnostics -------------------------------------------------------------------------
    def diagnostics(self):
        """Fit diagnostics of every GP: ``{"f": [...], "h": [...]}``, one
        `gpmhe.FitDiagnostics` per state and per output (see
        `MultiOutputGP.diagnostics`).

        Returns
        -------
        dict
            ``"f"``: n diagnostics, ``"h"``: p diagnostics (empty without outputs).

        Examples
        --------
        >>> from gpmhe import LearnedModel
        >>> from gpmhe.systems import batch_reactor as br
        >>> states, outputs = br.training_data(3, rng=0)
        >>> model = LearnedModel.from_trajectories(states, outputs, random_state=0, warn=False)
        >>> [len(v) for v in model.diagnostics().values()]
        [2, 1]
        """
        return {"f": self.f_gp.diagnostics(), "h": [] if self.h_gp is None else self.h_gp.diagnostics()}

    def summary(self):
        """A printable table of the GPs' `diagnostics` (one row per GP) with the problems found.

        Returns
        -------
        str
            The tables of the f- and h-GPs.

        Examples
        --------
        >>> from gpmhe import LearnedModel
        >>> from gpmhe.systems import batch_reactor as br
        >>> states, outputs = br.training_data(3, rng=0)
        >>> model = LearnedModel.from_trajectories(states, outputs, random_state=0, warn=False)
        >>> print(model.summary().splitlines()[0])
        f-GPs (mean="linear", N=90)
        """
        from gpmhe.gp.diagnostics import summary_table

        parts = [summary_table(f'f-GPs (mean="{self.f_gp.mean}", N={len(self.f_gp.D_train)})',
                               self.f_gp.diagnostics(), [f"x{i + 1}" for i in range(self.dim_x)])]
        if self.h_gp is not None:
            parts.append(summary_table(f'h-GPs (mean="{self.h_gp.mean}", N={len(self.h_gp.D_train)})',
                                       self.h_gp.diagnostics(), [f"y{i + 1}" for i in range(self.dim_y)]))
        return "\n".join(parts)

    def _warn_problems(self):
        import warnings

        from gpmhe.gp.diagnostics import FitWarning

        found = [f"{kind}-GP {i + 1}: {problem}" for kind, diags in self.diagnostics().items()
                 for i, dg in enumerate(diags) for problem in dg.warnings]
        if found:
            warnings.warn("LearnedModel: " + "; ".join(found) + " (print model.summary() for all numbers)",
                          FitWarning, stacklevel=3)

    def _add_nominal(self, d, gp_parts):
        """The GPs' stage values plus the nominal model's means and mean Jacobians."""
        nom = self.nominal.stage_eval(d)
        out = [np.ascontiguousarray(a) for a in gp_parts]
        for i in (0, 2, 4, 6):  # means and their gradients
            out[i] = out[i] + nom[i]
        return tuple(out)

    def _predict_f64(self, x, u):
        """`predict` as the Rust core's callback wants it (a bound method, so it pickles)."""
        return np.ascontiguousarray(self.predict(x, u), dtype=np.float64)

    def _stage_model(self):
        """What the Rust core evaluates (a `gpmhe._core.StageModel`): the GPs themselves; with a
        nominal model, `stage_eval` (the GPs' values from the core plus the nominal model's),
        called back."""
        if self.nominal is not None:
            return _core.StageModel.callback(self.stage_eval, self.dim_x, self.dim_u, self.dim_y,
                                             predict=self._predict_f64)
        return self._gp_stage_model()

    def _check_learning(self):
        """ValueError unless the f-GPs can learn online (`GPMHE`, ``learning=True``): sparse GPs
        (the inducing outputs are what is learned) without a nominal model."""
        from gpmhe.gp import SparseMultiOutputGP

        if not isinstance(self.f_gp, SparseMultiOutputGP):
            raise ValueError("learning: needs sparse f-GPs (a SparseMultiOutputGP: "
                             "LearnedModel.from_trajectories(..., n_inducing=...)); their inducing "
                             "outputs are what is learned")
        if self.nominal is not None:
            raise ValueError("learning: not with a nominal model")

    def _learning_stage_model(self):
        """The core's model of an estimator that learns: the f-GPs with their inducing outputs
        estimated by the window (`gpmhe._core.StageModel.learning`)."""
        self._check_learning()
        h = None if self.h_gp is None else self.h_gp._core_model
        return _core.StageModel.learning(self.f_gp._core_model, h, self.dim_u, self.f_residual)

    def _with_f_posterior(self, core_f):
        """This model with the f-GPs' core model ``core_f`` (the same GPs with another posterior
        of their inducing outputs): a new, independent `LearnedModel`."""
        f_gp = copy.copy(self.f_gp)
        fit = f_gp._fitted
        f_gp._fitted = fit._replace(model=core_f)
        f_gp._diagnostics = None
        return LearnedModel(f_gp, self.h_gp, self.dim_u, self.f_residual, self.nominal)

    def __getstate__(self):
        """Pickles without the core's view of the GPs (`_gp_stage_model` builds it again)."""
        state = dict(self.__dict__)
        state.pop("_gp_core", None)
        return state

    def _gp_stage_model(self):
        """The GPs as the core evaluates them (the one implementation of the learned model's
        values: `stage_eval` and `predict` read them from here); f's residual form applies
        without a nominal model."""
        f = self.f_gp._core_model
        h = None if self.h_gp is None else self.h_gp._core_model
        cached = self.__dict__.get("_gp_core")
        # Built once per fit of the GPs (setting a GP's theta refits it into a new core model).
        if cached is None or cached[0] is not f or cached[1] is not h:
            cached = (f, h, _core.StageModel.gp(f, h, self.dim_u,
                                                self.f_residual and self.nominal is None))
            self.__dict__["_gp_core"] = cached
        return cached[2]

    def save(self, path):
        """Save both GPs and the settings to one ``.npz`` file (no pickle).

        A nominal model's Python functions are not saved: pass the same nominal model to `load`.

        Parameters
        ----------
        path : str, os.PathLike or file-like object
            Destination, passed to `numpy.savez`.

        See Also
        --------
        load : Read the file back.

        Examples
        --------
        >>> import io
        >>> import numpy as np
        >>> from gpmhe import LearnedModel
        >>> from gpmhe.systems import batch_reactor as br
        >>> states, outputs = br.training_data(3, rng=0, steps=10)
        >>> model = LearnedModel.from_trajectories(states, outputs, optimizer=None)
        >>> buf = io.BytesIO()
        >>> model.save(buf)
        >>> _ = buf.seek(0)
        >>> loaded = LearnedModel.load(buf)
        >>> bool(np.array_equal(loaded.predict([1.0, 2.0]), model.predict([1.0, 2.0])))
        True
        """
        import io

        blobs = {}
        for name, gp in (("f_gp", self.f_gp), ("h_gp", self.h_gp)):
            if gp is not None:
                buf = io.BytesIO()
                gp.save(buf)
                blobs[name] = np.frombuffer(buf.getvalue(), dtype=np.uint8)
        np.savez(path, kind="LearnedModel", format_version=_FORMAT_VERSION, dim_u=self.dim_u,
                 f_residual=self.f_residual, has_nominal=self.nominal is not None, **blobs)

    @classmethod
    def load(cls, path, nominal=None):
        """Load a model written by `save`.

        Parameters
        ----------
        path : str, os.PathLike or file-like object
            The ``.npz`` file.
        nominal : KnownModel or None, default None
            The nominal model the saved model was fitted with (required then, refused
            otherwise).

        Returns
        -------
        LearnedModel
            The model with its fitted GPs.

        Raises
        ------
        ValueError
            If the file is not a saved `LearnedModel`, or ``nominal`` is missing or not
            expected.

        Examples
        --------
        >>> import io
        >>> from gpmhe import LearnedModel
        >>> from gpmhe.systems import batch_reactor as br
        >>> states, outputs = br.training_data(3, rng=0, steps=10)
        >>> buf = io.BytesIO()
        >>> LearnedModel.from_trajectories(states, outputs, optimizer=None).save(buf)
        >>> _ = buf.seek(0)
        >>> model = LearnedModel.load(buf)
        >>> model.dim_x, model.dim_y, model.f_gp.n_outputs
        (2, 1, 2)
        """
        import io

        from gpmhe.gp import MultiOutputGP
        from gpmhe.gp import SparseMultiOutputGP

        # Every entry is checked (a ValueError names the file and the entry): see gpmhe._npz.
        # Files of gpmhe <= 0.1 have no format version.
        with NpzReader(path, "LearnedModel", _FORMAT_VERSION, require_version=False) as f:
            gps = {}
            for name in ("f_gp", "h_gp"):
                if name == "h_gp" and name not in f:
                    gps[name] = None
                    continue
                blob = f.raw(name)
                if blob.dtype != np.uint8 or blob.ndim != 1:
                    raise f.error(name, "must be the bytes of a saved MultiOutputGP")
                try:
                    data = blob.tobytes()
                    sparse = _saved_kind(data) == SparseMultiOutputGP._kind
                    gps[name] = (SparseMultiOutputGP if sparse else MultiOutputGP).load(io.BytesIO(data))
                except ValueError as e:
                    raise f.error(name, f"is not a valid MultiOutputGP ({e})") from None
            dim_u, f_residual = f.integer("dim_u"), f.boolean("f_residual")
            has_nominal = f.boolean("has_nominal") if f.version >= 2 else False
            if has_nominal != (nominal is not None):
                raise ValueError(f"nominal: {f.name} was saved " + (
                    "with a nominal model: pass it as nominal=" if has_nominal else "without a nominal model"))
            try:
                return cls(gps["f_gp"], gps["h_gp"], dim_u=dim_u, f_residual=f_residual, nominal=nominal)
            except ValueError as e:
                raise ValueError(f"path: {f.name}: the GPs do not make a model ({e})") from None
