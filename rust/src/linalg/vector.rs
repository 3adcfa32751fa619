//! Element-wise loops and reductions on slices written so that the compiler vectorises them when
//! they are inlined into a caller (all are `#[inline(always)]`: inside a function built for AVX2
//! they become AVX2 code; there is no run-time dispatch here, unlike [`super::simd`]).
//!
//! The `_lanes4` reductions keep four partial sums over blocks of four entries, add them as
//! ((l0 + l1) + (l2 + l3)), and add the sum of the last 0–3 entries (taken on its own, from 0) at
//! the end. [`super::dot_lanes8`] sums in a different order (eight partial sums, the last entries
//! added one by one), so the two dot products round differently and are not interchangeable
//! where results must stay bit-identical: `gp.rs` uses these, `rgp/` the dispatched ones.

/// y += α x over the common length.
#[inline(always)]
pub(crate) fn axpy(y: &mut [f64], alpha: f64, x: &[f64]) {
    for (yi, xi) in y.iter_mut().zip(x) {
        *yi += alpha * xi;
    }
}

/// y += a₀ x₀, then += a₁ x₁, += a₂ x₂, += a₃ x₃, in one pass over y (four columns of a
/// matrix-vector product, with the same operations in the same order per entry).
#[inline(always)]
pub(crate) fn add4(y: &mut [f64], a: [f64; 4], x: [&[f64]; 4]) {
    let n = y
        .len()
        .min(x[0].len())
        .min(x[1].len())
        .min(x[2].len())
        .min(x[3].len());
    let (x0, x1, x2, x3) = (&x[0][..n], &x[1][..n], &x[2][..n], &x[3][..n]);
    for ((((yi, v0), v1), v2), v3) in y[..n].iter_mut().zip(x0).zip(x1).zip(x2).zip(x3) {
        *yi = (((*yi + a[0] * v0) + a[1] * v1) + a[2] * v2) + a[3] * v3;
    }
}

/// Σ a_i with four partial sums, so that the loop vectorises (a plain `sum` is a serial chain).
#[inline(always)]
pub(crate) fn sum_lanes4(a: &[f64]) -> f64 {
    let mut acc = [0.0; 4];
    let chunks = a.chunks_exact(4);
    let tail: f64 = chunks.remainder().iter().sum();
    for c in chunks {
        for l in 0..4 {
            acc[l] += c[l];
        }
    }
    (acc[0] + acc[1]) + (acc[2] + acc[3]) + tail
}

/// Σ a_i b_i (four partial sums, as [`sum_lanes4`]).
#[inline(always)]
pub(crate) fn dot_lanes4(a: &[f64], b: &[f64]) -> f64 {
    let mut acc = [0.0; 4];
    let (ca, cb) = (a.chunks_exact(4), b.chunks_exact(4));
    let tail: f64 = ca
        .remainder()
        .iter()
        .zip(cb.remainder())
        .map(|(x, y)| x * y)
        .sum();
    for (x, y) in ca.zip(cb) {
        for l in 0..4 {
            acc[l] += x[l] * y[l];
        }
    }
    (acc[0] + acc[1]) + (acc[2] + acc[3]) + tail
}

/// Σ v_i² (four partial sums, as [`dot_lanes4`]).
#[inline(always)]
pub(crate) fn sum_of_squares_lanes4(v: &[f64]) -> f64 {
    dot_lanes4(v, v)
}
