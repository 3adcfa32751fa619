//! Sparse GPs (`crate::sparse`): `SparseMultiGP` (gpmhe.SparseGaussianProcess and
//! gpmhe.SparseMultiOutputGP are its q = 1 and general cases), `sparse_objective` and
//! `select_inducing`; and the conversions between the core's [`GpModel`] and the two Python GP
//! classes, for `StageModel.gp`. Inputs must be C-contiguous float64 (gpmhe/gp/inducing.py converts
//! and validates first); the numerics run without the GIL.

use numpy::{PyArray1, PyArray2, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use super::convert::{array2, slice1, slice2};
use super::error::detach_interruptible;
use super::gp::{
    affine_mean, check_cols, mean_array, mean_coefficients, predict_arrays, with_gradients, Arr,
    PyMultiGp,
};
use crate::gp_model::GpModel;
use crate::sparse::{select_inducing, sparse_objective, SparseMethod, SparseMultiGp};

/// q independent sparse GPs on shared inputs, each with its own hyperparameters and inducing
/// points.
#[pyclass(name = "SparseMultiGP", module = "gpmhe._core", frozen)]
pub(super) struct PySparseMultiGp {
    pub(crate) inner: SparseMultiGp,
}

#[pymethods]
impl PySparseMultiGp {
    /// SparseMultiGP(x, y, z, thetas, method, mean=None): x (N, n_d), y (N, q), z a list of q
    /// arrays (m_o, n_d), thetas (q, n_d + 2), method "vfe" or "fitc"; with a prior mean
    /// (coefficients (q, n_d + 1)), y are the residuals y − m(x), as for `MultiGP`.
    ///
    /// `posterior`: for each output None or (mean (m_o,), covariance (m_o, m_o)), a posterior of
    /// its inducing outputs that replaces the fit's (as `replaced_posterior` gives it).
    #[new]
    #[pyo3(signature = (x, y, z, thetas, method, mean=None, posterior=None))]
    #[allow(clippy::too_many_arguments)]
    fn py_new(
        py: Python<'_>,
        x: PyReadonlyArray2<'_, f64>,
        y: PyReadonlyArray2<'_, f64>,
        z: Vec<PyReadonlyArray2<'_, f64>>,
        thetas: PyReadonlyArray2<'_, f64>,
        method: &str,
        mean: Option<PyReadonlyArray2<'_, f64>>,
        posterior: Option<Vec<Option<Posterior<'_>>>>,
    ) -> PyResult<Self> {
        let method = SparseMethod::parse(method)?;
        let (x, n, nd) = slice2("x", &x)?;
        let (y, ny, q) = slice2("y", &y)?;
        let (thetas, qt, cols) = slice2("thetas", &thetas)?;
        if ny != n {
            return Err(PyValueError::new_err(format!(
                "y: expected {n} rows (one per training input), got {ny}"
            )));
        }
        if qt != q || cols != nd + 2 || z.len() != q {
            return Err(PyValueError::new_err(format!(
                "thetas, z: expected thetas of shape ({q}, {}) and {q} sets of inducing points, \
                 got ({qt}, {cols}) and {}",
                nd + 2,
                z.len()
            )));
        }
        let zs = z
            .iter()
            .map(|a| {
                let (s, _, c) = slice2("z", a)?;
                check_cols("z", c, nd)?;
                Ok(s)
            })
            .collect::<PyResult<Vec<&[f64]>>>()?;
        let mean = affine_mean(mean.as_ref(), q, nd)?;
        let inner = detach_interruptible(py, || SparseMultiGp::new(x, y, &zs, thetas, method))?;
        let mut inner = match mean {
            Some(m) => inner.with_mean(m)?,
            None => inner,
        };
        replace_posteriors(&mut inner, posterior.unwrap_or_default())?;
        Ok(Self { inner })
    }

    // ---- copies and pickles -----------------------------------------------------------------
    /// Pickles as `SparseMultiGP(x, y, z, thetas, method, mean)`: the same data factorise to the same
    /// GP, bit for bit.
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
        let thetas: Vec<f64> = gps.iter().flat_map(|g| g.theta().to_vec()).collect();
        let posterior = self.replaced_posterior(py)?;
        let any = posterior.iter().any(Option::is_some);
        let args = (
            x,
            array2(py, y, n, q)?,
            self.inducing(py)?,
            array2(py, thetas, q, nd + 2)?,
            self.inner.method().name(),
            mean_coefficients(py, self.inner.mean())?,
            any.then_some(posterior),
        );
        (py.get_type::<Self>(), args).into_pyobject(py)
    }

    /// For each output, the posterior of its inducing outputs that replaced the fit's (mean,
    /// covariance), or None (the fit's).
    #[allow(clippy::type_complexity)]
    fn replaced_posterior<'py>(
        &self,
        py: Python<'py>,
    ) -> PyResult<Vec<Option<(Bound<'py, PyArray1<f64>>, Bound<'py, PyArray2<f64>>)>>> {
        self.inner
            .gps()
            .iter()
            .map(|g| {
                g.replaced_posterior()
                    .map(|(mu, cov)| {
                        Ok((
                            PyArray1::from_slice(py, mu),
                            array2(py, cov.clone(), mu.len(), mu.len())?,
                        ))
                    })
                    .transpose()
            })
            .collect()
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
    /// "vfe" or "fitc".
    #[getter]
    fn method(&self) -> &'static str {
        self.inner.method().name()
    }
    /// (q, n_d + 2) log-hyperparameters, one row per output.
    #[getter]
    fn thetas<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let data: Vec<f64> = self
            .inner
            .gps()
            .iter()
            .flat_map(|g| g.theta().to_vec())
            .collect();
        array2(py, data, self.inner.n_outputs(), self.inner.dim() + 2)
    }
    /// The prior mean's coefficients (q, n_d + 1), rows [b, w...], or None (zero mean).
    #[getter]
    fn mean<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyArray2<f64>>>> {
        mean_coefficients(py, self.inner.mean())
    }
    /// The inducing inputs of each output: a list of q arrays (m_o, n_d).
    #[getter]
    fn inducing<'py>(&self, py: Python<'py>) -> PyResult<Vec<Bound<'py, PyArray2<f64>>>> {
        let nd = self.inner.dim();
        self.inner
            .gps()
            .iter()
            .map(|g| array2(py, g.inducing().to_vec(), g.n_inducing(), nd))
            .collect()
    }
    /// The diagonal jitter each output's K(Z, Z) needed (0 if none).
    #[getter]
    fn jitters<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_vec(py, self.inner.gps().iter().map(|g| g.jitter()).collect())
    }

    /// The training objective of each output, shape (q,): the VFE bound or FITC's log marginal
    /// likelihood (named as `MultiGP`'s, the quantity a fit maximises).
    fn log_marginal_likelihoods<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        let v = self.inner.gps().iter().map(|g| g.objective()).collect();
        PyArray1::from_vec(py, v)
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

    /// Means only, shape (k, q).
    fn predict_mean<'py>(
        &self,
        py: Python<'py>,
        d: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<Arr<'py>> {
        mean_array(py, &self.inner, &d)
    }
}

