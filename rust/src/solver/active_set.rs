//! The active-set phase: projected Levenberg-Marquardt iterations (monotone in J). Variables at a
//! bound whose gradient pushes outward are held (an ε-active set), the others take a damped
//! Gauss-Newton step (Marquardt scaling; the damping, which starts at 0, in `damping.rs`), the
//! trial point is projected on the box and accepted on the gain ratio.
//!
//! One iteration, `active_set_iteration`, in order: the stopping tests on the
//! projected gradient and the iteration cap; the held set (`hold_active`); the
//! reduced step (`reduced_step`); the projected trial point
//! (`project_step`) and, for a clipped one, better candidates judged by the model
//! (`improve_clipped_step`); the tests that stop or damp before an evaluation
//! (`verdict`); the evaluation and the acceptance
//! (`judge_trial`); then `accept`, or for a rejected step along a stiff valley the
//! correction (`correction.rs`) and, failing that, `reject`; both update the damping.

// Index loops over variables touch several parallel arrays (z, bounds, duals, steps) and read
// better than zipped iterator chains.
#![allow(clippy::needless_range_loop)]

use super::box_lsq::{
    finite_lower, finite_upper, Limits, Progress, ARMIJO, DTOL_MAX_LAMBDA, EXTRAP_MAX, NOISE,
    NOISE_MAX, NOISE_PG,
};
use super::correction::STIFF;
use super::damping::{LmState, LAMBDA_RESTART};
use super::hessian::GnHessian;
use super::{projected_gradient_norm, BlockLsqProblem, BoxLsqSolver, SolverOptions, Status};
use crate::error::{Error, Result};
use crate::interrupt;

/// −(gᵀs + ½ sᵀHs): the decrease of J the Gauss-Newton model predicts for the step s (`hp` is
/// scratch for Hs).
fn model_decrease(h: &GnHessian, g: &[f64], s: &[f64], hp: &mut [f64]) -> f64 {
    h.matvec(s, hp);
    -(0..s.len())
        .map(|k| g[k] * s[k] + 0.5 * s[k] * hp[k])
        .sum::<f64>()
}

/// The candidate step of one iteration (the step in `work.step`, its point in `work.trial`).
struct Candidate {
    /// ‖z − P(z − ∇J)‖∞ at z.
    pg: f64,
    /// The decrease of J the Gauss-Newton model predicts for the step.
    pred: f64,
    /// Whether the projection on the box cut the step of a free variable.
    clipped: bool,
    /// The largest rounding noise of J known at z.
    known_noise: f64,
}

/// The evaluated trial point of one iteration.
struct Trial {
    /// J at the trial point (+∞ if the evaluation failed).
    ct: f64,
    /// The gain ratio (J(z) − J(trial)) / pred.
    rho: f64,
    /// ∇Jᵀ step, the slope along the step at z.
    gp: f64,
    /// The decrease of J the model predicted (the candidate's).
    pred: f64,
    /// Whether the predicted decrease is below J's rounding noise (the gain ratio says nothing).
    unmeasurable: bool,
    /// Whether the point is accepted.
    accept: bool,
    /// The projected gradient at the trial point over that at z, for an unmeasurable step (NaN
    /// otherwise).
    pg_ratio: f64,
    /// sᵀHs / sᵀDs: the model's curvature along the step relative to the scaling.
    kappa: f64,
}

/// What the tests before an evaluation decided.
enum Verdict {
    /// Evaluate the trial point.
    Evaluate,
    /// Damp harder and compute a new step without evaluating.
    Retry,
    /// Compute the undamped step without evaluating.
    Undamp,
    /// The phase stops.
    Stop(Status),
}

impl BoxLsqSolver {
    /// Projected active-set Levenberg-Marquardt iterations (monotone in J).
    pub(super) fn active_set_phase<P: BlockLsqProblem + ?Sized>(
        &mut self,
        prob: &mut P,
        z: &mut [f64],
        lim: Limits<'_>,
        pr: &mut Progress,
    ) -> Result<Status> {
        let mut st = LmState::new();
        // `g`, `diag`, `off` hold the derivatives at z here (start() or the interior phase).
        // Bounded: every iteration that does not stop the phase counts in pr.nit, which stops it
        // at opts.max_iter.
        loop {
            interrupt::check()?;
            if let Some(status) = self.active_set_iteration(prob, z, lim, pr, &mut st)? {
                return Ok(status);
            }
        }
    }

