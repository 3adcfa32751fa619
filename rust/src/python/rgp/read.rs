//! Reading what the user's model functions of an RGP-dKF step return: any numeric value as
//! float64 into a reused buffer, with its shape for the error messages.

use numpy::{PyArrayDyn, PyArrayMethods, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyFloat;

/// The shape of a value read by [`read_f64`] (up to four dimensions kept; more only appear in
/// error messages, as "…").
#[derive(PartialEq)]
pub(super) struct Shape {
    pub(super) ndim: usize,
    dims: [usize; 4],
}

impl Shape {
    fn of(dims: &[usize]) -> Self {
        let mut d = [0; 4];
        for (o, v) in d.iter_mut().zip(dims) {
            *o = *v;
        }
        Self {
            ndim: dims.len(),
            dims: d,
        }
    }

    pub(super) fn is(&self, dims: &[usize]) -> bool {
        self.ndim == dims.len() && self.dims[..self.ndim.min(4)] == *dims
    }

    /// Python's repr of the shape tuple: (), (3,), (2, 2).
    pub(super) fn repr(&self) -> String {
        let mut parts: Vec<String> = self.dims[..self.ndim.min(4)]
            .iter()
            .map(|d| d.to_string())
            .collect();
        if self.ndim > 4 {
            parts.push("…".into());
        }
        match parts.len() {
            1 => format!("({},)", parts[0]),
            _ => format!("({})", parts.join(", ")),
        }
    }
}

/// Copies the values of `obj` as float64 into `out` and returns its shape. Python floats and
/// C-contiguous float64 arrays are read directly; anything else goes through
/// `numpy.ascontiguousarray(obj, dtype=float64)` (lists, ints, other dtypes, column vectors
/// from views). A `ValueError` naming `arg` if that fails.
pub(super) fn read_f64(arg: &str, obj: &Bound<'_, PyAny>, out: &mut Vec<f64>) -> PyResult<Shape> {
    if let Ok(v) = obj.cast::<PyFloat>() {
        out.clear();
        out.push(v.value());
        return Ok(Shape::of(&[]));
    }
    let read = |a: &Bound<'_, PyArrayDyn<f64>>, out: &mut Vec<f64>| -> Option<Shape> {
        // SAFETY: the data are copied at once, with the GIL held and no Python code running in
        // between (as `PyArrayMethods::to_vec` does), into a buffer that is reused every step.
        let data = unsafe { a.as_slice() }
            .ok()
            .filter(|_| a.is_c_contiguous())?;
        out.clear();
        out.extend_from_slice(data);
        Some(Shape::of(a.shape()))
    };
    if let Ok(a) = obj.cast::<PyArrayDyn<f64>>() {
        if let Some(shape) = read(a, out) {
            return Ok(shape);
        }
    }
    let py = obj.py();
    let kwargs = pyo3::types::PyDict::new(py);
    kwargs.set_item("dtype", "float64")?;
    let conv = py
        .import("numpy")?
        .getattr("ascontiguousarray")?
        .call((obj,), Some(&kwargs))
        .map_err(|e| PyValueError::new_err(format!("{arg}: must be numeric ({e})")))?;
    conv.cast::<PyArrayDyn<f64>>()
        .ok()
        .and_then(|a| read(a, out))
        .ok_or_else(|| PyValueError::new_err(format!("{arg}: must be numeric")))
}
