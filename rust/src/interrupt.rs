//! Interrupt checks for long loops: a caller (the Python binding) installs a check for the
//! current thread for the duration of a call ([`install`]); the core's long loops (solver
//! iterations, batches of RGP updates, GP constructions) call [`check`] between units of work.
//! [`check`] runs the installed check at most once every [`INTERVAL`], so short calls never run
//! it and long ones stop within about that time; without an installed check it does nothing.
//! The check's error (normally `Error::Interrupted`) stops the loop and reaches the caller, which
//! leaves the object as it was before the call.

use std::cell::RefCell;
use std::time::{Duration, Instant};

use crate::error::Result;

/// The longest stretch of work between two runs of the installed check.
pub const INTERVAL: Duration = Duration::from_millis(50);

type CheckFn = Box<dyn FnMut() -> Result<()>>;

struct Hook {
    check: CheckFn,
    next: Instant,
}

thread_local! {
    static HOOK: RefCell<Option<Hook>> = const { RefCell::new(None) };
}

/// Restores the previously installed check (if any) when dropped.
#[must_use = "the check is removed when the guard is dropped"]
pub struct Guard {
    prev: Option<Hook>,
}

impl Drop for Guard {
    fn drop(&mut self) {
        let prev = self.prev.take();
        HOOK.with(|h| *h.borrow_mut() = prev);
    }
}

/// Installs `check` for the current thread until the guard is dropped; its first run is one
/// [`INTERVAL`] from now.
pub fn install(check: impl FnMut() -> Result<()> + 'static) -> Guard {
    let hook = Hook {
        check: Box::new(check),
        next: Instant::now() + INTERVAL,
    };
    let prev = HOOK.with(|h| h.borrow_mut().replace(hook));
    Guard { prev }
}

/// Runs the installed check if one [`INTERVAL`] has passed since it last ran; Ok otherwise.
pub fn check() -> Result<()> {
    // Taken out while it runs: the check may run code (a Python signal handler) that calls back
    // into the core and installs a check of its own.
    let due = HOOK.with(|h| {
        let mut h = h.borrow_mut();
        match h.as_ref() {
            Some(hook) if Instant::now() >= hook.next => h.take(),
            _ => None,
        }
    });
    let Some(mut hook) = due else {
        return Ok(());
    };
    let r = (hook.check)();
    hook.next = Instant::now() + INTERVAL;
    HOOK.with(|h| {
        let mut h = h.borrow_mut();
        if h.is_none() {
            *h = Some(hook);
        }
    });
    r
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::Error;

    #[test]
    fn check_runs_the_hook_after_the_interval_and_the_guard_removes_it() {
        assert!(check().is_ok());
        {
            let _g = install(|| Err(Error::interrupted("stop")));
            assert!(check().is_ok(), "not due yet");
            std::thread::sleep(INTERVAL + Duration::from_millis(5));
            assert_eq!(check(), Err(Error::interrupted("stop")));
            assert!(check().is_ok(), "not due again yet");
        }
        std::thread::sleep(INTERVAL + Duration::from_millis(5));
        assert!(check().is_ok());
    }
}
