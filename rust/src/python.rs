//! The pyo3 binding: the only file that knows Python. It turns numpy arrays into slices
//! (zero-copy when C-contiguous float64; the Python wrappers convert anything else first), releases
//! the GIL around the numerics, and maps core errors to exceptions: `InvalidInput` to `ValueError`,
//! `Numerical` to `gpmhe.NumericalError`.

use numpy::{PyArray2, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::create_exception;
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;

use crate::error::{check_finite, check_len, Error};
use crate::kernel::SeArd;

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
/// mean, var and, when asked for, (dmean_dd, dvar_dd).
type Predicted<'py> = (Arr<'py>, Arr<'py>, Option<(Arr<'py>, Arr<'py>)>);

/// Runs a batch prediction of `q` outputs at the points `d` with the GIL released and returns
/// (mean, var[, dmean, dvar]) shaped (k, q...) / (k, q..., n_d); `squeeze` drops the q axis.
/// Posterior means at the points `d`: shape (k,) with `squeeze` (one output), else (k, q).
fn mean_array<'py>(
    py: Python<'py>,
    model: &MultiGp,
    d: &PyReadonlyArray2<'py, f64>,
    squeeze: bool,
) -> PyResult<Arr<'py>> {
    let (d, k, cols) = slice2("D", d)?;
    let q = model.n_outputs();
    check_cols("D", cols, model.dim())?;
    crate::error::check_finite("D", d)?;
    let mut mean = vec![0.0; k * q];
    model.predict_mean_into(d, &mut mean, &mut GpWorkspace::default())?;
    if squeeze {
        array_nd(py, mean, [k])
    } else {
        array_nd(py, mean, [k, q])
    }
}

fn predict_arrays<'py>(
    py: Python<'py>,
    model: &MultiGp,
    d: &PyReadonlyArray2<'py, f64>,
    gradients: bool,
    squeeze: bool,
) -> PyResult<Predicted<'py>> {
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
    if squeeze {
        let grads = match gradients {
            true => Some((array_nd(py, dmean, [k, nd])?, array_nd(py, dvar, [k, nd])?)),
            false => None,
        };
        Ok((array_nd(py, mean, [k])?, array_nd(py, var, [k])?, grads))
    } else {
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
}

/// (mean, var, gradients) of the four-array prediction, as a Python tuple.
fn with_gradients<'py>(p: Predicted<'py>) -> PyResult<(Arr<'py>, Arr<'py>, Arr<'py>, Arr<'py>)> {
    match p {
        (m, v, Some((dm, dv))) => Ok((m, v, dm, dv)),
        _ => Err(PyRuntimeError::new_err(
            "internal: gradients were not computed",
        )),
    }
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
        let (m, v, _) = predict_arrays(py, &self.inner, &d, false, true)?;
        Ok((m, v))
    }

    /// (mean, var, dmean_dd, dvar_dd) of shapes (k,), (k,), (k, n_d), (k, n_d).
    fn predict_with_gradients<'py>(
        &self,
        py: Python<'py>,
        d: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<(Arr<'py>, Arr<'py>, Arr<'py>, Arr<'py>)> {
        with_gradients(predict_arrays(py, &self.inner, &d, true, true)?)
    }

    /// Means only, shape (k,): O(N) per point (no triangular solve).
    fn predict_mean<'py>(
        &self,
        py: Python<'py>,
        d: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<Arr<'py>> {
        mean_array(py, &self.inner, &d, true)
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
        let (m, v, _) = predict_arrays(py, &self.inner, &d, false, false)?;
        Ok((m, v))
    }

    /// (mean, var, dmean_dd, dvar_dd) of shapes (k, q), (k, q), (k, q, n_d), (k, q, n_d).
    fn predict_with_gradients<'py>(
        &self,
        py: Python<'py>,
        d: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<(Arr<'py>, Arr<'py>, Arr<'py>, Arr<'py>)> {
        with_gradients(predict_arrays(py, &self.inner, &d, true, false)?)
    }

    /// Means only, shape (k, q): O(N) per point and output (no triangular solves).
    fn predict_mean<'py>(
        &self,
        py: Python<'py>,
        d: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<Arr<'py>> {
        mean_array(py, &self.inner, &d, false)
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

// ===== MHE window =====

use crate::window::{Form, GpStageModel, StageEval, StageModel, WindowEval, WindowProblem};
use numpy::PyReadonlyArrayDyn;

/// A [`StageModel`] backed by a Python callable `stage_eval(d) -> (mean_x, var_x, dmean_x,
/// dvar_x, mean_y, var_y, dmean_y, dvar_y)` (the layout of [`StageEval`]); used for
/// `gpmhe.KnownModel`. Runs with the GIL held; a Python exception is kept and re-raised.
struct CallbackModel<'a, 'py> {
    func: &'a Bound<'py, PyAny>,
    dims: (usize, usize, usize),
    err: Option<PyErr>,
}

