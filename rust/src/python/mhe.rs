//! The moving-horizon estimator (`crate::mhe::MovingHorizon`) as `MovingHorizon`, its update
//! report, and `WindowSolver` (solver settings for `MovingHorizon` and for solving a set window
//! directly). The model is either the learned GPs (run without the GIL) or a Python callback
//! (`gpmhe.KnownModel.stage_eval`, run with the GIL), adapted to `StageModel` here. An exception
//! other than a numerical one stops the update (the estimator stays as it was) and is re-raised.

use numpy::{
    PyArray1, PyArray2, PyArrayDyn, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2,
    PyReadonlyArrayDyn, PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyArithmeticError, PyException, PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyTuple};

use super::convert::{array2, slice1, slice2};
use super::error::{detach_interruptible, interruptible};
use super::sparse::{extract_model, model_object};
use crate::error::{check_finite, check_len, Error};
use crate::mhe::{
    Arrival, ArrivalMean, ArrivalWeight, Form, GpStageModel, HistoryState, MovingHorizon, Outcome,
    Solved, StageEval, StageModel, WindowProblem, GP_CACHE_PARTS,
};
use crate::solver::{BoxLsqSolver, InteriorMode, SolverOptions};

type Arr1<'py> = Bound<'py, PyArray1<f64>>;
type Arr2<'py> = Bound<'py, PyArray2<f64>>;

/// A [`StageModel`] backed by the Python callable `stage_eval(d) -> (mean_x, var_x, dmean_x,
/// dvar_x, mean_y, var_y, dmean_y, dvar_y)` (the layout of [`StageEval`]) and, if given,
/// `predict(x, u) -> x_next`. A Python exception is kept (the binding re-raises it) and reported
/// to the core as a numerical failure if it is an `ArithmeticError` or `RuntimeError` (a trial
/// point is rejected, a failed solve keeps the warm start), as an interrupt if it is not an
/// `Exception` (KeyboardInterrupt, SystemExit), else as bad model output; the last two stop the
/// update.
pub(super) struct CallbackModel<'a, 'py> {
    pub(super) func: &'a Bound<'py, PyAny>,
    pub(super) predict: Option<&'a Bound<'py, PyAny>>,
    pub(super) dims: (usize, usize, usize),
    pub(super) err: Option<PyErr>,
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

/// The model behind an estimator: a Python callback (known model) or the learned GPs.
pub(super) enum Model {
    Callback {
        stage_eval: Py<PyAny>,
        predict: Option<Py<PyAny>>,
        dims: (usize, usize, usize),
    },
    Gp(Box<GpStageModel>),
}

impl Model {
    pub(super) fn clone_ref(&self, py: Python<'_>) -> Self {
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
        }
    }

    fn dims(&self) -> (usize, usize, usize) {
        match self {
            Model::Callback { dims, .. } => *dims,
            Model::Gp(gp) => (gp.dim_x(), gp.dim_u(), gp.dim_y()),
        }
    }
}

// ---- copies and pickles ---------------------------------------------------------------------
impl Model {
    /// `(constructor, args)` rebuilding this model: `StageModel.callback(stage_eval, dims...,
    /// predict)` or `StageModel.gp(f, h, dim_u, f_residual)`.
    fn reduce<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyTuple>> {
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
        }
    }
}

/// The float64 array `state[key]` with `cols` columns (2-D), as a flat row-major vector; a
/// ValueError naming the entry otherwise.
fn state_rows(state: &Bound<'_, PyDict>, key: &str, cols: usize) -> PyResult<Vec<f64>> {
    let a = state_item(state, key)?;
    let a = a
        .cast::<PyArrayDyn<f64>>()
        .map_err(|_| PyValueError::new_err(format!("{key}: must be a float64 array")))?;
    if a.ndim() != 2 || a.shape()[1] != cols {
        return Err(PyValueError::new_err(format!(
            "{key}: must have shape (rows, {cols}), got {:?}",
            a.shape()
        )));
    }
    Ok(a.readonly().as_array().iter().copied().collect())
}

/// The 1-D float64 array `state[key]` as a vector; a ValueError naming the entry otherwise.
fn state_rows_1d(state: &Bound<'_, PyDict>, key: &str) -> PyResult<Vec<f64>> {
    let a = state_item(state, key)?;
    let a = a
        .cast::<PyArrayDyn<f64>>()
        .map_err(|_| PyValueError::new_err(format!("{key}: must be a float64 array")))?;
    if a.ndim() != 1 {
        return Err(PyValueError::new_err(format!("{key}: must be 1-D")));
    }
    Ok(a.readonly().as_array().iter().copied().collect())
}

