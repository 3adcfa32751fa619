//! The MHE window and its solver.

use numpy::{PyArray2, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use super::convert::{array2, slice1, slice2};
use super::gp::PyMultiGp;
use crate::error::{check_finite, check_len, Error};

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