    /// One iteration; Some(status) when the phase stops, Err when an evaluation fails with an
    /// error that is not numerical.
    fn active_set_iteration<P: BlockLsqProblem + ?Sized>(
        &mut self,
        prob: &mut P,
        z: &mut [f64],
        lim: Limits<'_>,
        pr: &mut Progress,
        st: &mut LmState,
    ) -> Result<Option<Status>> {
        let Limits { lower, upper, opts } = lim;
        let pg = projected_gradient_norm(z, &self.g, lower, upper);
        if pg <= opts.gtol {
            return Ok(Some(Status::GradientTolerance));
        }
        if pr.nit >= opts.max_iter {
            return Ok(Some(Status::MaxIterations));
        }
        pr.nit += 1;
        self.hold_active(z, lower, upper, st.lambda);
        if !self.reduced_step(z, lower, upper) {
            return Ok(st.damp_harder(LAMBDA_RESTART).then_some(Status::NoProgress));
        }
        let (clipped, pnorm, znorm) = self.project_step(z, lower, upper);
        if pnorm <= opts.xtol * (opts.xtol + znorm) {
            return Ok(Some(Status::StepTolerance));
        }
        let known_noise = st.noise_est.max(self.noise_at_z);
        let mut pred = model_decrease(&self.h, &self.g, &self.work.step, &mut self.work.hp);
        if clipped {
            pred = self.improve_clipped_step(z, lower, upper, pred);
        }
        let cand = Candidate {
            pg,
            pred,
            clipped,
            known_noise,
        };
        match self.verdict(&cand, opts, pr, st) {
            Verdict::Evaluate => {}
            Verdict::Retry => {
                return Ok(st.damp_harder(LAMBDA_RESTART).then_some(Status::NoProgress))
            }
            Verdict::Undamp => {
                st.lambda = 0.0;
                return Ok(None);
            }
            Verdict::Stop(status) => return Ok(Some(status)),
        }
        let t = match self.judge_trial(prob, lim, pr, st, &cand)? {
            Err(status) => return Ok(Some(status)),
            Ok(t) => t,
        };
        if t.accept {
            return self.accept(prob, z, lim, pr, st, &t);
        }
        // A step along a stiff valley (κ < STIFF) is corrected before it is given up.
        let stiff = t.ct.is_finite() && !t.unmeasurable && t.kappa < STIFF;
        if stiff {
            if let Some(c) = self.correct(prob, lim, pr, t.kappa, t.pred, t.ct)? {
                let old = pr.cost;
                self.take_trial(prob, z, pr, c);
                st.moved();
                st.after_corrected_step((old - c) / t.pred, t.kappa);
                return Ok((old - c <= opts.ftol * old).then_some(Status::CostTolerance));
            }
        }
        self.reject(prob, z, lim, pr, st, &t, stiff)
    }

    /// The held set and the damping of this iteration into `work.fixed` and `work.shift`.
    ///
    /// ε-active set (Bertsekas' projected Newton): a variable within ε of a bound with the
    /// gradient pushing outward is held on that bound, with ε the size of the diagonally scaled
    /// projected-gradient step (capped), so that variables creeping towards a bound are caught
    /// instead of producing tiny projected steps.
    pub(super) fn hold_active(&mut self, z: &[f64], lower: &[f64], upper: &[f64], lambda: f64) {
        let len = z.len();
        let floor = self.scale_floor();
        let mut eps = 0.0f64;
        for k in 0..len {
            let d = self.scale(k, floor);
            eps = eps.max((z[k] - (z[k] - self.g[k] / d).clamp(lower[k], upper[k])).abs());
        }
        for k in 0..len {
            let e_l = eps.min(1e-3 * lower[k].abs().max(1.0));
            let e_u = eps.min(1e-3 * upper[k].abs().max(1.0));
            let at_l = finite_lower(lower[k]) && z[k] - lower[k] <= e_l && self.g[k] > 0.0;
            let at_u = finite_upper(upper[k]) && upper[k] - z[k] <= e_u && self.g[k] < 0.0;
            self.work.fixed[k] = self.fixed_bound[k] || at_l || at_u;
            self.work.shift[k] = lambda * self.scale(k, floor);
        }
    }

