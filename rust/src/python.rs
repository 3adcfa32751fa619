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

// ===== GP =====
// Exact GPs (rust/src/gp.rs): `GP` (one output), `MultiGP` (independent outputs on shared inputs)
// and `log_marginal_likelihood`. Inputs must be C-contiguous float64 (the Python wrappers in
// gpmhe/gp.py convert and validate first); the numerics run with the GIL released.

use crate::gp::{log_marginal_likelihood, Gp, GpWorkspace, MultiGp};
use numpy::{IntoPyArray, PyArray1, PyArrayDyn};

/// Fails with `ValueError` naming `arg` unless the point set has `nd` columns.
fn check_cols(arg: &str, cols: usize, nd: usize) -> PyResult<()> {
    if cols == nd {
        Ok(())
    } else {
        Err(PyValueError::new_err(format!(
            "{arg}: expected {nd} columns (input dimension n_d), got {cols}"
        )))
    }
}

/// A numpy array of the given shape that takes over a row-major vector (no copy, no reshape).
fn array_nd<'py, const D: usize>(
    py: Python<'py>,
    data: Vec<f64>,
    shape: [usize; D],
) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
    let arr = numpy::ndarray::ArrayD::from_shape_vec(&shape[..], data)
        .map_err(|e| PyRuntimeError::new_err(format!("internal: output shape: {e}")))?;
    Ok(arr.into_pyarray(py))
}

type Arr<'py> = Bound<'py, PyArrayDyn<f64>>;

