//! Triangular solves with a lower Cholesky factor L (column-major, one column a slice) for one
//! right-hand side of a few dozen to a few hundred entries, where faer's blocked solver spends
//! more on dispatch than on arithmetic. Both sweeps work on blocks of four columns: once four
//! unknowns are known, their contribution to the others is taken in one pass (it vectorises, and
//! x is read once per four columns).
//!
//! Two callers use them, `gp.rs` (a GP's K + σ²I, one test point) and `rgp/` (a basis's K, every
//! filter step), and their substitutions had grown different roundings that their results depend
//! on bit for bit. A [`Rounding`] says how a caller rounds; everything else is shared:
//!
//! * the diagonal: [`DivideByDiagonal`] divides by L_jj; [`ReciprocalWithFloor`] multiplies by a
//!   precomputed 1 / L_jj (a division's latency would dominate the sequential part) and sets
//!   results below a floor to 0 (subnormal numbers cost ~100 times a normal operation);
//! * a solved block's contribution to the unknowns left, y −= Σ_t a_t x_t: summed first and
//!   subtracted once ([`DivideByDiagonal`]), or subtracted term by term and skipped when the
//!   block is zero ([`ReciprocalWithFloor`]);
//! * the backward sweep (Lᵀ x = b): in column form, each solved block subtracted from the
//!   unknowns above it ([`Backward::Columns`]; it reads Lᵀ from the strict upper triangle, so the
//!   storage must hold a copy of it there, as `gp.rs`'s does), or in dot form, each block's dot
//!   products with the unknowns already solved taken in one pass ([`Backward::Dots`]; it reads
//!   L's columns again, still in cache from the forward sweep).

use super::simd::{dot4, dot_lanes8};
use super::vector::add4;

/// The backward sweep's form (see the module doc).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Backward {
    /// Solved blocks are subtracted from the unknowns above them (needs Lᵀ in the strict upper
    /// triangle). A leading block of fewer than four unknowns is solved column by column too.
    Columns,
    /// Each block takes its dot products with the solved unknowns first.
    Dots,
}

/// How one caller's substitutions round (see the module doc).
pub(crate) trait Rounding {
    /// The backward sweep's form.
    const BACKWARD: Backward;
    /// The unknown x_j from `rest`, its right-hand side less the solved unknowns' terms, and
    /// the diagonal entry `l_jj`.
    fn pivot(&self, j: usize, rest: f64, l_jj: f64) -> f64;
    /// y −= a₀ x₀ + a₁ x₁ + a₂ x₂ + a₃ x₃ over the common length: a solved block of four
    /// unknowns `a` taken from the unknowns left (`x`: the block's columns of L, or of Lᵀ).
    fn subtract4(&self, y: &mut [f64], a: [f64; 4], x: [&[f64]; 4]);
}

/// `gp.rs`'s rounding: divide by L_jj; y_i −= ((a₀x₀ + a₁x₁) + a₂x₂) + a₃x₃; backward sweep in
/// column form.
pub(crate) struct DivideByDiagonal;

impl Rounding for DivideByDiagonal {
    const BACKWARD: Backward = Backward::Columns;

    #[inline(always)]
    fn pivot(&self, _j: usize, rest: f64, l_jj: f64) -> f64 {
        rest / l_jj
    }

    #[inline(always)]
    fn subtract4(&self, y: &mut [f64], a: [f64; 4], x: [&[f64]; 4]) {
        let [x0, x1, x2, x3] = a;
        for ((((yi, a), b), c), d) in y.iter_mut().zip(x[0]).zip(x[1]).zip(x[2]).zip(x[3]) {
            *yi -= ((a * x0 + b * x1) + c * x2) + d * x3;
        }
    }
}

