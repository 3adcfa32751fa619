//! The moving-horizon estimator (`crate::mhe::MovingHorizon`) as `MovingHorizon`: a method
//! converts its arguments, runs the core with the model (`Model`, `stage_model.rs`) and maps the
//! error. An exception other than a numerical one stops the update (the estimator stays as it
//! was) and is re-raised. How a method reaches the core with the model: `run.rs`; copies and
//! pickles: `pickle.rs`.

use numpy::{PyArray1, PyArray2, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyTuple};

use super::arrival::{PyArrivalMean, PyArrivalWeight};
use super::pickle;
use super::stage_model::{Model, PyStageModel};
use super::window_solver::PyWindowSolver;
use crate::error::{check_finite, check_len};
use crate::mhe::{Arrival, Form, Loss, MovingHorizon, Solved, Step, WindowProblem};
use crate::python::convert::{array2, slice1, slice2};
use crate::solver::{BoxLsqSolver, SolverOptions};

type Arr1<'py> = Bound<'py, PyArray1<f64>>;
type Arr2<'py> = Bound<'py, PyArray2<f64>>;

/// A moving-horizon estimator (see `gpmhe.GPMHE`, which validates its settings and input and
/// holds the public attributes): `update(u, y)` is one whole update in one call.
#[pyclass(name = "MovingHorizon", module = "gpmhe._core")]
pub(crate) struct PyMovingHorizon {
    pub(crate) core: MovingHorizon,
    pub(crate) model: Model,
    /// The learned model's evaluation cache before `prepare` staged a window (for `abandon`).
    pub(crate) staged_cache: Option<[Vec<f64>; 9]>,
}

#[pymethods]
impl PyMovingHorizon {
    /// Whether the model runs without Python (the learned GPs or a compiled CasADi model).
    #[getter]
    fn native(&self) -> bool {
        !matches!(self.model, Model::Callback { .. })
    }

