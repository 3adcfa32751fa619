"""`RecursiveGP`: recursive GP regression of z(ζ) on a grid of basis vectors (Huber's recursive
GP, as the RGP-dKF of Husmann, Weishaupt & Aschemann uses it, §2), learning from direct noisy
measurements of z, or continuing from a sparse GP trained offline (`RecursiveGP.from_sparse`:
its inducing inputs become the basis vectors). The numerics run in Rust (``gpmhe._core``).
"""

from __future__ import annotations

from typing import Any, Sequence, Union

import numpy as np

from gpmhe._core import RecursiveGPCore
from gpmhe.gp import GaussianProcess, MultiOutputGP, SparseGaussianProcess, SparseMultiOutputGP
from gpmhe._validation import (
    boolean,
    finite_vector,
    float_array,
    integer,
    positive_scalar,
    symmetric_matrix,
)

__all__ = ["RecursiveGP"]

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
        if not isinstance(gp, (SparseGaussianProcess, SparseMultiOutputGP)):
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
