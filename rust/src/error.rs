//! The one error type of the numerical core.
//!
//! `InvalidInput` is the user's fault (shapes, NaN/inf, non-positive parameters) and becomes a
//! Python `ValueError` naming the argument; `Numerical` is a failure of the mathematics on valid
//! input (a matrix that stays indefinite after the jitter policy, a singular system) and becomes
//! `gpmhe.NumericalError`. `Interrupted` is neither: the computation was stopped from outside
//! (a signal such as Ctrl-C, or an exception raised by user code that is not a numerical
//! failure); it is never retried or treated as a bad trial point, and the binding re-raises the
//! original Python exception.

use thiserror::Error;

#[derive(Debug, Clone, PartialEq, Error)]
pub enum Error {
    #[error("{arg}: {msg}")]
    InvalidInput { arg: String, msg: String },
    #[error("{0}")]
    Numerical(String),
    #[error("interrupted: {0}")]
    Interrupted(String),
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

    pub fn interrupted(msg: impl Into<String>) -> Self {
        Error::Interrupted(msg.into())
    }

    /// The cost to use for a failed evaluation at a trial point: +∞ (the point is rejected) for
    /// a numerical failure, the error itself for anything else (bad model output, an interrupt),
    /// which must stop the computation.
    pub fn as_trial_cost(r: Result<f64>) -> Result<f64> {
        match r {
            Err(Error::Numerical(_)) => Ok(f64::INFINITY),
            other => other,
        }
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

/// The largest magnitude accepted in a value the core squares (gpmhe._validation.MAX_ABS in
/// Python): beyond it squares overflow f64 (whose largest square root is about 1.3e154).
pub const MAX_ABS: f64 = 1e150;

/// Fails with `InvalidInput` naming `arg` if any value is NaN, infinite or of magnitude above
/// [`MAX_ABS`] (for results of user functions, which Python cannot check before the core).
pub fn check_magnitude(arg: &str, values: &[f64]) -> Result<()> {
    check_finite(arg, values)?;
    match values.iter().position(|v| v.abs() > MAX_ABS) {
        None => Ok(()),
        Some(i) => Err(Error::invalid(
            arg,
            format!("contains a value of magnitude > {MAX_ABS:e} (its square overflows) at flat index {i}"),
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
