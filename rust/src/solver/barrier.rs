//! The interior phase: primal-dual log-barrier Gauss-Newton iterations from a point pushed
//! strictly inside the box, the barrier parameter μ decreasing from `mu_init` to `mu_final`
//! (IPOPT's monotone rule).
//!
//! One iteration of [`BoxLsqSolver::interior_phase`]: the barrier problem's optimality error
//! (`barrier_converged`, which lowers μ when it is small); the Newton step of the barrier problem
//! (`barrier_step`); the fraction-to-the-boundary limits on the primal and dual steps
//! (`step_limits`); the Armijo backtracking on the barrier merit (`line_search`), and after a
//! full step the parabola's extrapolation (`extrapolate`); the move and the dual update
//! (`update_duals`).

// Index loops over variables touch several parallel arrays (z, bounds, duals, steps) and read
// better than zipped iterator chains.
#![allow(clippy::needless_range_loop)]

use super::box_lsq::{
    finite_lower, finite_upper, Limits, Progress, ARMIJO, EXTRAP_MAX, LAMBDA_MAX, NOISE_PG,
};
use super::{BlockLsqProblem, BoxLsqSolver};
use crate::error::{Error, Result};
use crate::interrupt;

/// The log-barrier term −μ Σ ln s over the finite bounds of the free variables.
fn barrier(z: &[f64], lower: &[f64], upper: &[f64], fixed_bound: &[bool], mu: f64) -> f64 {
    let mut b = 0.0;
    for k in 0..z.len() {
        if fixed_bound[k] {
            continue;
        }
        if finite_lower(lower[k]) {
            b -= mu * (z[k] - lower[k]).ln();
        }
        if finite_upper(upper[k]) {
            b -= mu * (upper[k] - z[k]).ln();
        }
    }
    b
}

/// What the line search needs about one barrier step: μ, the merit at z, how far the step may
/// go and the merit's slope along it.
#[derive(Clone, Copy)]
struct StepLimits {
    mu: f64,
    /// φ_μ(z) = J(z) − μ Σ ln s.
    phi0: f64,
    /// Largest primal step length keeping z inside the box (fraction to the boundary).
    a_max: f64,
    /// Dual step length (fraction to the boundary, at most 1).
    a_d: f64,
    /// ∇φ_μᵀ Δz, the directional derivative of the barrier merit.
    dphi: f64,
}

/// An accepted point of the line search (in `work.trial`).
struct Accepted {
    /// Its cost J and barrier merit φ_μ.
    ct: f64,
    phit: f64,
    /// Its step length.
    alpha: f64,
    /// Whether the problem's derivatives refer to it.
    have_derivs: bool,
}

impl BoxLsqSolver {
    /// Moves z strictly inside the box (IPOPT's bound push, 1e-2 relative).
    pub(super) fn push_inside(&self, z: &mut [f64], lower: &[f64], upper: &[f64]) {
        const K1: f64 = 1e-2;
        const K2: f64 = 1e-2;
        for k in 0..z.len() {
            if self.fixed_bound[k] {
                continue;
            }
            let (l, u) = (lower[k], upper[k]);
            let w = u - l;
            if finite_lower(l) {
                let p = (K1 * l.abs().max(1.0)).min(if finite_upper(u) {
                    K2 * w
                } else {
                    f64::INFINITY
                });
                z[k] = z[k].max(l + p);
            }
            if finite_upper(u) {
                let p = (K1 * u.abs().max(1.0)).min(if finite_lower(l) {
                    K2 * w
                } else {
                    f64::INFINITY
                });
                z[k] = z[k].min(u - p);
            }
        }
    }

