//! What the last update of a moving-horizon estimator reported: the arrival prior of its window,
//! the covariance estimate, the cost and the solver's statistics and message. The history holds
//! it (`history.rs`) and records it in the same step as the window, so the estimator's public
//! attributes are read from one place and an update either changes all of them or none.

use crate::error::{Error, Result};
use crate::solver::SolveReport;

/// See the module documentation.
#[derive(Debug, Clone, PartialEq)]
pub struct Outcome {
    /// The arrival prior of the last window's first node (n).
    pub x_prior: Vec<f64>,
    /// The covariance estimate of the newest node (n × n, row-major): the last one that was
    /// computable (the initial covariance before any).
    pub covariance: Vec<f64>,
    /// The optimal cost J of the last window.
    pub cost: f64,
    /// Whether the last window's solver reported convergence.
    pub success: bool,
    /// The solver's iterations and window evaluations.
    pub nit: usize,
    pub nfev: usize,
    /// The solver's final ‖z − Π(z − ∇J)‖∞ (NaN after a solver failure, 0 for SciPy's solvers).
    pub projected_gradient: f64,
    /// The solver's message (see `GPMHE.message`).
    pub message: String,
    /// Whether the last update was given no input and waits for it (`set_last_input`).
    pub input_pending: bool,
    /// The estimate and covariance of the newest node before the last update (what the
    /// innovation's prediction starts from, `innovation.rs`); NaN when not known.
    pub x_before: Vec<f64>,
    pub covariance_before: Vec<f64>,
    /// The covariance of every node of the last window (nodes × n × n, row-major blocks): the
    /// diagonal blocks of the Gauss-Newton covariance whose last block is `covariance`; NaN
    /// when that was not computable.
    pub window_covariance: Vec<f64>,
}

/// How a window was solved, for [`Outcome::record`]: by the Rust solver (its report or the error
/// that stopped it), or by another solver that reports its own statistics.
#[derive(Debug, Clone)]
pub enum Solved {
    Rust(std::result::Result<SolveReport, Error>),
    Other {
        success: bool,
        nit: usize,
        message: String,
    },
}

impl Outcome {
    /// The outcome before any update: at x̂(0) = x0 with covariance `covariance`.
    pub fn initial(x0: &[f64], covariance: Vec<f64>) -> Self {
        Self {
            x_prior: x0.to_vec(),
            covariance: covariance.clone(),
            cost: 0.0,
            success: true,
            nit: 0,
            nfev: 0,
            projected_gradient: 0.0,
            message: String::new(),
            input_pending: false,
            x_before: x0.to_vec(),
            covariance_before: covariance.clone(),
            window_covariance: covariance,
        }
    }

    /// The outcome of a solved window of `nodes` nodes that started from the estimate
    /// `x_before` (with `self`'s covariance), with the covariance blocks of its nodes
    /// `window_covariance`: its last block is the new covariance; None (H singular) keeps
    /// `self`'s covariance and gives NaN blocks.
    #[allow(clippy::too_many_arguments)]
    pub fn record(
        &self,
        x_prior: Vec<f64>,
        window_covariance: Option<Vec<f64>>,
        nodes: usize,
        x_before: Vec<f64>,
        cost: f64,
        solved: &Solved,
        input_pending: bool,
    ) -> Self {
        let nn = self.covariance.len();
        let (success, nit, nfev, projected_gradient, message) = match solved {
            Solved::Rust(Ok(s)) => (
                s.status.is_success(),
                s.nit,
                s.nfev,
                s.projected_gradient,
                format!(
                    "{} (projected gradient {}, {} interior its)",
                    s.status.as_str(),
                    scientific(s.projected_gradient),
                    s.interior_iterations
                ),
            ),
            Solved::Rust(Err(e)) => (false, 0, 1, f64::NAN, format!("solver raised: {e}")),
            Solved::Other {
                success,
                nit,
                message,
            } => (*success, *nit, 0, 0.0, message.clone()),
        };
        Self {
            x_prior,
            covariance: window_covariance.as_deref().map_or_else(
                || self.covariance.clone(),
                |b| last_block(b, self.covariance.len()),
            ),
            cost,
            success,
            nit,
            nfev,
            projected_gradient,
            message,
            input_pending,
            x_before,
            covariance_before: self.covariance.clone(),
            window_covariance: window_covariance.unwrap_or_else(|| vec![f64::NAN; nodes * nn]),
        }
    }

