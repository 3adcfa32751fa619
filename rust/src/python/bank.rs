//! The estimator bank (`crate::mhe::EstimatorBank`) as `_core.EstimatorBank`: converts one
//! sample's arrays, calls the core and maps errors. A bank on the learned model or a compiled
//! CasADi model updates its estimators in parallel without the GIL (the calling thread meanwhile
//! runs Python's signal handlers: Ctrl-C stops the update with every estimator unchanged); a
//! Python callback model (`gpmhe.KnownModel`) runs them one after another with the GIL.
//! `gpmhe.EstimatorBank` (python/gpmhe/mhe/bank.py) validates the input and holds the public
//! attributes.

use numpy::{
    PyArray1, PyArrayDyn, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2, PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyIndexError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use super::convert::{slice1, slice2};
use super::error::{detach_interruptible, interruptible, model_domain_error};
use super::mhe::{CallbackModel, Model, PyMovingHorizon};
use crate::compiled::CompiledModel;
use crate::mhe::{
    bank_threads, BankSample, EstimatorBank, GpStageModel, MemberSettings, MovingHorizon,
};

/// The estimators: on the learned GPs or a compiled CasADi model (each with its own model clone,
/// the GPs or the library shared), or on a Python callback model (one for all, kept in `model`).
enum Inner {
    Gp(EstimatorBank<GpStageModel>),
    Compiled(EstimatorBank<CompiledModel>),
    Callback(EstimatorBank<()>),
}

/// `$body` with `$b` bound to the bank inside `$inner`, whatever its model type.
macro_rules! with_bank {
    ($inner:expr, $b:ident => $body:expr) => {
        match $inner {
            Inner::Gp($b) => $body,
            Inner::Compiled($b) => $body,
            Inner::Callback($b) => $body,
        }
    };
}

/// n independent `MovingHorizon` estimators with the settings of a template, updated together
/// (see `gpmhe.EstimatorBank`).
#[pyclass(name = "EstimatorBank", module = "gpmhe._core")]
pub(super) struct PyEstimatorBank {
    inner: Inner,
    /// The template's model (for a callback model, the one every estimator calls).
    model: Model,
}

/// The rows of a (k, cols) float64 array as vectors.
fn rows(name: &str, a: &PyReadonlyArray2<'_, f64>, k: usize) -> PyResult<Vec<Vec<f64>>> {
    let (data, r, c) = slice2(name, a)?;
    if r != k {
        return Err(PyValueError::new_err(format!(
            "{name}: needs {k} rows, got {r}"
        )));
    }
    Ok((0..k).map(|i| data[i * c..(i + 1) * c].to_vec()).collect())
}

impl PyEstimatorBank {
    fn len(&self) -> usize {
        with_bank!(&self.inner, b => b.len())
    }

    /// Estimator i with its model as a standalone `MovingHorizon` (a copy).
    fn window(&self, py: Python<'_>, i: usize) -> PyResult<PyMovingHorizon> {
        let out_of_range = || PyIndexError::new_err(format!("i: no estimator {i}"));
        Ok(match &self.inner {
            Inner::Gp(b) => {
                let m = b.member(i).ok_or_else(out_of_range)?;
                PyMovingHorizon {
                    core: m.estimator.clone(),
                    model: Model::Gp(Box::new(m.model.clone())),
                    staged_cache: None,
                }
            }
            Inner::Compiled(b) => PyMovingHorizon {
                core: b.member(i).ok_or_else(out_of_range)?.estimator.clone(),
                model: self.model.clone_ref(py),
                staged_cache: None,
            },
            Inner::Callback(b) => PyMovingHorizon {
                core: b.member(i).ok_or_else(out_of_range)?.estimator.clone(),
                model: self.model.clone_ref(py),
                staged_cache: None,
            },
        })
    }

    /// Every estimator's value of `f` stacked (k × the length of one), as an array of shape
    /// `[k] + shape`.
    fn stacked<'py>(
        &self,
        py: Python<'py>,
        shape: &[usize],
        f: impl Fn(&MovingHorizon) -> Vec<f64>,
    ) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
        let data: Vec<f64> = with_bank!(&self.inner, b => b.members().iter().flat_map(|m| f(&m.estimator)).collect());
        let mut dims = vec![self.len()];
        dims.extend_from_slice(shape);
        PyArray1::from_vec(py, data).reshape(dims)
    }

    /// Every estimator's value of `f`, in order.
    fn each<T>(&self, f: impl Fn(&MovingHorizon) -> T) -> Vec<T> {
        with_bank!(&self.inner, b => b.members().iter().map(|m| f(&m.estimator)).collect())
    }

    /// The state dimension n and the number of nodes of the last windows.
    fn window_shape(&self) -> (usize, usize) {
        let n = self.dims().0;
        let rows = self.each(|e| e.history().x_window().0.len() / n);
        (n, rows.first().copied().unwrap_or(1))
    }

    fn dims(&self) -> (usize, usize, usize) {
        with_bank!(&self.inner, b => b.dims())
    }
}