impl CallbackModel<'_, '_> {
    fn call(&self, d: &[f64], out: &mut StageEval) -> PyResult<()> {
        let py = self.func.py();
        let (n, m, p) = self.dims;
        let nd = n + m;
        let k = d.len() / nd.max(1);
        let arr = numpy::PyArray1::from_slice(py, d).reshape([k, nd])?;
        let res = self.func.call1((arr,))?;
        let parts: Vec<PyReadonlyArrayDyn<'_, f64>> = res.extract()?;
        if parts.len() != 8 {
            return Err(PyValueError::new_err(
                "model: stage_eval must return 8 arrays",
            ));
        }
        out.resize(k, n, m, p);
        let targets: [&mut Vec<f64>; 8] = [
            &mut out.mean_x,
            &mut out.var_x,
            &mut out.dmean_x,
            &mut out.dvar_x,
            &mut out.mean_y,
            &mut out.var_y,
            &mut out.dmean_y,
            &mut out.dvar_y,
        ];
        for (target, part) in targets.into_iter().zip(parts.iter()) {
            let src = part.as_slice().map_err(|_| {
                PyValueError::new_err("model: stage_eval must return C-contiguous float64 arrays")
            })?;
            if src.len() != target.len() {
                return Err(PyValueError::new_err(format!(
                    "model: stage_eval returned {} values where {} were expected",
                    src.len(),
                    target.len()
                )));
            }
            target.copy_from_slice(src);
        }
        Ok(())
    }
}

impl StageModel for CallbackModel<'_, '_> {
    fn dim_x(&self) -> usize {
        self.dims.0
    }
    fn dim_u(&self) -> usize {
        self.dims.1
    }
    fn dim_y(&self) -> usize {
        self.dims.2
    }
    fn evaluate(&mut self, d: &[f64], out: &mut StageEval) -> crate::Result<()> {
        match self.call(d, out) {
            Ok(()) => Ok(()),
            Err(e) => {
                self.err = Some(e);
                Err(Error::numerical("model callback failed"))
            }
        }
    }
}

/// The model behind a window: a Python callback (known model) or the learned GPs.
enum WindowModel {
    Callback(Py<PyAny>),
    Gp(Box<GpStageModel>),
}

/// One MHE window problem with its model and evaluation buffers (docs/user_guide/window.rst). The Python
/// estimator `gpmhe.GPMHE` sets the data each step and hands `cost_grad`, `gn_hessian`,
/// `residuals`, `jacobian` to SciPy; evaluations at the same z are cached.
#[pyclass(name = "MheWindow", module = "gpmhe._core")]
pub(crate) struct PyMheWindow {
    pub(crate) problem: WindowProblem,
    model: WindowModel,
    pub(crate) eval: WindowEval,
    /// z of the cached evaluation (empty when none).
    last_z: Vec<f64>,
    /// For a callback model: the Python one-step prediction `predict(x, u)` used for warm
    /// starts (None: the means of `stage_eval` at one point).
    predict: Option<Py<PyAny>>,
}

impl PyMheWindow {
    /// Evaluates at z unless the cache already holds it (with a Jacobian if wanted).
    pub(crate) fn ensure(
        &mut self,
        py: Python<'_>,
        z: &[f64],
        want_jacobian: bool,
    ) -> PyResult<()> {
        if self.last_z.as_slice() == z && (self.eval.has_jacobian() || !want_jacobian) {
            return Ok(());
        }
        self.last_z.clear();
        let dims = (
            self.problem.dim_x(),
            self.problem.dim_u(),
            self.problem.dim_y(),
        );
        let result = match &mut self.model {
            WindowModel::Gp(model) => {
                let (problem, eval) = (&self.problem, &mut self.eval);
                py.detach(|| problem.evaluate(&mut **model, z, want_jacobian, eval))
            }
            WindowModel::Callback(func) => {
                let func = func.bind(py);
                let mut model = CallbackModel {
                    func,
                    dims,
                    err: None,
                };
                let r = self
                    .problem
                    .evaluate(&mut model, z, want_jacobian, &mut self.eval);
                if let Some(e) = model.err {
                    return Err(e);
                }
                r
            }
        };
        result?;
        self.last_z.extend_from_slice(z);
        Ok(())
    }

