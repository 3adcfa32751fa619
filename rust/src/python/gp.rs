//! Exact GPs (`crate::gp`): `MultiGP` (independent outputs on shared inputs; gpmhe.GaussianProcess
//! is its q = 1 case), `log_marginal_likelihood` and the kernel matrix. Inputs must be C-contiguous
//! float64 (gpmhe/gp/base.py converts and validates first); the numerics run without the GIL.

use numpy::{PyArray2, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;

use super::convert::{array2, slice1, slice2};
use super::error::detach_interruptible;
use crate::error::Error;
use crate::kernel::SeArd;

use crate::gp::{log_marginal_likelihood, MultiGp};
use crate::gp_model::GpPredict;
use crate::mean::AffineMean;
use numpy::{IntoPyArray, PyArray1, PyArrayDyn};

/// Fails with `ValueError` naming `arg` unless the point set has `nd` columns.
pub(super) fn check_cols(arg: &str, cols: usize, nd: usize) -> PyResult<()> {
    if cols == nd {
        Ok(())
    } else {
        Err(PyValueError::new_err(format!(
            "{arg}: expected {nd} columns (input dimension n_d), got {cols}"
        )))
    }
}

/// A numpy array of the given shape that takes over a row-major vector (no copy, no reshape).
pub(super) fn array_nd<'py, const D: usize>(
    py: Python<'py>,
    data: Vec<f64>,
    shape: [usize; D],
) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
    let arr = numpy::ndarray::ArrayD::from_shape_vec(&shape[..], data)
        .map_err(|e| PyRuntimeError::new_err(format!("internal: output shape: {e}")))?;
    Ok(arr.into_pyarray(py))
}

pub(super) type Arr<'py> = Bound<'py, PyArrayDyn<f64>>;
/// mean, var and, when asked for, (dmean_dd, dvar_dd).
pub(super) type Predicted<'py> = (Arr<'py>, Arr<'py>, Option<(Arr<'py>, Arr<'py>)>);

/// Posterior means at the points `d`, shape (k, q).
pub(super) fn mean_array<'py, P: GpPredict>(
    py: Python<'py>,
    model: &P,
    d: &PyReadonlyArray2<'py, f64>,
) -> PyResult<Arr<'py>> {
    let (d, k, cols) = slice2("D", d)?;
    let q = model.n_outputs();
    check_cols("D", cols, model.dim())?;
    crate::error::check_finite("D", d)?;
    let mut mean = vec![0.0; k * q];
    model.predict_mean_into(d, &mut mean, &mut P::Workspace::default())?;
    array_nd(py, mean, [k, q])
}

/// Runs a batch prediction of the `q` outputs at the points `d` with the GIL released and
/// returns (mean, var[, dmean, dvar]) shaped (k, q) / (k, q, n_d).
pub(super) fn predict_arrays<'py, P: GpPredict>(
    py: Python<'py>,
    model: &P,
    d: &PyReadonlyArray2<'py, f64>,
    gradients: bool,
) -> PyResult<Predicted<'py>> {
    // Named "D" as in the Python API; the wrappers leave the NaN/inf scan to this O(k) check.
    let (d, k, cols) = slice2("D", d)?;
    let (q, nd) = (model.n_outputs(), model.dim());
    check_cols("D", cols, nd)?;
    crate::error::check_finite("D", d)?;
    let (mean, var, dmean, dvar) = py.detach(|| {
        let mut ws = P::Workspace::default();
        let (mut m, mut v) = (vec![0.0; k * q], vec![0.0; k * q]);
        if gradients {
            let (mut dm, mut dv) = (vec![0.0; k * q * nd], vec![0.0; k * q * nd]);
            model.predict_with_gradients_into(d, &mut m, &mut v, &mut dm, &mut dv, &mut ws)?;
            Ok::<_, Error>((m, v, dm, dv))
        } else {
            model.predict_into(d, &mut m, &mut v, &mut ws)?;
            Ok((m, v, Vec::new(), Vec::new()))
        }
    })?;
    let grads = match gradients {
        true => Some((
            array_nd(py, dmean, [k, q, nd])?,
            array_nd(py, dvar, [k, q, nd])?,
        )),
        false => None,
    };
    Ok((
        array_nd(py, mean, [k, q])?,
        array_nd(py, var, [k, q])?,
        grads,
    ))
}

