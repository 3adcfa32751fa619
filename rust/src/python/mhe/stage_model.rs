//! The model of a `MovingHorizon` as the core's [`StageModel`]: the learned GPs (fixed, or
//! learning online) or a compiled CasADi model (all run without the GIL), or a known model's Python functions
//! (`gpmhe.KnownModel.stage_eval`, run with the GIL) behind [`CallbackModel`], and the Python
//! class `StageModel` that holds one of them.

use faer::MatRef;
use numpy::{PyArray1, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArrayDyn};
use pyo3::exceptions::{PyArithmeticError, PyException, PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyTuple;

use std::sync::Arc;

use crate::compiled::{CompiledLibrary, CompiledModel};
use crate::error::Error;
use crate::gp_model::GpModel;
use crate::mhe::{GpStageModel, LearningStageModel, StageEval, StageModel};
use crate::python::convert::{array2, slice1, slice2};
use crate::python::sparse::{extract_model, model_object};

/// A [`StageModel`] backed by the Python callable `stage_eval(d) -> (mean_x, var_x, dmean_x,
/// dvar_x, mean_y, var_y, dmean_y, dvar_y)` (the layout of [`StageEval`]) and, if given,
/// `predict(x, u) -> x_next`. A Python exception is kept (the binding re-raises it) and reported
/// to the core as a numerical failure if it is an `ArithmeticError` or `RuntimeError` (a trial
/// point is rejected, a failed solve keeps the warm start), as an interrupt if it is not an
/// `Exception` (KeyboardInterrupt, SystemExit), else as bad model output; the last two stop the
/// update.
pub(crate) struct CallbackModel<'a, 'py> {
    pub(crate) func: &'a Bound<'py, PyAny>,
    pub(crate) predict: Option<&'a Bound<'py, PyAny>>,
    pub(crate) dims: (usize, usize, usize),
    pub(crate) err: Option<PyErr>,
}

impl CallbackModel<'_, '_> {
    fn keep(&mut self, e: PyErr) -> Error {
        let py = self.func.py();
        let msg = e.value(py).str().map(|s| s.to_string()).unwrap_or_default();
        let recoverable =
            e.is_instance_of::<PyArithmeticError>(py) || e.is_instance_of::<PyRuntimeError>(py);
        let interrupt = !e.is_instance_of::<PyException>(py);
        self.err = Some(e);
        match (recoverable, interrupt) {
            (true, _) => Error::numerical(msg),
            (false, true) => Error::interrupted(msg),
            (false, false) => Error::invalid("model", msg),
        }
    }

    fn call(&self, d: &[f64], out: &mut StageEval) -> PyResult<()> {
        let (n, m, p) = self.dims;
        let k = d.len() / (n + m).max(1);
        let arr = PyArray1::from_slice(self.func.py(), d).reshape([k, n + m])?;
        let parts: Vec<PyReadonlyArrayDyn<'_, f64>> = self.func.call1((arr,))?.extract()?;
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

    fn call_predict(
        predict: &Bound<'_, PyAny>,
        x: &[f64],
        u: &[f64],
        out: &mut [f64],
    ) -> PyResult<()> {
        let py = predict.py();
        let res = predict.call1((PyArray1::from_slice(py, x), PyArray1::from_slice(py, u)))?;
        let arr: PyReadonlyArray1<'_, f64> = res
            .extract()
            .map_err(|_| PyValueError::new_err("model: predict must return a float64 array"))?;
        let v = arr
            .as_slice()
            .map_err(|_| PyValueError::new_err("model: predict must return a contiguous array"))?;
        if v.len() != out.len() || !v.iter().all(|a| a.is_finite()) {
            return Err(PyValueError::new_err(format!(
                "model: predict must return {} finite values",
                out.len()
            )));
        }
        out.copy_from_slice(v);
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
        self.call(d, out).map_err(|e| self.keep(e))
    }
    fn predict_state(&mut self, x: &[f64], u: &[f64], out: &mut [f64]) -> crate::Result<()> {
        let r = match self.predict {
            Some(predict) => Self::call_predict(predict, x, u, out),
            None => {
                let mut d = x.to_vec();
                d.extend_from_slice(u);
                let mut ev = StageEval::default();
                self.call(&d, &mut ev)
                    .map(|()| out.copy_from_slice(&ev.mean_x))
            }
        };
        r.map_err(|e| self.keep(e))
    }
}

/// The model behind an estimator: a Python callback (known model), the learned GPs, or a
/// compiled CasADi model with the Python callable that builds it again (for pickles).
pub(crate) enum Model {
    Callback {
        stage_eval: Py<PyAny>,
        predict: Option<Py<PyAny>>,
        dims: (usize, usize, usize),
    },
    Gp(Box<GpStageModel>),
    /// Sparse f-GPs whose inducing outputs the estimator learns (`crate::mhe::learning`).
    Learning(Box<LearningStageModel>),
    Compiled {
        model: Box<CompiledModel>,
        rebuild: Py<PyAny>,
    },
}

impl Model {
    pub(crate) fn clone_ref(&self, py: Python<'_>) -> Self {
        match self {
            Model::Callback {
                stage_eval,
                predict,
                dims,
            } => Model::Callback {
                stage_eval: stage_eval.clone_ref(py),
                predict: predict.as_ref().map(|p| p.clone_ref(py)),
                dims: *dims,
            },
            Model::Gp(gp) => Model::Gp(gp.clone()),
            Model::Learning(l) => Model::Learning(l.clone()),
            Model::Compiled { model, rebuild } => Model::Compiled {
                model: Box::new(CompiledModel::new(Arc::clone(model.library()))),
                rebuild: rebuild.clone_ref(py),
            },
        }
    }

    pub(crate) fn dims(&self) -> (usize, usize, usize) {
        match self {
            Model::Callback { dims, .. } => *dims,
            Model::Gp(gp) => (gp.dim_x(), gp.dim_u(), gp.dim_y()),
            Model::Learning(l) => (l.dim_x(), l.dim_u(), l.dim_y()),
            Model::Compiled { model, .. } => model.library().dims(),
        }
    }
}

// ---- copies and pickles ---------------------------------------------------------------------
impl Model {
    /// `(constructor, args)` rebuilding this model: `StageModel.callback(stage_eval, dims...,
    /// predict)`, `StageModel.gp(f, h, dim_u, f_residual)` or the compiled model's `rebuild()`
    /// (which compiles again, or loads from gpmhe's cache, where the pickle is read).
    pub(crate) fn reduce<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyTuple>> {
        let cls = py.get_type::<PyStageModel>();
        match self {
            Model::Callback {
                stage_eval,
                predict,
                dims,
            } => {
                let args = (
                    stage_eval.clone_ref(py),
                    dims.0,
                    dims.1,
                    dims.2,
                    predict.as_ref().map(|p| p.clone_ref(py)),
                );
                (cls.getattr("callback")?, args).into_pyobject(py)
            }
            Model::Gp(gp) => {
                let (f, h) = gp.gps();
                let f = model_object(py, f)?;
                let h = h.map(|h| model_object(py, h)).transpose()?;
                let args = (f, h, gp.dim_u(), gp.f_residual());
                (cls.getattr("gp")?, args).into_pyobject(py)
            }
            Model::Learning(l) => {
                let f = model_object(py, &GpModel::Sparse((**l.fitted()).clone()))?;
                let h = l.h().map(|h| model_object(py, h)).transpose()?;
                let args = (f, h, l.dim_u(), l.f_residual());
                (cls.getattr("learning")?, args).into_pyobject(py)
            }
            Model::Compiled { rebuild, .. } => (rebuild.clone_ref(py), ()).into_pyobject(py),
        }
    }
}

/// The model of a `MovingHorizon`: `StageModel.gp(...)` (the learned GPs) or
/// `StageModel.callback(...)` (a `gpmhe.KnownModel`'s Python functions).
#[pyclass(name = "StageModel", module = "gpmhe._core", frozen)]
pub(crate) struct PyStageModel {
    pub(crate) model: Model,
}

impl PyStageModel {
    fn learning_model(&self) -> PyResult<&LearningStageModel> {
        match &self.model {
            Model::Learning(l) => Ok(l),
            _ => Err(PyValueError::new_err("model: not a learning model")),
        }
    }
}

#[pymethods]
impl PyStageModel {
    /// The learned model: `f_gp` (dim_x outputs) and `h_gp` (dim_y outputs, None when
    /// dim_y = 0) on inputs [x; u], each a `MultiGP` or a `SparseMultiGP`; `f_residual`: f's
    /// GPs model x(t+1) − x(t).
    #[staticmethod]
    fn gp(
        f_gp: &Bound<'_, PyAny>,
        h_gp: Option<&Bound<'_, PyAny>>,
        dim_u: usize,
        f_residual: bool,
    ) -> PyResult<Self> {
        let f = extract_model("f_gp", f_gp)?;
        let h = h_gp.map(|h| extract_model("h_gp", h)).transpose()?;
        let gp = GpStageModel::new(f, h, dim_u, f_residual)?;
        Ok(Self {
            model: Model::Gp(Box::new(gp)),
        })
    }

    /// The learned model whose f-GPs keep learning: `f_gp` a `SparseMultiGP` (dim_x outputs),
    /// its inducing outputs estimated by the estimator with the states; `h_gp` and the others as
    /// for `gp`.
    #[staticmethod]
    fn learning(
        f_gp: &Bound<'_, PyAny>,
        h_gp: Option<&Bound<'_, PyAny>>,
        dim_u: usize,
        f_residual: bool,
    ) -> PyResult<Self> {
        let GpModel::Sparse(f) = extract_model("f_gp", f_gp)? else {
            return Err(PyValueError::new_err(
                "f_gp: learning needs sparse GPs (a SparseMultiGP)",
            ));
        };
        let h = h_gp.map(|h| extract_model("h_gp", h)).transpose()?;
        let model = LearningStageModel::new(f, h, dim_u, f_residual)?;
        Ok(Self {
            model: Model::Learning(Box::new(model)),
        })
    }

    /// The learning model's fitted posterior of the inducing outputs: (mean (n_g,), covariance
    /// (n_g, n_g)), the prior learning starts from; and the start of each f-GP's block (dim_x + 1
    /// values). ValueError for another model.
    #[allow(clippy::type_complexity)]
    fn fitted_posterior<'py>(
        &self,
        py: Python<'py>,
    ) -> PyResult<(
        Bound<'py, PyArray1<f64>>,
        Bound<'py, numpy::PyArray2<f64>>,
        Vec<usize>,
    )> {
        let l = self.learning_model()?;
        let (mean, cov) = l.fitted_posterior();
        let ng = mean.len();
        let cov: Vec<f64> = (0..ng * ng).map(|k| cov[(k / ng, k % ng)]).collect();
        Ok((
            PyArray1::from_vec(py, mean),
            array2(py, cov, ng, ng)?,
            l.offsets().to_vec(),
        ))
    }

    /// The learning model's f-GPs with the posterior N(mean, cov) of their inducing outputs, as
    /// a `SparseMultiGP` that predicts with the full posterior variance. ValueError for another
    /// model or bad input; `NumericalError` if a block of `cov` is not positive definite.
    fn snapshot(
        &self,
        py: Python<'_>,
        mean: PyReadonlyArray1<'_, f64>,
        cov: PyReadonlyArray2<'_, f64>,
    ) -> PyResult<Py<PyAny>> {
        let l = self.learning_model()?;
        let (c, rows, cols) = slice2("cov", &cov)?;
        let f = l.snapshot(
            slice1("mean", &mean)?,
            MatRef::from_row_major_slice(c, rows, cols),
        )?;
        model_object(py, &GpModel::Sparse(f))
    }

    /// A model given by the Python callable `stage_eval` (see `gpmhe.KnownModel`), with
    /// `predict(x, u)` for one-step predictions if given (else the means of `stage_eval`).
    #[staticmethod]
    #[pyo3(signature = (stage_eval, dim_x, dim_u, dim_y, predict=None))]
    fn callback(
        stage_eval: Bound<'_, PyAny>,
        dim_x: usize,
        dim_u: usize,
        dim_y: usize,
        predict: Option<Bound<'_, PyAny>>,
    ) -> PyResult<Self> {
        if !stage_eval.is_callable() {
            return Err(PyValueError::new_err("stage_eval: must be callable"));
        }
        if predict.as_ref().is_some_and(|f| !f.is_callable()) {
            return Err(PyValueError::new_err("predict: must be callable or None"));
        }
        let model = Model::Callback {
            stage_eval: stage_eval.unbind(),
            predict: predict.map(Bound::unbind),
            dims: (dim_x, dim_u, dim_y),
        };
        Ok(Self { model })
    }

    /// A compiled CasADi model: the shared library at `path` (written by gpmhe from CasADi's
    /// generated C code) with the functions `stage` (f, ∂f/∂dᵀ, h, ∂h/∂dᵀ of one point d) and
    /// `predict` (f), for the dimensions given; `rebuild()` returns this model again (pickles
    /// call it). ValueError if the library cannot be loaded or its functions have other shapes.
    #[staticmethod]
    #[allow(clippy::too_many_arguments)]
    fn compiled(
        path: &str,
        stage: &str,
        predict: &str,
        dim_x: usize,
        dim_u: usize,
        dim_y: usize,
        rebuild: Bound<'_, PyAny>,
    ) -> PyResult<Self> {
        if !rebuild.is_callable() {
            return Err(PyValueError::new_err("rebuild: must be callable"));
        }
        let lib = CompiledLibrary::load(path, stage, predict, (dim_x, dim_u, dim_y))?;
        Ok(Self {
            model: Model::Compiled {
                model: Box::new(CompiledModel::new(Arc::new(lib))),
                rebuild: rebuild.unbind(),
            },
        })
    }

    /// Whether the model learns online (`StageModel.learning`).
    #[getter]
    fn learns(&self) -> bool {
        matches!(self.model, Model::Learning(_))
    }

    /// Whether the model runs compiled code without Python (the GPs or a compiled CasADi model).
    #[getter]
    fn native(&self) -> bool {
        !matches!(self.model, Model::Callback { .. })
    }

    /// (dim_x, dim_u, dim_y).
    #[getter]
    fn dims(&self) -> (usize, usize, usize) {
        self.model.dims()
    }

    /// The learned model's values at the points `d` (k, n + m), as the estimator's core
    /// evaluates them: (mean_x (k, n), var_x (k, n), dmean_x (k, n, n + m), dvar_x, mean_y
    /// (k, p), var_y, dmean_y (k, p, n + m), dvar_y). A callback model: ValueError (call its
    /// Python functions instead).
    fn evaluate<'py>(
        &self,
        py: Python<'py>,
        d: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<Bound<'py, PyTuple>> {
        let Model::Gp(gp) = &self.model else {
            return Err(PyValueError::new_err(
                "model: only the fixed GP model evaluates here (a callback model evaluates in \
                 Python, a learning model inside its estimator)",
            ));
        };
        let (n, m, p) = (gp.dim_x(), gp.dim_u(), gp.dim_y());
        let (points, k, cols) = slice2("d", &d)?;
        if cols != n + m {
            return Err(PyValueError::new_err(format!(
                "d: expected {} columns (dim_x + dim_u), got {cols}",
                n + m
            )));
        }
        // A fresh copy: every point evaluated in this batch, none taken from a cache.
        let mut model = GpStageModel::clone(gp);
        model.clear_cache();
        let mut ev = StageEval::default();
        let points = points.to_vec();
        py.detach(|| model.evaluate(&points, &mut ev))?;
        let nd = n + m;
        let a = |v: Vec<f64>, dims: &[usize]| -> PyResult<Bound<'py, PyAny>> {
            Ok(PyArray1::from_vec(py, v).reshape(dims.to_vec())?.into_any())
        };
        PyTuple::new(
            py,
            [
                a(ev.mean_x, &[k, n])?,
                a(ev.var_x, &[k, n])?,
                a(ev.dmean_x, &[k, n, nd])?,
                a(ev.dvar_x, &[k, n, nd])?,
                a(ev.mean_y, &[k, p])?,
                a(ev.var_y, &[k, p])?,
                a(ev.dmean_y, &[k, p, nd])?,
                a(ev.dvar_y, &[k, p, nd])?,
            ],
        )
    }

    /// The learned model's one-step prediction m_x(x, u) (n,), as the estimator's core makes it.
    fn predict<'py>(
        &self,
        py: Python<'py>,
        x: PyReadonlyArray1<'py, f64>,
        u: PyReadonlyArray1<'py, f64>,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let Model::Gp(gp) = &self.model else {
            return Err(PyValueError::new_err(
                "model: only the fixed GP model predicts here (a callback model predicts in \
                 Python, a learning model inside its estimator)",
            ));
        };
        let (x, u) = (slice1("x", &x)?, slice1("u", &u)?);
        let mut model = GpStageModel::clone(gp);
        let mut out = vec![0.0; gp.dim_x()];
        model.predict_mean(x, u, &mut out)?;
        Ok(PyArray1::from_vec(py, out))
    }

    // ---- copies and pickles -----------------------------------------------------------------
    /// Pickles as its constructor call: the GPs' data, or the Python callables (which must be
    /// picklable themselves, e.g. module-level functions or bound methods of picklable objects).
    fn __reduce__<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyTuple>> {
        self.model.reduce(py)
    }

    /// The model is immutable: a copy is the same object.
    fn __copy__(slf: Py<Self>) -> Py<Self> {
        slf
    }

    fn __deepcopy__(slf: Py<Self>, _memo: Bound<'_, PyAny>) -> Py<Self> {
        slf
    }
}