/// Runs a batch prediction of `q` outputs at the points `d` with the GIL released and returns
/// (mean, var[, dmean, dvar]) shaped (k, q...) / (k, q..., n_d); `squeeze` drops the q axis.
fn predict_arrays<'py>(
    py: Python<'py>,
    model: &MultiGp,
    d: &PyReadonlyArray2<'py, f64>,
    gradients: bool,
    squeeze: bool,
) -> PyResult<Vec<Arr<'py>>> {
    // Named "D" as in the Python API; the wrappers leave the NaN/inf scan to this O(k) check.
    let (d, k, cols) = slice2("D", d)?;
    let (q, nd) = (model.n_outputs(), model.dim());
    check_cols("D", cols, nd)?;
    crate::error::check_finite("D", d)?;
    let (mean, var, dmean, dvar) = py.detach(|| {
        let mut ws = GpWorkspace::default();
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
    let mut out = Vec::with_capacity(4);
    if squeeze {
        out.push(array_nd(py, mean, [k])?);
        out.push(array_nd(py, var, [k])?);
        if gradients {
            out.push(array_nd(py, dmean, [k, nd])?);
            out.push(array_nd(py, dvar, [k, nd])?);
        }
    } else {
        out.push(array_nd(py, mean, [k, q])?);
        out.push(array_nd(py, var, [k, q])?);
        if gradients {
            out.push(array_nd(py, dmean, [k, q, nd])?);
            out.push(array_nd(py, dvar, [k, q, nd])?);
        }
    }
    Ok(out)
}

/// One exact zero-mean GP with the SE-ARD kernel; the Cholesky factor is cached at construction.
#[pyclass(name = "GP", module = "gpmhe._core", frozen)]
pub(crate) struct PyGp {
    /// The GP as a one-output MultiGp, so predictions share one code path (see `gp()`).
    pub(crate) inner: MultiGp,
}

impl PyGp {
    pub(crate) fn gp(&self) -> &Gp {
        &self.inner.gps()[0]
    }
}

#[pymethods]
impl PyGp {
    /// GP(x, y, theta): x (N, n_d), y (N,), theta = log([sigma_f, lengthscales.., sigma_eps]).
    #[new]
    fn py_new(
        py: Python<'_>,
        x: PyReadonlyArray2<'_, f64>,
        y: PyReadonlyArray1<'_, f64>,
        theta: PyReadonlyArray1<'_, f64>,
    ) -> PyResult<Self> {
        let (x, _, cols) = slice2("x", &x)?;
        let (y, theta) = (slice1("y", &y)?, slice1("theta", &theta)?);
        check_cols("x", cols, theta.len().saturating_sub(2))?;
        let gp = py.detach(|| Gp::new(x, y, theta))?;
        Ok(Self {
            inner: MultiGp::from_gps(vec![gp])?,
        })
    }

    #[getter]
    fn dim(&self) -> usize {
        self.gp().dim()
    }
    #[getter]
    fn n_train(&self) -> usize {
        self.gp().n_train()
    }
    #[getter]
    fn theta<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_vec(py, self.gp().theta())
    }
    #[getter]
    fn sigma_f(&self) -> f64 {
        self.gp().kernel().sigma_f()
    }
    #[getter]
    fn lengthscales<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, self.gp().kernel().lengthscales())
    }
    #[getter]
    fn sigma_eps(&self) -> f64 {
        self.gp().sigma_eps()
    }
    #[getter]
    fn jitter(&self) -> f64 {
        self.gp().jitter()
    }
    #[getter]
    fn alpha<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, self.gp().alpha())
    }
    #[getter]
    fn x_train<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let g = self.gp();
        array2(py, g.x_train().to_vec(), g.n_train(), g.dim())
    }
    #[getter]
    fn y_train<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, self.gp().y_train())
    }

    /// (lml, grad) at this GP's theta; grad is empty unless eval_gradient.
    #[pyo3(signature = (eval_gradient=false))]
    fn log_marginal_likelihood<'py>(
        &self,
        py: Python<'py>,
        eval_gradient: bool,
    ) -> (f64, Bound<'py, PyArray1<f64>>) {
        let grad = if eval_gradient {
            py.detach(|| self.gp().log_marginal_likelihood_gradient())
        } else {
            Vec::new()
        };
        (
            self.gp().log_marginal_likelihood(),
            PyArray1::from_vec(py, grad),
        )
    }

    /// (mean, var) of shapes (k,), (k,) at the points d (k, n_d).
    fn predict<'py>(
        &self,
        py: Python<'py>,
        d: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<(Arr<'py>, Arr<'py>)> {
        let mut out = predict_arrays(py, &self.inner, &d, false, true)?.into_iter();
        match (out.next(), out.next()) {
            (Some(m), Some(v)) => Ok((m, v)),
            _ => Err(PyRuntimeError::new_err(
                "internal: missing prediction outputs",
            )),
        }
    }

    /// (mean, var, dmean_dd, dvar_dd) of shapes (k,), (k,), (k, n_d), (k, n_d).
    fn predict_with_gradients<'py>(
        &self,
        py: Python<'py>,
        d: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<(Arr<'py>, Arr<'py>, Arr<'py>, Arr<'py>)> {
        let mut out = predict_arrays(py, &self.inner, &d, true, true)?.into_iter();
        match (out.next(), out.next(), out.next(), out.next()) {
            (Some(m), Some(v), Some(dm), Some(dv)) => Ok((m, v, dm, dv)),
            _ => Err(PyRuntimeError::new_err(
                "internal: missing prediction outputs",
            )),
        }
    }
}

/// q independent GPs on shared inputs, each with its own hyperparameters.
#[pyclass(name = "MultiGP", module = "gpmhe._core", frozen)]
pub(crate) struct PyMultiGp {
    pub(crate) inner: MultiGp,
}

#[pymethods]
impl PyMultiGp {
    /// MultiGP(x, y, thetas): x (N, n_d), y (N, q), thetas (q, n_d + 2).
    #[new]
    fn py_new(
        py: Python<'_>,
        x: PyReadonlyArray2<'_, f64>,
        y: PyReadonlyArray2<'_, f64>,
        thetas: PyReadonlyArray2<'_, f64>,
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
        let inner = py.detach(|| MultiGp::new(x, y, thetas))?;
        Ok(Self { inner })
    }