/// (mean, var, gradients) of the four-array prediction, as a Python tuple.
pub(super) fn with_gradients<'py>(
    p: Predicted<'py>,
) -> PyResult<(Arr<'py>, Arr<'py>, Arr<'py>, Arr<'py>)> {
    match p {
        (m, v, Some((dm, dv))) => Ok((m, v, dm, dv)),
        _ => Err(PyRuntimeError::new_err(
            "internal: gradients were not computed",
        )),
    }
}

/// q independent GPs on shared inputs, each with its own hyperparameters.
#[pyclass(name = "MultiGP", module = "gpmhe._core", frozen)]
pub(super) struct PyMultiGp {
    pub(crate) inner: MultiGp,
}

/// The prior mean of a `MultiGP` or `SparseMultiGP` constructor: coefficients (q, n_d + 1), rows
/// [b, w...], or None (zero mean). A ValueError names `mean` if the shape does not fit.
pub(super) fn affine_mean(
    mean: Option<&PyReadonlyArray2<'_, f64>>,
    q: usize,
    nd: usize,
) -> PyResult<Option<AffineMean>> {
    let Some(mean) = mean else {
        return Ok(None);
    };
    let (coef, qm, cm) = slice2("mean", mean)?;
    if qm != q || cm != nd + 1 {
        return Err(PyValueError::new_err(format!(
            "mean: expected shape ({q}, {}), got ({qm}, {cm})",
            nd + 1
        )));
    }
    Ok(Some(AffineMean::new(q, nd, coef.to_vec())?))
}

/// The coefficients (q, n_d + 1) of a prior mean as a numpy array (None for the zero mean).
pub(super) fn mean_coefficients<'py>(
    py: Python<'py>,
    mean: Option<&AffineMean>,
) -> PyResult<Option<Bound<'py, PyArray2<f64>>>> {
    mean.map(|m| array2(py, m.coefficients().to_vec(), m.n_outputs(), m.dim() + 1))
        .transpose()
}

#[pymethods]
impl PyMultiGp {
    /// MultiGP(x, y, thetas, mean=None): x (N, n_d), y (N, q), thetas (q, n_d + 2); with a
    /// prior mean (coefficients (q, n_d + 1), rows [b, w...]), y are the residuals y − m(x).
    #[new]
    #[pyo3(signature = (x, y, thetas, mean=None))]
    fn py_new(
        py: Python<'_>,
        x: PyReadonlyArray2<'_, f64>,
        y: PyReadonlyArray2<'_, f64>,
        thetas: PyReadonlyArray2<'_, f64>,
        mean: Option<PyReadonlyArray2<'_, f64>>,
    ) -> PyResult<Self> {
        let (x, n, nd) = slice2("x", &x)?;
        let (y, ny, q) = slice2("y", &y)?;
        let (thetas, qt, cols) = slice2("thetas", &thetas)?;
        if ny != n {
            return Err(PyValueError::new_err(format!(
                "y: expected {n} rows (one per training input), got {ny}"
            )));
        }
        if qt != q || cols != nd + 2 {
            return Err(PyValueError::new_err(format!(
                "thetas: expected shape ({q}, {}), got ({qt}, {cols})",
                nd + 2
            )));
        }
        let mean = affine_mean(mean.as_ref(), q, nd)?;
        let inner = detach_interruptible(py, || MultiGp::new(x, y, thetas))?;
        Ok(Self {
            inner: match mean {
                Some(m) => inner.with_mean(m)?,
                None => inner,
            },
        })
    }

    // ---- copies and pickles -----------------------------------------------------------------
    /// Pickles as `MultiGP(x, y, thetas, mean)`: the same data factorise to the same GP, bit for
    /// bit.
    fn __reduce__<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, pyo3::types::PyTuple>> {
        let gps = self.inner.gps();
        let (q, nd) = (self.inner.n_outputs(), self.inner.dim());
        let n = gps[0].n_train();
        let x = array2(py, gps[0].x_train().to_vec(), n, nd)?;
        let mut y = vec![0.0; n * q];
        for (o, g) in gps.iter().enumerate() {
            for (i, v) in g.y_train().iter().enumerate() {
                y[i * q + o] = *v;
            }
        }
        let thetas: Vec<f64> = gps.iter().flat_map(|g| g.theta()).collect();
        let args = (
            x,
            array2(py, y, n, q)?,
            array2(py, thetas, q, nd + 2)?,
            self.mean(py)?,
        );
        (py.get_type::<Self>(), args).into_pyobject(py)
    }

