//! [`BoxLsqSolver`]: the solver's buffers, the driver [`BoxLsqSolver::solve`] (input checks, the
//! choice of phases, the fallback when the barrier phase ends above the start) and what both
//! phases share (their progress, constants, the Marquardt scaling).

// Index loops over variables touch several parallel arrays (z, bounds, duals, steps) and read
// better than zipped iterator chains.
#![allow(clippy::needless_range_loop)]

use super::block_tridiag::InverseBlocks;
use super::bordered::BorderedCholesky;
use super::hessian::GnHessian;
use super::sandwich::sandwich_diagonal_blocks;
use super::{
    projected_gradient_norm, BlockLsqProblem, InteriorMode, SolveReport, SolverOptions, Status,
};
use crate::error::{check_finite, check_len, Error, Result};

/// Work buffers of the solver, reused across calls (nothing is allocated once sized).
///
/// `g`, `h` and the two noise estimates always describe one point (the current z
/// whenever [`Progress::derivs_at_z`] holds); the scratch vectors are grouped by who uses them.
#[derive(Debug, Default, Clone)]
pub struct BoxLsqSolver {
    pub(super) chol: BorderedCholesky,
    /// The projected start, kept while the (non-monotone) barrier phase runs.
    pub(super) z0: Vec<f64>,
    /// Gradient 2Jᵀr of the last point taken.
    pub(super) g: Vec<f64>,
    /// Gauss-Newton Hessian 2JᵀJ of the last point taken.
    pub(super) h: GnHessian,
    /// Variables fixed by lower == upper.
    pub(super) fixed_bound: Vec<bool>,
    /// The damped Gauss-Newton step of either phase.
    pub(super) work: StepWork,
    /// The barrier phase's bound multipliers.
    pub(super) duals: Duals,
    /// The active-set phase's alternatives to a clipped step.
    pub(super) clip: ClipWork,
    /// The state of z kept while the active-set phase corrects a step (`correction.rs`).
    pub(super) saved: super::correction::Saved,
    /// The problem's cost and gradient noise at the point whose derivatives are in `g` and `h`.
    pub(super) noise_at_z: f64,
    pub(super) gnoise_at_z: f64,
    /// Whether `chol` holds the factor of `h` itself (no shift, nothing held): the last step
    /// was undamped and free, and `h` has not changed since, so a covariance needs no
    /// factorisation of its own.
    pub(super) chol_is_undamped: bool,
}

/// The Laplace covariances of a solved window ([`BoxLsqSolver::window_and_global_covariance`]):
/// every node's block (nodes × n × n), the global variables' (m × m) and the last node's with
/// the global variables (n × m), row-major.
#[derive(Debug, Default, Clone)]
pub struct Covariances {
    pub window: Option<Vec<f64>>,
    pub global: Option<Vec<f64>>,
    pub cross: Option<Vec<f64>>,
}

/// The linear system (H + diag(shift)) step = rhs with the `fixed` variables held, and the
/// point it leads to; used by both phases.
#[derive(Debug, Default, Clone)]
pub(super) struct StepWork {
    /// Damping (and in the barrier phase Σ) added to the diagonal.
    pub(super) shift: Vec<f64>,
    /// Variables held this iteration (unit row and column in the factorisation).
    pub(super) fixed: Vec<bool>,
    /// Right-hand side, then the step.
    pub(super) step: Vec<f64>,
    /// The trial point (in the active-set phase first the held variables' moves to their bound).
    pub(super) trial: Vec<f64>,
    /// Scratch: H·s products, a gradient at the trial point, a second trial point.
    pub(super) hp: Vec<f64>,
}

/// Multipliers of the lower and upper bounds and their Newton steps (barrier phase).
#[derive(Debug, Default, Clone)]
pub(super) struct Duals {
    pub(super) yl: Vec<f64>,
    pub(super) yu: Vec<f64>,
    pub(super) dyl: Vec<f64>,
    pub(super) dyu: Vec<f64>,
}

