"""gpmhe: state estimation with models learned by Gaussian processes.

GP-based moving horizon estimation (``GPMHE``) after Wolff, Lopez & Müller, and a recursive GP
inside an EKF (``RGPEKF``) after Husmann, Weishaupt & Aschemann, on a Rust numerical core
(``gpmhe._core``).
"""

from gpmhe._core import NumericalError
from gpmhe.mhe import GPMHE
from gpmhe.models import KnownModel

__all__ = ["NumericalError", "GPMHE", "KnownModel"]
__version__ = "0.1.0"