    /// Primal-dual barrier Gauss-Newton iterations from a strictly interior z down to mu_final.
    pub(super) fn interior_phase<P: BlockLsqProblem + ?Sized>(
        &mut self,
        prob: &mut P,
        z: &mut [f64],
        lim: Limits<'_>,
        pr: &mut Progress,
    ) -> Result<()> {
        let Limits { lower, upper, opts } = lim;
        let mut mu = opts.mu_init;
        let n_bounded = self.init_duals(z, lower, upper, mu);
        let mut lambda = 0.0f64;
        let mut failures = 0;
        // At most half of the iteration budget: the active-set phase polishes from wherever the
        // barrier phase got to (a window it cannot finish would otherwise end at the cap).
        let budget = pr.nit + opts.max_iter.div_ceil(2);
        while pr.nit < budget.min(opts.max_iter) {
            interrupt::check()?;
            if self.barrier_converged(z, lower, upper, mu, n_bounded) {
                if mu <= opts.mu_final {
                    break;
                }
                mu = opts.mu_final.max((0.2 * mu).min(mu.powf(1.5)));
                continue;
            }
            pr.nit += 1;
            if !self.barrier_step(z, lower, upper, mu, lambda) {
                lambda = (10.0 * lambda).max(1e-8);
                if lambda > LAMBDA_MAX {
                    break;
                }
                continue;
            }
            let mut limits = self.step_limits(z, lower, upper, mu);
            limits.phi0 = pr.cost + barrier(z, lower, upper, &self.fixed_bound, mu);
            let Some(mut acc) = self.line_search(prob, z, lim, pr, &limits)? else {
                // g and the blocks still hold the derivatives at z: damp harder and retry, but
                // leave the rest to the active-set phase after repeated failures.
                lambda = (10.0 * lambda).max(1e-8);
                failures += 1;
                if lambda > LAMBDA_MAX || failures >= 3 {
                    break;
                }
                continue;
            };
            if acc.have_derivs && acc.alpha == 1.0 {
                self.extrapolate(prob, z, lim, pr, &limits, &mut acc)?;
            }
            failures = 0;
            z.copy_from_slice(&self.work.trial);
            pr.cost = acc.ct;
            self.update_duals(z, lower, upper, mu, limits.a_d);
            if acc.have_derivs {
                pr.derivs_at_z = true;
            } else {
                match Error::as_trial_cost(prob.evaluate(z, true))? {
                    c if c.is_finite() => {
                        pr.nfev += 1;
                        pr.cost = c;
                        pr.derivs_at_z = true;
                    }
                    _ => break,
                }
            }
            self.take_derivatives(prob);
            if acc.alpha == 1.0 {
                lambda = if lambda < 1e-7 { 0.0 } else { lambda / 10.0 };
            }
        }
        if !pr.derivs_at_z {
            match prob.evaluate(z, true) {
                Ok(c) => {
                    pr.nfev += 1;
                    if c.is_finite() {
                        pr.cost = c;
                        pr.derivs_at_z = true;
                        self.take_derivatives(prob);
                    }
                }
                Err(Error::Numerical(_)) => {}
                Err(e) => return Err(e),
            }
        }
        Ok(())
    }

    /// Holds the fixed variables, sets the multipliers to μ / s (on the central path) and returns
    /// the number of finite bounds of free variables (at least 1).
    fn init_duals(&mut self, z: &[f64], lower: &[f64], upper: &[f64], mu: f64) -> usize {
        let has_l = |k: usize| finite_lower(lower[k]);
        let has_u = |k: usize| finite_upper(upper[k]);
        let d = &mut self.duals;
        for k in 0..z.len() {
            self.work.fixed[k] = self.fixed_bound[k];
            let free = !self.fixed_bound[k];
            d.yl[k] = if free && has_l(k) {
                mu / (z[k] - lower[k])
            } else {
                0.0
            };
            d.yu[k] = if free && has_u(k) {
                mu / (upper[k] - z[k])
            } else {
                0.0
            };
        }
        (0..z.len())
            .filter(|&k| !self.fixed_bound[k])
            .map(|k| has_l(k) as usize + has_u(k) as usize)
            .sum::<usize>()
            .max(1)
    }

