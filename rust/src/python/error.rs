//! Error mapping, in one place: the core's `InvalidInput` becomes `ValueError` (naming the
//! argument), `Numerical` becomes `gpmhe.NumericalError` (a `RuntimeError`), `Interrupted`
//! the Python exception that interrupted the core (see [`detach_interruptible`]), else
//! `KeyboardInterrupt`. A compiled model's value out of range becomes the
//! `gpmhe.models.base.ModelDomainError` a Python model raises for it ([`model_domain_error`]).

use std::cell::RefCell;
use std::rc::Rc;

use pyo3::create_exception;
use pyo3::exceptions::{PyKeyboardInterrupt, PyRuntimeError, PyValueError};
use pyo3::prelude::*;

use crate::error::Error;
use crate::interrupt;

create_exception!(
    gpmhe._core,
    NumericalError,
    PyRuntimeError,
    "A numerical failure on valid input (e.g. a matrix not positive definite after jitter)."
);

impl From<Error> for PyErr {
    fn from(err: Error) -> PyErr {
        match err {
            Error::InvalidInput { .. } => PyValueError::new_err(err.to_string()),
            Error::Numerical(_) => NumericalError::new_err(err.to_string()),
            Error::Interrupted(msg) => PyKeyboardInterrupt::new_err(msg),
        }
    }
}

/// `err` (a compiled model's value out of range) as the `ModelDomainError` a Python model's
/// callback raises for the same value, so that both kinds of model fail alike.
pub(super) fn model_domain_error(py: Python<'_>, err: Error) -> PyErr {
    let msg = match &err {
        Error::Numerical(msg) => msg.clone(),
        other => other.to_string(),
    };
    match py
        .import("gpmhe.models.base")
        .and_then(|m| m.getattr("ModelDomainError"))
        .and_then(|cls| cls.call1((msg,)))
    {
        Ok(exc) => PyErr::from_value(exc),
        Err(_) => err.into(),
    }
}

/// Runs `f` without the GIL, with the core's interrupt check (`crate::interrupt`) set to
/// re-attach and run Python's signal handlers (`PyErr_CheckSignals`) at most every
/// `interrupt::INTERVAL` of work: Ctrl-C (or any exception a signal handler raises) stops the
/// core's long loops and is re-raised here as it was raised. Short calls never take the GIL.
pub(super) fn detach_interruptible<T, F>(py: Python<'_>, f: F) -> PyResult<T>
where
    T: Send,
    F: FnOnce() -> crate::Result<T> + Send,
{
    match py.detach(move || interruptible(f)) {
        (Ok(v), _) => Ok(v),
        (Err(e), raised) => Err(raised.unwrap_or_else(|| e.into())),
    }
}

/// Runs `f` on this thread (with or without the GIL) with the core's interrupt check set to run
/// Python's signal handlers (attaching if need be); returns f's result and, if the check stopped
/// it, the exception the handler raised.
pub(super) fn interruptible<T>(
    f: impl FnOnce() -> crate::Result<T>,
) -> (crate::Result<T>, Option<PyErr>) {
    let raised: Rc<RefCell<Option<PyErr>>> = Rc::default();
    let slot = Rc::clone(&raised);
    let guard = interrupt::install(move || {
        Python::attach(|py| py.check_signals()).map_err(|e| {
            let msg = e.to_string();
            *slot.borrow_mut() = Some(e);
            Error::interrupted(msg)
        })
    });
    let result = f();
    drop(guard);
    let raised = match result {
        Err(Error::Interrupted(_)) => raised.borrow_mut().take(),
        _ => None,
    };
    (result, raised)
}
