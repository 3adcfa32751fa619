//! Run-time dispatched reductions (dot products, four at once for the back substitution, and the
//! fused column pass of a symmetric matrix-vector product) for vectors of a few dozen to a few
//! hundred entries: the per-step kernels of the RGP-dKF (`rgp/`).
//!
//! LLVM vectorises element-wise loops (axpy) by itself but not these reductions:
//! without reassociation it keeps their partial sums scalar. Each function here is written twice
//! with the same partial sums in the same order: portable Rust (eight partial sums as two arrays of
//! four), and AVX2 intrinsics (the same sums in two 4-lane registers), chosen at run time. Both
//! perform identical floating-point operations (no fused multiply-add), so the results do not
//! depend on the CPU.

/// a · b over the common length, with eight partial sums (see [`dot_portable`]); AVX2 when
/// the CPU has it, chosen at run time.
#[inline(always)]
pub(crate) fn dot_lanes8(a: &[f64], b: &[f64]) -> f64 {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2 (checked just above).
        return unsafe { avx2::dot(a, b) };
    }
    dot_portable(a, b)
}

/// y += α x and returns x · v (the dot product as [`dot_lanes8`] computes it), in one pass over x: one
/// column of a symmetric matrix-vector product from the lower triangle. Over the common length.
#[inline(always)]
pub(crate) fn symv_column(y: &mut [f64], alpha: f64, x: &[f64], v: &[f64]) -> f64 {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2 (checked just above).
        return unsafe { avx2::symv_column(y, alpha, x, v) };
    }
    symv_column_portable(y, alpha, x, v)
}

/// [x₀ · v, x₁ · v, x₂ · v, x₃ · v] over the common length, in one pass over v (four rows of a
/// transposed triangular solve). Each is summed in four partial sums over blocks of four
/// entries, added as ((l0 + l1) + (l2 + l3)), then the last 0–3 products in order.
#[inline(always)]
pub(crate) fn dot4(x: [&[f64]; 4], v: &[f64]) -> [f64; 4] {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2 (checked just above).
        return unsafe { avx2::dot4(x, v) };
    }
    dot4_portable(x, v)
}

pub(crate) fn dot4_portable(x: [&[f64]; 4], v: &[f64]) -> [f64; 4] {
    let n = x.iter().fold(v.len(), |n, c| n.min(c.len()));
    let mut out = [0.0; 4];
    for (o, c) in out.iter_mut().zip(x) {
        let mut acc = [0.0f64; 4];
        let mut i = 0;
        while i + 4 <= n {
            for l in 0..4 {
                acc[l] += c[i + l] * v[i + l];
            }
            i += 4;
        }
        let mut s = (acc[0] + acc[1]) + (acc[2] + acc[3]);
        while i < n {
            s += c[i] * v[i];
            i += 1;
        }
        *o = s;
    }
    out
}

/// The partial sums of [`dot_lanes8`]: blocks of eight go to two sets of four sums (s0 gets entries
/// 8i..8i+4, s1 entries 8i+4..8i+8), a following block of four to s0; then the lane sums
/// s0 + s1 are added as ((l0 + l1) + (l2 + l3)) and the last 0–3 products in order.
pub(crate) fn dot_portable(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len().min(b.len());
    let (a, b) = (&a[..n], &b[..n]);
    let (mut s0, mut s1) = ([0.0f64; 4], [0.0f64; 4]);
    let mut i = 0;
    while i + 8 <= n {
        for l in 0..4 {
            s0[l] += a[i + l] * b[i + l];
            s1[l] += a[i + 4 + l] * b[i + 4 + l];
        }
        i += 8;
    }
    if i + 4 <= n {
        for l in 0..4 {
            s0[l] += a[i + l] * b[i + l];
        }
        i += 4;
    }
    let mut s = ((s0[0] + s1[0]) + (s0[1] + s1[1])) + ((s0[2] + s1[2]) + (s0[3] + s1[3]));
    while i < n {
        s += a[i] * b[i];
        i += 1;
    }
    s
}

