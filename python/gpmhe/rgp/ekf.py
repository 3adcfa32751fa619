"""`RGPEKF`: the RGP-dKF of Husmann, Weishaupt & Aschemann (§3), an EKF that estimates the state
of x_{k+1} = f(x_k, u_k, z(ζ_k)), y_k = h(x_k) + v_k when z is *not* measured: the recursive GPs'
basis-vector weights are appended to the EKF state and learned from y.

The per-step numerics (J_k by triangular solves with K's Cholesky factor, the structured covariance
prediction, the EKF update) run in Rust (``gpmhe._core``), with the GIL released when n + Σ n_b ≥ 200
(smaller steps take a few µs, less than releasing the GIL costs under contention). This module
validates the constructor's inputs; each filter step is one core call, which also calls the user's
model functions (f, A, e in ``predict``; h, H in ``update``) and checks their results.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

import numpy as np

from gpmhe._core import NumericalError, RecursiveGPCore, RGPEKFCore
from gpmhe._validation import (
    MAX_ABS,
    boolean,
    finite_vector,
    float_array,
    integer,
    positive_scalar,
    symmetric_matrix,
)

from gpmhe.rgp.recursive import ArrayLike, RecursiveGP

__all__ = ["RGPEKF"]


def _gp_entries(prefix: str, g: RecursiveGP) -> dict:
    """The checkpoint entries of one GP: its basis ("grid": the constructor's arguments;
    "points": the arguments of ``RecursiveGPCore.from_points``) and its weights as stored."""
    _, args, (mean, cov) = g._core.__reduce__()
    entries = {prefix + "mean": mean, prefix + "cov": cov}
    if g.n_points is not None:
        entries.update({
            prefix + "basis": "grid", prefix + "lower": g.lower, prefix + "upper": g.upper,
            prefix + "n_points": np.asarray(g.n_points, dtype=np.int64),
            prefix + "params": np.array([g.sigma_K, g.L, g.sigma_r, g.sigma_p])})
        return entries
    points, sigma_k, lengthscales, jitter, prior_mean, sigma_r, sigma_p = args
    entries.update({
        prefix + "basis": "points", prefix + "points": points,
        prefix + "lengthscales": lengthscales,
        prefix + "params": np.array([sigma_k, jitter, sigma_r, sigma_p]),
        prefix + "has_prior_mean": prior_mean is not None,
        prefix + "prior_mean": np.zeros(len(lengthscales) + 1) if prior_mean is None else prior_mean})
    return entries


def _gp_from_entries(fl: Any, prefix: str) -> RecursiveGP:
    """The GP that `_gp_entries` saved under `prefix` in the open checkpoint `fl` (a
    `gpmhe._npz.NpzReader`), with its weights exactly as they were."""
    basis = fl.string(prefix + "basis") if fl.version >= 2 else "grid"
    if basis not in ("grid", "points"):
        raise fl.error(prefix + "basis", f"must be 'grid' or 'points', got {basis!r}")
    params = fl.floats(prefix + "params", (4,))
    try:
        if basis == "grid":
            g = RecursiveGP(fl.floats(prefix + "lower", (None,)), fl.floats(prefix + "upper", (None,)),
                            [int(v) for v in fl.array(prefix + "n_points", "i", (None,))], *params)
        else:
            points = fl.floats(prefix + "points", (None, None))
            prior_mean = fl.floats(prefix + "prior_mean", (points.shape[1] + 1,))
            if not fl.boolean(prefix + "has_prior_mean"):
                prior_mean = None
            sigma_k, jitter, sigma_r, sigma_p = (float(v) for v in params)
            core = RecursiveGPCore.from_points(points, sigma_k, fl.floats(prefix + "lengthscales", (None,)),
                                               jitter, prior_mean, sigma_r, sigma_p)
            g = RecursiveGP._on_points(core, sigma_r, sigma_p)
        g._core.__setstate__((fl.floats(prefix + "mean", (None,)), fl.floats(prefix + "cov", (None, None))))
    except (ValueError, NumericalError) as err:
        raise ValueError(f"path: {fl.name}: entries '{prefix}*' do not make a RecursiveGP ({err})") from None
    return g


def _as_fn(name: str, value: Any, shape: tuple[int, ...]) -> Callable[..., np.ndarray] | np.ndarray:
    """A user Jacobian: a callable, or a constant array validated now."""
    if callable(value):
        return value
    a = float_array(name, value, copy=True)
    if a.shape != shape and not (a.ndim <= 1 and a.size == shape[0] and shape[1:] == (1,)):
        raise ValueError(f"{name}: expected shape {shape}{' or ' + str(shape[:1]) if shape[1:] == (1,) else ''}, "
                         f"got {a.shape}")
    return np.ascontiguousarray(a.reshape(shape))


class RGPEKF:
    """The RGP-dKF: an extended Kalman filter that learns the disturbance model z(ζ) online.

    System (eq. 7):  x_{k+1} = f(x_k, u_k, z_k),  z_k = z(ζ_k),  y_k = h(x_k) + v_k,
    with v_k ~ N(0, R_x) and process noise N(0, Q_x). Each unknown z_j(ζ_j) (one per column of e)
    is a :class:`RecursiveGP` whose weights μ_zj are appended to the state:
    μ = [x; μ_z1; …; μ_zq] with covariance C, initially blockdiag(P0, C_z1, …) (C_z = K for a fresh
    GP). Per step (paper §3.4):

    1. ``predict(u, zeta)``: J_k and μ_z^p = J_k μ_z; x⁻ = f(x, u, μ_z^p);
       Ã = [[A, e J_k], [0, I]], C⁻ = Ã C Ãᵀ + ẽ (σ_K² − J_k K J_kᵀ + σ_r²) ẽᵀ
       + blockdiag(Q_x, σ_p² I), with A = ∂f/∂x and e = ∂f/∂z at (x, u, μ_z^p). Only the first n
       rows of Ã differ from I, so this costs O(N (n² + n_b)) instead of O(N³), N = n + Σ n_b.
    2. ``update(y)``: EKF update with H̃ = [H, 0], H = ∂h/∂x at the *predicted* state
       (variant 4a). With ``learning = False`` (variant 4b) only the states are updated: the
       weights' mean and covariance stay as predicted and the state rows get the consistent
       (Schmidt) update x += K_x ν, C[x, ·] −= K_x H C[x, ·].

    With ``pure_prediction=True`` (paper §3.2) the GPs are fixed, trained models: their weights are
    not part of the state and each enters as a noisy input with variance
    σ_K² − J K Jᵀ + J C_z Jᵀ + σ_r². A sparse GP trained offline serves as such a model, or as
    the starting point of learning, through `RecursiveGP.from_sparse` (a prior mean m(ζ) of it is
    added to μ_z^p).

    Parameters
    ----------
    dim_x : int
        Number of states n.
    f : callable f(x, u, z) -> (n,)
        Discrete-time transition. ``z`` is a float for one GP, an array of q values for several.
    A : callable A(x, u, z) -> (n, n), or constant array
        ∂f/∂x.
    e : callable e(x, u, z) -> (n,) or (n, q), or constant array
        ∂f/∂z.
    h : callable h(x) -> (p,)
        Measurement function.
    H : callable H(x) -> (p, n), or constant array_like of shape (p, n) or (n,)
        ∂h/∂x (a 1-D array is one output row).
    Q_x : array_like of shape (n, n), or float (times I)
        State process-noise covariance.
    R_x : array_like of shape (p, p), or float (times I)
        Measurement-noise covariance.
    x0 : array_like of shape (n,)
        Initial state estimate.
    P0 : array_like of shape (n, n), or float (times I)
        Initial state covariance.
    gps : RecursiveGP or sequence of RecursiveGP
        One GP per disturbance (the paper's "repeated implementation"); their basis vectors (a
        grid, or a sparse GP's inducing inputs with `RecursiveGP.from_sparse`), kernels, σ_r,
        σ_p and *current* weights define the GP part. They are copied, not modified.
    learning : bool, default True
        True: variant 4a (learn the GP); False: variant 4b (states only). Can be changed any time.
    pure_prediction : bool, default False
        Paper §3.2: the GPs are used as fixed noisy inputs, nothing is learned.

    Attributes
    ----------
    x : ndarray of shape (n,)
        State estimate. Can be assigned as in filterpy (``kf.x = ...``; validated, ValueError
        and no change on bad input).
    P : ndarray of shape (n, n)
        Its covariance, the state block of C. Can be assigned (symmetric positive semi-definite
        or a scalar times I); assigning it resets the states' cross-covariance with the GP
        weights to zero so that C stays positive semi-definite.
    mu : ndarray of shape (N,)
        Augmented mean [x; μ_z1; …; μ_zq], N = n + Σ n_b (N = n with ``pure_prediction``).
    C : ndarray of shape (N, N)
        Augmented covariance.
    z_pred : ndarray of shape (q,)
        μ_z^p = J_k μ_z of the last ``predict``.
    y : ndarray of shape (p,)
        Last innovation y − h(x⁻); NaN before the first update (shape (0,) while p is not
        known), so that filterpy's ``Saver`` records one shape from the start.
    S : ndarray of shape (p, p)
        Its covariance H̃ C⁻ H̃ᵀ + R_x; NaN before the first update, as ``y``.
    log_likelihood : float
        log N(y; h(x⁻), S) of the last update; NaN before the first.
    likelihood : float
        exp(log_likelihood).
    f, h : callable
        The model functions. They are read at every step, so they can be reassigned between
        steps.
    Q_x, R_x : ndarray
        The noise covariances, read at every step; can be reassigned between steps, validated
        as in the constructor (a bad value raises ValueError naming it and the old value stays).
        The arrays returned are read-only: assign a new value to change one.
    learning : bool
        Variant 4a (True) or 4b (False); can be changed any time.
    pure_prediction : bool
        As given.
    gps : list of RecursiveGP
        Copies of the given GPs (grids and hyperparameters; their weights are not updated, use
        `gp_weights`).
    dim_x, dim_z : int
        Number of states n and of GPs q.
    dim_y : int or None
        Number of outputs p (None until known from R_x, H or the first update).

    Raises
    ------
    ValueError
        If a setting is invalid (shapes, non-callable f or h, covariances not symmetric positive
        semi-definite, ``gps`` empty).

    See Also
    --------
    RecursiveGP : The recursive GP, learned from direct measurements.
    gpmhe.systems.second_order : The paper's example, with `make_rgp_dkf`.

    Notes
    -----
    Internally the weights of a GP with σ_p = 0 are kept whitened (L⁻¹ μ_z, with K = L Lᵀ), an
    exact change of coordinates that saves one triangular solve per step; ``mu``, ``C`` and
    ``gp_weights`` return them in the weights' coordinates. See the user guide, *The RGP-dKF*.

    References
    ----------
    .. [1] R. Husmann, S. Weishaupt and H. Aschemann, "Direct Integration of Recursive Gaussian
       Process Regression Into Extended Kalman Filters With Application to Vapor Compression
       Cycle Control".

    Examples
    --------
    A scalar plant x⁺ = 0.5 x + u + z(ζ) with the unknown z(ζ) = sin(ζ), measured state [1]_:

    >>> import numpy as np
    >>> from gpmhe import RGPEKF, RecursiveGP
    >>> gp = RecursiveGP(-2.0, 2.0, 9, sigma_K=2.0, L=1.0, sigma_r=0.01)
    >>> kf = RGPEKF(dim_x=1, f=lambda x, u, z: 0.5 * x + u + z, A=[[0.5]], e=[[1.0]],
    ...             h=lambda x: x, H=[[1.0]], Q_x=1e-6, R_x=1e-4, x0=[0.0], P0=1e-4, gps=gp)
    >>> rng = np.random.default_rng(0)
    >>> x = 0.0
    >>> for k in range(300):
    ...     u, zeta = rng.uniform(-1.0, 1.0), rng.uniform(-2.0, 2.0)
    ...     kf.predict(u, zeta)
    ...     x = 0.5 * x + u + np.sin(zeta)
    ...     kf.update([x + 0.01 * rng.standard_normal()])
    >>> kf.mu.shape, kf.C.shape  # one state and 9 weights
    ((10,), (10, 10))
    >>> print(np.round(kf.gp_predict([0.5, 1.0]), 1), np.round(np.sin([0.5, 1.0]), 1))
    [0.5 0.8] [0.5 0.8]
    """

    def __init__(
        self,
        dim_x: int,
        f: Callable[..., Any],
        A: Any,
        e: Any,
        h: Callable[..., Any],
        H: Any,
        Q_x: Any,
        R_x: Any,
        x0: ArrayLike,
        P0: Any,
        gps: RecursiveGP | Sequence[RecursiveGP],
        learning: bool = True,
        pure_prediction: bool = False,
    ) -> None:
        n = integer("dim_x", dim_x, low=1)
        if not callable(f):
            raise ValueError("f: must be callable f(x, u, z)")
        if not callable(h):
            raise ValueError("h: must be callable h(x)")
        try:
            gp_list = [gps] if isinstance(gps, RecursiveGP) else list(gps)
        except TypeError:
            gp_list = []
        if not gp_list or not all(isinstance(g, RecursiveGP) for g in gp_list):
            raise ValueError("gps: expected a RecursiveGP or a non-empty sequence of them")
        q = len(gp_list)
        x0a = float_array("x0", x0, copy=True).reshape(-1)
        if x0a.size != n:
            raise ValueError(f"x0: expected {n} values, got {x0a.size}")
        self.dim_x, self.dim_z = n, q
        self.f, self.h = f, h
        self._A = _as_fn("A", A, (n, n))
        self._e = _as_fn("e", e, (n, q))
        self._Q_x = symmetric_matrix("Q_x", Q_x, n)
        self.dim_y: int | None = None
        self._R_x, self.dim_y = self._noise_r(R_x)
        self._H = H if callable(H) else None
        if not callable(H):
            Ha = float_array("H", H, copy=True)
            Ha = Ha.reshape(1, -1) if Ha.ndim == 1 else Ha
            if Ha.ndim != 2 or Ha.shape[1] != n:
                raise ValueError(f"H: expected shape (p, {n}), got {Ha.shape}")
            if self.dim_y is not None and Ha.shape[0] != self.dim_y:
                raise ValueError(f"H, R_x: H has {Ha.shape[0]} rows but R_x is {self.dim_y}x{self.dim_y}")
            self._H = np.ascontiguousarray(Ha)
            self.dim_y = Ha.shape[0]
        if self._R_x.ndim == 0 and self.dim_y is not None:
            self._R_x = float(self._R_x) * np.eye(self.dim_y)
        self.gps = [g.copy() for g in gp_list]
        self._zeta_total = sum(g.dim_zeta for g in self.gps)
        self._scalar_zeta = self._zeta_total == 1
        self._zbuf = np.zeros(1)
        self._A_const = None if callable(self._A) else self._A
        self._e_const = None if callable(self._e) else self._e
        self._H_const = None if callable(self._H) else self._H
        # the callables among A, e, H (None: the constant stored in the core)
        self._A_fn = self._A if callable(self._A) else None
        self._e_fn = self._e if callable(self._e) else None
        self._H_fn = self._H if callable(self._H) else None
        self.learning = boolean("learning", learning)
        self.pure_prediction = boolean("pure_prediction", pure_prediction)
        self._core = RGPEKFCore(
            np.ascontiguousarray(x0a),
            symmetric_matrix("P0", P0, n),
            [g._core for g in self.gps],
            not self.pure_prediction,
        )
        # constant Jacobians are stored in the core once; the steps then pass None for them
        self._core.set_constant_jacobians(self._A_const, self._e_const, self._H_const)

    # -- state ---------------------------------------------------------------------------------
    @property
    def x(self) -> np.ndarray:
        """State estimate, shape (n,).

        Assignable (n values; ValueError and no change on bad input).
        """
        return self._core.x

    @x.setter
    def x(self, value: ArrayLike) -> None:
        # Replace the state estimate (n values; ValueError and no change on bad input).
        a = float_array("x", value, copy=True).reshape(-1)
        if a.size != self.dim_x:
            raise ValueError(f"x: expected {self.dim_x} values, got {a.size}")
        self._core.set_x(np.ascontiguousarray(a))

    @property
    def P(self) -> np.ndarray:
        """State covariance, shape (n, n): the state block of C.

        Assignable (symmetric positive semi-definite or a scalar times I); assigning resets the
        states' cross-covariance with the GP weights to zero.
        """
        return self._core.P

    @P.setter
    def P(self, value: Any) -> None:
        # Replace the state covariance (symmetric PSD (n, n) or a scalar times I; ValueError and
        # no change on bad input). The states' cross-covariance with the GP weights is reset to 0.
        self._core.set_p(symmetric_matrix("P", value, self.dim_x))

    # -- the noise covariances: read at every step, validated when assigned ----------------------
    def _noise_r(self, value: Any) -> tuple[np.ndarray, int | None]:
        """R_x validated as the constructor takes it, as (R_x, p): a symmetric positive
        semi-definite (p, p) matrix, or a positive scalar (times I once p is known; p stays None
        while it is not)."""
        a = float_array("R_x", value, copy=True)
        if a.ndim == 2:
            if self.dim_y is not None and a.shape != (self.dim_y, self.dim_y):
                raise ValueError(f"R_x: expected a scalar or shape ({self.dim_y}, {self.dim_y}), "
                                 f"got {a.shape}")
            return symmetric_matrix("R_x", a, a.shape[0]), a.shape[0]
        if a.ndim == 0:
            v = positive_scalar("R_x", float(a))
            return (a if self.dim_y is None else v * np.eye(self.dim_y)), self.dim_y
        raise ValueError(f"R_x: expected a (p, p) matrix or a scalar, got shape {a.shape}")

    @staticmethod
    def _read_only(a: np.ndarray) -> np.ndarray:
        view = a.view()
        view.flags.writeable = False
        return view

    @property
    def Q_x(self) -> np.ndarray:
        """State process-noise covariance, shape (n, n).

        Assignable between steps, validated as in the constructor (symmetric positive
        semi-definite, or a scalar times I; ValueError naming ``Q_x`` and no change on bad
        input). The array returned is read-only: assign a new value to change it.
        """
        return self._read_only(self._Q_x)

    @Q_x.setter
    def Q_x(self, value: Any) -> None:
        self._Q_x = symmetric_matrix("Q_x", value, self.dim_x)

    @property
    def R_x(self) -> np.ndarray:
        """Measurement-noise covariance, shape (p, p) (a 0-d array while p is not known: H a
        function and R_x given as a scalar, before the first update).

        Assignable between steps, validated as in the constructor (symmetric positive
        semi-definite of shape (p, p), or a positive scalar times I; ValueError naming ``R_x``
        and no change on bad input). The array returned is read-only: assign a new value to
        change it.
        """
        return self._read_only(self._R_x)

    @R_x.setter
    def R_x(self, value: Any) -> None:
        self._R_x, self.dim_y = self._noise_r(value)

    @property
    def z_pred(self) -> np.ndarray:
        """Predicted disturbances μ_z^p = J_k μ_z of the last ``predict``, shape (q,).

        The values passed to f, A and e as z.
        """
        return self._core.z_pred

    @property
    def mu(self) -> np.ndarray:
        """Augmented mean [x; μ_z1; …; μ_zq], shape (N,).

        The weights in their own coordinates (see Notes of the class).
        """
        return self._core.mu

    @property
    def C(self) -> np.ndarray:
        """Augmented covariance of [x; μ_z1; …; μ_zq], shape (N, N).

        The weights' blocks in their own coordinates (see Notes of the class).
        """
        return self._core.C

    @property
    def y(self) -> np.ndarray:
        """Innovation y − h(x⁻) of the last update, shape (p,).

        Named as filterpy's ``y``. NaN before the first update (shape (0,) while p is not
        known: H a function and R_x a scalar).
        """
        nu = self._core.innovation
        return np.full(self.dim_y, np.nan) if nu.size == 0 and self.dim_y else nu

    @property
    def S(self) -> np.ndarray:
        """Innovation covariance of the last update, shape (p, p).

        S = H̃ C⁻ H̃ᵀ + R_x, as filterpy's ``S``. NaN before the first update, as ``y``.
        """
        S = self._core.S
        return np.full((self.dim_y,) * 2, np.nan) if S.size == 0 and self.dim_y else S

    @property
    def log_likelihood(self) -> float:
        """Log-likelihood log N(y; h(x⁻), S) of the last measurement.

        Computed by ``update``, as filterpy's ``log_likelihood``; NaN before the first update
        (there is no measurement yet, and 0 would read as a perfect fit).
        """
        return float("nan") if self._core.S.size == 0 else self._core.log_likelihood

    @property
    def likelihood(self) -> float:
        """Likelihood N(y; h(x⁻), S) of the last measurement.

        exp(``log_likelihood``), as filterpy's ``likelihood``; NaN before the first update.
        """
        return float(np.exp(self.log_likelihood))

    def gp_weights(self, index: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Current mean and covariance of the basis-vector weights of one GP.

        Parameters
        ----------
        index : int, default 0
            Which GP (0 <= index < q).

        Returns
        -------
        mean : ndarray of shape (n_b,)
            The weights' mean μ_z.
        cov : ndarray of shape (n_b, n_b)
            Their covariance C_z.

        Raises
        ------
        ValueError
            If ``index`` is out of range.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import RGPEKF, RecursiveGP
        >>> gp = RecursiveGP(0.0, 1.0, 5)
        >>> kf = RGPEKF(1, lambda x, u, z: x + z, 1.0, 1.0, lambda x: x, [[1.0]],
        ...             Q_x=0.0, R_x=0.01, x0=[0.0], P0=0.0, gps=gp)
        >>> mean, cov = kf.gp_weights()
        >>> mean.shape, bool(np.allclose(cov, gp.K))  # a fresh GP: N(0, K)
        ((5,), True)
        """
        return self._core.gp_weights(self._index(index))

    def gp_predict(
        self, zeta: ArrayLike, index: int = 0, return_std: bool = False
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Predict one GP's disturbance z at inputs ζ with the filter's current weights.

        Parameters
        ----------
        zeta : array_like of shape (m, dim_zeta), or (m,) when dim_zeta = 1
            Inputs ζ of GP ``index``.
        index : int, default 0
            Which GP (0 <= index < q).
        return_std : bool, default False
            Also return the standard deviation (σ_r floor included).

        Returns
        -------
        mean : ndarray of shape (m,)
            Predicted mean of z.
        std : ndarray of shape (m,)
            Predicted standard deviation; only returned if ``return_std`` is True.

        See Also
        --------
        RecursiveGP.predict : The same for a stand-alone GP.

        Examples
        --------
        >>> from gpmhe import RGPEKF, RecursiveGP
        >>> kf = RGPEKF(1, lambda x, u, z: x + z, 1.0, 1.0, lambda x: x, [[1.0]], Q_x=0.0,
        ...             R_x=0.01, x0=[0.0], P0=0.0, gps=RecursiveGP(0.0, 1.0, 5, sigma_K=2.0))
        >>> mean, std = kf.gp_predict([0.2, 0.8], return_std=True)
        >>> print(mean, std.round(6))
        [0. 0.] [2. 2.]
        """
        i = self._index(index)
        return_std = boolean("return_std", return_std)
        mean, var = self._core.gp_predict(i, self.gps[i]._zeta_many(zeta))
        return (mean, np.sqrt(var)) if return_std else mean

    def _index(self, index: int) -> int:
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or not 0 <= index < self.dim_z:
            raise ValueError(f"index: must be an integer in [0, {self.dim_z}), got {index!r}")
        return int(index)

    # -- filter steps --------------------------------------------------------------------------
    def _zeta(self, zeta: Any) -> np.ndarray:
        # The values are checked here (finite, magnitude <= MAX_ABS), the Rust core checks again.
        if zeta is None:
            raise ValueError("zeta: the GP input is required")
        if (self._scalar_zeta and isinstance(zeta, (float, int, np.floating, np.integer))
                and not isinstance(zeta, bool) and abs(zeta) <= MAX_ABS):
            self._zbuf[0] = zeta
            return self._zbuf
        if self.dim_z == 1:
            z = float_array("zeta", zeta).reshape(-1)
        else:
            if not isinstance(zeta, (list, tuple, np.ndarray)) or len(zeta) != self.dim_z:
                raise ValueError(f"zeta: expected a sequence of one input per GP ({self.dim_z}), got {zeta!r}")
            z = np.concatenate([float_array(f"zeta[{i}]", v).reshape(-1) for i, v in enumerate(zeta)])
        if z.size != self._zeta_total:
            raise ValueError(f"zeta: expected {self._zeta_total} value(s) in total, got {z.size}")
        return np.ascontiguousarray(z)

    def predict(self, u: Any = None, zeta: Any = None) -> None:
        """Predict the state and the augmented covariance one step ahead.

        Computes J_k at ζ, μ_z^p = J_k μ_z, x⁻ = f(x, u, μ_z^p) and
        C⁻ = Ã C Ãᵀ + ẽ (σ_K² − J_k K J_kᵀ + σ_r²) ẽᵀ + blockdiag(Q_x, σ_p² I) (step 1 of the
        class description).

        Parameters
        ----------
        u : object, default None
            Input, passed to f, A and e untouched.
        zeta : float, array_like or sequence
            The GPs' inputs ζ_k: a scalar or array for one GP, a sequence with one entry per GP
            for several. Required.

        Raises
        ------
        ValueError
            On bad input or if f, A or e return a wrong shape, NaN or inf; the filter is then
            unchanged.

        Examples
        --------
        With a fresh GP the predicted disturbance is the prior mean 0:

        >>> from gpmhe import RGPEKF, RecursiveGP
        >>> kf = RGPEKF(1, lambda x, u, z: x + u + z, 1.0, 1.0, lambda x: x, [[1.0]], Q_x=0.0,
        ...             R_x=0.01, x0=[1.0], P0=0.0, gps=RecursiveGP(0.0, 1.0, 5))
        >>> kf.predict(u=2.0, zeta=0.5)
        >>> kf.x, kf.z_pred
        (array([3.]), array([0.]))
        """
        # One core call per step: it computes J_k, calls f (and A, e if callables) with
        # z = μ_z^p and predicts C. Finiteness of ζ and of the results is checked there.
        if not (self._scalar_zeta and isinstance(zeta, float) and abs(zeta) <= MAX_ABS):
            zeta = self._zeta(zeta)
        self._core.predict_step(self.f, u, zeta, self._A_fn, self._e_fn, self._Q_x)

    def update(self, y: ArrayLike) -> None:
        """EKF update with the measurement y (variant 4a, or 4b when ``learning`` is False).

        Evaluates h and H at the predicted state x⁻ (or whatever was assigned to ``x`` since),
        forms the innovation ν = y − h(x⁻) and its covariance S, and updates the augmented mean
        and covariance (only the state rows with ``learning=False`` or ``pure_prediction``).

        Parameters
        ----------
        y : array_like of shape (p,)
            The measurement.

        Raises
        ------
        ValueError
            For a bad y or bad results of h or H (state unchanged).
        gpmhe.NumericalError
            If the innovation covariance is not positive definite (state unchanged).

        Examples
        --------
        The disturbance is learned from the state measurement:

        >>> from gpmhe import RGPEKF, RecursiveGP
        >>> kf = RGPEKF(1, lambda x, u, z: x + z, 1.0, 1.0, lambda x: x, [[1.0]], Q_x=0.0,
        ...             R_x=1e-4, x0=[0.0], P0=0.0, gps=RecursiveGP(0.0, 1.0, 5))
        >>> kf.predict(zeta=0.5)
        >>> kf.update([1.0])
        >>> round(float(kf.x[0]), 3), round(float(kf.gp_predict([0.5])[0]), 3)
        (1.0, 1.0)
        """
        # One core call: it evaluates h (and H if callable) at the predicted state x⁻ (or
        # whatever was assigned to x since), forms ν = y − h(x⁻) and updates.
        if self.dim_y is None:
            y = float_array("y", y).reshape(-1)
        else:
            y = finite_vector("y", y, self.dim_y, flatten=True)
        self._core.update_step(
            y, self.h, self._H_fn, self._R_x, self.dim_y, self.learning and not self.pure_prediction
        )
        if self.dim_y is None:  # p is known from the first update on: R_x as the constructor's
            self.dim_y = len(self._core.innovation)
            self._R_x = float(self._R_x) * np.eye(self.dim_y)

    def __repr__(self) -> str:
        return (
            f"RGPEKF(dim_x={self.dim_x}, gps={len(self.gps)}, learning={self.learning}, "
            f"pure_prediction={self.pure_prediction}, x={self.x})"
        )

    # -- checkpoints: save and load ------------------------------------------------------------
    # (Copies and pickles need no code here: the Rust cores copy and pickle themselves with
    # their whole state; the user functions must be picklable to pickle the filter.)

    # 2: GPs on given points (RecursiveGP.from_sparse): entry 'gp<i>_basis' says "grid" or
    # "points" (files of version 1 hold grids only).
    _CHECKPOINT_VERSION = 2

    def save(self, path: Any) -> None:
        """Write the filter's whole state (settings, GPs, μ, C, last innovation) to an ``.npz``
        file.

        The file holds plain arrays only (no pickle). The user functions ``f``, ``h`` (and ``A``,
        ``e``, ``H`` where they are functions) are not saved: give them again to `load`. A filter
        loaded from the file continues exactly (bit for bit) as this one would.

        Parameters
        ----------
        path : str, os.PathLike or file-like object
            Destination, passed to `numpy.savez`.

        See Also
        --------
        load : Continue from the file.

        Examples
        --------
        >>> import io
        >>> import numpy as np
        >>> from gpmhe import RGPEKF, RecursiveGP
        >>> def f(x, u, z):
        ...     return 0.9 * x + z
        >>> def h(x):
        ...     return x
        >>> ekf = RGPEKF(1, f=f, A=0.9, e=1.0, h=h, H=[1.0], Q_x=1e-3, R_x=0.1, x0=[0.0], P0=1.0,
        ...              gps=RecursiveGP(-1, 1, 5))
        >>> ekf.predict(None, 0.2); ekf.update([0.5])
        >>> buf = io.BytesIO()
        >>> ekf.save(buf)
        >>> _ = buf.seek(0)
        >>> loaded = RGPEKF.load(buf, f=f, h=h)
        >>> for filt in (ekf, loaded):
        ...     filt.predict(None, 0.3); filt.update([0.4])
        >>> bool(np.array_equal(loaded.x, ekf.x) and np.array_equal(loaded.C, ekf.C))
        True
        """
        entries: dict = dict(
            kind="RGPEKF", format_version=self._CHECKPOINT_VERSION, dim_x=self.dim_x,
            learning=self.learning, pure_prediction=self.pure_prediction, Q_x=self._Q_x,
            R_x=self._R_x, n_gps=len(self.gps))
        for name, value in (("A", self._A), ("e", self._e), ("H", self._H)):
            entries[name + "_is_function"] = callable(value)
            if not callable(value):
                entries[name] = value
        for i, g in enumerate(self.gps):
            entries.update(_gp_entries(f"gp{i}_", g))
        # (The core's copies of the constant Jacobians are the entries A, e, H.)
        entries.update({"core_" + k: v for k, v in self._core.__getstate__().items()
                        if not k.endswith("_const")})
        np.savez(path, **entries)

    @classmethod
    def load(cls, path: Any, f: Callable[..., Any], h: Callable[..., Any], A: Any = None,
             e: Any = None, H: Any = None) -> "RGPEKF":
        """Continue a filter from a file written by `save`.

        Parameters
        ----------
        path : str, os.PathLike or file-like object
            The ``.npz`` file. It is read without pickle (``allow_pickle=False``), so a file from
            an untrusted source cannot run code.
        f, h : callable
            The transition and output functions, as given to the constructor.
        A, e, H : callable, array_like or None, default None
            As given to the constructor; None takes the constant saved in the file, and is only
            allowed where the saved filter had a constant (a function must be given again).

        Returns
        -------
        RGPEKF
            The filter with the saved settings, GPs and state.

        Raises
        ------
        ValueError
            If the file cannot be read, is not a saved RGPEKF, or an entry is missing, damaged or
            inconsistent (the message names the file and the entry), or if a function the saved
            filter used is not given.

        See Also
        --------
        save : Write the file.

        Examples
        --------
        >>> import io
        >>> from gpmhe import RGPEKF, RecursiveGP
        >>> def f(x, u, z):
        ...     return x + z
        >>> def h(x):
        ...     return x
        >>> ekf = RGPEKF(1, f=f, A=1.0, e=1.0, h=h, H=[1.0], Q_x=1e-3, R_x=0.1, x0=[0.5], P0=1.0,
        ...              gps=RecursiveGP(-1, 1, 5))
        >>> buf = io.BytesIO()
        >>> ekf.save(buf)
        >>> _ = buf.seek(0)
        >>> RGPEKF.load(buf, f=f, h=h).x
        array([0.5])
        """
        from gpmhe._npz import NpzReader

        with NpzReader(path, "RGPEKF", cls._CHECKPOINT_VERSION) as fl:
            n = fl.integer("dim_x", low=1)
            given = {"A": A, "e": e, "H": H}
            for name in given:
                saved = None if fl.boolean(name + "_is_function") else fl.floats(name, (None, None))
                if given[name] is None:
                    if saved is None:
                        raise ValueError(f"{name}: the filter in {fl.name} took {name} as a "
                                         f"function; give it again")
                    given[name] = saved
            gps = [_gp_from_entries(fl, f"gp{i}_") for i in range(fl.integer("n_gps", low=1))]
            fl.allow_nonfinite = ("core_log_likelihood",)
            state = {"inferred": fl.boolean("core_inferred"),
                     "log_likelihood": fl.float("core_log_likelihood")}
            keys = [("mu", 1), ("cov", 2), ("j", 1), ("dvar", 1), ("mu_zp", 1), ("z_pred", 1),
                    ("innovation", 1), ("S", 2)]
            keys += [(f"gp_{part}_{i}", dims) for i in range(len(gps))
                     for part, dims in (("mean", 1), ("cov", 2))]
            for key, dims in keys:
                state[key] = fl.floats("core_" + key, (None,) * dims)
            if state["S"].shape != (len(state["innovation"]),) * 2:
                raise fl.error("core_S", f"has shape {state['S'].shape}, expected (p, p) with p = "
                                         f"{len(state['innovation'])} (entry 'core_innovation')")
            try:
                ekf = cls(n, f, given["A"], given["e"], h, given["H"], fl.floats("Q_x"),
                          fl.floats("R_x"), x0=np.zeros(n), P0=np.eye(n), gps=gps,
                          learning=fl.boolean("learning"),
                          pure_prediction=fl.boolean("pure_prediction"))
            except ValueError as err:
                raise ValueError(f"path: {fl.name}: the saved settings are invalid ({err})") from None
            try:
                ekf._core.__setstate__(state)
            except ValueError as err:
                raise fl.state_error("core_", err) from None
            ekf._core.set_constant_jacobians(ekf._A_const, ekf._e_const, ekf._H_const)
        return ekf