    /// Bundles fitted GPs that share their training inputs.
    #[staticmethod]
    fn from_gps(gps: Vec<PyRef<'_, PyGp>>) -> PyResult<Self> {
        let inner = MultiGp::from_gps(gps.iter().map(|g| g.gp().clone()).collect())?;
        Ok(Self { inner })
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

    /// (mean, var) of shapes (k, q) at the points d (k, n_d).
    fn predict<'py>(
        &self,
        py: Python<'py>,
        d: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<(Arr<'py>, Arr<'py>)> {
        let mut out = predict_arrays(py, &self.inner, &d, false, false)?.into_iter();
        match (out.next(), out.next()) {
            (Some(m), Some(v)) => Ok((m, v)),
            _ => Err(PyRuntimeError::new_err(
                "internal: missing prediction outputs",
            )),
        }
    }

    /// (mean, var, dmean_dd, dvar_dd) of shapes (k, q), (k, q), (k, q, n_d), (k, q, n_d).
    fn predict_with_gradients<'py>(
        &self,
        py: Python<'py>,
        d: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<(Arr<'py>, Arr<'py>, Arr<'py>, Arr<'py>)> {
        let mut out = predict_arrays(py, &self.inner, &d, true, false)?.into_iter();
        match (out.next(), out.next(), out.next(), out.next()) {
            (Some(m), Some(v), Some(dm), Some(dv)) => Ok((m, v, dm, dv)),
            _ => Err(PyRuntimeError::new_err(
                "internal: missing prediction outputs",
            )),
        }
    }
}

/// (lml, grad): log p(y | x, theta) and, if eval_gradient, its gradient w.r.t.
/// theta = log([sigma_f, lengthscales.., sigma_eps]) (an empty array otherwise).
#[pyfunction]
#[pyo3(name = "log_marginal_likelihood", signature = (x, y, theta, eval_gradient=false))]
fn gp_log_marginal_likelihood<'py>(
    py: Python<'py>,
    x: PyReadonlyArray2<'py, f64>,
    y: PyReadonlyArray1<'py, f64>,
    theta: PyReadonlyArray1<'py, f64>,
    eval_gradient: bool,
) -> PyResult<(f64, Bound<'py, PyArray1<f64>>)> {
    let (x, _, cols) = slice2("x", &x)?;
    let (y, theta) = (slice1("y", &y)?, slice1("theta", &theta)?);
    check_cols("x", cols, theta.len().saturating_sub(2))?;
    let (lml, grad) = py.detach(|| log_marginal_likelihood(x, y, theta, eval_gradient))?;
    Ok((lml, PyArray1::from_vec(py, grad)))
}

// ===== RGP =====
// Recursive GP (`Rgp`) and the RGP-dKF kernels (`RgpEkf`); the Python classes live in
// python/gpmhe/rgp.py, which validates inputs and calls these once per step.

use crate::rgp::{Rgp, RgpBasis, RgpEkf};
use faer::MatRef;

/// A (mean, variance) pair of 1-D arrays.
type MeanVar<'py> = (Bound<'py, PyArray1<f64>>, Bound<'py, PyArray1<f64>>);

fn mat_to_array2<'py>(py: Python<'py>, m: MatRef<'_, f64>) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let (r, c) = (m.nrows(), m.ncols());
    let mut out = Vec::with_capacity(r * c);
    for i in 0..r {
        for j in 0..c {
            out.push(m[(i, j)]);
        }
    }
    array2(py, out, r, c)
}

/// Huber's recursive GP on a unit grid of basis vectors (see gpmhe.RecursiveGP).
#[pyclass(name = "RecursiveGPCore", module = "gpmhe._core")]
#[derive(Clone)]
pub struct RgpCore {
    inner: Rgp,
}

#[pymethods]
impl RgpCore {
    #[new]
    #[allow(clippy::too_many_arguments)]
    fn new(
        lower: PyReadonlyArray1<'_, f64>,
        upper: PyReadonlyArray1<'_, f64>,
        n_points: Vec<usize>,
        sigma_k: f64,
        l: f64,
        sigma_r: f64,
        sigma_p: f64,
    ) -> PyResult<Self> {
        let basis = RgpBasis::new(
            slice1("lower", &lower)?,
            slice1("upper", &upper)?,
            &n_points,
            sigma_k,
            l,
            sigma_r,
            sigma_p,
        )?;
        Ok(Self {
            inner: Rgp::new(basis),
        })
    }

    fn copy(&self) -> Self {
        self.clone()
    }