/// The active-set phase's candidates when the projected step was clipped by a bound.
#[derive(Debug, Default, Clone)]
pub(super) struct ClipWork {
    /// The step before projection on the box.
    pub(super) unprojected: Vec<f64>,
    /// The unprojected step truncated at the first bound it meets.
    pub(super) truncated: Vec<f64>,
    /// A shorter step along the projection arc P(z + αu) − z.
    pub(super) arc: Vec<f64>,
}

/// The box and the options of one solve, handed together to the steps of both phases.
#[derive(Clone, Copy)]
pub(super) struct Limits<'a> {
    pub(super) lower: &'a [f64],
    pub(super) upper: &'a [f64],
    pub(super) opts: &'a SolverOptions,
}

/// Mutable state shared by the two phases.
pub(super) struct Progress {
    pub(super) cost: f64,
    pub(super) nit: usize,
    pub(super) nfev: usize,
    /// Whether the problem's stored derivatives are those at the current z.
    pub(super) derivs_at_z: bool,
}

pub(super) const ARMIJO: f64 = 1e-4;
pub(super) const LAMBDA_MAX: f64 = 1e16;
/// Relative size below which a predicted decrease of J cannot be verified by evaluating J
/// (the floor of the solver's running noise estimate).
pub(super) const NOISE: f64 = 1e-10;
/// Largest mismatch between a failed step's cost and its prediction, relative to J, that the
/// active-set phase takes for rounding noise of J (a larger one is model error).
pub(super) const NOISE_MAX: f64 = 1e-4;
/// A projected gradient within this multiple of the gradient's rounding noise is noise (the
/// noise estimate is an ∞-norm of standard deviations; the steepest components sit in
/// directions of large curvature, where a large gradient is a tiny distance).
pub(super) const NOISE_PG: f64 = 10.0;
/// Longest extrapolated step (in multiples of the Gauss-Newton step) tried along flat directions.
pub(super) const EXTRAP_MAX: f64 = 10.0;
/// Largest Marquardt damping at which a damped step may stop the active-set phase on `dtol`
/// (only once the undamped step has failed since the last move).
pub(super) const DTOL_MAX_LAMBDA: f64 = 1e-3;

pub(super) fn finite_lower(l: f64) -> bool {
    l > f64::NEG_INFINITY
}
pub(super) fn finite_upper(u: f64) -> bool {
    u < f64::INFINITY
}

/// The checks of [`BoxLsqSolver::solve`]'s arrays, naming the bad argument (`len` = nodes · n
/// + global variables).
fn check_inputs(len: usize, z: &[f64], lower: &[f64], upper: &[f64]) -> Result<()> {
    if len == 0 {
        return Err(Error::invalid("z", "the problem has no variables"));
    }
    check_len("z", z, len)?;
    check_len("lower", lower, len)?;
    check_len("upper", upper, len)?;
    check_finite("z", z)?;
    if let Some(k) = (0..len).find(|&k| lower[k].is_nan() || upper[k].is_nan()) {
        return Err(Error::invalid("bounds", format!("NaN bound at index {k}")));
    }
    if let Some(k) = (0..len).find(|&k| lower[k] > upper[k]) {
        return Err(Error::invalid(
            "bounds",
            format!("lower > upper at index {k}"),
        ));
    }
    Ok(())
}

impl BoxLsqSolver {
    pub fn new() -> Self {
        Self::default()
    }

    fn resize(&mut self, nodes: usize, n: usize, m: usize) {
        self.chol_is_undamped = false;
        self.h.resize(nodes, n, m);
        let len = nodes * n + m;
        for v in [
            &mut self.g,
            &mut self.work.shift,
            &mut self.work.step,
            &mut self.work.trial,
            &mut self.work.hp,
            &mut self.duals.yl,
            &mut self.duals.yu,
            &mut self.duals.dyl,
            &mut self.duals.dyu,
            &mut self.clip.unprojected,
            &mut self.clip.truncated,
            &mut self.clip.arc,
        ] {
            v.resize(len, 0.0);
        }
        self.work.fixed.resize(len, false);
        self.fixed_bound.resize(len, false);
    }