    /// The model's one-step prediction m_x(x, u) into `out` (n).
    fn predict_state(
        &mut self,
        py: Python<'_>,
        x: &[f64],
        u: &[f64],
        out: &mut [f64],
    ) -> PyResult<()> {
        let dims = (
            self.problem.dim_x(),
            self.problem.dim_u(),
            self.problem.dim_y(),
        );
        match (&mut self.model, &self.predict) {
            (WindowModel::Gp(model), _) => Ok(model.predict_state(x, u, out)?),
            (WindowModel::Callback(_), Some(predict)) => {
                let xa = numpy::PyArray1::from_slice(py, x);
                let ua = numpy::PyArray1::from_slice(py, u);
                let res = predict.bind(py).call1((xa, ua))?;
                let arr: PyReadonlyArray1<'_, f64> = res.extract().map_err(|_| {
                    PyValueError::new_err("model: predict must return a float64 array")
                })?;
                let v = arr.as_slice().map_err(|_| {
                    PyValueError::new_err("model: predict must return a contiguous array")
                })?;
                if v.len() != out.len() || !v.iter().all(|a| a.is_finite()) {
                    return Err(PyValueError::new_err(format!(
                        "model: predict must return {} finite values",
                        out.len()
                    )));
                }
                out.copy_from_slice(v);
                Ok(())
            }
            (WindowModel::Callback(func), None) => {
                let model = CallbackModel {
                    func: func.bind(py),
                    dims,
                    err: None,
                };
                let mut d = x.to_vec();
                d.extend_from_slice(u);
                let mut ev = StageEval::default();
                model.call(&d, &mut ev)?;
                out.copy_from_slice(&ev.mean_x);
                Ok(())
            }
        }
    }

    /// `set_data`, then the warm start: the previous window's rows from `first` on (`first` < 0:
    /// none), each further node predicted from the one before with the model (node 0 without
    /// any overlap: the previous last row), all clipped into [lo, hi] (rows already inside stay
    /// bit-identical, so the learned model reuses their GP values). On error nothing changed
    /// but possibly the window data.
    #[allow(clippy::too_many_arguments)]
    fn prepare_impl(
        &mut self,
        py: Python<'_>,
        u: &PyReadonlyArray2<'_, f64>,
        y: &PyReadonlyArray2<'_, f64>,
        y_present: &[bool],
        x_prior: &PyReadonlyArray1<'_, f64>,
        prev: &PyReadonlyArray2<'_, f64>,
        first: isize,
        lo: &PyReadonlyArray1<'_, f64>,
        hi: &PyReadonlyArray1<'_, f64>,
    ) -> PyResult<Vec<f64>> {
        let n = self.problem.dim_x();
        let m = self.problem.dim_u();
        let (prev, rows, cols) = slice2("prev_window", prev)?;
        let (lo, hi) = (slice1("lower_inner", lo)?, slice1("upper_inner", hi)?);
        if cols != n || rows == 0 {
            return Err(PyValueError::new_err(format!(
                "prev_window: expected shape (rows >= 1, {n}), got ({rows}, {cols})"
            )));
        }
        check_finite("prev_window", prev)?;
        check_len("lower_inner", lo, n)?;
        check_len("upper_inner", hi, n)?;
        if (0..n).any(|a| lo[a].is_nan() || hi[a].is_nan() || lo[a] > hi[a]) {
            return Err(PyValueError::new_err(
                "lower_inner, upper_inner: need lower <= upper",
            ));
        }
        let (u, _, _) = slice2("u", u)?;
        let (y, _, _) = slice2("y", y)?;
        self.problem
            .set_data(u, y, y_present, slice1("x_prior", x_prior)?)?;
        self.last_z.clear();
        let nodes = self.problem.n_nodes();
        let kept = if first < 0 {
            0
        } else {
            (rows.saturating_sub(first as usize)).min(nodes)
        };
        let mut z = vec![0.0; nodes * n];
        if kept > 0 {
            let f = first as usize;
            z[..kept * n].copy_from_slice(&prev[f * n..(f + kept) * n]);
        }
        let mut next = vec![0.0; n];
        for i in kept..nodes {
            if i == 0 {
                z[..n].copy_from_slice(&prev[(rows - 1) * n..rows * n]);
            } else {
                let (done, rest) = z.split_at_mut(i * n);
                self.predict_state(py, &done[(i - 1) * n..], &u[(i - 1) * m..i * m], &mut next)?;
                rest[..n].copy_from_slice(&next);
            }
        }
        for (k, v) in z.iter_mut().enumerate() {
            *v = v.clamp(lo[k % n], hi[k % n]);
        }
        Ok(z)
    }

    /// The block-tridiagonal 2JᵀJ as a dense (n_nodes·n)² matrix.
    fn dense_gn(&self) -> Vec<f64> {
        let n = self.eval.dim_x();
        let nodes = self.eval.n_nodes();
        let nn = n * n;
        let nv = nodes * n;
        let mut diag = vec![0.0; nodes * nn];
        let mut off = vec![0.0; nodes.saturating_sub(1) * nn];
        self.eval.gauss_newton_blocks_into(&mut diag, &mut off);
        let mut h = vec![0.0; nv * nv];
        for i in 0..nodes {
            for a in 0..n {
                for b in 0..n {
                    h[(i * n + a) * nv + i * n + b] = diag[i * nn + a * n + b];
                    if i + 1 < nodes {
                        let v = off[i * nn + a * n + b];
                        h[(i * n + a) * nv + (i + 1) * n + b] = v;
                        h[((i + 1) * n + b) * nv + i * n + a] = v;
                    }
                }
            }
        }
        h
    }
}

