"""The stability theory of GP-MHE as software: certify the detectability assumption of Theorem 1,
design the MHE's prior weight P2 and discount η from it, and evaluate the minimal horizon, the
model mismatch and the error bound of Wolff, Lopez & Müller (Theorem 1, Corollary 1).

Everything here is pure Python on top of the public models. The semidefinite programs need the
optional dependency cvxpy (with the Clarabel solver), gpmhe's ``theory`` extra:
``pip install ".[theory]"`` in a clone of gpmhe, or ``pip install cvxpy clarabel``; cvxpy is
imported only when a function needs it.

The functions follow the paper's symbols: ``weight_bounds`` gives Q_min⁻¹, Q_max⁻¹, R_min⁻¹,
R_max⁻¹ of eqs. (14)–(17); ``certify_ioss`` finds a quadratic δ-IOSS Lyapunov function (18) and
returns a :class:`Certificate` (P1, P2, η, the minimal horizon M̄ and μ); ``mismatch`` gives
α₁^max, α₂^max of eqs. (19)–(20); ``corollary1`` the quantities (22)–(28); ``error_bound`` the
right-hand side of (21).
"""

from gpmhe.theory.bound import error_bound
from gpmhe.theory.certificate import Certificate, certify_ioss
from gpmhe.theory.corollary import Corollary1, corollary1
from gpmhe.theory.mismatch import Mismatch, mismatch
from gpmhe.theory.weights import WeightBounds, weight_bounds

__all__ = [
    "WeightBounds",
    "weight_bounds",
    "Certificate",
    "certify_ioss",
    "Mismatch",
    "mismatch",
    "Corollary1",
    "corollary1",
    "error_bound",
]
