//! Small dense helpers of the RGP-dKF: the quadratic form vᵀ C v, the Cholesky factor of the p × p
//! innovation covariance, the rank-p downdate of the augmented covariance and the symmetric copy
//! of its stored part.

use faer::linalg::solvers::Llt;
use faer::{Mat, MatRef, Side};

use crate::linalg::{axpy, dot_lanes8};

/// vᵀ C v for a symmetric C.
#[inline(always)]
pub(super) fn quad_form(c: MatRef<'_, f64>, v: &[f64]) -> f64 {
    let mut s = 0.0;
    for (jj, vj) in v.iter().enumerate() {
        let col = c.col(jj);
        let t = match col.try_as_col_major() {
            Some(col) => dot_lanes8(col.as_slice(), v),
            None => (0..v.len()).map(|i| col[i] * v[i]).sum(),
        };
        s += t * vj;
    }
    s
}

/// The lower Cholesky factor L (row-major, zero above the diagonal) of the symmetric p × p
/// matrix `s` (row-major); false if `s` is not positive definite. The innovation covariance has a
/// handful of rows: up to 8 a textbook loop (faer's setup would cost more than the arithmetic),
/// beyond that faer's Cholesky.
pub(super) fn cholesky(s: &[f64], p: usize, l: &mut [f64]) -> bool {
    if p > 8 {
        let Ok(llt) = Llt::new(MatRef::from_row_major_slice(s, p, p), Side::Lower) else {
            return false;
        };
        let lf = llt.L();
        for i in 0..p {
            for jj in 0..p {
                l[i * p + jj] = if jj <= i { lf[(i, jj)] } else { 0.0 };
            }
        }
        return true;
    }
    l[..p * p].fill(0.0);
    for jj in 0..p {
        let mut d = s[jj * p + jj];
        for k in 0..jj {
            d -= l[jj * p + k] * l[jj * p + k];
        }
        if !(d > 0.0 && d.is_finite()) {
            return false;
        }
        let djj = d.sqrt();
        l[jj * p + jj] = djj;
        for i in jj + 1..p {
            let mut v = s[i * p + jj];
            for k in 0..jj {
                v -= l[i * p + k] * l[jj * p + k];
            }
            l[i * p + jj] = v / djj;
        }
    }
    true
}

/// C −= W Wᵀ (W: N × p, column-major) on the stored part of the augmented covariance (see
/// [`RgpEkf`]): columns 0..n completely and, if `all` (variant 4a), the lower triangle of the other
/// columns; with `all` false (variant 4b) only the states' rows and columns change. C_ij and C_ji
/// of the state block subtract the same products in the same order, so it stays exactly symmetric.
#[inline(always)]
pub(super) fn rank_p_downdate(c: &mut Mat<f64>, w: &[f64], p: usize, n: usize, all: bool) {
    let nt = c.nrows();
    let wcol = |kk: usize| &w[kk * nt..(kk + 1) * nt];
    for j in 0..nt {
        let lo = if j < n {
            0
        } else if all {
            j
        } else {
            break;
        };
        let col = &mut c.col_as_slice_mut(j)[lo..];
        match p {
            // the common small cases in one pass over the column (same operations, same order)
            1 => axpy(col, -wcol(0)[j], &wcol(0)[lo..]),
            2 => {
                let (a0, a1) = (wcol(0)[j], wcol(1)[j]);
                let (w0, w1) = (&wcol(0)[lo..], &wcol(1)[lo..]);
                for ((ci, x0), x1) in col.iter_mut().zip(w0).zip(w1) {
                    *ci = (*ci - x0 * a0) - x1 * a1;
                }
            }
            _ => {
                for kk in 0..p {
                    let wk = wcol(kk);
                    let wjk = wk[j];
                    for (ci, wi) in col.iter_mut().zip(&wk[lo..]) {
                        *ci -= wi * wjk;
                    }
                }
            }
        }
    }
}

/// The full symmetric matrix from its stored part: the lower triangle, plus the complete first
/// columns of the state block (the upper triangle elsewhere may be stale).
pub(super) fn symmetric_from_lower(c: MatRef<'_, f64>) -> Mat<f64> {
    Mat::from_fn(c.nrows(), c.ncols(), |i, j| {
        if i >= j {
            c[(i, j)]
        } else {
            c[(j, i)]
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn small_cholesky_matches_faer_and_rejects_indefinite() {
        for p in [1, 2, 3, 5, 8, 9, 12] {
            let g = Mat::<f64>::from_fn(p, p, |i, j| ((i * 7 + j * 3) % 5) as f64 - 2.0);
            let a = &g * g.transpose() + Mat::<f64>::identity(p, p);
            let s: Vec<f64> = (0..p * p).map(|k| a[(k / p, k % p)]).collect();
            let mut l = vec![f64::NAN; p * p];
            assert!(cholesky(&s, p, &mut l));
            let want = Llt::new(a.as_ref(), Side::Lower).unwrap();
            for i in 0..p {
                for jj in 0..p {
                    let w = if jj <= i { want.L()[(i, jj)] } else { 0.0 };
                    assert!((l[i * p + jj] - w).abs() < 1e-12, "p = {p}");
                }
            }
            let mut bad = s.clone();
            bad[p * p - 1] = -1.0;
            assert!(!cholesky(&bad, p, &mut l), "p = {p}");
        }
    }
}
