//! Small dense linear algebra shared by the GP (`gp.rs`) and the recursive GP (`rgp/`), for the
//! vector sizes of one step (a few dozen to a few hundred), where faer's blocked routines cost
//! more in dispatch than in arithmetic:
//!
//! * `simd.rs`: reductions with AVX2 chosen at run time (`dot_lanes8`, `dot4`, `symv_column`);
//! * `vector.rs`: loops the compiler vectorises inside its caller's build (`axpy`, `add4`,
//!   `sum_lanes4`, `dot_lanes4`, `sum_of_squares_lanes4`). The two dot products sum in different
//!   orders (eight partial sums vs four, see `vector.rs`), so each caller keeps the one its
//!   results were computed with;
//! * `triangular.rs`: the forward and backward substitutions with a Cholesky factor, with the
//!   two callers' roundings as [`triangular::Rounding`]s.

pub(crate) mod simd;
pub(crate) mod triangular;
pub(crate) mod vector;

pub(crate) use simd::{dot4, dot_lanes8, symv_column};
pub(crate) use triangular::{
    back_substitution, forward_substitution, DivideByDiagonal, ReciprocalWithFloor,
};
pub(crate) use vector::{add4, axpy, dot_lanes4, sum_lanes4, sum_of_squares_lanes4};

/// Deterministic test vectors in [−0.5, 0.5) (no rand dependency).
#[cfg(test)]
pub(crate) fn test_data(n: usize, seed: u64) -> Vec<f64> {
    let mut s = seed;
    (0..n)
        .map(|_| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        })
        .collect()
}
