//! The real-time window solver (docs/user_guide/solver.rst): a bound-constrained Gauss-Newton /
//! Levenberg-Marquardt method for least-squares problems min ‖r(z)‖² s.t. lower ≤ z ≤ upper whose
//! Gauss-Newton Hessian 2JᵀJ is block-tridiagonal (the GP-MHE window: node i = window state x̄_i).
//!
//! Each linear system is solved by a block-tridiagonal Cholesky factorisation (the Riccati-like
//! recursion over the horizon, small dense nalgebra blocks), so one iteration costs O(M n³).
//!
//! Two phases:
//! 1. **Interior phase** (only when the start lies on or near a bound, or when asked): a primal-dual
//!    log-barrier Gauss-Newton method with a fraction-to-boundary rule and an Armijo line search on
//!    the barrier merit, the barrier parameter decreasing from `mu_init` to `mu_final` (IPOPT's
//!    monotone rule). It starts strictly inside the box, so early iterations cannot pin states to
//!    their bounds (docs/user_guide/solver.rst): projected/reflective least-squares methods started from the
//!    batch reactor's poor prior stop at worse minima with x1 on its bound.
//! 2. **Active-set Levenberg-Marquardt phase**: variables at a bound whose gradient pushes outward
//!    are held fixed, the others take a damped Gauss-Newton step (Marquardt scaling, Nielsen's
//!    damping update), the trial point is projected on the box and accepted on the gain ratio.
//!    It stops on the projected-gradient norm (`gtol`), the Gauss-Newton decrement (`dtol`: the
//!    next step would lower J by less than that), the step size (`xtol`), the relative cost
//!    decrease (`ftol`) or the iteration cap, and says which in [`Status`].
//!
//! The problem is reached through [`BlockLsqProblem`]; `window.rs`'s window problem implements it
//! through [`WindowLsq`]. All work buffers live in [`BoxLsqSolver`] and are reused between calls.

// Index loops over variables touch several parallel arrays (z, bounds, duals, steps) and read
// better than zipped iterator chains.
#![allow(clippy::needless_range_loop)]

use nalgebra::{Cholesky, DMatrix, DVectorView, DVectorViewMut};

use crate::error::{check_finite, check_len, Error, Result};
use crate::mhe::{StageModel, WindowEval, WindowProblem};

/// A least-squares problem J(z) = ‖r(z)‖² over `n_nodes` nodes of `node_dim` variables each whose
/// Gauss-Newton Hessian 2JᵀJ is block-tridiagonal.
pub trait BlockLsqProblem {
    fn n_nodes(&self) -> usize;
    fn node_dim(&self) -> usize;
    /// Evaluates at `z` (length n_nodes·node_dim) and returns the cost ‖r(z)‖². With
    /// `want_derivatives`, the gradient and Gauss-Newton blocks below refer to this `z` afterwards.
    fn evaluate(&mut self, z: &[f64], want_derivatives: bool) -> Result<f64>;
    /// 2Jᵀr at the last point evaluated with derivatives.
    fn gradient_into(&self, g: &mut [f64]);
    /// 2JᵀJ at the last point evaluated with derivatives: `diag` holds the n×n diagonal blocks
    /// (block i row-major at i·n·n), `off` the blocks (i, i+1).
    fn gauss_newton_blocks_into(&self, diag: &mut [f64], off: &mut [f64]);
    /// The rounding noise of J at the last point evaluated, if the problem can estimate it
    /// (cost changes below it cannot be measured); 0 when J is exact to rounding.
    fn cost_noise(&self) -> f64 {
        0.0
    }
    /// The rounding noise of the gradient (largest entry) at the last point evaluated with
    /// derivatives, if the problem can estimate it; 0 otherwise.
    fn gradient_noise(&self) -> f64 {
        0.0
    }
}

/// The GP-MHE window of `window.rs` (its model and evaluation buffers) as a [`BlockLsqProblem`].
pub struct WindowLsq<'a> {
    pub problem: &'a WindowProblem,
    pub model: &'a mut dyn StageModel,
    pub eval: &'a mut WindowEval,
}

impl BlockLsqProblem for WindowLsq<'_> {
    fn n_nodes(&self) -> usize {
        self.problem.n_nodes()
    }
    fn node_dim(&self) -> usize {
        self.problem.dim_x()
    }
    fn evaluate(&mut self, z: &[f64], want_derivatives: bool) -> Result<f64> {
        self.problem
            .evaluate(&mut *self.model, z, want_derivatives, self.eval)?;
        Ok(self.eval.cost())
    }
    fn gradient_into(&self, g: &mut [f64]) {
        self.eval.gradient_into(g);
    }
    fn gauss_newton_blocks_into(&self, diag: &mut [f64], off: &mut [f64]) {
        self.eval.gauss_newton_blocks_into(diag, off);
    }
    fn cost_noise(&self) -> f64 {
        self.eval.cost_noise()
    }
    fn gradient_noise(&self) -> f64 {
        self.eval.gradient_noise()
    }
}

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
    /// Stop when the next (nearly undamped, unclipped) Gauss-Newton step Δ predicts a decrease
    /// of J of at most dtol: pred = ½ΔᵀHΔ (H = 2JᵀJ on the free variables), the Gauss-Newton
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
    /// The next (nearly undamped, unclipped) Gauss-Newton step predicts a decrease of J of at
    /// most `dtol`: what is left to gain is below the requested accuracy.
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