    /// Checks a restored outcome against the state dimension n (an error names the entry).
    pub fn check(&self, n: usize) -> Result<()> {
        crate::error::check_len("outcome_x_prior", &self.x_prior, n)?;
        crate::error::check_len("outcome_P", &self.covariance, n * n)?;
        crate::error::check_finite("outcome_x_prior", &self.x_prior)?;
        crate::error::check_finite("outcome_P", &self.covariance)?;
        crate::error::check_len("outcome_x_before", &self.x_before, n)?;
        crate::error::check_len("outcome_P_before", &self.covariance_before, n * n)?;
        if self.window_covariance.len() % (n * n) != 0 || self.window_covariance.is_empty() {
            return Err(Error::invalid(
                "outcome_P_window",
                format!("must hold whole {n}×{n} blocks"),
            ));
        }
        if self.cost.is_nan() {
            return Err(Error::invalid("outcome_cost", "is NaN"));
        }
        Ok(())
    }
}

/// The last block of a stack of blocks of `nn` values each (n × n covariances: nn = n²).
pub fn last_block(blocks: &[f64], nn: usize) -> Vec<f64> {
    blocks[blocks.len() - nn..].to_vec()
}

/// `v` with two decimals and a signed two-digit exponent, as Python's `format(v, ".2e")`
/// ("1.23e-07"), so messages read the same whichever solver wrote them.
fn scientific(v: f64) -> String {
    if !v.is_finite() {
        return match v {
            v if v.is_nan() => "nan".into(),
            v if v > 0.0 => "inf".into(),
            _ => "-inf".into(),
        };
    }
    let s = format!("{v:.2e}");
    match s.split_once('e') {
        Some((mantissa, exp)) => {
            let (sign, digits) = match exp.strip_prefix('-') {
                Some(d) => ('-', d),
                None => ('+', exp),
            };
            format!("{mantissa}e{sign}{digits:0>2}")
        }
        None => s,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_read_as_python_formats_them() {
        assert_eq!(scientific(1.2345e-7), "1.23e-07");
        assert_eq!(scientific(0.0), "0.00e+00");
        assert_eq!(scientific(-3.5e120), "-3.50e+120");
        assert_eq!(scientific(12.0), "1.20e+01");
        assert_eq!(scientific(f64::NAN), "nan");
    }

    #[test]
    fn a_singular_covariance_keeps_the_previous_one() {
        let first = Outcome::initial(&[1.0], vec![2.0]);
        let solved = Solved::Other {
            success: true,
            nit: 3,
            message: "ok".into(),
        };
        let next = first.record(vec![0.5], None, 2, vec![1.0], 1.5, &solved, false);
        assert_eq!(next.covariance, vec![2.0]);
        assert_eq!((next.nit, next.nfev, next.cost), (3, 0, 1.5));
        // The window's blocks are unknown, and said so; what the update started from is kept.
        assert!(next.window_covariance.len() == 2 && next.window_covariance[0].is_nan());
        assert_eq!((next.x_before[0], next.covariance_before[0]), (1.0, 2.0));
        let blocks = Some(vec![4.0, 3.0]);
        let next = next.record(vec![0.5], blocks, 2, vec![0.7], 1.0, &solved, true);
        assert_eq!(next.covariance, vec![3.0]);
        assert_eq!(next.window_covariance, vec![4.0, 3.0]);
        assert_eq!((next.x_before[0], next.covariance_before[0]), (0.7, 2.0));
        assert!(next.input_pending);
    }
}
