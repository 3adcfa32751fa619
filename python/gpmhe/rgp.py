"""Recursive GP regression and the RGP-dKF (an EKF that learns a disturbance model online).

After Husmann, Weishaupt & Aschemann, "Direct Integration of Recursive Gaussian Process Regression
Into Extended Kalman Filters" (§2, §3), building on Huber's recursive GP; see the user guide,
*The RGP-dKF*. Two classes:

* :class:`RecursiveGP` learns z(ζ) from direct noisy measurements of z on a grid of basis vectors,
  or continues from a sparse GP trained offline (``RecursiveGP.from_sparse``: its inducing inputs
  become the basis vectors).
* :class:`RGPEKF` estimates the state of x_{k+1} = f(x_k, u_k, z(ζ_k)), y_k = h(x_k) + v_k when z is
  *not* measured: the RGP's basis-vector weights are appended to the EKF state and learned from y.

The per-step numerics (J_k by triangular solves with K's Cholesky factor, the structured covariance
prediction, the EKF update) run in Rust (``gpmhe._core``), with the GIL released when n + Σ n_b ≥ 200
(smaller steps take a few µs, less than releasing the GIL costs under contention). This module
validates the constructor's inputs; each filter step is one core call, which also calls the user's
model functions (f, A, e in ``predict``; h, H in ``update``) and checks their results.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence, Union

import numpy as np

from gpmhe._core import NumericalError, RecursiveGPCore, RGPEKFCore
from gpmhe.gp import GaussianProcess, MultiOutputGP
from gpmhe.sparse import _SparseGP
from gpmhe._validation import (
    MAX_ABS,
    boolean,
    finite_vector,
    float_array,
    integer,
    positive_scalar,
    symmetric_matrix,
)

__all__ = ["RecursiveGP", "RGPEKF"]

# Exact GPs, named in the message that refuses them in `RecursiveGP.from_sparse`.
_ExactGPs = (GaussianProcess, MultiOutputGP)

ArrayLike = Union[float, Sequence[float], np.ndarray]


class RecursiveGP:
    """Huber's recursive GP on a unit grid of basis vectors, with the RGP-dKF paper's changes.

    Model: z(ζ) has a zero-mean GP prior with kernel k(x, x') = σ_K² exp(−‖x − x'‖² / (2L)) on the
    normalised input x = f_norm(ζ) = (ζ − lower) (N_i − 1) / (upper − lower) (eq. 6), so the basis
    vectors X form a grid with unit spacing and one L serves all axes. The GP is represented by the
    weights w at the basis vectors, w ~ N(mean, cov), initially N(0, K), K = k(X, X). At a test
    input, J = k(x, X) K⁻¹ (two triangular solves with K's Cholesky factor, computed once; K⁻¹ is
    never formed), the prediction is

        mean = J w̄,   var = σ_K² − J K Jᵀ + J C Jᵀ + σ_r²,

    and a measurement y = z(ζ) + ε, ε ~ N(0, var_y), updates (eq. 4)

        G = C Jᵀ / (σ_K² − J K Jᵀ + J C Jᵀ + σ_r² + var_y),  w̄ += G (y − J w̄),
        C −= G J C,  C += σ_p² I.

    `from_sparse` builds instead a GP whose basis vectors are a fitted sparse GP's inducing inputs
    (no grid; its SE-ARD kernel in ζ units) and whose weights are that GP's posterior: it predicts
    exactly as the sparse GP, and learns on from there. A sparse GP's prior mean m(ζ) is then
    added to the mean (J w̄ + m(ζ)) and subtracted from y in the update.

    Parameters
    ----------
    lower : float or array_like of shape (dim_zeta,)
        Lower bounds of the input ζ that the grid spans.
    upper : float or array_like of shape (dim_zeta,)
        Upper bounds of the grid, > lower on every axis. Inputs outside the grid are allowed; the
        GP reverts to its prior there.
    n_points : int or sequence of int
        Basis vectors per axis N_i (≥ 2; an int is used for every axis); ``n_basis`` = Π N_i.
    sigma_K : float, default 1.0
        Prior standard deviation σ_K of z.
    L : float, default 1.0
        Squared length-scale in grid units (the kernel's 2L denominator); the length-scale in ζ
        units is √L (upper − lower) / (N_i − 1).
    sigma_r : float, default 0.0
        Floor σ_r added to the prediction standard deviation (variance σ_r²) for the model error of
        a finite basis; the paper suggests 0.01–0.1 σ_K.
    sigma_p : float, default 0.0
        Process noise σ_p of the weights (a forgetting factor: C += σ_p² I per update).

    Attributes
    ----------
    mean : ndarray of shape (n_basis,)
        Weights' mean w̄ (the paper's μ_z).
    cov : ndarray of shape (n_basis, n_basis)
        Weights' covariance C (the paper's C_z).
    basis_vectors : ndarray of shape (n_basis, dim_zeta)
        The basis vectors in ζ units (the first axis varies fastest); a sparse GP's inducing
        inputs for a GP from `from_sparse`.
    K : ndarray of shape (n_basis, n_basis)
        The kernel matrix k(X, X) of the basis vectors (without jitter).
    jitter : float
        Diagonal jitter added to K to factor it (0 if none was needed; a sparse GP's own jitter
        for a GP from `from_sparse`).
    lengthscales : ndarray of shape (dim_zeta,)
        The kernel's length-scales in ζ units, √L (upper − lower) / (N_i − 1) for a grid.
    prior_mean : ndarray of shape (dim_zeta + 1,) or None
        Coefficients [b, w_1, …] of the prior mean m(ζ) = b + wᵀζ added to every prediction:
        None for a grid, a sparse GP's fitted mean for a GP from `from_sparse`.
    n_basis : int
        Number of basis vectors Π N_i (m for a GP from `from_sparse`).
    dim_zeta : int
        Input dimension.
    lower, upper : ndarray of shape (dim_zeta,) or None
        The grid's bounds (None for a GP from `from_sparse`, which has no grid).
    n_points : tuple of int or None
        Basis vectors per axis (None for a GP from `from_sparse`).
    sigma_K, sigma_r, sigma_p : float
        The hyperparameters, as given (σ_K is the sparse GP's σ_f for a GP from `from_sparse`).
    L : float or None
        The squared length-scale in grid units, as given (None for a GP from `from_sparse`; see
        ``lengthscales``).

    Raises
    ------
    ValueError
        If the bounds, grid sizes or hyperparameters are invalid.

    See Also
    --------
    RGPEKF : Learns the weights from indirect measurements inside an EKF.
    from_sparse : The recursive GP that predicts as a fitted sparse GP.

    Notes
    -----
    Compared with Huber's RGP, the paper adds the floor σ_r² to the predictive variance and the
    weights' process noise σ_p² I (see the user guide, *The RGP-dKF*).

    References
    ----------
    .. [1] R. Husmann, S. Weishaupt and H. Aschemann, "Direct Integration of Recursive Gaussian
       Process Regression Into Extended Kalman Filters With Application to Vapor Compression
       Cycle Control".

    Examples
    --------
    Learn sin(ζ) on [−2, 2] from 200 noisy measurements, in one call, with 9 basis vectors
    (L = 1: the length-scale is one grid step, 0.5 in ζ) [1]_:

    >>> import numpy as np
    >>> from gpmhe import RecursiveGP
    >>> gp = RecursiveGP(-2.0, 2.0, 9, sigma_K=2.0, L=1.0, sigma_r=0.01)
    >>> rng = np.random.default_rng(0)
    >>> zeta = rng.uniform(-2.0, 2.0, 200)
    >>> _ = gp.update(zeta, np.sin(zeta) + 0.05 * rng.standard_normal(200), 0.05 ** 2)
    >>> mean, std = gp.predict([0.5, 1.0], return_std=True)
    >>> print(np.round(mean, 2), np.round(np.sin([0.5, 1.0]), 2))
    [0.47 0.85] [0.48 0.84]
    >>> bool(np.all(std < 0.05))
    True
    """

    def __init__(
        self,
        lower: ArrayLike,
        upper: ArrayLike,
        n_points: int | Sequence[int],
        sigma_K: float = 1.0,
        L: float = 1.0,
        sigma_r: float = 0.0,
        sigma_p: float = 0.0,
    ) -> None:
        lo = np.atleast_1d(float_array("lower", lower, copy=True))
        hi = np.atleast_1d(float_array("upper", upper, copy=True))
        if lo.ndim != 1 or lo.size == 0:
            raise ValueError(f"lower: expected a scalar or 1-D array, got shape {lo.shape}")
        if hi.shape != lo.shape:
            raise ValueError(f"upper: expected shape {lo.shape} like lower, got {hi.shape}")
        if np.any(hi <= lo):
            raise ValueError("lower, upper: upper must exceed lower on every axis")
        try:
            npts = np.atleast_1d(np.asarray(n_points))
        except (TypeError, ValueError):
            raise ValueError(f"n_points: expected an int or {lo.size} ints, got {n_points!r}") from None
        if npts.ndim != 1 or npts.size not in (1, lo.size):
            raise ValueError(f"n_points: expected an int or {lo.size} ints, got {n_points!r}")
        if not np.issubdtype(npts.dtype, np.integer) or np.any(npts < 2):
            raise ValueError(f"n_points: must be integers >= 2, got {n_points!r}")
        npts = np.broadcast_to(npts, lo.shape).astype(int)
        self.sigma_K = positive_scalar("sigma_K", sigma_K)
        self.L = positive_scalar("L", L)
        self.sigma_r = positive_scalar("sigma_r", sigma_r, allow_zero=True)
        self.sigma_p = positive_scalar("sigma_p", sigma_p, allow_zero=True)
        self.lower, self.upper, self.n_points = lo, hi, tuple(int(n) for n in npts)
        self.dim_zeta = lo.size
        self._core = RecursiveGPCore(
            lo, hi, list(self.n_points), self.sigma_K, self.L, self.sigma_r, self.sigma_p
        )
        self.n_basis = int(np.prod(self.n_points))

    @classmethod
    def from_sparse(cls, gp: Any, sigma_r: float = 0.0, sigma_p: float = 0.0,
                    output: int = 0) -> "RecursiveGP":
        """The recursive GP that predicts exactly as a fitted sparse GP.

        The basis vectors are the sparse GP's inducing inputs Z, the kernel its SE-ARD kernel
        (σ_K = σ_f, its length-scales, in ζ units, with its jitter on K = k(Z, Z)), and the
        weights the posterior of the inducing outputs u = f(Z), N(μ_u, Σ_u) with
        μ_u = K P⁻¹ K_uf Λ⁻¹ y and Σ_u = K P⁻¹ K (P = K + K_uf Λ⁻¹ K_fu, as in
        `SparseGaussianProcess`). Then J = k(ζ, Z) K⁻¹ gives the sparse GP's mean J μ_u and
        latent variance σ_f² − J K Jᵀ + J Σ_u Jᵀ, for VFE and FITC alike. A prior mean of the
        sparse GP (``mean="constant"`` or ``"linear"``) is kept: it is added to every
        prediction, and `update` learns the residual. The sparse GP is not modified.

        Parameters
        ----------
        gp : SparseGaussianProcess or SparseMultiOutputGP
            A fitted sparse GP whose inputs are ζ (n_d = dim_zeta).
        sigma_r : float, default 0.0
            Floor σ_r added to the prediction standard deviation (0 reproduces the sparse GP's
            latent standard deviation).
        sigma_p : float, default 0.0
            Process noise σ_p of the weights, for learning on with `update` or in `RGPEKF`.
        output : int, default 0
            Which output of a `SparseMultiOutputGP` (0 for a `SparseGaussianProcess`).

        Returns
        -------
        RecursiveGP
            The recursive GP, with ``basis_vectors`` = Z, ``mean`` = μ_u and ``cov`` = Σ_u; it
            has no grid (``lower``, ``upper``, ``n_points`` and ``L`` are None).

        Raises
        ------
        ValueError
            If ``gp`` is not a fitted sparse GP (an exact GP has no inducing points), ``output``
            is out of range, or ``sigma_r`` or ``sigma_p`` is invalid.

        See Also
        --------
        RGPEKF : Uses the GP as a fixed model (``pure_prediction=True``) or learns on.

        Notes
        -----
        The sparse GP's noise σ_ε is not part of the recursive GP: pass ``var_y=gp.sigma_eps**2``
        to `update` to learn on from measurements like the training data. For a FITC model
        this continues FITC exactly: updating with new data gives the FITC posterior of all the
        data (same θ and Z).

        Examples
        --------
        Train a sparse GP offline, then predict with the recursive GP:

        >>> import numpy as np
        >>> from gpmhe import RecursiveGP, SparseGaussianProcess
        >>> rng = np.random.default_rng(0)
        >>> D = rng.uniform(-2.0, 2.0, (500, 1))
        >>> sgp = SparseGaussianProcess(n_inducing=15).fit(D, np.sin(D[:, 0]) + 0.05 * rng.standard_normal(500))
        >>> gp = RecursiveGP.from_sparse(sgp)
        >>> bool(np.array_equal(gp.basis_vectors, sgp.inducing_points))
        True
        >>> mean, std = gp.predict([0.5, 1.0], return_std=True)
        >>> mean_s, std_s = sgp.predict([[0.5], [1.0]], return_std=True)
        >>> bool(np.allclose(mean, mean_s) and np.allclose(std, std_s))
        True
        """
        if not isinstance(gp, _SparseGP):
            got = type(gp).__name__
            hint = (" (an exact GP has no inducing points: fit a SparseGaussianProcess, whose "
                    "inducing points become the basis vectors)" if isinstance(gp, _ExactGPs) else "")
            raise ValueError(f"gp: expected a fitted SparseGaussianProcess or SparseMultiOutputGP, "
                             f"got {got}{hint}")
        model = gp._core_model
        if model is None:
            raise ValueError(f"gp: the {type(gp).__name__} is not fitted; call fit first")
        q = model.n_outputs
        out = integer("output", output)
        if out >= q:
            raise ValueError(f"output: the sparse GP has {q} output(s), got {output!r}")
        sigma_r = positive_scalar("sigma_r", sigma_r, allow_zero=True)
        sigma_p = positive_scalar("sigma_p", sigma_p, allow_zero=True)
        return cls._on_points(RecursiveGPCore.from_sparse(model, out, sigma_r, sigma_p), sigma_r,
                              sigma_p)

    @classmethod
    def _on_points(cls, core: RecursiveGPCore, sigma_r: float, sigma_p: float) -> "RecursiveGP":
        """The RecursiveGP around a core with basis vectors at given points."""
        new = object.__new__(cls)
        new.sigma_K, new.L = float(core.sigma_k), None
        new.sigma_r, new.sigma_p = sigma_r, sigma_p
        new.lower = new.upper = new.n_points = None
        new._core = core
        new.n_basis, new.dim_zeta = core.basis_vectors.shape
        return new

    # -- state -------------------------------------------------------------------------------
    @property
    def mean(self) -> np.ndarray:
        """Weights' mean w̄ (μ_z), shape (n_basis,).

        Initially zero; changed by `update` and `set_weights`.
        """
        return self._core.mean

    @property
    def cov(self) -> np.ndarray:
        """Weights' covariance C (C_z), shape (n_basis, n_basis).

        Initially the kernel matrix K; changed by `update` and `set_weights`.
        """
        return self._core.cov

    @property
    def basis_vectors(self) -> np.ndarray:
        """The basis vectors in ζ units, shape (n_basis, dim_zeta).

        A grid spanning [lower, upper] with ``n_points`` per axis, the first axis varying
        fastest; a sparse GP's inducing inputs for a GP from `from_sparse`.
        """
        return self._core.basis_vectors

    @property
    def K(self) -> np.ndarray:
        """Kernel matrix k(X, X) of the basis vectors, shape (n_basis, n_basis).

        Without jitter; the prior covariance of the weights.
        """
        return self._core.kernel_matrix

    @property
    def jitter(self) -> float:
        """Diagonal jitter added to K to factor it.

        0 unless K was numerically singular (e.g. a dense grid with a long length-scale); for a
        GP from `from_sparse`, the sparse GP's own jitter.
        """
        return self._core.jitter

    @property
    def lengthscales(self) -> np.ndarray:
        """The kernel's length-scales in ζ units, shape (dim_zeta,).

        √L (upper − lower) / (N_i − 1) per axis for a grid; the sparse GP's for a GP from
        `from_sparse`.
        """
        return self._core.lengthscales

    @property
    def prior_mean(self) -> np.ndarray | None:
        """Coefficients [b, w_1, …, w_dim_zeta] of the prior mean m(ζ) = b + wᵀζ, or None.

        Added to every prediction (the weights model z − m). None for a grid; a sparse GP's
        fitted mean for a GP from `from_sparse` (None if it was fitted with ``mean="zero"``).
        """
        return self._core.prior_mean

    def set_weights(self, mean: ArrayLike, cov: ArrayLike) -> None:
        """Replace the weights' mean and covariance (e.g. from a previous run).

        Parameters
        ----------
        mean : array_like of shape (n_basis,)
            New weights' mean w̄.
        cov : array_like of shape (n_basis, n_basis) or float
            New weights' covariance C: a symmetric positive semi-definite matrix, or a scalar
            (times I).

        Raises
        ------
        ValueError
            On a wrong shape, NaN or inf, or a covariance that is not symmetric positive
            semi-definite; the weights are then unchanged.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import RecursiveGP
        >>> gp = RecursiveGP(0.0, 1.0, 5)
        >>> gp.set_weights(np.ones(5), 1e-6)
        >>> print(np.round(gp.predict([0.25, 0.5]), 2))
        [1. 1.]
        """
        m = float_array("mean", mean, 1, copy=True)
        if m.shape != (self.n_basis,):
            raise ValueError(f"mean: expected shape ({self.n_basis},), got {m.shape}")
        c = symmetric_matrix("cov", cov, self.n_basis)
        self._core.set_weights(np.ascontiguousarray(m), c)

    def copy(self) -> "RecursiveGP":
        """An independent copy (same basis, hyperparameters and current weights).

        Returns
        -------
        RecursiveGP
            The copy; updating it leaves this GP unchanged.

        Examples
        --------
        >>> from gpmhe import RecursiveGP
        >>> gp = RecursiveGP(0.0, 1.0, 5)
        >>> other = gp.copy()
        >>> _ = other.update(0.5, 1.0, 0.01)
        >>> float(gp.mean.max()), bool(other.mean.max() > 0)
        (0.0, True)
        """
        new = object.__new__(RecursiveGP)
        new.__dict__.update(self.__dict__)
        new._core = self._core.copy()
        return new

    # -- inputs --------------------------------------------------------------------------------
    def _zeta_one(self, zeta: ArrayLike) -> np.ndarray:
        return finite_vector("zeta", zeta, self.dim_zeta, flatten=True)

    def _zeta_many(self, zeta: ArrayLike) -> np.ndarray:
        z = float_array("zeta", zeta, copy=True)
        if z.ndim <= 1 and self.dim_zeta == 1:
            z = z.reshape(-1, 1)
        elif z.ndim == 1 and z.size == self.dim_zeta:
            z = z.reshape(1, -1)
        if z.ndim != 2 or z.shape[1] != self.dim_zeta:
            raise ValueError(f"zeta: expected shape (m, {self.dim_zeta}), got {z.shape}")
        return np.ascontiguousarray(z)

    # -- learning and prediction ---------------------------------------------------------------
    def update(self, zeta: ArrayLike, y: Any, var_y: Any) -> Any:
        """Learn from direct measurements y = z(ζ) + ε, ε ~ N(0, var_y).

        Applies the update of the class description (eq. 4) once per measurement, in order.

        Parameters
        ----------
        zeta : float or array_like of shape (dim_zeta,), or (m, dim_zeta) / (m,) for m values
            Input(s) ζ; for several measurements one row per measurement (a 1-D array of m
            values when dim_zeta = 1).
        y : float or array_like of shape (m,)
            Measurement(s) of z.
        var_y : float or array_like of shape (m,)
            Measurement-noise variance(s), >= 0.

        Returns
        -------
        float or ndarray of shape (m,)
            The prediction J w̄ (+ m(ζ) with a ``prior_mean``) at each input, made just before
            its own update.

        Raises
        ------
        ValueError
            On bad input; the weights are then unchanged.

        Examples
        --------
        >>> from gpmhe import RecursiveGP
        >>> gp = RecursiveGP(0.0, 1.0, 5, sigma_K=1.0)
        >>> gp.update(0.5, 2.0, 1e-4)  # the prior mean, before learning
        0.0
        >>> round(gp.update(0.5, 2.0, 1e-4), 2)  # after learning the first measurement
        2.0
        """
        ys = float_array("y", y, copy=True)
        if ys.ndim > 1:
            raise ValueError(f"y: expected a scalar or a 1-D array, got shape {ys.shape}")
        if ys.ndim == 1:
            zs = self._zeta_many(zeta)
            if zs.shape[0] != ys.size:
                raise ValueError(f"y, zeta: {ys.size} measurements y for {zs.shape[0]} inputs zeta")
            vs = np.atleast_1d(float_array("var_y", var_y, copy=True))
            if vs.ndim != 1 or vs.size not in (1, ys.size) or np.any(vs < 0):
                raise ValueError(f"var_y: expected a scalar or {ys.size} values >= 0")
            return self._core.update_many(zs, np.ascontiguousarray(ys), np.ascontiguousarray(vs))
        z = self._zeta_one(zeta)
        return self._core.update(z, float(ys), positive_scalar("var_y", var_y, allow_zero=True))

    def predict(
        self, zeta: ArrayLike, return_std: bool = False
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Predict z at inputs ζ: mean J w̄ (+ m(ζ)) and optionally the standard deviation.

        Parameters
        ----------
        zeta : array_like of shape (m, dim_zeta), or (m,) when dim_zeta = 1
            Inputs (one input of dimension dim_zeta may also be a 1-D array).
        return_std : bool, default False
            Also return the standard deviation √(σ_K² − J K Jᵀ + J C Jᵀ + σ_r²).

        Returns
        -------
        mean : ndarray of shape (m,)
            Predicted mean of z.
        std : ndarray of shape (m,)
            Predicted standard deviation, the σ_r floor included; only returned if
            ``return_std`` is True.

        Examples
        --------
        Before any update the prediction is the prior N(0, σ_K² + σ_r²):

        >>> from gpmhe import RecursiveGP
        >>> gp = RecursiveGP(0.0, 1.0, 5, sigma_K=3.0, sigma_r=0.0)
        >>> mean, std = gp.predict([0.1, 0.9], return_std=True)
        >>> print(mean, std.round(6))
        [0. 0.] [3. 3.]
        """
        return_std = boolean("return_std", return_std)
        mean, var = self._core.predict(self._zeta_many(zeta))
        return (mean, np.sqrt(var)) if return_std else mean

    def J(self, zeta: ArrayLike) -> np.ndarray:
        """The inference row J = k(f_norm(ζ), X) K⁻¹ at one input.

        (f_norm(ζ) = ζ for a GP from `from_sparse`.)

        Parameters
        ----------
        zeta : float or array_like of shape (dim_zeta,)
            One input ζ.

        Returns
        -------
        ndarray of shape (n_basis,)
            J; the prediction's mean is J w̄ (+ m(ζ) with a ``prior_mean``).

        Examples
        --------
        At a basis vector, J picks that vector's weight:

        >>> import numpy as np
        >>> from gpmhe import RecursiveGP
        >>> gp = RecursiveGP(0.0, 1.0, 5)
        >>> print(np.round(gp.J(0.25), 6) + 0.0)
        [0. 1. 0. 0. 0.]
        """
        return self._core.j_row(self._zeta_one(zeta))

    def __repr__(self) -> str:
        if self.n_points is None:
            mean = "" if self.prior_mean is None else ", prior_mean=" + str(self.prior_mean.tolist())
            return (
                f"RecursiveGP(points: n_basis={self.n_basis}, dim_zeta={self.dim_zeta}, "
                f"sigma_K={self.sigma_K}, lengthscales={self.lengthscales.tolist()}, "
                f"sigma_r={self.sigma_r}, sigma_p={self.sigma_p}{mean})"
            )
        return (
            f"RecursiveGP(lower={self.lower.tolist()}, upper={self.upper.tolist()}, "
            f"n_points={list(self.n_points)}, sigma_K={self.sigma_K}, L={self.L}, "
            f"sigma_r={self.sigma_r}, sigma_p={self.sigma_p})"
        )


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
        Last innovation y − h(x⁻).
    S : ndarray of shape (p, p)
        Its covariance H̃ C⁻ H̃ᵀ + R_x.
    log_likelihood : float
        log N(y; h(x⁻), S) of the last update.
    likelihood : float
        exp(log_likelihood).
    f, h : callable
        The model functions. They are read at every step, so they can be reassigned between
        steps.
    Q_x, R_x : ndarray
        The noise covariances; can be reassigned between steps (then only checked for shape and
        finiteness).
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
        self.Q_x = symmetric_matrix("Q_x", Q_x, n)
        self.R_x = float_array("R_x", R_x, copy=True)
        self.dim_y: int | None = None
        if self.R_x.ndim == 2:
            self.dim_y = self.R_x.shape[0]
            self.R_x = symmetric_matrix("R_x", self.R_x, self.dim_y)
        elif self.R_x.ndim == 0:
            positive_scalar("R_x", float(self.R_x))
        else:
            raise ValueError(f"R_x: expected a (p, p) matrix or a scalar, got shape {self.R_x.shape}")
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
        if self.R_x.ndim == 0 and self.dim_y is not None:
            self.R_x = float(self.R_x) * np.eye(self.dim_y)
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

        Named as filterpy's ``y``.
        """
        return self._core.innovation

    @property
    def S(self) -> np.ndarray:
        """Innovation covariance of the last update, shape (p, p).

        S = H̃ C⁻ H̃ᵀ + R_x, as filterpy's ``S``.
        """
        return self._core.S

    @property
    def log_likelihood(self) -> float:
        """Log-likelihood log N(y; h(x⁻), S) of the last measurement.

        Computed by ``update``, as filterpy's ``log_likelihood``.
        """
        return self._core.log_likelihood

    @property
    def likelihood(self) -> float:
        """Likelihood N(y; h(x⁻), S) of the last measurement.

        exp(``log_likelihood``), as filterpy's ``likelihood``.
        """
        return float(np.exp(self._core.log_likelihood))

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
        self._core.predict_step(self.f, u, zeta, self._A_fn, self._e_fn, self.Q_x)

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
            y, self.h, self._H_fn, self.R_x, self.dim_y, self.learning and not self.pure_prediction
        )

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
            learning=self.learning, pure_prediction=self.pure_prediction, Q_x=self.Q_x,
            R_x=self.R_x, n_gps=len(self.gps))
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