    /// Reduced damped Gauss-Newton step into `work.step`, with the held variables moved onto
    /// their bounds (s_A = bound − z, right-hand side −g_F − H_FA s_A). Free variables whose step
    /// crosses a bound while the gradient pushes outward join the held set and the step is
    /// recomputed (a few passes; factorisations are cheap next to evaluations). False if the
    /// damped matrix is not positive definite or the step is not finite.
    pub(super) fn reduced_step(&mut self, z: &[f64], lower: &[f64], upper: &[f64]) -> bool {
        let len = z.len();
        let mut ok = false;
        for _pass in 0..4 {
            let w = &mut self.work;
            for k in 0..len {
                w.trial[k] = if w.fixed[k] && !self.fixed_bound[k] {
                    let b = if self.g[k] > 0.0 { lower[k] } else { upper[k] };
                    b - z[k]
                } else {
                    0.0
                };
            }
            self.h.matvec(&w.trial, &mut w.hp);
            for k in 0..len {
                w.step[k] = if w.fixed[k] {
                    0.0
                } else {
                    -self.g[k] - w.hp[k]
                };
            }
            ok = self.factor_step();
            if !ok {
                break;
            }
            let w = &mut self.work;
            self.chol.solve_in_place(&mut w.step);
            let mut added = false;
            for k in 0..len {
                if w.fixed[k] {
                    w.step[k] = w.trial[k];
                } else {
                    let zk = z[k] + w.step[k];
                    if (zk < lower[k] && self.g[k] > 0.0) || (zk > upper[k] && self.g[k] < 0.0) {
                        w.fixed[k] = true;
                        added = true;
                    }
                }
            }
            if !added {
                break;
            }
        }
        ok && !self.work.step.iter().any(|s| !s.is_finite())
    }

    /// The projected trial point P(z + step) into `work.trial` and the step actually taken into
    /// `work.step` (the unprojected one kept in `clip.unprojected`). Returns whether a free
    /// variable's step was clipped, ‖step‖∞ and ‖z‖∞.
    pub(super) fn project_step(
        &mut self,
        z: &[f64],
        lower: &[f64],
        upper: &[f64],
    ) -> (bool, f64, f64) {
        let w = &mut self.work;
        let mut znorm = 0.0f64;
        let mut pnorm = 0.0f64;
        let mut clipped = false;
        for k in 0..z.len() {
            self.clip.unprojected[k] = w.step[k];
            let target = z[k] + w.step[k];
            w.trial[k] = target.clamp(lower[k], upper[k]);
            clipped |= !w.fixed[k] && w.trial[k] != target;
            w.step[k] = w.trial[k] - z[k];
            znorm = znorm.max(z[k].abs());
            pnorm = pnorm.max(w.step[k].abs());
        }
        (clipped, pnorm, znorm)
    }

    /// For a clipped step with model decrease `pred`: a projected step can be poor when coupled
    /// variables hit a bound, so two other candidates are judged by the model before any
    /// evaluation, and the one predicting the largest decrease replaces `work.step` /
    /// `work.trial`. Returns its predicted decrease.
    ///
    /// 1. The unprojected step truncated at the first bound.
    /// 2. Shorter points on the projection arc P(z + αu) (Bertsekas' projected Newton search): a
    ///    projected step can predict an increase when many coupled variables sit at a bound,
    ///    while a shorter one along the arc still descends.
    fn improve_clipped_step(
        &mut self,
        z: &[f64],
        lower: &[f64],
        upper: &[f64],
        mut pred: f64,
    ) -> f64 {
        let len = z.len();
        let (w, c) = (&mut self.work, &mut self.clip);
        let mut a = 1.0f64;
        for k in 0..len {
            let u = c.unprojected[k];
            c.truncated[k] = u;
            if u < 0.0 && finite_lower(lower[k]) {
                a = a.min((lower[k] - z[k]) / u);
            } else if u > 0.0 && finite_upper(upper[k]) {
                a = a.min((upper[k] - z[k]) / u);
            }
        }
        let a = a.max(0.0);
        for k in 0..len {
            c.truncated[k] *= a;
        }
        let (h, g) = (&self.h, &self.g);
        let pred_t = model_decrease(h, g, &c.truncated, &mut w.hp);
        if pred_t > pred {
            pred = pred_t;
            for k in 0..len {
                w.step[k] = c.truncated[k];
                w.trial[k] = (z[k] + c.truncated[k]).clamp(lower[k], upper[k]);
            }
        }
        let mut alpha = 1.0;
        for _ in 0..6 {
            alpha *= 0.5;
            for k in 0..len {
                c.arc[k] = (z[k] + alpha * c.unprojected[k]).clamp(lower[k], upper[k]) - z[k];
            }
            let pred_a = model_decrease(h, g, &c.arc, &mut w.hp);
            if pred_a > pred {
                pred = pred_a;
                for k in 0..len {
                    w.step[k] = c.arc[k];
                    w.trial[k] = z[k] + c.arc[k];
                }
            }
        }
        pred
    }