#[pymethods]
impl PyEstimatorBank {
    /// k estimators with `template`'s model (shared, see the module docs), horizon, weights η,
    /// P2, form and solver settings; row i of `x0`, `lower`, `upper` (k, n), `q0` (k, n or n²)
    /// and `r0` (k, p or p²) are estimator i's x̂(0), state box and Q0, R0 (diagonals or
    /// row-major matrices).
    #[new]
    fn new(
        py: Python<'_>,
        template: PyRef<'_, PyMovingHorizon>,
        x0: PyReadonlyArray2<'_, f64>,
        lower: PyReadonlyArray2<'_, f64>,
        upper: PyReadonlyArray2<'_, f64>,
        q0: PyReadonlyArray2<'_, f64>,
        r0: PyReadonlyArray2<'_, f64>,
    ) -> PyResult<Self> {
        let k = x0.shape()[0];
        let (x0, lower, upper) = (
            rows("x0", &x0, k)?,
            rows("x_bounds", &lower, k)?,
            rows("x_bounds", &upper, k)?,
        );
        let (q0, r0) = (rows("Q0", &q0, k)?, rows("R0", &r0, k)?);
        let settings: Vec<MemberSettings> = (0..k)
            .map(|i| MemberSettings {
                x0: x0[i].clone(),
                lower: lower[i].clone(),
                upper: upper[i].clone(),
                q0: q0[i].clone(),
                r0: r0[i].clone(),
            })
            .collect();
        let inner = match &template.model {
            Model::Gp(gp) => Inner::Gp(EstimatorBank::new(&template.core, &**gp, &settings)?),
            Model::Compiled { model, .. } => {
                Inner::Compiled(EstimatorBank::new(&template.core, &**model, &settings)?)
            }
            Model::Callback { .. } => {
                Inner::Callback(EstimatorBank::new(&template.core, &(), &settings)?)
            }
            Model::Learning(_) => {
                return Err(PyValueError::new_err(
                    "model: a bank does not run estimators that learn (learning=True)",
                ))
            }
        };
        Ok(Self {
            inner,
            model: template.model.clone_ref(py),
        })
    }

    fn __len__(&self) -> usize {
        self.len()
    }

    /// Whether the estimators run in parallel (the learned model or a compiled CasADi model) or
    /// one after another (a Python model).
    #[getter]
    fn parallel(&self) -> bool {
        !matches!(self.inner, Inner::Callback(_))
    }

    /// The number of threads a parallel update runs on (rayon's pool: one per core unless
    /// the environment variable `RAYON_NUM_THREADS` says otherwise).
    #[staticmethod]
    fn threads() -> usize {
        bank_threads()
    }