#[pymethods]
impl PyMheWindow {
    /// A window whose model is the Python callable `stage_eval` (see `gpmhe.KnownModel`).
    /// `q0`, `r0`: diagonals of Q0, R0; `p2_sqrt`: S with P2 = SᵀS; `filtering`: the form.
    #[staticmethod]
    #[allow(clippy::too_many_arguments)]
    #[pyo3(signature = (stage_eval, dim_x, dim_u, dim_y, eta, q0, r0, p2_sqrt, filtering,
                        predict=None))]
    fn with_callback(
        stage_eval: Bound<'_, PyAny>,
        dim_x: usize,
        dim_u: usize,
        dim_y: usize,
        eta: f64,
        q0: PyReadonlyArray1<'_, f64>,
        r0: PyReadonlyArray1<'_, f64>,
        p2_sqrt: PyReadonlyArray2<'_, f64>,
        filtering: bool,
        predict: Option<Bound<'_, PyAny>>,
    ) -> PyResult<Self> {
        if !stage_eval.is_callable() {
            return Err(PyValueError::new_err("stage_eval: must be callable"));
        }
        if predict.as_ref().is_some_and(|f| !f.is_callable()) {
            return Err(PyValueError::new_err("predict: must be callable or None"));
        }
        let problem = window_problem(dim_x, dim_u, dim_y, eta, &q0, &r0, &p2_sqrt, filtering)?;
        Ok(Self {
            problem,
            model: WindowModel::Callback(stage_eval.unbind()),
            eval: WindowEval::default(),
            last_z: Vec::new(),
            predict: predict.map(Bound::unbind),
        })
    }

    /// A window on the learned model: `f_gp` (dim_x outputs) and `h_gp` (dim_y outputs, None when
    /// dim_y = 0) on inputs [x; u]; `f_residual`: f's GPs model x(t+1) − x(t).
    #[staticmethod]
    #[allow(clippy::too_many_arguments)]
    #[pyo3(signature = (f_gp, h_gp, dim_u, f_residual, eta, q0, r0, p2_sqrt, filtering))]
    fn with_gp(
        f_gp: PyRef<'_, PyMultiGp>,
        h_gp: Option<PyRef<'_, PyMultiGp>>,
        dim_u: usize,
        f_residual: bool,
        eta: f64,
        q0: PyReadonlyArray1<'_, f64>,
        r0: PyReadonlyArray1<'_, f64>,
        p2_sqrt: PyReadonlyArray2<'_, f64>,
        filtering: bool,
    ) -> PyResult<Self> {
        let model = GpStageModel::new(
            f_gp.inner.clone(),
            h_gp.map(|h| h.inner.clone()),
            dim_u,
            f_residual,
        )?;
        let problem = window_problem(
            model.dim_x(),
            dim_u,
            model.dim_y(),
            eta,
            &q0,
            &r0,
            &p2_sqrt,
            filtering,
        )?;
        Ok(Self {
            problem,
            model: WindowModel::Gp(Box::new(model)),
            eval: WindowEval::default(),
            last_z: Vec::new(),
            predict: None,
        })
    }

    /// Sets the window data: `u` (nodes, m), `y` (nodes, p), `y_present` (nodes,) bools,
    /// `x_prior` (n,). On error the previous window is kept.
    fn set_data(
        &mut self,
        u: PyReadonlyArray2<'_, f64>,
        y: PyReadonlyArray2<'_, f64>,
        y_present: Vec<bool>,
        x_prior: PyReadonlyArray1<'_, f64>,
    ) -> PyResult<()> {
        let (u, _, _) = slice2("u", &u)?;
        let (y, _, _) = slice2("y", &y)?;
        self.problem
            .set_data(u, y, &y_present, slice1("x_prior", &x_prior)?)?;
        self.last_z.clear();
        Ok(())
    }

    /// `set_data` and the warm start for one update: returns z0 (see GPMHE's update).
    /// `prev_window` (rows, n): the previous window's states; `first`: the index of the new
    /// window's first node in it (< 0: no overlap); `lower_inner`, `upper_inner` (n,): the box
    /// the warm start is clipped into.
    #[allow(clippy::too_many_arguments)]
    fn prepare<'py>(
        &mut self,
        py: Python<'py>,
        u: PyReadonlyArray2<'py, f64>,
        y: PyReadonlyArray2<'py, f64>,
        y_present: Vec<bool>,
        x_prior: PyReadonlyArray1<'py, f64>,
        prev_window: PyReadonlyArray2<'py, f64>,
        first: isize,
        lower_inner: PyReadonlyArray1<'py, f64>,
        upper_inner: PyReadonlyArray1<'py, f64>,
    ) -> PyResult<Bound<'py, numpy::PyArray1<f64>>> {
        let z = self.prepare_impl(
            py,
            &u,
            &y,
            &y_present,
            &x_prior,
            &prev_window,
            first,
            &lower_inner,
            &upper_inner,
        )?;
        Ok(numpy::PyArray1::from_vec(py, z))
    }

    /// The model's one-step prediction m_x(x, u) (n,).
    fn predict_next<'py>(
        &mut self,
        py: Python<'py>,
        x: PyReadonlyArray1<'py, f64>,
        u: PyReadonlyArray1<'py, f64>,
    ) -> PyResult<Bound<'py, numpy::PyArray1<f64>>> {
        let (x, u) = (slice1("x", &x)?, slice1("u", &u)?);
        check_len("x", x, self.problem.dim_x())?;
        check_len("u", u, self.problem.dim_u())?;
        check_finite("x", x)?;
        check_finite("u", u)?;
        let mut out = vec![0.0; self.problem.dim_x()];
        self.predict_state(py, x, u, &mut out)?;
        Ok(numpy::PyArray1::from_vec(py, out))
    }

    #[getter]
    fn n_nodes(&self) -> usize {
        self.problem.n_nodes()
    }

    #[getter]
    fn n_residuals(&self) -> usize {
        self.problem.n_residuals()
    }

    /// J(z) = ‖r(z)‖².
    fn cost(&mut self, py: Python<'_>, z: PyReadonlyArray1<'_, f64>) -> PyResult<f64> {
        self.ensure(py, slice1("z", &z)?, false)?;
        Ok(self.eval.cost())
    }

    /// (noise of J, noise of ∇J (largest entry)) at z: the estimated rounding noise of the cost
    /// and gradient from the model's mean and variance rounding (0 for a model computed to
    /// full precision).
    fn rounding_noise(
        &mut self,
        py: Python<'_>,
        z: PyReadonlyArray1<'_, f64>,
    ) -> PyResult<(f64, f64)> {
        self.ensure(py, slice1("z", &z)?, true)?;
        Ok((self.eval.cost_noise(), self.eval.gradient_noise()))
    }

    /// (J(z), ∇J(z) = 2Jᵀr).
    fn cost_grad<'py>(
        &mut self,
        py: Python<'py>,
        z: PyReadonlyArray1<'py, f64>,
    ) -> PyResult<(f64, Bound<'py, numpy::PyArray1<f64>>)> {
        self.ensure(py, slice1("z", &z)?, true)?;
        let mut g = vec![0.0; self.eval.n_vars()];
        self.eval.gradient_into(&mut g);
        Ok((self.eval.cost(), numpy::PyArray1::from_vec(py, g)))
    }

    /// The Gauss-Newton Hessian 2JᵀJ at z as a dense (n_nodes·n)² array.
    fn gn_hessian<'py>(
        &mut self,
        py: Python<'py>,
        z: PyReadonlyArray1<'py, f64>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        self.ensure(py, slice1("z", &z)?, true)?;
        let nv = self.eval.n_vars();
        array2(py, self.dense_gn(), nv, nv)
    }

    /// The stacked residuals r(z).
    fn residuals<'py>(
        &mut self,
        py: Python<'py>,
        z: PyReadonlyArray1<'py, f64>,
    ) -> PyResult<Bound<'py, numpy::PyArray1<f64>>> {
        self.ensure(py, slice1("z", &z)?, false)?;
        Ok(numpy::PyArray1::from_slice(py, self.eval.residuals()))
    }

    /// The dense Jacobian ∂r/∂z (n_residuals × n_nodes·n).
    fn jacobian<'py>(
        &mut self,
        py: Python<'py>,
        z: PyReadonlyArray1<'py, f64>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        self.ensure(py, slice1("z", &z)?, true)?;
        let (rows, cols) = (self.eval.n_residuals(), self.eval.n_vars());
        let mut jac = vec![0.0; rows * cols];
        self.eval.dense_jacobian_into(&mut jac);
        array2(py, jac, rows, cols)
    }
}

