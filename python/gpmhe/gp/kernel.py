"""`SEKernel`: the SE-ARD kernel with observation noise, the owner of the hyperparameters, their
bounds and the one mapping between natural units and θ = log([σ_f, ℓ_1..ℓ_nd, σ_ε]). The kernel
values are computed by the Rust core (``rust/src/kernel.rs``, `gpmhe._core.se_ard_kernel`)."""

from __future__ import annotations

from typing import Any, Optional

import numpy as np

from gpmhe import _core
from gpmhe._validation import float_array, positive, positive_scalar

__all__ = ["SEKernel", "DEFAULT_BOUNDS"]

#: Default hyperparameter bounds in natural units: (sigma_f, every length-scale, sigma_eps).
DEFAULT_BOUNDS = ((1e-3, 1e3), (1e-3, 1e3), (1e-5, 1e2))


def _check_bounds(bounds: Any, nd: Optional[int]) -> np.ndarray:
    """Natural-unit bounds as a float array of shape (3, 2) or (nd + 2, 2); with nd None (n_d not
    known yet) any n_d is accepted."""
    b = float_array("bounds", bounds)
    rows_ok = b.ndim == 2 and (b.shape[0] == 3 or (b.shape[0] > 3 if nd is None else b.shape[0] == nd + 2))
    if not rows_ok or b.shape[1] != 2:
        expected = "(n_d + 2, 2)" if nd is None else f"({nd + 2}, 2)"
        raise ValueError(f"bounds: expected shape (3, 2) (sigma_f, lengthscales, sigma_eps) or {expected}, got {b.shape}")
    if not np.all(np.isfinite(b)) or np.any(b <= 0) or np.any(b[:, 0] > b[:, 1]):
        raise ValueError("bounds: need finite 0 < low <= high in every row")
    return b


