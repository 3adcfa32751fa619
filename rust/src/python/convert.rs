//! Conversions between numpy arrays and slices, in one place: zero-copy views of C-contiguous
//! float64 input (the Python wrappers convert anything else first), and row-major vectors handed
//! to numpy as arrays without a copy.

use numpy::{PyArray2, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

/// The data of a 1-D float64 array as a slice; `ValueError` naming `arg` if not contiguous.
pub(crate) fn slice1<'a>(arg: &str, a: &'a PyReadonlyArray1<'_, f64>) -> PyResult<&'a [f64]> {
    a.as_slice()
        .map_err(|_| PyValueError::new_err(format!("{arg}: must be a contiguous float64 array")))
}

/// The data of a C-contiguous 2-D float64 array as a row-major slice, with (rows, cols).
pub(crate) fn slice2<'a>(
    arg: &str,
    a: &'a PyReadonlyArray2<'_, f64>,
) -> PyResult<(&'a [f64], usize, usize)> {
    let shape = a.shape();
    let (rows, cols) = (shape[0], shape[1]);
    // as_slice also accepts Fortran order, which would be read transposed here.
    if !a.is_c_contiguous() {
        return Err(PyValueError::new_err(format!(
            "{arg}: must be a C-contiguous float64 array"
        )));
    }
    let data = a.as_slice().map_err(|_| {
        PyValueError::new_err(format!("{arg}: must be a C-contiguous float64 array"))
    })?;
    Ok((data, rows, cols))
}

/// A row-major (rows × cols) numpy array from a vector.
pub(crate) fn array2(
    py: Python<'_>,
    data: Vec<f64>,
    rows: usize,
    cols: usize,
) -> PyResult<Bound<'_, PyArray2<f64>>> {
    numpy::PyArray1::from_vec(py, data).reshape([rows, cols])
}