fn state_item<'py>(state: &Bound<'py, PyDict>, key: &str) -> PyResult<Bound<'py, PyAny>> {
    state
        .get_item(key)?
        .ok_or_else(|| PyValueError::new_err(format!("{key}: missing from the state")))
}

fn state_usize(state: &Bound<'_, PyDict>, key: &str) -> PyResult<usize> {
    state_item(state, key)?
        .extract::<usize>()
        .map_err(|_| PyValueError::new_err(format!("{key}: must be a non-negative integer")))
}

/// The model of a `MovingHorizon`: `StageModel.gp(...)` (the learned GPs) or
/// `StageModel.callback(...)` (a `gpmhe.KnownModel`'s Python functions).
#[pyclass(name = "StageModel", module = "gpmhe._core", frozen)]
pub(super) struct PyStageModel {
    model: Model,
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

    /// (dim_x, dim_u, dim_y).
    #[getter]
    fn dims(&self) -> (usize, usize, usize) {
        self.model.dims()
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

/// A moving-horizon estimator (see `gpmhe.GPMHE`, which validates its settings and input and
/// holds the public attributes): `update(u, y)` is one whole update in one call.
#[pyclass(name = "MovingHorizon", module = "gpmhe._core")]
pub(super) struct PyMovingHorizon {
    pub(super) core: MovingHorizon,
    pub(super) model: Model,
    /// The learned model's evaluation cache before `prepare` staged a window (for `abandon`).
    pub(super) staged_cache: Option<[Vec<f64>; 9]>,
}

impl PyMovingHorizon {
    /// Runs `f` on the core with the model: the learned model without the GIL, a callback with
    /// it (a Python exception it raised is re-raised when `f` fails).
    fn run<T: Send>(
        &mut self,
        py: Python<'_>,
        f: impl FnOnce(&mut MovingHorizon, &mut dyn StageModel) -> crate::Result<T> + Send,
    ) -> PyResult<T> {
        let core = &mut self.core;
        match &mut self.model {
            Model::Gp(model) => {
                // An error (an interrupt among them) leaves the evaluation cache as it was: the
                // cache decides which values later updates reuse, bit for bit.
                let saved = model.cache();
                let r = detach_interruptible(py, || f(core, &mut **model));
                if r.is_err() {
                    // The model's own cache always fits it.
                    let _ = model.set_cache(saved);
                }
                r
            }
            Model::Callback {
                stage_eval,
                predict,
                dims,
            } => {
                let mut cb = CallbackModel {
                    func: stage_eval.bind(py),
                    predict: predict.as_ref().map(|f| f.bind(py)),
                    dims: *dims,
                    err: None,
                };
                // The model's exceptions reach Python anyway (a signal's handler runs inside the
                // callback); the check covers the core's own work between callbacks.
                match interruptible(|| f(core, &mut cb)) {
                    (Ok(v), _) => Ok(v),
                    (Err(_), Some(raised)) => Err(raised),
                    (Err(e), None) => Err(cb.err.take().unwrap_or_else(|| e.into())),
                }
            }
        }
    }

    fn n_vars(&self) -> usize {
        self.core.problem().n_nodes() * self.core.problem().dim_x()
    }

    fn dense_gn(eval: &crate::mhe::WindowEval) -> Vec<f64> {
        let (n, nodes) = (eval.dim_x(), eval.n_nodes());
        let (nn, nv) = (n * n, nodes * n);
        let mut diag = vec![0.0; nodes * nn];
        let mut off = vec![0.0; nodes.saturating_sub(1) * nn];
        eval.gauss_newton_blocks_into(&mut diag, &mut off);
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
impl PyMovingHorizon {
    /// An estimator on `model` (a `StageModel`). `q0`, `r0`: Q0 and R0, their diagonals or the
    /// flattened matrices; `p2_sqrt`: S with P2 = SᵀS; `filtering`: the form; `horizon`: M;
    /// `x0`: x̂(0) (zeros if None); `lower`, `upper`: the state box (±inf if None); `solver`: the
    /// solver settings; `arrival_mean` ("estimate" or "smoothed") and `arrival_weight`
    /// ("constant" or "ekf"): the arrival cost.
    #[new]
    #[allow(clippy::too_many_arguments)]
    #[pyo3(signature = (model, eta, q0, r0, p2_sqrt, filtering, horizon=1, x0=None, lower=None,
                        upper=None, solver=None, arrival_mean="estimate",
                        arrival_weight="constant"))]
    fn new(
        py: Python<'_>,
        model: PyRef<'_, PyStageModel>,
        eta: f64,
        q0: PyReadonlyArray1<'_, f64>,
        r0: PyReadonlyArray1<'_, f64>,
        p2_sqrt: PyReadonlyArray2<'_, f64>,
        filtering: bool,
        horizon: usize,
        x0: Option<PyReadonlyArray1<'_, f64>>,
        lower: Option<PyReadonlyArray1<'_, f64>>,
        upper: Option<PyReadonlyArray1<'_, f64>>,
        solver: Option<PyRef<'_, PyWindowSolver>>,
        arrival_mean: &str,
        arrival_weight: &str,
    ) -> PyResult<Self> {
        let arrival = parse_arrival(arrival_mean, arrival_weight)?;
        let (n, m, p) = model.model.dims();
        let form = match filtering {
            true => Form::Filtering,
            false => Form::Prediction,
        };
        let (p2, _, _) = slice2("P2", &p2_sqrt)?;
        let (q0, r0) = (slice1("Q0", &q0)?, slice1("R0", &r0)?);
        let problem = WindowProblem::new(n, m, p, eta, q0, r0, p2, form)?;
        let or = |a: &Option<PyReadonlyArray1<'_, f64>>, name: &str, fill: f64| {
            a.as_ref()
                .map_or(Ok(vec![fill; n]), |a| slice1(name, a).map(<[f64]>::to_vec))
        };
        let opts = solver.map_or_else(SolverOptions::default, |s| s.opts.clone());
        let mut core = MovingHorizon::new(
            problem,
            horizon,
            &or(&x0, "x0", 0.0)?,
            &or(&lower, "x_bounds", f64::NEG_INFINITY)?,
            &or(&upper, "x_bounds", f64::INFINITY)?,
            opts,
        )?;
        core.set_arrival(arrival);
        let model = model.model.clone_ref(py);
        Ok(Self {
            core,
            model,
            staged_cache: None,
        })
    }

