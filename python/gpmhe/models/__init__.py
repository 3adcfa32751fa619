"""The models a `GPMHE` runs on: `LearnedModel` (GPs for f and h learned from data, the
paper's GP-MHE; ``learned.py``, its training data in ``training.py``) and `KnownModel` (Python
callables or CasADi functions, the exact-model MHE; ``known.py``, CasADi in ``casadi.py``, unknown
parameters in ``parameters.py``), and `discretize` (``discretization.py``) for continuous-time
models. Both describe x(t+1) = f(x(t), u(t)) + w(t), y(t) = h(x(t), u(t)) + v(t): for a batch of
points d = [x; u] they give the means, the latent variances (zero for a known model) and their
gradients, and the Rust core a stage model to evaluate. See the user guide, *Notation*.
"""

from gpmhe.models.discretization import DiscreteDynamics, discretize
from gpmhe.models.known import KnownModel
from gpmhe.models.learned import LearnedModel

__all__ = ["KnownModel", "LearnedModel", "discretize", "DiscreteDynamics"]