    fn update(
        &mut self,
        py: Python<'_>,
        zeta: PyReadonlyArray1<'_, f64>,
        y: f64,
        var_y: f64,
    ) -> PyResult<f64> {
        let z = slice1("zeta", &zeta)?;
        let inner = &mut self.inner;
        Ok(py.detach(|| inner.update(z, y, var_y))?)
    }

    fn update_many<'py>(
        &mut self,
        py: Python<'py>,
        zeta: PyReadonlyArray2<'py, f64>,
        y: PyReadonlyArray1<'py, f64>,
        var_y: PyReadonlyArray1<'py, f64>,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let (z, _, _) = slice2("zeta", &zeta)?;
        let (y, v) = (slice1("y", &y)?, slice1("var_y", &var_y)?);
        let inner = &mut self.inner;
        let out = py.detach(|| inner.update_many(z, y, v))?;
        Ok(PyArray1::from_vec(py, out))
    }

    fn predict<'py>(
        &mut self,
        py: Python<'py>,
        zeta: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<MeanVar<'py>> {
        let (z, _, _) = slice2("zeta", &zeta)?;
        let inner = &mut self.inner;
        let (m, v) = py.detach(|| inner.predict(z))?;
        Ok((PyArray1::from_vec(py, m), PyArray1::from_vec(py, v)))
    }

    fn j_row<'py>(
        &mut self,
        py: Python<'py>,
        zeta: PyReadonlyArray1<'py, f64>,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let j = self.inner.j_row(slice1("zeta", &zeta)?)?;
        Ok(PyArray1::from_vec(py, j))
    }

    fn set_weights(
        &mut self,
        mean: PyReadonlyArray1<'_, f64>,
        cov: PyReadonlyArray2<'_, f64>,
    ) -> PyResult<()> {
        let (c, _, _) = slice2("cov", &cov)?;
        Ok(self.inner.set_weights(slice1("mean", &mean)?, c)?)
    }

    #[getter]
    fn mean<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, self.inner.mean())
    }

    #[getter]
    fn cov<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        mat_to_array2(py, self.inner.cov())
    }

    #[getter]
    fn basis_vectors<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let b = self.inner.basis();
        array2(py, b.basis_vectors(), b.n_basis(), b.dim())
    }

    #[getter]
    fn kernel_matrix<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        mat_to_array2(py, self.inner.basis().kernel_matrix())
    }

    #[getter]
    fn jitter(&self) -> f64 {
        self.inner.basis().jitter()
    }
}

/// Dimension n + Σ n_b (N in augmented mode) from which the per-step calls of `RGPEKFCore` release the GIL.
/// Below it a step's kernels take a few µs, less than a release and re-acquisition of the GIL costs
/// when other threads contend for it (numpy likewise keeps the GIL for small arrays).
const RGP_STEP_GIL_RELEASE_MIN_DIM: usize = 200;

/// Runs `f` with the GIL released if `release`, else holding it.
fn detach_if<T: Send>(py: Python<'_>, release: bool, f: impl FnOnce() -> T + Send) -> T {
    if release {
        py.detach(f)
    } else {
        f()
    }
}

/// The RGP-dKF state and per-step kernels (see gpmhe.RGPEKF). Constant Jacobians A, e, H are
/// stored once (`set_constant_jacobians`) so that a step passes only what changes.
#[pyclass(name = "RGPEKFCore", module = "gpmhe._core")]
pub struct RgpEkfCore {
    inner: RgpEkf,
    a_const: Option<Vec<f64>>,
    e_const: Option<Vec<f64>>,
    h_const: Option<Vec<f64>>,
}

/// The argument `given`, else the stored constant, else a `ValueError` naming `arg`.
fn given_or_const<'a>(
    arg: &str,
    given: &'a Option<PyReadonlyArray2<'_, f64>>,
    stored: &'a Option<Vec<f64>>,
) -> PyResult<&'a [f64]> {
    match (given, stored) {
        (Some(a), _) => Ok(slice2(arg, a)?.0),
        (None, Some(c)) => Ok(c),
        (None, None) => Err(PyValueError::new_err(format!(
            "{arg}: not given and no constant {arg} was stored"
        ))),
    }
}