pub(crate) fn symv_column_portable(y: &mut [f64], alpha: f64, x: &[f64], v: &[f64]) -> f64 {
    let n = y.len().min(x.len()).min(v.len());
    for (yi, xi) in y[..n].iter_mut().zip(&x[..n]) {
        *yi += alpha * xi;
    }
    dot_portable(&x[..n], &v[..n])
}

#[cfg(target_arch = "x86_64")]
pub(crate) mod avx2 {
    use std::arch::x86_64::*;

    /// ((l0 + l1) + (l2 + l3)) of s0 + s1, as in [`super::dot_portable`].
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[inline]
    #[target_feature(enable = "avx2")]
    unsafe fn lane_sum(s0: __m256d, s1: __m256d) -> f64 {
        let mut l = [0.0f64; 4];
        // SAFETY: `l` holds four f64 (unaligned store).
        unsafe { _mm256_storeu_pd(l.as_mut_ptr(), _mm256_add_pd(s0, s1)) };
        (l[0] + l[1]) + (l[2] + l[3])
    }

    /// [`super::dot_lanes8`] with AVX2.
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[inline]
    #[target_feature(enable = "avx2")]
    pub unsafe fn dot(a: &[f64], b: &[f64]) -> f64 {
        let n = a.len().min(b.len());
        let (pa, pb) = (a.as_ptr(), b.as_ptr());
        let (mut s0, mut s1) = (_mm256_setzero_pd(), _mm256_setzero_pd());
        let mut i = 0;
        // SAFETY (all loads): i + 8 ≤ n resp. i + 4 ≤ n, and both slices hold n entries.
        while i + 8 <= n {
            unsafe {
                let p0 = _mm256_mul_pd(_mm256_loadu_pd(pa.add(i)), _mm256_loadu_pd(pb.add(i)));
                let p1 = _mm256_mul_pd(
                    _mm256_loadu_pd(pa.add(i + 4)),
                    _mm256_loadu_pd(pb.add(i + 4)),
                );
                s0 = _mm256_add_pd(s0, p0);
                s1 = _mm256_add_pd(s1, p1);
            }
            i += 8;
        }
        if i + 4 <= n {
            unsafe {
                let p0 = _mm256_mul_pd(_mm256_loadu_pd(pa.add(i)), _mm256_loadu_pd(pb.add(i)));
                s0 = _mm256_add_pd(s0, p0);
            }
            i += 4;
        }
        // SAFETY: the caller guarantees AVX2.
        let mut s = unsafe { lane_sum(s0, s1) };
        while i < n {
            s += a[i] * b[i];
            i += 1;
        }
        s
    }

    /// [`super::dot4`] with AVX2.
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[inline]
    #[target_feature(enable = "avx2")]
    pub unsafe fn dot4(x: [&[f64]; 4], v: &[f64]) -> [f64; 4] {
        let n = x.iter().fold(v.len(), |n, c| n.min(c.len()));
        let pv = v.as_ptr();
        let (p0, p1, p2, p3) = (x[0].as_ptr(), x[1].as_ptr(), x[2].as_ptr(), x[3].as_ptr());
        let mut s = [_mm256_setzero_pd(); 4];
        let mut i = 0;
        // SAFETY (all loads): i + 4 ≤ n, and the five slices hold n entries.
        while i + 4 <= n {
            unsafe {
                let vi = _mm256_loadu_pd(pv.add(i));
                s[0] = _mm256_add_pd(s[0], _mm256_mul_pd(_mm256_loadu_pd(p0.add(i)), vi));
                s[1] = _mm256_add_pd(s[1], _mm256_mul_pd(_mm256_loadu_pd(p1.add(i)), vi));
                s[2] = _mm256_add_pd(s[2], _mm256_mul_pd(_mm256_loadu_pd(p2.add(i)), vi));
                s[3] = _mm256_add_pd(s[3], _mm256_mul_pd(_mm256_loadu_pd(p3.add(i)), vi));
            }
            i += 4;
        }
        let mut out = [0.0; 4];
        for c in 0..4 {
            let mut l = [0.0f64; 4];
            // SAFETY: `l` holds four f64 (unaligned store).
            unsafe { _mm256_storeu_pd(l.as_mut_ptr(), s[c]) };
            let mut t = (l[0] + l[1]) + (l[2] + l[3]);
            for k in i..n {
                t += x[c][k] * v[k];
            }
            out[c] = t;
        }
        out
    }

