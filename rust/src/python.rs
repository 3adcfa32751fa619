//! The pyo3 binding: the only file that knows Python. It turns numpy arrays into slices
//! (zero-copy when C-contiguous float64; the Python wrappers convert anything else first), releases
//! the GIL around the numerics, and maps core errors to exceptions: `InvalidInput` to `ValueError`,
//! `Numerical` to `gpmhe.NumericalError`.

use numpy::{PyArray2, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::create_exception;
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;

use crate::error::Error;
use crate::kernel::SeArd;

create_exception!(
    _core,
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

/// The SE-ARD cross-kernel matrix k(a_i, b_j) (tests and diagnostics).
#[pyfunction]
fn se_ard_kernel<'py>(
    py: Python<'py>,
    a: PyReadonlyArray2<'py, f64>,
    b: PyReadonlyArray2<'py, f64>,
    sigma_f: f64,
    lengthscales: PyReadonlyArray1<'py, f64>,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let kernel = SeArd::new(sigma_f, slice1("lengthscales", &lengthscales)?)?;
    let (a, na, _) = slice2("a", &a)?;
    let (b, nb, _) = slice2("b", &b)?;
    kernel.count_points("a", a)?;
    kernel.count_points("b", b)?;
    let out = py.detach(|| {
        let k = kernel.cross(a, b);
        let mut out = vec![0.0; na * nb];
        for i in 0..na {
            for j in 0..nb {
                out[i * nb + j] = k[(i, j)];
            }
        }
        out
    });
    array2(py, out, na, nb)
}

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("NumericalError", m.py().get_type::<NumericalError>())?;
    m.add_function(wrap_pyfunction!(se_ard_kernel, m)?)?;
    Ok(())
}