    /// Whether the optimality error of the barrier problem (IPOPT's E_μ with its dual scaling)
    /// is at most 10μ.
    fn barrier_converged(
        &self,
        z: &[f64],
        lower: &[f64],
        upper: &[f64],
        mu: f64,
        n_bounded: usize,
    ) -> bool {
        let d = &self.duals;
        let mut e_dual = 0.0f64;
        let mut e_comp = 0.0f64;
        let mut ysum = 0.0;
        for k in 0..z.len() {
            if self.fixed_bound[k] {
                continue;
            }
            e_dual = e_dual.max((self.g[k] - d.yl[k] + d.yu[k]).abs());
            if finite_lower(lower[k]) {
                e_comp = e_comp.max(((z[k] - lower[k]) * d.yl[k] - mu).abs());
            }
            if finite_upper(upper[k]) {
                e_comp = e_comp.max(((upper[k] - z[k]) * d.yu[k] - mu).abs());
            }
            ysum += d.yl[k] + d.yu[k];
        }
        let s_d = (ysum / n_bounded as f64).max(100.0) / 100.0;
        // A dual error within the gradient's rounding noise is as small as it can get.
        let e_dual = if e_dual <= NOISE_PG * self.gnoise_at_z {
            0.0
        } else {
            e_dual
        };
        (e_dual / s_d).max(e_comp) <= 10.0 * mu
    }

    /// The Newton step of the barrier problem, (H + Σ + λD) Δz = −∇φ_μ, into `work.step`; false
    /// if the matrix is not positive definite or the step not finite.
    #[allow(clippy::too_many_arguments)]
    fn barrier_step(
        &mut self,
        z: &[f64],
        lower: &[f64],
        upper: &[f64],
        mu: f64,
        lambda: f64,
    ) -> bool {
        let floor = self.scale_floor();
        for k in 0..z.len() {
            let (sl, su) = (z[k] - lower[k], upper[k] - z[k]);
            let mut sigma = 0.0;
            let mut rhs = -self.g[k];
            if finite_lower(lower[k]) && !self.fixed_bound[k] {
                sigma += self.duals.yl[k] / sl;
                rhs += mu / sl;
            }
            if finite_upper(upper[k]) && !self.fixed_bound[k] {
                sigma += self.duals.yu[k] / su;
                rhs -= mu / su;
            }
            self.work.shift[k] = sigma + lambda * self.scale(k, floor);
            self.work.step[k] = if self.work.fixed[k] { 0.0 } else { rhs };
        }
        let ok = self.factor_step();
        let w = &mut self.work;
        if ok {
            self.chol.solve_in_place(&mut w.step);
        }
        ok && !w.step.iter().any(|s| !s.is_finite())
    }

    /// Fraction to the boundary, primal and dual, for the step in `work.step`; the dual steps
    /// go to `duals.dyl`, `duals.dyu`. The merit `phi0` is left for the caller (NaN here).
    fn step_limits(&mut self, z: &[f64], lower: &[f64], upper: &[f64], mu: f64) -> StepLimits {
        let tau = (1.0 - mu).max(0.99);
        let mut a_max = f64::INFINITY;
        let mut a_d = 1.0f64;
        let mut dphi = 0.0;
        let d = &mut self.duals;
        for k in 0..z.len() {
            if self.fixed_bound[k] {
                d.dyl[k] = 0.0;
                d.dyu[k] = 0.0;
                continue;
            }
            let dz = self.work.step[k];
            let (sl, su) = (z[k] - lower[k], upper[k] - z[k]);
            let mut gb = self.g[k];
            d.dyl[k] = 0.0;
            d.dyu[k] = 0.0;
            if finite_lower(lower[k]) {
                gb -= mu / sl;
                if dz < 0.0 {
                    a_max = a_max.min(-tau * sl / dz);
                }
                d.dyl[k] = mu / sl - d.yl[k] - d.yl[k] / sl * dz;
                if d.dyl[k] < 0.0 {
                    a_d = a_d.min(-tau * d.yl[k] / d.dyl[k]);
                }
            }
            if finite_upper(upper[k]) {
                gb += mu / su;
                if dz > 0.0 {
                    a_max = a_max.min(tau * su / dz);
                }
                d.dyu[k] = mu / su - d.yu[k] + d.yu[k] / su * dz;
                if d.dyu[k] < 0.0 {
                    a_d = a_d.min(-tau * d.yu[k] / d.dyu[k]);
                }
            }
            dphi += gb * dz;
        }
        StepLimits {
            mu,
            phi0: f64::NAN,
            a_max,
            a_d,
            dphi,
        }
    }

