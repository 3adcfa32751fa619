"""Gaussian-process regression with the SE-ARD kernel, for learning the models of the
estimators.

The public classes are `GaussianProcess` (``single.py``), `MultiOutputGP` (``multi.py``) and
their sparse counterparts `SparseGaussianProcess`, `SparseMultiOutputGP` (``sparse.py``). All
four are one implementation (``base.py``'s `_GP`, with the one- or several-output shapes of
``outputs.py``) that owns an `SEKernel` (``kernel.py``: θ, its bounds, natural ↔ log units) and
hands the fit and the core model to an approximation object: exact (``exact.py``) or inducing
points (``inducing.py``). Shared fitting machinery (L-BFGS-B with restarts) is ``fit.py``; prior
means and hyperpriors ``priors.py``; fit diagnostics ``diagnostics.py``; the layer's warning and
error ``errors.py``. The numerics run on the Rust core; see the user guide, *Gaussian processes*.
"""

from gpmhe.gp.diagnostics import FitDiagnostics, FitWarning
from gpmhe.gp.errors import ConvergenceWarning, NotFittedError
from gpmhe.gp.kernel import SEKernel
from gpmhe.gp.multi import MultiOutputGP
from gpmhe.gp.single import GaussianProcess
from gpmhe.gp.sparse import SparseGaussianProcess, SparseMultiOutputGP

__all__ = ["GaussianProcess", "MultiOutputGP", "SparseGaussianProcess", "SparseMultiOutputGP",
           "SEKernel", "ConvergenceWarning", "NotFittedError", "FitDiagnostics", "FitWarning"]