    pub(super) fn take_derivatives<P: BlockLsqProblem + ?Sized>(&mut self, prob: &P) {
        self.noise_at_z = prob.cost_noise();
        self.gnoise_at_z = prob.gradient_noise();
        prob.gradient_into(&mut self.g);
        self.h.take(prob);
        self.chol_is_undamped = false;
    }

    /// Factors H + diag(`work.shift`) with `work.fixed` held into `chol` (see
    /// [`BorderedCholesky::factor`]) and records whether that is H itself.
    pub(super) fn factor_step(&mut self) -> bool {
        let w = &self.work;
        let ok = self.chol.factor(&self.h, &w.shift, &w.fixed);
        self.chol_is_undamped =
            ok && w.shift.iter().all(|&s| s == 0.0) && !w.fixed.iter().any(|&f| f);
        ok
    }

    /// Marquardt scaling: the diagonal of the Gauss-Newton Hessian, floored at
    /// [`Self::scale_floor`] (computed once by the caller for a whole loop over k).
    pub(super) fn scale(&self, k: usize, floor: f64) -> f64 {
        self.h.diagonal(k).max(floor)
    }

    /// The floor of the Marquardt scaling ([`GnHessian::scale_floor`]).
    pub(super) fn scale_floor(&self) -> f64 {
        self.h.scale_floor()
    }

    /// 4·sym(last n×n block of H⁻¹), H the Gauss-Newton Hessian at the point the last successful
    /// `solve` returned (its blocks are still in the solver's buffers): the Laplace covariance
    /// of the last node when J is 4× a negative log-likelihood, as in GP-MHE. None before any
    /// solve, or if H is singular or the block is not finite.
    pub fn last_node_covariance(&mut self) -> Option<Vec<f64>> {
        let b = self.undamped_inverse_blocks(InverseBlocks::Last)?;
        Some(symmetrised_blocks(b, self.h.n))
    }

    /// 4·sym of every diagonal n×n block of H⁻¹ (nodes × n × n; see `last_node_covariance`,
    /// whose block is the last one, bit for bit): the Laplace covariance of every node of the
    /// window. None as for `last_node_covariance`.
    pub fn window_covariance(&mut self) -> Option<Vec<f64>> {
        let n = self.h.n;
        let b = self.undamped_inverse_blocks(InverseBlocks::All)?;
        Some(symmetrised_blocks(b, n))
    }

    /// 4·sym of every diagonal n×n block of H⁻¹GH⁻¹ (nodes × n × n), H the Gauss-Newton Hessian
    /// at the point the last successful `solve` returned and G = (`g_diag`, `g_off`) in its
    /// block-tridiagonal storage: the covariance of the nodes when the residuals are weighted
    /// by other than their inverse covariances (`sandwich.rs`). None with global variables, before
    /// any solve, or if H is singular or a block is not finite.
    pub fn sandwich_window_covariance(&self, g_diag: &[f64], g_off: &[f64]) -> Option<Vec<f64>> {
        let (nodes, n) = (self.h.nodes, self.h.n);
        if nodes == 0 || self.h.m > 0 {
            return None;
        }
        let b = sandwich_diagonal_blocks(nodes, n, (&self.h.diag, &self.h.off), (g_diag, g_off))?;
        Some(symmetrised_blocks(b, n))
    }

    /// [`window_covariance`](Self::window_covariance), 4·sym of the global variables' block of
    /// H⁻¹ (m × m: their Laplace covariance) and 4× the block of the last node with them
    /// (n × m: the cross covariance), from one factorisation; all None before any solve or if H
    /// is singular, the global ones without global variables.
    pub fn window_and_global_covariance(&mut self) -> Covariances {
        if !self.factor_undamped() {
            return Covariances::default();
        }
        let n = self.h.n;
        let window = self
            .chol
            .inverse_blocks(InverseBlocks::All)
            .map(|b| symmetrised_blocks(b, n));
        let (m, inverse) = (self.h.m, self.chol.global_block_of_inverse());
        let cross = inverse.as_deref().and_then(|b| {
            let c = self.chol.last_node_global_block(b)?;
            Some(c.iter().map(|v| 4.0 * v).collect())
        });
        Covariances {
            window,
            global: inverse.map(|b| symmetrised_blocks(b, m)),
            cross,
        }
    }