#[allow(clippy::too_many_arguments)]
fn window_problem(
    dim_x: usize,
    dim_u: usize,
    dim_y: usize,
    eta: f64,
    q0: &PyReadonlyArray1<'_, f64>,
    r0: &PyReadonlyArray1<'_, f64>,
    p2_sqrt: &PyReadonlyArray2<'_, f64>,
    filtering: bool,
) -> PyResult<WindowProblem> {
    let (p2, _, _) = slice2("P2", p2_sqrt)?;
    let form = if filtering {
        Form::Filtering
    } else {
        Form::Prediction
    };
    Ok(WindowProblem::new(
        dim_x,
        dim_u,
        dim_y,
        eta,
        slice1("Q0", q0)?,
        slice1("R0", r0)?,
        p2,
        form,
    )?)
}

// ===== Window solver =====
// The real-time bounded Gauss-Newton solver (solver.rs) on a `MheWindow`: one call per update.

use crate::solver::{BoxLsqSolver, InteriorMode, SolveReport, SolverOptions, WindowLsq};

/// Solver settings and work buffers, one per estimator (reused every update).
#[pyclass(name = "WindowSolver", module = "gpmhe._core")]
struct PyWindowSolver {
    solver: BoxLsqSolver,
    opts: SolverOptions,
}