    /// The tests made before spending an evaluation on the candidate.
    fn verdict(
        &self,
        cand: &Candidate,
        opts: &SolverOptions,
        pr: &Progress,
        st: &LmState,
    ) -> Verdict {
        let Candidate {
            pg,
            pred,
            clipped,
            known_noise,
        } = *cand;
        let moves = self.work.step.iter().any(|&s| s != 0.0);
        let resolvable = 2.0 * known_noise.max(NOISE * pr.cost.abs().max(1.0));
        if !moves || (pred <= 0.0 && pred.abs() > resolvable) {
            // No candidate moves, or the model predicts no decrease along any: damp harder and
            // recompute (factorisations are cheap next to an evaluation), do not evaluate.
            return Verdict::Retry;
        }
        if !clipped
            && st.lambda <= 1.0
            && pred <= 2.0 * known_noise
            && pg <= NOISE_PG * self.gnoise_at_z
        {
            // Nothing left that J or ∇J can resolve: stop before spending an evaluation.
            return Verdict::Stop(Status::NoiseFloor);
        }
        if !clipped && st.lambda <= DTOL_MAX_LAMBDA && pred <= opts.dtol {
            // The Gauss-Newton decrement is the undamped step's pred (a clipped step's pred says
            // nothing about the free minimiser). A damped step can predict far less than it:
            // λ·diag H may dwarf the curvature of the directions that matter (stiff weights;
            // module `damping`), so a small damped pred only stops the phase once the undamped
            // step has failed since the last move; otherwise the undamped step is computed.
            if st.lambda == 0.0 || st.undamped_failed {
                return Verdict::Stop(Status::DecrementTolerance);
            }
            return Verdict::Undamp;
        }
        Verdict::Evaluate
    }

    /// Evaluates the trial point and decides whether to accept it, or Err(status) when repeated
    /// steps below J's rounding noise stop the phase (the outer Err: the evaluation failed with
    /// an error that is not numerical).
    ///
    /// Below the rounding noise of J (GP variances are differences of O(σ_f²) numbers) the gain
    /// ratio is meaningless: the step is accepted if it lowers the projected gradient instead,
    /// and the phase stops if that fails repeatedly.
    fn judge_trial<P: BlockLsqProblem + ?Sized>(
        &mut self,
        prob: &mut P,
        lim: Limits<'_>,
        pr: &mut Progress,
        st: &mut LmState,
        cand: &Candidate,
    ) -> Result<std::result::Result<Trial, Status>> {
        let len = self.g.len();
        let Candidate {
            pg,
            pred,
            clipped,
            known_noise,
        } = *cand;
        let w = &mut self.work;
        let gp: f64 = (0..len).map(|k| self.g[k] * w.step[k]).sum();
        let ct = Error::as_trial_cost(prob.evaluate(&w.trial, true))?;
        pr.nfev += 1;
        let rho = (pr.cost - ct) / pred;
        let mut accept = ct.is_finite() && pred > 0.0 && rho > ARMIJO;
        let mut noise = known_noise.max(NOISE * pr.cost.abs().max(1.0));
        let mismatch = (ct - (pr.cost - pred)).abs();
        if !accept
            && ct.is_finite()
            && pred > 0.0
            && mismatch > 10.0 * pred
            && mismatch <= NOISE_MAX * pr.cost.abs()
        {
            // A small step that "failed" by far more than its predicted decrease, by an amount
            // J's rounding could explain: the mismatch is rounding noise, not model error. (A
            // larger mismatch is model error: along a stiff valley a long step misses by
            // many times J.)
            st.noise_est = st.noise_est.max(mismatch);
            noise = noise.max(st.noise_est);
        }
        let unmeasurable = !clipped && pred <= 2.0 * noise;
        let mut pg_trial = f64::NAN;
        if unmeasurable && ct.is_finite() {
            prob.gradient_into(&mut w.hp);
            pg_trial = projected_gradient_norm(&w.trial, &w.hp, lim.lower, lim.upper);
        }
        if !accept && unmeasurable && ct.is_finite() {
            if pg_trial < pg {
                accept = true;
            } else {
                st.noise_failures += 1;
                if st.noise_failures >= 3 {
                    pr.derivs_at_z = false;
                    return Ok(Err(Status::CostTolerance));
                }
            }
        }
        Ok(Ok(Trial {
            ct,
            rho,
            gp,
            pred,
            unmeasurable,
            accept,
            pg_ratio: pg_trial / pg,
            kappa: self.step_curvature(-2.0 * (pred + gp)),
        }))
    }

