"""What the theory functions share: checks of their inputs (a learned model, positive definite
weights, the box of states and inputs) and the grid of cells the box is covered with."""

from __future__ import annotations


import numpy as np

from gpmhe._validation import symmetric_matrix


def _require_cvxpy():
    try:
        import cvxpy
    except ImportError:
        raise ImportError(
            "gpmhe.theory needs cvxpy for its semidefinite programs: pip install cvxpy clarabel "
            "(without a network, from a wheelhouse made with --extras theory: "
            "pip install --no-index --find-links wheelhouse \"gpmhe[theory]\")"
        ) from None
    return cvxpy


def _check_model(model):
    for attr in ("dim_x", "dim_y", "dim_u", "stage_eval"):
        if not hasattr(model, attr):
            raise ValueError("model: must be a gpmhe.LearnedModel or gpmhe.KnownModel")
    return model


def _is_learned(model):
    return hasattr(model, "f_gp")


def _check_spd(name, a, dim):
    """A symmetric positive definite (dim, dim) matrix from a scalar, a (dim,) diagonal or a
    (dim, dim) matrix, symmetrised."""
    m = symmetric_matrix(name, a, dim, definite=True, vector_is_diagonal=True)
    return 0.5 * (m + m.T)


def _check_box(name, bounds, dim):
    """(lower, upper) float arrays of shape (dim,), finite, lower < upper."""
    if dim == 0:
        if bounds is not None and np.size(bounds[0]) + np.size(bounds[1]) != 0:
            raise ValueError(f"{name}: the model has no inputs of this kind; pass None")
        return np.zeros(0), np.zeros(0)
    if bounds is None:
        raise ValueError(f"{name}: required, a pair (lower, upper) of shape ({dim},)")
    try:
        lower, upper = bounds
        lower = np.asarray(lower, dtype=np.float64).reshape(-1)
        upper = np.asarray(upper, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: must be a pair (lower, upper) of arrays of shape ({dim},)") from None
    if lower.shape != (dim,) or upper.shape != (dim,):
        raise ValueError(f"{name}: lower and upper must have shape ({dim},), got {lower.shape}, "
                         f"{upper.shape}")
    if not (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper))):
        raise ValueError(f"{name}: must be finite (the theory needs a compact box)")
    if np.any(lower >= upper):
        raise ValueError(f"{name}: lower must be < upper in every component")
    return lower, upper


# ============================================================================ grid of the box


class _Grid:
    """The box X × U cut into cells: the cell centres (k, n_d) and the half-widths (n_d,)."""

    def __init__(self, lower, upper, cells):
        nd = lower.size
        counts = np.broadcast_to(np.asarray(cells, dtype=int), (nd,))
        width = (upper - lower) / counts
        axes = [lower[i] + (np.arange(counts[i]) + 0.5) * width[i] for i in range(nd)]
        mesh = np.meshgrid(*axes, indexing="ij")
        self.centers = np.column_stack([m.reshape(-1) for m in mesh])
        self.half = 0.5 * width
        self.counts = counts
        self.lower, self.upper = lower, upper

    def nodes(self):
        """The corners of all cells, ((counts+1).prod(), n_d)."""
        axes = [np.linspace(self.lower[i], self.upper[i], self.counts[i] + 1)
                for i in range(self.half.size)]
        mesh = np.meshgrid(*axes, indexing="ij")
        return np.column_stack([m.reshape(-1) for m in mesh])

    def vertices(self):
        """The 2^n_d corners of a cell relative to its centre, (2^n_d, n_d)."""
        nd = self.half.size
        signs = np.array(np.meshgrid(*([[-1.0, 1.0]] * nd), indexing="ij")).reshape(nd, -1).T
        return signs * self.half


def _default_cells(nd):
    return max(2, int(round(150 ** (1.0 / nd)))) if nd <= 6 else 2


def _check_cells(cells, nd):
    if cells is None:
        return np.full(nd, _default_cells(nd))
    c = np.asarray(cells)
    if c.ndim == 0:
        c = np.full(nd, c)
    if c.shape != (nd,) or not np.all(np.equal(np.mod(c, 1), 0)) or np.any(c < 1):
        raise ValueError(f"cells: must be a positive integer or {nd} positive integers, got {cells!r}")
    return c.astype(int)