impl RgpEkfCore {
    /// [x; μ_z^p] after `infer`: x as an array, μ_z^p as a float for one GP, else an array.
    fn x_and_z<'py>(
        &self,
        py: Python<'py>,
    ) -> PyResult<(Bound<'py, PyArray1<f64>>, Bound<'py, PyAny>)> {
        let x = PyArray1::from_slice(py, &self.inner.mu()[..self.inner.dim_x()]);
        let z = self.inner.z_pred();
        let z = if z.len() == 1 {
            z[0].into_pyobject(py)?.into_any()
        } else {
            PyArray1::from_slice(py, z).into_any()
        };
        Ok((x, z))
    }
}

#[pymethods]
impl RgpEkfCore {
    #[new]
    fn new(
        x0: PyReadonlyArray1<'_, f64>,
        p0: PyReadonlyArray2<'_, f64>,
        gps: Vec<PyRef<'_, RgpCore>>,
        augmented: bool,
    ) -> PyResult<Self> {
        let (p, _, _) = slice2("P0", &p0)?;
        let gps = gps.iter().map(|g| g.inner.clone()).collect();
        Ok(Self {
            inner: RgpEkf::new(slice1("x0", &x0)?, p, gps, augmented)?,
            a_const: None,
            e_const: None,
            h_const: None,
        })
    }