    /// Factors the undamped H with nothing held, in the solver's own factor and scratch,
    /// unless the last step's factor is already that (the same call on the same H: the same
    /// bits).
    fn factor_undamped(&mut self) -> bool {
        if self.h.nodes == 0 {
            return false;
        }
        if self.chol_is_undamped {
            return true;
        }
        self.work.shift.fill(0.0);
        self.work.fixed.fill(false);
        self.factor_step()
    }

    /// The `which` diagonal blocks of H⁻¹ (see `last_node_covariance`), factored in the
    /// solver's own factor with its own scratch (`shift`, `fixed`), so no per-update allocation
    /// of blocks.
    fn undamped_inverse_blocks(&mut self, which: InverseBlocks) -> Option<Vec<f64>> {
        if !self.factor_undamped() {
            return None;
        }
        self.chol.inverse_blocks(which)
    }

    /// Minimises J(z) over lower ≤ z ≤ upper starting from `z` (a warm start; projected onto the
    /// box first) and writes the best point found into `z`. Bounds may be ±∞ and lower == upper
    /// fixes a variable. The returned cost is never above the cost at the projected start.
    /// Errors only on invalid input, when J is not finite at the start, or when an evaluation
    /// fails with an error that is not numerical (bad model output, an interrupt: z is then
    /// unspecified); otherwise z is always finite and the problem's derivatives refer to the
    /// returned z. A numerical failure at a trial point only rejects that point.
    pub fn solve<P: BlockLsqProblem + ?Sized>(
        &mut self,
        prob: &mut P,
        z: &mut [f64],
        lower: &[f64],
        upper: &[f64],
        opts: &SolverOptions,
    ) -> Result<SolveReport> {
        opts.validate()?;
        let (nodes, n, m) = (prob.n_nodes(), prob.node_dim(), prob.global_dim());
        let len = nodes * n + m;
        check_inputs(len, z, lower, upper)?;
        self.resize(nodes, n, m);
        for k in 0..len {
            z[k] = z[k].clamp(lower[k], upper[k]);
            self.fixed_bound[k] = lower[k] == upper[k];
        }

        let run_interior = self.wants_interior(z, lower, upper, opts);

        let lim = Limits { lower, upper, opts };
        let mut pr = Progress {
            cost: f64::NAN,
            nit: 0,
            nfev: 0,
            derivs_at_z: false,
        };
        let mut interior_iterations = 0;
        self.start(prob, z, &mut pr)?;
        let status;
        if !run_interior {
            status = self.active_set_phase(prob, z, lim, &mut pr)?;
        } else {
            // The barrier phase is not monotone in J: keep the (projected) start and its cost,
            // and fall back to the active-set phase from there if the result costs more.
            let cost0 = pr.cost;
            self.z0.clear();
            self.z0.extend_from_slice(z);
            let status_i = self.interior_path(prob, z, lim, &mut pr)?;
            interior_iterations = pr.nit;
            if pr.cost > cost0 {
                z.copy_from_slice(&self.z0);
                self.start(prob, z, &mut pr)?;
                status = self.active_set_phase(prob, z, lim, &mut pr)?;
            } else {
                status = status_i;
            }
        }
        if !pr.derivs_at_z {
            // Leave the problem's derivatives at the returned point (the caller may use them,
            // e.g. for a covariance); the cost there is already known.
            let c = prob.evaluate(z, true)?;
            pr.nfev += 1;
            pr.cost = c;
            self.take_derivatives(prob);
        }
        Ok(SolveReport {
            status,
            cost: pr.cost,
            projected_gradient: projected_gradient_norm(z, &self.g, lower, upper),
            nit: pr.nit,
            interior_iterations,
            nfev: pr.nfev,
        })
    }

