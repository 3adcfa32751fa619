//! gpmhe's numerical core: Gaussian-process regression (exact in `gp.rs`, sparse in `sparse/`,
//! one interface in `gp_model.rs`), the GP-MHE window problem and its solver, and the recursive GP
//! inside an EKF. Pure Rust; the pyo3 binding lives in `python/` behind the
//! `python` cargo feature, so `cargo test` needs no Python.

pub mod compiled;
pub mod error;
pub mod gp;
pub mod gp_model;
pub mod interrupt;
pub mod kernel;
mod linalg;
pub mod mean;
pub mod mhe;
pub mod rgp;
pub mod solver;
pub mod sparse;

#[cfg(feature = "python")]
mod python;

pub use error::{Error, Result};