    /// Armijo backtracking on φ_μ = J − μ Σ ln s from the largest step inside the box; the
    /// accepted point is left in `work.trial`. None after 12 halvings; Err if an evaluation fails
    /// with an error that is not numerical.
    fn line_search<P: BlockLsqProblem + ?Sized>(
        &mut self,
        prob: &mut P,
        z: &[f64],
        lim: Limits<'_>,
        pr: &mut Progress,
        limits: &StepLimits,
    ) -> Result<Option<Accepted>> {
        let Limits { lower, upper, .. } = lim;
        let StepLimits { mu, phi0, dphi, .. } = *limits;
        let w = &mut self.work;
        let mut alpha = limits.a_max.min(1.0);
        for ls in 0..12 {
            for k in 0..z.len() {
                w.trial[k] = z[k] + alpha * w.step[k];
            }
            let ct = Error::as_trial_cost(prob.evaluate(&w.trial, ls == 0))?;
            pr.nfev += 1;
            pr.derivs_at_z = false;
            let phit = ct + barrier(&w.trial, lower, upper, &self.fixed_bound, mu);
            if phit.is_finite() && phit <= phi0 + ARMIJO * alpha * dphi.min(0.0) {
                return Ok(Some(Accepted {
                    ct,
                    phit,
                    alpha,
                    have_derivs: ls == 0,
                }));
            }
            alpha *= 0.5;
        }
        Ok(None)
    }

    /// After a full step: Gauss-Newton underestimates the step along flat directions (rho ≈ 2),
    /// so try the minimiser of the parabola through φ(0), φ'(0), φ(1) and keep it in
    /// `work.trial` if its merit is lower.
    fn extrapolate<P: BlockLsqProblem + ?Sized>(
        &mut self,
        prob: &mut P,
        z: &[f64],
        lim: Limits<'_>,
        pr: &mut Progress,
        limits: &StepLimits,
        acc: &mut Accepted,
    ) -> Result<()> {
        let Limits { lower, upper, .. } = lim;
        let StepLimits { mu, phi0, dphi, .. } = *limits;
        let c = 2.0 * (acc.phit - phi0 - dphi);
        let a_star = if c > 0.0 { -dphi / c } else { f64::INFINITY };
        let a = a_star.min(EXTRAP_MAX).min(limits.a_max);
        if a > 1.5 {
            let w = &mut self.work;
            for k in 0..z.len() {
                w.hp[k] = z[k] + a * w.step[k];
            }
            let c2 = Error::as_trial_cost(prob.evaluate(&w.hp, true))?;
            pr.nfev += 1;
            let phi2 = c2 + barrier(&w.hp, lower, upper, &self.fixed_bound, mu);
            if phi2.is_finite() && phi2 < acc.phit {
                w.trial.copy_from_slice(&w.hp);
                acc.ct = c2;
            } else {
                acc.have_derivs = false;
            }
        }
        Ok(())
    }

    /// The dual step of length `a_d`, each multiplier kept within a factor KAPPA_SIGMA of the
    /// central path μ / s at the new z.
    fn update_duals(&mut self, z: &[f64], lower: &[f64], upper: &[f64], mu: f64, a_d: f64) {
        const KAPPA_SIGMA: f64 = 1e10;
        let d = &mut self.duals;
        for k in 0..z.len() {
            if self.fixed_bound[k] {
                continue;
            }
            if finite_lower(lower[k]) {
                let sl = z[k] - lower[k];
                let y = d.yl[k] + a_d * d.dyl[k];
                d.yl[k] = y.clamp(mu / (KAPPA_SIGMA * sl), KAPPA_SIGMA * mu / sl);
            }
            if finite_upper(upper[k]) {
                let su = upper[k] - z[k];
                let y = d.yu[k] + a_d * d.dyu[k];
                d.yu[k] = y.clamp(mu / (KAPPA_SIGMA * su), KAPPA_SIGMA * mu / su);
            }
        }
    }
}