    /// Moves to the accepted trial point, lowers the damping (fast after a well-predicted step,
    /// by Nielsen's rule otherwise), applies the `ftol` test and tries the parabola's minimiser
    /// along the step. Some(status) when the phase stops.
    fn accept<P: BlockLsqProblem + ?Sized>(
        &mut self,
        prob: &mut P,
        z: &mut [f64],
        lim: Limits<'_>,
        pr: &mut Progress,
        st: &mut LmState,
        t: &Trial,
    ) -> Result<Option<Status>> {
        let opts = lim.opts;
        let Trial {
            ct,
            rho,
            gp,
            unmeasurable,
            ..
        } = *t;
        st.moved();
        let decrease = pr.cost - ct;
        let old = pr.cost;
        self.take_trial(prob, z, pr, ct);
        if unmeasurable {
            st.after_unmeasurable_step(t.pg_ratio, rho, t.kappa);
            return Ok(None);
        }
        st.after_step(rho, t.kappa);
        if decrease <= opts.ftol * old {
            return Ok(Some(Status::CostTolerance));
        }
        // Along flat directions the Gauss-Newton model overestimates the curvature (rho ≈ 2,
        // slow linear convergence): try the parabola's minimiser along the step, keep it if it
        // costs less. The same parabola also shortens steps that overshoot (rho well below 1).
        let c = 2.0 * (ct - old - gp);
        let a_star = if c > 0.0 { -gp / c } else { f64::INFINITY };
        if gp < 0.0 && !(0.7..=1.5).contains(&a_star) {
            let a = a_star.clamp(0.2, EXTRAP_MAX);
            // z is already z_old + step
            let c2 = self.evaluate_along_step(prob, z, lim, pr, a - 1.0)?;
            if c2.is_finite() && c2 < pr.cost {
                self.take_trial(prob, z, pr, c2);
            } else {
                pr.derivs_at_z = false;
            }
        }
        Ok(None)
    }

    /// After a rejected trial point: before damping harder, tries the minimiser of the parabola
    /// through J(0), J'(0) and J(1) along the same step (a one-evaluation line search), unless
    /// the step was `corrected` in vain (along a stiff valley the parabola only shortens the
    /// step to a crawl). Some(NoProgress) when the damping is exhausted.
    #[allow(clippy::too_many_arguments)]
    fn reject<P: BlockLsqProblem + ?Sized>(
        &mut self,
        prob: &mut P,
        z: &mut [f64],
        lim: Limits<'_>,
        pr: &mut Progress,
        st: &mut LmState,
        t: &Trial,
        corrected: bool,
    ) -> Result<Option<Status>> {
        let Trial {
            ct,
            gp,
            pred,
            unmeasurable,
            ..
        } = *t;
        pr.derivs_at_z = false;
        let c = 2.0 * (ct - pr.cost - gp);
        if ct.is_finite() && !unmeasurable && !corrected && gp < 0.0 && c > 0.0 {
            let a = (-gp / c).clamp(0.05, 0.9);
            let php = -2.0 * (pred + gp); // stepᵀ H step
            let pred2 = -(a * gp + 0.5 * a * a * php);
            let c2 = self.evaluate_along_step(prob, z, lim, pr, a)?;
            if c2.is_finite() && pred2 > 0.0 && pr.cost - c2 > ARMIJO * pred2 {
                self.take_trial(prob, z, pr, c2);
                st.noise_failures = 0;
                st.lambda *= 2.0;
                return Ok(None);
            }
        }
        Ok(st.damp_harder(t.kappa).then_some(Status::NoProgress))
    }

    /// J at P(z + a·step) (left in `work.trial`), +∞ if the evaluation fails numerically (any
    /// other error is returned); the problem's derivatives then refer to that point.
    fn evaluate_along_step<P: BlockLsqProblem + ?Sized>(
        &mut self,
        prob: &mut P,
        z: &[f64],
        lim: Limits<'_>,
        pr: &mut Progress,
        a: f64,
    ) -> Result<f64> {
        let Limits { lower, upper, .. } = lim;
        let w = &mut self.work;
        for k in 0..z.len() {
            w.trial[k] = (z[k] + a * w.step[k]).clamp(lower[k], upper[k]);
        }
        let c2 = Error::as_trial_cost(prob.evaluate(&w.trial, true))?;
        pr.nfev += 1;
        Ok(c2)
    }

    /// Moves z to `work.trial`, whose cost is `cost` and whose derivatives the problem holds
    /// (it was the last point evaluated), and takes them.
    fn take_trial<P: BlockLsqProblem + ?Sized>(
        &mut self,
        prob: &P,
        z: &mut [f64],
        pr: &mut Progress,
        cost: f64,
    ) {
        z.copy_from_slice(&self.work.trial);
        pr.cost = cost;
        pr.derivs_at_z = true;
        self.take_derivatives(prob);
    }
}
