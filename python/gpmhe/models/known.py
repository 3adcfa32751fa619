"""`KnownModel`: a model given as Python callables, CasADi functions or a continuous-time
right-hand side (the exact-model MHE of the GP-MHE paper's comparison), possibly with unknown
constant parameters p estimated with the states (``parameters.py``).

It gives the estimator, for a batch of points d = [x; u], the means f(d), h(d), zero variances and
the Jacobians (`stage_eval`), and the Rust core a stage model that calls it back
(`_stage_model`). See the user guide, *Physics models*.
"""

from __future__ import annotations

import numpy as np

from gpmhe import _core
from gpmhe._validation import (
    MAX_ABS,
    boolean,
    finite_vector,
    integer,
    points,
    positive_scalar,
    real_array,
    within_limits,
)
from gpmhe.models.base import ModelDomainError, SharedOnCopy, call_user, check_picklable, point

__all__ = ["KnownModel"]


class KnownModel(SharedOnCopy):
    """An exactly known model x(t+1) = f(x, u) + w, y = h(x, u) + v for the exact-model MHE.

    The model's means are m_x(d) = f(x, u) and m_y(d) = h(x, u) at d = [x; u], its variances
    σ²_x, σ²_y are zero, so the weights of `GPMHE` reduce to Q0⁻¹ and R0⁻¹.

    Parameters
    ----------
    f : callable
        Noise-free transition x(t+1) = f(x, u). Per point (the default): ``f(x, u)`` returns a
        (dim_x,) array for 1-D ``x`` of shape (dim_x,) and ``u`` of shape (dim_u,) (an empty
        array when dim_u = 0). With ``vectorized=True`` see below.
    h : callable
        Noise-free output y = h(x, u), returning a (dim_y,) array.
    dim_x : int
        Number of states n (>= 1).
    dim_y : int
        Number of outputs p (>= 0).
    dim_u : int, default 0
        Number of inputs m (>= 0).
    f_jacobian : callable or None, default None
        ``f_jacobian(x, u)`` returning ∂f/∂x of shape (n, n). None: central finite differences
        with step ``fd_step`` · max(1, abs(x_i)).
    h_jacobian : callable or None, default None
        ``h_jacobian(x, u)`` returning ∂h/∂x of shape (p, n); None: finite differences.
    fd_step : float, default 1e-6
        Relative step of the finite differences.
    vectorized : bool, default False
        If True, every callable receives all points of a window evaluation at once: ``X`` of
        shape (k, n) and ``U`` of shape (k, m) (k >= 1 rows; ``U`` has m = 0 columns when
        dim_u = 0), and returns f(X, U) (k, n), h(X, U) (k, p), f_jacobian(X, U) (k, n, n),
        h_jacobian(X, U) (k, p, n); row i belongs to point i. Without Jacobians, the central
        differences stack the 2n shifted copies of X with X itself and call f (and h) once on
        those (2n+1)k rows. The callables must not modify X, U in place. `predict` calls f with
        k = 1.

    dim_p : int, default 0
        Number of unknown constant parameters p, estimated by `GPMHE` with the states (its
        ``p0``): every callable then takes p as a third argument (P of shape (k, dim_p) when
        vectorised), and the Jacobians are with respect to [x; p], of shape (n, n + dim_p) and
        (p, n + dim_p). `predict` then needs p.

    Attributes
    ----------
    f, h : callable
        The model functions, as given.
    f_jacobian, h_jacobian : callable or None
        The Jacobians, as given.
    dim_x, dim_y, dim_u : int
        The dimensions n, p, m.
    fd_step : float
        The finite-difference step.
    vectorized : bool
        Whether the callables take all points at once.
    dt : float or None
        The sample time of a model made by `from_ode` (a continuous-time model integrated over
        each sample interval); None for a discrete-time model.

    Raises
    ------
    ValueError
        If a function is not callable, a dimension is not a valid integer, ``fd_step`` is not
        positive or ``vectorized`` is not a bool.

    See Also
    --------
    LearnedModel : The model learned by Gaussian processes.
    GPMHE : The estimator that uses the model.
    KnownModel.from_casadi : A known model from CasADi functions.
    KnownModel.from_ode : A known model from a continuous-time right-hand side.

    Notes
    -----
    With ``vectorized=True``, a window evaluation of the MHE (all M+1 window points) costs one
    Python call per callable instead of k (per point: k calls each, plus 2nk without
    Jacobians); this is what bounds the exact-model MHE's time with the Rust solver (see the user
    guide, *The window solver*).

    Every returned array is checked for its shape and for NaN or inf in both modes; a violation
    raises ValueError naming the callable. At the window's start point, `GPMHE.update` then
    raises it and leaves the estimator's state unchanged. NaN or inf (or a ValueError,
    ArithmeticError or RuntimeError the callable raises) at a point a solver only tries rejects
    that step, for every solver: the model may be undefined outside the region the estimates lie
    in. A wrong shape is an error wherever it happens, and any other exception is passed on.

    Gradients with respect to u are not needed by the estimator (u is data) and are reported as
    zero.

    Examples
    --------
    The batch reactor of the GP-MHE paper, per point and vectorised:

    >>> import numpy as np
    >>> from gpmhe import KnownModel
    >>> from gpmhe.systems import batch_reactor as br
    >>> model = KnownModel(br.f, br.h, dim_x=2, dim_y=1)
    >>> print(model.predict([3.0, 1.0]))
    [2.71328 1.14336]
    >>> fast = KnownModel(br.f_batch, br.h_batch, dim_x=2, dim_y=1, vectorized=True,
    ...                   f_jacobian=br.f_jacobian_batch, h_jacobian=br.h_jacobian_batch)
    >>> print(fast.predict([3.0, 1.0]))
    [2.71328 1.14336]
    """

    #: A CasADi model's functions (`from_casadi`): evaluates f, h and their Jacobians at all
    #: points in one call; None for a model of Python callables.
    _casadi = None
    #: f and ∂f/∂x in one vectorised call (`from_ode`'s integrator), or None.
    _f_joint = None
    #: How the model on the augmented state [x; p̃] is built (see `_augment`), or None for a
    #: model without parameters.
    _parameter_source = None
    dim_p = 0
    # The sample time of a model from `from_ode`; None for a discrete-time model.
    dt = None
    #: How `_timed_model` builds the model with a per-sample interval (`from_ode`), or None.
    _time_step = None

    def __init__(self, f, h, dim_x, dim_y, dim_u=0, f_jacobian=None, h_jacobian=None,
                 fd_step=1e-6, vectorized=False, dim_p=0):
        for name, fn in (("f", f), ("h", h)):
            if not callable(fn):
                raise ValueError(f"{name}: must be callable")
        for name, fn in (("f_jacobian", f_jacobian), ("h_jacobian", h_jacobian)):
            if fn is not None and not callable(fn):
                raise ValueError(f"{name}: must be callable or None")
        dim_x, dim_y, dim_u = integer("dim_x", dim_x, 1), integer("dim_y", dim_y), integer("dim_u", dim_u)
        fd_step = positive_scalar("fd_step", fd_step)
        vectorized = boolean("vectorized", vectorized)
        self.f, self.h = f, h
        self.f_jacobian, self.h_jacobian = f_jacobian, h_jacobian
        self.dim_x, self.dim_y, self.dim_u = dim_x, dim_y, dim_u
        self.fd_step = fd_step
        self.vectorized = vectorized
        self.dim_p = integer("dim_p", dim_p)
        if self.dim_p:
            self._parameter_source = ("callables",)

    @classmethod
    def from_casadi(cls, f, h, jit=False, native=True):
        """The model of two CasADi functions, differentiated by CasADi's AD.

        The dimensions are read from the functions. The result is a vectorised `KnownModel`: a
        window evaluation of the estimator is one call of one CasADi function that returns f, h
        and both Jacobians at all window points (``Function.map`` over the points, cached per
        number of points), written straight into numpy arrays.

        Parameters
        ----------
        f : casadi.Function
            The transition x(t+1) = f(x, u): inputs x (dense vector of n values) and u (dense
            vector of m values; may be left out when there is no input), one output of n values.
        h : casadi.Function or None
            The output y = h(x, u) (or h(x)): the same inputs as f, one output of p values. None
            for no outputs (p = 0).
        jit : bool, default False
            Compile the functions to machine code with CasADi's JIT (needs a C compiler on the
            PATH, checked here by compiling a test function; about a second per function when
            first used, and again after unpickling): several times faster evaluations for
            larger models. The generated files go to a temporary directory of their own, removed
            once the code is loaded: nothing is written to the working directory.
        native : bool, default True
            The estimator's core runs the model as compiled C code: CasADi generates the C code
            of f, h and their Jacobians, a C compiler (``$CC``, default ``cc``) builds it once
            into a shared library kept in gpmhe's cache directory (``$GPMHE_CACHE_DIR``, else
            ``~/.cache/gpmhe``), and an update then runs without Python and without the GIL
            (and `EstimatorBank` updates its estimators in parallel), with the same results
            as the CasADi functions give. Without a working compiler the core calls the
            functions back through Python, with a `gpmhe.SettingsWarning`. False: always call
            back.

        Returns
        -------
        KnownModel
            A model with ``vectorized=True`` whose ``f``, ``h``, ``f_jacobian`` and
            ``h_jacobian`` evaluate the CasADi functions at the rows of X (k, n) and U (k, m).

        Raises
        ------
        ValueError
            If f or h is not a ``casadi.Function`` of one or two dense vector inputs and one
            vector output of matching sizes, depends on free symbols (not among its inputs), or
            ``jit`` is True and no C compiler works (the message names the argument).
        ImportError
            If CasADi (>= 3.6) is not installed.

        See Also
        --------
        from_ode : A model from a continuous-time right-hand side.

        Notes
        -----
        The functions are expanded to CasADi's SX form when possible (faster to evaluate);
        functions with MX-only operations (e.g. a rootfinder) stay MX. Gradients with respect to
        u are reported as zero, as for every `KnownModel`.

        The model pickles (CasADi functions pickle in their serialised form; a function that
        CasADi cannot serialise, such as a Python ``casadi.Callback``, raises
        ``pickle.PicklingError``) and copies as itself. Unpickling needs CasADi.

        Examples
        --------
        The batch reactor of `gpmhe.systems.batch_reactor` in CasADi:

        >>> import casadi as ca
        >>> import numpy as np
        >>> from gpmhe import KnownModel
        >>> x = ca.SX.sym("x", 2)
        >>> rate = 0.16 * x[0] ** 2 - 0.0064 * x[1]
        >>> f = ca.Function("f", [x], [x + 0.1 * ca.vertcat(-2 * rate, rate)])
        >>> h = ca.Function("h", [x], [x[0] + x[1]])
        >>> model = KnownModel.from_casadi(f, h)
        >>> model.dim_x, model.dim_y, model.dim_u
        (2, 1, 0)
        >>> print(model.predict([3.0, 1.0]))
        [2.71328 1.14336]
        >>> print(model.f_jacobian(np.array([[1.0, 0.0]]), np.zeros((1, 0)))[0])
        [[0.936   0.00128]
         [0.032   0.99936]]
        """
        from gpmhe.models.casadi import CasadiModel, CasadiPart, import_casadi

        ca = import_casadi("KnownModel.from_casadi")
        if isinstance(f, ca.Function) and f.n_in() == 3:
            return cls._parametrised(("casadi", f, h, boolean("jit", jit),
                                      boolean("native", native)), f, h)
        casadi_model = CasadiModel(f, h, jit=boolean("jit", jit), native=boolean("native", native))
        n, m, p = casadi_model.dims
        parts = {name: CasadiPart(casadi_model, name) for name in ("f", "h", "f_jacobian", "h_jacobian")}
        model = cls(parts["f"], parts["h"], n, p, m, f_jacobian=parts["f_jacobian"],
                    h_jacobian=parts["h_jacobian"], vectorized=True)
        model._casadi = casadi_model
        return model

    @classmethod
    def from_ode(cls, rhs, h, dt, dim_x=None, dim_y=None, dim_u=None, substeps=1, method="rk4",
                 rhs_jacobian=None, h_jacobian=None, fd_step=1e-6, newton_tol=1e-10,
                 newton_max_iter=20, jit=False, dim_p=0, native=True):
        """The model of a continuous-time system dx/dt = F(x, u), y = h(x, u), sampled every
        ``dt`` with u held constant.

        f is F integrated over ``dt`` by `discretize` (``substeps`` steps of ``method``), with
        the exact Jacobian of that discrete map. With CasADi functions the integrator is built
        in CasADi and the model is `from_casadi`'s; with numpy callables the model is a
        vectorised `KnownModel` whose window evaluation integrates f and its Jacobian in one
        pass.

        Parameters
        ----------
        rhs : callable or casadi.Function
            The right-hand side F: ``rhs(X, U)`` vectorised (X (k, n), U (k, m), returning
            (k, n)), or a ``casadi.Function`` of x or (x, u).
        h : callable, casadi.Function or None
            The output: ``h(X, U)`` vectorised, returning (k, p), with a numpy ``rhs``; a
            ``casadi.Function`` of x or (x, u), or None (no outputs), with a CasADi ``rhs``.
        dt : float
            Sample time (> 0).
        dim_x, dim_y : int or None, default None
            The numbers of states and outputs: required with a numpy ``rhs``; with CasADi read
            from the functions (if given, they must agree).
        dim_u : int or None, default None
            The number of inputs (None: 0 with numpy, read from the functions with CasADi).
        substeps : int, default 1
            Integration steps per sample time.
        method : {"rk4", "implicit-midpoint", "backward-euler"}, default "rk4"
            The scheme (see `discretize`).
        rhs_jacobian : callable or None, default None
            Numpy only: ∂F/∂x, ``rhs_jacobian(X, U)`` of shape (k, n, n); None: finite
            differences.
        h_jacobian : callable or None, default None
            Numpy only: ∂h/∂x, ``h_jacobian(X, U)`` of shape (k, p, n); None: finite
            differences.
        fd_step : float, default 1e-6
            Numpy only: relative step of the finite differences.
        newton_tol : float, default 1e-10
            Implicit schemes: Newton's tolerance on the residual.
        newton_max_iter : int, default 20
            Implicit schemes: the most Newton iterations per sub-step.
        jit : bool, default False
            CasADi only: compile the model for Python's evaluations (see `from_casadi`).
        dim_p : int, default 0
            Numpy only: the number of unknown parameters p; ``rhs(X, U, P)``, ``h(X, U, P)`` and
            the Jacobians (with respect to [x; p]) then take P (k, dim_p). A CasADi ``rhs`` with
            a third input p has parameters without this (see the user guide, *Unknown
            parameters*).
        native : bool, default True
            CasADi only: the estimator's core runs the model as compiled C code (see
            `from_casadi`).

        Returns
        -------
        KnownModel
            The sampled model, ``vectorized=True``, with ``dt`` its sample time: `GPMHE`
            integrates each stage of its window over that stage's own interval when
            `GPMHE.update` is given one (``dt``), over ``dt`` otherwise.

        Raises
        ------
        ValueError
            If a setting is invalid, the dimensions are missing (numpy) or disagree with the
            functions (CasADi), or numpy and CasADi functions are mixed.
        ImportError
            If the functions are CasADi's and CasADi is older than 3.6.

        See Also
        --------
        discretize : The discrete map alone.
        from_casadi : A model from discrete-time CasADi functions.

        Examples
        --------
        A damped pendulum driven by a torque, its angle measured, 4 RK4 steps per 0.1 s:

        >>> import numpy as np
        >>> from gpmhe import KnownModel
        >>> def pendulum(X, U):
        ...     return np.column_stack([X[:, 1], -9.81 * np.sin(X[:, 0]) - 0.5 * X[:, 1] + U[:, 0]])
        >>> def angle(X, U):
        ...     return X[:, :1]
        >>> model = KnownModel.from_ode(pendulum, angle, dt=0.1, dim_x=2, dim_y=1, dim_u=1,
        ...                             substeps=4)
        >>> print(np.round(model.predict([0.5, 0.0], [0.0]), 4))
        [ 0.477  -0.4522]
        """
        from gpmhe.models.discretization import discretize, is_casadi_function

        settings = dict(substeps=substeps, method=method, fd_step=fd_step, newton_tol=newton_tol,
                        newton_max_iter=newton_max_iter)
        if is_casadi_function(rhs) and rhs.n_in() == 3:
            if h_jacobian is not None or rhs_jacobian is not None:
                raise ValueError("rhs_jacobian, h_jacobian: not used with CasADi functions")
            settings.update(jit=boolean("jit", jit), native=boolean("native", native))
            model = cls._parametrised(("ode-casadi", rhs, h, dt, settings), rhs, h)
            model.dt = float(dt)
            return model
        if dim_p:
            if dim_x is None or dim_y is None:
                raise ValueError("dim_x, dim_y: required with a numpy rhs")
            model = cls._parametrised(("ode-numpy", rhs, h, dt, rhs_jacobian, h_jacobian, settings),
                                      rhs, h, (dim_x, dim_y, dim_u or 0, dim_p))
            model._augment(np.ones(model.dim_p))  # validates the settings now
            model.dt = float(dt)
            return model
        f = discretize(rhs, dt, substeps=substeps, method=method, rhs_jacobian=rhs_jacobian,
                       fd_step=fd_step, newton_tol=newton_tol, newton_max_iter=newton_max_iter)
        if is_casadi_function(rhs):
            if h_jacobian is not None:
                raise ValueError("h_jacobian: not used with CasADi functions (CasADi differentiates h)")
            model = cls.from_casadi(f, h, jit=jit, native=native)
            for name, given, actual in (("dim_x", dim_x, model.dim_x), ("dim_y", dim_y, model.dim_y),
                                        ("dim_u", dim_u, model.dim_u)):
                if given is not None and given != actual:
                    raise ValueError(f"{name}: {given!r} disagrees with the CasADi functions' {actual}")
            model.dt = float(dt)
            model._time_step = ("casadi", rhs, h, dict(settings, jit=boolean("jit", jit),
                                                       native=boolean("native", native)))
            return model
        if is_casadi_function(h):
            raise ValueError("h: a casadi.Function needs a CasADi rhs (give both in CasADi, or "
                             "both as numpy callables)")
        if boolean("jit", jit):
            raise ValueError("jit: only with CasADi functions")
        if dim_x is None or dim_y is None:
            raise ValueError("dim_x, dim_y: required with a numpy rhs")
        model = cls(f, h, dim_x, dim_y, 0 if dim_u is None else dim_u, f_jacobian=f.jacobian,
                    h_jacobian=h_jacobian, fd_step=fd_step, vectorized=True)
        model._f_joint = f.value_and_jacobian
        model.dt = f.dt
        model._time_step = ("numpy", f, h, h_jacobian)
        return model

    def _timed_model(self):
        """This model with the interval of each sample as one more input (the last entry of
        u): f integrates over it, h ignores it. For the estimator's core, built once; None for a
        model without a time step (or with parameters: its augmented model has one)."""
        if self._time_step is None:
            return None
        timed = self.__dict__.get("_timed")
        if timed is None:
            timed = self._build_timed()
            self.__dict__["_timed"] = timed
        return timed

    def _build_timed(self):
        from gpmhe.models.discretization import TimedDynamics, WithoutTime, _casadi_discretize

        kind, *rest = self._time_step
        if kind == "casadi":
            rhs, h, settings = rest
            f = _casadi_discretize(rhs, self.dt, settings["substeps"], settings["method"],
                                   settings["newton_tol"], settings["newton_max_iter"], timed=True)
            model = type(self).from_casadi(
                f, None if h is None else _casadi_without_time(h, self.dim_u), jit=settings["jit"],
                native=settings.get("native", True))
        else:
            dynamics, h, h_jacobian = rest
            f = TimedDynamics(dynamics)
            model = type(self)(f, WithoutTime(h), self.dim_x, self.dim_y, self.dim_u + 1,
                               f_jacobian=f.jacobian,
                               h_jacobian=None if h_jacobian is None else WithoutTime(h_jacobian),
                               fd_step=self.fd_step, vectorized=True)
            model._f_joint = f.value_and_jacobian
        model.dt = self.dt  # the interval its last input replaces
        return model

    # ---- unknown parameters (models/parameters.py) ------------------------------------------
    @classmethod
    def _parametrised(cls, source, f, h, dims=None):
        """A model with parameters: its dimensions, and how `_augment` builds the model on
        [x; p̃] (``source``: its kind and the user's functions and settings)."""
        model = cls.__new__(cls)
        model.f, model.h, model.f_jacobian, model.h_jacobian = f, h, None, None
        model.fd_step, model.vectorized = 1e-6, True
        model._parameter_source = source
        if dims is None:  # CasADi: read the sizes from the functions
            n, m, n_p = (f.size1_in(i) * f.size2_in(i) for i in range(3))
            if n_p == 0:
                raise ValueError(f"f: its third input p must have at least one value in {f}")
            dims = (n, 0 if h is None else h.size1_out(0) * h.size2_out(0), m, n_p)
        model.dim_x, model.dim_y, model.dim_u, model.dim_p = dims
        model._augment(np.ones(model.dim_p))  # checks the functions fit together
        return model

    def _unit_model(self):
        """The augmented model with unit scale (p̃ = p), built once."""
        if getattr(self, "_unit", None) is None:
            self._unit = self._augment(np.ones(self.dim_p))
        return self._unit

    def _augment(self, scale):
        """The model on the augmented state [x; p̃], p = scale ⊙ p̃, p̃ constant (a model without
        parameters: ValueError)."""
        from gpmhe.models import parameters as par

        if self._parameter_source is None:
            raise ValueError("model: has no parameters (dim_p = 0)")
        kind, *rest = self._parameter_source
        n, p, m, n_p = self.dim_x, self.dim_y, self.dim_u, self.dim_p
        cls = type(self)
        if kind == "callables":
            fa, ha, fja, hja = par.augment_numpy((self.f, self.h, self.f_jacobian, self.h_jacobian),
                                                 n, n_p, p, scale, self.vectorized, False)
            return cls(fa, ha, n + n_p, p, m, fja, hja, self.fd_step, self.vectorized)
        if kind == "casadi":
            f, h, jit, *native = rest  # (older pickles: no native)
            return cls.from_casadi(*par.augment_casadi(f, h, n, n_p, scale, False), jit=jit,
                                   native=native[0] if native else True)
        if kind == "ode-casadi":
            rhs, h, dt, settings = rest
            return cls.from_ode(*par.augment_casadi(rhs, h, n, n_p, scale, True), dt, **settings)
        rhs, h, dt, rj, hj, settings = rest
        fa, ha, fja, hja = par.augment_numpy((rhs, h, rj, hj), n, n_p, p, scale, True, True)
        return cls.from_ode(fa, ha, dt, n + n_p, p, m, rhs_jacobian=fja, h_jacobian=hja, **settings)

    # ---- per point (vectorized=False) ------------------------------------------------------
    def _call(self, fn, x, u, size, name):
        v = real_array(name, call_user(fn, name, x, u)).reshape(-1)
        if v.size != size:
            raise ValueError(f"{name}: returned {v.size} values, expected {size}")
        return v

    def _jac(self, fn, jac, x, u, size, name):
        if jac is not None:
            J = real_array(name + "_jacobian", call_user(jac, name + "_jacobian", x, u))
            if J.shape != (size, self.dim_x):
                raise ValueError(f"{name}_jacobian: returned shape {J.shape}, expected {(size, self.dim_x)}")
            return J
        J = np.empty((size, self.dim_x))
        for i in range(self.dim_x):
            step = self.fd_step * max(1.0, abs(x[i]))
            xp, xm = x.copy(), x.copy()
            xp[i] += step
            xm[i] -= step
            J[:, i] = (self._call(fn, xp, u, size, name) - self._call(fn, xm, u, size, name)) / (2 * step)
        return J

    def _points_loop(self, d, k):
        n, p = self.dim_x, self.dim_y
        mx, jx = np.empty((k, n)), np.empty((k, n, n))
        my, jy = np.empty((k, p)), np.empty((k, p, n))
        for i in range(k):
            x, u = d[i, :n].copy(), d[i, n:].copy()
            mx[i] = self._call(self.f, x, u, n, "f")
            jx[i] = self._jac(self.f, self.f_jacobian, x, u, n, "f")
            if p:
                my[i] = self._call(self.h, x, u, p, "h")
                jy[i] = self._jac(self.h, self.h_jacobian, x, u, p, "h")
        return mx, jx, my, jy

    # ---- vectorised (vectorized=True) ------------------------------------------------------
    def _call_batch(self, fn, X, U, size, name, rows="one row per point"):
        v = real_array(name, call_user(fn, name, X, U))
        if v.shape != (X.shape[0], size):
            raise ValueError(f"{name}: returned shape {v.shape}, expected {(X.shape[0], size)} "
                             f"(vectorized=True: {rows})")
        return v

    def _value_and_jac_batch(self, fn, jac, X, U, size, name):
        """Values (k, size) and ∂/∂x (k, size, n) at all k points: the analytic Jacobian, or
        central differences from one call on the (2n+1)k stacked points."""
        k, n = X.shape
        if jac is not None:
            v = self._call_batch(fn, X, U, size, name)
            J = real_array(name + "_jacobian", call_user(jac, name + "_jacobian", X, U))
            if J.shape != (k, size, n):
                raise ValueError(f"{name}_jacobian: returned shape {J.shape}, expected "
                                 f"{(k, size, n)} (vectorized=True: one matrix per point)")
            return v, J
        steps = self.fd_step * np.maximum(1.0, np.abs(X))          # (k, n), as per point
        shifted = np.repeat(X[None], 2 * n + 1, axis=0)              # (2n+1, k, n)
        idx = np.arange(n)
        shifted[1 + idx, :, idx] += steps.T                          # x + step_i e_i
        shifted[1 + n + idx, :, idx] -= steps.T                      # x − step_i e_i
        Us = np.tile(U, (2 * n + 1, 1))
        rows = f"one row per point: the {k} points and their {2 * n * k} finite-difference shifts"
        out = self._call_batch(fn, shifted.reshape(-1, n), Us, size, name, rows).reshape(
            2 * n + 1, k, size)
        J = (out[1:n + 1] - out[n + 1:]) / (2.0 * steps.T[:, :, None])  # (n, k, size)
        return out[0], np.ascontiguousarray(J.transpose(1, 2, 0))

    def _values(self, d, fn, size, name):
        """fn's values (k, size) at the points d (k, n + m), without Jacobians (the regression
        targets of a LearnedModel with this nominal model)."""
        n = self.dim_x
        if self.vectorized:
            v = self._call_batch(fn, d[:, :n].copy(), d[:, n:].copy(), size, name)
        else:
            v = np.array([self._call(fn, di[:n].copy(), di[n:].copy(), size, name) for di in d])
        if not within_limits(v):
            raise ModelDomainError(f"{name}: returned NaN or inf or a value of magnitude > {MAX_ABS:g}")
        return v.reshape(d.shape[0], size)

    def _points_batch(self, d):
        n, p = self.dim_x, self.dim_y
        X, U = d[:, :n].copy(), d[:, n:].copy()  # contiguous; shared by the calls below
        if self._f_joint is not None:  # an integrator: values and Jacobian in one pass
            mx, jx = call_user(self._f_joint, "f", X, U)
        else:
            mx, jx = self._value_and_jac_batch(self.f, self.f_jacobian, X, U, n, "f")
        if p:
            my, jy = self._value_and_jac_batch(self.h, self.h_jacobian, X, U, p, "h")
        else:
            my, jy = np.zeros((d.shape[0], 0)), np.zeros((d.shape[0], 0, n))
        return mx, jx, my, jy

    # ----------------------------------------------------------------------------------------
    def predict(self, x, u=None, p=None):
        """One-step prediction m_x = f(x, u) (f(x, u, p) for a model with parameters).

        Parameters
        ----------
        x : array_like of shape (dim_x,)
            State.
        u : array_like of shape (dim_u,) or None, default None
            Input; None for no input (dim_u = 0).
        p : array_like of shape (dim_p,) or None, default None
            The parameters of a model with parameters (required then, ignored otherwise).

        Returns
        -------
        ndarray of shape (dim_x,)
            f(x, u).

        Raises
        ------
        ValueError
            If x, u or p is not a finite vector of dim_x, dim_u or dim_p values (u missing when
            dim_u > 0, p missing when dim_p > 0),
            or f returns the wrong shape, NaN, inf or a value of magnitude > 1e150.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import KnownModel
        >>> model = KnownModel(lambda x, u: 0.5 * x + u, lambda x, u: x[:1], dim_x=2, dim_y=1,
        ...                    dim_u=2)
        >>> print(model.predict([2.0, 4.0], u=[1.0, 0.0]))
        [2. 2.]
        """
        if self.dim_p:
            p = finite_vector("p", p, self.dim_p, flatten=True) if p is not None else None
            if p is None:
                raise ValueError(f"p: required (dim_p = {self.dim_p})")
            x = finite_vector("x", x, self.dim_x, flatten=True)
            return self._unit_model().predict(np.concatenate([x, p]), u)[:self.dim_x]
        x, u = point(x, u, self.dim_x, self.dim_u)
        if self.vectorized:
            v = self._call_batch(self.f, x[None, :], u[None, :], self.dim_x, "f")[0]
        else:
            v = self._call(self.f, x, u, self.dim_x, "f")
        if not within_limits(v):
            raise ModelDomainError(f"f: returned NaN or inf or a value of magnitude > {MAX_ABS:g}")
        return v

    def stage_eval(self, d):
        """Means, variances and their gradients at a batch of points d = [x; u].

        This is what the estimators evaluate at every window point. For a known model the
        variances and their gradients are zero and the mean gradients' u-columns are zero.

        Parameters
        ----------
        d : array_like of shape (k, n + m) or (n + m,)
            Points [x; u], one per row (a 1-D array is one point).

        Returns
        -------
        mean_x : ndarray of shape (k, n)
            m_x(d) = f(x, u).
        var_x : ndarray of shape (k, n)
            σ²_x(d) (zeros).
        dmean_x : ndarray of shape (k, n, n + m)
            ∂m_x/∂d.
        dvar_x : ndarray of shape (k, n, n + m)
            ∂σ²_x/∂d (zeros).
        mean_y : ndarray of shape (k, p)
            m_y(d) = h(x, u).
        var_y : ndarray of shape (k, p)
            σ²_y(d) (zeros).
        dmean_y : ndarray of shape (k, p, n + m)
            ∂m_y/∂d.
        dvar_y : ndarray of shape (k, p, n + m)
            ∂σ²_y/∂d (zeros).

        Raises
        ------
        ValueError
            If d has the wrong shape or contains NaN or inf, or a callable returns the wrong
            shape, NaN or inf.

        Examples
        --------
        Finite differences reproduce the analytic Jacobian:

        >>> import numpy as np
        >>> from gpmhe import KnownModel
        >>> from gpmhe.systems import batch_reactor as br
        >>> model = KnownModel(br.f, br.h, dim_x=2, dim_y=1)
        >>> mx, vx, dmx, dvx, my, vy, dmy, dvy = model.stage_eval([[3.0, 1.0], [1.0, 2.0]])
        >>> mx.shape, dmx.shape, my.shape, dmy.shape
        ((2, 2), (2, 2, 2), (2, 1), (2, 1, 2))
        >>> bool(np.allclose(dmx[0], br.f_jacobian([3.0, 1.0]), atol=1e-8)), float(vx.max())
        (True, 0.0)
        """
        n, m, p = self.dim_x, self.dim_u, self.dim_y
        nd = n + m
        d = points("d", d, nd, one_point=True)
        k = d.shape[0]
        if self._casadi is not None:
            return self._casadi.stage(d)
        mx, jx, my, jy = self._points_batch(d) if self.vectorized else self._points_loop(d, k)
        fd = " (finite differences)"
        for a, name in ((mx, "f"), (my, "h"),
                        (jx, "f_jacobian" if self.f_jacobian is not None else "f" + fd),
                        (jy, "h_jacobian" if self.h_jacobian is not None else "h" + fd)):
            if not within_limits(a):
                raise ModelDomainError(f"{name}: returned NaN or inf or a value of magnitude > {MAX_ABS:g}")
        if m:
            dmx, dmy = np.zeros((k, n, nd)), np.zeros((k, p, nd))
            dmx[:, :, :n], dmy[:, :, :n] = jx, jy
        else:
            dmx, dmy = np.ascontiguousarray(jx), np.ascontiguousarray(jy)
        return (np.ascontiguousarray(mx), np.zeros((k, n)), dmx, np.zeros((k, n, nd)),
                np.ascontiguousarray(my), np.zeros((k, p)), dmy, np.zeros((k, p, nd)))

    # ---- pickling ---------------------------------------------------------------------------
    def __getstate__(self):
        """Pickling needs picklable callables (module-level functions, not lambdas or local
        functions): raise a `pickle.PicklingError` naming the one that is not. The model with
        per-sample intervals is built again when needed, not pickled."""
        check_picklable("KnownModel", {name: getattr(self, name) for name in
                                       ("f", "h", "f_jacobian", "h_jacobian")})
        return {key: value for key, value in self.__dict__.items() if key != "_timed"}

    def _predict_f64(self, x, u):
        """`predict` as the Rust core's callback wants it (a bound method, so it pickles)."""
        return np.ascontiguousarray(self.predict(x, u), dtype=np.float64)

    def _stage_model(self):
        """What the Rust core evaluates (a `gpmhe._core.StageModel`): this model's Python
        functions, called back, or a CasADi model's compiled functions (see
        `gpmhe.models.casadi.CasadiModel.core_model`)."""
        if self.dim_p:
            raise ValueError("model: has parameters; the estimator runs its augmented model")
        if self._casadi is not None:
            return self._casadi.core_model()
        return _core.StageModel.callback(self.stage_eval, self.dim_x, self.dim_u, self.dim_y,
                                         predict=self._predict_f64)


def _casadi_without_time(h, m):
    """The CasADi output function h(x[, u]) as h(x, v), v = [u; dt] (m + 1 values): y does not
    depend on the interval."""
    from gpmhe.models.casadi import _vec_call, import_casadi

    ca = import_casadi("KnownModel.from_ode")
    x = ca.MX.sym("x", h.size1_in(0) * h.size2_in(0))
    v = ca.MX.sym("u", m + 1)
    out = ca.Function(h.name(), [x, v], [_vec_call(ca, h, x, v[:m])], ["x", "u"], ["y"])
    try:
        return out.expand()
    except RuntimeError:
        return out