#[pymethods]
impl PyWindowSolver {
    /// See `gpmhe.GPMHE`'s `solver_options` for the meaning of each setting.
    #[new]
    #[allow(clippy::too_many_arguments)]
    #[pyo3(signature = (max_iter=100, gtol=1e-6, xtol=1e-12, ftol=1e-15, dtol=1e-2, interior="auto",
                        interior_zone=1e-5, mu_init=0.1, mu_final=1e-5))]
    fn new(
        max_iter: usize,
        gtol: f64,
        xtol: f64,
        ftol: f64,
        dtol: f64,
        interior: &str,
        interior_zone: f64,
        mu_init: f64,
        mu_final: f64,
    ) -> PyResult<Self> {
        let interior = match interior {
            "auto" => InteriorMode::Auto,
            "always" => InteriorMode::Always,
            "never" => InteriorMode::Never,
            other => {
                return Err(PyValueError::new_err(format!(
                    "interior: must be 'auto', 'always' or 'never', got {other:?}"
                )))
            }
        };
        let opts = SolverOptions {
            max_iter,
            gtol,
            xtol,
            ftol,
            dtol,
            interior,
            interior_zone,
            mu_init,
            mu_final,
        };
        opts.validate()?;
        Ok(Self {
            solver: BoxLsqSolver::new(),
            opts,
        })
    }

    /// Minimises the window's cost over lower ≤ z ≤ upper from the warm start `z0`. Returns
    /// (z, cost, status, success, nit, nfev, projected_gradient, interior_iterations, P) with P
    /// the last n×n block of 4(2JᵀJ)⁻¹ at z, symmetrised (None if 2JᵀJ is singular: see
    /// `GPMHE.P`); afterwards the window's cached evaluation (with derivatives) is at the
    /// returned z. Learned models run without the GIL; a known model's Python callback runs
    /// with it.
    fn solve<'py>(
        &mut self,
        py: Python<'py>,
        mut window: PyRefMut<'py, PyMheWindow>,
        z0: PyReadonlyArray1<'py, f64>,
        lower: PyReadonlyArray1<'py, f64>,
        upper: PyReadonlyArray1<'py, f64>,
    ) -> PyResult<SolveTuple<'py>> {
        let z = slice1("z0", &z0)?.to_vec();
        let (lower, upper) = (slice1("lower", &lower)?, slice1("upper", &upper)?);
        self.solve_impl(py, &mut window, z, lower, upper)
    }

    /// One whole GPMHE update in one call: `MheWindow.prepare` (data and warm start) with the
    /// same arguments, then `solve` on [lower, upper]. Returns `solve`'s tuple plus, for the
    /// filtering form, the one-step prediction m_x(x̄_t, u_t) from the window's last node (the
    /// next arrival prior; None in the prediction form).
    #[allow(clippy::too_many_arguments)]
    fn step<'py>(
        &mut self,
        py: Python<'py>,
        mut window: PyRefMut<'py, PyMheWindow>,
        u: PyReadonlyArray2<'py, f64>,
        y: PyReadonlyArray2<'py, f64>,
        y_present: Vec<bool>,
        x_prior: PyReadonlyArray1<'py, f64>,
        prev_window: PyReadonlyArray2<'py, f64>,
        first: isize,
        lower_inner: PyReadonlyArray1<'py, f64>,
        upper_inner: PyReadonlyArray1<'py, f64>,
        lower: PyReadonlyArray1<'py, f64>,
        upper: PyReadonlyArray1<'py, f64>,
    ) -> PyResult<(SolveTuple<'py>, Option<Bound<'py, numpy::PyArray1<f64>>>)> {
        let (lower, upper) = (slice1("lower", &lower)?, slice1("upper", &upper)?);
        let z0 = window.prepare_impl(
            py,
            &u,
            &y,
            &y_present,
            &x_prior,
            &prev_window,
            first,
            &lower_inner,
            &upper_inner,
        )?;
        let out = self.solve_impl(py, &mut window, z0, lower, upper)?;
        let next = if window.problem.form() == Form::Filtering {
            let n = window.problem.dim_x();
            let m = window.problem.dim_u();
            let (u, _, _) = slice2("u", &u)?;
            let rows = window.problem.n_nodes(); // (u holds rows·m values: checked by set_data)
            let z = out.0.readonly();
            let z = z.as_slice()?;
            let x_last = z[z.len() - n..].to_vec();
            let mut pred = vec![0.0; n];
            window.predict_state(py, &x_last, &u[(rows - 1) * m..rows * m], &mut pred)?;
            Some(numpy::PyArray1::from_vec(py, pred))
        } else {
            None
        };
        Ok((out, next))
    }
}

type SolveTuple<'py> = (
    Bound<'py, numpy::PyArray1<f64>>,
    f64,
    &'static str,
    bool,
    usize,
    usize,
    f64,
    usize,
    Option<Bound<'py, PyArray2<f64>>>,
);

