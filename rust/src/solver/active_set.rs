//! The active-set phase: projected Levenberg-Marquardt iterations (monotone in J) with an
//! ε-active set, Marquardt scaling, Nielsen's damping update and the stopping tests.

// Index loops over variables touch several parallel arrays (z, bounds, duals, steps) and read
// better than zipped iterator chains.
#![allow(clippy::needless_range_loop)]

use super::block_tridiag::block_tridiag_matvec;
use super::box_lsq::{
    finite_lower, finite_upper, Progress, ARMIJO, DTOL_MAX_LAMBDA, EXTRAP_MAX, LAMBDA_MAX,
    LAMBDA_MIN, NOISE, NOISE_PG,
};
use super::{projected_gradient_norm, BlockLsqProblem, BoxLsqSolver, SolverOptions, Status};

/// −(gᵀs + ½ sᵀHs): the decrease of J the Gauss-Newton model predicts for the step s, with H
/// given by its block-tridiagonal blocks (`hp` is scratch for Hs).
fn model_decrease(
    nodes: usize,
    n: usize,
    diag: &[f64],
    off: &[f64],
    g: &[f64],
    s: &[f64],
    hp: &mut [f64],
) -> f64 {
    block_tridiag_matvec(nodes, n, diag, off, s, hp);
    -(0..s.len())
        .map(|k| g[k] * s[k] + 0.5 * s[k] * hp[k])
        .sum::<f64>()
}