    /// Whether the interior phase runs first (see [`InteriorMode`]): some free variable has a
    /// finite bound and, for `Auto`, lies within `interior_zone` of it.
    fn wants_interior(
        &self,
        z: &[f64],
        lower: &[f64],
        upper: &[f64],
        opts: &SolverOptions,
    ) -> bool {
        let len = z.len();
        let has_bounds = (0..len)
            .any(|k| !self.fixed_bound[k] && (finite_lower(lower[k]) || finite_upper(upper[k])));
        let near = (0..len).any(|k| {
            if self.fixed_bound[k] {
                return false;
            }
            let (l, u) = (lower[k], upper[k]);
            let w_l = if finite_upper(u) {
                u - l
            } else {
                l.abs().max(1.0)
            };
            let w_u = if finite_lower(l) {
                u - l
            } else {
                u.abs().max(1.0)
            };
            (finite_lower(l) && z[k] - l <= opts.interior_zone * w_l)
                || (finite_upper(u) && u - z[k] <= opts.interior_zone * w_u)
        });
        match opts.interior {
            InteriorMode::Always => has_bounds,
            InteriorMode::Auto => has_bounds && near,
            InteriorMode::Never => false,
        }
    }

    /// Barrier phase from a pushed-inside copy of z, then the active-set polish.
    fn interior_path<P: BlockLsqProblem + ?Sized>(
        &mut self,
        prob: &mut P,
        z: &mut [f64],
        lim: Limits<'_>,
        pr: &mut Progress,
    ) -> Result<Status> {
        self.push_inside(z, lim.lower, lim.upper);
        self.start(prob, z, pr)?;
        self.interior_phase(prob, z, lim, pr)?;
        self.active_set_phase(prob, z, lim, pr)
    }

    pub(super) fn start<P: BlockLsqProblem + ?Sized>(
        &mut self,
        prob: &mut P,
        z: &[f64],
        pr: &mut Progress,
    ) -> Result<()> {
        let c = prob.evaluate(z, true)?;
        pr.nfev += 1;
        if !c.is_finite() {
            return Err(Error::numerical(
                "the window cost is not finite at the starting point",
            ));
        }
        pr.cost = c;
        pr.derivs_at_z = true;
        self.take_derivatives(prob);
        Ok(())
    }
}

