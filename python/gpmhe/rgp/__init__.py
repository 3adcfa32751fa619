"""The RGP-dKF of Husmann, Weishaupt & Aschemann, "Direct Integration of Recursive Gaussian Process
Regression Into Extended Kalman Filters": `RecursiveGP` (``recursive.py``) and `RGPEKF`, the EKF
that learns it online (``ekf.py``); see the user guide, *The RGP-dKF*.
"""

from gpmhe.rgp.ekf import RGPEKF
from gpmhe.rgp.recursive import RecursiveGP

__all__ = ["RecursiveGP", "RGPEKF"]