impl BoxLsqSolver {
    /// Projected active-set Levenberg-Marquardt iterations (monotone in J).
    pub(super) fn active_set_phase<P: BlockLsqProblem + ?Sized>(
        &mut self,
        prob: &mut P,
        z: &mut [f64],
        lower: &[f64],
        upper: &[f64],
        opts: &SolverOptions,
        pr: &mut Progress,
    ) -> Status {
        let (nodes, n) = (prob.n_nodes(), prob.node_dim());
        let len = z.len();
        let mut lambda = 1e-6;
        let mut nu = 2.0;
        let mut noise_failures = 0;
        // Rounding noise of J: at least NOISE relative, raised when small steps show more (a GP
        // with a large σ_f has variances σ_f² − ‖v‖² with large cancellation).
        let mut noise_est = 0.0f64;
        // `g`, `diag`, `off` hold the derivatives at z here (start() or the interior phase).
        loop {
            let pg = projected_gradient_norm(z, &self.g, lower, upper);
            if pg <= opts.gtol {
                return Status::GradientTolerance;
            }
            if pr.nit >= opts.max_iter {
                return Status::MaxIterations;
            }
            pr.nit += 1;
            // ε-active set (Bertsekas' projected Newton): a variable within ε of a bound with
            // the gradient pushing outward is held on that bound, with ε the size of the
            // diagonally scaled projected-gradient step (capped), so that variables creeping
            // towards a bound are caught instead of producing tiny projected steps.
            let mut eps = 0.0f64;
            for k in 0..len {
                let d = self.scale(n, k);
                eps = eps.max((z[k] - (z[k] - self.g[k] / d).clamp(lower[k], upper[k])).abs());
            }
            for k in 0..len {
                let e_l = eps.min(1e-3 * lower[k].abs().max(1.0));
                let e_u = eps.min(1e-3 * upper[k].abs().max(1.0));
                let at_l = finite_lower(lower[k]) && z[k] - lower[k] <= e_l && self.g[k] > 0.0;
                let at_u = finite_upper(upper[k]) && upper[k] - z[k] <= e_u && self.g[k] < 0.0;
                self.fixed[k] = self.fixed_bound[k] || at_l || at_u;
                self.shift[k] = lambda * self.scale(n, k);
            }
            // Reduced damped Gauss-Newton step with the held variables moved onto their bounds
            // (s_A = bound − z, right-hand side −g_F − H_FA s_A). Free variables whose step
            // crosses a bound while the gradient pushes outward join the held set and the step
            // is recomputed (a few passes; factorisations are cheap next to evaluations).
            let mut ok = false;
            for _pass in 0..4 {
                for k in 0..len {
                    self.trial[k] = if self.fixed[k] && !self.fixed_bound[k] {
                        let b = if self.g[k] > 0.0 { lower[k] } else { upper[k] };
                        b - z[k]
                    } else {
                        0.0
                    };
                }
                block_tridiag_matvec(nodes, n, &self.diag, &self.off, &self.trial, &mut self.hp);
                for k in 0..len {
                    self.step[k] = if self.fixed[k] {
                        0.0
                    } else {
                        -self.g[k] - self.hp[k]
                    };
                }
                ok = self
                    .chol
                    .factor(nodes, n, &self.diag, &self.off, &self.shift, &self.fixed);
                if !ok {
                    break;
                }
                self.chol.solve_in_place(&mut self.step);
                let mut added = false;
                for k in 0..len {
                    if self.fixed[k] {
                        self.step[k] = self.trial[k];
                    } else {
                        let zk = z[k] + self.step[k];
                        if (zk < lower[k] && self.g[k] > 0.0) || (zk > upper[k] && self.g[k] < 0.0)
                        {
                            self.fixed[k] = true;
                            added = true;
                        }
                    }
                }
                if !added {
                    break;
                }
            }
            if !ok || self.step.iter().any(|s| !s.is_finite()) {
                lambda *= nu;
                nu *= 2.0;
                if lambda > LAMBDA_MAX {
                    return Status::NoProgress;
                }
                continue;
            }
            // Projected trial point and the step actually taken.
            let mut znorm = 0.0f64;
            let mut pnorm = 0.0f64;
            let mut clipped = false;
            for k in 0..len {
                self.dyl[k] = self.step[k]; // the unprojected step (dyl is free scratch here)
                let target = z[k] + self.step[k];
                self.trial[k] = target.clamp(lower[k], upper[k]);
                clipped |= !self.fixed[k] && self.trial[k] != target;
                self.step[k] = self.trial[k] - z[k];
                znorm = znorm.max(z[k].abs());
                pnorm = pnorm.max(self.step[k].abs());
            }
            if pnorm <= opts.xtol * (opts.xtol + znorm) {
                return Status::StepTolerance;
            }
            let known_noise = noise_est.max(self.noise_at_z);
            let mut pred = model_decrease(
                nodes,
                n,
                &self.diag,
                &self.off,
                &self.g,
                &self.step,
                &mut self.hp,
            );
            if clipped {
                // A projected step can be poor when coupled variables hit a bound; the
                // unprojected step truncated at the first bound may predict more: keep
                // whichever model decrease is larger. `shift` is free scratch here.
                let mut a = 1.0f64;
                for k in 0..len {
                    let u = self.dyl[k];
                    self.shift[k] = u;
                    if u < 0.0 && finite_lower(lower[k]) {
                        a = a.min((lower[k] - z[k]) / u);
                    } else if u > 0.0 && finite_upper(upper[k]) {
                        a = a.min((upper[k] - z[k]) / u);
                    }
                }
                let a = a.max(0.0);
                for k in 0..len {
                    self.shift[k] *= a;
                }
                let pred_t = model_decrease(
                    nodes,
                    n,
                    &self.diag,
                    &self.off,
                    &self.g,
                    &self.shift,
                    &mut self.hp,
                );
                if pred_t > pred {
                    pred = pred_t;
                    for k in 0..len {
                        self.step[k] = self.shift[k];
                        self.trial[k] = (z[k] + self.shift[k]).clamp(lower[k], upper[k]);
                    }
                }
                // Shorter points on the projection arc P(z + αu) (Bertsekas' projected Newton
                // search), judged by the model before any evaluation: a projected step can
                // predict an increase when many coupled variables sit at a bound, while a
                // shorter one along the arc still descends. `dyu` is free scratch here.
                let mut alpha = 1.0;
                for _ in 0..6 {
                    alpha *= 0.5;
                    for k in 0..len {
                        self.dyu[k] = (z[k] + alpha * self.dyl[k]).clamp(lower[k], upper[k]) - z[k];
                    }
                    let pred_a = model_decrease(
                        nodes,
                        n,
                        &self.diag,
                        &self.off,
                        &self.g,
                        &self.dyu,
                        &mut self.hp,
                    );
                    if pred_a > pred {
                        pred = pred_a;
                        for k in 0..len {
                            self.step[k] = self.dyu[k];
                            self.trial[k] = z[k] + self.dyu[k];
                        }
                    }
                }
            }
            let moves = self.step.iter().any(|&s| s != 0.0);
            let resolvable = 2.0 * known_noise.max(NOISE * pr.cost.abs().max(1.0));
            if !moves || (pred <= 0.0 && pred.abs() > resolvable) {
                // No candidate moves, or the model predicts no decrease along any: damp harder
                // and recompute (factorisations are cheap next to an evaluation), do not
                // evaluate.
                lambda *= nu;
                nu *= 2.0;
                if lambda > LAMBDA_MAX {
                    return Status::NoProgress;
                }
                continue;
            }
            if !clipped
                && lambda <= 1.0
                && pred <= 2.0 * known_noise
                && pg <= NOISE_PG * self.gnoise_at_z
            {
                // Nothing left that J or ∇J can resolve: stop before spending an evaluation.
                return Status::NoiseFloor;
            }
            if !clipped && lambda <= DTOL_MAX_LAMBDA && pred <= opts.dtol {
                // (Damped by λ ≤ 1e-3 the step is within ~0.1 % of the Gauss-Newton step, so
                // pred is the Gauss-Newton decrement; a clipped step's pred says nothing about
                // the free minimiser.)
                return Status::DecrementTolerance;
            }
            let gp: f64 = (0..len).map(|k| self.g[k] * self.step[k]).sum();
            let ct = prob.evaluate(&self.trial, true).unwrap_or(f64::INFINITY);
            pr.nfev += 1;
            let rho = (pr.cost - ct) / pred;
            // Below the rounding noise of J (GP variances are differences of O(σ_f²) numbers)
            // the gain ratio is meaningless: accept the step if it lowers the projected
            // gradient instead, and stop if it does not.
            let mut accept = ct.is_finite() && pred > 0.0 && rho > ARMIJO;
            let mut noise = known_noise.max(NOISE * pr.cost.abs().max(1.0));
            let mismatch = (ct - (pr.cost - pred)).abs();
            if !accept && ct.is_finite() && pred > 0.0 && mismatch > 10.0 * pred {
                // A small step that "failed" by far more than its predicted decrease: the
                // mismatch is rounding noise, not model error.
                noise_est = noise_est.max(mismatch.min(1e-4 * pr.cost.abs()));
                noise = noise.max(noise_est);
            }
            let unmeasurable = !clipped && pred <= 2.0 * noise;
            if !accept && unmeasurable && ct.is_finite() {
                prob.gradient_into(&mut self.hp);
                if projected_gradient_norm(&self.trial, &self.hp, lower, upper) < pg {
                    accept = true;
                } else {
                    noise_failures += 1;
                    if noise_failures >= 3 {
                        pr.derivs_at_z = false;
                        return Status::CostTolerance;
                    }
                }
            }
            if accept {
                noise_failures = 0;
                let decrease = pr.cost - ct;
                let old = pr.cost;
                z.copy_from_slice(&self.trial);
                pr.cost = ct;
                pr.derivs_at_z = true;
                self.take_derivatives(prob);
                nu = 2.0;
                if unmeasurable {
                    lambda /= 3.0;
                    continue;
                }
                lambda = if (0.75..=1.25).contains(&rho) {
                    // The model predicted this step well: damping only slows the flat
                    // directions (Marquardt's λ·diag H dwarfs their curvature), so drop it fast
                    // rather than by Nielsen's 1/3 per step.
                    (lambda / 10.0).max(LAMBDA_MIN)
                } else {
                    lambda * (1.0 - (2.0 * rho - 1.0).powi(3)).max(1.0 / 3.0)
                };
                if decrease <= opts.ftol * old {
                    return Status::CostTolerance;
                }
                // Along flat directions the Gauss-Newton model overestimates the curvature
                // (rho ≈ 2, slow linear convergence): try the parabola's minimiser along the
                // step, keep it if it costs less.
                // The same parabola also shortens steps that overshoot (rho well below 1).
                let c = 2.0 * (ct - old - gp);
                let a_star = if c > 0.0 { -gp / c } else { f64::INFINITY };
                if gp < 0.0 && !(0.7..=1.5).contains(&a_star) {
                    let a = a_star.clamp(0.2, EXTRAP_MAX);
                    for k in 0..len {
                        self.trial[k] = (z[k] + (a - 1.0) * self.step[k]).clamp(lower[k], upper[k]);
                    }
                    let c2 = prob.evaluate(&self.trial, true).unwrap_or(f64::INFINITY);
                    pr.nfev += 1;
                    if c2.is_finite() && c2 < pr.cost {
                        z.copy_from_slice(&self.trial);
                        pr.cost = c2;
                        self.take_derivatives(prob);
                    } else {
                        pr.derivs_at_z = false;
                    }
                }
            } else {
                pr.derivs_at_z = false;
                // Before damping harder, try the minimiser of the parabola through J(0),
                // J'(0) and J(1) along the same step (a one-evaluation line search).
                let c = 2.0 * (ct - pr.cost - gp);
                if ct.is_finite() && !unmeasurable && gp < 0.0 && c > 0.0 {
                    let a = (-gp / c).clamp(0.05, 0.9);
                    let php = -2.0 * (pred + gp); // stepᵀ H step
                    let pred2 = -(a * gp + 0.5 * a * a * php);
                    for k in 0..len {
                        self.trial[k] = (z[k] + a * self.step[k]).clamp(lower[k], upper[k]);
                    }
                    let c2 = prob.evaluate(&self.trial, true).unwrap_or(f64::INFINITY);
                    pr.nfev += 1;
                    if c2.is_finite() && pred2 > 0.0 && pr.cost - c2 > ARMIJO * pred2 {
                        z.copy_from_slice(&self.trial);
                        pr.cost = c2;
                        pr.derivs_at_z = true;
                        self.take_derivatives(prob);
                        noise_failures = 0;
                        lambda *= 2.0;
                        continue;
                    }
                }
                lambda *= nu;
                nu *= 2.0;
                if lambda > LAMBDA_MAX {
                    return Status::NoProgress;
                }
            }
        }
    }
}
