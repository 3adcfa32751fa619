//! The Levenberg-Marquardt damping of the active-set phase ([`LmState`]): λ, relative to the
//! Marquardt scaling D = diag H, starts at 0 and returns to 0 after well-predicted steps.
//!
//! Why 0 and not a small λ: when the residual weights differ by orders of magnitude (an MHE
//! window with near-zero process noise has process weights ~1e8 against output weights ~1),
//! diag H is set by the stiff terms while the directions that matter (trajectories the model
//! allows) have curvature ~1e-8 of it. Any λ above that, e.g. the customary 1e-6, shrinks the
//! steps along them a hundredfold, so a "nearly undamped" λ is no such thing. Damping is applied
//! only after a failure, and then sized by the failed step: from λ = 0 it restarts at the model's
//! curvature along that step relative to D (its Rayleigh quotient κ = sᵀHs / sᵀDs), which about
//! halves the step along it whatever the weights; from there Nielsen's update takes over, and λ
//! returns to 0 once it falls below 1e-3 of the value it restarted at.

use super::box_lsq::LAMBDA_MAX;

/// Damping below which λ is set to 0 after a well-predicted step, until a restart from 0 sets
/// the floor relative to the damping it restarted at.
const LAMBDA_MIN: f64 = 1e-12;
/// The floor after a restart at λ₀: λ below FLOOR·λ₀ is 0.1 % of the curvature along the failed
/// step (absolute floors fail at weight ratios beyond 1/LAMBDA_MIN, where κ itself is smaller).
const FLOOR: f64 = 1e-3;
/// Damping after a failure from λ = 0 when no curvature along a step is known (the Gauss-Newton
/// matrix was singular, or no candidate predicted a decrease).
pub(super) const LAMBDA_RESTART: f64 = 1e-6;

/// What the active-set phase carries from one iteration to the next.
pub(super) struct LmState {
    /// Marquardt damping λ (relative to the scaling [`super::BoxLsqSolver::scale`]).
    pub(super) lambda: f64,
    /// Nielsen's growth factor of λ after a failed step.
    pub(super) nu: f64,
    /// Consecutive steps whose effect was below J's rounding noise and that did not lower the
    /// projected gradient.
    pub(super) noise_failures: usize,
    /// Rounding noise of J: at least NOISE relative, raised when small steps show more (a GP
    /// with a large σ_f has variances σ_f² − ‖v‖² with large cancellation).
    pub(super) noise_est: f64,
    /// Whether an undamped step was rejected since the last accepted point (the `dtol` test may
    /// then stop on a damped step).
    pub(super) undamped_failed: bool,
    /// λ below this is set to 0.
    floor: f64,
}

impl LmState {
    pub(super) fn new() -> Self {
        LmState {
            lambda: 0.0,
            nu: 2.0,
            noise_failures: 0,
            noise_est: 0.0,
            undamped_failed: false,
            floor: LAMBDA_MIN,
        }
    }

    /// A point was accepted: the failure counters restart.
    pub(super) fn moved(&mut self) {
        self.noise_failures = 0;
        self.undamped_failed = false;
        self.nu = 2.0;
    }

    /// After an accepted step with gain ratio `rho` whose model curvature along it is `kappa`
    /// (sᵀHs / sᵀDs, NaN if unknown).
    pub(super) fn after_step(&mut self, rho: f64, kappa: f64) {
        self.lambda = if (0.75..=1.25).contains(&rho) {
            // The model predicted this step well: damping only slows the flat directions
            // (Marquardt's λ·diag H dwarfs their curvature), so drop it fast rather than by
            // Nielsen's 1/3 per step, down to none.
            self.lambda / 10.0
        } else if self.lambda == 0.0 {
            // Nielsen's factor 1 + x from λ = 0: x·κ (x = 1 for rho ≤ 0 halves the step).
            let x = (-(2.0 * rho.max(0.0) - 1.0).powi(3)).max(0.0);
            if kappa.is_finite() && x > 0.0 {
                self.floor = FLOOR * kappa;
                x * kappa
            } else {
                0.0
            }
        } else {
            self.lambda * (1.0 - (2.0 * rho - 1.0).powi(3)).max(1.0 / 3.0)
        };
        self.snap();
    }

    /// After an accepted step too small for J to measure its gain, judged by the projected
    /// gradient instead: cut to at most half (`pg_ratio` ≤ ½, a Newton-like step) lowers λ;
    /// otherwise the (noisy) gain ratio `rho` decides, clamped to [0, 1].
    pub(super) fn after_unmeasurable_step(&mut self, pg_ratio: f64, rho: f64, kappa: f64) {
        if pg_ratio <= 0.5 {
            self.lambda /= 3.0;
            self.snap();
        } else {
            self.after_step(rho.clamp(0.0, 1.0), kappa);
        }
    }

    /// After a step accepted only once corrected (module `correction`): the tangent step itself
    /// failed, so λ falls by Nielsen's 1/3 at most.
    pub(super) fn after_corrected_step(&mut self, rho: f64, kappa: f64) {
        if rho >= 0.75 {
            self.lambda /= 3.0;
            self.snap();
        } else {
            self.after_step(rho, kappa);
        }
    }

    /// λ ← λν, ν ← 2ν (Nielsen), or from λ = 0 to `restart` (the curvature κ along the failed
    /// step, else LAMBDA_RESTART); true when λ passed LAMBDA_MAX: no step can lower J.
    pub(super) fn damp_harder(&mut self, restart: f64) -> bool {
        if self.lambda == 0.0 {
            self.undamped_failed = true;
            self.lambda = if restart.is_finite() && restart > 0.0 {
                restart
            } else {
                LAMBDA_RESTART
            };
            self.floor = FLOOR * self.lambda;
        } else {
            self.lambda *= self.nu;
            self.nu *= 2.0;
        }
        self.lambda > LAMBDA_MAX
    }

    fn snap(&mut self) {
        if self.lambda < self.floor {
            self.lambda = 0.0;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn damping_leaves_zero_only_after_a_failure_and_then_by_the_step_curvature() {
        let mut st = LmState::new();
        st.after_step(1.0, 1e-9);
        assert_eq!(st.lambda, 0.0);
        st.after_step(0.5, 1e-9); // neither good nor bad: Nielsen keeps λ
        assert_eq!(st.lambda, 0.0);
        assert!(!st.damp_harder(1e-9));
        assert_eq!(st.lambda, 1e-9);
        assert!(st.undamped_failed);
        assert!(!st.damp_harder(1e-9));
        assert_eq!(st.lambda, 2e-9);
        st.moved();
        st.after_step(1.0, 1e-9);
        assert!((st.lambda - 2e-10).abs() < 1e-24);
        let mut st = LmState::new();
        st.after_step(-3.0, 4e-8); // accepted with a poor gain ratio from λ = 0
        assert_eq!(st.lambda, 4e-8);
        let mut st = LmState::new();
        assert!(!st.damp_harder(f64::NAN));
        assert_eq!(st.lambda, LAMBDA_RESTART);
        // At weight ratios of 1e14 the step curvature is ~1e-14: a well-predicted step lowers λ
        // tenfold, not to 0 as an absolute floor of 1e-12 would.
        let mut st = LmState::new();
        st.damp_harder(2e-14);
        st.moved();
        st.after_step(1.0, 2e-14);
        assert!((st.lambda - 2e-15).abs() < 1e-29);
        for _ in 0..3 {
            st.after_step(1.0, 2e-14);
        }
        assert_eq!(st.lambda, 0.0);
    }
}