/// (value, grad_theta, grad_z): the sparse GP's training objective on x (N, n_d), y (N) with
/// inducing inputs z (m, n_d) at theta, and if eval_gradient its gradients w.r.t. theta (n_d + 2)
/// and z (m, n_d) (empty arrays otherwise).
#[pyfunction]
#[pyo3(name = "sparse_objective", signature = (x, y, z, theta, method, eval_gradient=false))]
#[allow(clippy::type_complexity)]
pub(super) fn sparse_gp_objective<'py>(
    py: Python<'py>,
    x: PyReadonlyArray2<'py, f64>,
    y: PyReadonlyArray1<'py, f64>,
    z: PyReadonlyArray2<'py, f64>,
    theta: PyReadonlyArray1<'py, f64>,
    method: &str,
    eval_gradient: bool,
) -> PyResult<(f64, Bound<'py, PyArray1<f64>>, Bound<'py, PyArray2<f64>>)> {
    let method = SparseMethod::parse(method)?;
    let (x, _, cols) = slice2("x", &x)?;
    let (z, m, zcols) = slice2("z", &z)?;
    let (y, theta) = (slice1("y", &y)?, slice1("theta", &theta)?);
    check_cols("x", cols, theta.len().saturating_sub(2))?;
    check_cols("z", zcols, cols)?;
    let obj = detach_interruptible(py, || {
        sparse_objective(x, y, z, theta, method, eval_gradient)
    })?;
    let rows = if eval_gradient { m } else { 0 };
    Ok((
        obj.value,
        PyArray1::from_vec(py, obj.grad_theta),
        array2(py, obj.grad_z, rows, cols)?,
    ))
}

