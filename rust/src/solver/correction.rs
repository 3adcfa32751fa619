//! The curvature correction of the active-set phase: a rejected step along a stiff, curved
//! valley of J is followed by a restoring step before it is given up.
//!
//! When some residuals carry far larger weights than others (an MHE window with near-zero
//! process noise: process weights ~1e8 against output weights ~1), J has narrow valleys where
//! the heavy residuals vanish, curved wherever the model is nonlinear. A Gauss-Newton step runs
//! along the valley's tangent and leaves it by O(‖s‖²), which the heavy weights turn into a cost
//! far above J(z): the step is rejected however good its direction (the Maratos effect of
//! penalty methods), and a monotone method is left crawling along the valley with steps short
//! enough for that excess to stay below their gain.
//!
//! The correction takes the derivatives at the rejected trial point and solves for a step that
//! restores the heavy residuals there without moving along the valley again: the trial's own
//! Gauss-Newton step damped by λ_r = √κ, where κ = sᵀHs / sᵀDs is the model's curvature along
//! the rejected step relative to the Marquardt scaling D = diag H. The stiff directions have
//! curvature ~1 relative to D (they set its diagonal) and the valley's ~κ, so λ_r ≫ κ freezes the
//! valley directions while λ_r ≪ 1 leaves the restoring ones undamped. The corrected point is
//! accepted if it lowers J by the usual fraction of the original step's predicted decrease;
//! while it does not but the restoring steps converge (each cuts the excess of J over J(z)
//! tenfold), up to RESTORE_STEPS of them are taken, from the derivatives at each new point
//! (at weight ratios of 1e12 one step seldom suffices). It
//! is tried only for steps along directions at least 1/STIFF times flatter than the diagonal
//! (κ < STIFF), where the separation exists; elsewhere a rejected step is handled as before.

// Index loops touch several parallel arrays and read better than zipped iterator chains.
#![allow(clippy::needless_range_loop)]

use super::box_lsq::{Limits, Progress, ARMIJO};
use super::hessian::GnHessian;
use super::{BlockLsqProblem, BoxLsqSolver};
use crate::error::{Error, Result};

/// Largest step curvature κ (relative to the Marquardt scaling) at which a rejected step is
/// corrected: the restoring damping √κ then sits at least 100 times from both scales.
pub(super) const STIFF: f64 = 1e-4;
/// Most restoring steps per correction.
const RESTORE_STEPS: usize = 3;

/// Copies of what describes z (its derivatives, the step and held set of this iteration) while
/// the correction works at the trial point.
#[derive(Debug, Default, Clone)]
pub(super) struct Saved {
    g: Vec<f64>,
    h: GnHessian,
    step: Vec<f64>,
    trial: Vec<f64>,
    fixed: Vec<bool>,
    noise: (f64, f64),
}

impl BoxLsqSolver {
    /// κ = sᵀHs / sᵀDs for the step in `work.step` over the free variables, given sᵀHs and with
    /// D the scaling at z; NaN when either is not positive.
    pub(super) fn step_curvature(&self, shs: f64) -> f64 {
        let floor = self.scale_floor();
        let sds: f64 = (0..self.g.len())
            .filter(|&k| !self.work.fixed[k])
            .map(|k| self.scale(k, floor) * self.work.step[k] * self.work.step[k])
            .sum();
        if shs > 0.0 && sds > 0.0 {
            shs / sds
        } else {
            f64::NAN
        }
    }

    /// The correction of the rejected trial point in `work.trial` (cost `ct`, its derivatives
    /// the last the problem computed), the step from z with model curvature `kappa` and
    /// predicted decrease `pred`: Some(J) at the corrected point when it is accepted (it is then in `work.trial`
    /// and the problem holds its derivatives); None otherwise, with the solver's state of z
    /// restored. Err if an evaluation fails with an error that is not numerical.
    pub(super) fn correct<P: BlockLsqProblem + ?Sized>(
        &mut self,
        prob: &mut P,
        lim: Limits<'_>,
        pr: &mut Progress,
        kappa: f64,
        pred: f64,
        ct: f64,
    ) -> Result<Option<f64>> {
        let Limits { lower, upper, .. } = lim;
        self.save();
        self.take_derivatives(prob);
        let mut zt = std::mem::take(&mut self.saved.trial);
        let mut result = None;
        let mut excess = ct - pr.cost;
        for _ in 0..RESTORE_STEPS {
            if !self.g.iter().all(|v| v.is_finite()) {
                break;
            }
            pr.nit += 1;
            self.hold_active(&zt, lower, upper, kappa.sqrt());
            if !self.reduced_step(&zt, lower, upper) {
                break;
            }
            self.project_step(&zt, lower, upper);
            let c = Error::as_trial_cost(prob.evaluate(&self.work.trial, true))?;
            pr.nfev += 1;
            if c.is_finite() && pr.cost - c > ARMIJO * pred {
                result = Some(c);
                break;
            }
            // Another restoring step only while they converge (the excess over J(z) falls
            // tenfold per step); the derivatives are then those at the new point.
            if !(c.is_finite() && c - pr.cost < 0.1 * excess) {
                break;
            }
            excess = c - pr.cost;
            zt.copy_from_slice(&self.work.trial);
            self.take_derivatives(prob);
        }
        self.saved.trial = zt;
        if result.is_none() {
            self.restore();
        }
        Ok(result)
    }

    fn save(&mut self) {
        let s = &mut self.saved;
        s.g.clone_from(&self.g);
        s.h.clone_from(&self.h);
        s.step.clone_from(&self.work.step);
        s.trial.clone_from(&self.work.trial);
        s.fixed.clone_from(&self.work.fixed);
        s.noise = (self.noise_at_z, self.gnoise_at_z);
    }

    fn restore(&mut self) {
        let s = &self.saved;
        self.g.copy_from_slice(&s.g);
        self.h.clone_from(&s.h);
        self.work.step.copy_from_slice(&s.step);
        self.work.trial.copy_from_slice(&s.trial);
        self.work.fixed.copy_from_slice(&s.fixed);
        (self.noise_at_z, self.gnoise_at_z) = s.noise;
    }
}
