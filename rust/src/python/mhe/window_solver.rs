//! `WindowSolver`: the real-time solver's settings (given to `MovingHorizon`) and work buffers,
//! also used directly on a window set with `MovingHorizon.set_data` (tests, diagnostics).

use numpy::{PyArray1, PyArray2, PyReadonlyArray1};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyTuple;

use super::moving_horizon::PyMovingHorizon;
use crate::python::convert::{array2, slice1};
use crate::solver::{BoxLsqSolver, InteriorMode, SolverOptions};

/// Solver settings and work buffers: given to `MovingHorizon` as its settings, or used directly
/// on a window set with `MovingHorizon.set_data` (tests, diagnostics).
#[pyclass(name = "WindowSolver", module = "gpmhe._core")]
pub(crate) struct PyWindowSolver {
    pub(crate) solver: BoxLsqSolver,
    pub(crate) opts: SolverOptions,
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