    /// Replaces the weights given (η, Q0 and R0 as diagonals or flattened matrices, S of P2)
    /// from the next update on and keeps the others; a new P2 also becomes the next arrival
    /// weight. On error nothing changes.
    #[pyo3(signature = (eta=None, q0=None, r0=None, p2_sqrt=None))]
    fn set_weights(
        &mut self,
        eta: Option<f64>,
        q0: Option<PyReadonlyArray1<'_, f64>>,
        r0: Option<PyReadonlyArray1<'_, f64>>,
        p2_sqrt: Option<PyReadonlyArray2<'_, f64>>,
    ) -> PyResult<()> {
        let p2 = p2_sqrt.as_ref().map(|a| slice2("P2", a)).transpose()?;
        let q0 = q0.as_ref().map(|a| slice1("Q0", a)).transpose()?;
        let r0 = r0.as_ref().map(|a| slice1("R0", a)).transpose()?;
        Ok(self.core.set_weights(eta, q0, r0, p2.map(|(s, _, _)| s))?)
    }

    /// Replaces the input of the last update (see `MovingHorizon::set_last_input`).
    fn set_last_input(&mut self, py: Python<'_>, u: PyReadonlyArray1<'_, f64>) -> PyResult<()> {
        let u = slice1("u", &u)?;
        self.run(py, |core, model| core.set_last_input(model, u))
    }

