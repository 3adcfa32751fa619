//! The solver's settings ([`SolverOptions`], [`InteriorMode`]) and what a solve reports
//! ([`SolveReport`], [`Status`]).

use crate::error::{Error, Result};

/// When the interior (barrier) phase runs before the active-set phase.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum InteriorMode {
    /// When some free variable of the start lies within `interior_zone` of a bound (the
    /// transient from a poor prior; a warm start well inside the box needs no barrier).
    Auto,
    /// Whenever some variable has a finite bound.
    Always,
    /// Never: a plain projected active-set Levenberg-Marquardt method.
    Never,
}

/// Solver settings. The defaults suit the GP-MHE window (costs of order 1–1000).
#[derive(Debug, Clone)]
pub struct SolverOptions {
    /// Cap on iterations (both phases together; an iteration is one linear solve).
    pub max_iter: usize,
    /// Stop when ‖z − P(z − ∇J)‖∞ ≤ gtol (P: projection on the box).
    pub gtol: f64,
    /// Stop when the projected step satisfies ‖Δz‖∞ ≤ xtol·(xtol + ‖z‖∞).
    pub xtol: f64,
    /// Stop when an accepted step lowers the cost by at most ftol·J.
    pub ftol: f64,
    /// Stop when the next undamped, unclipped Gauss-Newton step Δ predicts a decrease of J of
    /// at most dtol (a damped step only once the undamped one has failed since the last move): pred = ½ΔᵀHΔ (H = 2JᵀJ on the free variables), the Gauss-Newton
    /// decrement, so the point is within √(2·dtol) of the model's minimiser in the H-norm and
    /// its cost within ~dtol of the minimum. 0 disables the test (run to `gtol`). The default
    /// 1e-2 is statistical: GPMHE's J is 4× a negative log-likelihood, so such a step is
    /// √(dtol/2) ≈ 0.07 standard deviations of the window's Laplace posterior long.
    pub dtol: f64,
    pub interior: InteriorMode,
    /// `Auto` runs the interior phase when a free variable is within interior_zone·w of a bound
    /// (w = upper − lower, or max(1, |bound|) for one-sided bounds). The default 1e-5 means "on
    /// the bound" (GPMHE's warm start keeps 1e-6·w away from it): starts near but off a bound
    /// are handled well by the active-set phase, and late in a batch-reactor run the true x1
    /// sits close to its bound, where a wider zone ran the barrier phase at almost every step
    /// (0.01 did: 2-3x the evaluations at the same RMSE).
    pub interior_zone: f64,
    /// First and last barrier parameter of the interior phase.
    pub mu_init: f64,
    pub mu_final: f64,
}

impl Default for SolverOptions {
    fn default() -> Self {
        SolverOptions {
            max_iter: 100,
            gtol: 1e-6,
            xtol: 1e-12,
            ftol: 1e-15,
            dtol: 1e-2,
            interior: InteriorMode::Auto,
            interior_zone: 1e-5,
            mu_init: 0.1,
            mu_final: 1e-5,
        }
    }
}

impl SolverOptions {
    /// Checks every setting, naming the bad one.
    pub fn validate(&self) -> Result<()> {
        let positive = |name: &str, v: f64| {
            if v.is_finite() && v >= 0.0 {
                Ok(())
            } else {
                Err(Error::invalid(
                    name,
                    format!("must be finite and >= 0, got {v}"),
                ))
            }
        };
        positive("gtol", self.gtol)?;
        positive("xtol", self.xtol)?;
        positive("ftol", self.ftol)?;
        positive("dtol", self.dtol)?;
        positive("interior_zone", self.interior_zone)?;
        if !(self.mu_init.is_finite() && self.mu_init > 0.0) {
            return Err(Error::invalid("mu_init", "must be finite and > 0"));
        }
        if !(self.mu_final.is_finite() && self.mu_final > 0.0 && self.mu_final <= self.mu_init) {
            return Err(Error::invalid(
                "mu_final",
                "must be finite, > 0 and <= mu_init",
            ));
        }
        Ok(())
    }
}

/// Why the solver stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Status {
    /// Projected gradient below `gtol`: a first-order (KKT) point.
    GradientTolerance,
    /// The step became smaller than `xtol`.
    StepTolerance,
    /// An accepted step lowered the cost by less than `ftol` relative.
    CostTolerance,
    /// The next (nearly undamped) Gauss-Newton step predicts a decrease of J below J's
    /// rounding noise as estimated by the problem, and the projected gradient is within a
    /// small multiple of the gradient's rounding noise (GPs fitted to a large σ_f): neither the
    /// cost nor the gradient can verify further progress.
    NoiseFloor,
    /// The next undamped, unclipped Gauss-Newton step (or, after it failed, a lightly damped
    /// one) predicts a decrease of J of at most `dtol`: what is left to gain is below the
    /// requested accuracy.
    DecrementTolerance,
    /// `max_iter` reached.
    MaxIterations,
    /// No step could lower the cost (damping exhausted); the best point found is returned.
    NoProgress,
}

impl Status {
    pub fn as_str(&self) -> &'static str {
        match self {
            Status::GradientTolerance => "gradient-tolerance",
            Status::StepTolerance => "step-tolerance",
            Status::CostTolerance => "cost-tolerance",
            Status::NoiseFloor => "noise-floor",
            Status::DecrementTolerance => "decrement-tolerance",
            Status::MaxIterations => "max-iterations",
            Status::NoProgress => "no-progress",
        }
    }
    /// True for the three convergence criteria.
    pub fn is_success(&self) -> bool {
        matches!(
            self,
            Status::GradientTolerance
                | Status::StepTolerance
                | Status::CostTolerance
                | Status::NoiseFloor
                | Status::DecrementTolerance
        )
    }
}

/// The outcome of one solve; the solution itself is written into the caller's `z`.
#[derive(Debug, Clone)]
pub struct SolveReport {
    pub status: Status,
    /// J at the returned z.
    pub cost: f64,
    /// ‖z − P(z − ∇J)‖∞ at the returned z.
    pub projected_gradient: f64,
    /// Iterations of both phases (linear solves attempted).
    pub nit: usize,
    /// Iterations spent in the interior phase.
    pub interior_iterations: usize,
    /// Problem evaluations.
    pub nfev: usize,
}