class SEKernel:
    """The squared-exponential kernel with automatic relevance determination and noise.

    For each of q outputs o on inputs d with n_d components::

        k_o(d, d') = sigma_f[o]^2 exp(-1/2 (d - d')^T diag(lengthscales[o])^-2 (d - d')),

    and the observations add independent noise of standard deviation sigma_eps[o]. The
    hyperparameters are held in natural units; optimisers see them as
    ``theta = log([sigma_f, lengthscales..., sigma_eps])`` within log-bounds. A kernel is
    immutable: `with_theta` and `with_bounds` return new ones. Every GP class of gpmhe owns one,
    as its ``kernel`` attribute: before ``fit`` it holds the initial values, after it the fitted
    ones.

    Parameters
    ----------
    sigma_f : float or array_like of shape (q,), default 1.0
        Signal standard deviations (a scalar serves every output).
    lengthscales : float or array_like of shape (n_d,) or (q, n_d), default 1.0
        Length-scales, broadcast over outputs and input dimensions.
    sigma_eps : float or array_like of shape (q,), default 0.1
        Noise standard deviations.
    bounds : array_like of shape (3, 2) or (n_d + 2, 2), default ``DEFAULT_BOUNDS``
        (low, high) in natural units for sigma_f, the length-scales (one row for all or one row
        each) and sigma_eps; the optimiser keeps theta within their logarithms.

    Attributes
    ----------
    sigma_f, lengthscales, sigma_eps : ndarray
        The hyperparameters as given (copies; shapes as given, a scalar as shape ()).
    bounds : ndarray of shape (3, 2) or (n_d + 2, 2)
        The bounds as given.

    Raises
    ------
    ValueError
        If a hyperparameter is not finite and positive or has too many dimensions, or the bounds
        are not finite 0 < low <= high pairs.

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe import SEKernel
    >>> k = SEKernel(sigma_f=2.0, lengthscales=[1.0, 10.0])
    >>> k.theta(1, 2).round(3)
    array([[ 0.693,  0.   ,  2.303, -2.303]])
    >>> bool(np.isclose(k([[0.0, 0.0]], [[1.0, 0.0]])[0, 0], 4.0 * np.exp(-0.5)))
    True
    >>> SEKernel.from_theta(k.theta(1, 2)).sigma_f
    array([2.])
    """

    __slots__ = ("_sigma_f", "_lengthscales", "_sigma_eps", "_bounds")

    def __init__(self, sigma_f: Any = 1.0, lengthscales: Any = 1.0, sigma_eps: Any = 0.1,
                 bounds: Any = DEFAULT_BOUNDS) -> None:
        # copies: the kernel's arrays are made read-only, never the caller's
        sf, ls, se = (positive(name, value).copy() for name, value in
                      (("sigma_f", sigma_f), ("lengthscales", lengthscales), ("sigma_eps", sigma_eps)))
        if 0 in (sf.size, se.size, ls.size):
            raise ValueError("sigma_f, lengthscales, sigma_eps: must not be empty")
        if sf.ndim > 1 or se.ndim > 1 or ls.ndim > 2:
            raise ValueError("sigma_f, sigma_eps: scalar or (q,); lengthscales: scalar, (n_d,) or (q, n_d)")
        with np.errstate(over="ignore", divide="ignore"):
            if not np.all(np.isfinite(1.0 / (ls * ls))):
                raise ValueError(f"lengthscales: {float(ls.min()):g} is too small: 1/lengthscale^2 overflows "
                                 f"(at least about 1.5e-154)")
        self._sigma_f, self._lengthscales, self._sigma_eps = sf, ls, se
        self._bounds = _check_bounds(bounds, None).copy()
        for a in (sf, ls, se, self._bounds):
            a.setflags(write=False)

    # -- values ------------------------------------------------------------------------------

    @property
    def sigma_f(self) -> np.ndarray:
        """Signal standard deviations, a scalar (shape ()) or one per output (q,)."""
        return self._sigma_f.copy()

    @property
    def lengthscales(self) -> np.ndarray:
        """Length-scales: a scalar, (n_d,) or (q, n_d)."""
        return self._lengthscales.copy()

    @property
    def sigma_eps(self) -> np.ndarray:
        """Noise standard deviations, a scalar (shape ()) or one per output (q,)."""
        return self._sigma_eps.copy()

    @property
    def bounds(self) -> np.ndarray:
        """(low, high) in natural units: (3, 2) or (n_d + 2, 2)."""
        return self._bounds.copy()

    # -- natural <-> log ---------------------------------------------------------------------

    def theta(self, q: int, nd: int) -> np.ndarray:
        """theta of q outputs on n_d inputs: the hyperparameters broadcast.

        Parameters
        ----------
        q : int
            Number of outputs.
        nd : int
            Number of inputs n_d.

        Returns
        -------
        ndarray of shape (q, n_d + 2)
            One row log([sigma_f, lengthscales..., sigma_eps]) per output.

        Raises
        ------
        ValueError
            If the hyperparameters do not broadcast to q outputs and n_d inputs.

        Examples
        --------
        >>> from gpmhe import SEKernel
        >>> SEKernel(sigma_f=[1.0, 2.0], lengthscales=1.0).theta(2, 3).shape
        (2, 5)
        """
        try:
            sf, se = np.broadcast_to(self._sigma_f, (q,)), np.broadcast_to(self._sigma_eps, (q,))
        except ValueError:
            raise ValueError(f"sigma_f, sigma_eps: expected a scalar or {q} values (one per output)") from None
        try:
            ls = np.broadcast_to(self._lengthscales, (q, nd))
        except ValueError:
            raise ValueError(f"lengthscales: expected a scalar, ({nd},) or ({q}, {nd}), "
                             f"got {self._lengthscales.shape}") from None
        return np.log(np.column_stack([sf, ls, se]))

    @classmethod
    def from_theta(cls, theta: Any, bounds: Any = DEFAULT_BOUNDS) -> "SEKernel":
        """The kernel of theta: sigma_f (q,), lengthscales (q, n_d) and sigma_eps (q,).

        Parameters
        ----------
        theta : array_like of shape (q, n_d + 2) or (n_d + 2,)
            log([sigma_f, lengthscales..., sigma_eps]) per output (one row: one output).
        bounds : array_like of shape (3, 2) or (n_d + 2, 2), default ``DEFAULT_BOUNDS``
            The new kernel's bounds, in natural units.

        Returns
        -------
        SEKernel

        Raises
        ------
        ValueError
            If theta has fewer than 3 columns or exp(theta) overflows.

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import SEKernel
        >>> SEKernel.from_theta(np.log([2.0, 3.0, 0.5])).lengthscales
        array([[3.]])
        """
        t = float_array("theta", theta)
        if t.ndim not in (1, 2) or t.shape[-1] < 3:
            raise ValueError(f"theta: needs n_d + 2 >= 3 values per output, got shape {t.shape}")
        with np.errstate(over="ignore"):
            p = np.exp(t.reshape(-1, t.shape[-1]))
        if not np.all(np.isfinite(p)):
            raise ValueError("theta: exp(theta) overflows")
        return cls(p[:, 0], p[:, 1:-1], p[:, -1], bounds)

    def with_theta(self, theta: Any) -> "SEKernel":
        """A kernel with the values of theta and these bounds (see `from_theta`).

        Parameters
        ----------
        theta : array_like of shape (q, n_d + 2) or (n_d + 2,)
            log([sigma_f, lengthscales..., sigma_eps]) per output.

        Returns
        -------
        SEKernel

        Examples
        --------
        >>> import numpy as np
        >>> from gpmhe import SEKernel
        >>> k = SEKernel(bounds=[(0.1, 10.0), (0.1, 10.0), (1e-3, 1.0)]).with_theta(np.zeros(3))
        >>> k.sigma_eps, k.bounds[2]
        (array([1.]), array([0.001, 1.   ]))
        """
        return self.from_theta(theta, self._bounds)

    def with_bounds(self, bounds: Any) -> "SEKernel":
        """A kernel with these values and new bounds.

        Parameters
        ----------
        bounds : array_like of shape (3, 2) or (n_d + 2, 2)
            (low, high) in natural units.

        Returns
        -------
        SEKernel

        Examples
        --------
        >>> from gpmhe import SEKernel
        >>> SEKernel().with_bounds([(1.0, 2.0), (1.0, 2.0), (0.1, 0.2)]).bounds[0]
        array([1., 2.])
        """
        return SEKernel(self._sigma_f, self._lengthscales, self._sigma_eps, bounds)

    def log_bounds(self, nd: int) -> np.ndarray:
        """The bounds on theta for n_d inputs (one row per component of theta).

        Parameters
        ----------
        nd : int
            Number of inputs n_d.

        Returns
        -------
        ndarray of shape (n_d + 2, 2)
            log(low), log(high) per component.

        Raises
        ------
        ValueError
            If the bounds have n_d + 2 rows for another n_d.

        Examples
        --------
        One row for all length-scales is repeated for each input:

        >>> import numpy as np
        >>> from gpmhe import SEKernel
        >>> np.exp(SEKernel().log_bounds(2))
        array([[1.e-03, 1.e+03],
               [1.e-03, 1.e+03],
               [1.e-03, 1.e+03],
               [1.e-05, 1.e+02]])
        """
        b = _check_bounds(self._bounds, nd)
        if b.shape[0] == 3:
            b = np.vstack([b[0], np.repeat(b[1:2], nd, axis=0), b[2]])
        return np.log(b)

    # -- evaluation --------------------------------------------------------------------------

    def __call__(self, A: Any, B: Any = None, output: int = 0) -> np.ndarray:
        """The kernel matrix k_o(A_i, B_j) of one output, without the noise, shape (len(A), len(B)).

        Parameters
        ----------
        A : array_like of shape (k, n_d)
        B : array_like of shape (l, n_d) or None, default None (B = A)
        output : int, default 0
            The output o whose hyperparameters are used.

        Examples
        --------
        >>> from gpmhe import SEKernel
        >>> SEKernel(sigma_f=[1.0, 3.0])([[0.0]], output=1)
        array([[9.]])
        """
        A = float_array("A", A, 2)
        B = A if B is None else float_array("B", B, 2)
        if B.shape[1] != A.shape[1]:
            raise ValueError(f"B: expected {A.shape[1]} columns like A, got {B.shape[1]}")
        q = max(self._sigma_f.size, self._sigma_eps.size, self._lengthscales.shape[0] if self._lengthscales.ndim == 2 else 1)
        if not 0 <= output < q:
            raise ValueError(f"output: expected 0 <= output < {q}, got {output}")
        theta = np.exp(self.theta(q, A.shape[1])[output])
        return _core.se_ard_kernel(np.ascontiguousarray(A), np.ascontiguousarray(B), float(theta[0]),
                                   np.ascontiguousarray(theta[1:-1]))

    def __eq__(self, other: Any) -> bool:
        if not isinstance(other, SEKernel):
            return NotImplemented
        return all(np.array_equal(a, b) and a.shape == b.shape for a, b in zip(
            (self._sigma_f, self._lengthscales, self._sigma_eps, self._bounds),
            (other._sigma_f, other._lengthscales, other._sigma_eps, other._bounds)))

    __hash__ = None  # type: ignore[assignment]  (mutable-looking numpy values: not hashable)

    def __repr__(self) -> str:
        def fmt(a: np.ndarray) -> str:
            return f"{float(a):.4g}" if a.ndim == 0 else np.array2string(
                a, separator=", ", formatter={"float_kind": lambda v: f"{v:.4g}"})
        return (f"SEKernel(sigma_f={fmt(self._sigma_f)}, lengthscales={fmt(self._lengthscales)}, "
                f"sigma_eps={fmt(self._sigma_eps)})")


def one_output(sigma_f: Any, lengthscales: Any, sigma_eps: Any, bounds: Any) -> SEKernel:
    """The kernel of a one-output GP: sigma_f and sigma_eps numbers, lengthscales a number or 1-D."""
    sf, se = positive_scalar("sigma_f", sigma_f), positive_scalar("sigma_eps", sigma_eps)
    ls = positive("lengthscales", lengthscales)
    if ls.ndim > 1 or ls.size == 0:
        raise ValueError("lengthscales: must be a positive scalar or a 1-D array")
    return SEKernel(sf, ls, se, bounds)