/// `rgp/`'s rounding: multiply by `inv_diag[j]` = 1 / L_jj and set results below `tiny` in
/// magnitude to 0; y_i = (((y_i − a₀x₀) − a₁x₁) − a₂x₂) − a₃x₃, skipped for a zero block;
/// backward sweep in dot form.
pub(crate) struct ReciprocalWithFloor<'a> {
    pub(crate) inv_diag: &'a [f64],
    pub(crate) tiny: f64,
}

impl Rounding for ReciprocalWithFloor<'_> {
    const BACKWARD: Backward = Backward::Dots;

    #[inline(always)]
    fn pivot(&self, j: usize, rest: f64, _l_jj: f64) -> f64 {
        let v = rest * self.inv_diag[j];
        if v.abs() < self.tiny {
            0.0
        } else {
            v
        }
    }

    /// `y + (−a)x` rounds exactly as `y − ax` (negation is exact), so this is [`add4`] with the
    /// coefficients negated.
    #[inline(always)]
    fn subtract4(&self, y: &mut [f64], a: [f64; 4], x: [&[f64]; 4]) {
        if a != [0.0; 4] {
            add4(y, [-a[0], -a[1], -a[2], -a[3]], x);
        }
    }
}

/// Solves L x = b in place (`x` holds b on entry); `col(j)` is column j of L (its entries from
/// row j on are read).
#[inline(always)]
pub(crate) fn forward_substitution<'a, R: Rounding>(
    col: impl Fn(usize) -> &'a [f64],
    rounding: &R,
    x: &mut [f64],
) {
    let n = x.len();
    let mut j0 = 0;
    while j0 < n {
        let j1 = (j0 + 4).min(n);
        // The block's triangle, column by column.
        for j in j0..j1 {
            let c = col(j);
            let xj = rounding.pivot(j, x[j], c[j]);
            x[j] = xj;
            for s in j + 1..j1 {
                x[s] -= xj * c[s];
            }
        }
        if j1 - j0 == 4 && j1 < n {
            let a = [x[j0], x[j0 + 1], x[j0 + 2], x[j0 + 3]];
            let c = |t: usize| &col(j0 + t)[j1..];
            rounding.subtract4(&mut x[j1..], a, [c(0), c(1), c(2), c(3)]);
        }
        j0 = j1;
    }
}

/// Solves Lᵀ x = b in place with the same `col` as [`forward_substitution`], from the last
/// unknown to the first, in blocks of four aligned at the end. With [`Backward::Columns`] the
/// strict upper triangle of the storage must hold Lᵀ.
#[inline(always)]
pub(crate) fn back_substitution<'a, R: Rounding>(
    col: impl Fn(usize) -> &'a [f64],
    rounding: &R,
    x: &mut [f64],
) {
    let n = x.len();
    let mut i1 = n;
    while i1 > 0 {
        let i0 = i1.saturating_sub(4);
        let full = i1 - i0 == 4;
        // The solved unknowns' terms: dot form takes them now (column form has already
        // subtracted them, after the blocks below).
        let d = match R::BACKWARD {
            Backward::Dots if full && i1 < n => {
                let c = |t: usize| &col(i0 + t)[i1..];
                Some(dot4([c(0), c(1), c(2), c(3)], &x[i1..]))
            }
            Backward::Dots => {
                let mut d = [0.0; 4];
                for (t, dt) in d.iter_mut().enumerate().take(i1 - i0) {
                    *dt = dot_lanes8(&col(i0 + t)[i1..], &x[i1..]);
                }
                Some(d)
            }
            Backward::Columns => None,
        };
        if d.is_none() && !full {
            // Column form, leading block of fewer than four: column by column, last first.
            for j in (i0..i1).rev() {
                let c = col(j);
                let xj = rounding.pivot(j, x[j], c[j]);
                x[j] = xj;
                for (xi, u) in x[i0..j].iter_mut().zip(&c[i0..j]) {
                    *xi -= u * xj;
                }
            }
        } else {
            // The block's triangle row by row, last row first: L[jj, i] = column i below row i.
            for i in (i0..i1).rev() {
                let c = col(i);
                let mut s = match d {
                    Some(d) => x[i] - d[i - i0],
                    None => x[i],
                };
                for jj in i + 1..i1 {
                    s -= c[jj] * x[jj];
                }
                x[i] = rounding.pivot(i, s, c[i]);
            }
        }
        if d.is_none() && i0 > 0 {
            // Column form: the solved block leaves the unknowns above it (Lᵀ's columns).
            let a = [x[i0], x[i0 + 1], x[i0 + 2], x[i0 + 3]];
            let c = |t: usize| &col(i0 + t)[..i0];
            rounding.subtract4(&mut x[..i0], a, [c(0), c(1), c(2), c(3)]);
        }
        i1 = i0;
    }
}

