//! The arrival cost's settings as Python enums, `ArrivalMean` and `ArrivalWeight`
//! (`crate::mhe::arrival`): how `gpmhe.GPMHE`'s `arrival_mean` and `arrival_weight` reach the
//! core, typed.

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyTuple;

use crate::mhe::{ArrivalMean, ArrivalWeight};

/// The arrival prior's mean: the estimator's own earlier estimate, or the previous window's
/// smoothed estimate of the new first node, or the leaving node's prior filtered with its output
/// and carried over its stage at the window's solution.
#[pyclass(
    name = "ArrivalMean",
    module = "gpmhe._core",
    eq,
    eq_int,
    frozen,
    from_py_object
)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum PyArrivalMean {
    Estimate,
    Smoothed,
    Filtered,
}

/// The arrival weight: constant (P2), or updated by an EKF step over the node that leaves.
#[pyclass(
    name = "ArrivalWeight",
    module = "gpmhe._core",
    eq,
    eq_int,
    frozen,
    from_py_object
)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum PyArrivalWeight {
    Constant,
    Ekf,
}

#[pymethods]
impl PyArrivalMean {
    /// The value named "estimate", "smoothed" or "filtered".
    #[staticmethod]
    fn from_name(name: &str) -> PyResult<Self> {
        match name {
            "estimate" => Ok(Self::Estimate),
            "smoothed" => Ok(Self::Smoothed),
            "filtered" => Ok(Self::Filtered),
            _ => Err(PyValueError::new_err(format!(
                "arrival_mean: must be 'estimate', 'smoothed' or 'filtered', got {name:?}"
            ))),
        }
    }

    /// Its name, as `from_name` reads it.
    #[getter]
    fn name(&self) -> &'static str {
        match self {
            Self::Estimate => "estimate",
            Self::Smoothed => "smoothed",
            Self::Filtered => "filtered",
        }
    }

    /// Pickles by name.
    fn __reduce__<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyTuple>> {
        let from_name = py.get_type::<Self>().getattr("from_name")?;
        (from_name, (self.name(),)).into_pyobject(py)
    }
}

#[pymethods]
impl PyArrivalWeight {
    /// The value named "constant" or "ekf".
    #[staticmethod]
    fn from_name(name: &str) -> PyResult<Self> {
        match name {
            "constant" => Ok(Self::Constant),
            "ekf" => Ok(Self::Ekf),
            _ => Err(PyValueError::new_err(format!(
                "arrival_weight: must be 'constant' or 'ekf', got {name:?}"
            ))),
        }
    }

    /// Its name, as `from_name` reads it.
    #[getter]
    fn name(&self) -> &'static str {
        match self {
            Self::Constant => "constant",
            Self::Ekf => "ekf",
        }
    }

    /// Pickles by name.
    fn __reduce__<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyTuple>> {
        let from_name = py.get_type::<Self>().getattr("from_name")?;
        (from_name, (self.name(),)).into_pyobject(py)
    }
}

impl From<PyArrivalMean> for ArrivalMean {
    fn from(m: PyArrivalMean) -> Self {
        match m {
            PyArrivalMean::Estimate => ArrivalMean::Estimate,
            PyArrivalMean::Smoothed => ArrivalMean::Smoothed,
            PyArrivalMean::Filtered => ArrivalMean::Filtered,
        }
    }
}

impl From<ArrivalMean> for PyArrivalMean {
    fn from(m: ArrivalMean) -> Self {
        match m {
            ArrivalMean::Estimate => PyArrivalMean::Estimate,
            ArrivalMean::Smoothed => PyArrivalMean::Smoothed,
            ArrivalMean::Filtered => PyArrivalMean::Filtered,
        }
    }
}

impl From<PyArrivalWeight> for ArrivalWeight {
    fn from(w: PyArrivalWeight) -> Self {
        match w {
            PyArrivalWeight::Constant => ArrivalWeight::Constant,
            PyArrivalWeight::Ekf => ArrivalWeight::Ekf,
        }
    }
}

impl From<ArrivalWeight> for PyArrivalWeight {
    fn from(w: ArrivalWeight) -> Self {
        match w {
            ArrivalWeight::Constant => PyArrivalWeight::Constant,
            ArrivalWeight::Ekf => PyArrivalWeight::Ekf,
        }
    }
}