/// Block-tridiagonal Cholesky factorisation A = LLᵀ of a symmetric positive-definite matrix with
/// n×n blocks: L has diagonal blocks L_i and sub-diagonal blocks X_iᵀ with X_i = L_i⁻¹ A_{i,i+1};
/// L_{i+1}L_{i+1}ᵀ = A_{i+1,i+1} − X_iᵀX_i (the Riccati-like recursion). Cost O(nodes·n³).
#[derive(Debug, Default, Clone)]
pub struct BlockTridiagCholesky {
    n: usize,
    l: Vec<DMatrix<f64>>,
    x: Vec<DMatrix<f64>>,
}

impl BlockTridiagCholesky {
    /// Factors A + diag(shift), with `diag`/`off` row-major blocks as in [`BlockLsqProblem`].
    /// Variables with `fixed[k]` get a unit row and column (their solution equals their
    /// right-hand side). Returns false if the matrix is not numerically positive definite.
    pub fn factor(
        &mut self,
        nodes: usize,
        n: usize,
        diag: &[f64],
        off: &[f64],
        shift: &[f64],
        fixed: &[bool],
    ) -> bool {
        if self.n != n || self.l.len() != nodes {
            self.n = n;
            self.l = (0..nodes).map(|_| DMatrix::zeros(n, n)).collect();
            self.x = (0..nodes.saturating_sub(1))
                .map(|_| DMatrix::zeros(n, n))
                .collect();
        }
        let nn = n * n;
        for i in 0..nodes {
            let mut a = std::mem::replace(&mut self.l[i], DMatrix::zeros(0, 0));
            for r in 0..n {
                for c in 0..=r {
                    let (kr, kc) = (i * n + r, i * n + c);
                    a[(r, c)] = if fixed[kr] || fixed[kc] {
                        if r == c {
                            1.0
                        } else {
                            0.0
                        }
                    } else if r == c {
                        diag[i * nn + r * n + c] + shift[kr]
                    } else {
                        diag[i * nn + r * n + c]
                    };
                }
            }
            if i > 0 {
                let xp = &self.x[i - 1];
                // Lower triangle of a − XᵀX (the upper part of `a` is never read).
                for r in 0..n {
                    for c in 0..=r {
                        a[(r, c)] -= xp.column(r).dot(&xp.column(c));
                    }
                }
            }
            match Cholesky::new(a) {
                Some(ch) => self.l[i] = ch.unpack_dirty(),
                None => {
                    self.l[i] = DMatrix::zeros(n, n);
                    return false;
                }
            }
            let li = &self.l[i];
            if (0..n).any(|k| !(li[(k, k)].is_finite() && li[(k, k)] > 0.0)) {
                return false;
            }
            if i + 1 < nodes {
                let x = &mut self.x[i];
                for r in 0..n {
                    for c in 0..n {
                        x[(r, c)] = if fixed[i * n + r] || fixed[(i + 1) * n + c] {
                            0.0
                        } else {
                            off[i * nn + r * n + c]
                        };
                    }
                }
                self.l[i].solve_lower_triangular_unchecked_mut(x);
            }
        }
        true
    }

    /// Solves A x = b in place (after a successful [`factor`](Self::factor)).
    pub fn solve_in_place(&self, b: &mut [f64]) {
        let n = self.n;
        let nodes = self.l.len();
        for i in 0..nodes {
            let (prev, cur) = b.split_at_mut(i * n);
            let mut cur = DVectorViewMut::from_slice(&mut cur[..n], n);
            if i > 0 {
                let yp = DVectorView::from_slice(&prev[(i - 1) * n..], n);
                cur.gemv_tr(-1.0, &self.x[i - 1], &yp, 1.0);
            }
            self.l[i].solve_lower_triangular_unchecked_mut(&mut cur);
        }
        for i in (0..nodes).rev() {
            let (cur, next) = b.split_at_mut((i + 1) * n);
            let mut cur = DVectorViewMut::from_slice(&mut cur[i * n..], n);
            if i + 1 < nodes {
                let xn = DVectorView::from_slice(&next[..n], n);
                cur.gemv(-1.0, &self.x[i], &xn, 1.0);
            }
            self.l[i].tr_solve_lower_triangular_unchecked_mut(&mut cur);
        }
    }
}