    /// u(t − 1), the input of the last update (zeros before the first).
    #[getter]
    fn last_input<'py>(&self, py: Python<'py>) -> Arr1<'py> {
        let m = self.core.problem().dim_u();
        let u = self
            .core
            .history()
            .last_input()
            .map_or_else(|| vec![0.0; m], <[f64]>::to_vec);
        PyArray1::from_vec(py, u)
    }

    /// The next window's arrival weight P = SᵀS (n, n).
    #[getter]
    fn arrival_weight<'py>(&self, py: Python<'py>) -> PyResult<Arr2<'py>> {
        let n = self.core.problem().dim_x();
        let s = nalgebra::DMatrix::from_row_slice(n, n, self.core.history().arrival_sqrt());
        let w = s.transpose() * s;
        array2(py, w.transpose().as_slice().to_vec(), n, n)
    }

    /// Forgets every step: t = 0, x̂(0) = x0.
    fn reset(&mut self, x0: PyReadonlyArray1<'_, f64>) -> PyResult<()> {
        self.core.reset(slice1("x0", &x0)?)?;
        self.staged_cache = None;
        Ok(())
    }

    /// One whole update with u(t) (None: not known yet, see `MovingHorizon::prepare` in the
    /// core) and y(t) (None: not measured); what it reports is read from the getters below.
    /// On error the estimator is unchanged.
    #[pyo3(signature = (u, y=None))]
    fn update(
        &mut self,
        py: Python<'_>,
        u: Option<PyReadonlyArray1<'_, f64>>,
        y: Option<PyReadonlyArray1<'_, f64>>,
    ) -> PyResult<()> {
        let u = u.as_ref().map(|u| slice1("u", u)).transpose()?;
        let y = y.as_ref().map(|y| slice1("y", y)).transpose()?;
        self.run(py, |core, model| core.update(model, u, y))?;
        Ok(())
    }

    /// Stages the next window with u(t), y(t) without recording it; returns (z0, lower,
    /// upper): the warm start and the box of the stacked window states. The window methods
    /// (`cost`, ...) then evaluate it; `commit` records a solution.
    #[pyo3(signature = (u, y=None))]
    fn prepare<'py>(
        &mut self,
        py: Python<'py>,
        u: Option<PyReadonlyArray1<'py, f64>>,
        y: Option<PyReadonlyArray1<'py, f64>>,
    ) -> PyResult<(Arr1<'py>, Arr1<'py>, Arr1<'py>)> {
        let u = u.as_ref().map(|u| slice1("u", u)).transpose()?;
        let y = y.as_ref().map(|y| slice1("y", y)).transpose()?;
        if let Model::Gp(gp) = &self.model {
            if self.staged_cache.is_none() {
                self.staged_cache = Some(gp.cache());
            }
        }
        let z0 = self.run(py, |core, model| core.prepare(model, u, y))?;
        let (lo, hi) = self.core.bounds();
        Ok((
            PyArray1::from_vec(py, z0),
            PyArray1::from_slice(py, lo),
            PyArray1::from_slice(py, hi),
        ))
    }

    /// Records the staged window's solution z with how another solver found it: its `cost`
    /// (None: J(z) evaluated here), `success`, `nit`, `message` and the covariance `P` (n, n)
    /// of the last node (None: not computable, the previous one is kept). Returns (x_window
    /// (nodes, n), x_prior). On error nothing changes.
    #[pyo3(signature = (z, cost=None, success=true, nit=0, message=String::new(), P=None))]
    #[allow(non_snake_case, clippy::too_many_arguments)]
    fn commit<'py>(
        &mut self,
        py: Python<'py>,
        z: PyReadonlyArray1<'py, f64>,
        cost: Option<f64>,
        success: bool,
        nit: usize,
        message: String,
        P: Option<PyReadonlyArray2<'py, f64>>,
    ) -> PyResult<(Arr2<'py>, Arr1<'py>)> {
        let z = slice1("z", &z)?.to_vec();
        let cov = P.as_ref().map(|a| slice2("P", a)).transpose()?;
        let cov = cov.map(|(c, _, _)| c.to_vec());
        let solved = Solved::Other {
            success,
            nit,
            message,
        };
        let n = self.core.problem().dim_x();
        let (x_window, x_prior) = self.run(py, |core, model| {
            let cost = match cost {
                Some(c) => c,
                None => core.evaluate(model, &z, false)?.cost(),
            };
            core.commit(model, z, cov, cost, &solved)
        })?;
        self.staged_cache = None;
        let rows = x_window.len() / n;
        Ok((
            array2(py, x_window, rows, n)?,
            PyArray1::from_vec(py, x_prior),
        ))
    }

    /// Drops the staged window (after `prepare`, when its solve was abandoned, e.g. by an
    /// interrupt) and puts the learned model's evaluation cache back as it was before
    /// `prepare`, so the next update runs as if this one had never started.
    fn abandon(&mut self) {
        self.core.drop_staged();
        if let (Some(saved), Model::Gp(gp)) = (self.staged_cache.take(), &mut self.model) {
            // The model's own cache always fits it.
            let _ = gp.set_cache(saved);
        }
    }

    /// Sets a window directly (tests, diagnostics; it cannot be committed): `u` (nodes, m),
    /// `y` (nodes, p), `y_present` (nodes,), `x_prior` (n,). On error the window is kept.
    fn set_data(
        &mut self,
        u: PyReadonlyArray2<'_, f64>,
        y: PyReadonlyArray2<'_, f64>,
        y_present: Vec<bool>,
        x_prior: PyReadonlyArray1<'_, f64>,
    ) -> PyResult<()> {
        let (u, _, _) = slice2("u", &u)?;
        let (y, _, _) = slice2("y", &y)?;
        Ok(self
            .core
            .set_window(u, y, &y_present, slice1("x_prior", &x_prior)?)?)
    }

    /// The model's one-step prediction m_x(x, u) (n,).
    fn predict_next<'py>(
        &mut self,
        py: Python<'py>,
        x: PyReadonlyArray1<'py, f64>,
        u: PyReadonlyArray1<'py, f64>,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let (x, u) = (slice1("x", &x)?, slice1("u", &u)?);
        let p = self.core.problem();
        check_len("x", x, p.dim_x())?;
        check_len("u", u, p.dim_u())?;
        check_finite("x", x)?;
        check_finite("u", u)?;
        let mut out = vec![0.0; p.dim_x()];
        self.run(py, |_, model| model.predict_state(x, u, &mut out))?;
        Ok(PyArray1::from_vec(py, out))
    }

    /// Updates since construction or `reset`.
    #[getter]
    fn t(&self) -> usize {
        self.core.history().t()
    }

    // ---- what the last update reported (`crate::mhe::Outcome`) --------------------------------
    /// The last optimal window (nodes, n), oldest first (x̂(0) as one row before any update).
    #[getter]
    fn x_window<'py>(&self, py: Python<'py>) -> PyResult<Arr2<'py>> {
        let n = self.core.problem().dim_x();
        let (w, _) = self.core.history().x_window();
        array2(py, w.to_vec(), w.len() / n, n)
    }

    /// The estimate: the last row of `x_window` (n,).
    #[getter]
    fn x<'py>(&self, py: Python<'py>) -> Arr1<'py> {
        let n = self.core.problem().dim_x();
        let (w, _) = self.core.history().x_window();
        PyArray1::from_slice(py, &w[w.len() - n..])
    }

    /// The arrival prior of the last window's first node (n,).
    #[getter]
    fn x_prior<'py>(&self, py: Python<'py>) -> Arr1<'py> {
        PyArray1::from_slice(py, &self.core.history().outcome().x_prior)
    }

    /// The covariance estimate of the newest node (n, n).
    #[getter]
    fn covariance<'py>(&self, py: Python<'py>) -> PyResult<Arr2<'py>> {
        let n = self.core.problem().dim_x();
        array2(py, self.core.history().outcome().covariance.clone(), n, n)
    }

    /// The optimal cost J of the last window (0 before any update).
    #[getter]
    fn optimal_cost(&self) -> f64 {
        self.core.history().outcome().cost
    }

    #[getter]
    fn success(&self) -> bool {
        self.core.history().outcome().success
    }

    #[getter]
    fn nit(&self) -> usize {
        self.core.history().outcome().nit
    }

    #[getter]
    fn nfev(&self) -> usize {
        self.core.history().outcome().nfev
    }

    #[getter]
    fn projected_gradient(&self) -> f64 {
        self.core.history().outcome().projected_gradient
    }

    #[getter]
    fn message(&self) -> String {
        self.core.history().outcome().message.clone()
    }

    /// Whether the last update was given no input and waits for `set_last_input`.
    #[getter]
    fn input_pending(&self) -> bool {
        self.core.history().outcome().input_pending
    }

    #[getter]
    fn n_nodes(&self) -> usize {
        self.core.problem().n_nodes()
    }

    #[getter]
    fn n_residuals(&self) -> usize {
        self.core.problem().n_residuals()
    }

    /// J(z) = ‖r(z)‖² of the window.
    fn cost(&mut self, py: Python<'_>, z: PyReadonlyArray1<'_, f64>) -> PyResult<f64> {
        let z = slice1("z", &z)?;
        self.run(py, |core, model| Ok(core.evaluate(model, z, false)?.cost()))
    }

    /// (noise of J, noise of ∇J (largest entry)) at z: the estimated rounding noise of the cost
    /// and gradient from the model's mean and variance rounding (0 for a model computed to
    /// full precision).
    fn rounding_noise(
        &mut self,
        py: Python<'_>,
        z: PyReadonlyArray1<'_, f64>,
    ) -> PyResult<(f64, f64)> {
        let z = slice1("z", &z)?;
        self.run(py, |core, model| {
            let ev = core.evaluate(model, z, true)?;
            Ok((ev.cost_noise(), ev.gradient_noise()))
        })
    }

    /// (J(z), ∇J(z) = 2Jᵀr).
    fn cost_grad<'py>(
        &mut self,
        py: Python<'py>,
        z: PyReadonlyArray1<'py, f64>,
    ) -> PyResult<(f64, Bound<'py, PyArray1<f64>>)> {
        let z = slice1("z", &z)?;
        let mut g = vec![0.0; z.len()];
        let cost = self.run(py, |core, model| {
            let ev = core.evaluate(model, z, true)?;
            ev.gradient_into(&mut g);
            Ok(ev.cost())
        })?;
        Ok((cost, PyArray1::from_vec(py, g)))
    }

    /// The Gauss-Newton Hessian 2JᵀJ at z as a dense (n_nodes·n)² array.
    fn gn_hessian<'py>(
        &mut self,
        py: Python<'py>,
        z: PyReadonlyArray1<'py, f64>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let z = slice1("z", &z)?;
        let h = self.run(py, |core, model| {
            Ok(Self::dense_gn(core.evaluate(model, z, true)?))
        })?;
        let nv = self.n_vars();
        array2(py, h, nv, nv)
    }

    /// The stacked residuals r(z).
    fn residuals<'py>(
        &mut self,
        py: Python<'py>,
        z: PyReadonlyArray1<'py, f64>,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let z = slice1("z", &z)?;
        let r = self.run(py, |core, model| {
            Ok(core.evaluate(model, z, false)?.residuals().to_vec())
        })?;
        Ok(PyArray1::from_vec(py, r))
    }

    /// The dense Jacobian ∂r/∂z (n_residuals × n_nodes·n).
    fn jacobian<'py>(
        &mut self,
        py: Python<'py>,
        z: PyReadonlyArray1<'py, f64>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let z = slice1("z", &z)?;
        let (jac, rows, cols) = self.run(py, |core, model| {
            let ev = core.evaluate(model, z, true)?;
            let (rows, cols) = (ev.n_residuals(), ev.n_vars());
            let mut jac = vec![0.0; rows * cols];
            ev.dense_jacobian_into(&mut jac);
            Ok((jac, rows, cols))
        })?;
        array2(py, jac, rows, cols)
    }

    // ---- copies, pickles and checkpoints ------------------------------------------------------
    /// An independent copy: the settings, the history and the work buffers are copied, the
    /// model's GPs (immutable) are shared; the copy continues exactly as the original would.
    fn __copy__(&self, py: Python<'_>) -> Self {
        Self {
            core: self.core.clone(),
            model: self.model.clone_ref(py),
            staged_cache: self.staged_cache.clone(),
        }
    }

    fn __deepcopy__(&self, py: Python<'_>, _memo: Bound<'_, PyAny>) -> Self {
        self.__copy__(py)
    }

    /// Pickles as (MovingHorizon, constructor arguments, `__getstate__()`).
    fn __reduce__<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyTuple>> {
        let p = self.core.problem();
        let n = p.dim_x();
        let stage = Py::new(
            py,
            PyStageModel {
                model: self.model.clone_ref(py),
            },
        )?;
        let solver = Py::new(
            py,
            PyWindowSolver {
                solver: BoxLsqSolver::new(),
                opts: self.core.options().clone(),
            },
        )?;
        let (lower, upper) = self.core.x_bounds();
        let args = (
            stage,
            p.eta(),
            PyArray1::from_slice(py, p.q0()),
            PyArray1::from_slice(py, p.r0()),
            array2(py, p.p2_sqrt().to_vec(), n, n)?,
            p.form() == Form::Filtering,
            self.core.history().horizon(),
            None::<Py<PyAny>>,
            PyArray1::from_slice(py, lower),
            PyArray1::from_slice(py, upper),
            solver,
        )
            .into_pyobject(py)?
            .add(arrival_names(self.core.arrival()).into_pyobject(py)?)?;
        let cls = py.get_type::<Self>();
        (cls, args, self.__getstate__(py)?).into_pyobject(py)
    }

    /// The history as a dict of plain values: `t`, `window_t0` (ints), `u` (rows, m), `y`
    /// (rows, p), `present` (rows,) bool, `priors` (k, n), `x_window` (nodes, n).
    pub(super) fn __getstate__<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let s = self.core.history_state();
        let p = self.core.problem();
        let (n, m, dy) = (p.dim_x(), p.dim_u(), p.dim_y());
        let rows = s.present.len();
        let d = PyDict::new(py);
        d.set_item("t", s.t)?;
        d.set_item("window_t0", s.window_t0)?;
        d.set_item("u", array2(py, s.u, rows, m)?)?;
        d.set_item("y", array2(py, s.y, rows, dy)?)?;
        d.set_item("present", PyArray1::from_vec(py, s.present))?;
        let k = s.priors.len() / n;
        d.set_item("priors", array2(py, s.priors, k, n)?)?;
        let nodes = s.x_window.len() / n;
        d.set_item("x_window", array2(py, s.x_window, nodes, n)?)?;
        d.set_item("arrival_sqrt", array2(py, s.arrival_sqrt, n, n)?)?;
        outcome_items(py, &d, s.outcome, n)?;
        if let Model::Gp(gp) = &self.model {
            for (name, part) in GP_CACHE_PARTS.iter().zip(gp.cache()) {
                d.set_item(format!("cache_{name}"), PyArray1::from_vec(py, part))?;
            }
        }
        Ok(d)
    }

    /// Restores a history from `__getstate__` of an estimator with the same settings. Every
    /// entry is checked (a ValueError names it); on error nothing changes.
    pub(super) fn __setstate__(&mut self, state: Bound<'_, PyDict>) -> PyResult<()> {
        let p = self.core.problem();
        let (n, m, dy) = (p.dim_x(), p.dim_u(), p.dim_y());
        let present = state_item(&state, "present")?;
        let present = present
            .cast::<PyArrayDyn<bool>>()
            .map_err(|_| PyValueError::new_err("present: must be a bool array"))?;
        if present.ndim() != 1 {
            return Err(PyValueError::new_err("present: must be 1-D"));
        }
        let s = HistoryState {
            t: state_usize(&state, "t")?,
            u: state_rows(&state, "u", m)?,
            y: state_rows(&state, "y", dy)?,
            present: present.readonly().as_array().iter().copied().collect(),
            priors: state_rows(&state, "priors", n)?,
            x_window: state_rows(&state, "x_window", n)?,
            window_t0: state_usize(&state, "window_t0")?,
            // States saved before the arrival weight was recorded ran with P2.
            arrival_sqrt: match state.contains("arrival_sqrt")? {
                true => state_rows(&state, "arrival_sqrt", n)?,
                false => p.p2_sqrt().to_vec(),
            },
            outcome: read_outcome(&state, self.core.history().outcome(), n)?,
        };
        // The learned model's cache of the last evaluation (see `GpStageModel::cache`).
        let gp = match &self.model {
            Model::Gp(gp) => {
                let mut parts: [Vec<f64>; 9] = Default::default();
                for (part, name) in parts.iter_mut().zip(GP_CACHE_PARTS) {
                    *part = state_rows_1d(&state, &format!("cache_{name}"))?;
                }
                let mut gp = gp.clone();
                gp.set_cache(parts)
                    .map_err(|e| PyValueError::new_err(format!("cache_{e}")))?;
                Some(gp)
            }
            Model::Callback { .. } => None,
        };
        self.core.set_history_state(s)?;
        if let Some(gp) = gp {
            self.model = Model::Gp(gp);
        }
        self.staged_cache = None;
        Ok(())
    }
}

