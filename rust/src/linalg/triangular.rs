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
    /// triangle). The first 0–3 unknowns are solved column by column too.
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
    while j0 + 4 <= n {
        // The block's 4 × 4 triangle, column by column (fixed size, so it unrolls).
        let c = [col(j0), col(j0 + 1), col(j0 + 2), col(j0 + 3)];
        let mut xb = [x[j0], x[j0 + 1], x[j0 + 2], x[j0 + 3]];
        for q in 0..4 {
            let xj = rounding.pivot(j0 + q, xb[q], c[q][j0 + q]);
            xb[q] = xj;
            for s in q + 1..4 {
                xb[s] -= xj * c[q][j0 + s];
            }
        }
        x[j0..j0 + 4].copy_from_slice(&xb);
        let j1 = j0 + 4;
        if j1 < n {
            let c = |t: usize| &c[t][j1..];
            rounding.subtract4(&mut x[j1..], xb, [c(0), c(1), c(2), c(3)]);
        }
        j0 = j1;
    }
    // The last 0–3 unknowns, column by column.
    for j in j0..n {
        let c = col(j);
        let xj = rounding.pivot(j, x[j], c[j]);
        x[j] = xj;
        for s in j + 1..n {
            x[s] -= xj * c[s];
        }
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
    while i1 >= 4 {
        let i0 = i1 - 4;
        let c = [col(i0), col(i0 + 1), col(i0 + 2), col(i0 + 3)];
        // The solved unknowns' terms: dot form takes them now (column form has already
        // subtracted them, after the blocks below). The first block's dots are over nothing.
        let d = match R::BACKWARD {
            Backward::Dots if i1 < n => {
                let c = |t: usize| &c[t][i1..];
                Some(dot4([c(0), c(1), c(2), c(3)], &x[i1..]))
            }
            Backward::Dots => Some(c.map(|ct| dot_lanes8(&ct[i1..], &x[i1..]))),
            Backward::Columns => None,
        };
        // The block's 4 × 4 triangle row by row, last row first (L[i0 + r, i0 + q] is column
        // i0 + q below the diagonal; fixed size, so it unrolls).
        let mut xb = [x[i0], x[i0 + 1], x[i0 + 2], x[i0 + 3]];
        for q in (0..4).rev() {
            let mut s = match d {
                Some(d) => xb[q] - d[q],
                None => xb[q],
            };
            for r in q + 1..4 {
                s -= c[q][i0 + r] * xb[r];
            }
            xb[q] = rounding.pivot(i0 + q, s, c[q][i0 + q]);
        }
        x[i0..i1].copy_from_slice(&xb);
        if d.is_none() && i0 > 0 {
            // Column form: the solved block leaves the unknowns above it (Lᵀ's columns).
            let c = |t: usize| &c[t][..i0];
            rounding.subtract4(&mut x[..i0], xb, [c(0), c(1), c(2), c(3)]);
        }
        i1 = i0;
    }
    // The first 0–3 unknowns.
    match R::BACKWARD {
        Backward::Dots => {
            let mut d = [0.0; 4];
            for (t, dt) in d.iter_mut().enumerate().take(i1) {
                *dt = dot_lanes8(&col(t)[i1..], &x[i1..]);
            }
            for i in (0..i1).rev() {
                let c = col(i);
                let mut s = x[i] - d[i];
                for jj in i + 1..i1 {
                    s -= c[jj] * x[jj];
                }
                x[i] = rounding.pivot(i, s, c[i]);
            }
        }
        Backward::Columns => {
            // column by column, last first
            for j in (0..i1).rev() {
                let c = col(j);
                let xj = rounding.pivot(j, x[j], c[j]);
                x[j] = xj;
                for (xi, u) in x[..j].iter_mut().zip(&c[..j]) {
                    *xi -= u * xj;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::linalg::test_data as data;

    /// A well-conditioned lower factor, column-major, with Lᵀ copied into the upper triangle.
    fn factor(n: usize, seed: u64) -> Vec<f64> {
        let r = data(n * n, seed);
        let mut s = vec![0.0; n * n];
        for j in 0..n {
            for i in j..n {
                s[j * n + i] = if i == j {
                    1.0 + r[j * n + i].abs()
                } else {
                    r[j * n + i] / n as f64
                };
            }
            for i in 0..j {
                s[j * n + i] = s[i * n + j];
            }
        }
        s
    }

    #[test]
    fn both_roundings_solve_both_systems() {
        // sizes around and between the blocks of four, so every block shape is met
        for n in 1..23usize {
            let s = factor(n, 3 + n as u64);
            let col = |j: usize| &s[j * n..(j + 1) * n];
            let inv: Vec<f64> = (0..n).map(|j| 1.0 / s[j * n + j]).collect();
            let want = data(n, 7);
            // b = L want and b = Lᵀ want
            let lower: Vec<f64> = (0..n)
                .map(|i| (0..=i).map(|j| s[j * n + i] * want[j]).sum())
                .collect();
            let upper: Vec<f64> = (0..n)
                .map(|i| (i..n).map(|j| s[i * n + j] * want[j]).sum())
                .collect();
            let floor = ReciprocalWithFloor {
                inv_diag: &inv,
                tiny: 0.0,
            };
            let check = |x: &[f64], what: &str| {
                for (a, b) in x.iter().zip(&want) {
                    assert!((a - b).abs() <= 1e-13, "{what}, n = {n}: {a} vs {b}");
                }
            };
            let mut x = lower.clone();
            forward_substitution(col, &DivideByDiagonal, &mut x);
            check(&x, "forward, divide");
            let mut x = lower;
            forward_substitution(col, &floor, &mut x);
            check(&x, "forward, reciprocal");
            let mut x = upper.clone();
            back_substitution(col, &DivideByDiagonal, &mut x);
            check(&x, "backward, columns");
            let mut x = upper;
            back_substitution(col, &floor, &mut x);
            check(&x, "backward, dots");
        }
    }

    #[test]
    fn the_floor_sets_tiny_results_to_zero() {
        let n = 9;
        let s = factor(n, 1);
        let col = |j: usize| &s[j * n..(j + 1) * n];
        let inv: Vec<f64> = (0..n).map(|j| 1.0 / s[j * n + j]).collect();
        let floor = ReciprocalWithFloor {
            inv_diag: &inv,
            tiny: 1e-3,
        };
        let mut b = vec![0.0; n];
        b[0] = 1e-6;
        b[n - 1] = 1.0;
        forward_substitution(col, &floor, &mut b);
        assert_eq!(b[0], 0.0);
        assert!(b[n - 1] > 0.0);
        assert!(b.iter().all(|v| *v == 0.0 || v.abs() >= 1e-3));
    }
}