impl BlockTridiagCholesky {
    /// The last n×n diagonal block of A⁻¹ (row-major into `out`) after a successful
    /// [`factor`](Self::factor): L is block lower-bidiagonal, so (A⁻¹)_NN = L_N⁻ᵀ L_N⁻¹.
    pub fn last_block_of_inverse(&self, out: &mut [f64]) {
        let n = self.n;
        let Some(l) = self.l.last() else { return };
        let mut x = DMatrix::<f64>::identity(n, n);
        l.solve_lower_triangular_unchecked_mut(&mut x);
        let inv = x.transpose() * x;
        for r in 0..n {
            for c in 0..n {
                out[r * n + c] = inv[(r, c)];
            }
        }
    }
}

/// The last n×n block of (2JᵀJ)⁻¹ from the block-tridiagonal Gauss-Newton blocks (row-major
/// into `out`), or None when 2JᵀJ is not positive definite. O(nodes·n³).
pub fn gauss_newton_last_block_inverse(
    nodes: usize,
    n: usize,
    diag: &[f64],
    off: &[f64],
) -> Option<Vec<f64>> {
    let zero = vec![0.0; nodes * n];
    let free = vec![false; nodes * n];
    undamped_last_block_inverse(
        &mut BlockTridiagCholesky::default(),
        nodes,
        n,
        diag,
        off,
        &zero,
        &free,
    )
}

/// The last n×n block of the inverse of the undamped block-tridiagonal matrix (`zero` shifts,
/// nothing held), factored in `chol`; None if not positive definite or not finite.
fn undamped_last_block_inverse(
    chol: &mut BlockTridiagCholesky,
    nodes: usize,
    n: usize,
    diag: &[f64],
    off: &[f64],
    zero: &[f64],
    free: &[bool],
) -> Option<Vec<f64>> {
    if !chol.factor(nodes, n, diag, off, zero, free) {
        return None;
    }
    let mut out = vec![0.0; n * n];
    chol.last_block_of_inverse(&mut out);
    out.iter().all(|v| v.is_finite()).then_some(out)
}

/// y = A x for a block-tridiagonal symmetric A given by row-major `diag`/`off` blocks.
pub fn block_tridiag_matvec(
    nodes: usize,
    n: usize,
    diag: &[f64],
    off: &[f64],
    x: &[f64],
    y: &mut [f64],
) {
    let nn = n * n;
    for i in 0..nodes {
        for r in 0..n {
            let mut s = 0.0;
            for c in 0..n {
                s += diag[i * nn + r * n + c] * x[i * n + c];
                if i + 1 < nodes {
                    s += off[i * nn + r * n + c] * x[(i + 1) * n + c];
                }
                if i > 0 {
                    // block (i, i−1) = off_{i−1}ᵀ
                    s += off[(i - 1) * nn + c * n + r] * x[(i - 1) * n + c];
                }
            }
            y[i * n + r] = s;
        }
    }
}

/// ‖z − P(z − g)‖∞, the first-order optimality measure of a box-constrained problem.
pub fn projected_gradient_norm(z: &[f64], g: &[f64], lower: &[f64], upper: &[f64]) -> f64 {
    z.iter()
        .zip(g)
        .zip(lower.iter().zip(upper))
        .map(|((&zi, &gi), (&l, &u))| (zi - (zi - gi).clamp(l, u)).abs())
        .fold(0.0, f64::max)
}

/// Work buffers of the solver, reused across calls (nothing is allocated once sized).
#[derive(Debug, Default, Clone)]
pub struct BoxLsqSolver {
    chol: BlockTridiagCholesky,
    z0: Vec<f64>,
    g: Vec<f64>,
    diag: Vec<f64>,
    off: Vec<f64>,
    shift: Vec<f64>,
    fixed: Vec<bool>,
    fixed_bound: Vec<bool>,
    step: Vec<f64>,
    trial: Vec<f64>,
    hp: Vec<f64>,
    yl: Vec<f64>,
    yu: Vec<f64>,
    dyl: Vec<f64>,
    dyu: Vec<f64>,
    /// The problem's cost and gradient noise at the point whose derivatives are in `g`, `diag`,
    /// `off`.
    noise_at_z: f64,
    gnoise_at_z: f64,
    /// Window size of the last `solve` (0 before any).
    nodes: usize,
    n: usize,
}

/// Mutable state shared by the two phases.
struct Progress {
    cost: f64,
    nit: usize,
    nfev: usize,
    /// Whether the problem's stored derivatives are those at the current z.
    derivs_at_z: bool,
}

