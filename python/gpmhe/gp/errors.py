"""The GP layer's warning and error: `ConvergenceWarning` (an optimiser that stopped short) and
`NotFittedError` (a model used before ``fit``)."""

from __future__ import annotations


__all__ = ["ConvergenceWarning", "NotFittedError"]

class ConvergenceWarning(UserWarning):
    """The hyperparameter optimiser stopped where the fit has not converged.

    Issued by the GPs' ``fit`` when the best L-BFGS-B run (over the start and the random
    restarts) and a second run from it both stopped without reaching a point whose projected
    gradient is small, whatever status SciPy reported (an iteration limit, badly scaled data, or
    a kernel matrix whose jitter changes between trial points). The message says what to try.
    The best hyperparameters found are still used.

    See Also
    --------
    GaussianProcess.fit : Emits this warning.

    Examples
    --------
    Turn it into an error, e.g. in a test suite:

    >>> import warnings
    >>> from gpmhe import ConvergenceWarning
    >>> with warnings.catch_warnings():
    ...     warnings.simplefilter("error", ConvergenceWarning)
    ...     issubclass(ConvergenceWarning, UserWarning)
    True
    """


class NotFittedError(ValueError, AttributeError):
    """A method that needs a fitted model was called before ``fit``.

    It derives from both `ValueError` and `AttributeError` (as scikit-learn's error of the same
    name does), so either can be caught.

    See Also
    --------
    GaussianProcess.fit : Fit a single-output GP.
    MultiOutputGP.fit : Fit independent GPs for several outputs.

    Examples
    --------
    >>> from gpmhe import GaussianProcess, NotFittedError
    >>> try:
    ...     GaussianProcess().predict([[0.0]])
    ... except NotFittedError as err:
    ...     print(err)
    this GaussianProcess is not fitted yet; call fit(D, y) first
    """