    /// One update of every estimator: row i of `u` (k, m) and `y` (k, p) for estimator i,
    /// `present[i]` False when its y is missing (its row of `y` is ignored), row i of `r`
    /// (k, p or p²) its y's covariance, the diagonal or the row-major matrix (None: each one's
    /// R0). What each estimator reports is read from the getters below. Row i of `u_last`
    /// (k, m), if given, is estimator i's last input row as this sample completes it. On error
    /// no estimator changes.
    #[pyo3(signature = (u, y, present, r=None, u_last=None))]
    fn update<'py>(
        &mut self,
        py: Python<'py>,
        u: PyReadonlyArray2<'py, f64>,
        y: PyReadonlyArray2<'py, f64>,
        present: PyReadonlyArray1<'py, bool>,
        r: Option<PyReadonlyArray2<'py, f64>>,
        u_last: Option<PyReadonlyArray2<'py, f64>>,
    ) -> PyResult<()> {
        let (u, _, _) = slice2("U", &u)?;
        let (y, _, _) = slice2("Y", &y)?;
        let present = present
            .as_slice()
            .map_err(|_| PyValueError::new_err("present: must be a contiguous bool array"))?;
        let r = r.as_ref().map(|r| slice2("R", r)).transpose()?;
        let u_last = u_last.as_ref().map(|u| slice2("u_last", u)).transpose()?;
        let sample = BankSample {
            u,
            y,
            present,
            r: r.map(|(r, _, _)| r),
            u_last: u_last.map(|(u, _, _)| u),
        };
        match (&mut self.inner, &self.model) {
            (Inner::Gp(bank), _) => {
                detach_interruptible(py, || bank.par_update(sample))?;
            }
            (Inner::Compiled(bank), _) => {
                match py.detach(|| interruptible(|| bank.par_update(sample))) {
                    (Ok(_), _) => {}
                    (Err(_), Some(raised)) => return Err(raised),
                    (Err(e), None) => {
                        let domain = bank.members().iter().any(|m| m.model.is_domain_error(&e));
                        return Err(if domain {
                            model_domain_error(py, e)
                        } else {
                            e.into()
                        });
                    }
                }
            }
            (
                Inner::Callback(bank),
                Model::Callback {
                    stage_eval,
                    predict,
                    dims,
                },
            ) => {
                let (func, predict) = (stage_eval.bind(py), predict.as_ref().map(|f| f.bind(py)));
                let mut raised_by_model: Option<PyErr> = None;
                let run = interruptible(|| {
                    bank.update_each(sample, |est, _, row| {
                        let mut cb = CallbackModel {
                            func,
                            predict,
                            dims: *dims,
                            err: None,
                        };
                        let r = row.solve(est, &mut cb);
                        if r.is_err() {
                            raised_by_model = cb.err.take();
                        }
                        r
                    })
                });
                match run {
                    (Ok(_), _) => {}
                    (Err(_), Some(raised)) => return Err(raised),
                    (Err(e), None) => return Err(raised_by_model.unwrap_or_else(|| e.into())),
                }
            }
            (Inner::Callback(_), _) => {
                return Err(PyValueError::new_err("internal: bank and model disagree"))
            }
        };
        Ok(())
    }

    // ---- what the last update reported, one row per estimator --------------------------------
    /// Updates since construction (every estimator has had the same).
    #[getter]
    fn t(&self) -> usize {
        self.each(|e| e.history().t()).first().copied().unwrap_or(0)
    }

    /// The last optimal windows (k, nodes, n).
    #[getter]
    fn x_window<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
        let (n, nodes) = self.window_shape();
        self.stacked(py, &[nodes, n], |e| e.history().x_window().0.to_vec())
    }

    /// The estimates, the last rows of the windows (k, n).
    #[getter]
    fn x<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
        let n = self.dims().0;
        self.stacked(py, &[n], |e| {
            let w = e.history().x_window().0;
            w[w.len() - n..].to_vec()
        })
    }

    /// Each estimator's last recorded input row (k, m; zeros before the first update).
    #[getter]
    fn last_inputs<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
        let m = self.dims().1;
        self.stacked(py, &[m], |e| {
            e.history()
                .last_input()
                .map_or_else(|| vec![0.0; m], <[f64]>::to_vec)
        })
    }

    #[getter]
    fn x_prior<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
        let n = self.dims().0;
        self.stacked(py, &[n], |e| e.history().outcome().x_prior.clone())
    }

    /// The covariance estimates (k, n, n).
    #[getter]
    fn covariance<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
        let n = self.dims().0;
        self.stacked(py, &[n, n], |e| e.history().outcome().covariance.clone())
    }

    #[getter]
    fn optimal_cost<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_vec(py, self.each(|e| e.history().outcome().cost))
    }

    #[getter]
    fn success<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<bool>> {
        PyArray1::from_vec(py, self.each(|e| e.history().outcome().success))
    }

    #[getter]
    fn nit<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<i64>> {
        PyArray1::from_vec(py, self.each(|e| e.history().outcome().nit as i64))
    }

    #[getter]
    fn nfev<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<i64>> {
        PyArray1::from_vec(py, self.each(|e| e.history().outcome().nfev as i64))
    }

    #[getter]
    fn projected_gradient<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_vec(py, self.each(|e| e.history().outcome().projected_gradient))
    }

    /// The solvers' messages (`GPMHE.message`), one per estimator.
    #[getter]
    fn messages(&self) -> Vec<String> {
        self.each(|e| e.history().outcome().message.clone())
    }

    /// Estimator i as a standalone `MovingHorizon` (an independent copy that continues exactly
    /// as estimator i would).
    fn member(&self, py: Python<'_>, i: usize) -> PyResult<PyMovingHorizon> {
        self.window(py, i)
    }

    /// Restarts estimator `indices[j]` from row j of `x0` (its state x̂(0) as the core holds
    /// it, see `MovingHorizon.reset`); on error no estimator changes.
    fn reset(&mut self, indices: Vec<usize>, x0: PyReadonlyArray2<'_, f64>) -> PyResult<()> {
        let (data, k, n) = slice2("x0", &x0)?;
        if k != indices.len() {
            return Err(PyValueError::new_err(format!(
                "x0: needs one row per index ({}), got {k}",
                indices.len()
            )));
        }
        let rows: Vec<(usize, &[f64])> = indices
            .iter()
            .enumerate()
            .map(|(j, &i)| (i, &data[j * n..(j + 1) * n]))
            .collect();
        with_bank!(&mut self.inner, b => b.reset(&rows))?;
        Ok(())
    }

    /// Records a late output for estimator i (see `MovingHorizon.add_delayed`); on error
    /// nothing changes.
    #[pyo3(signature = (i, y, age, r=None))]
    fn add_delayed(
        &mut self,
        i: usize,
        y: PyReadonlyArray1<'_, f64>,
        age: usize,
        r: Option<PyReadonlyArray1<'_, f64>>,
    ) -> PyResult<()> {
        let r = r.as_ref().map(|r| slice1("R", r)).transpose()?;
        let y = slice1("y", &y)?;
        let estimator = with_bank!(&mut self.inner, b => b.member_mut(i).map(|m| &mut m.estimator));
        let estimator =
            estimator.ok_or_else(|| PyIndexError::new_err(format!("i: no estimator {i}")))?;
        Ok(estimator.add_delayed(y, age, r)?)
    }

    /// The largest age `add_delayed` accepts now (the same for every estimator).
    #[getter]
    fn max_delay(&self) -> usize {
        self.each(|e| e.history().max_delay().unwrap_or(0))
            .first()
            .copied()
            .unwrap_or(0)
    }

    /// Estimator i's state as `MovingHorizon.__getstate__` gives it.
    fn member_state<'py>(&self, py: Python<'py>, i: usize) -> PyResult<Bound<'py, PyDict>> {
        self.window(py, i)?.__getstate__(py)
    }

    /// Restores estimator i's state from `member_state` (checked as `MovingHorizon.__setstate__`
    /// checks it; on error nothing changes).
    fn set_member_state(
        &mut self,
        py: Python<'_>,
        i: usize,
        state: Bound<'_, PyDict>,
    ) -> PyResult<()> {
        let mut w = self.window(py, i)?;
        w.__setstate__(state)?;
        match (&mut self.inner, w.model) {
            (Inner::Gp(b), Model::Gp(gp)) => {
                if let Some(m) = b.member_mut(i) {
                    m.estimator = w.core;
                    m.model = *gp;
                }
            }
            (Inner::Callback(b), _) => {
                if let Some(m) = b.member_mut(i) {
                    m.estimator = w.core;
                }
            }
            (Inner::Compiled(b), _) => {
                if let Some(m) = b.member_mut(i) {
                    m.estimator = w.core;
                }
            }
            (Inner::Gp(_), _) => return Err(PyValueError::new_err("internal: model kind")),
        }
        Ok(())
    }

    /// An independent copy (the GPs stay shared).
    fn __copy__(&self, py: Python<'_>) -> Self {
        Self {
            inner: match &self.inner {
                Inner::Gp(b) => Inner::Gp(b.clone()),
                Inner::Compiled(b) => Inner::Compiled(b.clone()),
                Inner::Callback(b) => Inner::Callback(b.clone()),
            },
            model: self.model.clone_ref(py),
        }
    }

    fn __deepcopy__(&self, py: Python<'_>, _memo: Bound<'_, PyAny>) -> Self {
        self.__copy__(py)
    }
}
