//! The moving-horizon estimator's Python classes, one file each: `StageModel`
//! (`stage_model.rs`), `MovingHorizon` (`moving_horizon.rs`, how it reaches the core in
//! `run.rs`, its copies and pickles in `pickle.rs`), `WindowSolver` (`window_solver.rs`) and the arrival cost's settings
//! `ArrivalMean`, `ArrivalWeight` (`arrival.rs`).

mod arrival;
mod moving_horizon;
mod pickle;
mod run;
mod stage_model;
mod window_solver;

pub(crate) use arrival::{PyArrivalMean, PyArrivalWeight};
pub(crate) use moving_horizon::PyMovingHorizon;
pub(crate) use stage_model::{CallbackModel, Model, PyStageModel};
pub(crate) use window_solver::PyWindowSolver;