    /// Stores constant A (n × n), e (n × q), H (p × n) (None: given at every step).
    #[pyo3(signature = (a=None, e=None, h=None))]
    fn set_constant_jacobians(
        &mut self,
        a: Option<PyReadonlyArray2<'_, f64>>,
        e: Option<PyReadonlyArray2<'_, f64>>,
        h: Option<PyReadonlyArray2<'_, f64>>,
    ) -> PyResult<()> {
        let copy = |arg: &str, m: &Option<PyReadonlyArray2<'_, f64>>| -> PyResult<_> {
            m.as_ref()
                .map(|m| slice2(arg, m).map(|s| s.0.to_vec()))
                .transpose()
        };
        let (a, e, h) = (copy("A", &a)?, copy("e", &e)?, copy("H", &h)?);
        (self.a_const, self.e_const, self.h_const) = (a, e, h);
        Ok(())
    }

    /// J_k of every GP at the inputs ζ (concatenated); returns (x, μ_z^p).
    fn infer<'py>(
        &mut self,
        py: Python<'py>,
        zeta: PyReadonlyArray1<'py, f64>,
    ) -> PyResult<(Bound<'py, PyArray1<f64>>, Bound<'py, PyAny>)> {
        let z = slice1("zeta", &zeta)?;
        let release =
            self.inner.dim_x() + self.inner.n_basis_total() >= RGP_STEP_GIL_RELEASE_MIN_DIM;
        let inner = &mut self.inner;
        detach_if(py, release, || inner.infer(z).map(|_| ()))?;
        self.x_and_z(py)
    }

    /// `infer` for a single GP with a scalar input.
    fn infer_scalar<'py>(
        &mut self,
        py: Python<'py>,
        zeta: f64,
    ) -> PyResult<(Bound<'py, PyArray1<f64>>, Bound<'py, PyAny>)> {
        let release =
            self.inner.dim_x() + self.inner.n_basis_total() >= RGP_STEP_GIL_RELEASE_MIN_DIM;
        let inner = &mut self.inner;
        detach_if(py, release, || inner.infer(&[zeta]).map(|_| ()))?;
        self.x_and_z(py)
    }

    #[pyo3(signature = (x_pred, a, e, q_x))]
    fn predict(
        &mut self,
        py: Python<'_>,
        x_pred: PyReadonlyArray1<'_, f64>,
        a: Option<PyReadonlyArray2<'_, f64>>,
        e: Option<PyReadonlyArray2<'_, f64>>,
        q_x: PyReadonlyArray2<'_, f64>,
    ) -> PyResult<()> {
        let x = slice1("f(x, u, z)", &x_pred)?;
        let a = given_or_const("A", &a, &self.a_const)?;
        let e = given_or_const("e", &e, &self.e_const)?;
        let (q, _, _) = slice2("Q_x", &q_x)?;
        let release =
            self.inner.dim_x() + self.inner.n_basis_total() >= RGP_STEP_GIL_RELEASE_MIN_DIM;
        let inner = &mut self.inner;
        Ok(detach_if(py, release, || inner.predict(x, a, e, q))?)
    }

    /// EKF update with the measurement y and h(x⁻) (ν = y − h(x⁻) is formed here).
    #[pyo3(signature = (y, hx, h, r, learning))]
    fn update(
        &mut self,
        py: Python<'_>,
        y: PyReadonlyArray1<'_, f64>,
        hx: PyReadonlyArray1<'_, f64>,
        h: Option<PyReadonlyArray2<'_, f64>>,
        r: PyReadonlyArray2<'_, f64>,
        learning: bool,
    ) -> PyResult<f64> {
        let (y, hx) = (slice1("y", &y)?, slice1("h(x)", &hx)?);
        if hx.len() != y.len() {
            return Err(PyValueError::new_err(format!(
                "h: returned {} values but y has {}",
                hx.len(),
                y.len()
            )));
        }
        let nu: Vec<f64> = y.iter().zip(hx).map(|(a, b)| a - b).collect();
        let h = given_or_const("H", &h, &self.h_const)?;
        let (r, _, _) = slice2("R_x", &r)?;
        let release =
            self.inner.dim_x() + self.inner.n_basis_total() >= RGP_STEP_GIL_RELEASE_MIN_DIM;
        let inner = &mut self.inner;
        Ok(detach_if(py, release, || {
            inner.update(&nu, h, r, learning)
        })?)
    }

    #[getter]
    fn z_pred<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, self.inner.z_pred())
    }

    fn set_x(&mut self, x: PyReadonlyArray1<'_, f64>) -> PyResult<()> {
        Ok(self.inner.set_x(slice1("x", &x)?)?)
    }

    fn set_p(&mut self, p: PyReadonlyArray2<'_, f64>) -> PyResult<()> {
        Ok(self.inner.set_p(slice2("P", &p)?.0)?)
    }
    fn gp_predict<'py>(
        &mut self,
        py: Python<'py>,
        index: usize,
        zeta: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<MeanVar<'py>> {
        let (z, _, _) = slice2("zeta", &zeta)?;
        let inner = &mut self.inner;
        let (m, v) = py.detach(|| inner.gp_predict(index, z))?;
        Ok((PyArray1::from_vec(py, m), PyArray1::from_vec(py, v)))
    }

    #[allow(clippy::type_complexity)]
    fn gp_weights<'py>(
        &self,
        py: Python<'py>,
        index: usize,
    ) -> PyResult<(Bound<'py, PyArray1<f64>>, Bound<'py, PyArray2<f64>>)> {
        if index >= self.inner.n_gps() {
            return Err(PyValueError::new_err(format!(
                "index: there are {} GPs, got {index}",
                self.inner.n_gps()
            )));
        }
        let (m, c) = self.inner.gp_weights(index);
        Ok((PyArray1::from_slice(py, m), mat_to_array2(py, c.as_ref())?))
    }

    #[getter]
    fn x<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, &self.inner.mu()[..self.inner.dim_x()])
    }

    #[getter(P)]
    fn p<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let n = self.inner.dim_x();
        mat_to_array2(py, self.inner.cov().submatrix(0, 0, n, n))
    }

    #[getter]
    fn mu<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, self.inner.mu())
    }

    #[getter(C)]
    fn c<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        mat_to_array2(py, self.inner.cov().as_ref())
    }

    #[getter]
    fn innovation<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, self.inner.innovation())
    }

    #[getter(S)]
    fn s<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        mat_to_array2(py, self.inner.innovation_cov())
    }

    #[getter]
    fn log_likelihood(&self) -> f64 {
        self.inner.log_likelihood()
    }
}

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("NumericalError", m.py().get_type::<NumericalError>())?;
    m.add_function(wrap_pyfunction!(se_ard_kernel, m)?)?;
    // GP
    m.add_class::<PyGp>()?;
    m.add_class::<PyMultiGp>()?;
    m.add_function(wrap_pyfunction!(gp_log_marginal_likelihood, m)?)?;

    // RGP
    m.add_class::<RgpCore>()?;
    m.add_class::<RgpEkfCore>()?;
    Ok(())
}
