//! Recursive GP regression (Huber 2013, with the changes of Husmann, Weishaupt & Aschemann) and the
//! per-step kernels of the RGP-dKF, the EKF whose state is augmented by the RGP's basis-vector
//! weights (docs/user_guide/rgp_dkf.rst).
//!
//! * [`RgpBasis`]: the fixed part of one RGP: basis vectors on a unit grid (eq. 5, 6), the kernel
//!   σ_K² exp(−‖x − x'‖²/(2L)) as [`SeArd`] with all length-scales √L, and the Cholesky factor of
//!   K = k(X, X), computed once; or ([`RgpBasis::from_points`]) basis vectors at given points
//!   with an SE-ARD kernel in ζ units, such as a sparse GP's inducing inputs
//!   ([`Rgp::from_sparse`]), optionally with an affine prior mean. `J_k = k(X_k, X) K⁻¹` is two triangular solves per step (one
//!   for the whitened weights of [`RgpEkf`]); K⁻¹ is never formed.
//! * [`Rgp`]: Huber's recursive GP (inference eq. 3, update eq. 4 with process noise σ_p and the
//!   prediction-variance floor σ_r²).
//! * [`RgpEkf`]: the augmented mean μ = [x; μ_z1; …] and covariance C, the structured covariance
//!   prediction (12)–(13) in O(N·(n² + n_b)) (N = n + Σ n_b), and the EKF update 4a (states and
//!   weights) or 4b (states only, as a Schmidt "consider" update). In pure-prediction mode (§3.2)
//!   the weights are not part of the state: the trained GPs enter as noisy inputs.
//!
//! Files: `basis.rs` ([`RgpBasis`] and its triangular solves), `points.rs` (bases at given
//! points, the prior mean, [`Rgp::from_sparse`]), `recursive.rs` ([`Rgp`]),
//! `ekf.rs` ([`RgpEkf`]), `step.rs` (what a step assembles around the kernels: constant or
//! given Jacobians, the innovation, R_x), `dense.rs` (the small dense helpers of the filter: p × p Cholesky,
//! rank-p downdate, quadratic form). The reductions and triangular solves of the kernels are in
//! `crate::linalg` (AVX2 chosen at run time).

use crate::error::{Error, Result};

/// Largest relative jitter (times σ_K²) added to K's diagonal before giving up on its Cholesky.
const MAX_REL_JITTER: f64 = 1e-6;

/// Magnitudes below this, relative to their scale (σ_K² for K and k(x, X), σ_K for K's factor L
/// and for L⁻¹ k(X, x), 1 for J), are set to 0. Far from the diagonal K and L decay like the
/// kernel, and far from the input so do k(x, X) and the solves; products of such numbers fall
/// below the normal range (2.2e-308), and every operation producing or reading a subnormal number
/// costs a microcode assist (~100 times a normal one): it made some steps 1.5 times slower. Numbers
/// this small are more than 120 orders of magnitude below rounding error, and products of two of
/// them stay normal for σ_K above 1e-14.
const TINY_REL: f64 = 1e-140;

/// Runs `self.method(args)` compiled for AVX2 when the CPU has it (detected at run time, cached by
/// std), else the baseline (SSE2) build a portable wheel is compiled for. The per-step loops are
/// short and contiguous; AVX2 doubles their SIMD width. Both builds perform the same operations in
/// the same order (no fused multiply-add), so the results are identical.
macro_rules! with_avx2 {
    ($ty:ty, $self:ident . $method:ident ( $($arg:ident : $argty:ty),* ) -> $ret:ty) => {{
        #[cfg(target_arch = "x86_64")]
        {
            #[target_feature(enable = "avx2")]
            fn avx2(this: &mut $ty, $($arg: $argty),*) -> $ret {
                this.$method($($arg),*)
            }
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: the CPU supports AVX2, checked just above.
                return unsafe { avx2($self, $($arg),*) };
            }
        }
        $self.$method($($arg),*)
    }};
}

mod basis;
mod dense;
mod ekf;
mod points;
mod recursive;
mod step;

pub use basis::{Jitter, RgpBasis};
pub use ekf::{RgpEkf, RgpEkfState};
pub use recursive::Rgp;
pub use step::ConstantJacobians;

fn check_positive(arg: &str, v: f64) -> Result<()> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(Error::invalid(
            arg,
            format!("must be finite and > 0, got {v}"),
        ))
    }
}

fn check_nonneg(arg: &str, v: f64) -> Result<()> {
    if v.is_finite() && v >= 0.0 {
        Ok(())
    } else {
        Err(Error::invalid(
            arg,
            format!("must be finite and >= 0, got {v}"),
        ))
    }
}

/// A one-dimensional basis of `nb` points on [−2, 2] for the tests.
#[cfg(test)]
fn test_basis(nb: usize) -> RgpBasis {
    RgpBasis::new(&[-2.0], &[2.0], &[nb], 3.0, 2.0, 0.1, 0.0).unwrap()
}