const ARMIJO: f64 = 1e-4;
const LAMBDA_MAX: f64 = 1e16;
/// Floor of the damping after well-predicted steps (relative to the Marquardt scaling).
const LAMBDA_MIN: f64 = 1e-12;
/// Relative size below which a predicted decrease of J cannot be verified by evaluating J
/// (the floor of the solver's running noise estimate).
const NOISE: f64 = 1e-10;
/// A projected gradient within this multiple of the gradient's rounding noise is noise (the
/// noise estimate is an ∞-norm of standard deviations; the steepest components sit in
/// directions of large curvature, where a large gradient is a tiny distance).
const NOISE_PG: f64 = 10.0;
/// Longest extrapolated step (in multiples of the Gauss-Newton step) tried along flat directions.
const EXTRAP_MAX: f64 = 10.0;
/// Largest Marquardt damping at which a step's predicted decrease counts as the Gauss-Newton
/// decrement for the `dtol` test.
const DTOL_MAX_LAMBDA: f64 = 1e-3;

fn finite_lower(l: f64) -> bool {
    l > f64::NEG_INFINITY
}
fn finite_upper(u: f64) -> bool {
    u < f64::INFINITY
}

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
    pub fn new() -> Self {
        Self::default()
    }

    fn resize(&mut self, nodes: usize, n: usize) {
        (self.nodes, self.n) = (nodes, n);
        let len = nodes * n;
        let nn = n * n;
        for v in [
            &mut self.g,
            &mut self.shift,
            &mut self.step,
            &mut self.trial,
            &mut self.hp,
            &mut self.yl,
            &mut self.yu,
            &mut self.dyl,
            &mut self.dyu,
        ] {
            v.resize(len, 0.0);
        }
        self.fixed.resize(len, false);
        self.fixed_bound.resize(len, false);
        self.diag.resize(nodes * nn, 0.0);
        self.off.resize(nodes.saturating_sub(1) * nn, 0.0);
    }

    fn take_derivatives<P: BlockLsqProblem + ?Sized>(&mut self, prob: &P) {
        self.noise_at_z = prob.cost_noise();
        self.gnoise_at_z = prob.gradient_noise();
        prob.gradient_into(&mut self.g);
        prob.gauss_newton_blocks_into(&mut self.diag, &mut self.off);
    }

    /// Marquardt scaling: the diagonal of the Gauss-Newton Hessian, floored.
    fn scale(&self, n: usize, k: usize) -> f64 {
        let (i, r) = (k / n, k % n);
        let d = self.diag[i * n * n + r * n + r];
        let floor = 1e-10
            * self
                .diag
                .iter()
                .step_by(n + 1)
                .fold(1.0f64, |a, &b| a.max(b.abs()));
        d.max(floor)
    }

    /// 4·sym(last n×n block of H⁻¹), H the Gauss-Newton Hessian at the point the last successful
    /// `solve` returned (its blocks are still in the solver's buffers): the Laplace covariance
    /// of the last node when J is 4× a negative log-likelihood, as in GP-MHE. None before any
    /// solve, or if H is singular or the block is not finite.
    pub fn last_node_covariance(&mut self) -> Option<Vec<f64>> {
        let (nodes, n) = (self.nodes, self.n);
        if nodes == 0 {
            return None;
        }
        // The solver's own factor and scratch (`shift`, `fixed`), so no per-update allocation
        // of blocks.
        self.shift.fill(0.0);
        self.fixed.fill(false);
        let b = undamped_last_block_inverse(
            &mut self.chol,
            nodes,
            n,
            &self.diag,
            &self.off,
            &self.shift,
            &self.fixed,
        )?;
        Some(
            (0..n * n)
                .map(|k| 2.0 * (b[k] + b[(k % n) * n + k / n]))
                .collect(),
        )
    }

    /// Minimises J(z) over lower ≤ z ≤ upper starting from `z` (a warm start; projected onto the
    /// box first) and writes the best point found into `z`. Bounds may be ±∞ and lower == upper
    /// fixes a variable. The returned cost is never above the cost at the projected start. Errors only on invalid input or when J is not finite at the start;
    /// afterwards z is always finite and the problem's derivatives refer to the returned z.
    pub fn solve<P: BlockLsqProblem + ?Sized>(
        &mut self,
        prob: &mut P,
        z: &mut [f64],
        lower: &[f64],
        upper: &[f64],
        opts: &SolverOptions,
    ) -> Result<SolveReport> {
        opts.validate()?;
        let (nodes, n) = (prob.n_nodes(), prob.node_dim());
        let len = nodes * n;
        if nodes == 0 || n == 0 {
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
        self.resize(nodes, n);
        for k in 0..len {
            z[k] = z[k].clamp(lower[k], upper[k]);
            self.fixed_bound[k] = lower[k] == upper[k];
        }

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
        let run_interior = match opts.interior {
            InteriorMode::Always => has_bounds,
            InteriorMode::Auto => has_bounds && near,
            InteriorMode::Never => false,
        };

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
            status = self.active_set_phase(prob, z, lower, upper, opts, &mut pr);
        } else {
            // The barrier phase is not monotone in J: keep the (projected) start and its cost,
            // and fall back to the active-set phase from there if the result costs more.
            let cost0 = pr.cost;
            self.z0.clear();
            self.z0.extend_from_slice(z);
            let status_i = self.interior_path(prob, z, lower, upper, opts, &mut pr)?;
            interior_iterations = pr.nit;
            if pr.cost > cost0 {
                z.copy_from_slice(&self.z0);
                self.start(prob, z, &mut pr)?;
                status = self.active_set_phase(prob, z, lower, upper, opts, &mut pr);
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

    /// Barrier phase from a pushed-inside copy of z, then the active-set polish.
    fn interior_path<P: BlockLsqProblem + ?Sized>(
        &mut self,
        prob: &mut P,
        z: &mut [f64],
        lower: &[f64],
        upper: &[f64],
        opts: &SolverOptions,
        pr: &mut Progress,
    ) -> Result<Status> {
        self.push_inside(z, lower, upper);
        self.start(prob, z, pr)?;
        self.interior_phase(prob, z, lower, upper, opts, pr);
        Ok(self.active_set_phase(prob, z, lower, upper, opts, pr))
    }

    fn start<P: BlockLsqProblem + ?Sized>(
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

    /// Moves z strictly inside the box (IPOPT's bound push, 1e-2 relative).
    fn push_inside(&self, z: &mut [f64], lower: &[f64], upper: &[f64]) {
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
    fn interior_phase<P: BlockLsqProblem + ?Sized>(
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

    /// Projected active-set Levenberg-Marquardt iterations (monotone in J).
    fn active_set_phase<P: BlockLsqProblem + ?Sized>(
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The defaults without the early decrement stop: tests of first-order optimality run to
    /// `gtol`.
    pub(super) fn strict() -> SolverOptions {
        SolverOptions {
            dtol: 0.0,
            ..SolverOptions::default()
        }
    }
    use nalgebra::{DMatrix, DVector};

    /// Deterministic pseudo-random numbers in [−1, 1) (no rand dependency).
    struct Lcg(u64);
    impl Lcg {
        fn next(&mut self) -> f64 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((self.0 >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
        }
    }

    /// A synthetic window-like problem: prior rows on node 0, process rows
    /// z_{j+1} − f(z_j) on nodes j, j+1, output rows y_j − h(z_j) (p = 2) on node j; dense
    /// analytic Jacobian, from which the gradient and the Gauss-Newton blocks are formed.
    struct Synthetic {
        nodes: usize,
        n: usize,
        a: Vec<f64>,
        y: Vec<f64>,
        wq: f64,
        wr: f64,
        /// cost is +inf when z[0] exceeds this (tests robustness to failed evaluations)
        blowup: f64,
        r: Vec<f64>,
        jac: DMatrix<f64>,
    }

    const P: usize = 2;

    impl Synthetic {
        fn new(nodes: usize, n: usize, seed: u64) -> Self {
            let mut rng = Lcg(seed);
            let a: Vec<f64> = (0..n).map(|_| rng.next()).collect();
            let rows = n + (nodes - 1) * n + nodes * P;
            let mut p = Synthetic {
                nodes,
                n,
                a: a.clone(),
                y: vec![0.0; nodes * P],
                wq: 3.0,
                wr: 2.0,
                blowup: f64::INFINITY,
                r: vec![0.0; rows],
                jac: DMatrix::zeros(rows, nodes * n),
            };
            // Outputs of a noisy trajectory from a perturbed initial state, plus output noise:
            // residuals of order one at the optimum, as in a whitened MHE window.
            let mut x: Vec<f64> = a.iter().map(|v| v + 0.3 * rng.next()).collect();
            let (mut fx, mut fj) = (vec![0.0; n], DMatrix::zeros(n, n));
            let (mut hx, mut hj) = (vec![0.0; P], DMatrix::zeros(P, n));
            for j in 0..nodes {
                p.h(&x, &mut hx, &mut hj);
                for r in 0..P {
                    p.y[j * P + r] = hx[r] + 0.5 * rng.next();
                }
                p.f(&x, &mut fx, &mut fj);
                for r in 0..n {
                    x[r] = fx[r] + 0.3 * rng.next();
                }
            }
            p
        }
        fn f(&self, x: &[f64], out: &mut [f64], jac: &mut DMatrix<f64>) {
            let n = self.n;
            for r in 0..n {
                let nx = x[(r + 1) % n];
                out[r] = x[r] + 0.3 * nx.sin() - 0.1 * x[r] * x[r];
                for c in 0..n {
                    jac[(r, c)] = 0.0;
                }
                jac[(r, r)] += 1.0 - 0.2 * x[r];
                jac[(r, (r + 1) % n)] += 0.3 * nx.cos();
            }
        }
        fn h(&self, x: &[f64], out: &mut [f64], jac: &mut DMatrix<f64>) {
            let n = self.n;
            out[0] = x[0] + x[n - 1] * x[n - 1];
            out[1] = (0.5 * x[0]).exp() - x[1 % n];
            jac.fill(0.0);
            jac[(0, 0)] += 1.0;
            jac[(0, n - 1)] += 2.0 * x[n - 1];
            jac[(1, 0)] += 0.5 * (0.5 * x[0]).exp();
            jac[(1, 1 % n)] -= 1.0;
        }
        fn residuals(&mut self, z: &[f64]) {
            let n = self.n;
            self.jac.fill(0.0);
            let mut row = 0;
            for c in 0..n {
                self.r[row] = z[c] - self.a[c];
                self.jac[(row, c)] = 1.0;
                row += 1;
            }
            let mut fx = vec![0.0; n];
            let mut fj = DMatrix::zeros(n, n);
            for j in 0..self.nodes - 1 {
                self.f(&z[j * n..(j + 1) * n], &mut fx, &mut fj);
                for r in 0..n {
                    self.r[row] = self.wq * (z[(j + 1) * n + r] - fx[r]);
                    self.jac[(row, (j + 1) * n + r)] = self.wq;
                    for c in 0..n {
                        self.jac[(row, j * n + c)] = -self.wq * fj[(r, c)];
                    }
                    row += 1;
                }
            }
            let mut hx = vec![0.0; P];
            let mut hj = DMatrix::zeros(P, n);
            for j in 0..self.nodes {
                self.h(&z[j * n..(j + 1) * n], &mut hx, &mut hj);
                for r in 0..P {
                    self.r[row] = self.wr * (self.y[j * P + r] - hx[r]);
                    for c in 0..n {
                        self.jac[(row, j * n + c)] = -self.wr * hj[(r, c)];
                    }
                    row += 1;
                }
            }
        }
        fn dense_hessian(&self) -> DMatrix<f64> {
            self.jac.transpose() * &self.jac * 2.0
        }
    }

    impl BlockLsqProblem for Synthetic {
        fn n_nodes(&self) -> usize {
            self.nodes
        }
        fn node_dim(&self) -> usize {
            self.n
        }
        fn evaluate(&mut self, z: &[f64], _want: bool) -> Result<f64> {
            if z[0] > self.blowup {
                return Ok(f64::INFINITY);
            }
            self.residuals(z);
            Ok(self.r.iter().map(|v| v * v).sum())
        }
        fn gradient_into(&self, g: &mut [f64]) {
            let gv = self.jac.transpose() * DVector::from_column_slice(&self.r) * 2.0;
            g.copy_from_slice(gv.as_slice());
        }
        fn gauss_newton_blocks_into(&self, diag: &mut [f64], off: &mut [f64]) {
            let h = self.dense_hessian();
            let n = self.n;
            for i in 0..self.nodes {
                for r in 0..n {
                    for c in 0..n {
                        diag[i * n * n + r * n + c] = h[(i * n + r, i * n + c)];
                        if i + 1 < self.nodes {
                            off[i * n * n + r * n + c] = h[(i * n + r, (i + 1) * n + c)];
                        }
                    }
                }
            }
        }
    }

    fn random_z(nodes: usize, n: usize, seed: u64) -> Vec<f64> {
        let mut rng = Lcg(seed);
        (0..nodes * n).map(|_| rng.next()).collect()
    }

    #[test]
    fn synthetic_jacobian_matches_finite_differences() {
        let mut p = Synthetic::new(5, 3, 7);
        let z = random_z(5, 3, 8);
        p.residuals(&z);
        let (r0, jac) = (p.r.clone(), p.jac.clone());
        let h = 1e-6;
        for k in 0..z.len() {
            let mut zp = z.clone();
            zp[k] += h;
            p.residuals(&zp);
            for row in 0..r0.len() {
                let fd = (p.r[row] - r0[row]) / h;
                assert!((fd - jac[(row, k)]).abs() < 1e-4, "row {row} col {k}");
            }
        }
        // The Hessian really is block-tridiagonal.
        let hd = p.dense_hessian();
        for i in 0..15usize {
            for j in 0..15 {
                if (i / 3).abs_diff(j / 3) > 1 {
                    assert_eq!(hd[(i, j)], 0.0);
                }
            }
        }
    }

    fn dense_from_blocks(nodes: usize, n: usize, diag: &[f64], off: &[f64]) -> DMatrix<f64> {
        let mut a = DMatrix::zeros(nodes * n, nodes * n);
        for i in 0..nodes {
            for r in 0..n {
                for c in 0..n {
                    a[(i * n + r, i * n + c)] = diag[i * n * n + r * n + c];
                    if i + 1 < nodes {
                        let v = off[i * n * n + r * n + c];
                        a[(i * n + r, (i + 1) * n + c)] = v;
                        a[((i + 1) * n + c, i * n + r)] = v;
                    }
                }
            }
        }
        a
    }

    #[test]
    fn block_tridiagonal_solve_matches_dense_solve() {
        for &(nodes, n) in &[(1usize, 1usize), (1, 3), (2, 2), (16, 2), (7, 4)] {
            let mut p = Synthetic::new(nodes, n, 11 + nodes as u64);
            let z = random_z(nodes, n, 3);
            p.evaluate(&z, true).unwrap();
            let mut diag = vec![0.0; nodes * n * n];
            let mut off = vec![0.0; nodes.saturating_sub(1) * n * n];
            p.gauss_newton_blocks_into(&mut diag, &mut off);
            let mut rng = Lcg(5);
            let shift: Vec<f64> = (0..nodes * n).map(|_| 0.1 + rng.next().abs()).collect();
            let rhs: Vec<f64> = (0..nodes * n).map(|_| rng.next()).collect();
            for mask_every in [0usize, 3] {
                let fixed: Vec<bool> = (0..nodes * n)
                    .map(|k| mask_every > 0 && k % mask_every == 1)
                    .collect();
                let mut chol = BlockTridiagCholesky::default();
                assert!(chol.factor(nodes, n, &diag, &off, &shift, &fixed));
                let mut x: Vec<f64> = rhs
                    .iter()
                    .zip(&fixed)
                    .map(|(&b, &f)| if f { 0.0 } else { b })
                    .collect();
                chol.solve_in_place(&mut x);
                // Dense reference: the same matrix with fixed rows/cols replaced by identity.
                let mut a = dense_from_blocks(nodes, n, &diag, &off);
                for k in 0..nodes * n {
                    a[(k, k)] += shift[k];
                }
                for k in 0..nodes * n {
                    if fixed[k] {
                        a.row_mut(k).fill(0.0);
                        a.column_mut(k).fill(0.0);
                        a[(k, k)] = 1.0;
                    }
                }
                let b = DVector::from_iterator(
                    nodes * n,
                    rhs.iter()
                        .zip(&fixed)
                        .map(|(&b, &f)| if f { 0.0 } else { b }),
                );
                let xd = a.clone().cholesky().unwrap().solve(&b);
                for k in 0..nodes * n {
                    assert!(
                        (x[k] - xd[k]).abs() < 1e-10 * (1.0 + xd[k].abs()),
                        "{nodes} {n} {k}"
                    );
                }
                if mask_every == 0 {
                    // last diagonal block of the inverse of A + diag(shift)
                    let mut d2 = diag.clone();
                    for k in 0..nodes * n {
                        d2[(k / n) * n * n + (k % n) * n + k % n] += shift[k];
                    }
                    let inv = gauss_newton_last_block_inverse(nodes, n, &d2, &off).unwrap();
                    let ainv = a.clone().try_inverse().unwrap();
                    for r in 0..n {
                        for c in 0..n {
                            let e = ainv[((nodes - 1) * n + r, (nodes - 1) * n + c)];
                            assert!((inv[r * n + c] - e).abs() < 1e-9 * (1.0 + e.abs()));
                        }
                    }
                }
                let mut y = vec![0.0; nodes * n];
                block_tridiag_matvec(nodes, n, &diag, &off, &x, &mut y);
                let yd = dense_from_blocks(nodes, n, &diag, &off) * DVector::from_column_slice(&x);
                for k in 0..nodes * n {
                    assert!((y[k] - yd[k]).abs() < 1e-10 * (1.0 + yd[k].abs()));
                }
            }
        }
    }

    #[test]
    fn factor_reports_indefinite_matrix() {
        let diag = vec![1.0, 0.0, 0.0, -1.0];
        let mut chol = BlockTridiagCholesky::default();
        assert!(!chol.factor(1, 2, &diag, &[], &[0.0, 0.0], &[false, false]));
        // ... and recovers on the next call.
        assert!(chol.factor(1, 2, &diag, &[], &[0.0, 2.0], &[false, false]));
    }

    /// Reference: projected gradient descent with Armijo backtracking on the dense problem,
    /// many iterations (slow but independent of the Gauss-Newton machinery).
    fn reference_projected_gradient(
        p: &mut Synthetic,
        z0: &[f64],
        lo: &[f64],
        hi: &[f64],
    ) -> (Vec<f64>, f64) {
        let mut z: Vec<f64> = z0
            .iter()
            .zip(lo.iter().zip(hi))
            .map(|(&v, (&l, &u))| v.clamp(l, u))
            .collect();
        let mut c = p.evaluate(&z, true).unwrap();
        let mut g = vec![0.0; z.len()];
        let mut step = 1.0;
        for _ in 0..1500 {
            p.gradient_into(&mut g);
            if projected_gradient_norm(&z, &g, lo, hi) < 1e-9 {
                break;
            }
            step *= 4.0;
            loop {
                let zt: Vec<f64> = (0..z.len())
                    .map(|k| (z[k] - step * g[k]).clamp(lo[k], hi[k]))
                    .collect();
                let dec: f64 = (0..z.len()).map(|k| g[k] * (z[k] - zt[k])).sum();
                let ct = p.evaluate(&zt, true).unwrap();
                if ct <= c - 1e-4 * dec {
                    z = zt;
                    c = ct;
                    break;
                }
                step *= 0.5;
                p.evaluate(&z, true).unwrap();
                if step < 1e-20 {
                    return (z, c);
                }
            }
        }
        (z, c)
    }

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

#[cfg(test)]
mod window_tests {
    use super::tests::strict;
    use super::*;
    use crate::mhe::{Form, StageEval};

    /// The batch reactor (docs/user_guide/systems.rst) as an exact stage model (zero variances).
    struct Reactor;
    const T: f64 = 0.1;
    const K1: f64 = 0.16;
    const K2: f64 = 0.0064;
    fn step(x: &[f64]) -> [f64; 2] {
        [
            x[0] + T * (-2.0 * K1 * x[0] * x[0] + 2.0 * K2 * x[1]),
            x[1] + T * (K1 * x[0] * x[0] - K2 * x[1]),
        ]
    }
    impl StageModel for Reactor {
        fn dim_x(&self) -> usize {
            2
        }
        fn dim_u(&self) -> usize {
            0
        }
        fn dim_y(&self) -> usize {
            1
        }
        fn evaluate(&mut self, d: &[f64], out: &mut StageEval) -> Result<()> {
            let k = d.len() / 2;
            out.resize(k, 2, 0, 1);
            for i in 0..k {
                let x = &d[2 * i..2 * i + 2];
                let f = step(x);
                out.mean_x[2 * i..2 * i + 2].copy_from_slice(&f);
                out.var_x[2 * i..2 * i + 2].fill(0.0);
                out.dvar_x[4 * i..4 * i + 4].fill(0.0);
                out.dmean_x[4 * i..4 * i + 4].copy_from_slice(&[
                    1.0 - 4.0 * T * K1 * x[0],
                    2.0 * T * K2,
                    2.0 * T * K1 * x[0],
                    1.0 - T * K2,
                ]);
                out.mean_y[i] = x[0] + x[1];
                out.var_y[i] = 0.0;
                out.dmean_y[2 * i..2 * i + 2].copy_from_slice(&[1.0, 1.0]);
                out.dvar_y[2 * i..2 * i + 2].fill(0.0);
            }
            Ok(())
        }
    }

    #[test]
    fn batch_reactor_window_from_the_poor_prior_reaches_a_kkt_point() {
        let mut rng: u64 = 17;
        let mut noise = || {
            rng = rng
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((rng >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
        };
        for &(nodes, form) in &[
            (16usize, Form::Prediction),
            (8, Form::Filtering),
            (1, Form::Filtering),
        ] {
            let mut x = [3.0, 1.0];
            let mut y = vec![0.0; nodes];
            for yi in y.iter_mut() {
                *yi = x[0] + x[1] + 0.1 * noise();
                let f = step(&x);
                x = [f[0] + 0.01 * noise(), f[1] + 0.01 * noise()];
            }
            let mut problem = WindowProblem::new(
                2,
                0,
                1,
                0.91,
                &[1e-3, 1e-3],
                &[1e-2],
                &[1.0, 0.0, 0.0, 1.0],
                form,
            )
            .unwrap();
            let mut present = vec![true; nodes];
            if nodes > 3 {
                present[2] = false; // a y=None step
            }
            problem.set_data(&[], &y, &present, &[0.1, 4.5]).unwrap();
            // Warm start: the poor prior rolled forward through the model (x1 on its bound).
            let mut z = vec![0.0; nodes * 2];
            z[..2].copy_from_slice(&[0.1, 4.5]);
            for i in 1..nodes {
                let f = step(&z[2 * (i - 1)..2 * i]);
                z[2 * i..2 * i + 2].copy_from_slice(&f);
            }
            let lo = vec![0.1; nodes * 2];
            let hi = vec![4.5; nodes * 2];
            let mut model = Reactor;
            let mut eval = WindowEval::default();
            let mut lsq = WindowLsq {
                problem: &problem,
                model: &mut model,
                eval: &mut eval,
            };
            let mut solver = BoxLsqSolver::new();
            let rep = solver.solve(&mut lsq, &mut z, &lo, &hi, &strict()).unwrap();
            assert!(rep.status.is_success(), "{rep:?}");
            assert!(rep.projected_gradient <= 1e-6, "{rep:?}");
            assert!(z.iter().all(|&v| (0.1..=4.5).contains(&v)));
            // The problem's state refers to the returned point.
            assert_eq!(eval.cost(), rep.cost);
            let mut g = vec![0.0; nodes * 2];
            eval.gradient_into(&mut g);
            assert_eq!(
                projected_gradient_norm(&z, &g, &lo, &hi),
                rep.projected_gradient
            );
        }
    }
}
