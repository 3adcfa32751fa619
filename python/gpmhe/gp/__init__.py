"""Gaussian-process regression with the SE-ARD kernel, for learning the models of the
estimators: `GaussianProcess` (``single.py``) and `MultiOutputGP` (``multi.py``), exact GPs on
what they share (``base.py``, fitted by ``fit.py``), `SparseGaussianProcess` and
`SparseMultiOutputGP` (inducing points, ``sparse.py`` on ``sparse_base.py``), the hyperparameters θ and their bounds
(``kernel.py``), prior means and hyperpriors (``priors.py``), fit diagnostics
(``diagnostics.py``) and the layer's warning and error (``errors.py``). The numerics run on the
Rust core; see the user guide, *Gaussian processes*.
"""

from gpmhe.gp.diagnostics import FitDiagnostics, FitWarning
from gpmhe.gp.errors import ConvergenceWarning, NotFittedError
from gpmhe.gp.multi import MultiOutputGP
from gpmhe.gp.single import GaussianProcess
from gpmhe.gp.sparse import SparseGaussianProcess, SparseMultiOutputGP

__all__ = ["GaussianProcess", "MultiOutputGP", "SparseGaussianProcess", "SparseMultiOutputGP",
           "ConvergenceWarning", "NotFittedError", "FitDiagnostics", "FitWarning"]
