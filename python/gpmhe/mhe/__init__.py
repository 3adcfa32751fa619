"""Moving horizon estimation: `GPMHE` (``estimator.py``) with its settings (``settings.py``),
SciPy's reference solvers (``solvers.py``) and checkpoints (``checkpoint.py``), and
`EstimatorBank` (``bank.py``), many estimators updated together."""

from gpmhe.mhe.estimator import GPMHE
from gpmhe.mhe.bank import EstimatorBank

__all__ = ["GPMHE", "EstimatorBank"]
