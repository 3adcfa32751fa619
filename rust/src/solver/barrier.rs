//! The interior phase: primal-dual log-barrier Gauss-Newton iterations from a point pushed
//! strictly inside the box, the barrier parameter decreasing from `mu_init` to `mu_final`.

// Index loops over variables touch several parallel arrays (z, bounds, duals, steps) and read
// better than zipped iterator chains.
#![allow(clippy::needless_range_loop)]

use super::box_lsq::{
    finite_lower, finite_upper, Progress, ARMIJO, EXTRAP_MAX, LAMBDA_MAX, NOISE_PG,
};
use super::{BlockLsqProblem, BoxLsqSolver, SolverOptions};

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
        lower: &[f64],
        upper: &[f64],
        opts: &SolverOptions,
        pr: &mut Progress,
    ) {
        let (nodes, n) = (prob.n_nodes(), prob.node_dim());
        let len = z.len();
        let has_l = |k: usize| finite_lower(lower[k]);
        let has_u = |k: usize| finite_upper(upper[k]);
        let mut mu = opts.mu_init;
        for k in 0..len {
            self.fixed[k] = self.fixed_bound[k];
            let free = !self.fixed_bound[k];
            self.yl[k] = if free && has_l(k) {
                mu / (z[k] - lower[k])
            } else {
                0.0
            };
            self.yu[k] = if free && has_u(k) {
                mu / (upper[k] - z[k])
            } else {
                0.0
            };
        }
        let n_bounded = (0..len)
            .filter(|&k| !self.fixed_bound[k])
            .map(|k| has_l(k) as usize + has_u(k) as usize)
            .sum::<usize>()
            .max(1);
        let mut lambda = 0.0f64;
        let mut failures = 0;
        // At most half of the iteration budget: the active-set phase polishes from wherever the
        // barrier phase got to (a window it cannot finish would otherwise end at the cap).
        let budget = pr.nit + opts.max_iter.div_ceil(2);
        while pr.nit < budget.min(opts.max_iter) {
            // Optimality error of the barrier problem (IPOPT's E_mu with its dual scaling).
            let mut e_dual = 0.0f64;
            let mut e_comp = 0.0f64;
            let mut ysum = 0.0;
            for k in 0..len {
                if self.fixed_bound[k] {
                    continue;
                }
                e_dual = e_dual.max((self.g[k] - self.yl[k] + self.yu[k]).abs());
                if has_l(k) {
                    e_comp = e_comp.max(((z[k] - lower[k]) * self.yl[k] - mu).abs());
                }
                if has_u(k) {
                    e_comp = e_comp.max(((upper[k] - z[k]) * self.yu[k] - mu).abs());
                }
                ysum += self.yl[k] + self.yu[k];
            }
            let s_d = (ysum / n_bounded as f64).max(100.0) / 100.0;
            // A dual error within the gradient's rounding noise is as small as it can get.
            let e_dual = if e_dual <= NOISE_PG * self.gnoise_at_z {
                0.0
            } else {
                e_dual
            };
            if (e_dual / s_d).max(e_comp) <= 10.0 * mu {
                if mu <= opts.mu_final {
                    break;
                }
                mu = opts.mu_final.max((0.2 * mu).min(mu.powf(1.5)));
                continue;
            }
            pr.nit += 1;
            // Newton system (H + Σ + λD) Δz = −∇φ_μ.
            for k in 0..len {
                let (sl, su) = (z[k] - lower[k], upper[k] - z[k]);
                let mut sigma = 0.0;
                let mut rhs = -self.g[k];
                if has_l(k) && !self.fixed_bound[k] {
                    sigma += self.yl[k] / sl;
                    rhs += mu / sl;
                }
                if has_u(k) && !self.fixed_bound[k] {
                    sigma += self.yu[k] / su;
                    rhs -= mu / su;
                }
                self.shift[k] = sigma + lambda * self.scale(n, k);
                self.step[k] = if self.fixed[k] { 0.0 } else { rhs };
            }
            let ok = self
                .chol
                .factor(nodes, n, &self.diag, &self.off, &self.shift, &self.fixed);
            if ok {
                self.chol.solve_in_place(&mut self.step);
            }
            if !ok || self.step.iter().any(|s| !s.is_finite()) {
                lambda = (10.0 * lambda).max(1e-8);
                if lambda > LAMBDA_MAX {
                    break;
                }
                continue;
            }
            // Fraction to the boundary, primal and dual.
            let tau = (1.0 - mu).max(0.99);
            let mut a_max = f64::INFINITY;
            let mut a_d = 1.0f64;
            let mut dphi = 0.0;
            for k in 0..len {
                if self.fixed_bound[k] {
                    self.dyl[k] = 0.0;
                    self.dyu[k] = 0.0;
                    continue;
                }
                let dz = self.step[k];
                let (sl, su) = (z[k] - lower[k], upper[k] - z[k]);
                let mut gb = self.g[k];
                self.dyl[k] = 0.0;
                self.dyu[k] = 0.0;
                if has_l(k) {
                    gb -= mu / sl;
                    if dz < 0.0 {
                        a_max = a_max.min(-tau * sl / dz);
                    }
                    self.dyl[k] = mu / sl - self.yl[k] - self.yl[k] / sl * dz;
                    if self.dyl[k] < 0.0 {
                        a_d = a_d.min(-tau * self.yl[k] / self.dyl[k]);
                    }
                }
                if has_u(k) {
                    gb += mu / su;
                    if dz > 0.0 {
                        a_max = a_max.min(tau * su / dz);
                    }
                    self.dyu[k] = mu / su - self.yu[k] + self.yu[k] / su * dz;
                    if self.dyu[k] < 0.0 {
                        a_d = a_d.min(-tau * self.yu[k] / self.dyu[k]);
                    }
                }
                dphi += gb * dz;
            }
            // Armijo backtracking on φ_μ = J − μ Σ ln s.
            let phi0 = pr.cost + barrier(z, lower, upper, &self.fixed_bound, mu);
            let a_p = a_max.min(1.0);
            let mut alpha = a_p;
            let mut accepted = None;
            for ls in 0..12 {
                for k in 0..len {
                    self.trial[k] = z[k] + alpha * self.step[k];
                }
                let ct = prob.evaluate(&self.trial, ls == 0).unwrap_or(f64::INFINITY);
                pr.nfev += 1;
                pr.derivs_at_z = false;
                let phit = ct + barrier(&self.trial, lower, upper, &self.fixed_bound, mu);
                if phit.is_finite() && phit <= phi0 + ARMIJO * alpha * dphi.min(0.0) {
                    accepted = Some((ct, ls == 0, phit));
                    break;
                }
                alpha *= 0.5;
            }
            let Some((mut ct, mut have_derivs, phit)) = accepted else {
                // g and the blocks still hold the derivatives at z: damp harder and retry, but
                // leave the rest to the active-set phase after repeated failures.
                lambda = (10.0 * lambda).max(1e-8);
                failures += 1;
                if lambda > LAMBDA_MAX || failures >= 3 {
                    break;
                }
                continue;
            };
            if have_derivs && alpha == 1.0 {
                // Gauss-Newton underestimates the step along flat directions (rho ≈ 2):
                // try the minimiser of the parabola through φ(0), φ'(0), φ(1).
                let c = 2.0 * (phit - phi0 - dphi);
                let a_star = if c > 0.0 { -dphi / c } else { f64::INFINITY };
                let a = a_star.min(EXTRAP_MAX).min(a_max);
                if a > 1.5 {
                    for k in 0..len {
                        self.hp[k] = z[k] + a * self.step[k];
                    }
                    let c2 = prob.evaluate(&self.hp, true).unwrap_or(f64::INFINITY);
                    pr.nfev += 1;
                    let phi2 = c2 + barrier(&self.hp, lower, upper, &self.fixed_bound, mu);
                    if phi2.is_finite() && phi2 < phit {
                        self.trial.copy_from_slice(&self.hp);
                        ct = c2;
                    } else {
                        have_derivs = false;
                    }
                }
            }
            failures = 0;
            z.copy_from_slice(&self.trial);
            pr.cost = ct;
            const KAPPA_SIGMA: f64 = 1e10;
            for k in 0..len {
                if self.fixed_bound[k] {
                    continue;
                }
                if has_l(k) {
                    let sl = z[k] - lower[k];
                    let y = self.yl[k] + a_d * self.dyl[k];
                    self.yl[k] = y.clamp(mu / (KAPPA_SIGMA * sl), KAPPA_SIGMA * mu / sl);
                }
                if has_u(k) {
                    let su = upper[k] - z[k];
                    let y = self.yu[k] + a_d * self.dyu[k];
                    self.yu[k] = y.clamp(mu / (KAPPA_SIGMA * su), KAPPA_SIGMA * mu / su);
                }
            }
            if have_derivs {
                pr.derivs_at_z = true;
            } else {
                match prob.evaluate(z, true) {
                    Ok(c) if c.is_finite() => {
                        pr.nfev += 1;
                        pr.cost = c;
                        pr.derivs_at_z = true;
                    }
                    _ => break,
                }
            }
            self.take_derivatives(prob);
            if alpha == 1.0 {
                lambda = if lambda < 1e-7 { 0.0 } else { lambda / 10.0 };
            }
        }
        if !pr.derivs_at_z {
            if let Ok(c) = prob.evaluate(z, true) {
                pr.nfev += 1;
                if c.is_finite() {
                    pr.cost = c;
                    pr.derivs_at_z = true;
                    self.take_derivatives(prob);
                }
            }
        }
    }
}
