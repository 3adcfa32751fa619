//! The pyo3 binding, the only code that knows Python: one file per area (gp, sparse, mhe, bank, rgp), with the
//! array conversions (`convert`) and the error mapping (`error`) in one place each. A method
//! converts its arguments, calls the core (without the GIL around the numerics) and maps the
//! error; the algorithms live in the core modules.

mod bank;
mod convert;
mod error;
mod gp;
mod mhe;
mod rgp;
mod sparse;

use pyo3::prelude::*;

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("NumericalError", m.py().get_type::<error::NumericalError>())?;
    m.add_function(wrap_pyfunction!(gp::se_ard_kernel, m)?)?;
    // GP
    m.add_class::<gp::PyMultiGp>()?;
    m.add_function(wrap_pyfunction!(gp::gp_log_marginal_likelihood, m)?)?;
    m.add_class::<sparse::PySparseMultiGp>()?;
    m.add_function(wrap_pyfunction!(sparse::sparse_gp_objective, m)?)?;
    m.add_function(wrap_pyfunction!(sparse::py_select_inducing, m)?)?;
    // MHE window
    m.add_class::<mhe::PyStageModel>()?;
    m.add_class::<mhe::PyMovingHorizon>()?;
    m.add_class::<mhe::PyArrivalMean>()?;
    m.add_class::<mhe::PyArrivalWeight>()?;
    m.add_class::<bank::PyEstimatorBank>()?;
    // Window solver
    m.add_class::<mhe::PyWindowSolver>()?;
    m.add_class::<rgp::RgpCore>()?;
    m.add_class::<rgp::RgpEkfCore>()?;
    Ok(())
}