/// The arrival cost from its names (see `crate::mhe::arrival`).
fn parse_arrival(mean: &str, weight: &str) -> PyResult<Arrival> {
    let mean = match mean {
        "estimate" => ArrivalMean::Estimate,
        "smoothed" => ArrivalMean::Smoothed,
        _ => {
            return Err(PyValueError::new_err(format!(
                "arrival_mean: must be 'estimate' or 'smoothed', got {mean:?}"
            )))
        }
    };
    let weight = match weight {
        "constant" => ArrivalWeight::Constant,
        "ekf" => ArrivalWeight::Ekf,
        _ => {
            return Err(PyValueError::new_err(format!(
                "arrival_weight: must be 'constant' or 'ekf', got {weight:?}"
            )))
        }
    };
    Ok(Arrival { mean, weight })
}

/// The names `parse_arrival` reads.
fn arrival_names(a: Arrival) -> (&'static str, &'static str) {
    let mean = match a.mean {
        ArrivalMean::Estimate => "estimate",
        ArrivalMean::Smoothed => "smoothed",
    };
    let weight = match a.weight {
        ArrivalWeight::Constant => "constant",
        ArrivalWeight::Ekf => "ekf",
    };
    (mean, weight)
}

/// Writes `outcome` into a state dict as `outcome_x_prior`, `outcome_P`, `outcome_cost`,
/// `outcome_success`, `outcome_nit`, `outcome_nfev`, `outcome_projected_gradient`,
/// `outcome_message` and `outcome_input_pending`.
fn outcome_items(py: Python<'_>, d: &Bound<'_, PyDict>, o: Outcome, n: usize) -> PyResult<()> {
    d.set_item("outcome_x_prior", PyArray1::from_vec(py, o.x_prior))?;
    d.set_item("outcome_P", array2(py, o.covariance, n, n)?)?;
    d.set_item("outcome_cost", o.cost)?;
    d.set_item("outcome_success", o.success)?;
    d.set_item("outcome_nit", o.nit)?;
    d.set_item("outcome_nfev", o.nfev)?;
    d.set_item("outcome_projected_gradient", o.projected_gradient)?;
    d.set_item("outcome_message", o.message)?;
    d.set_item("outcome_input_pending", o.input_pending)?;
    Ok(())
}

