"""Constants the theory modules share: the paper's reference and the machine epsilon."""

import numpy as np

_PAPER = ("T. M. Wolff, V. G. Lopez and M. A. Müller, \"Robust stability of Gaussian process "
          "based moving horizon estimation\", IEEE CDC 2023.")
_EPS = np.finfo(float).eps
