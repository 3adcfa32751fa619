"""gpmhe: state estimation with models learned by Gaussian processes.

GP-based moving horizon estimation (``GPMHE``) after Wolff, Lopez & Müller, and a recursive GP
inside an EKF (``RGPEKF``) after Husmann, Weishaupt & Aschemann, on a Rust numerical core
(``gpmhe._core``). The estimators follow filterpy's conventions (``update``, ``batch_filter``,
attributes ``x`` and ``P``; `RGPEKF` also ``predict``).

* Gaussian processes: `GaussianProcess`, `MultiOutputGP` (with `ConvergenceWarning`,
  `NotFittedError`), their fit diagnostics `FitDiagnostics`, `FitWarning`, and their sparse
  (inducing-point) forms `SparseGaussianProcess`, `SparseMultiOutputGP` for thousands of
  training points, all with an `SEKernel` that owns the hyperparameters and their bounds;
* moving horizon estimation: `GPMHE` with a `LearnedModel` (GP-MHE) or a `KnownModel` (from
  Python callables, CasADi functions or a continuous-time model sampled by `discretize`), and
  `EstimatorBank`, many of them updated together (in parallel);
* the RGP-dKF: `RecursiveGP`, `RGPEKF`;
* `NumericalError`: a numerical failure on valid input; `SettingsWarning`: a setting assumed
  (identity weights when no noise information is given) or without effect;
* `monte_carlo`: Monte Carlo studies of estimators over many seeds, serially or on a Dask cluster
  (`gpmhe.study`);
* `gpmhe.consistency`: χ² tests of an estimator's uncertainty over a run (NEES, NIS);
* `gpmhe.baselines`: EKF baselines on filterpy; `gpmhe.systems`: the papers' example plants.

See the user guide, starting with *Notation*.
"""

from gpmhe._core import NumericalError
from gpmhe._validation import SettingsWarning
from gpmhe.gp import (ConvergenceWarning, FitDiagnostics, FitWarning, GaussianProcess,
                      MultiOutputGP, NotFittedError, SEKernel, SparseGaussianProcess, SparseMultiOutputGP)
from gpmhe.mhe import GPMHE, EstimatorBank
from gpmhe.models import KnownModel, LearnedModel
from gpmhe.models.discretization import DiscreteDynamics, discretize
from gpmhe.rgp import RGPEKF, RecursiveGP
from gpmhe.study import monte_carlo

__all__ = [
    "NumericalError",
    "SettingsWarning",
    # GP
    "GaussianProcess",
    "MultiOutputGP",
    "SparseGaussianProcess",
    "SparseMultiOutputGP",
    "SEKernel",
    "ConvergenceWarning",
    "NotFittedError",
    "FitDiagnostics",
    "FitWarning",
    # MHE
    "GPMHE",
    "EstimatorBank",
    "KnownModel",
    "LearnedModel",
    "discretize",
    "DiscreteDynamics",
    # RGP-dKF
    "RecursiveGP",
    "RGPEKF",
    # studies
    "monte_carlo",
]
__version__ = "0.1.0"