#[cfg(test)]
mod tmp_old_copies {
    #![allow(dead_code, clippy::all)]
    use super::*;
    use faer::Mat;
    enum Triangle { Lower, Upper }
/// Forward (L x = b) or backward (Lᵀ x = b) substitution for each N-long column of `v`, with
/// `s` the Cholesky storage (N × N column-major, L in the lower and Lᵀ in the strict upper
/// triangle), column-oriented and four unknowns at a time: once x_j … x_j+3 are known (a 4 × 4
/// triangle), columns j … j+3 of L below them (forward) or of Lᵀ above them (backward) are
/// subtracted from the unknowns left in one pass, whose elements are independent (it
/// vectorises, and x is loaded and stored once per four columns).
#[inline(always)]
fn old_gp_substitution(s: &[f64], n: usize, v: &mut [f64], tri: Triangle) {
    const B: usize = 4;
    let col = |j: usize| &s[j * n..(j + 1) * n];
    for x in v.chunks_exact_mut(n) {
        match tri {
            Triangle::Lower => {
                let mut j = 0;
                while j + B <= n {
                    let c = [col(j), col(j + 1), col(j + 2), col(j + 3)];
                    // The 4 × 4 diagonal block, in order.
                    for q in 0..B {
                        let mut xq = x[j + q];
                        for r in 0..q {
                            xq -= c[r][j + q] * x[j + r];
                        }
                        x[j + q] = xq / c[q][j + q];
                    }
                    let (x0, x1, x2, x3) = (x[j], x[j + 1], x[j + 2], x[j + 3]);
                    let rest = j + B;
                    for ((((xi, a), b), cc), d) in x[rest..]
                        .iter_mut()
                        .zip(&c[0][rest..])
                        .zip(&c[1][rest..])
                        .zip(&c[2][rest..])
                        .zip(&c[3][rest..])
                    {
                        *xi -= ((a * x0 + b * x1) + cc * x2) + d * x3;
                    }
                    j += B;
                }
                for j in j..n {
                    let c = col(j);
                    let xj = x[j] / c[j];
                    x[j] = xj;
                    for (xi, l) in x[j + 1..].iter_mut().zip(&c[j + 1..]) {
                        *xi -= l * xj;
                    }
                }
            }
            Triangle::Upper => {
                let mut end = n;
                while end >= B {
                    let j = end - B;
                    let c = [col(j), col(j + 1), col(j + 2), col(j + 3)];
                    // The 4 × 4 diagonal block of Lᵀ, last unknown first.
                    for q in (0..B).rev() {
                        let mut xq = x[j + q];
                        for r in q + 1..B {
                            xq -= c[r][j + q] * x[j + r];
                        }
                        x[j + q] = xq / c[q][j + q];
                    }
                    let (x0, x1, x2, x3) = (x[j], x[j + 1], x[j + 2], x[j + 3]);
                    for ((((xi, a), b), cc), d) in x[..j]
                        .iter_mut()
                        .zip(&c[0][..j])
                        .zip(&c[1][..j])
                        .zip(&c[2][..j])
                        .zip(&c[3][..j])
                    {
                        *xi -= ((a * x0 + b * x1) + cc * x2) + d * x3;
                    }
                    end = j;
                }
                for j in (0..end).rev() {
                    let c = col(j);
                    let xj = x[j] / c[j];
                    x[j] = xj;
                    for (xi, u) in x[..j].iter_mut().zip(&c[..j]) {
                        *xi -= u * xj;
                    }
                }
            }
        }
    }
}

/// y += α x.
#[inline(always)]
fn _axpy(y: &mut [f64], alpha: f64, x: &[f64]) {
    for (yi, xi) in y.iter_mut().zip(x) {
        *yi += alpha * xi;
    }
}

/// y −= a₀ x₀, then −= a₁ x₁, −= a₂ x₂, −= a₃ x₃, in one pass over y (the four axpys of a block of
/// four columns in a substitution). `y + (−a)x` rounds exactly as `y − ax` (negation is exact), so
/// this is [`add4`] with the coefficients negated.
#[inline(always)]
fn sub4(y: &mut [f64], a: [f64; 4], x: [&[f64]; 4]) {
    old_add4(y, [-a[0], -a[1], -a[2], -a[3]], x)
}

/// y += a₀ x₀, then += a₁ x₁, += a₂ x₂, += a₃ x₃, in one pass over y (four columns of a
/// matrix-vector product, with the same operations in the same order per entry).
#[inline(always)]
fn old_add4(y: &mut [f64], a: [f64; 4], x: [&[f64]; 4]) {
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

// The two substitutions below are the per-step triangular solves with K's Cholesky factor for one
// right-hand side of length n_b ≤ a few hundred. faer's blocked solver is built for large and
// multi-column systems; at this size its dispatch overhead cost more than the arithmetic, so
// both work on blocks of four columns of L (the forward one subtracts a solved block from the
// rest of v in one pass, `sub4`; the backward one takes four dot products in one pass, `dot4`).
// The diagonal is applied as a multiplication by its precomputed reciprocal: a division's
// latency would otherwise dominate the sequential part.

/// Solves L v = b in place (L lower triangular, column-major; `inv_diag` = 1 / diag(L)); entries
/// of v below `tiny` in magnitude are set to 0 (see TINY_REL).
#[inline(always)]
fn old_forward(l: &Mat<f64>, inv_diag: &[f64], tiny: f64, v: &mut [f64]) {
    let nb = v.len();
    let mut j0 = 0;
    while j0 < nb {
        let j1 = (j0 + 4).min(nb);
        for j in j0..j1 {
            let mut vj = v[j] * inv_diag[j];
            if vj.abs() < tiny {
                vj = 0.0;
            }
            v[j] = vj;
            let col = l.col_as_slice(j);
            for s in j + 1..j1 {
                v[s] -= vj * col[s];
            }
        }
        if j1 - j0 == 4 && j1 < nb {
            let a = [v[j0], v[j0 + 1], v[j0 + 2], v[j0 + 3]];
            if a != [0.0; 4] {
                let c = |t: usize| &l.col_as_slice(j0 + t)[j1..];
                sub4(&mut v[j1..], a, [c(0), c(1), c(2), c(3)]);
            }
        }
        j0 = j1;
    }
}

/// Solves Lᵀ v = b in place with the same lower factor L (column-major; `inv_diag` = 1 / diag(L))
/// in dot form, from the last row to the first: v_i = (b_i − L[i+1.., i] · v[i+1..]) / L_ii, four
/// rows at a time (their dots with the already solved part in one pass, `dot4`). Reading L's
/// columns again, still in cache from the forward substitution, instead of a stored Lᵀ halves the
/// memory a step streams through. Entries of v below `tiny` in magnitude are set to 0.
#[inline(always)]
fn old_back(l: &Mat<f64>, inv_diag: &[f64], tiny: f64, v: &mut [f64]) {
    let nb = v.len();
    let mut i1 = nb;
    while i1 > 0 {
        let i0 = i1.saturating_sub(4);
        let d = if i1 - i0 == 4 && i1 < nb {
            let c = |t: usize| &l.col_as_slice(i0 + t)[i1..];
            dot4([c(0), c(1), c(2), c(3)], &v[i1..])
        } else {
            let mut d = [0.0; 4];
            for (t, dt) in d.iter_mut().enumerate().take(i1 - i0) {
                *dt = dot_lanes8(&l.col_as_slice(i0 + t)[i1..], &v[i1..]);
            }
            d
        };
        for i in (i0..i1).rev() {
            let col = l.col_as_slice(i);
            let mut s = v[i] - d[i - i0];
            for jj in i + 1..i1 {
                s -= col[jj] * v[jj];
            }
            let vi = s * inv_diag[i];
            v[i] = if vi.abs() < tiny { 0.0 } else { vi };
        }
        i1 = i0;
    }
}


    fn data(n: usize, seed: u64) -> Vec<f64> {
        let mut s = seed;
        (0..n).map(|_| { s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407); ((s >> 11) as f64 / (1u64 << 53) as f64) - 0.5 }).collect()
    }
    /// A random well-conditioned lower factor with exact Lᵀ copy above, column-major; some tiny entries.
    fn factor(n: usize, seed: u64) -> Vec<f64> {
        let r = data(n * n, seed);
        let mut s = vec![0.0; n * n];
        for j in 0..n { for i in j..n { s[j * n + i] = if i == j { 1.0 + r[j * n + i].abs() } else if (i + j) % 7 == 3 { 1e-150 * r[j*n+i] } else { r[j * n + i] }; } }
        for j in 0..n { for i in 0..j { s[j * n + i] = s[i * n + j]; } }
        s
    }
    #[test]
    fn shared_substitution_equals_the_old_ones_bit_for_bit() {
        for n in 1..60usize {
            for seed in 0..6u64 {
                let s = factor(n, 100 + seed * 7 + n as u64);
                let mut b = data(n, 5 + seed);
                if seed % 3 == 1 { for i in 0..n.min(6) { b[i] = 0.0; } if n > 2 { b[2] = -0.0; } }
                let col = |j: usize| &s[j * n..(j + 1) * n];
                for lower in [true, false] {
                    let (mut x_old, mut x_new) = (b.clone(), b.clone());
                    old_gp_substitution(&s, n, &mut x_old, if lower { Triangle::Lower } else { Triangle::Upper });
                    if lower { forward_substitution(col, &DivideByDiagonal, &mut x_new) } else { back_substitution(col, &DivideByDiagonal, &mut x_new) }
                    for i in 0..n { assert_eq!(x_old[i].to_bits(), x_new[i].to_bits(), "gp n={n} lower={lower} i={i}"); }
                }
                let l = Mat::<f64>::from_fn(n, n, |i, j| if i >= j { s[j * n + i] } else { 0.0 });
                let inv: Vec<f64> = (0..n).map(|j| 1.0 / l[(j, j)]).collect();
                for tiny in [0.0, 1e-140, 1e-3] {
                    let rounding = ReciprocalWithFloor { inv_diag: &inv, tiny };
                    let lc = |j: usize| l.col_as_slice(j);
                    let (mut x_old, mut x_new) = (b.clone(), b.clone());
                    old_forward(&l, &inv, tiny, &mut x_old);
                    forward_substitution(lc, &rounding, &mut x_new);
                    for i in 0..n { assert_eq!(x_old[i].to_bits(), x_new[i].to_bits(), "rgp fwd n={n} i={i}"); }
                    let (mut x_old, mut x_new) = (b.clone(), b.clone());
                    old_back(&l, &inv, tiny, &mut x_old);
                    back_substitution(lc, &rounding, &mut x_new);
                    for i in 0..n { assert_eq!(x_old[i].to_bits(), x_new[i].to_bits(), "rgp back n={n} i={i}"); }
                }
            }
        }
    }
}
