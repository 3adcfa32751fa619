"""Type stubs of the Rust extension module gpmhe._core."""

import numpy as np
import numpy.typing as npt

class NumericalError(RuntimeError):
    """A numerical failure on valid input (e.g. a matrix not positive definite after jitter)."""

def se_ard_kernel(
    a: npt.NDArray[np.float64],
    b: npt.NDArray[np.float64],
    sigma_f: float,
    lengthscales: npt.NDArray[np.float64],
) -> npt.NDArray[np.float64]: ...