    /// An estimator on `model` (a `StageModel`). `q0`, `r0`: Q0 and R0, their diagonals or the
    /// flattened matrices; `p2_sqrt`: S with P2 = SᵀS; `filtering`: the form; `horizon`: M;
    /// `x0`: x̂(0) (zeros if None); `lower`, `upper`: the state box (±inf if None); `solver`: the
    /// solver settings; `arrival_mean` and `arrival_weight`
    /// ("constant" or "ekf"): the arrival cost; `loss` ("squared", "huber", "cauchy") and
    /// `loss_scale`: the penalty of the whitened output residuals.
    #[new]
    #[allow(clippy::too_many_arguments)]
    #[pyo3(signature = (model, eta, q0, r0, p2_sqrt, filtering, horizon=1, x0=None, lower=None,
                        upper=None, solver=None, arrival_mean=PyArrivalMean::Estimate,
                        arrival_weight=PyArrivalWeight::Constant, loss="squared", loss_scale=1.0))]
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
        arrival_mean: PyArrivalMean,
        arrival_weight: PyArrivalWeight,
        loss: &str,
        loss_scale: f64,
    ) -> PyResult<Self> {
        let arrival = Arrival {
            mean: arrival_mean.into(),
            weight: arrival_weight.into(),
        };
        let (n, m, p) = model.model.dims();
        let form = match filtering {
            true => Form::Filtering,
            false => Form::Prediction,
        };
        let (p2, _, _) = slice2("P2", &p2_sqrt)?;
        let (q0, r0) = (slice1("Q0", &q0)?, slice1("R0", &r0)?);
        let mut problem = WindowProblem::new(n, m, p, eta, q0, r0, p2, form)?;
        problem.set_loss(Loss::from_name(loss, loss_scale)?);
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

    /// How many times `set_weights` replaced weights since construction (a copy keeps the
    /// count).
    #[getter]
    fn weights_version(&self) -> u64 {
        self.core.weights_version()
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
    /// Makes the estimator learn the model's global variables (a `StageModel.learning`: the
    /// f-GPs' inducing outputs) from the prior N(g0, sigma0), drifting by a random walk of
    /// variance `drift` per step. Before the first update only; on error nothing changes.
    fn enable_learning(
        &mut self,
        g0: PyReadonlyArray1<'_, f64>,
        sigma0: PyReadonlyArray2<'_, f64>,
        drift: f64,
    ) -> PyResult<()> {
        let (s0, _, _) = slice2("sigma0", &sigma0)?;
        self.core.enable_learning(slice1("g0", &g0)?, s0, drift)?;
        Ok(())
    }

    /// The learning state: None if the estimator does not learn, else (g (n_g,), its covariance
    /// (n_g, n_g)) after the last update (the prior before any).
    #[getter]
    fn learning<'py>(&self, py: Python<'py>) -> PyResult<Option<(Arr1<'py>, Arr2<'py>)>> {
        let Some(l) = self.core.learning() else {
            return Ok(None);
        };
        let s = l.state();
        let ng = s.g.len();
        Ok(Some((
            PyArray1::from_slice(py, &s.g),
            array2(py, s.g_cov.clone(), ng, ng)?,
        )))
    }

    fn reset(&mut self, x0: PyReadonlyArray1<'_, f64>) -> PyResult<()> {
        self.core.reset(slice1("x0", &x0)?)?;
        self.staged_cache = None;
        Ok(())
    }

    /// One whole update with u(t) (None: not known yet, see `MovingHorizon::prepare` in the
    /// core), y(t) (None: not measured), its covariance `r` (p or p² values; None: R0) and
    /// `u_last`, the last input row as this sample completes it (None: as recorded); what it
    /// reports is read from the getters below. On error the estimator is unchanged.
    #[pyo3(signature = (u, y=None, r=None, u_last=None))]
    fn update(
        &mut self,
        py: Python<'_>,
        u: Option<PyReadonlyArray1<'_, f64>>,
        y: Option<PyReadonlyArray1<'_, f64>>,
        r: Option<PyReadonlyArray1<'_, f64>>,
        u_last: Option<PyReadonlyArray1<'_, f64>>,
    ) -> PyResult<()> {
        let step = Step {
            u: u.as_ref().map(|u| slice1("u", u)).transpose()?,
            y: y.as_ref().map(|y| slice1("y", y)).transpose()?,
            r: r.as_ref().map(|r| slice1("R", r)).transpose()?,
            u_last: u_last.as_ref().map(|u| slice1("u_last", u)).transpose()?,
        };
        self.run(py, |core, model| core.update_step(model, step))?;
        Ok(())
    }

    /// The largest age `add_delayed` accepts now (0 while no older output is in the window).
    #[getter]
    fn max_delay(&self) -> usize {
        self.core.history().max_delay().unwrap_or(0)
    }

    /// Records an output `y` (NaN: channels not in it) measured `age` steps before the newest
    /// one, with its covariance `r` (None: R0), for the windows from the next update on. On
    /// error nothing changes.
    #[pyo3(signature = (y, age, r=None))]
    fn add_delayed(
        &mut self,
        y: PyReadonlyArray1<'_, f64>,
        age: usize,
        r: Option<PyReadonlyArray1<'_, f64>>,
    ) -> PyResult<()> {
        let r = r.as_ref().map(|r| slice1("R", r)).transpose()?;
        self.core.add_delayed(slice1("y", &y)?, age, r)?;
        self.staged_cache = None;
        Ok(())
    }

    /// Stages the next window with u(t), y(t) without recording it; returns (z0, lower,
    /// upper): the warm start and the box of the stacked window states. The window methods
    /// (`cost`, ...) then evaluate it; `commit` records a solution.
    #[pyo3(signature = (u, y=None, r=None, u_last=None))]
    fn prepare<'py>(
        &mut self,
        py: Python<'py>,
        u: Option<PyReadonlyArray1<'py, f64>>,
        y: Option<PyReadonlyArray1<'py, f64>>,
        r: Option<PyReadonlyArray1<'py, f64>>,
        u_last: Option<PyReadonlyArray1<'py, f64>>,
    ) -> PyResult<(Arr1<'py>, Arr1<'py>, Arr1<'py>)> {
        let step = Step {
            u: u.as_ref().map(|u| slice1("u", u)).transpose()?,
            y: y.as_ref().map(|y| slice1("y", y)).transpose()?,
            r: r.as_ref().map(|r| slice1("R", r)).transpose()?,
            u_last: u_last.as_ref().map(|u| slice1("u_last", u)).transpose()?,
        };
        if let Model::Gp(gp) = &self.model {
            if self.staged_cache.is_none() {
                self.staged_cache = Some(gp.cache());
            }
        }
        let z0 = self.run(py, |core, model| core.prepare_step(model, step))?;
        let (lo, hi) = self.core.bounds();
        Ok((
            PyArray1::from_vec(py, z0),
            PyArray1::from_slice(py, lo),
            PyArray1::from_slice(py, hi),
        ))
    }

    /// Records the staged window's solution z with how another solver found it: its `cost`
    /// (None: J(z) evaluated here), `success`, `nit`, `message` and the covariance blocks of the
    /// window's nodes `P_window` (nodes·n·n, flattened; the last block is the estimate's; None:
    /// not computable, the previous covariance is kept). Returns (x_window (nodes, n),
    /// x_prior). On error nothing changes.
    #[pyo3(signature = (z, cost=None, success=true, nit=0, message=String::new(), P_window=None))]
    #[allow(non_snake_case, clippy::too_many_arguments)]
    fn commit<'py>(
        &mut self,
        py: Python<'py>,
        z: PyReadonlyArray1<'py, f64>,
        cost: Option<f64>,
        success: bool,
        nit: usize,
        message: String,
        P_window: Option<PyReadonlyArray1<'py, f64>>,
    ) -> PyResult<(Arr2<'py>, Arr1<'py>)> {
        let z = slice1("z", &z)?.to_vec();
        let blocks = P_window
            .as_ref()
            .map(|a| slice1("P_window", a))
            .transpose()?
            .map(<[f64]>::to_vec);
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
            core.commit(model, z, blocks, cost, &solved)
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

    /// The covariance of every node of the last window (nodes, n, n; NaN when not computable),
    /// flattened.
    #[getter]
    fn window_covariance<'py>(&self, py: Python<'py>) -> Arr1<'py> {
        PyArray1::from_slice(py, &self.core.history().outcome().window_covariance)
    }

    /// The newest sample's innovation, computed with the model at the first read after a change
    /// (see `innovation.rs` in the core), then kept: (ν (p,), S (p, p), NIS, log-likelihood,
    /// measured channels).
    #[allow(clippy::type_complexity)]
    fn innovation<'py>(
        &mut self,
        py: Python<'py>,
    ) -> PyResult<(Arr1<'py>, Arr2<'py>, f64, f64, usize)> {
        let p = self.core.problem().dim_y();
        let inn = match self.core.kept_innovation() {
            Some(inn) => inn.clone(),
            None => self.read(py, |core, model| core.innovation(model))?,
        };
        Ok((
            PyArray1::from_vec(py, inn.nu),
            array2(py, inn.s, p, p)?,
            inn.nis,
            inn.log_likelihood,
            inn.measured,
        ))
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

    /// The Gauss-Newton Hessian 2JᵀJ at z as a dense (n_nodes·n + n_g)² array (n_g: the global
    /// variables of an estimator that learns).
    fn gn_hessian<'py>(
        &mut self,
        py: Python<'py>,
        z: PyReadonlyArray1<'py, f64>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let z = slice1("z", &z)?;
        let (h, nv) = self.run(py, |core, model| {
            let ev = core.evaluate(model, z, true)?;
            Ok((ev.dense_gauss_newton(), ev.n_vars()))
        })?;
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

    /// The discount of every residual row at z (η^{M_t} for the arrival prior's rows,
    /// η^{M_t−1−i} for the rows of the stage at node i, 1 for the newest node).
    fn row_discounts<'py>(
        &mut self,
        py: Python<'py>,
        z: PyReadonlyArray1<'py, f64>,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let z = slice1("z", &z)?;
        let w = self.run(py, |core, model| core.row_discounts(model, z))?;
        Ok(PyArray1::from_vec(py, w))
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
            .add(
                (
                    PyArrivalMean::from(self.core.arrival().mean),
                    PyArrivalWeight::from(self.core.arrival().weight),
                    p.loss().name_and_scale().0,
                    p.loss().name_and_scale().1,
                )
                    .into_pyobject(py)?,
            )?;
        let cls = py.get_type::<Self>();
        (cls, args, self.__getstate__(py)?).into_pyobject(py)
    }

    /// The estimator's state (see `pickle::get_state`).
    pub(crate) fn __getstate__<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        pickle::get_state(py, &self.core, &self.model)
    }

    /// Restores a state from `__getstate__` of an estimator with the same settings. Every
    /// entry is checked (a ValueError names it); on error nothing changes.
    pub(crate) fn __setstate__(&mut self, state: Bound<'_, PyDict>) -> PyResult<()> {
        if let Some(gp) = pickle::set_state(&state, &mut self.core, &self.model)? {
            self.model = Model::Gp(Box::new(gp));
        }
        self.staged_cache = None;
        Ok(())
    }
}