/// Indices of at most m rows of x (N, n_d) chosen by greedy conditional-variance selection under
/// the kernel of theta (see `crate::sparse::select_inducing`).
#[pyfunction]
#[pyo3(name = "select_inducing")]
pub(super) fn py_select_inducing<'py>(
    py: Python<'py>,
    x: PyReadonlyArray2<'py, f64>,
    theta: PyReadonlyArray1<'py, f64>,
    m: usize,
) -> PyResult<Bound<'py, PyArray1<i64>>> {
    let (x, _, cols) = slice2("x", &x)?;
    let theta = slice1("theta", &theta)?;
    check_cols("x", cols, theta.len().saturating_sub(2))?;
    let idx = detach_interruptible(py, || select_inducing(x, theta, m))?;
    Ok(PyArray1::from_vec(
        py,
        idx.into_iter().map(|i| i as i64).collect(),
    ))
}

/// The core model of a `MultiGP` or `SparseMultiGP` (a ValueError naming `arg` otherwise).
pub(super) fn extract_model(arg: &str, obj: &Bound<'_, PyAny>) -> PyResult<GpModel> {
    if let Ok(gp) = obj.cast::<PyMultiGp>() {
        return Ok(GpModel::Exact(gp.get().inner.clone()));
    }
    if let Ok(gp) = obj.cast::<PySparseMultiGp>() {
        return Ok(GpModel::Sparse(gp.get().inner.clone()));
    }
    Err(PyValueError::new_err(format!(
        "{arg}: must be a gpmhe._core.MultiGP or SparseMultiGP"
    )))
}

/// A posterior of one output's inducing outputs: (mean, covariance).
type Posterior<'py> = (PyReadonlyArray1<'py, f64>, PyReadonlyArray2<'py, f64>);

/// Replaces each output's posterior of its inducing outputs where one is given (q entries);
/// nothing changes on error.
fn replace_posteriors(
    gp: &mut SparseMultiGp,
    posterior: Vec<Option<Posterior<'_>>>,
) -> PyResult<()> {
    if posterior.is_empty() {
        return Ok(());
    }
    let q = gp.n_outputs();
    if posterior.len() != q {
        return Err(PyValueError::new_err(format!(
            "posterior: needs {q} entries (one per output)"
        )));
    }
    let mut out = gp.clone();
    for (o, p) in posterior.iter().enumerate() {
        let Some((mu, cov)) = p else { continue };
        let (c, rows, cols) = slice2("posterior", cov)?;
        let g = out
            .gp_mut(o)
            .ok_or_else(|| PyValueError::new_err("posterior: no such output"))?;
        g.set_inducing_posterior(
            slice1("posterior", mu)?,
            faer::MatRef::from_row_major_slice(c, rows, cols),
        )?;
    }
    *gp = out;
    Ok(())
}

/// The Python object (`MultiGP` or `SparseMultiGP`) of a core model.
pub(super) fn model_object(py: Python<'_>, model: &GpModel) -> PyResult<Py<PyAny>> {
    Ok(match model {
        GpModel::Exact(g) => Py::new(py, PyMultiGp { inner: g.clone() })?.into_any(),
        GpModel::Sparse(g) => Py::new(py, PySparseMultiGp { inner: g.clone() })?.into_any(),
    })
}