/// The outcome in a state dict (see `outcome_items`); a state without one (saved before
/// estimators recorded it) keeps `current`. An entry of the wrong type is a ValueError naming
/// it; the values are checked by `HistoryState`'s restore.
fn read_outcome(state: &Bound<'_, PyDict>, current: &Outcome, n: usize) -> PyResult<Outcome> {
    if !state.contains("outcome_x_prior")? {
        return Ok(current.clone());
    }
    let item = |key: &str| state_item(state, key);
    let typed = |key: &str, what: &str| PyValueError::new_err(format!("{key}: must be {what}"));
    Ok(Outcome {
        x_prior: state_rows_1d(state, "outcome_x_prior")?,
        covariance: state_rows(state, "outcome_P", n)?,
        cost: item("outcome_cost")?
            .extract()
            .map_err(|_| typed("outcome_cost", "a number"))?,
        success: item("outcome_success")?
            .extract()
            .map_err(|_| typed("outcome_success", "a bool"))?,
        nit: state_usize(state, "outcome_nit")?,
        nfev: state_usize(state, "outcome_nfev")?,
        projected_gradient: item("outcome_projected_gradient")?
            .extract()
            .map_err(|_| typed("outcome_projected_gradient", "a number"))?,
        message: item("outcome_message")?
            .extract()
            .map_err(|_| typed("outcome_message", "a string"))?,
        input_pending: item("outcome_input_pending")?
            .extract()
            .map_err(|_| typed("outcome_input_pending", "a bool"))?,
    })
}