    /// [`super::symv_column`] with AVX2.
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[inline]
    #[target_feature(enable = "avx2")]
    pub unsafe fn symv_column(y: &mut [f64], alpha: f64, x: &[f64], v: &[f64]) -> f64 {
        let n = y.len().min(x.len()).min(v.len());
        let (py, px, pv) = (y.as_mut_ptr(), x.as_ptr(), v.as_ptr());
        let al = _mm256_set1_pd(alpha);
        let (mut s0, mut s1) = (_mm256_setzero_pd(), _mm256_setzero_pd());
        let mut i = 0;
        // SAFETY (all loads and stores): i + 8 ≤ n resp. i + 4 ≤ n, and the three slices hold n
        // entries; y is borrowed mutably, so it does not overlap x or v.
        while i + 8 <= n {
            unsafe {
                let x0 = _mm256_loadu_pd(px.add(i));
                let x1 = _mm256_loadu_pd(px.add(i + 4));
                let y0 = _mm256_add_pd(_mm256_loadu_pd(py.add(i)), _mm256_mul_pd(al, x0));
                let y1 = _mm256_add_pd(_mm256_loadu_pd(py.add(i + 4)), _mm256_mul_pd(al, x1));
                _mm256_storeu_pd(py.add(i), y0);
                _mm256_storeu_pd(py.add(i + 4), y1);
                s0 = _mm256_add_pd(s0, _mm256_mul_pd(x0, _mm256_loadu_pd(pv.add(i))));
                s1 = _mm256_add_pd(s1, _mm256_mul_pd(x1, _mm256_loadu_pd(pv.add(i + 4))));
            }
            i += 8;
        }
        if i + 4 <= n {
            unsafe {
                let x0 = _mm256_loadu_pd(px.add(i));
                let y0 = _mm256_add_pd(_mm256_loadu_pd(py.add(i)), _mm256_mul_pd(al, x0));
                _mm256_storeu_pd(py.add(i), y0);
                s0 = _mm256_add_pd(s0, _mm256_mul_pd(x0, _mm256_loadu_pd(pv.add(i))));
            }
            i += 4;
        }
        // SAFETY: the caller guarantees AVX2.
        let mut s = unsafe { lane_sum(s0, s1) };
        while i < n {
            y[i] += alpha * x[i];
            s += x[i] * v[i];
            i += 1;
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::linalg::test_data as data;

    #[test]
    fn dot_and_symv_column_agree_with_plain_sums_and_across_cpus() {
        for n in [0, 1, 3, 4, 5, 7, 8, 9, 12, 13, 16, 31, 80, 125] {
            let (a, b, y0) = (data(n, 1), data(n, 2), data(n, 3));
            let plain: f64 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
            let d = dot_lanes8(&a, &b);
            assert!((d - plain).abs() <= 1e-14 * (1.0 + plain.abs()), "n = {n}");
            assert_eq!(d.to_bits(), dot_portable(&a, &b).to_bits(), "n = {n}");
            let (mut y1, mut y2) = (y0.clone(), y0.clone());
            let s1 = symv_column(&mut y1, 0.7, &a, &b);
            let s2 = symv_column_portable(&mut y2, 0.7, &a, &b);
            assert_eq!(s1.to_bits(), d.to_bits());
            assert_eq!(s2.to_bits(), d.to_bits());
            for i in 0..n {
                assert_eq!(y1[i], y0[i] + 0.7 * a[i]);
                assert_eq!(y2[i], y1[i]);
            }
            let cols = [data(n, 4), data(n, 5), data(n, 6), data(n, 7)];
            let x = [&cols[0][..], &cols[1][..], &cols[2][..], &cols[3][..]];
            let (d4, d4p) = (dot4(x, &a), dot4_portable(x, &a));
            for c in 0..4 {
                let plain: f64 = cols[c].iter().zip(&a).map(|(x, y)| x * y).sum();
                assert!(
                    (d4[c] - plain).abs() <= 1e-14 * (1.0 + plain.abs()),
                    "n = {n}"
                );
                assert_eq!(d4[c].to_bits(), d4p[c].to_bits(), "n = {n}");
            }
        }
    }
}
