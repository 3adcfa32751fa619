"""The SE-ARD kernel's hyperparameters θ = log([σ_f, length-scales…, σ_ε]): the one mapping
between natural units and log units, and the default bounds the optimiser keeps θ in. The kernel
itself is computed by the Rust core (``rust/src/kernel.rs``)."""

from __future__ import annotations

from typing import Any, Optional, Tuple

import numpy as np

from gpmhe._validation import (
    float_array,
)


__all__ = ["DEFAULT_BOUNDS"]

#: Default hyperparameter bounds in natural units: (sigma_f, every length-scale, sigma_eps).
DEFAULT_BOUNDS = ((1e-3, 1e3), (1e-3, 1e3), (1e-5, 1e2))


class _Theta:
    """theta = log([sigma_f, lengthscales..., sigma_eps]), one row per output, in one place.

    The public classes keep the hyperparameters in natural units (``sigma_f``, ``lengthscales``,
    ``sigma_eps``), the optimiser works on theta within log-bounds, and the core takes theta as a
    (q, n_d + 2) array: these are all of the conversions between them, and the bounds.
    """

    @staticmethod
    def from_natural(sigma_f: Any, lengthscales: Any, sigma_eps: Any, q: int, nd: int) -> np.ndarray:
        """(q, n_d + 2) theta from natural units broadcast over q outputs and n_d inputs."""
        try:
            sf = np.broadcast_to(sigma_f, (q,))
            se = np.broadcast_to(sigma_eps, (q,))
        except ValueError:
            raise ValueError(f"sigma_f, sigma_eps: expected a scalar or {q} values (one per output)") from None
        try:
            ls = np.broadcast_to(lengthscales, (q, nd))
        except ValueError:
            raise ValueError(
                f"lengthscales: expected a scalar, ({nd},) or ({q}, {nd}), got {np.shape(lengthscales)}"
            ) from None
        return np.log(np.column_stack([sf, ls, se]))

    @staticmethod
    def to_natural(theta: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(sigma_f (q,), lengthscales (q, n_d), sigma_eps (q,)) of a (q, n_d + 2) theta."""
        t = np.exp(theta)
        return t[:, 0].copy(), t[:, 1:-1].copy(), t[:, -1].copy()

    @staticmethod
    def log_bounds(bounds: Any, nd: Optional[int]) -> np.ndarray:
        """Natural-unit bounds -> (nd + 2, 2) bounds on theta. With nd None (n_d not known yet)
        only the form is checked and the rows are returned as given."""
        b = float_array("bounds", bounds)
        rows_ok = b.ndim == 2 and (b.shape[0] == 3 or (b.shape[0] > 3 if nd is None else b.shape[0] == nd + 2))
        if not rows_ok or b.shape[1] != 2:
            expected = "(n_d + 2, 2)" if nd is None else f"({nd + 2}, 2)"
            raise ValueError(
                f"bounds: expected shape (3, 2) (sigma_f, lengthscales, sigma_eps) or {expected}, got {b.shape}"
            )
        if not np.all(np.isfinite(b)) or np.any(b <= 0) or np.any(b[:, 0] > b[:, 1]):
            raise ValueError("bounds: need finite 0 < low <= high in every row")
        if b.shape[0] == 3 and nd is not None:
            b = np.vstack([b[0], np.repeat(b[1:2], nd, axis=0), b[2]])
        return np.log(b)