/// 4·sym(B) = 2(B + Bᵀ) of every n×n row-major block B of `blocks`, in place (entry (r, c) and
/// (c, r) get the same sum: addition commutes).
fn symmetrised_blocks(mut blocks: Vec<f64>, n: usize) -> Vec<f64> {
    for b in blocks.chunks_exact_mut(n * n) {
        for r in 0..n {
            for c in r..n {
                let v = 2.0 * (b[r * n + c] + b[c * n + r]);
                b[r * n + c] = v;
                b[c * n + r] = v;
            }
        }
    }
    blocks
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solver::test_problem::{random_z, reference_projected_gradient, strict, Synthetic};

    #[test]
    fn unconstrained_solution_is_stationary_and_matches_reference() {
        for seed in 0..5u64 {
            let (nodes, n) = (6, 2);
            let mut p = Synthetic::new(nodes, n, 100 + seed);
            let lo = vec![f64::NEG_INFINITY; nodes * n];
            let hi = vec![f64::INFINITY; nodes * n];
            let mut z = random_z(nodes, n, 200 + seed);
            let z0 = z.clone();
            let mut s = BoxLsqSolver::new();
            let rep = s.solve(&mut p, &mut z, &lo, &hi, &strict()).unwrap();
            assert!(rep.status.is_success(), "{rep:?}");
            assert!(rep.projected_gradient <= 1e-6, "{rep:?}");
            assert_eq!(rep.interior_iterations, 0);
            assert!((p.evaluate(&z, true).unwrap() - rep.cost).abs() <= 1e-12 * (1.0 + rep.cost));
            let (_, cref) = reference_projected_gradient(&mut p, &z0, &lo, &hi);
            assert!(
                rep.cost <= cref * (1.0 + 1e-6) + 1e-12,
                "{} vs {cref}",
                rep.cost
            );
        }
    }

    #[test]
    fn covariance_reuses_the_last_undamped_factor_with_the_same_bits() {
        // A decrement stop after an undamped, free step leaves H's own factor in the solver;
        // the covariances from it equal those from a fresh factorisation bit for bit.
        let mut reused = [0, 0];
        for (seed, m) in (0..6u64).zip([0usize, 0, 0, 3, 3, 3]) {
            let (nodes, n) = (6, 2);
            let mut p = Synthetic::with_globals(nodes, n, m, 100 + seed);
            let len = nodes * n + m;
            let (lo, hi) = (vec![f64::NEG_INFINITY; len], vec![f64::INFINITY; len]);
            let mut z = random_z(nodes, n, 200 + seed);
            z.extend(random_z(1, m, 300 + seed));
            let opts = SolverOptions {
                dtol: 1e-3,
                ..SolverOptions::default()
            };
            let mut s = BoxLsqSolver::new();
            s.solve(&mut p, &mut z, &lo, &hi, &opts).unwrap();
            reused[(m > 0) as usize] += s.chol_is_undamped as usize;
            let c = s.window_and_global_covariance();
            s.chol_is_undamped = false;
            let fresh = s.window_and_global_covariance();
            assert!(c.window.is_some() && c.window == fresh.window, "{seed}");
            assert!(c.global == fresh.global && c.cross == fresh.cross, "{seed}");
            assert_eq!(s.window_covariance(), fresh.window);
        }
        assert!(
            reused[0] > 0 && reused[1] > 0,
            "the test must exercise the reuse: {reused:?}"
        );
    }

    #[test]
    fn decrement_stop_leaves_at_most_dtol_to_gain() {
        // The default dtol stops once the next Gauss-Newton step predicts less than dtol;
        // continuing to gtol from there must gain about that much, not more.
        let mut early = 0;
        for seed in 0..5u64 {
            let (nodes, n) = (6, 2);
            let mut p = Synthetic::new(nodes, n, 100 + seed);
            let lo = vec![f64::NEG_INFINITY; nodes * n];
            let hi = vec![f64::INFINITY; nodes * n];
            let mut z = random_z(nodes, n, 200 + seed);
            let opts = SolverOptions {
                dtol: 1e-3,
                ..SolverOptions::default()
            };
            let rep = BoxLsqSolver::new()
                .solve(&mut p, &mut z, &lo, &hi, &opts)
                .unwrap();
            assert!(rep.status.is_success(), "{rep:?}");
            early += (rep.status == Status::DecrementTolerance) as usize;
            let strict_rep = BoxLsqSolver::new()
                .solve(&mut p, &mut z, &lo, &hi, &strict())
                .unwrap();
            assert!(strict_rep.projected_gradient <= 1e-6, "{strict_rep:?}");
            assert!(
                rep.cost - strict_rep.cost <= 2.0 * opts.dtol,
                "{} vs {}",
                rep.cost,
                strict_rep.cost
            );
        }
        assert!(early > 0, "the test must exercise the decrement stop");
    }

    #[test]
    fn bounded_solution_satisfies_kkt_and_is_no_worse_than_reference() {
        let mut n_active = 0;
        for seed in 0..4u64 {
            let (nodes, n) = (8, 2);
            let mut p = Synthetic::new(nodes, n, 300 + seed);
            // Tight box so that some bounds are active at the optimum.
            let lo = vec![-0.4; nodes * n];
            let hi = vec![0.5; nodes * n];
            for mode in [
                InteriorMode::Auto,
                InteriorMode::Always,
                InteriorMode::Never,
            ] {
                let mut z = random_z(nodes, n, 400 + seed);
                let z0 = z.clone();
                let opts = SolverOptions {
                    interior: mode,
                    ..strict()
                };
                let rep = BoxLsqSolver::new()
                    .solve(&mut p, &mut z, &lo, &hi, &opts)
                    .unwrap();
                assert!(rep.status.is_success(), "{mode:?} {rep:?}");
                assert!(rep.projected_gradient <= 1e-6, "{mode:?} {rep:?}");
                assert!(z.iter().all(|&v| (-0.4..=0.5).contains(&v)));
                if mode == InteriorMode::Always {
                    assert!(rep.interior_iterations > 0);
                }
                n_active += z.iter().filter(|&&v| v == -0.4 || v == 0.5).count();
                let (_, cref) = reference_projected_gradient(&mut p, &z0, &lo, &hi);
                assert!(
                    rep.cost <= cref * (1.0 + 1e-6) + 1e-12,
                    "{mode:?} {} vs {cref}",
                    rep.cost
                );
            }
        }
        assert!(n_active > 0, "the test must exercise active bounds");
    }

    #[test]
    fn start_on_bound_is_released_by_the_interior_phase() {
        // Optimum well inside, start exactly on the lower bound with the gradient pushing out.
        let (nodes, n) = (5, 2);
        let mut p = Synthetic::new(nodes, n, 9);
        let lo = vec![-3.0; nodes * n];
        let hi = vec![3.0; nodes * n];
        let mut z = vec![-3.0; nodes * n];
        let opts = SolverOptions {
            interior: InteriorMode::Always,
            ..strict()
        };
        let rep = BoxLsqSolver::new()
            .solve(&mut p, &mut z, &lo, &hi, &opts)
            .unwrap();
        assert!(rep.interior_iterations > 0);
        assert!(rep.projected_gradient <= 1e-6, "{rep:?}");
        let mut g = vec![0.0; nodes * n];
        p.evaluate(&z, true).unwrap();
        p.gradient_into(&mut g);
        // Interior optimum: the full gradient vanishes and nothing sits on a bound.
        assert!(g.iter().all(|v| v.abs() <= 1e-6));
        assert!(z.iter().all(|&v| v > -3.0 && v < 3.0));
    }

    #[test]
    fn all_bounds_active_returns_the_fixed_point() {
        let (nodes, n) = (4, 2);
        let mut p = Synthetic::new(nodes, n, 1);
        let fix = random_z(nodes, n, 2);
        let mut z = vec![0.0; nodes * n];
        let rep = BoxLsqSolver::new()
            .solve(&mut p, &mut z, &fix, &fix, &strict())
            .unwrap();
        assert_eq!(z, fix);
        assert_eq!(rep.status, Status::GradientTolerance);
        assert_eq!(rep.projected_gradient, 0.0);
    }

    #[test]
    fn horizon_one_and_single_node() {
        for nodes in [1usize, 2] {
            let mut p = Synthetic::new(nodes, 3, 21);
            let lo = vec![-1.0; nodes * 3];
            let hi = vec![1.0; nodes * 3];
            let mut z = vec![0.0; nodes * 3];
            let rep = BoxLsqSolver::new()
                .solve(&mut p, &mut z, &lo, &hi, &strict())
                .unwrap();
            assert!(
                rep.projected_gradient <= 1e-6 && rep.status.is_success(),
                "{rep:?}"
            );
        }
    }

    #[test]
    fn infinite_cost_at_trial_points_is_survived() {
        let (nodes, n) = (5, 2);
        let mut p = Synthetic::new(nodes, n, 33);
        p.a[0] = 3.0; // the prior pulls z[0] towards the blow-up region
        p.blowup = 0.7;
        let lo = vec![f64::NEG_INFINITY; nodes * n];
        let hi = vec![f64::INFINITY; nodes * n];
        let mut z = vec![0.0; nodes * n];
        let rep = BoxLsqSolver::new()
            .solve(&mut p, &mut z, &lo, &hi, &strict())
            .unwrap();
        assert!(z.iter().all(|v| v.is_finite()) && rep.cost.is_finite());
        assert!(z[0] <= 0.7);
    }

    /// `Synthetic` whose k-th evaluation (1-based) fails with `err`.
    struct FailsAt {
        p: Synthetic,
        k: usize,
        calls: usize,
        err: Error,
    }

    impl BlockLsqProblem for FailsAt {
        fn n_nodes(&self) -> usize {
            self.p.n_nodes()
        }
        fn node_dim(&self) -> usize {
            self.p.node_dim()
        }
        fn evaluate(&mut self, z: &[f64], want_derivatives: bool) -> Result<f64> {
            self.calls += 1;
            if self.calls == self.k {
                return Err(self.err.clone());
            }
            self.p.evaluate(z, want_derivatives)
        }
        fn gradient_into(&self, g: &mut [f64]) {
            self.p.gradient_into(g)
        }
        fn gauss_newton_blocks_into(&self, diag: &mut [f64], off: &mut [f64]) {
            self.p.gauss_newton_blocks_into(diag, off)
        }
    }

    #[test]
    fn only_numerical_failures_at_trial_points_are_survived_other_errors_stop_the_solve() {
        let (nodes, n) = (5, 2);
        let lo = vec![0.05; nodes * n]; // the start lies near the bound: both phases run
        let hi = vec![f64::INFINITY; nodes * n];
        let solve = |k: usize, err: Error| {
            let p = Synthetic::new(nodes, n, 21);
            let mut prob = FailsAt {
                p,
                k,
                calls: 0,
                err,
            };
            let mut z = vec![0.06; nodes * n];
            let r = BoxLsqSolver::new().solve(&mut prob, &mut z, &lo, &hi, &strict());
            (r, prob.calls)
        };
        let (clean, total) = solve(0, Error::numerical("never"));
        assert!(clean.is_ok() && total > 4, "{total}");
        for k in 2..=total {
            let (r, _) = solve(k, Error::numerical("nan at a trial point"));
            assert!(r.is_ok(), "numerical failure at evaluation {k}: {r:?}");
            for err in [
                Error::interrupted("ctrl-c"),
                Error::invalid("model", "bad output"),
            ] {
                let (r, calls) = solve(k, err.clone());
                assert_eq!(r.unwrap_err(), err, "evaluation {k}");
                assert_eq!(calls, k, "the solve stops at the failing evaluation");
            }
        }
    }

    #[test]
    fn max_iterations_is_reported_and_point_is_finite() {
        let (nodes, n) = (6, 2);
        let mut p = Synthetic::new(nodes, n, 44);
        let lo = vec![-0.4; nodes * n];
        let hi = vec![0.5; nodes * n];
        let mut z = vec![0.0; nodes * n];
        let opts = SolverOptions {
            max_iter: 1,
            ..strict()
        };
        let rep = BoxLsqSolver::new()
            .solve(&mut p, &mut z, &lo, &hi, &opts)
            .unwrap();
        assert_eq!(rep.status, Status::MaxIterations);
        assert!(!rep.status.is_success());
        assert_eq!(rep.nit, 1);
        assert!(z.iter().all(|v| v.is_finite()));
    }

    #[test]
    fn invalid_input_is_rejected_naming_the_argument() {
        let mut p = Synthetic::new(3, 2, 1);
        let mut s = BoxLsqSolver::new();
        let ok = vec![0.0; 6];
        let mut z = vec![0.0; 6];
        let lo = vec![1.0; 6];
        let hi = vec![0.0; 6];
        let e = s.solve(&mut p, &mut z, &lo, &hi, &strict()).unwrap_err();
        assert!(matches!(e, Error::InvalidInput { ref arg, .. } if arg == "bounds"));
        let mut zn = vec![f64::NAN; 6];
        let e = s.solve(&mut p, &mut zn, &ok, &ok, &strict()).unwrap_err();
        assert!(matches!(e, Error::InvalidInput { ref arg, .. } if arg == "z"));
        let mut short = vec![0.0; 5];
        let e = s
            .solve(&mut p, &mut short, &ok, &ok, &strict())
            .unwrap_err();
        assert!(matches!(e, Error::InvalidInput { ref arg, .. } if arg == "z"));
        let opts = SolverOptions {
            gtol: -1.0,
            ..strict()
        };
        let e = s.solve(&mut p, &mut z, &ok, &ok, &opts).unwrap_err();
        assert!(matches!(e, Error::InvalidInput { ref arg, .. } if arg == "gtol"));
    }
}