impl PyWindowSolver {
    fn solve_impl<'py>(
        &mut self,
        py: Python<'py>,
        w: &mut PyMheWindow,
        mut z: Vec<f64>,
        lower: &[f64],
        upper: &[f64],
    ) -> PyResult<SolveTuple<'py>> {
        w.last_z.clear();
        let dims = (w.problem.dim_x(), w.problem.dim_u(), w.problem.dim_y());
        let (solver, opts) = (&mut self.solver, &self.opts);
        let report: SolveReport = match &mut w.model {
            WindowModel::Gp(model) => {
                let (problem, eval) = (&w.problem, &mut w.eval);
                py.detach(|| {
                    let mut lsq = WindowLsq {
                        problem,
                        model: &mut **model,
                        eval,
                    };
                    solver.solve(&mut lsq, &mut z, lower, upper, opts)
                })?
            }
            WindowModel::Callback(func) => {
                let mut model = CallbackModel {
                    func: func.bind(py),
                    dims,
                    err: None,
                };
                let mut lsq = WindowLsq {
                    problem: &w.problem,
                    model: &mut model,
                    eval: &mut w.eval,
                };
                match solver.solve(&mut lsq, &mut z, lower, upper, opts) {
                    Ok(r) => r,
                    // A Python exception raised by the model is more useful than its wrapper.
                    Err(e) => return Err(model.err.take().unwrap_or_else(|| e.into())),
                }
            }
        };
        w.last_z.extend_from_slice(&z);
        let cov = self
            .solver
            .last_node_covariance()
            .map(|c| array2(py, c, dims.0, dims.0))
            .transpose()?;
        Ok((
            numpy::PyArray1::from_vec(py, z),
            report.cost,
            report.status.as_str(),
            report.status.is_success(),
            report.nit,
            report.nfev,
            report.projected_gradient,
            report.interior_iterations,
            cov,
        ))
    }
}

// ===== RGP =====
// Recursive GP (`Rgp`) and the RGP-dKF kernels (`RgpEkf`); the Python classes live in
// python/gpmhe/rgp.py, which validates inputs and calls these once per step.

use crate::rgp::{Rgp, RgpBasis, RgpEkf};
use faer::MatRef;
use pyo3::types::PyFloat;

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
    /// Per-step copies of the inputs and of the user functions' results (a few values each).
    buf: StepBuffers,
}

#[derive(Default)]
struct StepBuffers {
    zeta: Vec<f64>,
    x_pred: Vec<f64>,
    a: Vec<f64>,
    e: Vec<f64>,
    q: Vec<f64>,
    y: Vec<f64>,
    hx: Vec<f64>,
    h: Vec<f64>,
    r: Vec<f64>,
}

/// The shape of a value read by [`read_f64`] (up to four dimensions kept; more only appear in
/// error messages, as "…").
#[derive(PartialEq)]
struct Shape {
    ndim: usize,
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

    fn is(&self, dims: &[usize]) -> bool {
        self.ndim == dims.len() && self.dims[..self.ndim.min(4)] == *dims
    }

