//! The real-time window solver (docs/user_guide/solver.rst): a bound-constrained Gauss-Newton /
//! Levenberg-Marquardt method for least-squares problems min ‖r(z)‖² s.t. lower ≤ z ≤ upper whose
//! Gauss-Newton Hessian 2JᵀJ is block-tridiagonal (the GP-MHE window: node i = window state x̄_i),
//! optionally bordered by global variables that couple with every node (a quantity constant over
//! the window, such as a GP's inducing outputs; bounded or not, as any variable).
//!
//! Each linear system is solved by a block-tridiagonal Cholesky factorisation (the Riccati-like
//! recursion over the horizon, small dense nalgebra blocks), so one iteration costs O(M n³); m
//! global variables add their Schur complement, O(M n² m + M n m² + m³).
//!
//! Two phases:
//! 1. **Interior phase** (only when the start lies on or near a bound, or when asked): a primal-dual
//!    log-barrier Gauss-Newton method with a fraction-to-boundary rule and an Armijo line search on
//!    the barrier merit, the barrier parameter decreasing from `mu_init` to `mu_final` (IPOPT's
//!    monotone rule). It starts strictly inside the box, so early iterations cannot pin states to
//!    their bounds (docs/user_guide/solver.rst): projected/reflective least-squares methods started from the
//!    batch reactor's poor prior stop at worse minima with x1 on its bound.
//! 2. **Active-set Levenberg-Marquardt phase**: variables at a bound whose gradient pushes outward
//!    are held fixed, the others take a Gauss-Newton step, undamped until a step fails (then
//!    Marquardt scaling, Nielsen's damping update), the trial point is projected on the box and
//!    accepted on the gain ratio; a rejected step along a stiff valley of J (residual weights
//!    that differ by orders of magnitude) is first corrected back into the valley.
//!    It stops on the projected-gradient norm (`gtol`), the Gauss-Newton decrement (`dtol`: the
//!    next undamped step would lower J by less than that), the step size (`xtol`), the relative
//!    cost decrease (`ftol`) or the iteration cap, and says which in [`Status`].
//!
//! The problem is reached through [`BlockLsqProblem`]; the MHE window implements it
//! (`crate::mhe::WindowLsq`).
//!
//! Files: `options.rs` (settings, status, report), `block_tridiag.rs` (the block-tridiagonal
//! Cholesky factorisation and products), `hessian.rs` (the Gauss-Newton Hessian, block-tridiagonal
//! or bordered by global variables), `bordered.rs` (its factorisation), `box_lsq.rs`
//! ([`BoxLsqSolver`]: buffers, the driver `solve` and what both phases share), `barrier.rs` (the
//! interior phase), `active_set.rs` (the active-set phase), `damping.rs` (its damping),
//! `correction.rs` (its correction of steps along stiff valleys), `stiff_tests.rs` (tests on
//! stiff windows), `global_tests.rs` (tests on windows with global variables), `sandwich.rs`
//! (the covariance H⁻¹GH⁻¹ of a discounted window).

/// `$body` with `$d` the nalgebra dimension of n×n blocks: `Const` (stack matrices) for
/// n ≤ 6, the sizes of the shipped systems, `Dyn` beyond; the same generic code either way.
macro_rules! with_block_dim {
    ($n:expr, $d:ident => $body:expr) => {
        with_block_dim!(@arms $n, $d, $body; 1 2 3 4 5 6)
    };
    (@arms $n:expr, $d:ident, $body:expr; $($k:literal)*) => {
        match $n {
            $($k => {
                let $d = nalgebra::Const::<$k>;
                $body
            })*
            n => {
                let $d = nalgebra::Dyn(n);
                $body
            }
        }
    };
}
pub(crate) use with_block_dim;

mod active_set;
mod barrier;
mod block_tridiag;
mod bordered;
mod box_lsq;
mod correction;
mod damping;
#[cfg(test)]
mod global_tests;
mod hessian;
mod options;
mod sandwich;
#[cfg(test)]
mod stiff_tests;
#[cfg(test)]
pub(crate) mod test_problem;

pub use block_tridiag::{
    block_tridiag_matvec, gauss_newton_last_block_inverse, BlockTridiagCholesky,
};
pub use box_lsq::{BoxLsqSolver, Covariances};
pub use options::{InteriorMode, SolveReport, SolverOptions, Status};

use crate::error::Result;

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
    /// Number of global variables: they follow the nodes' variables in z and may couple with
    /// every node (0, the default, for a plain window).
    fn global_dim(&self) -> usize {
        0
    }
    /// The rest of 2JᵀJ when [`global_dim`](Self::global_dim) m > 0: `border` (nodes·n × m,
    /// row-major) the blocks between the nodes' variables and the global ones, `corner` (m × m,
    /// row-major) the global block. Not called when m = 0.
    fn gauss_newton_border_into(&self, _border: &mut [f64], _corner: &mut [f64]) {}
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

/// ‖z − P(z − g)‖∞, the first-order optimality measure of a box-constrained problem.
pub fn projected_gradient_norm(z: &[f64], g: &[f64], lower: &[f64], upper: &[f64]) -> f64 {
    z.iter()
        .zip(g)
        .zip(lower.iter().zip(upper))
        .map(|((&zi, &gi), (&l, &u))| (zi - (zi - gi).clamp(l, u)).abs())
        .fold(0.0, f64::max)
}