/// Solver settings and work buffers: given to `MovingHorizon` as its settings, or used directly
/// on a window set with `MovingHorizon.set_data` (tests, diagnostics).
#[pyclass(name = "WindowSolver", module = "gpmhe._core")]
pub(super) struct PyWindowSolver {
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

    /// Pickles as its constructor call with the settings (the work buffers are not kept).
    fn __reduce__<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyTuple>> {
        let o = &self.opts;
        let interior = match o.interior {
            InteriorMode::Auto => "auto",
            InteriorMode::Always => "always",
            InteriorMode::Never => "never",
        };
        let args = (
            o.max_iter,
            o.gtol,
            o.xtol,
            o.ftol,
            o.dtol,
            interior,
            o.interior_zone,
            o.mu_init,
            o.mu_final,
        );
        (py.get_type::<Self>(), args).into_pyobject(py)
    }

    /// Minimises the window's cost over lower ≤ z ≤ upper from `z0`. Returns (z, cost, status,
    /// success, nit, nfev, projected_gradient, interior_iterations, P) with P the last n×n
    /// block of 4(2JᵀJ)⁻¹ at z (None if singular); the window's evaluation is left at z.
    #[allow(clippy::type_complexity)]
    fn solve<'py>(
        &mut self,
        py: Python<'py>,
        mut window: PyRefMut<'py, PyMovingHorizon>,
        z0: PyReadonlyArray1<'py, f64>,
        lower: PyReadonlyArray1<'py, f64>,
        upper: PyReadonlyArray1<'py, f64>,
    ) -> PyResult<SolveTuple<'py>> {
        let mut z = slice1("z0", &z0)?.to_vec();
        let (lower, upper) = (slice1("lower", &lower)?, slice1("upper", &upper)?);
        let (solver, opts) = (&mut self.solver, &self.opts);
        let report = window.run(py, |core, model| {
            core.solve_with(model, &mut z, lower, upper, solver, opts)
        })?;
        let n = window.core.problem().dim_x();
        let cov = self
            .solver
            .last_node_covariance()
            .map(|c| array2(py, c, n, n))
            .transpose()?;
        Ok((
            PyArray1::from_vec(py, z),
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

type SolveTuple<'py> = (
    Bound<'py, PyArray1<f64>>,
    f64,
    &'static str,
    bool,
    usize,
    usize,
    f64,
    usize,
    Option<Bound<'py, PyArray2<f64>>>,
);
