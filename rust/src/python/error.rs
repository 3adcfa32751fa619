//! Error mapping, in one place: the core's `InvalidInput` becomes `ValueError` (naming the
//! argument), `Numerical` becomes `gpmhe.NumericalError` (a `RuntimeError`).

use pyo3::create_exception;
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;

use crate::error::Error;

create_exception!(
    gpmhe._core,
    NumericalError,
    PyRuntimeError,
    "A numerical failure on valid input (e.g. a matrix not positive definite after jitter)."
);

impl From<Error> for PyErr {
    fn from(err: Error) -> PyErr {
        match err {
            Error::InvalidInput { .. } => PyValueError::new_err(err.to_string()),
            Error::Numerical(_) => NumericalError::new_err(err.to_string()),
        }
    }
}