    /// Python's repr of the shape tuple: (), (3,), (2, 2).
    fn repr(&self) -> String {
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
fn read_f64(arg: &str, obj: &Bound<'_, PyAny>, out: &mut Vec<f64>) -> PyResult<Shape> {
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

impl RgpEkfCore {
    /// Whether a step's kernels run with the GIL released (see RGP_STEP_GIL_RELEASE_MIN_DIM).
    fn release_gil(&self) -> bool {
        self.inner.dim_x() + self.inner.n_basis_total() >= RGP_STEP_GIL_RELEASE_MIN_DIM
    }

    /// A fresh array of the current state x (the user's functions may keep it).
    fn x_array<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, self.inner.x())
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
            buf: StepBuffers::default(),
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

    /// One prediction step (paper §3.4, steps 1–3) in one call: J_k and μ_z^p at the GP inputs
    /// `zeta` (a float for one 1-D GP, else the inputs of all GPs concatenated), then
    /// x⁻ = f(x, u, z), A(x, u, z) and e(x, u, z) (None: the stored constants) called here with
    /// z = μ_z^p (a float for one GP, else an array), then the structured covariance prediction
    /// with Q_x. Bad input or results raise ValueError naming them; C and μ stay unchanged.
    #[pyo3(signature = (f, u, zeta, a_fn, e_fn, q_x))]
    #[allow(clippy::too_many_arguments)]
    fn predict_step(
        &mut self,
        py: Python<'_>,
        f: &Bound<'_, PyAny>,
        u: &Bound<'_, PyAny>,
        zeta: &Bound<'_, PyAny>,
        a_fn: Option<&Bound<'_, PyAny>>,
        e_fn: Option<&Bound<'_, PyAny>>,
        q_x: &Bound<'_, PyAny>,
    ) -> PyResult<()> {
        let release = self.release_gil();
        read_f64("zeta", zeta, &mut self.buf.zeta)?;
        {
            let (inner, z) = (&mut self.inner, &self.buf.zeta);
            detach_if(py, release, || inner.infer(z).map(|_| ()))?;
        }
        let (n, q) = (self.inner.dim_x(), self.inner.n_gps());
        let x = self.x_array(py);
        let zp = self.inner.z_pred();
        let z = if q == 1 {
            PyFloat::new(py, zp[0]).into_any()
        } else {
            PyArray1::from_slice(py, zp).into_any()
        };
        let xp = f.call1((&x, u, &z))?;
        let shape = read_f64("f", &xp, &mut self.buf.x_pred)?;
        if self.buf.x_pred.len() != n {
            return Err(PyValueError::new_err(format!(
                "f: returned {} values (shape {}), expected {n}",
                self.buf.x_pred.len(),
                shape.repr()
            )));
        }
        if let Some(a_fn) = a_fn {
            let shape = read_f64("A", &a_fn.call1((&x, u, &z))?, &mut self.buf.a)?;
            if !shape.is(&[n, n]) {
                return Err(PyValueError::new_err(format!(
                    "A: returned shape {}, expected ({n}, {n})",
                    shape.repr()
                )));
            }
        }
        if let Some(e_fn) = e_fn {
            let shape = read_f64("e", &e_fn.call1((&x, u, &z))?, &mut self.buf.e)?;
            if self.buf.e.len() != n * q {
                return Err(PyValueError::new_err(format!(
                    "e: returned shape {}, expected ({n}, {q})",
                    shape.repr()
                )));
            }
        }
        read_f64("Q_x", q_x, &mut self.buf.q)?;
        let missing = |arg: &str| {
            PyValueError::new_err(format!("{arg}: not given and no constant {arg} was stored"))
        };
        let a = match (a_fn, &self.a_const) {
            (Some(_), _) => &self.buf.a,
            (None, Some(c)) => c,
            (None, None) => return Err(missing("A")),
        };
        let e = match (e_fn, &self.e_const) {
            (Some(_), _) => &self.buf.e,
            (None, Some(c)) => c,
            (None, None) => return Err(missing("e")),
        };
        let (inner, xp, qb) = (&mut self.inner, &self.buf.x_pred, &self.buf.q);
        Ok(detach_if(py, release, || inner.predict(xp, a, e, qb))?)
    }

    /// One EKF update (paper §3.4, step 4) in one call: h(x⁻) and H(x⁻) (None: the stored
    /// constant) called here, ν = y − h(x⁻), then the update with R_x (a (p, p) array, or a
    /// scalar meaning R_x I). `dim_y`, if known, is the required number of outputs. Returns the
    /// log-likelihood. Bad input raises ValueError naming it, an indefinite innovation
    /// covariance gpmhe.NumericalError; C and μ stay unchanged.
    #[pyo3(signature = (y, h, h_fn, r, dim_y, learning))]
    #[allow(clippy::too_many_arguments)]
    fn update_step(
        &mut self,
        py: Python<'_>,
        y: &Bound<'_, PyAny>,
        h: &Bound<'_, PyAny>,
        h_fn: Option<&Bound<'_, PyAny>>,
        r: &Bound<'_, PyAny>,
        dim_y: Option<usize>,
        learning: bool,
    ) -> PyResult<f64> {
        read_f64("y", y, &mut self.buf.y)?;
        let (n, p) = (self.inner.dim_x(), self.buf.y.len());
        if let Some(d) = dim_y {
            if p != d {
                return Err(PyValueError::new_err(format!(
                    "y: expected {d} value(s), got {p}"
                )));
            }
        }
        let x = self.x_array(py);
        read_f64("h", &h.call1((&x,))?, &mut self.buf.hx)?;
        if self.buf.hx.len() != p {
            return Err(PyValueError::new_err(format!(
                "h: returned {} values but y has {p}",
                self.buf.hx.len()
            )));
        }
        if let Some(h_fn) = h_fn {
            let shape = read_f64("H", &h_fn.call1((&x,))?, &mut self.buf.h)?;
            if self.buf.h.len() != p * n {
                return Err(PyValueError::new_err(format!(
                    "H: shape {} does not match ({p}, {n})",
                    shape.repr()
                )));
            }
        }
        let h = match (h_fn, &self.h_const) {
            (Some(_), _) => &self.buf.h,
            (None, Some(c)) => c,
            (None, None) => {
                return Err(PyValueError::new_err(
                    "H: not given and no constant H was stored",
                ))
            }
        };
        // ν = y − h(x⁻), in place of h(x⁻)
        for (v, yi) in self.buf.hx.iter_mut().zip(&self.buf.y) {
            *v = yi - *v;
        }
        if read_f64("R_x", r, &mut self.buf.r)?.ndim == 0 {
            // a scalar: R_x I
            let rv = self.buf.r[0];
            self.buf.r.clear();
            self.buf.r.resize(p * p, 0.0);
            for i in 0..p {
                self.buf.r[i * p + i] = rv;
            }
        }
        let release = self.release_gil();
        let (inner, nu, rb) = (&mut self.inner, &self.buf.hx, &self.buf.r);
        Ok(detach_if(py, release, || {
            inner.update(nu, h, rb, learning)
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
        Ok((PyArray1::from_vec(py, m), mat_to_array2(py, c.as_ref())?))
    }

    #[getter]
    fn x<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, self.inner.x())
    }

    #[getter(P)]
    fn p<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        mat_to_array2(py, self.inner.p())
    }

    #[getter]
    fn mu<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_vec(py, self.inner.mu())
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
    // MHE window
    m.add_class::<PyMheWindow>()?;
    // Window solver
    m.add_class::<PyWindowSolver>()?;
    m.add_class::<RgpCore>()?;
    m.add_class::<RgpEkfCore>()?;
    Ok(())
}