    /// Immutable: a copy is the same object.
    fn __copy__(slf: Py<Self>) -> Py<Self> {
        slf
    }

    fn __deepcopy__(slf: Py<Self>, _memo: Bound<'_, PyAny>) -> Py<Self> {
        slf
    }

    #[getter]
    fn n_outputs(&self) -> usize {
        self.inner.n_outputs()
    }
    #[getter]
    fn dim(&self) -> usize {
        self.inner.dim()
    }
    #[getter]
    fn n_train(&self) -> usize {
        self.inner.gps()[0].n_train()
    }
    /// (q, n_d + 2) log-hyperparameters, one row per output.
    #[getter]
    fn thetas<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let data: Vec<f64> = self.inner.gps().iter().flat_map(|g| g.theta()).collect();
        array2(py, data, self.inner.n_outputs(), self.inner.dim() + 2)
    }
    /// The prior mean's coefficients (q, n_d + 1), rows [b, w...], or None (zero mean).
    #[getter]
    fn mean<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyArray2<f64>>>> {
        mean_coefficients(py, self.inner.mean())
    }
    /// The diagonal jitter each output's factorisation needed (0 if none).
    #[getter]
    fn jitters<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_vec(py, self.inner.gps().iter().map(|g| g.jitter()).collect())
    }

    /// The log marginal likelihood of each output, shape (q,).
    fn log_marginal_likelihoods<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        let v = self
            .inner
            .gps()
            .iter()
            .map(|g| g.log_marginal_likelihood())
            .collect();
        PyArray1::from_vec(py, v)
    }

    /// The gradients of each output's log marginal likelihood w.r.t. its theta, shape
    /// (q, n_d + 2), from the cached factors (O(N³) per output for K⁻¹).
    fn log_marginal_likelihood_gradients<'py>(
        &self,
        py: Python<'py>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let gps = self.inner.gps();
        let data: Vec<f64> = py.detach(|| {
            gps.iter()
                .flat_map(|g| g.log_marginal_likelihood_gradient())
                .collect()
        });
        array2(py, data, self.inner.n_outputs(), self.inner.dim() + 2)
    }

    /// (mean, var) of shapes (k, q) at the points d (k, n_d).
    fn predict<'py>(
        &self,
        py: Python<'py>,
        d: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<(Arr<'py>, Arr<'py>)> {
        let (m, v, _) = predict_arrays(py, &self.inner, &d, false)?;
        Ok((m, v))
    }

    /// (mean, var, dmean_dd, dvar_dd) of shapes (k, q), (k, q), (k, q, n_d), (k, q, n_d).
    fn predict_with_gradients<'py>(
        &self,
        py: Python<'py>,
        d: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<(Arr<'py>, Arr<'py>, Arr<'py>, Arr<'py>)> {
        with_gradients(predict_arrays(py, &self.inner, &d, true)?)
    }

    /// Means only, shape (k, q): O(N) per point and output (no triangular solves).
    fn predict_mean<'py>(
        &self,
        py: Python<'py>,
        d: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<Arr<'py>> {
        mean_array(py, &self.inner, &d)
    }
}

/// (lml, grad): log p(y | x, theta) and, if eval_gradient, its gradient w.r.t.
/// theta = log([sigma_f, lengthscales.., sigma_eps]) (an empty array otherwise).
#[pyfunction]
#[pyo3(name = "log_marginal_likelihood", signature = (x, y, theta, eval_gradient=false))]
pub(super) fn gp_log_marginal_likelihood<'py>(
    py: Python<'py>,
    x: PyReadonlyArray2<'py, f64>,
    y: PyReadonlyArray1<'py, f64>,
    theta: PyReadonlyArray1<'py, f64>,
    eval_gradient: bool,
) -> PyResult<(f64, Bound<'py, PyArray1<f64>>)> {
    let (x, _, cols) = slice2("x", &x)?;
    let (y, theta) = (slice1("y", &y)?, slice1("theta", &theta)?);
    check_cols("x", cols, theta.len().saturating_sub(2))?;
    let (lml, grad) =
        detach_interruptible(py, || log_marginal_likelihood(x, y, theta, eval_gradient))?;
    Ok((lml, PyArray1::from_vec(py, grad)))
}

/// The SE-ARD cross-kernel matrix k(a_i, b_j) (tests and diagnostics).
#[pyfunction]
pub(super) fn se_ard_kernel<'py>(
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
