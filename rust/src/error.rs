//! The one error type of the numerical core.
//!
//! `InvalidInput` is the user's fault (shapes, NaN/inf, non-positive parameters) and becomes a
//! Python `ValueError` naming the argument; `Numerical` is a failure of the mathematics on valid
//! input (a matrix that stays indefinite after the jitter policy, a singular system) and becomes
//! `gpmhe.NumericalError`.

use thiserror::Error;

#[derive(Debug, Clone, PartialEq, Error)]
pub enum Error {
    #[error("{arg}: {msg}")]
    InvalidInput { arg: String, msg: String },
    #[error("{0}")]
    Numerical(String),
}

pub type Result<T> = std::result::Result<T, Error>;

impl Error {
    /// A bad-input error that names the offending argument.
    pub fn invalid(arg: impl Into<String>, msg: impl Into<String>) -> Self {
        Error::InvalidInput {
            arg: arg.into(),
            msg: msg.into(),
        }
    }

    pub fn numerical(msg: impl Into<String>) -> Self {
        Error::Numerical(msg.into())
    }
}

/// Fails with `InvalidInput` naming `arg` if any value is NaN or infinite.
pub fn check_finite(arg: &str, values: &[f64]) -> Result<()> {
    match values.iter().position(|v| !v.is_finite()) {
        None => Ok(()),
        Some(i) => Err(Error::invalid(
            arg,
            format!("contains a non-finite value at flat index {i}"),
        )),
    }
}

/// Fails with `InvalidInput` naming `arg` unless `values.len() == expected`.
pub fn check_len(arg: &str, values: &[f64], expected: usize) -> Result<()> {
    if values.len() == expected {
        Ok(())
    } else {
        Err(Error::invalid(
            arg,
            format!("expected {expected} values, got {}", values.len()),
        ))
    }
}
